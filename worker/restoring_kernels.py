"""Numba batch kernels for the displacement-driven restoring-force models
(:mod:`worker.restoring`): Bouc-Wen and Bouc-Wen-Baber-Noori.

The layout, the accounting (trajectory or in-kernel NMSE with early rejection), the
divergence guard and the compaction are those of :mod:`worker.kernels` (its ``_account``,
``_compact`` and ``_finish`` are reused). The input record is the displacement ``x``; the
output is the force ``F_i = c v_i + k x_i + alpha z_i``, ``v_i`` the velocity at sample ``i``
(central differences, computed once by the caller). Row 0 of the work array holds the last
output force, so that the guard's bound applies to the force.

Between samples the displacement moves on a straight line (first-order hold), so the
hysteretic state is integrated in the displacement itself: over step ``i``, classical RK4
steps of ``dz/dx = g(z, e; sign(dx))`` (and ``de/dx = alpha z`` for the Baber-Noori energy),
``m`` of them of size ``(x[i+1] - x[i]) / m``. The models are rate independent, so the sample
interval enters only through the viscous term; a step with no displacement leaves the state
unchanged.

Step control: ``m`` is chosen per particle and per sample step, at least the spec's
``substeps``, so that ``|dx| L <= KAPPA`` for the particle's rate scale ``L`` at the step's
start (:func:`_bw_rate`, :func:`_bwbn_rate`): the stiffness of the Bouc-Wen law
``|d g / d z|``, and for Baber-Noori the pinching notch, ``zeta_1 / zeta_2`` times ``|g|``: a
notch of width zeta_2 in z that a coarse step jumps over gives a loop no finer step
reproduces (sharma's posterior under 4 fixed substeps: NMSE 2.82 %, 6.12 % at 64 and more).
A particle that needs no more than ``substeps`` is integrated exactly as before.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from worker.kernels import _JIT, _account, _compact, _finish, _zpow

# rows: 0 F (the last output), 1 z, 2 acc, 3 c, 4 k, 5 alpha, 6 A, 7 beta, 8 gamma, 9 n, 10 |z| bound (inf: none)
BW_ROWS = 11
# rows: 0 F, 1 z, 2 e, 3 acc, 4 c, 5 k, 6 alpha, 7 A, 8 beta, 9 gamma, 10 n, 11 delta_nu, 12 delta_eta,
# 13 p, 14 zeta_s, 15 psi, 16 delta_psi, 17 lambda, 18 q
BWBN_ROWS = 19


@njit(inline="always", **_JIT)
def _pow(az, n, n_exp):
    """``az**n``: for an integer exponent ``n_exp`` in 1..4 (constant in the caller's loop) by
    multiplications, else (``n_exp`` 0) by ``pow`` (~20x slower)."""
    if n_exp == 0:
        return math.pow(az, n)
    return _zpow(az, n_exp) * az


@njit(inline="always", **_JIT)
def _root(a, n, n_exp):
    """``a**(1/n)`` (as :func:`_pow`: integer ``n_exp`` by square roots where it can)."""
    if n_exp == 1:
        return a
    if n_exp == 2:
        return math.sqrt(a)
    if n_exp == 4:
        return math.sqrt(math.sqrt(a))
    return math.pow(a, 1.0 / n)


_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01  # ln 2 in two parts (Cody and Waite): k * _LN2_HI is exact
_LN2_LO = 1.90821492927058770002e-10


@njit(inline="always", **_JIT)
def _exp_neg(x):
    """``exp(x)`` for ``x <= 0``, within 1 ulp of libm's (measured: 2.2e-16 relative over
    [-50, 0]), in plain arithmetic that LLVM vectorises (numba's ``math.exp`` is a libm call
    per particle without SVML; this is ~5x faster in a loop). ``x`` below -708 is taken as
    -708 (the result ~3e-308 instead of a subnormal or 0). ``exp(r)`` for
    ``|r| <= ln2 / 2`` by its Taylor series to ``r^13 / 13!`` (truncation < 1e-17), times
    ``2^k`` made from the exponent's bits."""
    x = max(x, -708.0)
    k = math.floor(x * _LOG2E + 0.5)
    r = (x - k * _LN2_HI) - k * _LN2_LO
    p = 1.0 / 6227020800.0
    p = p * r + 1.0 / 479001600.0
    p = p * r + 1.0 / 39916800.0
    p = p * r + 1.0 / 3628800.0
    p = p * r + 1.0 / 362880.0
    p = p * r + 1.0 / 40320.0
    p = p * r + 1.0 / 5040.0
    p = p * r + 1.0 / 720.0
    p = p * r + 1.0 / 120.0
    p = p * r + 1.0 / 24.0
    p = p * r + 1.0 / 6.0
    p = p * r + 0.5
    p = p * r + 1.0
    p = p * r + 1.0
    return p * np.int64((np.int64(k) + 1023) << 52).view(np.float64)


#: the step control's bound on |dx| L per RK4 step, L a particle's rate scale (module
#: docstring; docs/design.md, "Step control"), and the most steps one sample step may take (a
#: particle asking for more is DIVERGED). Kept here, not imported: numba's cache knows a kernel's
#: file, not the globals it reads from another
KAPPA = 1.0
MAX_SUBSTEPS = 4096
#: the pinching notch counts in the step control only where a step's z may come within this many
#: zeta_2 of its centre (beyond, h differs from 1 by less than zeta_1 exp(-16) ~ 1e-7)
NOTCH_REACH = 4.0


@njit(inline="always", **_JIT)
def _steps_wanted(ad, rate):
    """The RK4 steps a sample step of length ``ad`` (|dx|) asks for at the rate scale ``rate``,
    unrounded: ``ad rate / KAPPA`` (the step takes :func:`_steps_taken` of it)."""
    return ad * rate / KAPPA


@njit(inline="always", **_JIT)
def _steps_taken(want, substeps):
    """The RK4 steps of a sample step that asks for ``want``: ``substeps`` or more,
    ``ceil(want)``; 0 (DIVERGED) past MAX_SUBSTEPS or for a rate that is not a number."""
    if not want <= MAX_SUBSTEPS:
        return 0
    return max(substeps, math.ceil(want))


@njit(inline="always", **_JIT)
def _stiffness(az, zu, n, n_exp, nu, beta, gamma):
    """A bound of ``|d g / d z|`` for ``g = A - nu |z|^n (beta sign + gamma)`` near ``|z| = az``:
    ``nu n a^(n - 1) (beta + |gamma|)`` at ``a = max(az, |zu|)`` (the state's scale; with n = 1
    no power at all)."""
    b = nu * (beta + abs(gamma))
    if n_exp == 1:
        return b
    a = max(az, abs(zu))
    ok = a > 0.0 and a < math.inf
    return n * b * (_pow(a, n, n_exp) / a if ok else 1.0)


@njit(inline="always", **_JIT)
def _bw_rate(z, A, beta, gamma, n, n_exp):
    """The Bouc-Wen law's rate scale at ``z`` (:func:`_stiffness`, ``z_u = (A / (beta +
    gamma))^(1/n)``; beta + gamma > 0 for every particle that reaches a kernel: the domain,
    ``worker.restoring._Restoring.outside``)."""
    return _stiffness(abs(z), _root(A / (beta + gamma), n, n_exp), n, n_exp, 1.0, beta, gamma)


@njit(inline="always", **_JIT)
def _bw_slope(z, s, A, beta, gamma, n, n_exp):
    """dz/dx of Bouc-Wen: ``A - |z|^n (beta sign(s z) + gamma)``, s the sign of dx."""
    return A - _pow(abs(z), n, n_exp) * (beta * math.copysign(1.0, s * z) + gamma)


@njit(inline="always", **_JIT)
def _bw_rk4(z0, d, dx, A, be, ga, ne, n_exp):
    """z after one RK4 step of size ``dx`` in x from ``z0`` (``d``: the sample step, its sign)."""
    hh = 0.5 * dx
    q1 = _bw_slope(z0, d, A, be, ga, ne, n_exp)
    q2 = _bw_slope(z0 + hh * q1, d, A, be, ga, ne, n_exp)
    q3 = _bw_slope(z0 + hh * q2, d, A, be, ga, ne, n_exp)
    q4 = _bw_slope(z0 + dx * q3, d, A, be, ga, ne, n_exp)
    return z0 + dx / 6.0 * ((q1 + q4) + 2.0 * (q2 + q3))


@njit(**_JIT)
def _bw_steps(w, n_act, d, substeps, n_exp, want, before):
    """Advance z over one sample step of length ``d`` in x: per particle, :func:`_steps_taken`
    RK4 steps (its rate :func:`_bw_rate`). Every particle takes ``substeps`` steps in one loop
    across particles (it vectorises); one that asks for more starts again from its state
    (kept in ``before``) with its count, one past MAX_SUBSTEPS is DIVERGED (NaN)."""
    z = w[1]
    A = w[6]
    be = w[7]
    ga = w[8]
    ne = w[9]
    ad = abs(d)
    for j in range(n_act):
        want[j] = _steps_wanted(ad, _bw_rate(z[j], A[j], be[j], ga[j], ne[j], n_exp))
        before[j] = z[j]
    dx = d / substeps
    for _ in range(substeps):
        for j in range(n_act):
            z[j] = _bw_rk4(z[j], d, dx, A[j], be[j], ga[j], ne[j], n_exp)
    for j in range(n_act):
        if not want[j] <= substeps:
            m = _steps_taken(want[j], substeps)
            if m == 0:
                z[j] = np.nan
                continue
            zj = before[j]
            for _ in range(m):
                zj = _bw_rk4(zj, d, d / m, A[j], be[j], ga[j], ne[j], n_exp)
            z[j] = zj


@njit(**_JIT)
def _output(w, n_act, x, v, c_row, out):
    """``F = c v + k x + alpha z`` into ``out`` and row 0 (z in row 1; c, k, alpha in rows
    ``c_row``, ``c_row + 1``, ``c_row + 2``)."""
    F = w[0]
    z = w[1]
    c = w[c_row]
    k = w[c_row + 1]
    al = w[c_row + 2]
    for j in range(n_act):
        f = c[j] * v + k[j] * x + al[j] * z[j]
        F[j] = f
        out[j] = f


@njit(**_JIT)
def bw_restoring_run(w, n_exp, disp, vel, substeps, bound, obs, start, stop, scale, eps, cols, want_traj, traj, dist, status):
    """Run a Bouc-Wen restoring-force batch in place. ``w`` is ``(BW_ROWS, n)``; ``n_exp``:
    the exponent of every particle when it is an integer in 1..4, else 0 (read from row 9)."""
    n = w.shape[1]
    idx = cols.copy()
    y = np.empty(n)
    flag = np.zeros(n, dtype=np.int8)
    n_act = n
    ns = disp.shape[0]
    z = w[1]
    zmax = w[10]
    want = np.empty(n)
    before = np.empty(n)
    for i in range(ns):
        for j in range(n_act):  # past the bound the equation implies: the integration is wrong
            if abs(z[j]) > zmax[j]:
                z[j] = np.nan  # the finiteness test below flags it DIVERGED
        _output(w, n_act, disp[i], vel[i], 3, y)
        if _account(w, 2, 2, n_act, i, y, bound, obs, start, stop, scale, eps, want_traj, traj, idx, flag,
                    dist, status):
            n_act = _compact(w, idx, flag, n_act)
            if n_act == 0:
                return
        if i + 1 < ns:
            d = disp[i + 1] - disp[i]
            if d != 0.0:
                _steps_bw(w, n_act, d, substeps, n_exp, want, before)
    _finish(w, 2, n_act, scale, idx, dist, status)


@njit(inline="always", **_JIT)
def _bwbn_slopes(z, e, s, pj, n_exp):
    """(dz/dx, de/dx) of Bouc-Wen-Baber-Noori (Foliente 1995, as Ortiz et al. 2015 use it,
    with nu0 = eta0 = 1 and no degradation of A): ``h(z, e) (A - nu |z|^n (beta sign(s z) +
    gamma)) / eta`` and ``alpha z``; see :class:`worker.restoring.BWBNRestoring`. ``pj``:
    (alpha, A, beta, gamma, n, delta_nu, delta_eta, p, zeta_s, psi, delta_psi, lambda, q)."""
    al, A, beta, gamma, n, dnu, deta, p, zs, psi, dpsi, lam, q = pj
    nu = 1.0 + dnu * e
    eta = 1.0 + deta * e
    zu = _root(A / (nu * (beta + gamma)), n, n_exp)
    z1 = zs * (1.0 - _exp_neg(-p * e))
    z2 = (psi + dpsi * e) * (lam + z1)
    u = (math.copysign(1.0, s) * z - q * zu) / z2
    h = 1.0 - z1 * _exp_neg(-u * u)
    g = A - nu * _pow(abs(z), n, n_exp) * (beta * math.copysign(1.0, s * z) + gamma)
    return h * g / eta, al * z


@njit(inline="always", **_JIT)
def _bwbn_rate(z, e, ad, s, pj, n_exp):
    """The Baber-Noori law's rate scale at (z, e) over a sample step of length ``ad`` in the
    direction of ``s``: (:func:`_stiffness` + the pinching notch's ``zeta_1 / zeta_2 |g|``) /
    eta (|d h / d z| <= 0.86 zeta_1 / zeta_2), the notch's only where z may come within
    NOTCH_REACH zeta_2 of its centre ``q z_u sign(s)`` (z moves by at most ``ad |g| / eta``);
    ``pj`` as in :func:`_bwbn_slopes`."""
    _al, A, beta, gamma, n, dnu, deta, p, zs, psi, dpsi, lam, q = pj
    nu = 1.0 + dnu * e
    eta = 1.0 + deta * e
    az = abs(z)
    zu = _root(A / (nu * (beta + gamma)), n, n_exp)
    z1 = zs * (1.0 - _exp_neg(-p * e))
    z2 = (psi + dpsi * e) * (lam + z1)
    g = abs(A) + nu * _pow(az, n, n_exp) * (beta + abs(gamma))
    near = abs(math.copysign(1.0, s) * z - q * zu) - ad * g / eta < NOTCH_REACH * z2
    return (_stiffness(az, zu, n, n_exp, nu, beta, gamma) + (z1 / z2 * g if near else 0.0)) / eta


@njit(inline="always", **_JIT)
def _bwbn_rk4(z0, e0, d, dx, pj, n_exp):
    """(z, e) after one RK4 step of size ``dx`` in x from (z0, e0) (``d``: the sample step)."""
    hh = 0.5 * dx
    h6 = dx / 6.0
    q1, r1 = _bwbn_slopes(z0, e0, d, pj, n_exp)
    q2, r2 = _bwbn_slopes(z0 + hh * q1, e0 + hh * r1, d, pj, n_exp)
    q3, r3 = _bwbn_slopes(z0 + hh * q2, e0 + hh * r2, d, pj, n_exp)
    q4, r4 = _bwbn_slopes(z0 + dx * q3, e0 + dx * r3, d, pj, n_exp)
    return z0 + h6 * ((q1 + q4) + 2.0 * (q2 + q3)), e0 + h6 * ((r1 + r4) + 2.0 * (r2 + r3))


@njit(inline="always", **_JIT)
def _bwbn_params(w, j):
    """Particle j's ``pj`` (:func:`_bwbn_slopes`)."""
    return (w[6, j], w[7, j], w[8, j], w[9, j], w[10, j], w[11, j], w[12, j], w[13, j], w[14, j], w[15, j], w[16, j],
            w[17, j], w[18, j])


@njit(**_JIT)
def _bwbn_steps(w, n_act, d, substeps, n_exp, want, before):
    """Advance (z, e) over one sample step of length ``d`` in x: per particle, :func:`_steps_taken`
    RK4 steps (its rate :func:`_bwbn_rate`), as :func:`_bw_steps` does (``before``: (2, n), the
    states at the step's start)."""
    z = w[1]
    e = w[2]
    ad = abs(d)
    for j in range(n_act):
        want[j] = _steps_wanted(ad, _bwbn_rate(z[j], e[j], ad, d, _bwbn_params(w, j), n_exp))
        before[0, j] = z[j]
        before[1, j] = e[j]
    dx = d / substeps
    for _ in range(substeps):
        for j in range(n_act):
            z[j], e[j] = _bwbn_rk4(z[j], e[j], d, dx, _bwbn_params(w, j), n_exp)
    for j in range(n_act):
        if not want[j] <= substeps:
            m = _steps_taken(want[j], substeps)
            if m == 0:
                z[j] = np.nan
                continue
            zj, ej, pj = before[0, j], before[1, j], _bwbn_params(w, j)
            for _ in range(m):
                zj, ej = _bwbn_rk4(zj, ej, d, d / m, pj, n_exp)
            z[j] = zj
            e[j] = ej


@njit(**_JIT)
def bwbn_restoring_run(w, n_exp, disp, vel, substeps, bound, obs, start, stop, scale, eps, cols, want_traj, traj, dist,
                       status):
    """Run a Bouc-Wen-Baber-Noori restoring-force batch in place. ``w`` is ``(BWBN_ROWS, n)``;
    ``n_exp`` as in :func:`bw_restoring_run` (row 10)."""
    n = w.shape[1]
    idx = cols.copy()
    y = np.empty(n)
    flag = np.zeros(n, dtype=np.int8)
    n_act = n
    ns = disp.shape[0]
    want = np.empty(n)
    before = np.empty((2, n))
    for i in range(ns):
        _output(w, n_act, disp[i], vel[i], 4, y)
        if _account(w, 3, 3, n_act, i, y, bound, obs, start, stop, scale, eps, want_traj, traj, idx, flag,
                    dist, status):
            n_act = _compact(w, idx, flag, n_act)
            if n_act == 0:
                return
        if i + 1 < ns:
            d = disp[i + 1] - disp[i]
            if d != 0.0:
                _steps_bwbn(w, n_act, d, substeps, n_exp, want, before)
    _finish(w, 3, n_act, scale, idx, dist, status)


# one specialisation per exponent code (0: real n; 1..4), so that it is a constant in the loops
@njit(**_JIT)
def _bw_0(w, n_act, d, substeps, want, before):
    _bw_steps(w, n_act, d, substeps, 0, want, before)


@njit(**_JIT)
def _bw_1(w, n_act, d, substeps, want, before):
    _bw_steps(w, n_act, d, substeps, 1, want, before)


@njit(**_JIT)
def _bw_2(w, n_act, d, substeps, want, before):
    _bw_steps(w, n_act, d, substeps, 2, want, before)


@njit(**_JIT)
def _bw_3(w, n_act, d, substeps, want, before):
    _bw_steps(w, n_act, d, substeps, 3, want, before)


@njit(**_JIT)
def _bw_4(w, n_act, d, substeps, want, before):
    _bw_steps(w, n_act, d, substeps, 4, want, before)


@njit(**_JIT)
def _steps_bw(w, n_act, d, substeps, n_exp, want, before):
    if n_exp == 1:
        _bw_1(w, n_act, d, substeps, want, before)
    elif n_exp == 2:
        _bw_2(w, n_act, d, substeps, want, before)
    elif n_exp == 3:
        _bw_3(w, n_act, d, substeps, want, before)
    elif n_exp == 4:
        _bw_4(w, n_act, d, substeps, want, before)
    else:
        _bw_0(w, n_act, d, substeps, want, before)


@njit(**_JIT)
def _bwbn_0(w, n_act, d, substeps, want, before):
    _bwbn_steps(w, n_act, d, substeps, 0, want, before)


@njit(**_JIT)
def _bwbn_1(w, n_act, d, substeps, want, before):
    _bwbn_steps(w, n_act, d, substeps, 1, want, before)


@njit(**_JIT)
def _bwbn_2(w, n_act, d, substeps, want, before):
    _bwbn_steps(w, n_act, d, substeps, 2, want, before)


@njit(**_JIT)
def _bwbn_3(w, n_act, d, substeps, want, before):
    _bwbn_steps(w, n_act, d, substeps, 3, want, before)


@njit(**_JIT)
def _bwbn_4(w, n_act, d, substeps, want, before):
    _bwbn_steps(w, n_act, d, substeps, 4, want, before)


@njit(**_JIT)
def _steps_bwbn(w, n_act, d, substeps, n_exp, want, before):
    if n_exp == 1:
        _bwbn_1(w, n_act, d, substeps, want, before)
    elif n_exp == 2:
        _bwbn_2(w, n_act, d, substeps, want, before)
    elif n_exp == 3:
        _bwbn_3(w, n_act, d, substeps, want, before)
    elif n_exp == 4:
        _bwbn_4(w, n_act, d, substeps, want, before)
    else:
        _bwbn_0(w, n_act, d, substeps, want, before)


# --------------------------------------------------------------------------- Spencer (MR damper)

# rows: 0 F, 1 y, 2 z, 3 acc, 4 alpha, 5 c0, 6 c1, 7 k0, 8 k1, 9 x0, 10 gamma, 11 beta, 12 A, 13 n, 14 1/(c0 + c1),
# 15 |z| bound (inf: none)
SPENCER_ROWS = 16


@njit(inline="always", **_JIT)
def _spencer_rates(x, v, y, z, p, n_exp):
    """(y', z') of Spencer et al.'s modified Bouc-Wen at displacement x and velocity v:
    ``y' = (alpha z + c0 v + k0 (x - y)) / (c0 + c1)``,
    ``z' = -gamma |u| z |z|^(n-1) - beta u |z|^n + A u`` with ``u = v - y'``; ``p``:
    (alpha, c0, k0, gamma, beta, A, n, 1 / (c0 + c1))."""
    al, c0, k0, ga, be, A, n, inv = p
    yd = (al * z + c0 * v + k0 * (x - y)) * inv
    u = v - yd
    az = abs(z)
    zd = u * (A - _pow(az, n, n_exp) * (be + ga * math.copysign(1.0, u * z)))
    return yd, zd


@njit(**_JIT)
def _spencer_steps(w, n_act, x0, v, h, substeps, n_exp):
    """Advance (y, z) over one sample step in time: ``substeps`` RK4 steps of size ``h``,
    the displacement ``x0 + v t`` (linear between samples, velocity ``v`` over the step)."""
    y = w[1]
    z = w[2]
    hh = 0.5 * h
    h6 = h / 6.0
    for s in range(substeps):
        xa = x0 + v * (s * h)
        xm = xa + v * hh
        xb = xa + v * h
        for j in range(n_act):
            p = (w[4, j], w[5, j], w[7, j], w[10, j], w[11, j], w[12, j], w[13, j], w[14, j])
            y0 = y[j]
            z0 = z[j]
            a1, b1 = _spencer_rates(xa, v, y0, z0, p, n_exp)
            a2, b2 = _spencer_rates(xm, v, y0 + hh * a1, z0 + hh * b1, p, n_exp)
            a3, b3 = _spencer_rates(xm, v, y0 + hh * a2, z0 + hh * b2, p, n_exp)
            a4, b4 = _spencer_rates(xb, v, y0 + h * a3, z0 + h * b3, p, n_exp)
            y[j] = y0 + h6 * ((a1 + a4) + 2.0 * (a2 + a3))
            z[j] = z0 + h6 * ((b1 + b4) + 2.0 * (b2 + b3))


@njit(**_JIT)
def _spencer_output(w, n_act, x, v, out):
    """``F = c1 y' + k1 (x - x0)`` with y' at the sample's velocity ``v``."""
    F = w[0]
    y = w[1]
    z = w[2]
    for j in range(n_act):
        yd = (w[4, j] * z[j] + w[5, j] * v + w[7, j] * (x - y[j])) * w[14, j]
        f = w[6, j] * yd + w[8, j] * (x - w[9, j])
        F[j] = f
        out[j] = f


@njit(**_JIT)
def spencer_run(w, n_exp, disp, vel, volt, h, substeps, bound, obs, start, stop, scale, eps, cols, want_traj, traj, dist,
                status):
    """Run a Spencer MR-damper batch in place: at a constant voltage (``volt`` empty, ``w``
    is ``(SPENCER_ROWS, n)``) or driven by the coil voltage ``volt`` (one per sample, ``w``
    is ``(SPENCER_V_ROWS, n)``). ``h`` the RK4 step in time (dt / substeps); ``n_exp`` as in
    :func:`bw_restoring_run` (the exponent's row)."""
    n = w.shape[1]
    idx = cols.copy()
    out = np.empty(n)
    flag = np.zeros(n, dtype=np.int8)
    n_act = n
    ns = disp.shape[0]
    dt = h * substeps
    driven = volt.shape[0] > 0
    n_state = 4 if driven else 3  # the state rows after F: y, z (and u)
    z = w[2]
    zmax = w[w.shape[0] - 1]
    for i in range(ns):
        for j in range(n_act):  # past the bound the equation implies: the integration is wrong
            if abs(z[j]) > zmax[j]:
                z[j] = np.nan  # the finiteness test below flags it DIVERGED
        if driven:
            _spencer_v_output(w, n_act, disp[i], vel[i], out)
        else:
            _spencer_output(w, n_act, disp[i], vel[i], out)
        if _account(w, n_state, n_state, n_act, i, out, bound, obs, start, stop, scale, eps, want_traj, traj, idx, flag,
                    dist, status):
            n_act = _compact(w, idx, flag, n_act)
            if n_act == 0:
                return
        if i + 1 < ns:
            v = (disp[i + 1] - disp[i]) / dt
            if driven:
                _spencer_v_step(w, n_act, disp[i], v, volt[i], (volt[i + 1] - volt[i]) / dt, h, substeps, n_exp)
            elif n_exp == 1:
                _spencer_1(w, n_act, disp[i], v, h, substeps)
            elif n_exp == 2:
                _spencer_2(w, n_act, disp[i], v, h, substeps)
            else:
                _spencer_0(w, n_act, disp[i], v, h, substeps)
    _finish(w, n_state, n_act, scale, idx, dist, status)


@njit(**_JIT)
def _spencer_0(w, n_act, x0, v, h, substeps):
    _spencer_steps(w, n_act, x0, v, h, substeps, 0)


@njit(**_JIT)
def _spencer_1(w, n_act, x0, v, h, substeps):
    _spencer_steps(w, n_act, x0, v, h, substeps, 1)


@njit(**_JIT)
def _spencer_2(w, n_act, x0, v, h, substeps):
    _spencer_steps(w, n_act, x0, v, h, substeps, 2)


# ------------------------------------------------------- Spencer with the coil voltage as an input

# rows: 0 F, 1 y, 2 z, 3 u (the filtered voltage), 4 acc, 5 alpha_a, 6 alpha_b, 7 c0a, 8 c0b, 9 c1a, 10 c1b, 11 k0,
# 12 k1, 13 x0, 14 gamma, 15 beta, 16 A, 17 n, 18 eta, 19 |z| bound (inf: none)
SPENCER_V_ROWS = 20


@njit(inline="always", **_JIT)
def _spencer_v_rates(x, v, e, y, z, u, p, n_exp):
    """(y', z', u') of Spencer et al.'s model with voltage-dependent alpha, c0, c1 (their Eqs.
    9-12) at displacement x, velocity v and commanded voltage e: alpha = alpha_a + alpha_b u,
    c0 = c0a + c0b u, c1 = c1a + c1b u in :func:`_spencer_rates`, and ``u' = -eta (u - e)``;
    ``p``: (alpha_a, alpha_b, c0a, c0b, c1a, c1b, k0, gamma, beta, A, n, eta)."""
    ala, alb, c0a, c0b, c1a, c1b, k0, ga, be, A, n, eta = p
    c0 = c0a + c0b * u
    inv = 1.0 / (c0 + c1a + c1b * u)
    yd, zd = _spencer_rates(x, v, y, z, (ala + alb * u, c0, k0, ga, be, A, n, inv), n_exp)
    return yd, zd, -eta * (u - e)


@njit(inline="always", **_JIT)
def _spencer_v_steps(w, n_act, x0, v, e0, de, h, substeps, n_exp):
    """Advance (y, z, u) over one sample step in time: ``substeps`` RK4 steps of size ``h``,
    the displacement ``x0 + v t`` and the commanded voltage ``e0 + de t`` (both linear
    between samples)."""
    y = w[1]
    z = w[2]
    u = w[3]
    hh = 0.5 * h
    h6 = h / 6.0
    for s in range(substeps):
        xa = x0 + v * (s * h)
        xm = xa + v * hh
        xb = xa + v * h
        ea = e0 + de * (s * h)
        em = ea + de * hh
        eb = ea + de * h
        for j in range(n_act):
            p = (w[5, j], w[6, j], w[7, j], w[8, j], w[9, j], w[10, j], w[11, j], w[14, j], w[15, j], w[16, j], w[17, j],
                 w[18, j])
            y0 = y[j]
            z0 = z[j]
            u0 = u[j]
            a1, b1, c1 = _spencer_v_rates(xa, v, ea, y0, z0, u0, p, n_exp)
            a2, b2, c2 = _spencer_v_rates(xm, v, em, y0 + hh * a1, z0 + hh * b1, u0 + hh * c1, p, n_exp)
            a3, b3, c3 = _spencer_v_rates(xm, v, em, y0 + hh * a2, z0 + hh * b2, u0 + hh * c2, p, n_exp)
            a4, b4, c4 = _spencer_v_rates(xb, v, eb, y0 + h * a3, z0 + h * b3, u0 + h * c3, p, n_exp)
            y[j] = y0 + h6 * ((a1 + a4) + 2.0 * (a2 + a3))
            z[j] = z0 + h6 * ((b1 + b4) + 2.0 * (b2 + b3))
            u[j] = u0 + h6 * ((c1 + c4) + 2.0 * (c2 + c3))


@njit(**_JIT)
def _spencer_v_output(w, n_act, x, v, out):
    """``F = c1(u) y' + k1 (x - x0)`` with y' at the sample's velocity ``v``."""
    F = w[0]
    y = w[1]
    z = w[2]
    u = w[3]
    for j in range(n_act):
        uj = u[j]
        c0 = w[7, j] + w[8, j] * uj
        c1 = w[9, j] + w[10, j] * uj
        s = c0 + c1
        yd = ((w[5, j] + w[6, j] * uj) * z[j] + c0 * v + w[11, j] * (x - y[j])) / s
        f = c1 * yd + w[12, j] * (x - w[13, j])
        f = f if s > 0.0 else np.nan  # flagged DIVERGED: c0 + c1 must stay positive
        F[j] = f
        out[j] = f


@njit(**_JIT)
def _spencer_v_0(w, n_act, x0, v, e0, de, h, substeps):
    _spencer_v_steps(w, n_act, x0, v, e0, de, h, substeps, 0)


@njit(**_JIT)
def _spencer_v_1(w, n_act, x0, v, e0, de, h, substeps):
    _spencer_v_steps(w, n_act, x0, v, e0, de, h, substeps, 1)


@njit(**_JIT)
def _spencer_v_2(w, n_act, x0, v, e0, de, h, substeps):
    _spencer_v_steps(w, n_act, x0, v, e0, de, h, substeps, 2)


@njit(**_JIT)
def _spencer_v_step(w, n_act, x0, v, e0, de, h, substeps, n_exp):
    if n_exp == 1:
        _spencer_v_1(w, n_act, x0, v, e0, de, h, substeps)
    elif n_exp == 2:
        _spencer_v_2(w, n_act, x0, v, e0, de, h, substeps)
    else:
        _spencer_v_0(w, n_act, x0, v, e0, de, h, substeps)
