"""What the HTTP, browser and container tests (and benchmarks/http_latency.py) share: `abcns
serve` as a user starts it, job specs, and an event-stream reader."""

from __future__ import annotations

import json
import os
import signal
import subprocess
from pathlib import Path

import httpx
import numpy as np
import yaml
from conftest import BIN, ROOT, free_port, stop, wait_until

from service.run.store import Store

TOKEN = "s3cret-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


class Service:
    """`abcns serve` as a user starts it; its output (the address, the access log) goes to
    ``log`` beside the store directory."""

    def __init__(self, store_dir: Path, scheduler: str, max_running: int = 1, port: int | None = None,
                 env: dict | None = None):
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.store_dir = Path(store_dir)
        self.log = self.store_dir.parent / f"serve-{self.port}.log"
        self.args = [BIN / "abcns", "serve", "--port", str(self.port), "--scheduler", scheduler, "--store-dir",
                     str(store_dir), "--token", TOKEN, "--max-running", str(max_running)]
        self.env = env or {}
        self.proc: subprocess.Popen | None = None
        self.start()

    def start(self) -> None:
        # one append, and so one event, per population as it is done (not coalesced), so a
        # test can act between populations of these short jobs
        env = {**os.environ, "PYTHONPATH": str(ROOT), "ABCNS_STORE_INTERVAL_S": "0", **self.env}
        with self.log.open("ab") as out:
            self.proc = subprocess.Popen(self.args, stdout=out, stderr=out, start_new_session=True, env=env)
        wait_until(self.healthy, 60, "the service to answer /health", 0.2)

    def healthy(self) -> bool:
        try:
            return httpx.get(f"{self.url}/health", timeout=2).status_code == 200
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


def duffing_spec(max_populations: int = 8, particles: int = 500) -> dict:
    """Paper §4.1 (examples/duffing_41) with inline data, shortened."""
    raw = yaml.safe_load((ROOT / "examples" / "duffing_41" / "spec.yaml").read_text())
    folder = ROOT / "examples" / "duffing_41"
    raw["data"]["input"] = np.load(folder / "force.npy").tolist()
    raw["data"]["observed"] = np.load(folder / "displacement.npy").tolist()
    raw["sampler"].update(particles=particles, batch_size=250)
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": max_populations}
    return raw


def demo_spec(seed: int) -> dict:
    with np.load(ROOT / "data" / "authors-demo" / "demo_data.npz") as d:
        force, x = d["force"].tolist(), d["displacement"].tolist()
    raw = yaml.safe_load((ROOT / "examples" / "authors_demo" / "spec.yaml").read_text())
    raw["data"].update(input=force, observed=x)
    raw["sampler"].update(particles=200, batch_size=100)
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": 3}
    raw["seed"] = seed
    return raw


def parse_events(lines) -> list[dict]:
    """Server-sent events from the lines of a stream (``event``, ``id`` as int, ``data`` as JSON)."""
    events: list[dict] = []
    current: dict = {}
    for line in lines:
        if not line:
            if "event" in current:
                current["data"] = json.loads(current.get("data", "null"))
                current["id"] = int(current["id"])
                events.append(current)
            current = {}
            continue
        field, _, value = line.partition(":")
        if field in ("event", "data", "id"):
            current[field] = value.lstrip(" ")
    return events


def follow(url: str, job_id: str, after: int = 0, until=None, timeout: float = 240) -> list[dict]:
    """Read the job's event stream (from Last-Event-ID ``after``) until a terminal event or
    until ``until(events)`` is true."""
    events: list[dict] = []
    headers = {**AUTH, **({"Last-Event-ID": str(after)} if after else {})}
    with httpx.stream("GET", f"{url}/jobs/{job_id}/events", headers=headers, timeout=timeout) as r:
        assert r.status_code == 200, r.read()
        current: list[str] = []
        for line in r.iter_lines():
            current.append(line)
            if line:
                continue
            got = parse_events(current)
            current = []
            events += got
            if got and (got[-1]["event"] in ("finished", "failed", "cancelled") or (until and until(events))):
                return events
    return events


def populations(events: list[dict]) -> int:
    return sum(e["event"] == "population" for e in events)


def same_populations(a: Path, b: Path) -> None:
    sa, sb = Store.open(a), Store.open(b)
    assert sa.n_populations == sb.n_populations > 0
    for p, q in zip(sa.populations(), sb.populations()):
        for name in ("models", "theta", "distances", "weights", "survivors"):
            np.testing.assert_array_equal(getattr(p, name), getattr(q, name), err_msg=f"population {p.t} {name}")
