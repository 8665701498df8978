"""Discrepancies between simulated and observed data.

Every distance is bound to the observed data at construction, maps a batch of simulated
outputs ``(n, n_samples)`` to ``(n,)`` non-negative distances, and describes itself with
``config()`` (JSON, for provenance). Rows that are not finite give ``+inf`` (a rejection),
never NaN.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol, runtime_checkable

import numpy as np

from abcns.errors import InvalidSetting
from abcns.noise import Noise


@runtime_checkable
class Distance(Protocol):
    observed: np.ndarray

    def __call__(self, simulated: np.ndarray) -> np.ndarray: ...

    def config(self) -> dict: ...


def _finite_observed(observed: np.ndarray) -> np.ndarray:
    observed = np.asarray(observed, dtype=float)
    if observed.ndim != 1 or observed.size == 0:
        raise InvalidSetting(("observed",), f"must be a non-empty 1-d array, got shape {observed.shape}")
    bad = np.flatnonzero(~np.isfinite(observed))
    if bad.size:
        raise InvalidSetting(("observed",), f"has {bad.size} non-finite values (first at index {bad[0]})")
    return observed


def _clean(d: np.ndarray) -> np.ndarray:
    d = np.asarray(d, dtype=float)
    d[~np.isfinite(d)] = np.inf
    return d


def check_window(window: tuple[int, int] | None, n_samples: int, name: str) -> tuple[int, int]:
    """Validate a half-open sample window ``[start, stop)`` against a record length (errors
    at ``(name,)``: ``fit``, the NMSE's window, or the caller's)."""
    if window is None:
        return 0, n_samples
    try:
        start, stop = (int(v) for v in window)
    except (TypeError, ValueError):
        raise InvalidSetting((name,), f"must be [start, stop], got {window!r}") from None
    if not 0 <= start < stop <= n_samples:
        raise InvalidSetting((name,), f"[{start}, {stop}) must satisfy 0 <= start < stop <= {n_samples}")
    if stop - start < 2:
        raise InvalidSetting((name,), "needs at least 2 samples")
    return start, stop


class NMSE:
    """Normalised mean squared error, paper Eq. (7), on the window ``[start, stop)``.

    ``100 / (n * var(obs)) * sum((sim - obs)^2)`` with ``var`` the sample variance
    (ddof = 1) of the observed data in the window, as in the authors' demo.
    """

    def __init__(self, observed: np.ndarray, window: tuple[int, int] | None = None):
        observed = _finite_observed(observed)
        self.start, self.stop = check_window(window, observed.size, "fit")
        self.observed = observed
        segment = observed[self.start : self.stop]
        variance = float(np.var(segment, ddof=1))
        if not variance > 0.0:
            raise InvalidSetting(("observed",), "is constant on the fit window; the NMSE is undefined")
        self.scale = 100.0 / (segment.size * variance)

    def __call__(self, simulated: np.ndarray) -> np.ndarray:
        simulated = np.atleast_2d(simulated)
        if simulated.shape[1] < self.stop:
            raise ValueError(f"simulated output has {simulated.shape[1]} samples, the window needs {self.stop}")
        with np.errstate(over="ignore", invalid="ignore"):
            diff = simulated[:, self.start : self.stop] - self.observed[self.start : self.stop]
            return _clean(self.scale * np.einsum("ij,ij->i", diff, diff))

    def noise(self, noise_std: float | None = None) -> Noise:
        """The noise model of this distance (``abcns.noise``): a sum of squares over the
        window's samples; with ``noise_std`` (the measurement noise's standard deviation,
        in the observed record's units) its variance per sample in % NMSE."""
        if noise_std is None:
            return Noise(self.stop - self.start)
        if not (isinstance(noise_std, (int, float)) and math.isfinite(noise_std) and noise_std > 0):
            raise InvalidSetting(("noise_std",), f"must be a finite positive number, got {noise_std!r}")
        try:
            variance = self.scale * float(noise_std) ** 2
        except OverflowError:  # the square past float64's range
            variance = math.inf
        if not math.isfinite(variance):
            raise InvalidSetting(("noise_std",), f"{noise_std:.6g} is too large for this record: its variance in % "
                                   "NMSE is not a finite number")
        return Noise(self.stop - self.start, variance)

    def config(self) -> dict:
        return {"name": "nmse", "window": [self.start, self.stop]}


def gk_summaries(samples: np.ndarray) -> np.ndarray:
    """The g-and-k summaries of the paper (§3.2, after [43]): P20, P40, P60, P80, skewness.

    ``samples`` (n, m) -> (n, 5). Skewness is the biased sample skewness
    ``m3 / m2^1.5``.
    """
    samples = np.atleast_2d(samples)
    pct = np.percentile(samples, [20.0, 40.0, 60.0, 80.0], axis=1).T
    centred = samples - samples.mean(axis=1, keepdims=True)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        squared = centred * centred  # the same bits as centred**2
        m2 = np.mean(squared, axis=1)
        m3 = np.mean(squared * centred, axis=1)  # 1/30 of centred**3's time (numpy's pow); last bits differ
        skew = m3 / m2**1.5
    return np.column_stack([pct, skew])


def order_statistics(samples: np.ndarray) -> np.ndarray:
    """The sorted sample, the other summary the paper names in §3.2."""
    return np.sort(np.atleast_2d(samples), axis=1)


SUMMARIES: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "gk": gk_summaries,
    "order_statistics": order_statistics,
}


class SummaryEuclidean:
    """Euclidean distance between summary statistics, paper Eq. (9)."""

    def __init__(self, observed: np.ndarray, summaries: str | Callable[[np.ndarray], np.ndarray] = "gk"):
        observed = _finite_observed(observed)
        if isinstance(summaries, str):
            if summaries not in SUMMARIES:
                raise InvalidSetting(("summaries",), f"unknown summaries {summaries!r}; known: {sorted(SUMMARIES)}")
            self.summaries_name = summaries
            summaries = SUMMARIES[summaries]
        else:
            self.summaries_name = getattr(summaries, "__name__", repr(summaries))
        self.summaries = summaries
        self.observed = observed
        self.observed_summaries = summaries(observed[None, :])[0]
        if not np.all(np.isfinite(self.observed_summaries)):
            raise InvalidSetting(("summaries",), "the observed data's summaries are not finite")

    def __call__(self, simulated: np.ndarray) -> np.ndarray:
        with np.errstate(over="ignore", invalid="ignore"):
            s = self.summaries(np.atleast_2d(simulated))
            return _clean(np.sqrt(np.sum((s - self.observed_summaries) ** 2, axis=1)))

    def config(self) -> dict:
        return {"name": "summary_euclidean", "summaries": self.summaries_name}


class CallableDistance:
    """Any user function ``f(simulated (n, m), observed (m,)) -> (n,)``."""

    def __init__(self, observed: np.ndarray, function: Callable[[np.ndarray, np.ndarray], np.ndarray]):
        self.observed = _finite_observed(observed)
        self.function = function

    def __call__(self, simulated: np.ndarray) -> np.ndarray:
        simulated = np.atleast_2d(simulated)
        with np.errstate(over="ignore", invalid="ignore"):
            d = _clean(np.asarray(self.function(simulated, self.observed), dtype=float).reshape(-1))
        if d.shape[0] != simulated.shape[0]:
            raise ValueError(f"distance function returned {d.shape[0]} values for {simulated.shape[0]} simulations")
        return d

    def config(self) -> dict:
        f = self.function
        return {"name": "callable", "function": f"{getattr(f, '__module__', '?')}:{getattr(f, '__qualname__', repr(f))}"}
