"""Sampler settings and stop rules: frozen, validated on construction."""

from __future__ import annotations

import enum
import itertools
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Literal, TypeGuard

from abcns.errors import InvalidSetting
from abcns.priors import Model


class StopReason(enum.StrEnum):
    """Why a run ended; stored with the result."""

    MIN_EPSILON_DECREASE = "min_epsilon_decrease"  # the paper's rule
    EPSILON_TARGET = "epsilon_target"
    SCHEDULE_END = "schedule_end"  # a given tolerance schedule was followed to its end
    MAX_POPULATIONS = "max_populations"
    MAX_SIMULATIONS = "max_simulations"
    MAX_SECONDS = "max_seconds"
    CANCELLED = "cancelled"
    PROPOSAL_EXHAUSTED = "proposal_exhausted"  # an ellipsoid lies (almost) outside the prior
    COMPLETED = "completed"  # a one-population algorithm (rejection) finished
    PILOT_FAILED = "pilot_failed"  # every prior-predictive simulation of the pilot failed or diverged
    NOISE_FLOOR = "noise_floor"  # the decision tolerance was reached (abcns.noise)
    # above the decision tolerance, the tolerance stopped moving towards it (StopRules.reason_after)
    STALLED = "stalled"
    TIES = "ties"  # every particle has the same distance: no lower tolerance leaves a particle
    # a population ran stop.max_simulations_without_acceptance simulations and accepted none
    NOTHING_ACCEPTED = "nothing_accepted"


class Stopped(Exception):
    """A stop rule ended a population before it was full (on a worker, ``run_draw`` turns it
    into the draw's ``stop`` field; it does not cross processes). ``note``: the sentence
    that says why, for the run's notes (None where the reason says it all)."""

    def __init__(self, reason: StopReason, note: str | None = None):
        super().__init__(reason.value)
        self.reason = reason
        self.note = note

    @property
    def notes(self) -> tuple[str, ...]:
        return () if self.note is None else (self.note,)

# The documented valid ranges of the numeric settings (docs/design.md, "The job spec"): what one process
# can hold and a run can count, not admission limits (a service sets lower ones).
MAX_PARTICLES = 10**8  # a population of 10^8 particles of 8 parameters is ~7 GB in the runner
MAX_BATCH_SIZE = 10**7
MAX_COUNT = 2**62  # simulations, populations, pilot sizes, redraws: counters in int64
MAX_SEED = 2**63 - 1  # numpy's SeedSequence takes any non-negative int; the store keeps int64
#: an alive model's least share of a population's new particles is this many per dimension
#: plus one, over the new particles (evidence variant; ``abcns.evidence.allocation``): an
#: ellipsoid fitted to 20 points uniform in a 3-d ball, enlarged by 1.1, holds 0.90 of it on
#: average, to 40 points 0.97, to 100 0.996 (10 (d + 1) points: 0.95-0.97 for d = 2..6), and
#: a rare model fitted to a handful of points lost most of its region population after
#: population, unmeasured (its evidence fell 100-fold on a toy whose exact p was 0.002)
LEAST_NEW_PER_DIMENSION = 10
#: ``NSSettings.min_model_probability``'s default: a model dies below it (evidence variant)
DEATH_PROBABILITY = 1e-3
MAX_ENLARGEMENT = 10.0  # f0 beyond 10 scales the ellipsoid past the prior box of any useful fit
MAX_ELLIPSOIDS = 64  # ``NSSettings.max_ellipsoids``' largest value (a store's ellipsoid dimension)
#: ``NSSettings.max_ellipsoids``' default: one ellipsoid per this many particles, at least
#: ``LEAST_ELLIPSOIDS`` (so up to 512 particles keep the former fixed 8, ~45 points below the
#: next tolerance per ellipsoid), at most ``MAX_ELLIPSOIDS``. A cap that does not grow with N
#: makes each ellipsoid of a larger population cover more of a curved or split region: on the
#: cyclic test gill (BWBN, 11-D, seed 1) the 1,400 points of a 2,000-particle population at
#: eps 3.78 were bounded by 7 ellipsoids of e^3.3 the total volume of 32 (e^2.3 inside the
#: box), and the run needed 19.5 M simulations to eps 3.0 against 1.5 M now (issue Y,
#: docs/benchmarks.md, "Mode loss and 2,000 particles")
PARTICLES_PER_ELLIPSOID = 64
LEAST_ELLIPSOIDS = 8

# The settings' fields are the job spec's sampler and stop sections (``service.spec`` builds
# its schema from them: types, Literal choices, defaults); a field with this metadata is a
# safety bound of the library, not a setting a job spec gives.
NOT_IN_SPEC = {"spec": False}


def _check(cond: bool, path: tuple[str, ...], message: str) -> None:
    if not cond:
        raise InvalidSetting(path, message)


def _is_number(x: object) -> TypeGuard[float]:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _is_int(x: object, low: int, high: int) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and low <= x <= high


def check_seed(seed: object) -> None:
    """A run's seed: an integer in [0, 2^63 - 1]."""
    _check(_is_int(seed, 0, MAX_SEED), ("seed",), f"must be an integer in [0, 2^63 - 1], got {seed!r}")


#: stop rules that do not count as "a stop rule set": the safety net ends a run that cannot
#: progress, never a healthy one, and the noise floor needs a noise model the run may not have
SAFETY_NETS = ("max_simulations_without_acceptance", "noise_floor", "decrease_above_floor")

#: above the decision tolerance, a population whose tolerance fell by less than this share of
#: its distance to the decision tolerance has stalled (StopReason.STALLED): a run approaching
#: its floor closes that distance by a share (1 - alpha)^(2/p) or more per population (0.1 or
#: more for p <= 20, alpha <= 0.5); a run held at a model's best fit above the floor closes
#: ever less of it (the paper variant on §4.1)
STALL_SHARE = 1e-3


@dataclass(frozen=True)
class StopRules:
    """When to stop. Budgets (simulations, seconds) are checked inside a population too.

    ``min_epsilon_decrease``: stop when eps_t - eps_{t+1} < this (paper, §3.1; an absolute
    difference of distances, % NMSE for the NMSE). In a run with a noise floor (an NMSE run)
    it ends the run only at or below the decision tolerance, unless ``decrease_above_floor``
    (a job spec that names ``min_epsilon_decrease`` sets it: a user's own rule is theirs):
    no default rule ends such a run above its decision tolerance, where its answer would be
    provisional (docs/design.md, "The noise floor and the decision tolerance"); a run that
    stalls there stops (``StopReason.STALLED``, :data:`STALL_SHARE`) and its summary says so;
    ``epsilon_target``: stop once a population was accepted at eps_t <= target;
    ``noise_floor``: the evidence variant stops at the decision tolerance, the lowest
    tolerance above the run's noise floor by its spread (``abcns.noise``), when the run knows
    its distance's noise model; the paper variant keeps its own rules (its summary still
    shows the decision);
    ``max_simulations_without_acceptance``: stop (``NOTHING_ACCEPTED``) when a population has
    run this many simulations without accepting one particle: the data, the priors and the
    model cannot meet at this tolerance (docs/design.md, "Stop", on the default). A safety
    net, not a rule that ends a healthy run: it does not count as "a stop rule set".
    """

    min_epsilon_decrease: float | None = 0.01
    epsilon_target: float | None = None
    max_populations: int | None = None
    max_simulations: int | None = None
    max_seconds: float | None = None
    noise_floor: bool = True
    max_simulations_without_acceptance: int | None = 1_000_000
    decrease_above_floor: bool = False

    def __post_init__(self) -> None:
        for name in ("min_epsilon_decrease", "epsilon_target", "max_seconds"):
            v = getattr(self, name)
            _check(v is None or (_is_number(v) and v > 0), ("stop", name), f"must be a positive number or null, got {v!r}")
        for name in ("max_populations", "max_simulations", "max_simulations_without_acceptance"):
            v = getattr(self, name)
            _check(
                v is None or _is_int(v, 1, MAX_COUNT),
                ("stop", name),
                f"must be an integer in [1, 2^62] or null, got {v!r}",
            )
        for name in ("noise_floor", "decrease_above_floor"):
            v = getattr(self, name)
            _check(isinstance(v, bool), ("stop", name), f"must be true or false, got {v!r}")
        rules = {k: v for k, v in asdict(self).items() if k not in SAFETY_NETS}
        _check(any(v is not None for v in rules.values()), ("stop",), "at least one stop rule must be set")

    def reason_after(self, epsilon: float, epsilon_next: float, t: int, decrease: bool = True,
                     decision: float | None = None) -> StopReason | None:
        """The rule that ends the run after population ``t`` (accepted at ``epsilon``, the
        next tolerance ``epsilon_next``), or None to go on; ``decrease``: whether
        ``min_epsilon_decrease`` applies (not along a given schedule); ``decision``: the
        run's decision tolerance as estimated now (None without a noise floor): above it,
        ``min_epsilon_decrease`` waits (unless ``decrease_above_floor``) and a stalled
        tolerance stops the run. Budgets are checked by :class:`abcns.filling.Budget`, inside
        populations too."""
        if self.epsilon_target is not None and epsilon <= self.epsilon_target:
            return StopReason.EPSILON_TARGET
        step = epsilon - epsilon_next
        if decision is not None and epsilon > decision and not self.decrease_above_floor:
            if decrease and step < STALL_SHARE * (epsilon - decision):
                return StopReason.STALLED
        elif decrease and self.min_epsilon_decrease is not None and step < self.min_epsilon_decrease:
            return StopReason.MIN_EPSILON_DECREASE
        if self.max_populations is not None and t >= self.max_populations:
            return StopReason.MAX_POPULATIONS
        return None


def _check_common(n_particles: object, batch_size: object, epsilon_initial: object, pilot_size: object) -> None:
    _check(pilot_size is None or _is_int(pilot_size, 2, MAX_COUNT), ("settings", "pilot_size"),
           f"must be an integer in [2, 2^62] or null, got {pilot_size!r}")
    _check(
        _is_int(n_particles, 2, MAX_PARTICLES),
        ("settings", "particles"),
        f"must be an integer in [2, {MAX_PARTICLES:.0e}], got {n_particles!r}",
    )
    _check(
        _is_int(batch_size, 1, MAX_BATCH_SIZE),
        ("settings", "batch_size"),
        f"must be an integer in [1, {MAX_BATCH_SIZE:.0e}], got {batch_size!r}",
    )
    _check(
        epsilon_initial is None or (_is_number(epsilon_initial) and epsilon_initial > 0),
        ("settings", "epsilon_initial"),
        f"must be a positive number or null (chosen from a pilot), got {epsilon_initial!r}",
    )


@dataclass(frozen=True)
class NSSettings:
    """ABC-NS hyperparameters (paper §2.2; defaults as in the paper and the authors' demo).

    alpha : share of particles dropped per population (alpha0); next eps is the
        (alpha N)-th largest distance.
    beta : share of particles kept as survivors (beta0); (1 - beta) N new per population.
    enlargement : f0, the factor on the ellipsoid matrix.
    weights : "paper" -> (1/e)(1 - (e/eps)^2); "kernel" -> (1/eps)(1 - (e/eps)^2) (demo).
    epsilon_initial : tolerance of the first population; None: a prior-predictive pilot of
        ``pilot_size`` simulations (default N) sets it to their ``pilot_quantile`` quantile.
    batch_size : proposals per batch (part of the random stream: the same batch size and
        seed give the same result on any number of workers).
    max_redraws : prior-bound redraws allowed per proposal before the run stops with
        PROPOSAL_EXHAUSTED.
    variant : "evidence" (default): model probabilities from each model's ABC evidence,
        proposals and survivors allocated by them, bounds fitted in each model's unit prior
        box to every particle below the next tolerance and split into several ellipsoids;
        "paper": Algorithm 2 as published and as the authors' demo runs it (particle shares,
        equal proposals, one ellipsoid on the survivors in raw units).
    max_ellipsoids : most ellipsoids in a model's bound (evidence variant; default one per
        64 particles, at least 8 and at most 64: :data:`PARTICLES_PER_ELLIPSOID`).
    min_model_probability : a model dies when its probability plus three standard errors
        falls below this in two populations in a row (evidence variant; default 1e-3).
    min_proposal_share : share of proposals every alive model gets at least (evidence
        variant; default 0.05, and at most half of all proposals go to such floors).
    """

    particles: int = 1000
    alpha: float = 0.3
    beta: float = 0.6
    enlargement: float = 1.1
    weights: Literal["paper", "kernel"] = "paper"
    epsilon_initial: float | None = None
    pilot_size: int | None = None
    pilot_quantile: float = 0.5
    batch_size: int = 25
    max_redraws: int = field(default=100_000, metadata=NOT_IN_SPEC)
    variant: Literal["evidence", "paper"] = "evidence"
    max_ellipsoids: int | None = None
    min_model_probability: float | None = None
    min_proposal_share: float | None = None

    def __post_init__(self) -> None:
        _check_common(self.particles, self.batch_size, self.epsilon_initial, self.pilot_size)
        _check(self.variant in ("evidence", "paper"), ("settings", "variant"),
               f"must be 'evidence' or 'paper', got {self.variant!r}")
        if self.variant == "paper":
            for name in ("max_ellipsoids", "min_model_probability", "min_proposal_share"):
                _check(getattr(self, name) is None, ("settings", name),
                       "applies to variant 'evidence' only (the paper variant has one ellipsoid, particle shares "
                       "and equal proposals)")
        _check(
            self.max_ellipsoids is None or (isinstance(self.max_ellipsoids, int) and not isinstance(self.max_ellipsoids, bool)
                                            and 1 <= self.max_ellipsoids <= MAX_ELLIPSOIDS),
            ("settings", "max_ellipsoids"), f"must be an integer in [1, {MAX_ELLIPSOIDS}], got {self.max_ellipsoids!r}",
        )
        for name, top in (("min_model_probability", 0.5), ("min_proposal_share", 0.5)):
            v = getattr(self, name)
            _check(v is None or (_is_number(v) and 0 <= v <= top), ("settings", name),
                   f"must lie in [0, {top}], got {v!r}")
        for name in ("alpha", "beta", "pilot_quantile"):
            v = getattr(self, name)
            _check(_is_number(v) and 0 < v < 1, ("settings", name), f"must lie in (0, 1), got {v!r}")
        _check(
            self.beta <= 1 - self.alpha + 1e-12,
            ("settings", "beta"),
            f"beta ({self.beta}) must not exceed 1 - alpha ({1 - self.alpha:g}): survivors are drawn "
            "from the particles left after dropping alpha N",
        )
        _check(
            _is_number(self.enlargement) and 1 <= self.enlargement <= MAX_ENLARGEMENT,
            ("settings", "enlargement"),
            f"must lie in [1, {MAX_ENLARGEMENT:g}], got {self.enlargement!r}",
        )
        _check(self.weights in ("paper", "kernel"), ("settings", "weights"), f"must be 'paper' or 'kernel', got {self.weights!r}")
        _check(self.n_drop >= 1, ("settings", "alpha"), f"alpha * particles rounds to {self.n_drop}; at least 1 must drop")
        _check(self.n_new >= 1, ("settings", "beta"), f"(1 - beta) * particles rounds to {self.n_new}; at least 1 must be new")
        _check(_is_int(self.max_redraws, 1, MAX_COUNT), ("settings", "max_redraws"), "must be an integer in [1, 2^62]")

    @property
    def evidence(self) -> bool:
        return self.variant == "evidence"

    @property
    def n_ellipsoids(self) -> int:
        """Most ellipsoids per model: 1 in the paper variant, else ``max_ellipsoids`` or its
        default, which grows with the particles (:data:`PARTICLES_PER_ELLIPSOID`)."""
        if not self.evidence:
            return 1
        if self.max_ellipsoids is not None:
            return self.max_ellipsoids
        return min(MAX_ELLIPSOIDS, max(LEAST_ELLIPSOIDS, -(-self.particles // PARTICLES_PER_ELLIPSOID)))

    @property
    def death_probability(self) -> float:
        return DEATH_PROBABILITY if self.min_model_probability is None else float(self.min_model_probability)

    @property
    def proposal_floor(self) -> float:
        return 0.05 if self.min_proposal_share is None else float(self.min_proposal_share)

    @property
    def n_drop(self) -> int:
        return round(self.alpha * self.particles)

    @property
    def n_survivors(self) -> int:
        return round(self.beta * self.particles)

    @property
    def n_new(self) -> int:
        return self.particles - self.n_survivors

    def check_particles(self, models: Sequence[Model]) -> None:
        """Is N large enough for the models' dimensions? Each model's share of survivors
        at equal model probabilities must be able to define an ellipsoid (d + 1 points)."""
        d_max = max(m.n_dim for m in models)
        per_model = self.n_survivors // len(models)
        _check(
            per_model >= d_max + 1,
            ("settings", "particles"),
            f"{self.particles} particles give {per_model} survivors per model with {len(models)} models; "
            f"a {d_max}-parameter model needs at least {d_max + 1}",
        )


@dataclass(frozen=True)
class SMCSettings:
    """ABC-SMC (Toni et al. 2009) with Beaumont's Gaussian kernel of twice the weighted
    covariance. Tolerances follow ``schedule`` when given (paper Fig. 2), else each next
    tolerance is the ``quantile`` of the current population's distances."""

    particles: int = 1000
    quantile: float = 0.5
    schedule: tuple[float, ...] | None = None
    epsilon_initial: float | None = None
    pilot_size: int | None = None
    pilot_quantile: float = 0.5
    batch_size: int = 25
    max_redraws: int = field(default=100_000, metadata=NOT_IN_SPEC)

    def __post_init__(self) -> None:
        _check_common(self.particles, self.batch_size, self.epsilon_initial, self.pilot_size)
        _check(_is_int(self.max_redraws, 1, MAX_COUNT), ("settings", "max_redraws"), "must be an integer in [1, 2^62]")
        for name in ("quantile", "pilot_quantile"):
            v = getattr(self, name)
            _check(_is_number(v) and 0 < v < 1, ("settings", name), f"must lie in (0, 1), got {v!r}")
        if self.schedule is not None:
            sched = tuple(float(e) for e in self.schedule)
            _check(len(sched) >= 1 and all(e > 0 and math.isfinite(e) for e in sched), ("settings", "schedule"),
                   "must hold finite positive tolerances")
            _check(all(a >= b for a, b in itertools.pairwise(sched)), ("settings", "schedule"), "must not increase")
            object.__setattr__(self, "schedule", sched)

    def check_particles(self, models: Sequence[Model]) -> None:
        d_max = max(m.n_dim for m in models)
        _check(
            self.particles // len(models) >= d_max + 1,
            ("settings", "particles"),
            f"{self.particles} particles are too few for {len(models)} models of up to {d_max} parameters",
        )


@dataclass(frozen=True)
class RejectionSettings:
    """ABC rejection (paper Algorithm 1): N particles from the priors below epsilon."""

    particles: int = 1000
    epsilon_initial: float | None = None
    pilot_size: int | None = None
    pilot_quantile: float = 0.5
    batch_size: int = 25

    def __post_init__(self) -> None:
        _check_common(self.particles, self.batch_size, self.epsilon_initial, self.pilot_size)
        _check(_is_number(self.pilot_quantile) and 0 < self.pilot_quantile < 1, ("settings", "pilot_quantile"),
               f"must lie in (0, 1), got {self.pilot_quantile!r}")

    def check_particles(self, models: Sequence[Model]) -> None:
        return None
