"""Shared fixtures: real processes started as a user would (`dask scheduler`, `dask worker`,
`abcns serve`), on 127.0.0.1 only, stopped at the end."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from distributed import Client

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


class StockCluster:
    """A `dask scheduler` and `dask worker` processes."""

    def __init__(self, tmp: Path, n_workers: int = 2):
        self.port = free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "start_new_session": True, "env": env}
        self.procs = [subprocess.Popen([BIN / "dask", "scheduler", "--host", "127.0.0.1", "--port", str(self.port),
                                        "--dashboard-address", ":0"], **quiet)]
        for _ in range(n_workers):
            self.procs.append(subprocess.Popen([BIN / "dask", "worker", self.address, "--nthreads", "1", "--nworkers", "1",
                                                "--no-dashboard", "--local-directory", str(tmp)], **quiet))
        with Client(self.address, timeout=30) as client:
            client.wait_for_workers(n_workers, timeout=60)

    def worker_pids(self) -> list[int]:
        with Client(self.address, timeout=30) as client:
            return sorted(client.run(os.getpid).values())

    def close(self) -> None:
        stop(self.procs)


@pytest.fixture
def stock_cluster(tmp_path):
    cluster = StockCluster(tmp_path)
    yield cluster.address
    cluster.close()


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A stock cluster shared by the tests of one module."""
    c = StockCluster(tmp_path_factory.mktemp("dask"))
    yield c
    c.close()


def wait_until(predicate, timeout: float, what: str, interval: float = 0.05):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise TimeoutError(f"timed out after {timeout} s waiting for {what}")
