"""ABC-SMC baseline (Toni et al. 2009) with Beaumont's Gaussian perturbation kernel.

Population 1 is ABC rejection at eps_1. At t >= 2 a proposal draws a model m from the
previous model probabilities, a particle of m by its weight, and perturbs it with a
Gaussian of covariance twice the weighted covariance of m's particles (Beaumont et al.
2009), redrawn until inside the prior box. An accepted particle's weight is
``pi(m) pi(theta | m) / (p_{t-1}(m) sum_j w_j N(theta; theta_j, Sigma_m))`` (importance
weight on the joint (m, theta)); model probabilities are the weight mass per model and
stored weights are normalised within each model. Dead models (p = 0) stay dead.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.special import logsumexp

from abcns.executor import Executor
from abcns.filling import Budget, Stopped, draw_inside, fill
from abcns.priors import Model
from abcns.rejection import initial_epsilon, pad, population_from, prior_proposer, uniform_weights
from abcns.result import Population, RunEnd
from abcns.settings import SMCSettings, StopReason, StopRules


class Kernel:
    """Gaussian mixture kernel of one model: components at its particles."""

    def __init__(self, model: Model, theta: np.ndarray, weights: np.ndarray):
        self.model = model
        self.theta = theta
        self.weights = weights / weights.sum()
        mean = self.weights @ theta
        centred = theta - mean
        cov = 2.0 * (centred.T * self.weights) @ centred
        floor = (1e-6 * (model.high - model.low)) ** 2  # one particle, or collinear ones
        cov = cov + np.diag(floor)
        self.chol = np.linalg.cholesky(cov)
        self.log_norm = -0.5 * model.n_dim * np.log(2 * np.pi) - np.sum(np.log(np.diag(self.chol)))

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        j = rng.choice(self.theta.shape[0], size=n, p=self.weights)
        return self.theta[j] + rng.standard_normal((n, self.model.n_dim)) @ self.chol.T

    def log_density(self, x: np.ndarray) -> np.ndarray:
        """log sum_j w_j N(x; theta_j, Sigma), x (n, d) -> (n,)."""
        diff = x[:, None, :] - self.theta[None, :, :]  # (n, J, d)
        z = np.linalg.solve(self.chol, diff.reshape(-1, self.model.n_dim).T).T.reshape(diff.shape)
        log_k = self.log_norm - 0.5 * np.sum(z * z, axis=2)
        return logsumexp(log_k, b=self.weights[None, :], axis=1)


@dataclass(frozen=True, eq=False)
class KernelProposer:
    """Each proposal picks a model by ``p_model``, then a point from its kernel (a weighted
    particle perturbed by a Gaussian), redrawn until inside the prior box."""

    models: tuple[Model, ...]
    p_model: np.ndarray
    kernels: tuple[Kernel | None, ...]
    max_redraws: int

    def __call__(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        which = rng.choice(len(self.models), size=n, p=self.p_model).astype(np.int16)
        theta = pad(self.models, n)
        redraws = np.zeros(n, dtype=np.int64)
        for m, model in enumerate(self.models):
            rows = np.flatnonzero(which == m)
            if rows.size:
                kernel = self.kernels[m]
                assert kernel is not None  # drawn, so p_model[m] > 0
                theta[rows, : model.n_dim], redraws[rows] = draw_inside(
                    kernel.sample, model.in_prior, rows.size, rng, self.max_redraws
                )
        return which, theta, redraws


def abc_smc(
    models: Sequence[Model],
    executor: Executor,
    settings: SMCSettings = SMCSettings(),
    stop: StopRules = StopRules(),
    seed: int = 0,
    *,
    history: Sequence[Population] = (),
    budget: Budget | None = None,
    clock: Callable[[], float] = time.monotonic,
    cancel: Callable[[], bool] | None = None,
) -> Generator[Population, None, RunEnd]:
    """Yield ABC-SMC populations until a stop rule holds or the schedule ends.
    ``history`` and ``budget`` resume a run, as for :func:`abcns.nested.abc_ns`."""
    settings.check_particles(models)
    n_models = len(models)
    budget = budget or Budget(stop, clock, cancel)
    schedule = settings.schedule
    source, n_pilot = ("resumed" if history else "schedule"), 0

    def next_eps(pop: Population) -> float:
        if schedule is not None:
            return schedule[pop.t] if pop.t < len(schedule) else np.nan
        return float(np.quantile(pop.distances, settings.quantile))

    try:
        if history:
            pop = history[-1]
        else:
            if schedule is not None:
                eps = schedule[0]
            else:
                eps, source, n_pilot = initial_epsilon(models, settings, executor, budget, seed)
            filled = fill(prior_proposer(models), settings.particles, eps, executor, budget,
                          seed=seed, t=1, batch_size=settings.batch_size)
            counts = np.bincount(filled.models, minlength=n_models)
            pop = population_from(
                1, eps, np.nan, filled.models, filled.theta, filled.distances,
                uniform_weights(filled.models, n_models), filled, budget.elapsed(), counts / counts.sum(),
            )
            pop = _with_next(pop, next_eps(pop))
            yield pop
        while True:
            if schedule is not None and pop.t >= len(schedule):
                return RunEnd(StopReason.SCHEDULE_END, budget.n_simulations, n_pilot, source)
            reason = stop.reason_after(pop.epsilon, pop.epsilon_next, pop.t, decrease=schedule is None)
            if reason is not None:
                return RunEnd(reason, budget.n_simulations, n_pilot, source)
            budget.check()
            p_model = pop.model_probabilities
            kernels = [
                Kernel(model, pop.theta[pop.models == m, : model.n_dim], pop.weights[pop.models == m])
                if p_model[m] > 0 else None
                for m, model in enumerate(models)
            ]
            eps = pop.epsilon_next
            filled = fill(KernelProposer(tuple(models), p_model, tuple(kernels), settings.max_redraws),
                          settings.particles, eps, executor, budget,
                          seed=seed, t=pop.t + 1, batch_size=settings.batch_size)
            log_w = np.empty(filled.models.shape[0])
            for m, model in enumerate(models):
                rows = np.flatnonzero(filled.models == m)
                if rows.size:
                    kernel = kernels[m]
                    assert kernel is not None  # proposed, so p_model[m] > 0
                    x = filled.theta[rows, : model.n_dim]
                    log_w[rows] = (-np.log(n_models) - model.log_prior_volume()
                                   - np.log(p_model[m]) - kernel.log_density(x))
            w = np.exp(log_w - log_w.max())
            mass = np.bincount(filled.models, weights=w, minlength=n_models)
            norm_w = w / mass[filled.models]
            pop = population_from(
                pop.t + 1, eps, np.nan, filled.models, filled.theta, filled.distances, norm_w,
                filled, budget.elapsed(), mass / mass.sum(),
            )
            pop = _with_next(pop, next_eps(pop))
            yield pop
    except Stopped as stopped:
        return RunEnd(stopped.reason, budget.n_simulations, n_pilot, source, stopped.notes)


def _with_next(pop: Population, eps_next: float) -> Population:
    return replace(pop, epsilon_next=float(eps_next))
