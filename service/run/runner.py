"""The runner: one job, every population into its zarr store. The one run loop of the CLI,
the HTTP jobs, the analysis and the examples.

``run_job`` validates the spec, opens or creates the job's store, and drives the abcns
population iterator with an executor: a :class:`DaskExecutor` over a client (the job's
data go to the cluster once, as a task, so they survive lost workers), or with no client
the serial executor in this process. Each complete population is appended to the store
(data first, counter last). Run on a store of an unfinished job it resumes from the last
complete population: the random stream is keyed by (seed, population, batch), so the end
result equals an uninterrupted run's, and the serial executor's equals the Dask one's.
"""

from __future__ import annotations

import fcntl
import gc
import hashlib
import json
import math
import os
import queue
import shutil
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from distributed import Client

from abcns import NSSettings, Population, Result, RunEnd, SpecError, StopReason
from abcns.executor import SerialExecutor
from abcns.filling import Budget
from abcns.run import algorithm_name, consume, iterate
from service.run.dask_executor import LOCAL_POPULATION_S, DaskExecutor
from service.run.model_error import model_error_warning, residual_check
from service.run.store import Store, StoreIncomplete, data_hash, result_from_store
from service.spec import Job, JobSpec, build, job_arrays


@dataclass
class Progress:
    """What a progress display needs after each population."""

    population: Population
    n_simulations_total: int
    elapsed_s: float
    simulations_per_s: float | None  # None for a population read back from the store
    # on a Dask cluster: its worker threads now, and the share of their time since the
    # previous population spent on the simulations the run used (the workers' compute time
    # of the tasks consumed over workers x wall time); None in the runner's process, and for
    # a population cheap enough to be evaluated there (DaskExecutor's ``local_s``)
    workers: int | None = None
    efficiency: float | None = None
    # the seconds of simulation the run used since the previous population, wherever they
    # ran (the workers' compute time of the tasks consumed, or the in-process engine's calls)
    busy_s: float | None = None

    def event(self, models: Sequence[str]) -> dict[str, Any]:
        """The population event, in plain JSON types (``service.http.schemas.ProgressOut``):
        what a job loop's message carries, HTTP publishes and the CLI's progress line shows.
        The model probabilities by model name; the noise floor and the decision tolerance as
        estimated after the population (None while the run knows none)."""
        pop, floor = self.population, self.population.floor
        return {
            "population": int(pop.t), "epsilon": float(pop.epsilon), "epsilon_next": float(pop.epsilon_next),
            "acceptance_rate": float(pop.acceptance_rate), "simulations": int(self.n_simulations_total),
            "model_probabilities": {name: float(p) for name, p in zip(models, pop.model_probabilities, strict=True)},
            "elapsed_s": float(self.elapsed_s),
            "simulations_per_s": None if self.simulations_per_s is None else float(self.simulations_per_s),
            "noise_floor": None if floor is None else float(floor.floor),
            "decision_tolerance": None if floor is None else float(floor.decision),
            "workers": self.workers, "efficiency": self.efficiency,
        }


class TimedEvaluate:
    """An evaluator that adds the seconds its calls take to ``busy_s``: the simulation time
    of the in-process engine (:attr:`Progress.busy_s`)."""

    def __init__(self, evaluate: Callable) -> None:
        self.evaluate, self.busy_s = evaluate, 0.0

    def __call__(self, batch):
        start = time.perf_counter()
        try:
            return self.evaluate(batch)
        finally:
            self.busy_s += time.perf_counter() - start


def job_key(spec: JobSpec, seed: int, dhash: str) -> str:
    text = json.dumps({"spec": spec.model_dump(mode="json"), "seed": seed, "data": dhash}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def stored_job_key(store: Store) -> str | None:
    """The job key of a store's own spec, seed and data as this version dumps the spec (a
    store that an earlier version, with another dump of the same spec, made for this job
    resumes); None when the store does not record them or its spec no longer validates."""
    a = store.attrs
    try:
        return job_key(JobSpec.model_validate(a["spec"]), int(a["seed"]), str(a["data_hash"]))
    except (KeyError, TypeError, ValueError):  # pydantic's ValidationError is a ValueError
        return None


#: the stop reasons of a budget: a run they stop before its first population has no result
BUDGETS = {"max_seconds": "its time budget (stop.max_seconds, or the service's max_job_seconds) ran out",
           "max_simulations": "its simulation budget (stop.max_simulations) was spent"}


def no_population_note(reason: str | None, n_simulations: int | None) -> str | None:
    """The sentence of a run that a budget stopped before its first population (issue Z.5:
    such a job ended a plain ``finished``), or None."""
    if reason not in BUDGETS:
        return None
    return (f"no population: {BUDGETS[reason]} after {n_simulations or 0:,} simulations, before the first population "
            "was complete; there is no result (give the job a larger budget)")


def summary(store: Store, result: Result | None = None) -> dict:
    """The store's JSON summary. ``result``: the store's result when the caller holds it
    already (:func:`run_job` returns the one it read back at the run's end), not read again:
    that read is most of a summary's time (every population, its bounds' eigendecompositions;
    ~5 % of a §4.1 job's time on its worker). The attributes are read once (a file each time)."""
    attrs = store.attrs
    n_populations = int(attrs["n_populations"])
    # without a population, the run's notes and simulations still say why and after how much it stopped
    run = attrs.get("run", {})
    out = (result if result is not None else result_from_store(store)).summary() if n_populations else {
        "notes": run.get("notes", []), "n_simulations": run.get("n_simulations"), "wall_time_s": run.get("wall_time_s")}
    out["status"] = attrs.get("status", "unknown")
    out["stop_reason"] = attrs.get("stop_reason")
    if not n_populations and out["status"] == "finished" and (
            note := no_population_note(out["stop_reason"], out.get("n_simulations"))):
        out["notes"] = [note, *out.get("notes", [])]
        out["no_population"] = True
    if attrs.get("error"):
        out["error"] = attrs["error"]
    out["n_populations"] = n_populations
    if run.get("residuals"):  # the best fit's residuals against independent noise (service.run.model_error)
        out["residuals"] = run["residuals"]
        warning = model_error_warning(run["residuals"])
        if warning:
            out["warnings"] = [*out.get("warnings", []), warning]
    if run.get("placement"):  # where the job ran and why (service.run.jobs)
        out["placement"] = run["placement"]
    return out


WRITE_INTERVAL_ENV = "ABCNS_STORE_INTERVAL_S"
LOCAL_POPULATION_ENV = "ABCNS_LOCAL_POPULATION_S"


def write_interval() -> float:
    """The coalescing interval: ``ABCNS_STORE_INTERVAL_S`` (0: one append per population)."""
    return _seconds_env(WRITE_INTERVAL_ENV, 1.0)


def local_population_s() -> float:
    """``ABCNS_LOCAL_POPULATION_S``: a population whose simulations cost less than this many
    seconds in all runs in the runner's process, not on the cluster (0: never;
    :data:`service.run.dask_executor.LOCAL_POPULATION_S` by default)."""
    return _seconds_env(LOCAL_POPULATION_ENV, LOCAL_POPULATION_S)


def _seconds_env(name: str, default: float) -> float:
    """A number of seconds from the environment (unset or empty: ``default``), or a SpecError."""
    raw = os.environ.get(name) or str(default)
    try:
        value = float(raw)
    except ValueError:
        raise SpecError(name, f"must be a number of seconds, got {raw!r}") from None
    if not 0 <= value <= 3600:
        raise SpecError(name, f"must be between 0 and 3600 seconds, got {value}")
    return value


_RUNS = 0  # runs going on in this process (frozen_heap counts them; alone() asks)
_RUNS_LOCK = threading.Lock()


@contextmanager
def frozen_heap() -> Iterator[None]:
    """While runs go on in this process, the objects alive when each started (the modules, the
    Dask client and, for a LocalCluster, its scheduler) are left out of the cyclic garbage
    collector's full passes (``gc.freeze``); when the last run ends they are handed back
    (``gc.unfreeze``), so nothing is kept for good. A full pass over the ~200,000 objects of a
    runner's process stalls every thread of it (the scheduler and the client included, so the
    workers wait) for ~110-140 ms, once every second or two on a busy run: on 16 cores, 3-4
    such gaps between populations in a 2.5 s run at 2 ms and 14 workers. Frozen, a full
    pass takes ~7 ms. It changes no result (the collector only frees unreachable cycles)."""
    global _RUNS
    with _RUNS_LOCK:
        gc.freeze()  # also the objects of a run that starts while another goes on
        _RUNS += 1
    try:
        yield
    finally:
        with _RUNS_LOCK:
            _RUNS -= 1
            if _RUNS == 0:
                gc.unfreeze()


def alone() -> bool:
    """Whether at most one run goes on in this process now (the service runs several in one
    interpreter: a population evaluated here would take turns with the other runs' on one
    core, while the workers wait; :class:`DaskExecutor` evaluates none here then)."""
    return _RUNS <= 1


class PopulationWriter:
    """Appends populations to the store in order on a background thread while the next
    ones are computed; the progress callback runs once its population is in the store.
    Populations that come within ``interval_s`` (:func:`write_interval`) of the last append
    go in one append, so a job whose populations come fast pays about one append a
    second, not one per population.

    ``store`` is either the store or, for a new one, the call that makes it: then it is made
    on this thread first, while the run's first population goes to the cluster (making it
    was ~50 ms before a run's first task); :attr:`store` holds it once :meth:`close` has
    returned (None if making it failed: that error is the writer's)."""

    def __init__(self, store: Store | Callable[[], Store], job_key: str,
                 on_population: Callable[[Progress], None] | None, interval_s: float):
        self.store: Store | None = store if isinstance(store, Store) else None
        self._create = None if isinstance(store, Store) else store
        self.job_key, self.on_population = job_key, on_population
        self.interval_s = interval_s
        self.queue: queue.SimpleQueue = queue.SimpleQueue()
        self.error: BaseException | None = None
        self.last_append = -math.inf
        self.closing = threading.Event()
        self.thread = threading.Thread(target=self._run, name="abcns-store", daemon=True)
        self.thread.start()

    def put(self, progress: Progress, info: dict | None) -> None:
        if self.error is not None:
            raise self.error  # surface a failed write early
        self.queue.put((progress, info))

    def close(self, raise_error: bool = True) -> None:
        """Write what is queued now and stop the thread."""
        self.closing.set()
        self.queue.put(None)
        self.thread.join()
        if raise_error and self.error is not None:
            raise self.error

    def _run(self) -> None:
        if self._create is not None:
            try:
                self.store = self._create()
            except BaseException as err:  # handed to the runner's thread
                self.error = err
        done = False
        while not done:
            items = [self.queue.get()]
            # populations that come while the last append settles join this one: at most
            # about one append per interval_s on a fast job (an append of any number of
            # populations costs ~50-150 ms of CPU that the runner's own thread would miss)
            if items[0] is not None:  # (close() cuts the wait short)
                self.closing.wait(max(0.0, self.last_append + self.interval_s - time.monotonic()))
            while items[-1] is not None and self.interval_s > 0 and not self.queue.empty():
                items.append(self.queue.get())  # (interval 0: every population its own append)
            if items[-1] is None:
                done = True
                items.pop()
            if not items or self.error is not None:
                continue
            self.last_append = time.monotonic()
            assert self.store is not None  # made, or self.error is set
            try:
                self.store.append_many([(p.population, p.n_simulations_total) for p, _ in items])
                infos = [info for _, info in items if info is not None]
                if infos:
                    self.store.set_status("running", job_key=self.job_key, run=infos[-1])
                if self.on_population is not None:
                    for progress, _ in items:
                        self.on_population(progress)
            except BaseException as err:  # handed to the runner's thread
                self.error = err


def _existing_store(path: Path, key: str, owned: bool) -> Store | None:
    """The store of this job at ``path`` to resume, or None to create one. A store another
    job made is an error. So is one whose creation a killed process left unfinished (no
    ``format_version``, or no job key and no population), unless the caller ``owned`` the
    path (the service's job folder): then it is removed, since nothing in it was ever a
    population."""
    if not (path.exists() and any(path.iterdir())):
        return None
    try:
        store = Store.open(path)
    except StoreIncomplete:
        if not owned:
            raise
        shutil.rmtree(path)
        return None
    if owned and store.attrs.get("job_key") is None and store.n_populations == 0:
        shutil.rmtree(path)
        return None
    if store.attrs.get("job_key") != key and stored_job_key(store) != key:
        raise SpecError("--out", f"{path} holds another job (different spec, seed or data); choose another --out")
    return store


def _within_store(job: Job, store: Store | None) -> Job:
    """The job with at most as many ellipsoids per model as ``store`` holds room for: a store
    written before the default grew with the particles (8 for any number; now one per 64
    particles, ``abcns.settings.PARTICLES_PER_ELLIPSOID``) resumes under its own cap, where the
    new default would make bounds it cannot hold. A spec that sets ``max_ellipsoids`` is
    left as it is (its own number sized the store)."""
    settings = job.settings
    held = None if store is None else store.attrs.get("max_ellipsoids")
    if held is None or not isinstance(settings, NSSettings) or settings.max_ellipsoids is not None \
            or settings.n_ellipsoids <= int(held):
        return job
    return replace(job, settings=replace(settings, max_ellipsoids=int(held)))


def lock_path(store_path: Path) -> Path:
    """The file a run on a store of the service's holds locked (:func:`store_lock`)."""
    path = Path(store_path)
    return path.with_name(path.name + ".lock")


@contextmanager
def store_lock(store_path: Path) -> Iterator[None]:
    """Hold ``<store>.lock`` (an exclusive ``flock``, waited for) while a job's loop runs on
    a store of the service's: a run that a restarted service or a rescheduled task starts on
    the store while an earlier one still ends its last batch (its caller gone, it stops at
    its next check) waits for it, so a store never has two writers. The kernel drops the lock
    of a process that dies."""
    with lock_path(store_path).open("a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def wait_for_store_lock(store_path: Path, timeout_s: float = 30.0) -> None:
    """Wait (``timeout_s`` at most) until no run holds ``store_path``'s :func:`store_lock`."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with lock_path(store_path).open("a") as f:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                fcntl.flock(f, fcntl.LOCK_UN)
                return
        except BlockingIOError:
            time.sleep(0.05)
        except OSError:  # purged, or the disk
            return


def run_job(
    spec: JobSpec, base_dir: Path | None, store_path: Path, client: Client | None, *, seed: int | None = None,
    on_population: Callable[[Progress], None] | None = None, cancel: Callable[[], bool] | None = None,
    allow_import: bool = False, owned_store: bool = False, data: Mapping[str, np.ndarray] | None = None,
    local_s: float | None = None, placement: dict | None = None,
) -> Result:
    """Run (or resume) one job to its end; return its result. ``client``: a Dask client, or
    None to run in this process. ``allow_import`` lets the spec name local
    ``package.module:factory`` simulators (the CLI, the examples; never HTTP). ``owned_store``:
    the store path belongs to the caller (the service's job folder), so a store whose
    creation a killed process left unfinished is made again; elsewhere (``--out``) it is an
    error, never deleted; an owned store is run under :func:`store_lock`. ``data``,
    ``local_s``, ``placement``: a job run on a worker (:mod:`service.run.jobs`: the caller's
    records, 25 ms rule and placement; :func:`with_records`)."""
    if not owned_store:
        return _run_job(spec, base_dir, store_path, client, seed, on_population, cancel, allow_import, False, data,
                        local_s, placement)
    with store_lock(store_path):
        return _run_job(spec, base_dir, store_path, client, seed, on_population, cancel, allow_import, True, data,
                        local_s, placement)


def _run_job(
    spec: JobSpec, base_dir: Path | None, store_path: Path, client: Client | None, seed: int | None,
    on_population: Callable[[Progress], None] | None, cancel: Callable[[], bool] | None,
    allow_import: bool, owned_store: bool, data: Mapping[str, np.ndarray] | None,
    local_s: float | None, placement: dict | None,
) -> Result:
    """:func:`run_job`'s body."""
    if seed is not None:
        spec = spec.model_copy(update={"seed": seed})
    job: Job = build(with_records(spec, data), base_dir, allow_import)  # every check before anything runs
    interval_s, local_s = write_interval(), local_population_s() if local_s is None else local_s
    arrays = job_arrays(job)
    dhash = data_hash(*(a for a in arrays.values() if a is not None))
    key = job_key(spec, job.seed, dhash)
    store_path = Path(store_path)
    store = _existing_store(store_path, key, owned_store)
    job = _within_store(job, store)
    # a finished run records why it stopped with its status; a store "finished" with no stop
    # reason (a status change that a killed process cut, before it was one write) is resumed:
    # the run ends again where it did and says why (read as it is, its result would say
    # "cancelled", result_of's word for a run with no stop reason)
    if store is not None and store.attrs.get("status") == "finished" and store.attrs.get("stop_reason"):
        return result_from_store(store)
    history, n_simulations, elapsed_s, run_info = ([], 0, 0.0, {}) if store is None else _resumed(store, key)
    _place(store, key, run_info, placement)
    # a new store (running, with the job's key) is made on the writer's thread meanwhile
    writer = PopulationWriter(store if store is not None else partial(_new_store, store_path, spec.model_dump(mode="json"),
                                                                      job, dhash, key), key, on_population, interval_s)
    budget = Budget(job.stop, cancel=cancel, n_simulations=n_simulations, elapsed_before_s=elapsed_s)
    executor: SerialExecutor | DaskExecutor | None = None
    timed = TimedEvaluate(job.evaluate)

    def written(pop: Population) -> None:
        info = None
        if pop.t == 1:  # what a resume needs, as the algorithm found it (no pilot: a schedule)
            source, n_pilot = budget.epsilon_initial or ("schedule", 0)
            run_info["epsilon_initial_source"], run_info["n_pilot_simulations"] = source, n_pilot
            info = dict(run_info)
        now = time.monotonic()
        dt = now - start
        workers = efficiency = None
        busy_now = executor.busy_s if isinstance(executor, DaskExecutor) else timed.busy_s
        wall, busy = now - last[0], busy_now - last[1]
        if isinstance(executor, DaskExecutor):
            workers = executor.n_workers()
            if wall > 0 and workers and not executor.last_here:  # none for a population evaluated here
                efficiency = min(1.0, busy / (workers * wall))
        last[:] = [now, busy_now]
        progress = Progress(pop, budget.n_simulations, budget.elapsed(),
                            (budget.n_simulations - sims_start) / dt if dt > 0 else 0.0, workers, efficiency, busy)
        writer.put(progress, info)

    with frozen_heap():  # to the end: a full pass over the heap handed back stalled the last append ~140 ms
        try:
            executor = (SerialExecutor(timed) if client is None
                        else DaskExecutor(client, key, job.description, arrays, allow_import, budget=budget,
                                          evaluate=job.evaluate, local_s=local_s, alone=alone))
            gen = iterate(job.models, executor, job.settings, job.stop, job.seed, history=history, budget=budget,
                          noise=job.noise)
            start, sims_start = time.monotonic(), budget.n_simulations
            last = [start, 0.0]  # when the previous population ended, the workers' busy seconds then
            end = consume(gen, written)
            writer.close()
        except BaseException as err:
            writer.close(raise_error=False)  # what was computed is stored
            if writer.store is not None:  # (None: making it failed)
                writer.store.set_status("failed", None, job_key=key, error=f"{type(err).__name__}: {err}")
            raise
        finally:
            getattr(executor, "close", lambda: None)()  # the Dask executor releases the job's data
        assert writer.store is not None  # close() raised otherwise
        _record_end(writer.store, key, end, run_info, budget)
        # the store's result, with the mixture the run grew (its answer's reading: not again)
        result = replace(result_from_store(writer.store), mixture=end.mixture)
        _record_residuals(writer.store, job, result)
        return result


def _place(store: Store | None, key: str, run_info: dict, placement: dict | None) -> None:
    """Record where the job runs and why (:mod:`service.run.jobs`) with the run information
    (a resumed store: now); run in the caller's process, an earlier placement no longer holds."""
    if placement is None:
        run_info.pop("placement", None)
        return
    run_info["placement"] = placement
    if store is not None:
        store.set_status("running", job_key=key, run=run_info)


def with_records(spec: JobSpec, data: Mapping[str, np.ndarray] | None) -> JobSpec:
    """The spec to build the job from: ``spec`` with the records in ``data`` (the records the
    spec's files hold, as the caller read them: a worker elsewhere has not its files) inline;
    the store and job key keep the spec as given. A copy, not validated again."""
    if not data:
        return spec
    inline = {key: np.asarray(value, dtype=float).tolist() for key, value in data.items()}
    return spec.model_copy(update={"data": spec.data.model_copy(update=inline)})


def _resumed(store: Store, key: str) -> tuple[list[Population], int, float, dict]:
    """What a resumed run starts from (the store's populations, simulations so far, elapsed
    time and run information); the store is marked running with this job's key."""
    history, state = store.populations(), store.run_state()
    run_info = dict(store.attrs.get("run", {}))
    store.set_status("running", job_key=key)
    return history, int(state["n_simulations_total"]), float(state["elapsed_s"]), run_info


def _new_store(path: Path, spec_json: dict, job: Job, dhash: str, key: str) -> Store:
    """The job's new, empty store."""
    return Store.create(path, spec=spec_json, seed=job.seed, model_names=[m.name for m in job.models],
                        parameter_names=[list(m.parameter_names) for m in job.models],
                        n_particles=job.settings.particles, data_hash=dhash, algorithm=algorithm_name(job.settings),
                        max_ellipsoids=getattr(job.settings, "n_ellipsoids", 1), job_key=key)


def _record_residuals(store: Store, job: Job, result: Result) -> None:
    """The best fit's residuals against independent noise (:mod:`service.run.model_error`)
    in the run's information, once the run has ended (a second write: a run killed in between
    is finished without them)."""
    check = residual_check(job, result)
    if check is not None:
        store.set_status(store.attrs["status"], store.attrs.get("stop_reason"),
                         run={**store.attrs.get("run", {}), "residuals": check})


def _record_end(store: Store, key: str, end: RunEnd, run_info: dict, budget: Budget) -> None:
    """The run's end in the store, in one status write: cancelled or finished, why, where
    eps_1 came from (the algorithm's word), the simulations, the wall time and the notes."""
    if end.epsilon_initial_source != "resumed":  # the algorithm says where eps_1 came from
        run_info["epsilon_initial_source"] = end.epsilon_initial_source
        run_info["n_pilot_simulations"] = end.n_pilot_simulations
    notes = list(run_info.get("notes", [])) + list(end.notes)
    status = "cancelled" if end.reason is StopReason.CANCELLED else "finished"
    run_info.update(n_simulations=budget.n_simulations, wall_time_s=budget.elapsed(), notes=notes)
    store.set_status(status, end.reason.value, job_key=key, run=run_info)
