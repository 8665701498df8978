"""The three problems, each built once for both tools: the same data, the same numba
simulators, the same distance.

abcns gets the problem's batch evaluator (its own machinery: batches, the in-kernel NMSE
with early rejection for the oscillators). pyABC gets, per model, a function of one
parameter dict that runs the same simulator on one row and returns its output as the
summary statistics (the trajectory on the fit window for the oscillators; the five g-and-k
summaries of abcns.distances.gk_summaries for §3.2), and a fixed distance that is abcns' own:
``abcns.NMSE`` on the trajectory, or the Euclidean distance between the summaries (what
``abcns.SummaryEuclidean`` computes from the raw draws).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from abcns import NMSE, Model, NSSettings, StopRules
from abcns.distances import gk_summaries
from abcns.executor import OK, Evaluate
from abcns.noise import Noise
from examples.paper import gandk_32, linear_31
from service.spec import build, load
from worker.description import simulator_for
from worker.simulators import GAndK, Linear

ROOT = Path(__file__).resolve().parents[2]


@dataclass
class Case:
    key: str  # "3.1"
    title: str
    models: list[Model]
    evaluate: Evaluate  # abcns
    settings: NSSettings  # abcns
    stop: StopRules  # abcns: the paper's rule plus the target and the budget
    simulators: list  # per model, for pyABC
    distance: Callable[[dict, dict], float]  # pyABC: (x, x0) -> float
    observed: dict  # pyABC's x0
    output: Callable[[np.ndarray], dict]  # one simulated row -> pyABC summary statistics dict
    failed: dict  # what a diverged simulation returns (distance +inf)
    truth_model: str
    truth: dict[str, float]
    levels: tuple[float, ...]
    target: float  # pyABC minimum_epsilon and abcns epsilon_target (0: none)
    max_simulations: int
    max_seconds: float
    budget_note: str
    particles: int = 1000
    notes: list[str] = field(default_factory=list)
    noise: Noise | None = None  # abcns: the distance's noise model (the noise floor), as a job's


def full_row(model: Model, simulator, pars: dict) -> np.ndarray:
    """A model's parameter dict -> the simulator's full parameter row (1, p): free values,
    fixed values, then the simulator's defaults (as worker.compose does for a batch)."""
    const = {**simulator.defaults, **model.fixed}
    return np.array([[float(pars[p]) if p in model.priors else float(const[p]) for p in simulator.parameter_names]])


_RNG: dict[int, np.random.Generator] = {}
SEED = [0]


def process_rng() -> np.random.Generator:
    """One generator per process (pyABC forks its workers): seeded by (run seed, pid)."""
    pid = os.getpid()
    g = _RNG.get(pid)
    if g is None:
        g = _RNG[pid] = np.random.default_rng([SEED[0], pid])
    return g


def pyabc_model(case: Case, i: int) -> Callable[[dict], dict]:
    model, sim = case.models[i], case.simulators[i]

    def simulate_one(pars: dict) -> dict:
        out = sim.simulate(full_row(model, sim, pars), process_rng())
        if out.status[0] != OK:
            return case.failed
        return case.output(out.values[0])

    simulate_one.__name__ = model.name
    return simulate_one


def _nmse_case(nmse: NMSE) -> dict:
    n = nmse.stop

    def distance(x: dict, x0: dict) -> float:
        return float(nmse(x["y"][None, :])[0])

    return {
        "distance": distance,
        "noise": nmse.noise(),
        "observed": {"y": nmse.observed[:n].copy()},
        "output": lambda row: {"y": np.array(row[:n], dtype=float)},
        "failed": {"y": np.full(n, np.inf)},
    }


def _budget(stop: StopRules, target: float, sims: int, seconds: float) -> StopRules:
    return replace(stop, epsilon_target=target or None, max_simulations=sims, max_seconds=seconds)


def linear(quick: bool) -> Case:
    p = linear_31()
    ev = p.evaluate
    obs = p.data["observed"]
    sim = Linear(p.data["force"], float(p.data["dt"]), state_bound=1e3 * np.max(np.abs(obs)))  # as examples.paper
    nmse = NMSE(p.data["observed"])
    sims, secs = (2_000, 15.0) if quick else (400_000, 300.0)
    return Case(
        "3.1", "§3.1 linear oscillator (c, k), NMSE, target ε 0.01", p.models, ev,
        _particles(p.settings, quick), _budget(p.stop, 0.01, sims, secs), [sim], **_nmse_case(nmse),
        truth_model="linear", truth=p.truth["linear"], levels=(10.0, 1.0, 0.1, 0.03, 0.01), target=0.01,
        max_simulations=sims, max_seconds=secs, particles=_n(quick),
        budget_note=f"stop at ε ≤ 0.01 (abcns also at the paper's rule, ε decrease < 1e-3); cap {sims:,} simulations "
                    f"or {secs:.0f} s",
    )


def gandk(quick: bool) -> Case:
    p = gandk_32()
    gk = GAndK(p.data["observed"].size)
    obs_s = gk_summaries(p.data["observed"][None, :])[0]

    def distance(x: dict, x0: dict) -> float:
        d = float(np.sqrt(np.sum((x["s"] - x0["s"]) ** 2)))
        return d if np.isfinite(d) else np.inf

    sims, secs = (1_000, 15.0) if quick else (40_000, 120.0)
    return Case(
        "3.2", "§3.2 g-and-k (A, B, g, k), Euclidean distance of (P20, P40, P60, P80, skewness)", p.models, p.evaluate,
        _particles(p.settings, quick), _budget(p.stop, 0.05, sims, secs), [gk], distance, {"s": obs_s},
        lambda row: {"s": gk_summaries(row[None, :])[0]}, {"s": np.full(5, np.inf)},
        truth_model="gandk", truth=p.truth["gandk"], levels=(20.0, 10.0, 5.0, 2.0, 1.0, 0.5, 0.3), target=0.05,
        max_simulations=sims, max_seconds=secs, particles=_n(quick),
        budget_note=f"target ε 0.05 (below the distance's noise floor of ~0.24 at the truth, so neither tool can reach it); "
                    f"the budget decides: {sims:,} simulations or {secs:.0f} s",
    )


def duffing(quick: bool) -> Case:
    job = build(*load(ROOT / "examples" / "duffing_41" / "spec.yaml"))
    stop_ = job.spec.data.fit[1]
    dt = job.spec.data.dt or 1.0 / job.spec.data.fs
    # as the job's evaluator builds them: only the fit window is simulated
    sims_ = [simulator_for(m, job.force[:stop_], dt, job.observed[:stop_], i) for i, m in enumerate(job.description.models)]
    nmse = NMSE(job.observed[:stop_])
    sims, secs = (2_000, 15.0) if quick else (600_000, 300.0)
    return Case(
        "4.1", "§4.1 cubic vs cubic-quintic Duffing, 1 % noise, NMSE on the first 500 samples", job.models, job.evaluate,
        _particles(job.settings, quick), _budget(job.stop, 0.0, sims, secs), sims_, **_nmse_case(nmse),
        truth_model="cubic-quintic", truth={"c": 0.05, "k": 50.0, "k3": 1000.0, "k5": 1e5},
        levels=(10.0, 1.0, 0.1, 0.03, 0.015), target=0.0, max_simulations=sims, max_seconds=secs, particles=_n(quick),
        budget_note=f"no target: as low as each gets within {sims:,} simulations or {secs:.0f} s (abcns also stops at the "
                    f"paper's rule, ε decrease < 1e-7); the truth's own NMSE is 0.0121 (noise floor)",
    )


def _n(quick: bool) -> int:
    return 100 if quick else 1000


def _particles(settings: NSSettings, quick: bool) -> NSSettings:
    return replace(settings, particles=_n(quick), batch_size=50) if quick else settings


CASES = {"3.1": linear, "3.2": gandk, "4.1": duffing}
