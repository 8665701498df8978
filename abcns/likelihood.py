"""The Gaussian reading of a run: every new particle it drew weighted by the likelihood.

With the NMSE and independent Gaussian noise of variance ``v`` per sample in distance units
(``abcns.noise``), the likelihood is ``L(theta) = C exp(-d(theta) / (2 v))``. Every new
particle x of model m is a draw from the mixture of the regions that proposed its
population and the earlier ones (``abcns.mixture``); in the shell between two tolerances
where it lies, eps_{u+1} <= d < eps_u, only the proposals of populations 1..u can land, so
with S(x) the mixture of those (final once the tolerance falls below x's distance)

    Z_m ~ sum over m's new particles x of L(x) / S(x),

model m's exact evidence (importance nested sampling: Feroz et al. 2019); the same weights
make the particles an importance sample of m's exact posterior. Survivors are not counted
again (each was a new particle once). ``same_model_as`` copies are read from every particle
of both, each weighted by L p_m / (sum_k p_k S_k) (:class:`abcns.mixture.Mixture`), in the
answer (:meth:`abcns.result.Result.reading`); the run's own steps read each copy alone.
Without a stated noise, its variance is integrated out under Jeffreys' prior
(:func:`marginal`). In a run stopped above its floor, a model whose reading rests on fewer
than 2 (d + 1) effective particles (:func:`enough`) takes its posterior from the answer
population's particles instead
(:meth:`abcns.result.Result.answer_draws`). A run at its floor holds its decision tolerance
while an alive model's reading is thin (:func:`thin`), and a model about to leave on a thin
reading first keeps its best particles below the next tolerance (:func:`kept`). The
derivation, why (issue W), the standard error and the limits: docs/design.md, "Reading by
the likelihood".
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from abcns.evidence import probabilities
from abcns.mixture import Mixture, log_estimate
from abcns.noise import METHODS, Floor


@dataclass(frozen=True, eq=False)
class Reading:
    """The likelihood-weighted answer of a run, per model: ``log_z`` and ``log_z_se`` (the
    log evidence, relative to a common constant; -inf / inf for a model with no particle),
    ``probabilities`` and ``se`` (Z / sum Z, delta method), ``ess`` (Kish's effective
    number of particles), ``theta[m]`` / ``weights[m]``: the model's weighted particles
    (``theta`` (n, d_m), weights summing to 1), and ``covariance``: the log Z's (n_models,
    n_models; off the diagonal only between ``same_model_as`` copies, read from the same
    particles: the split log Z_m - log Z_k has variance C_mm + C_kk - 2 C_mk)."""

    log_z: np.ndarray
    log_z_se: np.ndarray
    probabilities: np.ndarray
    se: np.ndarray
    ess: np.ndarray
    theta: tuple[np.ndarray, ...]
    weights: tuple[np.ndarray, ...]
    covariance: np.ndarray


def gaussian(variance: float, reference: float) -> Callable[[np.ndarray], np.ndarray]:
    """log L(d) - log L(reference) for Gaussian noise of a stated ``variance`` per sample in
    distance units: -(d - reference) / (2 v)."""
    return lambda d: -(d - reference) / (2.0 * variance)


def marginal(n_samples: int, reference: float) -> Callable[[np.ndarray], np.ndarray]:
    """The same for Gaussian noise of unknown variance, integrated out under Jeffreys' prior
    p(sigma) ~ 1 / sigma: L ~ (sum of squared residuals)^(-n / 2), so
    -(n / 2) log(d / reference). Near the best fit it is the Gaussian one with
    v = reference / n; farther out its tails are heavier, as the noise could be larger."""
    return lambda d: -0.5 * n_samples * np.log(d / reference)


def of_floor(floor: Floor) -> Callable[[np.ndarray], np.ndarray] | None:
    """The log likelihood a run's ``floor`` gives: :func:`gaussian` with a stated noise,
    :func:`marginal` with an estimated one; None when the best fit is exact (d = 0: no noise
    to weigh by)."""
    if not floor.best > 0:
        return None
    if METHODS[floor.method] == "stated":
        return gaussian(floor.variance, floor.best)
    return marginal(floor.n_samples, floor.best)


def enough(ess: np.ndarray, dims: Sequence[int], per: float = 2, least: float = 0) -> np.ndarray:
    """Whether each model's reading rests on at least ``per`` (d + 1) effective particles
    (2 by default), and at least ``least`` of them. Fewer than 2 (d + 1), and its weights sit
    on a handful of particles: a run stopped above its floor, whose last region is far wider
    than the posterior, weighs its few particles nearest the best fit (the cyclic test gill's
    BWBN at 80 populations: 2.7 effective particles, intervals 0.35-1.24 of the exact width);
    a model's few particles far from its best fit can hide most of its evidence."""
    return np.asarray(ess) >= np.maximum(per * (np.asarray(dims) + 1), least)


def spared(before: Mixture | None, dims: Sequence[int], floor: Floor | None, threshold: float,
           now: Mixture | None = None) -> np.ndarray | None:
    """The models the reading of the run so far (``before``: the run read as if it stopped
    before this population) keeps from death by probability: those whose probability plus
    three standard errors is at or above ``threshold``, and those it rests on fewer than
    max(5 (d + 1), 64) effective particles for (:func:`thin`'s bar: a model's evidence is
    final when it dies, and its few particles far from its best fit can hide most of it: the
    cyclic test chiu's losing uniform copy, seed 4, died on 37 whose core was thin, its split
    against its log copy 1.39 nats off; spared to 71, 0.07), read without and with this
    population (``now``: a model that dies keeps its particles in it, and they can thin the
    reading it leaves with: gill's uniform copy in the cyclic tests, seed 1, had 25 effective
    particles without its last population and 3.2 with it); None without a reading (no
    floor, an exact best fit, no particle yet)."""
    log_l = None if floor is None or before is None or not before.n.any() else of_floor(floor)
    if log_l is None or before is None:
        return None
    r = read(before, dims, log_l)
    out = (r.probabilities + 3 * r.se >= threshold) | ~enough(r.ess, dims, HELD_EFFECTIVE, HELD_LEAST)
    if now is not None and not out.all():  # read again only where a model could die
        out |= ~enough(read(now, dims, log_l).ess, dims, HELD_EFFECTIVE, HELD_LEAST)
    return out


def kept(mixture: Mixture, dims: Sequence[int], floor: Floor | None, epsilon_next: float, which: np.ndarray,
         distances: np.ndarray) -> tuple[float, list[int]]:
    """(the next tolerance, the models that hold it) after a population (``mixture``: grown
    with it; ``epsilon_next``: the tolerance its distances give; ``which`` and ``distances``:
    all its particles, survivors too). A model with particles in it but none below that
    tolerance leaves the run (``no_particles``; with fewer than 2 (d + 1) below it, its next
    bound is a fit of too few points, and it leaves soon after). Where the common tolerance
    jumped far below that model's best fit, the likelihood inside its region varies by many
    e-folds and the reading weighs its few particles nearest the best fit: its evidence rests
    on a handful of them, and falls short of its own (a model that fits much worse than
    another: the cyclic test chiu's Bouc-Wen, on 2.5 effective particles, 2.5 nats below its
    own run's). While that reading rests on fewer than 2 (d + 1) effective particles
    (:func:`enough`), the next
    tolerance is raised so that the model keeps its 2 (d + 1) best particles (more than that
    in the population, else it leaves): each population then shrinks its region by its own
    nested sampling, towards its best fit, until its reading holds. The tolerance
    unchanged, no model, without a reading."""
    log_l = None if floor is None else of_floor(floor)
    eps = epsilon_next
    counts = np.bincount(which, minlength=len(dims))
    below = np.bincount(which, weights=distances < eps, minlength=len(dims))
    keep = np.array([2 * (d + 1) for d in dims])
    leaving = (counts > keep) & (below < keep)
    if log_l is None or not leaving.any():
        return eps, []
    leaving &= ~enough(read(mixture, dims, log_l).ess, dims)
    for m in map(int, np.flatnonzero(leaving)):
        eps = max(eps, float(np.sort(distances[which == m])[keep[m]]))
    return eps, [int(m) for m in np.flatnonzero(leaving)]


#: a run at its decision tolerance accepts the next population there too while an alive
#: model's reading rests on fewer than HELD_EFFECTIVE (d + 1) effective particles
#: (:func:`thin`): measured on a degree-10 polynomial toy (11 parameters, tests/test_reading.py,
#: seeds 1-4), the first population there gave 2.8-5.1 of them and intervals 0.42-1.19 of the
#: exact widths, means up to 1.04 sd off; 2 (d + 1) gave 0.85-1.31 and 0.55 sd; 5 (d + 1),
#: 0.95-1.15 and 0.21 sd, for 10-20 % more simulations
HELD_EFFECTIVE = 5
#: and on fewer than HELD_LEAST, whatever d: a weighted mean's Monte Carlo error is about
#: 1 / sqrt(effective particles) posterior sd, whatever the model's dimension, and 5 (d + 1)
#: is only 10-25 for d = 1-4 (errors of 0.2-0.3 sd). 64 puts a mean within 0.25 sd at 2 of
#: its errors: the exact-Bayes benchmark's losing cubic-quintic (d = 4, seed 1), alive at the
#: end with 50 effective particles above its 5 (d + 1) = 25, had c 0.42 sd off (3 errors)
HELD_LEAST = 64
#: at most this many populations after the first accepted at the decision tolerance (each
#: adds about as many effective particles as that one: 13-19 populations for the toy)
HELD_POPULATIONS = 30


def thin(mixture: Mixture, dims: Sequence[int], floor: Floor | None, alive: np.ndarray) -> np.ndarray:
    """The ``alive`` models (boolean (n_models,)) whose reading of the run so far
    (``mixture``) rests on fewer than :data:`HELD_EFFECTIVE` (d + 1) effective particles, or
    fewer than :data:`HELD_LEAST`; none without a reading."""
    log_l = None if floor is None or not mixture.n.any() else of_floor(floor)
    if log_l is None:
        return np.zeros(len(dims), dtype=bool)
    return alive & ~enough(read(mixture, dims, log_l).ess, dims, HELD_EFFECTIVE, HELD_LEAST)


def held_target(n_dim: int) -> int:
    """The effective particles a run at its floor holds its decision tolerance for (:func:`thin`):
    max(:data:`HELD_EFFECTIVE` (d + 1), :data:`HELD_LEAST`)."""
    return max(HELD_EFFECTIVE * (n_dim + 1), HELD_LEAST)


def read(mixture: Mixture, dims: Sequence[int], log_likelihood: Callable[[np.ndarray], np.ndarray]) -> Reading:
    """The reading of an ABC-NS run's particles (``mixture``: :meth:`abcns.mixture.Mixture.of`
    its populations) of models of ``dims`` parameters, with ``log_likelihood`` of a distance
    (:func:`gaussian`, :func:`marginal`; relative to the best fit's, so the weights stay
    finite): every new particle x weighted by L(x) / S(x) (a copy's, ``same_model_as``, by
    L(x) p_m(x) / G(x) over its family's particles: ``abcns.mixture.Mixture``), the sum's
    standard error :func:`abcns.mixture.log_estimate`'s. Copies read from the same particles
    have correlated errors: the probabilities' standard errors take their covariance
    (:func:`covariance`)."""
    n_models = len(dims)
    log_z, log_z_se, ess = np.full(n_models, -np.inf), np.full(n_models, np.inf), np.zeros(n_models)
    thetas: list[np.ndarray] = [np.zeros((0, d)) for d in dims]
    weights: list[np.ndarray] = [np.zeros(0) for _ in dims]
    cov = np.zeros((n_models, n_models))
    for family in dict.fromkeys(mixture.families):
        part, log_r, n = mixture.weighed(family[0])
        if not part.ids.size:
            continue
        log_l = log_likelihood(part.distances)
        shares: dict[int, np.ndarray] = {}
        for c, m in enumerate(family):
            log_w = log_l + log_r[:, c] - part.log_s  # log_r 0 for a model's own particles
            if not np.isfinite(np.max(log_w)):
                continue
            log_z[m], var = log_estimate(log_w, part.log_u - 2 * part.log_s, n)
            log_z_se[m] = math.sqrt(var)
            cov[m, m] = var
            w = np.exp(log_w - log_z[m])
            keep = w > 0
            thetas[m] = part.theta[keep]
            weights[m] = w[keep] / w.sum()
            ess[m] = float(w.sum()) ** 2 / float(np.sum(w**2))
            shares[m] = w / w.sum()
        for a, b in itertools.combinations(shares, 2):
            cov[a, b] = cov[b, a] = covariance(shares[a], shares[b], n)
    p, se = probabilities(log_z, log_z_se, cov if any(len(f) > 1 for f in mixture.families) else None)
    return Reading(log_z, log_z_se, p, se, ess, tuple(thetas), tuple(weights), cov)


def covariance(a: np.ndarray, b: np.ndarray, n: int) -> float:
    """The covariance of log sum of two sets of weights over the same ``n`` independent draws
    (``a`` and ``b``, each normalised to sum to 1; 0 where a draw has none): sum a b - 1 / n,
    as :func:`abcns.mixture.log_total`'s variance is sum a^2 - 1 / n. The regions' volumes'
    part is left out (their share of either variance: 0.00005 of 0.0068 on the closed-form
    copies)."""
    return float(np.sum(a * b)) - 1.0 / n
