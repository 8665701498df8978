"""Uniform and log-uniform priors and candidate models (a named parameter space with fixed
values)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from abcns.errors import InvalidSetting


@dataclass(frozen=True)
class Uniform:
    """Uniform prior U(low, high) on one parameter; finite bounds, low < high, and a finite
    width (``high - low``, which sampling and the prior volume use).

    ``log``: uniform in log(theta) instead (log-uniform, scale-free: each decade of [low, high]
    holds the same prior mass), which needs low > 0. The bounds stay in the parameter's own
    units (:meth:`Model.to_coordinates` maps to the coordinate the prior is uniform in)."""

    low: float
    high: float
    log: bool = False

    def __post_init__(self) -> None:
        for name in ("low", "high"):
            value = getattr(self, name)
            if not isinstance(value, (int, float, np.floating, np.integer)) or isinstance(value, bool):
                raise InvalidSetting((name,), f"must be a number, got {value!r}")
            if not math.isfinite(value):
                raise InvalidSetting((name,), f"must be finite, got {value!r}")
        if not self.low < self.high:
            raise InvalidSetting(("low",), f"must be below high, got low={self.low!r} >= high={self.high!r}")
        if not math.isfinite(float(self.high) - float(self.low)):  # [-1e308, 1e308]: sampling would give inf
            raise InvalidSetting(("high",), f"the width high - low overflows a float, got [{self.low!r}, {self.high!r}]")
        if not isinstance(self.log, bool):
            raise InvalidSetting(("log",), f"must be true or false, got {self.log!r}")
        if self.log and not self.low > 0:
            raise InvalidSetting(("low",), f"a log-uniform prior needs low > 0, got {self.low!r}")
        object.__setattr__(self, "low", float(self.low))
        object.__setattr__(self, "high", float(self.high))

    @property
    def width(self) -> float:
        return self.high - self.low

    def pair(self) -> list[Any]:
        """The spec's form: ``[low, high]``, or ``[low, high, "log"]``."""
        return [self.low, self.high, "log"] if self.log else [self.low, self.high]

    @classmethod
    def parse(cls, value: Any) -> Uniform:
        """A prior from the spec's form, ``[low, high]`` or ``[low, high, "log"]``."""
        if isinstance(value, Uniform):
            return value
        if isinstance(value, (list, tuple)) and len(value) == 3:
            low, high, scale = value
            if scale != "log":
                raise InvalidSetting((), f"the third entry of a prior is \"log\" (log-uniform), got {scale!r}")
            return cls(low, high, log=True)
        try:
            low, high = value
        except (TypeError, ValueError):
            raise InvalidSetting((), f"must be [low, high] or [low, high, \"log\"], got {value!r}") from None
        return cls(low, high)


def in_box(theta: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Which rows of ``theta`` (..., d) lie in the box: ``np.all((theta >= low) & (theta <= high),
    axis=-1)`` (faces included, NaN outside), compiled (``abcns.compiled.in_box``): the prior
    box test of :meth:`Model.in_prior` and of the proposals (``bounds.Frame.in_prior``)."""
    from abcns import compiled

    x = np.asarray(theta, dtype=float)
    if x.ndim == 0 or x.shape[-1] != low.shape[0]:
        raise ValueError(f"theta has shape {x.shape}; a box in {low.shape[0]} dimensions needs (..., {low.shape[0]})")
    return compiled.in_box(np.ascontiguousarray(x.reshape(-1, x.shape[-1])), low, high).reshape(x.shape[:-1])


def same_models(models: Sequence[Model]) -> list[list[int]]:
    """For each model, the other models it is the same model as (``Model.same_model_as``,
    either way round, and the other copies of the same one)."""
    key = [m.same_model_as or m.name for m in models]
    return [[j for j in range(len(models)) if j != i and key[j] == key[i]] for i in range(len(models))]


@dataclass(frozen=True)
class Model:
    """A candidate model: its free parameters with uniform (or log-uniform) priors, and fixed
    values.

    ``priors`` keeps the order given; that order is the column order of the parameter
    vectors the algorithm proposes for this model. ``fixed`` holds parameters of the
    simulator that are not inferred. ``config`` is free JSON-able provenance (the
    simulator's name and options), never interpreted by the algorithm.

    ``same_model_as``: the name of another model of the run that this one is, under other
    priors (the same simulator, parameters and fixed values; ``abcns.run.check_models``).
    Declared side by side, the two are one model under an equal mixture of their priors, and
    ABC-NS's evidence variant fits each one's bound to the particles of both (each inside its
    own prior box): a region one prior's volume hides from its particles is still proposed
    from, once the other's particles have found it.
    """

    name: str
    priors: Mapping[str, Uniform]
    fixed: Mapping[str, float] = field(default_factory=dict)
    config: Mapping[str, object] = field(default_factory=dict)
    same_model_as: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise InvalidSetting(("name",), "a model needs a non-empty name")
        if not self.priors:
            raise InvalidSetting(("priors",), "a model needs at least one free parameter")
        if self.same_model_as is not None and (not isinstance(self.same_model_as, str) or not self.same_model_as
                                               or self.same_model_as == self.name):
            raise InvalidSetting(("same_model_as",), f"must name another model of the run, got {self.same_model_as!r}")
        priors: dict[str, Uniform] = {}
        # unchecked input (YAML, JSON, Python): a [low, high] pair is accepted too, validated below
        given: Mapping[str, Any] = self.priors
        for key, value in given.items():
            try:
                priors[key] = Uniform.parse(value)
            except InvalidSetting as err:
                raise InvalidSetting(("priors", key), err.message) from None
        fixed: dict[str, float] = {}
        for key, number in self.fixed.items():
            where = ("fixed", key)
            if key in priors:
                raise InvalidSetting(where, "is both fixed and given a prior")
            try:
                fval = float(number)
            except (TypeError, ValueError):
                raise InvalidSetting(where, f"must be a number, got {number!r}") from None
            if not math.isfinite(fval):
                raise InvalidSetting(where, f"must be finite, got {number!r}")
            fixed[key] = fval
        object.__setattr__(self, "priors", priors)
        object.__setattr__(self, "fixed", fixed)
        object.__setattr__(self, "config", dict(self.config))

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(self.priors)

    @property
    def n_dim(self) -> int:
        return len(self.priors)

    @property
    def low(self) -> np.ndarray:
        return np.array([p.low for p in self.priors.values()])

    @property
    def high(self) -> np.ndarray:
        return np.array([p.high for p in self.priors.values()])

    @property
    def log_columns(self) -> np.ndarray:
        """Which parameters have a log-uniform prior (bool, n_dim)."""
        return np.array([p.log for p in self.priors.values()])

    def to_coordinates(self, theta: np.ndarray) -> np.ndarray:
        """``theta`` (..., n_dim) in the coordinates the prior is uniform in: log of the
        log-uniform parameters' columns; ``theta`` itself when there are none."""
        return self._log_columns_through(theta, np.log)

    def from_coordinates(self, u: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`to_coordinates`."""
        return self._log_columns_through(u, np.exp)

    def _log_columns_through(self, x: np.ndarray, f: Any) -> np.ndarray:
        logs = self.log_columns
        if not logs.any():
            return x
        out = np.array(x, dtype=float)
        out[..., logs] = f(out[..., logs])
        return out

    @property
    def coordinate_low(self) -> np.ndarray:
        """The prior box's low ends in the coordinates the prior is uniform in."""
        return self.to_coordinates(self.low)

    @property
    def coordinate_width(self) -> np.ndarray:
        """The prior box's widths in those coordinates: ``high - low``, or log(high / low)."""
        return self.to_coordinates(self.high) - self.coordinate_low

    def sample_prior(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` draws from the prior, shape (n, n_dim): uniform in its coordinates."""
        return self.from_coordinates(self.coordinate_low + self.coordinate_width * rng.random((n, self.n_dim)))

    def in_prior(self, theta: np.ndarray) -> np.ndarray:
        """Boolean mask of the rows of ``theta`` (n, n_dim) inside the prior box (:func:`in_box`)."""
        return in_box(theta, self.low, self.high)

    def log_prior_volume(self) -> float:
        """log of the prior box's volume in the coordinates the prior is uniform in
        (:meth:`to_coordinates`): the sum of the log widths ``high - low`` (log(high / low) for a
        log-uniform prior)."""
        return float(np.sum(np.log(self.coordinate_width)))

    def log_prior_density(self, theta: np.ndarray) -> np.ndarray:
        """The prior's log density at each row of ``theta`` (n, n_dim) inside the box, in the
        parameters' own units: ``-log_prior_volume()``, less log(theta) of each log-uniform
        parameter (the Jacobian of d log theta / d theta)."""
        out = np.full(np.shape(theta)[0], -self.log_prior_volume())
        logs = self.log_columns
        if logs.any():
            out -= np.sum(np.log(np.asarray(theta)[:, logs]), axis=1)
        return out

    @classmethod
    def from_dict(cls, desc: Mapping[str, Any]) -> Model:
        """The model a dict describes: :meth:`config_dict`'s form (``config`` kept as it is) or
        a job spec's (``name``, ``simulator``, ``priors`` as [low, high] or [low, high, "log"], ``fixed``; the
        simulator's name kept as ``config``). InvalidSetting names the field (``priors.k``)."""
        config = desc.get("config") or ({"simulator": desc["simulator"]} if "simulator" in desc else {})
        return cls(desc["name"], desc["priors"], desc.get("fixed") or {}, config=config,
                   same_model_as=desc.get("same_model_as"))

    def config_dict(self) -> dict:
        """JSON-able, the inverse of :meth:`from_dict`."""
        return {
            "name": self.name,
            "priors": {k: p.pair() for k, p in self.priors.items()},
            "fixed": dict(self.fixed),
            **({"config": dict(self.config)} if self.config else {}),
            **({"same_model_as": self.same_model_as} if self.same_model_as is not None else {}),
        }
