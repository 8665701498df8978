"""Scale-out: the runner (``service.run.runner.run_job``) on 1 to 32 Dask worker processes.

    python -m benchmarks.scale [--workers 1,2,4,8,16,32] [--stock-workers 1,8] [--populations 10]
                               [--batch-size B] [--d41-workers 1,2] [--d41-populations 6]
                               [--skip-local] [--skip-stock] [--skip-d41] [--quick]
                               [--sleep-ms MS] [--pyabc-workers 8,14] [--pyabc-generations 8] [--timeline]

Figures only (nothing is asserted about speed). Four parts (the fourth only when asked for):

1. **Latency-bound, LocalCluster.** The authors' demo (examples/authors_demo/spec.yaml), the
   cubic model only, its sampler settings (1000 particles) with the default batch size (25), run
   for ``--populations`` populations with the plugin simulator ``benchmarks.sleepy:factory``:
   the built-in Duffing, then 2 ms of sleep per simulation, the stand-in for an expensive
   model on many machines. Run on ``distributed.LocalCluster(n_workers=N,
   threads_per_worker=1, processes=True)``: N worker processes on this machine's cores
   (they mostly sleep). The ideal is N x 500 simulations/s.
2. **The same against a stock cluster**: ``dask scheduler`` and ``dask worker --nworkers N
   --nthreads 1`` started as subprocesses (their modules, ``python -m
   distributed.cli.dask_scheduler``, by this interpreter), reached with
   ``distributed.Client(address)``: the scheduler in a process of its own.
3. **Paper §4.1 with the real kernels** (examples/duffing_41/spec.yaml, ``--d41-populations``
   populations) on 1 and 2 LocalCluster workers, beside the kernel alone: the evaluator
   called in this process on one batch of prior draws (epsilon = inf: every simulation runs
   to the end), best of several calls; and, for reference, the evaluator's own time on the
   run's batches in a serial in-process run (early rejection at each population's epsilon).
4. **pyABC on the same machine and pattern** (``--pyabc-workers``, none by default; needs
   pyABC, the optional extra ``.[bench]``, and prints a line saying it is skipped when pyABC
   cannot be imported): ``pyabc.ABCSMC`` with ``MulticoreEvalParallelSampler(n_procs=W)``
   (W forked worker processes), population size 1000, ``--pyabc-generations`` generations
   (``max_nr_populations``; default 8) after pyABC's calibration sample, otherwise its
   defaults (MedianEpsilon, MultivariateNormalTransition), its history in a sqlite file in
   the run's temporary directory. The model (:func:`pyabc_model`): two parameters ``a``,
   ``b`` with independent uniform priors on [-5, 5]; one simulation sleeps
   ``benchmarks.sleepy.SECONDS`` (2 ms, or ``--sleep-ms``: the same cost as the sleepy
   plugin's per simulation) and returns ``y = (a, b) + N(0, 0.5^2 I)``; observed ``y =
   (1, -0.5)``; distance the squared Euclidean ``|y - y_obs|^2``. *simulations*: pyABC's own
   count, ``History.total_nr_simulations`` (the sum of its populations' ``nr_samples``, the
   calibration sample's 1000 included): every simulation its workers started, those still
   running when a population filled too, so it compares with the sleepy table's *executed*
   rather than its *simulations*. *wall*: ``ABCSMC.new`` (the sqlite file) and ``run``.
   *efficiency*: simulations per second over W / ``SECONDS``, as the sleepy table's. pyABC's
   workers reseed from the OS: runs are not reproducible, and the count varies a little.

Columns. *simulations*: what the algorithm used (the result's serial-equivalent count; the
same for every N, the run being deterministic). *executed*: rows the workers actually
simulated (the sleepy plugin counts them), with the surplus tasks the executor submitted
ahead and cancelled too late. *wall*: ``run_job`` from call to return (store creation, data to
the cluster, evaluator built on each worker; the workers are started and warmed before).
*runner CPU*: ``time.process_time()`` of this process around ``run_job``: the client, the
store writes and, for a LocalCluster, the scheduler (it runs in this process); for the stock
cluster the scheduler's process is measured separately (psutil). *workers CPU*: the worker
processes' CPU time (psutil, through ``client.run``; nannies not counted). *Dask floor*:
the same cluster running only the job's pattern of tasks that sleep (:func:`dask_floor`),
its efficiency and Dask's own CPU per task there (this process, with a stock scheduler's;
the workers). *No-barrier floor*: the same tasks submitted at once, no population between
them (``dask_floor(barrier=False)``): the ceiling of any design that runs the job's batches
as Dask tasks, look-ahead of any kind included.

``--timeline``: each sleepy row also taken apart from Dask's task stream (:func:`timeline`):
the time before population 1's first task (the store created, the job's data and first
tasks to the cluster), after the last population's last used task (the last append, the
status, the result read back), the gaps between populations (the step, the dispatch, any
stall of the runner's process) and the populations' spans against their simulations' time
on W workers (the tail and the surplus). The task stream costs the scheduler a little CPU.

``--quick``: 1 population, LocalCluster 1 and 2 workers, stock 1 worker, §4.1 1 and 2
workers with 1 population (a smoke run, under a minute).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import psutil
import yaml
from distributed import Client, as_completed, get_task_stream

from abcns import run
from abcns.filling import draws
from abcns.rejection import prior_proposer
from benchmarks import sleepy
from benchmarks.harness import ROOT, free_port, stop
from service.run.dask_executor import cluster_env
from service.run.dask_executor import local_cluster as embedded_cluster
from service.run.runner import run_job
from service.spec import JobSpec, build, load, parse

DEMO = ROOT / "examples" / "authors_demo" / "spec.yaml"
D41 = ROOT / "examples" / "duffing_41" / "spec.yaml"

# the workers import the plugin by name: LocalCluster's spawned processes inherit this
# process's sys.path, the stock cluster's processes get PYTHONPATH (set below for both)
os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)


def sleepy_spec(populations: int, batch_size: int | None, variant: str | None = None) -> tuple[JobSpec, Path]:
    """The authors' demo, cubic model only, simulated by the sleepy plugin (``variant``: the
    sampler's, else the demo's: paper)."""
    raw = yaml.safe_load(DEMO.read_text())
    if variant is not None:
        raw["sampler"]["variant"] = variant
    raw["name"] = "authors-demo-sleepy"
    raw["models"] = [{**m, "simulator": sleepy.NAME} for m in raw["models"] if m["name"] == "cubic"]
    # the default unit (the demo's spec says 200, the size its figures were measured with)
    raw["sampler"].pop("batch_size", None)
    if batch_size is not None:
        raw["sampler"]["batch_size"] = batch_size
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": populations}
    return parse(raw), DEMO.parent


def d41_spec(populations: int) -> tuple[JobSpec, Path]:
    spec, base = load(D41)
    return spec.model_copy(update={"stop": spec.stop.model_copy(update={
        "min_epsilon_decrease": None, "max_populations": populations})}), base


# -- on the workers (imported by reference: benchmarks.scale is importable there) --------

def _warm_worker() -> int:
    """Import the plugin and what a task imports, and load the Duffing kernel (numba's
    cache) on a worker: once per worker process, as on a long-lived cluster."""
    import abcns.nested  # noqa: F401 - what unpickling a task's proposer imports
    import worker.tasks  # noqa: F401
    from benchmarks import sleepy as plugin
    from worker.simulators import Duffing

    duffing = Duffing(force=np.zeros(16), dt=0.01, substeps=1)
    duffing.simulate(np.array([[1.0, 0.1, 50.0, 0.0, 1000.0, 0.0]]))
    duffing.distance_nmse(np.array([[1.0, 0.1, 50.0, 0.0, 1000.0, 0.0]]), np.arange(16.0), 0, 16)
    return plugin.simulated()


def _cpu_seconds() -> float:
    t = psutil.Process().cpu_times()
    return t.user + t.system


def _simulated() -> int:
    return sleepy.simulated()


def _sleep(seconds: float) -> float:
    time.sleep(seconds)
    return seconds


def dask_floor(client: Client, pids: list[int], units: int, rounds: int, seconds: float,
               barrier: bool = True) -> tuple[float, float, float]:
    """Efficiency of Dask alone on this run's pattern of work: ``rounds`` populations of
    ``units`` tasks that only sleep ``seconds`` (a batch of the sleepy simulator, without the
    simulator, the algorithm or the store), each population submitted at once and gathered
    as its tasks complete, the next one after the last. The best a population loop on Dask
    tasks can do on this cluster. Also Dask's own CPU per task there, in ms: this process
    (client, and a LocalCluster's scheduler) with ``pids`` (a stock scheduler), and the
    workers (sleeping costs nothing: the rest is Dask's).

    ``barrier=False``: the same ``rounds x units`` tasks submitted at once and gathered,
    no population between them: what Dask gives this much work in tasks of this size with
    no runner and no barrier, the ceiling of any design that runs the job's batches as Dask
    tasks (perfect look-ahead included)."""
    n = max(1, sum(client.nthreads().values()))
    tag = "abcns-floor" if barrier else "abcns-stream"
    for warm in (True, False):
        cpu0, other0, workers0 = time.process_time(), _proc_cpu(pids), workers_cpu(client)
        start = time.perf_counter()
        waves = [units] if warm else [units] * rounds if barrier else [rounds * units]  # tasks submitted at once
        for r, size in enumerate(waves):
            futures = client.map(_sleep, [seconds] * size, key=[(tag, int(warm), r, i) for i in range(size)],
                                 pure=False)
            for _ in as_completed(futures, with_results=True):
                pass
        wall = time.perf_counter() - start
        runner = time.process_time() - cpu0 + _proc_cpu(pids) - other0
        workers = workers_cpu(client) - workers0
    tasks = rounds * units
    return rounds * units * seconds / (n * wall), 1e3 * runner / tasks, 1e3 * workers / tasks


def workers_cpu(client: Client) -> float:
    return sum(client.run(_cpu_seconds).values())


def workers_simulated(client: Client) -> int:
    return sum(client.run(_simulated).values())


# -- clusters ------------------------------------------------------------------------------

@contextmanager
def local_cluster(n: int) -> Iterator[tuple[Client, list[int], float]]:
    """(client, extra pids to measure, start-up seconds): LocalCluster, scheduler in this process."""
    start = time.perf_counter()
    with embedded_cluster(n) as cluster, Client(cluster) as client:
        client.wait_for_workers(n, timeout=300)
        client.run(_warm_worker)
        yield client, [], time.perf_counter() - start


@contextmanager
def stock_cluster(n: int, tmp: Path) -> Iterator[tuple[Client, list[int], float]]:
    """`dask scheduler` + `dask worker --nworkers n --nthreads 1`; the scheduler's pid to measure."""
    start = time.perf_counter()
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "start_new_session": True, "cwd": ROOT,
             "env": {**os.environ, **cluster_env()}}  # the Dask settings of docs/deploy.md
    # the CLI's modules, run by this interpreter (no `dask` script needed on PATH: a machine
    # with the packages installed by `pip --target` has none)
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--dashboard-address", ":0"], **quiet)]
    try:
        procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address,
                                       "--nworkers", str(n), "--nthreads", "1",
                                       "--no-dashboard", "--local-directory", str(tmp)], **quiet))
        with Client(address, timeout=60) as client:
            client.wait_for_workers(n, timeout=300)
            client.run(_warm_worker)
            yield client, [procs[0].pid], time.perf_counter() - start
    finally:
        stop(procs, timeout=30)


# -- measuring -----------------------------------------------------------------------------

def _proc_cpu(pids: list[int]) -> float:
    total = 0.0
    for pid in pids:
        t = psutil.Process(pid).cpu_times()
        total += t.user + t.system
    return total


def warm_up(client: Client, spec: JobSpec, base: Path, tmp: Path) -> None:
    """A small job first (100 particles, batches of 20, 1 population), so the timed run finds
    the client, scheduler and workers past their first-job costs (imports, connections)."""
    small = spec.model_copy(update={
        "sampler": spec.sampler.model_copy(update={"particles": 100, "batch_size": 20}),
        "stop": spec.stop.model_copy(update={"max_populations": 1})})
    store = Path(tempfile.mkdtemp(dir=tmp)) / "warm.zarr"
    run_job(small, base, store, client, allow_import=True)
    shutil.rmtree(store.parent, ignore_errors=True)


def measure(client: Client, pids: list[int], spec: JobSpec, base: Path, tmp: Path, count: bool = True,
            tasks: bool = False) -> dict:
    """One ``run_job`` into a fresh store (after :func:`warm_up`); wall, CPU of this process,
    of the pids and of the workers; with ``tasks``, the run's batch tasks from Dask's task
    stream (:func:`task_rows`), for :func:`timeline`."""
    warm_up(client, spec, base, tmp)
    store = Path(tempfile.mkdtemp(dir=tmp)) / "job.zarr"
    w_cpu0 = workers_cpu(client)
    sims0 = workers_simulated(client) if count else 0
    other0 = _proc_cpu(pids)
    with get_task_stream(client) if tasks else contextlib.nullcontext() as stream:
        epoch = time.time()  # the task stream's clock
        cpu0, t0 = time.process_time(), time.perf_counter()
        res = run_job(spec, base, store, client, allow_import=True)
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    other = _proc_cpu(pids) - other0
    w_cpu = workers_cpu(client) - w_cpu0
    executed = workers_simulated(client) - sims0 if count else None
    shutil.rmtree(store.parent, ignore_errors=True)
    n = res.n_simulations
    pops = res.populations
    # populations 2 on: the rate once the job is under way (no store creation, no first population)
    steady = sum(p.n_simulations for p in pops[1:]) / (pops[-1].elapsed_s - pops[0].elapsed_s) if len(pops) > 1 else np.nan
    out: dict = {"populations": len(res.populations), "simulations": n, "executed": executed, "wall": wall,
                 "rate": n / wall, "steady": steady, "runner_us": 1e6 * cpu / n, "other_us": 1e6 * other / n if pids else None,
                 "workers_us": 1e6 * w_cpu / n, "stop": res.stop_reason.value, "load": os.getloadavg()[0]}
    if stream is not None:
        out["timeline"] = timeline(task_rows(stream.data, epoch), [p.n_simulations for p in pops],
                                   spec.sampler.batch_size, wall)
    return out


def task_rows(records: list[dict], epoch: float) -> list[tuple[int, int, float, float]]:
    """(population, first batch, compute start, compute stop) of each batch task in Dask's
    task-stream records (``get_task_stream``), in seconds after ``epoch``. A batch task's key
    is ``(group, population, first batch, last batch)`` (``service.run.dask_executor``); the
    anchors (population 0) and the job's data are left out."""
    rows = []
    for rec in records:
        key = rec["key"]
        if not (isinstance(key, tuple) and len(key) == 4 and str(key[0]).startswith("abcns-") and key[1] > 0):
            continue
        for step in rec["startstops"]:
            if step["action"] == "compute":
                rows.append((int(key[1]), int(key[2]), step["start"] - epoch, step["stop"] - epoch))
    return rows


def timeline(rows: list[tuple[int, int, float, float]], simulations: list[int], batch_size: int, wall: float) -> dict:
    """Where a run's wall time went, from its batch tasks (:func:`task_rows`) and each
    population's simulations: ``start`` (before population 1's first task: the store created,
    the job's data and first tasks to the cluster), ``end`` (after the last population's last
    used task: the last append, the status, the result read back), ``gaps`` (from each
    population's last used task to the next one's first: the step, the dispatch, any stall
    of the runner's process), ``spans`` (each population's first task to its last used one:
    its simulations, the tail and the surplus beside them). A used task holds a batch at or
    below the population's ``ceil(simulations / batch_size)``."""
    first, last = {}, {}
    for t, n in enumerate(simulations, start=1):
        used = -(-n // batch_size)
        own = [r for r in rows if r[0] == t]
        if not own:
            continue
        first[t] = min(r[2] for r in own)
        last[t] = max((r[3] for r in own if r[1] <= used), default=first[t])
    ts = sorted(first)
    if not ts:
        return {"start": np.nan, "end": np.nan, "gaps": [], "spans": np.nan}
    gaps = [first[t + 1] - last[t] for t in ts[:-1] if t + 1 in first]
    return {"start": first[ts[0]], "end": wall - last[ts[-1]], "gaps": gaps,
            "spans": sum(last[t] - first[t] for t in ts)}


def engine_alone(spec: JobSpec, base: Path) -> tuple[float, float]:
    """CPU µs per simulation of the same job in this process with the built-in Duffing (no
    sleep, no Dask, no store), best of 3; and the kernel's share of it."""
    raw = spec.model_dump(mode="json")
    raw["models"] = [{**m, "simulator": "duffing"} for m in raw["models"]]
    job = build(parse(raw), base)
    best, kernel, spent = np.inf, 0.0, [0.0]

    def timed(b):
        t = time.process_time()
        out = job.evaluate(b)
        spent[0] += time.process_time() - t
        return out

    for _ in range(3):
        spent[0] = 0.0
        t = time.process_time()
        r = run(job.models, timed, job.settings, job.stop, job.seed)
        cpu = time.process_time() - t
        if cpu < best:
            best, kernel = cpu, spent[0]
    return 1e6 * best / r.n_simulations, 1e6 * kernel / r.n_simulations


def sleepy_table(title: str, cluster: Callable, counts: list[int], spec: JobSpec, base: Path, tmp: Path,
                 stock: bool, skip_floor: bool = False, with_timeline: bool = False) -> None:
    print(f"\n## {title}")
    engine, kernel = engine_alone(spec, base)
    print(f"the same job in this process with the plain Duffing (engine + kernel, no sleep, no Dask, no store): "
          f"{engine:.0f} µs CPU per simulation, of which the evaluator {kernel:.0f}")
    sched = " scheduler CPU µs/sim |" if stock else ""
    print(f"| workers | simulations | executed | wall s | sims/s | ideal sims/s | efficiency | steady | Dask floor | "
          f"no-barrier floor | "
          f"runner CPU µs/sim |{sched} workers CPU µs/sim | Dask floor CPU ms/task: runner{' + scheduler' if stock else ''}, "
          f"workers | start-up s | load |")
    print("|" + "---:|" * (15 + stock), flush=True)
    timelines = []
    for n in counts:
        with cluster(n) as (client, pids, startup):
            r = measure(client, pids, spec, base, tmp, tasks=with_timeline)
            if with_timeline:
                timelines.append((n, r))
            units = round(r["simulations"] / (r["populations"] * spec.sampler.batch_size))
            floor, floor_runner, floor_workers = (np.nan,) * 3 if skip_floor else dask_floor(
                client, pids, units, r["populations"], spec.sampler.batch_size * sleepy.SECONDS)
            stream = np.nan if skip_floor else dask_floor(client, pids, units, r["populations"],
                                                          spec.sampler.batch_size * sleepy.SECONDS, barrier=False)[0]
        ideal = n / sleepy.SECONDS  # simulations/s of n workers that only sleep
        extra = f" {r['other_us']:.0f} |" if stock else ""
        print(f"| {n} | {r['simulations']} | {r['executed']} | {r['wall']:.2f} | {r['rate']:.0f} | "
              f"{ideal:.0f} | {r['rate'] / ideal:.2f} | {r['steady'] / ideal:.2f} | {floor:.2f} | {stream:.2f} | "
              f"{r['runner_us']:.0f} |{extra} "
              f"{r['workers_us']:.0f} | {floor_runner:.1f}, {floor_workers:.1f} | {startup:.1f} | {r['load']:.1f} |",
              flush=True)
    if timelines:
        print_timeline(timelines, sleepy.SECONDS)


def print_timeline(timelines: list[tuple[int, dict]], seconds: float) -> None:
    """The ``--timeline`` table: each row's wall time, taken apart (:func:`timeline`)."""
    print("\ntimeline (Dask's task stream): before the first task | after the last used task | gaps between "
          "populations: total (median; over 100 ms) | populations' spans against their simulations on W workers")
    print("| workers | wall s | start ms | end ms | gaps ms | spans s / simulations s |")
    print("|---:|---:|---:|---:|---|---:|")
    for n, r in timelines:
        tl, gaps = r["timeline"], np.array(r["timeline"]["gaps"])
        gap_text = (f"{1e3 * gaps.sum():.0f} ({1e3 * np.median(gaps):.0f}; {int((gaps > 0.1).sum())} of {gaps.size})"
                    if gaps.size else "")
        print(f"| {n} | {r['wall']:.2f} | {1e3 * tl['start']:.0f} | {1e3 * tl['end']:.0f} | {gap_text} | "
              f"{tl['spans']:.2f} / {r['simulations'] * seconds / n:.2f} |", flush=True)


def kernel_alone(spec: JobSpec, base: Path, repeats: int) -> dict:
    """This process, no Dask: the evaluator on one batch of prior draws at epsilon = inf (best
    of ``repeats`` calls); a serial in-process run (best of 3): its wall and the evaluator's
    time on its own batches."""
    job = build(spec, base)
    batch = next(draws(prior_proposer(job.models), seed=0, t=1, epsilon=np.inf, batch_size=job.settings.batch_size)).batch()
    job.evaluate(batch)  # compile / load numba's cache
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        job.evaluate(batch)
        best = min(best, time.perf_counter() - t)
    walls, spent, cpus = [], [], []
    for _ in range(3):
        spent.append(0.0)

        def timed(b):
            t = time.perf_counter()
            out = job.evaluate(b)
            spent[-1] += time.perf_counter() - t
            return out

        t, c = time.perf_counter(), time.process_time()
        r = run(job.models, timed, job.settings, job.stop, job.seed)
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    n = r.n_simulations
    return {"one_batch": len(batch.theta) / best, "own_batches": n / min(spent), "serial": n / min(walls),
            "serial_us": 1e6 * cpus[int(np.argmin(walls))] / n, "simulations": n}


def d41_table(counts: list[int], populations: int, tmp: Path) -> None:
    spec, base = d41_spec(populations)
    k = kernel_alone(spec, base, repeats=20)
    print(f"\n## paper §4.1 (examples/duffing_41, real kernels), {populations} populations, "
          f"batch size {spec.sampler.batch_size}, LocalCluster")
    print(f"kernel alone, this process: {k['one_batch']:.0f} sims/s on one batch of prior draws (epsilon = inf, best of "
          f"20 calls); {k['own_batches']:.0f} sims/s on a serial in-process run's own batches (early rejection; "
          f"{k['simulations']} simulations; best of 3 runs); that serial run end to end (engine, no Dask, no store): "
          f"{k['serial']:.0f} sims/s, {k['serial_us']:.1f} µs of CPU per simulation")
    print("| workers | simulations | wall s | sims/s end to end | runner CPU µs/sim | workers CPU µs/sim | "
          "end to end / (N x kernel alone) | same, vs the run's own batches | load |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|", flush=True)
    for n in counts:
        with local_cluster(n) as (client, pids, _):
            r = measure(client, pids, spec, base, tmp, count=False)
        print(f"| {n} | {r['simulations']} | {r['wall']:.2f} | {r['rate']:.0f} | {r['runner_us']:.0f} | "
              f"{r['workers_us']:.0f} | {r['rate'] / (n * k['one_batch']):.3f} | {r['rate'] / (n * k['own_batches']):.3f} | "
              f"{r['load']:.1f} |",
              flush=True)


# -- pyABC on the same pattern (optional: pyABC is imported here only) ---------------------

PYABC_OBSERVED = (1.0, -0.5)
PYABC_NOISE = 0.5


def pyabc_model(parameter: dict, seconds: float) -> dict:
    """One simulation of part 4's model: sleep ``seconds``, then ``(a, b)`` plus Gaussian
    noise of standard deviation ``PYABC_NOISE`` (numpy's global generator: pyABC reseeds it
    in each worker)."""
    time.sleep(seconds)
    return {"y": np.array([parameter["a"], parameter["b"]]) + PYABC_NOISE * np.random.standard_normal(2)}  # noqa: NPY002


def pyabc_distance(x: dict, x0: dict) -> float:
    """Squared Euclidean distance between simulated and observed ``y``."""
    return float(np.sum((x["y"] - x0["y"]) ** 2))


def pyabc_table(counts: list[int], generations: int, tmp: Path) -> None:
    """Part 4: pyABC's ABC-SMC on ``W`` forked processes for each ``W`` in ``counts``."""
    try:
        import pyabc
        from pyabc.sampler import MulticoreEvalParallelSampler
    except ImportError as exc:
        print(f"\n## pyABC: skipped, pyABC cannot be imported ({exc}); pip install 'pyabc>=0.13' "
              f"or the extra .[bench]", flush=True)
        return
    logging.getLogger("ABC").setLevel(logging.ERROR)  # pyABC logs every generation at INFO
    print(f"\n## pyABC {pyabc.__version__}, ABCSMC with MulticoreEvalParallelSampler(n_procs=W), population size "
          f"1000, {generations} generations after the calibration sample, 2-parameter Gaussian location model, "
          f"{1e3 * sleepy.SECONDS:g} ms sleep per simulation, history in sqlite")
    print("| workers | simulations | wall s | sims/s | ideal sims/s | efficiency | final epsilon | load |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|", flush=True)
    prior = pyabc.Distribution(a=pyabc.RV("uniform", -5, 10), b=pyabc.RV("uniform", -5, 10))
    model = functools.partial(pyabc_model, seconds=sleepy.SECONDS)
    for n in counts:
        db = Path(tempfile.mkdtemp(dir=tmp)) / "pyabc.db"
        try:
            abc = pyabc.ABCSMC(model, prior, pyabc_distance, population_size=1000,
                               sampler=MulticoreEvalParallelSampler(n_procs=n))
            t0 = time.perf_counter()
            abc.new(f"sqlite:///{db}", {"y": np.array(PYABC_OBSERVED)})
            history = abc.run(max_nr_populations=generations)
            wall = time.perf_counter() - t0
            sims = int(history.total_nr_simulations)
            eps = float(history.get_all_populations().sort_values("t")["epsilon"].iloc[-1])
        finally:
            shutil.rmtree(db.parent, ignore_errors=True)
        ideal = n / sleepy.SECONDS
        print(f"| {n} | {sims} | {wall:.2f} | {sims / wall:.0f} | {ideal:.0f} | {sims / wall / ideal:.2f} | "
              f"{eps:.3g} | {os.getloadavg()[0]:.1f} |", flush=True)


def _counts(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workers", type=_counts, default=[1, 2, 4, 8, 16, 32], help="LocalCluster sizes (1,2,4)")
    parser.add_argument("--stock-workers", type=_counts, default=[1, 8], help="stock cluster sizes")
    parser.add_argument("--populations", type=int, default=10, help="populations of the sleepy job")
    parser.add_argument("--batch-size", type=int, default=None, help="override the sleepy job's sampler.batch_size")
    parser.add_argument("--variant", choices=["paper", "evidence"], default=None,
                        help="the sleepy job's ABC-NS variant (default: the demo's, paper)")
    parser.add_argument("--sleep-ms", type=float, default=None,
                        help="the sleepy simulator's sleep per simulation (default 2 ms)")
    parser.add_argument("--d41-workers", type=_counts, default=[1, 2])
    parser.add_argument("--d41-populations", type=int, default=6)
    parser.add_argument("--skip-local", action="store_true")
    parser.add_argument("--skip-stock", action="store_true")
    parser.add_argument("--skip-d41", action="store_true")
    parser.add_argument("--skip-floor", action="store_true", help="no Dask floor column (half the time per row)")
    parser.add_argument("--pyabc-workers", type=_counts, default=[],
                        help="pyABC MulticoreEvalParallelSampler sizes, e.g. 8,14 (default: none; needs pyabc)")
    parser.add_argument("--pyabc-generations", type=int, default=8, help="pyABC generations (max_nr_populations)")
    parser.add_argument("--timeline", action="store_true",
                        help="also take each sleepy row's wall time apart from Dask's task stream (start, end, gaps "
                             "between populations, their spans)")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 1 population, 1-2 workers")
    args = parser.parse_args()
    if args.sleep_ms is not None:  # before any worker starts: they inherit the variable
        os.environ["ABCNS_SLEEPY_MS"] = str(args.sleep_ms)
        sleepy.SECONDS = args.sleep_ms / 1e3
    if args.quick:
        args.workers, args.stock_workers, args.populations = [1, 2], [1], 1
        args.d41_workers, args.d41_populations = [1, 2], 1

    spec, base = sleepy_spec(args.populations, args.batch_size, args.variant)
    print(f"# scale-out: {spec.name}, cubic model, {spec.sampler.variant} variant, {spec.sampler.particles} particles, "
          f"batch size {spec.sampler.batch_size}, {args.populations} populations, "
          f"{1e3 * sleepy.SECONDS:g} ms sleep per simulation; {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory(prefix="abcns-scale-") as tmpdir:
        tmp = Path(tmpdir)
        if not args.skip_local:
            sleepy_table("latency-bound, LocalCluster (scheduler in the runner's process)", local_cluster,
                         args.workers, spec, base, tmp, stock=False, skip_floor=args.skip_floor,
                         with_timeline=args.timeline)
        if not args.skip_stock:
            sleepy_table("latency-bound, stock `dask scheduler` + `dask worker --nworkers N --nthreads 1`",
                         lambda n: stock_cluster(n, tmp), args.stock_workers, spec, base, tmp, stock=True,
                         skip_floor=args.skip_floor, with_timeline=args.timeline)
        if not args.skip_d41:
            d41_table(args.d41_workers, args.d41_populations, tmp)
        if args.pyabc_workers:
            pyabc_table(args.pyabc_workers, args.pyabc_generations, tmp)


if __name__ == "__main__":
    main()
