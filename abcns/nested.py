"""ABC-NS (paper Algorithm 2) with joint model selection over models of any dimension.

One population t holds N particles accepted below eps_t. Finishing it (a pure function of
the particles and a generator) gives:

1. eps_{t+1} = the (alpha N)-th largest distance (steps 10-11, 27);
2. weights (step 9/28): zero for e >= eps_{t+1}; otherwise ``(1/e)(1 - (e/eps_t)^2)``
   ("paper") or ``(1/eps_t)(1 - (e/eps_t)^2)`` ("kernel", the authors' demo);
3. survivors (step 14/29): per model ``round(beta N * n_model / N)`` by largest remainder
   (so they add up to beta N), drawn by weight without replacement from the model's
   positive-weight particles; a model short of them gives its shortfall to the others;
4. one ellipsoid per model with survivors (steps 15-16, 30): mean and covariance of the
   survivors, scaled to hold them all, matrix times f0 (see ``abcns.ellipsoid`` for the
   repair of degenerate covariances and the rule for fewer than d + 1 survivors).

Population t + 1 = the survivors plus (1 - beta) N new particles: each proposal picks a
model with survivors with equal probability, then a point uniform in its ellipsoid,
redrawn until inside the prior box (redraws are counted, not simulated). A model with no
survivors has no particles from then on: it is dead and stays dead. Model probabilities
are particle shares (Eq. 12).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Generator, Sequence

import numpy as np

from abcns import ellipsoid as ell
from abcns.executor import Executor
from abcns.filling import Budget, Propose, Stopped, draw_inside, fill, population_rng
from abcns.priors import Model
from abcns.rejection import initial_epsilon, pad, population_from, prior_proposer
from abcns.result import Population, RunEnd
from abcns.settings import NSSettings, StopReason, StopRules


def apportion(total: int, shares: np.ndarray) -> np.ndarray:
    """Split ``total`` into integers proportional to ``shares`` (largest remainder)."""
    shares = np.asarray(shares, dtype=float)
    if total <= 0 or shares.sum() <= 0:
        return np.zeros(shares.shape, dtype=np.int64)
    exact = total * shares / shares.sum()
    base = np.floor(exact).astype(np.int64)
    remainder = total - int(base.sum())
    order = np.argsort(-(exact - base), kind="stable")
    base[order[:remainder]] += 1
    return base


def survivor_quotas(total: int, counts: np.ndarray, capacity: np.ndarray) -> np.ndarray:
    """Survivors per model: proportional to particle counts, capped by each model's
    positive-weight particles, shortfalls passed on to models with room left."""
    total = min(total, int(capacity.sum()))
    quota = np.minimum(apportion(total, counts), capacity)
    while quota.sum() < total:
        room = capacity - quota
        extra = apportion(total - int(quota.sum()), np.where(room > 0, counts + 1e-12, 0.0))
        quota = np.minimum(quota + extra, capacity)
    return quota


def ns_weights(distances: np.ndarray, epsilon: float, epsilon_next: float, form: str) -> np.ndarray:
    """Unnormalised survivor-selection weights (zero for e >= eps_next)."""
    kernel = 1.0 - (distances / epsilon) ** 2
    if form == "paper":
        w = kernel / np.maximum(distances, epsilon * 1e-12)  # an exact match (e = 0) stays finite
    else:
        w = kernel / epsilon
    return np.where((distances < epsilon_next) & (kernel > 0), w, 0.0)


def finish_population(
    models: Sequence[Model],
    t: int,
    epsilon: float,
    which: np.ndarray,
    theta: np.ndarray,
    distances: np.ndarray,
    previous: Sequence[ell.Ellipsoid | None],
    settings: NSSettings,
    rng: np.random.Generator,
) -> tuple[float, np.ndarray, np.ndarray, tuple[ell.Ellipsoid | None, ...], list[str]]:
    """(eps_next, weights normalised per model, survivor mask, next ellipsoids, notes)."""
    n_models = len(models)
    eps_next = float(np.sort(distances)[::-1][settings.n_drop - 1])
    raw = ns_weights(distances, epsilon, eps_next, settings.weights)
    counts = np.bincount(which, minlength=n_models)
    capacity = np.bincount(which, weights=raw > 0, minlength=n_models).astype(np.int64)
    quotas = survivor_quotas(settings.n_survivors, counts, capacity)
    notes = []
    if quotas.sum() < settings.n_survivors:
        notes.append(f"population {t}: only {quotas.sum()} particles below eps_next (ties); fewer survivors")
    weights = np.zeros_like(raw)
    survivors = np.zeros(which.shape[0], dtype=bool)
    ellipsoids: list[ell.Ellipsoid | None] = []
    for m, model in enumerate(models):
        rows = np.flatnonzero((which == m) & (raw > 0))
        if rows.size:
            weights[rows] = raw[rows] / raw[rows].sum()
        if quotas[m] == 0:
            ellipsoids.append(None)
            continue
        keep = rng.choice(rows, size=int(quotas[m]), replace=False, p=weights[rows])
        survivors[keep] = True
        prev = previous[m] if previous[m] is not None else ell.from_box(model.low, model.high)
        fallback = ell.from_matrix(prev.centre, prev.matrix / (settings.enlargement if prev.note != "box" else 1.0))
        fitted = ell.fit(theta[np.sort(keep), : model.n_dim], fallback=fallback)
        if fitted.note:
            notes.append(f"population {t}: ellipsoid of {model.name} {fitted.note} ({quotas[m]} survivors)")
        ellipsoids.append(ell.enlarge(fitted, settings.enlargement))
    return eps_next, weights, survivors, tuple(ellipsoids), notes


def ellipsoid_proposer(models: Sequence[Model], ellipsoids: Sequence[ell.Ellipsoid | None], max_redraws: int) -> Propose:
    """Equal-probability choice among models with an ellipsoid, uniform point inside it,
    redrawn until inside the prior box. ``redraws[i]`` is the number of out-of-box draws
    before proposal i, exactly as a one-at-a-time loop would count them."""
    alive = [m for m, e in enumerate(ellipsoids) if e is not None]

    def propose(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        which = np.asarray(alive, dtype=np.int16)[rng.integers(len(alive), size=n)]
        theta = pad(models, n)
        redraws = np.zeros(n, dtype=np.int64)
        for m in alive:
            rows = np.flatnonzero(which == m)
            if rows.size == 0:
                continue
            model, e = models[m], ellipsoids[m]
            theta[rows, : model.n_dim], redraws[rows] = draw_inside(
                lambda k, g, e=e: ell.sample(e, k, g), model.in_prior, rows.size, rng, max_redraws
            )
        return which, theta, redraws

    return propose


def abc_ns(
    models: Sequence[Model],
    executor: Executor,
    settings: NSSettings = NSSettings(),
    stop: StopRules = StopRules(),
    seed: int = 0,
    *,
    history: Sequence[Population] = (),
    budget: Budget | None = None,
    clock: Callable[[], float] = time.monotonic,
    cancel: Callable[[], bool] | None = None,
) -> Generator[Population, None, RunEnd]:
    """Yield ABC-NS populations until a stop rule holds; return a :class:`RunEnd`.

    ``history`` resumes a run: the populations already done (at least the last one);
    ``budget`` then carries the simulations and seconds already spent.
    """
    settings.check_models(models)
    n_models = len(models)
    budget = budget or Budget(stop, clock, cancel)
    source, n_pilot, notes = "resumed" if history else "given", 0, []

    def end(reason: StopReason) -> RunEnd:
        return RunEnd(reason, budget.n_simulations, n_pilot, source, tuple(notes))

    def complete(t, eps, which, theta, distances, filled, previous) -> Population:
        eps_next, weights, survivors, ellipsoids, more = finish_population(
            models, t, eps, which, theta, distances, previous, settings, population_rng(seed, t)
        )
        notes.extend(more)
        counts = np.bincount(which, minlength=n_models)
        return population_from(
            t, eps, eps_next, which, theta, distances, weights, filled, budget.elapsed(),
            counts / counts.sum(), survivors=survivors, ellipsoids=ellipsoids,
        )

    def stop_after(pop: Population) -> StopReason | None:
        if stop.epsilon_target is not None and pop.epsilon <= stop.epsilon_target:
            return StopReason.EPSILON_TARGET
        if stop.min_epsilon_decrease is not None and pop.epsilon - pop.epsilon_next < stop.min_epsilon_decrease:
            return StopReason.MIN_EPSILON_DECREASE
        if stop.max_populations is not None and pop.t >= stop.max_populations:
            return StopReason.MAX_POPULATIONS
        return None

    try:
        if history:
            pop = history[-1]
        else:
            eps, source, n_pilot = initial_epsilon(models, settings, executor, budget, seed)
            filled = fill(prior_proposer(models), settings.particles, eps, executor, budget,
                          seed=seed, t=1, batch_size=settings.batch_size)
            pop = complete(1, eps, filled.models, filled.theta, filled.distances, filled, [None] * n_models)
            yield pop
        while (reason := stop_after(pop)) is None:
            budget.check()
            t, eps = pop.t + 1, pop.epsilon_next
            propose = ellipsoid_proposer(models, pop.ellipsoids, settings.max_redraws)
            filled = fill(propose, settings.n_new, eps, executor, budget,
                          seed=seed, t=t, batch_size=settings.batch_size)
            keep = np.flatnonzero(pop.survivors)
            pop = complete(
                t, eps,
                np.concatenate([pop.models[keep], filled.models]),
                np.concatenate([pop.theta[keep], filled.theta]),
                np.concatenate([pop.distances[keep], filled.distances]),
                filled, pop.ellipsoids,
            )
            yield pop
    except Stopped as stopped:
        return end(stopped.reason)
    return end(reason)
