"""Issue K.4: chaos on real processes. Ten small jobs on `abcns serve` against a stock
`dask scheduler` with two `dask worker`s; while they run, SIGKILLs of a worker (twice), of
the service (restarted), then of the scheduler (restarted on the same port, workers
started again, as compose's `restart:` or systemd would), then of the service again.

Every job must end `finished` with populations bit-identical to a run of its stored spec in
one process (``service.report.analysis.run_to_store``, which the determinism tests tie to
`abcns run`), its event ids 1, 2, ... with none lost or repeated, and `/health` must answer
throughout except while the service is down. The kills are driven by the count of finished
populations (events), not by timing."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from distributed import Client
from http_helpers import same_populations

from benchmarks.harness import AUTH, BIN, ROOT, Service, duffing_spec, free_port, probe_client, stop, wait_until
from service.report.analysis import run_to_store
from service.spec import parse

pytestmark = [pytest.mark.http, pytest.mark.distributed]
N_JOBS = 10


class KillableCluster:
    """A scheduler on a fixed port and two workers, each killable and restartable."""

    def __init__(self, tmp: Path):
        self.tmp, self.port = tmp, free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.env = {**os.environ, "PYTHONPATH": str(ROOT)}
        self.scheduler = self._scheduler()
        self.workers: list[subprocess.Popen] = []
        self.start_workers()

    def _popen(self, args: list, log: str) -> subprocess.Popen:
        with (self.tmp / log).open("ab") as out:
            return subprocess.Popen(args, stdout=out, stderr=out, start_new_session=True, env=self.env)

    def _scheduler(self) -> subprocess.Popen:
        proc = self._popen([BIN / "dask", "scheduler", "--host", "127.0.0.1", "--port", str(self.port),
                            "--dashboard-address", ":0"], "scheduler.log")
        wait_until(lambda: _answers(self.port), 60, "the scheduler to listen", 0.1)
        return proc

    def start_workers(self) -> None:
        stop([w for w in self.workers if w.poll() is None])
        self.workers = [self._popen([BIN / "dask", "worker", self.address, "--nthreads", "1", "--nworkers", "1",
                                     "--no-dashboard", "--local-directory", str(self.tmp)], "workers.log")
                        for _ in range(2)]
        with self.client() as client:
            client.wait_for_workers(2, timeout=60)

    def client(self) -> Client:
        """A client of the scheduler. A scheduler just restarted listens before it can take a
        client (distributed's handshake then fails an assertion): retry for up to 60 s."""
        deadline = time.monotonic() + 60
        while True:
            try:
                return Client(self.address, timeout=30)
            except (AssertionError, OSError, TimeoutError):
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)

    def kill_a_worker_process(self) -> None:
        """SIGKILL one worker process (its nanny, the `dask worker` process, starts a new one).
        A worker that leaves while it is asked for its pid (one still starting after an
        earlier kill) answers nothing: the others do."""
        with self.client() as client:
            client.wait_for_workers(2, timeout=60)
            pids = client.run(os.getpid, on_error="return").values()
        os.kill(sorted(pid for pid in pids if isinstance(pid, int))[0], signal.SIGKILL)

    def kill_and_restart_the_scheduler(self) -> None:
        os.killpg(self.scheduler.pid, signal.SIGKILL)
        self.scheduler.wait()
        self.scheduler = self._scheduler()
        self.start_workers()  # workers leave when their scheduler does

    def close(self) -> None:
        stop([*self.workers, self.scheduler])


def _answers(port: int) -> bool:
    import socket

    try:
        socket.create_connection(("127.0.0.1", port), 1).close()
        return True
    except OSError:
        return False


def populations_done(http: httpx.Client, service: Service) -> int:
    try:
        jobs = http.get(f"{service.url}/jobs", headers=AUTH).json()
    except httpx.HTTPError:
        return 0
    return sum((j.get("progress") or {}).get("population", 0) for j in jobs)


@pytest.mark.slow
def test_jobs_survive_killed_workers_service_and_scheduler(tmp_path):
    cluster = KillableCluster(tmp_path)
    service = Service(tmp_path / "jobs", cluster.address, max_running=2, env={"ABCNS_MAX_RESUMES": "10"})
    down = threading.Event()
    stopping = threading.Event()
    missed: list[float] = []  # /health probes that failed while the service was up

    def probe() -> None:
        with probe_client(timeout=5) as probes:  # each probe a new connection, as httpx.get's
            while not stopping.is_set():
                was_down = down.is_set()
                try:
                    ok = probes.get(f"{service.url}/health").status_code == 200
                except httpx.HTTPError:
                    ok = False
                if not ok and not was_down and not down.is_set():
                    missed.append(time.monotonic())
                time.sleep(0.1)

    start = time.monotonic()
    rss_before = service.rss_mb()
    prober = threading.Thread(target=probe, daemon=True)
    prober.start()
    kills: list[str] = []
    http = probe_client(timeout=10)  # the polls below: a new connection each, without a client built each time
    try:
        ids = []
        for seed in range(1, N_JOBS + 1):
            spec = {**duffing_spec(max_populations=6, particles=200), "seed": seed, "name": f"chaos-{seed}"}
            r = httpx.post(f"{service.url}/jobs", json=spec, headers=AUTH, timeout=60)
            assert r.status_code == 201, r.text
            ids.append(r.json()["id"])

        def at(n_populations: int, what: str, action) -> None:
            wait_until(lambda: populations_done(http, service) >= n_populations, 300, f"{n_populations} populations")
            action()
            kills.append(f"{what} after {populations_done(http, service)} populations")

        def kill_service() -> None:
            down.set()
            service.kill()
            service.start()
            down.clear()

        at(3, "a worker", cluster.kill_a_worker_process)
        at(8, "a worker", cluster.kill_a_worker_process)
        at(14, "the service", kill_service)
        at(22, "the scheduler", cluster.kill_and_restart_the_scheduler)
        at(30, "the service", kill_service)

        def all_ended() -> bool:
            jobs = http.get(f"{service.url}/jobs", headers=AUTH).json()
            return len(jobs) == N_JOBS and all(j["status"] in ("finished", "failed", "cancelled") for j in jobs)

        wait_until(all_ended, 600, "every job to end", 0.5)
        wall = time.monotonic() - start
        rss_after = service.rss_mb()
        jobs = {j["id"]: j for j in httpx.get(f"{service.url}/jobs", headers=AUTH, timeout=10).json()}
        for job_id in ids:
            folder = service.job_dir(job_id)
            events = [json.loads(line) for line in (folder / "events.jsonl").read_text().splitlines()]
            assert jobs[job_id]["status"] == "finished", (kills, jobs[job_id].get("error"), events[-4:])
            assert [e["id"] for e in events] == list(range(1, len(events) + 1)), [e["id"] for e in events]
            announced = [e["data"]["population"] for e in events if e["event"] == "population"]
            assert announced == list(range(1, 7)), announced  # each population announced once, in order
            spec = parse(json.loads((folder / "spec.json").read_text()))
            run_to_store(spec, folder, tmp_path / f"ref-{job_id}.zarr")
            same_populations(folder / "store.zarr", tmp_path / f"ref-{job_id}.zarr")
        requeued = sum("requeued" in (service.job_dir(i) / "events.jsonl").read_text() for i in ids)
        print(f"chaos: {N_JOBS} jobs, kills: {kills}; {requeued} jobs requeued by the scheduler's loss; "
              f"{wall:.0f} s; service RSS {rss_before:.0f} MB before, {rss_after:.0f} MB after")
        assert not missed, f"/health did not answer {len(missed)} times while the service was up"
        assert np.isfinite(wall)
    finally:
        http.close()
        stopping.set()
        prober.join(timeout=10)
        service.close()
        cluster.close()
