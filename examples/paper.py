"""The paper's problems as ready-to-run Python objects.

Each builder returns a :class:`Problem`: the candidate models, a batch evaluator, the
paper's settings and stop rule, and the truth where known. Synthetic data are made here
with a fixed seed, so every run of a test or benchmark sees the same data.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from abcns import NMSE, Model, NSSettings, StopRules, SummaryEuclidean
from abcns.executor import Evaluate
from examples import make_data
from worker.compose import evaluator
from worker.simulators import Duffing, GAndK, Linear

DATA = Path(__file__).resolve().parents[1] / "data"  # the committed data sets, one folder each (data/README.md)


@dataclass
class Problem:
    name: str
    models: list[Model]
    evaluate: Evaluate
    settings: NSSettings
    stop: StopRules
    truth: dict[str, dict[str, float]] = field(default_factory=dict)  # {model: {parameter: value}}
    data: dict[str, np.ndarray] = field(default_factory=dict)


def authors_demo(path: Path | None = None) -> Problem:
    """The authors' MATLAB demo (``data/authors-demo``): linear vs cubic
    Duffing, noise-free data of the cubic model, their settings, one RK4 step per sample,
    the demo's kernel weights."""
    with np.load(path or DATA / "authors-demo" / "demo_data.npz") as f:
        d = dict(f)
    force, observed, dt = d["force"], d["displacement"], float(d["dt"])
    models = [
        Model("linear", {"c": (0.002, 0.2), "k": (20, 80)}, {"m": 1, "k3": 0, "k5": 0}),
        Model("cubic", {"c": (0.002, 0.2), "k": (20, 80), "k3": (500, 1500)}, {"m": 1, "k5": 0}),
    ]
    sim = Duffing(force, dt, substeps=1, state_bound=1e3 * np.max(np.abs(observed)))
    return Problem(
        "authors-demo", models, evaluator(models, [sim, sim], NMSE(observed)),
        NSSettings(particles=1000, alpha=0.3, beta=0.6, enlargement=1.1, weights="kernel", epsilon_initial=100, batch_size=200,
                   variant="paper"),
        StopRules(min_epsilon_decrease=0.01),
        truth={"cubic": {"c": 0.05, "k": 50.0, "k3": 1000.0}},
        data={"force": force, "observed": observed, "dt": np.array(dt)},
    )


def linear_31(seed: int = 31) -> Problem:
    """Paper §3.1: m = 1 known, c = 20, k = 1e4 (Table 1 priors), Gaussian force of std 10,
    500 samples at 100 Hz, noise-free displacement from the exact zero-order-hold solution;
    stop when the tolerance falls by less than 1e-3."""
    d = make_data.linear_31(seed)
    force, observed, dt = d["force"], d["displacement"], 0.01
    sim = Linear(force, dt, state_bound=1e3 * np.max(np.abs(observed)))
    models = [Model("linear", {"c": (10, 50), "k": (5000, 15000)}, {"m": 1})]
    return Problem(
        "paper-3.1-linear", models, evaluator(models, [sim], NMSE(observed)),
        NSSettings(particles=1000, alpha=0.3, beta=0.6, enlargement=1.1, epsilon_initial=100, batch_size=200),
        StopRules(min_epsilon_decrease=1e-3),
        truth={"linear": {"c": 20.0, "k": 1e4}},
        data={"force": force, "observed": observed, "dt": np.array(dt)},
    )


def gandk_32(seed: int = 32) -> Problem:
    """Paper §3.2: 1e4 draws of the g-and-k distribution at (A, B, g, k) = (3, 1, 2, 0.5),
    c = 0.8, priors U(0, 10), Euclidean distance between (P20, P40, P60, P80, skewness)."""
    observed = make_data.gandk_32(seed)["observed"]
    gk = GAndK(observed.size)
    models = [Model("gandk", {p: (0, 10) for p in ("A", "B", "g", "k")}, {"c": 0.8})]
    return Problem(
        "paper-3.2-gandk", models, evaluator(models, [gk], SummaryEuclidean(observed, "gk")),
        NSSettings(particles=1000, alpha=0.3, beta=0.6, enlargement=1.1, epsilon_initial=100, batch_size=200),
        StopRules(min_epsilon_decrease=1e-5),
        truth={"gandk": {"A": 3.0, "B": 1.0, "g": 2.0, "k": 0.5}},
        data={"observed": observed},
    )
