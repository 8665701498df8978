"""The HTTP service against hostile and careless clients (issue N; I.3, I.5, I.6), every
test on real processes: `abcns serve` under uvicorn, a stock `dask scheduler` and workers.

Each test names the finding it covers; the markup-in-names (N.1), /docs offline (I.4) and
live-panel (I.7) findings are browser tests (tests/test_browser.py).
"""

from __future__ import annotations

import collections
import json
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
import uuid
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest
from http_helpers import follow, parse_events, populations, same_populations

from benchmarks.harness import AUTH, ROOT, TOKEN, Service, duffing_spec, probe_client, wait_until
from service.http.schemas import NAME_MAX_CHARS, PAGE_MAX
from service.run.store import Store

pytestmark = pytest.mark.http
SHUTDOWN_S = 20  # the stated bound: SIGTERM to exit, streams open and a job running


def post(service: Service, spec: dict) -> httpx.Response:
    """POST /jobs with Python's JSON (which writes a lone surrogate as an escape; httpx's
    json= would refuse to encode it)."""
    return httpx.post(f"{service.url}/jobs", content=json.dumps(spec), timeout=60,
                      headers={**AUTH, "Content-Type": "application/json"})


def get(service: Service, path: str, **kw) -> httpx.Response:
    return httpx.get(f"{service.url}{path}", headers={**AUTH, **kw.pop("headers", {})}, timeout=60, **kw)


def peak_rss_mb(service: Service) -> float:
    """The high-water mark of the service's resident memory (VmHWM)."""
    for line in Path(f"/proc/{service.proc.pid}/status").read_text().splitlines():  # type: ignore[union-attr]
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM")


def short_job(service: Service, max_populations: int = 2, **spec_update) -> str:
    """A job run to its end; its id."""
    spec = {**duffing_spec(max_populations=max_populations, particles=200), **spec_update}
    r = post(service, spec)
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    assert follow(service.url, job_id)[-1]["event"] == "finished"
    return job_id


# ---------------------------------------------------------------------------- N.2
def test_a_job_the_service_dies_under_is_resumed_once_then_failed(fresh):
    """N.2: the service SIGKILLed twice while the same job runs: the first restart resumes
    it, the second marks it failed with the reason (ABCNS_MAX_RESUMES=1) instead of
    running it again; a later restart leaves it failed."""
    job_id = post(fresh, duffing_spec(max_populations=400))
    assert job_id.status_code == 201
    job_id = job_id.json()["id"]
    events = follow(fresh.url, job_id, until=lambda ev: populations(ev) >= 1)
    fresh.kill()
    fresh.start()
    more = follow(fresh.url, job_id, after=events[-1]["id"], until=lambda ev: populations(ev) >= 1)
    assert more[0]["event"] == "started" and more[0]["data"]["resumed"]  # resumed once
    fresh.kill()
    fresh.start()
    status = get(fresh, f"/jobs/{job_id}").json()
    assert status["status"] == "failed", status
    assert "stopped 2 times" in status["error"] and "not resumed" in status["error"]
    last = follow(fresh.url, job_id, after=more[-1]["id"])
    assert last[-1]["event"] == "failed" and last[-1]["data"]["error"] == status["error"]
    assert "started" not in {e["event"] for e in last}  # not run again
    fresh.close()
    fresh.start()
    assert get(fresh, f"/jobs/{job_id}").json()["status"] == "failed"


# ---------------------------------------------------------------------------- N.3
def test_names_must_be_short_text_and_a_bad_record_never_breaks_the_list(fresh):
    """N.3: a lone surrogate, a control character or an over-long name (the job's or a
    model's) gets 422 naming the field; records a crash or an old version left unreadable
    or with such a name are skipped or shown escaped: the job list, the index page and the
    job's status still answer 200."""
    def with_name(where: str, name: str) -> dict:
        spec = duffing_spec(max_populations=1)
        if where == "name":
            spec["name"] = name
        else:
            spec["models"][0]["name"] = name
        return spec

    for where, field in (("name", "name"), ("model", "models[0].name")):
        for name, what in (("\ud800x", "Unicode"), ("bell\x07", "control"), ("n" * (NAME_MAX_CHARS + 1), "at most")):
            r = post(fresh, with_name(where, name))
            assert r.status_code == 422, (field, what, r.text)
            assert r.json()["detail"][0]["field"] == field and what in r.json()["detail"][0]["msg"]
    spec = duffing_spec(max_populations=1)
    spec["models"][0]["priors"]["\udfffk"] = [1, 2]  # anywhere, a key too
    r = post(fresh, spec)
    assert r.status_code == 422 and r.json()["detail"][0]["field"].startswith("models[0].priors.")
    assert get(fresh, "/jobs").status_code == 200
    ok = short_job(fresh, max_populations=1)
    # records that the service cannot read, or that an older version wrote with such a name
    fresh.close()
    folder = fresh.store_dir
    (folder / ("a" * 32)).mkdir()
    (folder / ("a" * 32) / "job.json").write_text("{cut sho")
    (folder / ("b" * 32)).mkdir()
    (folder / ("b" * 32) / "job.json").write_text(json.dumps({"id": "c" * 32, "status": "finished"}))
    old = "d" * 32
    (folder / old).mkdir()
    legacy = {"id": old, "status": "finished", "created_at": time.time(), "error": None,
              "spec": {**duffing_spec(max_populations=1), "name": "\ud800x"}}
    (folder / old / "job.json").write_text(json.dumps(legacy))  # json escapes the surrogate; loading brings it back
    fresh.start()
    listed = get(fresh, "/jobs")
    assert listed.status_code == 200, listed.text
    names = {j["id"]: j["name"] for j in listed.json()}
    assert names == {ok: "paper-4.1-duffing", old: "\\ud800x"}
    assert httpx.get(f"{fresh.url}/", timeout=10).status_code == 200
    assert get(fresh, f"/jobs/{old}").status_code == 200 and get(fresh, f"/jobs/{ok}").status_code == 200


# ---------------------------------------------------------------------------- N.4
@pytest.fixture(scope="module")
def bomb(tmp_path_factory) -> Path:
    """A 13 MB .npz whose array ``big`` is 3e9 bytes (375e6 float64 zeros) once
    decompressed, beside a small array ``x``."""
    path = tmp_path_factory.mktemp("bomb") / "bomb.npz"
    n = 375_000_000
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        with zf.open("x.npy", "w") as f:
            np.lib.format.write_array(f, np.load(ROOT / "examples" / "duffing_41" / "displacement.npy"))
        with zf.open("force.npy", "w") as f:
            np.lib.format.write_array(f, np.load(ROOT / "examples" / "duffing_41" / "force.npy"))
        with zf.open("big.npy", "w", force_zip64=True) as f:
            np.lib.format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False, "shape": (n,)})
            zeros, left = bytes(64 << 20), n * 8
            while left:
                f.write(zeros[: min(left, len(zeros))])
                left -= min(left, len(zeros))
    return path


def upload(service: Service, spec: dict | str, npz: Path) -> httpx.Response:
    with npz.open("rb") as f:
        return httpx.post(f"{service.url}/jobs/upload", data={"spec": spec if isinstance(spec, str) else json.dumps(spec)},
                          files={"data": f}, headers=AUTH, timeout=120)


def test_an_upload_bomb_is_refused_from_its_header(fresh, bomb):
    """N.4: the spec is checked before the .npz is opened; only the arrays the spec names
    are read, and each only after its declared shape passed the limit: the 3e9-byte array
    is refused (422 naming data.observed) and the service's peak memory does not move."""
    spec = duffing_spec(max_populations=1)
    spec["data"].update(input="npz:force", observed="npz:big")
    peak = peak_rss_mb(fresh)
    bad = {**spec, "sampler": {**spec["sampler"], "particles": "many"}}
    r = upload(fresh, bad, bomb)
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "sampler.particles"
    r = upload(fresh, spec, bomb)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"][0]
    assert detail["field"] == "data.observed" and "375000000 samples" in detail["msg"] and "limit" in detail["msg"]
    spec["data"]["observed"] = "npz:x"  # the bomb is in the file but not named: never read
    r = upload(fresh, spec, bomb)
    assert r.status_code == 201, r.text
    grown = peak_rss_mb(fresh) - peak
    print(f"peak RSS {peak:.0f} MB before the bomb uploads, +{grown:.0f} MB after")
    assert grown < 300, f"the service's peak memory grew by {grown:.0f} MB"
    assert follow(fresh.url, r.json()["id"])[-1]["event"] == "finished"


# ---------------------------------------------------------------------------- N.5
def test_data_stay_out_of_memory_and_an_ended_job_can_be_purged(fresh, tmp_path):
    """N.5: an upload of 2e7 samples is kept in the job's data.npz (cut to the 1,000 samples
    its windows read, R.4), not in job.json; a restarted service does not hold it (resident
    memory about that of an empty service); DELETE ?purge=true removes an ended job and its
    folder, and refuses a running one."""
    rss_empty = fresh.rss_mb()
    folder = ROOT / "examples" / "duffing_41"
    force, x = np.load(folder / "force.npy"), np.load(folder / "displacement.npy")
    np.savez_compressed(tmp_path / "big.npz", force=np.tile(force, 20_000), x=np.tile(x, 20_000))  # 2e7 samples each
    spec = duffing_spec(max_populations=1)
    spec["data"].update(input="npz:force", observed="npz:x")
    r = upload(fresh, spec, tmp_path / "big.npz")
    assert r.status_code == 201, r.text
    big = r.json()["id"]
    assert follow(fresh.url, big)[-1]["event"] == "finished"
    job_dir = fresh.job_dir(big)
    assert (job_dir / "job.json").stat().st_size < 4096 and (job_dir / "spec.json").stat().st_size < 4096
    with np.load(job_dir / "data.npz") as d:
        assert d["observed"].size == 1000
    fresh.close()
    fresh.start()
    assert get(fresh, f"/jobs/{big}").json()["status"] == "finished"
    rss_restarted = fresh.rss_mb()
    print(f"RSS of the service: {rss_empty:.0f} MB empty, {rss_restarted:.0f} MB restarted with the 2e7-sample job")
    assert rss_restarted < rss_empty + 150
    running = post(fresh, duffing_spec(max_populations=400)).json()["id"]
    follow(fresh.url, running, until=lambda ev: populations(ev) >= 1)
    assert httpx.delete(f"{fresh.url}/jobs/{running}", params={"purge": "true"}, headers=AUTH).status_code == 409
    assert httpx.delete(f"{fresh.url}/jobs/{big}", headers=AUTH).status_code == 409  # cancel: it has ended
    assert httpx.delete(f"{fresh.url}/jobs/{big}", params={"purge": "true"}, headers=AUTH).status_code == 204
    assert get(fresh, f"/jobs/{big}").status_code == 404 and not job_dir.exists()
    assert big not in {j["id"] for j in get(fresh, "/jobs").json()}
    assert httpx.delete(f"{fresh.url}/jobs/{running}", headers=AUTH).status_code == 202


# ---------------------------------------------------------------------------- N.6
def test_populations_come_in_pages(service):
    """N.6: GET /jobs/{id}/populations/{t}?offset=&limit= answers one page of particles
    (at most PAGE_MAX); the pages put together are the stored population."""
    job_id = short_job(service, max_populations=2)
    whole = Store.open(service.job_dir(job_id) / "store.zarr").population(2)
    pages = []
    for offset in range(0, 200, 70):
        r = get(service, f"/jobs/{job_id}/populations/2", params={"offset": offset, "limit": 70})
        assert r.status_code == 200, r.text
        page = r.json()
        assert page["offset"] == offset and page["n_particles"] == 200 and len(page["distances"]) == min(70, 200 - offset)
        pages.append(page)
    np.testing.assert_array_equal(np.concatenate([p["distances"] for p in pages]), whole.distances)
    np.testing.assert_array_equal(np.concatenate([p["models"] for p in pages]), whole.models)
    theta = np.array([row for p in pages for row in p["theta"]], dtype=float)
    np.testing.assert_array_equal(theta, whole.theta)
    assert pages[0]["epsilon"] == whole.epsilon and pages[0]["model_probabilities"] == whole.model_probabilities.tolist()
    r = get(service, f"/jobs/{job_id}/populations/2", params={"limit": PAGE_MAX + 1})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "limit"


# ---------------------------------------------------------------------------- N.7
@pytest.mark.parametrize("path", ["data.fs", "seed", "sampler.particles", "data.fit", "models[0].integrator.substeps"])
def test_nan_and_infinity_get_422_with_the_value_as_text(service, path):
    """N.7: NaN or Infinity (Python's JSON reads them) where a number is expected: 422
    naming the field, the value shown as text (not a 500 from echoing it)."""
    for token in ("NaN", "Infinity", "-Infinity"):
        spec = duffing_spec(max_populations=1)
        marker = "__VALUE__"
        if path == "data.fs":
            spec["data"]["fs"] = marker
        elif path == "seed":
            spec["seed"] = marker
        elif path == "sampler.particles":
            spec["sampler"]["particles"] = marker
        elif path == "data.fit":
            spec["data"]["fit"] = [0, marker]
        else:
            spec["models"][0]["integrator"]["substeps"] = marker
        body = json.dumps(spec).replace(f'"{marker}"', token)
        r = httpx.post(f"{service.url}/jobs", content=body, headers={**AUTH, "Content-Type": "application/json"},
                       timeout=60)
        assert r.status_code == 422, (path, token, r.status_code, r.text[:300])
        detail = r.json()["detail"][0]
        assert detail["field"] == (path if path != "data.fit" else "data.fit[1]") and detail["input"] == token


# ---------------------------------------------------------------------------- N.8
def test_sigterm_ends_streams_requeues_the_job_and_exits(fresh):
    """N.8: with a job running and event streams open (one following the running job, one
    on a queued job), SIGTERM ends the streams, stops the job between batches (recorded
    queued, not finished) and the process exits within SHUTDOWN_S; the next start resumes
    the job."""
    running = post(fresh, duffing_spec(max_populations=400)).json()["id"]
    queued = post(fresh, duffing_spec(max_populations=400)).json()["id"]
    seen = follow(fresh.url, running, until=lambda ev: populations(ev) >= 2)
    streams: dict[str, list] = {}

    def read(job_id: str) -> None:
        with httpx.stream("GET", f"{fresh.url}/jobs/{job_id}/events", headers=AUTH, timeout=120) as r:
            streams[job_id] = parse_events(r.iter_lines())

    threads = [threading.Thread(target=read, args=(j,), daemon=True) for j in (running, queued)]
    for t in threads:
        t.start()
    wait_until(lambda: fresh.log.read_text().count(f"/jobs/{running}/events") == 2
               and f"/jobs/{queued}/events" in fresh.log.read_text(), 30, "both streams to be open (the access log)")
    start = time.monotonic()
    os.killpg(fresh.proc.pid, signal.SIGTERM)  # type: ignore[union-attr]
    fresh.proc.wait(timeout=SHUTDOWN_S)  # type: ignore[union-attr]
    took = time.monotonic() - start
    print(f"SIGTERM to exit: {took:.1f} s")
    for t in threads:
        t.join(timeout=10)
        assert not t.is_alive()
    assert streams[running][-1]["event"] == "population" and streams[queued][-1]["event"] == "queued"
    record = json.loads((fresh.job_dir(running) / "job.json").read_text())
    assert record["status"] == "queued" and record["crashes"] == 0
    fresh.start()
    resumed = follow(fresh.url, running, after=seen[-1]["id"], until=lambda ev: ev[-1]["event"] == "started")
    assert resumed[-1]["data"]["resumed"] and "finished" not in {e["event"] for e in resumed}
    for job_id in (running, queued):
        httpx.delete(f"{fresh.url}/jobs/{job_id}", headers=AUTH)


# ---------------------------------------------------------------------------- N.9, I.6
def test_last_event_id_past_the_end_returns_at_once_and_malformed_gets_400(service):
    """N.9 / I.6: on an ended job a stream from past its last event (Last-Event-ID or
    ?after=) ends at once with nothing; a Last-Event-ID that is not digits (a non-ASCII
    byte included) gets 400. A stream that hangs fails on the read timeout."""
    job_id = short_job(service, max_populations=1)
    for kw in ({"headers": {"Last-Event-ID": "99"}}, {"params": {"after": 99}}):
        with httpx.stream("GET", f"{service.url}/jobs/{job_id}/events", timeout=httpx.Timeout(60, read=30),
                          **{**kw, "headers": {**AUTH, **kw.get("headers", {})}}) as r:
            assert r.status_code == 200
            assert parse_events(r.iter_lines()) == []
    events = follow(service.url, job_id, after=2)
    assert [e["id"] for e in events] == [3, 4, 5] and events[-1]["event"] == "finished"
    for bad in (b"abc", b"\xb2", b"-1", b"1" * 40):
        r = httpx.get(f"{service.url}/jobs/{job_id}/events", headers={**AUTH, "Last-Event-ID": bad},
                      timeout=httpx.Timeout(60, read=30))
        assert r.status_code == 400, (bad, r.status_code, r.text[:200])


# ---------------------------------------------------------------------------- N.10
def test_structural_errors_name_the_field_and_statuses_are_right(service):
    """N.10: pydantic's own errors carry detail[i].field (a dotted path); a text/plain body
    gets 415; HEAD /health 200; the token is checked before the body is parsed (a
    malformed body without a token: 401, with a wrong one: 403)."""
    for change, field in ((lambda s: s["sampler"].update(particles="many"), "sampler.particles"),
                          (lambda s: s["models"][0]["priors"].update(k=[1]), "models[0].priors.k"),
                          (lambda s: s.pop("data"), "data"),
                          (lambda s: s["stop"].update(wrong=1), "stop.wrong")):
        spec = duffing_spec(max_populations=1)
        change(spec)
        r = post(service, spec)
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == field, (field, r.text[:300])
    r = httpx.post(f"{service.url}/jobs", content=json.dumps(duffing_spec()), timeout=60,
                   headers={**AUTH, "Content-Type": "text/plain"})
    assert r.status_code == 415
    assert httpx.head(f"{service.url}/health", timeout=10).status_code == 200
    for headers, status in (({}, 401), ({"Authorization": "Bearer wrong"}, 403)):
        r = httpx.post(f"{service.url}/jobs", content=b"{not json", timeout=60,
                       headers={**headers, "Content-Type": "application/json"})
        assert r.status_code == status
    r = httpx.post(f"{service.url}/jobs", content=b"{not json", timeout=60,
                   headers={**AUTH, "Content-Type": "application/json"})
    assert r.status_code == 400


# ---------------------------------------------------------------------------- N.11, Q.12
def test_events_give_the_model_probabilities_by_name(service):
    """N.11, Q.12: with a model name of the longest allowed length, the queued event names
    the models, and population events and the job's progress give the model probabilities
    by name ({model name: value}, in the job's model order), not as a positional list."""
    spec = duffing_spec(max_populations=3, particles=200)
    long_name = "m" * NAME_MAX_CHARS
    spec["models"][0]["name"] = long_name
    job_id = post(service, spec).json()["id"]
    events = follow(service.url, job_id)
    names = [long_name, "cubic-quintic"]
    assert events[0]["event"] == "queued" and events[0]["data"]["models"] == names
    pops = [e for e in events if e["event"] == "population"]
    assert len(pops) == 3 and all(list(e["data"]["model_probabilities"]) == names for e in pops)
    info = get(service, f"/jobs/{job_id}").json()
    assert info["models"] == names and list(info["progress"]["model_probabilities"]) == names


# ---------------------------------------------------------------------------- T (issue 23)
def test_events_and_the_result_give_the_noise_floor_and_the_decision(service):
    """Issue T: each population event (and the job's progress) carries the noise floor and
    the decision tolerance as estimated after that population (the §4.1 NMSE has a floor
    from its first population: numbers, the decision above the floor); GET /jobs/{id}/result
    is the summary, with the answer's population (``decision``) and the ``noise_floor`` as
    the last event gave them, read from the store, and says the answer is provisional."""
    job_id = post(service, duffing_spec(max_populations=3, particles=200)).json()["id"]
    pops = [e["data"] for e in follow(service.url, job_id) if e["event"] == "population"]
    assert len(pops) == 3
    for p in pops:
        assert 0 < p["noise_floor"] < p["decision_tolerance"], p
    info = get(service, f"/jobs/{job_id}").json()
    assert info["progress"]["decision_tolerance"] == pops[-1]["decision_tolerance"]
    result = get(service, f"/jobs/{job_id}/result").json()
    floor, decision = result["noise_floor"], result["decision"]
    assert floor["floor"] == pytest.approx(pops[-1]["noise_floor"], rel=1e-12)
    assert floor["decision_tolerance"] == pytest.approx(pops[-1]["decision_tolerance"], rel=1e-12)
    # three populations end far above the decision tolerance: the answer says it is provisional (issue W)
    assert floor["method"] == "estimated" and decision["rule"] == "max_populations" and decision["provisional"] is True
    assert any(w.startswith("provisional") for w in result["warnings"])
    assert decision["population"] == 3 and decision["model_probabilities"] == result["model_probabilities"]


# ---------------------------------------------------------------------------- N.12
def _closed(sock: socket.socket) -> bytes:
    """Read until the server closes the connection (the socket's timeout fails a hang)."""
    out = b""
    while chunk := sock.recv(4096):
        out += chunk
    return out


def test_slow_clients_are_dropped(cluster, tmp_path):
    """N.12: a connection that sends nothing, partial headers, headers one byte at a time
    or a body slower than the deadlines (here ABCNS_HEADER_TIMEOUT_S=2,
    ABCNS_BODY_TIMEOUT_S=3) is closed by the server (the body with a 408); other clients are
    served meanwhile. A connection still open after 30 s fails the test (socket timeout)."""
    service = Service(tmp_path / "jobs", cluster.address,
                      env={"ABCNS_HEADER_TIMEOUT_S": "2", "ABCNS_BODY_TIMEOUT_S": "3"})
    try:
        def connect() -> socket.socket:
            s = socket.create_connection(("127.0.0.1", service.port), timeout=30)
            return s

        silent = connect()
        partial = connect()
        partial.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")
        body = connect()
        body.sendall(b"POST /jobs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer " + TOKEN.encode()
                     + b"\r\nContent-Type: application/json\r\nContent-Length: 1000\r\n\r\n{\"name\":")
        assert httpx.get(f"{service.url}/health", timeout=10).status_code == 200  # served meanwhile
        # the headers dripped while the deadlines of the three above run out (the server's
        # answers wait in their sockets), not after them
        drip = connect()
        drip.settimeout(0.2)
        request, closed_at = b"GET /health HTTP/1.1\r\nHost: x\r\nX-Pad: " + b"a" * 200 + b"\r\n\r\n", None
        for i in range(len(request)):  # one byte at a time, each followed by a 0.2 s look for the close
            try:
                drip.sendall(request[i: i + 1])
                if drip.recv(1) == b"":
                    closed_at = i
                    break
            except TimeoutError:
                continue
            except (BrokenPipeError, ConnectionResetError):
                closed_at = i
                break
        assert closed_at is not None and closed_at < len(request) - 1  # closed before the headers were complete
        assert _closed(silent) == b""
        assert _closed(partial) == b""
        assert _closed(body).startswith(b"HTTP/1.1 408")
        for s in (silent, partial, body, drip):
            s.close()
    finally:
        service.close()


# ---------------------------------------------------------------------------- I.3
def test_serve_prints_its_address_and_logs_requests(service):
    """I.3: `abcns serve` prints the address it listens on and logs every request (this
    test's own: the service's log holds the module's earlier requests too)."""
    marker = uuid.uuid4().hex
    get(service, "/jobs", params={"request": marker})
    wait_until(lambda: f'"GET /jobs?request={marker} HTTP/1.1" 200'.encode() in service.log.read_bytes(), 10,
               "the access-log line")
    out = service.log.read_text()
    assert f"http://127.0.0.1:{service.port}" in out and '"GET /health HTTP/1.1" 200' in out


# ---------------------------------------------------------------------------- I.5
def test_curl_upload_with_the_spec_as_a_file_or_a_field(service, tmp_path):
    """I.5: the README's curl command (spec as a file part), the spec as a text field read
    from a file, and a clear 422 naming the field when a part is missing."""
    folder = ROOT / "examples" / "duffing_41"
    np.savez(tmp_path / "x.npz", force=np.load(folder / "force.npy"), x=np.load(folder / "displacement.npy"))
    spec = duffing_spec(max_populations=1)
    spec["data"].update(input="npz:force", observed="npz:x")
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    curl = shutil.which("curl")
    assert curl, "curl is not installed"

    def run(*form: str) -> tuple[int, dict]:
        done = subprocess.run([curl, "-sS", "-w", "\n%{http_code}", "-H", f"Authorization: Bearer {TOKEN}", *form,
                               f"{service.url}/jobs/upload"], capture_output=True, text=True, cwd=tmp_path, timeout=120)
        assert done.returncode == 0, done.stderr
        body, _, code = done.stdout.rpartition("\n")
        return int(code), json.loads(body)

    code, out = run("-F", "spec=@spec.json", "-F", "data=@x.npz")
    assert code == 201, out
    assert follow(service.url, out["id"])[-1]["event"] == "finished"
    code, out = run("-F", "spec=<spec.json", "-F", "data=@x.npz")
    assert code == 201, out
    code, out = run("-F", "data=@x.npz")
    assert code == 422 and out["detail"][0]["field"] == "spec"
    code, out = run("-F", "spec=@spec.json")
    assert code == 422 and out["detail"][0]["field"] == "data"


# ---------------------------------------------------------------------------- the whole list at once
def test_the_service_survives_the_whole_list_in_one_run_and_health_keeps_answering(fresh, bomb, tmp_path):
    """Every finding against one service while a job runs; a thread measures GET /health all
    along. The service answers everything with the right status, still lists its jobs, and
    never stops answering /health: every probe answers within 2 s (a service blocked by a
    request would miss that by the request's own duration). The latency itself is printed,
    not asserted (speed lives in benchmarks/http_latency.py): p99 ~10-40 ms on 2 quiet cores,
    117-322 ms with a benchmark running beside it."""
    latencies: list[tuple[float, str]] = []  # (seconds, the step running meanwhile)
    done = threading.Event()
    step = ["start"]

    def poll() -> None:
        with httpx.Client(timeout=10) as client:
            while not done.is_set():
                start = time.perf_counter()
                assert client.get(f"{fresh.url}/health").status_code == 200
                latencies.append((time.perf_counter() - start, step[0]))
                time.sleep(0.02)

    poller = threading.Thread(target=poll, daemon=True)
    poller.start()
    silent = socket.create_connection(("127.0.0.1", fresh.port), timeout=30)
    try:
        step[0] = "submit"
        running = post(fresh, duffing_spec(max_populations=30, particles=1000))
        assert running.status_code == 201
        running_id = running.json()["id"]
        step[0] = "names"
        xss = duffing_spec(max_populations=1, particles=200)
        xss["name"] = xss["models"][0]["name"] = '<img src=x onerror="document.title=1">'
        assert post(fresh, xss).status_code == 201  # markup is text: accepted, shown as text
        assert post(fresh, {**duffing_spec(max_populations=1), "name": "\ud800x"}).status_code == 422
        step[0] = "nan"
        body = json.dumps(duffing_spec(max_populations=1)).replace('"seed": 41', '"seed": NaN')
        assert httpx.post(f"{fresh.url}/jobs", content=body, headers={**AUTH, "Content-Type": "application/json"},
                          timeout=60).status_code == 422
        assert httpx.post(f"{fresh.url}/jobs", content=b"x", headers={**AUTH, "Content-Type": "text/plain"},
                          timeout=60).status_code == 415
        assert httpx.post(f"{fresh.url}/jobs", content=b"{cut", headers={"Content-Type": "application/json"},
                          timeout=60).status_code == 401
        step[0] = "bomb"
        spec = duffing_spec(max_populations=1)
        spec["data"].update(input="npz:force", observed="npz:big")
        assert upload(fresh, spec, bomb).status_code == 422
        step[0] = "head"
        assert httpx.head(f"{fresh.url}/health", timeout=10).status_code == 200
        silent.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")  # never finished
        step[0] = "follow"
        events = follow(fresh.url, running_id, until=lambda ev: populations(ev) >= 3)
        assert populations(events) >= 3
        step[0] = "page"
        assert get(fresh, f"/jobs/{running_id}/populations/2", params={"limit": 100}).status_code == 200
        with httpx.stream("GET", f"{fresh.url}/jobs/{running_id}/events", headers={**AUTH, "Last-Event-ID": b"\xb2"},
                          timeout=30) as r:
            assert r.status_code == 400
        step[0] = "to the end"
        assert follow(fresh.url, running_id)[-1]["event"] == "finished"
        with httpx.stream("GET", f"{fresh.url}/jobs/{running_id}/events", headers={**AUTH, "Last-Event-ID": "999"},
                          timeout=httpx.Timeout(60, read=30)) as r:
            assert r.status_code == 200 and parse_events(r.iter_lines()) == []
        step[0] = "purge"
        r = httpx.delete(f"{fresh.url}/jobs/{running_id}", params={"purge": "true"}, headers=AUTH, timeout=60)
        assert r.status_code == 204
        listed = get(fresh, "/jobs")
        assert listed.status_code == 200 and running_id not in [j["id"] for j in listed.json()]
    finally:
        silent.close()
        done.set()
        poller.join(timeout=30)
    ms = np.array([t for t, _ in latencies]) * 1000
    p50, p99 = np.percentile(ms, [50, 99])
    slowest = sorted(zip(ms, (w for _, w in latencies)), reverse=True)[:5]
    print(f"/health over {ms.size} requests: p50 {p50:.1f} ms, p99 {p99:.1f} ms, max {ms.max():.1f} ms; "
          f"slowest during: {[(round(t), w) for t, w in slowest]}")
    assert ms.size > 50 and ms.max() < 2000, f"/health max {ms.max():.1f} ms"


# ---------------------------------------------------------------------------- issue M
def test_specs_that_would_fail_at_run_time_are_refused_at_submission(service):
    """Issue M: each of these was accepted with 201 and failed (or never ended) at run time;
    each is now a 422 naming the field, and nothing is queued."""
    before = get(service, "/jobs").json()
    cases = (
        (lambda s: s.update(seed=-1), "seed"),
        (lambda s: s.update(seed=2**63), "seed"),
        (lambda s: s["sampler"].update(enlargement=1e308), "sampler.enlargement"),
        (lambda s: s["sampler"].update(particles=10**9), "sampler.particles"),
        (lambda s: s["sampler"].update(particles=10**30), "sampler.particles"),
        (lambda s: s["sampler"].update(particles=2**63), "sampler.particles"),
        (lambda s: s.update(distance={"name": "nmse", "summaries": "gk"}), "distance.summaries"),
        (lambda s: s["sampler"].update(quantile=0.3), "sampler.quantile"),  # abc-smc's, not abc-ns's
        (lambda s: s["stop"].update(epsilon_target=0), "stop.epsilon_target"),
        # P.3: values outside a simulator's valid range (every simulation failed, and the model "died")
        (lambda s: s["models"][0]["fixed"].update(m=0), "models[0].fixed.m"),
        (lambda s: s["models"][1].update(simulator="bouc_wen", fixed={"m": 1, "n": 1.5},
                                         priors={"c": [1, 2], "A": [1, 2], "alpha": [0, 1], "beta": [0, 1]}),
         "models[1].fixed.n"),
    )
    for change, field in cases:
        spec = duffing_spec(max_populations=1)
        change(spec)
        r = post(service, spec)
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == field, (field, r.status_code, r.text[:300])
    assert get(service, "/jobs").json() == before


# ---------------------------------------------------------------------------- issue K
def limited_spec(**stop) -> dict:
    """duffing_spec on 999 samples (the held-out window dropped), two populations."""
    spec = duffing_spec(max_populations=2, particles=200)
    spec["data"].pop("test")
    spec["data"]["input"], spec["data"]["observed"] = spec["data"]["input"][:999], spec["data"]["observed"][:999]
    spec["stop"].update(stop)
    return spec


def test_admission_limits_name_the_field_and_the_limit_and_come_from_the_environment(cluster, tmp_path):
    """K.1, K.2, L.3: every limit set by an ABCNS_* variable (so the environment reaches
    `abcns serve`), reported by /limits and /health; a job over one gets 422 naming the
    field and the limit; a job that names no budget gets the service's, and ends by it."""
    env = {"ABCNS_MAX_PARTICLES": "5000", "ABCNS_MAX_BATCH_SIZE": "4000", "ABCNS_MAX_SUBSTEPS": "100",
           "ABCNS_MAX_SAMPLES": "999", "ABCNS_MAX_MODELS": "3", "ABCNS_MAX_MEMORY_MB": "40",
           "ABCNS_MAX_JOB_SECONDS": "600", "ABCNS_MAX_JOB_SIMULATIONS": "1500"}
    service = Service(tmp_path / "jobs", cluster.address, env=env)
    try:
        limits = httpx.get(f"{service.url}/limits", timeout=10).json()
        assert {k: limits[k] for k in ("max_particles", "max_batch_size", "max_substeps", "max_samples", "max_models",
                                       "max_memory_mb", "max_job_seconds", "max_job_simulations")} == \
            {"max_particles": 5000, "max_batch_size": 4000, "max_substeps": 100, "max_samples": 999, "max_models": 3,
             "max_memory_mb": 40, "max_job_seconds": 600, "max_job_simulations": 1500}
        assert httpx.get(f"{service.url}/health", timeout=10).json()["limits"] == limits

        def over(change, field: str, limit: str) -> None:
            spec = limited_spec()
            change(spec)
            r = post(service, spec)
            assert r.status_code == 422, (field, r.status_code, r.text[:300])
            detail = r.json()["detail"][0]
            assert detail["field"] == field and f"limit of {limit}" in detail["msg"], (field, detail)

        over(lambda s: s["sampler"].update(particles=5001), "sampler.particles", "5,000")
        over(lambda s: s["sampler"].update(batch_size=4001), "sampler.batch_size", "4,000")
        over(lambda s: s["models"][0]["integrator"].update(substeps=10**9), "models[0].integrator.substeps", "100")
        over(lambda s: s["models"][1]["integrator"].pop("substeps") and s["models"][1]["priors"].update(k=[5, 5e9]),
             "models[1].integrator.substeps", "100")  # chosen from the priors
        over(lambda s: s.update(models=[dict(m) for m in s["models"] * 2])  # copies: each renamed once
             or [m.update(name=f"m{i}") for i, m in enumerate(s["models"])], "models", "3")
        over(lambda s: s["data"].update(input=duffing_spec()["data"]["input"], observed=duffing_spec()["data"]["observed"])
             or s["data"].pop("fit"), "data.observed", "999")  # read whole (with a fit window: cut to it, R.4)
        over(lambda s: s["sampler"].update(particles=4000) or s.update(stop={"epsilon_target": 0.01}),
             "stop.max_populations", "40")  # 4000 x 9 x 8 B x 200 populations assumed: 55 MB
        over(lambda s: s["stop"].update(max_seconds=601), "stop.max_seconds", "600")
        over(lambda s: s["stop"].update(max_simulations=10**12), "stop.max_simulations", "1,500")

        spec = limited_spec()
        spec["stop"]["max_populations"] = 1000  # only the service's budget ends it (14 MB estimated)
        r = post(service, spec)
        assert r.status_code == 201, r.text
        job_id = r.json()["id"]
        stored = json.loads((service.job_dir(job_id) / "spec.json").read_text())
        assert stored["stop"]["max_seconds"] == 600 and stored["stop"]["max_simulations"] == 1500
        assert follow(service.url, job_id)[-1]["event"] == "finished"
        result = get(service, f"/jobs/{job_id}/result").json()
        assert result["stop_reason"] == "max_simulations" and result["n_simulations"] <= 1500, result
    finally:
        service.close()


def test_a_full_queue_answers_429_with_retry_after(cluster, tmp_path):
    """K.3: with ABCNS_MAX_QUEUED=1, one job running and one waiting, the next is refused
    with 429 and Retry-After; nothing is left of it."""
    service = Service(tmp_path / "jobs", cluster.address, env={"ABCNS_MAX_QUEUED": "1", "ABCNS_RETRY_AFTER_S": "7"})
    try:
        spec = duffing_spec(max_populations=10_000, particles=200, noise_floor=False)  # runs until cancelled
        running = post(service, spec).json()["id"]
        wait_until(lambda: get(service, f"/jobs/{running}").json()["status"] == "running", 60, "the first job to run")
        waiting = post(service, spec)
        assert waiting.status_code == 201, waiting.text
        r = post(service, spec)
        assert r.status_code == 429 and r.headers["Retry-After"] == "7" and "limit is 1" in r.text, (r.status_code, r.text)
        assert len(get(service, "/jobs").json()) == 2
        for job_id in (waiting.json()["id"], running):
            assert httpx.delete(f"{service.url}/jobs/{job_id}", headers=AUTH, timeout=10).status_code == 202
    finally:
        service.close()


def test_a_full_store_disk_requeues_that_job_which_resumes_to_the_same_result(cluster, tmp_path, monkeypatch):
    """K.5, Z.6: the store of one job stops taking writes (ENOSPC at its third population,
    once, injected into Store.append_many in this process, where the workers run); that job
    is requeued with the reason in its events (it failed for good before: issue Z.6), the
    populations written before stay, it resumes from them once the disk takes writes and
    ends with the same populations as the other job (the same spec and seed, another name),
    which ran beside it; no temporary file is left in its folder."""
    import errno

    from distributed import Client, LocalCluster

    from service.http.jobs import JobManager
    from service.spec import parse

    real_append = Store.append_many
    full = [True]

    def append_many(self, pops):
        if self.attrs["spec"]["name"] == "full-disk" and self.n_populations + len(pops) > 2 and full[0]:
            full[0] = False
            raise OSError(errno.ENOSPC, "No space left on device", str(self.path))
        return real_append(self, pops)

    monkeypatch.setattr(Store, "append_many", append_many)
    monkeypatch.setenv("ABCNS_STORE_INTERVAL_S", "0")  # one append per population
    folder = ROOT / "examples" / "duffing_41"
    arrays = {"input": np.load(folder / "force.npy"), "observed": np.load(folder / "displacement.npy")}
    # workers in this process (the job loops run on workers): the patched store is theirs
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, scheduler_port=0,
                      dashboard_address="127.0.0.1:0", scheduler_kwargs={"dashboard": False}) as lc, \
            Client(lc) as client:
        manager = JobManager(tmp_path / "jobs", client, max_running=2, loop=None)
        try:
            jobs = {}
            for name in ("full-disk", "fine"):
                raw = {**duffing_spec(max_populations=5, particles=200), "name": name}
                jobs[name] = manager.submit(parse(raw), dict(arrays))  # (submit empties the dict)
            wait_until(lambda: all(j.status in ("finished", "failed") for j in jobs.values()), 300, "both jobs to end")
            bad, good = jobs["full-disk"], jobs["fine"]
            assert not full[0], "the disk never refused a write"
            assert bad.status == "finished" and good.status == "finished", (bad.error, good.error)
            events = [json.loads(line) for line in (bad.folder / "events.jsonl").read_text().splitlines()]
            requeued = [e["data"]["reason"] for e in events if e["event"] == "requeued"]
            assert len(requeued) == 1 and "the disk is full" in requeued[0] and "No space left" in requeued[0], requeued
            announced = [e["data"]["population"] for e in events if e["event"] == "population"]
            assert announced == [1, 2, 3, 4, 5], announced
            same_populations(bad.store_path, good.store_path)
            assert not [p.name for p in bad.folder.rglob("*") if p.suffix in (".tmp", ".partial")]
        finally:
            manager.shutdown(10)


# ---------------------------------------------------------------------------- K.6
HOSTILE_JSON = ["NaN", "Infinity", "-Infinity", "1e999", "-1e999", "1" + "0" * 400, "-" + "9" * 30, "null", "true",
                "[]", "{}", '"\\ud800"', '"' + "x" * 100_000 + '"', "[" * 5000 + "]" * 5000, '{"a": ' * 2000 + "1" + "}" * 2000,
                '"\\u0000"', "0.0", "-0", "1e-320"]
BAD_BYTES = [b"\xff\xfe", b"\xc3\x28", b"\xed\xa0\x80", b"\x00"]


def leaf_paths(value, path=()):
    """Every place in a spec a value can go (one element of a data list, not all of them)."""
    if isinstance(value, dict):
        yield path
        for k, v in value.items():
            yield from leaf_paths(v, (*path, k))
    elif isinstance(value, list):
        yield path
        for i, v in enumerate(value[:2]):
            yield from leaf_paths(v, (*path, i))
    else:
        yield path


def with_marker(spec: dict, path: tuple, marker: str) -> dict:
    spec = json.loads(json.dumps(spec))
    if not path:
        return marker  # type: ignore[return-value]
    node = spec
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = marker
    return spec


def test_hostile_values_anywhere_in_either_submit_route_never_give_a_server_error(service, tmp_path):
    """K.6: a seeded hypothesis run puts one hostile JSON value (NaN, Infinity, 1e999, a
    400-digit integer, 5000-deep nesting, a lone surrogate, 100 KB of text, null, ...) or a
    non-UTF-8 byte sequence at any place of a valid spec, and posts it to POST /jobs and as
    the spec of POST /jobs/upload. Every answer is a 4xx (422s name a field) or a 201 (the
    job is then cancelled); never a 5xx; the service still answers and lists its jobs."""
    from hypothesis import HealthCheck, given, seed, settings
    from hypothesis import strategies as st

    base = duffing_spec(max_populations=1, particles=200)
    base["data"]["input"], base["data"]["observed"] = base["data"]["input"][:600], base["data"]["observed"][:600]
    base["data"].pop("test")
    upload_spec = json.loads(json.dumps(base))
    upload_spec["data"].update(input="npz:force", observed="npz:x")
    specs = {"jobs": base, "upload": upload_spec}
    where = st.sampled_from(sorted(specs)).flatmap(lambda r: st.tuples(st.just(r), st.sampled_from(list(leaf_paths(specs[r])))))
    np.savez(tmp_path / "x.npz", force=np.array(base["data"]["input"]), x=np.array(base["data"]["observed"]))
    seen: collections.Counter = collections.Counter()

    @seed(20261124)
    @settings(max_examples=300, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(place=where, value=st.sampled_from(HOSTILE_JSON + BAD_BYTES))
    def hostile(place, value):
        route, path = place
        marker = "__HOSTILE__"
        text = json.dumps(with_marker(specs[route], path, marker)).encode()
        raw = value if isinstance(value, bytes) else value.encode()
        if isinstance(value, bytes):
            raw = b'"' + raw + b'"'
        body = text.replace(f'"{marker}"'.encode(), raw)
        if route == "jobs":
            r = http.post(f"{service.url}/jobs", content=body, headers={**AUTH, "Content-Type": "application/json"})
        else:
            with (tmp_path / "x.npz").open("rb") as f:
                r = http.post(f"{service.url}/jobs/upload", headers=AUTH,
                              files={"spec": ("spec.json", body, "application/json"), "data": ("x.npz", f)})
        assert r.status_code < 500, (path, value[:50], route, r.status_code, r.text[:300])
        if r.status_code == 201:
            http.delete(f"{service.url}/jobs/{r.json()['id']}", headers=AUTH)
        elif r.status_code == 422:
            assert r.json()["detail"][0]["field"], r.text[:300]
        seen[r.status_code] += 1

    with probe_client(timeout=60) as http:  # a new connection per request, as httpx.post, at ~1/20 of its CPU
        hostile()
    print(f"hostile submissions by status: {dict(seen)}")
    assert seen[422] > 100 and set(seen) <= {201, 400, 413, 422}, seen
    assert httpx.get(f"{service.url}/health", timeout=10).status_code == 200
    assert get(service, "/jobs").status_code == 200
