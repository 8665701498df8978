"""Bounding ellipsoids as an immutable value and small pure functions.

An ellipsoid is ``{x : (x - centre)^T matrix^{-1} (x - centre) <= 1}``. The paper
(Algorithm 2, steps 15-16 and 30) fits one to the surviving particles from their mean
(Eq. 4) and covariance (Eq. 5), scaled so that every survivor is inside, and enlarges
it by f0 (the matrix, not the axes, is multiplied by f0, as in the authors' demo).

Degenerate inputs are handled explicitly and reported in ``Ellipsoid.note``:

- ``"repaired"``: the covariance was ill-conditioned or singular (for example collinear
  points); its eigenvalues were clipped from below at ``lambda_max / max_condition``.
- ``"fallback"``: fewer than d+1 points, or a covariance that is zero or not finite:
  the shape of ``fallback`` (the model's previous ellipsoid, or the ellipsoid
  circumscribing the prior box) is recentred at the points' mean and grown, if needed,
  until it holds every point. A model too sparse to define its own shape keeps the last
  shape it had.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

#: eigenvalues below lambda_max / MAX_CONDITION are clipped (repair of the covariance)
MAX_CONDITION = 1e12


@dataclass(frozen=True, eq=False)
class Ellipsoid:
    """Ellipsoid value. ``axes`` (d, d) satisfies ``axes @ axes.T == matrix``."""

    centre: np.ndarray  # (d,)
    matrix: np.ndarray  # (d, d) symmetric positive definite
    axes: np.ndarray  # (d, d)
    log_volume: float
    note: str = ""  # "" | "repaired" | "fallback" | "box" (from_box)

    @property
    def n_dim(self) -> int:
        return int(self.centre.shape[0])


def log_unit_ball(d: int) -> float:
    """log of the volume of the unit ball in d dimensions (plain Python, so that
    ``abcns.compiled`` compiles this same function for its kernels)."""
    return 0.5 * d * math.log(math.pi) - math.lgamma(0.5 * d + 1.0)


_log_unit_ball = functools.lru_cache(maxsize=64)(log_unit_ball)


def from_matrix(centre: np.ndarray, matrix: np.ndarray, note: str = "") -> Ellipsoid:
    """Build an ellipsoid from its centre and a symmetric positive-definite matrix."""
    return from_matrices([centre], [matrix], [note])[0]


def from_matrices(centres: Sequence[np.ndarray], matrices: Sequence[np.ndarray],
                  notes: Sequence[str]) -> list[Ellipsoid]:
    """:func:`from_matrix` of each (centre, matrix, note), of one dimension d, in one stacked
    call of each numpy step (a stack gives each matrix the bits it gets alone); none for none."""
    cs = [np.asarray(c, dtype=float).reshape(-1) for c in centres]
    if not cs:
        return []
    d = cs[0].shape[0]
    ms = [np.asarray(m, dtype=float) for m in matrices]
    for c, m in zip(cs, ms, strict=True):
        if m.shape != (c.shape[0], c.shape[0]) or c.shape[0] != d:
            raise ValueError(f"matrix has shape {m.shape}, expected ({c.shape[0]}, {c.shape[0]}) for a "
                             f"{c.shape[0]}-d centre")
    stack = np.stack(ms)
    stack = 0.5 * (stack + stack.transpose(0, 2, 1))
    eigval, eigvec = np.linalg.eigh(stack)
    bad = np.flatnonzero(~(np.isfinite(eigval).all(axis=1) & (eigval[:, 0] > 0.0)))
    if bad.size:
        raise ValueError(f"ellipsoid matrix must be positive definite; eigenvalues {eigval[bad[0]]}")
    axes = eigvec * np.sqrt(eigval)[:, None, :]
    log_det = np.sum(np.log(eigval), axis=1)
    lub = _log_unit_ball(d)
    return [Ellipsoid(c, stack[i].copy(), axes[i].copy(), lub + 0.5 * float(log_det[i]), note)
            for i, (c, note) in enumerate(zip(cs, notes, strict=True))]


def from_box(low: np.ndarray, high: np.ndarray) -> Ellipsoid:
    """The axis-aligned ellipsoid through the corners of the box [low, high]."""
    low, high = np.asarray(low, float), np.asarray(high, float)
    d = low.shape[0]
    half = 0.5 * (high - low)
    return from_matrix(0.5 * (low + high), np.diag(d * half**2), note="box")


def stacked(ells: Sequence[Ellipsoid]) -> tuple[np.ndarray, np.ndarray]:
    """(axes (k, d, d), centres (k, d)) of ``ells``, stacked as floats, never to be written to:
    a tuple's (a bound: immutable) are kept for its next calls, the last 256 by identity.
    (Not flagged read-only: numba would compile its kernels once more for such arrays, ~1.4 s
    on a cold cache.)"""
    return _stacked_tuple(ells) if isinstance(ells, tuple) else _stack(ells)


def _stack(ells: Sequence[Ellipsoid]) -> tuple[np.ndarray, np.ndarray]:
    return (np.stack([e.axes for e in ells]).astype(float, copy=False),
            np.stack([e.centre for e in ells]).astype(float, copy=False))


_stacked_tuple = functools.lru_cache(maxsize=256)(_stack)


def mahalanobis2_each(ells: Sequence[Ellipsoid], x: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distances (k, n) of the rows of ``x`` (n, d) to each of ``k``
    ellipsoids of the same dimension, in one stacked solve (LAPACK solves each matrix as it
    would alone: the same bits as one call per ellipsoid)."""
    axes, centres = stacked(ells)
    diff = np.atleast_2d(x)[None, :, :] - centres[:, None, :]  # (k, n, d)
    y = np.linalg.solve(axes, diff.transpose(0, 2, 1))  # (k, d, n)
    y *= y
    return y.sum(axis=1)


def mahalanobis2(ell: Ellipsoid, x: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance of the rows of ``x`` (n, d) to the ellipsoid."""
    return mahalanobis2_each((ell,), x)[0]


#: relative slack of :func:`contains` (a point on the boundary is inside)
CONTAINS_SLACK = 1e-9


def contains(ell: Ellipsoid, x: np.ndarray) -> np.ndarray:
    """Boolean mask: which rows of ``x`` lie inside (boundary included, 1e-9 slack)."""
    return mahalanobis2(ell, x) <= 1.0 + CONTAINS_SLACK


def n_containing(ells: Sequence[Ellipsoid], x: np.ndarray) -> np.ndarray:
    """How many of ``ells`` hold each row of ``x`` (:func:`contains` of each, counted).

    Always the counts of ``mahalanobis2_each(ells, x) <= 1 + CONTAINS_SLACK``, bit for bit,
    at a fraction of its cost: the squared distances are first computed with the inverses
    of the ``axes`` (a product instead of an LU solve, in one compiled pass over the points:
    ``abcns.compiled.count_inside``), and used only if no point lies within their proven
    error of the threshold; otherwise (rare) the whole call is redone by that exact
    expression. (The bound below holds for any order of the sums, so for the compiled loops
    as for BLAS.)

    Error bound, relative, for ``A = axes``, the computed inverse ``X``, ``u = eps`` (twice
    the unit roundoff), ``kappa = |A|_F |X|_F`` and the same ``diff = x - centre`` both ways
    (Higham, Accuracy and Stability of Numerical Algorithms, 2nd ed., Sec. 3.5, Thm 9.4):

    - ``X @ diff = (I + R) A^{-1} diff`` with the left residual ``R = X A - I``, measured
      (within ``(d + 1) u kappa``); with the rounding of the product, the fast ``y`` is within
      ``(|R| + d u kappa) |y|`` of the true ``y = A^{-1} diff``; ``cond_2(A) <= kappa / (1 - |R|)``;
    - LU with partial pivoting (``np.linalg.solve``) solves ``(A + dA) y = diff`` with
      ``|dA| <= 3 d u |L||U|``, so ``|dA|_2 <= 3 d u d^2 2^(d-1) |A|_2`` (growth factor at
      most 2^(d-1)): its ``y`` is within ``1.01 cond_2(A) |dA|_2 / |A|_2`` of the true one;
    - the sum of squares adds ``d u``, either way.

    So the two squared distances differ by at most ``~2 b`` relative to the fast one, with
    ``b = |R| + (d + 1 + 4 d^3 2^d) u kappa`` (the largest over the ellipsoids); with a factor
    5 to spare, ``m = 10 b``. A point whose fast value is below ``t (1 - 2m)`` or above
    ``t (1 + 2m)`` (``t = 1 + CONTAINS_SLACK``) is on the same side of ``t`` both ways. ``m`` is
    ~1e-10 for cond(axes) < 100 in 4 dimensions, ~1e-7 at cond 1e4. Exact path when: any
    point is within that window; ``m > 1e-3`` (ill-conditioned ``axes``); any fast value is
    not finite or above 1e300 (non-finite ``x``, overflow: the warnings stay the exact path's).
    """
    counts = _n_containing_fast(ells, x)
    return np.sum(mahalanobis2_each(ells, x) <= 1.0 + CONTAINS_SLACK, axis=0) if counts is None else counts


def _n_containing_fast(ells: Sequence[Ellipsoid], x: np.ndarray) -> np.ndarray | None:
    """:func:`n_containing` by the inverses of ``axes`` (compiled:
    ``abcns.compiled.count_inside``, one pass over the points); None when it cannot be sure
    (and on any input the exact path should judge: a bad shape or type, a singular matrix)."""
    x = np.atleast_2d(x)
    if x.ndim != 2 or x.dtype.kind not in "biuf" or not ells:
        return None
    from abcns import compiled

    try:  # on a bad shape or a singular matrix, the exact path raises its own error
        axes, centres = stacked(ells)
        if axes.shape[1:] != (x.shape[1], x.shape[1]) or centres.shape[1] != x.shape[1]:
            return None
        counts, ok = compiled.count_inside(np.ascontiguousarray(x.T, dtype=float), axes, centres, CONTAINS_SLACK)
    except ValueError:  # np.linalg.LinAlgError included
        return None
    return counts if ok else None


def _check_enlargement(f0: float) -> None:
    if not f0 > 0:
        raise ValueError(f"enlargement factor must be > 0, got {f0}")


def _enlarged(centres: Sequence[np.ndarray], matrices: Sequence[np.ndarray], notes: Sequence[str],
              f0: float) -> list[Ellipsoid]:
    """The ellipsoids :func:`from_matrices` makes of ``matrices``, enlarged by ``f0``: each
    matrix symmetrised as ``from_matrices`` does (an ellipsoid's matrix already is: the same
    bits), times f0."""
    stack = np.stack(matrices)
    return from_matrices(centres, list(0.5 * (stack + stack.transpose(0, 2, 1)) * f0), notes)


def sample(ell: Ellipsoid, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniform inside the ellipsoid, shape (n, d)."""
    z, u = unit_draws(ell.n_dim, n, rng)
    return from_unit_draws(ell, z, u)


def unit_draws(d: int, n: int, rng: np.random.Generator,
               out: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The random numbers of :func:`sample`: normals (n, d) (directions) and uniforms (n, 1)
    (radii), drawn in that order (into ``out``'s C-contiguous arrays when given: the same
    numbers)."""
    if out is None:
        return rng.standard_normal((n, d)), rng.random((n, 1))
    rng.standard_normal(out=out[0])
    rng.random(out=out[1])
    return out


def from_unit_draws(ell: Ellipsoid, z: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The points of :func:`sample` from its random numbers: ``centre + axes (u^(1/d) z / |z|)``."""
    return in_ellipsoid(ell, unit_ball_points(z, u))


def unit_ball_points(z: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Points uniform in the unit ball from normals ``z`` (n, d) and uniforms ``u`` (n, 1):
    ``u^(1/d) z / |z|`` (row by row: the same bits for any stack of rows)."""
    norms = np.sqrt((z * z).sum(axis=1, keepdims=True))  # np.linalg.norm(z, axis=1), same sum
    norms[norms == 0.0] = 1.0
    radius = u ** (1.0 / z.shape[1])
    return radius * z / norms


def in_ellipsoid(ell: Ellipsoid, w: np.ndarray) -> np.ndarray:
    """The unit ball's points ``w`` (n, d) mapped into the ellipsoid: ``centre + axes w``."""
    return ell.centre + w @ ell.axes.T


def _repair(covs: np.ndarray, max_condition: float, scales: Sequence[float]) -> list[tuple[np.ndarray, bool] | None]:
    """Clip small eigenvalues of each covariance (k, d, d); None where one carries no usable
    shape (not finite, or no spread above the rounding error of coordinates of size its
    ``scales``)."""
    covs = 0.5 * (covs + covs.transpose(0, 2, 1))
    out: list[tuple[np.ndarray, bool] | None] = [None] * covs.shape[0]
    finite = [i for i in range(covs.shape[0]) if np.isfinite(covs[i]).all()]
    if not finite:
        return out
    eigval, eigvec = np.linalg.eigh(covs[finite])
    for i, ev, vec in zip(finite, eigval, eigvec, strict=True):
        top = ev[-1]
        if not top > (1e3 * np.finfo(float).eps * scales[i]) ** 2:
            continue
        floor = top / max_condition
        if ev[0] >= floor:
            out[i] = covs[i].copy(), False
        else:
            out[i] = (vec * np.maximum(ev, floor)) @ vec.T, True
    return out


def _covariance(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``np.cov(points, rowvar=False)`` (n > 1 points, (d, d)), by its own steps (the same
    bits: ``centre`` is the points' mean as ``np.cov`` computes it), without its checks."""
    x = np.array(points, dtype=float).T
    x -= centre[:, None]
    c = np.dot(x, x.T.conj())
    c *= np.true_divide(1, points.shape[0] - 1)
    return c


def fit(
    points: np.ndarray,
    fallback: Ellipsoid | None = None,
    max_condition: float = MAX_CONDITION,
) -> Ellipsoid:
    """Smallest scaling of the points' covariance ellipsoid that holds every point.

    Parameters
    ----------
    points : (n, d) array, n >= 1
    fallback : ellipsoid whose shape is used when the points cannot define one
        (n < d + 1, zero or non-finite covariance); required in that case.
    max_condition : largest condition number kept; above it the covariance is repaired.
    """
    return fit_many([points], fallback, max_condition)[0]


def fit_many(
    point_sets: Sequence[np.ndarray],
    fallback: Ellipsoid | Callable[[], Ellipsoid] | Sequence[Ellipsoid] | None = None,
    max_condition: float = MAX_CONDITION,
    enlargement: float | None = None,
) -> list[Ellipsoid]:
    """:func:`fit` of each set of points (of one dimension), the matrix steps stacked.
    ``fallback`` may be a function that makes it, called only if a set needs it, or one
    fallback per set. With ``enlargement`` f0, each fit enlarged by it (Algorithm 2, step 16:
    the matrix times f0, the axes grow by sqrt(f0)): ``from_matrix(e.centre, f0 * e.matrix,
    e.note)`` of each fit ``e``, bit for bit, without making the fits themselves (an
    ellipsoid's matrix is the symmetrised one it is made from, and enlarging multiplies that)."""
    if enlargement is not None:
        _check_enlargement(enlargement)
    sets = [np.atleast_2d(np.asarray(p, dtype=float)) for p in point_sets]
    d = sets[0].shape[1]
    for p in sets:
        if p.shape[0] == 0:
            raise ValueError("cannot fit an ellipsoid to zero points")
        if not np.isfinite(p).all():
            raise ValueError("cannot fit an ellipsoid to non-finite points")
    centres = [p.mean(axis=0) for p in sets]
    scales = [max(1e-300, float(np.max(np.abs(p)))) for p in sets]
    shaped = [i for i, p in enumerate(sets) if p.shape[0] > d]
    repaired: list[tuple[np.ndarray, bool] | None] = [None] * len(sets)
    if shaped:
        covs = np.stack([_covariance(sets[i], centres[i]).reshape(d, d) for i in shaped])
        for i, r in zip(shaped, _repair(covs, max_condition, [scales[i] for i in shaped]), strict=True):
            repaired[i] = r
    shapes, notes = [], []
    for i, (p, r) in enumerate(zip(sets, repaired, strict=True)):
        if r is None:
            if callable(fallback):
                fallback = fallback()
            fb = fallback[i] if isinstance(fallback, Sequence) else fallback
            if fb is None:
                raise ValueError(f"{p.shape[0]} points in {d} dimensions define no ellipsoid and no fallback was given")
            assert isinstance(fb, Ellipsoid)
            if fb.n_dim != d:
                raise ValueError(f"fallback has {fb.n_dim} dimensions, points have {d}")
            shapes.append(fb.matrix)
            notes.append("fallback")
        else:
            shapes.append(r[0])
            notes.append("repaired" if r[1] else "")
    trials = from_matrices(centres, shapes, notes)
    grown = []
    for p, r, trial, shape in zip(sets, repaired, trials, shapes, strict=True):
        scale = float(np.max(mahalanobis2(trial, p)))
        if r is None:
            scale = max(1.0, scale)
        elif not scale > 0.0:  # every point at the centre: keep the covariance shape as is
            scale = 1.0
        grown.append(shape * scale * (1.0 + 1e-10))
    return from_matrices(centres, grown, notes) if enlargement is None else _enlarged(centres, grown, notes, enlargement)
