"""The region a model's proposals come from: a union of ellipsoids.

ABC-NS (paper, Algorithm 2) bounds the surviving particles of a model by one ellipsoid.
A curved or split accepted region is covered poorly by one ellipsoid, so a bound here is a
tuple of ellipsoids (one in the paper variant), found by recursive 2-means splits that
are kept only when they halve the volume (the rule of MultiNest and dynesty's
``bounding.py``; the code is our own). Every function is pure, and each random draw comes
from the generator it is given.

- :func:`fit_union` : points -> ellipsoids (each enlarged by f0);
- :func:`sample_union` : points uniform on the union (an ellipsoid is chosen by volume, a
  point uniform in it is kept with probability 1 / the number of ellipsoids holding it);
- :func:`union_volume` : Monte Carlo estimate of log vol(union ∩ box) and its standard error;
- :func:`coverage` : two-fold cross-validated share of points that the bound's ellipsoids,
  refitted to the other half of their points, hold (how much of the accepted region the
  bound misses).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.linalg.lapack import dtrtrs
from scipy.special import gammaincinv, logsumexp

from abcns import ellipsoid as ell

Union = tuple[ell.Ellipsoid, ...]
#: halves replace a node only when their ellipsoids' total volume is below this share of it
#: (a convex region split by chance fluctuations of few points leaves gaps)
SPLIT_GAIN = 0.8
#: fewest points an ellipsoid of a split is fitted to (and at least 2 (d + 1)). Measured on
#: §4.1 (seeds 1-8): 10 needs ~23 % fewer simulations to eps 0.015 than 20; on the closed-form
#: toys both keep log Z within its standard error (the coverage correction sees the gaps)
LEAF_POINTS = 10
#: a point is an outlier when its squared whitened radius exceeds the chi-square quantile
#: 1 - OUTLIER_TAIL / n, scaled by the points' median radius (see :func:`outliers`)
OUTLIER_TAIL = 0.01
#: k-means (Lloyd) iterations of a split
KMEANS_ITERATIONS = 25


def min_points(d: int) -> int:
    """Fewest points an ellipsoid of a split may be fitted to: 2 (d + 1)."""
    return 2 * (d + 1)


def _node(points: np.ndarray) -> tuple[float, np.ndarray, np.ndarray] | None:
    """(log volume of the points' covariance ellipsoid scaled to hold them all, the points
    whitened by that covariance, the covariance), or None when the covariance is singular.
    The cheap part of ``ellipsoid.fit`` that the split search needs."""
    n, d = points.shape
    centred = points - points.sum(axis=0) / n  # the mean, as ``mean(axis=0)`` computes it
    cov = centred.T @ centred / (n - 1)
    try:
        chol = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return None
    # solve_triangular(chol, centred.T, lower=True) without its argument checks (the factor
    # of a finite covariance is finite): the LAPACK call it makes for a C-ordered factor
    y = dtrtrs(chol.T, centred.T, lower=0, trans=1)[0].T
    r2 = float((y * y).sum(axis=1).max())
    if not r2 > 0:
        return None
    log_volume = ell._log_unit_ball(d) + float(np.log(chol.diagonal()).sum()) + 0.5 * d * np.log(r2)
    return log_volume, y, cov


def two_means(points: np.ndarray, y: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """A 2-means clustering of ``points`` in whitened coordinates ``y``, started at the two
    points farthest apart along ``axis`` (deterministic): which points are in the second
    cluster (a boolean mask)."""
    proj = points @ axis
    centres = y[[np.argmin(proj), np.argmax(proj)]]
    second = np.zeros(points.shape[0], dtype=bool)
    for i in range(KMEANS_ITERATIONS):
        # nearer to centre 1 than to centre 0: a half-space test
        new = y @ (centres[1] - centres[0]) > 0.5 * (centres[1] @ centres[1] - centres[0] @ centres[0])
        if i > 0 and (new == second).all():
            break
        second = new
        for k, members in enumerate((~second, second)):
            count = np.count_nonzero(members)
            if count:  # the members' mean, as ``mean(axis=0)`` computes it
                centres[k] = y[members].sum(axis=0) / count
    return second


def _tree(points: np.ndarray, rows: np.ndarray, log_volume: float, y: np.ndarray, cov: np.ndarray,
          max_ellipsoids: int, leaf: int, log_root: float) -> list[tuple[float, list[np.ndarray]]]:
    """``best[k - 1]``: (total volume relative to the root's, the row sets) of the at most k
    ellipsoids of least total volume that hold ``points[rows]``: the node's own ellipsoid, or
    the best choices of its two 2-means halves together (found the same way, recursively;
    the halves are started along the leading eigenvector of the node's covariance ``cov``)."""
    own = float(np.exp(log_volume - log_root))
    best = [(own, [rows])] * max_ellipsoids
    d = points.shape[1]
    if max_ellipsoids < 2 or rows.size < 2 * leaf:
        return best
    in_second = two_means(points[rows], y, np.linalg.eigh(cov)[1][:, -1])
    parts = [rows[~in_second], rows[in_second]]
    if min(p.size for p in parts) < max(leaf, d + 1):
        return best
    halves = []
    for part in parts:
        node = _node(points[part])
        if node is None:
            return best
        halves.append(_tree(points, part, node[0], node[1], node[2], max_ellipsoids - 1, leaf, log_root))
    first, second = halves
    for k in range(2, max_ellipsoids + 1):
        # k1 ellipsoids for the first half, k - k1 for the second (the first k1 of least total)
        k1 = min(range(1, k), key=lambda k1: first[k1 - 1][0] + second[k - k1 - 1][0])
        total = first[k1 - 1][0] + second[k - k1 - 1][0]
        if total < SPLIT_GAIN * best[k - 2][0]:
            best[k - 1] = (total, first[k1 - 1][1] + second[k - k1 - 1][1])
        else:
            best[k - 1] = best[k - 2]
    return best


def outliers(y: np.ndarray) -> np.ndarray:
    """Rows of whitened points ``y`` far outside the rest: squared radius above the chi-square
    (d) quantile 1 - OUTLIER_TAIL / n, rescaled so the points' median radius is the
    chi-square median. A Gaussian cloud loses a point in about 1 % of fits, a uniform one
    never; a stochastic simulator's lucky draw far from the accepted region (which would
    otherwise make the bound ten times larger) is left out, and the cross-validated
    coverage counts what that leaves out."""
    n, d = y.shape
    r2 = np.sum(y * y, axis=1)
    scale = float(np.median(r2)) / _chi2_quantile(0.5, d)
    return r2 > _chi2_quantile(1.0 - OUTLIER_TAIL / n, d) * scale


def _chi2_quantile(q: float, d: int) -> float:
    """The chi-square (d) quantile q, as ``scipy.stats.chi2.ppf`` computes it (the same
    bits), without importing scipy.stats (a third of a second at every process start)."""
    return float(2.0 * gammaincinv(0.5 * d, q))


def fit_union(points: np.ndarray, enlargement: float, max_ellipsoids: int, fallback: ell.Ellipsoid) -> Union:
    """Ellipsoids that hold every point but far :func:`outliers`, each enlarged by
    ``enlargement`` (f0).

    The points' ellipsoid (``abcns.ellipsoid.fit``, with ``fallback`` when the points define
    no shape) is split by 2-means, recursively, while each half keeps ``LEAF_POINTS`` and
    :func:`min_points` points; of the ellipsoids of that tree, the set of at most
    ``max_ellipsoids`` with the least total volume is kept (a node is replaced by its
    halves' best sets only when those hold less than ``SPLIT_GAIN`` of its volume)."""
    root = _node(points) if max_ellipsoids > 1 and points.shape[0] > points.shape[1] else None
    if root is not None:
        far = outliers(root[1])
        if np.any(far) and np.count_nonzero(~far) > 2 * min_points(points.shape[1]):
            points = points[~far]
            root = _node(points)
    if root is None:
        chosen = [ell.fit(points, fallback=fallback)]
    else:
        leaf = max(LEAF_POINTS, min_points(points.shape[1]))
        rows = np.arange(points.shape[0])
        _, sets = _tree(points, rows, root[0], root[1], root[2], max_ellipsoids, leaf, root[0])[-1]
        parent = ell.fit(points, fallback=fallback)
        chosen = [parent] if len(sets) == 1 else [ell.fit(points[r], fallback=parent) for r in sets]
    return tuple(ell.enlarge(e, enlargement) for e in chosen)


def n_inside(bound: Union, x: np.ndarray) -> np.ndarray:
    """How many ellipsoids of the union hold each row of ``x``."""
    return ell.n_containing(bound, x)


def _log_volumes(bound: Union) -> np.ndarray:
    return np.array([e.log_volume for e in bound])


def _mixture(bound: Union, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` draws from the ellipsoids' volume-weighted mixture (not yet uniform on the union)."""
    logv = _log_volumes(bound)
    k = rng.choice(len(bound), size=n, p=np.exp(logv - logsumexp(logv)))
    x = np.empty((n, bound[0].n_dim))
    for j, e in enumerate(bound):
        rows = np.flatnonzero(k == j)
        x[rows] = ell.sample(e, rows.size, rng)
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
        keep = x[rng.random(chunk) * n_inside(bound, x) < 1.0][: n - n_got]
        got.append(keep)
        n_got += keep.shape[0]
    return np.concatenate(got)


def union_volume(
    bound: Union, inside: Callable[[np.ndarray], np.ndarray], n_draws: int, rng: np.random.Generator
) -> tuple[float, float]:
    """(log vol(union ∩ {inside}), its standard error) by ``n_draws`` Monte Carlo draws.

    vol = sum_k vol(E_k) * E[1{inside(x)} / q(x)] for x from the volume-weighted mixture,
    q(x) the number of ellipsoids holding x (1 for a single ellipsoid)."""
    x = _mixture(bound, n_draws, rng)
    w = inside(x) / n_inside(bound, x) if len(bound) > 1 else inside(x).astype(float)
    mean = float(np.mean(w))
    if mean <= 0.0:
        return -np.inf, np.inf
    se = float(np.std(w, ddof=1)) / np.sqrt(n_draws) / mean if n_draws > 1 else np.inf
    return float(logsumexp(_log_volumes(bound)) + np.log(mean)), se


def coverage(points: np.ndarray, bound: Union, enlargement: float, rng: np.random.Generator,
             uniform: np.ndarray | None = None) -> tuple[float, int]:
    """(estimated share of the sampled region that ``bound`` holds, points tested), for a
    ``bound`` that :func:`fit_union` fitted to ``points``; only the points marked ``uniform``
    (default all) are tested: those drawn uniformly from the region (a population's new
    particles; survivors, drawn by weight, crowd its centre and would hide a miss at its edge).

    Cross-validation of the bound as it was fitted, ellipsoid by ellipsoid: each point
    belongs to the ellipsoid of ``bound`` it lies deepest in (the group that ellipsoid was
    fitted to); a point outside every ellipsoid is an outlier the fit left out, and is
    missed. Each group is split at random into halves; each half is fitted by one ellipsoid
    (enlarged like the bound's), and the tested points of the other halves are tested
    against the union of those ellipsoids. The share an ellipsoid fitted to n points misses
    falls like 1/n (d/n around uniform points), so the bound, fitted to twice the points,
    misses about half of what the half-fits miss: ``coverage = (1 - outliers / n)(1 -
    missed / 2)``, over the n tested points, ``missed`` the share of the grouped ones the
    half-fits miss.

    Refitting the halves with the same groups tests the bound's own structure: a
    :func:`fit_union` of half the points can split into fewer ellipsoids (fewer points per
    leaf) or more, and then measures another bound (a disc split into five ellipsoids of
    ~16 points each missed 18 % of itself while fits to its halves, one ellipsoid each, said
    1 %)."""
    uniform = np.ones(points.shape[0], bool) if uniform is None else uniform
    n = int(np.count_nonzero(uniform))
    if n < 4:
        return 1.0, 0
    depth = ell.mahalanobis2_each(bound, points)
    group = np.argmin(depth, axis=0)
    inside = depth[group, np.arange(points.shape[0])] <= 1.0 + ell.CONTAINS_SLACK
    halves: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
    for j in range(len(bound)):
        rows = np.flatnonzero(inside & (group == j))
        rows = rows[rng.permutation(rows.size)]
        halves[0].append(rows[: rows.size // 2])
        halves[1].append(rows[rows.size // 2 :])
    n_in = int(np.count_nonzero(inside & uniform))
    held = 0
    for train, test in (halves, halves[::-1]):
        fold = tuple(ell.enlarge(ell.fit(points[rows], fallback=e), enlargement)
                     for rows, e in zip(train, bound) if rows.size)
        rows = np.concatenate(test)
        rows = rows[uniform[rows]]
        if fold and rows.size:
            held += int(np.count_nonzero(n_inside(fold, points[rows]) > 0))
    missed = 1.0 - held / n_in if n_in else 0.0
    return n_in / n * (1.0 - 0.5 * missed), n


def in_unit_box(x: np.ndarray) -> np.ndarray:
    return np.all((x >= 0.0) & (x <= 1.0), axis=-1)




class Frame:
    """The coordinates a model's bound lives in: its unit prior box ``(theta - low) / width``
    (so that a condition-number cap and a volume mean the same for every parameter), or the
    raw parameters (the paper variant: ``unit=False``, no arithmetic on the way)."""

    def __init__(self, low: np.ndarray, high: np.ndarray, unit: bool):
        self.unit = unit
        self.low = np.asarray(low, float)
        self.width = np.asarray(high, float) - self.low
        self.high = np.asarray(high, float)
        #: log volume of the prior box in these coordinates
        self.log_box_volume = 0.0 if unit else float(np.sum(np.log(self.width)))

    def to_frame(self, theta: np.ndarray) -> np.ndarray:
        return (theta - self.low) / self.width if self.unit else theta

    def from_frame(self, x: np.ndarray) -> np.ndarray:
        return self.low + self.width * x if self.unit else x

    def inside(self, x: np.ndarray) -> np.ndarray:
        """Which rows of ``x`` (in this frame) lie inside the prior box."""
        if self.unit:
            return in_unit_box(x)
        return np.all((x >= self.low) & (x <= self.high), axis=-1)

    def box_ellipsoid(self) -> ell.Ellipsoid:
        """The ellipsoid through the prior box's corners (the first fallback shape)."""
        d = self.low.shape[0]
        return ell.from_box(np.zeros(d), np.ones(d)) if self.unit else ell.from_box(self.low, self.high)
