"""ABC-NS (paper Algorithm 2) with joint model selection over models of any dimension.

One population t holds N particles accepted below eps_t. Finishing it (a pure function of
the particles and generators keyed by (seed, t)) gives:

1. eps_{t+1} = the (alpha N)-th largest distance (steps 10-11, 27);
2. weights (step 9/28): zero for e >= eps_{t+1}; otherwise ``(1/e)(1 - (e/eps_t)^2)``
   ("paper") or ``(1/eps_t)(1 - (e/eps_t)^2)`` ("kernel", the authors' demo);
3. survivors (step 14/29): beta N in all, split over models, drawn by weight without
   replacement from each model's positive-weight particles; a model short of them gives its
   shortfall to the others;
4. a bound per alive model (steps 15-16, 30): ellipsoids enlarged by f0.

Population t + 1 = the survivors plus (1 - beta) N new particles: each proposal picks a
model, then a point uniform in its bound, redrawn until inside the prior box (redraws are
counted, not simulated).

Two variants (``NSSettings.variant``): ``"paper"``, the published algorithm as the authors'
demo runs it, and ``"evidence"`` (the default), the model probabilities from each model's
evidence. What each decides is stated in ``abcns.variants`` (:class:`~abcns.variants.Paper`,
:class:`~abcns.variants.Evidence`); the evidence estimator in ``abcns.evidence`` and
``abcns.mixture`` (derived in docs/design.md, "The evidence"); this module holds the steps
both share (the paper's Algorithm 2) and the run loop.

The evidence bookkeeping (``Population.evidence``) is computed in both variants; in the paper
variant it is a diagnostic and uses its own random stream, so the paper's populations are
exactly those of the published algorithm.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass

import numpy as np

from abcns import bounds as bd
from abcns import ellipsoid as ell
from abcns import evidence as ev
from abcns import likelihood
from abcns.executor import Executor
from abcns.filling import Budget, Filled, Filling, Stopped, draw_inside, fill, population_rng
from abcns.mixture import HELD, NOT_FITTED, OUTSIDE, Mixture, held_without
from abcns.noise import Floor, Noise, Standing, Tracker, standing, standings, waited_for
from abcns.priors import Model, same_models
from abcns.rejection import initial_epsilon, pad, population_from, prior_proposer
from abcns.result import Population, RunEnd
from abcns.settings import NSSettings, StopReason, StopRules
from abcns.variants import variant_of


def next_tolerance(distances: np.ndarray, n_drop: int, lower: float | None = None) -> float | None:
    """eps_{t+1}: the (alpha N)-th largest distance (``n_drop``-th), raised to ``lower`` (the
    decision tolerance, when the run stops at its noise floor) if it falls below it. When no
    particle lies strictly below that value (more than (1 - alpha) N particles share the
    smallest distance: a rounded or discrete distance), the smallest distance above the
    minimum, so the tied particles are below it; None when every particle has the same
    distance (no tolerance below it leaves a particle)."""
    eps = float(np.sort(distances)[::-1][n_drop - 1])
    if lower is not None and eps < lower:
        eps = float(lower)
    if np.any(distances < eps):
        return eps
    above = distances[distances > distances.min()]
    return float(above.min()) if above.size else None


def ns_weights(distances: np.ndarray, epsilon: float, epsilon_next: float, form: str) -> np.ndarray:
    """Unnormalised survivor-selection weights (zero for e >= eps_next)."""
    kernel = 1.0 - (distances / epsilon) ** 2
    if form == "paper":
        w = kernel / np.maximum(distances, epsilon * 1e-12)  # an exact match (e = 0) stays finite
    else:
        w = kernel / epsilon
    return np.where((distances < epsilon_next) & (kernel > 0), w, 0.0)


def geometry_rng(seed: int, t: int) -> np.random.Generator:
    """The generator of population t's bound geometry (its volume's Monte Carlo): its own
    stream, so the paper variant's survivors are unchanged by it."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(t, 0, 1)))


#: Monte Carlo draws per model for the volume of its bound. 10,000 (20,000 until issue 24's
#: cheap-kernel work): the log volume's standard error is ~0.005 on §4.1 (0.0035 at 20,000,
#: 0.007 at 5,000; medians over seeds 1-20), far below the evidence's other errors (~0.05, the
#: acceptance's binomial error), and it enters log Z's standard error. The volume was the
#: largest single cost of a cheap population's step (docs/benchmarks.md, issue 24's notes).
VOLUME_DRAWS = 10_000


#: a model's bound geometry (log prior mass, its standard error, and its particles' rows with
#: their parts in the bound: ``abcns.mixture`` codes, ``Population.held``)
GeometryResult = tuple[float, float, tuple[np.ndarray, np.ndarray]]
#: its measurement, given the population's geometry generator
Geometry = Callable[[np.random.Generator], GeometryResult]


@dataclass(frozen=True, eq=False)
class Step:
    """What finishing a population gives (see :func:`finish_population`): everything the next
    population's proposals need. The geometry of the new bounds (their prior volume, and
    whether each holds the particles it was fitted to when refitted without them), which only
    the evidence of the *next* population uses, is measured by :meth:`evidence`, so a runner can
    overlap it with the next population's simulations."""

    epsilon_next: float
    weights: np.ndarray
    survivors: np.ndarray
    bounds: tuple[bd.Union, ...]
    model_probabilities: np.ndarray
    notes: list[str]
    counted: ev.Evidence  # the evidence but its bounds' geometry (that of a model without a bound)
    geometry_jobs: tuple[Geometry | None, ...]
    tied: bool = False  # every particle has the same distance: no lower tolerance exists
    kept: tuple[int, ...] = ()  # the models whose thin reading held eps_next up (:func:`abcns.likelihood.kept`)

    def evidence(self, geometry: np.random.Generator) -> tuple[ev.Evidence, np.ndarray]:
        """(the population's evidence bookkeeping, each particle's part in its model's new
        bound: ``Population.held``), its bounds' geometry measured now with ``geometry``
        (used model by model, in model order)."""
        c = self.counted
        log_volume, log_volume_se = c.log_volume.copy(), c.log_volume_se.copy()
        held = np.full((self.weights.shape[0], len(self.geometry_jobs)), NOT_FITTED, np.int8)
        for m, job in enumerate(self.geometry_jobs):
            if job is not None:
                log_volume[m], log_volume_se[m], (rows, flags) = job(geometry)
                held[rows, m] = flags
        return dataclasses.replace(c, log_volume=log_volume, log_volume_se=log_volume_se), held


def finish_population(
    models: Sequence[Model],
    frames: Sequence[bd.Frame],
    t: int,
    epsilon: float,
    which: np.ndarray,
    theta: np.ndarray,
    distances: np.ndarray,
    is_new: np.ndarray,
    filled: Filled,
    previous: Population | None,
    mixture: Mixture,
    settings: NSSettings,
    rng: np.random.Generator,
    lower: float | None = None,
    spared: Callable[[float, np.ndarray, np.ndarray], np.ndarray | None] | None = None,
    holding: Keep | None = None,
) -> Step:
    """eps_next (:func:`next_tolerance`, not below ``lower``, raised by ``holding``: :func:`_next`),
    weights per model, the evidence (``abcns.evidence.estimate``, from the ``mixture`` grown
    with this population: ``abcns.mixture``), what the variant decides
    (``abcns.variants``: deaths, but not of the ``spared``, survivors, bounds, allocation);
    the evidence once :meth:`Step.evidence` has measured the bounds. All particles at one
    distance: eps_next is eps_t (``Step.tied``), the run must stop."""
    n_models, variant = len(models), variant_of(settings)
    n_proposed, n_accepted = filled.counts(n_models)
    previous_evidence = previous.evidence if previous is not None else None
    assert previous is None or previous_evidence is not None
    found, eps_next, est, kept = _next(epsilon, which, distances, n_proposed, n_accepted, previous_evidence, mixture,
                                       settings.n_drop, lower, holding)
    copies = same_models(models) if variant.fits_all else [[] for _ in models]
    est, relayed = _relayed(models, copies, which, theta, distances < eps_next, is_new, est)
    raw = ns_weights(distances, epsilon, eps_next, settings.weights)
    counts, positive = np.bincount(which, minlength=n_models), raw > 0
    capacity = np.bincount(which, weights=positive, minlength=n_models).astype(np.int64)
    alive_now = ev.alive(counts, n_proposed, previous_evidence)

    spare = None if spared is None else functools.partial(spared, eps_next, est.log_z, np.sqrt(est.var_z))
    quotas, death = variant.survive(models, est, counts, capacity, alive_now, previous_evidence, spare)
    alive_next = death == ev.ALIVE
    failed = (death != ev.ALIVE) & (n_proposed > 0) & (filled.failures(n_models) == n_proposed)
    death = np.where(failed, ev.SIMULATIONS_FAILED, death)
    notes = _survival_notes(t, models, est, death, alive_now & ~alive_next, int(quotas.sum()), settings.n_survivors,
                            [(m, copies[m]) for m in relayed if alive_next[m]])
    weights = np.zeros_like(raw)
    survivors = np.zeros(which.shape[0], dtype=bool)
    bounds: list[bd.Union] = []
    geometry_jobs: list[Geometry | None] = []
    for m, model in enumerate(models):
        rows = np.flatnonzero((which == m) & positive)
        if rows.size:
            weights[rows] = raw[rows] / raw[rows].sum()
        if not alive_next[m] or (quotas[m] == 0 and m not in relayed):
            bounds.append(())
            geometry_jobs.append(None)
            continue
        keep = rng.choice(rows, size=int(quotas[m]), replace=False, p=weights[rows]) if quotas[m] else rows[:0]
        survivors[keep] = True
        frame = frames[m]
        others = np.flatnonzero(np.isin(which, copies[m]) & positive) if copies[m] else None
        points, fitted = _fitted_points(model, frame, theta, rows, others)
        prev_bound = previous.ellipsoids[m] if previous is not None else ()
        bound, groups = variant.bound(points, theta[np.sort(keep), : model.n_dim], frame,
                                      _fallback(prev_bound, frame, settings))
        notes += [f"population {t}: ellipsoid of {model.name} {e.note} ({rows.size} points)" for e in bound if e.note]
        bounds.append(bound)
        geometry_jobs.append(_geometry_job(bound, frame, points, fitted, groups, settings.enlargement))

    acceptance = np.where(n_proposed > 0, n_accepted / np.maximum(n_proposed, 1), 0.5)
    alloc, probabilities = variant.proposals(models, est, counts, acceptance, alive_next)
    counted = ev.Evidence(log_z=est.log_z, log_z_se=np.sqrt(est.var_z), log_z_next=est.log_z_next,
                          log_z_next_se=np.sqrt(est.var_next), log_volume=np.full(n_models, np.nan),
                          log_volume_se=np.full(n_models, np.nan), allocation=alloc, n_proposed=n_proposed,
                          n_accepted=n_accepted, death=death)
    notes += _tolerance_notes(t, models, float(distances[0]), found, eps_next, kept)
    return Step(eps_next, weights, survivors, tuple(bounds), probabilities, notes, counted, tuple(geometry_jobs),
                tied=found is None, kept=tuple(kept))


def _survival_notes(t: int, models: Sequence[Model], est: ev.Estimate, death: np.ndarray, dying: np.ndarray,
                    n_kept: int, n_survivors: int, relayed: list[tuple[int, list[int]]]) -> list[str]:
    """What population t's survival step says: the ``relayed`` copies (with their twins), the
    ``dying`` models and why, and a shortfall of survivors (``n_kept`` of ``n_survivors``)."""
    notes = [f"population {t}: {models[m].name} has no particle below the next tolerance; its evidence there is read "
             f"from the particles of {', '.join(models[j].name for j in twins)} (the same model) inside its prior "
             "box, and its bound fitted to them" for m, twins in relayed]
    notes += [f"population {t}: {models[m].name} dies ({ev.DEATH_RULES[int(death[m])]}; p = {est.p_next[m]:.3g} at "
              "the next tolerance)" for m in map(int, np.flatnonzero(dying))]
    if n_kept < n_survivors:
        notes.append(f"population {t}: only {n_kept} survivors (ties at eps_next, or few particles of the "
                     "alive models below it); the next population draws more new particles")
    return notes


def _tolerance_notes(t: int, models: Sequence[Model], first: float, found: float | None, eps_next: float,
                     kept: list[int]) -> list[str]:
    """What population t's next tolerance says: none below the distance ``first`` all its
    particles share (``found`` None: ties), or raised from ``found`` for the ``kept`` models."""
    if found is None:
        return [f"population {t}: every particle has the distance {first:.6g}; no tolerance below it leaves a "
                "particle, so the run stops (ties)"]
    if not kept:
        return []
    return [f"population {t}: the next tolerance is held at {eps_next:.6g} (not {found:.6g}) for "
            f"{', '.join(models[m].name for m in kept)}: fewer than 2 (d + 1) of its particles below {found:.6g}, "
            "and its likelihood reading would rest on fewer than 2 (d + 1) effective particles"]


#: what raises a population's next tolerance for models that would leave the run on a thin
#: reading: (eps_next, log Z and its standard error per model) -> (eps_next, the models)
#: (:func:`abcns.likelihood.kept`, bound to the run's reading and the population)
Keep = Callable[[float, np.ndarray, np.ndarray], tuple[float, list[int]]]


def _next(epsilon: float, which: np.ndarray, distances: np.ndarray, n_proposed: np.ndarray, n_accepted: np.ndarray,
          previous: ev.Evidence | None, mixture: Mixture, n_drop: int, lower: float | None,
          keep: Keep | None) -> tuple[float | None, float, ev.Estimate, list[int]]:
    """(the tolerance the distances give, :func:`next_tolerance`; eps_next; the evidence
    estimate at it; the models ``keep`` raised eps_next for). ``keep`` is asked with the
    population's log Z (which does not depend on eps_next), and the estimate made again at
    the raised eps_next."""
    found = next_tolerance(distances, n_drop, lower)
    eps_next = epsilon if found is None else found
    est = ev.estimate(which, distances, epsilon, eps_next, n_proposed, n_accepted, previous, mixture)
    if keep is None or found is None:
        return found, eps_next, est, []
    raised, kept = keep(eps_next, est.log_z, np.sqrt(est.var_z))
    if not kept:
        return found, eps_next, est, []
    return found, raised, ev.estimate(which, distances, epsilon, raised, n_proposed, n_accepted, previous, mixture), kept


def _relayed(models: Sequence[Model], copies: Sequence[Sequence[int]], which: np.ndarray, theta: np.ndarray,
             below: np.ndarray, is_new: np.ndarray, est: ev.Estimate) -> tuple[ev.Estimate, list[int]]:
    """(the estimate, the models it relays): a model alive now with no particle ``below`` the
    next tolerance (no prediction there) whose copies (``copies``, :func:`same_models`) have
    particles below it inside its prior box takes its prediction from theirs. The same model
    under prior p_m has Z_m = Z_j E_j[p_m / p_j] for any copy j (its ABC posterior at eps_next
    under p_j); E_j is the mean over j's new particles below eps_next (uniform in j's region
    there, as the prediction's share takes them; all of j's particles below it if none is new),
    its log's variance the delta method's, var(ratio) / (n mean^2) (one particle in m's box
    among n: about 1). Several copies are combined by inverse variance."""
    log_next, var_next, relayed = est.log_z_next.copy(), est.var_next.copy(), []
    for m, twins in enumerate(copies):
        if not twins or np.isfinite(est.log_z_next[m]) or not np.isfinite(est.log_z[m]):
            continue
        model = models[m]
        for j in twins:
            rows = np.flatnonzero((which == j) & below & is_new)
            rows = rows if rows.size else np.flatnonzero((which == j) & below)
            x = theta[rows, : model.n_dim]
            inside = model.in_prior(x)
            if not inside.any():
                continue
            log_ratio = model.log_prior_density(x[inside]) - models[j].log_prior_density(x[inside])
            top = float(log_ratio.max())
            ratio = np.zeros(rows.size)
            ratio[inside] = np.exp(log_ratio - top)
            mean = float(ratio.mean())
            log_next[m], var_next[m] = ev.combine(log_next[m], var_next[m], est.log_z_next[j] + top + math.log(mean),
                                                  est.var_next[j] + float(ratio.var()) / (rows.size * mean**2))
        if np.isfinite(log_next[m]):
            relayed.append(m)
    if not relayed:
        return est, relayed
    p_next, se_next = ev.probabilities(log_next, np.sqrt(var_next))
    return dataclasses.replace(est, log_z_next=log_next, var_next=var_next, p_next=p_next, se_next=se_next), relayed


def _fallback(previous_bound: bd.Union, frame: bd.Frame, settings: NSSettings) -> ell.Ellipsoid:
    """The ellipsoid a fit falls back to when its points cannot make one: the previous bound's
    largest, without its enlargement, or the prior box's."""
    if not previous_bound:
        return frame.box_ellipsoid()
    largest = max(previous_bound, key=lambda e: e.log_volume)
    return ell.from_matrix(largest.centre, largest.matrix / settings.enlargement)


def _fitted_points(model: Model, frame: bd.Frame, theta: np.ndarray, rows: np.ndarray,
                   others: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(the points model m's bound is fitted to, in its frame, their rows): its particles
    below the next tolerance (``rows``), then those of the models it is the same model as
    (``others``, their rows; None: it has none) inside its prior box."""
    points = frame.to_frame(theta[rows, : model.n_dim])
    if others is None or not others.size:
        return points, rows
    others = others[model.in_prior(theta[others, : model.n_dim])]
    return np.vstack([points, frame.to_frame(theta[others, : model.n_dim])]), np.concatenate([rows, others])


def _geometry_job(bound: bd.Union, frame: bd.Frame, points: np.ndarray, rows: np.ndarray,
                  groups: list[np.ndarray] | None, enlargement: float) -> Geometry:
    """The measurement of one model's new bound, for :meth:`Step.evidence`: (log prior mass
    of the bound by Monte Carlo, its standard error, and (``rows``, their parts in the bound:
    ``abcns.mixture`` codes): the population's rows of ``points``, the model's own and its
    copies', each HELD or OUTSIDE by the bound refitted without it
    (:func:`abcns.mixture.held_without`) when the bound's ellipsoids were fitted to
    ``groups`` of ``points`` with this ``enlargement`` (the evidence variant); else (None)
    NOT_FITTED (the paper's bound, fitted to the survivors: the mixture reads their
    membership as it is)."""

    def measure(geometry: np.random.Generator) -> GeometryResult:
        if groups is not None:
            held = held_without(points, rows.size, bound, groups, enlargement)
            flags = np.where(held, HELD, OUTSIDE).astype(np.int8)
        else:
            flags = np.full(rows.size, NOT_FITTED, np.int8)
        log_v, log_v_se = bd.union_volume(bound, frame.box, VOLUME_DRAWS, geometry)
        return log_v - frame.log_box_volume, log_v_se, (rows, flags)

    return measure


@dataclass(frozen=True, eq=False)
class BoundProposer:
    """Each proposal picks a model (with equal probability among those with a bound when
    ``allocation`` is None, the paper's rule; else by ``allocation``), then a point uniform
    in its bound, redrawn until inside the prior box. ``redraws[i]`` is the number of
    out-of-box draws before proposal i, exactly as a one-at-a-time loop would count them."""

    models: tuple[Model, ...]
    frames: tuple[bd.Frame, ...]
    bounds: tuple[bd.Union, ...]
    allocation: np.ndarray | None
    max_redraws: int

    @functools.cached_property
    def _cdf(self) -> np.ndarray:
        """``allocation``'s cumulative shares (:func:`bounds.cumulative`), made once for every
        batch the proposer draws."""
        assert self.allocation is not None
        return bd.cumulative(self.allocation)

    def __call__(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        alive = [m for m, b in enumerate(self.bounds) if b]
        if self.allocation is None:
            which = np.asarray(alive, dtype=np.int16)[rng.integers(len(alive), size=n)]
        else:  # rng.choice(len(models), size=n, p=allocation), by its own numbers
            which = bd.choose(self._cdf, n, rng).astype(np.int16)
        theta = pad(self.models, n)
        redraws = np.zeros(n, dtype=np.int64)
        for m in alive:
            rows = np.flatnonzero(which == m)
            if rows.size == 0:
                continue
            model, frame, bound = self.models[m], self.frames[m], self.bounds[m]

            def draw(k: int, g: np.random.Generator, b: bd.Union = bound, f: bd.Frame = frame) -> np.ndarray:
                return f.from_frame(bd.sample_union(b, k, g))

            # the model's prior box (model.in_prior's test: the frame holds its low and high)
            theta[rows, : model.n_dim], redraws[rows] = draw_inside(draw, frame.in_prior, rows.size, rng,
                                                                    self.max_redraws)
        return which, theta, redraws


def _stop_reason(stop: StopRules, at_floor: bool, t: int, eps: float, eps_next: float, tied: bool,
                 mark: Standing | None, decisions: Sequence[float | None], held: bool = False,
                 kept: bool = False) -> StopReason | None:
    """The rule that ends the run after population t: ties, the noise floor (``at_floor``:
    the run stops there, and this population's ``mark`` says it was accepted at the decision
    tolerance or below: :func:`abcns.noise.standing`; unless ``held``, a model's reading
    still thin: then the next population is accepted at the decision tolerance too, up to
    ``max_populations``), then ``stop``'s rules, which wait for the decision tolerance
    (:meth:`StopRules.reason_after`) while it holds still (:func:`abcns.noise.waited_for` of
    ``decisions``, one per population); a step that a model's thin reading set (``kept``:
    :func:`abcns.likelihood.kept`) is that model's, not the run's: no stall, no
    ``min_epsilon_decrease``."""
    if tied:
        return StopReason.TIES
    if at_floor and mark is not None and mark.reached:
        if held and (stop.max_populations is None or t < stop.max_populations):
            return None
        return StopReason.NOISE_FLOOR  # the lowest population tolerance above the floor
    return stop.reason_after(eps, eps_next, t, decrease=not kept, decision=waited_for(decisions))


def _with_survivors(pop: Population, filled: Filled) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(models, theta, distances, is_new) of the population made of ``pop``'s survivors and
    the new particles ``filled``."""
    assert pop.survivors is not None  # set on every ABC-NS population
    keep = np.flatnonzero(pop.survivors)
    return (np.concatenate([pop.models[keep], filled.models]), np.concatenate([pop.theta[keep], filled.theta]),
            np.concatenate([pop.distances[keep], filled.distances]),
            np.concatenate([np.zeros(keep.size, bool), np.ones(filled.models.shape[0], bool)]))


def abc_ns(
    models: Sequence[Model],
    executor: Executor,
    settings: NSSettings = NSSettings(),
    stop: StopRules = StopRules(),
    seed: int = 0,
    *,
    history: Sequence[Population] = (),
    budget: Budget | None = None,
    clock: Callable[[], float] = time.monotonic,
    cancel: Callable[[], bool] | None = None,
    noise: Noise | None = None,
) -> Generator[Population, None, RunEnd]:
    """Yield ABC-NS populations until a stop rule holds; return a :class:`RunEnd`.

    ``history`` resumes a run: every population already done (the likelihood reading, which
    decides deaths and the holding of the floor, reads them all);
    ``budget`` then carries the simulations and seconds already spent. ``noise``: what is
    known of the distance's noise (``abcns.noise``): each population then carries the noise
    floor as estimated so far, and the evidence variant stops at the decision tolerance
    (``stop.noise_floor``): when the (alpha N)-th largest distance falls below it, the next
    population is accepted at the decision tolerance itself, and the run stops after it
    (while a model's reading is thin, :meth:`_Run.held`, after a few more there).

    Once a population is full and finished (:func:`finish_population`), the next one is
    opened (``executor.map``: an executor that runs ahead starts simulating) before this one's
    bound geometry is measured (:meth:`Step.evidence`) and the population is yielded; its
    own random streams make the order irrelevant to the result.
    """
    settings.check_particles(models)
    run = _Run(models, executor, settings, stop, seed, budget or Budget(stop, clock, cancel), history, noise)
    return (yield from run.populations(history))


class _Run:
    """One ABC-NS run's state between populations (:func:`abc_ns`)."""

    def __init__(self, models: Sequence[Model], executor: Executor, settings: NSSettings, stop: StopRules,
                 seed: int, budget: Budget, history: Sequence[Population], noise: Noise | None):
        self.models, self.executor, self.settings, self.stop, self.seed = models, executor, settings, stop, seed
        self.budget = budget
        self.source, self.n_pilot = "resumed" if history else "given", 0
        self.notes: list[str] = []
        self.variant = variant_of(settings)
        self.frames = [bd.Frame(m, unit=self.variant.unit_box) for m in models]
        self.floors = Tracker(noise, models, history)
        self.decisions = [None if p.floor is None else p.floor.decision for p in history]
        self.dims = [m.n_dim for m in models]
        # every particle so far in the mixture of the regions that proposed them: the evidence
        # and the likelihood reading (abcns.mixture), grown again over a resumed run's history.
        # The run's own decisions read each same_model_as copy from its own particles; the
        # answer reads them together (Result.reading; docs/design.md, "Copies read together")
        self.mixture = Mixture.of(history, self.frames, self.dims)
        self.at_floor = self.variant.reads_floor and stop.noise_floor and noise is not None
        # the first population accepted at the decision tolerance or below (:meth:`held`)
        self.first_reached = next((p.t for p, mark in zip(history, standings(history), strict=True)
                                   if mark is not None and mark.reached), None)
        self.pending: Filling | None = None  # the next population, started
        # the populations in a row, up to the last, whose next tolerance a leaving model's thin
        # reading held up (:meth:`keeper`; at most likelihood.HELD_POPULATIONS)
        self.kept_in_a_row = 0
        for pop in reversed(history):
            if not self.was_kept(pop):
                break
            self.kept_in_a_row += 1

    def end(self, reason: StopReason) -> RunEnd:
        return RunEnd(reason, self.budget.n_simulations, self.n_pilot, self.source, tuple(self.notes), self.mixture)

    def start(self, t: int, eps: float, bounds: Sequence[bd.Union], allocation: np.ndarray, n_survivors: int) -> Filling:
        """Open population t: proposals from ``bounds`` by the evidence's ``allocation`` (the
        evidence variant) or the paper's rule; N particles in every population (when fewer
        than beta N survive, more are new)."""
        s = self.settings
        propose = BoundProposer(tuple(self.models), tuple(self.frames), tuple(bounds),
                                allocation if self.variant.allocates else None, s.max_redraws)
        return Filling(propose, s.particles - n_survivors, eps, self.executor, seed=self.seed, t=t,
                       batch_size=s.batch_size)

    def complete(self, t, eps, which, theta, distances, is_new, filled, previous) -> tuple[Population, StopReason | None]:
        """Finish population t; when the run goes on, open population t + 1 (an executor that
        runs ahead starts simulating) before this one's bound geometry is measured."""
        floor = self.floors.after(which, distances)
        lower = floor.decision if self.at_floor and floor is not None else None
        before = self.mixture if self.variant.reads_floor else None  # the reading without this population
        self.mixture = self.mixture.grown(previous, eps, which, theta, distances, is_new, filled.counts(len(self.models))[0])

        def spared(eps_next: float, log_z: np.ndarray, log_z_se: np.ndarray) -> np.ndarray | None:
            return likelihood.spared(before, self.dims, floor, self.settings.death_probability, self.mixture)

        step = finish_population(self.models, self.frames, t, eps, which, theta, distances, is_new, filled, previous,
                                 self.mixture, self.settings, population_rng(self.seed, t), lower,
                                 spared if before is not None else None, self.keeper(floor, which, distances))
        self.kept_in_a_row = self.kept_in_a_row + 1 if step.kept else 0
        self.notes.extend(step.notes)
        self.decisions.append(None if floor is None else floor.decision)
        mark = standing(eps, floor if previous is None else previous.floor)
        if self.first_reached is None and mark is not None and mark.reached:
            self.first_reached = t
        held = self.held(t, mark, floor, step.model_probabilities > 0)
        reason = _stop_reason(self.stop, self.at_floor, t, eps, step.epsilon_next, step.tied, mark, self.decisions,
                              bool(held), bool(step.kept))
        if reason is None and held:
            self.notes.append(f"population {t}: accepted at the decision tolerance {eps:.6g}; the reading of "
                              f"{', '.join(held)} rests on fewer than max({likelihood.HELD_EFFECTIVE} (d + 1), "
                              f"{likelihood.HELD_LEAST}) effective particles: the run goes on at the decision tolerance")
        if reason is StopReason.NOISE_FLOOR:
            assert floor is not None
            self.notes.append(f"population {t}: accepted at the decision tolerance {eps:.6g}; the run stops (noise "
                              f"floor now {floor.floor:.6g} + its spread {floor.spread:.3g})")
        if reason is None and self.budget.reason() is None:
            self.pending = self.start(t + 1, step.epsilon_next, step.bounds, step.counted.allocation,
                                      int(np.count_nonzero(step.survivors)))
        evidence, held_flags = step.evidence(geometry_rng(self.seed, t))
        pop = population_from(
            t, eps, step.epsilon_next, which, theta, distances, step.weights, filled, self.budget.elapsed(),
            step.model_probabilities, survivors=step.survivors, ellipsoids=step.bounds,
            evidence=evidence, held=held_flags, floor=floor, standing=mark,
        )
        return pop, reason

    def keeper(self, floor: Floor | None, which: np.ndarray, distances: np.ndarray) -> Keep | None:
        """What raises population t's next tolerance for a model that would leave the run on a
        thin reading (:func:`abcns.likelihood.kept`: the reading with this population, whose
        particles are ``which``, ``distances``); None for a run without a reading, and once
        :data:`abcns.likelihood.HELD_POPULATIONS` populations in a row were held up so (the MR
        damper's Bouc-Wen, at its own floor, held the tolerance at 15.668 for 130 populations:
        its best particles no longer shrink its region, and the mixture's weights stay on the
        earlier, wider regions' particles, so its reading never fills). (Death by
        probability takes its probability from the reading so far, without this population's
        particles (:func:`abcns.likelihood.spared`): read with them, the losing cubic-quintic of the
        exact-Bayes benchmark left one population earlier in seeds 2 and 4, on 10-11
        effective particles, its ln Bayes factor 2.4 and 1.4 nats low, against 0.4 and 0.2.)"""
        if not self.variant.reads_floor or floor is None or self.kept_in_a_row >= likelihood.HELD_POPULATIONS:
            return None

        def keep(eps_next: float, log_z: np.ndarray, log_z_se: np.ndarray) -> tuple[float, list[int]]:
            return likelihood.kept(self.mixture, self.dims, floor, eps_next, which, distances)

        return keep

    def was_kept(self, pop: Population) -> bool:
        """Whether a stored population's next tolerance was raised by :meth:`keeper` (above the
        one its distances and the decision tolerance give)."""
        lower = pop.floor.decision if self.at_floor and pop.floor is not None else None
        found = next_tolerance(pop.distances, self.settings.n_drop, lower)
        return found is not None and pop.epsilon_next > found

    def held(self, t: int, mark: Standing | None, floor: Floor | None, alive: np.ndarray) -> list[str]:
        """The names of the ``alive`` models whose reading is thin (:func:`abcns.likelihood.thin`)
        after population t, accepted at the decision tolerance (``mark``), while the run may
        still hold it (at most :data:`abcns.likelihood.HELD_POPULATIONS` populations after the
        first accepted there); [] otherwise."""
        if not (self.at_floor and mark is not None and mark.reached and self.first_reached is not None
                and t - self.first_reached < likelihood.HELD_POPULATIONS):
            return []
        thin = likelihood.thin(self.mixture, self.dims, floor, alive)
        return [m.name for m, is_thin in zip(self.models, thin, strict=True) if is_thin]

    def populations(self, history: Sequence[Population]) -> Generator[Population, None, RunEnd]:
        """The populations after ``history`` (the first from the priors when it is empty)."""
        settings, budget = self.settings, self.budget
        try:
            if history:
                pop = history[-1]
                tied = next_tolerance(pop.distances, settings.n_drop) is None
                mark = standings(history[-2:])[-1]
                held = self.held(pop.t, mark, pop.floor, pop.model_probabilities > 0)
                reason = _stop_reason(self.stop, self.at_floor, pop.t, pop.epsilon, pop.epsilon_next, tied,
                                      mark, self.decisions, bool(held), self.was_kept(pop))
            else:
                eps, self.source, self.n_pilot = initial_epsilon(self.models, settings, self.executor, budget, self.seed)
                filled = fill(prior_proposer(self.models), settings.particles, eps, self.executor, budget,
                              seed=self.seed, t=1, batch_size=settings.batch_size)
                pop, reason = self.complete(1, eps, filled.models, filled.theta, filled.distances,
                                            np.ones(filled.models.shape[0], bool), filled, None)
                yield pop
            while reason is None:
                budget.check()
                assert pop.evidence is not None and pop.survivors is not None  # set on every ABC-NS population
                filling = self.pending or self.start(  # a resumed run opens it here
                    pop.t + 1, pop.epsilon_next, pop.ellipsoids, pop.evidence.allocation,
                    int(np.count_nonzero(pop.survivors)))
                self.pending = None
                filled = filling.finish(budget)
                pop, reason = self.complete(pop.t + 1, pop.epsilon_next, *_with_survivors(pop, filled), filled, pop)
                yield pop
        except Stopped as stopped:
            self.notes.extend(stopped.notes)
            return self.end(stopped.reason)
        finally:
            if self.pending is not None:
                self.pending.close()
        return self.end(reason)
