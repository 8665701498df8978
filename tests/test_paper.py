"""The paper's examples and the authors' own run. Seeds fixed; tolerances from the issue's
acceptance criteria (the reference run's own posterior spread, ±50 % on cost)."""

import json

import numpy as np
import pytest

from abcns import SMCSettings, StopRules, run
from examples.paper import DATA, authors_demo, gandk_32, linear_31

pytestmark = pytest.mark.slow
SEED = 1


@pytest.fixture(scope="module")
def demo_run():
    problem = authors_demo()
    return problem, run(problem.models, problem.evaluate, problem.settings, problem.stop, seed=SEED)


def test_authors_demo_selects_cubic_with_the_reference_posterior(demo_run):
    _problem, r = demo_run
    ref = json.loads((DATA / "authors-demo" / "reference_run.json").read_text())
    assert r.model_probabilities()["cubic"] >= 0.99
    post = r.posterior()["cubic"]
    for name, truth, ref_std in zip(("c", "k", "k3"), (0.05, 50.0, 1000.0), ref["final_posterior_cubic"]["std"]):
        assert abs(post[name]["mean"] - truth) < ref_std, name
        assert 0.5 * ref_std < post[name]["std"] < 2 * ref_std, name  # same spread as the authors' run


def test_authors_demo_costs_like_the_reference(demo_run):
    _, r = demo_run
    ref = json.loads((DATA / "authors-demo" / "reference_run.json").read_text())
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


def test_linear_31_posterior_means_at_the_truth_to_monte_carlo_error(linear_runs):
    """The data are noise-free, so the tolerance ball of the last population is centred on the
    truth (the NMSE is quadratic in the parameters near it) and the posterior mean differs
    from the truth by Monte Carlo error only: standard error std / sqrt(N), N = 1000
    particles (c: 0.067 / 31.6 = 0.0021, k: 6.6 / 31.6 = 0.21). Measured on seeds 1-7:
    -1.2 to +2.1 standard errors; allowed 4. (The 1 % of the truth this replaces was 94 and
    480 standard errors.)"""
    problem, ns, _smc = linear_runs
    theta, _, _ = ns.particles("linear")
    for name, truth in problem.truth["linear"].items():
        post = ns.posterior()["linear"][name]
        se = post["std"] / np.sqrt(theta.shape[0])
        assert abs(post["mean"] - truth) < 4 * se, (name, post["mean"] - truth, se)


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
    falls fast; the run is cut at 12,000 simulations. The truth must lie in every 95 %
    interval; at this budget only k is well identified. The bounds come from the spread of
    the run over seeds 1-5 (measured 2026-11-29, after issue Y's bound fix): k's 95 % interval
    0.835, 0.820, 0.894, 0.891, 0.912 wide (mean 0.87, sd 0.04; the prior U(0, 10) would give
    9.5), final tolerance 1.93, 1.84, 1.92, 1.94, 2.22 (mean 1.97, sd 0.15): each must stay
    below the mean + 4 sd, 1.03 and 2.57, so
    a posterior that misses k or a run that stalls fails."""
    problem = gandk_32()
    r = run(problem.models, problem.evaluate, problem.settings, StopRules(max_simulations=12_000), seed=SEED)
    post = r.posterior()["gandk"]
    for name, truth in problem.truth["gandk"].items():
        assert post[name]["q2_5"] <= truth <= post[name]["q97_5"], (name, post[name])
    assert post["k"]["q97_5"] - post["k"]["q2_5"] < 0.87 + 4 * 0.04, post["k"]
    assert r.final.epsilon < 1.97 + 4 * 0.15
