"""Ellipsoid geometry: uniformity, containment, degenerate inputs."""

import math

import numpy as np
import pytest
from scipy import stats

from abcns import ellipsoid as ell

SEED = 20261122


@pytest.mark.parametrize("d", [1, 2, 3, 5, 10])
def test_samples_are_uniform_inside(d):
    """radius^d of a uniform point in the unit ball is U(0, 1) (dynesty's check); mapped
    back through the ellipsoid's axes. KS test at alpha = 1e-4 per dimension: with five
    dimensions the false-failure rate of this test is 5e-4."""
    rng = np.random.default_rng(SEED + d)
    a = rng.standard_normal((d, d))
    e = ell.from_matrix(rng.standard_normal(d), a @ a.T + 0.1 * np.eye(d))
    x = ell.sample(e, 20_000, rng)
    r2 = ell.mahalanobis2(e, x)
    assert np.all(r2 <= 1 + 1e-9)
    assert stats.kstest(r2 ** (d / 2), "uniform").pvalue > 1e-4
    # the mean of uniform points is the centre: standard error sqrt(var/n) per axis
    y = np.linalg.solve(e.axes, (x - e.centre).T).T  # unit-ball coordinates, var = 1/(d+2)
    assert np.all(np.abs(y.mean(axis=0)) < 5 * math.sqrt(1 / (d + 2) / x.shape[0]))


@pytest.mark.parametrize("d", [1, 2, 4, 7, 10])
def test_fit_holds_every_point_and_is_tight(d):
    rng = np.random.default_rng(SEED)
    pts = rng.standard_normal((max(3 * d, d + 1), d)) * rng.uniform(0.1, 10, d)
    e = ell.fit(pts)
    assert np.all(ell.contains(e, pts))
    assert ell.mahalanobis2(e, pts).max() == pytest.approx(1.0, rel=1e-8)  # scaled to the farthest point
    big = ell.fit_many([pts], enlargement=1.1)[0]
    np.testing.assert_allclose(big.matrix, 1.1 * e.matrix)
    assert big.log_volume == pytest.approx(e.log_volume + 0.5 * d * math.log(1.1))


def test_log_volume_of_a_ball():
    e = ell.from_matrix(np.zeros(3), 4.0 * np.eye(3))  # radius 2
    assert math.exp(e.log_volume) == pytest.approx(4 / 3 * math.pi * 8)


@pytest.mark.parametrize("d", range(1, 11))
def test_degenerate_inputs_do_not_crash(d):
    rng = np.random.default_rng(SEED + 100 + d)
    box = ell.from_box(np.zeros(d), np.ones(d))
    cases = {
        "one point": rng.random((1, d)),
        "d points (fewer than d+1)": rng.random((d, d)),
        "identical points": np.tile(rng.random(d), (d + 3, 1)),
        "collinear points": np.outer(np.linspace(0, 1, d + 5), rng.random(d)) + 0.3,
        "tiny spread": 0.5 + 1e-14 * rng.standard_normal((d + 5, d)),
    }
    for name, pts in cases.items():
        e = ell.fit(pts, fallback=box)
        assert np.all(np.isfinite(e.matrix)), name
        assert np.all(ell.contains(e, pts)), name
        x = ell.sample(e, 100, rng)
        assert np.all(np.isfinite(x)), name
        if d > 1 and name in ("collinear points",):
            assert e.note == "repaired", name
        if name in ("one point", "identical points") or (name.startswith("d points")):
            assert e.note == "fallback", name


def test_fit_without_fallback_refuses_too_few_points():
    with pytest.raises(ValueError, match="no fallback"):
        ell.fit(np.zeros((2, 3)))


def test_box_ellipsoid_holds_the_box_corners():
    low, high = np.array([0.0, 10.0, -5.0]), np.array([1.0, 20.0, 5.0])
    corners = np.array(np.meshgrid(*zip(low, high))).reshape(3, -1).T
    assert np.all(ell.contains(ell.from_box(low, high), corners))


def test_stored_centre_and_matrix_rebuild_the_same_ellipsoid():
    rng = np.random.default_rng(SEED)
    e = ell.fit_many([rng.standard_normal((20, 4))], enlargement=1.1)[0]
    again = ell.from_matrix(e.centre.copy(), e.matrix.copy(), e.note)
    np.testing.assert_array_equal(again.axes, e.axes)
    np.testing.assert_array_equal(ell.sample(again, 5, np.random.default_rng(1)), ell.sample(e, 5, np.random.default_rng(1)))


def test_n_containing_is_the_solve_count_exactly():
    """The fast count (inverse of the axes, used only outside its error window around the
    threshold) equals the solve-based count bit for bit: random and ill-conditioned
    ellipsoids, points on, just inside and just outside the boundaries."""
    rng = np.random.default_rng(SEED)
    paths = set()
    for trial in range(300):
        d, k = int(rng.integers(1, 7)), int(rng.integers(1, 6))
        ells = []
        for _ in range(k):
            q, _ = np.linalg.qr(rng.standard_normal((d, d)))
            lam = 10.0 ** rng.uniform(-12 if trial % 4 == 0 else -2, 2, d)
            ells.append(ell.from_matrix(rng.standard_normal(d), (q * lam) @ q.T))
        z = rng.standard_normal((40 * k, d))
        z /= np.linalg.norm(z, axis=1, keepdims=True)
        r = 1.0 + rng.choice([0.0, 1e-15, -1e-15, 1e-12, -1e-12, 1e-9, 2e-9, -1e-9, 1e-6, -1e-6], z.shape[0])
        if trial % 2:
            r = 1.0 + rng.choice([1e-6, -1e-6, 1e-3, -1e-3], z.shape[0])  # clear of the window: fast path
        x = np.concatenate([e.centre + (r[i::k, None] * z[i::k]) @ e.axes.T for i, e in enumerate(ells)])
        expected = np.sum(ell.mahalanobis2_each(ells, x) <= 1.0 + ell.CONTAINS_SLACK, axis=0)
        np.testing.assert_array_equal(ell.n_containing(ells, x), expected)
        paths.add(ell._n_containing_fast(ells, x) is None)
    assert paths == {True, False}  # both the fast path and the fallback were exercised


def test_fit_many_with_a_fallback_per_set_is_each_fit_bit_for_bit():
    """The coverage's half-fits go through one stacked ``fit_many``, each set with its own
    fallback (its ellipsoid of the bound): the same bits as fitting each set alone, also a
    set too small to define a shape (its fallback's matrix, scaled to hold its points)."""
    rng = np.random.default_rng(3)
    sets = [rng.normal(size=(40, 3)), rng.normal(size=(2, 3)) + 5.0, 2.0 * rng.normal(size=(25, 3))]
    fallbacks = [ell.from_box(np.zeros(3), np.full(3, k)) for k in (1.0, 2.0, 3.0)]
    together = ell.fit_many(sets, fallbacks)
    for got, points, fallback in zip(together, sets, fallbacks, strict=True):
        alone = ell.fit(points, fallback=fallback)
        assert np.array_equal(got.centre, alone.centre) and np.array_equal(got.matrix, alone.matrix)
        assert got.note == alone.note
    assert together[1].note == "fallback"


def test_fit_many_enlarged_is_the_fits_enlarged_bit_for_bit():
    """A bound's ellipsoids (``bounds.fit_union``), the coverage's half-fits and the paper's one
    ellipsoid are fits enlarged by f0; ``fit_many(..., enlargement=f0)`` makes them without
    making the fits first: every field the same bits as each fit with its matrix times f0
    (``from_matrix``), a repaired (collinear) set and a fallback included."""
    rng = np.random.default_rng(4)
    line = np.outer(rng.normal(size=30), [1.0, 2.0, -1.0]) + 1e-14 * rng.normal(size=(30, 3))
    sets = [rng.normal(size=(40, 3)), rng.normal(size=(2, 3)) + 5.0, line]
    fallback = ell.from_box(np.zeros(3), np.full(3, 2.0))
    for f0 in (1.1, 1.0, 0.7):
        direct = ell.fit_many(sets, fallback, enlargement=f0)
        after = [ell.from_matrix(e.centre, f0 * e.matrix, e.note) for e in ell.fit_many(sets, fallback)]
        for a, b in zip(direct, after, strict=True):
            for field in ("centre", "matrix", "axes"):
                assert np.array_equal(getattr(a, field), getattr(b, field)), (f0, field)
            assert a.log_volume == b.log_volume and a.note == b.note
    assert [e.note for e in direct] == ["", "fallback", "repaired"]
    with pytest.raises(ValueError, match="enlargement factor must be > 0"):
        ell.fit_many(sets, fallback, enlargement=0.0)
