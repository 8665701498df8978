"""Numba kernels of the population step's geometry: the split tree of ``abcns.bounds``, the
ellipsoid counts of ``abcns.ellipsoid``, the volume weights of ``bounds.union_volume``, the
labels of ``bounds.choose`` and the prior-box test of ``priors.in_box``. Imported on first use
(numba's import and its compiled-function cache cost ~0.5 s, which ``import abcns`` does not pay).

None of them decides a result by its own rounding (:func:`labels` and :func:`in_box` only
compare):

- :func:`tree_rows` returns only *which rows* go to which ellipsoid of a bound (each set
  is then fitted by ``ellipsoid.fit``, in numpy, as before). Its arithmetic (means,
  covariances, Cholesky factors, whitened points, 2-means) rounds differently from
  numpy's BLAS and LAPACK calls, so a decision can differ only where two compared values
  agree to ~1e-15 (a point on a 2-means boundary, two splits of equal volume), which a
  continuous sample does not meet. The split axis is the leading eigenvector of a node's
  covariance from numpy's ``eigh`` (called back from the kernel, once per level of the
  tree), so its sign, which orders the two halves and hence the ellipsoids of the bound,
  is the one LAPACK's dsyevd gives as numpy calls it.
- :func:`count_inside` is exact or says it cannot be: see ``ellipsoid.n_containing``;
  :func:`mixture_weights` likewise, with margins that cover numpy's rounding too.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, objmode

from abcns.ellipsoid import log_unit_ball


@njit(cache=True, error_model="numpy")
def _invert(a: np.ndarray, out: np.ndarray) -> bool:
    """``out`` = a^-1 by Gauss-Jordan elimination with partial pivoting; False when a pivot is
    zero or not finite. (Any inverse serves :func:`count_inside`: its error bound uses the
    residual of the inverse it got.)"""
    d = a.shape[0]
    w = a.copy()
    out[:] = 0.0
    for i in range(d):
        out[i, i] = 1.0
    for c in range(d):
        p = c
        for r in range(c + 1, d):
            if abs(w[r, c]) > abs(w[p, c]):
                p = r
        piv = w[p, c]
        if not (piv != 0.0 and math.isfinite(piv)):
            return False
        if p != c:
            for j in range(d):
                w[c, j], w[p, j] = w[p, j], w[c, j]
                out[c, j], out[p, j] = out[p, j], out[c, j]
        for j in range(d):
            w[c, j] /= piv
            out[c, j] /= piv
        for r in range(d):
            if r != c:
                f = w[r, c]
                for j in range(d):
                    w[r, j] -= f * w[c, j]
                    out[r, j] -= f * out[c, j]
    return True


#: points per block of the distance loops (their work arrays stay in the L1 cache)
BLOCK = 256


@njit(cache=True, error_model="numpy")
def _distances(xt: np.ndarray, inv: np.ndarray, centre: np.ndarray, diff: np.ndarray, y: np.ndarray,
               s: np.ndarray) -> None:
    """``s[i] = |inv (x_i - centre)|^2`` for the columns x_i of ``xt`` (d, n); ``diff`` (d, >= n)
    and ``y`` (>= n,) are work space. Each sum runs over the points innermost (vectorised)."""
    d, n = xt.shape
    for b in range(d):
        cb = centre[b]
        for i in range(n):
            diff[b, i] = xt[b, i] - cb
    for i in range(n):
        s[i] = 0.0
    for a in range(d):
        for i in range(n):
            y[i] = 0.0
        for b in range(d):
            c = inv[a, b]
            for i in range(n):
                y[i] += c * diff[b, i]
        for i in range(n):
            s[i] += y[i] * y[i]


@njit(cache=True, error_model="numpy")
def _inverses(axes: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(the inverses of the k axes matrices, their Frobenius norms, the relative error bound
    m of ``ellipsoid.n_containing``: ``10 max_j (|X_j A_j - I|_F + (d + 1 + 4 d^3 2^d) eps
    |A_j|_F |X_j|_F)``); m is inf when a matrix cannot be inverted."""
    k, d, _ = axes.shape
    inv = np.empty((k, d, d))
    norms = np.empty(k)
    eps = 2.220446049250313e-16  # np.finfo(float).eps
    m = 0.0
    for j in range(k):
        if not _invert(axes[j], inv[j]):
            return inv, norms, np.inf
        res2 = a2 = x2 = 0.0
        for a in range(d):
            for b in range(d):
                r = 0.0
                for c in range(d):
                    r += inv[j, a, c] * axes[j, c, b]
                if a == b:
                    r -= 1.0
                res2 += r * r
                a2 += axes[j, a, b] * axes[j, a, b]
                x2 += inv[j, a, b] * inv[j, a, b]
        norms[j] = math.sqrt(x2)
        m = max(m, 10.0 * (math.sqrt(res2) + (d + 1 + 4 * d**3 * 2.0**d) * eps * math.sqrt(a2 * x2)))
    return inv, norms, m


@njit(cache=True, error_model="numpy")
def count_inside(xt: np.ndarray, axes: np.ndarray, centres: np.ndarray, slack: float) -> tuple[np.ndarray, bool]:
    """How many of the k ellipsoids (``axes`` (k, d, d), ``centres`` (k, d)) hold each column
    of ``xt`` (d, n), by the inverses of the axes, with the proven error window of
    ``ellipsoid.n_containing``: (counts, True), or (partial counts, False) as soon as one
    squared distance is within the window of ``1 + slack``, not finite or above 1e300, or
    when an axes matrix is too ill-conditioned for the bound (m > 1e-3)."""
    n = xt.shape[1]
    counts = np.zeros(n, np.int64)
    inv, inv_norm, m = _inverses(axes)
    if not m <= 1e-3:
        return counts, False
    ok = _count(xt, inv, inv_norm, centres, np.zeros(n), np.ones(n, np.bool_), m, 1.0 + slack, counts)
    return counts, ok


@njit(cache=True, error_model="numpy")
def _count(xt: np.ndarray, inv: np.ndarray, inv_norm: np.ndarray, centres: np.ndarray, shift: np.ndarray,
           held: np.ndarray, m: float, t: float, holders: np.ndarray) -> bool:
    """Add to ``holders[i]`` the ellipsoids (``inv``, ``centres``) that hold point i (column
    of ``xt``) for sure, with distances of relative error m and points within ``shift[i]``
    of where they should be (the distance moves by up to ``1.01 |inv|_F shift``); False as
    soon as a point of ``held`` is too close to call (or its distance is not finite or above
    1e300). Inside for sure: ``(sqrt(s (1 + m)) + delta)^2 (1 + m) < t``; outside for sure:
    ``(sqrt(s (1 - m)) - delta)^2 (1 - m) > t``, said without a square root per point."""
    d, n = xt.shape
    t_in, t_out = math.sqrt(t / (1.0 + m)), math.sqrt(t / (1.0 - m))
    s = np.empty(BLOCK)
    y = np.empty(BLOCK)
    diff = np.empty((d, BLOCK))
    for first in range(0, n, BLOCK):  # blocks of points: the work arrays stay in the L1 cache
        last = min(n, first + BLOCK)
        for j in range(centres.shape[0]):
            _distances(xt[:, first:last], inv[j], centres[j], diff, y, s)
            grow = 1.01 * inv_norm[j]
            for c in range(last - first):
                i = first + c
                delta = grow * shift[i]
                below, above = t_in - delta, t_out + delta
                if s[c] * (1.0 + m) < below * below and below > 0.0:
                    holders[i] += 1
                elif not (s[c] * (1.0 - m) > above * above and s[c] <= 1e300) and held[i]:
                    return False
    return True


#: ``ellipsoid.log_unit_ball``, the same function, compiled
_log_unit_ball = njit(cache=True, error_model="numpy")(log_unit_ball)


@njit(cache=True, error_model="numpy")
def _node(points: np.ndarray, rows: np.ndarray, cov: np.ndarray, y: np.ndarray) -> tuple[bool, float]:
    """The covariance ellipsoid of ``points[rows]`` scaled to hold them all (the shape
    ``ellipsoid.fit`` makes when it needs no repair), measured for the split tree only:
    (ok, its log volume); fills ``cov`` (d, d) and the whitened points ``y`` (len(rows), d).
    Not ok when the covariance is not positive definite (Cholesky fails, as LAPACK's dpotrf
    does: a pivot <= 0 or NaN) or every point sits at the mean.

    Not a second ``fit``: no ellipsoid is made from these numbers. The tree compares their
    volumes and clusters the whitened points (in the kernel's own rounding: see the
    module's docstring); each ellipsoid of a bound is then made by ``ellipsoid.fit_many``
    from the rows the tree chose, with fit's repair and fallback."""
    n = rows.shape[0]
    d = points.shape[1]
    mean = np.zeros(d)
    for i in range(n):
        for j in range(d):
            mean[j] += points[rows[i], j]
    for j in range(d):
        mean[j] /= n
    for i in range(n):
        for j in range(d):
            y[i, j] = points[rows[i], j] - mean[j]
    for a in range(d):
        for b in range(a + 1):
            s = 0.0
            for i in range(n):
                s += y[i, a] * y[i, b]
            cov[a, b] = s / (n - 1)
            cov[b, a] = cov[a, b]
    chol = np.zeros((d, d))
    log_det = 0.0
    for j in range(d):
        s = cov[j, j]
        for k in range(j):
            s -= chol[j, k] * chol[j, k]
        if not s > 0.0:
            return False, 0.0
        chol[j, j] = math.sqrt(s)
        log_det += math.log(chol[j, j])
        for i in range(j + 1, d):
            t = cov[i, j]
            for k in range(j):
                t -= chol[i, k] * chol[j, k]
            chol[i, j] = t / chol[j, j]
    r2 = 0.0
    for i in range(n):
        q = 0.0
        for j in range(d):  # forward substitution: y_i = chol^-1 (p_i - mean)
            t = y[i, j]
            for k in range(j):
                t -= chol[j, k] * y[i, k]
            y[i, j] = t / chol[j, j]
            q += y[i, j] * y[i, j]
        r2 = max(r2, q)
    if not r2 > 0.0:
        return False, 0.0
    return True, _log_unit_ball(d) + log_det + 0.5 * d * math.log(r2)


@njit(cache=True, error_model="numpy")
def radii(points: np.ndarray) -> tuple[bool, np.ndarray]:
    """(ok, squared whitened radius of each point) of :func:`_node` of all ``points``."""
    n, d = points.shape
    y = np.empty((n, d))
    ok, _ = _node(points, np.arange(n), np.empty((d, d)), y)
    r2 = np.empty(n)
    for i in range(n):
        q = 0.0
        for j in range(d):
            q += y[i, j] * y[i, j]
        r2[i] = q
    return ok, r2


@njit(cache=True, error_model="numpy")
def _two_means(points: np.ndarray, rows: np.ndarray, y: np.ndarray, axis: np.ndarray,
               iterations: int) -> np.ndarray:
    """A 2-means clustering of ``points[rows]`` in whitened coordinates ``y``, started at the
    means of the two sides of the rows' mean along ``axis`` (deterministic), at most
    ``iterations`` Lloyd steps: which rows are in the second cluster (a boolean mask).

    Not at two single rows (the two farthest apart along ``axis``, before issue Y's mode
    loss): whitened, a point of a cluster lies as far out in each of the other d - 1
    directions as the clusters lie apart, so in 11-D the first assignment to two single
    points was a coin toss per point and Lloyd settled on halves that cut the clusters (two
    balls at least 10 radii apart were split 68 / 108 across both)."""
    n = rows.shape[0]
    d = points.shape[1]
    proj = np.empty(n)
    mid = 0.0
    for i in range(n):
        p = 0.0
        for j in range(d):
            p += points[rows[i], j] * axis[j]
        proj[i] = p
        mid += p
    mid /= n
    c0 = np.zeros(d)
    c1 = np.zeros(d)
    _side_means(y, proj > mid, c0, c1)
    second = np.zeros(n, np.bool_)
    new = np.zeros(n, np.bool_)
    for it in range(iterations):
        thr = 0.0
        for j in range(d):
            thr += c1[j] * c1[j] - c0[j] * c0[j]
        thr *= 0.5
        changed = False
        for i in range(n):
            v = 0.0
            for j in range(d):
                v += y[i, j] * (c1[j] - c0[j])
            new[i] = v > thr
            changed = changed or new[i] != second[i]
        if it > 0 and not changed:
            break
        for i in range(n):
            second[i] = new[i]
        _side_means(y, second, c0, c1)
    return second


@njit(cache=True, error_model="numpy")
def _side_means(y: np.ndarray, second: np.ndarray, c0: np.ndarray, c1: np.ndarray) -> None:
    """The means of the rows of ``y`` outside and inside the mask ``second``, into ``c0`` and
    ``c1``; a side with no row keeps its value (2-means' start and each Lloyd step)."""
    n, d = second.shape[0], y.shape[1]
    s0 = np.zeros(d)
    s1 = np.zeros(d)
    n1 = 0
    for i in range(n):
        if second[i]:
            n1 += 1
            for j in range(d):
                s1[j] += y[i, j]
        else:
            for j in range(d):
                s0[j] += y[i, j]
    if n - n1 > 0:
        for j in range(d):
            c0[j] = s0[j] / (n - n1)
    if n1 > 0:
        for j in range(d):
            c1[j] = s1[j] / n1


@njit(cache=True, error_model="numpy")
def tree_rows(points: np.ndarray, max_ellipsoids: int, leaf: int, split_gain: float,
              iterations: int) -> tuple[bool, np.ndarray, np.ndarray]:
    """``bounds._tree_sets`` from the root ``points``, its best set of at most
    ``max_ellipsoids``: (ok, rows of the sets one after the other, each ascending, the sets'
    start offsets and the end). Not ok when the root has no covariance ellipsoid.

    Three steps: :func:`_grow` makes the tree (each node a segment of a permutation of the
    rows), :func:`_best_sets` finds each node's best set of at most k ellipsoids, and
    :func:`_emit_sets` writes the root's."""
    n = points.shape[0]
    ok, n_nodes, start, stop, budget, child, log_volume, perm = _grow(points, max_ellipsoids, leaf, iterations)
    if not ok:
        return False, perm[:0], np.zeros(1, np.int64)
    choice = _best_sets(log_volume[:n_nodes], child, budget, max_ellipsoids, split_gain)
    out, offsets = _emit_sets(choice, child, start, stop, perm, n, max_ellipsoids)
    return True, out, offsets


@njit(cache=True, error_model="numpy")
def _grow(points: np.ndarray, max_ellipsoids: int, leaf: int, iterations: int) -> tuple[
        bool, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The split tree of :func:`tree_rows`: (ok, the number of nodes, ``start``, ``stop``,
    ``budget``, ``child``, ``log_volume``, ``perm``). Node v's rows are ``perm[start[v]:stop[v]]``;
    ``budget[v]`` is the most ellipsoids it may be split into, ``child[v]`` its halves (-1: none),
    ``log_volume[v]`` the log volume of its covariance ellipsoid (:func:`_node`). Node 0 is
    the root; not ok when it has no ellipsoid.

    The nodes are made breadth first, a level after the other, with one call of numpy's
    ``eigh`` per level for the split axes (:func:`_split_axes`); a node's segment of
    ``perm`` is split (stably) into its halves' segments (:func:`_split_level`)."""
    n, d = points.shape
    cap = 1 + 2 * max_ellipsoids * (n // max(2 * leaf, 1) + 1)
    start = np.zeros(cap, np.int64)
    stop = np.zeros(cap, np.int64)
    budget = np.zeros(cap, np.int64)
    child = -np.ones((cap, 2), np.int64)
    log_volume = np.zeros(cap)
    covs = np.zeros((cap, d, d))
    perm = np.arange(n)
    ybuf = np.empty((n, d))  # the whitened points of each node still to split, in its segment
    work = np.empty(n, np.int64)

    ok, lv = _node(points, perm, covs[0], ybuf)
    if not ok:
        return False, 0, start, stop, budget, child, log_volume, perm
    start[0], stop[0], budget[0], log_volume[0] = 0, n, max_ellipsoids, lv
    n_nodes = 1
    lo_level, hi_level = 0, 1  # the nodes of a level of the tree are made one after the other
    while lo_level < hi_level:  # breadth first: one eigh call (numpy's) per level of the tree
        todo = _splittable(start, stop, budget, lo_level, hi_level, leaf)
        lo_level = hi_level
        if todo.shape[0] == 0:
            break
        axes = _split_axes(covs, todo)
        n_nodes = _split_level(points, todo, axes, leaf, iterations, n_nodes, start, stop, budget, child,
                               log_volume, covs, perm, ybuf, work)
        hi_level = n_nodes
    return True, n_nodes, start, stop, budget, child, log_volume, perm


@njit(cache=True, error_model="numpy")
def _splittable(start: np.ndarray, stop: np.ndarray, budget: np.ndarray, lo: int, hi: int,
                leaf: int) -> np.ndarray:
    """The nodes lo, ..., hi - 1 (a level of the tree) that may be split: a budget of at
    least 2 ellipsoids and at least 2 ``leaf`` rows."""
    todo = np.empty(hi - lo, np.int64)
    n_todo = 0
    for v in range(lo, hi):
        if budget[v] >= 2 and stop[v] - start[v] >= 2 * leaf:
            todo[n_todo] = v
            n_todo += 1
    return todo[:n_todo]


@njit(cache=True, error_model="numpy")
def _split_axes(covs: np.ndarray, todo: np.ndarray) -> np.ndarray:
    """The split axis of each node of ``todo``: the leading eigenvector of its covariance
    (``covs[v]``), from one call of numpy's ``eigh`` on their stack (so LAPACK's dsyevd as
    numpy calls it gives their signs, which order the halves)."""
    n_todo = todo.shape[0]
    d = covs.shape[1]
    stacked = np.empty((n_todo, d, d))
    for i in range(n_todo):
        for a in range(d):
            for b in range(d):
                stacked[i, a, b] = covs[todo[i], a, b]
    with objmode(axes="float64[:, :]"):
        axes = np.ascontiguousarray(np.linalg.eigh(stacked)[1][:, :, -1])
    return axes


@njit(cache=True, error_model="numpy")
def _split_level(points: np.ndarray, todo: np.ndarray, axes: np.ndarray, leaf: int, iterations: int,
                 n_nodes: int, start: np.ndarray, stop: np.ndarray, budget: np.ndarray, child: np.ndarray,
                 log_volume: np.ndarray, covs: np.ndarray, perm: np.ndarray, ybuf: np.ndarray,
                 work: np.ndarray) -> int:
    """Split each node v of ``todo`` along ``axes[i]`` into two new nodes (appended after the
    first ``n_nodes``), when :func:`_halves` keeps both and both have an ellipsoid; the
    halves' rows take v's segment of ``perm``, the first half's first. Returns the new
    number of nodes."""
    for i in range(todo.shape[0]):
        v = todo[i]
        s, e = start[v], stop[v]
        n0 = _halves(points, perm[s:e], ybuf[s:e], axes[i], leaf, iterations, work)
        if n0 < 0:
            continue
        ok0, lv0 = _node(points, work[:n0], covs[n_nodes], ybuf[s:s + n0])
        if not ok0:
            continue
        ok1, lv1 = _node(points, work[n0:e - s], covs[n_nodes + 1], ybuf[s + n0:e])
        if not ok1:
            continue
        start[n_nodes], stop[n_nodes], log_volume[n_nodes] = s, s + n0, lv0
        start[n_nodes + 1], stop[n_nodes + 1], log_volume[n_nodes + 1] = s + n0, e, lv1
        budget[n_nodes] = budget[n_nodes + 1] = budget[v] - 1
        for r in range(e - s):
            perm[s + r] = work[r]
        child[v, 0], child[v, 1] = n_nodes, n_nodes + 1
        n_nodes += 2
    return n_nodes


@njit(cache=True, error_model="numpy")
def _halves(points: np.ndarray, rows: np.ndarray, y: np.ndarray, axis: np.ndarray, leaf: int, iterations: int,
            work: np.ndarray) -> int:
    """The 2-means split (:func:`_two_means`) of a node's ``rows`` (whitened points ``y``):
    the number n0 of the first half's rows, with ``work`` = the first half's rows then the
    second's, each in the order of ``rows`` (a stable partition). When 2-means leaves a half
    fewer than ``leaf`` or d + 1 rows (a small group apart from the rest, as at the tip of a
    curved ridge, kept alone), the rows are split at
    their median along ``axis`` instead (:func:`_median_split`), so that one stray group
    does not keep the node, and every node under it, whole; -1 when even that leaves a half
    too small (a node of fewer than 2 ``leaf`` rows, which :func:`_splittable` never splits)."""
    second = _two_means(points, rows, y, axis, iterations)
    m = rows.shape[0]
    least = max(leaf, points.shape[1] + 1)
    n1 = 0
    for r in range(m):
        n1 += second[r]
    if min(m - n1, n1) < least:
        if m // 2 < least:
            return -1
        second = _median_split(points, rows, axis)
        n1 = m - m // 2
    n0 = m - n1
    a, b = 0, n0
    for r in range(m):
        if second[r]:
            work[b] = rows[r]
            b += 1
        else:
            work[a] = rows[r]
            a += 1
    return n0


@njit(cache=True, error_model="numpy")
def _median_split(points: np.ndarray, rows: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The rows of ``points[rows]`` above their median along ``axis`` (the upper m - m // 2 of
    their projections, ties in row order: a stable sort), as :func:`_two_means`' mask."""
    m = rows.shape[0]
    proj = np.empty(m)
    for i in range(m):
        p = 0.0
        for j in range(points.shape[1]):
            p += points[rows[i], j] * axis[j]
        proj[i] = p
    second = np.zeros(m, np.bool_)
    second[np.argsort(proj, kind="mergesort")[m // 2:]] = True
    return second


@njit(cache=True, error_model="numpy")
def _best_sets(log_volume: np.ndarray, child: np.ndarray, budget: np.ndarray, max_ellipsoids: int,
               split_gain: float) -> np.ndarray:
    """The dynamic programme of ``bounds._tree_sets`` over the nodes of :func:`_grow`:
    ``choice[v, k]``, how node v's best set of at most k ellipsoids is made: -1 its own
    ellipsoid, -2 as with k - 1, else k1 (k1 for the first half, k - k1 for the second).
    ``total[v, k]`` is that set's volume relative to the root's; the halves' sets replace
    the best set of at most k - 1 only when they hold less than ``split_gain`` of it."""
    n_nodes = log_volume.shape[0]
    total = np.zeros((n_nodes, max_ellipsoids + 1))
    choice = np.zeros((n_nodes, max_ellipsoids + 1), np.int64)
    for v in range(n_nodes - 1, -1, -1):  # children after parents: reverse order is bottom-up
        total[v, 1] = math.exp(log_volume[v] - log_volume[0])
        choice[v, 1] = -1
        first, sec = child[v, 0], child[v, 1]
        for k in range(2, budget[v] + 1):
            total[v, k], choice[v, k] = total[v, k - 1], -2
            if first < 0:
                continue
            best_k1, best_t = 1, total[first, 1] + total[sec, k - 1]
            for k1 in range(2, k):
                t = total[first, k1] + total[sec, k - k1]
                if t < best_t:
                    best_k1, best_t = k1, t
            if best_t < split_gain * total[v, k - 1]:
                total[v, k], choice[v, k] = best_t, best_k1
    return choice


@njit(cache=True, error_model="numpy")
def _emit_sets(choice: np.ndarray, child: np.ndarray, start: np.ndarray, stop: np.ndarray, perm: np.ndarray,
               n: int, max_ellipsoids: int) -> tuple[np.ndarray, np.ndarray]:
    """The root's best set of at most ``max_ellipsoids`` (:func:`_best_sets`' ``choice``),
    first half before second: (the rows of its nodes one after the other, each ascending,
    the start offsets and the end)."""
    out = np.empty(n, np.int64)
    member = np.zeros(n, np.bool_)
    offsets = np.zeros(max_ellipsoids + 1, np.int64)
    n_sets = 0
    todo_v = np.empty(max_ellipsoids, np.int64)  # a stack of (node, k): the sets still to emit
    todo_k = np.empty(max_ellipsoids, np.int64)
    todo_v[0], todo_k[0], n_todo = 0, max_ellipsoids, 1
    while n_todo > 0:
        n_todo -= 1
        v, k = todo_v[n_todo], todo_k[n_todo]
        while choice[v, k] == -2:
            k -= 1
        if choice[v, k] == -1:
            for r in range(start[v], stop[v]):
                member[perm[r]] = True
            at = offsets[n_sets]
            for r in range(n):  # the node's rows, ascending
                if member[r]:
                    out[at] = r
                    at += 1
                    member[r] = False
            n_sets += 1
            offsets[n_sets] = at
        else:
            k1 = choice[v, k]
            todo_v[n_todo], todo_k[n_todo] = child[v, 1], k - k1
            todo_v[n_todo + 1], todo_k[n_todo + 1] = child[v, 0], k1
            n_todo += 2
    return out[:offsets[n_sets]], offsets[:n_sets + 1]


@njit(cache=True, error_model="numpy")
def labels(cdf: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``cdf.searchsorted(u, side="right")`` (``Generator.choice``'s last step), by a scan of
    the few entries of ``cdf``: the first index whose entry exceeds u, else len(cdf)."""
    k = cdf.shape[0]
    out = np.empty(u.shape[0], np.int64)
    for i in range(u.shape[0]):
        j = 0
        while j < k and not u[i] < cdf[j]:
            j += 1
        out[i] = j
    return out


@njit(cache=True, error_model="numpy")
def mixture_weights(which: np.ndarray, z: np.ndarray, u: np.ndarray, centres: np.ndarray, axes: np.ndarray,
                    low: np.ndarray, high: np.ndarray, slack: float, count: bool) -> tuple[np.ndarray, bool]:
    """``bounds.union_volume``'s weights without the points' bits: point i of ellipsoid
    ``which[i]`` is ``centre + axes (u^(1/d) z / |z|)`` (``z``, ``u``: that ellipsoid's
    draws, the ellipsoids' draws one after the other in ellipsoid order, each in row order);
    its weight is 1{low <= x <= high} / (the number of ellipsoids that hold it) (``count``)
    or 1{low <= x <= high}. Every decision is taken with a margin that covers the rounding of
    both this loop and numpy's arithmetic in ``ellipsoid.sample`` (so the weights are those of
    the points numpy would make), else (w, False).

    The margins. numpy's point and this loop's each lie within
    ``e_i = (4 d + 128) eps (|centre_i| + sum_j |axes_ij|)`` of the exact one: the norm of z
    (d + 2 roundings), the power (libm's, or numpy's SIMD one: a few ulp; 32 allowed; here a
    square root for d = 2 and 4), the product and quotient (2), the matrix product (d), the
    sum (1), on ``|u^(1/d) z / |z|| <= 1``, with room to spare. A box face is decided when
    the point is farther than ``2 e_i`` from it (:func:`_place_in_box`); an ellipsoid as in
    :func:`_count`, the distance moved by ``1.01 |inv|_F |2 e|`` (the point's shift through
    the inverse axes) and by the relative error m of the fast distances (``count_inside``'s
    bound)."""
    n, d = z.shape
    w = np.zeros(n)
    inv, inv_norm, m = _inverses(axes)
    if count and not m <= 1e-3:
        return w, False
    xt = np.empty((d, n))  # the points, transposed (the loops below run over points, innermost)
    shift = np.empty(n)  # a bound on |numpy's point - this one|
    held = np.zeros(n, np.bool_)
    if not _place_in_box(which, z, u, centres, axes, low, high, xt, shift, held):
        return w, False
    if not count:
        for i in range(n):
            w[i] = 1.0 if held[i] else 0.0
        return w, True
    holders = np.zeros(n, np.int64)
    if not _count(xt, inv, inv_norm, centres, shift, held, m, 1.0 + slack, holders):
        return w, False
    for i in range(n):
        if held[i]:
            if holders[i] == 0:
                return w, False  # numpy's 1 / 0: its own path says what that gives
            w[i] = 1.0 / holders[i]
    return w, True


@njit(cache=True, error_model="numpy")
def _place_in_box(which: np.ndarray, z: np.ndarray, u: np.ndarray, centres: np.ndarray, axes: np.ndarray,
                  low: np.ndarray, high: np.ndarray, xt: np.ndarray, shift: np.ndarray, held: np.ndarray) -> bool:
    """The points of :func:`mixture_weights` (columns of ``xt`` (d, n)), the bound ``shift[i]``
    on the distance of point i from numpy's (``|2 e|``, e the margins of
    :func:`mixture_weights`), and whether it lies in the box [``low``, ``high``] (``held``);
    False as soon as a ``z`` row is zero or a point is within ``2 e_i`` of a face."""
    n, d = z.shape
    rel = (4 * d + 128) * 2.220446049250313e-16  # np.finfo(float).eps
    start = _draw_starts(which, centres.shape[0])
    for i in range(n):
        q = which[i]
        at = start[q]
        start[q] += 1
        norm2 = 0.0
        for b in range(d):
            norm2 += z[at, b] * z[at, b]
        if not norm2 > 0.0:
            return False
        scale = _unit_radius(u[at], d) / math.sqrt(norm2)
        inside = True
        shift2 = 0.0
        for a in range(d):
            v = centres[q, a]
            bound = abs(centres[q, a])
            for b in range(d):
                v += axes[q, a, b] * (scale * z[at, b])
                bound += abs(axes[q, a, b])
            xt[a, i] = v
            err = 2.0 * rel * bound
            shift2 += err * err
            if abs(v - low[a]) <= err or abs(v - high[a]) <= err:
                return False  # too close to a face to call
            if not (v >= low[a] and v <= high[a]):
                inside = False
        held[i] = inside
        shift[i] = math.sqrt(shift2)
    return True


@njit(cache=True, error_model="numpy")
def _draw_starts(which: np.ndarray, k: int) -> np.ndarray:
    """Where each of the k ellipsoids' draws begin (in ellipsoid order) for the labels
    ``which``: the cumulative counts, from 0."""
    start = np.zeros(k + 1, np.int64)
    for i in range(which.shape[0]):
        start[which[i] + 1] += 1
    for j in range(k):
        start[j + 1] += start[j]
    return start


@njit(cache=True, error_model="numpy")
def _unit_radius(u: float, d: int) -> float:
    """``u^(1/d)``, the radius of a point uniform in the unit ball (a square root, or two,
    for d = 2 and 4)."""
    if d == 1:
        return u
    if d == 2:
        return math.sqrt(u)
    if d == 4:
        return math.sqrt(math.sqrt(u))
    return u ** (1.0 / d)


@njit(cache=True, error_model="numpy")
def in_box(x: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """``np.all((x >= low) & (x <= high), axis=-1)`` for x (n, d)."""
    n, d = x.shape
    out = np.empty(n, np.bool_)
    for i in range(n):
        ok = True
        for j in range(d):
            if not (x[i, j] >= low[j] and x[i, j] <= high[j]):
                ok = False
                break
        out[i] = ok
    return out
