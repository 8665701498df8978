"""The summary's warnings: why a run's answer may not be what it looks like, as the sentences
a user reads (the CLI's ``warning:`` lines, the live page, ``GET /jobs/{id}/result``).

:mod:`abcns.result` holds what the run computed (its populations, the decision population,
the model probabilities, the posterior); this module only reads a :class:`abcns.Result` and
says in words what in it a user should know. It lives in the core, not in ``service/report``,
because the summary the core makes (:meth:`abcns.Result.summary`) carries the warnings, and a
run in a notebook, with no service, shows them too.

- "no noise floor": the best fit fell with the tolerance (noise-free data, or a model that
  fits them exactly): the answer is the final population's;
- "provisional": the run stopped above its decision tolerance (:attr:`abcns.Result.provisional`);
- "floor above the run": the noise floor lies above every tolerance of the run (a stated
  noise larger than the data's misfit);
- "few effective particles": a provisional run's model whose likelihood reading rests on too
  few effective particles is read from its last tolerance's particles
  (:meth:`abcns.Result.answer_draws`), wider than the data's; or a run at its floor whose
  reading of a model still rests on fewer than :func:`abcns.likelihood.held_target` of them
  after it held the decision tolerance as long as it may (:func:`abcns.likelihood.thin`);
- "below the noise floor": the final population's model probabilities differ (by more than
  :data:`BELOW_FLOOR_CHANGE`) from those at the decision tolerance, which are the answer;
- "undecided": the answer holds two or more models above :data:`CONTENDER` while the
  tolerance sits at one model's best fit (its best distance is above :data:`AT_BEST_FIT` of
  the tolerance), so a lower tolerance could still separate them but that model holds it up;
- "failures": more than :data:`FAILURE_SHARE` of a model's simulations failed or diverged
  (counted as rejections: the model's probability and posterior hold only where its
  simulator works);
- "failed": a model died because every one of its simulations failed (death rule
  ``failed``): the data did not reject it, its simulator never ran.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from abcns.likelihood import HELD_EFFECTIVE, HELD_LEAST, enough, held_target
from abcns.noise import Standing

if TYPE_CHECKING:
    from abcns.result import Result

#: the share of a model's simulations that may fail or diverge before the summary warns
FAILURE_SHARE = 0.01
#: the change of a model probability from the decision population to the final one that is told
BELOW_FLOOR_CHANGE = 0.05
#: a model probability above which a model is still in contention
CONTENDER = 0.1
#: the share of the tolerance above which a model's best distance holds the tolerance up
AT_BEST_FIT = 0.5


def warnings(r: Result) -> list[str]:
    """Every warning of run ``r``, in the order of the module's list ([] before its first
    population)."""
    if not r.populations:
        return []
    return _floor(r) + _thin_reading(r) + _below_floor(r) + _undecided(r) + _failures(r)


def _floor(r: Result) -> list[str]:
    """Where the run stands to its noise floor: none found, stopped above it, or the floor above the run."""
    floor = r.floor
    if floor is None:
        return []
    out = []
    if not r.reached_floor and not r.floor_settled:
        out.append(f"no noise floor: the best fit fell with the tolerance to {floor.best:.4g} (the decision tolerance "
                   "halved within the last populations): noise-free data or a model that fits them exactly; the "
                   "answer is the final population's")
    if r.provisional:
        out.append(f"provisional: the run stopped ({r.stop_reason.value}) at eps {r.final.epsilon:.4g}, above "
                   f"the decision tolerance {floor.decision:.4g} (noise floor {floor.floor:.4g}); its model "
                   "probabilities and intervals are not yet those of the data: run it on (a larger budget, or "
                   "without the rule that stopped it)")
    pop = r.decision_population()
    if r.standings[pop.t - 1] is Standing.BELOW:
        out.append(f"floor above the run: the noise floor's decision tolerance {floor.decision:.4g} lies above every "
                   f"tolerance of the run (the highest {pop.epsilon:.4g}); the stated noise is larger than the "
                   "data's misfit")
    return out


def _thin_reading(r: Result) -> list[str]:
    """A warning per model whose posterior is not the likelihood reading's, as the run stopped
    above its floor and the reading rests on too few effective particles; and per model whose
    reading at the floor rests on fewer effective particles than the run holds its decision
    tolerance for."""
    reading, pop = r.reading(), r.decision_population()
    if reading is None:
        return []
    out = [f"few effective particles: {m.name}'s likelihood reading of this provisional run rests on "
           f"{reading.ess[i]:.3g} effective particles (fewer than 2 (d + 1) = {2 * (m.n_dim + 1)}), so its "
           f"intervals are those of population {pop.t}'s particles, the ABC posterior at eps {pop.epsilon:.4g}: "
           "wider than the data's"
           for i, m in enumerate(r.models) if i in r.alive(pop.t) and r.answer_draws(i)[2] == "tolerance"]
    if r.reached_floor:
        held = r.final.t - pop.t + 1
        many = enough(reading.ess, [m.n_dim for m in r.models], HELD_EFFECTIVE, HELD_LEAST)
        out += [f"few effective particles: {m.name}'s likelihood reading rests on {reading.ess[i]:.3g} effective "
                f"particles (fewer than max({HELD_EFFECTIVE} (d + 1), {HELD_LEAST}) = {held_target(m.n_dim)}) after {held} "
                f"populations at the decision tolerance: its means and intervals carry a Monte Carlo error of about "
                f"{1 / np.sqrt(max(reading.ess[i], 1)):.2g} posterior sd; a larger population (more particles) makes it "
                "smaller"
                for i, m in enumerate(r.models) if i in r.alive() and not many[i]]
    return out


def _below_floor(r: Result) -> list[str]:
    """The answer changed below the noise floor (read at the decision population, not by the likelihood)."""
    pop, final, floor = r.decision_population(), r.final, r.floor
    if pop is final or r.reading() is not None:
        return []
    if np.max(np.abs(final.model_probabilities - pop.model_probabilities)) <= BELOW_FLOOR_CHANGE:
        return []
    named = lambda q: ", ".join(f"{m.name} {v:.2f}" for m, v in zip(r.models, q, strict=True))
    return [f"below the noise floor: at the final tolerance {final.epsilon:.4g} (population "
            f"{final.t}) the model probabilities are {named(final.model_probabilities)}, but "
            f"at the decision tolerance {pop.epsilon:.4g} (population {pop.t}, above the noise floor "
            f"{floor.floor if floor else float('nan'):.4g}) they are {named(pop.model_probabilities)}: "
            "below the floor the model that fits the noise best wins; the answer is the latter"]


def _undecided(r: Result) -> list[str]:
    """Two or more models in contention while the tolerance sits at one model's best fit."""
    pop = r.decision_population()
    p = pop.model_probabilities
    contenders = [i for i in range(len(r.models)) if p[i] > CONTENDER]
    if len(contenders) < 2:
        return []
    for i in contenders:
        d = pop.distances[pop.models == i]
        if d.size and np.min(d) > AT_BEST_FIT * pop.epsilon:
            names = ", ".join(f"{r.models[j].name} (p = {p[j]:.2f})" for j in contenders)
            return [f"undecided: {names} are all above {CONTENDER:g} while the tolerance {pop.epsilon:.4g} sits at the "
                    f"best fit of {r.models[i].name} (its best distance {np.min(d):.4g}); a tolerance below "
                    "that would separate them"]
    return []


def _failures(r: Result) -> list[str]:
    """Models whose simulations failed: more than :data:`FAILURE_SHARE` of them, or every one (death rule ``failed``)."""
    out = [f"failures: {f['failed']} of {name}'s {f['simulations']} simulations "
           f"({100 * f['share']:.3g} %) failed or diverged; they count as rejections, so its "
           "probability and posterior hold only where its simulator works (a draw outside a simulator's stated domain, "
           "such as a restoring-force model's beta + gamma <= 0, counts here)"
           for name, f in r.failures().items() if f["share"] > FAILURE_SHARE]
    died = r.died_at()
    out += [f"failed: every simulation of {name} failed in population {died.get(name, '?')}, so it died "
            "without being compared with the data (check its fixed values and priors)"
            for name, rule in r.death_rules().items() if rule == "failed"]
    return out
