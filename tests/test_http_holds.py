"""The service holds, round two (issue R): one request never freezes it, and an accepted job
makes progress. One test (or more) per finding R.1-R.9, each on real processes (`abcns
serve`, a stock `dask scheduler` and workers) except where a fault must be injected into
the job manager's own process (R.8, R.9's cancel race); plus issue Q's points 4 (a YAML
spec in the upload) and 12 (the API's shapes), and a seeded slice of the fuzz run
(benchmarks/http_fuzz.py).
"""

from __future__ import annotations

import asyncio
import errno
import json
import os
import select
import signal
import socket
import struct
import subprocess
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import yaml
from distributed import Client, LocalCluster
from http_helpers import follow

from benchmarks.harness import AUTH, ROOT, TOKEN, Service, StockCluster, duffing_spec, wait_until
from benchmarks.http_hostile import zeros_npz

pytestmark = pytest.mark.http
TERMINAL = ("finished", "failed", "cancelled")


def post(service: Service, spec: dict | bytes, path: str = "/jobs") -> httpx.Response:
    body = spec if isinstance(spec, bytes) else json.dumps(spec).encode()
    return httpx.post(f"{service.url}{path}", content=body, timeout=120,
                      headers={**AUTH, "Content-Type": "application/json"})


def get(service: Service, path: str, **kw) -> httpx.Response:
    return httpx.get(f"{service.url}{path}", headers={**AUTH, **kw.pop("headers", {})}, timeout=60, **kw)


def cancel(service: Service, job_id: str) -> None:
    httpx.delete(f"{service.url}/jobs/{job_id}", headers=AUTH, timeout=60)


def field(r: httpx.Response) -> str:
    return r.json()["detail"][0]["field"]


def ended(service: Service, job_id: str) -> dict | None:
    info = get(service, f"/jobs/{job_id}").json()
    return info if info["status"] in TERMINAL else None


def kill(procs: list[subprocess.Popen]) -> None:
    """SIGKILL: a worker still runs a dropped batch, and nothing need wait for it."""
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


# ---------------------------------------------------------------------------- R.1
def test_health_answers_within_a_second_while_a_large_body_is_parsed_and_validated(service):
    """R.1: a 15 MB body of 3.8 million numbers (inside every limit, so it is parsed and
    validated in full: ~1-3 s of CPU) is sent on a raw socket; /health is asked again and
    again until the body's answer arrives. Every probe answers within 1 s (the issue's
    bound), and some probes answered while the body was provably still being handled (its
    whole body sent, its answer not yet there). Before, parsing and validating ran on the
    event loop, and the first probe waited for all of it."""
    n = 1_900_000
    spec = duffing_spec(max_populations=1, particles=200)
    spec["data"].update(input="__INPUT__", observed="__OBSERVED__")
    numbers = b"[" + b",".join([b"0.5"] * n) + b"]"
    body = json.dumps(spec).encode().replace(b'"__INPUT__"', numbers).replace(b'"__OBSERVED__"', numbers)
    head = (f"POST /jobs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\nContent-Type: application/json\r\n"
            f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n").encode()
    probes: list[tuple[float, bool]] = []  # (seconds, the body's answer still pending when the probe answered)
    with socket.create_connection(("127.0.0.1", service.port), timeout=300) as sock, \
            httpx.Client(timeout=30) as http:
        sock.sendall(head + body)  # returns once the server has read all but what the socket buffers hold
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            start = time.perf_counter()
            assert http.get(f"{service.url}/health").status_code == 200
            took = time.perf_counter() - start
            pending = not select.select([sock], [], [], 0)[0]
            probes.append((took, pending))
            if not pending:
                break
            time.sleep(0.02)
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    status = int(answer.split(b" ", 2)[1])
    during = [t for t, pending in probes if pending]
    print(f"{len(during)} probes while the body was handled, slowest {max(t for t, _ in probes):.3f} s; answer {status}")
    assert status == 422 and b"data.observed" in answer  # a constant record: refused, naming it
    assert len(during) >= 3, probes
    assert max(t for t, _ in probes) < 1.0, probes


def test_deep_wide_and_huge_bodies_are_refused_at_once(service):
    """R.1: the issue's bodies get 413: a flat array of 14 million zeros from its bytes,
    before it is parsed (naming the body); 900 levels around a million zeros, and a spec
    40 levels deep, at the walk's 33rd level (naming the top-level field)."""
    deep = b'{"name":"x","data":' + b"[" * 900 + b",".join([b"0"] * 1_000_000) + b"]" * 900 + b"}"
    wide = b'{"name":"x","data":[' + b",".join([b"0"] * 14_000_000) + b"]}"
    nested = json.dumps({**duffing_spec(max_populations=1), "name": "__X__"}).encode()
    nested = nested.replace(b'"__X__"', b"[" * 40 + b"1" + b"]" * 40)
    for body, name, words in ((deep, "data", "deeper than 32"), (wide, "body", "JSON values"),
                              (nested, "name", "deeper than 32")):
        r = post(service, body)
        assert r.status_code == 413 and field(r) == name and words in r.json()["detail"][0]["msg"], r.text[:300]


# ---------------------------------------------------------------------------- R.2
def test_physically_invalid_specs_are_refused_and_a_job_that_accepts_nothing_stops(service):
    """R.2: the issue's specs. fs 1e308 (a subnormal interval), m = -1, m = 0, priors
    [-1e308, 1e308] and (since issue Z.4) a force of 2^62, which every simulation left the
    divergence guard with, get 422 naming the field; a job that accepts nothing (a first
    tolerance of 1e-9 %, above the NMSE's floor but far below the record's 1 % noise) stops
    by itself with nothing_accepted (here after 20,000 simulations; 10^6 by default), its
    terminal event saying why."""
    cases = ((lambda s: s["data"].update(fs=1e308), "data.fs"),
             (lambda s: s["models"][0]["fixed"].update(m=-1), "models[0].fixed.m"),
             (lambda s: s["models"][1]["fixed"].update(m=0), "models[1].fixed.m"),
             (lambda s: s["models"][0]["priors"].update(k=[-1e308, 1e308]), "models[0].priors.k"),
             (lambda s: s["data"].update(input=[f * 2.0**62 for f in s["data"]["input"]]), "data.input"))
    for change, name in cases:
        spec = duffing_spec(max_populations=1, particles=200)
        change(spec)
        r = post(service, spec)
        assert r.status_code == 422 and field(r) == name, (name, r.status_code, r.text[:300])
    spec = duffing_spec(max_populations=2, particles=200)
    spec["sampler"]["epsilon_initial"] = 1e-9
    spec["stop"]["max_simulations_without_acceptance"] = 20_000
    r = post(service, spec)
    assert r.status_code == 201, r.text
    try:
        last = wait_until(lambda: ended(service, r.json()["id"]), 240, "the job to stop by itself", 0.5)
        last = follow(service.url, r.json()["id"])[-1]
        assert last["event"] == "finished" and last["data"]["stop_reason"] == "nothing_accepted", last
        assert last["data"]["n_populations"] == 0 and "20,000 simulations" in last["data"]["notes"][0]
    finally:
        cancel(service, r.json()["id"])  # (had it not stopped, it would hold the only running slot)


# ---------------------------------------------------------------------------- R.3
def test_the_time_budget_and_a_cancel_end_a_job_while_its_batch_runs(tmp_path):
    """R.3: batches of 50,000 simulations of 1,000 RK4 substeps per sample (about 90 s each
    on this project's machine). A cancel ends one job while its batches still run on the
    workers (seen on the workers after the job ended), and a time budget of 10 s another
    after ~10 s of its own run, not a batch's 90 s, also as the service reports it; before, both
    waited for the batch to end (later, the second for its loop to rejoin a worker thread that
    its dropped batch held). The budget was 3 s until a full suite on a loaded machine
    (2026-12-05) ended the job before its two batches were seen running."""
    cluster = StockCluster(tmp_path / "dask")
    service = Service(tmp_path / "jobs", cluster.address, env={"ABCNS_MAX_BATCH_SIZE": "50000"})
    try:
        with Client(cluster.address, timeout=30) as client:
            def running() -> set[str]:
                """The keys of the batch tasks the workers' threads run: ``(group, population,
                first, last)``, batches numbered from 1. Not a seceded job loop, nor the job's
                data or its anchors (``first`` 0), no-ops that run for an instant: two of them
                caught running at once passed for the job's two batches (a CI failure). A
                worker killed below but not yet removed by the scheduler is skipped (its
                broadcast raised CommClosedError: a failure of this suite on 2026-12-05)."""
                keys = client.run(lambda dask_worker: [str(ts.key) for ts in dask_worker.state.executing
                                                       if isinstance(ts.key, tuple) and len(ts.key) == 4
                                                       and ts.key[2] >= 1], on_error="ignore")
                return {k for ks in keys.values() for k in ks}

            def executing() -> int:
                return len(running())

            spec = duffing_spec(max_populations=1, particles=200)
            for model in spec["models"]:
                model["integrator"]["substeps"] = 1000
            spec["sampler"]["batch_size"] = 50_000
            r = post(service, spec)
            assert r.status_code == 201, r.text
            first = r.json()["id"]
            wait_until(lambda: executing() >= 1, 120, "the first batch to run", 0.5)
            cancel(service, first)
            info = wait_until(lambda: ended(service, first), 60, "the cancel to end the job", 0.2)
            assert info["status"] == "cancelled" and executing() >= 1, info  # the batch still runs
            # its dropped batches would hold both workers (and two cores the other tests need)
            # for a batch's time: in their place one worker of two threads, where the next
            # job's loop runs and both its batches (the loop secedes: its thread runs one)
            kill(cluster.procs[1:])
            del cluster.procs[1:]
            cluster.start_workers(1, threads=2)
            spec["stop"]["max_seconds"] = 10
            second = post(service, spec).json()["id"]
            # its clock starts when its loop gets a worker (issue U: the loop is a task on one)

            def both_running() -> tuple[set[str]] | None:
                keys = running()
                return (keys,) if len(keys) == 2 or ended(service, second) else None

            (batches,) = wait_until(both_running, 120, "the job's two batches to run", 0.2)
            info = wait_until(lambda: ended(service, second), 300, "the time budget to end the job", 0.2)
            # reported ended while both its batches still run: its loop did not wait to rejoin
            # a thread of its worker, which only a batch's end frees (it did: ~20-90 s later)
            assert len(batches) == 2 and batches <= running(), (info, batches)
            result = get(service, f"/jobs/{second}/result").json()
            assert result["stop_reason"] == "max_seconds", (info, result)
            # no population in its 10 s (a batch is ~90 s): it says so (Z.5), not a plain finished
            assert result["n_populations"] > 0 or (info["status"] == "failed" and info["error"].startswith(
                "no population: its time budget")), (info, result)
            # ended by its budget, not by its batch (a batch is ~90 s; the job ran ~10 s)
            assert result["wall_time_s"] is not None and result["wall_time_s"] < 30, result
    finally:
        service.close()
        kill(cluster.procs)


# ---------------------------------------------------------------------------- R.4
def upload(service: Service, spec: dict | str, npz: Path, name: str = "spec.json") -> httpx.Response:
    text = spec if isinstance(spec, str) else json.dumps(spec)
    with npz.open("rb") as f:
        return httpx.post(f"{service.url}/jobs/upload", files={"spec": (name, text.encode()), "data": ("x.npz", f)},
                          headers=AUTH, timeout=300)


def test_an_upload_is_cut_to_the_samples_the_job_reads_and_stored_compressed(service, tmp_path):
    """R.4: records of 2^25 samples (longdouble: 512 MB each once decompressed, from a file
    of about a megabyte) are refused from their npy header, naming the field; the same as
    float64, with a fit and a test window on the first 1,000 samples, are read only that
    far and stored compressed: the job's data.npz is a few kilobytes (was 2 x 256 MB)."""
    duffing = ROOT / "examples" / "duffing_41"
    head = {"force": np.load(duffing / "force.npy"), "x": np.load(duffing / "displacement.npy")}
    spec = duffing_spec(max_populations=1, particles=200)
    spec["data"].update(input="npz:force", observed="npz:x")
    (tmp_path / "long.npz").write_bytes(zeros_npz(2**25, "longdouble", head))
    r = upload(service, spec, tmp_path / "long.npz")
    assert r.status_code == 422 and field(r) in ("data.input", "data.observed") and "dtype" in r.text, r.text[:300]
    (tmp_path / "big.npz").write_bytes(zeros_npz(2**25, "float64", head))
    print(f"the upload: {(tmp_path / 'big.npz').stat().st_size / 1e6:.2f} MB for 2 x 2^25 float64 samples")
    r = upload(service, spec, tmp_path / "big.npz")
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    data = service.job_dir(job_id) / "data.npz"
    with np.load(data) as d:
        assert d["observed"].size == d["input"].size == 1000
        np.testing.assert_array_equal(d["observed"], head["x"])
    assert data.stat().st_size < 100_000, data.stat().st_size
    assert follow(service.url, job_id)[-1]["event"] == "finished"


# ---------------------------------------------------------------------------- R.5
def test_the_queue_limit_holds_under_thirty_concurrent_submissions(cluster, tmp_path):
    """R.5: with ABCNS_MAX_QUEUED=3 and one job running at a time, 30 submissions at once:
    at most 3 queued + 1 running are accepted (the issue saw 7), the rest get 429, and the
    job list holds exactly the accepted ones."""
    service = Service(tmp_path / "jobs", cluster.address, env={"ABCNS_MAX_QUEUED": "3"})
    try:
        spec = json.dumps(duffing_spec(max_populations=10_000, particles=200, noise_floor=False)).encode()  # runs until cancelled

        async def burst() -> list[httpx.Response]:
            async with httpx.AsyncClient(timeout=120) as http:
                return await asyncio.gather(*(http.post(f"{service.url}/jobs", content=spec, headers={
                    **AUTH, "Content-Type": "application/json"}) for _ in range(30)))

        answers = asyncio.run(burst())
        codes = sorted(r.status_code for r in answers)
        accepted = [r.json()["id"] for r in answers if r.status_code == 201]
        print(f"30 at once: {codes.count(201)} x 201, {codes.count(429)} x 429")
        assert set(codes) == {201, 429} and 3 <= len(accepted) <= 4, codes
        assert {j["id"] for j in get(service, "/jobs").json()} == set(accepted)
        for job_id in accepted:
            cancel(service, job_id)
    finally:
        service.close()


# ---------------------------------------------------------------------------- R.6, R.7
def test_a_number_of_five_thousand_digits_and_duplicate_model_names_get_422(service, tmp_path):
    """R.6: a 5,000-digit integer (past Python's conversion limit) in /jobs and in an
    upload's spec: 422 naming the field (was a 500). R.7: two models of one name: 422 naming
    models[1].name (was 201, then the job failed)."""
    text = json.dumps(duffing_spec(max_populations=1)).replace('"seed": 41', '"seed": ' + "7" * 5000)
    r = post(service, text.encode())
    assert r.status_code == 422 and field(r) == "seed" and "5,000 digits" in r.text, r.text[:300]
    np.savez(tmp_path / "x.npz", x=np.zeros(3))
    r = upload(service, text, tmp_path / "x.npz")
    assert r.status_code == 422 and field(r) == "seed", r.text[:300]
    spec = duffing_spec(max_populations=1)
    spec["models"][1]["name"] = spec["models"][0]["name"]
    r = post(service, spec)
    assert r.status_code == 422 and field(r) == "models[1].name" and "duplicate" in r.text, r.text[:300]


def test_data_never_name_a_file_over_http(service, tmp_path):
    """No files over HTTP: data given as a name (a job folder's own data.npz, another job's,
    a 100 KB name) get 422 naming the field, in /jobs and in an upload (where only npz:KEY
    names the upload's arrays). Found by the fuzz run: a 100 KB name reached the file
    system (503, "File name too long")."""
    np.savez(tmp_path / "x.npz", x=np.zeros(3))
    for name in ("data.npz:observed", f"../{'0' * 32}/data.npz:observed", "x" * 100_000, "/etc/passwd"):
        spec = duffing_spec(max_populations=1)
        spec["data"]["observed"] = name
        r = post(service, spec)
        assert r.status_code == 422 and field(r) == "data.observed", (name[:40], r.status_code, r.text[:300])
        r = upload(service, spec, tmp_path / "x.npz")
        assert r.status_code == 422 and field(r) == "data.observed", (name[:40], r.status_code, r.text[:300])


# ---------------------------------------------------------------------------- R.8
def test_a_submission_while_the_disk_is_full_gets_503_with_retry_after(cluster, tmp_path, monkeypatch):
    """R.8: the job manager's writes fail with ENOSPC (injected into its own process: the
    app served in-process through httpx's ASGI transport, its lifespan run around it); a
    submission gets 503 with Retry-After naming the cause, nothing is left of it, and the
    next one, once the disk takes writes again, gets 201."""
    from service.http import jobs
    from service.http.api import create_app
    from service.http.settings import Settings

    full = threading.Event()
    write = jobs._write_json

    def write_json(path, data):
        if full.is_set():
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return write(path, data)

    monkeypatch.setattr(jobs, "_write_json", write_json)
    settings = Settings(store_dir=tmp_path / "jobs", scheduler=cluster.address, token=TOKEN, retry_after_s=11)
    app = create_app(settings)
    spec = duffing_spec(max_populations=1, particles=200)

    async def submit_twice() -> None:
        async with app.router.lifespan_context(app), httpx.AsyncClient(
                transport=httpx.ASGITransport(app=app, raise_app_exceptions=False), base_url="http://abcns",
                headers=AUTH, timeout=120) as http:
            full.set()
            r = await http.post("/jobs", json=spec)
            assert r.status_code == 503 and r.headers["Retry-After"] == "11" and "No space left" in r.text, r.text[:300]
            assert list((tmp_path / "jobs").iterdir()) == []
            full.clear()
            r = await http.post("/jobs", json=spec)
            assert r.status_code == 201, r.text
            await http.delete(f"/jobs/{r.json()['id']}")

    asyncio.run(submit_twice())


def test_a_failed_job_keeps_its_error_when_its_record_could_not_be_written(cluster, tmp_path, monkeypatch):
    """R.8: a job fails (its store takes no writes: ENOSPC) and its final job.json cannot be
    written either; a restarted manager finds it failed with the error its terminal event
    recorded (before: failed, the error lost)."""
    from service.http.jobs import JobManager, JobRecord
    from service.run.store import Store
    from service.spec import parse

    def append_many(self, pops):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.path))

    save = JobRecord.save

    def record(self):
        if self.status == "failed":
            raise OSError(errno.ENOSPC, "No space left on device", str(self.folder))
        save(self)

    monkeypatch.setattr(Store, "append_many", append_many)
    monkeypatch.setattr(JobRecord, "save", record)
    monkeypatch.setenv("ABCNS_STORE_INTERVAL_S", "0")
    duffing = ROOT / "examples" / "duffing_41"
    arrays = {"input": np.load(duffing / "force.npy"), "observed": np.load(duffing / "displacement.npy")}
    # workers in this process (the job loops run on workers): the patched store is theirs
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, scheduler_port=0,
                      dashboard_address="127.0.0.1:0", scheduler_kwargs={"dashboard": False}) as lc, \
            Client(lc) as client:
        manager = JobManager(tmp_path / "jobs", client, max_running=1, loop=None)
        try:
            job = manager.submit(parse(duffing_spec(max_populations=2, particles=200)), arrays)
            wait_until(lambda: job.status == "failed", 120, "the job to fail")
        finally:
            manager.shutdown(10)
        assert json.loads((job.folder / "job.json").read_text())["status"] == "running"  # the write failed
        monkeypatch.setattr(JobRecord, "save", save)
        again = JobManager(tmp_path / "jobs", client, max_running=1, loop=None)
        try:
            back = again.get(job.id)
            assert back.status == "failed" and "No space left on device" in (back.error or ""), back
        finally:
            again.shutdown(10)


# ---------------------------------------------------------------------------- R.9
def test_headers_over_sixteen_kib_get_431(service):
    """R.9: a request whose head exceeds 16 KiB gets 431 (headers of 100 KB were answered)."""
    r = httpx.get(f"{service.url}/health", headers={"X-Pad": "a" * 20_000}, timeout=30)
    assert r.status_code == 431, r.status_code
    assert httpx.get(f"{service.url}/health", headers={"X-Pad": "a" * 15_000}, timeout=30).status_code == 200


def test_a_dropped_event_stream_logs_no_error(cluster, tmp_path):
    """R.9: 40 event streams of an ended job of 30 populations, each dropped by its client
    (a reset) while the service replays the events: nothing in the service's log says
    ERROR or shows a traceback (before: 38 of 40 drops logged anyio.BrokenResourceError with
    a traceback). The log is read once the service has exited (SIGTERM, then its exit
    waited for): by then every stream's handler has ended and written what it had to say,
    however long that took on a busy machine."""
    service = Service(tmp_path / "jobs", cluster.address)
    try:
        spec = duffing_spec(max_populations=30, particles=100)
        spec["sampler"]["batch_size"] = 100
        job_id = post(service, spec).json()["id"]
        assert follow(service.url, job_id)[-1]["event"] == "finished"
        path = f"/jobs/{job_id}/events"
        request = f"GET {path} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\n\r\n".encode()
        before = service.log.stat().st_size
        for _ in range(40):
            with socket.create_connection(("127.0.0.1", service.port), timeout=30) as sock:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
                sock.sendall(request)
                assert sock.recv(200).startswith(b"HTTP/1.1 200")
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close with a reset
        assert get(service, "/health").status_code == 200
    finally:
        service.close()
    # ended by its own shutdown (uvicorn raises the SIGTERM again once it is done), not killed: its log is complete
    assert service.proc is not None and service.proc.returncode in (0, -signal.SIGTERM), service.proc.returncode
    log = service.log.read_bytes()[before:].decode(errors="replace")
    assert log.count(f"GET {path} HTTP/1.1") == 40, log[-3000:]  # every dropped stream was served
    assert "Traceback" not in log and "ERROR" not in log and "BrokenResourceError" not in log, log[-3000:]


def test_the_result_of_an_ended_job_is_computed_once_and_kept(service):
    """R.9: the summary of an ended job is written beside it when it ends; /result answers
    from it, the same as before, even once the store is gone (before: rebuilt from the
    store on every call, 20 calls at once took the RSS from 363 MB to 1.73 GB)."""
    job_id = post(service, duffing_spec(max_populations=2, particles=200)).json()["id"]
    assert follow(service.url, job_id)[-1]["event"] == "finished"
    first = get(service, f"/jobs/{job_id}/result").json()
    folder = service.job_dir(job_id)
    assert (folder / "result.json").is_file()
    (folder / "store.zarr").rename(folder / "moved.zarr")
    again = [get(service, f"/jobs/{job_id}/result") for _ in range(3)]
    assert all(r.status_code == 200 and r.json() == first for r in again)
    (folder / "moved.zarr").rename(folder / "store.zarr")


def test_a_cancel_as_the_dispatcher_takes_the_job_stops_it_without_error(tmp_path):
    """R.9: the dispatcher has taken a queued job (out of the queue, not yet running) when a
    cancel comes: the cancel no longer removes it from the queue (a ValueError before); the
    job never runs and ends cancelled. In-process, with the dispatcher stopped first."""
    from service.http.jobs import JobManager
    from service.spec import parse

    duffing = ROOT / "examples" / "duffing_41"
    arrays = {"input": np.load(duffing / "force.npy"), "observed": np.load(duffing / "displacement.npy")}
    manager = JobManager(tmp_path / "jobs", None, max_running=1, loop=None)  # type: ignore[arg-type]
    manager.begin_shutdown()
    manager.dispatcher.join(timeout=10)
    manager.stopping = False
    job = manager.submit(parse(duffing_spec(max_populations=1, particles=200)), arrays)
    with manager.lock:  # what the dispatcher does, up to starting the job's thread
        manager.jobs[manager.queue.popleft()]
        manager.running.add(job.id)
    manager.cancel(job.id)
    manager._run(job)  # the job's thread
    assert job.status == "cancelled" and not job.store_path.exists() and not manager.running


# ---------------------------------------------------------------------------- CI's chaos run
class Killed(BaseException):
    """The service process dies here (SIGKILL): nothing more of the job's thread runs."""


class StoreWriteCut(Exception):
    pass


def idle_manager(folder: Path):
    """A job manager whose dispatcher is stopped: the test runs a job's thread itself."""
    from service.http.jobs import JobManager

    manager = JobManager(folder, None, max_running=1, loop=None)  # type: ignore[arg-type]
    manager.begin_shutdown()
    manager.dispatcher.join(timeout=10)
    manager.stopping = False
    return manager


def restarted_manager(folder: Path):
    """A job manager on ``folder`` as a restarted service makes it (its dispatcher running)."""
    from service.http.jobs import JobManager

    return JobManager(folder, None, max_running=1, loop=None)  # type: ignore[arg-type]


def take(manager, job) -> None:
    with manager.lock:  # what the dispatcher does, up to starting the job's thread
        assert manager.queue.popleft() == job.id
        manager.running.add(job.id)


def duffing_job(manager, populations: int = 2):
    from service.spec import parse

    duffing = ROOT / "examples" / "duffing_41"
    arrays = {"input": np.load(duffing / "force.npy"), "observed": np.load(duffing / "displacement.npy")}
    return manager.submit(parse(duffing_spec(max_populations=populations, particles=200)), arrays)


def test_a_service_killed_in_a_jobs_final_status_write_resumes_it_to_finished(tmp_path, monkeypatch):
    """CI's chaos run: the service was SIGKILLed while it recorded a job's end in its store
    (set_status("finished", ...)), then restarted; the job ended "cancelled" (its last event
    with stop_reason null), though nobody cancelled it. Here the service dies at its second
    write of the store's metadata once that status change begins (a status change was five
    writes, one per key: the store was left "finished" with no stop reason), or not at all
    where the change is one write; a new manager on the same folder then resumes the job or
    finds it ended. Either way it ends finished, with its stop reason. In-process: the job's
    thread is run by the test, the kill a BaseException that nothing in it catches."""
    import zarr

    from service.http.jobs import TERMINAL as ENDED
    from service.run.store import Store

    manager = idle_manager(tmp_path / "jobs")
    job = duffing_job(manager)
    take(manager, job)
    writes: list[str] = []  # the store's metadata writes since the final status change began
    store_set, set_status = zarr.storage.LocalStore.set, Store.set_status

    async def cut_at_the_second_write(self, key, value):
        if writes and key == "zarr.json":
            writes.append(key)
            if len(writes) > 2:
                raise StoreWriteCut
        await store_set(self, key, value)

    def final(self, status, *args, **kwargs):
        if status == "finished":
            writes.append("begins")
        try:
            set_status(self, status, *args, **kwargs)
        except StoreWriteCut:
            raise Killed from None

    with monkeypatch.context() as m:
        m.setattr(zarr.storage.LocalStore, "set", cut_at_the_second_write)
        m.setattr(Store, "set_status", final)
        try:
            manager._run(job)
        except Killed:
            assert job.status == "running"  # the service died with the job running
    again = restarted_manager(tmp_path / "jobs")
    try:
        back = again.get(job.id)
        wait_until(lambda: back.status in ENDED, 300, "the job to end")
        events = [json.loads(line) for line in (job.folder / "events.jsonl").read_text().splitlines()]
        assert back.status == "finished", (back.error, events[-3:])
        assert events[-1]["event"] == "finished" and events[-1]["data"]["stop_reason"] == "max_populations", events[-3:]
        assert Store.open(job.store_path).attrs["stop_reason"] == "max_populations"
    finally:
        again.shutdown(10)


def test_a_population_whose_message_was_lost_is_announced_from_the_store_before_the_next(tmp_path, monkeypatch):
    """CI's chaos run: a job's loop stored population 1, and its worker died before the
    message that announces it reached the service; the loop resumed elsewhere from the store
    and announced population 2, and the job's log never said population 1 (its events began
    at 2, and the backfill at the loop's end starts after the last one announced). Here the
    first message is dropped: the log still announces 1 then 2, population 1 as stored."""
    from service.http.jobs import JobManager

    manager = idle_manager(tmp_path / "jobs")
    job = duffing_job(manager, populations=2)
    take(manager, job)
    announce, dropped = JobManager._announce, []

    def lose_the_first(self, job, progress):
        if not dropped:  # the loop's first message: lost with its worker
            dropped.append(progress)
            return
        announce(self, job, progress)

    monkeypatch.setattr(JobManager, "_announce", lose_the_first)
    manager._run(job)
    events = [json.loads(line) for line in (job.folder / "events.jsonl").read_text().splitlines()]
    announced = [e["data"] for e in events if e["event"] == "population"]
    assert job.status == "finished" and dropped[0]["population"] == 1, (job.status, dropped)
    assert [a["population"] for a in announced] == [1, 2], announced
    assert announced[0]["epsilon"] == dropped[0]["epsilon"], (announced[0], dropped[0])


def test_a_run_that_says_cancelled_when_nobody_cancelled_the_job_fails_saying_so(tmp_path, monkeypatch):
    """The service ends a job "cancelled" only when it was cancelled. A run whose result says
    "cancelled" otherwise (as run_job's did for a store left "finished" with no stop reason)
    fails, and its error says why, instead of ending cancelled in silence."""
    import dataclasses

    from abcns import StopReason
    from service.http import jobs
    from service.run.runner import run_job

    def says_cancelled(*args, **kwargs):
        return dataclasses.replace(run_job(*args, **kwargs), stop_reason=StopReason.CANCELLED)

    manager = idle_manager(tmp_path / "jobs")
    job = duffing_job(manager, populations=1)
    take(manager, job)
    monkeypatch.setattr(jobs, "run_job", says_cancelled)
    manager._run(job)
    events = [json.loads(line) for line in (job.folder / "events.jsonl").read_text().splitlines()]
    assert job.status == "failed" and events[-1]["event"] == "failed", (job.status, events[-1])
    assert "nobody cancelled" in (job.error or ""), job.error


# ---------------------------------------------------------------------------- Q.4, Q.12
def test_an_upload_takes_a_yaml_spec(service, tmp_path):
    """Q.4: the spec part of an upload may be YAML (what `abcns run` reads), by its file
    name or as a text field; a bad YAML spec gets 422 naming the field (was 400 "not
    JSON"); a YAML bomb (aliases) or a date where a number goes is refused the same way."""
    duffing = ROOT / "examples" / "duffing_41"
    np.savez(tmp_path / "x.npz", force=np.load(duffing / "force.npy"), x=np.load(duffing / "displacement.npy"))
    raw = yaml.safe_load((duffing / "spec.yaml").read_text())
    raw["data"].update(input="npz:force", observed="npz:x")
    raw["sampler"].update(particles=200, batch_size=100)
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": 1}
    text = yaml.safe_dump(raw)
    r = upload(service, text, tmp_path / "x.npz", name="spec.yaml")
    assert r.status_code == 201, r.text
    assert follow(service.url, r.json()["id"])[-1]["event"] == "finished"
    with (tmp_path / "x.npz").open("rb") as f:  # as a text field: JSON if it parses as JSON, else YAML
        r = httpx.post(f"{service.url}/jobs/upload", data={"spec": text}, files={"data": f}, headers=AUTH, timeout=60)
    assert r.status_code == 201, r.text
    cancel(service, r.json()["id"])
    bad = text.replace("particles: 200", "particles: many")
    r = upload(service, bad, tmp_path / "x.npz", name="spec.yaml")
    assert r.status_code == 422 and field(r) == "sampler.particles", r.text[:300]
    bomb = "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, "
        f"*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}]\n"
        for i in range(8))
    r = upload(service, bomb, tmp_path / "x.npz", name="spec.yaml")
    assert r.status_code == 413 and "values" in r.text, r.text[:300]
    r = upload(service, text.replace("seed: 41", "seed: 2026-11-24"), tmp_path / "x.npz", name="spec.yaml")
    assert r.status_code == 422 and field(r) == "seed" and "date" in r.text, r.text[:300]


def test_api_shapes_names_iso_times_typed_limits_and_location(service):
    """Q.12: a 201 carries the job's Location; created_at is ISO 8601; model probabilities in
    events and progress are {model name: value}; /health and /limits give the limits with
    the same types (integers where the limit is one)."""
    r = post(service, duffing_spec(max_populations=2, particles=200))
    assert r.status_code == 201 and r.headers["Location"] == f"/jobs/{r.json()['id']}", r.headers
    job_id = r.json()["id"]
    events = follow(service.url, job_id)
    names = ["cubic", "cubic-quintic"]
    for e in events:
        if e["event"] in ("population", "finished"):
            assert list(e["data"]["model_probabilities"]) == names, e
    info = httpx.get(f"{service.url}{r.headers['Location']}", headers=AUTH, timeout=30).json()
    assert list(info["progress"]["model_probabilities"]) == names
    created = info["created_at"]
    assert created.endswith("Z") and abs(
        time.time() - __import__("datetime").datetime.fromisoformat(created).timestamp()) < 3600, created
    limits = httpx.get(f"{service.url}/limits", timeout=30).json()
    health = httpx.get(f"{service.url}/health", timeout=30).json()["limits"]
    assert health == limits and {k: type(v) for k, v in health.items()} == {k: type(v) for k, v in limits.items()}
    assert isinstance(limits["max_particles"], int) and isinstance(limits["max_job_seconds"], float)


# ---------------------------------------------------------------------------- the fuzz, a slice
def test_a_slice_of_the_fuzz_run_gives_no_server_error(service):
    """A seeded slice (30 requests) of benchmarks/http_fuzz.py: deep, wide and huge-number
    JSON, physically invalid specs, YAML and .npz uploads. No answer is a 5xx, every 4xx
    names a field, and every accepted job ends or makes a population."""
    from benchmarks.http_fuzz import fuzz

    counts, stuck = fuzz(service.url, examples=30, seed=7, follow_s=120)
    print(dict(counts))
    answers = {k: n for k, n in counts.items() if k[0] != "job"}
    assert sum(answers.values()) == 30 and not stuck, (counts, stuck)
    assert not any(status >= 500 or (status in (400, 413, 422) and name.startswith("("))
                   for status, _, name in answers), counts
