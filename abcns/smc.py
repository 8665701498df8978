"""ABC-SMC baseline (Toni et al. 2009) with Beaumont's Gaussian perturbation kernel.

Population 1 is ABC rejection at eps_1. At t >= 2 a proposal draws a model m from the
previous model probabilities, a particle of m by its weight, and perturbs it with a
Gaussian of covariance twice the weighted covariance of m's particles (Beaumont et al.
2009), redrawn until inside the prior box. The redraws truncate the kernel to the box, so
m's proposal density is ``K_m(theta) / M_m`` inside it, ``K_m(theta) = sum_j w_j N(theta;
theta_j, Sigma_m)`` and ``M_m`` the kernel's mass inside the box. An accepted particle's
weight is ``pi(m) pi(theta | m) M_m / (p_{t-1}(m) K_m(theta))`` (importance weight on the
joint (m, theta)); model probabilities are the weight mass per model and stored weights are
normalised within each model. Dead models (p = 0) stay dead.

``M_m`` is a Monte Carlo estimate (:meth:`Kernel.box_mass`: the share of
:data:`BOX_MASS_DRAWS` kernel draws inside the box, from a generator of its own keyed by
(seed, t)). The mass of a Gaussian component in a box has a closed form only for a
diagonal covariance, and Beaumont's covariance is full; the estimate's relative standard
error ``sqrt((1 - M) / (M n))`` is at most 0.32 % for M >= 0.5, which moves a model
probability p by at most ``p (1 - p)`` times that. Leaving ``M_m`` out (as before) favoured
the model whose particles sit near its prior's bounds: U(0, 1) against U(-1, 1) on |x|,
exact p = 0.5, gave 0.52-0.58 (tests/test_closed_form.py).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import solve_triangular

from abcns.executor import Executor
from abcns.filling import Budget, Filled, Stopped, draw_inside, fill
from abcns.priors import Model
from abcns.rejection import initial_epsilon, pad, population_from, prior_proposer, uniform_weights
from abcns.result import Population, RunEnd
from abcns.settings import SMCSettings, StopReason, StopRules

#: kernel draws per model for its mass inside the prior box (:meth:`Kernel.box_mass`)
BOX_MASS_DRAWS = 100_000
#: elements of the (points, components, d) differences :meth:`Kernel.log_density` holds at once
DENSITY_CHUNK = 1 << 21


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
        """log sum_j w_j N(x; theta_j, Sigma), x (n, d) -> (n,); in chunks of rows of ``x``
        so at most :data:`DENSITY_CHUNK` differences are held at once (not n J d)."""
        n, (n_comp, d) = x.shape[0], self.theta.shape
        rows = max(1, DENSITY_CHUNK // max(1, n_comp * d))
        out = np.empty(n)
        for a in range(0, n, rows):
            diff = x[a : a + rows, None, :] - self.theta[None, :, :]  # (rows, J, d)
            z = solve_triangular(self.chol, diff.reshape(-1, d).T, lower=True).T.reshape(diff.shape)
            log_k = -0.5 * np.sum(z * z, axis=2)
            top = np.max(log_k, axis=1)
            out[a : a + rows] = self.log_norm + top + np.log(np.exp(log_k - top[:, None]) @ self.weights)
        return out

    def box_mass(self, n_draws: int, rng: np.random.Generator) -> float:
        """The kernel's mass inside the model's prior box: the share of ``n_draws`` draws
        that fall in it (at least one count, so a log stays finite)."""
        inside = int(np.count_nonzero(self.model.in_prior(self.sample(n_draws, rng))))
        return max(inside, 1) / n_draws


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


def _log_weights(models: Sequence[Model], filled: Filled, kernels: Sequence[Kernel | None], p_model: np.ndarray,
                 log_box_mass: Sequence[float]) -> np.ndarray:
    """Each new particle's log importance weight: prior over proposal density (the model's
    kernel, truncated to the prior box, times its share)."""
    n_models = len(models)
    log_w = np.empty(filled.models.shape[0])
    for m, model in enumerate(models):
        rows = np.flatnonzero(filled.models == m)
        if rows.size:
            kernel = kernels[m]
            assert kernel is not None  # proposed, so p_model[m] > 0
            x = filled.theta[rows, : model.n_dim]
            log_w[rows] = (-np.log(n_models) + model.log_prior_density(x) + log_box_mass[m]
                           - np.log(p_model[m]) - kernel.log_density(x))
    return log_w


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
            # the kernels' mass inside the prior boxes, from a stream of its own (population t + 1)
            mass_rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(pop.t + 1, 0, 2)))
            log_box_mass = [np.log(k.box_mass(BOX_MASS_DRAWS, mass_rng)) if k is not None else 0.0 for k in kernels]
            eps = pop.epsilon_next
            filled = fill(KernelProposer(tuple(models), p_model, tuple(kernels), settings.max_redraws),
                          settings.particles, eps, executor, budget,
                          seed=seed, t=pop.t + 1, batch_size=settings.batch_size)
            w = np.exp((log_w := _log_weights(models, filled, kernels, p_model, log_box_mass)) - log_w.max())
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
