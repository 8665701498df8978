"""Real processes as a user starts them, on 127.0.0.1 only: a stock `dask scheduler` with
`dask worker` processes, and `abcns serve`; plus the shortened §4.1 job the HTTP
measurements submit. Shared by the benchmarks (``http_latency``, ``scale``) and the tests
(``tests/conftest.py``, ``tests/http_helpers.py``), which import it as ``benchmarks.harness``.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml
from distributed import Client

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
TOKEN = "s3cret-token"  # noqa: S105 - the benchmark service's own token
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop(procs: list[subprocess.Popen], timeout: float = 20) -> None:
    """SIGTERM to each process group, SIGKILL to those still there after ``timeout`` s."""
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def wait_until(predicate, timeout: float, what: str, interval: float = 0.05):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise TimeoutError(f"timed out after {timeout} s waiting for {what}")


class StockCluster:
    """A `dask scheduler` and `dask worker` processes, with the Dask settings of docs/deploy.md."""

    def __init__(self, tmp: Path, n_workers: int = 2):
        from service.run.dask_executor import cluster_env

        self.port = free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        env = {**os.environ, **cluster_env(), "PYTHONPATH": str(ROOT)}
        self.tmp = tmp
        self.quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "start_new_session": True, "env": env}
        self.procs = [subprocess.Popen([BIN / "dask", "scheduler", "--host", "127.0.0.1", "--port", str(self.port),
                                        "--dashboard-address", ":0"], **self.quiet)]
        self.start_workers(n_workers)

    def start_workers(self, n: int, threads: int = 1) -> None:
        """``n`` more `dask worker` processes of ``threads`` threads; returns once the scheduler has them."""
        for _ in range(n):
            self.procs.append(subprocess.Popen([BIN / "dask", "worker", self.address, "--nthreads", str(threads),
                                                "--nworkers", "1", "--no-dashboard", "--local-directory", str(self.tmp)],
                                               **self.quiet))
        with Client(self.address, timeout=30) as client:
            client.wait_for_workers(len(self.procs) - 1, timeout=60)

    def worker_pids(self) -> list[int]:
        """The pids of the workers that answer: one just killed may still be listed by the
        scheduler, and its closed connection would fail the whole broadcast (a test's
        CommClosedError after a SIGKILL, 2026-12-05), so it is left out."""
        with Client(self.address, timeout=30) as client:
            return sorted(client.run(os.getpid, on_error="ignore").values())

    def close(self) -> None:
        stop(self.procs)


def probe_client(timeout: float = 2):
    """An httpx client for a loop of requests that behaves as a call of ``httpx.get`` each
    (a new connection per request, none kept), without its cost: each ``httpx.get`` builds a
    client (its TLS context) for ~25 ms of CPU, ~1 ms with this one; a poll every 0.05 s
    through ``httpx.get`` takes half a core of a 2-core machine from what it waits for."""
    import httpx

    return httpx.Client(timeout=timeout, limits=httpx.Limits(max_keepalive_connections=0))


class Service:
    """`abcns serve` as a user starts it; its output (the address, the access log) goes to
    ``log`` beside the store directory."""

    def __init__(self, store_dir: Path, scheduler: str, max_running: int | None = 1, port: int | None = None,
                 env: dict | None = None):
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.store_dir = Path(store_dir)
        self.log = self.store_dir.parent / f"serve-{self.port}.log"
        self.args = [BIN / "abcns", "serve", "--port", str(self.port), "--scheduler", scheduler, "--store-dir",
                     str(store_dir), "--token", TOKEN, *([] if max_running is None else ["--max-running", str(max_running)])]
        self.env = env or {}
        self.proc: subprocess.Popen | None = None
        self.start()

    def start(self) -> None:
        # one append, and so one event, per population as it is done (not coalesced), so a
        # test can act between populations of these short jobs
        env = {**os.environ, "PYTHONPATH": str(ROOT), "ABCNS_STORE_INTERVAL_S": "0", **self.env}
        with self.log.open("ab") as out:
            self.proc = subprocess.Popen(self.args, stdout=out, stderr=out, start_new_session=True, env=env)
        with probe_client() as http:
            wait_until(lambda: self.healthy(http), 60, "the service to answer /health", 0.05)

    def healthy(self, http) -> bool:
        """Whether /health answers 200 (asked through ``http``, a :func:`probe_client`)."""
        import httpx  # the dev extra: the cluster helpers above run on the runtime install (make bench)

        try:
            return http.get(f"{self.url}/health").status_code == 200
        except httpx.HTTPError:
            return False

    def kill(self) -> None:
        os.killpg(self.proc.pid, signal.SIGKILL)  # type: ignore[union-attr]
        self.proc.wait()  # type: ignore[union-attr]

    def close(self) -> None:
        stop([self.proc])  # type: ignore[list-item]

    def job_dir(self, job_id: str) -> Path:
        return self.store_dir / job_id

    def rss_mb(self) -> float:
        """The resident memory of the `abcns serve` process."""
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():  # type: ignore[union-attr]
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        raise RuntimeError("no VmRSS")


def duffing_spec(max_populations: int = 8, particles: int = 500, noise_floor: bool = True) -> dict:
    """Paper §4.1 (examples/duffing_41) with inline data, shortened; ``noise_floor=False``:
    a run that does not stop at the noise floor either (one that runs until cancelled)."""
    raw = yaml.safe_load((ROOT / "examples" / "duffing_41" / "spec.yaml").read_text())
    folder = ROOT / "examples" / "duffing_41"
    raw["data"]["input"] = np.load(folder / "force.npy").tolist()
    raw["data"]["observed"] = np.load(folder / "displacement.npy").tolist()
    raw["sampler"].update(particles=particles, batch_size=250)
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": max_populations, "noise_floor": noise_floor}
    return raw
