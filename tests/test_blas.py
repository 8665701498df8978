"""The population step runs with one BLAS thread, whatever the caller's BLAS allows
(abcns/blas.py): a Python-API user imports numpy first, so no environment variable set at
import can limit it."""

import numpy as np
import pytest
from closed_form import two_models
from threadpoolctl import threadpool_info, threadpool_limits

import abcns.nested as nested
from abcns import NSSettings, StopRules, run
from abcns.blas import limited, one_thread


def blas_threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


def test_step_proposals_and_batches_see_one_blas_thread_the_caller_its_own(monkeypatch):
    """Two BLAS threads allowed when the run starts (as numpy imported first gives on a
    2-core machine): inside the step (finish_population), the bounds' geometry
    (Step.evidence) and the in-process batches (proposals and simulations) every BLAS
    library has one thread; the caller's callback between populations sees two."""
    seen: dict[str, list[list[int]]] = {"step": [], "geometry": [], "batch": [], "caller": []}
    finish, evidence = nested.finish_population, nested.Step.evidence

    def step(*args):
        seen["step"].append(blas_threads())
        return finish(*args)

    def geometry(self, rng):
        seen["geometry"].append(blas_threads())
        return evidence(self, rng)

    monkeypatch.setattr(nested, "finish_population", step)
    monkeypatch.setattr(nested.Step, "evidence", geometry)
    models, evaluate = two_models()

    def batch(b):
        seen["batch"].append(blas_threads())
        return evaluate(b)

    with threadpool_limits(limits=2, user_api="blas"):
        if not blas_threads() or min(blas_threads()) < 2:
            pytest.skip(f"no BLAS library here takes two threads ({threadpool_info()})")
        run(models, batch, NSSettings(particles=200, epsilon_initial=2.0, batch_size=50),
            StopRules(min_epsilon_decrease=None, max_populations=3), seed=1,
            on_population=lambda _: seen["caller"].append(blas_threads()))
        after = blas_threads()
    for where in ("step", "geometry", "batch"):
        assert seen[where] and all(n == [1] * len(n) for n in seen[where]), (where, seen[where])
    assert len(seen["caller"]) == 3 and all(min(n) == 2 for n in seen["caller"]), seen["caller"]
    assert min(after) == 2


def test_nested_holders_restore_the_callers_count_when_the_last_leaves():
    """Two iterators at once in one process (the service's jobs, each on its thread): the
    limit holds until the last one leaves, then the caller's count comes back."""
    with threadpool_limits(limits=2, user_api="blas"):
        if min(blas_threads() or [0]) < 2:
            pytest.skip("no BLAS library here takes two threads")
        with one_thread():
            with one_thread():
                assert max(blas_threads()) == 1
            assert max(blas_threads()) == 1
        assert min(blas_threads()) == 2


def test_limited_passes_on_the_return_value_and_closes_the_iterator():
    closed = []

    def gen():
        try:
            yield np.zeros(1)
            yield np.ones(1)
            return "end"
        finally:
            closed.append(True)

    g = limited(gen())
    assert [float(x[0]) for x in g] == [0.0, 1.0] and closed == [True]
    g = limited(gen())
    next(g)
    g.close()
    assert closed == [True, True]
    g = limited(gen())
    next(g), next(g)
    with pytest.raises(StopIteration) as done:
        next(g)
    assert done.value.value == "end"
