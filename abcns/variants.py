"""The two variants of ABC-NS (``NSSettings.variant``): what each decides when a population
is finished, beside the steps they share (:func:`abcns.nested.finish_population`).

A variant decides, from the population and its evidence estimate (``abcns.evidence``):

- **deaths and survivor quotas**: which models go on and how many survivors each keeps;
- **bounds**: the region each alive model's next proposals are drawn from;
- **proposals and probabilities**: the share of the next population's proposals each model
  gets, and the model probabilities the population reports.

``"paper"`` is the published algorithm as the authors' demo runs it; ``"evidence"`` (the
default) reads the model probabilities from each model's evidence: :class:`Paper` and
:class:`Evidence` state each.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from abcns import bounds as bd
from abcns import ellipsoid as ell
from abcns import evidence as ev
from abcns.priors import Model
from abcns.settings import LEAST_NEW_PER_DIMENSION, NSSettings


def apportion(total: int, shares: np.ndarray) -> np.ndarray:
    """Split ``total`` into integers proportional to ``shares`` (largest remainder)."""
    shares = np.asarray(shares, dtype=float)
    if total <= 0 or shares.sum() <= 0:
        return np.zeros(shares.shape, dtype=np.int64)
    exact = total * shares / shares.sum()
    base = np.floor(exact).astype(np.int64)
    remainder = total - int(base.sum())
    order = np.argsort(-(exact - base), kind="stable")
    base[order[:remainder]] += 1
    return base


def survivor_quotas(total: int, counts: np.ndarray, capacity: np.ndarray) -> np.ndarray:
    """Survivors per model: proportional to particle counts, capped by each model's
    positive-weight particles, shortfalls passed on to models with room left."""
    total = min(total, int(capacity.sum()))
    quota = np.minimum(apportion(total, counts), capacity)
    while quota.sum() < total:
        room = capacity - quota
        extra = apportion(total - int(quota.sum()), np.where(room > 0, counts + 1e-12, 0.0))
        quota = np.minimum(quota + extra, capacity)
    return quota


def _floored_quotas(total: int, shares: np.ndarray, capacity: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """Survivor quotas proportional to ``shares``, each at least min(floor, capacity) and at
    most its capacity; the floors are taken from the largest quotas."""
    quota = survivor_quotas(total, shares, capacity)
    need = np.minimum(floor, capacity)
    while np.any(quota < need):
        donors = np.flatnonzero(quota > need)
        if donors.size == 0:
            break
        quota[int(np.argmax(need - quota))] += 1
        quota[donors[np.argmax(quota[donors])]] -= 1
    return quota


def deaths(alive_now: np.ndarray, dying: np.ndarray, code: int) -> np.ndarray:
    """Death codes per model (``abcns.evidence.DEATH_RULES``): ALIVE for a model alive now,
    ``code`` for those ``dying``, DEAD_BEFORE for the others."""
    return np.where(dying, code, np.where(alive_now, ev.ALIVE, ev.DEAD_BEFORE)).astype(np.int64)


@dataclass(frozen=True)
class Paper:
    """The published algorithm: survivors per model follow particle counts, one ellipsoid per
    model fitted to its survivors in raw parameter units, proposals pick an alive model with
    equal probability, the probabilities are particle shares (Eq. 12), and a model with no
    survivors is dead."""

    settings: NSSettings

    def survive(self, models: Sequence[Model], est: ev.Estimate, counts: np.ndarray, capacity: np.ndarray,
                alive_now: np.ndarray, previous_evidence: ev.Evidence | None,
                spared: Callable[[], np.ndarray | None] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(survivor quotas per model, death codes: :func:`deaths`)."""
        quotas = survivor_quotas(self.settings.n_survivors, counts, capacity)
        return quotas, deaths(alive_now, alive_now & (quotas == 0), ev.NO_PARTICLES)

    def bound(self, points: np.ndarray, survivors: np.ndarray, frame: bd.Frame,
              fallback: ell.Ellipsoid) -> tuple[bd.Union, None]:
        """(one ellipsoid fitted to the survivors (theta) in ``frame`` (the raw coordinates:
        log theta for a log-uniform prior), enlarged by f0; None: not a fit of ``points``, so
        the mixture reads its membership as it is)."""
        return tuple(ell.fit_many([frame.to_frame(survivors)], fallback, enlargement=self.settings.enlargement)), None

    #: the bound is a model's own: not fitted to its copies' particles
    fits_all = False
    #: bounds in raw parameter units, proposals pick an alive model with equal probability, and
    #: the run neither stops at its noise floor nor reads by the likelihood
    unit_box = allocates = reads_floor = False

    def proposals(self, models: Sequence[Model], est: ev.Estimate, counts: np.ndarray, acceptance: np.ndarray,
                  alive_next: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the next population's proposal share per model, this population's probabilities)."""
        return alive_next / max(1, int(np.count_nonzero(alive_next))), counts / counts.sum()


@dataclass(frozen=True)
class Evidence:
    """Model probabilities from each model's evidence: survivors and proposals follow the
    probability predicted at eps_{t+1} (survivors at least 2 (d + 1) each while a model has
    them; proposals p / acceptance with a floor per alive model); a model dies when it has no
    particle below eps_{t+1} (a copy, ``same_model_as``, not while its twins have particles
    there inside its prior box), or when its probability plus three standard errors there falls
    below ``min_model_probability`` in two populations in a row; bounds are unions of
    ellipsoids fitted in the unit prior box to every particle below eps_{t+1}. With a noise
    floor, a model the likelihood reading still gives a share is spared
    (:func:`abcns.likelihood.spared`)."""

    settings: NSSettings

    def survive(self, models: Sequence[Model], est: ev.Estimate, counts: np.ndarray, capacity: np.ndarray,
                alive_now: np.ndarray, previous_evidence: ev.Evidence | None,
                spared: Callable[[], np.ndarray | None] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(survivor quotas per model, death codes: :func:`deaths`); ``spared``: the models the
        likelihood reading keeps from death by probability (:func:`abcns.likelihood.spared`),
        asked only when a model would die by it."""
        s = self.settings
        # no prediction at eps_next: no particle below it (a copy's may be relayed from its
        # twin's particles, abcns.nested._relayed)
        predicted = np.isfinite(est.log_z_next)
        death = deaths(alive_now, alive_now & ~predicted, ev.NO_PARTICLES)
        # by probability only when the previous population's prediction was below the threshold
        # too: one population's error bar can be wrong (a few in a thousand beyond 3 standard
        # errors), and death is for good
        improbable = alive_now & predicted & (est.p_next + 3 * est.se_next < s.death_probability)
        if previous_evidence is not None:
            p_was, se_was = ev.probabilities(previous_evidence.log_z_next, previous_evidence.log_z_next_se)
            improbable &= p_was + 3 * se_was < s.death_probability
        else:
            improbable[:] = False
        kept = spared() if spared is not None and improbable.any() else None
        if kept is not None:
            improbable &= ~kept
        death = np.where(improbable, ev.IMPROBABLE, death)
        alive_next = death == ev.ALIVE
        shares = np.where(alive_next, est.p_next, 0.0)
        floor = np.array([bd.min_points(m.n_dim) for m in models])
        return _floored_quotas(s.n_survivors, shares, np.where(alive_next, capacity, 0), floor), death

    def bound(self, points: np.ndarray, survivors: np.ndarray, frame: bd.Frame,
              fallback: ell.Ellipsoid) -> tuple[bd.Union, list[np.ndarray]]:
        """(a union of ellipsoids fitted to every particle below eps_{t+1} (``points``, already
        in the unit box), the rows of ``points`` each ellipsoid is fitted to: the mixture reads
        its membership of them leave-one-out, ``abcns.mixture.held_without``)."""
        return bd.fit_union_groups(points, self.settings.enlargement, self.settings.n_ellipsoids, fallback)

    #: the bound is fitted to every point below eps_{t+1}, its copies' particles too
    fits_all = True
    #: bounds in each model's unit prior box; proposals by the evidence's allocation; the run
    #: stops at its noise floor (``StopRules.noise_floor``) and reads by the likelihood
    unit_box = allocates = reads_floor = True

    def proposals(self, models: Sequence[Model], est: ev.Estimate, counts: np.ndarray, acceptance: np.ndarray,
                  alive_next: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the next population's proposal share per model, this population's probabilities)."""
        s = self.settings
        least = np.array([LEAST_NEW_PER_DIMENSION * (m.n_dim + 1) for m in models]) / max(1, s.particles - s.n_survivors)
        return ev.allocation(est.p_next, acceptance, alive_next, s.proposal_floor, least), est.p_now


def variant_of(settings: NSSettings) -> Paper | Evidence:
    """The variant ``settings`` selects."""
    return Evidence(settings) if settings.evidence else Paper(settings)
