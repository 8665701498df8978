"""Problems with known answers (shared by the statistical tests)."""

import numpy as np
from scipy import integrate, stats

from abcns import OK, Model, per_model

S_OBS = 0.5


def normal_simulator(sigma: float):
    """theta (n, 1) -> distance |s - S_OBS| with s ~ N(theta, sigma^2)."""

    def f(theta, rng):
        s = theta[:, 0] + sigma * rng.standard_normal(theta.shape[0])
        return np.abs(s - S_OBS), np.full(theta.shape[0], OK, np.int8)

    return f


def gaussian_mean(sigma=0.1):
    models = [Model("mean", {"theta": (-5, 5)})]
    return models, per_model([normal_simulator(sigma)])


def two_models(a1=5.0, a2=20.0):
    """M1: theta ~ U(-a1, a1), M2: theta ~ U(-a2, a2); both s ~ N(theta, 1)."""
    models = [Model("narrow", {"theta": (-a1, a1)}), Model("wide", {"theta": (-a2, a2)})]
    return models, per_model([normal_simulator(1.0), normal_simulator(1.0)])


def abc_model_probability(eps, a1=5.0, a2=20.0):
    """Exact ABC posterior p(narrow | |s - S_OBS| < eps) with equal model priors."""

    def evidence(a):
        dens = lambda s: (stats.norm.cdf(a - s) - stats.norm.cdf(-a - s)) / (2 * a)  # noqa: E731
        return integrate.quad(dens, S_OBS - eps, S_OBS + eps)[0]

    e1, e2 = evidence(a1), evidence(a2)
    return e1 / (e1 + e2)
