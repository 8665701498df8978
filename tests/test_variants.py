"""The population step's parts, apart: the evidence estimator (``abcns.evidence.estimate``,
from ``abcns.mixture``) and the two variants (``abcns.variants``). Exact arithmetic on
hand-made populations: no seed, no tolerance beyond floating point."""

import math
from types import SimpleNamespace

import numpy as np

from abcns import bounds as bd
from abcns import ellipsoid as ell
from abcns import evidence as ev
from abcns.mixture import HELD, NOT_FITTED, OUTSIDE, Mixture
from abcns.priors import Model
from abcns.settings import NSSettings
from abcns.variants import Evidence, Paper, variant_of

MODELS = [Model("a", {"x": (0.0, 1.0)}), Model("b", {"x": (0.0, 1.0), "y": (0.0, 1.0)})]


def empty() -> Mixture:
    return Mixture.empty([bd.Frame(m, unit=True) for m in MODELS], [m.n_dim for m in MODELS])


def previous_evidence(**over) -> ev.Evidence:
    base = dict(log_z=np.log([0.5, 0.25]), log_z_se=np.array([0.1, 0.1]),
                log_z_next=np.log([0.2, 0.1]), log_z_next_se=np.array([0.1, 0.1]),
                log_volume=np.log([0.4, 0.2]), log_volume_se=np.array([0.01, 0.01]),
                allocation=np.array([0.5, 0.5]), n_proposed=np.array([100, 100]),
                n_accepted=np.array([50, 25]), death=np.zeros(2, dtype=np.int64))
    return ev.Evidence(**{**base, **over})


def first(which: np.ndarray, d: np.ndarray, eps: float, n_proposed: np.ndarray) -> Mixture:
    theta = np.full((which.size, 2), 0.5)
    return empty().grown(None, eps, which, theta, d, np.ones(which.size, bool), n_proposed)


def test_the_first_population_is_rejection_from_the_priors():
    """Z = accepted / proposed exactly (the binomial's variance), and the prediction at
    eps_next the share of proposals below it."""
    which = np.array([0, 0, 0, 0, 1, 1])
    d = np.array([0.1, 0.2, 0.6, 0.7, 0.3, 0.8])
    n = np.array([40, 20])
    est = ev.estimate(which, d, 1.0, 0.5, n, np.array([4, 2]), None, first(which, d, 1.0, n))
    np.testing.assert_allclose(est.log_z, np.log([0.1, 0.1]))
    np.testing.assert_allclose(est.var_z, [0.9 / 4, 0.9 / 2])
    np.testing.assert_allclose(est.log_z_next, np.log([2 / 40, 1 / 20]))
    np.testing.assert_allclose(est.p_now, [0.5, 0.5])


def test_the_mixture_counts_what_the_last_bound_misses_through_the_regions_before():
    """Model a, d(x) = |x - 0.3|. Population 1: 100 proposals from the prior on a grid
    (0.005, 0.015, ...), 60 below eps_1 = 0.3. Its bound B_1 = [0.2, 0.6] (prior mass 0.4)
    proposes 40 new particles of population 2 on a grid; eps_2 = 0.2, whose region [0.1,
    0.5) B_1 misses a quarter of. The 10 particles of population 1 in [0.1, 0.2) count
    1 / 100 each, the 30 in [0.2, 0.5) and population 2's 30 there 1 / (100 + 40 / 0.4) each:
    Z = 0.1 + 0.15 + 0.15 = 0.4, the truth, where the bound's acceptance times its volume
    says 0.3 (the coverage estimate had to divide it by 0.75). A particle B_1 was fitted to
    that the bound refitted without it leaves (OUTSIDE) counts as outside it: 1 / 100."""
    x1 = 0.005 + 0.01 * np.arange(100)
    keep = np.abs(x1 - 0.3) < 0.3
    which1, theta1 = np.zeros(60, np.int64), np.column_stack([x1[keep], np.full(60, np.nan)])
    d1 = np.abs(theta1[:, 0] - 0.3)
    mixture = empty().grown(None, 0.5, which1, theta1, d1, np.ones(60, bool), np.array([100, 0]))
    bound = (ell.from_matrix(np.array([0.4]), np.array([[0.04]])),)
    held = np.full((60, 2), NOT_FITTED, np.int8)
    previous = SimpleNamespace(survivors=np.zeros(60, bool), ellipsoids=(bound, ()), held=held, models=which1,
                               evidence=previous_evidence(log_volume=np.log([0.4, 1.0]), log_volume_se=np.zeros(2)))
    x2 = 0.205 + 0.01 * np.arange(40)
    theta2 = np.column_stack([x2, np.full(40, np.nan)])
    d2 = np.abs(x2 - 0.3)
    grown = mixture.grown(previous, 0.3, np.zeros(40, np.int64), theta2, d2, np.ones(40, bool), np.array([40, 0]))
    log_z, var = grown.log_z(0.2)
    assert math.isclose(log_z[0], math.log(0.4)) and log_z[1] == -np.inf and var[1] == np.inf
    held[np.flatnonzero(np.isclose(theta1[:, 0], 0.215)), 0] = OUTSIDE
    held[np.flatnonzero(np.isclose(theta1[:, 0], 0.225)), 0] = HELD
    grown = mixture.grown(previous, 0.3, np.zeros(40, np.int64), theta2, d2, np.ones(40, bool), np.array([40, 0]))
    assert math.isclose(grown.log_z(0.2)[0][0], math.log(0.4 + 1 / 100 - 1 / 200))


def test_a_model_without_particles_has_no_evidence():
    """Dead after the previous population (it proposes nothing), or at the first population
    with no accepted particle; but a model alive after the previous population that proposed
    and has no particle (a copy relayed by its twin's particles: no survivors) is alive, its
    log Z that of 0 accepted of its 10 proposals in its bound: log((1/2) / 11) + log V."""
    which, d = np.array([0, 0, 0]), np.array([0.1, 0.2, 0.3])
    n = np.array([10, 10])
    mixture = first(which, d, 0.4, n)
    dead = previous_evidence(death=np.array([ev.ALIVE, ev.NO_PARTICLES]))
    est = ev.estimate(which, d, 0.4, 0.25, np.array([10, 0]), np.array([3, 0]), dead, mixture)
    assert est.log_z[1] == -np.inf and est.p_now[1] == 0.0 and est.p_next[1] == 0.0
    est = ev.estimate(which, d, 0.4, 0.25, n, np.array([3, 0]), None, mixture)
    assert est.log_z[1] == -np.inf and est.p_now[1] == 0.0 and est.p_next[1] == 0.0
    est = ev.estimate(which, d, 0.4, 0.25, n, np.array([3, 0]), previous_evidence(), mixture)
    assert math.isclose(est.log_z[1], math.log(0.5 / 11 * 0.2)) and est.p_now[1] > 0 and est.p_next[1] == 0.0


def estimate_with(p_next, se_next=(0.0, 0.0)) -> ev.Estimate:
    p = np.asarray(p_next, float)
    return ev.Estimate(np.log(p), np.zeros(2), np.log(p), np.zeros(2), p, p, np.asarray(se_next, float))


def test_the_paper_variant_keeps_survivors_by_counts_and_picks_models_evenly():
    paper = Paper(NSSettings(particles=100, variant="paper"))
    quotas, death = paper.survive(MODELS, estimate_with([0.5, 0.5]), np.array([75, 25]), np.array([60, 20]),
                                  np.array([True, True]), None)
    assert quotas.tolist() == [45, 15] and death.tolist() == [ev.ALIVE, ev.ALIVE]  # beta N = 60, 3:1
    alloc, probabilities = paper.proposals(MODELS, estimate_with([0.9, 0.1]), np.array([75, 25]), np.ones(2),
                                           np.array([True, True]))
    assert alloc.tolist() == [0.5, 0.5] and probabilities.tolist() == [0.75, 0.25]  # Eq. 12: shares


def test_the_evidence_variant_kills_by_probability_only_twice_in_a_row():
    s = NSSettings(particles=100)
    evidence = Evidence(s)
    low = estimate_with([0.9995, 0.0005])  # below the default threshold, 1e-3
    args = (MODELS, low, np.array([90, 10]), np.array([80, 8]), np.array([True, True]))
    _, once = evidence.survive(*args, previous_evidence(log_z_next=np.log([0.5, 0.5])))
    assert once.tolist() == [ev.ALIVE, ev.ALIVE]  # the previous prediction was above the threshold
    quotas, twice = evidence.survive(*args, previous_evidence(log_z_next=np.log([0.9995, 0.0005]),
                                                              log_z_next_se=np.zeros(2)))
    assert twice.tolist() == [ev.ALIVE, ev.IMPROBABLE] and quotas[1] == 0 and quotas.sum() == s.n_survivors


def test_the_evidence_variant_keeps_the_survivor_floor_and_follows_p():
    s = NSSettings(particles=100)
    quotas, _ = Evidence(s).survive(MODELS, estimate_with([0.98, 0.02]), np.array([50, 50]), np.array([60, 60]),
                                    np.array([True, True]), None)
    assert quotas.sum() == s.n_survivors and quotas[1] == 6  # 2 (d + 1) for the 2-d model, above 0.02 x 60
    assert isinstance(variant_of(s), Evidence) and isinstance(variant_of(NSSettings(variant="paper")), Paper)
