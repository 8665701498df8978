"""Batches: how they are drawn, how they are evaluated, and the executor protocol.

A :class:`Draw` describes one batch: how many proposals, from which proposer, with which
seed (keyed by job seed, population and batch index, never by the cluster). Wherever it runs,
:func:`run_draw` draws the proposals (a :class:`Batch`), simulates them with the job's
evaluator and returns a :class:`Simulated`: the distances and statuses of every row, and the
parameters only of the rows that can be accepted. So proposals are made where the
simulations run (the runner ships a description of a few kilobytes, not the proposals), and
the result of a draw is the same in this process or on any worker.

An executor takes an iterable of :class:`Draw` and yields one :class:`Simulated` per draw
**in submission order** (never in completion order: simulation cost depends on the
parameters, so taking whatever finishes first biases the posterior). The caller pulls lazily
and closes the iterator when it has enough; an executor that runs draws ahead cancels the
surplus on close, and may take hints of how many results the caller still needs
(:meth:`Executor.map`). :class:`SerialExecutor` is the in-process reference; the Dask executor
lives in ``service/`` behind the same protocol.
"""

from __future__ import annotations

import pickle
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Literal, Protocol, cast, overload

import numpy as np

from abcns.settings import Stopped, StopReason

#: simulation status codes
OK, DIVERGED, FAILED = 0, 1, 2

# propose(n, rng) -> (models (n,), theta (n, d_max), redraws (n,)); picklable (a worker calls it)
Propose = Callable[[int, np.random.Generator], tuple[np.ndarray, np.ndarray, np.ndarray]]


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


@dataclass(frozen=True, eq=False)
class Draw:
    """One batch, described: ``size`` proposals from ``propose``, seeded by
    ``SeedSequence(seed, spawn_key=(population, index))``, whose two children seed the
    proposals and the simulations. ``keep_all``: every simulated row is kept with its
    parameters (the pilot), not only those with distance < ``epsilon``."""

    population: int
    index: int
    size: int
    epsilon: float
    seed: int
    propose: Propose
    keep_all: bool = False

    def seeds(self) -> tuple[np.random.SeedSequence, np.random.SeedSequence]:
        """(proposal seed, simulation seed): the children ``SeedSequence(seed, spawn_key=
        (t, b)).spawn(2)`` would give, built directly so a draw can be run twice."""
        key = (self.population, self.index)
        return (np.random.SeedSequence(self.seed, spawn_key=(*key, 0)),
                np.random.SeedSequence(self.seed, spawn_key=(*key, 1)))

    def batch(self) -> Batch:
        """The proposals (raises Stopped(PROPOSAL_EXHAUSTED) when a bound lies outside the prior)."""
        proposal_seed, simulation_seed = self.seeds()
        models, theta, redraws = self.propose(self.size, np.random.default_rng(proposal_seed))
        return Batch(self.population, self.index, models, theta, float(self.epsilon), simulation_seed, redraws)


def pack_draws(draws: Sequence[Draw]) -> bytes:
    """Draws as bytes, pickled in-band in one go (a proposer they share is written once).

    In-band, so the arrays of the proposer (ellipsoids, kernels) unpickle into fresh, aligned
    memory wherever the draws run: out-of-band buffers (pickle 5, as Dask sends them) land at
    any byte offset, and some numpy loops round differently on unaligned data."""
    fields = [(d.population, d.index, d.size, d.epsilon, d.seed, d.propose, d.keep_all) for d in draws]
    return pickle.dumps(fields, protocol=4)


def unpack_draws(data: bytes) -> list[Draw]:
    return [Draw(*fields) for fields in pickle.loads(data)]  # noqa: S301 - the runner's own bytes, never a user's


def pack_results(results: Sequence[Simulated]) -> bytes:
    """Results as bytes, pickled in-band (as :func:`pack_draws`: arrays land aligned)."""
    return pickle.dumps([(r.models, r.distances, r.status, r.redraws, r.theta, r.stop) for r in results], protocol=4)


def unpack_results(data: bytes) -> list[Simulated]:
    return [Simulated(*fields) for fields in pickle.loads(data)]  # noqa: S301 - a worker's bytes for this runner


@dataclass(frozen=True, eq=False)
class Simulated:
    """What the runner needs of a draw: per row the model, distance (+inf when not OK),
    status and prior-bound redraws; ``theta`` holds only the kept rows (OK with distance <
    epsilon, or every row with ``keep_all``), in row order. ``stop`` is set (and the arrays
    empty) when the proposals could not be drawn."""

    models: np.ndarray  # (n,) int16
    distances: np.ndarray  # (n,) float
    status: np.ndarray  # (n,) int8
    redraws: np.ndarray  # (n,) int64
    theta: np.ndarray  # (kept, d_max) float
    stop: StopReason | None = None

    def __len__(self) -> int:
        return int(self.models.shape[0])

    def kept(self, epsilon: float, keep_all: bool) -> np.ndarray:
        """(n,) bool: the rows whose parameters ``theta`` holds."""
        return kept_rows(self.status, self.distances, epsilon, keep_all)


def kept_rows(status: np.ndarray, distances: np.ndarray, epsilon: float, keep_all: bool) -> np.ndarray:
    """(n,) bool: OK rows with distance < epsilon, or every row with ``keep_all``."""
    if keep_all:
        return np.ones(status.shape[0], bool)
    return (status == OK) & (distances < epsilon)


def run_draw(evaluate: Evaluate, draw: Draw) -> Simulated:
    """Draw a batch's proposals, evaluate them, keep what the runner needs (in any process)."""
    try:
        batch = draw.batch()
    except Stopped as stopped:
        empty = np.zeros(0)
        return Simulated(empty.astype(np.int16), empty, empty.astype(np.int8), empty.astype(np.int64),
                         np.zeros((0, 0)), stopped.reason)
    evaluated = evaluate_batch(evaluate, batch)
    kept = kept_rows(evaluated.status, evaluated.distances, draw.epsilon, draw.keep_all)
    return Simulated(batch.models.astype(np.int16, copy=False), evaluated.distances, evaluated.status,
                     batch.redraws, batch.theta[kept])


class Executor(Protocol):
    def map(self, draws: Iterable[Draw]) -> Iterator[Simulated]:
        """Run draws (:func:`run_draw`); yield results in submission order; cancel surplus on
        close(). An executor that runs draws ahead may start when ``map`` is called, and its
        iterator may take hints: ``expect(batches, at_least=False)``, the number of results
        the caller expects to consume from now on (``abcns.filling`` calls it when it opens
        a population, with the bound that holds were every simulation kept, and after each
        batch, with an estimate from the acceptance so far). Hints change how far ahead the
        executor runs, never a result."""
        ...


class BatchError(RuntimeError):
    """An unexpected exception while a batch was evaluated (a bug in a simulator, not a
    numerical failure, which is a counted rejection): the message names the batch
    (population, index), the model (a :class:`SimulatorError`'s) and the exception's type."""


#: what a simulator may raise for a particle it cannot simulate: a counted rejection (status
#: FAILED) of that particle. ``numpy.linalg.LinAlgError`` subclasses ValueError, which is not
#: numerical (a shape bug in a plugin or a distance raises it too), hence named on its own.
NUMERICAL_ERRORS: tuple[type[Exception], ...] = (ArithmeticError, np.linalg.LinAlgError)


class SimulatorError(RuntimeError):
    """A model's simulator (or distance) raised an exception that is not numerical: a bug,
    which fails the job. The message names the model and the exception."""


def evaluate_batch(evaluate: Evaluate, batch: Batch) -> Evaluated:
    """``evaluate(batch)``, with an unexpected exception turned into a BatchError naming the batch."""
    try:
        return evaluate(batch)
    except Exception as err:
        what = str(err) if isinstance(err, SimulatorError) else f"{type(err).__name__}: {err}"  # it names the exception
        raise BatchError(f"population {batch.population}, batch {batch.index}: {what}") from err


class SerialExecutor:
    """Run one draw at a time in this process."""

    def __init__(self, evaluate: Evaluate):
        self.evaluate = evaluate

    def map(self, draws: Iterable[Draw]) -> Iterator[Simulated]:
        for draw in draws:
            yield run_draw(self.evaluate, draw)


SimulateDistance = Callable[[np.ndarray, np.random.Generator], tuple[np.ndarray, np.ndarray]]


class SimulateDistanceEpsilon(Protocol):
    """A :data:`SimulateDistance` that also takes the batch's tolerance as ``epsilon=``."""

    def __call__(self, theta: np.ndarray, rng: np.random.Generator, /,
                 epsilon: float = ...) -> tuple[np.ndarray, np.ndarray]: ...


@overload
def per_model(functions: Sequence[SimulateDistance], pass_epsilon: Literal[False] = False,
              names: Sequence[str] | None = None) -> Evaluate: ...
@overload
def per_model(functions: Sequence[SimulateDistanceEpsilon], pass_epsilon: bool,
              names: Sequence[str] | None = None) -> Evaluate: ...
def per_model(functions: Sequence[SimulateDistance] | Sequence[SimulateDistanceEpsilon],
              pass_epsilon: bool = False, names: Sequence[str] | None = None) -> Evaluate:
    """Make a batch evaluator from one function per model.

    ``functions[m](theta, rng) -> (distances, status)`` receives the rows of model ``m``
    without padding, shape (n_m, d_m); with ``pass_epsilon`` it is called as
    ``functions[m](theta, rng, epsilon=batch.epsilon)`` (for early rejection). One generator
    seeded from ``batch.seed`` is used for the models in index order; a function with the
    attribute ``uses_rng = False`` (it never draws a random number) is passed None instead,
    and the generator is made only for the first model that may use it.

    A failure belongs to its row. When a function raises a numerical error
    (:data:`NUMERICAL_ERRORS`: ``ArithmeticError``, i.e. ZeroDivisionError, OverflowError,
    FloatingPointError, and ``numpy.linalg.LinAlgError``), its rows are evaluated again one
    at a time, row ``r`` with a generator of its own (``SeedSequence(entropy, spawn_key=
    batch.seed.spawn_key + (m, r))``), and only the rows that raise again are FAILED (distance
    +inf): a row's fate never depends on its batch-mates. Any other exception is a bug (a
    shape mistake in a plugin or a distance raises ValueError, for one) and raises
    :class:`SimulatorError` naming the model (``names[m]``, default ``model m``) and the
    exception. A status the function sets (DIVERGED, FAILED) is a rejection as well.
    """

    def label(m: int) -> str:
        return names[m] if names is not None else f"model {m}"

    def call(m: int, theta: np.ndarray, rng: np.random.Generator, epsilon: float) -> tuple[np.ndarray, np.ndarray]:
        try:
            if pass_epsilon:
                # only the second overload passes True: these functions take epsilon
                f_eps = cast("SimulateDistanceEpsilon", functions[m])
                return f_eps(theta, rng, epsilon=epsilon)
            return functions[m](theta, rng)
        except NUMERICAL_ERRORS:
            raise
        except Exception as err:
            where = f" at {np.array2string(theta[0], precision=6)}" if theta.shape[0] == 1 else ""
            raise SimulatorError(f"{label(m)}{where}: {type(err).__name__}: {err}") from err

    def one_at_a_time(m: int, theta: np.ndarray, rows: np.ndarray, batch: Batch) -> tuple[np.ndarray, np.ndarray]:
        d = np.full(rows.size, np.inf)
        s = np.full(rows.size, FAILED, dtype=np.int8)
        for i, r in enumerate(rows):
            rng = np.random.default_rng(np.random.SeedSequence(batch.seed.entropy,
                                                               spawn_key=(*batch.seed.spawn_key, m, int(r))))
            try:
                d_r, s_r = call(m, theta[i : i + 1], rng, batch.epsilon)
            except NUMERICAL_ERRORS:
                continue  # this row stays FAILED with distance +inf
            d[i], s[i] = np.asarray(d_r).reshape(-1)[0], np.asarray(s_r).reshape(-1)[0]
        return d, s

    # a function marked ``uses_rng = False`` is passed no generator (the generator is made
    # only when a model that may use it comes: making it costs ~30 µs a batch, and a function
    # that leaves it untouched leaves the next model the same stream)
    uses_rng = [getattr(f, "uses_rng", True) for f in functions]

    def evaluate(batch: Batch) -> Evaluated:
        rng: np.random.Generator | None = None
        distances = np.full(len(batch), np.inf)
        status = np.full(len(batch), FAILED, dtype=np.int8)
        for m in map(int, np.unique(batch.models)):
            rows = np.flatnonzero(batch.models == m)
            theta = batch.theta[rows]
            theta = theta[:, ~np.all(np.isnan(theta), axis=0)]
            if rng is None and uses_rng[m]:
                rng = np.random.default_rng(batch.seed)
            try:
                d, s = call(m, theta, rng, batch.epsilon)  # type: ignore[arg-type]  # None: uses_rng False
            except NUMERICAL_ERRORS:
                d, s = one_at_a_time(m, theta, rows, batch)
            distances[rows] = d
            status[rows] = s
        status[(status == OK) & ~np.isfinite(distances)] = FAILED
        distances[status != OK] = np.inf
        return Evaluated(distances, status)

    return evaluate
