"""Compose models, simulators and a distance into a batch evaluator.

``evaluator(models, simulators, distance)`` returns ``evaluate(batch) -> Evaluated``:
each model's rows are expanded to the simulator's full parameter vector (free values,
then fixed values, then the simulator's defaults), simulated as one batch, and scored
by the distance; rows that are not OK get distance +inf.

When the distance is an :class:`abcns.distances.NMSE` and the simulator offers
``distance_nmse`` (the built-in oscillators), the NMSE is computed inside the simulator
(no trajectory array) with early rejection at the batch's epsilon: a particle whose partial
NMSE reaches epsilon stops and reports that partial NMSE (>= epsilon, so it is rejected as
it would have been). Other distances take the generic path.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import numpy as np

from abcns.distances import NMSE, Distance
from abcns.executor import OK, Batch, Evaluate, Evaluated, SimulateDistance, per_model
from abcns.priors import Model, SpecError


def check_model(model: Model, simulator, where: str) -> None:
    """Every simulator parameter is inferred, fixed or defaulted; no unknown names."""
    names = tuple(simulator.parameter_names)
    for key in model.priors:
        if key not in names:
            raise SpecError(f"{where}.priors.{key}", f"is not a parameter of {simulator.name} {names}")
    for key in model.fixed:
        if key not in names:
            raise SpecError(f"{where}.fixed.{key}", f"is not a parameter of {simulator.name} {names}")
    missing = [p for p in names if p not in model.priors and p not in model.fixed and p not in simulator.defaults]
    if missing:
        raise SpecError(f"{where}.priors", f"parameters {missing} of {simulator.name} need a prior or a fixed value")


def model_function(model: Model, simulator, distance: Distance) -> SimulateDistance:
    """``f(theta, rng, epsilon=inf) -> (distances, status)`` for one model."""
    names = tuple(simulator.parameter_names)
    free = [names.index(p) for p in model.priors]
    const = {**simulator.defaults, **model.fixed}
    const_cols = [names.index(p) for p in const if p in names]
    const_vals = np.array([const[names[j]] for j in const_cols])
    fast = isinstance(distance, NMSE) and callable(getattr(simulator, "distance_nmse", None))

    def simulate_distance(theta: np.ndarray, rng: np.random.Generator,
                          epsilon: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        full = np.empty((theta.shape[0], len(names)))
        full[:, free] = theta
        full[:, const_cols] = const_vals
        if fast:
            return simulator.distance_nmse(full, distance.observed, distance.start, distance.stop, epsilon)
        out = simulator.simulate(full, rng)
        d = np.full(theta.shape[0], np.inf)
        ok = out.status == OK
        if ok.any():
            d[ok] = distance(out.values[ok])
        return d, out.status

    return simulate_distance


def evaluator(models: Sequence[Model], simulators: Sequence, distance: Distance,
              early_rejection: bool = True) -> Evaluate:
    """The batch evaluator; ``early_rejection`` passes each batch's epsilon to the simulators."""
    if len(models) != len(simulators):
        raise ValueError(f"{len(models)} models but {len(simulators)} simulators")
    for i, (model, sim) in enumerate(zip(models, simulators, strict=True)):
        check_model(model, sim, f"models[{i}]")
    functions = [model_function(m, s, distance) for m, s in zip(models, simulators, strict=True)]

    def evaluate(batch: Batch) -> Evaluated:
        epsilon = float(batch.epsilon) if early_rejection else np.inf
        return per_model([partial(f, epsilon=epsilon) for f in functions])(batch)

    return evaluate
