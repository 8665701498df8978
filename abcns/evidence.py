"""The ABC evidence of each model, and the model probabilities it gives.

The ABC posterior probability of model m at tolerance eps is

    p(m | d < eps) = Z_m(eps) / sum_j Z_j(eps),   Z_m(eps) = prior mass of {theta : d < eps}

(equal model priors; for a stochastic simulator, the prior expectation of P(d < eps | theta)).
The paper reports particle shares instead (Eq. 12), which ignore how much prior volume lies
under eps. ABC-NS already counts what Z needs, every population:

- population 1 is rejection from the prior: Z_m = accepted / proposed for model m;
- later, model m's proposals are uniform on B_m, its bound (a union of ellipsoids) intersected
  with the prior box, so vol({d < eps_t} ∩ B_m) = a_m vol(B_m), with a_m the acceptance of
  m's new proposals. The bound misses a share 1 - c of the accepted region (c is measured by
  cross-validation when the bound is fitted), so the direct estimate is
  ``log Z = log a + log V - log c``, V the prior mass of B_m (Monte Carlo, in the unit box);
- the share r_m of m's new particles below the next tolerance predicts Z_m(eps_{t+1}) =
  Z_m(eps_t) r_m c_m / c'_m (the nested-sampling recursion; c_m and c'_m the coverages of
  the regions at eps_t and eps_{t+1} by the bound the new particles came from, both from its
  cross-validation: c'_m on the tested points below eps_{t+1}).

Each population's log Z combines the prediction from the previous population and the direct
estimate by inverse variance (binomial variances on the log scale at the Agresti-Coull
estimate; delta method), so the estimate gathers information over populations. Every term of
the standard error is derived in docs/design.md ("The evidence's standard error"). Pure
functions on arrays, one entry per model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from abcns import bounds as bd

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
    at t + 1 (NaN when there is none); ``coverage`` (measured on ``n_coverage`` points): the
    share of the accepted region that bound holds;
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
    coverage: np.ndarray
    n_coverage: np.ndarray
    allocation: np.ndarray
    n_proposed: np.ndarray
    n_accepted: np.ndarray
    death: np.ndarray

    FLOATS = ("log_z", "log_z_se", "log_z_next", "log_z_next_se", "log_volume", "log_volume_se",
              "coverage", "allocation")
    INTS = ("n_coverage", "n_proposed", "n_accepted", "death")


@dataclass(frozen=True, eq=False)
class Tested:
    """The coverage test of the bounds that proposed a population's new particles, point by
    point: the previous population's particles (``which``, ``distances``) and each one's
    part in its model's test (``flags``, :func:`abcns.bounds.coverage_test` codes)."""

    which: np.ndarray
    distances: np.ndarray
    flags: np.ndarray

    def below(self, epsilon: float, n_models: int) -> tuple[np.ndarray, np.ndarray]:
        """(coverage, points tested) of each model's bound on its tested points below
        ``epsilon``: the bound's coverage of the region there (:func:`abcns.bounds.coverage_of`)."""
        out = [bd.coverage_of(self.flags[(self.which == m) & (self.distances < epsilon)]) for m in range(n_models)]
        return np.array([c for c, _ in out]), np.array([n for _, n in out])


def log_share(k: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(log a, its variance) for a share a of k successes in n binomial trials, elementwise.

    The point is log(k / n); where k = 0, log((1/2) / (n + 1)) (finite: a share of zero
    must not declare a model dead on its own). The variance is the delta method's
    (1 - a) / (n a), evaluated at the Agresti-Coull estimate a = (k + 2) / (n + 4) (two
    successes and two failures added): (n - k + 2) / ((n + 4)(k + 2)). At a = k / n it would
    rest on the count of the rarer outcome, which is the error's own source: an acceptance
    near 1 with fewer rejections than due is too high and its variance too small at once
    (docs/design.md, "The evidence's standard error"). Infinite where n = 0."""
    k, n = np.asarray(k, float), np.asarray(n, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        log = np.where(k > 0, np.log(k / np.maximum(n, 1.0)), np.log(0.5 / (n + 1.0)))
        var = np.where(n > 0, (n - k + 2.0) / ((n + 4.0) * (k + 2.0)), np.inf)
    return log, var


def log_coverage_variance(coverage: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Variance of log c for a coverage c measured by ``bounds.coverage`` on n points: the
    binomial error of the held-out share (at least one point's worth), plus the error of its
    1/n correction, which halves the share the half-fits miss and is uncertain by as much as
    it corrects (1 - c); zero where nothing was measured (n = 0)."""
    c, n = np.asarray(coverage, float), np.asarray(n, float)
    m = np.maximum(n, 1.0)
    return np.where(n > 0, np.maximum(1.0 - c, 1.0 / m) / (np.maximum(c, 1e-12) * m) + (1.0 - c) ** 2, 0.0)


def coverage_term_next(var_c: np.ndarray, w_pred: np.ndarray) -> np.ndarray:
    """What log c adds to the variance of the prediction log Z + log r + log c - log c'.

    log Z holds -log c with the direct estimate's weight 1 - w (w: the prediction's weight),
    so the sum holds +log c with weight w: its variance w^2 var_c replaces the (1 - w)^2 var_c
    log Z carries, a change of (2 w - 1) var_c. Without c' measured (:func:`coverage_ratio`)
    the prediction takes c' = 1, the bound's misses outside the region at the next tolerance;
    at worst they lie inside it, which is then short of at most (1 - c) / r: that share enters
    as an error of its own size (``unmeasured``)."""
    return (2.0 * np.asarray(w_pred, float) - 1.0) * var_c


def unmeasured(coverage: np.ndarray, log_r: np.ndarray) -> np.ndarray:
    """The variance of log c' taken as 0 where it is not measured: ((1 - c) / r)^2, at most 1
    (:func:`coverage_term_next`)."""
    r = np.exp(np.minimum(np.asarray(log_r, float), 0.0))
    return np.minimum((1.0 - np.asarray(coverage, float)) / np.maximum(r, 1e-12), 1.0) ** 2


def coverage_ratio(coverage: np.ndarray, coverage_next: np.ndarray,
                   n_next: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(log(c / c'), the variance log c' adds) for a bound's coverage c of a region and c'
    of the smaller region at the next tolerance, measured on the ``n_next`` tested points
    inside it (:meth:`Tested.below`). log c' is a coverage measured like c and carries
    :func:`log_coverage_variance` as c does, its halving law's uncertainty included; its
    covariance with log c (its points are a subset of c's) is not subtracted. The delta
    method's smaller variance of log(c / c') (the two shares' binomial errors and (c - c')^2
    for the halving) was measured too small: on the cyclic tests' copies (18 runs replayed)
    their split's z-scores had sd 1.15, against 0.98 with this one (docs/design.md)."""
    c, c1 = np.maximum(np.asarray(coverage, float), 1e-12), np.maximum(np.asarray(coverage_next, float), 1e-12)
    return np.log(c) - np.log(c1), log_coverage_variance(c1, n_next)


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


def probabilities(log_z: np.ndarray, log_z_se: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """p_m = Z_m / sum Z and its standard error (delta method on independent log Z):
    var p_m = p_m^2 [(1 - p_m)^2 s_m^2 + sum_{j != m} p_j^2 s_j^2]."""
    log_z = np.asarray(log_z, float)
    alive = np.isfinite(log_z)
    p = np.zeros(log_z.shape)
    if not alive.any():
        return p, np.zeros(log_z.shape)
    top = np.max(log_z[alive])
    z = np.where(alive, np.exp(np.where(alive, log_z, top) - top), 0.0)
    p = z / z.sum()
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


def estimate(which: np.ndarray, distances: np.ndarray, is_new: np.ndarray, epsilon_next: float,
             n_proposed: np.ndarray, n_accepted: np.ndarray, previous: Evidence | None,
             tested: Tested | None = None) -> Estimate:
    """The evidence of population t from its counts and the previous population's evidence
    (its prediction at eps_t and its bounds' geometry): the two estimates of log Z at eps_t
    combined by inverse variance, then the prediction at ``epsilon_next``. ``which``: each
    particle's model; ``is_new``: drawn in this population (not a survivor); ``previous``
    None for the first population (rejection from the priors: Z = accepted / proposed,
    exactly); ``tested``: the previous population's coverage test, point by point (None:
    not recorded; the prediction then takes c' = 1). docs/design.md, "The evidence's
    standard error", derives every term."""
    n_models = n_proposed.shape[0]
    counts = np.bincount(which, minlength=n_models)
    alive_now = alive(counts, n_proposed, previous)
    if previous is None:
        log_z, var_z = log_share(n_accepted, n_proposed)
        cover, var_c, w_pred = np.ones(n_models), np.zeros(n_models), np.zeros(n_models)
    else:
        log_a, var_a = log_share(n_accepted, n_proposed)
        cover = np.where(previous.n_coverage > 0, np.maximum(previous.coverage, 1e-12), 1.0)
        var_c = log_coverage_variance(cover, previous.n_coverage)
        direct = log_a + previous.log_volume - np.log(cover)
        var_pred = previous.log_z_next_se**2
        # a coverage not measured (fewer than 4 of the bound's new particles) is unknown, not 1:
        # a bound fitted to a few survivors can miss most of the region, so the direct estimate
        # then has no weight and the prediction carries log Z
        var_direct = np.where(previous.n_coverage > 0, var_a + previous.log_volume_se**2 + var_c, np.inf)
        log_z, var_z = combine(previous.log_z_next, var_pred, direct, var_direct)
        with np.errstate(invalid="ignore"):  # the prediction's weight in the combination
            w_pred = np.where(np.isfinite(var_pred), np.nan_to_num(var_z / var_pred, nan=1.0, posinf=1.0), 0.0)
    log_z = np.where(alive_now, log_z, -np.inf)
    var_z = np.where(alive_now, var_z, np.inf)
    p_now, _ = probabilities(log_z, np.sqrt(var_z))

    # the prediction at eps_next: the share of each model's new particles below it, times
    # c / c' (the coverages of the regions at eps_t and eps_next by the bound they were drawn
    # from; c' = 1 where it is not measured: the bound's misses then taken at the region's edge)
    below = distances < epsilon_next
    k_new = np.bincount(which, weights=is_new & below, minlength=n_models)
    n_new = np.bincount(which, weights=is_new, minlength=n_models)
    k_all = np.bincount(which, weights=below, minlength=n_models)
    k_r, n_r = np.where(n_new > 0, k_new, k_all), np.where(n_new > 0, n_new, counts)
    log_r, var_r = log_share(k_r, n_r)
    capacity = k_all > 0
    if previous is not None and tested is not None:
        cover_next, n_next = tested.below(epsilon_next, n_models)
        measured = (previous.n_coverage > 0) & (n_next > 0)
        log_q, var_q = coverage_ratio(cover, cover_next, n_next)
    else:
        measured, log_q, var_q = np.zeros(n_models, bool), np.zeros(n_models), np.zeros(n_models)
    log_q = np.where(measured, log_q, np.log(cover))
    var_q = np.where(measured, var_q, unmeasured(cover, log_r))
    log_z_next = np.where(capacity, log_z + log_r + log_q, -np.inf)
    var_next = np.where(capacity, var_z + var_r + (coverage_term_next(var_c, w_pred) + var_q), np.inf)
    p_next, se_next = probabilities(log_z_next, np.sqrt(var_next))
    return Estimate(log_z, var_z, log_z_next, var_next, p_now, p_next, se_next)
