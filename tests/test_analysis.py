"""abcns.analysis against hand-computed values on small cases (no simulator, no run)."""

from __future__ import annotations

import numpy as np
import pytest

from abcns import DIVERGED, OK, Model, Population, Result, StopReason
from abcns.analysis import bands, confusion, draw_parameters, fit_test_nmse, nmse, point_estimates, predictive


def make_result(theta_a: np.ndarray, d_a: np.ndarray, theta_b: np.ndarray | None = None,
                d_b: np.ndarray | None = None, weighted: bool = False) -> Result:
    """A one-population result: model "a" (1 parameter) and optionally model "b" (2)."""
    models = (Model("a", {"x": (0.0, 10.0)}), Model("b", {"x": (0.0, 10.0), "y": (0.0, 10.0)}))
    theta_b = np.zeros((0, 2)) if theta_b is None else theta_b
    d_b = np.zeros(0) if d_b is None else d_b
    na, nb = theta_a.shape[0], theta_b.shape[0]
    theta = np.full((na + nb, 2), np.nan)
    theta[:na, :1] = theta_a
    theta[na:] = theta_b
    w = np.concatenate([np.full(na, 1.0 / na), np.full(nb, 1.0 / max(nb, 1))])
    pop = Population(t=1, epsilon=1.0, epsilon_next=0.5, models=np.repeat([0, 1], [na, nb]), theta=theta,
                     distances=np.concatenate([d_a, d_b]), weights=w, n_accepted=na + nb, n_simulations=na + nb,
                     n_failed=0, n_redraws=0, elapsed_s=0.0,
                     model_probabilities=np.array([na, nb]) / (na + nb))
    return Result("abc-ns", models, (pop,), StopReason.MAX_POPULATIONS, 0, {}, "given", na + nb, 0, 0.0,
                  weighted_posterior=weighted)


def test_bands_hand_computed():
    # 101 trajectories whose value at time k is i * (k + 1), i = 0..100: numpy's linear
    # quantile of 0..100 at q is 100 q exactly, so the bands are 100 q (k + 1).
    traj = np.arange(101.0)[:, None] * np.array([1.0, 2.0, 3.0])
    b = bands(traj)
    np.testing.assert_allclose(b["median"], [50, 100, 150])
    np.testing.assert_allclose(b["lower_50"], [25, 50, 75])
    np.testing.assert_allclose(b["upper_50"], [75, 150, 225])
    np.testing.assert_allclose(b["lower_99"], [0.5, 1.0, 1.5])
    np.testing.assert_allclose(b["upper_99"], [99.5, 199, 298.5])
    with pytest.raises(ValueError, match="every simulation failed"):
        bands(np.zeros((0, 3)))


def test_predictive_ignores_rows_not_ok():
    # particles x = 1..5; the simulator returns x * [1, 1], x = 5 diverges (its values are
    # garbage 1e9 and must not enter the bands); x = 4 gives NaN without a status.
    res = make_result(np.arange(1.0, 6.0)[:, None], np.arange(5.0))

    def simulate(theta):
        values = theta[:, :1] * np.ones((1, 2))
        values[theta[:, 0] == 5] = 1e9
        values[theta[:, 0] == 4] = np.nan
        return values, np.where(theta[:, 0] == 5, DIVERGED, OK)

    p = predictive(res, "a", simulate)
    assert p.n_failed == 2 and p.trajectories.shape == (3, 2)
    np.testing.assert_allclose(p.bands["median"], [2, 2])   # median of 1, 2, 3
    np.testing.assert_allclose(p.bands["upper_99"], [2.99, 2.99])  # 1 + 2 * 0.995
    # plain array return: the NaN row is dropped, the 1e9 row is not (no status to say so)
    q = predictive(res, 0, lambda th: simulate(th)[0])
    assert q.n_failed == 1 and q.model == "a"


def test_draw_parameters():
    res = make_result(np.arange(1.0, 6.0)[:, None], np.arange(5.0), np.array([[1.0, 2.0]]), np.array([0.1]))
    np.testing.assert_array_equal(draw_parameters(res, "b"), [[1.0, 2.0]])
    with pytest.raises(ValueError, match="rng"):
        draw_parameters(res, "a", 10)
    x = draw_parameters(res, "a", 20_000, np.random.default_rng(3))[:, 0]
    # uniform over 5 particles: each share 0.2, sd sqrt(0.2 * 0.8 / 20000) = 0.0028; 5 sd
    np.testing.assert_allclose(np.bincount(x.astype(int), minlength=6)[1:] / x.size, 0.2, atol=0.015)


def test_nmse_eq7_by_hand():
    obs = np.array([1.0, 3.0, 2.0, 6.0])
    sim = np.array([1.0, 2.0, 2.0, 4.0])
    # whole record: var(ddof=1) of obs = 14/3; sum sq err = 1 + 4 = 5; 100 / (4 * 14/3) * 5
    assert nmse(sim, obs) == pytest.approx(100 * 5 / (4 * 14 / 3))
    # window [1, 3): obs 3, 2 -> var 0.5; err 1 -> 100 / (2 * 0.5) * 1 = 100
    assert nmse(sim, obs, (1, 3)) == pytest.approx(100.0)
    np.testing.assert_allclose(nmse(np.stack([sim, obs]), obs, (1, 3)), [100.0, 0.0])


def test_point_estimates():
    # particles x = 1, 2, 6 with distances 0.3, 0.1, 0.2: mean 3, best 2
    res = make_result(np.array([[1.0], [2.0], [6.0]]), np.array([0.3, 0.1, 0.2]))
    pts = point_estimates(res, "a")
    assert pts["posterior_mean"][0] == pytest.approx(3.0) and pts["best"][0] == 2.0


def test_fit_test_nmse_values():
    res = make_result(np.array([[1.0], [2.0], [6.0]]), np.array([0.3, 0.1, 0.2]))
    obs = np.array([3.0, 4.0, 4.0, 2.0])
    scores = fit_test_nmse(res, "a", lambda th: th[:, :1] * np.ones((1, 4)), obs, {"fit": (0, 2), "test": (2, 4), "x": None})
    # fit [0, 2): obs 3, 4, var 0.5, scale 100 / (2 * 0.5) = 100
    #   mean (3): err 0, 1 -> 100; best (2): err 1, 2 -> 500
    # test [2, 4): obs 4, 2, var 2, scale 100 / 4 = 25
    #   mean (3): err 1, 1 -> 50; best (2): err 2, 0 -> 100
    assert scores == {"posterior_mean": {"fit": pytest.approx(100.0), "test": pytest.approx(50.0)},
                      "best": {"fit": pytest.approx(500.0), "test": pytest.approx(100.0)}}
    bad = fit_test_nmse(res, "a", lambda th: (th[:, :1] * np.ones((1, 4)), np.full(2, DIVERGED)), obs, {"fit": (0, 2)})
    assert bad["best"]["fit"] == np.inf


def test_confusion_matrix_by_hand():
    # two data sets with "true" levels 1 and 3; model "a" fitted on set i has mean
    # parameter m_i; its score on set j is |m_i - level_j|. Model "b" dies in fit 1
    # (no particles) and is eliminated.
    levels = [1.0, 3.0]
    fit0 = make_result(np.array([[1.0], [1.0]]), np.zeros(2), np.array([[0.0, 0.0]]), np.zeros(1))
    fit1 = make_result(np.array([[2.0], [4.0]]), np.zeros(2))

    def score(model, theta, j):
        return abs(theta[0] - levels[j])

    c = confusion([fit0, fit1], score, datasets=["low", "high"])
    np.testing.assert_allclose(c.matrices["a"], [[0, 2], [2, 0]])
    assert c.matrices["b"][1, 0] == np.inf and c.eliminated == ("b",)
    assert c.best == "a" and c.mean["a"] == pytest.approx(1.0) and c.worst["a"] == 2.0
    assert c.datasets == ("low", "high")


def test_confusion_rule_mean_then_worst():
    # two models on two data sets; "b" has the smaller mean, "c" the smaller worst entry:
    # the rule picks the smaller mean; with equal means the smaller worst entry.
    models = (Model("b", {"x": (0.0, 10.0)}), Model("c", {"x": (0.0, 10.0)}))
    fits = []
    for x in (1.0, 2.0):
        pop = Population(1, 1.0, 0.5, np.array([0, 1]), np.array([[x], [x]]), np.zeros(2), np.full(2, 1.0),
                         2, 2, 0, 0, 0.0, model_probabilities=np.array([0.5, 0.5]))
        fits.append(Result("abc-ns", models, (pop,), StopReason.MAX_POPULATIONS, 0, {}, "given", 2, 0, 0.0))
    table = {"b": [[0.0, 3.0], [0.0, 0.0]], "c": [[1.0, 1.0], [1.0, 1.0]]}
    c = confusion(fits, lambda m, th, j: table[m][int(th[0]) - 1][j])
    assert c.mean == {"b": 0.75, "c": 1.0} and c.best == "b"
    table["c"] = [[0.5, 1.0], [0.5, 1.0]]   # mean 0.75 too, worst 1 < 3
    assert confusion(fits, lambda m, th, j: table[m][int(th[0]) - 1][j]).best == "c"
