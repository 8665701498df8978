"""Reference simulators against a slow, exact-as-possible integration.

The reference is scipy's DOP853 (rtol 1e-11, atol 1e-13) restarted at every sample so the
held force (or, for ``input_interpolation="linear"``, the straight line to the next sample)
is exact; restarted N times its own error is at most about N x 1e-11 (relative,
errors of the restarts adding up in the worst case). RK4 with step h has global error
E(h) ~ C h^4, so halving the step estimates it (Richardson): y_h - y_(h/2) = (15/16) C h^4,
E(h) ~ (16/15) |y_h - y_(h/2)|; for a right-hand side that is not smooth (|v| in Bouc-Wen)
the order can drop to 1, and E(h) ~ 2 |y_h - y_(h/2)| bounds it then. Each tolerance below is
such an estimate, computed in the test, plus the reference's own error.
"""

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.special import ndtri

from abcns import DIVERGED, OK
from examples.paper import DATA
from worker.simulators import BoucWen, Duffing, GAndK, Linear

SEED = 1234
RTOL_REF = 1e-11  # DOP853's rtol in reference()


def reference(rhs, force, dt, n_state, observe=lambda s, f: s[0], interpolation="hold"):
    state = np.zeros(n_state)
    out = [observe(state, force[0])]
    for i in range(force.size - 1):
        f0, slope = force[i], (force[i + 1] - force[i]) / dt if interpolation == "linear" else 0.0
        sol = solve_ivp(lambda t, s: rhs(s, f0 + slope * t), (0, dt), state, method="DOP853", rtol=1e-11, atol=1e-13)
        state = sol.y[:, -1]
        out.append(observe(state, force[i + 1]))
    return np.array(out)


def rel_l2(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def test_duffing_reproduces_the_authors_data_exactly():
    with np.load(DATA / "authors-demo" / "demo_data.npz") as f:
        d = dict(f)
    out = Duffing(d["force"], float(d["dt"]), substeps=1).simulate(np.array([[1, 0.05, 50, 0, 1000, 0]]))
    assert out.status[0] == OK
    # the same RK4 steps in another order of operations: float64 rounding (eps 2.2e-16 of the
    # state, max |x| = 0.158) at most once per step and sample, 501 samples: 501 * 2.2e-16 *
    # 0.158 = 1.7e-14 (measured 4.8e-16)
    x = d["displacement"]
    np.testing.assert_allclose(out.values[0], x, rtol=0, atol=x.size * np.finfo(float).eps * np.max(np.abs(x)))


@pytest.mark.parametrize("interpolation", ["hold", "linear"])
@pytest.mark.parametrize("output", ["displacement", "velocity", "acceleration"])
def test_duffing_against_dop853(output, interpolation):
    rng = np.random.default_rng(SEED)
    force = 10 * rng.standard_normal(120)
    dt = 0.01
    lo, hi = np.array([0.005, 5, 100, 1e4]), np.array([0.5, 500, 1e4, 1e6])  # paper Table 3
    idx = {"displacement": 0, "velocity": 1}
    for _ in range(3):
        c, k, k3, k5 = lo + (hi - lo) * rng.random(4)
        p = np.array([[1.0, c, k, 0.0, k3, k5]])

        def rhs(s, f):
            return [s[1], f - c * s[1] - k * s[0] - k3 * s[0] ** 3 - k5 * s[0] ** 5]

        obs = (lambda s, f: rhs(s, f)[1]) if output == "acceleration" else (lambda s, f, j=idx.get(output): s[j])
        ref = reference(rhs, force, dt, 2, obs, interpolation)
        out = Duffing(force, dt, substeps=16, output=output, input_interpolation=interpolation).simulate(p)
        assert out.status[0] == OK
        y32, y64 = (Duffing(force, dt, substeps=s, output=output, input_interpolation=interpolation).simulate(p).values[0]
                    for s in (32, 64))
        # fourth order: halving the step divides the change by 2^4 = 16 (measured 15.9-16.1)
        assert 14 < rel_l2(out.values[0], y32) / rel_l2(y32, y64) < 18
        # the error is the step-halving estimate (16/15) |y_16 - y_32| (measured 1.5e-10 to
        # 1.5e-9, equal to the error to 1 %), given a factor 2, plus the reference's error
        estimate = 16 / 15 * rel_l2(out.values[0], y32)
        assert rel_l2(out.values[0], ref) < 2 * estimate + force.size * RTOL_REF


@pytest.mark.parametrize("interpolation", ["hold", "linear"])
@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_linear_exact_recursion_against_dop853(interpolation, backend):
    rng = np.random.default_rng(SEED)
    force = 10 * rng.standard_normal(200)
    for c, k in [(20.0, 1e4), (10.0, 5000.0), (50.0, 15000.0), (-1.0, 100.0), (3.0, -50.0)]:
        ref = reference(lambda s, f, c=c, k=k: [s[1], f - c * s[1] - k * s[0]], force, 0.01, 2,
                        interpolation=interpolation)
        out = Linear(force, 0.01, input_interpolation=interpolation, backend=backend).simulate(np.array([[1.0, c, k]]))
        # either recursion is exact for its interpolation (the first-order hold's ramp
        # coefficients come from the same matrix exponential): what differs is the
        # reference's own error, at most 200 restarts x rtol 1e-11 = 2e-9 (measured 7e-15
        # to 7e-12)
        assert rel_l2(out.values[0], ref) < force.size * RTOL_REF, (c, k)


@pytest.mark.parametrize("interpolation", ["hold", "linear"])
@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_bouc_wen_against_dop853(n, interpolation):
    rng = np.random.default_rng(SEED + n)
    dt = 1 / 4096
    force = 50 * rng.standard_normal(200)
    # the Bouc-Wen benchmark's values (m, c, k, A = 2, 10, 5e4, 5e4; alpha = 800, beta = -1100
    # for n = 1, alpha + beta < 0 as Table 6 allows), scaled so the |z|^n terms matter at z ~ 50
    m, c, k, A = 2.0, 10.0, 5e4, 5e4
    alpha, beta = 800.0 / 50.0 ** (n - 1), -1100.0 / 50.0 ** (n - 1)

    def rhs(s, f):
        y, v, z = s
        zdot = A * v - alpha * abs(v) * abs(z) ** (n - 1) * z - beta * v * abs(z) ** n
        return [v, (f - c * v - k * y - z) / m, zdot]

    ref = reference(rhs, force, dt, 3, interpolation=interpolation)
    p = np.array([[m, c, k, alpha, beta, A, n]])
    out = BoucWen(force, dt, substeps=8, input_interpolation=interpolation).simulate(p)
    assert out.status[0] == OK
    # |v| and |z|^n are not smooth at 0, so the order is not 4 (halving the step divides the
    # error by 2 to 22, measured): the order-1 step-halving bound 2 |y_8 - y_16| (measured
    # 1.7 to 2.8 times the error, 1.2e-9 for n = 4 to 5.4e-7 for n = 1), plus the reference's
    # own error (200 restarts x 1e-11)
    half = BoucWen(force, dt, substeps=16, input_interpolation=interpolation).simulate(p).values[0]
    assert rel_l2(out.values[0], ref) < 2 * rel_l2(out.values[0], half) + force.size * RTOL_REF


def test_blow_ups_are_flagged_never_nan():
    rng = np.random.default_rng(SEED)
    force = 1e3 * rng.standard_normal(300)
    p = np.array([[1.0, -50.0, 10.0, 0, 1e4, 1e6],  # negative damping: grows without bound
                  [1.0, 0.1, 50.0, 0, -1e4, 0],  # softening cubic: escapes
                  [1.0, 0.5, 50.0, 0, 1e3, 0]])  # healthy
    out = Duffing(force, 0.01, substeps=1, state_bound=1e3).simulate(p)
    assert out.status.tolist() == [DIVERGED, DIVERGED, OK]
    assert np.all(np.isfinite(out.values[2]))
    bw = BoucWen(force, 1 / 4096, substeps=2, state_bound=1.0).simulate(
        np.array([[1.0, -1e3, -1e5, -1e4, -1e4, 1e6, 2], [2.0, 10.0, 0.0, 1e3, 1e3, 1e4, 1]]))
    assert bw.status[0] == DIVERGED and bw.status[1] == OK


def test_gandk_median_and_quantiles():
    """z = 0 maps to A, so the sample median estimates A; the sample quantiles of n iid draws
    estimate the quantile function Q with standard error sqrt(p(1-p)/n)/density =
    sqrt(p(1-p)/n) Q'(p) (Q' by central difference): 0.0012, 0.0028, 0.0106 at p = 0.2, 0.5,
    0.8; measured deviations -2.1, -0.7, +1.2 standard errors; allowed 4 (a 6e-5 chance each)."""
    rng = np.random.default_rng(SEED)
    theta = np.array([[3.0, 1.0, 2.0, 0.5, 0.8]])
    x = GAndK(200_000).simulate(theta, rng).values[0]

    def q(p):
        return GAndK.quantile(theta, ndtri(np.array([p])))[0, 0]  # the quantile function at probability p

    for p in (0.2, 0.5, 0.8):
        se = np.sqrt(p * (1 - p) / x.size) * (q(p + 1e-6) - q(p - 1e-6)) / 2e-6
        assert abs(np.quantile(x, p) - q(p)) < 4 * se, (p, np.quantile(x, p) - q(p), se)
    assert q(0.5) == 3.0
    assert abs(np.median(x) - 3.0) < 4 * np.sqrt(0.25 / x.size) * (q(0.5 + 1e-6) - q(0.5 - 1e-6)) / 2e-6
