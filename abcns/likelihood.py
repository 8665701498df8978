"""The Gaussian reading of a run: every population's new particles weighted by the likelihood.

With the NMSE and independent Gaussian noise of variance ``v`` per sample in distance units
(``abcns.noise``), the likelihood is ``L(theta) = C exp(-d(theta) / (2 v))``, and nested
sampling's identity (Skilling 2006) over the ABC evidence ``X_m(eps)`` (``abcns.evidence``)
gives model m's exact evidence

    Z_m ~ sum_t X_m(eps_t) mean over m's new particles of population t of
          exp(-d / (2 v)) 1{d >= eps_{t+1}},

with no cut in model m's last population with new particles. The same weights make the
particles an importance sample of model m's exact posterior; survivors are left out (each
was a new particle once, where it is counted). Without a stated noise, its variance is
integrated out under Jeffreys' prior (:func:`marginal`). In a run stopped above its floor, a
model whose reading rests on fewer than 2 (d + 1) effective particles (:func:`enough`) takes
its posterior from the answer population's particles instead
(:meth:`abcns.result.Result.answer_draws`). A run at its floor holds its decision tolerance
while an alive model's reading is thin (:func:`thin`), and a model about to leave on a thin
reading first keeps its best particles below the next tolerance (:func:`kept`). The
derivation, why (issue W), the standard error and the limits: docs/design.md, "Reading by
the likelihood".
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from abcns.evidence import probabilities
from abcns.noise import METHODS, Floor


@dataclass(frozen=True, eq=False)
class Reading:
    """The likelihood-weighted answer of a run, per model: ``log_z`` and ``log_z_se`` (the
    log evidence, relative to a common constant; -inf / inf for a model with no particle),
    ``probabilities`` and ``se`` (Z / sum Z, delta method), ``ess`` (Kish's effective
    number of particles), and ``theta[m]`` / ``weights[m]``: the model's weighted
    particles (``theta`` (n, d_m), weights summing to 1)."""

    log_z: np.ndarray
    log_z_se: np.ndarray
    probabilities: np.ndarray
    se: np.ndarray
    ess: np.ndarray
    theta: tuple[np.ndarray, ...]
    weights: tuple[np.ndarray, ...]


@dataclass(frozen=True, eq=False)
class Record:
    """What the reading needs of one population: its new particles (``models``, ``theta``,
    ``distances``), its tolerance and the next, and each model's log X (the evidence at its
    tolerance) with its standard error."""

    models: np.ndarray
    theta: np.ndarray
    distances: np.ndarray
    epsilon: float
    epsilon_next: float
    log_z: np.ndarray
    log_z_se: np.ndarray


def record(pop, previous=None) -> Record:
    """``pop``'s record (an ABC-NS population with its evidence); ``previous``: the population
    before it, whose survivors come first among ``pop``'s particles (the new ones follow)."""
    first = 0 if previous is None or previous.survivors is None else int(np.count_nonzero(previous.survivors))
    return Record(pop.models[first:], pop.theta[first:], pop.distances[first:], pop.epsilon, pop.epsilon_next,
                  pop.evidence.log_z, pop.evidence.log_z_se)


def records(populations: Sequence) -> list[Record]:
    """The records of a run's populations, in order."""
    return [record(pop, populations[i - 1] if i else None) for i, pop in enumerate(populations)]


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


def spared(shells: Sequence[Record], dims: Sequence[int], floor: Floor | None, threshold: float,
           now: Record | None = None) -> np.ndarray | None:
    """The models the reading of ``shells`` so far (the run read as if it stopped now) keeps
    from death by probability: those whose probability plus three standard errors is at or
    above ``threshold``, and those it rests on fewer than 2 (d + 1) effective particles for
    (a model's few particles far from its best fit can hide most of its evidence), read
    without and with ``now`` (the population that decides: a model that dies keeps its
    particles in it, and they can thin the reading it leaves with: gill's uniform copy in
    the cyclic tests, seed 1, had 25 effective particles without its last population and
    3.2 with it); None without a reading (no floor, or an exact best fit)."""
    log_l = None if floor is None or not shells else of_floor(floor)
    if log_l is None:
        return None
    r = read(shells, dims, log_l)
    out = (r.probabilities + 3 * r.se >= threshold) | ~enough(r.ess, dims)
    if now is not None and not out.all():  # read again only where a model could die
        out |= ~enough(read([*shells, now], dims, log_l).ess, dims)
    return out


def kept(shells: Sequence[Record], dims: Sequence[int], floor: Floor | None, which: np.ndarray,
         distances: np.ndarray) -> tuple[float, list[int]]:
    """(the next tolerance, the models that hold it) after the population of ``shells[-1]``
    (its new particles; its ``epsilon_next``, the tolerance the population's distances give;
    ``which`` and ``distances``: all its particles, survivors too). A model with particles in
    it but none below that tolerance leaves the run (``no_particles``; with fewer than
    2 (d + 1) below it, its next bound is a fit of too few points, and it leaves soon after),
    and its reading ends with that population's region, {d < eps_t}, uncut. Where the common
    tolerance jumped far below that model's best fit, the likelihood inside that region
    varies by many e-folds and the reading weighs its few particles nearest the best fit: its
    evidence rests on a handful of them, and falls short of its own (a model that fits much
    worse than another: the cyclic test chiu's Bouc-Wen, on 2.5 effective particles, 2.5 nats
    below its own run's). While that reading (of ``shells``) rests on fewer than 2 (d + 1)
    effective particles (:func:`enough`, the rule that spares a model from death by
    probability), the next tolerance is raised so that the model keeps its 2 (d + 1) best
    particles (more than that in the population, else it leaves): each population then
    shrinks its region by its own nested sampling, towards its best fit, until its reading
    holds. The tolerance unchanged, no model, without a reading."""
    log_l = None if floor is None else of_floor(floor)
    eps = shells[-1].epsilon_next
    counts = np.bincount(which, minlength=len(dims))
    below = np.bincount(which, weights=distances < eps, minlength=len(dims))
    keep = np.array([2 * (d + 1) for d in dims])
    leaving = (counts > keep) & (below < keep)
    if log_l is None or not leaving.any():
        return eps, []
    leaving &= ~enough(read(shells, dims, log_l).ess, dims)
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


def thin(shells: Sequence[Record], dims: Sequence[int], floor: Floor | None, alive: np.ndarray) -> np.ndarray:
    """The ``alive`` models (boolean (n_models,)) whose reading of ``shells`` rests on fewer
    than :data:`HELD_EFFECTIVE` (d + 1) effective particles, or fewer than :data:`HELD_LEAST`;
    none without a reading."""
    log_l = None if floor is None or not shells else of_floor(floor)
    if log_l is None:
        return np.zeros(len(dims), dtype=bool)
    return alive & ~enough(read(shells, dims, log_l).ess, dims, HELD_EFFECTIVE, HELD_LEAST)


def held_target(n_dim: int) -> int:
    """The effective particles a run at its floor holds its decision tolerance for (:func:`thin`):
    max(:data:`HELD_EFFECTIVE` (d + 1), :data:`HELD_LEAST`)."""
    return max(HELD_EFFECTIVE * (n_dim + 1), HELD_LEAST)


def regions(shells: Sequence[Record]) -> tuple[np.ndarray, np.ndarray]:
    """(each population's region, the tolerance that cuts it) of a run's ``shells``.
    Consecutive populations accepted at one tolerance that did not move (eps_{t+1} = eps_t: a
    run held at its decision tolerance while its reading is thin, :func:`thin`) sample one
    region, {d < eps}, and their new particles are read together; the cut is that of the last
    of them. Every other population is a region of its own, cut at its eps_{t+1}."""
    region = np.zeros(len(shells), dtype=np.int64)
    for i in range(1, len(shells)):
        before = shells[i - 1]
        held = before.epsilon_next == before.epsilon == shells[i].epsilon
        region[i] = region[i - 1] + (0 if held else 1)
    cut_of = {int(g): rec.epsilon_next for g, rec in zip(region, shells, strict=True)}  # the last population's
    return region, np.array([cut_of[int(g)] for g in region])


def read(shells: Sequence[Record], dims: Sequence[int], log_likelihood: Callable[[np.ndarray], np.ndarray]) -> Reading:
    """The reading of an ABC-NS run's population ``shells`` (:func:`records`) of models of
    ``dims`` parameters, with ``log_likelihood`` of a distance (:func:`gaussian`,
    :func:`marginal`; relative to the best fit's, so the weights stay finite). A region that
    several populations sampled (:func:`regions`) counts the mean of their estimates."""
    n_models = len(dims)
    region, cut = regions(shells)
    last = np.full(n_models, -1)  # each model's last region with new particles
    readers = np.zeros((n_models, len(shells)))  # how many populations read each model's region
    for i, rec in enumerate(shells):
        there = np.unique(rec.models)
        last[there] = region[i]
        readers[there[np.isfinite(rec.log_z[there])], region[i]] += 1
    parts: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in range(n_models)]  # (theta, log weight)
    log_c: list[list[float]] = [[] for _ in range(n_models)]  # log of each population's contribution
    se_c: list[list[float]] = [[] for _ in range(n_models)]  # its log X error
    for i, rec in enumerate(shells):
        for m in range(n_models):
            rows = rec.models == m
            n = int(np.count_nonzero(rows))
            if n == 0 or not np.isfinite(rec.log_z[m]):
                continue
            d = rec.distances[rows]
            log_l = log_likelihood(d)
            if region[i] < last[m]:
                log_l = np.where(d >= cut[i], log_l, -np.inf)
            log_w = rec.log_z[m] - np.log(n * readers[m, region[i]]) + log_l
            parts[m].append((rec.theta[rows, : dims[m]], log_w))
            top = np.max(log_w)
            if np.isfinite(top):
                log_c[m].append(float(top + np.log(np.sum(np.exp(log_w - top)))))
                se_c[m].append(float(rec.log_z_se[m]))
    log_z = np.full(n_models, -np.inf)
    log_z_se = np.full(n_models, np.inf)
    ess = np.zeros(n_models)
    thetas, weights = [], []
    for m in range(n_models):
        if not log_c[m]:
            thetas.append(np.zeros((0, dims[m])))
            weights.append(np.zeros(0))
            continue
        theta = np.concatenate([p[0] for p in parts[m]])
        log_w = np.concatenate([p[1] for p in parts[m]])
        shift = np.max(log_w)
        w = np.exp(log_w - shift)
        total = float(np.sum(w))
        log_z[m] = shift + np.log(total)
        share = np.exp(np.asarray(log_c[m]) - log_z[m])
        chained = float(np.sum(share * np.asarray(se_c[m])))
        # the shells' means: each population's part is X / n sum of n draws; its variance is
        # X^2 / n var(draw), estimated from the same draws
        var_mc = 0.0
        for _, lw in parts[m]:
            wi = np.exp(lw - shift)
            var_mc += wi.size * np.var(wi) if wi.size > 1 else wi.sum() ** 2
        log_z_se[m] = float(np.sqrt(chained**2 + var_mc / total**2))
        keep = w > 0
        thetas.append(theta[keep])
        weights.append(w[keep] / total)
        ess[m] = total**2 / float(np.sum(w**2))
    p, se = probabilities(log_z, log_z_se)
    return Reading(log_z, log_z_se, p, se, ess, tuple(thetas), tuple(weights))
