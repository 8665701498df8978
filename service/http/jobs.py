"""Many jobs, one cluster: the queue, the job threads, and each job's event log.

Every job lives in its own folder of the store directory:

- ``job.json``: the record (id, status, created_at, error, name, model names, crash count),
  small and rewritten on every change of status;
- ``spec.json``: the spec as submitted, its data replaced by references to ``data.npz``
  (written once);
- ``data.npz``: the job's arrays (``input``, ``observed``), compressed, cut to the samples
  the job reads (``service.spec.samples_read``);
- ``events.jsonl``: its events, ids 1, 2, ...;
- ``store.zarr``: its populations;
- ``result.json``: the summary of an ended job, computed once when it ends (``GET
  /jobs/{id}/result`` reads it; a running job's summary is computed per request, one at a
  time).

The manager keeps only the records in memory (no spec, no data, no events): the spec is
read when the job starts, the events when a client asks for them. A restarted service lists
every job from the folders (a folder it cannot read is skipped and logged, never an error
of the job list) and puts the queued and running ones back in the queue; a running one
resumes from its last complete population (the runner's resume), so it ends exactly as an
uninterrupted run, and its events continue. A job found ``running`` was running when the
service died; it is resumed at most ``max_resumes`` times, then marked failed with the
reason, so a job that kills the service cannot do it again on every restart. A job whose
record could not be written when it ended (a full disk) gets its status and its error back
from its terminal event. A job whose store write finds the disk full is requeued and resumes
from its stored populations once the disk has room for its next ones (the dispatcher starts
the queue's head only then; a submission without that room is refused: :class:`NoSpace`).

Admission is exact under any concurrency: a submission takes its place in the queue under
the manager's lock before anything is built or written (and gives it back if it fails), and
a cancel finds a queued job in the queue under the same lock, or stops it once it runs.
"""

from __future__ import annotations

import asyncio
import datetime
import json
import logging
import math
import re
import shutil
import threading
import time
import uuid
from collections import deque
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from distributed import Client

from abcns import SpecError, StopReason
from service.http.limits import Limits, admit
from service.run.jobs import (
    JOB_RESOURCE,
    JobRun,
    WorkerWatch,
    ask_to_spread,
    cluster_slots,
    job_workers,
    no_space,
    prepare_cluster,
    run_one,
    scheduler_id,
    scheduler_identity,
    spread_next,
)
from service.run.runner import Progress, local_population_s, run_job, summary, wait_for_store_lock
from service.run.store import Store, StoreError, metadata
from service.spec import JobSpec, build, cut_to_read, spec_text

TERMINAL = ("finished", "failed", "cancelled")
STATUSES = ("queued", "running", *TERMINAL)
DATA_FILE = "data.npz"
RESULT_FILE = "result.json"
JOB_ID = re.compile(r"[0-9a-f]{32}")
UTILIZATION_WINDOW_S = 60.0  # /health's utilization: over the last minute
log = logging.getLogger("abcns.jobs")


def _write_json(path: Path, data: dict) -> None:
    """Atomic (a reader sees the old or the new file); on a full disk no temporary file is
    left behind (issue Z.6)."""
    metadata.replace(path, json.dumps(data).encode())


FIRST_POPULATIONS = 10  # the populations whose room a job needs before it is admitted, and to start
STORE_FIXED_BYTES = 1 << 20  # its files besides its populations (§4.1's store: ~0.5 MB in 4 KB blocks)
DEFAULT_PARTICLES = 1000  # a spec's sampler without particles: abcns's default
MAX_NO_SPACE = 3  # requeues of a job whose writes found the disk full, before it fails (issue Z.6)


class NoSpace(Exception):
    """The job store's disk has no room for a job's first populations (HTTP 507)."""


def space_needed(spec: JobSpec, data_bytes: int = 0, max_particles: int | None = None) -> int:
    """Bytes a job needs: its data, its files and its first :data:`FIRST_POPULATIONS`
    populations at 8 bytes a value, uncompressed (particles x (parameters + 4): theta, the
    distance, the weight, the model, the survivor flag; §4.1 measured 41 bytes a particle,
    compressed, against this bound's 64). Particles count up to ``max_particles``: a job
    with more is refused by the service's limits, naming the field (a 422, not a 507)."""
    dims = max(len(m.priors) for m in spec.models)
    particles = int(getattr(spec.sampler, "particles", None) or DEFAULT_PARTICLES)
    particles = particles if max_particles is None else min(particles, max_particles)
    return STORE_FIXED_BYTES + data_bytes + FIRST_POPULATIONS * particles * (dims + 4) * 8


def _read_json(path: Path) -> Any:
    """The JSON in ``path``, or None when it is missing or unreadable."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def clean_text(s: str) -> str:
    """``s`` with anything that is not Unicode text (a lone surrogate) written as an escape:
    what a record written before names were checked may hold."""
    return s.encode("utf-8", "backslashreplace").decode("utf-8")


TAIL_EVENTS = 256  # the recent events of a log kept in memory for its followers
SEND_GAP_S = 0.25  # a stream sends at most once per this: the events meanwhile go together


class _Entry:
    """A recent event, and its server-sent form once one follower has made it (shared)."""

    __slots__ = ("record", "sent")

    def __init__(self, record: dict):
        self.record, self.sent = record, b""


class EventLog:
    """Append-only events of one job, on disk; async readers wake on append.

    The last id and event name are kept in memory, and the last :data:`TAIL_EVENTS` events
    (appended to the tail on the event loop, after the line is on disk). A follower reads
    the file once, to catch up, then takes new events from the tail: one file read and one
    encoding of each event for all of a job's streams together (500 streams that each read
    the file and encoded each event stalled the service's loop for seconds, issue Z.1). A
    follower that fell behind the tail reads the file again. ``append`` may be called from
    any thread; ``follow`` runs on the service's event loop."""

    def __init__(self, path: Path, loop: asyncio.AbstractEventLoop | None):
        self.path = path
        self.loop = loop
        self.lock = threading.Lock()
        self.last_id = 0
        self.last_event: str | None = None
        self.last_population: dict | None = None
        self.last_error: str | None = None  # a terminal event's error (what job.json may have missed)
        self.tail: deque[_Entry] = deque(maxlen=TAIL_EVENTS)  # touched on the loop only
        self._changed: asyncio.Future | None = loop.create_future() if loop is not None else None
        self._scan()

    def _scan(self) -> None:
        """Find the last event; a line cut by a crash (and anything after it) is cut off the
        file, so the events appended next follow the last complete one."""
        if not self.path.exists():
            return
        good = 0
        with self.path.open("rb") as f:
            for line in f:
                try:
                    if not line.endswith(b"\n"):
                        raise ValueError("a line cut short")
                    e = json.loads(line)
                    self.last_id, self.last_event = int(e["id"]), str(e["event"])
                    if self.last_event == "population":
                        self.last_population = e["data"]
                    elif self.last_event in TERMINAL:
                        error = e["data"].get("error")
                        self.last_error = error if isinstance(error, str) else None
                except (ValueError, KeyError, TypeError):
                    break
                good += len(line)
        if good < self.path.stat().st_size:
            with self.path.open("r+b") as f:
                f.truncate(good)

    def append(self, event: str, data: dict) -> dict:
        with self.lock:
            record: dict[str, Any] = {"id": self.last_id + 1, "event": event, "data": data, "time": time.time()}
            with self.path.open("a") as f:
                f.write(json.dumps(record) + "\n")
            self.last_id, self.last_event = record["id"], event
            if event == "population":
                self.last_population = data
            if self.loop is not None and not self.loop.is_closed():  # under the lock: the tail in id order
                self.loop.call_soon_threadsafe(self._notify, record)
        return record

    def _notify(self, record: dict | None = None) -> None:
        """On the loop: ``record`` joins the tail (None: only wake the followers)."""
        if record is not None:
            self.tail.append(_Entry(record))
        changed, self._changed = self._changed, self.loop.create_future()  # type: ignore[union-attr]
        assert changed is not None  # called on the loop, which a log with a loop has
        changed.set_result(None)

    def read(self, pos: int = 0) -> tuple[list[dict], int]:
        """The complete events from byte ``pos`` on, and the position after them."""
        try:
            with self.path.open("rb") as f:
                f.seek(pos)
                chunk = f.read()
        except FileNotFoundError:  # purged
            return [], pos
        end = chunk.rfind(b"\n") + 1  # a line being appended is read next time
        events = [json.loads(line) for line in chunk[:end].splitlines() if line.strip()]
        return events, pos + end

    def ended(self) -> bool:
        return self.last_event in TERMINAL

    def _recent(self, after: int) -> list[_Entry] | None:
        """The tail's events after id ``after``; None when the tail does not reach back to it."""
        if not self.tail or self.tail[0].record["id"] > after + 1:
            return None
        return [e for e in self.tail if e.record["id"] > after]

    async def follow(self, after: int, closing: asyncio.Event, encode: Callable[[dict], bytes],
                     heartbeat_s: float = 15.0) -> AsyncIterator[bytes | None]:
        """Every event after ``after``, then the new ones, until a terminal event, as chunks
        of ``encode(record)`` bytes (at most one chunk per :data:`SEND_GAP_S`; a tail event's
        bytes are made once for every follower); at once to the end for an ended job
        (``after`` past its last event included), and at once when ``closing`` is set (the
        service is stopping: the manager wakes every follower). ``None`` is a keep-alive."""
        pos, file = 0, True  # the file read to ``pos`` (a line boundary at or before ``after``)
        while True:
            waiter = self._changed
            ended = self.ended()  # before reading: an ended log's terminal line is on disk
            recent = None if file else self._recent(after)
            if recent is None or (ended and not (recent and recent[-1].record["event"] in TERMINAL)):
                events, pos = self.read(pos)
                recent, file = [_Entry(e) for e in events if e["id"] > after], False
            chunk, last = self._encoded(recent, encode)
            if chunk:
                after = recent[-1].record["id"]
                yield chunk
                if last:
                    return
            if ended or closing.is_set():
                return
            if chunk:
                await asyncio.sleep(SEND_GAP_S)  # the events meanwhile go in the next chunk
                continue
            assert waiter is not None, "a log read by follow() has an event loop"
            done, _ = await asyncio.wait([waiter], timeout=heartbeat_s)  # a shared future: no task per stream
            if not done and not closing.is_set():
                yield None  # a keep-alive; the caller decides what to send

    @staticmethod
    def _encoded(entries: list[_Entry], encode: Callable[[dict], bytes]) -> tuple[bytes, bool]:
        """The entries' bytes (up to a terminal one), and whether a terminal one ended them."""
        out = []
        for e in entries:
            if not e.sent:
                e.sent = encode(e.record)
            out.append(e.sent)
            if e.record["event"] in TERMINAL:
                return b"".join(out), True
        return b"".join(out), False


@dataclass
class JobRecord:
    """What the manager keeps of a job: its metadata, never its spec or data."""

    id: str
    folder: Path
    name: str
    models: list[str]
    status: str
    created_at: float
    error: str | None = None
    crashes: int = 0  # times the service died while this job ran
    progress: dict | None = None
    placement: dict | None = None  # where its loop runs (service.run.jobs.place), while it runs
    cancel: threading.Event = field(default_factory=threading.Event)
    announcing: threading.Lock = field(default_factory=threading.Lock)  # one population event at a time
    turn: threading.Event = field(default_factory=threading.Event)  # asked to give its worker to a waiting job
    running_since: float = 0.0  # monotonic: when its loop last started (its turn's start)
    task: str | None = None  # its loop's Dask task, while it runs on a worker
    events: EventLog | None = None  # opened when the manager takes the job (``log``)

    @property
    def log(self) -> EventLog:
        """The job's event log: every job the manager holds has one."""
        assert self.events is not None, f"job {self.id}: its event log was never opened"
        return self.events

    @property
    def store_path(self) -> Path:
        return self.folder / "store.zarr"

    def spec(self) -> dict:
        return json.loads((self.folder / "spec.json").read_text())

    def save(self) -> None:
        _write_json(self.folder / "job.json", {
            "id": self.id, "status": self.status, "created_at": self.created_at, "error": self.error,
            "name": self.name, "models": self.models, "crashes": self.crashes})

    def public(self) -> dict[str, Any]:
        created = datetime.datetime.fromtimestamp(self.created_at, datetime.UTC).isoformat(timespec="milliseconds")
        return {"id": self.id, "name": self.name, "models": self.models, "status": self.status,
                "created_at": created.replace("+00:00", "Z"), "error": self.error, "progress": self.progress,
                "placement": self.placement if self.status == "running" else None}

    @classmethod
    def read(cls, folder: Path, loop: asyncio.AbstractEventLoop | None) -> JobRecord:
        """The record in ``folder``; ValueError (or OSError) if it is not one. A record of
        the first layout (the spec, data included, inside job.json) is split into job.json
        and spec.json (the spec unchanged, so a resume finds its store's job key)."""
        raw = json.loads((folder / "job.json").read_text())
        if not isinstance(raw, dict):
            raise ValueError("job.json is not an object")
        if "spec" in raw:
            spec = raw.pop("spec")
            raw["name"] = spec.get("name", "job")
            raw["models"] = [m["name"] for m in spec["models"]]
            _write_json(folder / "spec.json", spec)
        if raw.get("id") != folder.name or not JOB_ID.fullmatch(folder.name):
            raise ValueError(f"id {raw.get('id')!r} is not its folder's name")
        if raw.get("status") not in STATUSES:
            raise ValueError(f"unknown status {raw.get('status')!r}")
        name, models = raw.get("name"), raw.get("models")
        if not isinstance(name, str) or not isinstance(models, list) or not all(isinstance(m, str) for m in models):
            raise ValueError("name or model names missing")
        error = raw.get("error")
        job = cls(folder.name, folder, clean_text(name), [clean_text(m) for m in models], raw["status"],
                  float(raw["created_at"]), clean_text(error) if isinstance(error, str) else None,
                  int(raw.get("crashes", 0)))
        if not (folder / "spec.json").is_file():
            raise ValueError("no spec.json")
        job.events = EventLog(folder / "events.jsonl", loop)
        job.progress = job.events.last_population
        if job.progress is not None and isinstance(job.progress.get("model_probabilities"), list):
            # an event of an earlier version: the probabilities in the job's model order
            probabilities = dict(zip(job.models, job.progress["model_probabilities"], strict=True))
            job.progress = {**job.progress, "model_probabilities": probabilities}
        job.save_or_log()  # the current layout
        return job

    def save_or_log(self) -> None:
        """save(), or a line in the log when the disk takes nothing (the record in memory is
        right; the terminal event has what a restart needs)."""
        try:
            self.save()
        except OSError as err:
            log.error("job %s: cannot write its job.json (status %s): %s", self.id, self.status, err)


def _stored(job: JobRecord) -> int:
    """The populations in the job's store (0 without one)."""
    try:
        return Store.open(job.store_path).n_populations
    except (StoreError, OSError):
        return 0


class QueueFull(Exception):
    """Too many jobs wait already (HTTP 429 with Retry-After)."""


class JobManager:
    """The queue and the running jobs of one service process."""

    def __init__(self, store_dir: Path, client: Client, max_running: int | None,
                 loop: asyncio.AbstractEventLoop | None,
                 max_resumes: int = 1, limits: Limits | None = None, max_queued: int | None = None,
                 scheduler_address: str | None = None, turn_s: float | None = None, disk_reserve_mb: float = 0.0):
        self.store_dir = Path(store_dir)
        self.store_dir.mkdir(parents=True, exist_ok=True)
        self.client = client
        self.scheduler_address = scheduler_address  # None: an embedded cluster, which cannot go away alone
        self.client_lock = threading.Lock()
        self.max_running = max_running
        self.max_resumes = max_resumes
        self.turn_s = turn_s  # None: no turns (a job keeps its worker to its end)
        self.disk_reserve = int(disk_reserve_mb * 2**20)  # bytes the jobs leave free on the store's disk
        self.no_space: dict[str, int] = {}  # job id -> its requeues for a full disk
        self.waiting_for_space: str | None = None  # the job at the queue's head that waits for room (logged once)
        self.limits = limits or Limits()
        self.max_queued = max_queued
        self.loop = loop
        self.jobs: dict[str, JobRecord] = {}
        self.queue: deque[str] = deque()
        self.running: set[str] = set()
        self.held: dict[str, str] = {}  # job id -> the worker whose job slot its loop was given
        self.spread_asked: set[str] = set()  # the tasks of running jobs asked to spread (no job waits)
        self.prepared_on: str | None = None  # the id of the scheduler prepared for job tasks (_free_slots)
        self.busy: deque[tuple[float, float]] = deque()  # (monotonic, simulation s) per population: utilization()
        self.busy_lock = threading.Lock()
        self.admitting = 0  # submissions that hold a place in the queue while they are built and written
        self.lock = threading.Lock()
        self.result_lock = threading.Lock()  # one summary computed at a time (each reads a whole store)
        self.wake = threading.Condition(self.lock)
        self.stopping = False
        self.closing = asyncio.Event()  # set on the loop when the service stops: every event stream ends
        self._load()
        self.dispatcher = threading.Thread(target=self._dispatch, name="abcns-dispatcher", daemon=True)
        self.dispatcher.start()

    # ------------------------------------------------------------------ state
    def _load(self) -> None:
        """Every job in the store directory; unfinished ones go back in the queue."""
        found = []
        for folder in self.store_dir.iterdir():
            if not (folder.is_dir() and (folder / "job.json").is_file()):
                continue
            try:
                found.append(JobRecord.read(folder, self.loop))
            except (OSError, ValueError, KeyError, TypeError) as err:
                log.warning("skipping the job folder %s: %s", folder, err)
        for job in sorted(found, key=lambda j: j.created_at):
            self.jobs[job.id] = job
            if job.status not in TERMINAL and job.events is not None and job.events.ended():
                # the service died (or the disk was full) between a job's terminal event and its
                # status (``_end``): both come back from the event
                # an ended log's last event is a terminal one (a str)
                job.status, job.error = job.events.last_event, job.events.last_error  # type: ignore[assignment]
                job.save_or_log()
                continue
            if job.status == "running":  # the service died while it ran
                job.crashes += 1
                if job.crashes > self.max_resumes:
                    self._end(job, "failed", f"the service stopped {job.crashes} times while this job ran (it may be "
                                             f"what stops it); not resumed again (ABCNS_MAX_RESUMES={self.max_resumes})")
                    continue
            if job.status not in TERMINAL:
                job.status = "queued"
                job.save_or_log()
                self.queue.append(job.id)

    def submit(self, spec: JobSpec, arrays: dict[str, np.ndarray]) -> JobRecord:
        """Queue a job: its arrays (``input``, ``observed``), cut to the samples the job
        reads, go compressed to data.npz beside the spec, which refers to them; everything
        is validated before it is queued (SpecError naming the field; an OSError when the
        disk takes nothing; either way nothing is left behind). The job's place in the queue
        is taken first, under the lock (QueueFull when there is none). ``arrays`` is emptied
        once they are stored: build() reads them back, and a long record is not held twice."""
        with self.lock:
            waiting = len(self.queue) + self.admitting
            if self.max_queued is not None and waiting >= self.max_queued:
                raise QueueFull(f"{waiting} jobs are waiting (the limit is {self.max_queued}); try again later")
            self.admitting += 1
        job_id = uuid.uuid4().hex
        folder = self.store_dir / job_id
        try:
            self.check_space(space_needed(spec, sum(int(a.nbytes) for a in arrays.values()), self.limits.max_particles),
                             "this job")
            folder.mkdir()
            stored = dict(cut_to_read(spec, arrays))  # a new dict: cut_to_read may return arrays itself
            arrays.clear()
            # mypy checks **stored against savez_compressed's keyword allow_pickle (bool) too;
            # numpy takes the arrays as its **kwds
            np.savez_compressed(folder / DATA_FILE, **stored)  # type: ignore[arg-type]
            keys = list(stored)
            del stored
            data = spec.data.model_copy(update={k: f"{DATA_FILE}:{k}" for k in keys})
            spec = spec.model_copy(update={"data": data})
            built = build(spec, folder, allow_import=False)  # raises SpecError naming the field
            spec = admit(spec, built, self.limits)  # the service's limits (SpecError) and default budget
            _write_json(folder / "spec.json", spec_text(spec))
            job = JobRecord(job_id, folder, spec.name, [m.name for m in spec.models], "queued", time.time())
            job.events = EventLog(folder / "events.jsonl", self.loop)
            job.save()
            job.events.append("queued", {"id": job_id, "name": job.name, "models": job.models,
                                         "distance": spec.distance.name})  # the live page's tolerance unit
        except BaseException:
            with self.lock:
                self.admitting -= 1
            shutil.rmtree(folder, ignore_errors=True)
            raise
        with self.lock:
            self.admitting -= 1
            self.jobs[job_id] = job
            self.queue.append(job_id)
            self.wake.notify_all()
        return job

    def check_space(self, need: int, what: str) -> None:
        """NoSpace, naming the numbers, when the store's disk has less than ``need`` bytes
        free besides the reserve (``ABCNS_DISK_RESERVE_MB``)."""
        free = shutil.disk_usage(self.store_dir).free
        if free < need + self.disk_reserve:
            raise NoSpace(f"the disk of the job store has {free / 2**20:.1f} MB free; {what} needs about "
                          f"{need / 2**20:.1f} MB (its data and its first {FIRST_POPULATIONS} populations: particles x "
                          f"(parameters + 4) x 8 bytes each) and the service keeps {self.disk_reserve / 2**20:.0f} MB "
                          "free (ABCNS_DISK_RESERVE_MB); try again once there is room")

    def _has_space(self, job: JobRecord) -> bool:
        """Whether the disk has room for the job's next populations (logged once when not:
        the job waits at the queue's head, and starts once there is room)."""
        try:
            self.check_space(space_needed(JobSpec.model_validate(job.spec())), f"job {job.id}")
        except NoSpace as err:
            if self.waiting_for_space != job.id:
                self.waiting_for_space = job.id
                log.warning("job %s waits: %s", job.id, err)
            return False
        except (OSError, ValueError):  # its spec unreadable: its run says so
            pass
        self.waiting_for_space = None
        return True

    def get(self, job_id: str) -> JobRecord | None:
        return self.jobs.get(job_id)

    def list(self, status: str | None = None) -> list[JobRecord]:
        jobs = sorted(list(self.jobs.values()), key=lambda j: j.created_at)
        return [j for j in jobs if status is None or j.status == status]

    def running_on(self) -> dict[str, str]:
        """Each running job's worker (where its loop was placed; a job rescheduled after its
        worker died reports the new one once it starts there)."""
        return {job_id: (self.jobs[job_id].placement or {}).get("worker") or worker
                for job_id, worker in list(self.held.items()) if job_id in self.jobs}

    def utilization(self, workers: int, window_s: float = UTILIZATION_WINDOW_S) -> float | None:
        """The cluster's share of time on the jobs' simulations over the last ``window_s``:
        the simulation seconds of the populations that came in that window (each job loop's
        own measure: its tasks' compute time, or its in-process engine's calls), over
        ``workers x window_s``; None without workers."""
        if workers <= 0:
            return None
        since = time.monotonic() - window_s
        busy = sum(b for t, b in list(self.busy) if t >= since)
        return min(1.0, busy / (workers * window_s))

    def _forget_busy(self) -> None:
        """Drop the populations older than the window (appended in time order)."""
        with self.busy_lock:
            since = time.monotonic() - UTILIZATION_WINDOW_S
            while self.busy and self.busy[0][0] < since:
                self.busy.popleft()

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for j in list(self.jobs.values()):
            out[j.status] = out.get(j.status, 0) + 1
        return out

    def cancel(self, job_id: str) -> JobRecord:
        """A queued job never starts (it is taken out of the queue under the lock, so the
        dispatcher cannot have it); one the dispatcher has taken, or that runs, stops within
        a moment, even in the middle of a batch; what it did stays in the store."""
        job = self.jobs[job_id]
        with self.lock:
            queued = job_id in self.queue
            if queued:
                self.queue.remove(job_id)
            job.cancel.set()
        if queued:
            self._end(job, "cancelled", None)
        return job

    def purge(self, job_id: str) -> bool:
        """Delete an ended job and its folder; False if it has not ended."""
        with self.lock:
            job = self.jobs.get(job_id)
            if job is None or job.status not in TERMINAL:
                return False
            del self.jobs[job_id]
        shutil.rmtree(job.folder, ignore_errors=True)
        return True

    def result(self, job: JobRecord) -> dict | None:
        """The job's summary (None before its store exists): an ended job's is read from
        result.json, written when it ended (or here, once, for a job that ended before this
        version); a running job's is computed from its store. Summaries are computed one at
        a time: each reads the whole store."""
        cached = job.folder / RESULT_FILE
        if job.status in TERMINAL and (out := _read_json(cached)) is not None:
            return out
        with self.result_lock:
            if job.status in TERMINAL and (out := _read_json(cached)) is not None:
                return out  # computed by the request before this one
            ended = job.status in TERMINAL
            try:
                out = summary(Store.open(job.store_path))
            except StoreError:
                return None
            if ended:
                self._cache(job, out)
            return out

    def _cache(self, job: JobRecord, result: dict) -> None:
        try:
            _write_json(job.folder / RESULT_FILE, result)
        except OSError as err:  # a full disk: computed again next time
            log.warning("job %s: cannot write its %s: %s", job.id, RESULT_FILE, err)

    # ------------------------------------------------------------------ running
    def _dispatch(self) -> None:
        """Start queued jobs, in order, while there is room: a job slot on a worker that no
        running job holds (one job loop per worker process, :mod:`service.run.jobs`), and
        fewer running jobs than ``max_running`` when it is set. Without a client (tests of
        the manager alone) a job runs in this process, ``max_running`` (or one) at a time."""
        while True:
            # outside the lock: replacing a client that gave up may take seconds, and submit()
            # must not wait for it; so does asking the scheduler for its workers
            connected = self.stopping or self._connected()
            look = self.queue or self.prepared_on is None  # the first look prepares the cluster
            free = self._free_slots() if connected and look and not self.stopping else []
            if connected and not self.queue and not self.stopping:
                self._spread_idle()
            with self.lock:
                if self.stopping:
                    return
                cap = self.max_running or (math.inf if self.client is not None else 1)
                if ((self.client is not None and not free) or not self.queue or len(self.running) >= cap
                        or not self._has_space(self.jobs[self.queue[0]])):
                    if self.queue and connected:
                        self._end_a_turn()
                    self.wake.wait(timeout=1.0)  # a new job, a free slot, or the scheduler back: look again
                    continue
                job = self.jobs[self.queue.popleft()]
                self.running.add(job.id)
                worker = free[0] if self.client is not None else None
                if worker is not None:
                    self.held[job.id] = worker
            threading.Thread(target=self._run, args=(job, worker), name=f"abcns-job-{job.id[:8]}",
                             daemon=True).start()

    def _end_a_turn(self) -> None:
        """Jobs wait and no slot is free: ask the job that has run longest since it last
        started, if that is ``turn_s`` or more, to give its worker back after its current
        population (:meth:`_on_worker`); it goes to the back of the queue and resumes from
        its store, bit-identical. One such request at a time. Called under the lock."""
        if self.turn_s is None or self.client is None:
            return
        running = [self.jobs[i] for i in self.running if i in self.held]
        if any(job.turn.is_set() for job in running):
            return
        now = time.monotonic()
        due = [job for job in running if job.running_since and now - job.running_since >= self.turn_s]
        if due:
            min(due, key=lambda job: job.running_since).turn.set()

    def _spread_idle(self) -> None:
        """No job waits: the running jobs placed whole by the queue rule spread, one per free
        job slot, the latest started first (:func:`service.run.jobs.spread_next`), each asked
        once (:func:`service.run.jobs.ask_to_spread`). The scheduler is asked for the free
        slots only while such a job runs, and only once every running job has said where it
        runs: right after a job starts the scheduler may still show its slot free, and a job
        asked on that count (its ask lost, as it had no worker yet) kept the count from the
        job that needed it, which then never spread (1 run in 7 of its test)."""
        with self.lock:
            running = sorted((self.jobs[i] for i in self.running if i in self.jobs and self.jobs[i].task),
                             key=lambda j: j.running_since)
        if self.client is None or not any((j.placement or {}).get("reason") == "queue"
                                          and j.task not in self.spread_asked for j in running):
            return
        if any(j.placement is None for j in running):
            return  # a job just started holds a slot the scheduler may still show free: look again once it is placed
        tasks = {j.task: j for j in running}
        for key in spread_next([(j.task, j.placement) for j in running], self.spread_asked, len(self._free_slots())):
            worker = (tasks[key].placement or {}).get("worker") or self.held.get(tasks[key].id, "")
            if worker and ask_to_spread(self.client, key, worker):
                self.spread_asked.add(key)  # asked once; a job not reached is asked at the next look

    def _free_slots(self) -> Sequence[str]:
        """The workers with a job slot that no running job holds (none without a client, or
        when the scheduler does not answer). The cluster is prepared for job tasks
        (:func:`service.run.jobs.prepare_cluster`: the job slots' plugin, the task's modules
        imported on the scheduler) at the dispatcher's first look, before any job comes, and
        again at the first look at another scheduler (restarted) or at workers without slots."""
        if self.client is None:
            return []
        try:
            info = scheduler_identity(self.client)
            slots = job_workers(self.client, info)
            if scheduler_id(info) != self.prepared_on or (not slots and info.get("workers")):
                # a scheduler new to this manager (the first look, a restart), or one whose
                # workers lost their job slots: ready for job tasks before one is sent
                self.prepared_on = prepare_cluster(self.client)
                slots = job_workers(self.client)
        except Exception as err:  # the scheduler went away meanwhile: look again later
            log.warning("cannot list the workers: %r", err)
            return []
        with self.lock:
            held = set(self.held.values())
        return [addr for addr in slots if addr not in held]

    def _announce(self, job: JobRecord, progress: dict) -> None:
        """Append a population event unless that population was announced already (a job
        loop's message that comes after the store was read back, or twice); the populations
        before it that were stored but never announced first, from the store (a loop whose
        worker died between storing a population and sending its message resumes elsewhere
        and announces the next: in CI's chaos run a job's log began at population 2)."""
        with job.announcing:
            seen = job.progress["population"] if job.progress is not None else 0
            if progress["population"] <= seen:
                return
            for event in self._stored_events(job, seen + 1, progress["population"] - 1):
                job.log.append("population", event)
            job.progress = progress
            job.log.append("population", progress)

    def _backfill(self, job: JobRecord) -> None:
        """Population events for populations in the store but not in the log (the service
        died between a store append and its event; a job loop's last messages did not come)."""
        with job.announcing:
            seen = job.progress["population"] if job.progress is not None else 0
            for event in self._stored_events(job, seen + 1, None):
                job.progress = event
                job.log.append("population", event)

    @staticmethod
    def _stored_events(job: JobRecord, first: int, last: int | None) -> tuple[dict, ...]:
        """The population events of the job's stored populations ``first``..``last`` (None:
        its last), as their messages would have said; none where the store cannot be read."""
        try:
            store = Store.open(job.store_path)
        except StoreError:
            return ()
        last = store.n_populations if last is None else min(last, store.n_populations)
        if last < first:
            return ()
        totals = store.totals()
        return tuple(Progress(pop, totals[t - 1], pop.elapsed_s, None).event(job.models)
                     for t in range(first, last + 1) for pop in [store.population(t)])

    def _connected(self) -> bool:
        """Is the client connected to a scheduler? A client that gave up reconnecting is
        replaced by a new one to the same address (a restarted scheduler)."""
        with self.client_lock:  # the dispatcher and job threads ask: one replacement at a time
            status = getattr(self.client, "status", "running")
            if status in ("closed", "closing", "failed") and self.scheduler_address and not self.stopping:
                try:
                    self.client = Client(self.scheduler_address, timeout=5)
                    self.prepared_on = None  # prepared at the dispatcher's next look, jobs or not
                    log.warning("reconnected to the scheduler at %s with a new client", self.scheduler_address)
                except (OSError, TimeoutError, AssertionError) as err:  # AssertionError: a scheduler still starting
                    log.warning("the scheduler at %s does not answer yet: %r", self.scheduler_address, err)
                    return False
                status = self.client.status
            return status == "running"

    def _scheduler_id(self) -> str | None:
        try:
            return self.client.scheduler_info(n_workers=0).get("id")
        except Exception:
            return None

    def _lost_scheduler(self, started_on: str | None) -> bool:
        """After a failure: did the scheduler the job ran on go away (killed, restarted)? Then
        its futures are gone, and the job's failure is not the job's."""
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not self._connected():
            time.sleep(0.2)  # the client reconnects by itself when the scheduler is back soon
        return started_on is not None and self._scheduler_id() != started_on

    def _run(self, job: JobRecord, worker: str | None = None) -> None:
        """Run (or resume) the job: its loop on ``worker`` (:meth:`_on_worker`), or in this
        process without a client (:meth:`_here`); then end it by what the run said."""
        if job.cancel.is_set():  # cancelled as the dispatcher took it: it never starts
            try:
                self._end(job, "cancelled", None)
            finally:
                self._free(job)
            return
        resumed = job.store_path.exists()
        started_on = self._scheduler_id()
        job.status = "running"
        job.save_or_log()
        job.log.append("started", {"resumed": resumed})
        try:
            if resumed:
                self._backfill(job)
            spec = JobSpec.model_validate(job.spec())
            status, error, made = self._here(job, spec) if worker is None else self._on_worker(job, spec, worker)
            self._release_slot(job)  # its loop has ended: the next job may start while this one's end is written
            if status in ("yielded", "lost") and not (job.cancel.is_set() or self.stopping):
                job.status = "queued"  # resumed from its store: behind the jobs that waited, or first
                job.save_or_log()
                job.log.append("requeued", {"reason": "its worker was lost" if status == "lost" else
                                            f"its turn ended ({self.turn_s:g} s): a waiting job takes its worker"})
                with self.lock:
                    (self.queue.appendleft if status == "lost" else self.queue.append)(job.id)
            elif status in ("yielded", "lost"):
                status = "cancelled"
            if status == "no_space":
                self._full(job, error or "no space left on the disk")
                return
            if status == "cancelled" and job.cancel.is_set():
                self._end(job, "cancelled", None)
            elif status == "cancelled" and self.stopping:
                job.status = "queued"  # the service is stopping: the job resumes when it starts again
                job.save_or_log()
            elif status == "cancelled":  # nobody cancelled it: a job never ends "cancelled" unless it was
                self._end(job, "failed", "the run ended with the stop reason 'cancelled', but nobody cancelled the "
                                         "job (its store records no stop reason of its own); submit it again")
            elif status not in ("yielded", "lost"):
                self._end(job, status, error, made)
        except (SpecError, StoreError) as err:
            self._end(job, "failed", str(err))
        except Exception as err:
            if no_space(err):
                self._full(job, f"{type(err).__name__}: {err}")
            elif not self.stopping and self._lost_scheduler(started_on):
                # the scheduler died under the job: back to the front of the queue, resumed from
                # its last complete population once a scheduler answers again
                job.status = "queued"
                job.save_or_log()
                job.log.append("requeued", {"reason": f"lost the scheduler ({type(err).__name__}: {err})"})
                with self.lock:
                    self.queue.appendleft(job.id)
            else:
                self._end(job, "failed", f"{type(err).__name__}: {err}")
        finally:
            self._free(job)

    def _full(self, job: JobRecord, error: str) -> None:
        """A write of the job found the disk full: its stored populations are kept, and it
        goes back to the queue, resumed from them once the disk has room for its next
        populations (the dispatcher waits for it: :meth:`_has_space`); at the
        :data:`MAX_NO_SPACE`-th time (a disk that says it has room and takes nothing) it
        fails. A job the service stops meanwhile stays queued (a restart with room resumes it)."""
        self._release_slot(job)
        n = self.no_space[job.id] = self.no_space.get(job.id, 0) + 1
        stored = _stored(job)
        if n >= MAX_NO_SPACE and not self.stopping:
            self._end(job, "failed", f"the disk was full {n} times ({error}); its {stored} stored populations are kept")
            return
        job.status = "queued"
        job.save_or_log()
        try:
            job.log.append("requeued", {"reason": f"the disk is full ({error}): it resumes from its {stored} stored "
                                                  "populations once the disk has room"})
        except OSError as err:
            log.error("job %s: cannot append its requeued event: %s", job.id, err)
        if not (self.stopping or job.cancel.is_set()):
            with self.lock:
                self.queue.append(job.id)
        elif job.cancel.is_set():
            self._end(job, "cancelled", None)

    def _release_slot(self, job: JobRecord) -> None:
        with self.lock:
            if self.held.pop(job.id, None) is not None:
                self.wake.notify_all()

    def _free(self, job: JobRecord) -> None:
        job.placement = None
        job.turn.clear()
        self.spread_asked.discard(job.task or "")
        job.task = None
        with self.lock:
            self.running.discard(job.id)
            self.held.pop(job.id, None)
            self.wake.notify_all()

    def _here(self, job: JobRecord, spec: JobSpec) -> tuple[str, str | None, dict | None]:
        """The job's loop in this process (a manager without a client: serial)."""

        def on_population(p: Progress) -> None:
            self._announce(job, p.event(job.models))

        result = run_job(spec, job.folder, job.store_path, self.client, on_population=on_population,
                         cancel=lambda: job.cancel.is_set() or self.stopping, owned_store=True)
        return ("cancelled" if result.stop_reason is StopReason.CANCELLED else "finished"), None, None

    def _on_worker(self, job: JobRecord, spec: JobSpec, worker: str) -> tuple[str, str | None, dict | None]:
        """The job's loop as one Dask task (:func:`service.run.jobs.run_one`) on ``worker``'s
        job slot: never in the service's interpreter (its GIL is the HTTP loop's). Pinned
        loosely: if that worker dies, the scheduler runs the task on another, which resumes
        the store. Its messages come through the scheduler's event log (a topic per job):
        where it runs, then one per population. A cancel, or the service stopping, releases
        the task (the run stops at its next batch, :func:`run_one`'s cancel) and waits for
        its store's lock: the populations it made are stored when this returns."""
        client = self.client
        topic = f"abcns-job-{job.id}"
        data = JobRun.of(spec, job.folder, job.store_path, job.name).data  # sent inline: a worker reads no file of ours

        placed = [False]

        def place(placement: dict | None) -> None:
            with job.announcing:
                job.placement, placed[0] = placement, True
                job.log.append("placed", {"placement": placement})
            where = (placement or {}).get("worker")
            with self.lock:  # rerun elsewhere after its worker died: that worker's slot is the one it holds
                if where and job.id in self.held:
                    self.held[job.id] = where

        released = threading.Event()

        def on_message(event: tuple) -> None:  # on the client's event loop
            msg = event[1]
            try:
                if msg.get("kind") == "start":
                    place(msg.get("placement"))
                elif msg.get("kind") == "population":
                    if msg.get("busy_s") is not None:
                        self.busy.append((time.monotonic(), float(msg["busy_s"])))
                        self._forget_busy()
                    self._announce(job, msg["event"])
                    if job.turn.is_set():  # its turn ends here: the next population has hardly begun
                        released.set()
            except Exception as err:  # a message of another version, a full disk: logged, the store has it
                log.warning("job %s: a message of its loop was not recorded: %r", job.id, err)

        client.subscribe_topic(topic, on_message)
        threads, slots = cluster_slots(client)
        with self.lock:  # the queue rule's figures: the jobs running (this one too) and waiting, the loops at once
            jobs, loops = len(self.running) + len(self.queue), min(len(slots), self.max_running or len(slots))
        job.task = f"abcns-job-{job.id}-{uuid.uuid4().hex[:8]}"
        future = client.submit(run_one, spec, data, str(job.store_path), local_s=local_population_s(), threads=threads,
                               jobs=jobs, slots=loops, topic=topic, owned_store=True, key=job.task,
                               workers=[worker], allow_other_workers=True, resources={JOB_RESOURCE: 1}, pure=False)
        job.running_since = time.monotonic()
        lost, done = WorkerWatch(client, worker), threading.Event()
        future.add_done_callback(lambda _: done.set())
        try:
            while True:
                # (not future.result(timeout=...): distributed's sync() loses its result when the
                # timeout and the result meet, and raises UnboundLocalError)
                if done.wait(0.2):
                    out = future.result()
                    break
                gone = lost.gone((job.placement or {}).get("worker") or worker)
                if job.cancel.is_set() or self.stopping or released.is_set() or gone:
                    future.release()  # the run stops at its next batch; what it made is stored
                    wait_for_store_lock(job.store_path)
                    return ("cancelled" if job.cancel.is_set() or self.stopping
                            else "lost" if gone else "yielded"), None, None
        finally:
            client.unsubscribe_topic(topic)
        if not placed[0] and out.get("placement"):  # its messages did not come before its end (the same stream)
            place(out["placement"])
        self._backfill(job)  # populations whose messages did not come (the store is the record)
        status, error, made = out["status"], out.get("error"), out.get("summary")  # the summary: made on the worker
        if status in ("finished", "cancelled", "no_space"):
            return status, error if status == "no_space" else None, made
        return "failed", (error or status).split("\nTraceback")[0], made

    def _end(self, job: JobRecord, status: str, error: str | None, made: dict | None = None) -> None:
        """The job's summary (``made`` by its loop's worker, else computed here once; kept in
        result.json), its terminal event, then
        its status: whoever sees the job ended finds the event in its log (a poller that
        reads the status, then the events, misses nothing). A write that fails (a full disk)
        is logged: the status holds in memory, and a restart recovers status and error
        from the terminal event when job.json missed them."""
        result = made
        if result is None:
            with self.result_lock:
                try:
                    result = summary(Store.open(job.store_path))
                except StoreError:
                    result = None
        if result is not None:
            self._cache(job, result)
        if status == "finished" and result and result.get("no_population"):  # a budget spent before population 1
            status, error = "failed", result["notes"][0]
        data: dict[str, Any] = {"status": status}
        if error:
            data["error"] = error
        if result:
            probs = result.get("model_probabilities") or {}
            data.update(stop_reason=result.get("stop_reason"), n_populations=result.get("n_populations"),
                        n_simulations=result.get("n_simulations"),
                        model_probabilities={m: probs.get(m) for m in job.models})
            if result.get("notes"):
                data["notes"] = result["notes"]  # why it stopped, in words (nothing_accepted)
        try:
            job.log.append(status, data)
        except OSError as err:
            log.error("job %s: cannot append its %s event: %s", job.id, status, err)
        job.status, job.error = status, error
        job.save_or_log()

    def begin_shutdown(self) -> None:
        """Stop taking jobs, stop the running ones between batches, end every event stream.
        Thread-safe (the stream side is scheduled on the loop)."""
        with self.lock:
            self.stopping = True
            self.wake.notify_all()
        if self.loop is not None and not self.loop.is_closed():
            self.loop.call_soon_threadsafe(self._close_streams)

    def _close_streams(self) -> None:
        """On the loop: every event stream ends (its follower wakes and sees ``closing``)."""
        self.closing.set()
        for job in list(self.jobs.values()):
            if job.events is not None and job.events.loop is not None:
                job.events._notify()

    def shutdown(self, timeout_s: float) -> None:
        """Stop; running jobs stop between batches and stay queued for the next start. A job
        still running after ``timeout_s`` is recorded as queued all the same (it resumes
        from its last complete population; the service did not die under it)."""
        self.begin_shutdown()
        deadline = time.monotonic() + timeout_s
        while self.running and time.monotonic() < deadline:
            time.sleep(0.05)
        for job_id in list(self.running):
            job = self.jobs[job_id]
            if job.status == "running":
                job.status = "queued"
                job.save_or_log()
