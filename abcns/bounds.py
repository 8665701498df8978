"""The region a model's proposals come from: a union of ellipsoids.

ABC-NS (paper, Algorithm 2) bounds the surviving particles of a model by one ellipsoid.
A curved or split accepted region is covered poorly by one ellipsoid, so a bound here is a
tuple of ellipsoids (one in the paper variant), found by recursive 2-means splits that
are kept only when the halves' ellipsoids hold less than ``SPLIT_GAIN`` (0.8) of the
volume of the one they replace (MultiNest and dynesty's ``bounding.py`` split this way
with their own thresholds; the code is our own). Every function is pure, and each random draw comes
from the generator it is given.

- :func:`fit_union` : points -> ellipsoids (each enlarged by f0);
- :func:`sample_union` : points uniform on the union (an ellipsoid is chosen by volume, a
  point uniform in it is kept with probability 1 / the number of ellipsoids holding it);
- :func:`union_volume` : Monte Carlo estimate of log vol(union ∩ box) and its standard error.

How much of the accepted region a bound misses needs no measure: the evidence counts it
through the older regions that held it (``abcns.mixture``). What no later region holds is
lost to the run, so a bound is never split finer than its points can show
(``POINTS_PER_ELLIPSOID``).
"""

from __future__ import annotations

import functools
import itertools

import numpy as np
from scipy.special import gammaincinv, logsumexp

from abcns import ellipsoid as ell
from abcns.priors import Model, in_box

Union = tuple[ell.Ellipsoid, ...]
#: halves replace a node only when their ellipsoids' total volume is below this share of it
#: (a convex region split by chance fluctuations of few points leaves gaps)
SPLIT_GAIN = 0.8
#: fewest points an ellipsoid of a split is fitted to (and at least 2 (d + 1)). Measured on
#: §4.1 (seeds 1-8): 10 needs ~23 % fewer simulations to eps 0.015 than 20; on the closed-form
#: toys both kept log Z within its standard error
LEAF_POINTS = 10
#: a bound has at most one ellipsoid per this many of the points it is fitted to (and at most
#: ``max_ellipsoids``): a few points split into several sets show no shape. A losing cubic
#: (3-d, 24-50 points below the next tolerance) bounded by 2-4 ellipsoids of 10-16 points held
#: 0.65-0.93 of its points left out one at a time, by one 0.93-0.98; its bounds lost the end of
#: its curved region where its posterior lies, population after population, and its log
#: evidence ended 46 nats low (linear-vs-cubic, data seed 4, seed 5). 64 kept it too, but §4.1's
#: winner (4-d, ~700 points) then got 10 ellipsoids instead of 16, for 38 % more simulations
#: (docs/benchmarks.md, "A rare model's bound")
POINTS_PER_ELLIPSOID = 32
#: a point is an outlier when its squared whitened radius exceeds the chi-square quantile
#: 1 - OUTLIER_TAIL / n, scaled by the points' median radius (see :func:`outliers`)
OUTLIER_TAIL = 0.01
#: k-means (Lloyd) iterations of a split
KMEANS_ITERATIONS = 25


def min_points(d: int) -> int:
    """Fewest points an ellipsoid of a split may be fitted to: 2 (d + 1)."""
    return 2 * (d + 1)


def _tree_sets(points: np.ndarray, max_ellipsoids: int) -> list[np.ndarray] | None:
    """The row sets (each ascending) of the at most ``max_ellipsoids`` ellipsoids of least
    total volume that hold ``points``, or None when the points have no covariance
    ellipsoid (singular covariance, or every point at the mean).

    The tree: a node's ellipsoid is its points' covariance ellipsoid scaled to hold them
    all; a node of at least 2 ``leaf`` points (``leaf`` = max(LEAF_POINTS, 2 (d + 1))) is
    split by a 2-means clustering in whitened coordinates, started at the means of the two
    sides of the points' mean along the leading eigenvector of its covariance (deterministic,
    ``KMEANS_ITERATIONS`` Lloyd steps at most), or, when 2-means leaves a half fewer than
    ``leaf`` and d + 1 points (a small group apart at one end), at the points' median along
    that eigenvector, when both halves have an ellipsoid; a node's best set of at most k
    ellipsoids is its own ellipsoid, or its halves' best sets together (k1 for the first half, k - k1 for the
    second, k1 of least total) when they hold less than ``SPLIT_GAIN`` of the volume of
    its best set of at most k - 1. Compiled (``abcns.compiled.tree_rows``): only the
    sets come from there, never an ellipsoid."""
    from abcns import compiled

    leaf = max(LEAF_POINTS, min_points(points.shape[1]))
    ok, rows, offsets = compiled.tree_rows(np.ascontiguousarray(points, dtype=float), max_ellipsoids, leaf,
                                           SPLIT_GAIN, KMEANS_ITERATIONS)
    return [rows[a:b] for a, b in itertools.pairwise(offsets)] if ok else None


def _radii(points: np.ndarray) -> np.ndarray | None:
    """Squared whitened radii of the points in their covariance ellipsoid (None as
    :func:`_tree_sets`)."""
    from abcns import compiled

    ok, r2 = compiled.radii(np.ascontiguousarray(points, dtype=float))
    return r2 if ok else None


def outliers(r2: np.ndarray, d: int) -> np.ndarray:
    """Which of n points in d dimensions, of squared whitened radii ``r2``, lie far outside
    the rest: squared radius above the chi-square (d) quantile 1 - OUTLIER_TAIL / n, rescaled
    so the points' median radius is the chi-square median. A Gaussian cloud loses a point in
    about 1 % of fits, a uniform one never; a stochastic simulator's lucky draw far from the
    accepted region (which would otherwise make the bound ten times larger) is left out, and
    the evidence counts what that leaves out through the older regions that held it."""
    scale = float(np.median(r2)) / _chi2_quantile(0.5, d)
    return r2 > _chi2_quantile(1.0 - OUTLIER_TAIL / r2.shape[0], d) * scale


def _chi2_quantile(q: float, d: int) -> float:
    """The chi-square (d) quantile q, as ``scipy.stats.chi2.ppf`` computes it (the same
    bits), without importing scipy.stats (a third of a second at every process start)."""
    return float(2.0 * gammaincinv(0.5 * d, q))


def union_groups(points: np.ndarray, max_ellipsoids: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """(the rows of ``points`` :func:`fit_union` keeps, ascending; the rows each of its
    ellipsoids is fitted to): far :func:`outliers` left out (while enough points stay), the
    kept points grouped by :func:`_tree_sets` into at most ``max_ellipsoids`` sets and one
    per ``POINTS_PER_ELLIPSOID`` points, or one group of them all."""
    kept = np.arange(points.shape[0])
    max_ellipsoids = min(max_ellipsoids, points.shape[0] // POINTS_PER_ELLIPSOID)
    if max_ellipsoids > 1 and points.shape[0] > points.shape[1] and (r2 := _radii(points)) is not None:
        far = outliers(r2, points.shape[1])
        if np.any(far) and np.count_nonzero(~far) > 2 * min_points(points.shape[1]):
            kept = kept[~far]
        sets = _tree_sets(points[kept], max_ellipsoids)
        if sets is not None and len(sets) > 1:
            return kept, [kept[r] for r in sets]
    return kept, [kept]


def fit_union(points: np.ndarray, enlargement: float, max_ellipsoids: int, fallback: ell.Ellipsoid) -> Union:
    """:func:`fit_union_groups`'s ellipsoids."""
    return fit_union_groups(points, enlargement, max_ellipsoids, fallback)[0]


def fit_union_groups(points: np.ndarray, enlargement: float, max_ellipsoids: int,
                     fallback: ell.Ellipsoid) -> tuple[Union, list[np.ndarray]]:
    """(ellipsoids that hold every point but far :func:`outliers`, each enlarged by
    ``enlargement`` (f0), one per group of :func:`union_groups`; those groups' rows).

    The points' ellipsoid (``abcns.ellipsoid.fit``, with ``fallback`` when the points define
    no shape) is split by 2-means (at the median where 2-means strands a small group),
    recursively, while each half keeps ``LEAF_POINTS`` and :func:`min_points` points; of the
    ellipsoids of that tree, the set of at most ``max_ellipsoids`` (and one per
    ``POINTS_PER_ELLIPSOID`` points) with the least total volume is kept (a node is replaced
    by its halves' best sets only when those hold less than ``SPLIT_GAIN`` of its volume)."""
    kept, groups = union_groups(points, max_ellipsoids)
    if len(groups) == 1:
        return tuple(ell.fit_many([points[kept]], fallback, enlargement=enlargement)), groups
    # the kept points' own ellipsoid is the groups' fallback shape, made only if one needs it
    return tuple(ell.fit_many([points[g] for g in groups], fallback=lambda: ell.fit(points[kept], fallback=fallback),
                              enlargement=enlargement)), groups


def _log_volumes(bound: Union) -> np.ndarray:
    return np.array([e.log_volume for e in bound])


@functools.lru_cache(maxsize=256)
def _volume_shares(bound: Union) -> tuple[float, np.ndarray]:
    """(log of the ellipsoids' total volume, their cumulative volume shares as
    ``Generator.choice`` makes them from ``p = exp(log v - logsumexp(log v))``), computed
    once per bound (a bound is immutable; the cache holds the last 256, keyed by identity:
    scipy's logsumexp costs ~0.1 ms a call)."""
    logv = _log_volumes(bound)
    total = float(logsumexp(logv))
    cdf = np.exp(logv - total).cumsum()
    cdf /= cdf[-1]
    cdf.flags.writeable = False
    return total, cdf


_SQRT_EPS = float(np.sqrt(np.finfo(float).eps))


def choose(cdf: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``rng.choice(len(p), size=n, p=p)`` for ``cdf = p.cumsum() / its last``, by the same
    random numbers (``rng.random(n)`` searched in ``cdf``, as numpy does) at a fraction of
    the call's cost on few draws."""
    from abcns import compiled

    return compiled.labels(cdf, rng.random(n))


def cumulative(p: np.ndarray) -> np.ndarray:
    """The ``cdf`` of :func:`choose` for probabilities ``p``, checked as ``Generator.choice``
    checks them (non-negative, summing to 1 within sqrt(eps))."""
    p = np.asarray(p, dtype=float)
    if p.ndim != 1 or (p < 0).any() or not abs(float(p.sum()) - 1.0) <= _SQRT_EPS:
        raise ValueError(f"probabilities must be non-negative and sum to 1, got {p}")
    cdf = p.cumsum()
    cdf /= cdf[-1]
    return cdf


def _mixture_draws(bound: Union, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The random numbers of ``n`` draws from the ellipsoids' volume-weighted mixture: which
    ellipsoid each draw is from (``rng.choice(len(bound), size=n, p=volume shares)``'s
    numbers, :func:`choose`), then each ellipsoid's normals and uniforms
    (:func:`ellipsoid.unit_draws`) for its draws, in ellipsoid order: (which, normals,
    uniforms), the last two the ellipsoids' draws one after the other."""
    which = choose(_volume_shares(bound)[1], n, rng)
    d = bound[0].n_dim
    z, u = np.empty((n, d)), np.empty((n, 1))
    at = 0
    for k in np.bincount(which, minlength=len(bound)):
        ell.unit_draws(d, int(k), rng, out=(z[at:at + k], u[at:at + k]))
        at += k
    return which, z, u


def _mixture(bound: Union, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` draws from the ellipsoids' volume-weighted mixture (not yet uniform on the union)."""
    return _place(bound, *_mixture_draws(bound, n, rng))


def _place(bound: Union, which: np.ndarray, z: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The points of :func:`_mixture_draws`' numbers: ``ellipsoid.from_unit_draws`` of each
    ellipsoid's, the elementwise steps done once for all (the same bits row by row)."""
    w = ell.unit_ball_points(z, u)
    grouped = np.empty_like(w)  # the points in ellipsoid order, as the numbers come
    at = 0
    for e, k in zip(bound, np.bincount(which, minlength=len(bound)), strict=True):
        part = grouped[at:at + k]
        np.matmul(w[at:at + k], e.axes.T, out=part)
        part += e.centre  # ellipsoid.in_ellipsoid's centre + w @ axes.T
        at += k
    x = np.empty_like(grouped)
    x[np.argsort(which, kind="stable")] = grouped
    return x


def sample_union(bound: Union, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniform on the union. With one ellipsoid this is exactly
    ``ellipsoid.sample`` (the paper variant's random stream)."""
    if len(bound) == 1:
        return ell.sample(bound[0], n, rng)
    got: list[np.ndarray] = []
    n_got = 0
    while n_got < n:
        chunk = max(2 * (n - n_got), 64)
        x = _mixture(bound, chunk, rng)
        keep = x[rng.random(chunk) * ell.n_containing(bound, x) < 1.0][: n - n_got]
        got.append(keep)
        n_got += keep.shape[0]
    return np.concatenate(got)


def union_volume(bound: Union, box: tuple[np.ndarray, np.ndarray], n_draws: int,
                 rng: np.random.Generator) -> tuple[float, float]:
    """(log vol(union ∩ box), its standard error) by ``n_draws`` Monte Carlo draws; ``box``
    is (low, high), a point inside when ``low <= x <= high``.

    vol = sum_k vol(E_k) * E[1{x in box} / q(x)] for x from the volume-weighted mixture,
    q(x) the number of ellipsoids holding x (1 for a single ellipsoid). The weights come
    from a compiled loop (``abcns.compiled.mixture_weights``) that decides each point's box
    and ellipsoids with margins covering both its rounding and numpy's, so they are those
    of the points ``_mixture`` makes; when a point is too close to call, the points are made
    (from the same random numbers) and tested in numpy."""
    from abcns import compiled

    low, high = (np.broadcast_to(np.asarray(v, dtype=float), (bound[0].n_dim,)) for v in box)
    which, z, u = _mixture_draws(bound, n_draws, rng)
    axes, centres = ell.stacked(bound)
    w, ok = compiled.mixture_weights(which, z, u[:, 0], centres, axes, np.ascontiguousarray(low),
                                     np.ascontiguousarray(high), ell.CONTAINS_SLACK, len(bound) > 1)
    if not ok:
        x = _place(bound, which, z, u)
        held = np.all((x >= low) & (x <= high), axis=-1)
        w = held / ell.n_containing(bound, x) if len(bound) > 1 else held.astype(float)
    mean = float(np.mean(w))
    if mean <= 0.0:
        return -np.inf, np.inf
    se = float(np.std(w, ddof=1)) / np.sqrt(n_draws) / mean if n_draws > 1 else np.inf
    return float(_volume_shares(bound)[0] + np.log(mean)), se


class Frame:
    """The coordinates a model's bound lives in: its unit prior box ``(u - low) / width``
    (so that a condition-number cap and a volume mean the same for every parameter), or the
    raw coordinates ``u`` (the paper variant: ``unit=False``, no arithmetic on the way), where
    ``u`` is theta in the coordinates its prior is uniform in (``Model.to_coordinates``: log
    theta for a log-uniform prior, theta itself otherwise) and ``low``, ``width`` are the
    prior's there. The box test is the model's (``Model.in_prior``'s, on theta), and the box's
    volume ``Model.log_prior_volume``; all held as arrays for the proposals' loops."""

    def __init__(self, model: Model, unit: bool):
        self.unit = unit
        self.model_low = model.low
        self.model_high = model.high
        #: the model's own map to the prior's coordinates, when any prior is log-uniform
        self.coordinates = model if model.log_columns.any() else None
        self.low, self.high = model.coordinate_low, model.to_coordinates(model.high)
        self.width = self.high - self.low
        #: log volume of the prior box in these coordinates
        self.log_box_volume = 0.0 if unit else model.log_prior_volume()
        #: the prior's log density at rows of theta inside the box, in the parameters' own units
        self.log_prior_density = model.log_prior_density

    def to_frame(self, theta: np.ndarray) -> np.ndarray:
        u = self.coordinates.to_coordinates(theta) if self.coordinates else theta
        return (u - self.low) / self.width if self.unit else u

    def from_frame(self, x: np.ndarray) -> np.ndarray:
        u = self.low + self.width * x if self.unit else x
        return self.coordinates.from_coordinates(u) if self.coordinates else u

    @property
    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of the prior box in these coordinates."""
        d = self.low.shape[0]
        return (np.zeros(d), np.ones(d)) if self.unit else (self.low, self.high)

    def in_prior(self, theta: np.ndarray) -> np.ndarray:
        """Which rows of ``theta`` (raw parameters) lie inside the prior box: ``Model.in_prior``
        (``priors.in_box``) on the arrays held here."""
        return in_box(theta, self.model_low, self.model_high)

    def box_ellipsoid(self) -> ell.Ellipsoid:
        """The ellipsoid through the prior box's corners (the first fallback shape)."""
        d = self.low.shape[0]
        return ell.from_box(np.zeros(d), np.ones(d)) if self.unit else ell.from_box(self.low, self.high)
