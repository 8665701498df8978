"""Restoring-force models driven by a measured displacement: the spec's input record
(``data.input``) is the displacement ``x`` imposed on the device or specimen, the observed
record (``data.observed``) the force it resists with. Causality is the reverse of the
force-driven oscillators of :mod:`worker.simulators` (no mass, no equation of motion).

Both models are ``F = c x' + k x + alpha z`` with the hysteretic state ``z`` (a
displacement, z(0) = 0):

- ``bouc_wen_restoring`` (:class:`BoucWenRestoring`):
  ``z' = x' (A - |z|^n (beta sign(x' z) + gamma))``;
- ``bwbn_restoring`` (:class:`BWBNRestoring`), Bouc-Wen-Baber-Noori in the form of Foliente
  (J. Struct. Eng. 121(6), 1995) as Ortiz, Alvarez & Bedoya-Ruiz (Comput. Struct. 146, 2015)
  use it, with their nu0 = eta0 = 1 and no degradation of A (delta_A = 0):
  ``z' = h(z, e) x' (A - nu |z|^n (beta sign(x' z) + gamma)) / eta``,
  ``nu = 1 + delta_nu e``, ``eta = 1 + delta_eta e``, ``e(t) = alpha * integral of z dx``
  (the work of the hysteretic force), and the pinching function
  ``h = 1 - zeta_1 exp(-(z sign(x') - q z_u)^2 / zeta_2^2)`` with
  ``z_u = (A / (nu (beta + gamma)))^(1/n)``, ``zeta_1 = zeta_s (1 - exp(-p e))``,
  ``zeta_2 = (psi + delta_psi e) (lambda + zeta_1)``.

A third, ``spencer_mr`` (:class:`SpencerMR`), is Spencer et al.'s modified Bouc-Wen for MR
dampers, integrated in time (its internal displacement has dynamics); see its docstring. Its
form with the coil voltage as a second input channel (the spec's ``data.voltage``) and the
voltage-dependent alpha, c0, c1 of Spencer et al. is ``spencer_mr_voltage``
(:class:`SpencerMRVoltage`).

Note the names: ``alpha`` here weighs the hysteretic force (Ortiz's (1 - alpha) k), and
``beta``/``gamma`` are the ``|x'|`` and ``x'`` coefficients; in the force-driven
``bouc_wen`` (paper Eq. 15) those two are called ``alpha`` and ``beta``.

Velocity rule: the viscous term uses ``v_i = (x[i+1] - x[i-1]) / (2 dt)`` (central
differences, one-sided ``(x[1] - x[0]) / dt`` and ``(x[-1] - x[-2]) / dt`` at the ends;
``numpy.gradient``); the hysteretic state sees the displacement moving on a straight line
between samples (first-order hold) and is integrated in ``x`` itself (the models are rate
independent): classical RK4 steps of ``dz/dx``, at least ``substeps`` per sample step, more
where a particle's stiffness or pinching notch needs them (the step control of
:mod:`worker.restoring_kernels`). With ``c = 0`` (the default) the sample interval plays no
role at all, as for quasi-static tests.
"""

from __future__ import annotations

import copy
import math

import numpy as np

from abcns.errors import InvalidSetting
from abcns.executor import DIVERGED, OK
from worker.simulators import BoucWen, Oscillator, Range, SimOutput, _substeps

NONNEGATIVE = Range(0.0, math.inf)
POSITIVE_OPEN = Range(0.0, math.inf, low_open=True)
#: the exponent n: real, 0.5..10 (|z|^n by pow; past 10 the loops are a step function)
EXPONENT = Range(0.5, 10.0)


def _stiffness(az: np.ndarray, zu: np.ndarray, n: np.ndarray, nu: np.ndarray | float, beta: np.ndarray,
               gamma: np.ndarray) -> np.ndarray:
    """(numpy reference) ``restoring_kernels._stiffness``: ``nu n a^(n - 1) (beta + |gamma|)``
    at ``a = max(|z|, |z_u|)``, ``nu (beta + |gamma|)`` for n = 1 or a state of no scale."""
    b = nu * (beta + np.abs(gamma))
    a = np.maximum(az, np.abs(zu))
    with np.errstate(all="ignore"):
        scaled = n * b * a ** (n - 1.0)
    return np.where(n == 1.0, b, np.where((a > 0) & np.isfinite(a), scaled, n * b))


def _displacement(x) -> np.ndarray:
    """The displacement record, checked (non-finite samples refused at the path ``("force",)``)."""
    if x is None:
        raise InvalidSetting(("force",), "this simulator needs the displacement record as its input")
    x = np.asarray(x, dtype=float)
    if x.ndim != 1 or x.size < 2:
        raise InvalidSetting(("force",), f"the displacement must be a 1-d array of at least 2 samples, got shape {x.shape}")
    bad = np.flatnonzero(~np.isfinite(x))
    if bad.size:
        raise InvalidSetting(("force",), f"the displacement has non-finite values (sample {bad[0]} is {x[bad[0]]})")
    return x


class _Restoring(Oscillator):
    """The shared part: the displacement record, its velocity, the backend dispatch and the
    in-kernel NMSE of :class:`worker.simulators.Oscillator`."""

    n_state = 2

    def __init__(self, force=None, dt: float = 0.01, substeps: int = 1, state_bound: float = np.inf,
                 backend: str = "numba"):
        super().__init__(_displacement(force), dt, output="displacement", state_bound=state_bound, backend=backend)
        self.output = "force"
        self.substeps = _substeps(substeps)
        self.velocity = np.gradient(self.force, self.dt)

    @property
    def displacement(self) -> np.ndarray:
        return self.force

    def _method(self) -> dict:
        return {"substeps": self.substeps, "integration": "RK4 in x, displacement linear between samples, at least "
                "substeps steps per sample, more where a particle's rate asks (worker.restoring_kernels, step control)",
                "velocity": "central differences (numpy.gradient)"}

    def config(self) -> dict:
        cfg = super().config()
        cfg.pop("input_interpolation")
        return {**cfg, "input": "displacement"}

    def slopes(self, p: tuple, state: list[np.ndarray], s: float) -> list[np.ndarray]:
        """(numpy reference) d state / dx for every particle, s the sign of dx."""
        raise NotImplementedError

    def z_bound(self, p: tuple) -> np.ndarray:
        return np.full(p[0].shape, np.inf)

    #: the two coefficients whose sum must be positive (:meth:`outside`)
    bounded_by: tuple[str, str] = ("beta", "gamma")

    def outside(self, params: np.ndarray) -> np.ndarray:
        """The rows outside the model's domain: the sum of the two coefficients of ``|z|^n``
        (:attr:`bounded_by`) not positive. There z has no bound (the Bouc-Wen equation is BIBO
        stable only where it is positive: Ikhouane, Manosa & Rodellar, Syst. Control Lett. 56,
        2007) and Baber-Noori's ultimate z_u = (A / (nu (beta + gamma)))^(1/n), the centre of
        the pinching, is negative or undefined. Such a row is DIVERGED at once, never
        integrated: the prior is the box restricted to the domain (docs/design.md, "The
        domain: beta + gamma > 0")."""
        a, b = (self.parameter_names.index(k) for k in self.bounded_by)
        with np.errstate(invalid="ignore"):
            return ~(params[:, a] + params[:, b] > 0)

    def _inside_only(self, params: np.ndarray, trajectories: bool, call):
        """``call`` (params -> (values or distances, status)) on the rows inside the domain;
        the rows outside are DIVERGED (zero trajectories, infinite distances)."""
        params = np.atleast_2d(np.asarray(params, dtype=float))
        out = self.outside(params)
        if not out.any():
            return call(params)
        n = params.shape[0]
        values = np.zeros((n, self.force.size)) if trajectories else np.full(n, np.inf)
        status = np.full(n, DIVERGED, dtype=np.int8)
        inside = np.flatnonzero(~out)
        if inside.size:
            values[inside], status[inside] = call(params[inside])
        return values, status

    def _run(self, params, observed=None, *args, **kwargs):
        return self._inside_only(params, observed is None,
                                 lambda p: super(_Restoring, self)._run(p, observed, *args, **kwargs))

    def simulate(self, params: np.ndarray, rng: np.random.Generator | None = None) -> SimOutput:
        if self.backend == "numba":
            return super().simulate(params)
        return SimOutput(*self._inside_only(params, True, self._numpy_pair))

    def _numpy_pair(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out = self._simulate_numpy(params)
        return out.values, out.status

    def _simulate_numpy(self, params: np.ndarray) -> SimOutput:
        params = np.atleast_2d(np.asarray(params, dtype=float))
        n = params.shape[0]
        p = tuple(params[:, j] for j in range(params.shape[1]))
        c, k, al = p[0], p[1], p[2]
        x, v = self.force, self.velocity
        state = [np.zeros(n) for _ in range(self.n_state - 1)]
        zmax = self.z_bound(p)
        out = np.empty((n, x.size))
        bad = np.zeros(n, dtype=bool)
        with np.errstate(all="ignore"):
            for i in range(x.size):
                state[0] = np.where(np.abs(state[0]) > zmax, np.nan, state[0])
                f = c * v[i] + k * x[i] + al * state[0]
                now = ~np.isfinite(f) | (np.abs(f) > self.state_bound)
                for s_ in state:
                    now |= ~np.isfinite(s_)
                bad |= now
                for s_ in state:
                    s_[bad] = 0.0
                out[:, i] = np.where(bad, 0.0, f)
                if i + 1 < x.size and x[i + 1] != x[i]:
                    state = self._rk4_numpy(p, state, x[i + 1] - x[i])
        return SimOutput(out, np.where(bad, DIVERGED, OK).astype(np.int8))

    def finer(self) -> _Restoring:
        """This simulator at twice the ``substeps`` (the run's check of its own error,
        ``service/run/model_error.py``)."""
        out = copy.copy(self)
        out.substeps = 2 * self.substeps
        return out

    def rate(self, p: tuple, state: list[np.ndarray], d: float) -> np.ndarray:
        """(numpy reference) each particle's rate scale for the step control over a sample
        step ``d`` (the kernels' ``_bw_rate``, ``_bwbn_rate``)."""
        raise NotImplementedError

    def _rk4_numpy(self, p: tuple, state: list[np.ndarray], d: float) -> list[np.ndarray]:
        """One sample step of length ``d``: per particle, the kernels' step count
        (``restoring_kernels._steps_taken``; 0: DIVERGED, the state made NaN)."""
        from worker.restoring_kernels import KAPPA, MAX_SUBSTEPS

        with np.errstate(all="ignore"):
            want = abs(d) * self.rate(p, state, d) / KAPPA
        counts = np.where(want <= MAX_SUBSTEPS, np.maximum(self.substeps, np.ceil(np.nan_to_num(want))), 0).astype(int)
        out = [a.copy() for a in state]
        for m in np.unique(counts):
            sel = counts == m
            if m == 0:
                for a in out:
                    a[sel] = np.nan
                continue
            sub, now = tuple(a[sel] for a in p), [a[sel] for a in state]
            h, s = d / m, float(np.sign(d))
            for _ in range(m):
                k1 = self.slopes(sub, now, s)
                k2 = self.slopes(sub, [a + 0.5 * h * b for a, b in zip(now, k1, strict=True)], s)
                k3 = self.slopes(sub, [a + 0.5 * h * b for a, b in zip(now, k2, strict=True)], s)
                k4 = self.slopes(sub, [a + h * b for a, b in zip(now, k3, strict=True)], s)
                now = [a + (h / 6.0) * ((b1 + b4) + 2.0 * (b2 + b3)) for a, b1, b2, b3, b4 in zip(now, k1, k2, k3, k4,
                                                                                                strict=True)]
            for a, b in zip(out, now, strict=True):
                a[sel] = b
        return out

    #: the column of the exponent n in the parameter vector
    n_column = 6

    def _groups(self, params: np.ndarray, rows: int, first: int):
        """The kernel calls: one per exponent code (an integer n in 1..4 is specialised, any
        other n is code 0), each with the parameters in rows ``first..`` of its work array."""
        n = params[:, self.n_column]
        codes = np.where(np.isin(n, (1.0, 2.0, 3.0, 4.0)), n, 0.0).astype(np.int64)
        groups = np.unique(codes)
        parts = []
        for g in groups:
            sel = None if groups.size == 1 else np.flatnonzero(codes == g)
            p = params if sel is None else params[sel]
            w = np.zeros((rows, p.shape[0]))
            w[first : first + p.shape[1]] = p.T
            parts.append((sel, w, (int(g),)))
        return parts

    def _kernels_r(self):
        from worker import restoring_kernels

        return restoring_kernels


class BoucWenRestoring(_Restoring):
    """Bouc-Wen restoring force driven by the displacement (module docstring):
    ``F = c x' + k x + alpha z``, ``z' = x' (A - |z|^n (beta sign(x' z) + gamma))``.

    Valid ranges (refused before a run, naming the field): c, alpha, A, beta >= 0; n in
    0.5..10 (real); k and gamma any finite number (beta + gamma > 0 keeps z bounded, by
    ``(A / (beta + gamma))^(1/n)``; a particle past that bound, or with a non-finite state,
    is DIVERGED)."""

    name = "bouc_wen_restoring"
    parameter_names = ("c", "k", "alpha", "A", "beta", "gamma", "n")
    defaults = {"c": 0.0}
    ranges = {"c": NONNEGATIVE, "alpha": NONNEGATIVE, "A": NONNEGATIVE, "beta": NONNEGATIVE,
              "n": EXPONENT}

    def z_bound(self, p: tuple) -> np.ndarray:
        """As :meth:`worker.simulators.BoucWen.z_bound` (its alpha is this beta, its beta this gamma)."""
        return BoucWen.z_bound(p[4], p[5], p[3], p[6])

    def slopes(self, p, state, s):
        _c, _k, _al, A, beta, gamma, n = p
        z = state[0]
        return [A - np.abs(z) ** n * (beta * np.sign(s * z + (z == 0)) + gamma)]

    def rate(self, p, state, d):
        _c, _k, _al, A, beta, gamma, n = p
        return _stiffness(np.abs(state[0]), (A / (beta + gamma)) ** (1.0 / n), n, 1.0, beta, gamma)

    def _work(self, params):
        params = np.atleast_2d(np.asarray(params, dtype=float))
        parts = self._groups(params, self._kernels_r().BW_ROWS, 3)
        for _sel, w, _extra in parts:
            w[10] = self.z_bound(tuple(w[3 + j] for j in range(7)))
        return parts

    def _call(self, w, extra, kind, *args):
        self._kernels_r().bw_restoring_run(w, extra[0], self.force, self.velocity, self.substeps, *args)


class BWBNRestoring(_Restoring):
    """Bouc-Wen-Baber-Noori restoring force driven by the displacement (module docstring):
    energy-based strength (``delta_nu``) and stiffness (``delta_eta``) degradation and
    pinching (``zeta_s``, ``p``, ``q``, ``psi``, ``delta_psi``, ``lambda``).

    Valid ranges (refused before a run, naming the field): c, alpha, A, beta, delta_nu,
    delta_eta, p, delta_psi >= 0; n in 0.5..10; zeta_s in [0, 1) (h stays positive); q in
    [0, 1); psi > 0 and lambda > 0 (zeta_2 > 0). With zeta_s = 0 and delta_nu = delta_eta = 0
    it is :class:`BoucWenRestoring`."""

    name = "bwbn_restoring"
    parameter_names = ("c", "k", "alpha", "A", "beta", "gamma", "n", "delta_nu", "delta_eta", "p", "zeta_s", "psi",
                       "delta_psi", "lambda", "q")
    defaults = {"c": 0.0, "delta_psi": 0.0}
    ranges = {
        "c": NONNEGATIVE, "alpha": NONNEGATIVE, "A": NONNEGATIVE, "beta": NONNEGATIVE, "n": EXPONENT,
        "delta_nu": NONNEGATIVE, "delta_eta": NONNEGATIVE, "p": NONNEGATIVE,
        "zeta_s": Range(0.0, 1.0, high_open=True), "psi": POSITIVE_OPEN, "delta_psi": NONNEGATIVE,
        "lambda": POSITIVE_OPEN, "q": Range(0.0, 1.0, high_open=True)}
    n_state = 3

    def slopes(self, p, state, s):
        _c, _k, al, A, beta, gamma, n, dnu, deta, pp, zs, psi, dpsi, lam, q = p
        z, e = state
        nu = 1.0 + dnu * e
        zu = (A / (nu * (beta + gamma))) ** (1.0 / n)
        z1 = zs * (1.0 - np.exp(-pp * e))
        z2 = (psi + dpsi * e) * (lam + z1)
        h = 1.0 - z1 * np.exp(-(((s * z - q * zu) / z2) ** 2))
        g = A - nu * np.abs(z) ** n * (beta * np.sign(s * z + (z == 0)) + gamma)
        return [h * g / (1.0 + deta * e), al * z]

    def rate(self, p, state, d):
        from worker.restoring_kernels import NOTCH_REACH

        _c, _k, _al, A, beta, gamma, n, dnu, deta, pp, zs, psi, dpsi, lam, q = p
        z, e = state
        nu, eta = 1.0 + dnu * e, 1.0 + deta * e
        az = np.abs(z)
        zu = (A / (nu * (beta + gamma))) ** (1.0 / n)
        z1 = zs * (1.0 - np.exp(-pp * e))
        z2 = (psi + dpsi * e) * (lam + z1)
        g = np.abs(A) + nu * az**n * (beta + np.abs(gamma))
        near = np.abs(np.sign(d) * z - q * zu) - abs(d) * g / eta < NOTCH_REACH * z2
        return (_stiffness(az, zu, n, nu, beta, gamma) + np.where(near, z1 / z2 * g, 0.0)) / eta

    def _work(self, params):
        params = np.atleast_2d(np.asarray(params, dtype=float))
        return self._groups(params, self._kernels_r().BWBN_ROWS, 4)

    def _call(self, w, extra, kind, *args):
        self._kernels_r().bwbn_restoring_run(w, extra[0], self.force, self.velocity, self.substeps, *args)


class SpencerMR(_Restoring):
    """Spencer, Dyke, Sain & Carlson's modified Bouc-Wen model of an MR damper (J. Eng.
    Mech. 123(3), 1997, Eqs. 6-8), driven by the displacement ``x``, at one coil voltage (its
    voltage-dependent alpha, c0, c1 are plain parameters here: a record at constant voltage):

    ``F = c1 y' + k1 (x - x0)``,
    ``y' = (alpha z + c0 x' + k0 (x - y)) / (c0 + c1)``,
    ``z' = -gamma |x' - y'| z |z|^(n-1) - beta (x' - y') |z|^n + A (x' - y')``.

    The internal displacement ``y`` has dynamics of its own (the model is not rate
    independent), so it is integrated in time: ``substeps`` RK4 steps per sample, the
    displacement linear between samples (its velocity over step i ``(x[i+1] - x[i]) / dt``);
    the output at a sample uses the central-difference velocity (module docstring).

    Valid ranges (refused before a run, naming the field): c0, c1 > 0; alpha, k0, k1, A,
    gamma >= 0; n in 0.5..10; beta, x0 any finite number. As for Bouc-Wen, ``|z|`` stays below
    ``(A / (gamma + beta))^(1/n)`` when ``gamma + beta > 0``: a particle past 1.05 times that
    (an RK4 step too coarse for its stiffness: refine ``substeps``) is DIVERGED."""

    name = "spencer_mr"
    parameter_names: tuple[str, ...] = ("alpha", "c0", "c1", "k0", "k1", "x0", "gamma", "beta", "A", "n")
    defaults = {"x0": 0.0}
    ranges = {"alpha": NONNEGATIVE, "c0": POSITIVE_OPEN, "c1": POSITIVE_OPEN, "k0": NONNEGATIVE, "k1": NONNEGATIVE,
              "A": NONNEGATIVE, "gamma": NONNEGATIVE, "n": EXPONENT}
    n_state = 3
    n_column = 9

    def _method(self) -> dict:
        return {"substeps": self.substeps, "integration": "RK4 in time, displacement linear between samples",
                "velocity": "central differences (numpy.gradient) at the samples; the step's slope within it"}

    def _work(self, params):
        params = np.atleast_2d(np.asarray(params, dtype=float))
        parts = self._groups(params, self._kernels_r().SPENCER_ROWS, 4)
        for _sel, w, _extra in parts:
            with np.errstate(all="ignore"):
                w[14] = 1.0 / (w[5] + w[6])
            w[15] = self.z_bound(tuple(w[4 + j] for j in range(10)))
        return parts

    def z_bound(self, p: tuple) -> np.ndarray:
        """As :meth:`worker.simulators.BoucWen.z_bound` (its alpha is this gamma, its beta this beta)."""
        return BoucWen.z_bound(p[6], p[7], p[8], p[9])

    def _call(self, w, extra, kind, *args):
        self._kernels_r().spencer_run(w, extra[0], self.force, self.velocity, NO_VOLTAGE, self.dt / self.substeps,
                                      self.substeps, *args)

    def _simulate_numpy(self, params: np.ndarray) -> SimOutput:
        """The reference of :class:`SpencerMRVoltage` at zero voltage with no voltage terms."""
        params = np.atleast_2d(np.asarray(params, dtype=float))
        zero = np.zeros(params.shape[0])
        al, c0, c1, k0, k1, x0, ga, be, A, n = params.T
        full = np.column_stack([al, zero, c0, zero, c1, zero, k0, k1, x0, ga, be, A, n, zero])
        return _spencer_numpy(full, self.force, self.velocity, np.zeros(self.force.size), self.dt, self.substeps,
                              self.state_bound)


#: the constant-voltage kernel's voltage record (none)
NO_VOLTAGE = np.zeros(0)


def _voltage(voltage, n_samples: int) -> np.ndarray:
    """The coil voltage record, checked against the displacement's length (errors at the
    path ``("voltage",)``)."""
    if voltage is None:
        raise InvalidSetting(("voltage",), "simulator 'spencer_mr_voltage' needs the coil voltage record (one sample "
                                        "per displacement sample)")
    v = np.asarray(voltage, dtype=float)
    if v.ndim != 1 or v.size != n_samples:
        raise InvalidSetting(("voltage",), f"must have one sample per displacement sample ({n_samples}), got shape {v.shape}")
    bad = np.flatnonzero(~np.isfinite(v))
    if bad.size:
        raise InvalidSetting(("voltage",), f"has non-finite values (sample {bad[0]} is {v[bad[0]]})")
    return v


def _spencer_numpy(params: np.ndarray, x: np.ndarray, v: np.ndarray, e: np.ndarray, dt: float, substeps: int,
                   state_bound: float) -> SimOutput:
    """(numpy reference) :class:`SpencerMRVoltage`'s parameters ``params`` (n, 14) over the
    displacement ``x`` (velocity ``v`` at the samples) and the commanded voltage ``e``."""
    ala, alb, c0a, c0b, c1a, c1b, k0, k1, x0, ga, be, A, n, eta = params.T
    h = dt / substeps
    y, z, u = (np.zeros(params.shape[0]) for _ in range(3))
    out = np.empty((params.shape[0], x.size))
    bad = np.zeros(params.shape[0], dtype=bool)

    def rates(xt, vt, et, y, z, u):
        c0, c1 = c0a + c0b * u, c1a + c1b * u
        yd = ((ala + alb * u) * z + c0 * vt + k0 * (xt - y)) / (c0 + c1)
        w = vt - yd
        return yd, w * (A - np.abs(z) ** n * (be + ga * np.sign(w * z))), -eta * (u - et)

    zmax = BoucWen.z_bound(ga, be, A, n)
    with np.errstate(all="ignore"):
        for i in range(x.size):
            z = np.where(np.abs(z) > zmax, np.nan, z)
            c1 = c1a + c1b * u
            f = c1 * rates(x[i], v[i], e[i], y, z, u)[0] + k1 * (x[i] - x0)
            f = np.where(c0a + c0b * u + c1 > 0, f, np.nan)
            bad |= ~np.isfinite(f) | ~np.isfinite(y) | ~np.isfinite(z) | ~np.isfinite(u) | (np.abs(f) > state_bound)
            y[bad], z[bad], u[bad] = 0.0, 0.0, 0.0
            out[:, i] = np.where(bad, 0.0, f)
            if i + 1 < x.size:
                vs, es = (x[i + 1] - x[i]) / dt, (e[i + 1] - e[i]) / dt
                for s in range(substeps):
                    xa, ea = x[i] + vs * (s * h), e[i] + es * (s * h)
                    xm, em = xa + vs * 0.5 * h, ea + es * 0.5 * h
                    a1, b1, c1_ = rates(xa, vs, ea, y, z, u)
                    a2, b2, c2 = rates(xm, vs, em, y + 0.5 * h * a1, z + 0.5 * h * b1, u + 0.5 * h * c1_)
                    a3, b3, c3 = rates(xm, vs, em, y + 0.5 * h * a2, z + 0.5 * h * b2, u + 0.5 * h * c2)
                    a4, b4, c4 = rates(xa + vs * h, vs, ea + es * h, y + h * a3, z + h * b3, u + h * c3)
                    y = y + (h / 6.0) * ((a1 + a4) + 2.0 * (a2 + a3))
                    z = z + (h / 6.0) * ((b1 + b4) + 2.0 * (b2 + b3))
                    u = u + (h / 6.0) * ((c1_ + c4) + 2.0 * (c2 + c3))
    return SimOutput(out, np.where(bad, DIVERGED, OK).astype(np.int8))


class SpencerMRVoltage(SpencerMR):
    """Spencer, Dyke, Sain & Carlson's modified Bouc-Wen model of an MR damper with the coil
    voltage as a second input channel (J. Eng. Mech. 123(3), 1997, Eqs. 6-12): the model of
    :class:`SpencerMR` with

    ``alpha = alpha_a + alpha_b u``, ``c0 = c0a + c0b u``, ``c1 = c1a + c1b u``,
    ``u' = -eta (u - e)``,

    ``e`` the commanded voltage (the spec's ``data.voltage``, one sample per displacement
    sample, linear between samples like the displacement) and ``u`` its first-order filter
    (the current driver and the fluid's reaction; u(0) = 0). y, z and u are integrated
    together: ``substeps`` RK4 steps per sample (RK4 on ``u`` needs ``eta dt / substeps <
    2.78``; Spencer's eta = 190 /s is 0.06 at 3 kHz).

    Valid ranges (refused before a run, naming the field): c0a, c1a, eta > 0; alpha_a,
    alpha_b, c0b, c1b, k0, k1, A, gamma >= 0; n in 0.5..10; beta, x0 any finite number. The
    voltage record must be finite (``data.voltage``); the laws take u as it is, negative
    included (a measured command rings below 0 at its steps, and so does a decimated one), and
    a particle whose c0 + c1 is not positive at a sample (c0a + c1a < -(c0b + c1b) u) is
    DIVERGED. With alpha_b = c0b = c1b = 0 it is :class:`SpencerMR` (the voltage plays no
    part)."""

    name = "spencer_mr_voltage"
    parameter_names = ("alpha_a", "alpha_b", "c0a", "c0b", "c1a", "c1b", "k0", "k1", "x0", "gamma", "beta", "A", "n",
                       "eta")
    defaults = {"x0": 0.0}
    ranges = {"alpha_a": NONNEGATIVE, "alpha_b": NONNEGATIVE, "c0a": POSITIVE_OPEN, "c0b": NONNEGATIVE,
              "c1a": POSITIVE_OPEN, "c1b": NONNEGATIVE, "k0": NONNEGATIVE, "k1": NONNEGATIVE, "A": NONNEGATIVE,
              "gamma": NONNEGATIVE, "n": EXPONENT, "eta": POSITIVE_OPEN}
    n_state = 4
    n_column = 12

    def __init__(self, force=None, dt: float = 0.01, substeps: int = 1, state_bound: float = np.inf,
                 backend: str = "numba", voltage=None):
        super().__init__(force, dt, substeps=substeps, state_bound=state_bound, backend=backend)
        self.voltage = _voltage(voltage, self.force.size)

    def config(self) -> dict:
        return {**super().config(), "input": "displacement, voltage"}

    def _work(self, params):
        params = np.atleast_2d(np.asarray(params, dtype=float))
        parts = self._groups(params, self._kernels_r().SPENCER_V_ROWS, 5)
        for _sel, w, _extra in parts:
            w[19] = BoucWen.z_bound(w[14], w[15], w[16], w[17])
        return parts

    def _call(self, w, extra, kind, *args):
        self._kernels_r().spencer_run(w, extra[0], self.force, self.velocity, self.voltage, self.dt / self.substeps,
                                      self.substeps, *args)

    def _simulate_numpy(self, params: np.ndarray) -> SimOutput:
        params = np.atleast_2d(np.asarray(params, dtype=float))
        return _spencer_numpy(params, self.force, self.velocity, self.voltage, self.dt, self.substeps, self.state_bound)
