"""Issue U in the service: `abcns serve` runs each job's population loop as a Dask task on a
worker of its own (never in the service's interpreter), as many jobs at once as the cluster
has workers by default, and says where each runs; a job whose loop's worker is SIGKILLed
resumes from its store on another and ends bit-identical. Real processes: a stock `dask
scheduler` with two `dask worker`s, `abcns serve` under uvicorn."""

from __future__ import annotations

import json
import os
import signal
import sys
from pathlib import Path

import httpx
import pytest
from distributed import Client
from http_helpers import follow, same_populations

from benchmarks.harness import AUTH, Service, StockCluster, duffing_spec, probe_client, wait_until
from service.report.analysis import run_to_store
from service.run.jobs import PLUGIN_NAME, job_workers
from service.spec import parse

pytestmark = [pytest.mark.http, pytest.mark.distributed]


def submit(service: Service, seed: int, populations: int = 8, particles: int = 500, floor: bool = True) -> str:
    spec = {**duffing_spec(max_populations=populations, particles=particles, noise_floor=floor), "seed": seed,
            "name": f"u-{seed}"}
    r = httpx.post(f"{service.url}/jobs", json=spec, headers=AUTH, timeout=60)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def identical_to_a_run_alone(service: Service, job_id: str, tmp: Path) -> None:
    """The job's store equals its stored spec run alone in one process (what `abcns run`
    gives: service.report.analysis.run_to_store, tied to it by the determinism tests)."""
    folder = service.job_dir(job_id)
    run_to_store(parse(json.loads((folder / "spec.json").read_text())), folder, tmp / f"alone-{job_id}.zarr")
    same_populations(folder / "store.zarr", tmp / f"alone-{job_id}.zarr")


@pytest.fixture
def two_workers(tmp_path):
    cluster = StockCluster(tmp_path / "dask", n_workers=2)
    yield cluster
    cluster.close()


def test_two_jobs_run_at_once_each_on_a_worker_of_its_own_and_equal_runs_alone(two_workers, tmp_path):
    """With no --max-running, two jobs submitted together both run (the old default ran one
    at a time in the service's interpreter): /health lists both, on two different workers of
    the cluster, and GET /jobs/{id} gives each its placement; each ends bit-identical to its
    spec run alone. The jobs are long enough (30 populations spread over the cluster, ~3 s
    each here) that the first is still running when the second is placed."""
    service = Service(tmp_path / "jobs", two_workers.address, max_running=None)
    try:
        ids = [submit(service, seed, populations=30) for seed in (1, 2)]
        seen: dict[str, str] = {}
        with probe_client(timeout=10) as http:
            def both_running() -> bool:  # in one answer: at the same moment
                now = http.get(f"{service.url}/health").json()["running_on"]
                seen.update(now)
                return set(ids) <= set(now)

            wait_until(both_running, 120, "both jobs to run at once")
            with Client(two_workers.address, timeout=30) as client:
                workers = set(client.nthreads())
            assert seen[ids[0]] != seen[ids[1]] and {seen[i] for i in ids} <= workers, (seen, workers)
            for job_id in ids:
                info = http.get(f"{service.url}/jobs/{job_id}", headers=AUTH).json()
                # (it may have ended since, or its placement not yet be known: /health lists a
                # job on its worker before the worker's placement message arrives)
                if info["status"] == "running" and info["placement"] is not None:
                    assert info["placement"]["worker"] == seen[job_id], info
        for job_id in ids:
            events = follow(service.url, job_id)
            assert events[-1]["event"] == "finished", events[-3:]
            placed = [e["data"]["placement"] for e in events if e["event"] == "placed"]
            assert placed and placed[0]["worker"] == seen[job_id] and placed[0]["mode"] in ("whole", "spread")
        # the workers' share of time on the jobs' simulations over the last minute
        assert 0 < httpx.get(f"{service.url}/health", timeout=10).json()["utilization"] <= 1
        for job_id in ids:
            identical_to_a_run_alone(service, job_id, tmp_path)
    finally:
        service.close()


def test_a_job_whose_loop_worker_is_killed_resumes_elsewhere_identical(two_workers, tmp_path):
    """SIGKILL of the worker process that runs a job's loop, after its second population:
    Dask runs the job's task again on the other worker, which resumes the store; the job
    ends bit-identical to its spec run alone, every population announced once, in order,
    and a second `placed` event names the new worker."""
    service = Service(tmp_path / "jobs", two_workers.address, max_running=None)
    try:
        job_id = submit(service, seed=3, populations=40, particles=1000)  # ~6 s here: killed early in it
        first = follow(service.url, job_id, until=lambda ev: sum(e["event"] == "population" for e in ev) >= 2)
        worker = next(e["data"]["placement"]["worker"] for e in first if e["event"] == "placed")
        with Client(two_workers.address, timeout=30) as client:
            pid = client.run(os.getpid, workers=[worker])[worker]
        os.kill(pid, signal.SIGKILL)
        events = first + follow(service.url, job_id, after=first[-1]["id"])
        assert [e["id"] for e in events] == list(range(1, len(events) + 1))
        assert events[-1]["event"] == "finished", events[-3:]
        assert [e["data"]["population"] for e in events if e["event"] == "population"] == list(range(1, 41))
        placed = [e["data"]["placement"]["worker"] for e in events if e["event"] == "placed"]
        assert len(placed) >= 2 and placed[-1] != worker, placed
        identical_to_a_run_alone(service, job_id, tmp_path)
    finally:
        service.close()


def test_a_short_job_does_not_wait_for_a_long_one_and_the_long_one_resumes_identical(tmp_path):
    """Turns: on one worker, a long job (200 populations, no noise-floor stop: several
    seconds on any machine; 60, 1.3 s of CPU, finished before the short one once on a quiet
    machine) and a short one (3) submitted right after it. The long job's
    turn (ABCNS_TURN_S=1 here) ends after a population: it is requeued (a `requeued` event),
    the short job runs and finishes before the long one, and the long one resumes from its
    store and ends bit-identical to its spec run alone (before: the short job waited for the
    long one's end)."""
    cluster = StockCluster(tmp_path / "dask", n_workers=1)
    service = Service(tmp_path / "jobs", cluster.address, max_running=None, env={"ABCNS_TURN_S": "1"})
    try:
        long_id = submit(service, seed=4, populations=200, floor=False)
        short_id = submit(service, seed=5, populations=3)
        short, long_ = follow(service.url, short_id), follow(service.url, long_id)
        assert short[-1]["event"] == "finished" and long_[-1]["event"] == "finished", (short[-2:], long_[-2:])
        ended = {i: json.loads((service.job_dir(i) / "events.jsonl").read_text().splitlines()[-1])["time"]
                 for i in (short_id, long_id)}
        assert ended[short_id] < ended[long_id], "the short job waited for the long one"
        assert any(e["event"] == "requeued" and "turn" in e["data"]["reason"] for e in long_), \
            [e["event"] for e in long_]
        announced = [e["data"]["population"] for e in long_ if e["event"] == "population"]
        assert announced == list(range(1, len(announced) + 1)) and len(announced) >= 10, announced
        identical_to_a_run_alone(service, long_id, tmp_path)
        identical_to_a_run_alone(service, short_id, tmp_path)
    finally:
        service.close()
        cluster.close()


def test_the_service_readies_a_fresh_cluster_for_jobs_before_any_is_submitted(private_cluster, tmp_path):
    """`abcns serve` started on a fresh stock cluster, no job submitted: the job slots'
    plugin is on the scheduler, both workers declare their slot, and the job task's module
    is imported on the scheduler, which unpickles every task it is sent (on a fresh
    scheduler that import held its event loop 0.6-2 s at the first job's submission, the
    workers idle meanwhile: issue U's 2.0 s before the first jobs). Before, all of it
    waited for the first job's dispatch, and this waited in vain. No time is measured: the
    wait is for the state, however long the machine takes."""
    service = Service(tmp_path / "jobs", private_cluster.address, max_running=None)
    try:
        with Client(private_cluster.address, timeout=30) as client:
            def ready() -> bool:
                plugins = client.run_on_scheduler(lambda dask_scheduler: sorted(dask_scheduler.worker_plugins))
                imported = client.run_on_scheduler(lambda: "service.run.jobs" in sys.modules)
                return PLUGIN_NAME in plugins and imported and len(job_workers(client)) == 2

            wait_until(ready, 60, "the cluster to be ready for jobs", 0.2)
        assert not list(service.store_dir.iterdir()), "a job was submitted"
    finally:
        service.close()


def test_the_service_runs_a_dear_job_whole_while_jobs_fill_the_workers_and_spreads_it_when_a_slot_frees(
        cluster, tmp_path):
    """The queue rule in the service (ABCNS_LOCAL_POPULATION_S=1e-7 s: every population is
    dear), on the shared cluster's 2 single-threaded workers, no --max-running: jobs a (4
    populations of 2,000 particles), b (10 of 2,000) and c (100 of 4,000), submitted at once. c starts only
    when a slot frees, while another job runs: 2 jobs for 2 slots and 2 threads, so c runs whole
    (reason queue; before: spread). When that job ends, no job waits and its slot is free: c is
    asked to spread, and says so in a second `placed` event (reason idle). Every job ends
    bit-identical to its spec run alone. c is long enough to outlast the dispatcher's next look
    after the other job's end (within 1 s) whichever way a was placed: a may be placed when it
    alone has reached the service (`jobs` 1: spread, 3.2 s for its 4 populations), then b
    whole (queue), c on b's slot, and c must outlast a by the look: c of 40 populations of
    2,000 ended 0.13 s before a (a fresh clone, 2026-12-05), of 100 of 2,000 0.37 s after it,
    unasked (a submitted and placed before b and c, 2 runs of 2), of 100 of 4,000 asked
    ~0.2 s after a's end and ran ~4 s more (2 of 2); c of 16 of 500 ended first 1 run in 7;
    and a outlasts the three submissions: a of 2 populations of 500 sometimes ended before c
    came, so b spread and c was placed spread."""
    service = Service(tmp_path / "jobs", cluster.address, max_running=None, env={"ABCNS_LOCAL_POPULATION_S": "1e-7"})
    try:
        ids = [submit(service, seed, populations=n, particles=k, floor=False)
               for seed, n, k in ((6, 4, 2000), (7, 10, 2000), (8, 100, 4000))]
        events = {job_id: follow(service.url, job_id) for job_id in ids}
        for job_id in ids:
            assert events[job_id][-1]["event"] == "finished", events[job_id][-3:]
        placed = [e["data"]["placement"] for e in events[ids[2]] if e["event"] == "placed"]
        assert [(p["mode"], p["reason"]) for p in placed] == [("whole", "queue"), ("spread", "idle")], placed
        assert (placed[0]["jobs"], placed[0]["job_slots"], placed[0]["worker_threads"]) == (2, 2, 2), placed[0]
        for job_id in ids:
            identical_to_a_run_alone(service, job_id, tmp_path)
    finally:
        service.close()
