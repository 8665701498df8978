"""The population step's parts, apart: the evidence estimator (``abcns.evidence.estimate``)
and the two variants (``abcns.variants``). Exact arithmetic on hand-made populations: no
seed, no tolerance beyond floating point."""

import numpy as np

from abcns import evidence as ev
from abcns.priors import Model
from abcns.settings import NSSettings
from abcns.variants import Evidence, Paper, variant_of

MODELS = [Model("a", {"x": (0.0, 1.0)}), Model("b", {"x": (0.0, 1.0), "y": (0.0, 1.0)})]


def previous_evidence(**over) -> ev.Evidence:
    base = dict(log_z=np.log([0.5, 0.25]), log_z_se=np.array([0.1, 0.1]),
                log_z_next=np.log([0.2, 0.1]), log_z_next_se=np.array([0.1, 0.1]),
                log_volume=np.log([0.4, 0.2]), log_volume_se=np.array([0.01, 0.01]),
                coverage=np.array([1.0, 1.0]), n_coverage=np.array([100, 100]),
                allocation=np.array([0.5, 0.5]), n_proposed=np.array([100, 100]),
                n_accepted=np.array([50, 25]), death=np.zeros(2, dtype=np.int64))
    return ev.Evidence(**{**base, **over})


def test_the_first_population_is_rejection_from_the_priors():
    """Z = accepted / proposed exactly (Agresti-Coull variance), and the prediction at
    eps_next is Z times the share of new particles below it."""
    which = np.array([0, 0, 0, 0, 1, 1])
    d = np.array([0.1, 0.2, 0.6, 0.7, 0.3, 0.8])
    est = ev.estimate(which, d, np.ones(6, bool), 0.5, np.array([40, 20]), np.array([4, 2]), None)
    np.testing.assert_allclose(est.log_z, np.log([0.1, 0.1]))
    np.testing.assert_allclose(est.log_z_next, np.log([0.1 * 2 / 4, 0.1 * 1 / 2]))
    np.testing.assert_allclose(est.p_now, [0.5, 0.5])
    assert np.all(est.var_next > est.var_z)  # the share below eps_next adds its own variance


def test_an_unmeasured_coverage_leaves_log_z_to_the_prediction():
    """With n_coverage 0 the direct estimate has no weight: log Z is the previous prediction."""
    prev = previous_evidence(n_coverage=np.array([0, 100]), coverage=np.array([1.0, 1.0]))
    which, d = np.array([0, 0, 1, 1]), np.array([0.1, 0.2, 0.1, 0.2])
    est = ev.estimate(which, d, np.ones(4, bool), 0.15, np.array([10, 10]), np.array([9, 1]), prev)
    assert est.log_z[0] == prev.log_z_next[0] and est.var_z[0] == prev.log_z_next_se[0] ** 2
    assert est.log_z[1] != prev.log_z_next[1]  # measured: the two estimates combine


def test_a_model_without_particles_has_no_evidence():
    """Dead after the previous population (it proposes nothing), or at the first population
    with no accepted particle; but a model alive after the previous population that proposed
    and has no particle (a copy relayed by its twin's particles: no survivors) is alive, its
    log Z the previous prediction (its direct estimate unmeasured: no coverage of its own)."""
    which, d = np.array([0, 0, 0]), np.array([0.1, 0.2, 0.3])
    dead = previous_evidence(death=np.array([ev.ALIVE, ev.NO_PARTICLES]))
    est = ev.estimate(which, d, np.ones(3, bool), 0.25, np.array([10, 0]), np.array([3, 0]), dead)
    assert est.log_z[1] == -np.inf and est.p_now[1] == 0.0 and est.p_next[1] == 0.0
    est = ev.estimate(which, d, np.ones(3, bool), 0.25, np.array([10, 10]), np.array([3, 0]), None)
    assert est.log_z[1] == -np.inf and est.p_now[1] == 0.0 and est.p_next[1] == 0.0
    relayed = previous_evidence(n_coverage=np.array([100, 0]))
    est = ev.estimate(which, d, np.ones(3, bool), 0.25, np.array([10, 10]), np.array([3, 0]), relayed)
    assert est.log_z[1] == np.log(0.1) and est.p_now[1] > 0 and est.p_next[1] == 0.0


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
