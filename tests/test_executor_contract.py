"""The executor contract (abcns.executor.Executor), one suite for every executor: the serial
one in this process and the Dask one over real worker processes.

- ``map(draws)`` yields one Simulated per draw, in submission order, bit-identical to
  running each draw here (proposals drawn where it runs, theta only for the kept rows);
- it pulls draws lazily: a consumer that stops early leaves the rest of an endless
  stream undrawn, and closing the map cancels the surplus;
- a draw whose proposals cannot be drawn (a bound outside the prior box) comes back with
  its stop reason, in its place;
- an unexpected exception in a simulator surfaces as a BatchError naming the batch;
- a whole run through either executor gives the same populations.

The batches are the authors' demo problem's (tests' seed 3)."""

from __future__ import annotations

import itertools
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from distributed import Client, as_completed

import abcns
from abcns import ellipsoid as ell
from abcns.bounds import Frame
from abcns.executor import BatchError, Draw, SerialExecutor, run_draw
from abcns.filling import draws
from abcns.nested import BoundProposer
from abcns.rejection import prior_proposer
from abcns.settings import StopReason
from benchmarks.harness import wait_until
from service.run import dask_executor
from service.run.dask_executor import DaskExecutor, local_cluster
from service.spec import build, description, parse

pytestmark = pytest.mark.distributed
ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "data" / "authors-demo" / "demo_data.npz"


@pytest.fixture(scope="module")
def job():
    raw = yaml.safe_load((ROOT / "examples" / "authors_demo" / "spec.yaml").read_text())
    raw["data"].update(input=f"{DEMO}:force", observed=f"{DEMO}:displacement")
    raw["sampler"].update(particles=200, batch_size=50)
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": 4}
    spec = parse(raw)
    return spec, build(spec, ROOT)


@pytest.fixture(scope="module")
def client():
    with local_cluster(2) as cluster, \
            Client(cluster) as c:
        yield c


def test_the_embedded_cluster_asks_for_no_fixed_port(client):
    """Q.1: the embedded cluster's scheduler and its HTTP server (started even without a
    dashboard) are on free ports: Dask's default 8787 is often a user's own dashboard, and
    asking for it failed every test here ("Port 8787 is already in use", a warning made an
    error) and warned on every `abcns run` beside a Dask user's cluster."""
    scheduler = client.cluster.scheduler
    assert scheduler.http_server.port != 8787 and scheduler.port != 8786
    assert scheduler.http_server.address == "127.0.0.1"  # no dashboard asked: not served to the network


@pytest.fixture(params=["serial", "dask", "dask-here"])
def make_executor(request, job, client):
    """Each executor: the serial one, the Dask one, and the Dask one with every population
    cheap enough to be evaluated in this process (``dask-here``: a batch's cost as if
    measured, and the job's evaluator given)."""
    spec, built = job

    def make(evaluate=None):
        if request.param == "serial":
            return SerialExecutor(evaluate or built.evaluate)
        arrays = {"force": built.force, "observed": built.observed}
        if request.param == "dask":
            return DaskExecutor(client, f"contract-{request.param}", description(spec), arrays)
        executor = DaskExecutor(client, f"contract-{request.param}", description(spec), arrays,
                                evaluate=evaluate or built.evaluate, local_s=dask_executor.LOCAL_POPULATION_S)
        executor.batch_seconds, executor.expected = 1e-6, 1
        return executor

    make.kind = request.param  # type: ignore[attr-defined]
    return make


def stream(models, seed: int = 3, epsilon: float = np.inf):
    """An endless stream of prior draws (population 1)."""
    return draws(prior_proposer(models), seed=seed, t=1, epsilon=epsilon, batch_size=50)


@pytest.mark.parametrize("epsilon", [np.inf, 30.0])
def test_results_come_in_submission_order_and_equal_running_here(make_executor, job, epsilon):
    _, built = job
    wanted = list(itertools.islice(stream(built.models, epsilon=epsilon), 12))
    executor = make_executor()
    got = list(itertools.islice(executor.map(iter(wanted)), 12))
    assert len(got) == 12
    n_kept = 0
    for draw, result in zip(wanted, got):
        direct = run_draw(built.evaluate, draw)
        batch = draw.batch()  # the proposals, drawn here: the worker drew the same
        np.testing.assert_array_equal(result.models, batch.models)
        np.testing.assert_array_equal(result.redraws, batch.redraws)
        for name in ("models", "distances", "status", "redraws", "theta"):
            np.testing.assert_array_equal(getattr(result, name), getattr(direct, name), err_msg=name)
        kept = result.kept(draw.epsilon, draw.keep_all)
        np.testing.assert_array_equal(result.theta, batch.theta[kept])  # theta of the kept rows only
        n_kept += int(kept.sum())
    assert 0 < n_kept < 12 * 50 if np.isfinite(epsilon) else n_kept == 12 * 50 - sum(
        int(np.count_nonzero(r.status != 0)) for r in got)
    getattr(executor, "close", lambda: None)()


def test_a_draw_that_cannot_be_drawn_returns_its_stop_reason_in_place(make_executor, job):
    """A bound far outside the prior box: the proposals run out of redraws on the worker."""
    _, built = job
    models = tuple(built.models)
    frames = tuple(Frame(m, unit=True) for m in models)
    outside = tuple((ell.from_box(np.full(m.n_dim, 5.0), np.full(m.n_dim, 6.0)),) for m in models)
    exhausted = BoundProposer(models, frames, outside, None, max_redraws=1)
    good = list(itertools.islice(stream(built.models), 2))
    bad = Draw(1, 3, 50, np.inf, 3, exhausted)
    executor = make_executor()
    got = list(executor.map(iter([*good, bad])))
    assert [r.stop for r in got] == [None, None, StopReason.PROPOSAL_EXHAUSTED]
    assert len(got[0]) == 50 and len(got[2]) == 0
    getattr(executor, "close", lambda: None)()


def test_batches_are_pulled_lazily_and_surplus_is_dropped_on_close(make_executor, job):
    _, built = job
    drawn = [0]

    def counted():
        for draw in stream(built.models):
            drawn[0] += 1
            yield draw

    executor = make_executor()
    results = executor.map(counted())
    first = [next(results) for _ in range(3)]
    results.close()  # the consumer stops: pending work is cancelled
    assert len(first) == 3 and drawn[0] < 100  # an endless stream was not drained
    again = list(itertools.islice(executor.map(counted()), 2))  # the executor still serves a new map
    assert len(again) == 2
    getattr(executor, "close", lambda: None)()


def test_a_simulator_bug_names_the_batch(make_executor, job):
    if make_executor.kind == "dask":  # the Dask executor runs registry simulators only: a plugin bug is
        pytest.skip("covered by tests/test_cli.py::test_a_bug_in_a_simulator_names_the_batch_and_the_exception")

    def broken(batch):
        raise KeyError("boom")

    _, built = job
    with pytest.raises(BatchError, match=r"population 1, batch \d+: KeyError"):
        next(make_executor(broken).map(stream(built.models)))


def test_a_run_through_either_executor_gives_the_same_populations(make_executor, job):
    _, built = job
    executor = make_executor()
    result = abcns.run(built.models, executor, built.settings, built.stop, built.seed)
    getattr(executor, "close", lambda: None)()
    reference = abcns.run(built.models, built.evaluate, built.settings, built.stop, built.seed)
    assert len(result.populations) == len(reference.populations) == 4
    for p, q in zip(result.populations, reference.populations):
        for name in ("models", "theta", "distances", "weights"):
            np.testing.assert_array_equal(getattr(p, name), getattr(q, name), err_msg=f"{p.t} {name}")


def cheap_batches(monkeypatch) -> None:
    """Every batch measured at 0.1 ms (a worker's first batch, which loads the kernels, or a
    busy machine would make a measured cost of this job's populations vary, and with it
    where they run)."""
    measured = DaskExecutor._measured
    monkeypatch.setattr(DaskExecutor, "_measured",
                        lambda ex, seconds, size, on_worker=True: measured(ex, 1e-4 * size, size, on_worker))


def test_cheap_populations_are_evaluated_here_and_the_run_is_the_same(job, client, monkeypatch):
    """Issue O.4, cheap kernels never lose to no cluster: a population whose simulations
    the cluster would shorten by less than Dask's round trips cost is evaluated in the
    runner's process. Population 1 goes to the cluster (nothing is measured yet), the
    later ones (batches measured at 0.1 ms: :func:`cheap_batches`) are evaluated here, no
    task of theirs reaches the cluster, and the run equals the serial one bit for bit."""
    spec, built = job
    decided: list[bool] = []
    here = dask_executor.Stream.here

    def recorded(stream):
        first = stream.local is None
        out = here(stream)
        if first:
            decided.append(out)
        return out

    monkeypatch.setattr(dask_executor.Stream, "here", recorded)
    cheap_batches(monkeypatch)
    submitted: set[int] = set()  # the populations of the batch tasks sent to the cluster
    client_map = client.map

    def recorded_map(*args, key=None, **kwargs):
        submitted.update(k[1] for k in key or () if isinstance(k, tuple) and len(k) == 4)
        return client_map(*args, key=key, **kwargs)

    monkeypatch.setattr(client, "map", recorded_map)
    arrays = {"force": built.force, "observed": built.observed}
    executor = DaskExecutor(client, "contract-mixed", description(spec), arrays, evaluate=built.evaluate,
                            local_s=dask_executor.LOCAL_POPULATION_S)
    try:
        result = abcns.run(built.models, executor, built.settings, built.stop, built.seed)
    finally:
        executor.close()
    reference = abcns.run(built.models, built.evaluate, built.settings, built.stop, built.seed)
    assert decided[0] is False and all(decided[1:]) and len(decided) == len(reference.populations) == 4, decided
    assert submitted == {0, 1}  # the anchors and population 1's batches only
    for p, q in zip(result.populations, reference.populations):
        for name in ("models", "theta", "distances", "weights"):
            np.testing.assert_array_equal(getattr(p, name), getattr(q, name), err_msg=f"{p.t} {name}")


def test_no_population_is_evaluated_here_while_other_runs_share_the_process(job, client):
    """``alone`` (the runner's count of runs in its process) is asked as each population
    opens: with another run beside it, a cheap population goes to the cluster."""
    spec, built = job
    others = [False]
    executor = DaskExecutor(client, "contract-crowd", description(spec), {"force": built.force, "observed": built.observed},
                            evaluate=built.evaluate, local_s=dask_executor.LOCAL_POPULATION_S, alone=lambda: not others[0])
    executor.batch_seconds, executor.expected = 1e-6, 1
    try:
        alone = executor.map(stream(built.models))
        assert alone.here()
        alone.close()
        others[0] = True
        crowded = executor.map(stream(built.models))
        assert not crowded.here()
        next(crowded)  # from the cluster
        crowded.close()
    finally:
        executor.close()


def test_the_runner_evaluates_cheap_populations_here_by_default(job, client, monkeypatch, tmp_path):
    """``run_job`` gives its executor the job's evaluator and ``ABCNS_LOCAL_POPULATION_S``
    (default ``LOCAL_POPULATION_S``; the suite sets 0, see conftest.py): with the default,
    this cheap job's later populations are evaluated in the runner, and its store holds what
    a run in this process stores."""
    from service.run.runner import run_job
    from service.run.store import Store

    spec, _ = job
    decided: list[bool] = []
    here = dask_executor.Stream.here
    monkeypatch.setattr(dask_executor.Stream, "here",
                        lambda stream: decided.append(here(stream)) or decided[-1])
    cheap_batches(monkeypatch)
    monkeypatch.delenv("ABCNS_LOCAL_POPULATION_S", raising=False)
    on_cluster = run_job(spec, ROOT, tmp_path / "cluster.zarr", client)
    assert True in decided
    monkeypatch.setenv("ABCNS_LOCAL_POPULATION_S", "0")
    decided.clear()
    run_job(spec, ROOT, tmp_path / "cluster-only.zarr", client)
    assert decided and True not in decided  # 0: every population on the cluster
    here_only = run_job(spec, ROOT, tmp_path / "serial.zarr", None)
    assert len(on_cluster.populations) == len(here_only.populations) == 4
    for p, q in zip(Store.open(tmp_path / "cluster.zarr").populations(), here_only.populations):
        for name in ("models", "theta", "distances", "weights"):
            np.testing.assert_array_equal(getattr(p, name), getattr(q, name), err_msg=f"{p.t} {name}")


def test_dask_queues_a_run_s_batches_on_the_scheduler_oldest_first(job, client, monkeypatch):
    """How the Dask executor keeps the oldest batch first: a run's tasks form one task group
    that the scheduler treats as root-ish from the first task on (the anchors: without them a
    group of two tasks on two threads is not), so it queues them and hands them out in
    priority order; and each ``client.map`` of a top-up is a later priority generation than
    the ones before (``fifo_timeout=0``), so a task submitted later never jumps ahead."""
    spec, built = job
    monkeypatch.setattr(dask_executor, "IN_FLIGHT_PER_THREAD", 10)  # room for 13 tasks on 2 threads
    executor = DaskExecutor(client, "contract-queue", description(spec), {"force": built.force, "observed": built.observed})
    results = executor.map(stream(built.models))

    def on_scheduler(dask_scheduler, keys):
        tasks = [dask_scheduler.tasks.get(tuple(k)) for k in keys]  # (tuple keys arrive as lists)
        return None if None in tasks else [(t.priority, dask_scheduler.is_rootish(t)) for t in tasks]

    def scheduler_view(keys):  # once the scheduler has the tasks (they travel on another channel)
        return wait_until(lambda: client.run_on_scheduler(on_scheduler, keys=keys), 30, "the scheduler to see the tasks")

    try:
        results.expect(1)  # two batches (10 % more, rounded up), one task each
        first = [task.key for task, _ in results.pending]
        assert len(first) == 2
        assert all(rootish for _, rootish in scheduler_view(first))
        results.expect(11)  # a second call: 13 batches in flight
        keys = [task.key for task, _ in results.pending]
        assert len(keys) == 13 and keys[:2] == first
        priorities = [p for p, _ in scheduler_view(keys)]
        assert all(a < b for a, b in itertools.pairwise(priorities)), priorities
        got = [next(results) for _ in range(13)]
        for draw, result in zip(itertools.islice(stream(built.models), 13), got):
            np.testing.assert_array_equal(result.distances, run_draw(built.evaluate, draw).distances)
    finally:
        results.close()
        executor.close()


def test_dask_keeps_at_most_two_tasks_per_worker_thread_in_flight(job, client):
    """However many batches the caller expects, the executor submits no more tasks than two
    per worker thread (one running, one next; more would only wait in the scheduler's queue
    and be released unrun when the population ends); as results come, it submits the rest,
    and the results are the batches in order."""
    spec, built = job
    executor = DaskExecutor(client, "contract-cap", description(spec), {"force": built.force, "observed": built.observed})
    results = executor.map(stream(built.models))
    try:
        results.expect(40)  # 44 batches wanted, one batch per task (no batch cost measured yet)
        assert len(results.pending) == 2 * 2  # two worker threads
        got = []
        for _ in range(12):
            got.append(next(results))
            assert results._in_flight() <= 4
        assert results.submitted > 4  # topped up as results came
        for draw, result in zip(itertools.islice(stream(built.models), 12), got):
            np.testing.assert_array_equal(result.distances, run_draw(built.evaluate, draw).distances)
    finally:
        results.close()
        executor.close()


def test_a_task_that_as_completed_never_reports_is_still_taken(job, client):
    """When the scheduler's connection drops while ``as_completed`` fetches a result, its
    tracker dies and that task is never reported (seen in the chaos runs: the job waited
    forever). The stream then takes the done task itself. Here ``as_completed`` is replaced,
    after the first task went out, by one that hears of no earlier task; the stream must
    still hand out the first batch, equal to running it here. The thread's 120 s are a
    guard against the old hang, not a speed limit (the batch takes milliseconds)."""
    spec, built = job
    executor = DaskExecutor(client, "contract-lost", description(spec), {"force": built.force, "observed": built.observed})
    results = executor.map(stream(built.models))
    try:
        results.expect(1)  # the first tasks are submitted and tracked by the stream's as_completed
        results.completed = as_completed(with_results=True, raise_errors=False)  # ...which now forgets them
        got: list = []
        reader = threading.Thread(target=lambda: got.append(next(results)), daemon=True)
        reader.start()
        reader.join(120)
        assert got, "the stream waits forever for a task as_completed lost"
        first = next(iter(stream(built.models)))
        np.testing.assert_array_equal(got[0].distances, run_draw(built.evaluate, first).distances)
    finally:
        results.close()
        executor.close()


def test_a_cheap_population_goes_to_every_worker():
    """Batches of 1 ms (a cheap kernel: §4.1's are ~1-3 ms): a task holds at least 20 ms of
    compute where the need allows, but never so many batches that fewer tasks than workers
    hold the need, so every worker has its part of a small population."""
    cheap = SimpleNamespace(batch_seconds=0.001, time_cap=lambda: 2**62)

    def size(need: int, workers: int) -> int:
        return DaskExecutor.group_size(cheap, need=need, consumed=0, n_workers=workers)  # type: ignore[arg-type]

    assert size(10, 2) == 5  # two workers, five batches each
    assert size(10, 1) == 10  # one worker: one task
    assert size(12, 4) == 3
    assert size(40, 2) == 20  # the 20 ms floor, where the need allows it
    assert size(10_000, 2) == 100  # the 100 ms ceiling


def test_cluster_settings_reach_a_stock_process_through_the_environment():
    """docs/deploy.md and docker/compose.yaml give stock Dask processes the embedded cluster's
    settings as environment variables (``cluster_env``): Dask reads them back as they are."""
    import json
    import subprocess
    import sys

    from service.run.dask_executor import CLUSTER_CONFIG, cluster_env

    code = "import dask, json, sys; print(json.dumps({k: dask.config.get(k) for k in json.loads(sys.argv[1])}))"
    done = subprocess.run([sys.executable, "-c", code, json.dumps(list(CLUSTER_CONFIG))], env=cluster_env(),
                          capture_output=True, text=True, check=True, timeout=120)
    assert json.loads(done.stdout) == CLUSTER_CONFIG


def test_summary_distances_on_workers_equal_the_runner_s(client):
    """g-and-k with summary statistics, through Dask and here, bit for bit. The observed data
    reach a worker at an unaligned byte offset, where numpy's mean of cubes rounds differently
    (skewness off in the last bit); job_parts copies them to aligned memory."""
    raw = yaml.safe_load((ROOT / "examples" / "gandk_32" / "spec.yaml").read_text())
    raw["sampler"] = {"algorithm": "rejection", "particles": 200, "batch_size": 50}
    spec = parse(raw)
    built = build(spec, ROOT / "examples" / "gandk_32")
    executor = DaskExecutor(client, "contract-gk", description(spec), {"force": None, "observed": built.observed})
    wanted = list(itertools.islice(stream(built.models, epsilon=5.0), 4))
    got = list(executor.map(iter(wanted)))
    executor.close()
    for draw, result in zip(wanted, got):
        np.testing.assert_array_equal(result.distances, run_draw(built.evaluate, draw).distances)


def test_unaligned_data_give_the_aligned_distances(job):
    """The cause of the test above, without Dask: the same observed record at an odd byte offset."""
    from worker.description import job_parts

    raw = yaml.safe_load((ROOT / "examples" / "gandk_32" / "spec.yaml").read_text())
    spec = parse(raw)
    observed = build(spec, ROOT / "examples" / "gandk_32").observed
    buffer = np.zeros(observed.nbytes + 3, np.uint8)
    unaligned = buffer[3:].view(np.float64)
    unaligned[:] = observed
    assert not unaligned.flags.aligned
    _, _, aligned_distance = job_parts(description(spec), {"force": None, "observed": observed})
    _, _, distance = job_parts(description(spec), {"force": None, "observed": unaligned})
    assert distance.observed_summaries.tobytes() == aligned_distance.observed_summaries.tobytes()
