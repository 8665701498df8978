"""A small hand-made :class:`abcns.Result` with a noise floor, for the tests of what a person
sees of it (the CLI's summary, the figures): no run needed."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from abcns import Model, Population, Result, StopReason
from abcns.noise import Floor

#: the floor of :func:`floored_result`: best fit 2.4 (model 1), p = 2, v = 0.2: floor 2.8,
#: spread 0.4, decision tolerance 3.2
FLOOR = Floor(best=2.4, model=1, n_parameters=2, variance=0.2, method=0, n_samples=100)


def floored_result(n: int = 200, seed: int = 0, floor: Floor | None = FLOOR,
                   floors: Sequence[Floor] | None = None) -> Result:
    """Two models, five populations at tolerances 10 / t (10, 5, 3.33, 2.5, 2). The answer
    (population 3, the lowest tolerance at or above the decision tolerance 3.2) is
    linear 0.9 / cubic 0.1; populations 4 and 5, below it, turn to cubic 0.9. ``floors``:
    the floor after each population, in place of ``floor`` after every one."""
    rng = np.random.default_rng(seed)
    models = (Model("linear", {"c": (0.0, 1.0), "k": (0.0, 100.0)}),
              Model("cubic", {"c": (0.0, 1.0), "k": (0.0, 100.0)}))
    which = np.repeat([0, 1], n // 2)
    pops = tuple(Population(t=t, epsilon=10.0 / t, epsilon_next=10.0 / (t + 1), models=which,
                            theta=np.column_stack([rng.uniform(0, 1, n), rng.uniform(0, 100, n)]),
                            distances=rng.uniform(0, 10.0 / t, n), weights=np.full(n, 1.0 / n), n_accepted=n,
                            n_simulations=2 * n, n_failed=0, n_redraws=0, elapsed_s=float(t),
                            model_probabilities=np.array([0.9, 0.1] if t <= 3 else [0.1, 0.9]),
                            floor=floor if floors is None else floors[t - 1])
                 for t in range(1, 6))
    return Result("abc-ns", models, pops, StopReason.MAX_POPULATIONS, 0, {}, "given", 10 * n, 0, 5.0)
