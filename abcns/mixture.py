"""Importance nested sampling's evidence: every particle a run has drawn, weighted by the
mixture of the regions that proposed them (Feroz, Hobson, Cameron & Pettitt 2019,
"Importance nested sampling and the MultiNest algorithm", Open J. Astrophys. 2).

Population i + 1 proposes model m's new particles uniformly in a region of prior mass V_i:
the prior box (population 1, V_0 = 1), then the bound B_i fitted after population i, inside
the box (``Evidence.log_volume``), n_{i+1} proposals (``Evidence.n_proposed``, simulated or
failed; redraws outside the box are not proposals). Over the run's first t populations the
proposals come from the mixture S_t(x) = sum_{i < t} n_{i+1} 1{x in B_i} / V_i, which holds
the whole box (population 1's term); so for any eps <= eps_t

    Z_m(eps) = sum over m's new particles x of populations 1..t with d(x) < eps of 1 / S_t(x)

(a proposal rejected in population i has d >= eps_i >= eps and counts 0). No coverage of
the accepted region by a bound is needed: what B_{t-1} misses of it is counted through the
older regions that held it. The standard error is that of n = sum_i n_i independent draws
from the mixture (:func:`log_total`, an upper bound for the deterministic mixture's).

One correction: a particle that B_i was fitted to lies inside B_i by construction, where a
fresh point of the region there might not. Its membership of B_i is read leave-one-out
(:func:`held_without`: its group of ``bounds.union_groups`` refitted without it), measured
with the bound's geometry (``Population.held``). Read in-sample instead, the closed-form
copies' log Z ran 0.07-0.08 low (docs/benchmarks.md, "The coverage's two biases").

A particle leaves the sum once the tolerance falls to its distance; its sum S is then final
(the shell it lies in, eps_{u+1} <= d < eps_u, is reached by the proposals of populations
1..u only), and the likelihood reading (``abcns.likelihood.read``) weighs every particle ever
drawn by L(d) / S. :class:`Mixture` holds this per model between populations, grown one
population at a time (:meth:`Mixture.grown`); a resumed run grows it again over its stored
populations (:meth:`Mixture.of`), in the same steps, so the same bits.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from abcns import bounds as bd
from abcns import ellipsoid as ell

#: a particle's part in its model's new bound (``Population.held``): not one of the points it
#: was fitted to (its membership is read as it is), or one that the bound refitted without it
#: leaves OUTSIDE or HELD
NOT_FITTED, OUTSIDE, HELD = -1, 0, 1


def inside_without_each(x: np.ndarray, f0: float) -> np.ndarray | None:
    """For each of the n points ``x`` of one group: whether it lies inside the covariance
    ellipsoid of the other n - 1 scaled to hold them all and enlarged by ``f0`` (what
    ``ellipsoid.fit_many`` would fit to them, unless its covariance needs repair), by rank-one
    downdates: with u = x - mean, S = U^T U, W = U S^-1 and g_ij = w_i . u_j, removing point i
    moves the mean by u_i / (n - 1) and S by -n / (n - 1) u_i u_i^T (Sherman-Morrison), so
    every Mahalanobis distance under every leave-one-out fit comes from g. Point i is held when
    its own distance is within f0 of the largest of the others'; that largest is at least the
    distance of the point farthest out in-sample (one column of g), which settles most points,
    and only the rest read their whole row (O(n d^2) and O(n) a row, against O(n^2) for all
    of g: 700 points in 3 dimensions, 6 ms -> 0.3 ms; 45 in 11, 0.05 ms against 0.1 ms a
    refit). None where n - 1 <= d or S is singular."""
    n, d = x.shape
    if n - 1 <= d:
        return None
    u = x - x.mean(axis=0)
    try:
        w = np.linalg.solve(u.T @ u, u.T).T
    except np.linalg.LinAlgError:
        return None
    k, c, h = n / (n - 1), 1.0 / (n - 1), np.einsum("ij,ij->i", w, u)
    denom = 1.0 - k * h  # zero when point i alone spans a direction
    if not np.all(denom > 1e-12):
        return None

    def without(i: np.ndarray, j: np.ndarray, g: np.ndarray) -> np.ndarray:
        """x_j's squared distance when point i is left out (g = g_ij; arrays that broadcast):
        (n - 2) (w^T S^-1 w + k (w^T S^-1 u_i)^2 / (1 - k h_i)), w = u_j + u_i / (n - 1)."""
        return (n - 2) * (h[j] + 2 * c * g + c * c * h[i] + k * (g + c * h[i]) ** 2 / denom[i])

    own = (n - 2) * (k * k * h + k * (k * h) ** 2 / denom)  # x_i's, x_i - mean_i = k u_i
    limit = f0 * (1.0 + 1e-10) * (1.0 + ell.CONTAINS_SLACK)
    every = np.arange(n)
    far, second = np.argsort(h)[::-1][:2]
    witness = np.where(every == far, second, far)  # the point farthest out in-sample, but i itself
    held = own <= limit * without(every, witness, np.einsum("ij,ij->i", w, u[witness]))
    for i in np.flatnonzero(~held):  # the largest of the others' distances, from its whole row
        row = without(np.full(n, i), every, u @ w[i])
        row[i] = -np.inf
        held[i] = own[i] <= limit * row.max()
    return held


def held_without(points: np.ndarray, n_own: int, bound: bd.Union, groups: list[np.ndarray],
                 enlargement: float) -> np.ndarray:
    """Whether ``bound``, whose ellipsoid j ``bounds.fit_union_groups`` fitted to the rows
    ``groups[j]`` of ``points``, holds each of the first ``n_own`` points when its ellipsoid
    is refitted without that point (the others as they are): by downdates
    (:func:`inside_without_each`) where the ellipsoid's covariance needed no repair, else by
    refitting. A point the fit left out (an outlier) is read as it is."""
    held = ell.n_containing(bound, points[:n_own]) > 0
    for j, rows in enumerate(groups):
        own = rows[rows < n_own]
        if not own.size:
            continue
        fast = inside_without_each(points[rows], enlargement) if bound[j].note == "" else None
        if fast is not None:
            without = fast[rows < n_own]
        elif rows.size > 1:
            refits = ell.fit_many([points[rows[rows != i]] for i in own], [bound[j]] * own.size,
                                  enlargement=enlargement)
            without = np.array([bool(ell.n_containing((e,), points[i : i + 1])[0])
                                for e, i in zip(refits, own, strict=True)])
        else:
            without = np.zeros(own.size, bool)  # its ellipsoid goes with it
        rest = bound[:j] + bound[j + 1 :]
        in_rest = ell.n_containing(rest, points[own]) > 0 if rest else np.zeros(own.size, bool)
        held[own] = without | in_rest
    return held


def log_total(log_w: np.ndarray, n: int) -> tuple[float, float]:
    """(log of the sum of the weights exp(``log_w``), its standard error) for an estimate over
    ``n`` proposals (the weights of those not kept are 0): that of ``n`` independent draws from
    the mixture, var(n w) / n, relative to the sum."""
    top = float(np.max(log_w))
    w = np.exp(log_w - top)
    z = float(w.sum())
    return top + math.log(z), math.sqrt(max(float(np.sum((w * n) ** 2)) / n - z**2, 0.0) / n) / z


def volume_variance(log_w: np.ndarray, log_v: np.ndarray) -> float:
    """The variance the regions' volumes (each log V_i measured with variance var_i by Monte
    Carlo: :data:`abcns.nested.VOLUME_DRAWS`) give the log of a sum of weights exp(``log_w``),
    each weight w = f(x) / S(x): d log w / d log V_i = c_i(x) / S(x), with c_i(x) = n_i / V_i
    1{x in B_i}; so var log sum w = sum_i (sum_x a_x c_i(x) / S(x))^2 var_i with a_x = w_x /
    sum w, at most sum_x a_x v(x) (Jensen), v(x) = sum_i (c_i(x) / S(x))^2 var_i = u(x) /
    S(x)^2 (``log_v``: its log, the particle's own)."""
    top = float(np.max(log_w))
    a = np.exp(log_w - top)
    return float(np.sum(a * np.exp(log_v)) / np.sum(a))


def log_estimate(log_w: np.ndarray, log_v: np.ndarray, n: int) -> tuple[float, float]:
    """(log of the sum of the weights exp(``log_w``) over ``n`` proposals, its variance): the
    draws' (:func:`log_total`) and the regions' volumes' (:func:`volume_variance`, ``log_v``
    each particle's log u / S^2)."""
    log_z, se = log_total(log_w, n)
    return log_z, se**2 + volume_variance(log_w, log_v)


@dataclass(frozen=True, eq=False)
class Particles:
    """Some of one model's new particles: ``theta`` (n, d), the same in its bounds' frame
    (``x``), ``distances``, ``log_s`` (log S at each: the mixture of the regions that could
    have proposed it), ``log_u`` (log of the sum over those regions of (n / V)^2 var log V:
    its weight's variance from the regions' volumes is u / S^2, :func:`volume_variance`)
    and ``ids`` (its number in the run, to find it among a population's rows)."""

    theta: np.ndarray
    x: np.ndarray
    distances: np.ndarray
    log_s: np.ndarray
    log_u: np.ndarray
    ids: np.ndarray

    FIELDS = ("theta", "x", "distances", "log_s", "log_u", "ids")

    def take(self, rows: np.ndarray) -> Particles:
        return Particles(*(getattr(self, f)[rows] for f in self.FIELDS))

    @staticmethod
    def join(parts: Sequence[Particles], d: int) -> Particles:
        if not parts:
            return Particles(np.zeros((0, d)), np.zeros((0, d)), np.zeros(0), np.zeros(0), np.zeros(0),
                             np.zeros(0, np.int64))
        return Particles(*(np.concatenate([getattr(p, f) for p in parts]) for f in Particles.FIELDS))


#: one population's proposal region of a model: its bound (None: the prior box), log(n / V)
#: (the population's proposals over the region's prior mass) and log((n / V)^2 var log V)
#: (-inf: the box, whose volume is exact)
Column = tuple[bd.Union | None, float, float]


def _add(log_s: np.ndarray, log_u: np.ndarray, inside: np.ndarray, column: Column,
         log_r: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(log S, log u) with ``column``'s terms added where ``inside``, each times r (``log_r``
    per row; None: 1) and its u term times r^2."""
    log_s, log_u = log_s.copy(), log_u.copy()
    r = 0.0 if log_r is None else log_r[inside]
    log_s[inside] = np.logaddexp(log_s[inside], column[1] + r)
    log_u[inside] = np.logaddexp(log_u[inside], column[2] + 2 * r)
    return log_s, log_u


def _sums(columns: Sequence[Column], x: np.ndarray, log_s: np.ndarray | None = None, log_u: np.ndarray | None = None,
          log_r: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(log S, log u) over ``columns`` at each row of ``x`` (-inf outside all), added to
    ``log_s`` and ``log_u`` (None: none yet), each term times r (:func:`_add`)."""
    if log_s is None or log_u is None:
        log_s, log_u = np.full(x.shape[0], -np.inf), np.full(x.shape[0], -np.inf)
    for column in columns:
        inside = np.ones(x.shape[0], bool) if column[0] is None else ell.n_containing(column[0], x) > 0
        log_s, log_u = _add(log_s, log_u, inside, column, log_r)
    return log_s, log_u


@dataclass(frozen=True, eq=False)
class Mixture:
    """A run's particles and the mixture of its proposal regions, per model, after a
    population (immutable: :meth:`grown` makes the next). ``active[m]``: model m's new
    particles below that population's tolerance, their S still growing; ``left[m]``: those
    that left, their S final; ``columns[m]``: every proposal region of m so far; ``n[m]``:
    its proposals in all; ``row_ids``: the ids of that population's particles, row by row;
    ``next_id``: the next new particle's; ``n_populations``: the populations grown so far;
    ``families[m]``: the models m is one model with
    (m and its ``same_model_as`` copies, in model order: ``abcns.priors.same_models``).

    A family's copies are one model under several priors p_k, so every copy's proposals are
    draws of the one parameter: from the family's mixture G(theta) = sum_k p_k(theta)
    S_k(theta) in the parameters' own units, and each copy m's evidence is read from all of
    them, each weighted by p_m / G (multiple importance sampling, the balance heuristic:
    Veach & Guibas 1995). A particle's ``log_s`` is log G / p_j for its own copy j (S_j
    itself for a model without copies), so copy m weighs it by p_m / p_j / (G / p_j). A copy
    whose prior hides a mode its twin's finds is read with that mode (the cyclic test gill)."""

    frames: tuple[bd.Frame, ...]
    dims: tuple[int, ...]
    families: tuple[tuple[int, ...], ...]
    active: tuple[Particles, ...]
    left: tuple[tuple[Particles, ...], ...]
    columns: tuple[tuple[Column, ...], ...]
    n: np.ndarray
    row_ids: np.ndarray
    next_id: int
    n_populations: int

    @classmethod
    def empty(cls, frames: Sequence[bd.Frame], dims: Sequence[int],
              copies: Sequence[Sequence[int]] | None = None) -> Mixture:
        """No particle yet; ``copies[m]``: the models m is the same model as
        (``abcns.priors.same_models``; None: none)."""
        k = len(dims)
        families = tuple(tuple(sorted({m, *(copies[m] if copies is not None else ())})) for m in range(k))
        return cls(tuple(frames), tuple(dims), families, tuple(Particles.join([], d) for d in dims), ((),) * k,
                   ((),) * k, np.zeros(k, np.int64), np.zeros(0, np.int64), 0, 0)

    @classmethod
    def of(cls, populations: Sequence, frames: Sequence[bd.Frame], dims: Sequence[int],
           copies: Sequence[Sequence[int]] | None = None, grown: Mixture | None = None) -> Mixture:
        """The mixture after ``populations`` (ABC-NS populations with their evidence), grown
        as the run grew it. ``grown``: the mixture the run itself grew, when the caller holds
        it (``RunEnd.mixture``), taken as it is when it is this one (grown over as many
        populations and proposals, in the same frames and families), the same bits without
        growing it again (a §4.1 job's summary: 0.15 s of its 1.5 s)."""
        mixture = cls.empty(frames, dims, copies)
        if grown is not None and mixture.same_as(grown, populations):
            return grown
        for i, pop in enumerate(populations):
            previous = populations[i - 1] if i else None
            first = int(np.count_nonzero(previous.survivors)) if previous is not None else 0
            mixture = mixture.grown(previous, pop.epsilon, pop.models, pop.theta, pop.distances,
                                    np.arange(pop.n_particles) >= first, pop.evidence.n_proposed)
        return mixture

    def same_as(self, other: Mixture, populations: Sequence) -> bool:
        """Whether ``other`` is this (empty) mixture grown over ``populations``."""
        n = sum((np.asarray(p.evidence.n_proposed, np.int64) for p in populations), np.zeros(len(self.dims), np.int64))
        return (other.n_populations == len(populations) and np.array_equal(other.n, n) and other.dims == self.dims
                and other.families == self.families
                and all(a.unit == b.unit for a, b in zip(other.frames, self.frames, strict=True)))

    def grown(self, previous, epsilon: float, which: np.ndarray, theta: np.ndarray, distances: np.ndarray,
              is_new: np.ndarray, n_proposed: np.ndarray) -> Mixture:
        """The mixture with the population accepted at ``epsilon`` (its particles ``which``,
        ``theta``, ``distances``, the survivors of ``previous`` first, then the ``is_new``
        ones; ``n_proposed``: its proposals per model). The particles at or above ``epsilon``
        leave, the region that proposed this population (``previous``'s bound, the prior box
        for the first) joins the sum of those that stay (its own model's and its copies'),
        then the new particles join with their sums over every region of their family so
        far."""
        ids = np.empty(which.shape[0], np.int64)
        if previous is not None:
            ids[~is_new] = self.row_ids[np.flatnonzero(previous.survivors)]
        n_new = int(np.count_nonzero(is_new))
        ids[is_new] = self.next_id + np.arange(n_new)
        active, left, columns = list(self.active), list(self.left), list(self.columns)
        n = self.n + np.asarray(n_proposed, np.int64)
        for m in range(len(self.dims)):
            stay = active[m].distances < epsilon
            if not stay.all():
                left[m] = (*left[m], active[m].take(~stay))
                active[m] = active[m].take(stay)
        for m in range(len(self.dims)):
            if n_proposed[m] > 0:
                column = self._column(previous, m, int(n_proposed[m]))
                for j in self.families[m]:
                    a = active[j]
                    if j == m:
                        inside, log_r = self._held(previous, m, column[0], a, a.x), None
                    else:  # a copy's particles inside m's prior box
                        rows, log_r = self._in_box(m, j, a.theta)
                        inside = np.zeros(a.ids.shape[0], bool)
                        inside[rows] = self._held(previous, m, column[0], a.take(rows), None)
                    log_s, log_u = _add(a.log_s, a.log_u, inside, column, log_r)
                    active[j] = Particles(a.theta, a.x, a.distances, log_s, log_u, a.ids)
                columns[m] = (*columns[m], column)
        for j, (frame, d) in enumerate(zip(self.frames, self.dims, strict=True)):
            rows = np.flatnonzero(is_new & (which == j))
            if rows.size:
                th = theta[rows, :d]
                x = frame.to_frame(th)
                log_s, log_u = _sums(columns[j], x)
                for k in self.families[j]:
                    if k != j:
                        inside, log_r = self._in_box(k, j, th)
                        part_s, part_u = _sums(columns[k], self.frames[k].to_frame(th[inside]), log_s[inside],
                                               log_u[inside], log_r[inside])
                        log_s[inside], log_u[inside] = part_s, part_u
                # drawn from the last region: inside it, whatever the rounding of the test
                outside = ~np.isfinite(log_s)
                log_s[outside], log_u[outside] = columns[j][-1][1], columns[j][-1][2]
                new = Particles(th, x, distances[rows], log_s, log_u, ids[rows])
                active[j] = Particles.join([active[j], new], d)
        return Mixture(self.frames, self.dims, self.families, tuple(active), tuple(left), tuple(columns), n, ids,
                       self.next_id + n_new, self.n_populations + 1)

    def _in_box(self, k: int, j: int, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the rows of copy j's ``theta`` inside copy k's prior box, log p_k / p_j at every
        row: the priors' densities in the parameters' units, -inf outside)."""
        inside = np.flatnonzero(self.frames[k].in_prior(theta))
        log_r = np.full(theta.shape[0], -np.inf)
        log_r[inside] = self.frames[k].log_prior_density(theta[inside]) - self.frames[j].log_prior_density(theta[inside])
        return inside, log_r

    @staticmethod
    def _column(previous, m: int, n_proposed: int) -> Column:
        """The region that proposed model m's particles of the population after ``previous``."""
        if previous is None:
            return None, math.log(n_proposed), -math.inf
        log_w = math.log(n_proposed) - float(previous.evidence.log_volume[m])
        se = float(previous.evidence.log_volume_se[m])
        return previous.ellipsoids[m], log_w, 2 * (log_w + math.log(se)) if se > 0 else -math.inf

    def _held(self, previous, m: int, bound: bd.Union | None, particles: Particles, x: np.ndarray | None) -> np.ndarray:
        """Which ``particles`` (model m's, at ``x`` in its frame, or a copy's inside m's prior
        box: None) lie in m's ``bound`` (None: the box), those it was fitted to
        (``previous.held[:, m]``) read leave-one-out."""
        if bound is None:
            return np.ones(particles.ids.shape[0], bool)
        if not particles.ids.size:
            return np.zeros(0, bool)
        inside = ell.n_containing(bound, self.frames[m].to_frame(particles.theta) if x is None else x) > 0
        if previous.held is None:
            return inside
        flags = previous.held[:, m]
        fitted = np.flatnonzero(flags != NOT_FITTED)
        if fitted.size:
            order = np.argsort(self.row_ids[fitted])
            known, flag = self.row_ids[fitted][order], flags[fitted][order]
            at = np.minimum(np.searchsorted(known, particles.ids), known.size - 1)
            found = known[at] == particles.ids
            inside[found] = flag[at[found]] == HELD
        return inside

    def weighed(self, m: int, active: bool = False) -> tuple[Particles, np.ndarray, int]:
        """(the particles model m's family is read from: every new particle of each of its
        copies so far, those that left, then those below the last tolerance, each with its S
        (final, or as it stands now); only the latter if ``active``; log p_k / p_j at each
        (rows) for each copy k of the family (columns, in ``families[m]``'s order; j the
        particle's own copy: 0 for k = j, -inf outside k's prior box); the family's proposals
        in all)."""
        family = self.families[m]
        parts, log_r = [], []
        for j in family:
            p = self.active[j] if active else Particles.join([*self.left[j], self.active[j]], self.dims[j])
            r = np.zeros((p.ids.shape[0], len(family)))
            for c, k in enumerate(family):
                if k != j:
                    r[:, c] = self._in_box(k, j, p.theta)[1]
            parts.append(p)
            log_r.append(r)
        n = int(sum(self.n[j] for j in family))
        return Particles.join(parts, self.dims[m]) if len(parts) > 1 else parts[0], np.concatenate(log_r), n

    def log_z(self, epsilon: float) -> tuple[np.ndarray, np.ndarray]:
        """(log Z_m(``epsilon``), its variance) per model, from its family's active particles
        below ``epsilon`` (at most the last population's tolerance) inside its prior box;
        -inf / inf for a model with none (:func:`log_estimate`)."""
        k = len(self.dims)
        log_z, var = np.full(k, -np.inf), np.full(k, np.inf)
        for m in range(k):
            p, log_r, n = self.weighed(m, active=True)
            r = log_r[:, self.families[m].index(m)]
            below = (p.distances < epsilon) & np.isfinite(r)
            if below.any():
                log_s = p.log_s[below]
                log_z[m], var[m] = log_estimate(r[below] - log_s, p.log_u[below] - 2 * log_s, n)
        return log_z, var
