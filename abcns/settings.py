"""Sampler settings and stop rules: frozen, validated on construction."""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

from abcns.priors import Model, SpecError


class StopReason(enum.StrEnum):
    """Why a run ended; stored with the result."""

    MIN_EPSILON_DECREASE = "min_epsilon_decrease"  # the paper's rule
    EPSILON_TARGET = "epsilon_target"
    SCHEDULE_END = "schedule_end"  # a given tolerance schedule was followed to its end
    MAX_POPULATIONS = "max_populations"
    MAX_SIMULATIONS = "max_simulations"
    MAX_SECONDS = "max_seconds"
    CANCELLED = "cancelled"
    PROPOSAL_EXHAUSTED = "proposal_exhausted"  # an ellipsoid lies (almost) outside the prior
    COMPLETED = "completed"  # a one-population algorithm (rejection) finished


def _check(cond: bool, field: str, message: str) -> None:
    if not cond:
        raise SpecError(field, message)


def _is_number(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


@dataclass(frozen=True)
class StopRules:
    """When to stop. Budgets (simulations, seconds) are checked inside a population too.

    ``min_epsilon_decrease``: stop when eps_t - eps_{t+1} < this (paper, §3.1);
    ``epsilon_target``: stop once a population was accepted at eps_t <= target.
    """

    min_epsilon_decrease: float | None = 0.01
    epsilon_target: float | None = None
    max_populations: int | None = None
    max_simulations: int | None = None
    max_seconds: float | None = None

    def __post_init__(self) -> None:
        for name in ("min_epsilon_decrease", "epsilon_target", "max_seconds"):
            v = getattr(self, name)
            _check(v is None or (_is_number(v) and v > 0), f"stop.{name}", f"must be a positive number or null, got {v!r}")
        for name in ("max_populations", "max_simulations"):
            v = getattr(self, name)
            _check(
                v is None or (isinstance(v, int) and not isinstance(v, bool) and v >= 1),
                f"stop.{name}",
                f"must be a positive integer or null, got {v!r}",
            )
        _check(any(v is not None for v in asdict(self).values()), "stop", "at least one stop rule must be set")


def _check_common(n_particles: object, batch_size: object, epsilon_initial: object) -> None:
    _check(
        isinstance(n_particles, int) and not isinstance(n_particles, bool) and n_particles >= 2,
        "sampler.particles",
        f"must be an integer >= 2, got {n_particles!r}",
    )
    _check(
        isinstance(batch_size, int) and not isinstance(batch_size, bool) and batch_size >= 1,
        "sampler.batch_size",
        f"must be a positive integer, got {batch_size!r}",
    )
    _check(
        epsilon_initial is None or (_is_number(epsilon_initial) and epsilon_initial > 0),
        "sampler.epsilon_initial",
        f"must be a positive number or null (chosen from a pilot), got {epsilon_initial!r}",
    )


@dataclass(frozen=True)
class NSSettings:
    """ABC-NS hyperparameters (paper §2.2; defaults as in the paper and the authors' demo).

    alpha : share of particles dropped per population (alpha0); next eps is the
        (alpha N)-th largest distance.
    beta : share of particles kept as survivors (beta0); (1 - beta) N new per population.
    enlargement : f0, the factor on the ellipsoid matrix.
    weights : "paper" -> (1/e)(1 - (e/eps)^2); "kernel" -> (1/eps)(1 - (e/eps)^2) (demo).
    epsilon_initial : tolerance of the first population; None: a prior-predictive pilot of
        ``pilot_size`` simulations (default N) sets it to their ``pilot_quantile`` quantile.
    batch_size : proposals per batch (part of the random stream: the same batch size and
        seed give the same result on any number of workers).
    max_redraws : prior-bound redraws allowed per proposal before the run stops with
        PROPOSAL_EXHAUSTED.
    """

    particles: int = 1000
    alpha: float = 0.3
    beta: float = 0.6
    enlargement: float = 1.1
    weights: str = "paper"
    epsilon_initial: float | None = None
    pilot_size: int | None = None
    pilot_quantile: float = 0.5
    batch_size: int = 200
    max_redraws: int = 100_000

    def __post_init__(self) -> None:
        _check_common(self.particles, self.batch_size, self.epsilon_initial)
        for name in ("alpha", "beta", "pilot_quantile"):
            v = getattr(self, name)
            _check(_is_number(v) and 0 < v < 1, f"sampler.{name}", f"must lie in (0, 1), got {v!r}")
        _check(
            self.beta <= 1 - self.alpha + 1e-12,
            "sampler.beta",
            f"beta ({self.beta}) must not exceed 1 - alpha ({1 - self.alpha:g}): survivors are drawn "
            "from the particles left after dropping alpha N",
        )
        _check(
            _is_number(self.enlargement) and self.enlargement >= 1,
            "sampler.enlargement",
            f"must be >= 1, got {self.enlargement!r}",
        )
        _check(self.weights in ("paper", "kernel"), "sampler.weights", f"must be 'paper' or 'kernel', got {self.weights!r}")
        _check(self.n_drop >= 1, "sampler.alpha", f"alpha * particles rounds to {self.n_drop}; at least 1 must drop")
        _check(self.n_new >= 1, "sampler.beta", f"(1 - beta) * particles rounds to {self.n_new}; at least 1 must be new")
        _check(
            self.pilot_size is None or (isinstance(self.pilot_size, int) and self.pilot_size >= 2),
            "sampler.pilot_size",
            f"must be an integer >= 2 or null, got {self.pilot_size!r}",
        )
        _check(isinstance(self.max_redraws, int) and self.max_redraws >= 1, "sampler.max_redraws", "must be >= 1")

    @property
    def n_drop(self) -> int:
        return int(round(self.alpha * self.particles))

    @property
    def n_survivors(self) -> int:
        return int(round(self.beta * self.particles))

    @property
    def n_new(self) -> int:
        return self.particles - self.n_survivors

    def check_models(self, models: Sequence[Model]) -> None:
        """Is N large enough for the models' dimensions? Each model's share of survivors
        at equal model probabilities must be able to define an ellipsoid (d + 1 points)."""
        d_max = max(m.n_dim for m in models)
        per_model = self.n_survivors // len(models)
        _check(
            per_model >= d_max + 1,
            "sampler.particles",
            f"{self.particles} particles give {per_model} survivors per model with {len(models)} models; "
            f"a {d_max}-parameter model needs at least {d_max + 1}",
        )


@dataclass(frozen=True)
class SMCSettings:
    """ABC-SMC (Toni et al. 2009) with Beaumont's Gaussian kernel of twice the weighted
    covariance. Tolerances follow ``schedule`` when given (paper Fig. 2), else each next
    tolerance is the ``quantile`` of the current population's distances."""

    particles: int = 1000
    quantile: float = 0.5
    schedule: tuple[float, ...] | None = None
    epsilon_initial: float | None = None
    pilot_size: int | None = None
    pilot_quantile: float = 0.5
    batch_size: int = 200
    max_redraws: int = 100_000

    def __post_init__(self) -> None:
        _check_common(self.particles, self.batch_size, self.epsilon_initial)
        for name in ("quantile", "pilot_quantile"):
            v = getattr(self, name)
            _check(_is_number(v) and 0 < v < 1, f"sampler.{name}", f"must lie in (0, 1), got {v!r}")
        if self.schedule is not None:
            sched = tuple(float(e) for e in self.schedule)
            _check(len(sched) >= 1 and all(e > 0 and math.isfinite(e) for e in sched), "sampler.schedule", "must be positive")
            _check(all(a >= b for a, b in zip(sched, sched[1:])), "sampler.schedule", "must not increase")
            object.__setattr__(self, "schedule", sched)

    def check_models(self, models: Sequence[Model]) -> None:
        d_max = max(m.n_dim for m in models)
        _check(
            self.particles // len(models) >= d_max + 1,
            "sampler.particles",
            f"{self.particles} particles are too few for {len(models)} models of up to {d_max} parameters",
        )


@dataclass(frozen=True)
class RejectionSettings:
    """ABC rejection (paper Algorithm 1): N particles from the priors below epsilon."""

    particles: int = 1000
    epsilon_initial: float | None = None
    pilot_size: int | None = None
    pilot_quantile: float = 0.5
    batch_size: int = 200

    def __post_init__(self) -> None:
        _check_common(self.particles, self.batch_size, self.epsilon_initial)
        _check(0 < self.pilot_quantile < 1, "sampler.pilot_quantile", "must lie in (0, 1)")

    def check_models(self, models: Sequence[Model]) -> None:
        return None
