"""The paper's examples and the authors' own run. Seeds fixed; tolerances from the issue's
acceptance criteria (the reference run's own posterior spread, ±50 % on cost)."""

import json

import numpy as np
import pytest

from abcns import SMCSettings, StopRules, run
from examples.paper import SHARED, authors_demo, gandk_32, linear_31

pytestmark = pytest.mark.slow
SEED = 1


@pytest.fixture(scope="module")
def demo_run():
    problem = authors_demo()
    return problem, run(problem.models, problem.evaluate, problem.settings, problem.stop, seed=SEED)


def test_authors_demo_selects_cubic_with_the_reference_posterior(demo_run):
    problem, r = demo_run
    ref = json.loads((SHARED / "abcns-reference-demo" / "reference_run.json").read_text())
    assert r.model_probabilities()["cubic"] >= 0.99
    post = r.posterior()["cubic"]
    for name, truth, ref_std in zip(("c", "k", "k3"), (0.05, 50.0, 1000.0), ref["final_posterior_cubic"]["std"]):
        assert abs(post[name]["mean"] - truth) < ref_std, name
        assert 0.5 * ref_std < post[name]["std"] < 2 * ref_std, name  # same spread as the authors' run


def test_authors_demo_costs_like_the_reference(demo_run):
    _, r = demo_run
    ref = json.loads((SHARED / "abcns-reference-demo" / "reference_run.json").read_text())
    assert 0.5 * ref["populations"] <= len(r.populations) <= 1.5 * ref["populations"]
    assert 0.5 * ref["simulations_total_approx"] <= r.n_simulations <= 1.5 * ref["simulations_total_approx"]
    assert np.mean([p.acceptance_rate for p in r.populations]) >= 0.4
    assert "linear" in r.died_at()


@pytest.fixture(scope="module")
def linear_runs():
    problem = linear_31()
    ns = run(problem.models, problem.evaluate, problem.settings, problem.stop, seed=SEED)
    smc = run(problem.models, problem.evaluate, SMCSettings(particles=1000, schedule=tuple(p.epsilon for p in
              ns.populations)), StopRules(max_simulations=2_000_000), seed=SEED)
    return problem, ns, smc


def test_linear_31_posterior_means_within_one_percent(linear_runs):
    problem, ns, smc = linear_runs
    for name, truth in problem.truth["linear"].items():
        assert abs(ns.posterior()["linear"][name]["mean"] - truth) < 0.01 * truth, name


def test_linear_31_ns_beats_smc_on_the_same_schedule(linear_runs):
    _, ns, smc = linear_runs
    assert smc.stop_reason.value == "schedule_end"
    assert len(smc.populations) == len(ns.populations)
    assert ns.n_simulations < smc.n_simulations
    ns_acc = np.array([p.acceptance_rate for p in ns.populations])
    smc_acc = np.array([p.acceptance_rate for p in smc.populations])
    assert np.all(ns_acc[1:] > smc_acc[1:])  # population 1 is rejection for both


def test_gandk_32_truth_inside_every_95_interval():
    """With independent random numbers per simulation the distance has a noise floor
    (~0.24 at the truth) and the single ellipsoid bounds a curved region, so acceptance
    falls fast; the run is cut at 12,000 simulations (eps ~ 10-14, measured). The truth
    must lie in every 95 % interval; at this budget only k is well identified (measured
    interval ~[0.03, 2.4] of the prior [0, 10]), so its interval must be narrower than 30 %
    of the prior range and a posterior that misses k fails."""
    problem = gandk_32()
    r = run(problem.models, problem.evaluate, problem.settings, StopRules(max_simulations=12_000), seed=SEED)
    post = r.posterior()["gandk"]
    for name, truth in problem.truth["gandk"].items():
        assert post[name]["q2_5"] <= truth <= post[name]["q97_5"], (name, post[name])
    assert post["k"]["q97_5"] - post["k"]["q2_5"] < 3.0, post["k"]
    assert r.final.epsilon < 20.0
