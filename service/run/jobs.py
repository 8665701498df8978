"""Many jobs on one Dask cluster: each job's population loop runs on a worker, never in the
caller's interpreter, and no two job loops ever share a worker process (nor its GIL).

One population of a job is made from the previous one's particles, so a job's populations
are synchronous, and a cheap job gains nothing from being spread over workers (§4.1's
Duffing: ~10 ms of simulations a population; Dask's round trips cost more). What keeps the
cluster busy is running many jobs at once, each where it runs fastest (docs/design.md, "The
contracts": workers never wait, across jobs).

**A job is one Dask task.** :func:`run_one`, a plain top-level function of picklable
arguments (the validated spec, a pydantic model pickled as data, not parsed again; the
records of its data files read by the caller and sent inline, so a worker needs none of the
caller's files; the store's path; the seed and the caller's settings), calls
:func:`service.run.runner.run_job` on the worker. The worker writes the job's zarr store, so
the stores' folder must be one the workers can write (the embedded cluster, one machine, or
a shared file system). Progress (a start event with the
placement, then one event per population) comes back through Dask's event log
(``Worker.log_event``, ``Client.subscribe_topic``, a topic per call of :func:`run_jobs`);
the task returns the job's outcome and JSON summary. Where a job runs never changes its
result: a batch's result does not depend on where it runs (the determinism contract), and
the in-process engine and the Dask executor give the same bits.

**Placement by cost and by the queue, decided on the worker before the run.** The task times the job's
own evaluator on one batch of the first population's kind of proposals (``batch_size``
draws from the priors, with a generator of its own, so the job's random stream is
untouched): a warm-up call (it loads the compiled kernels, as the run's first batch would),
then at most three timed calls (fewer once 20 ms are measured), the fastest of them giving
``c``, the seconds a simulation costs. A population's simulations are estimated at ``c x
particles`` (a population simulates about as many proposals as it has particles: §4.1's
run ~0.5-2 N per population, the first ~5 N, a rare one ~7 N). Today's rule of the runner
(:meth:`service.run.dask_executor.Stream.here`, ``ABCNS_LOCAL_POPULATION_S``: 25 ms) says
what a population must cost for the cluster to shorten it by more than Dask's round trips
cost: ``local_s x min(2, W / (W - 1))`` over ``W`` worker threads. At or below it the job
runs **whole** on its worker (``reason`` cheap): ``run_job(..., client=None)`` inside the
task, the in-process engine, no task per batch, the worker's thread held for the whole job.
Above it the job **spreads** (``reason`` dear): the task secedes
(``distributed.secede``: the worker's thread goes back to the cluster, and the task never
rejoins: rejoining waits for a free thread, which a batch the job dropped at its cancel or
time budget may hold for as long as a batch runs, and the job would be reported ended only
then) and hands the worker's client to ``run_job``, so the Dask executor fans the
job's batches out over every worker with a free thread (and its own per-population rule
still keeps a population that turns out cheap in the job's process), unless **the queue
rule** (:func:`queue_full`) says every worker thread runs a job anyway: the jobs running or
waiting (this one too, as the caller counted them when it handed the job out: ``jobs``)
and the job slots (``job_slots``) are each at least ``W``. Then a dear job runs whole too
(``reason`` queue): spread, it would only take its turn on threads that other jobs' loops
keep busy, and pay Dask's round trips and each population's surplus tasks for nothing
(docs/benchmarks.md, "Many jobs at once": 8 sleepy jobs on 2 workers). Workers of several
threads have fewer slots than threads (one loop per process): there a queue never fills
the threads, and dear jobs spread as before. With one worker thread in the cluster a job
always runs whole (spreading would send its batches back to its own process); with
``local_s`` 0 ("always on the cluster", as for one job) it always spreads. **The tail**: a
job placed whole by the queue rule spreads once no job waits and a job slot is free (the
caller asks it, :func:`ask_to_spread`, one job per free slot, the latest started first:
:func:`spread_next`): its whole run stops at its next batch, as at a turn's end (the rows
of the population being filled are dropped), and resumes from its store spread, in the same
task and worker slot, bit-identical (the resume contract). The decision is recorded in the
store (the run information's ``placement``, also in the summary: ``mode``, ``reason``,
``worker``, ``simulation_s``, ``population_s``, ``limit_s``, ``worker_threads``, ``jobs``,
``job_slots``, ``pilot``: the warm calls, or the first call alone when that already put a
population under the limit; after the tail's move ``reason`` idle and ``whole_populations``)
and sent with the job's start event (a second one at the move). Near the limit either
placement costs about the same (that is what the limit means), so the estimate's error
there matters little; a job whole because it is cheap stays whole.

**One job loop per worker process: a worker resource.** Each job task asks for the
resource ``abcns-job`` (:data:`JOB_RESOURCE`), of which every worker has one. Dask keeps a
task's resources while it is seceded: the worker releases them only when the task ends, in
any state (``WorkerState._execute_done_common``), and the scheduler only when the task
leaves processing; so a spread job's seceded task still holds its worker's slot while its
batches use the freed thread, and a second job task can never start in that process. (A
thread count would not do: a seceded task frees its thread, and the scheduler would start
the next job beside it.) The workers get the resource from a worker plugin
(:class:`JobSlot`, registered before the first job by :func:`prepare_cluster`, idempotent;
it reaches workers that join later, a nanny's replacement included) that declares
``abcns-job=1`` on a worker that does not declare it already, so the embedded cluster and a
stock ``dask worker`` need nothing (``dask worker --resources abcns-job=1`` is the same).
The scheduler places a task
with a resource on any worker that has it, busy or not; a worker then queues it behind the
job it runs, while another worker may be free (a seceded job even makes its worker look
idle). So :func:`run_jobs` hands a job to the scheduler only when a worker's slot is free,
pinned there (``workers=[address]``, loosely: if that worker dies the scheduler runs the task
on another, where ``run_job`` resumes the store), and keeps the rest in order on the
client: a slot that frees takes the next job.

A job that fails (its simulator raises, its store holds another job) fails alone: the task
returns its outcome and message, and the other jobs go on. Releasing a job's task (the
caller stops, Ctrl-C) cancels the run at its next batch (the task looks at its own state on
the worker, no round trip); its store keeps the complete populations, and running it again
resumes.
"""

from __future__ import annotations

import errno
import importlib
import logging
import math
import queue
import re
import time
import traceback
import uuid
from collections import deque
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from distributed import Client, Future, get_client, get_worker, secede
from distributed.diagnostics.plugin import WorkerPlugin

from abcns import Result, SpecError, StopReason
from abcns.executor import Batch, BatchError
from service.run.runner import Progress, local_population_s, run_job, summary, with_records
from service.run.store import Store, StoreError
from service.spec import Job, JobSpec, build, load_array

#: the worker resource a job task holds while it runs (one per worker process)
JOB_RESOURCE = "abcns-job"
#: the name of :class:`JobSlot` among the cluster's plugins
PLUGIN_NAME = "abcns-job-slot"
#: the pilot: timed calls of the evaluator at most, and the measured time after which it stops
PILOT_CALLS = 3
PILOT_S = 0.02
#: seconds between two looks at the cluster's workers while jobs wait for a slot
LOOK_S = 1.0
log = logging.getLogger("abcns.jobs")


class JobSlot(WorkerPlugin):
    """Declares one :data:`JOB_RESOURCE` on every worker that does not declare it already
    (``dask worker --resources abcns-job=N`` keeps its N)."""

    idempotent = True  # registered again (another run on the same cluster): nothing changes

    async def setup(self, worker) -> None:
        if JOB_RESOURCE not in worker.state.total_resources:
            await worker.set_resources(**{JOB_RESOURCE: 1})


def prepare_cluster(client: Client) -> str:
    """Make the cluster ready for job tasks before the first one comes; return the
    scheduler's id (what it was prepared for: a restarted scheduler has another).

    The job slots' plugin (:class:`JobSlot`) is registered, idempotent: each worker, and each
    that joins later, imports this module as it unpickles the plugin. And this module is
    imported on the scheduler: the scheduler unpickles every task it is sent, and a job
    task's function and spec import this module, the spec's and abcns's there (~0.6-2 s on a
    fresh `dask scheduler`, on its event loop: meanwhile it schedules nothing and answers
    no one; the service's workers sat idle that long before their first jobs). A scheduler
    that refuses ``run_on_scheduler`` pays it at the first job instead (logged)."""
    client.register_plugin(JobSlot(), name=PLUGIN_NAME)
    try:
        client.run_on_scheduler(importlib.import_module, __name__)
    except Exception as err:  # not needed for the jobs to run: only what their first one waits
        log.warning("could not import %s on the scheduler ahead of the first job: %r", __name__, err)
    return scheduler_id(client.scheduler_info(n_workers=0))


def scheduler_id(info: Mapping[str, Any]) -> str:
    """The scheduler's id in its ``scheduler_info`` ("" when it gives none)."""
    return str(info.get("id") or "")


def scheduler_identity(client: Client) -> dict[str, Any]:
    """The scheduler's identity with every worker, asked now. ``Client.scheduler_info`` fetches
    it and then returns the client's cache, which the client's periodic update may overwrite
    meanwhile with a copy that lists no worker (distributed 2026.8): `/health` then said 0
    workers now and then (1 run in 5 of tests/test_submit.py)."""
    scheduler = client.scheduler
    if scheduler is None:  # a client never connected, or closed
        raise RuntimeError("the Dask client is not connected")
    return client.sync(scheduler.identity, n_workers=-1)


def job_workers(client: Client, info: Mapping[str, Any] | None = None) -> dict[str, int]:
    """The workers that have a job slot, and their threads (from ``info``, the scheduler's
    :func:`scheduler_identity`, when given)."""
    workers = (info if info is not None else scheduler_identity(client))["workers"]
    return {addr: int(w.get("nthreads", 1)) for addr, w in workers.items()
            if (w.get("resources") or {}).get(JOB_RESOURCE, 0) >= 1}


# ---------------------------------------------------------------------------- the jobs


@dataclass
class JobRun:
    """One job of a call of :func:`run_jobs`: its spec, the records of its data files (read
    here, sent inline), its store and a label (the progress lines', unique in the call)."""

    spec: JobSpec
    store: Path
    label: str
    data: dict[str, np.ndarray] = field(default_factory=dict)

    @classmethod
    def of(cls, spec: JobSpec, base_dir: Path | None, store: Path, label: str) -> JobRun:
        """The job of ``spec`` whose data files are relative to ``base_dir`` (read now)."""
        data = {key: load_array(source, base_dir, f"data.{key}") for key in ("input", "observed")
                if isinstance(source := getattr(spec.data, key), str)}
        return cls(spec, Path(store).absolute(), label, data)


def store_names(names: Sequence[str]) -> list[str]:
    """A distinct store name for each spec name, in order: the name made safe for a file
    name (characters other than letters, digits, ``.``, ``_`` and ``-`` become ``-``); the
    first spec of a name keeps it, the next ones get ``-2``, ``-3``, ... (the first free),
    so adding a spec at the end of a command line never renames the stores of the others."""
    taken: set[str] = set()
    out = []
    for name in names:
        stem = re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-.") or "job"
        candidate, k = stem, 1
        while candidate.lower() in taken:
            k += 1
            candidate = f"{stem}-{k}"
        taken.add(candidate.lower())
        out.append(candidate)
    return out


@dataclass
class Outcome:
    """How a job ended: ``status`` (``finished``, ``cancelled``, ``failed``: the job's own
    failure, a simulator's exception; ``refused``: its spec, data or store; ``no_space``: a
    write found the disk full, its stored populations stand; ``error``: a bug),
    its message, the placement and the store's JSON summary (None when it has no store)."""

    status: str
    error: str | None = None
    placement: dict | None = None
    summary: dict | None = None


# ---------------------------------------------------------------------------- on a worker


def pilot_batch(job: Job, size: int, rng: np.random.Generator) -> Batch:
    """``size`` proposals as the first population makes them: a model with equal
    probability, a point uniform in its prior box (epsilon infinite: every row in full)."""
    models = rng.integers(len(job.models), size=size)
    theta = np.full((size, max(m.n_dim for m in job.models)), np.nan)
    for m, model in enumerate(job.models):
        rows = np.flatnonzero(models == m)
        theta[rows, :model.n_dim] = model.sample_prior(rows.size, rng)
    return Batch(0, 0, models, theta, math.inf, np.random.SeedSequence(0), np.zeros(size, dtype=np.int64))


def simulation_seconds(job: Job, limit_s: float) -> tuple[float, float, bool]:
    """(seconds a simulation costs, seconds the pilot took, whether warm calls measured it):
    the job's evaluator timed on one batch of prior proposals, after a warm-up call; when
    the warm-up call alone (an upper bound: it loads the kernels) already puts a population
    (``c x particles``) at or below ``limit_s``, that call's time."""
    settings = job.settings
    size = max(1, min(int(settings.batch_size), int(settings.particles)))
    batch = pilot_batch(job, size, np.random.default_rng(job.seed))
    start = time.perf_counter()
    job.evaluate(batch)  # the warm-up: loads the kernels (the run's first batch would)
    first = time.perf_counter() - start
    if first / size * settings.particles <= limit_s:
        return first / size, first, False
    best, spent = math.inf, 0.0
    for _ in range(PILOT_CALLS):
        t0 = time.perf_counter()
        job.evaluate(batch)
        took = time.perf_counter() - t0
        best, spent = min(best, took), spent + took
        if spent >= PILOT_S:
            break
    return best / size, first + spent, True


def limit_seconds(local_s: float, threads: int) -> float:
    """What a population's simulations may cost for its job to run whole: ``local_s x
    min(2, W / (W - 1))`` (the Dask executor's rule, :meth:`Stream.here`); unbounded on one
    worker thread; 0 when ``local_s`` is 0 (every population on the cluster)."""
    if local_s <= 0:
        return 0.0
    if threads < 2:
        return math.inf
    return local_s * min(2.0, threads / (threads - 1))


def queue_full(jobs: int | None, slots: int | None, threads: int) -> bool:
    """Whether every worker thread runs a job's loop anyway (the queue rule): the jobs
    running or waiting, and the job slots (the loops that may run at once: one per worker
    process, at most the service's ``--max-running``), are each at least the cluster's
    worker threads. Workers of several threads have fewer slots than threads: their queue
    never fills the cluster, and a dear job spreads there. Unknown figures (None): not full."""
    return jobs is not None and slots is not None and min(jobs, slots) >= threads


def cluster_slots(client: Client) -> tuple[int, dict[str, int]]:
    """The cluster's worker threads, and its workers with a job slot and their threads
    (:func:`job_workers`), from one scheduler call."""
    info = scheduler_identity(client)
    return sum(int(w.get("nthreads", 1)) for w in info["workers"].values()), job_workers(client, info)


def place(job: Job, local_s: float, threads: int, worker: str, jobs: int | None = None,
          slots: int | None = None) -> dict:
    """The job's placement (``mode`` whole or spread), why (``reason``) and what it was
    decided from: its cost (the pilot) against the limit, and the queue (``jobs`` running or
    waiting with this one, ``job_slots``) against the worker threads (:func:`queue_full`)."""
    limit = limit_seconds(local_s, threads)
    out: dict[str, Any] = {"worker": worker, "worker_threads": threads, "local_s": local_s,
                           "limit_s": None if math.isinf(limit) else limit, "particles": int(job.settings.particles),
                           "jobs": jobs, "job_slots": slots}
    if limit == 0 or math.isinf(limit):  # nothing to measure
        out.update(mode="spread" if limit == 0 else "whole", reason="on the cluster" if limit == 0 else "one thread",
                   simulation_s=None, population_s=None, pilot_s=0.0)
        return out
    try:
        c, spent, warm = simulation_seconds(job, limit)
    except Exception as err:  # the run says what is wrong, with its batch
        out.update(mode="whole", reason="pilot failed", simulation_s=None, population_s=None, pilot_s=None,
                   note=f"the pilot failed ({type(err).__name__}); the run reports it")
        return out
    cost = c * job.settings.particles
    mode, reason = (("whole", "cheap") if cost <= limit else ("whole", "queue") if queue_full(jobs, slots, threads)
                    else ("spread", "dear"))
    out.update(mode=mode, reason=reason, simulation_s=c, population_s=cost, pilot_s=spent,
               pilot="warm calls" if warm else "first call (at most)")
    return out


# ---------------------------------------------------------------------------- the tail


#: on a worker: the keys of the job tasks asked to spread (:func:`ask_to_spread`)
ASKED: set[str] = set()


def _asked(key: str) -> None:
    """On a worker (``Client.run``, its event loop): the job task ``key`` is to spread."""
    ASKED.add(key)


def ask_to_spread(client: Client, key: str, worker: str) -> bool:
    """Tell the job task ``key`` on ``worker``, placed whole by the queue rule, that no job
    waits and a job slot is free: it spreads from its next batch (:func:`run_one`). False
    (logged) when the worker did not answer; the job then stays whole."""
    try:
        client.run(_asked, key, workers=[worker])
        return True
    except Exception as err:  # the worker left meanwhile: its job is placed again anyway
        log.warning("could not ask job task %s on %s to spread: %r", key, worker, err)
        return False


def spread_next(running: Sequence[tuple[Any, Mapping[str, Any] | None]], asked: Collection[Any], free: int) -> list:
    """Which running jobs to ask to spread now that no job waits (``running``: each job's
    id and placement, oldest start first; ``asked``: those asked before; ``free``: the job
    slots no loop holds): the jobs placed whole by the queue rule, the latest started
    first (the most work left, like their peers), one per free slot beyond the jobs asked
    already that still run. Each so spreads over its own thread and at least one idle one;
    asking every whole job at once would share the idle threads among many, each paying
    the cluster's round trips for a small share."""
    room = free - sum(1 for job, _ in running if job in asked)
    movable = [job for job, p in running if (p or {}).get("reason") == "queue" and job not in asked]
    return movable[::-1][:max(0, room)]


def _released(worker, key) -> bool:
    """Whether the caller released this task (it is cancelled on the worker, or gone)."""
    ts = worker.state.tasks.get(key)
    return ts is None or ts.state in ("cancelled", "released", "forgotten")


def run_one(spec: JobSpec, data: dict[str, np.ndarray], store: str, *, seed: int | None = None,
            allow_import: bool = False, local_s: float, threads: int, topic: str | None = None,
            index: int = 0, owned_store: bool = False, jobs: int | None = None, slots: int | None = None) -> dict:
    """The Dask task of one job: decide its placement (:func:`place`; ``jobs``, ``slots``:
    the queue as the caller saw it when it handed the job out), run (or resume) it with
    :func:`run_job` whole here or spread from here (:func:`_run_placed`), and return its
    outcome as a dict (:class:`Outcome`'s fields). Holds the worker's :data:`JOB_RESOURCE`
    (the caller asks for it). Never raises for the job's own failure: the other jobs go on.
    ``owned_store``: the store is the service's (:func:`run_job`'s lock and clean-up)."""
    worker = get_worker()
    key = worker.get_current_task()

    def emit(kind: str, **msg: Any) -> None:
        if topic is not None:
            worker.log_event(topic, {"job": index, "kind": kind, **msg})

    placement: dict | None = None
    path = Path(store)
    try:
        if seed is not None:
            spec = spec.model_copy(update={"seed": seed})
        if _finished(path):  # run_job gives its result at once (or refuses another job's store)
            run_job(spec, None, path, None, data=data, allow_import=allow_import)
            return _outcome(path, None, "finished")
        job = build(with_records(spec, data), None, allow_import)  # the job as run_job builds it
        placement = place(job, local_s, threads, worker.address, jobs, slots)
        emit("start", placement=placement)

        names = [m.name for m in job.models]

        def progress(p: Progress) -> None:
            emit("population", event=p.event(names), busy_s=p.busy_s)

        run = partial(run_job, spec, None, path, data=data, on_population=progress, allow_import=allow_import,
                      local_s=local_s, owned_store=owned_store)
        placement, result = _run_placed(run, placement, lambda: _released(worker, key), str(key), emit, path)
        status = Store.open(path).attrs.get("status")
        return _outcome(path, placement, "finished" if status == "finished" else "cancelled",
                        None if status == "finished" else "the job was cancelled", result)
    except BatchError as err:  # a bug in a simulator: which batch, which exception
        return _outcome(path, placement, "failed", f"the job failed in {err}")
    except SpecError as err:
        return _outcome(path, placement, "refused", str(err))
    except Exception as err:  # a bug; the other jobs go on, the caller says so
        if no_space(err):  # a full disk: the stored populations stand, the caller may resume them
            return _outcome(path, placement, "no_space", f"{type(err).__name__}: {err}")
        return _outcome(path, placement, "error", f"{type(err).__name__}: {err}\n{traceback.format_exc()}")
    finally:
        ASKED.discard(str(key))


def _run_placed(run: Callable[..., Result], placement: dict, released: Callable[[], bool], key: str,
                emit: Callable[..., None], path: Path) -> tuple[dict, Result]:
    """Run the job where it is placed: whole here (``run(None)``, the in-process engine), or
    spread from here (the task secedes, never to rejoin: the worker's thread goes to the
    batches, and the loop ends with its task without waiting for a thread, which a batch it
    dropped may hold). A job placed whole by the queue rule spreads once the caller
    asks (:func:`ask_to_spread`: no job waits, a slot is free): its whole run stops at its
    next batch (the rows of the population being filled are dropped, as at a turn's end)
    and resumes from its store spread, bit-identical (the resume contract); the new
    placement (``reason`` idle, ``whole_populations``: those it made whole) is sent as a
    second start event and recorded. Returns the final placement and the result."""
    movable = placement["mode"] == "whole" and placement.get("reason") == "queue"

    def asked() -> bool:
        return movable and key in ASKED

    if placement["mode"] == "whole" and not asked():
        result = run(None, cancel=lambda: released() or asked(), placement=placement)
        if released() or not asked() or result.stop_reason is not StopReason.CANCELLED:
            return placement, result
    if placement["mode"] == "whole":  # asked to spread, before its run or during it
        placement = {**placement, "mode": "spread", "reason": "idle", "whole_populations": _populations(path)}
        emit("start", placement=placement)
    client = get_client()
    secede()
    return placement, run(client, cancel=released, placement=placement)


def _populations(path: Path) -> int:
    """The populations in the store at ``path`` (0 without one)."""
    try:
        return Store.open(path).n_populations
    except (StoreError, OSError, KeyError, ValueError):
        return 0


def no_space(err: BaseException | None) -> bool:
    """Whether ``err`` (or what caused it) is a full disk (ENOSPC, EDQUOT)."""
    seen = 0
    while err is not None and seen < 10:
        if isinstance(err, OSError) and err.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        err, seen = err.__cause__ or err.__context__, seen + 1
    return False


def _finished(path: Path) -> bool:
    try:
        attrs = Store.open(path).attrs
    except (StoreError, OSError, KeyError, ValueError):
        return False
    return attrs.get("status") == "finished" and bool(attrs.get("stop_reason"))


def _outcome(path: Path, placement: dict | None, status: str, error: str | None = None,
             result: Result | None = None) -> dict:
    """The task's outcome; its summary from ``result`` (the run's own) when given."""
    try:
        s = summary(Store.open(path), result)
    except Exception:  # no store (refused before it was made), or unreadable
        s = None
    return {"status": status, "error": error, "placement": placement if placement is not None
            else (s or {}).get("placement"), "summary": s}


# ---------------------------------------------------------------------------- the caller


class WorkerWatch:
    """Whether the worker a job's loop runs on has left the cluster for good: Dask reruns a
    lost worker's task on another worker with a free job slot, but a worker's job slot is
    declared after it joins (``JobSlot``), and the scheduler does not look again at a task
    that found no worker when slots appear later: with every worker lost at once, the task
    would wait forever. So a loop whose worker has been gone ``LOST_S`` without a new
    placement is released and the job requeued (placed on a free slot when there is one:
    :func:`run_jobs`, and the service's ``JobManager``)."""

    LOOK_S = 1.0
    LOST_S = 5.0

    def __init__(self, client: Client, worker: str):
        self.client, self.next_look, self.worker = client, 0.0, worker
        self.missing_since: float | None = None

    def gone(self, worker: str) -> bool:
        now = time.monotonic()
        if now < self.next_look:
            return False
        self.next_look = now + self.LOOK_S
        try:
            alive = worker in self.client.nthreads()
        except Exception:  # the scheduler is away: not this watch's concern
            return False
        if alive or worker != self.worker:  # there, or placed anew (the new worker's clock starts)
            self.worker, self.missing_since = worker, None if alive else now
            return False
        if self.missing_since is None:
            self.missing_since = now
        return now - self.missing_since >= self.LOST_S


def run_jobs(client: Client, jobs: Sequence[JobRun], *, seed: int | None = None, allow_import: bool = False,
             local_s: float | None = None, on_event: Callable[[int, dict], None] | None = None,
             poll_s: float = 0.2) -> list[Outcome]:
    """Run ``jobs`` on the cluster of ``client``, each as one task (:func:`run_one`) on a
    worker with a free job slot, in the order given as slots free (each told the queue as it
    is then: the queue rule of :func:`place`); once none waits, the jobs placed whole by that
    rule are asked to spread as slots free (:func:`spread_next`). Return their outcomes in
    that order. ``on_event(index, event)`` is called on this thread for each job's events:
    ``{"kind": "start", "placement": {...}}``, then ``{"kind": "population", "event": {...},
    "busy_s": ...}`` (the population event, :meth:`service.run.runner.Progress.event`). ``local_s``:
    :func:`service.run.runner.local_population_s` (None: this process's). Interrupted
    (KeyboardInterrupt), the jobs' tasks are released: each run stops at its next batch."""
    local_s = local_population_s() if local_s is None else local_s
    prepare_cluster(client)
    nonce = uuid.uuid4().hex[:8]
    topic = f"abcns-jobs-{nonce}"
    events: queue.SimpleQueue = queue.SimpleQueue()
    client.subscribe_topic(topic, lambda event: events.put(event[1]))  # on the client's loop: only queued
    waiting = deque(range(len(jobs)))
    running: dict[int, tuple[Future, str]] = {}
    watches: dict[int, WorkerWatch] = {}
    where: dict[int, str] = {}  # the worker of each running job's latest start event
    placed: dict[int, dict | None] = {}  # each job's latest placement (its start events)
    asked: set[int] = set()  # the jobs asked to spread (the tail)
    outcomes: list[Outcome | None] = [None] * len(jobs)
    next_look, n_slots = 0.0, 0

    def deliver(wait_s: float = 0.0) -> None:
        """Hand every queued event to ``on_event``, waiting ``wait_s`` at most for the first."""
        while True:
            try:
                msg = events.get(timeout=wait_s) if wait_s > 0 else events.get_nowait()
            except queue.Empty:
                return
            wait_s = 0.0
            if isinstance(msg, dict) and msg.get("kind") == "start" and "job" in msg:
                placed[int(msg["job"])] = msg.get("placement")
                where[int(msg["job"])] = str((msg.get("placement") or {}).get("worker") or "")
            if on_event is not None and isinstance(msg, dict) and "job" in msg:
                on_event(int(msg["job"]), {k: v for k, v in msg.items() if k != "job"})

    try:
        while waiting or running:
            if waiting and time.monotonic() >= next_look:
                next_look = time.monotonic() + LOOK_S
                threads, slots = cluster_slots(client)
                n_slots = len(slots)
                held = {addr for _, addr in running.values()}
                for addr in (a for a in slots if a not in held):
                    if not waiting:
                        break
                    i = waiting.popleft()
                    running[i] = (_submit(client, jobs[i], addr, events, key=f"abcns-job-{nonce}-{i}", topic=topic,
                                          index=i, seed=seed, allow_import=allow_import, local_s=local_s,
                                          threads=threads, jobs=len(running) + len(waiting) + 1, slots=n_slots), addr)
                    watches[i], where[i] = WorkerWatch(client, addr), addr
            deliver(poll_s)
            for i, (future, addr) in list(running.items()):
                if future.done():
                    deliver()  # its last population's event came before its end
                    outcomes[i] = _collect(future)
                    future.release()
                    del running[i]
                    next_look = 0.0  # a slot is free
                elif watches[i].gone(where.get(i) or addr):  # its worker left, and Dask did not place it again
                    future.release()
                    del running[i]
                    waiting.appendleft(i)  # resumed from its store on the next free slot
                    asked.discard(i)  # placed again there
                    next_look = 0.0
                    if on_event is not None:
                        on_event(i, {"kind": "requeued", "reason": "its worker was lost"})
            if not waiting and running:  # the tail: idle slots go to jobs placed whole by the queue rule
                _spread_idle(client, running, where, placed, asked, n_slots - len(running))
        deliver(min(poll_s, 0.05))  # an event still on its way after the last task's end
    finally:
        for future, _ in running.values():
            future.release()  # each run stops at its next batch (run_one's cancel)
        client.unsubscribe_topic(topic)
    return [o if o is not None else Outcome("error", "no outcome") for o in outcomes]


def _submit(client: Client, job: JobRun, addr: str, events: queue.SimpleQueue, *, key: str, **kwargs: Any) -> Future:
    """The job's task ``key`` (:func:`run_one`, with ``kwargs``) on ``addr``'s job slot,
    pinned loosely; its end puts None on ``events`` (wakes :func:`run_jobs`: a slot is free)."""
    future = client.submit(run_one, job.spec, job.data, str(job.store), key=key, workers=[addr],
                           allow_other_workers=True, resources={JOB_RESOURCE: 1}, pure=False, **kwargs)
    future.add_done_callback(lambda _: events.put(None))
    return future


def _spread_idle(client: Client, running: Mapping[int, tuple[Future, str]], where: Mapping[int, str],
                 placed: Mapping[int, dict | None], asked: set[int], free: int) -> None:
    """No job waits: ask the running jobs that :func:`spread_next` names to spread (once
    each; in handing-out order, the start order)."""
    for i in spread_next([(i, placed.get(i)) for i in sorted(running)], asked, free):
        asked.add(i)
        future, addr = running[i]
        ask_to_spread(client, str(future.key), where.get(i) or addr)


def _collect(future: Future) -> Outcome:
    """The outcome of a finished job task; a task that erred (its worker died again and
    again: ``KilledWorker``) is a failed job."""
    if future.status == "finished":
        out = future.result()
        return Outcome(out["status"], out["error"], out["placement"], out["summary"])
    try:
        err = future.exception()
    except Exception as e:  # cancelled
        err = e
    return Outcome("failed", f"{type(err).__name__}: {err}")


def placement_text(placement: Mapping[str, Any] | None) -> str:
    """The placement in words, for a progress or summary line."""
    if not placement:
        return "placement unknown"
    mode, worker, limit, cost, c = (placement.get(k) for k in ("mode", "worker", "limit_s", "population_s",
                                                               "simulation_s"))
    where = f"whole on {worker}" if mode == "whole" else f"spread over the cluster from {worker}"
    if cost is None or c is None or limit is None:
        why = ("one worker thread in the cluster" if limit is None
               else "ABCNS_LOCAL_POPULATION_S is 0: every population on the cluster" if limit == 0
               else placement.get("note", "not measured"))
    else:
        sign = "<=" if cost <= limit else ">"
        most = "at most " if placement.get("pilot", "").startswith("first") else "~"
        why = (f"a population {most}{cost * 1e3:.3g} ms of simulations ({c * 1e6:.3g} us each x "
               f"{placement['particles']} particles) {sign} {limit * 1e3:.3g} ms")
    return f"{where}: {why}{_queue_text(placement)}"


def _queue_text(placement: Mapping[str, Any]) -> str:
    """What the queue rule added to the placement, in words ("" when it had no say)."""
    reason, jobs, threads = (placement.get(k) for k in ("reason", "jobs", "worker_threads"))
    if reason == "queue":
        return f", but {jobs} jobs for {threads} worker threads: every thread has a job"
    if reason == "idle":
        return f"; after {placement.get('whole_populations')} populations whole: no job waits, a slot is free"
    if reason == "dear" and jobs is not None:
        return f", and {jobs} jobs for {threads} worker threads"
    return ""
