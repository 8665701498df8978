"""ABC rejection (paper Algorithm 1), which is also the first population of ABC-NS and
ABC-SMC, and the prior-predictive pilot that sets the initial tolerance when none is given."""

from __future__ import annotations

import time
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass

import numpy as np

from abcns.executor import Executor
from abcns.filling import Budget, Filled, Propose, Stopped, fill
from abcns.priors import Model
from abcns.result import Population, RunEnd
from abcns.settings import RejectionSettings, StopReason, StopRules


def pad(models: Sequence[Model], n: int) -> np.ndarray:
    return np.full((n, max(m.n_dim for m in models)), np.nan)


@dataclass(frozen=True, eq=False)
class PriorProposer:
    """Each proposal picks a model with equal probability, then draws from its prior."""

    models: tuple[Model, ...]

    def __call__(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        which = rng.integers(len(self.models), size=n)
        theta = pad(self.models, n)
        for i, model in enumerate(self.models):
            rows = np.flatnonzero(which == i)
            theta[rows, : model.n_dim] = model.sample_prior(rows.size, rng)
        return which.astype(np.int16), theta, np.zeros(n, dtype=np.int64)


def prior_proposer(models: Sequence[Model]) -> Propose:
    return PriorProposer(tuple(models))


def initial_epsilon(
    models: Sequence[Model], settings, executor: Executor, budget: Budget, seed: int
) -> tuple[float, str, int]:
    """(epsilon_1, "given" | "pilot" | "pilot_finite", pilot simulations).

    Without ``settings.epsilon_initial``, ``pilot_size`` (default N) prior-predictive
    simulations are run (population index 0 of the seed stream) and epsilon_1 is the
    ``pilot_quantile`` quantile of their distances (failed ones count as +inf). When that
    quantile is +inf (more than 1 - q failed or diverged) it is the quantile of the finite
    ones ("pilot_finite"); when every one failed the run stops (``PILOT_FAILED``). The
    source and the pilot's simulations are also set on ``budget.epsilon_initial``.
    """
    if settings.epsilon_initial is not None:
        budget.epsilon_initial = ("given", 0)
        return float(settings.epsilon_initial), "given", 0
    size = settings.pilot_size or settings.particles
    before = budget.n_simulations
    pilot = fill(
        prior_proposer(models), size, np.inf, executor, budget,
        seed=seed, t=0, batch_size=settings.batch_size, accept_all=True,
    )
    eps = float(np.quantile(pilot.distances, settings.pilot_quantile, method="higher"))
    source = "pilot"
    if not np.isfinite(eps):
        # more than 1 - q of the prior's simulations failed or diverged (wide priors): the
        # quantile of those that did not; the failures stay counted rejections
        finite = pilot.distances[np.isfinite(pilot.distances)]
        if finite.size == 0:
            raise Stopped(StopReason.PILOT_FAILED)
        eps, source = float(np.quantile(finite, settings.pilot_quantile, method="higher")), "pilot_finite"
    budget.epsilon_initial = (source, budget.n_simulations - before)
    return eps, source, budget.n_simulations - before


def uniform_weights(model_index: np.ndarray, n_models: int) -> np.ndarray:
    counts = np.bincount(model_index, minlength=n_models)
    return 1.0 / counts[model_index]


def population_from(
    t: int, epsilon: float, epsilon_next: float, models: np.ndarray, theta: np.ndarray,
    distances: np.ndarray, weights: np.ndarray, filled: Filled, elapsed_s: float,
    model_probabilities: np.ndarray, **extra,
) -> Population:
    n_models = np.shape(model_probabilities)[0]
    return Population(
        t=t, epsilon=epsilon, epsilon_next=epsilon_next, models=models, theta=theta,
        distances=distances, weights=weights, n_accepted=int(filled.models.shape[0]),
        n_simulations=filled.n_simulations, n_failed=filled.n_failed, n_redraws=filled.n_redraws,
        elapsed_s=elapsed_s, model_probabilities=model_probabilities,
        n_simulations_by_model=filled.counts(n_models)[0], n_failed_by_model=filled.failures(n_models), **extra,
    )


def abc_rejection(
    models: Sequence[Model],
    executor: Executor,
    settings: RejectionSettings = RejectionSettings(),
    stop: StopRules = StopRules(max_populations=1),
    seed: int = 0,
    *,
    history: Sequence[Population] = (),
    budget: Budget | None = None,
    clock: Callable[[], float] = time.monotonic,
    cancel: Callable[[], bool] | None = None,
) -> Generator[Population, None, RunEnd]:
    """Algorithm 1: N particles from the priors with distance below epsilon; one population."""
    settings.check_particles(models)
    budget = budget or Budget(stop, clock, cancel)
    source, n_pilot = "given", 0
    if history:  # the one population is done
        return RunEnd(StopReason.COMPLETED, budget.n_simulations, 0, "resumed")
    try:
        eps, source, n_pilot = initial_epsilon(models, settings, executor, budget, seed)
        filled = fill(prior_proposer(models), settings.particles, eps, executor, budget,
                      seed=seed, t=1, batch_size=settings.batch_size)
    except Stopped as stopped:
        return RunEnd(stopped.reason, budget.n_simulations, n_pilot, source, stopped.notes)
    counts = np.bincount(filled.models, minlength=len(models))
    yield population_from(
        1, eps, eps, filled.models, filled.theta, filled.distances,
        uniform_weights(filled.models, len(models)), filled, budget.elapsed(), counts / counts.sum(),
    )
    return RunEnd(StopReason.COMPLETED, budget.n_simulations, n_pilot, source)
