"""The ABC evidence of each model, and the model probabilities it gives.

The ABC posterior probability of model m at tolerance eps is

    p(m | d < eps) = Z_m(eps) / sum_j Z_j(eps),   Z_m(eps) = prior mass of {theta : d < eps}

(equal model priors; for a stochastic simulator, the prior expectation of P(d < eps | theta)).
The paper reports particle shares instead (Eq. 12), which ignore how much prior volume lies
under eps. ABC-NS already draws what Z needs: every particle of every population, proposed
uniformly in a region of known prior mass (the prior box, then a bound), is an importance
sample of the prior restricted to the tolerance, weighted by the mixture of all the regions
that proposed them (``abcns.mixture``: importance nested sampling's estimator). Each
population gives log Z at its own tolerance and the prediction at the next, both from its
mixture, with their standard errors (docs/design.md, "The evidence"). Pure functions on
arrays, one entry per model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from abcns.mixture import Mixture

#: death codes (``Evidence.death``): why a model is dead from the next population on;
#: SIMULATIONS_FAILED: every one of its simulations in the population failed or diverged
ALIVE, NO_PARTICLES, IMPROBABLE, DEAD_BEFORE, SIMULATIONS_FAILED = 0, 1, 2, 3, 4
DEATH_RULES = {NO_PARTICLES: "no_particles", IMPROBABLE: "probability", DEAD_BEFORE: "dead",
               SIMULATIONS_FAILED: "failed"}


@dataclass(frozen=True, eq=False)
class Evidence:
    """Evidence bookkeeping of one population, arrays of shape (n_models,).

    ``log_z``/``log_z_se``: log Z_m(eps_t) and its standard error (-inf / inf for a dead model);
    ``log_z_next``/``log_z_next_se``: the prediction at eps_{t+1};
    ``log_volume``/``log_volume_se``: log prior mass of the bound that proposes m's particles
    at t + 1 (NaN when there is none), measured by Monte Carlo;
    ``allocation``: the probability that a proposal of population t + 1 is of model m;
    ``n_proposed``/``n_accepted``: model m's new proposals simulated in this population and
    those accepted; ``death``: ALIVE, or why m has no particles from t + 1 on.
    """

    log_z: np.ndarray
    log_z_se: np.ndarray
    log_z_next: np.ndarray
    log_z_next_se: np.ndarray
    log_volume: np.ndarray
    log_volume_se: np.ndarray
    allocation: np.ndarray
    n_proposed: np.ndarray
    n_accepted: np.ndarray
    death: np.ndarray

    FLOATS = ("log_z", "log_z_se", "log_z_next", "log_z_next_se", "log_volume", "log_volume_se", "allocation")
    INTS = ("n_proposed", "n_accepted", "death")


def log_share(k: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(log a, its variance) for a share a of k successes in n binomial trials, elementwise.

    The point is log(k / n); where k = 0, log((1/2) / (n + 1)) (finite: a share of zero
    must not declare a model dead on its own). The variance is the delta method's
    (1 - a) / (n a), evaluated at the Agresti-Coull estimate a = (k + 2) / (n + 4) (two
    successes and two failures added): (n - k + 2) / ((n + 4)(k + 2)). At a = k / n it would
    rest on the count of the rarer outcome, which is the error's own source: an acceptance
    near 1 with fewer rejections than due is too high and its variance too small at once.
    Infinite where n = 0."""
    k, n = np.asarray(k, float), np.asarray(n, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        log = np.where(k > 0, np.log(k / np.maximum(n, 1.0)), np.log(0.5 / (n + 1.0)))
        var = np.where(n > 0, (n - k + 2.0) / ((n + 4.0) * (k + 2.0)), np.inf)
    return log, var


def combine(a: np.ndarray, var_a: np.ndarray, b: np.ndarray, var_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-variance mean of two estimates (either may be missing: infinite variance)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    var_a, var_b = np.asarray(var_a, float), np.asarray(var_b, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        wa = np.where(np.isfinite(var_a), 1.0 / np.maximum(var_a, 1e-300), 0.0)
        wb = np.where(np.isfinite(var_b), 1.0 / np.maximum(var_b, 1e-300), 0.0)
        total = wa + wb
        mean = np.where(total > 0, (wa * np.where(wa > 0, a, 0.0) + wb * np.where(wb > 0, b, 0.0)) / total,
                        np.where(np.isfinite(a), a, b))
        var = np.where(total > 0, 1.0 / total, np.inf)
    return mean, var


def probabilities(log_z: np.ndarray, log_z_se: np.ndarray,
                  covariance: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """p_m = Z_m / sum Z and its standard error (delta method on independent log Z):
    var p_m = p_m^2 [(1 - p_m)^2 s_m^2 + sum_{j != m} p_j^2 s_j^2]; with the ``covariance``
    of the log Z (copies read from the same particles, ``abcns.likelihood.read``), J C J^T's
    diagonal, J_mj = p_m (delta_mj - p_j)."""
    log_z = np.asarray(log_z, float)
    alive = np.isfinite(log_z)
    p = np.zeros(log_z.shape)
    if not alive.any():
        return p, np.zeros(log_z.shape)
    top = np.max(log_z[alive])
    z = np.where(alive, np.exp(np.where(alive, log_z, top) - top), 0.0)
    p = z / z.sum()
    if covariance is not None:
        c = np.where(np.outer(alive, alive) & np.isfinite(covariance), covariance, 0.0)
        jac = np.diag(p) - np.outer(p, p)
        return p, np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", jac, c, jac), 0.0))
    s2 = np.where(alive, np.asarray(log_z_se, float) ** 2, 0.0)
    s2 = np.where(np.isfinite(s2), s2, 0.0)
    total = np.sum(p**2 * s2)
    var = p**2 * ((1 - p) ** 2 * s2 + (total - p**2 * s2))
    return p, np.sqrt(var)


def allocation(p: np.ndarray, acceptance: np.ndarray, alive: np.ndarray, floor: float,
               least: np.ndarray | None = None) -> np.ndarray:
    """Proposal probabilities for the next population: proportional to s_m / a_m (so the
    accepted new particles follow the shares s), mixed with the uniform choice so every alive
    model gets at least ``floor`` of the proposals (at most half of them in all). s is the
    model probabilities ``p``, each raised to ``least`` (a model's least share of the new
    particles, at most 1 / (2 n_alive) each), so a rare model keeps enough new particles for
    its bound and its evidence (:data:`abcns.settings.LEAST_NEW_PER_DIMENSION`)."""
    n_alive = int(np.count_nonzero(alive))
    out = np.zeros(p.shape)
    if n_alive == 0:
        return out
    share = np.where(alive, p, 0.0)
    if least is not None and share.sum() > 0:
        share = share / share.sum()
        share = np.where(alive, np.maximum(share, np.minimum(least, 0.5 / n_alive)), 0.0)
    want = np.where(alive, share / np.clip(acceptance, 0.01, 1.0), 0.0)
    want = want / want.sum() if want.sum() > 0 else alive / n_alive
    f = min(floor, 0.5 / n_alive)
    out = np.where(alive, (1.0 - n_alive * f) * want + f, 0.0)
    return out / out.sum()


def alive(counts: np.ndarray, n_proposed: np.ndarray, previous: Evidence | None) -> np.ndarray:
    """The models alive in a population: those with particles in it, and those alive after
    the previous population that proposed in it. A model alive after a population has
    survivors in the next, unless it is a copy held by its twin's particles
    (``abcns.nested``, "relayed"), which has only the new particles it is given."""
    out = np.asarray(counts) > 0
    if previous is not None:
        out |= (previous.death == ALIVE) & (np.asarray(n_proposed) > 0)
    return out


@dataclass(frozen=True)
class Estimate:
    """One population's evidence estimate (:func:`estimate`), per model: log Z at eps_t and
    its variance, the prediction at eps_{t+1} and its variance, and the probabilities both
    give (``se_next``: the standard errors of ``p_next``)."""

    log_z: np.ndarray
    var_z: np.ndarray
    log_z_next: np.ndarray
    var_next: np.ndarray
    p_now: np.ndarray
    p_next: np.ndarray
    se_next: np.ndarray


def estimate(which: np.ndarray, distances: np.ndarray, epsilon: float, epsilon_next: float, n_proposed: np.ndarray,
             n_accepted: np.ndarray, previous: Evidence | None, mixture: Mixture) -> Estimate:
    """The evidence of population t (accepted at ``epsilon``; ``which``, ``distances``: its
    particles' models and distances) from the ``mixture`` grown with it: log Z at
    ``epsilon`` and at ``epsilon_next`` (the prediction), each with its variance. A model
    alive now (:func:`alive`; ``previous``: the previous population's evidence, None for
    the first) with no particle below ``epsilon`` (a copy whose twin's particles drew its
    bound, none of its proposals accepted) takes log Z from this population's acceptance,
    0 of n, in its region: log((1/2) / (n + 1)) + log V (:func:`log_share`; finite: a share
    of zero must not declare a model dead on its own). A model with none of this
    population's particles below ``epsilon_next`` has no prediction there (-inf: it dies,
    or is relayed by its twin, ``abcns.nested._relayed``)."""
    n_models = n_proposed.shape[0]
    counts = np.bincount(which, minlength=n_models)
    alive_now = alive(counts, n_proposed, previous)
    log_z, var_z = mixture.log_z(epsilon)
    if previous is not None:
        log_a, var_a = log_share(n_accepted, n_proposed)
        none = ~np.isfinite(log_z) & np.isfinite(previous.log_volume)
        log_z = np.where(none, log_a + previous.log_volume, log_z)
        var_z = np.where(none, var_a + previous.log_volume_se**2, var_z)
    log_z = np.where(alive_now, log_z, -np.inf)
    var_z = np.where(alive_now, var_z, np.inf)
    p_now, _ = probabilities(log_z, np.sqrt(var_z))
    capacity = np.bincount(which, weights=distances < epsilon_next, minlength=n_models) > 0
    log_next, var_next = mixture.log_z(epsilon_next)
    log_next = np.where(capacity & np.isfinite(log_z), log_next, -np.inf)
    var_next = np.where(np.isfinite(log_next), var_next, np.inf)
    p_next, se_next = probabilities(log_next, np.sqrt(var_next))
    return Estimate(log_z, var_z, log_next, var_next, p_now, p_next, se_next)
