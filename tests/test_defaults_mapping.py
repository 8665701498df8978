"""A simulator default (Bouc-Wen k = 0) never overrides a parameter the model infers.

Regression: the evaluator filled the defaults after the free values, so a Bouc-Wen model
with a prior on k simulated k = 0 whatever was proposed."""

import numpy as np

from abcns import NMSE, Batch, Model
from worker.compose import evaluator
from worker.simulators import BoucWen


def test_inferred_parameter_with_a_default_is_used():
    rng = np.random.default_rng(7)
    force = rng.standard_normal(300) * 50
    sim = BoucWen(force=force, dt=1 / 750, substeps=4, backend="numpy")
    truth = np.array([[2.0, 10.0, 5e4, 800.0, -1100.0, 5e4, 1.0]])  # m c k alpha beta A n
    observed = sim.simulate(truth).values[0]
    model = Model("bw", {"m": (1, 3), "c": (1, 20), "k": (1e4, 1e5), "A": (1e4, 1e5), "alpha": (0, 2000),
                         "beta": (-2000, 2000)}, {"n": 1})
    evaluate = evaluator([model], [sim], NMSE(observed), early_rejection=False)
    theta = np.array([[2.0, 10.0, 5e4, 5e4, 800.0, -1100.0], [2.0, 10.0, 0.0, 5e4, 800.0, -1100.0]])
    out = evaluate(Batch(population=1, index=1, models=np.zeros(2, int), theta=theta, seed=np.random.SeedSequence(1),
                         epsilon=np.inf, redraws=np.zeros(2, int)))
    assert out.distances[0] == 0.0      # the truth reproduces the data exactly
    assert out.distances[1] > 1.0       # k = 0 is a different system
