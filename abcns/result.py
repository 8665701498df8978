"""Result values: one record per population, and the result of a run."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from abcns.ellipsoid import Ellipsoid
from abcns.priors import Model
from abcns.settings import StopReason

QUANTILES = (0.025, 0.05, 0.5, 0.95, 0.975)


@dataclass(frozen=True, eq=False)
class Population:
    """One complete population t (1-based).

    Particles: ``models`` (N,), ``theta`` (N, d_max; NaN beyond a model's dimension),
    ``distances`` (N,), ``weights`` (N,; normalised to sum to 1 within each model; for
    ABC-NS the survivor-selection weights, zero for dropped particles).
    ``epsilon`` is the tolerance this population was accepted under, ``epsilon_next`` the
    one the next population will use. Counters cover the simulations run to fill this
    population (including failed ones); ``n_redraws`` counts prior-bound redraws, which
    are not simulations. ``survivors`` marks the particles kept for t + 1 (ABC-NS) and
    ``ellipsoids[m]`` the enlarged ellipsoid that proposes model m's particles at t + 1
    (None for a dead model and for the baselines).
    """

    t: int
    epsilon: float
    epsilon_next: float
    models: np.ndarray
    theta: np.ndarray
    distances: np.ndarray
    weights: np.ndarray
    n_accepted: int
    n_simulations: int
    n_failed: int
    n_redraws: int
    elapsed_s: float
    survivors: np.ndarray | None = None
    ellipsoids: tuple[Ellipsoid | None, ...] = ()
    model_probabilities: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def acceptance_rate(self) -> float:
        return self.n_accepted / self.n_simulations if self.n_simulations else 0.0

    @property
    def n_particles(self) -> int:
        return int(self.models.shape[0])

    def model_counts(self, n_models: int) -> np.ndarray:
        return np.bincount(self.models, minlength=n_models)


@dataclass(frozen=True)
class RunEnd:
    """What a population iterator returns when it stops (its ``StopIteration.value``)."""

    reason: StopReason
    n_simulations: int  # every simulation of the run so far, pilot and unfinished population included
    n_pilot_simulations: int
    epsilon_initial_source: str
    notes: tuple[str, ...] = ()


def weighted_quantiles(x: np.ndarray, w: np.ndarray, qs: Sequence[float]) -> np.ndarray:
    """Quantiles of a weighted sample (midpoint interpolation of the weighted CDF)."""
    order = np.argsort(x)
    x, w = x[order], w[order]
    cdf = (np.cumsum(w) - 0.5 * w) / np.sum(w)
    return np.interp(qs, cdf, x)


def posterior_summary(theta: np.ndarray, weights: np.ndarray | None, names: Sequence[str]) -> dict:
    """{parameter: {mean, std, q2_5, q5, q50, q95, q97_5}} of one model's particles."""
    out = {}
    w = np.full(theta.shape[0], 1.0 / theta.shape[0]) if weights is None else weights / np.sum(weights)
    for j, name in enumerate(names):
        x = theta[:, j]
        mean = float(np.sum(w * x))
        std = float(np.sqrt(np.sum(w * (x - mean) ** 2)))
        q = weighted_quantiles(x, w, QUANTILES)
        out[name] = {"mean": mean, "std": std, **{f"q{_qname(p)}": float(v) for p, v in zip(QUANTILES, q)}}
    return out


def _qname(p: float) -> str:
    s = f"{100 * p:g}"
    return s.replace(".", "_")


@dataclass(frozen=True, eq=False)
class Result:
    """A run: its populations, why it stopped, and what it was run with.

    ``n_simulations`` counts every simulation, including the pilot and an unfinished last
    population cut short by a budget; the populations' own counters cover only complete
    populations. Posterior summaries come from the last complete population, weighted
    by its weights for ABC-SMC and uniformly for ABC-NS and rejection (each population is
    the sample the paper reports).
    """

    algorithm: str
    models: tuple[Model, ...]
    populations: tuple[Population, ...]
    stop_reason: StopReason
    seed: int
    settings: dict
    epsilon_initial_source: str  # "given" | "pilot"
    n_simulations: int
    n_pilot_simulations: int
    wall_time_s: float
    weighted_posterior: bool = False
    notes: tuple[str, ...] = ()

    @property
    def final(self) -> Population:
        if not self.populations:
            raise ValueError(f"the run stopped ({self.stop_reason.value}) before its first population was complete")
        return self.populations[-1]

    @property
    def model_names(self) -> list[str]:
        return [m.name for m in self.models]

    def model_probabilities(self, t: int | None = None) -> dict[str, float]:
        pop = self.final if t is None else self.populations[t - 1]
        return {m.name: float(p) for m, p in zip(self.models, pop.model_probabilities)}

    def alive(self, t: int | None = None) -> list[int]:
        pop = self.final if t is None else self.populations[t - 1]
        return [i for i, p in enumerate(pop.model_probabilities) if p > 0]

    def died_at(self) -> dict[str, int]:
        """{model: first population with no particle} for every model that died."""
        out = {}
        for i, m in enumerate(self.models):
            for pop in self.populations:
                if pop.model_probabilities[i] == 0:
                    out[m.name] = pop.t
                    break
        return out

    def particles(self, model: int | str, t: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(theta (n, d_m), distances (n,), weights (n,)) of one model in population t."""
        i = self.model_names.index(model) if isinstance(model, str) else model
        pop = self.final if t is None else self.populations[t - 1]
        rows = pop.models == i
        return pop.theta[rows, : self.models[i].n_dim], pop.distances[rows], pop.weights[rows]

    def posterior(self) -> dict[str, dict]:
        out = {}
        for i in self.alive():
            theta, _, w = self.particles(i)
            out[self.models[i].name] = posterior_summary(
                theta, w if self.weighted_posterior else None, self.models[i].parameter_names
            )
        return out

    def summary(self) -> dict:
        """The JSON summary of DESIGN.md (plus a few more fields)."""
        pops = self.populations
        return {
            "algorithm": self.algorithm,
            "status": "finished",
            "stop_reason": self.stop_reason.value,
            "n_populations": len(pops),
            "n_simulations": self.n_simulations,
            "n_pilot_simulations": self.n_pilot_simulations,
            "wall_time_s": self.wall_time_s,
            "seed": self.seed,
            "epsilon_initial_source": self.epsilon_initial_source,
            "epsilon": [p.epsilon for p in pops],
            "epsilon_next": pops[-1].epsilon_next if pops else None,
            "acceptance_rate": [p.acceptance_rate for p in pops],
            "simulations": [p.n_simulations for p in pops],
            "failed_simulations": [p.n_failed for p in pops],
            "redraws": [p.n_redraws for p in pops],
            "model_probabilities": self.model_probabilities() if pops else {},
            "model_probabilities_by_population": [self.model_probabilities(p.t) for p in pops],
            "dead_models": self.died_at(),
            "posterior": self.posterior() if pops else {},
            "notes": list(self.notes),
            "settings": self.settings,
            "models": [m.config_dict() for m in self.models],
        }
