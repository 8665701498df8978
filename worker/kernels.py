"""Numba batch kernels for the forced oscillators (Duffing, Bouc-Wen, exact linear).

Layout. A batch of ``n`` particles lives in one C-ordered work array ``w`` of shape
``(rows, n)``: the state components first (one contiguous ``(n,)`` row each), then the
NMSE accumulator, then the per-particle coefficients (already divided by the mass). Every
loop has the particles innermost, so each RK4 step is one loop over the batch that LLVM
vectorises; the force is one array shared by the batch. Between samples it is held
(``hold`` 0, zero-order: ``force[i]`` over step i) or interpolated linearly (``hold`` 1,
first-order: ``force[i] + (force[i+1] - force[i]) tau``, tau the fraction of step i gone)
or band-limited (``hold`` 2, RK4 kernels only: read from ``fine``, the force at every stage
time, made once per simulator by :func:`worker.simulators.band_limited`):
the RK4 stages of a substep then see the force at the substep's start, middle and end, and
the linear model's exact recursion takes the ramp's own coefficients
(:func:`hold_coefficients`). With ``hold`` 0 every loop is the zero-order-hold loop it
always was, to the bit. Kernels are ``@njit(cache=True)``; those that integrate and score
have ``fastmath={"contract"}`` only (FMA contraction, no reassociation, NaN/inf semantics
kept) and ``error_model="numpy"`` (no Python exception branches in the loops); the linear
model's coefficients (:func:`hold_coefficients`) have no ``fastmath``; none is parallel.

Drivers take a block of particles (``w`` holds only them; a few hundred keep the work
array in L1) and ``cols``, their columns in the caller's ``dist``, ``status`` and
flattened ``(n_samples, n_total)`` trajectory array ``traj``. Each driver does, for every
sample ``i``: read the output of the current state (output[0]
is the state at rest), account for it, then advance over step ``i``. Accounting is either

- trajectory mode: store the output in ``traj[i * n_total + column]`` (the caller
  returns the transpose of ``traj.reshape(n_samples, n_total)``), or
- distance mode: add ``(y - obs[i])**2`` to the accumulator when ``start <= i < stop``;
  the NMSE is ``scale * sum``. With a finite ``eps`` a particle whose partial NMSE
  reaches ``eps`` is retired at once: status OK, distance = that partial NMSE (already
  ``>= eps``, so it is rejected exactly as it would have been after the full record:
  the partial sums are non-decreasing in floating point).

The divergence guard, per sample: a particle whose displacement leaves ``bound`` or whose
state, output or accumulated sum is not finite is retired with status DIVERGED and
distance +inf (its trajectory row keeps zeros from there on: frozen at rest). Retired
particles are removed from the working set by compaction, so later steps skip them.
"""

from __future__ import annotations

import math
import os
import sys
from typing import Literal, TypedDict


def _prefer_wide_vectors() -> None:
    """On AVX-512 hosts, let LLVM use 512-bit vectors (numba's default CPU tuning prefers
    256-bit ones): the RK4 loops are FMA-throughput bound, and measured 1.3-1.5x faster.

    This sets numba's target features (``NUMBA_CPU_FEATURES``, i.e. ``config.CPU_FEATURES``)
    for the whole process, so it only acts when numba has not compiled anything yet, and
    never when ``NUMBA_CPU_FEATURES`` is set or ``NUMBA_ENABLE_AVX=0``. Opt out with
    ``ABCNS_NUMBA_WIDE_VECTORS=0``. The results do not depend on the vector width (no
    reassociation, no floating-point reductions across particles)."""
    if (os.environ.get("ABCNS_NUMBA_WIDE_VECTORS", "1") == "0" or os.environ.get("NUMBA_CPU_FEATURES")
            or os.environ.get("NUMBA_ENABLE_AVX") == "0"):
        return
    try:
        import llvmlite.binding as ll

        features = ll.get_host_cpu_features().flatten()
    except Exception:  # no feature map on this platform: keep numba's defaults
        return
    if "+avx512f" not in features.split(","):
        return
    wanted = features + ",-prefer-256-bit"
    if "numba" not in sys.modules:
        os.environ["NUMBA_CPU_FEATURES"] = wanted
        return
    from numba.core import config
    from numba.core.registry import cpu_target

    # numba.core.config creates its settings at import time (globals() updated from the
    # environment), so they are invisible to a type checker
    if config.CPU_FEATURES is None and "_toplevel_target_context" not in vars(cpu_target):  # type: ignore[attr-defined]
        config.CPU_FEATURES = wanted  # type: ignore[attr-defined]


_prefer_wide_vectors()

import numpy as np  # noqa: E402
from numba import njit  # noqa: E402

from abcns.executor import DIVERGED, OK  # noqa: E402

_FM = {"contract"}
_BIG = 1.7976931348623157e308  # the largest finite double
OUTPUT_CODES = {"displacement": 0, "velocity": 1, "acceleration": 2, "force": 3}  # force: worker/restoring.py


class _JitOptions(TypedDict):
    """The options the integrating and scoring kernels are compiled with (typed so that
    ``njit(**_JIT)`` checks)."""

    cache: bool
    fastmath: set[str]
    error_model: Literal["python", "numpy"]
    nogil: bool


# nogil: a batch runs for up to minutes in a Dask worker's thread; holding the GIL, it stalled
# the worker's event loop (heartbeats, results) and a job loop in the same process (its time
# budget and cancel) while it ran
_JIT: _JitOptions = {"cache": True, "fastmath": _FM, "error_model": "numpy", "nogil": True}


# --------------------------------------------------------------------------- shared


@njit(**_JIT)
def _account(w, n_state, acc_row, n_act, i, y, bound, obs, start, stop, scale, eps, want_traj, traj, idx, flag,
             dist, status):
    """Check, record and score the outputs ``y[:n_act]`` of sample ``i``; returns how many
    particles were retired (``flag``: 1 rejected, 2 diverged; their results written).

    ``idx`` holds the particles' columns in the caller's arrays: ``dist``, ``status`` and
    the flattened ``(n_samples, n_total)`` trajectory array ``traj``. The finiteness test
    is on ``|y| + |state[1]| + |state[last]|`` (one comparison, branch-free, vectorised):
    a non-finite component, or components summing past the largest double, fail it."""
    acc = w[acc_row]
    x = w[0]
    r1 = w[1]
    rl = w[n_state - 1]
    n_flag = 0
    if (not want_traj) and start <= i < stop:
        o = obs[i]
        for j in range(n_act):
            yj = y[j]
            e = yj - o
            d = acc[j] + e * e
            acc[j] = d
            good = (abs(x[j]) <= bound) & (abs(yj) + (abs(r1[j]) + abs(rl[j])) <= _BIG) & (d <= _BIG)
            code = 2 * (1 - good) + good * (scale * d >= eps)
            flag[j] = code
            n_flag += code != 0
    else:
        for j in range(n_act):
            good = (abs(x[j]) <= bound) & (abs(y[j]) + (abs(r1[j]) + abs(rl[j])) <= _BIG)
            code = 2 * (1 - good) + good * (scale * acc[j] >= eps)
            flag[j] = code
            n_flag += code != 0
    if want_traj:
        row = i * dist.shape[0]
        for j in range(n_act):
            traj[row + idx[j]] = y[j] if flag[j] != 2 else 0.0
    if n_flag:
        _retire(w, acc_row, n_act, scale, idx, flag, dist, status)
    return n_flag


@njit(**_JIT)
def _retire(w, acc_row, n_act, scale, idx, flag, dist, status):
    """Results of the flagged particles: code 1 rejected (OK, partial NMSE), 2 DIVERGED."""
    acc = w[acc_row]
    for j in range(n_act):
        code = flag[j]
        if code == 1:
            status[idx[j]] = OK
            dist[idx[j]] = scale * acc[j]
        elif code == 2:
            status[idx[j]] = DIVERGED
            dist[idx[j]] = np.inf


@njit(cache=True)
def _compact(w, idx, flag, n_act):
    """Drop the flagged particles from the working set, keeping the order; returns the new size."""
    rows = w.shape[0]
    k = 0
    for j in range(n_act):
        if flag[j] == 0:
            if k != j:
                for r in range(rows):
                    w[r, k] = w[r, j]
                idx[k] = idx[j]
            k += 1
    return k


@njit(cache=True)
def _finish(w, acc_row, n_act, scale, idx, dist, status):
    acc = w[acc_row]
    for j in range(n_act):
        p = idx[j]
        status[p] = OK
        dist[p] = scale * acc[j]


# --------------------------------------------------------------------------- Duffing

# rows: 0 x, 1 v, 2 acc, 3 1/m, 4 c/m, 5 k/m, 6 k2/m, 7 k3/m, 8 k5/m
DUFFING_ROWS = 9


@njit(inline="always", **_JIT)
def _ramp(f0, f1, s, substeps):
    """The linearly interpolated force at the start, middle and end of substep ``s`` of a
    sample step from ``f0`` to ``f1``."""
    df = f1 - f0
    return (f0 + df * (s / substeps), f0 + df * ((s + 0.5) / substeps), f0 + df * ((s + 1.0) / substeps))


@njit(inline="always", **_JIT)
def _duffing_rk4(x0, v0, fa, fm, fb, c, a, b, d, e, h):
    """One classical RK4 step of x' = v, v' = acc(t, x, v) for one particle, the x stages
    written out; ``fa``, ``fm``, ``fb``: force / m at the step's start, middle and end."""
    hh = 0.5 * h
    hq = 0.25 * h * h
    hhh = 0.5 * h * h
    h26 = h * h / 6.0
    h6 = h / 6.0
    a1 = fa - c * v0 - x0 * (a + x0 * (b + x0 * (d + e * (x0 * x0))))
    xs = x0 + hh * v0
    vs = v0 + hh * a1
    a2 = fm - c * vs - xs * (a + xs * (b + xs * (d + e * (xs * xs))))
    xs = xs + hq * a1
    vs = v0 + hh * a2
    a3 = fm - c * vs - xs * (a + xs * (b + xs * (d + e * (xs * xs))))
    xh = x0 + h * v0
    xs = xh + hhh * a2
    vs = v0 + h * a3
    a4 = fb - c * vs - xs * (a + xs * (b + xs * (d + e * (xs * xs))))
    a23 = a2 + a3
    return xh + h26 * (a1 + a23), v0 + h6 * ((a1 + a4) + 2.0 * a23)


@njit(inline="always", **_JIT)
def _stage(f0, f1, s, substeps, hold, fine, base):
    """The force at the start, middle and end of substep ``s`` of a sample step from ``f0``
    to ``f1``: ramped (``hold`` 1) or read from ``fine``, the band-limited force at every
    stage time, from ``base`` = 2 substeps i on (``hold`` 2)."""
    if hold == 1:
        return _ramp(f0, f1, s, substeps)
    b = base + 2 * s
    return fine[b], fine[b + 1], fine[b + 2]


@njit(**_JIT)
def _duffing_steps(w, n_act, f0, f1, h, substeps, hold, fine, base):
    """Advance over one sample step: ``substeps`` RK4 steps, the force held at ``f0``
    (``hold`` 0), ramped from ``f0`` to ``f1`` (``hold`` 1) or band-limited (``hold`` 2,
    from ``fine[base:]``; :func:`_stage`)."""
    x = w[0]
    v = w[1]
    im = w[3]
    cm = w[4]
    k1m = w[5]
    k2m = w[6]
    k3m = w[7]
    k5m = w[8]
    for s in range(substeps):
        if hold == 0:
            for j in range(n_act):
                fj = f0 * im[j]
                x[j], v[j] = _duffing_rk4(x[j], v[j], fj, fj, fj, cm[j], k1m[j], k2m[j], k3m[j], k5m[j], h)
        else:
            fa, fm, fb = _stage(f0, f1, s, substeps, hold, fine, base)
            for j in range(n_act):
                x[j], v[j] = _duffing_rk4(x[j], v[j], fa * im[j], fm * im[j], fb * im[j], cm[j], k1m[j], k2m[j],
                                          k3m[j], k5m[j], h)


@njit(**_JIT)
def _duffing_output(w, n_act, f, kind, y):
    x = w[0]
    v = w[1]
    if kind == 0:
        for j in range(n_act):
            y[j] = x[j]
    elif kind == 1:
        for j in range(n_act):
            y[j] = v[j]
    else:
        im = w[3]
        cm = w[4]
        k1m = w[5]
        k2m = w[6]
        k3m = w[7]
        k5m = w[8]
        for j in range(n_act):
            xj = x[j]
            y[j] = f * im[j] - cm[j] * v[j] - xj * (k1m[j] + xj * (k2m[j] + xj * (k3m[j] + k5m[j] * (xj * xj))))


@njit(**_JIT)
def duffing_run(w, force, fine, h, substeps, hold, kind, bound, obs, start, stop, scale, eps, cols, want_traj, traj, dist,
                status):
    """Run a Duffing batch in place; see the module docstring. ``w`` is ``(DUFFING_ROWS, n)``;
    ``fine``: the band-limited force at every RK4 stage time (``hold`` 2; else unread)."""
    n = w.shape[1]
    idx = cols.copy()
    y = np.empty(n)
    flag = np.zeros(n, dtype=np.int8)
    n_act = n
    ns = force.shape[0]
    for i in range(ns):
        _duffing_output(w, n_act, force[i], kind, y)
        if _account(w, 2, 2, n_act, i, y, bound, obs, start, stop, scale, eps, want_traj, traj, idx, flag,
                    dist, status):
            n_act = _compact(w, idx, flag, n_act)
            if n_act == 0:
                return
        if i + 1 < ns:
            _duffing_steps(w, n_act, force[i], force[i + 1], h, substeps, hold, fine, 2 * substeps * i)
    _finish(w, 2, n_act, scale, idx, dist, status)


# --------------------------------------------------------------------------- Bouc-Wen

# rows: 0 y, 1 v, 2 z, 3 acc, 4 1/m, 5 c/m, 6 k/m, 7 alpha, 8 beta, 9 A, 10 |z| bound (inf: none)
BOUC_WEN_ROWS = 11


@njit(**_JIT)
def _zpow(az, n):
    """|z|**(n - 1) for the integer exponent n (a constant in each caller)."""
    if n == 1:
        return 1.0
    if n == 2:
        return az
    if n == 3:
        return az * az
    return az * az * az


@njit(**_JIT)
def _zdot(v, z, A, alpha, beta, n):
    """``A v - alpha |v| |z|^(n-1) z - beta v |z|^n`` written as
    ``v (A - |z|^(n-1) (beta |z| + alpha sign(v) z))`` (one multiplication fewer)."""
    az = abs(z)
    return v * (A - _zpow(az, n) * (beta * az + (alpha * math.copysign(1.0, v)) * z))


@njit(inline="always", **_JIT)
def _bouc_wen_rk4(y0, v0, z0, fa, fm, fb, c, k, mi, alpha, beta, A, h, n_exp):
    """One classical RK4 step of the Bouc-Wen state (y, v, z) for one particle; ``fa``,
    ``fm``, ``fb``: force / m at the step's start, middle and end."""
    hh = 0.5 * h
    hq = 0.25 * h * h
    hhh = 0.5 * h * h
    h26 = h * h / 6.0
    h6 = h / 6.0
    # stage 1
    a1 = fa - c * v0 - k * y0 - mi * z0
    q1 = _zdot(v0, z0, A, alpha, beta, n_exp)
    # stage 2
    ys = y0 + hh * v0
    vs = v0 + hh * a1
    zs = z0 + hh * q1
    a2 = fm - c * vs - k * ys - mi * zs
    q2 = _zdot(vs, zs, A, alpha, beta, n_exp)
    # stage 3
    ys = ys + hq * a1
    vs = v0 + hh * a2
    zs = z0 + hh * q2
    a3 = fm - c * vs - k * ys - mi * zs
    q3 = _zdot(vs, zs, A, alpha, beta, n_exp)
    # stage 4
    yh = y0 + h * v0
    ys = yh + hhh * a2
    vs = v0 + h * a3
    zs = z0 + h * q3
    a4 = fb - c * vs - k * ys - mi * zs
    q4 = _zdot(vs, zs, A, alpha, beta, n_exp)
    a23 = a2 + a3
    return (yh + h26 * (a1 + a23), v0 + h6 * ((a1 + a4) + 2.0 * a23),
            z0 + h6 * ((q1 + q4) + 2.0 * (q2 + q3)))


@njit(**_JIT)
def _bouc_wen_steps(w, n_act, f0, f1, h, substeps, hold, fine, base, n_exp):
    """Advance over one sample step (as :func:`_duffing_steps`)."""
    y = w[0]
    v = w[1]
    z = w[2]
    im = w[4]
    cm = w[5]
    km = w[6]
    al = w[7]
    be = w[8]
    Am = w[9]
    for s in range(substeps):
        if hold == 0:
            for j in range(n_act):
                fj = f0 * im[j]
                y[j], v[j], z[j] = _bouc_wen_rk4(y[j], v[j], z[j], fj, fj, fj, cm[j], km[j], im[j], al[j], be[j],
                                                 Am[j], h, n_exp)
        else:
            fa, fm, fb = _stage(f0, f1, s, substeps, hold, fine, base)
            for j in range(n_act):
                mi = im[j]
                y[j], v[j], z[j] = _bouc_wen_rk4(y[j], v[j], z[j], fa * mi, fm * mi, fb * mi, cm[j], km[j], mi,
                                                 al[j], be[j], Am[j], h, n_exp)


# one specialisation per exponent (BOUC_WEN_EXPONENTS in worker/simulators.py), so the
# exponent is a compile-time constant in the loop
@njit(**_JIT)
def _bouc_wen_steps_1(w, n_act, f0, f1, h, substeps, hold, fine, base):
    _bouc_wen_steps(w, n_act, f0, f1, h, substeps, hold, fine, base, 1)


@njit(**_JIT)
def _bouc_wen_steps_2(w, n_act, f0, f1, h, substeps, hold, fine, base):
    _bouc_wen_steps(w, n_act, f0, f1, h, substeps, hold, fine, base, 2)


@njit(**_JIT)
def _bouc_wen_steps_3(w, n_act, f0, f1, h, substeps, hold, fine, base):
    _bouc_wen_steps(w, n_act, f0, f1, h, substeps, hold, fine, base, 3)


@njit(**_JIT)
def _bouc_wen_steps_4(w, n_act, f0, f1, h, substeps, hold, fine, base):
    _bouc_wen_steps(w, n_act, f0, f1, h, substeps, hold, fine, base, 4)


@njit(**_JIT)
def _bouc_wen_output(w, n_act, f, kind, out):
    y = w[0]
    v = w[1]
    if kind == 0:
        for j in range(n_act):
            out[j] = y[j]
    elif kind == 1:
        for j in range(n_act):
            out[j] = v[j]
    else:
        z = w[2]
        im = w[4]
        cm = w[5]
        km = w[6]
        for j in range(n_act):
            out[j] = f * im[j] - cm[j] * v[j] - km[j] * y[j] - im[j] * z[j]


@njit(**_JIT)
def bouc_wen_run(w, n_exp, force, fine, h, substeps, hold, kind, bound, obs, start, stop, scale, eps, cols, want_traj, traj,
                 dist, status):
    """Run a Bouc-Wen batch (one exponent ``n_exp`` in 1..4) in place. ``w`` is ``(BOUC_WEN_ROWS, n)``."""
    n = w.shape[1]
    idx = cols.copy()
    y = np.empty(n)
    flag = np.zeros(n, dtype=np.int8)
    n_act = n
    ns = force.shape[0]
    z = w[2]
    zmax = w[10]
    for i in range(ns):
        for j in range(n_act):  # past the bound the equation implies: the integration is wrong
            if abs(z[j]) > zmax[j]:
                z[j] = np.nan  # the finiteness test below flags it DIVERGED
        _bouc_wen_output(w, n_act, force[i], kind, y)
        if _account(w, 3, 3, n_act, i, y, bound, obs, start, stop, scale, eps, want_traj, traj, idx, flag,
                    dist, status):
            n_act = _compact(w, idx, flag, n_act)
            if n_act == 0:
                return
        if i + 1 < ns:
            f0 = force[i]
            f1 = force[i + 1]
            base = 2 * substeps * i
            if n_exp == 1:
                _bouc_wen_steps_1(w, n_act, f0, f1, h, substeps, hold, fine, base)
            elif n_exp == 2:
                _bouc_wen_steps_2(w, n_act, f0, f1, h, substeps, hold, fine, base)
            elif n_exp == 3:
                _bouc_wen_steps_3(w, n_act, f0, f1, h, substeps, hold, fine, base)
            else:
                _bouc_wen_steps_4(w, n_act, f0, f1, h, substeps, hold, fine, base)
    _finish(w, 3, n_act, scale, idx, dist, status)


# --------------------------------------------------------------------------- linear, exact

# rows: 0 x, 1 v, 2 acc, 3 p11, 4 p12, 5 p21, 6 p22, 7 g1, 8 g2, 9 1/m, 10 c/m, 11 k/m, 12 r1, 13 r2
LINEAR_ROWS = 14
_TAYLOR_TERMS = 14  # with the scaled norm <= 1/2 the first omitted term is < 3e-17


@njit(cache=True, error_model="numpy")
def _hold_taylor(m12, m21, m22, mb, sc):
    """``F = expm(M) - I`` of :func:`hold_coefficients`' scaled matrix (``M`` = [[0, m12],
    [m21, m22]] with the force column ``mb`` and the ramp's ``sc``), as (F's 2 x 2 block,
    its Gamma column, its ramp column): phi_1(M) = I + M/2! + M^2/3! + ... by Horner,
    Y <- I + (M Y) / q, then F = M Y (carrying F instead of expm(M) keeps the squaring free
    of cancellation)."""
    p11, p12, p21, p22, g1, g2 = 1.0, 0.0, 0.0, 1.0, 0.0, 0.0
    r1, r2, y34 = 0.0, 0.0, 0.0  # the ramp's column and the (f, slope) entry of Y
    for q in range(_TAYLOR_TERMS, 1, -1):
        r = 1.0 / q
        n11 = 1.0 + (m12 * p21) * r
        n12 = (m12 * p22) * r
        n21 = (m21 * p11 + m22 * p21) * r
        n22 = 1.0 + (m21 * p12 + m22 * p22) * r
        ng1 = (m12 * g2) * r
        ng2 = (m21 * g1 + m22 * g2 + mb) * r
        nr1 = (m12 * r2) * r
        nr2 = (m21 * r1 + m22 * r2 + mb * y34) * r
        p11, p12, p21, p22, g1, g2 = n11, n12, n21, n22, ng1, ng2
        r1, r2, y34 = nr1, nr2, sc * r
    return (m12 * p21, m12 * p22, m21 * p11 + m22 * p21, m21 * p12 + m22 * p22,
            m12 * g2, m21 * g1 + m22 * g2 + mb, m12 * r2, m21 * r1 + m22 * r2 + mb * y34)


@njit(cache=True, error_model="numpy")
def _hold_square(s, sigma, f11, f12, f21, f22, fg1, fg2, fr1, fr2):
    """:func:`_hold_taylor`'s F squared ``s`` times: (I + F)^2 = I + (2 F + F F); the Gamma
    part: (I + F) g + g = 2 g + F g; the ramp's: (I + F) r + sigma g + r = 2 r + F r + sigma g."""
    for _ in range(s):
        n11 = 2.0 * f11 + (f11 * f11 + f12 * f21)
        n12 = 2.0 * f12 + (f11 * f12 + f12 * f22)
        n21 = 2.0 * f21 + (f21 * f11 + f22 * f21)
        n22 = 2.0 * f22 + (f21 * f12 + f22 * f22)
        ng1 = 2.0 * fg1 + (f11 * fg1 + f12 * fg2)
        ng2 = 2.0 * fg2 + (f21 * fg1 + f22 * fg2)
        nr1 = 2.0 * fr1 + (f11 * fr1 + f12 * fr2) + sigma * fg1
        nr2 = 2.0 * fr2 + (f21 * fr1 + f22 * fr2) + sigma * fg2
        f11, f12, f21, f22, fg1, fg2 = n11, n12, n21, n22, ng1, ng2
        fr1, fr2, sigma = nr1, nr2, 2.0 * sigma
    return f11, f12, f21, f22, fg1, fg2, fr1, fr2


@njit(cache=True, error_model="numpy")
def hold_coefficients(m, c, k, dt, w):
    """Fill rows 3..13 of ``w`` with the exact transition of ``m x'' + c x' + k x = f`` over
    one sample for a held force and for a linear ramp: ``s_{i+1} = Phi s_i + Gamma f_i``
    (zero-order hold) and ``s_{i+1} = Phi s_i + Gamma f_i + R (f_{i+1} - f_i)`` (first-order
    hold), with ``[[Phi, Gamma, R], [0, 1, 1], [0, 0, 1]] = expm(dt [[A, B, 0], [0, 0, 1/dt],
    [0, 0, 0]])``, ``A = [[0, 1], [-k/m, -c/m]]``, ``B = [0, 1/m]`` (the force and its slope
    appended to the state).

    Per particle: scale the augmented matrix by ``2**-s`` so that the inf-norm of its
    ``A`` block is at most 1/2, sum the Taylor series of ``expm(M) - I`` by Horner (14
    terms), square ``s`` times as ``F <- 2 F + F F`` (no cancellation against the
    identity). The bottom rows stay ``[0, 1, sigma]``, ``[0, 0, 1]`` (sigma the scaled
    1), so only ``(Phi, Gamma, R, sigma)`` is carried: squaring gives ``(P P, P g + g, P r
    + sigma g + r, 2 sigma)``. ``(Phi, Gamma)`` are computed exactly as the zero-order hold
    alone would be (R rides along). A non-finite or absurdly large matrix gives NaN
    coefficients (the particle is then flagged DIVERGED by the recursion)."""
    n = m.shape[0]
    for j in range(n):
        im = 1.0 / m[j]
        w[9, j] = im
        w[10, j] = c[j] * im
        w[11, j] = k[j] * im
        a21 = -k[j] * im * dt
        a22 = -c[j] * im * dt
        b2 = im * dt
        norm = max(dt, abs(a21) + abs(a22))
        if not (norm <= 1e300 and abs(b2) <= 1e300):
            for row in (3, 4, 5, 6, 7, 8, 12, 13):
                w[row, j] = np.nan
            continue
        s = 0
        sc = 1.0
        while norm * sc > 0.5:
            sc *= 0.5
            s += 1
        f11, f12, f21, f22, fg1, fg2, fr1, fr2 = _hold_taylor(dt * sc, a21 * sc, a22 * sc, b2 * sc, sc)
        f11, f12, f21, f22, fg1, fg2, fr1, fr2 = _hold_square(s, sc, f11, f12, f21, f22, fg1, fg2, fr1, fr2)
        w[3, j] = 1.0 + f11  # Phi = I + F
        w[4, j] = f12
        w[5, j] = f21
        w[6, j] = 1.0 + f22
        w[7, j] = fg1  # Gamma
        w[8, j] = fg2
        w[12, j] = fr1  # R
        w[13, j] = fr2


@njit(**_JIT)
def _linear_output(w, n_act, f, kind, y):
    x = w[0]
    v = w[1]
    if kind == 0:
        for j in range(n_act):
            y[j] = x[j]
    elif kind == 1:
        for j in range(n_act):
            y[j] = v[j]
    else:
        im = w[9]
        cm = w[10]
        km = w[11]
        for j in range(n_act):
            y[j] = f * im[j] - cm[j] * v[j] - km[j] * x[j]


@njit(**_JIT)
def _linear_step(w, n_act, f0, f1, hold):
    """One sample step: ``Phi s + Gamma f0`` (``hold`` 0), plus the ramp's ``R (f1 - f0)``
    (``hold`` 1)."""
    x = w[0]
    v = w[1]
    p11 = w[3]
    p12 = w[4]
    p21 = w[5]
    p22 = w[6]
    g1 = w[7]
    g2 = w[8]
    if hold == 0:
        for j in range(n_act):
            x0 = x[j]
            v0 = v[j]
            x[j] = p11[j] * x0 + p12[j] * v0 + g1[j] * f0
            v[j] = p21[j] * x0 + p22[j] * v0 + g2[j] * f0
    else:
        r1 = w[12]
        r2 = w[13]
        df = f1 - f0
        for j in range(n_act):
            x0 = x[j]
            v0 = v[j]
            x[j] = p11[j] * x0 + p12[j] * v0 + g1[j] * f0 + r1[j] * df
            v[j] = p21[j] * x0 + p22[j] * v0 + g2[j] * f0 + r2[j] * df


@njit(**_JIT)
def _linear_disp_nmse(w, n_act, f, o, bound, scale, eps, flag):
    """The fused displacement-NMSE sample for the linear recursion (the hot path): score
    ``x`` against ``o``, check, flag, advance. Returns the number flagged."""
    x = w[0]
    v = w[1]
    acc = w[2]
    p11 = w[3]
    p12 = w[4]
    p21 = w[5]
    p22 = w[6]
    g1 = w[7]
    g2 = w[8]
    n_flag = 0
    for j in range(n_act):
        x0 = x[j]
        v0 = v[j]
        e = x0 - o
        d = acc[j] + e * e
        acc[j] = d
        good = abs(x0) <= bound and abs(v0) <= _BIG and d <= _BIG
        code = 2 if not good else (1 if scale * d >= eps else 0)
        flag[j] = code
        n_flag += code != 0
        x[j] = p11[j] * x0 + p12[j] * v0 + g1[j] * f
        v[j] = p21[j] * x0 + p22[j] * v0 + g2[j] * f
    return n_flag


@njit(**_JIT)
def linear_run(w, force, hold, kind, bound, obs, start, stop, scale, eps, cols, want_traj, traj, dist, status):
    """Run the exact recursion for a batch in place, for a held (``hold`` 0) or linearly
    interpolated (1) force; rows 3..13 of ``w`` come from :func:`hold_coefficients`.
    ``w`` is ``(LINEAR_ROWS, n)``."""
    n = w.shape[1]
    idx = cols.copy()
    y = np.empty(n)
    flag = np.zeros(n, dtype=np.int8)
    n_act = n
    ns = force.shape[0]
    i = 0
    while i < ns:
        if (not want_traj) and hold == 0 and kind == 0 and start <= i < stop and i + 1 < ns:
            # fused: score the current displacement and advance in one pass
            n_flag = _linear_disp_nmse(w, n_act, force[i], obs[i], bound, scale, eps, flag)
            if n_flag:
                _retire(w, 2, n_act, scale, idx, flag, dist, status)
                n_act = _compact(w, idx, flag, n_act)
                if n_act == 0:
                    return
            i += 1
            continue
        _linear_output(w, n_act, force[i], kind, y)
        if _account(w, 2, 2, n_act, i, y, bound, obs, start, stop, scale, eps, want_traj, traj, idx, flag,
                    dist, status):
            n_act = _compact(w, idx, flag, n_act)
            if n_act == 0:
                return
        if i + 1 < ns:
            _linear_step(w, n_act, force[i], force[i + 1], hold)
        i += 1
    _finish(w, 2, n_act, scale, idx, dist, status)


# --------------------------------------------------------------------------- substeps


def choose_substeps(omega_max: float, dt: float, rel_tol: float = 1e-4, n_samples: int | None = None) -> int:
    """RK4 substeps per sample so the integration error at the highest natural frequency
    the priors allow stays below ``rel_tol`` per radian of phase (or, with ``n_samples``,
    below ``rel_tol`` over the whole record).

    Derivation. On the linear part ``s' = A s`` RK4 multiplies the state each step by
    ``R(hA)``, ``R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24``, whose leading error against
    ``e^z`` is ``z^5/120``. For a mode with eigenvalue ``lambda`` (``theta = |lambda| h``)
    the relative error per step is about ``theta^5 / 120``, i.e. ``theta^4 / 120`` per
    radian of phase (``|lambda| t``) advanced: a phase lag plus a smaller amplitude
    decay (``theta^6/144`` per step for an undamped mode). Requiring ``theta^4 / 120 <=
    rel_tol`` gives ``h <= (120 rel_tol)^(1/4) / omega_max``, so ``substeps =
    ceil(dt * omega_max / (120 rel_tol)^(1/4))`` (0.331 rad per substep for
    ``rel_tol = 1e-4``). A constant (held) force adds no error: RK4 keeps the static
    equilibrium of ``s' = A s + b`` exactly. The error per radian is smaller by
    ``(omega / omega_max)^4`` for the slower modes.

    With ``n_samples`` the bound is for the record: an undamped mode turns through at most
    ``omega_max * dt * n_samples`` radians and the phase errors add up, so the per-radian
    tolerance becomes ``rel_tol / (omega_max * dt * n_samples)`` (worst case; damped or
    forced responses forget old errors).

    ``omega_max``: the largest eigenvalue modulus of the linearised dynamics the priors
    allow, e.g. ``sqrt(k_max / m_min)`` for the Duffing linear part, ``sqrt((k_max +
    A_max) / m_min)`` for Bouc-Wen (``z ~ A y`` at small amplitude); with damping
    ``|c|/(2m) + sqrt(c^2/(4m^2) + |k|/m)``.

    What it does not cover: nonlinear stiffening (``k3 x^2``, ``k5 x^4`` raise the local
    frequency with amplitude: add them to ``k_max`` at the amplitude you expect), the
    Bouc-Wen relaxation rate ``n (|alpha| + |beta|) |v| |z|^(n-1)`` (state dependent, it
    can exceed any prior-based bound), and the RK4 stability limit for unstable or stiff
    parameter sets, which the divergence guard flags instead.
    """
    if not (omega_max >= 0 and math.isfinite(omega_max)):
        raise ValueError(f"omega_max must be finite and non-negative, got {omega_max!r}")
    if not (dt > 0 and math.isfinite(dt)):
        raise ValueError(f"dt must be positive, got {dt!r}")
    if not (0 < rel_tol < 1):
        raise ValueError(f"rel_tol must be in (0, 1), got {rel_tol!r}")
    if n_samples is not None:
        radians = omega_max * dt * max(int(n_samples), 1)
        if radians > 1.0:
            rel_tol = rel_tol / radians
    theta = (120.0 * rel_tol) ** 0.25
    return max(1, math.ceil(dt * omega_max / theta * (1 - 1e-12)))
