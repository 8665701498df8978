"""Many jobs at once against one after another: the paper §4.1 job
(examples/duffing_41/spec.yaml, to its noise floor) with seeds 1..N.

    python -m benchmarks.jobs [--jobs 16] [--workers 2] [--spec SPEC] [--keep DIR] [--ceiling] [--service]

*one after another*: every job in this process, ``run_job(..., client=None)`` (the
in-process engine, a store each), the first one paying for loading the compiled kernels.
*together*: every job at once through :func:`service.run.jobs.run_jobs` on a LocalCluster
of ``--workers`` single-threaded worker processes (started before the clock starts; its
start is printed apart), each job one task on a worker, whole or spread as its placement
rule decides (each worker loads the kernels once, inside the clock). Then every job's
stores are compared: the populations (models, parameters, distances, weights, survivors,
tolerances, simulation counts) must be bit-identical between the two. Printed: both wall
times, the ratio (one after another over together: the rate of jobs together over the
rate one after another), each job's placement, and the load average before and after each
phase (the machine may be shared: a load above its cores slows either phase).

*through the service* (``--service``): the same jobs submitted at once to `abcns serve`
(no ``--max-running``: one job per worker) on a stock `dask scheduler` with ``--workers``
`dask worker` processes (all started before the clock), each job's data inline in its JSON
spec; the clock runs from the first submission to the last job's end, read from the jobs'
terminal events. Their stores are compared with the jobs run alone too.

*plain processes* (``--ceiling``): the same jobs on ``--workers`` plain processes of
``concurrent.futures`` (started and warmed before the clock, no Dask), a job at a time
each: what this machine gives at that many processes now, the ceiling of the ratio.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import shutil
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from distributed import Client

from service.run.dask_executor import local_cluster
from service.run.jobs import JobRun, run_jobs
from service.run.runner import run_job
from service.run.store import Store
from service.spec import JobSpec, load, load_array

SPEC = Path(__file__).resolve().parents[1] / "examples" / "duffing_41" / "spec.yaml"
FIELDS = ("models", "theta", "distances", "weights", "survivors")


def load_average() -> str:
    return "/".join(f"{x:.2f}" for x in os.getloadavg())


def same_populations(a: Path, b: Path) -> str | None:
    """None when the two stores hold bit-identical populations, else what differs."""
    sa, sb = Store.open(a), Store.open(b)
    if sa.n_populations != sb.n_populations:
        return f"{sa.n_populations} populations against {sb.n_populations}"
    for p, q in zip(sa.populations(), sb.populations(), strict=True):
        for name in FIELDS:
            if not np.array_equal(getattr(p, name), getattr(q, name), equal_nan=True):
                return f"population {p.t}: {name}"
        if (p.epsilon, p.epsilon_next, p.n_simulations) != (q.epsilon, q.epsilon_next, q.n_simulations):
            return f"population {p.t}: tolerance or simulations"
    return None


def _one(spec: JobSpec, base: Path, store: Path, seed: int) -> None:
    run_job(spec, base, store, None, seed=seed)


def _warm() -> None:
    """A plain process's warm-up, as a worker's: the modules imported (the kernels load in
    the clock, as on the workers)."""


def plain_processes(spec: JobSpec, base: Path, folder: Path, seeds: range, n: int) -> float:
    """Seconds for the jobs on ``n`` plain processes (a job at a time each), started first."""
    with ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn")) as pool:
        for f in [pool.submit(_warm) for _ in range(4 * n)]:
            f.result()
        start = time.monotonic()
        for f in [pool.submit(_one, spec, base, folder / f"plain-{seed}.zarr", seed) for seed in seeds]:
            f.result()
        return time.monotonic() - start


def through_service(spec: JobSpec, base: Path, folder: Path, seeds: range,
                    n: int) -> tuple[float, float, dict[int, Path], Counter]:
    """Seconds for the jobs submitted at once to `abcns serve` on ``n`` stock workers, the
    seconds their submissions took, their stores by seed, and their placements."""
    import httpx

    from benchmarks.harness import AUTH, Service, StockCluster, wait_until

    data = {key: load_array(getattr(spec.data, key), base, f"data.{key}").tolist() for key in ("input", "observed")}
    raw = spec.model_dump(mode="json")
    raw["data"].update(data)
    cluster = StockCluster(folder / "dask", n_workers=n)
    service = Service(folder / "service-jobs", cluster.address, max_running=None)
    try:
        with httpx.Client(timeout=120, headers=AUTH) as http:
            start = time.time()
            ids = {seed: http.post(f"{service.url}/jobs", json={**raw, "seed": seed, "name": f"seed-{seed}"}).json()["id"]
                   for seed in seeds}
            submitted = time.time() - start

            def ended() -> bool:
                return all(j["status"] in ("finished", "failed", "cancelled") for j in http.get(f"{service.url}/jobs").json())

            wait_until(ended, 3600, "every job to end", 0.5)
        last, places = 0.0, Counter()
        for seed, job_id in ids.items():
            events = [json.loads(line) for line in (service.job_dir(job_id) / "events.jsonl").read_text().splitlines()]
            if events[-1]["event"] != "finished":
                raise SystemExit(f"seed {seed} ended {events[-1]['event']} through the service: {events[-1]['data']}")
            last = max(last, events[-1]["time"])
            placed = [e["data"]["placement"] for e in events if e["event"] == "placed"]
            places[placed[0]["mode"] if placed else "?"] += 1
        return last - start, submitted, {seed: service.job_dir(job_id) / "store.zarr" for seed, job_id in ids.items()}, places
    finally:
        service.close()
        cluster.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", type=int, default=16)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--spec", type=Path, default=SPEC)
    parser.add_argument("--keep", type=Path, default=None, help="keep the stores in this folder")
    parser.add_argument("--ceiling", action="store_true", help="also the jobs on plain processes (no Dask)")
    parser.add_argument("--service", action="store_true", help="also the jobs through `abcns serve`")
    args = parser.parse_args()
    spec, base = load(args.spec)
    seeds = range(1, args.jobs + 1)
    folder = args.keep or Path(tempfile.mkdtemp(prefix="abcns-jobs-"))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        load_0 = load_average()
        start = time.monotonic()
        for seed in seeds:
            run_job(spec, base, folder / f"alone-{seed}.zarr", None, seed=seed)
        alone_s = time.monotonic() - start
        load_1 = load_average()

        jobs = [JobRun.of(spec.model_copy(update={"seed": seed}), base, folder / f"together-{seed}.zarr", f"seed-{seed}")
                for seed in seeds]
        start = time.monotonic()
        with local_cluster(args.workers) as cluster, Client(cluster) as client:
            client.wait_for_workers(args.workers, timeout=120)
            cluster_s = time.monotonic() - start
            load_2 = load_average()
            start = time.monotonic()
            outcomes = run_jobs(client, jobs)
            together_s = time.monotonic() - start
            load_3 = load_average()
        if args.ceiling:
            load_4 = load_average()
            plain_s = plain_processes(spec, base, folder, seeds, args.workers)
            load_5 = load_average()
        if args.service:
            load_6 = load_average()
            service_s, submit_s, service_stores, service_places = through_service(spec, base, folder, seeds, args.workers)
            load_7 = load_average()
        failed = [f"seed {s}: {o.status} {o.error}" for s, o in zip(seeds, outcomes, strict=True) if o.status != "finished"]
        if failed:
            raise SystemExit("jobs failed together:\n" + "\n".join(failed))
        differ = {seed: d for seed in seeds
                  if (d := same_populations(folder / f"alone-{seed}.zarr", folder / f"together-{seed}.zarr"))}
        if args.ceiling:
            differ |= {seed: f"plain: {d}" for seed in seeds
                       if (d := same_populations(folder / f"alone-{seed}.zarr", folder / f"plain-{seed}.zarr"))}
        if args.service:
            differ |= {seed: f"service: {d}" for seed in seeds
                       if (d := same_populations(folder / f"alone-{seed}.zarr", service_stores[seed]))}
        sims = sum(Store.open(folder / f"alone-{seed}.zarr").run_state()["n_simulations_total"] for seed in seeds)
        places = Counter((o.placement or {}).get("mode", "?") for o in outcomes)
        print(f"{args.spec.name} (seeds 1-{args.jobs}), {os.cpu_count()} cores; {sims:,} simulations in all")
        print(f"{'':38s} {'wall s':>8s} {'jobs/min':>9s} {'load avg (1/5/15 min) before -> after':>40s}")
        print(f"{'one after another, one process':38s} {alone_s:8.1f} {60 * args.jobs / alone_s:9.1f} "
              f"{load_0:>19s} -> {load_1:<17s}")
        print(f"{f'together, {args.workers} workers (run_jobs)':38s} {together_s:8.1f} {60 * args.jobs / together_s:9.1f} "
              f"{load_2:>19s} -> {load_3:<17s}")
        if args.ceiling:
            print(f"{f'{args.workers} plain processes (no Dask)':38s} {plain_s:8.1f} {60 * args.jobs / plain_s:9.1f} "
                  f"{load_4:>19s} -> {load_5:<17s}")
        if args.service:
            print(f"{f'through abcns serve, {args.workers} workers':38s} {service_s:8.1f} {60 * args.jobs / service_s:9.1f} "
                  f"{load_6:>19s} -> {load_7:<17s}")
            print(f"through the service: ratio {alone_s / service_s:.2f}; the {args.jobs} submissions took {submit_s:.1f} s "
                  "of it (each spec's data inline, parsed apart); placements: "
                  + ", ".join(f"{n} {mode}" for mode, n in sorted(service_places.items())))
        ceiling = f" (plain processes: {alone_s / plain_s:.2f})" if args.ceiling else ""
        print(f"ratio (one after another / together): {alone_s / together_s:.2f}{ceiling}; the cluster's start "
              f"{cluster_s:.1f} s apart; placements: " + ", ".join(f"{n} {mode}" for mode, n in sorted(places.items())))
        print("results: every job bit-identical" if not differ
              else "results DIFFER: " + "; ".join(f"seed {s}: {d}" for s, d in differ.items()))
        if differ:
            raise SystemExit(1)
    finally:
        if args.keep is None:
            shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
