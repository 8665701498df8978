"""The noise floor of a run, and the tolerance at which its models are decided.

Below some tolerance the data's noise, not the model, decides which simulations are
accepted, and with nested candidate models a run taken below it chooses the model that fits
the noise best. For a distance that is a scaled sum of ``n`` squared residuals (the NMSE,
paper Eq. 7) with one sample's noise ``v`` in distance units, linearised least squares
gives, for the true model with ``p`` free parameters and its best fit ``d_min``:

    d_min / v ~ chi^2_(n - p),        (d(theta*) - d_min) / v ~ chi^2_p.

So the truth's own distance, the **noise floor**, is expected at ``F = d_min + p v``, with
spread ``sqrt(2 p) v``; ``v`` is ``d_min / (n - p)`` unless the spec states the noise
(``Noise.variance``). The **decision tolerance** is ``eps_dec = F + sqrt(2 p) v``: the run's
model probabilities are read at the population accepted at it (its :class:`Standing`;
:meth:`abcns.result.Result.decision_population`), and the evidence variant stops there by
default (``StopRules.noise_floor``). ``d_min`` is the lowest distance any model has reached
and ``p`` the largest number of free parameters among the models still alive and the best
fit's model, so the decision tolerance only falls as the run goes on. Why this level, and
the sources: docs/design.md, "The noise floor and the decision tolerance".
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from abcns.errors import InvalidSetting
from abcns.priors import Model

#: how a floor was estimated (``Floor.method``; stored as its index)
METHODS = ("estimated", "stated")


@dataclass(frozen=True)
class Noise:
    """What a run knows of its distance's noise: the distance is a scaled sum of squares of
    ``n_samples`` residuals (the NMSE over its fit window), and, when the user states it,
    ``variance``, one sample's noise variance in distance units (``NMSE.noise``
    converts a noise standard deviation in the data's units)."""

    n_samples: int
    variance: float | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.n_samples, int) and self.n_samples >= 2):
            raise InvalidSetting(("fit",), f"a noise floor needs at least 2 samples, got {self.n_samples!r}")
        if self.variance is not None and not (math.isfinite(self.variance) and self.variance > 0):
            raise InvalidSetting(("noise_std",), f"must give a finite positive noise variance, got {self.variance!r}")


@dataclass(frozen=True)
class Floor:
    """The noise floor as estimated after one population (see the module docstring).

    ``best``: the lowest distance any particle of the run has reached so far, by model
    ``model``; ``n_parameters``: the most free parameters of a model alive or of ``model``
    (p); ``variance``: one sample's noise in distance units (``METHODS[method]``: estimated
    from ``best`` or stated); ``floor`` = best + p v, the truth's expected distance;
    ``spread`` = sqrt(2 p) v; ``decision`` = floor + spread, the decision tolerance."""

    best: float
    model: int
    n_parameters: int
    variance: float
    method: int
    n_samples: int

    @property
    def floor(self) -> float:
        return self.best + self.n_parameters * self.variance

    @property
    def spread(self) -> float:
        return math.sqrt(2.0 * self.n_parameters) * self.variance

    @property
    def decision(self) -> float:
        return self.floor + self.spread

    def describe(self) -> dict:
        """JSON for the summary."""
        return {"best_distance": self.best, "model_index": self.model, "n_parameters": self.n_parameters,
                "noise_variance": self.variance, "method": METHODS[self.method], "n_samples": self.n_samples,
                "floor": self.floor, "spread": self.spread, "decision_tolerance": self.decision}


def estimate(noise: Noise, models: Sequence[Model], best: np.ndarray, alive: np.ndarray) -> Floor | None:
    """The floor from each model's best distance so far (``best`` (n_models,), +inf for a
    model never seen) and the models ``alive`` (boolean (n_models,)); None when no model has a
    finite best distance."""
    finite = np.isfinite(best)
    if not finite.any():
        return None
    m = int(np.argmin(np.where(finite, best, np.inf)))
    d_min = float(best[m])
    p = max(models[i].n_dim for i in range(len(models)) if alive[i] or i == m)
    if noise.variance is not None:
        variance, method = noise.variance, METHODS.index("stated")
    else:
        variance, method = d_min / max(noise.n_samples - p, 1), METHODS.index("estimated")
    return Floor(d_min, m, p, variance, method, noise.n_samples)


class Standing(IntEnum):
    """Where a population's tolerance stands to the decision tolerance in force when it was
    chosen (``Population.standing``; :func:`standing`)."""

    ABOVE = 0  #: above it: the (alpha N)-th largest distance (or the run's first tolerance) set it
    AT = 1  #: the decision tolerance set it (the quantile fell to it or below; :func:`abcns.nested.next_tolerance`)
    BELOW = 2  #: below it: the first tolerance under a floor above the run, or a run that does not stop there

    @property
    def reached(self) -> bool:
        """Whether the population was accepted at the decision tolerance or below it."""
        return self is not Standing.ABOVE


def standing(epsilon: float, in_force: Floor | None) -> Standing | None:
    """The one place "at the decision tolerance" is decided: a population accepted at
    ``epsilon`` against the decision tolerance ``in_force`` when ``epsilon`` was chosen (the
    floor after the previous population; for the first population, the floor after it).
    None without a floor. The evidence variant accepts a population at exactly
    ``in_force.decision`` when the (alpha N)-th largest distance falls below it, and stops
    after that population, even where the floor it finds falls further (the floor only
    falls, so that population is also the lowest at or above the final decision tolerance)."""
    if in_force is None:
        return None
    decision = in_force.decision
    return Standing.ABOVE if epsilon > decision else Standing.AT if epsilon == decision else Standing.BELOW


def standings(populations: Sequence) -> list[Standing | None]:
    """Each population's :class:`Standing`: its record (``Population.standing``), or, for a
    population made without one (a store, a result written before the record), the one
    :func:`standing` gives it from its tolerance and the floors."""
    return [p.standing if p.standing is not None else
            standing(p.epsilon, (populations[i - 1] if i else p).floor) for i, p in enumerate(populations)]


#: the stop rules wait for the decision tolerance only while it has not halved over this many
#: populations (:func:`waited_for`)
SETTLE_POPULATIONS = 5


def waited_for(decisions: Sequence[float | None]) -> float | None:
    """The decision tolerance the stop rules wait for (``StopRules.reason_after``), given
    the decision tolerance estimated after each population so far (None where unknown; the
    last: now). None when the run knows none, or when it fell below half of its value
    :data:`SETTLE_POPULATIONS` populations ago: the best fit then falls with the tolerance
    (noise-free data, a model that fits exactly: the authors' demo data fell 1e4-fold in 40
    populations), there is no floor to wait for, and the paper's rule applies as it always
    did. Near a real floor the estimate moves by a few percent a population."""
    now = decisions[-1] if decisions else None
    if now is None:
        return None
    if len(decisions) > SETTLE_POPULATIONS:
        then = decisions[-1 - SETTLE_POPULATIONS]
        if then is not None and now < 0.5 * then:
            return None
    return now


def best_by_model(which: np.ndarray, distances: np.ndarray, n_models: int,
                  previous: np.ndarray | None = None) -> np.ndarray:
    """Each model's lowest distance among ``distances`` (+inf where it has none), combined
    with the ``previous`` running minimum."""
    best = np.full(n_models, np.inf) if previous is None else np.array(previous, dtype=float)
    np.minimum.at(best, which, distances)
    return best


class Tracker:
    """A run's noise floor, population by population: each model's best distance so far
    (rebuilt from the ``history`` of a resumed run) and the floor it gives."""

    def __init__(self, noise: Noise | None, models: Sequence[Model], history: Sequence = ()):
        self.noise, self.models = noise, models
        n = len(models)
        self.best = (best_by_model(np.concatenate([p.models for p in history]),
                                   np.concatenate([p.distances for p in history]), n)
                     if history else np.full(n, np.inf))

    def after(self, which: np.ndarray, distances: np.ndarray) -> Floor | None:
        """The floor once a population of particles (``which``: their models) has these
        ``distances``; None without a noise model."""
        self.best = best_by_model(which, distances, len(self.models), self.best)
        if self.noise is None:
            return None
        return estimate(self.noise, self.models, self.best, np.bincount(which, minlength=len(self.models)) > 0)


#: the lags of the residuals' autocorrelation that :func:`whiteness` tests (1..WHITENESS_LAGS)
WHITENESS_LAGS = 10
#: the false-alarm probability of :func:`whiteness` on independent noise (its p-value threshold)
WHITENESS_LEVEL = 0.01


@dataclass(frozen=True)
class Whiteness:
    """The Ljung-Box test of a best fit's residuals (:func:`whiteness`): ``statistic`` Q,
    chi^2 with ``lags`` degrees of freedom when the residuals are independent noise;
    ``p_value`` its upper tail; ``autocorrelation`` at lags 1..``lags``; ``correlated`` when
    ``p_value`` < :data:`WHITENESS_LEVEL` (the noise floor is then likely optimistic);
    ``correlated_share``: lag 1's autocorrelation, clipped to [0, 1], about the share of the
    residuals' power that a smooth model error holds (docs/design.md, "Model error")."""

    statistic: float
    lags: int
    p_value: float
    autocorrelation: tuple[float, ...]
    n_samples: int

    @property
    def correlated(self) -> bool:
        return self.p_value < WHITENESS_LEVEL

    @property
    def correlated_share(self) -> float:
        return min(1.0, max(0.0, self.autocorrelation[0])) if self.autocorrelation else 0.0

    def describe(self) -> dict:
        """JSON for the summary."""
        return {"test": "ljung-box", "statistic": self.statistic, "lags": self.lags, "p_value": self.p_value,
                "level": WHITENESS_LEVEL, "correlated": self.correlated, "correlated_share": self.correlated_share,
                "autocorrelation": list(self.autocorrelation), "n_samples": self.n_samples}


def whiteness(residuals: np.ndarray, lags: int = WHITENESS_LAGS) -> Whiteness | None:
    """Whether ``residuals`` (a best fit's, in time order) look like independent noise: the
    Ljung-Box statistic ``Q = n (n + 2) sum_k r_k^2 / (n - k)`` over lags 1..``lags`` of
    their autocorrelation ``r_k`` (mean removed), against chi^2_lags (docs/design.md, "Model
    error made visible", derives it and its false-alarm rate with a fitted model). None when
    the record is too short (fewer than 5 ``lags`` samples) or the residuals are all equal."""
    from scipy.stats import chi2

    r = np.asarray(residuals, dtype=float).ravel()
    n = r.size
    lags = min(int(lags), n // 5)
    if lags < 1 or not np.all(np.isfinite(r)):
        return None
    r = r - r.mean()
    c0 = float(r @ r)
    if not c0 > 0:
        return None
    rho = np.array([float(r[:-k] @ r[k:]) / c0 for k in range(1, lags + 1)])
    q = float(n * (n + 2) * np.sum(rho**2 / (n - np.arange(1, lags + 1))))
    return Whiteness(q, lags, float(chi2.sf(q, lags)), tuple(float(v) for v in rho), n)


def projected_shift(jacobian: np.ndarray, delta: np.ndarray, sigma: float) -> tuple[np.ndarray, float]:
    """How far a change ``delta`` (n,) of a simulated record moves a least-squares fit whose
    Jacobian is ``jacobian`` (n, p): the parameter move ``J^+ delta`` and its length in the
    fit's standard deviations, ``||J J^+ delta|| / sigma`` (the Mahalanobis length of the move
    under the linearised Gaussian posterior with noise sd ``sigma``; docs/design.md, "Model
    error made visible")."""
    shift = np.linalg.lstsq(jacobian, delta, rcond=None)[0]
    return shift, float(np.linalg.norm(jacobian @ shift) / sigma)
