"""Closed-form checks. Seeds fixed (override with ABCNS_TEST_SEED); each tolerance is
4 Monte Carlo standard errors (false-failure rate about 6e-5 per check)."""

import math
import os

import numpy as np
import pytest
from closed_form import (
    S_OBS,
    abc_model_probability,
    balls_4_and_5,
    balls_4_and_5_log_evidence,
    evidence_two_models,
    gaussian_mean,
    line_and_disc,
    line_and_disc_log_evidence,
    needle,
    two_models,
    uniform_and_log,
    uniform_and_log_log_evidence,
    uniform_and_log_window,
)

from abcns import OK, Model, NSSettings, RejectionSettings, SMCSettings, StopRules, per_model, run
from abcns import ellipsoid as ell
from abcns.evidence import probabilities

SEED = int(os.environ.get("ABCNS_TEST_SEED", "7"))


def test_gaussian_mean_posterior_abc_ns():
    """s ~ N(theta, 0.1^2), s_obs = 0.5, theta ~ U(-5, 5): posterior N(0.5, 0.1^2). At the
    final tolerance eps the ABC posterior is that normal convolved with U(-eps, eps), so its
    sd is sqrt(0.1^2 + eps^2/3). The population's particles are correlated (survivors carry
    over), so the standard errors use the (1 - beta) N = 400 new particles of one
    population as the effective sample size: se(mean) = sd/20, se(sd) = sd/sqrt(2*400)."""
    models, evaluate = gaussian_mean(0.1)
    r = run(models, evaluate, NSSettings(particles=1000, epsilon_initial=5),
            StopRules(min_epsilon_decrease=None, epsilon_target=0.01), seed=SEED)
    theta, _, _ = r.particles(0)
    sd = math.sqrt(0.1**2 + r.final.epsilon**2 / 3)
    n_eff = 400
    assert abs(theta.mean() - S_OBS) < 4 * sd / math.sqrt(n_eff)
    assert abs(theta.std() - sd) < 4 * sd / math.sqrt(2 * n_eff)


def test_two_models_rejection_matches_exact_abc_probability():
    """Rejection ABC at eps = 0.2 samples the ABC posterior exactly; p(narrow) = 0.8.
    se = sqrt(p (1 - p) / N)."""
    models, evaluate = two_models()
    p = abc_model_probability(0.2)
    r = run(models, evaluate, RejectionSettings(particles=2000, epsilon_initial=0.2), StopRules(max_populations=1),
            seed=SEED)
    assert abs(r.model_probabilities()["narrow"] - p) < 4 * math.sqrt(p * (1 - p) / 2000)


def test_two_models_smc_matches_exact_abc_probability():
    """ABC-SMC importance weights on (m, theta): p(narrow) at the final eps; se from the
    effective sample size of the joint weights."""
    models, evaluate = two_models()
    r = run(models, evaluate, SMCSettings(particles=1000, epsilon_initial=2.0, batch_size=500),
            StopRules(min_epsilon_decrease=None, epsilon_target=0.1), seed=SEED)
    pop = r.final
    p = abc_model_probability(pop.epsilon)
    w = pop.weights * pop.model_probabilities[pop.models]  # joint weights, sum 1
    ess = 1.0 / np.sum(w**2)
    assert abs(pop.model_probabilities[0] - p) < 4 * math.sqrt(p * (1 - p) / ess)


def test_smc_weights_count_the_kernels_mass_inside_the_prior_box():
    """P.6: U(0, 1) against U(-1, 1), both on |x|: Z(eps) = eps under either prior, so p = 0.5
    exactly at every tolerance. Proposals are redrawn into the prior box; leaving the
    kernel's mass inside it out of the weights favoured the model whose particles sit at
    its bound (0.541-0.553 on seeds 1-5 with these settings). Tolerance 0.02: 3.5 standard
    deviations of p, which measured 0.0057 over seeds 1-30 (mean 0.4996; N = 5000 gives a
    joint effective sample size of about 4900, sqrt(0.25 / 4900) = 0.0071, bounds it); about
    2e-3 false failures over the five seeds."""
    models = [Model("half", {"x": (0, 1)}), Model("full", {"x": (-1, 1)})]

    def absx(theta, rng):
        return np.abs(theta[:, 0]), np.full(theta.shape[0], OK, np.int8)

    settings = SMCSettings(particles=5000, schedule=(1.0, 0.25, 0.1), batch_size=1000)
    for seed in range(1, 6):
        r = run(models, per_model([absx, absx]), settings, StopRules(), seed=seed)
        assert abs(r.model_probabilities()["half"] - 0.5) < 0.02, (seed, r.model_probabilities())


def test_smc_kernel_density_in_chunks_is_the_density(monkeypatch):
    """P.6: Kernel.log_density holds at most DENSITY_CHUNK differences at once; chunked or not,
    the density is the mixture's (against scipy's multivariate normal)."""
    from scipy.stats import multivariate_normal

    from abcns import smc

    rng = np.random.default_rng(3)
    model = Model("m", {"a": (0, 1), "b": (0, 1), "c": (0, 1)})
    theta, w = rng.random((50, 3)), rng.random(50)
    kernel = smc.Kernel(model, theta, w)
    x = rng.random((40, 3))
    cov = kernel.chol @ kernel.chol.T
    exact = np.log(sum(wj / w.sum() * multivariate_normal(t, cov).pdf(x) for t, wj in zip(theta, w)))
    whole = kernel.log_density(x)
    np.testing.assert_allclose(whole, exact, rtol=1e-12)
    monkeypatch.setattr(smc, "DENSITY_CHUNK", 3 * 50 * 7)  # seven points at a time
    np.testing.assert_allclose(kernel.log_density(x), whole, rtol=1e-14)


def test_abc_ns_paper_variant_equal_models_stay_even():
    """Two identical models: by symmetry p = 0.5 at every population (se with 400 new
    particles per population)."""
    models, evaluate = two_models(a1=5.0, a2=5.0)
    r = run(models, evaluate, NSSettings(particles=1000, epsilon_initial=2.0, variant="paper"),
            StopRules(min_epsilon_decrease=None, max_populations=8), seed=SEED)
    shares = np.array([pop.model_probabilities[0] for pop in r.populations])
    assert np.all(np.abs(shares - 0.5) < 4 * math.sqrt(0.25 / 400)), shares


def test_abc_ns_paper_variant_shares_drift_to_even_when_fits_are_equal():
    """Why the evidence variant is the default: the paper's particle shares (Eq. 12) are not
    ABC posterior probabilities. Population 1 (rejection) has the right 0.8; later
    populations drift toward 0.5 because proposals pick models with equal probability."""
    models, evaluate = two_models()
    r = run(models, evaluate, NSSettings(particles=1000, epsilon_initial=2.0, variant="paper"),
            StopRules(min_epsilon_decrease=None, max_populations=10), seed=SEED)
    first = r.populations[0].model_probabilities[0]
    p1 = abc_model_probability(2.0)
    assert abs(first - p1) < 4 * math.sqrt(p1 * (1 - p1) / 1000)
    assert r.final.model_probabilities[0] < first - 0.1


# The evidence variant against exact ABC answers, at every population from the third on,
# seeds 1-5 (benchmarks/evidence_calibration.py runs the same checks over many seeds and
# prints their statistics; the figures below are from it, seeds 1-200, batch 200, with the
# mixture's evidence, abcns.mixture, 2026-12-05; the coverage estimate it replaced in brackets):
# - |p - exact| <= 0.03 (the issue's bar), or 4 of p's own standard errors where those are
#   larger than 0.0075. The largest error is 0.036 / 0.032 / 0.043 on two_models /
#   line_and_disc / balls_4_and_5 (0.043 / 0.018 / 0.061), where p's standard error is
#   0.01-0.02; p's z-scores have sd 0.98 / 0.79 / 0.84 (1.02 / 1.00 / 0.93).
# - where a model holds at least 100 particles, |log Z - exact| < 4 of the evidence's own
#   standard errors: |z| > 4 in none of 2,756 / 2,944 / 11,548 checks (0.03 % of
#   balls_4_and_5's before; a normal: 0.006 %), |z| > 3 in 0.11 / 0.03 / 0.04 % (a normal:
#   0.27 %; 0.25 / 0.27 / 0.33 %), sd of z 0.96 / 0.79 / 0.82 (1.01 / 0.93 / 0.96): the
#   standard error of independent draws is an upper bound for the deterministic mixture.
#   Models with fewer particles have less reliable errors (docs/benchmarks.md, known
#   limits): their p is still checked.
EVIDENCE_SEEDS = [1, 2, 3, 4, 5]
# These checks were measured with batches of 200 (the default until the unit became 25 for
# scale-out). The batch size changes the draws, not their distribution.
EVIDENCE_BATCH = 200


def check_evidence(r, exact_log_z, n_models=2):
    for pop in r.populations[2:]:
        ev = pop.evidence
        exact = exact_log_z(pop.epsilon)
        p_exact = np.exp(exact - np.logaddexp.reduce(exact))
        _, p_se = probabilities(ev.log_z, ev.log_z_se)
        off = np.abs(pop.model_probabilities - p_exact)
        assert np.all(off <= np.maximum(0.03, 4 * p_se)), (pop.t, pop.model_probabilities, p_exact, p_se)
        counts = pop.model_counts(n_models)
        for m in range(n_models):
            if counts[m] < 100:
                continue
            z = (ev.log_z[m] - exact[m]) / ev.log_z_se[m]
            assert abs(z) < 4, (pop.t, m, ev.log_z[m], exact[m], ev.log_z_se[m])


@pytest.mark.slow
@pytest.mark.parametrize("seed", EVIDENCE_SEEDS)
def test_evidence_two_models_match_exact_abc_probability(seed):
    """Stochastic simulator, exact p(narrow) = 0.80 at every eps (two_models)."""
    models, evaluate = two_models()
    r = run(models, evaluate, NSSettings(particles=1000, epsilon_initial=2.0, batch_size=EVIDENCE_BATCH),
            StopRules(min_epsilon_decrease=None, epsilon_target=0.1), seed=seed)
    assert len(r.populations) >= 6
    check_evidence(r, lambda eps: np.log([evidence_two_models(eps, a) for a in (5.0, 20.0)]))


@pytest.mark.slow
@pytest.mark.parametrize("seed", EVIDENCE_SEEDS)
def test_evidence_line_and_disc_match_exact_abc_probability(seed):
    """Deterministic 1-d against 2-d: p(line) = 2 / (2 + pi eps), 0.86 at eps 0.1 to 0.996."""
    models, evaluate = line_and_disc()
    r = run(models, evaluate, NSSettings(particles=1000, epsilon_initial=0.3, batch_size=EVIDENCE_BATCH),
            StopRules(min_epsilon_decrease=None, epsilon_target=0.003), seed=seed)
    assert len(r.populations) >= 10
    check_evidence(r, line_and_disc_log_evidence)
    # the paper's particle shares are further off than the evidence on the same run
    pop = r.final
    p_exact = 2 / (2 + math.pi * pop.epsilon)
    assert abs(pop.particle_shares[0] - p_exact) > abs(pop.model_probabilities[0] - p_exact)


def test_a_rare_model_keeps_enough_new_particles():
    """line_and_disc seed 4 (batch 200): at population 11 the disc used to have 20
    particles and fewer than 4 new ones below the next tolerance. Each alive model now keeps
    10 (d + 1) new particles a population (``abcns.settings.LEAST_NEW_PER_DIMENSION``), and
    population 12's log Z is within its own 4 standard errors of the exact one."""
    models, evaluate = line_and_disc()
    r = run(models, evaluate, NSSettings(particles=1000, epsilon_initial=0.3, batch_size=EVIDENCE_BATCH),
            StopRules(min_epsilon_decrease=None, max_populations=12), seed=4)
    assert all(p.evidence.n_accepted[1] >= 20 for p in r.populations[1:])
    pop = r.final
    z = (pop.evidence.log_z[1] - line_and_disc_log_evidence(pop.epsilon)[1]) / pop.evidence.log_z_se[1]
    assert abs(z) < 4, (pop.t, z, pop.evidence.log_z_se[1])


@pytest.mark.slow
@pytest.mark.parametrize("seed", EVIDENCE_SEEDS)
def test_evidence_balls_4_and_5_match_exact_abc_probability(seed):
    """Deterministic 4-d against 5-d balls: p(ball5) = 256 eps / (15 + 256 eps), 0.88 at
    eps 0.45 to 0.34 at 0.03 (~30 populations, both models with hundreds of particles)."""
    models, evaluate = balls_4_and_5()
    r = run(models, evaluate, NSSettings(particles=1000, epsilon_initial=0.45, batch_size=EVIDENCE_BATCH),
            StopRules(min_epsilon_decrease=None, epsilon_target=0.03), seed=seed)
    assert len(r.populations) >= 25
    check_evidence(r, balls_4_and_5_log_evidence)


def test_evidence_variant_separates_what_the_paper_variant_does_not():
    """The paper variant's shares drift (above); the evidence variant holds the exact 0.8 on
    the same problem and seed at population 10, within 4 of its own standard errors."""
    models, evaluate = two_models()
    r = run(models, evaluate, NSSettings(particles=1000, epsilon_initial=2.0, batch_size=EVIDENCE_BATCH),
            StopRules(min_epsilon_decrease=None, max_populations=10), seed=SEED)
    p = abc_model_probability(r.final.epsilon)
    _, se = probabilities(r.final.evidence.log_z, r.final.evidence.log_z_se)
    assert abs(r.final.model_probabilities[0] - p) < 4 * se[0]


def _log_uniform_moments(a, b):
    """Mean and sd of x with density 1 / x on [a, b]."""
    mean = (b - a) / math.log(b / a)
    return mean, math.sqrt((b * b - a * a) / (2 * math.log(b / a)) - mean**2)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_log_uniform_prior_gives_its_exact_evidence_and_posterior(seed):
    """One distance |x - 0.1| under U(0.01, 1) and under log-uniform on [0.01, 1]
    (uniform_and_log): the accepted interval's prior mass is each model's exact ABC evidence
    (p(log) 0.70 at eps 0.05), and the log model's ABC posterior is 1 / x on [0.1 - eps, 0.1 +
    eps], mean 0.0910 at eps 0.05 (the uniform prior's 0.1 lies 5 standard errors away). The
    evidence checks as the other closed forms (check_evidence); the posterior mean within 4
    standard errors, the new particles of one population (0.4 of the model's) as the
    effective sample size, as in test_gaussian_mean_posterior_abc_ns."""
    models, evaluate = uniform_and_log()
    r = run(models, evaluate, NSSettings(particles=1000, epsilon_initial=0.9, batch_size=EVIDENCE_BATCH),
            StopRules(min_epsilon_decrease=None, epsilon_target=0.05), seed=seed)
    assert len(r.populations) >= 5
    check_evidence(r, uniform_and_log_log_evidence)
    theta, _, _ = r.particles(1)
    mean, sd = _log_uniform_moments(*uniform_and_log_window(r.final.epsilon))
    assert abs(theta[:, 0].mean() - mean) < 4 * sd / math.sqrt(0.4 * theta.shape[0]), (theta[:, 0].mean(), mean)


def test_a_log_uniform_prior_weighs_the_smc_particles_by_its_density():
    """ABC-SMC's importance weights take the prior's density: with the uniform prior's
    constant in place of 1 / x the log model's weights are off. p(log) at the final eps
    against the exact (uniform_and_log), se from the joint weights' effective sample size;
    and the log model's weighted posterior mean within 4 of its standard errors."""
    models, evaluate = uniform_and_log()
    r = run(models, evaluate, SMCSettings(particles=1000, epsilon_initial=0.9, batch_size=500),
            StopRules(min_epsilon_decrease=None, epsilon_target=0.05), seed=SEED)
    pop = r.final
    exact = uniform_and_log_log_evidence(pop.epsilon)
    p = float(np.exp(exact[1] - np.logaddexp.reduce(exact)))
    w = pop.weights * pop.model_probabilities[pop.models]
    assert abs(pop.model_probabilities[1] - p) < 4 * math.sqrt(p * (1 - p) * np.sum(w**2)), (pop.model_probabilities, p)
    rows = pop.models == 1
    wl = pop.weights[rows] / pop.weights[rows].sum()
    mean, sd = _log_uniform_moments(*uniform_and_log_window(pop.epsilon))
    assert abs(np.sum(wl * pop.theta[rows, 0]) - mean) < 4 * sd * math.sqrt(np.sum(wl**2))


def test_the_paper_variant_samples_a_log_uniform_prior_in_log_theta():
    """The paper variant fits its ellipsoids in the raw coordinates, which for a log-uniform
    prior are log x (the log model alone; both models' distance is the same function): each
    ellipsoid's centre lies inside its population's accepted interval of log x (fitted to x
    itself, its centre was near 0.1, outside [log 0.05, log 0.15] and the prior's [log 0.01, 0]),
    and the last population is 1 / x on that interval (mean within 4 standard errors, as above)."""
    models, evaluate = uniform_and_log()
    r = run(models[1:], evaluate, NSSettings(particles=1000, epsilon_initial=0.9, variant="paper"),
            StopRules(min_epsilon_decrease=None, epsilon_target=0.05), seed=SEED)
    for pop in r.populations:
        a, b = uniform_and_log_window(pop.epsilon)
        assert math.log(a) <= pop.ellipsoids[0][0].centre[0] <= math.log(b), (pop.t, pop.ellipsoids[0][0].centre)
    theta, _, _ = r.particles(0)
    mean, sd = _log_uniform_moments(*uniform_and_log_window(r.final.epsilon))
    assert abs(theta[:, 0].mean() - mean) < 4 * sd / math.sqrt(0.4 * theta.shape[0]), (theta[:, 0].mean(), mean)


@pytest.mark.parametrize("seed", [1, 2, 3, 10, 12])
def test_a_model_under_a_second_prior_finds_a_needle_for_the_first(seed):
    """One model under two priors (needle: U(1e-4, 1) and, ``same_model_as`` it, log-uniform on
    the same range). Below eps 0.05 only the needle at x = 3e-4 is accepted: 1/500 of the
    uniform prior's accepted mass at eps 0.1 and never held by its own particles (alone, the
    uniform model stalls at eps 0.05; beside an unlinked log copy it dies there with no
    particles: seeds 1-3), but most of the log prior's. Fitted to both copies' particles, the
    uniform copy's bound holds the needle in every population once the log copy has a particle
    there, both copies' evidence is the exact one at every population (check_evidence), and at
    the end (eps <= 0.01) the uniform copy has particles in the needle and its log Z within 4
    of its standard errors. On seeds 10 and 12 (9 of seeds 1-30; 6 with the coverage estimate
    the mixture replaced) the uniform copy has no particle in the needle when the tolerance
    passes 0.05 (0.8 % of its accepted mass at eps 0.057, among ~60 particles): its
    prediction there is relayed from the log copy's
    particles (``abcns.nested._relayed``), within 4 of its standard errors of the exact one;
    before the relay, the copy died there."""
    models, evaluate, log_evidence = needle()
    r = run(models, evaluate, NSSettings(particles=300, epsilon_initial=0.5, batch_size=100),
            StopRules(min_epsilon_decrease=None, epsilon_target=0.01, max_populations=60), seed=seed)
    assert r.final.epsilon <= 0.01
    check_evidence(r, log_evidence)
    needle_unit = np.array([[(3e-4 - 1e-4) / (1 - 1e-4)]])  # in the uniform copy's unit prior box
    for pop in r.populations[:-1]:
        held = np.abs(pop.theta[pop.models == 1, 0] - 3e-4) < pop.epsilon_next / 1000
        if pop.ellipsoids[0] and held.any():
            assert ell.n_containing(pop.ellipsoids[0], needle_unit)[0] > 0, pop.t
    relayed = [p for p in r.populations if p.evidence.n_accepted[0] and not np.any(
        (p.models == 0) & (p.distances < p.epsilon_next))]
    assert len(relayed) == (seed in (10, 12)), [p.t for p in relayed]
    for p in relayed:
        ev = p.evidence
        assert abs(ev.log_z_next[0] - log_evidence(p.epsilon_next)[0]) < 4 * ev.log_z_next_se[0], (p.t, ev.log_z_next)
    theta, _, _ = r.particles(0)
    assert theta.shape[0] >= 10 and np.all(np.abs(theta[:, 0] - 3e-4) < 1e-5)
    ev = r.final.evidence
    assert abs(ev.log_z[0] - log_evidence(r.final.epsilon)[0]) < 4 * ev.log_z_se[0], (ev.log_z, ev.log_z_se)


def test_the_mixture_counts_what_a_bound_misses_of_the_region_and_of_the_next():
    """X: a bound that holds only part of the accepted region, and of the next one. Model m's
    accepted region at eps is the disc |theta - x0| < eps in its unit prior box (eps = 0.1,
    x0 the box's centre); population 1 proposes 1,000 points from the box, then the bound,
    the ellipse of semi-axes 1.3 eps and 0.25 eps about x0, proposes 1,000 more: it holds
    c ~ 0.28 of the disc and c' ~ 0.73 of the next region (radius 0.4 eps; quadrature), and
    misses their tops and bottoms. The mixture (``abcns.mixture``) counts what the ellipse
    misses through population 1's particles there, so Z(eps) and Z(0.4 eps), each estimated
    without bias, have mean relative errors over 100 such runs (seed 0) within 4 of their
    own standard errors (sd / 10) of zero; the ellipse's acceptance times its volume alone
    is off by log c (-1.27), and the coverage estimate the mixture replaced had to guess c
    and c' (docs/design.md, "The evidence")."""
    import types

    from scipy import integrate

    from abcns import bounds as bd
    from abcns.mixture import Mixture

    eps, a, b, r_next, x0 = 0.1, 0.13, 0.025, 0.04, np.array([0.5, 0.5])

    def share(r: float) -> float:  # of the disc of radius r that the ellipse holds
        return 2 * integrate.quad(lambda x: min(math.sqrt(r**2 - x**2), b * math.sqrt(1 - x**2 / a**2)), -r, r)[0] / (
            math.pi * r**2)

    assert 0.25 < share(eps) < 0.3 and 0.7 < share(r_next) < 0.8
    model = Model("disc", {"x": (0.0, 1.0), "y": (0.0, 1.0)})
    ellipse = ell.from_matrix(x0, np.diag([a**2, b**2]))
    log_v = math.log(math.pi * a * b)
    rng = np.random.default_rng(0)
    errors, alone = [], []
    for _ in range(100):
        x1 = rng.random((1000, 2))
        d1 = np.linalg.norm(x1 - x0, axis=1)
        x1, d1 = x1[d1 < eps], d1[d1 < eps]
        mixture = Mixture.empty([bd.Frame(model, unit=True)], [2]).grown(
            None, eps, np.zeros(d1.size, np.int64), x1, d1, np.ones(d1.size, bool), np.array([1000]))
        u = rng.standard_normal((1000, 2))
        x2 = x0 + u * (np.sqrt(rng.random(1000)) / np.linalg.norm(u, axis=1))[:, None] * [a, b]
        d2 = np.linalg.norm(x2 - x0, axis=1)
        x2, d2 = x2[d2 < eps], d2[d2 < eps]
        previous = types.SimpleNamespace(
            survivors=np.zeros(d1.size, bool), ellipsoids=((ellipse,),), held=None, models=np.zeros(d1.size),
            evidence=types.SimpleNamespace(log_volume=np.array([log_v]), log_volume_se=np.array([0.0])))
        mixture = mixture.grown(previous, eps, np.zeros(d2.size, np.int64), x2, d2, np.ones(d2.size, bool),
                                np.array([1000]))
        errors.append([math.exp(mixture.log_z(r)[0][0]) / (math.pi * r**2) - 1 for r in (eps, r_next)])
        alone.append(math.log(d2.size / 1000) + log_v - math.log(math.pi * eps**2))
    mean, se = np.mean(errors, axis=0), np.std(errors, axis=0, ddof=1) / 10
    assert np.all(np.abs(mean) < 4 * se), (mean, se)
    assert abs(np.mean(alone) - math.log(share(eps))) < 0.05 and np.mean(alone) < -1.2
