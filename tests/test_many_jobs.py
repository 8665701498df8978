"""`abcns run SPEC... --out-dir DIR`: many jobs on one cluster (service/run/jobs.py), each
job's population loop on a worker, at most one per worker process; a result bit-identical
to the job's run alone in this process; a cheap job whole on one worker (no task per
batch); a failing job fails alone. One LocalCluster of 2 worker processes for the module,
reached by the CLI with --scheduler."""

from __future__ import annotations

import json
import os
import re
from itertools import pairwise
from pathlib import Path

import pytest
import yaml
from cli_in_process import invoke
from distributed import Client, get_task_stream
from test_distributed import assert_same_store
from typer.testing import Result

from service.run.dask_executor import local_cluster
from service.run.jobs import JobRun, place, placement_text, run_jobs, spread_next
from service.run.runner import run_job, summary
from service.run.store import Store
from service.spec import build, load

pytestmark = pytest.mark.distributed
ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "data" / "authors-demo" / "demo_data.npz"
POPULATIONS = 3


@pytest.fixture(scope="module")
def cluster():
    """2 single-threaded worker processes; a client of the test's own (the task stream)."""
    with local_cluster(2) as c, Client(c) as client:
        client.wait_for_workers(2, timeout=120)
        yield client


def write_spec(folder: Path, seed: int, name: str = "demo", simulator: str | None = None, particles: int = 200,
               populations: int = POPULATIONS) -> Path:
    """The authors' demo with the evidence variant, shortened: 200 particles, 3 populations."""
    raw = yaml.safe_load((ROOT / "examples" / "authors_demo" / "evidence.yaml").read_text())
    raw["data"].update(input=f"{DEMO}:force", observed=f"{DEMO}:displacement")
    raw["sampler"] = {"particles": particles}
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": populations}
    raw.update(name=name, seed=seed)
    if simulator is not None:
        for model in raw["models"]:
            model["simulator"] = simulator
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}-{seed}.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def alone(spec: Path, out: Path) -> Path:
    """The job run alone in this process (no cluster)."""
    job_spec, base = load(spec)
    run_job(job_spec, base, out, None)
    return out


def abcns_run(*args, code: int = 0, env: dict | None = None) -> Result:
    """`abcns run ARGS` in this process (tests/cli_in_process; tests.faulty_plugin importable here
    and on the module's in-process cluster); it must exit ``code``."""
    return invoke("run", *args, code=code, env=env)


def job_tasks(records: list[dict]) -> list[dict]:
    return [r for r in records if str(r["key"]).startswith("abcns-job-")]


def test_three_jobs_together_give_each_job_s_result_alone(cluster, tmp_path):
    """Three jobs of one name (stores demo, demo-2, demo-3) at once on 2 workers, each
    spread (the suite's ABCNS_LOCAL_POPULATION_S=0: every population on the cluster): the
    populations of each equal, bit for bit, its run alone in this process; a line per
    population of each job, prefixed with its store's name; never two jobs at once in one
    worker process."""
    specs = [write_spec(tmp_path / "specs", seed) for seed in (1, 2, 3)]
    with get_task_stream(cluster) as stream:
        done = abcns_run(*specs, "--out-dir", tmp_path / "out", "--scheduler", cluster.scheduler.address)
    stems = ["demo", "demo-2", "demo-3"]
    assert {p.name for p in (tmp_path / "out").iterdir()} == {f"{s}.zarr" for s in stems}
    for spec, stem in zip(specs, stems, strict=True):
        assert_same_store(alone(spec, tmp_path / f"alone-{stem}.zarr"), tmp_path / "out" / f"{stem}.zarr")
        store = Store.open(tmp_path / "out" / f"{stem}.zarr")
        assert store.attrs["status"] == "finished"
        assert store.attrs["run"]["placement"]["mode"] == "spread"
        pops = [line for line in done.stdout.splitlines() if line.startswith(f"[{stem}] population ")]
        assert len(pops) == POPULATIONS, done.stdout
    assert "3 jobs: 3 finished" in done.stdout
    # one job loop per worker process: the job tasks on one worker never overlap in time
    by_worker: dict[str, list[tuple[float, float]]] = {}
    for record in job_tasks(stream.data):
        compute = [s for s in record["startstops"] if s["action"] == "compute"]
        by_worker.setdefault(record["worker"], []).append((compute[0]["start"], compute[-1]["stop"]))
    assert sum(map(len, by_worker.values())) == 3
    for spans in by_worker.values():
        spans.sort()
        assert all(a[1] <= b[0] for a, b in pairwise(spans)), spans


def test_a_cheap_job_runs_whole_on_one_worker(cluster, tmp_path):
    """With the default rule (25 ms), the shortened demo (a population: ~200 simulations of
    a few microseconds) runs whole on its worker: the store and the summary say so, and the
    cluster ran one task for it, the job's (no batch, no data task); the same result as alone.
    Run again, the finished store is not run again."""
    spec = write_spec(tmp_path / "specs", 4, name="cheap")
    with get_task_stream(cluster) as stream:
        done = abcns_run(spec, "--out-dir", tmp_path / "out", "--scheduler", cluster.scheduler.address,
                         env={"ABCNS_LOCAL_POPULATION_S": "0.025"})
    out = tmp_path / "out" / "cheap.zarr"
    placement = Store.open(out).attrs["run"]["placement"]
    assert placement["mode"] == "whole" and placement["population_s"] <= placement["limit_s"] == 0.05, placement
    assert placement["worker"] in cluster.scheduler_info()["workers"]
    keys = [str(r["key"]) for r in stream.data]
    assert len(keys) == 1 and keys[0].startswith("abcns-job-"), keys
    assert stream.data[0]["worker"] == placement["worker"]
    assert "[cheap] whole on tcp://" in done.stdout
    s = json.loads(invoke("summary", out, "--json").stdout)
    assert s["placement"]["mode"] == "whole"
    assert_same_store(alone(spec, tmp_path / "alone.zarr"), out)
    # run again: the finished store is not run again (no pilot, no population), the same summary
    again = abcns_run(spec, "--out-dir", tmp_path / "out", "--scheduler", cluster.scheduler.address, "--json",
                      env={"ABCNS_LOCAL_POPULATION_S": "0.025"})
    (only,) = json.loads(again.stdout)
    assert only["outcome"] == "finished" and only["store"] == str(out)
    assert {k: v for k, v in only.items() if k not in ("spec", "store", "outcome", "error")} == s


def test_a_job_s_summary_is_made_from_its_run_s_result_without_reading_the_store_again(cluster, tmp_path):
    """At a job's end its task reads the whole result from the store once (run_job's end,
    every population and its bounds: most of a summary's time, ~5 % of a §4.1 job's) and
    makes the summary from it, not from a second read; that summary is the store's."""

    def count(on: bool) -> int:  # on a worker: count the whole-result reads of the runner's module
        from service.run import runner, store

        if on:
            runner.__dict__["reads"] = 0

            def counted(s):
                runner.__dict__["reads"] += 1
                return store.result_from_store(s)

            runner.result_from_store = counted
            return 0
        runner.result_from_store = store.result_from_store
        return runner.__dict__.pop("reads", 0)

    spec, base = load(write_spec(tmp_path / "specs", 5, name="once"))
    cluster.run(count, True)
    try:
        (outcome,) = run_jobs(cluster, [JobRun.of(spec, base, tmp_path / "once.zarr", "once")], local_s=0.025)
    finally:
        reads = sum(cluster.run(count, False).values())
    assert outcome.status == "finished" and outcome.placement["mode"] == "whole", outcome
    assert reads == 1  # before: 2 (the summary read the store's result again)
    assert outcome.summary == summary(Store.open(tmp_path / "once.zarr"))


def test_a_failing_job_fails_alone_naming_the_job(cluster, tmp_path):
    """A job whose simulator raises (tests/faulty_plugin.py, in its first batches) fails with a
    message naming it, its batch and the exception, exit code 4; the two others finish."""
    specs = [write_spec(tmp_path / "specs", 1, name="good"),
             write_spec(tmp_path / "specs", 2, name="faulty", simulator="tests.faulty_plugin:Faulty"),
             write_spec(tmp_path / "specs", 3, name="good")]
    done = abcns_run(*specs, "--out-dir", tmp_path / "out", "--scheduler", cluster.scheduler.address, "--quiet",
                     code=4)
    errors = [line for line in done.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, done.stderr[-3000:]
    # population 0: the prior-predictive pilot that sets the first tolerance (the spec gives none)
    assert re.match(r"error: job faulty: the job failed in population 0, batch \d+: model '(linear|cubic)' "
                    r"\(simulator 'tests\.faulty_plugin:Faulty'\): RuntimeError: a bug in the user's simulator; "
                    r"the populations before it are in \S+faulty\.zarr$", errors[0]), errors
    assert "Traceback" not in done.stderr
    assert "3 jobs: 2 finished, 1 failed" in done.stdout
    for stem in ("good", "good-2"):
        assert Store.open(tmp_path / "out" / f"{stem}.zarr").attrs["status"] == "finished"
    assert Store.open(tmp_path / "out" / "faulty.zarr").attrs["status"] == "failed"


def test_jobs_whose_workers_all_die_at_once_are_placed_again_and_end_as_alone(tmp_path):
    """Both worker processes SIGKILLed at once as the first population is announced: Dask
    cannot run the jobs' tasks again by itself (a new worker's job slot is declared after it
    joins, and a task that found no worker is not looked at again), so run_jobs requeues each
    job whose worker has been gone 5 s (WorkerWatch) and places it on a new worker's free
    slot; every job ends finished, equal to its run alone (before: the jobs waited forever)."""
    import signal

    from service.run.jobs import JobRun, run_jobs

    specs = []
    for seed in (5, 6):
        path = write_spec(tmp_path / "specs", seed, name=f"lost-{seed}")
        raw = yaml.safe_load(path.read_text())
        raw["stop"]["max_populations"] = 8  # still running when the kill lands
        path.write_text(yaml.safe_dump(raw))
        specs.append(path)
    jobs = [JobRun.of(*load(spec), tmp_path / "out" / f"{spec.stem}.zarr", spec.stem) for spec in specs]
    events: list[tuple[int, str]] = []
    with local_cluster(2) as c, Client(c) as client:
        client.wait_for_workers(2, timeout=120)
        pids = list(client.run(os.getpid).values())

        def on_event(i: int, event: dict) -> None:
            events.append((i, event["kind"]))
            if event["kind"] == "population" and pids:
                for pid in pids:
                    os.kill(pid, signal.SIGKILL)
                pids.clear()

        outcomes = run_jobs(client, jobs, on_event=on_event)
    assert [o.status for o in outcomes] == ["finished", "finished"], [(o.status, o.error) for o in outcomes]
    assert any(kind == "requeued" for _, kind in events), events
    for spec, job in zip(specs, jobs, strict=True):
        assert_same_store(alone(spec, tmp_path / f"alone-{spec.stem}.zarr"), job.store)


def test_out_and_out_dir_are_exclusive_and_several_specs_need_out_dir(tmp_path):
    from typer.testing import CliRunner

    from service.cli import app

    spec = str(write_spec(tmp_path, 1))
    both = CliRunner().invoke(app, ["run", spec, "--out", str(tmp_path / "a.zarr"), "--out-dir", str(tmp_path / "d")])
    assert both.exit_code == 2 and "error: give --out (one spec's store) or --out-dir (a store per spec), not both" \
        in both.output, both.output
    many = CliRunner().invoke(app, ["run", spec, spec, "--out", str(tmp_path / "a.zarr")])
    assert many.exit_code == 2 and "2 specs need --out-dir DIR" in many.output, many.output
    neither = CliRunner().invoke(app, ["run", spec])
    assert neither.exit_code == 2 and "give --out STORE for one spec, or --out-dir DIR" in neither.output, neither.output
    assert not (tmp_path / "a.zarr").exists() and not (tmp_path / "d").exists()


def test_store_names_are_distinct_and_stable():
    from service.run.jobs import store_names

    assert store_names(["a", "b", "a", "a b/c", "a", "a-2"]) == ["a", "b", "a-2", "a-b-c", "a-3", "a-2-2"]


#: what a population may cost to run whole, in the queue rule's tests: any population costs more
DEAR_S = 1e-7


def test_the_queue_rule_places_a_dear_job_whole_when_every_worker_thread_has_a_job(tmp_path):
    """:func:`place` with ``local_s`` 1e-7 s (the limit 2e-7 s: every population is dear):
    the job runs whole when the jobs running or waiting (this one too) and the job slots are
    each at least the worker threads (every thread runs a job anyway), and says so (reason
    ``queue``, the figures recorded, in words); it spreads when alone, when the jobs are
    fewer than the threads, on workers of several threads (2 slots never fill 16 threads)
    and without figures (as before); a cheap job runs whole, and ``local_s`` 0 keeps every
    population on the cluster, whatever the queue. Before: every dear job spread."""
    spec, base = load(write_spec(tmp_path, 1))
    job = build(spec, base, False)

    def placed(local_s: float, threads: int, jobs: int | None, slots: int | None) -> tuple[str, str]:
        p = place(job, local_s, threads, "tcp://w", jobs, slots)
        return p["mode"], p["reason"]

    assert placed(DEAR_S, 2, 3, 2) == placed(DEAR_S, 2, 2, 2) == ("whole", "queue")
    assert placed(DEAR_S, 2, 1, 2) == ("spread", "dear")  # a lone dear job still spreads
    assert placed(DEAR_S, 4, 3, 4) == ("spread", "dear")  # a thread would idle
    assert placed(DEAR_S, 16, 32, 2) == ("spread", "dear")  # 2 workers of 8 threads
    assert placed(DEAR_S, 2, None, None) == ("spread", "dear")
    assert placed(1e3, 2, 1, 2) == ("whole", "cheap")
    assert placed(0.0, 2, 3, 2) == ("spread", "on the cluster")
    p = place(job, DEAR_S, 2, "tcp://w", 3, 2)
    assert p["jobs"] == 3 and p["job_slots"] == 2 and p["worker_threads"] == 2 and p["population_s"] > p["limit_s"]
    assert placement_text(p).startswith("whole on tcp://w: a population ~")
    assert placement_text(p).endswith(" > 0.0002 ms, but 3 jobs for 2 worker threads: every thread has a job")


def test_the_tail_spreads_one_whole_job_per_free_slot_the_latest_started_first():
    """:func:`spread_next` (no job waits): of the jobs placed whole by the queue rule, the
    latest started spreads first, one per free job slot beyond the jobs already asked that
    still run; a job whole because it is cheap, or not placed yet, stays."""
    queue, cheap = {"mode": "whole", "reason": "queue"}, {"mode": "whole", "reason": "cheap"}
    running = [("a", queue), ("b", cheap), ("c", queue), ("d", None)]
    assert spread_next(running, set(), 1) == ["c"]
    assert spread_next(running, set(), 5) == ["c", "a"]
    assert spread_next(running, {"c"}, 1) == []  # the free slot's threads are c's batches'
    assert spread_next(running, {"c", "z"}, 2) == ["a"]  # z has ended: it holds no slot's threads
    assert spread_next(running, set(), 0) == []


def test_dear_jobs_run_whole_while_every_thread_has_one_and_the_last_spreads_when_a_slot_frees(cluster, tmp_path):
    """Two dear jobs (``local_s`` 1e-7 s) on 2 single-threaded workers through run_jobs:
    each is placed whole by the queue rule (2 jobs, 2 slots, 2 threads), where each spread
    before. When the short one (200 particles, 3 populations) ends, no job waits and a slot
    is free: the long one (2000 particles, 20 populations) is asked to spread (with 1000
    and 15, ~5x the short one's time, it once ended unasked: the suite in reverse, a fresh
    clone, 2026-12-05), stops its whole run at its next batch and resumes from its store spread (a second
    start event; the store's placement says so, with the populations it made whole). Both
    results equal, bit for bit, their runs alone in this process."""
    specs = [write_spec(tmp_path / "specs", 1, name="short"),
             write_spec(tmp_path / "specs", 2, name="long", particles=2000, populations=20)]
    starts: dict[int, list[dict]] = {0: [], 1: []}

    def on_event(i: int, event: dict) -> None:
        if event["kind"] == "start":
            starts[i].append(event["placement"])

    jobs = [JobRun.of(*load(spec), tmp_path / "out" / f"{spec.stem}.zarr", spec.stem) for spec in specs]
    outcomes = run_jobs(cluster, jobs, local_s=DEAR_S, on_event=on_event)
    assert [o.status for o in outcomes] == ["finished", "finished"], outcomes
    for first in (starts[0][0], starts[1][0]):
        assert (first["mode"], first["reason"], first["jobs"], first["job_slots"]) == ("whole", "queue", 2, 2), first
    assert len(starts[0]) == 1, starts[0]
    assert [(p["mode"], p["reason"]) for p in starts[1]] == [("whole", "queue"), ("spread", "idle")], starts[1]
    moved = Store.open(jobs[1].store).attrs["run"]["placement"]
    assert moved == starts[1][1] == outcomes[1].placement and 0 <= moved["whole_populations"] < 20, moved
    for spec, job in zip(specs, jobs, strict=True):
        assert_same_store(alone(spec, tmp_path / f"alone-{spec.stem}.zarr"), job.store)
