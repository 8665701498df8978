"""Batches of proposals, their evaluation, and the executor protocol.

An executor takes an iterable of :class:`Batch` and yields one :class:`Evaluated` per
batch **in submission order** (never in completion order: simulation cost depends on
the parameters, so taking whatever finishes first biases the posterior). The caller
pulls lazily and closes the iterator when it has enough; an executor that runs batches
ahead cancels the surplus on close. :class:`SerialExecutor` is the in-process reference;
the Dask executor lives in ``service/`` behind the same protocol.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Literal, Protocol, cast, overload

import numpy as np

#: simulation status codes
OK, DIVERGED, FAILED = 0, 1, 2
STATUS_NAMES = {OK: "ok", DIVERGED: "diverged", FAILED: "failed"}


@dataclass(frozen=True, eq=False)
class Batch:
    """Proposals to simulate.

    ``theta`` is (n, d_max), each row padded with NaN beyond its model's dimension.
    ``seed`` seeds any randomness of the simulation itself (stochastic simulators); it is
    derived from (job seed, population, batch index), so re-running a batch anywhere gives
    the same answer. ``epsilon`` is the acceptance tolerance (a simulator may stop early
    once a particle cannot be accepted). ``redraws`` counts the prior-bound redraws each
    proposal needed (bookkeeping, not simulations).
    """

    population: int
    index: int
    models: np.ndarray  # (n,) int
    theta: np.ndarray  # (n, d_max) float
    epsilon: float
    seed: np.random.SeedSequence
    redraws: np.ndarray  # (n,) int

    def __len__(self) -> int:
        return int(self.models.shape[0])


@dataclass(frozen=True, eq=False)
class Evaluated:
    """Distances (+inf when not OK) and status codes, one per proposal of a batch."""

    distances: np.ndarray  # (n,) float
    status: np.ndarray  # (n,) int8


Evaluate = Callable[[Batch], Evaluated]


class Executor(Protocol):
    def map(self, batches: Iterable[Batch]) -> Iterator[Evaluated]:
        """Evaluate batches; yield results in submission order; cancel surplus on close()."""
        ...


class BatchError(RuntimeError):
    """An unexpected exception while a batch was evaluated (a bug in a simulator, not a
    numerical failure, which is a counted rejection): the message names the batch
    (population, index) and the exception's type."""


def evaluate_batch(evaluate: Evaluate, batch: Batch) -> Evaluated:
    """``evaluate(batch)``, with an unexpected exception turned into a BatchError naming the batch."""
    try:
        return evaluate(batch)
    except Exception as err:
        raise BatchError(f"population {batch.population}, batch {batch.index}: {type(err).__name__}: {err}") from err


class SerialExecutor:
    """Evaluate one batch at a time in this process."""

    def __init__(self, evaluate: Evaluate):
        self.evaluate = evaluate

    def map(self, batches: Iterable[Batch]) -> Iterator[Evaluated]:
        for batch in batches:
            yield evaluate_batch(self.evaluate, batch)


SimulateDistance = Callable[[np.ndarray, np.random.Generator], tuple[np.ndarray, np.ndarray]]


class SimulateDistanceEpsilon(Protocol):
    """A :data:`SimulateDistance` that also takes the batch's tolerance as ``epsilon=``."""

    def __call__(self, theta: np.ndarray, rng: np.random.Generator, /,
                 epsilon: float = ...) -> tuple[np.ndarray, np.ndarray]: ...


@overload
def per_model(functions: Sequence[SimulateDistance], pass_epsilon: Literal[False] = False) -> Evaluate: ...
@overload
def per_model(functions: Sequence[SimulateDistanceEpsilon], pass_epsilon: bool) -> Evaluate: ...
def per_model(functions: Sequence[SimulateDistance] | Sequence[SimulateDistanceEpsilon],
              pass_epsilon: bool = False) -> Evaluate:
    """Make a batch evaluator from one function per model.

    ``functions[m](theta, rng) -> (distances, status)`` receives the rows of model ``m``
    without padding, shape (n_m, d_m); with ``pass_epsilon`` it is called as
    ``functions[m](theta, rng, epsilon=batch.epsilon)`` (for early rejection). One generator
    seeded from ``batch.seed`` is used for
    the models in index order. A numerical error raised by a function (``ArithmeticError``,
    ``ValueError``, ``LinAlgError``) marks its rows FAILED; anything else is a bug and
    propagates.
    """

    def evaluate(batch: Batch) -> Evaluated:
        rng = np.random.default_rng(batch.seed)
        distances = np.full(len(batch), np.inf)
        status = np.full(len(batch), FAILED, dtype=np.int8)
        for m in np.unique(batch.models):
            rows = np.flatnonzero(batch.models == m)
            theta = batch.theta[rows]
            theta = theta[:, ~np.all(np.isnan(theta), axis=0)]
            try:
                if pass_epsilon:
                    # only the second overload passes True: these functions take epsilon
                    f_eps = cast("SimulateDistanceEpsilon", functions[int(m)])
                    d, s = f_eps(theta, rng, epsilon=batch.epsilon)
                else:
                    d, s = functions[int(m)](theta, rng)
            except (ArithmeticError, ValueError, np.linalg.LinAlgError):
                continue  # rows stay FAILED with distance +inf
            distances[rows] = d
            status[rows] = s
        status[(status == OK) & ~np.isfinite(distances)] = FAILED
        distances[status != OK] = np.inf
        return Evaluated(distances, status)

    return evaluate
