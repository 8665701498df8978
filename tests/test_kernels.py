"""The numba kernels against a slow reference, the numpy simulators, and themselves."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from abcns import InvalidSetting
from abcns.distances import NMSE
from abcns.executor import DIVERGED, FAILED, OK, Batch
from abcns.priors import Model
from worker.compose import evaluator
from worker.kernels import choose_substeps
from worker.simulators import BoucWen, Duffing, Linear

# Test priors. Bouc-Wen: paper Table 6 (m assumed in [1, 5], n fixed per draw); Duffing
# and linear: wide boxes with negative damping and stiffness.
DUFFING_PRIOR = {"m": (0.5, 2.0), "c": (-2.0, 20.0), "k": (-1e3, 1e4), "k2": (-1e4, 1e4), "k3": (0.0, 1e6),
                 "k5": (0.0, 1e8)}
BOUC_WEN_PRIOR = {"m": (1.0, 5.0), "c": (-1e3, 1e3), "k": (-1e5, 1e6), "alpha": (-1e4, 1e5), "beta": (-1e4, 1e5),
                  "A": (0.0, 1e6)}
LINEAR_PRIOR = {"m": (0.5, 2.0), "c": (-5.0, 50.0), "k": (-1e3, 1e5)}


def draw(prior: dict, size: int, rng: np.random.Generator) -> np.ndarray:
    low = np.array([lo for lo, _ in prior.values()])
    high = np.array([hi for _, hi in prior.values()])
    return low + (high - low) * rng.random((size, len(prior)))


def bouc_wen_draw(size: int, rng: np.random.Generator, n_exp: int | None = None) -> np.ndarray:
    p = draw(BOUC_WEN_PRIOR, size, rng)
    n = rng.integers(1, 5, size) if n_exp is None else np.full(size, n_exp)
    return np.column_stack([p, n])


def omega_max(prior: dict, stiffness: tuple[str, ...] = ("k",)) -> float:
    """The largest eigenvalue modulus of the linear part over the prior box."""
    m = prior["m"][0]
    c = max(abs(v) for v in prior["c"])
    k = sum(max(abs(v) for v in prior[s]) for s in stiffness)
    return c / (2 * m) + math.sqrt(c * c / (4 * m * m) + k / m)


def rel_l2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a - b, axis=-1) / np.linalg.norm(b, axis=-1)


def reference(rhs, n_state: int, force: np.ndarray, dt: float, observe, interpolation: str = "hold") -> np.ndarray:
    """DOP853 restarted at every sample, so the held force (or the straight line to the next
    sample, ``interpolation="linear"``) is exact."""
    state = np.zeros(n_state)
    out = np.empty(force.size)
    out[0] = observe(state, force[0])
    for i in range(force.size - 1):
        f = force[i]
        slope = (force[i + 1] - f) / dt if interpolation == "linear" else 0.0
        sol = solve_ivp(lambda t, s, f=f, g=slope: rhs(s, f + g * t), (0.0, dt), state, method="DOP853", rtol=1e-11,
                        atol=1e-13)
        assert sol.success
        state = sol.y[:, -1]
        out[i + 1] = observe(state, force[i + 1])
    return out


def duffing_rhs(p):
    m, c, k, k2, k3, k5 = p
    def rhs(s, f):
        x, v = s
        return np.array([v, (f - c * v - x * (k + x * (k2 + x * (k3 + k5 * x * x)))) / m])

    return rhs


def bouc_wen_rhs(p):
    m, c, k, alpha, beta, A, n = p
    n = int(n)

    def rhs(s, f):
        y, v, z = s
        az = abs(z)
        return np.array([v, (f - c * v - k * y - z) / m,
                         A * v - alpha * abs(v) * az ** (n - 1) * z - beta * v * az**n])

    return rhs


def linear_rhs(p):
    m, c, k = p
    return lambda s, f: np.array([s[1], (f - c * s[1] - k * s[0]) / m])


# ---------------------------------------------------------------- accuracy against the reference


def test_choose_substeps():
    assert choose_substeps(0.0, 0.01) == 1
    theta = (120 * 1e-4) ** 0.25
    assert choose_substeps(100.0, 0.01) == math.ceil(1.0 / theta)
    assert choose_substeps(100.0, 0.01, 1e-6) > choose_substeps(100.0, 0.01, 1e-4)
    # the record-length form divides the tolerance by the radians turned over the record
    assert choose_substeps(100.0, 0.01, 1e-4, n_samples=100) == choose_substeps(100.0, 0.01, 1e-4 / 100.0)
    with pytest.raises(ValueError, match="omega_max must be finite and non-negative"):
        choose_substeps(-1.0, 0.01)


@pytest.mark.slow
@pytest.mark.parametrize("interpolation", ["hold", "linear"])
def test_duffing_against_reference(interpolation):
    rng = np.random.default_rng(11)
    dt, ns = 0.01, 120
    force = rng.standard_normal(ns)
    substeps = choose_substeps(omega_max(DUFFING_PRIOR), dt, 1e-4, n_samples=ns)
    params = draw(DUFFING_PRIOR, 3, rng)
    for output, obs_index in (("displacement", 0), ("velocity", 1)):
        sim = Duffing(force, dt, substeps=substeps, output=output, input_interpolation=interpolation).simulate(params)
        assert np.all(sim.status == OK)
        for p, got in zip(params, sim.values, strict=True):
            ref = reference(duffing_rhs(p), 2, force, dt, lambda s, f, j=obs_index: s[j], interpolation)
            assert rel_l2(got, ref) <= 1e-4


@pytest.mark.slow
@pytest.mark.parametrize("interpolation", ["hold", "linear"])
def test_bouc_wen_against_reference(interpolation):
    rng = np.random.default_rng(12)
    dt, ns = 1.0 / 4096, 150
    force = 0.1 * rng.standard_normal(ns)
    om = omega_max(BOUC_WEN_PRIOR, ("k", "A"))
    substeps = choose_substeps(om, dt, 1e-4, n_samples=ns)
    # draws from Table 6; keep those inside what choose_substeps covers: stable enough to
    # stay finite and with the hysteretic rate n (|alpha| + |beta|) |v| |z|^(n-1) below
    # omega_max along the path (z recovered from the acceleration output)
    params = bouc_wen_draw(40, rng)
    outs = {o: BoucWen(force, dt, substeps=substeps, output=o, input_interpolation=interpolation).simulate(params)
            for o in ("displacement", "velocity", "acceleration")}
    y, v, a = (outs[o].values for o in ("displacement", "velocity", "acceleration"))
    m, c, k, alpha, beta, n = (params[:, j : j + 1] for j in (0, 1, 2, 3, 4, 6))
    with np.errstate(all="ignore"):
        z = force - m * a - c * v - k * y  # the acceleration output is at the sample times, where both holds agree
        rate = np.max(n * (np.abs(alpha) + np.abs(beta)) * np.abs(v) * np.abs(z) ** (n - 1), axis=1)
    keep = np.flatnonzero((outs["displacement"].status == OK) & (rate <= om)
                          & (np.max(np.abs(y), axis=1) < 1.0))[:3]
    assert keep.size == 3
    for j in keep:
        ref = reference(bouc_wen_rhs(params[j]), 3, force, dt, lambda s, f: s[0], interpolation)
        assert rel_l2(y[j], ref) <= 1e-4


@pytest.mark.slow
@pytest.mark.parametrize("interpolation", ["hold", "linear"])
def test_linear_against_reference(interpolation):
    rng = np.random.default_rng(13)
    dt, ns = 0.01, 120
    force = rng.standard_normal(ns)
    params = draw(LINEAR_PRIOR, 3, rng)
    for output, observe in (("displacement", lambda s, f: s[0]), ("velocity", lambda s, f: s[1])):
        sim = Linear(force, dt, output=output, input_interpolation=interpolation).simulate(params)
        assert np.all(sim.status == OK)
        for p, got in zip(params, sim.values, strict=True):
            ref = reference(linear_rhs(p), 2, force, dt, observe, interpolation)
            assert rel_l2(got, ref) <= 1e-8  # exact discretisation: only rounding


# ---------------------------------------------------------------- numba against the numpy reference


def cases():
    rng = np.random.default_rng(21)
    f100 = rng.standard_normal(200)
    f4096 = 0.1 * rng.standard_normal(200)
    yield "duffing", Duffing, dict(force=f100, dt=0.01, substeps=12), draw(DUFFING_PRIOR, 40, rng)
    yield "bouc_wen", BoucWen, dict(force=f4096, dt=1 / 4096, substeps=6), bouc_wen_draw(40, rng)
    yield "linear", Linear, dict(force=f100, dt=0.01), draw(LINEAR_PRIOR, 40, rng)


CASES = list(cases())


INTERPOLATIONS = ["hold", "linear"]


@pytest.mark.parametrize("interpolation", INTERPOLATIONS)
@pytest.mark.parametrize("output", ["displacement", "velocity", "acceleration"])
@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_numba_equals_numpy(case, output, interpolation):
    _, cls, kwargs, params = case
    kwargs = {**kwargs, "input_interpolation": interpolation}
    for bound in (np.inf, 0.05):
        fast = cls(**kwargs, output=output, state_bound=bound, backend="numba").simulate(params)
        slow = cls(**kwargs, output=output, state_bound=bound, backend="numpy").simulate(params)
        assert fast.values.shape == slow.values.shape
        np.testing.assert_array_equal(fast.status, slow.status)
        ok = fast.status == OK
        assert ok.sum() >= 5
        err = rel_l2(fast.values[ok], slow.values[ok])
        assert np.all(err <= 1e-12 * max(1.0, kwargs["force"].size / 100)), err.max()
        assert np.all(np.isfinite(fast.values))


@pytest.mark.parametrize("interpolation", INTERPOLATIONS)
@pytest.mark.parametrize("output", ["displacement", "acceleration"])
@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_kernel_nmse_equals_trajectory_nmse(case, output, interpolation):
    _, cls, kwargs, params = case
    kwargs = {**kwargs, "input_interpolation": interpolation}
    sim = cls(**kwargs, output=output, state_bound=10.0)
    out = sim.simulate(params)
    ok = out.status == OK
    rng = np.random.default_rng(5)
    noise = 0.1 * np.std(out.values[ok]) * rng.standard_normal(out.values.shape[1])
    observed = out.values[np.flatnonzero(ok)[0]] + noise
    for window in ((0, observed.size), (17, 150)):
        expected = np.full(params.shape[0], np.inf)
        expected[ok] = NMSE(observed, window)(out.values[ok])
        d, status = sim.distance_nmse(params, observed, *window)
        np.testing.assert_array_equal(status, out.status)
        assert not np.any(np.isnan(d))
        np.testing.assert_allclose(d[ok], expected[ok], rtol=1e-10, atol=0)
        assert np.all(np.isinf(d[~ok]))
        # the numpy backend's distance_nmse is the same thing
        d_ref, s_ref = cls(**kwargs, output=output, state_bound=10.0, backend="numpy").distance_nmse(
            params, observed, *window)
        np.testing.assert_array_equal(s_ref, status)
        np.testing.assert_allclose(d_ref[ok], d[ok], rtol=1e-9)


@pytest.mark.parametrize("interpolation", INTERPOLATIONS)
@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_early_rejection_same_decisions(case, interpolation):
    _, cls, kwargs, params = case
    sim = cls(**kwargs, input_interpolation=interpolation)
    out = sim.simulate(params)
    observed = out.values[np.flatnonzero(out.status == OK)[0]] * 1.1
    full, status_full = sim.distance_nmse(params, observed, 0, observed.size)
    finite = np.sort(full[np.isfinite(full)])
    for eps in (finite[len(finite) // 4], finite[len(finite) // 2], finite[-1], 0.0, 1e-300):
        early, status = sim.distance_nmse(params, observed, 0, observed.size, epsilon=eps)
        accepted = (status_full == OK) & (full < eps)
        np.testing.assert_array_equal((status == OK) & (early < eps), accepted)
        np.testing.assert_array_equal(early[accepted], full[accepted])
        # a particle stopped before it would have diverged is a plain rejection
        changed = status != status_full
        assert np.all((status_full[changed] == DIVERGED) & (status[changed] == OK))
        rejected = (status == OK) & ~accepted
        assert np.all(np.isfinite(early[rejected])) and np.all(early[rejected] >= eps)
        both = rejected & (status_full == OK)
        assert np.all(early[both] <= full[both])


# ---------------------------------------------------------------- divergence


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_blow_ups_are_diverged_never_nan(backend):
    rng = np.random.default_rng(3)
    f = rng.standard_normal(300)
    obs = rng.standard_normal(300)
    duffing = np.array([[1.0, -1e3, 1e4, 0, 0, 0],       # strongly negative damping
                        [1.0, 1.0, -1e5, 0, -1e6, 0],    # negative stiffness and softening: escapes
                        [1.0, 1.0, 1e4, 0, 1e6, 1e8],    # fine
                        [0.0, 1.0, 1.0, 0, 0, 0],        # zero mass
                        [np.nan, 1.0, 1.0, 0, 0, 0]])
    bw = np.array([[1.0, -1e3, 1e4, 1e3, 1e3, 1e5, 2],
                   [1.0, 10.0, -1e5, -1e4, -1e4, 0.0, 3],  # alpha + beta < 0, unstable
                   [1.0, 10.0, 1e4, 1e5, 1e5, 1e6, 2],     # very stiff hysteresis at this step
                   [2.0, 10.0, 0.0, 5e4, 1e3, 5e4, 2]])    # the benchmark's values: fine
    lin = np.array([[1.0, -1e3, 1e4], [1.0, 1.0, -1e5], [1.0, 1.0, 1e4], [0.0, 1.0, 1.0], [1e-300, 1e300, 1e300]])
    kw = {"backend": backend, "state_bound": 1e3}
    for sim, p in ((Duffing(f, 0.01, substeps=4, **kw), duffing),
                   (BoucWen(f, 1 / 4096, substeps=2, **kw), bw),
                   (Linear(f, 0.01, **kw), lin)):
        out = sim.simulate(p)
        d, status = sim.distance_nmse(p, obs, 0, 300)
        d_eps, status_eps = sim.distance_nmse(p, obs, 0, 300, epsilon=50.0)
        assert not np.any(np.isnan(d)) and not np.any(np.isnan(d_eps))
        assert status[0] == DIVERGED and status[1] == DIVERGED
        assert np.all(np.isinf(d[status != OK]))
        if backend == "numba":
            assert np.all(np.isfinite(out.values))
            stopped = (status == DIVERGED) & (status_eps == OK)  # rejected before diverging
            assert np.all(d_eps[stopped] >= 50.0) and np.all(np.isinf(d_eps[status_eps != OK]))
        np.testing.assert_array_equal(out.status, status)
        assert np.all(np.isin(status, (OK, DIVERGED)))
    assert status[2] == OK


def test_bouc_wen_mixed_exponents_and_empty_batch():
    rng = np.random.default_rng(4)
    f = 0.1 * rng.standard_normal(100)
    p = bouc_wen_draw(30, rng)
    fast = BoucWen(f, 1 / 4096, substeps=4).simulate(p)
    slow = BoucWen(f, 1 / 4096, substeps=4, backend="numpy").simulate(p)
    np.testing.assert_array_equal(fast.status, slow.status)
    ok = fast.status == OK
    assert np.all(rel_l2(fast.values[ok], slow.values[ok]) <= 1e-12)
    empty = BoucWen(f, 1 / 4096).simulate(np.empty((0, 7)))
    assert empty.values.shape == (0, 100) and empty.status.shape == (0,)
    for cls, d in ((Duffing, 6), (Linear, 3)):
        out = cls(f, 0.01).simulate(np.empty((0, d)))
        assert out.values.shape == (0, 100)


# ---------------------------------------------------------------- the evaluator's fast path


def test_evaluator_uses_in_kernel_nmse_with_early_rejection():
    rng = np.random.default_rng(8)
    f = rng.standard_normal(200)
    true = np.array([[1.0, 2.0, 1e3, 0.0, 1e5, 0.0]])
    observed = Duffing(f, 0.01, substeps=8).simulate(true).values[0]
    model = Model("duffing", {"c": (0.0, 10.0), "k": (5e2, 2e3)}, {"m": 1.0, "k3": 1e5, "k5": 0.0})
    theta = np.column_stack([rng.uniform(0, 10, 64), rng.uniform(5e2, 2e3, 64)])
    seed, redraws = np.random.SeedSequence(1), np.zeros(64, dtype=int)
    pilot = Batch(0, 0, np.zeros(64, dtype=int), theta, np.inf, seed, redraws)
    generic = evaluator([model], [Duffing(f, 0.01, substeps=8, backend="numpy")], NMSE(observed))(pilot)
    eps = float(np.median(generic.distances))
    batch = Batch(1, 0, np.zeros(64, dtype=int), theta, eps, seed, redraws)
    fast = evaluator([model], [Duffing(f, 0.01, substeps=8)], NMSE(observed))(batch)
    slow = evaluator([model], [Duffing(f, 0.01, substeps=8)], NMSE(observed), early_rejection=False)(batch)
    assert not np.any(np.isin(fast.status, (FAILED,)))
    np.testing.assert_array_equal(fast.status, generic.status)
    np.testing.assert_array_equal(fast.distances < eps, generic.distances < eps)
    np.testing.assert_allclose(slow.distances, generic.distances, rtol=1e-9)
    assert 0 < np.count_nonzero(fast.distances < eps) < 64


def test_the_in_kernel_nmse_checks_its_record_once(monkeypatch):
    """An evaluator passes the same record on every call: its NMSE (finite values, window,
    variance: ~60 µs) is built once per record. A record written into since is checked
    again: its distances are a fresh simulator's, and a non-finite value is refused."""
    import worker.simulators as sims

    built = []
    real = sims._nmse
    monkeypatch.setattr(sims, "_nmse", lambda *args: built.append(args) or real(*args))
    rng = np.random.default_rng(9)
    f = rng.standard_normal(100)
    params = np.array([[1.0, 2.0, 1e3, 0.0, 1e5, 0.0], [1.0, 0.5, 8e2, 0.0, 2e5, 0.0]])
    observed = Duffing(f, 0.01, substeps=2).simulate(params[:1]).values[0] + 0.01 * rng.standard_normal(100)
    sim = Duffing(f, 0.01, substeps=2)
    first = sim.distance_nmse(params, observed, 10, 90)
    again = sim.distance_nmse(params, observed, 10, 90)
    assert len(built) == 1
    np.testing.assert_array_equal(first[0], again[0])
    observed *= 2.0  # the same array, other values: checked again
    changed = sim.distance_nmse(params, observed, 10, 90)
    assert len(built) == 2
    np.testing.assert_array_equal(changed[0], Duffing(f, 0.01, substeps=2).distance_nmse(params, observed, 10, 90)[0])
    assert not np.array_equal(changed[0], first[0])
    sim.distance_nmse(params, observed, 0, 90)  # another window: checked again
    assert len(built) == 4
    observed[20] = np.nan
    with pytest.raises(InvalidSetting, match="non-finite"):
        sim.distance_nmse(params, observed, 10, 90)


# ---------------------------------------------------------------- build properties


def test_kernels_are_cached_and_serial():
    from worker import kernels

    for name in ("duffing_run", "bouc_wen_run", "linear_run", "hold_coefficients", "_duffing_steps",
                 "_bouc_wen_steps_2", "_account"):
        dispatcher = getattr(kernels, name)
        assert not dispatcher.targetoptions.get("parallel", False)
        assert type(dispatcher._cache).__name__ != "NullCache"
        assert dispatcher.targetoptions.get("fastmath") in (None, {"contract"})


def test_backend_and_window_validation():
    f = np.random.default_rng(0).standard_normal(50)
    with pytest.raises(InvalidSetting):
        Duffing(f, 0.01, backend="fortran")
    sim = Duffing(f, 0.01)
    assert sim.config()["backend"] == "numba" and Linear(f, 0.01).config()["backend"] == "numba"
    p = np.array([[1.0, 1.0, 100.0, 0.0, 0.0, 0.0]])
    for window in ((0, 51), (10, 11), (-1, 20)):
        with pytest.raises(InvalidSetting, match=r"^fit: "):  # data.fit in a spec
            sim.distance_nmse(p, f, *window)
    with pytest.raises(ValueError, match="is constant on the fit window"):
        sim.distance_nmse(p, np.zeros(50), 0, 50)  # constant observed: NMSE undefined


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_bouc_wen_z_bound_flags_a_too_coarse_integration(backend):
    """With A >= 0, alpha >= 0, alpha + beta > 0 the exact |z| never exceeds
    (A / (alpha + beta))^(1/n). At one RK4 step per sample this stiff hysteresis overshoots
    it while staying finite (measured with the bound switched off: status OK, |y| 0.03,
    finite garbage); the bound flags it DIVERGED. 64 substeps stay inside: OK."""
    rng = np.random.default_rng(77)
    force = 50 * rng.standard_normal(400)
    p = np.array([[2.0, 10.0, 0.0, 1e4, 1e3, 5e4, 1.0]])
    assert BoucWen(force, 1 / 750, substeps=64, backend=backend).simulate(p).status[0] == OK
    assert BoucWen(force, 1 / 750, substeps=1, backend=backend).simulate(p).status[0] == DIVERGED
    if backend == "numpy":
        unguarded = BoucWen(force, 1 / 750, substeps=1, backend="numpy")
        unguarded.extra_bad = lambda p, state: False
        out = unguarded.simulate(p)
        assert out.status[0] == OK and np.all(np.isfinite(out.values))  # what the bound catches
    assert BoucWen.z_bound(np.array([-1.0]), np.array([5.0]), np.array([1.0]), np.array([1.0]))[0] == np.inf


def test_the_simulating_kernels_release_the_gil():
    """A batch runs in a Dask worker's thread for up to minutes (tests/test_http_holds.py's
    R.3: ~20-90 s). Holding the GIL, it stalled the worker's event loop and the job loop
    seceded in the same process: a job ended by its time budget was reported ended ~16 s
    later. Every kernel a batch calls from Python (``*_run``) is compiled with nogil."""
    from numba.core.registry import CPUDispatcher

    from worker import kernels, restoring_kernels

    runs = {f"{mod.__name__}.{name}": f.targetoptions.get("nogil") for mod in (kernels, restoring_kernels)
            for name, f in vars(mod).items() if isinstance(f, CPUDispatcher) and name.endswith("_run")}
    assert len(runs) == 6 and all(runs.values()), runs
