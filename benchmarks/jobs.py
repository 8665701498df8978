"""Many jobs at once against one after another: the paper §4.1 job
(examples/duffing_41/spec.yaml, to its noise floor) with seeds 1..N.

    python -m benchmarks.jobs [--jobs 16] [--workers 2] [--spec SPEC] [--keep DIR] [--ceiling] [--service]
                              [--sleepy MS] [--no-alone]

*one after another*: every job in this process as ``abcns run`` runs it, ``run_job(...,
client=None)`` (the in-process engine, a store each) then its summary (as every job of the
other paths makes it), the first one paying for loading the compiled kernels.
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
`dask worker` processes (all started, and readied by the service, before the clock), each
job's data inline in its JSON spec; the clock runs from the first submission to the last job's end, read from the jobs'
terminal events. Their stores are compared with the jobs run alone too.

*where the time goes* (printed for run_jobs and the service): the CPU seconds per job of the
caller's process (client, scheduler and nannies for run_jobs; for the service: `abcns serve`
and its children, the scheduler) and of the workers (each with its nanny), from ``psutil``;
and from the scheduler's task stream (``get_task_stream``: each job task's compute on its
worker), the workers' idle seconds before their first job, between one job's end and the
next one's start (the *gaps*: what dispatching costs), and after their last.

*sleepy jobs* (``--sleepy MS``): the jobs are ``benchmarks.scale``'s (the authors' demo, cubic
model, evidence variant, 10 populations) with the sleepy plugin (``MS`` ms a simulation),
run together only (``--no-alone`` implied: one after another they take jobs x ~14 s), and
the figure is the *utilization*: the jobs' simulations x ``MS`` over workers x wall.

*plain processes* (``--ceiling``): the same jobs on ``--workers`` plain processes of
``concurrent.futures`` (started and warmed before the clock, no Dask), a job at a time
each: what this machine gives at that many processes now, the ceiling of the ratio.
"""

from __future__ import annotations

import argparse
import itertools
import json
import multiprocessing
import os
import shutil
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import psutil
from distributed import Client, get_task_stream

from service.run.dask_executor import local_cluster
from service.run.jobs import JobRun, job_workers, run_jobs
from service.run.runner import run_job, summary
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


def _one(spec: JobSpec, base: Path | None, store: Path, seed: int) -> None:
    """One job as ``abcns run`` runs it in its own process: the run, then its summary (as a
    job on a worker makes it)."""
    result = run_job(spec, base, store, None, seed=seed)
    summary(Store.open(store), result)


def _warm() -> None:
    """A plain process's warm-up, as a worker's: the modules imported (the kernels load in
    the clock, as on the workers)."""


def plain_processes(spec: JobSpec, base: Path | None, folder: Path, seeds: range, n: int) -> dict:
    """The jobs on ``n`` plain processes (a job at a time each), started first: the wall
    seconds and the processes' CPU seconds."""
    with ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn")) as pool:
        for f in [pool.submit(_warm) for _ in range(4 * n)]:
            f.result()
        pids = [c.pid for c in psutil.Process().children()]
        cpu_0, start = cpu_seconds(pids), time.monotonic()
        for f in [pool.submit(_one, spec, base, folder / f"plain-{seed}.zarr", seed) for seed in seeds]:
            f.result()
        return {"wall": time.monotonic() - start, "cpu": cpu_seconds(pids) - cpu_0}


def cpu_seconds(pids: list[int]) -> float:
    """CPU seconds (user + system) of the processes ``pids`` and their children."""
    total = 0.0
    for pid in pids:
        try:
            proc = psutil.Process(pid)
            for q in [proc, *proc.children(recursive=True)]:
                t = q.cpu_times()  # with the children it has waited for (ended ones)
                total += t.user + t.system + t.children_user + t.children_system
        except psutil.NoSuchProcess:
            continue
    return total


def worker_idle(records: list[dict], start: float, end: float) -> dict[str, float]:
    """From task-stream records: the job tasks' (keys ``abcns-job-...``) compute spans per
    worker, and the workers' idle seconds (summed over workers) before their first job
    (after ``start``), between one job's end and the next one's start (``gaps``, with
    their count and median), and after their last (until ``end``)."""
    spans: dict[str, list[tuple[float, float]]] = {}
    for rec in records:
        if str(rec.get("key", "")).startswith("abcns-job"):
            for ss in rec.get("startstops", []):
                if ss.get("action") == "compute":
                    spans.setdefault(rec["worker"], []).append((ss["start"], ss["stop"]))
    gaps, before, after = [], 0.0, 0.0
    for runs in spans.values():
        runs.sort()
        before += max(0.0, runs[0][0] - start)
        after += max(0.0, end - runs[-1][1])
        # (each worker's times are put on the scheduler's clock by its estimated offset, which
        # moves between heartbeats on a loaded machine: a gap can come out negative, read as 0)
        gaps += [max(0.0, b[0] - a[1]) for a, b in itertools.pairwise(runs)]
    return {"before": before, "gaps": float(sum(gaps)), "n_gaps": len(gaps),
            "median_gap": float(np.median(gaps)) if gaps else 0.0, "after": after,
            "tasks": sum(len(r) for r in spans.values())}


def where_time_goes(label: str, jobs: int, workers: int, wall: float, cpu: dict[str, float], idle: dict) -> str:
    """The lines of CPU per job and the workers' idle time of one phase."""
    parts = ", ".join(f"{name} {1e3 * s / jobs:.0f}" for name, s in cpu.items())
    return (f"  {label}: CPU ms per job: {parts}; workers idle (of {workers} x {wall:.1f} s): before their first "
            f"job {idle['before']:.2f} s, between jobs {idle['gaps']:.2f} s ({idle['n_gaps']} gaps, median "
            f"{1e3 * idle['median_gap']:.0f} ms), after their last {idle['after']:.2f} s; {idle['tasks']} job tasks")


def together(args, jobs: list[JobRun]) -> dict:
    """The jobs through run_jobs on a LocalCluster: wall, outcomes, CPU and idle time."""
    start = time.monotonic()
    with local_cluster(args.workers) as cluster, Client(cluster) as client:
        client.wait_for_workers(args.workers, timeout=120)
        cluster_s = time.monotonic() - start
        load = load_average()
        kids = [c.pid for c in psutil.Process().children()]
        cpu_0 = (time.process_time(), cpu_seconds(kids))
        with get_task_stream(client) as stream:
            t0, start = time.time(), time.monotonic()
            outcomes = run_jobs(client, jobs, allow_import=args.sleepy is not None)
            wall = time.monotonic() - start
            t1 = time.time()
        cpu = {"caller (client, scheduler, nannies)": time.process_time() - cpu_0[0],
               "workers": cpu_seconds(kids) - cpu_0[1]}
        idle = worker_idle(stream.data, t0, t1)
    return {"wall": wall, "outcomes": outcomes, "cluster_s": cluster_s, "load": (load, load_average()),
            "cpu": cpu, "idle": idle}


def through_service(spec: JobSpec, base: Path, folder: Path, seeds: range, n: int) -> dict:
    """The jobs submitted at once to `abcns serve` on ``n`` stock workers: the seconds from
    the first submission to the last job's end, the seconds their submissions took, their
    stores by seed, their placements, the processes' CPU and the workers' idle time."""
    import httpx

    from benchmarks.harness import AUTH, Service, StockCluster, wait_until

    data = {key: load_array(getattr(spec.data, key), base, f"data.{key}").tolist() for key in ("input", "observed")}
    raw = spec.model_dump(mode="json")
    raw["data"].update(data)
    cluster = StockCluster(folder / "dask", n_workers=n)
    service = Service(folder / "service-jobs", cluster.address, max_running=None)
    groups = {"service": [service.proc.pid], "scheduler": [cluster.procs[0].pid],  # type: ignore[union-attr]
              "workers": [p.pid for p in cluster.procs[1:]]}
    try:
        with Client(cluster.address, timeout=30) as watcher, get_task_stream(watcher) as stream:
            # the service readies the cluster as it starts (service.run.jobs.prepare_cluster): the
            # job slots' plugin, whose unpickling imports the job's code on each worker (~2-3.5 s a
            # worker on a loaded machine), and that code imported on the scheduler, which unpickles
            # every task; the clock starts once it has, as for a service up a while (the kernels
            # load in the clock, as on run_jobs's workers)
            wait_until(lambda: len(job_workers(watcher)) == n and watcher.run_on_scheduler(
                lambda: "service.run.jobs" in sys.modules), 120, "the service to ready the cluster", 0.2)
            settled(watcher)
            cpu_0 = {name: cpu_seconds(pids) for name, pids in groups.items()}
            with httpx.Client(timeout=120, headers=AUTH) as http:
                # the intake's child (it parses every submission) started with the service and may
                # still be importing: a refused submission before the clock waits for it, as a
                # service up for a while would not
                http.post(f"{service.url}/jobs", json={})
                start = time.time()
                ids = {seed: http.post(f"{service.url}/jobs", json={**raw, "seed": seed, "name": f"seed-{seed}"}).json()["id"]
                       for seed in seeds}
                submitted = time.time() - start
                wait_ended(http, service.url)
            cpu = {name: cpu_seconds(pids) - cpu_0[name] for name, pids in groups.items()}
            records = stream.data
        last, places = service_ends(service, ids)
        return {"wall": last - start, "submit_s": submitted, "places": places, "cpu": cpu,
                "idle": worker_idle(records, start, last),
                "stores": {seed: service.job_dir(job_id) / "store.zarr" for seed, job_id in ids.items()}}
    finally:
        service.close()
        cluster.close()


def settled(client: Client, within_s: float = 0.05, timeout_s: float = 30.0) -> None:
    """Until each worker's estimate of its clock's offset from the scheduler's (what the
    task stream's times are shifted by) is within ``within_s`` of 0, its true value on
    one host. A worker's event loop held by an import (the job slots' plugin: ~2 s) biases
    the estimate made by the heartbeat it delayed (+0.7 s seen) until its next heartbeat: a
    first job's start would read that much late. Goes on after ``timeout_s``, saying so."""
    from benchmarks.harness import wait_until

    try:
        wait_until(lambda: all(abs(d) <= within_s for d in client.run(
            lambda dask_worker: dask_worker.scheduler_delay).values()), timeout_s, "the workers' clocks", 0.2)
    except TimeoutError:
        print(f"(the workers' clock offsets did not settle within {within_s} s: their idle times are off by as much)")


def wait_ended(http, url: str) -> None:
    """Until every job of the service has ended."""
    from benchmarks.harness import wait_until

    def ended() -> bool:
        return all(j["status"] in ("finished", "failed", "cancelled") for j in http.get(f"{url}/jobs").json())

    wait_until(ended, 3600, "every job to end", 2.0)  # the wall comes from the events: a slow poll, little CPU


def service_ends(service, ids: dict[int, str]) -> tuple[float, Counter]:
    """The last job's end (its terminal event's time) and the jobs' placements; exits when a
    job did not finish."""
    last, places = 0.0, Counter()
    for seed, job_id in ids.items():
        events = [json.loads(line) for line in (service.job_dir(job_id) / "events.jsonl").read_text().splitlines()]
        if events[-1]["event"] != "finished":
            raise SystemExit(f"seed {seed} ended {events[-1]['event']} through the service: {events[-1]['data']}")
        last = max(last, events[-1]["time"])
        placed = [e["data"]["placement"] for e in events if e["event"] == "placed"]
        places[placement_kind(placed[-1] if placed else None)] += 1
    return last, places


def placement_kind(placement: dict | None) -> str:
    """A job's final placement for the counts: its mode and why (the queue rule: ``whole
    (queue)``; ``spread (idle)``: placed whole by it, spread once a slot was free)."""
    if not placement:
        return "?"
    return f"{placement['mode']} ({placement['reason']})" if placement.get("reason") else placement["mode"]


def job_specs(args) -> tuple[JobSpec, Path | None]:
    """The jobs' spec: ``--spec``, or with ``--sleepy`` benchmarks.scale's sleepy job."""
    if args.sleepy is None:
        return load(args.spec)
    os.environ["ABCNS_SLEEPY_MS"] = f"{args.sleepy:g}"  # before benchmarks.scale (and sleepy) is imported
    from benchmarks.scale import sleepy_spec  # sets PYTHONPATH for the workers, which import the plugin

    return sleepy_spec(10, None, "evidence")


def alone(spec: JobSpec, base: Path | None, folder: Path, seeds: range) -> dict:
    load_0 = load_average()
    start, cpu_0, each = time.monotonic(), time.process_time(), []
    for seed in seeds:
        t = time.monotonic()
        _one(spec, base, folder / f"alone-{seed}.zarr", seed)
        each.append(time.monotonic() - t)
    return {"wall": time.monotonic() - start, "cpu": time.process_time() - cpu_0, "each": each,
            "load": (load_0, load_average())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", type=int, default=16)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--spec", type=Path, default=SPEC)
    parser.add_argument("--keep", type=Path, default=None, help="keep the stores in this folder")
    parser.add_argument("--ceiling", action="store_true", help="also the jobs on plain processes (no Dask)")
    parser.add_argument("--service", action="store_true", help="also the jobs through `abcns serve`")
    parser.add_argument("--sleepy", type=float, default=None, metavar="MS",
                        help="benchmarks.scale's sleepy job (MS ms a simulation) instead of --spec; together only")
    parser.add_argument("--no-alone", action="store_true", help="skip the jobs one after another (no ratio, no check)")
    args = parser.parse_args()
    if args.sleepy is not None and args.service:
        parser.error("--sleepy runs a plugin simulator, which the service never imports: not with --service")
    spec, base = job_specs(args)
    seeds = range(1, args.jobs + 1)
    folder = args.keep or Path(tempfile.mkdtemp(prefix="abcns-jobs-"))
    folder.mkdir(parents=True, exist_ok=True)
    skip_alone = args.no_alone or args.sleepy is not None
    try:
        one = None if skip_alone else alone(spec, base, folder, seeds)
        jobs = [JobRun.of(spec.model_copy(update={"seed": seed}), base, folder / f"together-{seed}.zarr", f"seed-{seed}")
                for seed in seeds]
        both = together(args, jobs)
        plain = None
        if args.ceiling:
            load = load_average()
            plain = {**plain_processes(spec, base, folder, seeds, args.workers), "load": (load, load_average())}
        served = None
        if args.service:
            load = load_average()
            served = through_service(spec, base, folder, seeds, args.workers)
            served["load"] = (load, load_average())
        report(args, folder, seeds, one, both, plain, served)
    finally:
        if args.keep is None:
            shutil.rmtree(folder, ignore_errors=True)


def report(args, folder: Path, seeds: range, one: dict | None, both: dict, plain: dict | None,
           served: dict | None) -> None:
    """Print the table, check the results against the jobs alone; exit 1 if one differs."""
    failed = [f"seed {s}: {o.status} {o.error}" for s, o in zip(seeds, both["outcomes"], strict=True)
              if o.status != "finished"]
    if failed:
        raise SystemExit("jobs failed together:\n" + "\n".join(failed))
    stores = {seed: folder / f"{'alone' if one else 'together'}-{seed}.zarr" for seed in seeds}
    sims = sum(Store.open(stores[seed]).run_state()["n_simulations_total"] for seed in seeds)
    name = f"sleepy {args.sleepy:g} ms (benchmarks.scale's job)" if args.sleepy is not None else args.spec.name
    print(f"{name} (seeds 1-{args.jobs}), {os.cpu_count()} cores; {sims:,} simulations in all")
    print(f"{'':38s} {'wall s':>8s} {'jobs/min':>9s} {'load avg (1/5/15 min) before -> after':>40s}")
    rows = [("one after another, one process", one), (f"together, {args.workers} workers (run_jobs)", both),
            (f"{args.workers} plain processes (no Dask)", plain), (f"through abcns serve, {args.workers} workers", served)]
    for label, r in rows:
        if r is not None:
            print(f"{label:38s} {r['wall']:8.1f} {60 * args.jobs / r['wall']:9.1f} {r['load'][0]:>19s} -> {r['load'][1]:<17s}")
    if one is not None:
        each = np.array(one["each"])
        print(f"one job alone: {each.mean():.2f} s on average ({each.min():.2f}-{each.max():.2f}), CPU ms per job "
              f"{1e3 * one['cpu'] / args.jobs:.0f}; each: " + " ".join(f"{x:.2f}" for x in each))
    if plain is not None:
        print(f"  plain processes: CPU ms per job {1e3 * plain['cpu'] / args.jobs:.0f}")
    print(where_time_goes("run_jobs", args.jobs, args.workers, both["wall"], both["cpu"], both["idle"]))
    if served is not None:
        print(where_time_goes("service", args.jobs, args.workers, served["wall"], served["cpu"], served["idle"]))
        print(f"through the service: the {args.jobs} submissions took {served['submit_s']:.1f} s of it (each spec's data "
              "inline, parsed apart); placements: " + ", ".join(f"{n} {m}" for m, n in sorted(served["places"].items())))
    places = Counter(placement_kind(o.placement) for o in both["outcomes"])
    print(f"run_jobs: the cluster's start {both['cluster_s']:.1f} s apart; placements: "
          + ", ".join(f"{n} {mode}" for mode, n in sorted(places.items())))
    if args.sleepy is not None:
        for label, r in rows[1:]:
            if r is not None:
                print(f"utilization, {label}: {sims * args.sleepy / 1e3 / (args.workers * r['wall']):.3f}")
    if one is None:
        print("results: not checked (no run alone)")
        return
    ratios = "; ".join(f"{label}: {one['wall'] / r['wall']:.2f}" for label, r in rows[1:] if r is not None)
    print(f"ratio (one after another / together): {ratios}")
    check(folder, seeds, plain is not None, served)


def check(folder: Path, seeds: range, plain: bool, served: dict | None) -> None:
    differ = {seed: d for seed in seeds
              if (d := same_populations(folder / f"alone-{seed}.zarr", folder / f"together-{seed}.zarr"))}
    if plain:
        differ |= {seed: f"plain: {d}" for seed in seeds
                   if (d := same_populations(folder / f"alone-{seed}.zarr", folder / f"plain-{seed}.zarr"))}
    if served is not None:
        differ |= {seed: f"service: {d}" for seed in seeds
                   if (d := same_populations(folder / f"alone-{seed}.zarr", served["stores"][seed]))}
    print("results: every job bit-identical" if not differ
          else "results DIFFER: " + "; ".join(f"seed {s}: {d}" for s, d in differ.items()))
    if differ:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
