"""Dask's per-task costs on this machine, measured for the cluster model (``costs.py``).

    python -m benchmarks.cluster_model costs [--workers 1,2] [--rounds 40]

On a LocalCluster (scheduler in this process) and a stock ``dask scheduler`` (its own
process; its CPU read with psutil), W single-threaded workers with the project's Dask
settings, tasks that only sleep, submitted as the executor does (``client.map`` with
``fifo_timeout=0``, gathered with ``as_completed(with_results=True)``, released after):

- **main thread CPU** (``time.thread_time``) in ``client.map``, in the ``as_completed`` loop
  and in the releases, per call and per task: rounds of n = 1 and n = 16 tasks, the difference over 15;
- **event loops' CPU** per task (the process's CPU less the main thread's: the client's
  loop, and the scheduler for a LocalCluster), and a stock scheduler's own CPU per task;
- **the worker's overhead per task**: ``2 x rounds`` tasks of 20 ms all given to one worker
  (restricted to it, so never queued on the scheduler); wall per task less the 20 ms;
- **latencies**: one task at a time, from ``client.map`` to the task's start on the worker
  and from its end to its result in the main thread (``time.time()`` on both sides);
- **background**: the runner process's CPU per second while every worker runs one long task;
- **sleep overshoot**: ``time.sleep(0.05)`` less 50 ms, in a worker.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import tempfile
import time

import psutil
from distributed import Client, as_completed

from benchmarks.harness import BIN, ROOT, free_port, stop
from service.run.dask_executor import cluster_env, local_cluster

BACKGROUND_S = 10.0  # psutil reads CPU in 10 ms ticks: +-1 ms/s


def _nap(seconds: float) -> tuple[float, float]:
    start = time.time()
    time.sleep(seconds)
    return start, time.time()


def _overshoot(n: int) -> float:
    total = 0.0
    for _ in range(n):
        t = time.perf_counter()
        time.sleep(0.05)
        total += time.perf_counter() - t - 0.05
    return total / n


def _cpu(pid: int) -> float:
    t = psutil.Process(pid).cpu_times()
    return t.user + t.system


def _rounds(client: Client, n: int, rounds: int, seconds: float, sched_pid: int | None, tag: str) -> dict[str, float]:
    """Per round: main-thread CPU, the rest of this process's CPU, the scheduler's (stock)."""
    me = os.getpid()
    submit = wait = release = loop = sched = 0.0
    for r in range(rounds):
        m0, p0, s0 = time.thread_time(), _cpu(me), _cpu(sched_pid) if sched_pid else 0.0
        futures = client.map(_nap, [seconds] * n, key=[(f"cost-{tag}", n, r, i) for i in range(n)], pure=False,
                             fifo_timeout=0)
        m1 = time.thread_time()
        for _ in as_completed(futures, with_results=True):
            pass
        m2 = time.thread_time()
        for f in futures:
            f.release()
        m3 = time.thread_time()
        del futures
        time.sleep(0.02)  # let the release reach the scheduler
        p1, s1 = _cpu(me), _cpu(sched_pid) if sched_pid else 0.0
        submit, wait, release = submit + m1 - m0, wait + m2 - m1, release + m3 - m2
        loop += (p1 - p0) - (m3 - m0)  # the process less the main thread: the event loops
        sched += s1 - s0
    return {"submit": submit / rounds, "wait": wait / rounds, "release": release / rounds, "loop": loop / rounds,
            "sched": sched / rounds}


def measure(client: Client, sched_pid: int | None, rounds: int) -> dict[str, float]:
    n_workers = len(client.nthreads())
    client.run(_overshoot, 2)  # imports, connections
    for n in (1, 16):
        _rounds(client, n, 3, 0.0, sched_pid, "warm")
    one = _rounds(client, 1, rounds, 0.0, sched_pid, "one")
    many = _rounds(client, 16, rounds, 0.0, sched_pid, "many")
    out = {f"{k}_task": (many[k] - one[k]) / 15 for k in one}
    out.update({f"{k}_call": one[k] - out[f"{k}_task"] for k in one})
    # latencies, one task at a time
    to_start, to_main = [], []
    for r in range(rounds):
        t0 = time.time()
        (f,) = client.map(_nap, [0.01], key=[("cost-latency", r)], pure=False, fifo_timeout=0)
        start, end = f.result()
        t1 = time.time()
        to_start.append(start - t0)
        to_main.append(t1 - end)
        f.release()
    out["to_start"], out["to_main"] = statistics.median(to_start), statistics.median(to_main)
    # the worker's overhead: the first worker kept fed with 20 ms tasks (the others get none)
    first = sorted(client.nthreads())[0]
    n = 2 * rounds
    t0 = time.perf_counter()
    futures = client.map(_nap, [0.02] * n, key=[("cost-worker", i) for i in range(n)], pure=False, fifo_timeout=0,
                         workers=[first], allow_other_workers=False)
    for _ in as_completed(futures):
        pass
    out["worker_task"] = (time.perf_counter() - t0) / n - 0.02
    del futures
    # background: the runner's process (and a stock scheduler) while nothing runs
    p0, s0 = _cpu(os.getpid()), _cpu(sched_pid) if sched_pid else 0.0
    time.sleep(3.0)
    out["background"] = (_cpu(os.getpid()) - p0) / 3.0
    out["sched_background"] = ((_cpu(sched_pid) - s0) / 3.0) if sched_pid else 0.0
    out["overshoot"] = statistics.median(client.run(_overshoot, 20).values())
    out["workers"] = n_workers
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workers", default="1,2")
    parser.add_argument("--rounds", type=int, default=40)
    args = parser.parse_args(argv)
    print(f"# Dask per-task costs, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; seconds (ms shown)")
    keys = ["submit_call", "submit_task", "wait_call", "wait_task", "release_call", "release_task", "loop_call",
            "loop_task", "sched_call", "sched_task", "to_start", "to_main",
            "worker_task", "background", "sched_background", "overshoot"]
    print("| cluster | workers | " + " | ".join(keys) + " |")
    print("|---|---:|" + "---:|" * len(keys))
    for w in [int(x) for x in args.workers.split(",")]:
        with local_cluster(w) as cluster, Client(cluster) as client:
            client.wait_for_workers(w)
            r = measure(client, None, args.rounds)
        print(f"| LocalCluster | {w} | " + " | ".join(f"{1e3 * r[k]:.3f}" for k in keys) + " |", flush=True)
        with tempfile.TemporaryDirectory() as tmp:
            port = free_port()
            quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "start_new_session": True,
                     "cwd": ROOT, "env": {**os.environ, **cluster_env(), "PYTHONPATH": str(ROOT)}}
            procs = [subprocess.Popen([BIN / "dask", "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                       "--dashboard-address", ":0"], **quiet)]
            try:
                procs.append(subprocess.Popen([BIN / "dask", "worker", f"tcp://127.0.0.1:{port}", "--nworkers", str(w),
                                               "--nthreads", "1", "--no-dashboard", "--local-directory", tmp], **quiet))
                with Client(f"tcp://127.0.0.1:{port}", timeout=60) as client:
                    client.wait_for_workers(w, timeout=120)
                    r = measure(client, procs[0].pid, args.rounds)
            finally:
                stop(procs, timeout=30)
        print(f"| stock scheduler | {w} | " + " | ".join(f"{1e3 * r[k]:.3f}" for k in keys) + " |", flush=True)


if __name__ == "__main__":
    main()
