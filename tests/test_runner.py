"""The runner (``service.run.runner.run_job``) hands back its run's result with the mixture
the run grew (its answer read without growing it again), and keeps the cyclic garbage
collector's full passes short while a run goes on (``frozen_heap``): the objects alive when the run starts
are frozen (``gc.freeze``) during the run and handed back when it ends, whatever way it
ends. What this buys is measured, not tested (docs/benchmarks.md, "The runner's pauses": a
full pass over a runner's ~200,000 objects stalls all its threads ~110-140 ms, against ~7
ms frozen); these tests check the mechanism (no timing)."""

import gc
import threading
from pathlib import Path
from types import SimpleNamespace

import pytest

import service.run.runner as runner
from abcns.executor import SerialExecutor
from service.run.runner import alone, frozen_heap, run_job, summary
from service.run.store import Store
from service.spec import parse
from tests.test_store import linear_demo_raw


def test_a_run_is_frozen_while_it_goes_on_and_hands_everything_back(tmp_path, monkeypatch):
    seen = []
    consume = runner.consume

    def watched(gen, written):
        seen.append(gc.get_freeze_count())
        return consume(gen, written)

    def read_back(store):
        seen.append(gc.get_freeze_count())
        return result_from_store(store)

    result_from_store = runner.result_from_store
    monkeypatch.setattr(runner, "consume", watched)
    monkeypatch.setattr(runner, "result_from_store", read_back)
    before = gc.get_freeze_count()
    result = run_job(parse(linear_demo_raw("gc")), Path("/"), tmp_path / "gc.zarr", None)
    assert len(result.populations) == 2
    # the objects alive at the start are frozen during the run, and to its end (the last
    # append, the status, the result read back: a full pass there stalled the end ~140 ms)
    assert len(seen) == 2 and min(seen) > before
    assert gc.get_freeze_count() == before  # and handed back when it ends

    def dies(progress) -> None:
        raise RuntimeError("the runner dies")

    with pytest.raises(RuntimeError, match="the runner dies"):
        run_job(parse(linear_demo_raw("gc-dies")), Path("/"), tmp_path / "dies.zarr", None, on_population=dies)
    assert gc.get_freeze_count() == before  # also when the run fails


def test_a_job_s_result_holds_the_mixture_its_run_grew(tmp_path):
    """The store's result, handed back with the run's own mixture (``RunEnd.mixture``: the
    answer's reading takes it, ``abcns.mixture.Mixture.of``); a result read from the store
    later has none and grows it again, to the same summary."""
    spec = parse(linear_demo_raw("grown"))
    result = run_job(spec, Path("/"), tmp_path / "grown.zarr", None)
    assert result.mixture is not None and result.mixture.n_populations == len(result.populations) == 2
    assert run_job(spec, Path("/"), tmp_path / "grown.zarr", None).mixture is None  # finished: read back
    assert summary(Store.open(tmp_path / "grown.zarr"), result) == summary(Store.open(tmp_path / "grown.zarr"))


def test_overlapping_runs_unfreeze_when_the_last_ends():
    """Two runs in one process (the service's job threads): the first to end leaves the
    other's objects frozen; the last hands them all back."""
    before = gc.get_freeze_count()
    with frozen_heap():
        first = gc.get_freeze_count()
        assert first > before
        with frozen_heap():
            assert gc.get_freeze_count() >= first
        assert gc.get_freeze_count() >= first  # the second ended, the first goes on: still frozen
    assert gc.get_freeze_count() == before



def test_a_run_is_alone_in_its_process_until_another_overlaps():
    """The Dask executor evaluates a cheap population in the runner's process only while no
    other run shares it: two jobs of `abcns serve --max-running 2` (one interpreter), §4.1's
    40 populations each, took 6.8-6.9 s together with their populations evaluated in it,
    against 4.6-5.0 s on the two workers."""
    assert alone()
    with frozen_heap():
        assert alone()
        with frozen_heap():
            assert not alone()
        assert alone()
    assert alone()


def test_a_new_store_is_made_while_the_first_population_starts(tmp_path, monkeypatch):
    """A new store is made on the writer's thread while the executor opens and population 1's
    batches go out (making it took ~50 ms before a run's first task: docs/benchmarks.md). Here
    the making waits until the executor has been asked for population 1's batches: a runner
    that makes the store first never gets there (the wait's bound only ends that case)."""
    asked = threading.Event()
    serial_map = SerialExecutor.map

    def map_(self, draws):
        asked.set()
        return serial_map(self, draws)

    new_store = runner._new_store

    def made_once_asked(*args):
        if not asked.wait(60):
            raise AssertionError("the store was made before population 1's batches were asked for")
        return new_store(*args)

    monkeypatch.setattr(SerialExecutor, "map", map_)
    monkeypatch.setattr(runner, "_new_store", made_once_asked)
    result = run_job(parse(linear_demo_raw("early")), Path("/"), tmp_path / "early.zarr", None)
    store = Store.open(tmp_path / "early.zarr")
    assert store.attrs["status"] == "finished" and store.n_populations == len(result.populations) == 2


def test_a_store_that_cannot_be_made_fails_the_run_with_its_own_error(tmp_path, monkeypatch):
    def no_space(*args):
        raise OSError("No space left on device")

    monkeypatch.setattr(runner, "_new_store", no_space)
    with pytest.raises(OSError, match="No space left on device"):
        run_job(parse(linear_demo_raw("full")), Path("/"), tmp_path / "full.zarr", None)


@pytest.mark.parametrize(("interval_s", "appends"), [(0.0, [[1], [2], [3]]), (1.0, [[1, 2, 3]])])
def test_populations_that_come_while_the_store_is_made_are_appended_as_the_interval_says(interval_s, appends):
    """``ABCNS_STORE_INTERVAL_S=0`` writes every population on its own (the service's tests
    rely on it: what was announced is what is stored), also those that came while the new
    store was being made; with an interval they go in one append."""
    made, written = threading.Event(), []

    class Store:
        def append_many(self, pops):
            written.append([pop.t for pop, _ in pops])

    def make():
        made.wait(60)
        return Store()

    writer = runner.PopulationWriter(make, "key", None, interval_s)
    for t in (1, 2, 3):
        writer.put(SimpleNamespace(population=SimpleNamespace(t=t), n_simulations_total=10 * t), None)  # type: ignore[arg-type]
    made.set()
    writer.close()
    assert written == appends


def test_a_store_written_under_the_former_ellipsoid_cap_resumes_under_it(tmp_path, monkeypatch):
    """Before issue Y's mode-loss fix a model's bound had at most 8 ellipsoids for any number
    of particles, and a store has room for its own job's cap; now 1,000 particles bound with up
    to 16. §4.1 (1,000 particles) stopped after a few populations under the former default
    resumes to its 10th under the store's 8 (before: "population 4: 15 ellipsoids for model 0;
    the store holds 8", as the new default bounds it with more). The first run is cancelled
    once its loop has handed 2 populations to the store's writer (counted there, in the run's
    own thread: the writer's progress callback, which waits for the store to be made, once came
    after all 10 on a fresh clone)."""
    import abcns.settings
    from benchmarks.harness import duffing_spec

    spec, path = parse(duffing_spec(max_populations=10, particles=1000, noise_floor=False)), tmp_path / "s.zarr"
    handed: list = []
    put = runner.PopulationWriter.put

    def counted(self, progress, info):
        handed.append(progress.population.t)
        put(self, progress, info)

    monkeypatch.setenv("ABCNS_STORE_INTERVAL_S", "0")  # one append per population
    with monkeypatch.context() as former:
        former.setattr(abcns.settings, "PARTICLES_PER_ELLIPSOID", 10**6)  # the former default: 8
        former.setattr(runner.PopulationWriter, "put", counted)
        run_job(spec, None, path, None, cancel=lambda: len(handed) >= 2)
    assert Store.open(path).attrs["max_ellipsoids"] == 8 and 2 <= Store.open(path).n_populations < 10
    result = run_job(spec, None, path, None)
    assert len(result.populations) == 10
    assert max(len(b) for p in Store.open(path).populations() for b in p.ellipsoids) <= 8
