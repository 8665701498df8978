"""End-to-end throughput of the runner on the paper §4.1 example (cubic vs cubic-quintic
Duffing, examples/duffing_41/spec.yaml, first 40 populations), beside the simulator alone.

    python -m benchmarks.runner [--populations N] [--batch-size B] [--spec SPEC]

``--substeps N`` sets every model's RK4 substeps per sample (the §4.1 spec lets the
simulator choose them from the priors): ``--substeps 128`` makes the same job's simulations
~10x dearer, the regime where the runner's overheads are small and a second worker pays.

Simulations per second counts the simulations the algorithm used (the serial-equivalent
count stored in the result), wall time from the first batch to the last population stored.
Rows: the simulator alone on a batch of 1000 prior draws (one core, in-kernel NMSE), the
engine in-process (serial executor, no store), ``abcns run``'s code path without a cluster
(``run_job`` in this process, zarr store: what a cluster must beat), and with a Dask
LocalCluster of 1 and 2 worker processes (populations cheaper than
``ABCNS_LOCAL_POPULATION_S`` evaluated in the runner: ``service.run.dask_executor``). Each row but the first is the
fastest of ``--repeats`` runs (after a one-population warm-up: numba's cache, the workers'
imports). *runner CPU µs/sim*: ``time.process_time()`` of this process over that run, per
simulation: the whole engine in-process; with Dask, the runner (step, geometry, store),
the client and the scheduler (a LocalCluster's runs in this process).
"""

from __future__ import annotations

import argparse
import itertools
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np
from distributed import Client

from abcns import run
from abcns.filling import draws
from abcns.rejection import prior_proposer
from service.run.dask_executor import local_cluster
from service.run.runner import run_job
from service.spec import build, load

SPEC = Path(__file__).resolve().parents[1] / "examples" / "duffing_41" / "spec.yaml"


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--populations", type=int, default=40)
    parser.add_argument("--batch-size", type=int, default=None, help="override sampler.batch_size")
    parser.add_argument("--spec", type=Path, default=SPEC, help="a job spec (default: paper §4.1)")
    parser.add_argument("--substeps", type=int, default=None, help="override every model's integrator.substeps")
    parser.add_argument("--repeats", type=int, default=3, help="runs per configuration, the fastest kept")
    parser.add_argument("--workers", type=lambda t: [int(x) for x in t.split(",") if x.strip()], default=[1, 2],
                        help="LocalCluster sizes (default 1,2; empty: in-process only)")
    args = parser.parse_args()
    spec, base = load(args.spec)
    if args.substeps is not None:
        spec = spec.model_copy(update={"models": [
            m.model_copy(update={"integrator": m.integrator.model_copy(update={"substeps": args.substeps})})
            for m in spec.models]})
    stop = spec.stop.model_copy(update={"max_populations": args.populations})
    sampler = spec.sampler.model_copy(update={"batch_size": args.batch_size or spec.sampler.batch_size})
    spec = spec.model_copy(update={"stop": stop, "sampler": sampler})
    job = build(spec, base)
    rows = []

    # the simulator alone: one batch of 1000 prior draws, in-kernel NMSE, best of 5
    batch = next(draws(prior_proposer(job.models), seed=0, t=1, epsilon=np.inf, batch_size=1000)).batch()
    job.evaluate(batch)  # compile / load the cache
    best = min(_timed(lambda: job.evaluate(batch)) for _ in range(5))
    rows.append(("simulator alone (1 core, batch 1000)", 1000 / best, None, None))

    warm = spec.model_copy(update={"stop": stop.model_copy(update={"max_populations": 1})})
    run(job.models, job.evaluate, job.settings, replace(job.stop, max_populations=1), job.seed)  # numba's cache
    reference, wall, cpu = _best(args.repeats, lambda: run(job.models, job.evaluate, job.settings, job.stop, job.seed))
    rows.append((f"engine in-process, serial ({len(reference.populations)} populations)",
                 reference.n_simulations / wall, wall, cpu / reference.n_simulations))

    res, wall, cpu = _best_run_job(spec, warm, base, None, args.repeats)
    rows.append(("abcns runner, in this process (no cluster), zarr store", res.n_simulations / wall, wall,
                 cpu / res.n_simulations))

    for n_workers in args.workers:
        with local_cluster(n_workers) as cluster, \
                Client(cluster) as client:
            res, wall, cpu = _best_run_job(spec, warm, base, client, args.repeats)
        same = all(np.array_equal(p.theta, q.theta, equal_nan=True) for p, q in zip(res.populations, reference.populations))
        rows.append((f"abcns runner, LocalCluster {n_workers} worker(s), zarr store (identical: {same})",
                     res.n_simulations / wall, wall, cpu / res.n_simulations))

    at = "" if args.substeps is None else f" at {args.substeps} substeps"
    print(f"{spec.name}{at}, {len(reference.populations)} populations, {reference.n_simulations} simulations, "
          f"batch size {job.settings.batch_size}; {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    print(f"{'configuration':70s} {'sims/s':>10s} {'wall s':>8s} {'vs simulator':>12s} {'runner CPU µs/sim':>18s}")
    for name, rate, wall, cpu in rows:
        print(f"{name:70s} {rate:10.0f} {'' if wall is None else f'{wall:8.2f}':>8s} {rate / rows[0][1]:12.2f} "
              f"{'' if cpu is None else f'{1e6 * cpu:18.1f}':>18s}")
    if len(rows) > 3:
        print(f"LocalCluster 1 worker / engine in-process: {rows[3][1] / rows[1][1]:.2f}; "
              f"/ runner without a cluster: {rows[3][1] / rows[2][1]:.2f}")
    if len(rows) > 4:
        print(f"2 workers / 1 worker: {rows[4][1] / rows[3][1]:.2f}")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


def _best_run_job(spec, warm, base: Path, client: Client | None, repeats: int):
    """:func:`_best` of ``run_job`` (each into a fresh store) after one run of ``warm`` (numba's
    cache; on a cluster, the workers load the kernels once)."""
    tmp = Path(tempfile.mkdtemp())
    try:
        run_job(warm, base, tmp / "warm.zarr", client)
        stores = (tmp / f"job{i}.zarr" for i in range(repeats))
        return _best(repeats, partial(run_job, spec, base, client=client), stores)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _best(repeats: int, fn, args: Iterator = itertools.repeat(())):
    """(result, wall s, CPU s of this process) of the fastest of ``repeats`` calls of ``fn``
    (the i-th called with the i-th of ``args``, a tuple or a single argument)."""
    best = None
    for _, arg in zip(range(repeats), args):
        wall, cpu = time.perf_counter(), time.process_time()
        out = fn(*arg) if isinstance(arg, tuple) else fn(arg)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        if best is None or wall < best[1]:
            best = (out, wall, cpu)
    assert best is not None
    return best


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


if __name__ == "__main__":
    main()
