"""Many jobs, one cluster: the queue, the job threads, and each job's event log.

Every job lives in its own folder of the store directory: ``job.json`` (id, status, spec),
``events.jsonl`` (its events, ids 1, 2, ...) and ``store.zarr`` (its populations). A
restarted service lists every job from the folders and puts the queued and running ones
back in the queue; a running one resumes from its last complete population (the runner's
resume), so it ends exactly as an uninterrupted run, and its events continue.
"""

from __future__ import annotations

import asyncio
import json
import os
import threading
import time
import uuid
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from distributed import Client

from abcns import SpecError
from service.runner import Progress, run_job, summary
from service.spec import JobSpec, build
from service.store import Store, StoreError

TERMINAL = ("finished", "failed", "cancelled")
EVENT_TYPES = ("queued", "started", "population", *TERMINAL)


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data))
    os.replace(tmp, path)  # atomic: a reader sees the old or the new file


class EventLog:
    """Append-only events of one job, on disk and in memory; async readers wake on append.

    ``append`` may be called from any thread; ``follow`` runs on the service's event loop."""

    def __init__(self, path: Path, loop: asyncio.AbstractEventLoop | None):
        self.path = path
        self.loop = loop
        self.lock = threading.Lock()
        self.events: list[dict] = []
        if path.exists():
            for line in path.read_text().splitlines():
                if line.strip():
                    try:
                        self.events.append(json.loads(line))
                    except json.JSONDecodeError:
                        break  # a line cut by a crash: the events after it are re-emitted
        self._changed = asyncio.Event() if loop is not None else None

    @property
    def last_id(self) -> int:
        return self.events[-1]["id"] if self.events else 0

    def append(self, event: str, data: dict) -> dict:
        with self.lock:
            record = {"id": self.last_id + 1, "event": event, "data": data, "time": time.time()}
            with self.path.open("a") as f:
                f.write(json.dumps(record) + "\n")
            self.events.append(record)
        if self.loop is not None and not self.loop.is_closed():
            self.loop.call_soon_threadsafe(self._notify)
        return record

    def _notify(self) -> None:
        changed, self._changed = self._changed, asyncio.Event()
        changed.set()  # type: ignore[union-attr]

    def since(self, after: int) -> list[dict]:
        with self.lock:
            return [e for e in self.events if e["id"] > after]

    def ended(self) -> bool:
        with self.lock:
            return bool(self.events) and self.events[-1]["event"] in TERMINAL

    async def follow(self, after: int = 0, heartbeat_s: float = 15.0):
        """Every event after ``after``, then each new one, until a terminal event."""
        while True:
            waiter = self._changed
            for e in self.since(after):
                after = e["id"]
                yield e
                if e["event"] in TERMINAL:
                    return
            try:
                await asyncio.wait_for(waiter.wait(), heartbeat_s)  # type: ignore[union-attr]
            except TimeoutError:
                yield None  # a keep-alive; the caller decides what to send


@dataclass
class JobRecord:
    id: str
    folder: Path
    spec: dict
    status: str
    created_at: float
    error: str | None = None
    progress: dict | None = None
    result: dict | None = None
    cancel: threading.Event = field(default_factory=threading.Event)
    events: EventLog | None = None

    @property
    def store_path(self) -> Path:
        return self.folder / "store.zarr"

    def save(self) -> None:
        _write_json(self.folder / "job.json", {"id": self.id, "status": self.status, "created_at": self.created_at,
                                               "error": self.error, "spec": self.spec})

    def public(self) -> dict[str, Any]:
        return {"id": self.id, "name": self.spec.get("name"), "status": self.status, "created_at": self.created_at,
                "error": self.error, "progress": self.progress}


class JobManager:
    """The queue and the running jobs of one service process."""

    def __init__(self, store_dir: Path, client: Client, max_running: int, loop: asyncio.AbstractEventLoop | None):
        self.store_dir = Path(store_dir)
        self.store_dir.mkdir(parents=True, exist_ok=True)
        self.client = client
        self.max_running = max_running
        self.loop = loop
        self.jobs: dict[str, JobRecord] = {}
        self.queue: deque[str] = deque()
        self.running: set[str] = set()
        self.lock = threading.Lock()
        self.wake = threading.Condition(self.lock)
        self.stopping = False
        self._load()
        self.dispatcher = threading.Thread(target=self._dispatch, name="abcns-dispatcher", daemon=True)
        self.dispatcher.start()

    # ------------------------------------------------------------------ state
    def _load(self) -> None:
        """Every job in the store directory; unfinished ones go back in the queue."""
        found = []
        for folder in self.store_dir.iterdir():
            meta = folder / "job.json"
            if not (folder.is_dir() and meta.is_file()):
                continue
            try:
                raw = json.loads(meta.read_text())
            except (OSError, json.JSONDecodeError):
                continue
            job = JobRecord(raw["id"], folder, raw["spec"], raw["status"], raw["created_at"], raw.get("error"))
            job.events = EventLog(folder / "events.jsonl", self.loop)
            job.progress = self._progress_from_events(job)
            found.append(job)
        for job in sorted(found, key=lambda j: j.created_at):
            self.jobs[job.id] = job
            if job.status not in TERMINAL:
                job.status = "queued"
                job.save()
                self.queue.append(job.id)

    @staticmethod
    def _progress_from_events(job: JobRecord) -> dict | None:
        pops = [e for e in job.events.events if e["event"] == "population"]  # type: ignore[union-attr]
        return pops[-1]["data"] if pops else None

    def submit(self, spec: JobSpec) -> JobRecord:
        """Validate completely (files are not allowed: data inline), then queue."""
        build(spec, None, allow_import=False)  # raises SpecError naming the field
        job_id = uuid.uuid4().hex
        folder = self.store_dir / job_id
        folder.mkdir()
        job = JobRecord(job_id, folder, spec.model_dump(mode="json"), "queued", time.time())
        job.events = EventLog(folder / "events.jsonl", self.loop)
        job.save()
        job.events.append("queued", {"id": job_id})
        with self.lock:
            self.jobs[job_id] = job
            self.queue.append(job_id)
            self.wake.notify_all()
        return job

    def get(self, job_id: str) -> JobRecord | None:
        return self.jobs.get(job_id)

    def list(self, status: str | None = None) -> list[JobRecord]:
        jobs = sorted(self.jobs.values(), key=lambda j: j.created_at)
        return [j for j in jobs if status is None or j.status == status]

    def cancel(self, job_id: str) -> JobRecord:
        job = self.jobs[job_id]
        with self.lock:
            if job.status == "queued":
                self.queue.remove(job_id)
                self._end(job, "cancelled", None)
                return job
        job.cancel.set()  # a running job stops between batches; what it did stays in the store
        return job

    def result(self, job: JobRecord) -> dict | None:
        if job.result is None and job.store_path.exists():
            try:
                job.result = summary(Store.open(job.store_path))
            except StoreError:
                return None
        return job.result

    # ------------------------------------------------------------------ running
    def _dispatch(self) -> None:
        while True:
            with self.lock:
                while not self.stopping and (not self.queue or len(self.running) >= self.max_running):
                    self.wake.wait()
                if self.stopping:
                    return
                job = self.jobs[self.queue.popleft()]
                self.running.add(job.id)
            threading.Thread(target=self._run, args=(job,), name=f"abcns-job-{job.id[:8]}", daemon=True).start()

    @staticmethod
    def _progress(job: JobRecord, pop, n_simulations_total: int, elapsed_s: float, rate: float | None) -> dict:
        return {
            "population": pop.t, "epsilon": pop.epsilon, "epsilon_next": pop.epsilon_next,
            "acceptance_rate": pop.acceptance_rate, "simulations": int(n_simulations_total),
            "model_probabilities": dict(zip([m["name"] for m in job.spec["models"]], map(float, pop.model_probabilities))),
            "elapsed_s": float(elapsed_s), "simulations_per_s": rate,
        }

    def _backfill(self, job: JobRecord) -> None:
        """Population events for populations in the store but not in the log (the service
        died between a store append and its event)."""
        try:
            store = Store.open(job.store_path)
        except StoreError:
            return
        seen = {e["data"]["population"] for e in job.events.events if e["event"] == "population"}  # type: ignore[union-attr]
        missing = [t for t in range(1, store.n_populations + 1) if t not in seen]
        if not missing:
            return
        totals = store.dataset()["n_simulations_total"].values
        for t in missing:
            pop = store.population(t)
            job.progress = self._progress(job, pop, totals[t - 1], pop.elapsed_s, None)
            job.events.append("population", job.progress)  # type: ignore[union-attr]

    def _run(self, job: JobRecord) -> None:
        resumed = job.store_path.exists()
        job.status = "running"
        job.save()
        job.events.append("started", {"resumed": resumed})  # type: ignore[union-attr]
        if resumed:
            self._backfill(job)

        def on_population(p: Progress) -> None:
            job.progress = self._progress(job, p.population, p.n_simulations_total, p.elapsed_s, p.simulations_per_s)
            job.events.append("population", job.progress)  # type: ignore[union-attr]

        try:
            spec = JobSpec.model_validate(job.spec)
            result = run_job(spec, None, job.store_path, self.client, on_population=on_population,
                             cancel=lambda: job.cancel.is_set() or self.stopping)
            if result.stop_reason.value == "cancelled" and self.stopping and not job.cancel.is_set():
                job.status = "queued"  # the service is stopping: the job resumes when it starts again
                job.save()
            else:
                self._end(job, "cancelled" if result.stop_reason.value == "cancelled" else "finished", None)
        except (SpecError, StoreError) as err:
            self._end(job, "failed", str(err))
        except Exception as err:  # noqa: BLE001 - a job's failure must not take the service down
            self._end(job, "failed", f"{type(err).__name__}: {err}")
        finally:
            with self.lock:
                self.running.discard(job.id)
                self.wake.notify_all()

    def _end(self, job: JobRecord, status: str, error: str | None) -> None:
        job.status, job.error, job.result = status, error, None
        job.save()
        data: dict[str, Any] = {"status": status}
        if error:
            data["error"] = error
        result = self.result(job)
        if result:
            data.update(stop_reason=result.get("stop_reason"), n_populations=result.get("n_populations"),
                        n_simulations=result.get("n_simulations"),
                        model_probabilities=result.get("model_probabilities"))
        job.events.append(status, data)  # type: ignore[union-attr]

    def shutdown(self, timeout_s: float = 30.0) -> None:
        """Stop taking jobs; running ones stop between batches and stay queued for the next start."""
        with self.lock:
            self.stopping = True
            self.wake.notify_all()
        deadline = time.monotonic() + timeout_s
        while self.running and time.monotonic() < deadline:
            time.sleep(0.05)
