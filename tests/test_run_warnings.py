"""The summary's warnings word for word (abcns/run_warnings.py): one hand-made run a warning,
no sampling. The sentences are what the CLI prints after ``warning:``, the live page lists and
``GET /jobs/{id}/result`` returns; a change to one of them, or to the check that makes it, shows
here. The runs: :func:`tests.toy_results.floored_result` (five populations at tolerances
10 / t; the answer linear 0.9 / cubic 0.1 up to population 3, cubic 0.9 below), changed where
a warning needs it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from abcns import Result, StopReason
from abcns.evidence import SIMULATIONS_FAILED, Evidence
from abcns.noise import Floor
from tests.toy_results import FLOOR, floored_result


def with_populations(r: Result, change) -> Result:
    """``r`` with ``change(population)`` for each of its populations."""
    return dataclasses.replace(r, populations=tuple(change(p) for p in r.populations))


def floor(best: float) -> Floor:
    return dataclasses.replace(FLOOR, best=best)


def undecided() -> Result:
    """No floor; the answer linear 0.55 / cubic 0.45 while linear's best distance is 0.6 of the tolerance."""
    def change(p):
        d = np.where(p.models == 0, 0.6 * p.epsilon, 0.1 * p.epsilon)
        return dataclasses.replace(p, floor=None, distances=d, model_probabilities=np.array([0.55, 0.45]))
    return with_populations(floored_result(floor=None), change)


def failing() -> Result:
    """No floor; 3 of cubic's 100 simulations fail each population, and linear dies in
    population 2 because every one of its simulations failed (death rule ``failed``)."""
    def change(p):
        evidence = Evidence(**{name: np.zeros(2) for name in Evidence.FLOATS},
                            **{name: np.zeros(2, np.int64) for name in Evidence.INTS[:2]},
                            death=np.array([SIMULATIONS_FAILED if p.t == 2 else 0, 0]))
        probabilities = np.array([0.0, 1.0]) if p.t >= 2 else p.model_probabilities
        return dataclasses.replace(p, floor=None, evidence=evidence, model_probabilities=probabilities,
                                   n_simulations_by_model=np.array([100, 100]), n_failed_by_model=np.array([0, 3]))
    return with_populations(floored_result(floor=None), change)


def falling() -> Result:
    """Seven populations (the five of :func:`floored_result` and two more at tolerances 1.5 and
    1) whose best fit falls tenfold a population: no floor to wait for."""
    r = floored_result()
    more = tuple(dataclasses.replace(r.populations[-1], t=t, epsilon=eps, epsilon_next=eps / 2)
                 for t, eps in ((6, 1.5), (7, 1.0)))
    falls = lambda t: Floor(best=10.0 ** -t, model=1, n_parameters=2, variance=10.0 ** -t / 10, method=0, n_samples=100)
    return dataclasses.replace(r, populations=tuple(dataclasses.replace(p, floor=falls(p.t)) for p in r.populations + more))


CASES = {
    # the floor's decision tolerance 3.2 lies between populations 3 (3.33) and 4 (2.5)
    "below the noise floor": (floored_result(), [
        "below the noise floor: at the final tolerance 2 (population 5) the model probabilities are linear 0.10, "
        "cubic 0.90, but at the decision tolerance 3.333 (population 3, above the noise floor 2.8) they are "
        "linear 0.90, cubic 0.10: below the floor the model that fits the noise best wins; the answer is the latter"]),
    # a floor of 0.5 (decision 1.3): every tolerance of the run above it, and the floor held still
    "provisional": (floored_result(floor=floor(0.1)), [
        "provisional: the run stopped (max_populations) at eps 2, above the decision tolerance 0.9 (noise floor "
        "0.5); its model probabilities and intervals are not yet those of the data: run it on (a larger budget, or "
        "without the rule that stopped it)"]),
    # a floor of 20.4 (decision 20.8): above every tolerance of the run (the answer the same throughout)
    "floor above the run": (with_populations(floored_result(floor=floor(20.0)), lambda p: dataclasses.replace(
        p, model_probabilities=np.array([0.9, 0.1]))), [
        "floor above the run: the noise floor's decision tolerance 20.8 lies above every tolerance of the run (the "
        "highest 10); the stated noise is larger than the data's misfit"]),
    # the best fit falls tenfold a population to 1e-7 over seven populations (a floor settles over five)
    "no noise floor": (falling(), [
        "no noise floor: the best fit fell with the tolerance to 1e-07 (the decision tolerance halved within the "
        "last populations): noise-free data or a model that fits them exactly; the answer is the final population's"]),
    "undecided": (undecided(), [
        "undecided: linear (p = 0.55), cubic (p = 0.45) are all above 0.1 while the tolerance 2 sits at the best "
        "fit of linear (its best distance 1.2); a tolerance below that would separate them"]),
    "failures and failed": (failing(), [
        "failures: 15 of cubic's 500 simulations (3 %) failed or diverged; they count as rejections, so its "
        "probability and posterior hold only where its simulator works (a draw outside a simulator's stated "
        "domain, such as a restoring-force model's beta + gamma <= 0, counts here)",
        "failed: every simulation of linear failed in population 2, so it died without being compared with the data "
        "(check its fixed values and priors)"]),
}


@pytest.mark.parametrize("name", list(CASES))
def test_each_warning_word_for_word(name):
    result, expected = CASES[name]
    assert result.summary()["warnings"] == expected
    assert result.warnings() == expected


def test_a_run_without_a_population_warns_of_nothing():
    r = floored_result()
    assert dataclasses.replace(r, populations=(), stop_reason=StopReason.NOTHING_ACCEPTED).warnings() == []
