"""Filling a population: draws out, results consumed in submission order.

Shared by ABC-NS, ABC-SMC and rejection. Batch ``b`` of population ``t`` is a
:class:`abcns.executor.Draw` seeded by ``SeedSequence(seed, spawn_key=(t, b))`` (``b >= 1``;
``b = 0`` is kept for population-level draws such as the survivor selection; the pilot
is population 0); the executor draws its proposals and simulates them where it runs.
Particles are accepted in batch order and, within a batch, in row order, until the
population is full, so the accepted set and every counter are exactly those of a serial
one-at-a-time run over the same random stream, whatever the executor.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from abcns.executor import OK, Draw, Executor, Propose
from abcns.settings import Stopped, StopReason, StopRules

__all__ = ["Budget", "Filled", "Filling", "Propose", "Stopped", "draw_inside", "draws", "fill", "population_rng"]


def population_rng(seed: int, t: int) -> np.random.Generator:
    """The generator for population-level draws of population ``t`` (batch index 0)."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(t, 0)))


def draw_inside(
    draw: Callable[[int, np.random.Generator], np.ndarray],
    inside: Callable[[np.ndarray], np.ndarray],
    n: int,
    rng: np.random.Generator,
    max_redraws: int,
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points from ``draw`` that satisfy ``inside`` (the prior box), drawn in chunks.

    Returns (points (n, d), redraws (n,)), where ``redraws[i]`` is the number of rejected
    draws before point i in the draw sequence, exactly what a one-at-a-time loop counts.
    Raises Stopped(PROPOSAL_EXHAUSTED) after ``max_redraws * n + 10_000`` draws.
    """
    got: list[np.ndarray] = []
    gaps: list[np.ndarray] = []
    n_got = n_drawn = since_last = 0
    while n_got < n:
        chunk = max(2 * (n - n_got), 64)
        draws = draw(chunk, rng)
        ok = np.flatnonzero(inside(draws))[: n - n_got]
        if ok.size:
            gap = np.empty_like(ok)  # draws rejected before each accepted one
            gap[0] = ok[0] + since_last
            np.subtract(ok[1:], ok[:-1] + 1, out=gap[1:])
            gaps.append(gap)
            got.append(draws[ok])
            n_got += ok.size
            since_last = chunk - ok[-1] - 1
        else:
            since_last += chunk
        n_drawn += chunk
        if n_got < n and n_drawn > max_redraws * n + 10_000:
            raise Stopped(StopReason.PROPOSAL_EXHAUSTED)
    return np.concatenate(got), np.concatenate(gaps)


class Budget:
    """Simulation, time and cancel budgets of a run, checked between batches (and by an
    executor that runs ahead while it waits for a batch: ``service.run.dask_executor``)."""

    def __init__(
        self,
        stop: StopRules,
        clock: Callable[[], float] = time.monotonic,
        cancel: Callable[[], bool] | None = None,
        n_simulations: int = 0,
        elapsed_before_s: float = 0.0,
    ):
        self.stop = stop
        self.clock = clock
        self.cancel = cancel
        self.n_simulations = n_simulations
        self.start = clock() - elapsed_before_s
        #: where epsilon_1 came from and the pilot's simulations, once the run knows
        #: (``abcns.rejection.initial_epsilon`` sets it): the runner stores it with population
        #: 1, so that a run resumed later still says it
        self.epsilon_initial: tuple[str, int] | None = None

    def elapsed(self) -> float:
        return self.clock() - self.start

    def simulations_left(self) -> int | None:
        if self.stop.max_simulations is None:
            return None
        return max(0, self.stop.max_simulations - self.n_simulations)

    def seconds_left(self) -> float | None:
        if self.stop.max_seconds is None:
            return None
        return max(0.0, self.stop.max_seconds - self.elapsed())

    def reason(self) -> StopReason | None:
        """Why the run must stop now (a budget spent, or cancelled), or None."""
        if self.cancel is not None and self.cancel():
            return StopReason.CANCELLED
        left = self.simulations_left()
        if left is not None and left <= 0:
            return StopReason.MAX_SIMULATIONS
        if self.stop.max_seconds is not None and self.elapsed() >= self.stop.max_seconds:
            return StopReason.MAX_SECONDS
        return None

    def check(self) -> None:
        """Raise Stopped when a budget is spent or the run was cancelled."""
        if (reason := self.reason()) is not None:
            raise Stopped(reason)


@dataclass(frozen=True, eq=False)
class Filled:
    """Accepted particles in acceptance order, and what it took to get them."""

    models: np.ndarray
    theta: np.ndarray
    distances: np.ndarray
    n_simulations: int
    n_failed: int
    n_redraws: int
    simulated_models: np.ndarray  # (n_simulations,) the model of every simulation counted
    failed_models: np.ndarray  # (n_failed,) the model of every simulation that failed or diverged

    def counts(self, n_models: int) -> tuple[np.ndarray, np.ndarray]:
        """(simulations, accepted particles) per model."""
        return (np.bincount(self.simulated_models, minlength=n_models),
                np.bincount(self.models, minlength=n_models))

    def failures(self, n_models: int) -> np.ndarray:
        """Simulations that failed or diverged, per model."""
        return np.bincount(self.failed_models, minlength=n_models)


def draws(propose: Propose, *, seed: int, t: int, epsilon: float, batch_size: int,
          keep_all: bool = False) -> Iterator[Draw]:
    """The endless stream of population ``t``'s draws, batch indices 1, 2, ..."""
    for b in itertools.count(1):
        yield Draw(t, b, batch_size, float(epsilon), seed, propose, keep_all)


class Filling:
    """A population being filled: ``executor.map`` is called when this is made, so an executor
    that runs draws ahead (Dask) starts simulating while the caller finishes other work;
    :meth:`finish` consumes the results in submission order. Nothing is consumed, and no
    budget checked, before :meth:`finish`; :meth:`close` drops the stream unconsumed."""

    def __init__(self, propose: Propose, n_needed: int, epsilon: float, executor: Executor, *,
                 seed: int, t: int, batch_size: int, accept_all: bool = False):
        self.n_needed, self.epsilon, self.accept_all, self.t = n_needed, epsilon, accept_all, t
        self.results = executor.map(draws(propose, seed=seed, t=t, epsilon=epsilon, batch_size=batch_size,
                                          keep_all=accept_all))
        self.expect = getattr(self.results, "expect", None)  # an executor that runs ahead takes hints:
        if self.expect is not None:  # this many batches were every simulation kept (exactly, with accept_all)
            self.expect(n_needed / batch_size, at_least=not accept_all)

    def close(self) -> None:
        close = getattr(self.results, "close", None)
        if close is not None:
            close()

    def finish(self, budget: Budget) -> Filled:
        """Run batches until ``n_needed`` particles have distance < ``epsilon``.

        With ``accept_all`` every simulation is kept, failed ones too (the pilot). Budgets are
        checked before each batch is consumed and the simulation budget per simulation; on a
        stop, :class:`Stopped` is raised after the simulations done are added to
        ``budget.n_simulations``. The stream is closed on return (surplus cancelled).
        """
        n_needed, epsilon = self.n_needed, self.epsilon
        kept: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        simulated: list[np.ndarray] = []
        failed: list[np.ndarray] = []
        n_kept = n_sims = n_failed = n_redraws = n_batches = 0
        try:
            budget.check()
            for batch in self.results:  # in submission order
                if batch.stop is not None:
                    raise Stopped(batch.stop)
                ok = batch.status == OK
                accept = batch.kept(epsilon, self.accept_all)
                # the row at which this batch completes the population, if it does
                cum = np.cumsum(accept)
                n_rows = min(len(batch), int(np.searchsorted(cum, n_needed - n_kept)) + 1)
                left = budget.simulations_left()
                if cut := (left is not None and left < n_rows):
                    n_rows = left
                rows = slice(0, n_rows)
                take = np.flatnonzero(accept[rows])  # a prefix of the kept rows, whose theta the batch holds
                kept.append((batch.models[take], batch.theta[: take.size], batch.distances[take]))
                simulated.append(batch.models[rows])
                n_kept += take.size
                n_sims += n_rows
                failed.append(batch.models[rows][~ok[rows]])
                n_failed += failed[-1].size
                n_redraws += int(batch.redraws[rows].sum())
                budget.n_simulations += n_rows
                if n_kept >= n_needed:
                    break
                if cut:
                    raise Stopped(StopReason.MAX_SIMULATIONS)
                self._check_acceptance(n_kept, n_sims, budget.stop)
                n_batches += 1
                if self.expect is not None:  # batches still needed at this population's acceptance so far
                    self.expect((n_needed - n_kept) * n_batches / max(n_kept, 0.5))
                budget.check()
        finally:
            self.close()
        models, theta, distances = (np.concatenate(parts) for parts in zip(*kept, strict=True))
        return Filled(models, theta, distances, n_sims, n_failed, n_redraws, np.concatenate(simulated),
                      np.concatenate(failed))

    def _check_acceptance(self, n_kept: int, n_sims: int, stop: StopRules) -> None:
        """Stop (NOTHING_ACCEPTED, with the sentence that says why) when this population has
        run ``stop.max_simulations_without_acceptance`` simulations and kept none (checked
        after each batch, so where it stops depends on the batch size alone)."""
        limit = stop.max_simulations_without_acceptance
        if limit is not None and n_kept == 0 and n_sims >= limit:
            raise Stopped(StopReason.NOTHING_ACCEPTED, (
                f"nothing accepted: population {self.t} ran {n_sims:,} simulations and none came below the tolerance "
                f"{self.epsilon:.4g} (stop.max_simulations_without_acceptance: {limit:,}); the models, their priors "
                "and the data cannot meet there: check the data's units and sampling rate, the masses and the priors"))


def fill(
    propose: Propose,
    n_needed: int,
    epsilon: float,
    executor: Executor,
    budget: Budget,
    *,
    seed: int,
    t: int,
    batch_size: int,
    accept_all: bool = False,
) -> Filled:
    """Fill a population now (:class:`Filling`, made and finished): run batches until
    ``n_needed`` particles have distance < ``epsilon``."""
    budget.check()
    return Filling(propose, n_needed, epsilon, executor, seed=seed, t=t, batch_size=batch_size,
                   accept_all=accept_all).finish(budget)
