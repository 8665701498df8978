"""The measured figures the cluster model is calibrated and validated against.

``SIXTEEN``: benchmarks/measurements/2026-11-25-16-cores.md (a 16-core machine, one worker
process per core, LocalCluster, commit 80c2423), one session per variant (the paper
variant's as committed; the evidence variant's with OPENBLAS_NUM_THREADS=1). ``LOCAL``:
this project's 2-core machine, benchmarks/measurements/2026-11-25-2-cores.md.

Per session: ``engine``: µs of CPU per simulation of the same job in-process with the plain
Duffing, and the evaluator's part (``benchmarks.scale``'s line above its table; the ratio
that carries the trace's runner CPU to that machine); ``jobs``: workers -> (efficiency,
executed rows, runner CPU µs per simulation); ``floor``: workers -> (efficiency, runner CPU
ms per task) of ``benchmarks.scale.dask_floor`` (``rounds`` rounds of ``units`` 50 ms tasks).
``FED``: the 16-core file's "Dask alone" runs: (workers, task seconds) -> (tasks in 8 s,
efficiency), 2 W in flight, one task submitted as each completes.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Session:
    machine: str
    trace: str
    engine: tuple[float, float]  # (engine µs/sim, of which the evaluator)
    jobs: dict[int, tuple[float, int, float]]
    floor: dict[int, tuple[float, float]]
    units: int
    rounds: int = 10
    load: str = ""


SIXTEEN = {
    "paper": Session(
        "16 cores", "paper-1000", (47, 20),
        jobs={1: (0.89, 7800, 455), 2: (0.85, 7900, 377), 4: (0.78, 7950, 249), 8: (0.64, 8175, 224),
              14: (0.50, 9075, 176)},
        floor={1: (0.97, 3.5), 2: (0.93, 2.7), 4: (0.88, 2.6), 8: (0.88, 1.8), 14: (0.67, 1.4)},
        units=31),  # round(7654 / (10 x 25))
    "evidence": Session(
        "16 cores", "evidence-1000", (104, 19),
        jobs={1: (0.83, 7125, 683), 8: (0.44, 7550, 412), 14: (0.34, 8175, 339)},
        floor={1: (0.95, 5.1), 8: (0.77, 2.6), 14: (0.69, 2.8)},
        units=28),  # round(6978 / (10 x 25))
}

#: the second 16-core session (benchmarks/measurements/2026-11-25-16-cores-b.md: the compiled
#: step, evidence variant, LocalCluster, one run each), measured after the model had predicted
#: it from the traces re-recorded with that step (docs/benchmarks.md):
#: (trace, ms per simulation, workers) -> (efficiency, executed rows)
PREDICTED_THEN_MEASURED = {
    ("evidence-1000-cheap-step", 2.0, 1): (0.87, 7125), ("evidence-1000-cheap-step", 2.0, 8): (0.58, 7600),
    ("evidence-1000-cheap-step", 2.0, 14): (0.45, 8175),
    ("evidence-1000-cheap-step", 20.0, 8): (0.79, 7650), ("evidence-1000-cheap-step", 20.0, 14): (0.72, 8095),
    ("evidence-1000-b5-cheap-step", 20.0, 8): (0.91, 6900), ("evidence-1000-b5-cheap-step", 20.0, 14): (0.86, 6985),
}

#: (workers, task seconds) -> (tasks completed in 8 s, efficiency)
FED = {(1, 0.05): (156, 0.97), (1, 0.01): (570, 0.71), (8, 0.05): (1186, 0.91), (8, 0.01): (1381, 0.21),
       (14, 0.05): (1368, 0.60), (14, 0.01): (1404, 0.12)}
FED_DURATION_S = 8.0


@dataclass(frozen=True)
class LocalSession(Session):
    #: the same job on a stock `dask scheduler` (its own process) and `dask worker` processes
    stock_jobs: dict[int, tuple[float, int, float]] | None = None


#: this 2-core machine, benchmarks/measurements/2026-11-25-2-cores.md (under real-time
#: priority, `chrt -r 1`: the machine is shared, other engineers' tests ran at a load of
#: 13-32); 4 and 8 workers share the 2 cores (they mostly sleep)
LOCAL = {
    "paper": LocalSession(
        "2 cores", "paper-1000", (20, 7),
        jobs={1: (0.90, 7800, 473), 2: (0.84, 7900, 443), 4: (0.77, 7925, 292), 8: (0.60, 8200, 263)},
        floor={1: (0.97, 3.4), 2: (0.93, 2.9), 4: (0.91, 2.5), 8: (0.84, 2.2)}, units=31,
        stock_jobs={1: (0.89, 7800, 355), 2: (0.86, 7900, 272)}),
    "evidence": LocalSession(
        "2 cores", "evidence-1000", (57, 8),
        jobs={1: (0.88, 7125, 546), 2: (0.83, 7150, 469), 4: (0.74, 7325, 329), 8: (0.56, 7525, 302)},
        floor={1: (0.96, 3.5), 2: (0.96, 2.7), 4: (0.94, 2.3), 8: (0.79, 2.3)}, units=28,
        stock_jobs={1: (0.88, 7125, 387), 2: (0.82, 7150, 340)}),
}

#: Dask's costs on this machine, LocalCluster, 1 and 2 workers averaged
#: (``python -m benchmarks.cluster_model costs``, the same file): seconds
LOCAL_COSTS = {
    # the runner's process per task: event loops 2.70 / 1.80 ms, main thread 0.19 / 0.12 ms
    "per_task": (2.696 + 0.008 + 0.161 + 0.024 + 1.796 + 0.006 + 0.088 + 0.022) / 2 * 1e-3,
    # per client.map call: event loops 3.57 / 4.45 ms, main thread 0.71 / 0.80 ms
    "per_call": (3.569 + 0.597 + 0.062 + 0.050 + 4.451 + 0.607 + 0.144 + 0.053) / 2 * 1e-3,
    "background": (6.667 + 10.0) / 2 * 1e-3,  # CPU per second while every worker runs a long task
    "worker_task": (2.041 + 2.132) / 2 * 1e-3,
    "overshoot": (0.058 + 0.068) / 2 * 1e-3,
}

#: queues of whole §4.1 jobs on this 2-core machine: docs/benchmarks.md "Many jobs at once",
#: ``benchmarks.jobs --jobs 16 --workers 2 --service [--ceiling]``, four runs in 6 minutes
#: (2026-11-28, before the summary's second read was cut): the 16 jobs' seconds one after
#: another in one process, and the wall of each way of running them together. Each job's own
#: time was not printed then: the model takes 16 equal jobs. The dispatch (``gap_s``): the
#: median idle gap on a worker between one job task's end and the next one's start, measured
#: on 2026-11-29 with the same code (run_jobs 135 ms, the service 59 ms; plain processes: 0);
#: ``other_cpu_s``: the CPU per job of the processes besides the workers, measured then too
#: (run_jobs: its process, client, scheduler and nannies, 77 ms; the service: `abcns serve` 147 ms
#: and the scheduler 111 ms)
QUEUE_2_CORES: dict[str, dict] = {
    f"run {i}": {"workers": 2, "alone_s": [alone / 16] * 16,
                 "walls": {k: v for k, v in (("run_jobs", run_jobs), ("abcns serve", served), ("plain processes", plain))
                           if v is not None},
                 "gap_s": {"run_jobs": 0.135, "abcns serve": 0.059},
                 "other_cpu_s": {"run_jobs": 0.077, "abcns serve": 0.258}}
    for i, (alone, run_jobs, served, plain) in enumerate([(28.3, 15.9, 19.2, 15.1), (26.3, 15.6, 17.2, None),
                                                          (32.9, 21.9, 25.2, None), (38.3, 25.3, 20.4, 18.0)], 1)
}

#: queues of sleepy jobs on this 2-core machine: ``benchmarks.jobs --sleepy 2 --jobs 4 --workers 2``
#: (benchmarks.scale's job, evidence variant, N = 1000, batch 25: the trace evidence-1000-warm),
#: run_jobs on a LocalCluster, two runs on 2026-11-29 at load 3.9-4.3 (other developers' work):
#: (trace, ms a simulation, jobs, workers) -> measured utilizations
QUEUE_SLEEPY_2_CORES = {("evidence-1000-warm", 2.0, 4, 2): (0.825, 0.810)}
