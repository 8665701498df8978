"""Result values: one record per population, and the result of a run.

What the run computed and what follows from it (the decision population, the model
probabilities, their errors, the posterior, the JSON summary); the summary's warnings, the
sentences a user reads of it, are :mod:`abcns.run_warnings`'s."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from abcns import run_warnings
from abcns.bounds import Frame
from abcns.ellipsoid import Ellipsoid
from abcns.evidence import DEAD_BEFORE, DEATH_RULES, Evidence, probabilities
from abcns.likelihood import Reading, enough, held_target, of_floor, read
from abcns.mixture import Mixture
from abcns.noise import Floor, Standing, standings, waited_for
from abcns.priors import Model, same_models
from abcns.settings import DEATH_PROBABILITY, StopReason

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
    ``ellipsoids[m]`` the enlarged ellipsoids whose union proposes model m's particles at
    t + 1 (one in the paper variant; empty for a dead model; the whole tuple is empty for the
    baselines), in model m's unit prior box for the evidence variant and in raw units for
    the paper's. ``n_simulations_by_model`` and ``n_failed_by_model`` (n_models,) split
    ``n_simulations`` and ``n_failed`` by model (empty when not recorded). ``evidence`` is
    ABC-NS's per-model evidence bookkeeping (:class:`abcns.evidence.Evidence`), None for the
    baselines. ``model_probabilities`` are
    the evidence's for ABC-NS's default variant, particle shares (Eq. 12) for the paper's,
    importance-weight mass for ABC-SMC and shares for rejection. ``floor`` is the noise floor
    as estimated after this population (:class:`abcns.noise.Floor`; ABC-NS runs that know
    their distance's noise model, else None). ``standing`` is where ``epsilon`` stands to
    the decision tolerance in force when it was chosen (:class:`abcns.noise.Standing`: set by
    it, above or below it; None without a floor, or where the population was made without the
    record: :func:`abcns.noise.standings` then gives it from the floors). ``held`` (ABC-NS,
    else None; (n_particles, n_models)) is each particle's part in each model's new bound
    (``abcns.mixture`` codes: -1 not fitted to it, 0 outside the bound refitted without it, 1
    held by it; a model's bound is fitted to its own particles and its ``same_model_as``
    copies'), from which the evidence's mixture reads the bound's membership of the particles
    it was fitted to.
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
    ellipsoids: tuple[tuple[Ellipsoid, ...], ...] = ()
    model_probabilities: np.ndarray = field(default_factory=lambda: np.zeros(0))
    evidence: Evidence | None = None
    n_simulations_by_model: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    n_failed_by_model: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    floor: Floor | None = None
    standing: Standing | None = None
    held: np.ndarray | None = None

    @property
    def acceptance_rate(self) -> float:
        return self.n_accepted / self.n_simulations if self.n_simulations else 0.0

    @property
    def n_particles(self) -> int:
        return int(self.models.shape[0])

    def model_counts(self, n_models: int) -> np.ndarray:
        return np.bincount(self.models, minlength=n_models)

    @property
    def particle_shares(self) -> np.ndarray:
        """Share of particles per model (the paper's Eq. 12)."""
        n_models = self.model_probabilities.shape[0]
        return self.model_counts(n_models) / max(1, self.n_particles)


@dataclass(frozen=True)
class RunEnd:
    """What a population iterator returns when it stops (its ``StopIteration.value``)."""

    reason: StopReason
    n_simulations: int  # every simulation of the run so far, pilot and unfinished population included
    n_pilot_simulations: int
    epsilon_initial_source: str
    notes: tuple[str, ...] = ()
    #: ABC-NS's mixture after its last population (None from the other algorithms): the
    #: answer's reading takes it rather than growing it again (:attr:`Result.mixture`)
    mixture: Mixture | None = field(default=None, repr=False, compare=False)


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
        out[name] = {"mean": mean, "std": std, **{f"q{_qname(p)}": float(v) for p, v in zip(QUANTILES, q, strict=True)}}
    return out


def _qname(p: float) -> str:
    s = f"{100 * p:g}"
    return s.replace(".", "_")


@dataclass(frozen=True, eq=False)
class Result:
    """A run: its populations, why it stopped, and what it was run with.

    ``n_simulations`` counts every simulation, including the pilot and an unfinished last
    population cut short by a budget; the populations' own counters cover only complete
    populations. Posterior summaries (:meth:`posterior`) come from the last complete
    population unless another is named (:meth:`summary` reads them at the decision
    population), weighted by its weights for ABC-SMC and uniformly for ABC-NS and rejection
    (each population is the sample the paper reports).
    """

    algorithm: str
    models: tuple[Model, ...]
    populations: tuple[Population, ...]
    stop_reason: StopReason
    seed: int
    settings: dict
    epsilon_initial_source: str  # "given" | "pilot" | "pilot_finite" | "schedule" | "resumed"
    n_simulations: int
    n_pilot_simulations: int
    wall_time_s: float
    weighted_posterior: bool = False
    notes: tuple[str, ...] = ()
    #: the mixture the run grew (``RunEnd.mixture``), when this result is the run's own: its
    #: reading is then made without growing it again over the populations (``Mixture.of``)
    mixture: Mixture | None = field(default=None, repr=False, compare=False)

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
        return {m.name: float(p) for m, p in zip(self.models, pop.model_probabilities, strict=True)}

    @property
    def floor(self) -> Floor | None:
        """The noise floor as estimated at the end of the run (``abcns.noise``), or None."""
        return self.final.floor if self.populations else None

    def decision_population(self) -> Population:
        """The population the run's answer is read from, by each population's standing to the
        decision tolerance in force when its tolerance was chosen (:func:`abcns.noise.standings`):
        the first accepted at it (the evidence variant stops there); else the one before the
        first accepted below it (a run that went on past it; the first population when that is
        the first: the floor lies above the run); the final population when the run knows no
        floor or stopped above it."""
        if self.floor is None:
            return self.final
        for i, mark in enumerate(self.standings):
            if mark is not None and mark.reached:
                return self.populations[i if mark is Standing.AT or i == 0 else i - 1]
        return self.final

    @functools.cached_property
    def standings(self) -> list[Standing | None]:
        """Each population's standing to the decision tolerance (:func:`abcns.noise.standings`)."""
        return standings(self.populations)

    @property
    def reached_floor(self) -> bool | None:
        """Whether the run got to its decision tolerance (its last population's standing, at
        or below it: :class:`abcns.noise.Standing`); None when it knows no floor."""
        if self.floor is None:
            return None
        mark = self.standings[-1]
        return mark is not None and mark.reached

    @property
    def floor_settled(self) -> bool:
        """Whether the run's decision tolerance held still at its end (:func:`abcns.noise.waited_for`);
        not when the best fit fell with the tolerance (noise-free data, a model that fits exactly)."""
        return waited_for([None if p.floor is None else p.floor.decision for p in self.populations]) is not None

    @property
    def provisional(self) -> bool:
        """Whether the run stopped above its decision tolerance (a budget, the user's own
        rule, a stalled tolerance): its answer is not yet that of the data."""
        return self.reached_floor is False and self.floor_settled

    def reading(self) -> Reading | None:
        """The likelihood-weighted answer (:attr:`_reading`, made once)."""
        return self._reading

    @functools.cached_property
    def _reading(self) -> Reading | None:
        """The likelihood-weighted answer (:mod:`abcns.likelihood`): the evidence variant of a
        run that knows its noise (a floor), read over all its populations with the floor's
        noise variance, ``same_model_as`` copies from both copies' particles; None otherwise
        (the answer is then the decision population's)."""
        floor = self.floor
        if (floor is None or self.settings.get("sampler", {}).get("variant") != "evidence"
                or any(p.evidence is None for p in self.populations) or not self.floor_settled):
            return None
        log_l = of_floor(floor)
        if log_l is None:
            return None
        dims = [m.n_dim for m in self.models]
        frames = [Frame(m, unit=True) for m in self.models]
        return read(Mixture.of(self.populations, frames, dims, same_models(self.models), self.mixture), dims, log_l)

    def answer_draws(self, model: int) -> tuple[np.ndarray, np.ndarray, str]:
        """(theta (n, d), weights (n,) summing to 1, how) of one model in the run's answer.
        ``how``: ``likelihood``, the reading's weighted particles (:meth:`reading`), unless
        the run stopped above its floor (:attr:`provisional`) and the model's reading rests on
        too few effective particles (:func:`abcns.likelihood.enough`) while it has particles
        in the decision population: then ``tolerance``, those particles (uniform weights for
        ABC-NS), as without a reading. At the floor the weights in the last region vary by a
        few e-folds; above it by many (the cyclic test gill's BWBN at 80 populations: e^22),
        and the reading weighs its few particles nearest the best fit, intervals narrower than
        the data's, where its last tolerance's are wider."""
        reading, answer = self.reading(), self.decision_population()
        thin = (reading is not None and self.provisional and model in self.alive(answer.t)
                and not enough(reading.ess, [m.n_dim for m in self.models])[model])
        if reading is not None and not thin:
            return reading.theta[model], reading.weights[model], "likelihood"
        theta, _, w = self.particles(model, answer.t)
        w = w if self.weighted_posterior else np.ones(theta.shape[0])
        return theta, w / np.sum(w), "tolerance"

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

    def death_rules(self) -> dict[str, str]:
        """{model: the rule that killed it} (``abcns.evidence.DEATH_RULES``) for ABC-NS runs."""
        out = {}
        for pop in self.populations:
            if pop.evidence is None:
                continue
            for i, code in enumerate(pop.evidence.death):
                if code in DEATH_RULES and code != DEAD_BEFORE and self.models[i].name not in out:
                    out[self.models[i].name] = DEATH_RULES[int(code)]
        return out

    def model_probability_se(self, t: int | None = None) -> dict[str, float]:
        """Standard errors of the model probabilities of population t (default: the final
        one; evidence variant; else {})."""
        pop = self.final if t is None else self.populations[t - 1]
        if pop.evidence is None or self.settings.get("sampler", {}).get("variant") != "evidence":
            return {}
        _, se = probabilities(pop.evidence.log_z, pop.evidence.log_z_se)
        return {m.name: float(v) for m, v in zip(self.models, se, strict=True)}

    def failures(self) -> dict[str, dict[str, float]]:
        """{model: {"failed", "simulations", "share"}}: simulations that failed or diverged
        (counted rejections), over the complete populations ({} when not recorded)."""
        pops = [p for p in self.populations if p.n_failed_by_model.shape[0] == len(self.models)]
        if not pops:
            return {}
        failed = np.sum([p.n_failed_by_model for p in pops], axis=0)
        simulated = np.sum([p.n_simulations_by_model for p in pops], axis=0)
        return {m.name: {"failed": int(failed[i]), "simulations": int(simulated[i]),
                         "share": float(failed[i] / simulated[i]) if simulated[i] else 0.0}
                for i, m in enumerate(self.models)}

    def warnings(self) -> list[str]:
        """Why the answer may not be what it looks like: the summary's ``warnings``, each a
        sentence a user reads (:func:`abcns.run_warnings.warnings`)."""
        return run_warnings.warnings(self)

    def particles(self, model: int | str, t: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(theta (n, d_m), distances (n,), weights (n,)) of one model in population t."""
        i = self.model_names.index(model) if isinstance(model, str) else model
        pop = self.final if t is None else self.populations[t - 1]
        rows = pop.models == i
        return pop.theta[rows, : self.models[i].n_dim], pop.distances[rows], pop.weights[rows]

    def posterior(self, t: int | None = None) -> dict[str, dict]:
        """{model: {parameter: summary}} of population t (default: the final one), for the
        alive models with particles in it (a copy relayed by its twin's particles may have none:
        ``abcns.nested._relayed``)."""
        out = {}
        for i in self.alive(t):
            theta, _, w = self.particles(i, t)
            if theta.shape[0]:
                out[self.models[i].name] = posterior_summary(
                    theta, w if self.weighted_posterior else None, self.models[i].parameter_names
                )
        return out

    def _named(self, values: np.ndarray) -> dict[str, float]:
        return {m.name: float(v) for m, v in zip(self.models, values, strict=True)}

    def _log_evidence(self, pop: Population) -> dict[str, dict[str, float | None]]:
        ev = pop.evidence
        if ev is None:
            return {}
        finite = lambda x: float(x) if np.isfinite(x) else None
        return {m.name: {"log_z": finite(ev.log_z[i]), "se": finite(ev.log_z_se[i])} for i, m in enumerate(self.models)}

    def _ellipsoid_counts(self) -> dict[str, object]:
        """Ellipsoids per model in the final bounds, and repairs / fallbacks over the run."""
        notes = [e.note for p in self.populations for bound in p.ellipsoids for e in bound]
        return {"final": {m.name: len(b) for m, b in zip(self.models, self.final.ellipsoids, strict=False)},  # () without bounds
                "repaired": notes.count("repaired"), "fallback": notes.count("fallback")}

    def _noise_floor(self) -> dict | None:
        floor = self.floor
        if floor is None:
            return None
        return {**floor.describe(), "model": self.models[floor.model].name}

    def _at(self, pop: Population) -> dict:
        """What the run says at population ``pop``: tolerance, model probabilities, errors."""
        return {"population": pop.t, "epsilon": pop.epsilon, "model_probabilities": self.model_probabilities(pop.t),
                "model_probability_se": self.model_probability_se(pop.t)}

    def _decision(self, answer: Population, reading: Reading | None) -> dict:
        """``summary.decision``: where and how the answer is read. ``rule``: ``noise_floor``
        when the run got to its decision tolerance, else the stop reason that ended it above
        (``provisional``), ``final`` without a floor; ``reading``: ``likelihood`` (every
        population weighted by the Gaussian likelihood, :mod:`abcns.likelihood`) or
        ``tolerance`` (the decision population's particles); ``posterior_reading`` (with a
        likelihood reading): per model shown, which of the two its posterior is
        (:meth:`answer_draws`: ``tolerance`` for a provisional run's model on too few
        effective particles)."""
        reached_ = self.reached_floor
        out = {**self._at(answer), "rule": "final" if reached_ is None else "noise_floor" if reached_ else
               self.stop_reason.value, "provisional": self.provisional, "reading": "tolerance"}
        if reading is not None:
            out.update(reading="likelihood", model_probabilities=self._named(reading.probabilities),
                       model_probability_se=self._named(reading.se),
                       effective_particles=self._named(reading.ess))
        return out

    def _answer(self, answer: Population | None) -> dict:
        """The answer's fields of the summary: from the likelihood reading when the run has
        one (:meth:`reading`), else from the decision population."""
        if answer is None:
            return {"model_probabilities": {}, "model_probability_se": {}, "log_evidence": {}, "posterior": {},
                    "decision": None}
        reading = self.reading()
        out = {"decision": self._decision(answer, reading)}
        if reading is None:
            out.update(model_probabilities=self.model_probabilities(answer.t),
                       model_probability_se=self.model_probability_se(answer.t),
                       log_evidence=self._log_evidence(answer), posterior=self.posterior(answer.t))
            return out
        finite = lambda x: float(x) if np.isfinite(x) else None
        # every model alive at the answer's population, and every other whose probability
        # is above the threshold of death by probability (a model that left the run early
        # but that the likelihood still gives a share)
        threshold = self.settings.get("sampler", {}).get("min_model_probability") or DEATH_PROBABILITY
        alive = sorted(set(self.alive(answer.t)) | {i for i, p in enumerate(reading.probabilities) if p >= threshold})
        # lower_bound: a model read on fewer effective particles than a run at its floor holds
        # its tolerance for (likelihood.held_target) left the run early; where that was far
        # above its own best fit its particles never sampled its likelihood's peak, and its
        # log_z reads low by more than se says (the exact-Bayes benchmark's §4.1 cubic, 10-20
        # effective particles: from 0.3 to 74,348 nats low; the cyclic tests' Bouc-Wen, 10-37,
        # within 0.5 nats). An estimate from below, not a bound proved
        out.update(model_probabilities=self._named(reading.probabilities), model_probability_se=self._named(reading.se),
                   log_evidence={m.name: {"log_z": finite(reading.log_z[i]), "se": finite(reading.log_z_se[i]),
                                          "effective_particles": float(reading.ess[i]),
                                          "lower_bound": bool(reading.ess[i] < held_target(m.n_dim))}
                                 for i, m in enumerate(self.models)},
                   posterior={})
        for i in alive:
            theta, w, how = self.answer_draws(i)
            if theta.shape[0]:
                out["posterior"][self.models[i].name] = posterior_summary(theta, w, self.models[i].parameter_names)
                out["decision"].setdefault("posterior_reading", {})[self.models[i].name] = how
        return out

    def summary(self) -> dict:
        """The JSON summary of docs/design.md, "The summary" (plus a few more fields). The answer (model
        probabilities, their errors, the evidence, the posterior) is read at the decision
        population (:meth:`decision_population`: the lowest tolerance above the noise floor
        by its spread, or the final population when the run knows no floor); ``final`` says
        what the last population gives, and the curves are per population."""
        pops = self.populations
        answer = self.decision_population() if pops else None
        answer_ = self._answer(answer)
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
            "failures_by_model": self.failures(),
            "redraws": [p.n_redraws for p in pops],
            **{k: answer_[k] for k in ("model_probabilities", "model_probability_se", "decision")},
            "final": self._at(pops[-1]) if pops else None,
            "noise_floor": self._noise_floor(),
            "model_probabilities_by_population": [self.model_probabilities(p.t) for p in pops],
            "particle_shares": self._named(answer.particle_shares) if answer else {},
            "particle_shares_by_population": [self._named(p.particle_shares) for p in pops],
            "log_evidence": answer_["log_evidence"],
            "dead_models": self.died_at(),
            "death_rules": self.death_rules(),
            "ellipsoids": self._ellipsoid_counts() if pops else {},
            "warnings": self.warnings(),
            "posterior": answer_["posterior"],
            "notes": list(self.notes),
            "settings": self.settings,
            "models": [m.config_dict() for m in self.models],
        }
