"""Status latency of the HTTP service while jobs run.

Starts a stock `dask scheduler` with ``--workers`` `dask worker` processes and `abcns serve
--max-running JOBS` on 127.0.0.1 (``benchmarks.harness``, as the tests start them), submits
``--jobs`` §4.1 jobs (each job's loop on a worker of its own: one job loop per worker
process), waits until every one runs, and times ``GET /jobs/{id}`` (in turn over the jobs)
while they run; prints p50, p99 and max, how many jobs ran at the first and the last
request, and the load average, then stops everything.

    python -m benchmarks.http_latency [--requests 1000] [--jobs 2] [--workers JOBS]

``--jobs 16`` is issue U's condition ("p99 < 100 ms while 16 jobs run"): 16 worker
processes, each running a job's loop, on however many cores the machine has. The jobs
run until cancelled (no noise floor, 400 populations at most), so every one is still
running when the last request is answered.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from benchmarks.harness import AUTH, Service, StockCluster, duffing_spec


def running(http: httpx.Client, ids: list[str]) -> int:
    """How many of ``ids`` the service lists as running."""
    jobs = {j["id"]: j["status"] for j in http.get("/jobs").json()}
    return sum(jobs.get(i) == "running" for i in ids)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--requests", type=int, default=1000)
    parser.add_argument("--jobs", type=int, default=2, help="jobs running while the status is asked")
    parser.add_argument("--workers", type=int, default=None, help="dask workers (default: one per job)")
    args = parser.parse_args()
    workers = args.workers or args.jobs
    tmp = Path(tempfile.mkdtemp())
    cluster = StockCluster(tmp / "dask", n_workers=workers)
    service = Service(tmp / "jobs", cluster.address, max_running=args.jobs)
    spec = duffing_spec(max_populations=400, particles=1000, noise_floor=args.jobs <= 2)
    try:
        with httpx.Client(base_url=service.url, headers=AUTH, timeout=30) as http:
            ids = [http.post("/jobs", json=spec).json()["id"] for _ in range(args.jobs)]
            while running(http, ids) < args.jobs:
                time.sleep(0.1)
            first, load = running(http, ids), os.getloadavg()[0]
            times, answered = [], 0
            for k in range(args.requests):
                t = time.perf_counter()
                r = http.get(f"/jobs/{ids[k % len(ids)]}")
                times.append(time.perf_counter() - t)
                answered += r.json()["status"] == "running"
            last = running(http, ids)
            ms = np.array(times) * 1e3
            print(f"GET /jobs/{{id}}: {args.requests} requests over {args.jobs} jobs on {workers} workers, "
                  f"{os.cpu_count()} cores; {answered} answered while the job was running; jobs running at the "
                  f"first / last request: {first} / {last}; load average {load:.1f} -> {os.getloadavg()[0]:.1f}")
            print(f"p50 {np.percentile(ms, 50):.2f} ms   p99 {np.percentile(ms, 99):.2f} ms   max {ms.max():.2f} ms")
            for i in ids:
                http.delete(f"/jobs/{i}")
    finally:
        service.close()
        cluster.close()


if __name__ == "__main__":
    main()
