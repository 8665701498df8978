"""Two things the runner (``service.run.runner.run_job``) does so the workers do not wait on
its process, checked by mechanism (no timing; what they buy is measured in
docs/benchmarks.md, "The runner's pauses"):

- the cyclic garbage collector's full passes are kept short while a run goes on
  (``frozen_heap``): the objects alive when the run starts are frozen (``gc.freeze``) during
  the run and handed back when it ends, whatever way it ends (a full pass over a runner's
  ~200,000 objects stalls all its threads ~110-140 ms, against ~7 ms frozen);
- a new job's store is made by the writer thread while the first population runs."""

import gc
from pathlib import Path

import pytest

import service.run.runner as runner
from service.run.runner import frozen_heap, run_job
from service.spec import parse
from tests.test_store import linear_demo_raw


def test_a_run_is_frozen_while_it_goes_on_and_hands_everything_back(tmp_path, monkeypatch):
    seen = []
    consume = runner.consume

    def watched(gen, written):
        seen.append(gc.get_freeze_count())
        return consume(gen, written)

    monkeypatch.setattr(runner, "consume", watched)
    before = gc.get_freeze_count()
    result = run_job(parse(linear_demo_raw("gc")), Path("/"), tmp_path / "gc.zarr", None)
    assert len(result.populations) == 2
    assert seen and seen[0] > before  # the objects alive at the start are frozen during the run
    assert gc.get_freeze_count() == before  # and handed back when it ends

    def dies(progress) -> None:
        raise RuntimeError("the runner dies")

    with pytest.raises(RuntimeError, match="the runner dies"):
        run_job(parse(linear_demo_raw("gc-dies")), Path("/"), tmp_path / "dies.zarr", None, on_population=dies)
    assert gc.get_freeze_count() == before  # also when the run fails


def test_overlapping_runs_unfreeze_when_the_last_ends():
    """Two runs in one process (the service's job threads): the first to end leaves the
    other's objects frozen; the last hands them all back."""
    before = gc.get_freeze_count()
    with frozen_heap():
        first = gc.get_freeze_count()
        assert first > before
        with frozen_heap():
            kept = [object() for _ in range(10)]  # noqa: F841 - objects the second run made
            assert gc.get_freeze_count() >= first
        assert gc.get_freeze_count() >= first  # the second ended, the first goes on: still frozen
    assert gc.get_freeze_count() == before


def test_a_new_jobs_store_is_made_while_its_first_population_runs(tmp_path, monkeypatch):
    """The writer thread makes a new job's store while the runner's thread simulates: here the
    store's creation waits until the first batch is simulated, which is possible only when it
    does not come first (before, it did, and this wait ran out)."""
    import threading

    from abcns.executor import SerialExecutor

    simulated = threading.Event()
    order = []

    class Watched(SerialExecutor):
        def map(self, draws):
            for result in super().map(draws):
                simulated.set()
                yield result

    new_store = runner._new_store

    def made_later(*args):
        order.append("store waits" if simulated.wait(timeout=20) else "store first")
        return new_store(*args)

    monkeypatch.setattr(runner, "SerialExecutor", Watched)
    monkeypatch.setattr(runner, "_new_store", made_later)
    result = run_job(parse(linear_demo_raw("made-later")), Path("/"), tmp_path / "later.zarr", None)
    assert order == ["store waits"]
    assert len(result.populations) == 2 and result.stop_reason.value == "max_populations"
