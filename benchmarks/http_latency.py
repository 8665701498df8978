"""Status latency of the HTTP service while two jobs run.

Starts a stock `dask scheduler` with two `dask worker` processes and `abcns serve
--max-running 2` on 127.0.0.1 (``benchmarks.harness``, as the tests start them), submits
two §4.1 jobs, and times ``GET /jobs/{id}`` (alternating between the two) while they run;
prints p50, p99 and max, then stops everything.

    python -m benchmarks.http_latency [--requests 1000]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from benchmarks.harness import AUTH, Service, StockCluster, duffing_spec


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--requests", type=int, default=1000)
    args = parser.parse_args()
    tmp = Path(tempfile.mkdtemp())
    cluster = StockCluster(tmp / "dask")
    service = Service(tmp / "jobs", cluster.address, max_running=2)
    try:
        with httpx.Client(base_url=service.url, headers=AUTH, timeout=30) as http:
            ids = [http.post("/jobs", json=duffing_spec(max_populations=400, particles=1000)).json()["id"]
                   for _ in range(2)]
            while any(http.get(f"/jobs/{i}").json()["status"] != "running" for i in ids):
                time.sleep(0.1)
            times, running = [], 0
            for k in range(args.requests):
                t = time.perf_counter()
                r = http.get(f"/jobs/{ids[k % 2]}")
                times.append(time.perf_counter() - t)
                running += r.json()["status"] == "running"
            ms = np.array(times) * 1e3
            print(f"GET /jobs/{{id}}: {args.requests} requests, {running} answered while the job was running")
            print(f"p50 {np.percentile(ms, 50):.2f} ms   p99 {np.percentile(ms, 99):.2f} ms   max {ms.max():.2f} ms")
            for i in ids:
                http.delete(f"/jobs/{i}")
    finally:
        service.close()
        cluster.close()


if __name__ == "__main__":
    main()
