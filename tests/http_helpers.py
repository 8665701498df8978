"""What the HTTP, browser and chaos tests share besides ``benchmarks.harness`` (`abcns serve`
as a user starts it, the §4.1 job): the demo job, an event-stream reader, store comparison,
and the reset of a service shared by a module's tests (``settle``)."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import numpy as np
import yaml

from benchmarks.harness import AUTH, ROOT, Service, probe_client, wait_until
from service.http.jobs import TERMINAL
from service.run.store import Store


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


def settle(service: Service) -> None:
    """Cancel every job of ``service`` still queued or running and wait until each has
    ended: a service shared by a module's tests starts each test with its one running slot
    free, and no job a test left behind moves under the next."""
    with probe_client(timeout=60) as http:
        def jobs() -> list[dict]:
            return http.get(f"{service.url}/jobs", headers=AUTH).json()

        for job in jobs():
            if job["status"] not in TERMINAL:
                http.delete(f"{service.url}/jobs/{job['id']}", headers=AUTH)
        wait_until(lambda: all(j["status"] in TERMINAL for j in jobs()), 120, "the jobs left by a test to end", 0.05)
