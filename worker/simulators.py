"""Batch simulators, reference grade (vectorised numpy across the batch).

The protocol a simulator (built-in or user) follows is :class:`Simulator`; a simulator
that can compute the NMSE itself also follows :class:`NMSECapable` (the evaluator's fast
path, :mod:`worker.compose`). A factory (the class, or a plugin's callable) may declare
``needs_input``: True (the oscillators) when it is driven by the input record, False
(g-and-k) when it only needs the observed record's length; see
:func:`worker.description.simulator_for` for the keywords each kind is called with.

Forced oscillators (:class:`Oscillator`) take the excitation sampled every ``dt``; between
samples it is held (``input_interpolation="hold"``, the default: ``force[i]`` constant over
step i, a zero-order hold, as the paper's data were made), interpolated linearly
(``"linear"``: ``force[i] + (force[i+1] - force[i]) (t - t_i) / dt`` over step i, a
first-order hold) or reconstructed as the band-limited signal through the samples
(``"bandlimited"``, Duffing and Bouc-Wen: :func:`band_limited`, computed once when the
simulator is built, at every RK4 stage time), for a measured continuous input; see
:data:`INTERPOLATIONS`. The state
starts at rest and the output has one value per force sample (output[0] is the initial
state, output[i + 1] the state after step i). ``Duffing`` and ``BoucWen`` integrate with
classical fixed-step RK4 with ``substeps`` steps per sample (the authors' demo uses 1),
each RK4 stage seeing the force at its own time; ``Linear`` uses the exact recursion for
either hold (the ramp's coefficients come from the same matrix exponential). A row whose
state leaves ``state_bound`` or stops being finite is flagged DIVERGED and frozen at zero,
so no overflow spreads and nothing garbage is returned.

Backends. ``backend="numba"`` (the default) runs the compiled kernels of
:mod:`worker.kernels`; ``backend="numpy"`` keeps the vectorised numpy code below as the
reference. The oscillators also offer ``distance_nmse(params, observed, start, stop,
epsilon=inf) -> (distances, status)``: the NMSE of :class:`abcns.distances.NMSE`
accumulated inside the kernel (no ``(n, n_samples)`` array), with early rejection of the
particles whose partial NMSE reaches ``epsilon`` (status OK, distance = that partial NMSE,
which is ``>= epsilon``, so the accept/reject decision is unchanged). With the numba
backend a row whose squared error overflows is DIVERGED (numpy: an OK row with distance
+inf, which the executor turns into FAILED).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import scipy.linalg

from abcns.distances import NMSE
from abcns.errors import InvalidSetting
from abcns.executor import DIVERGED, OK

OUTPUTS = ("displacement", "velocity", "acceleration")
BACKENDS = ("numba", "numpy")
_BIG = float(np.finfo(float).max)
#: how the input is interpolated between samples: "hold" (zero-order: the sample's value over
#: the step, the default), "linear" (first-order: a straight line to the next sample) or
#: "bandlimited" (the band-limited signal through the samples, :func:`band_limited`; the RK4
#: oscillators only)
INTERPOLATIONS = ("hold", "linear", "bandlimited")
#: the Bouc-Wen exponents n the kernels are specialised for (worker/kernels.py, bouc_wen_run)
#: and the numpy reference computes
BOUC_WEN_EXPONENTS = (1, 2, 3, 4)


@dataclass(frozen=True)
class Range:
    """The valid values of one simulator parameter: between ``low`` and ``high`` (each end
    open or closed), integers only with ``integer``. A simulator states them in its
    ``ranges`` ({parameter: Range}); a parameter it does not name takes any finite value.
    A fixed value must lie in the range; a uniform prior [a, b] in its closure (an open end
    has probability zero under the prior), and an integer parameter cannot have a prior."""

    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = False
    integer: bool = False

    def holds(self, x: float) -> bool:
        """Whether the value ``x`` is valid."""
        if not math.isfinite(x) or (self.integer and x != round(x)):
            return False
        above = x > self.low if self.low_open else x >= self.low
        below = x < self.high if self.high_open else x <= self.high
        return above and below

    def holds_prior(self, low: float, high: float) -> bool:
        """Whether the prior U(low, high) lies in the range's closure."""
        return not self.integer and self.low <= low and high <= self.high

    def __str__(self) -> str:
        kind = "an integer" if self.integer else "a number"
        if self.integer and math.isfinite(self.low) and math.isfinite(self.high):
            return f"{kind} in {self.low:g}..{self.high:g}"
        parts = []
        if math.isfinite(self.low):
            parts.append(f"{'>' if self.low_open else '>='} {self.low:g}")
        if math.isfinite(self.high):
            parts.append(f"{'<' if self.high_open else '<='} {self.high:g}")
        return f"{kind} {' and '.join(parts)}" if parts else f"a finite {kind.split()[-1]}"


#: m > 0 (every oscillator divides by the mass)
POSITIVE = Range(0.0, math.inf, low_open=True)


@dataclass(frozen=True, eq=False)
class SimOutput:
    values: np.ndarray  # (n, n_samples)
    status: np.ndarray  # (n,) int8


@runtime_checkable
class Simulator(Protocol):
    """What the evaluator needs of a simulator (built-in or plugin).

    - ``name``: shown in error messages and recorded by ``config()``;
    - ``parameter_names``: the full parameter vector's column order;
    - ``defaults``: values used for parameters a model neither fixes nor infers (may be empty);
    - ``n_samples``: the length of one simulated record (must equal the observed record's);
    - ``simulate(params (n, p), rng) -> SimOutput``: outputs ``(n, n_samples)`` and a status
      per row (``abcns.OK`` / ``DIVERGED`` / ``FAILED``); a row that is not OK may hold
      anything, it is never read;
    - ``config() -> dict``: JSON for provenance;
    - optionally ``ranges``: {parameter: :class:`Range`}, the valid values of the parameters
      it names (fixed values and priors are checked against them before a run).
    """

    name: str
    parameter_names: Sequence[str]
    defaults: Mapping[str, float]
    n_samples: int

    def simulate(self, params: np.ndarray, rng: np.random.Generator) -> SimOutput: ...

    def config(self) -> dict: ...


@runtime_checkable
class NMSECapable(Protocol):
    """The optional fast path: a simulator that computes the NMSE of
    :class:`abcns.distances.NMSE` itself, without returning the trajectories.

    ``distance_nmse(params (n, p), observed, start, stop, epsilon=inf) -> (distances (n,),
    status (n,) int8)``: the NMSE of the window ``[start, stop)``; not-OK rows have distance
    +inf; a row may stop early once its partial NMSE reaches ``epsilon`` (status OK, distance
    ``>= epsilon``, so the accept/reject decision at ``epsilon`` is unchanged)."""

    def distance_nmse(self, params: np.ndarray, observed: np.ndarray, start: int, stop: int,
                      epsilon: float = np.inf) -> tuple[np.ndarray, np.ndarray]: ...


def _force(force: np.ndarray | None, dt: float) -> np.ndarray:
    if force is None:
        raise InvalidSetting(("force",), "this simulator needs an input force")
    force = np.asarray(force, dtype=float)
    if force.ndim != 1 or force.size < 2:
        raise InvalidSetting(("force",), f"must be a 1-d array of at least 2 samples, got shape {force.shape}")
    if not np.all(np.isfinite(force)):
        raise InvalidSetting(("force",), "has non-finite values")
    if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
        raise InvalidSetting(("dt",), f"must be a positive number, got {dt!r}")
    return force


#: the band-limited interpolation's reach (samples each side) and its Kaiser window's beta
SINC_HALF_WIDTH, SINC_BETA = 24, 9.0


def band_limited(force: np.ndarray, factor: int) -> np.ndarray:
    """The band-limited signal through the samples ``force`` (interval dt) at ``factor``
    points per interval: ``(force.size - 1) * factor + 1`` values, ``out[i * factor] ==
    force[i]``.

    Whittaker-Shannon interpolation with a Kaiser-windowed sinc (``SINC_HALF_WIDTH`` samples
    each side, beta ``SINC_BETA``): ``x(t_i + tau dt) = sum_k x[i + k] sinc(tau - k) w(tau -
    k)``, the record reflected through its end points for the taps beyond them (``2 x[0] -
    x[k]``: its value and slope go on). Measured on random-phase multisines with tones to
    0.15 fs (docs/design.md, "A continuous input"): error below 5e-5 of the RMS from 24
    samples in, 3e-4 from 10 in, up to 2.5 % of it within a sample of the record's ends, where
    what lies beyond the record is unknown."""
    x = np.asarray(force, dtype=float)
    n, factor, half = x.size, int(factor), SINC_HALF_WIDTH
    if factor == 1:
        return x.copy()
    reach = min(half, n - 1)
    padded = np.concatenate([2.0 * x[0] - x[reach:0:-1], x, 2.0 * x[-1] - x[-2 : -reach - 2 : -1]])
    if reach < half:  # a record shorter than the taps' reach: zeros beyond the mirror
        padded = np.concatenate([np.zeros(half - reach), padded, np.zeros(half - reach)])
    taps = np.arange(-half + 1, half + 1)
    out = np.empty((n - 1) * factor + 1)
    for j in range(factor):
        d = j / factor - taps
        h = np.sinc(d) * np.i0(SINC_BETA * np.sqrt(np.clip(1.0 - (d / (half + 0.5)) ** 2, 0.0, None))) / np.i0(SINC_BETA)
        # out[i factor + j] = sum_k x[i + k] h(k), x[i + k] = padded[i + k + half]
        values = np.convolve(padded, h[::-1], mode="valid")[1:]
        out[j::factor] = values[: out[j::factor].size]
    out[::factor] = x  # the samples themselves (the sinc's zeros, to rounding)
    return out


def _substeps(substeps: object) -> int:
    if not (isinstance(substeps, int) and not isinstance(substeps, bool) and substeps >= 1):
        raise InvalidSetting(("substeps",), f"must be a positive integer, got {substeps!r}")
    return substeps


def _one_of(value: str, allowed: tuple[str, ...], where: str) -> str:
    """``value`` when it is one of ``allowed``, else an InvalidSetting at the keyword ``where``."""
    if value not in allowed:
        raise InvalidSetting((where,), f"must be one of {allowed}, got {value!r}")
    return value


def _kernels():
    """The numba kernels, imported on first use (numba's import is slow)."""
    from worker import kernels

    return kernels


def _nmse(observed: np.ndarray, start: int, stop: int, n_samples: int) -> NMSE:
    """:class:`abcns.distances.NMSE` on ``[start, stop)`` of ``observed`` (which validates the
    record and the window), checked to fit ``n_samples`` simulated samples."""
    nmse = NMSE(np.ascontiguousarray(observed, dtype=float), (start, stop))
    if nmse.stop > n_samples:
        raise ValueError(f"window [{nmse.start}, {nmse.stop}) does not fit {n_samples} simulated samples")
    return nmse


#: allowance on the Bouc-Wen |z| bound for RK4's overshoot (an accurate step stays far inside)
Z_SLACK = 1.05


def _linear_omega(m_min: float, c_max: float, k_max: float) -> float:
    """Largest eigenvalue modulus of ``m x'' + c x' + k x`` over the bounds (m_min > 0)."""
    if not m_min > 0:
        return float("inf")
    return c_max / (2 * m_min) + float(np.sqrt(c_max**2 / (4 * m_min**2) + k_max / m_min))


def _least_magnitude(lo: float, hi: float) -> float:
    """The smallest |x| over [lo, hi] (0 when it holds 0)."""
    return 0.0 if lo <= 0 <= hi else min(abs(lo), abs(hi))


def _linear_omega_min(m_max: float, c_min: float, k_min: float) -> float:
    """A lower bound, over the bounds, of the largest eigenvalue modulus of ``m x'' + c x' + k x``
    (``c_min``, ``k_min``: least magnitudes): the roots' product is k/m and their sum -c/m,
    so the larger one is at least sqrt(|k| / m) and at least |c| / (2 m)."""
    if not m_max > 0:
        return 0.0
    return max(float(np.sqrt(k_min / m_max)), c_min / (2 * m_max))


class Oscillator:
    """A forced oscillator: the input record, the output, the divergence guard, the backend
    dispatch and the in-kernel NMSE (:class:`NMSECapable`).

    Subclasses define the numba path (``_work``: the kernel's work rows; ``_call``: the
    kernel call), the numpy reference (``_simulate_numpy``) and ``_method()`` (what
    ``config()`` records about the integration)."""

    needs_input = True
    name = ""
    parameter_names: tuple[str, ...] = ()
    defaults: dict[str, float] = {}
    ranges: dict[str, Range] = {"m": POSITIVE}

    def __init__(self, force=None, dt: float = 0.01, output: str = "displacement", state_bound: float = np.inf,
                 backend: str = "numba", input_interpolation: str = "hold"):
        self.force = _force(force, dt)
        self.dt = float(dt)
        self.output = _one_of(output, OUTPUTS, "output")
        self.state_bound = float(state_bound)
        self.backend = _one_of(backend, BACKENDS, "backend")
        self.input_interpolation = _one_of(input_interpolation, INTERPOLATIONS, "input_interpolation")

    @property
    def _hold(self) -> int:
        """The kernels' ``hold`` code: 0 held, 1 linear, 2 band-limited."""
        return INTERPOLATIONS.index(self.input_interpolation)

    #: the force at every RK4 stage time (``bandlimited``; :func:`band_limited`), else a placeholder
    fine: np.ndarray = np.zeros(1)

    def _stage_forces(self, i: int, substeps: int) -> list[tuple[float, float, float]]:
        """The force at the start, middle and end of each substep of step i (numpy
        reference; as the kernels compute it)."""
        f0 = float(self.force[i])
        if self.input_interpolation == "hold":
            return [(f0, f0, f0)] * substeps
        if self.input_interpolation == "bandlimited":
            b = 2 * substeps * i
            return [(float(self.fine[b + 2 * s]), float(self.fine[b + 2 * s + 1]), float(self.fine[b + 2 * s + 2]))
                    for s in range(substeps)]
        df = float(self.force[i + 1]) - f0
        return [(f0 + df * (s / substeps), f0 + df * ((s + 0.5) / substeps), f0 + df * ((s + 1.0) / substeps))
                for s in range(substeps)]

    @property
    def n_samples(self) -> int:
        return int(self.force.size)

    def _method(self) -> dict:
        """The integration's settings for ``config()``."""
        raise NotImplementedError

    def config(self) -> dict:
        return {"simulator": self.name, **self._method(), "output": self.output, "dt": self.dt,
                "n_samples": int(self.force.size), "state_bound": self.state_bound, "backend": self.backend,
                "input_interpolation": self.input_interpolation}

    # -- numba path: subclasses define the work rows and the kernel call
    def _work(self, params: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, tuple]]:
        """[(rows of the batch, work array, extra kernel arguments)], one per kernel call."""
        raise NotImplementedError

    def _call(self, w: np.ndarray, extra: tuple, *args) -> None:
        raise NotImplementedError

    #: particles per kernel call: the work array of a block stays in the L1 cache
    block = 256

    def _run(self, params: np.ndarray, observed=None, start: int = 0, stop: int = 0, scale: float = 1.0,
             epsilon: float = np.inf):
        """Trajectories (observed None) or in-kernel NMSE; returns (values or distances, status)."""
        params = np.atleast_2d(np.asarray(params, dtype=float))
        n, ns = params.shape[0], self.force.size
        kind = _kernels().OUTPUT_CODES[self.output]
        bound = min(self.state_bound, _BIG) if self.state_bound == self.state_bound else _BIG
        want_traj = observed is None
        obs = np.zeros(1) if want_traj else observed
        traj = np.zeros(ns * n if want_traj else 1)
        dist = np.full(n, np.inf)
        status = np.zeros(n, dtype=np.int8)
        for rows, w, extra in self._work(params):
            cols = np.arange(n) if rows is None else rows.astype(np.int64)
            for b0 in range(0, cols.size, self.block):
                wb = np.ascontiguousarray(w[:, b0 : b0 + self.block])
                self._call(wb, extra, kind, bound, obs, int(start), int(stop), float(scale), float(epsilon),
                           cols[b0 : b0 + self.block], want_traj, traj, dist, status)
        if want_traj:
            return traj.reshape(ns, n).T, status
        return dist, status

    def distance_nmse(self, params: np.ndarray, observed: np.ndarray, start: int, stop: int,
                      epsilon: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """The NMSE of :class:`abcns.distances.NMSE` on ``[start, stop)`` without building the
        trajectories; particles whose partial NMSE reaches ``epsilon`` stop early (status OK,
        distance >= epsilon). Returns ``(distances (n,), status (n,) int8)``; not-OK rows
        have distance +inf."""
        nmse = self._checked_nmse(observed, start, stop)
        if self.backend == "numpy":
            # the reference: simulate, then NMSE
            out = self.simulate(params)
            d = np.full(out.status.shape[0], np.inf)
            ok = out.status == OK
            if ok.any():
                d[ok] = nmse(out.values[ok])
            return d, out.status
        return self._run(params, nmse.observed, nmse.start, nmse.stop, nmse.scale, epsilon)

    #: the last checked NMSE: (the observed array given, a copy of its values, start, stop, the NMSE)
    _nmse_memo: tuple[np.ndarray, np.ndarray, int, int, NMSE] | None = None

    def _checked_nmse(self, observed: np.ndarray, start: int, stop: int) -> NMSE:
        """:func:`_nmse` of the arguments, checked once: an evaluator passes the same record on
        every call (checking it and its variance again cost ~60 µs a call, a quarter of a
        cheap batch's kernel time). Reused only for the very array last given, with the same
        values (compared: the caller may have written into it), so it is the NMSE a fresh
        check would build, bit for bit."""
        memo = self._nmse_memo
        if (memo is not None and memo[0] is observed and memo[2] == start and memo[3] == stop
                and np.array_equal(memo[1], observed)):
            return memo[4]
        nmse = _nmse(observed, start, stop, self.n_samples)
        if isinstance(observed, np.ndarray):
            self._nmse_memo = (observed, observed.copy(), start, stop, nmse)
        return nmse

    def simulate(self, params: np.ndarray, rng: np.random.Generator | None = None) -> SimOutput:
        """Outputs ``(n, n_samples)`` (with numba: a transposed, Fortran-ordered view) and status."""
        if self.backend == "numba":
            values, status = self._run(params)
            return SimOutput(values, status)
        return self._simulate_numpy(params)

    def _simulate_numpy(self, params: np.ndarray) -> SimOutput:
        raise NotImplementedError


class _RK4Oscillator(Oscillator):
    """Fixed-step RK4 with ``substeps`` steps per sample. Subclasses define the state
    (``n_state``) and its derivative."""

    n_state = 2

    def __init__(self, force=None, dt: float = 0.01, substeps: int = 1, output: str = "displacement",
                 state_bound: float = np.inf, backend: str = "numba", input_interpolation: str = "hold"):
        super().__init__(force, dt, output=output, state_bound=state_bound, backend=backend,
                         input_interpolation=input_interpolation)
        self.substeps = _substeps(substeps)
        if self.input_interpolation == "bandlimited":  # once per simulator, not per simulation
            self.fine = band_limited(self.force, 2 * self.substeps)

    def _method(self) -> dict:
        return {"substeps": self.substeps}

    def derivative(self, p: tuple, state: list[np.ndarray], f: float) -> list[np.ndarray]:
        raise NotImplementedError

    def extra_bad(self, p: tuple, state: list[np.ndarray]) -> np.ndarray | bool:
        """Model-specific divergence test on the state after a sample (none by default)."""
        return False

    def unpack(self, params: np.ndarray) -> tuple:
        return tuple(params[:, j] for j in range(params.shape[1]))

    def observe(self, p: tuple, state: list[np.ndarray], f: float) -> np.ndarray:
        if self.output == "displacement":
            return state[0]
        if self.output == "velocity":
            return state[1]
        return self.derivative(p, state, f)[1]

    def _simulate_numpy(self, params: np.ndarray) -> SimOutput:
        params = np.atleast_2d(np.asarray(params, dtype=float))
        n = params.shape[0]
        p = self.unpack(params)
        force, h = self.force, self.dt / self.substeps
        state = [np.zeros(n) for _ in range(self.n_state)]
        bad = np.zeros(n, dtype=bool)
        out = np.empty((n, force.size))
        with np.errstate(all="ignore"):
            out[:, 0] = self.observe(p, state, force[0])
            for i in range(force.size - 1):
                for fa, fm, fb in self._stage_forces(i, self.substeps):
                    k1 = self.derivative(p, state, fa)
                    k2 = self.derivative(p, [s + 0.5 * h * d for s, d in zip(state, k1, strict=True)], fm)
                    k3 = self.derivative(p, [s + 0.5 * h * d for s, d in zip(state, k2, strict=True)], fm)
                    k4 = self.derivative(p, [s + h * d for s, d in zip(state, k3, strict=True)], fb)
                    state = [s + (h / 6.0) * (a + 2.0 * b + 2.0 * c + d)
                             for s, a, b, c, d in zip(state, k1, k2, k3, k4, strict=True)]
                # the divergence guard: non-finite or out of bound, then frozen at rest
                now = ~np.all(np.isfinite(state), axis=0) | (np.abs(state[0]) > self.state_bound)
                now |= self.extra_bad(p, state)
                if now.any():
                    bad |= now
                    for s in state:
                        s[bad] = 0.0
                out[:, i + 1] = self.observe(p, state, force[i + 1])
        status = np.where(bad | ~np.all(np.isfinite(out), axis=1), DIVERGED, OK).astype(np.int8)
        return SimOutput(out, status)


class Duffing(_RK4Oscillator):
    """``m x'' + c x' + k x + k2 x^2 + k3 x^3 + k5 x^5 = f(t)`` (paper Eqs. 6, 10, 11).

    ``k2`` (the optional quadratic term) defaults to 0; the others must be fixed or given
    priors."""

    name = "duffing"
    parameter_names = ("m", "c", "k", "k2", "k3", "k5")
    defaults = {"k2": 0.0}

    @staticmethod
    def omega_max(bounds: dict[str, tuple[float, float]]) -> float:
        """Highest natural frequency of the linear part the bounds allow (nonlinear
        stiffening not included: see ``worker.kernels.choose_substeps``)."""
        mag = {p: max(abs(lo), abs(hi)) for p, (lo, hi) in bounds.items()}
        return _linear_omega(min(abs(v) for v in bounds["m"]), mag["c"], mag["k"])

    @staticmethod
    def omega_min(bounds: dict[str, tuple[float, float]]) -> float:
        """The lowest the highest natural frequency of the linear part gets over the bounds."""
        least = {p: _least_magnitude(*bounds[p]) for p in ("c", "k")}
        return _linear_omega_min(max(abs(v) for v in bounds["m"]), least["c"], least["k"])

    def _work(self, params):
        K = _kernels()
        params = np.atleast_2d(np.asarray(params, dtype=float))
        w = np.zeros((K.DUFFING_ROWS, params.shape[0]))
        with np.errstate(all="ignore"):
            im = 1.0 / params[:, 0]
            w[3] = im
            w[4:9] = params[:, 1:6].T * im
        return [(None, w, ())]

    def _call(self, w, extra, kind, *args):
        _kernels().duffing_run(w, self.force, self.fine, self.dt / self.substeps, self.substeps, self._hold,
                                kind, *args)

    def derivative(self, p, state, f):
        m, c, k, k2, k3, k5 = p
        x, v = state
        x2 = x * x
        restoring = c * v + x * (k + x * (k2 + x * (k3 + k5 * x2)))
        return [v, (f - restoring) / m]


class BoucWen(_RK4Oscillator):
    """Bouc-Wen hysteresis, paper Eqs. (14)-(15):

    ``m y'' + c y' + k y + z = f(t)``,
    ``z' = A y' - alpha |y'| |z|^(n-1) z - beta y' |z|^n`` (both parities of Eq. 15 reduce
    to this form), with integer ``n`` in 1..4 (fixed, not inferred) and ``k`` default 0
    (the paper folds the linear stiffness into A).
    """

    name = "bouc_wen"
    parameter_names = ("m", "c", "k", "alpha", "beta", "A", "n")
    defaults = {"k": 0.0}
    ranges = {"m": POSITIVE, "n": Range(min(BOUC_WEN_EXPONENTS), max(BOUC_WEN_EXPONENTS), integer=True)}
    n_state = 3

    @staticmethod
    def omega_max(bounds: dict[str, tuple[float, float]]) -> float:
        """As for Duffing with stiffness |k| + A (at small amplitude z ~ A y)."""
        mag = {p: max(abs(lo), abs(hi)) for p, (lo, hi) in bounds.items()}
        return _linear_omega(min(abs(v) for v in bounds["m"]), mag["c"], mag["k"] + mag["A"])

    @staticmethod
    def omega_min(bounds: dict[str, tuple[float, float]]) -> float:
        """As for Duffing with stiffness k + A."""
        (k_lo, k_hi), (a_lo, a_hi) = bounds["k"], bounds["A"]
        return _linear_omega_min(max(abs(v) for v in bounds["m"]), _least_magnitude(*bounds["c"]),
                                 _least_magnitude(k_lo + a_lo, k_hi + a_hi))

    def unpack(self, params):
        n = params[:, 6]
        if not np.all(np.isin(n, BOUC_WEN_EXPONENTS)):  # refused by the spec's validation (ranges) before a run
            raise InvalidSetting(("fixed", "n"), f"Bouc-Wen n must be an integer in 1..4, got {np.unique(n)}")
        return (*tuple(params[:, j] for j in range(6)), n.astype(np.int64))

    def _work(self, params):
        K = _kernels()
        params = np.atleast_2d(np.asarray(params, dtype=float))
        n_exp = self.unpack(params)[6]
        groups = np.unique(n_exp)
        parts = []
        for g in groups:
            rows = None if groups.size == 1 else np.flatnonzero(n_exp == g)
            p = params if rows is None else params[rows]
            w = np.zeros((K.BOUC_WEN_ROWS, p.shape[0]))
            with np.errstate(all="ignore"):
                im = 1.0 / p[:, 0]
                w[4] = im
                w[5] = p[:, 1] * im
                w[6] = p[:, 2] * im
            w[7:10] = p[:, 3:6].T
            w[10] = BoucWen.z_bound(p[:, 3], p[:, 4], p[:, 5], p[:, 6])
            parts.append((rows, w, (int(g),)))
        return parts

    def _call(self, w, extra, kind, *args):
        _kernels().bouc_wen_run(w, extra[0], self.force, self.fine, self.dt / self.substeps, self.substeps, self._hold,
                                kind, *args)

    @staticmethod
    def z_bound(alpha: np.ndarray, beta: np.ndarray, A: np.ndarray, n: np.ndarray) -> np.ndarray:
        """The bound on |z| the equation implies, times ``Z_SLACK``; +inf where none exists.

        From rest, for z > 0 and v > 0, ``z' = v (A - (alpha + beta) z^n)`` stops z at
        ``(A / (alpha + beta))^(1/n)`` when alpha + beta > 0; for v < 0, ``z' = v (A + (alpha -
        beta) z^n)`` only lowers z below that level when alpha >= 0 (and symmetrically for
        z < 0). So with A >= 0, alpha >= 0 and alpha + beta > 0 the exact |z| never exceeds
        it; an integrated |z| past ``Z_SLACK`` times it means the RK4 step is far too coarse
        for that particle, which is flagged DIVERGED."""
        with np.errstate(all="ignore"):
            zmax = Z_SLACK * (A / (alpha + beta)) ** (1.0 / n)
        ok = (A >= 0) & (alpha >= 0) & (alpha + beta > 0) & np.isfinite(zmax)
        return np.where(ok, zmax, np.inf)

    def extra_bad(self, p, state) -> np.ndarray:
        _m, _c, _k, alpha, beta, A, n = p
        return np.abs(state[2]) > self.z_bound(alpha, beta, A, n)

    def derivative(self, p, state, f):
        m, c, k, alpha, beta, A, n = p
        y, v, z = state
        az = np.abs(z)
        az_nm1 = np.where(n == 1, 1.0, np.where(n == 2, az, np.where(n == 3, az * az, az * az * az)))
        zdot = A * v - alpha * np.abs(v) * az_nm1 * z - beta * v * az_nm1 * az
        return [v, (f - c * v - k * y - z) / m, zdot]


class Linear(Oscillator):
    """``m x'' + c x' + k x = f(t)`` by the exact recursion for the interpolated force:
    ``s_{i+1} = Phi s_i + Gamma f_i`` (held) or ``s_{i+1} = Phi s_i + Gamma f_i + R (f_{i+1}
    - f_i)`` (linear), with ``[[Phi, Gamma, R], [0, 1, 1], [0, 0, 1]] = expm([[A, B, 0], [0,
    0, 1/dt], [0, 0, 0]] dt)``. Exact for a force held, or ramped linearly, over each
    sample; no substeps."""

    name = "linear"
    parameter_names = ("m", "c", "k")
    defaults: dict[str, float] = {}

    def __init__(self, force=None, dt: float = 0.01, output: str = "displacement", state_bound: float = np.inf,
                 backend: str = "numba", input_interpolation: str = "hold"):
        if input_interpolation == "bandlimited":
            raise InvalidSetting(("input_interpolation",), "the linear simulator's exact recursion takes 'hold' or "
                            "'linear'; for 'bandlimited' use duffing with k3 = k5 = 0 fixed")
        super().__init__(force, dt, output=output, state_bound=state_bound, backend=backend,
                         input_interpolation=input_interpolation)

    def _method(self) -> dict:
        return {"method": "exact-zoh" if self.input_interpolation == "hold" else "exact-foh"}

    def _work(self, params):
        K = _kernels()
        params = np.atleast_2d(np.asarray(params, dtype=float))
        w = np.zeros((K.LINEAR_ROWS, params.shape[0]))
        K.hold_coefficients(np.ascontiguousarray(params[:, 0]), np.ascontiguousarray(params[:, 1]),
                            np.ascontiguousarray(params[:, 2]), self.dt, w)
        return [(None, w, ())]

    def _call(self, w, extra, kind, *args):
        _kernels().linear_run(w, self.force, self._hold, kind, *args)

    def _simulate_numpy(self, params: np.ndarray) -> SimOutput:
        params = np.atleast_2d(np.asarray(params, dtype=float))
        n = params.shape[0]
        m, c, k = params[:, 0], params[:, 1], params[:, 2]
        ramp = self.input_interpolation == "linear"
        aug = np.zeros((n, 4, 4) if ramp else (n, 3, 3))  # the force (and its slope) appended to the state
        aug[:, 0, 1] = 1.0
        if ramp:
            aug[:, 2, 3] = 1.0 / self.dt
        with np.errstate(all="ignore"):
            aug[:, 1, 0] = -k / m
            aug[:, 1, 1] = -c / m
            aug[:, 1, 2] = 1.0 / m
            finite = np.all(np.isfinite(aug.reshape(n, -1)), axis=1)
            aug[~finite] = 0.0  # expm of a non-finite matrix fails; these rows are DIVERGED below
            e = scipy.linalg.expm(aug * self.dt) if n else aug
            e[~finite] = np.nan
        p11, p12, p21, p22, g1, g2 = e[:, 0, 0], e[:, 0, 1], e[:, 1, 0], e[:, 1, 1], e[:, 0, 2], e[:, 1, 2]
        x, v = np.zeros(n), np.zeros(n)
        out = np.empty((n, self.force.size))
        bad = ~np.all(np.isfinite(e.reshape(n, -1)), axis=1)
        with np.errstate(all="ignore"):
            for i, f in enumerate(self.force):
                if self.output == "displacement":
                    out[:, i] = x
                elif self.output == "velocity":
                    out[:, i] = v
                else:
                    out[:, i] = (f - c * v - k * x) / m
                if ramp:
                    df = self.force[i + 1] - f if i + 1 < self.force.size else 0.0
                    x, v = (p11 * x + p12 * v + g1 * f + e[:, 0, 3] * df,
                            p21 * x + p22 * v + g2 * f + e[:, 1, 3] * df)
                else:
                    x, v = p11 * x + p12 * v + g1 * f, p21 * x + p22 * v + g2 * f
                now = ~np.isfinite(x) | ~np.isfinite(v) | (np.abs(x) > self.state_bound)
                if now.any():
                    bad |= now
                    x[bad] = 0.0
                    v[bad] = 0.0
        return SimOutput(out, np.where(bad, DIVERGED, OK).astype(np.int8))


class GAndK:
    """The g-and-k distribution (paper Eq. 8): ``n_samples`` draws per particle,
    ``A + B (1 + c tanh(g z / 2)) (1 + z^2)^k z`` with z standard normal
    (``(1 - e^{-gz}) / (1 + e^{-gz}) = tanh(gz/2)``). ``c`` is usually fixed at 0.8."""

    name = "gandk"
    parameter_names = ("A", "B", "g", "k", "c")
    defaults = {"c": 0.8}
    # B a scale; k > -1/2 keeps the quantile function increasing in the tails ((1 + z^2)^k z ~ z^(2k + 1))
    ranges = {"B": POSITIVE, "k": Range(-0.5, math.inf, low_open=True)}
    needs_input = False

    def __init__(self, n_samples: int = 10_000):
        if not (isinstance(n_samples, int) and n_samples >= 2):
            raise InvalidSetting(("observed",), f"g-and-k needs at least 2 observed samples, got {n_samples!r}")
        self.n_samples = n_samples

    def config(self) -> dict:
        return {"simulator": self.name, "n_samples": self.n_samples}

    @staticmethod
    def quantile(params: np.ndarray, z: np.ndarray) -> np.ndarray:
        A, B, g, k, c = (params[:, j : j + 1] for j in range(5))
        return A + B * (1.0 + c * np.tanh(0.5 * g * z)) * (1.0 + z * z) ** k * z

    def simulate(self, params: np.ndarray, rng: np.random.Generator) -> SimOutput:
        params = np.atleast_2d(np.asarray(params, dtype=float))
        z = rng.standard_normal((params.shape[0], self.n_samples))
        with np.errstate(all="ignore"):
            values = self.quantile(params, z)
        status = np.where(np.all(np.isfinite(values), axis=1), OK, DIVERGED).astype(np.int8)
        return SimOutput(values, status)
