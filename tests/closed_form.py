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


def evidence_two_models(eps, a):
    """Z(eps) = P(|s - S_OBS| < eps) under theta ~ U(-a, a), s ~ N(theta, 1) (quadrature)."""
    dens = lambda s: (stats.norm.cdf(a - s) - stats.norm.cdf(-a - s)) / (2 * a)
    return integrate.quad(dens, S_OBS - eps, S_OBS + eps)[0]


def abc_model_probability(eps, a1=5.0, a2=20.0):
    """Exact ABC posterior p(narrow | |s - S_OBS| < eps) with equal model priors."""
    e1, e2 = evidence_two_models(eps, a1), evidence_two_models(eps, a2)
    return e1 / (e1 + e2)


def line_and_disc(x0=0.3, y0=0.6):
    """Deterministic distances: M1 ``|a - x0|`` with a ~ U(0, 1); M2 the distance of (a, b)
    ~ U(0, 1)^2 to (x0, y0). For eps <= 0.3 the accepted sets lie inside the boxes, so the
    ABC evidences are Z1 = 2 eps and Z2 = pi eps^2 exactly."""
    models = [Model("line", {"a": (0, 1)}), Model("disc", {"a": (0, 1), "b": (0, 1)})]

    def line(theta, rng):
        return np.abs(theta[:, 0] - x0), np.full(theta.shape[0], OK, np.int8)

    def disc(theta, rng):
        return np.hypot(theta[:, 0] - x0, theta[:, 1] - y0), np.full(theta.shape[0], OK, np.int8)

    return models, per_model([line, disc])


def line_and_disc_log_evidence(eps):
    """Exact log Z of :func:`line_and_disc` (eps <= 0.3)."""
    return np.log([2 * eps, np.pi * eps**2])


def balls_4_and_5():
    """Deterministic distances in four and five dimensions: M1 ``2 |theta - c|`` with theta ~
    U(0, 1)^4, M2 ``|theta - c|`` with theta ~ U(0, 1)^5, c the centre of the box. For eps <=
    0.5 the accepted sets are balls inside the boxes (radius eps / 2 and eps), so the ABC
    evidences are the balls' volumes Z1 = (pi^2 / 2)(eps / 2)^4 and Z2 = (8 pi^2 / 15) eps^5
    exactly; p(M2) = 256 eps / (15 + 256 eps): 0.88 at eps 0.45, 0.63 at 0.1, 0.34 at 0.03."""
    models = [Model("ball4", {f"x{i}": (0, 1) for i in range(4)}), Model("ball5", {f"x{i}": (0, 1) for i in range(5)})]

    def ball(scale: float, d: int):
        def f(theta, rng):
            return scale * np.linalg.norm(theta[:, :d] - 0.5, axis=1), np.full(theta.shape[0], OK, np.int8)

        return f

    return models, per_model([ball(2.0, 4), ball(1.0, 5)])


def balls_4_and_5_log_evidence(eps):
    """Exact log Z of :func:`balls_4_and_5` (eps <= 0.5)."""
    return np.log([np.pi**2 / 2 * (eps / 2) ** 4, 8 * np.pi**2 / 15 * eps**5])


def uniform_and_log(x0=0.1, low=0.01, high=1.0):
    """One deterministic distance ``|x - x0|`` under two priors on x: U(low, high) and
    log-uniform on [low, high] (``[low, high, "log"]``)."""
    models = [Model("uniform", {"x": (low, high)}), Model("log", {"x": (low, high, "log")})]

    def dist(theta, rng):
        return np.abs(theta[:, 0] - x0), np.full(theta.shape[0], OK, np.int8)

    return models, per_model([dist, dist])


def uniform_and_log_window(eps, x0=0.1, low=0.01, high=1.0):
    """The accepted interval of x at eps: [x0 - eps, x0 + eps] within the prior's bounds."""
    return max(x0 - eps, low), min(x0 + eps, high)


def uniform_and_log_log_evidence(eps, low=0.01, high=1.0):
    """Exact log Z of :func:`uniform_and_log`: the accepted interval's prior mass under each."""
    a, b = uniform_and_log_window(eps, low=low, high=high)
    return np.log([(b - a) / (high - low), np.log(b / a) / np.log(high / low)])



def needle(x_needle=0.0003, slope=1000.0, x_broad=0.7, offset=0.05):
    """A distance with two basins on x in [1e-4, 1]: a broad one, ``|x - x_broad| + offset``,
    and a needle, ``slope |x - x_needle|``, the only one below ``offset``. Under U(1e-4, 1) the
    needle holds 2 eps / slope of the prior at eps, 1/500 of the broad basin's at eps 0.1;
    under the log-uniform prior on the same range, a third. Models ``uniform`` and ``log``
    (``same_model_as`` uniform) over that one distance. Returns (models, evaluate, the exact
    log Z of each at eps)."""
    low, high = 1e-4, 1.0
    models = [Model("uniform", {"x": (low, high)}), Model("log", {"x": (low, high, "log")}, same_model_as="uniform")]

    def dist(theta, rng):
        x = theta[:, 0]
        return np.minimum(np.abs(x - x_broad) + offset, slope * np.abs(x - x_needle)), np.full(x.shape[0], OK, np.int8)

    def pieces(m, eps):
        """Model m's accepted intervals at eps, in its unit prior box."""
        out = [(max(x_needle - eps / slope, low), x_needle + eps / slope)]
        if eps > offset:
            out.append((x_broad - (eps - offset), min(x_broad + (eps - offset), high)))
        if m == 0:
            return [((a - low) / (high - low), (b - low) / (high - low)) for a, b in out]
        return [(np.log(a / low) / np.log(high / low), np.log(b / low) / np.log(high / low)) for a, b in out]

    def log_evidence(eps):
        return np.log([sum(b - a for a, b in pieces(m, eps)) for m in (0, 1)])

    return models, per_model([dist, dist]), log_evidence
