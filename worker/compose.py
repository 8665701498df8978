"""Compose models, simulators and a distance into a batch evaluator.

``evaluator(models, simulators, distance)`` returns ``evaluate(batch) -> Evaluated``:
each model's rows are expanded to the simulator's full parameter vector (free values,
then fixed values, then the simulator's defaults), simulated as one batch, and scored
by the distance; rows that are not OK get distance +inf. A simulator that raises a numerical
error fails only the rows that raise it; any other exception fails the job with a message
naming the model and its simulator (:func:`abcns.executor.per_model`).

When the distance is an :class:`abcns.distances.NMSE` and the simulator is
:class:`~worker.simulators.NMSECapable` (the built-in oscillators), the NMSE is computed inside the simulator
(no trajectory array) with early rejection at the batch's epsilon: a particle whose partial
NMSE reaches epsilon stops and reports that partial NMSE (>= epsilon, so it is rejected as
it would have been). Other distances take the generic path.

A job's description becomes models and simulators in :mod:`worker.description`; the
Dask tasks that build and run an evaluator on a worker are in :mod:`worker.tasks`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from abcns.distances import NMSE, Distance
from abcns.errors import InvalidSetting
from abcns.executor import OK, Evaluate, SimulateDistanceEpsilon, per_model
from abcns.priors import Model
from worker.simulators import NMSECapable, Range, Simulator


def check_model(model: Model, simulator: Simulator, where: tuple = ()) -> None:
    """Every simulator parameter is inferred, fixed or defaulted; no unknown names."""
    names = tuple(simulator.parameter_names)
    for key in model.priors:
        if key not in names:
            raise InvalidSetting((*where, "priors", key), f"is not a parameter of {simulator.name} {names}")
    for key in model.fixed:
        if key not in names:
            raise InvalidSetting((*where, "fixed", key), f"is not a parameter of {simulator.name} {names}")
    missing = [p for p in names if p not in model.priors and p not in model.fixed and p not in simulator.defaults]
    if missing:
        raise InvalidSetting((*where, "priors"), f"parameters {missing} of {simulator.name} need a prior or a fixed value")


def check_ranges(model: Model, simulator: Simulator, where: tuple = ()) -> None:
    """The model's fixed values and priors lie in the valid ranges its simulator states
    (``simulator.ranges``, :class:`worker.simulators.Range`); an InvalidSetting at the
    field behind ``where`` (``("models", 1, "fixed", "n")``) otherwise. A simulator without ``ranges`` states none."""
    ranges: dict[str, Range] = getattr(simulator, "ranges", None) or {}
    for key, value in model.fixed.items():
        valid = ranges.get(key)
        if valid is not None and not valid.holds(float(value)):
            raise InvalidSetting((*where, "fixed", key), f"must be {valid} for simulator {simulator.name}, got {value!r}")
    for key, prior in model.priors.items():
        valid = ranges.get(key)
        if valid is None or valid.holds_prior(prior.low, prior.high):
            continue
        if valid.integer:
            raise InvalidSetting((*where, "priors", key), f"{key} of simulator {simulator.name} is {valid}: fix it "
                            f"(fixed: {{{key}: ...}}), it cannot have a uniform prior")
        raise InvalidSetting((*where, "priors", key), f"[{prior.low:g}, {prior.high:g}] leaves the valid range of {key} "
                        f"for simulator {simulator.name}: {valid}")
    pair = getattr(simulator, "bounded_by", None)
    if pair is not None and all(k in simulator.parameter_names for k in pair):
        check_domain(model, simulator, pair, where)


def check_domain(model: Model, simulator: Simulator, pair: tuple[str, str], where: tuple = ()) -> None:
    """A restoring-force model whose box holds no point of its domain (the sum of the pair's
    values positive: ``worker.restoring._Restoring.outside``) is refused, naming the second
    of the two; a box only partly inside it is the box restricted to the domain."""
    defaults = getattr(simulator, "defaults", {})

    def highest(key: str) -> tuple[float, str]:
        if key in model.priors:
            return float(model.priors[key].high), "priors"
        return float(model.fixed.get(key, defaults.get(key, np.nan))), "fixed"

    (a, _), (b, field) = highest(pair[0]), highest(pair[1])
    if not a + b > 0:
        raise InvalidSetting((*where, field, pair[1]), f"{pair[0]} + {pair[1]} is at most {a + b:g} in this model's "
                             f"prior box, but simulator {simulator.name} needs {pair[0]} + {pair[1]} > 0 (its "
                             "hysteretic state is unbounded otherwise)")


def full_parameters(model: Model, simulator: Simulator) -> Callable[[np.ndarray], np.ndarray]:
    """The one mapping from a model's free parameters (n, d) to the simulator's full
    parameter vectors (n, p): the free ones in the simulator's columns, then the model's
    fixed values, then the simulator's defaults for what the model neither fixes nor infers
    (a default never overrides an inferred parameter)."""
    names = tuple(simulator.parameter_names)
    free = [names.index(p) for p in model.priors]
    const = {p: v for p, v in {**simulator.defaults, **model.fixed}.items() if p not in model.priors}
    const_cols = [names.index(p) for p in const if p in names]
    const_vals = np.array([const[names[j]] for j in const_cols])

    def expand(theta: np.ndarray) -> np.ndarray:
        theta = np.atleast_2d(theta)
        full = np.empty((theta.shape[0], len(names)))
        full[:, free] = theta
        full[:, const_cols] = const_vals
        return full

    return expand


def model_function(model: Model, simulator: Simulator, distance: Distance) -> SimulateDistanceEpsilon:
    """``f(theta, rng, epsilon=inf) -> (distances, status)`` for one model."""
    expand = full_parameters(model, simulator)
    # the fast path needs both: the distance is the NMSE, and the simulator can compute it
    nmse = distance if isinstance(distance, NMSE) else None
    capable = simulator if isinstance(simulator, NMSECapable) else None

    def simulate_distance(theta: np.ndarray, rng: np.random.Generator,
                          epsilon: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        full = expand(theta)
        if nmse is not None and capable is not None:
            return capable.distance_nmse(full, nmse.observed, nmse.start, nmse.stop, epsilon)
        out = simulator.simulate(full, rng)
        d = np.full(theta.shape[0], np.inf)
        ok = out.status == OK
        if ok.any():
            d[ok] = distance(out.values[ok])
        return d, out.status

    # the in-kernel NMSE is deterministic: the batch's generator need not be made for it
    simulate_distance.uses_rng = nmse is None or capable is None  # type: ignore[attr-defined]
    return simulate_distance


def evaluator(models: Sequence[Model], simulators: Sequence[Simulator], distance: Distance,
              early_rejection: bool = True) -> Evaluate:
    """The batch evaluator; ``early_rejection`` passes each batch's epsilon to the simulators."""
    if len(models) != len(simulators):
        raise ValueError(f"{len(models)} models but {len(simulators)} simulators")
    n_observed = int(np.size(distance.observed))
    for i, (model, sim) in enumerate(zip(models, simulators, strict=True)):
        check_model(model, sim, ("models", i))
        check_ranges(model, sim, ("models", i))
        if sim.n_samples != n_observed:
            raise InvalidSetting(
                ("observed",),
                f"has {n_observed} samples but model {model.name!r} simulates {sim.n_samples} "
                "(input and observed records must have the same length)",
            )
    pairs = list(zip(models, simulators, strict=True))
    return per_model([model_function(m, s, distance) for m, s in pairs], pass_epsilon=early_rejection,
                     names=[f"model {m.name!r} (simulator {m.config.get('simulator', s.name)!r})" for m, s in pairs])
