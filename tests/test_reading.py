"""The answer of an NMSE run (issue W): no default rule ends it above its decision tolerance,
the floor stop ends at the first population accepted there, and the answer is read by
weighting every population with the Gaussian likelihood (``abcns.likelihood``), so the model
probabilities and intervals are those of exact Bayesian inference with the same noise.

The toy: a straight line with Gaussian noise (sd 0.1, 100 points), fitted by a line
(a, b) and by a parabola (a, b, c), both linear in their parameters, so the exact
posterior and evidence are closed-form (a Gaussian in a box the posterior lies well inside:
the box's cut is below 1e-12 of the mass for these data). The spec states the noise (sd
0.1), as exact Bayes knows it.
"""

import dataclasses
import math

import numpy as np
import pytest

import abcns
from abcns import OK, Model, NSSettings, StopReason, StopRules, per_model
from abcns.distances import NMSE
from abcns.executor import SerialExecutor
from abcns.mixture import Mixture
from abcns.noise import Standing, standings
from abcns.run import iterate

X = np.linspace(-1, 1, 100)
SIGMA = 0.1
DESIGNS = {"line": np.stack([np.ones_like(X), X], axis=1), "parabola": np.stack([np.ones_like(X), X, X**2], axis=1)}


def data(seed: int) -> np.ndarray:
    return 1.0 + 2.0 * X + SIGMA * np.random.default_rng(100 + seed).standard_normal(X.size)


def linear(y: np.ndarray, width: float = 3.0):
    """(models, evaluate, the NMSE) of a line and a parabola fitted to ``y``; the parabola's
    c ~ U(-width, width)."""
    nmse = NMSE(y)

    def simulator(design):
        return lambda theta, _rng: (nmse(theta @ design.T), np.full(theta.shape[0], OK, np.int8))

    models = [Model("line", {"a": (0, 2), "b": (0, 4)}),
              Model("parabola", {"a": (0, 2), "b": (0, 4), "c": (-width, width)})]
    return models, per_model([simulator(DESIGNS["line"]), simulator(DESIGNS["parabola"])]), nmse


def problem(seed: int, width: float = 3.0, stated: bool = True):
    """(models, evaluate, noise) of data set ``seed``; the parabola's c ~ U(-width, width);
    the noise stated (sd 0.1) or estimated from the best fit."""
    models, evaluate, nmse = linear(data(seed), width)
    return models, evaluate, nmse.noise(SIGMA if stated else None)


def closed_form(y: np.ndarray, width: float = 3.0) -> tuple[dict[str, float], dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Each model's exact log evidence and posterior (mean, sd) per parameter on ``y``: least
    squares with known noise, the evidence a Gaussian integral over the prior box."""
    log_z, post = {}, {}
    for (name, design), volume in zip(DESIGNS.items(), (8.0, 8.0 * 2 * width)):
        beta = np.linalg.lstsq(design, y, rcond=None)[0]
        chi2 = float(np.sum((y - design @ beta) ** 2)) / SIGMA**2
        precision = design.T @ design / SIGMA**2
        p = design.shape[1]
        log_z[name] = -chi2 / 2 + p / 2 * math.log(2 * math.pi) - 0.5 * np.linalg.slogdet(precision)[1] - math.log(volume)
        post[name] = (beta, np.sqrt(np.diag(np.linalg.inv(precision))))
    return log_z, post


def exact(seed: int, width: float = 3.0) -> tuple[dict[str, float], dict[str, tuple[np.ndarray, np.ndarray]]]:
    """The exact model probabilities and each model's posterior (mean, sd) per parameter."""
    log_z, post = closed_form(data(seed), width)
    top = max(log_z.values())
    z = {k: math.exp(v - top) for k, v in log_z.items()}
    return {k: v / sum(z.values()) for k, v in z.items()}, post


SETTINGS = NSSettings(particles=300, epsilon_initial=1000, batch_size=50)


def test_the_default_rules_wait_for_the_decision_tolerance():
    """Seed 3, the noise estimated (no ``noise_std``): the paper's rule (eps_t - eps_{t+1} <
    0.01) used to end this run above its decision tolerance, and the summary said nothing.
    By default it now waits: the run stops at the floor. Set by the user
    (``decrease_above_floor``, as a job spec that names ``min_epsilon_decrease`` does), it
    still ends the run there, and the answer says it is provisional."""
    models, evaluate, noise = problem(3, stated=False)
    r = abcns.run(models, evaluate, SETTINGS, StopRules(), seed=3, noise=noise)
    assert r.stop_reason is StopReason.NOISE_FLOOR
    assert r.final.standing is Standing.AT
    s = r.summary()
    assert s["decision"]["rule"] == "noise_floor" and s["decision"]["provisional"] is False
    assert not [w for w in s["warnings"] if w.startswith("provisional")]

    early = abcns.run(models, evaluate, SETTINGS, StopRules(decrease_above_floor=True), seed=3, noise=noise)
    assert early.stop_reason is StopReason.MIN_EPSILON_DECREASE
    assert early.final.epsilon > early.floor.decision
    s = early.summary()
    assert s["decision"]["rule"] == "min_epsilon_decrease" and s["decision"]["provisional"] is True
    provisional = [w for w in s["warnings"] if w.startswith("provisional")]
    assert len(provisional) == 1 and f"{early.final.epsilon:.4g}" in provisional[0]
    assert f"{early.floor.decision:.4g}" in provisional[0]


def test_above_the_floor_the_paper_rule_waits_and_a_stall_stops_the_run():
    """``min_epsilon_decrease`` (0.01 by default) ends a run with a floor only at or below its
    decision tolerance, unless the user set it (``decrease_above_floor``); above it, a
    population that closes less than :data:`abcns.settings.STALL_SHARE` of its distance to
    the decision tolerance stops the run (``stalled``: the tolerance is held at a model's
    best fit above the floor, the paper variant's §4.1 stall)."""
    rules = StopRules()
    # above the decision tolerance 1.0: a step of 0.005 waits, a step of 1e-4 of 2.0 stalls
    assert rules.reason_after(3.0, 2.995, 10, decision=1.0) is None
    assert rules.reason_after(3.0, 3.0 - 1e-4, 10, decision=1.0) is StopReason.STALLED
    # at or below it, the paper's rule applies
    assert rules.reason_after(1.0, 0.995, 10, decision=1.0) is StopReason.MIN_EPSILON_DECREASE
    # without a floor, as before
    assert rules.reason_after(3.0, 2.995, 10) is StopReason.MIN_EPSILON_DECREASE
    # the user's own rule ends the run where it holds
    mine = StopRules(decrease_above_floor=True)
    assert mine.reason_after(3.0, 2.995, 10, decision=1.0) is StopReason.MIN_EPSILON_DECREASE
    # along a given schedule (ABC-SMC) neither rule applies
    assert rules.reason_after(3.0, 3.0 - 1e-4, 10, decrease=False, decision=1.0) is None


@pytest.mark.parametrize("seed", [1, 3])
def test_the_floor_stop_ends_at_the_first_population_accepted_at_the_decision_tolerance(seed):
    """docs/design.md: the run stops after the population accepted at the decision tolerance.
    The floor falls as the run finds better fits, so the tolerance the last population was
    accepted at (the decision tolerance estimated after the population before) can lie above
    the one estimated after it; the run used to go on, accepting population after population
    at a slightly lower tolerance (seeds 1 and 3 of this toy with c ~ U(-30, 30): 3 and 2 of
    them). Now it stops after the first population accepted at the decision tolerance, unless
    a model's reading there is thin (``abcns.likelihood.thin``): each population it then
    accepts at the decision tolerance says so in a note."""
    models, evaluate, noise = problem(seed, width=30.0)
    r = abcns.run(models, evaluate, SETTINGS, StopRules(min_epsilon_decrease=1e-9, max_populations=60), seed=seed,
                  noise=noise)
    assert r.stop_reason is StopReason.NOISE_FLOOR
    pops = r.populations
    first = next(i for i, p in enumerate(pops) if p.standing is not Standing.ABOVE)
    assert [p.standing for p in pops] == [Standing.ABOVE] * first + [Standing.AT] * (len(pops) - first)
    held = [n for n in r.notes if n.endswith("the run goes on at the decision tolerance")]
    assert len(held) == len(pops) - 1 - first
    # a store's populations carry no record: the floors give the same one, and a run resumed
    # from them before its last population stops after it, as the run did
    bare = [dataclasses.replace(p, standing=None) for p in pops]
    assert standings(bare) == [p.standing for p in pops]
    more = iterate(models, SerialExecutor(evaluate), SETTINGS, StopRules(min_epsilon_decrease=1e-9, max_populations=60),
                   seed, noise=noise, history=bare[:-1])
    got = list(more)
    assert [p.epsilon for p in got] == [pops[-1].epsilon] and got[0].standing is Standing.AT
    assert pops[-1].epsilon == pops[-2].floor.decision
    assert r.decision_population() is pops[first]


def check_against_exact(summary: dict, seed: int, width: float, models: tuple[str, ...],
                        errors: float | None = None) -> None:
    """The summary's probabilities within 3 of their standard errors (plus 0.002 for a
    probability's own rounding in the delta method) of the exact ones; each named model's
    95 % intervals 0.8-1.25 times the exact width and its means within 0.25 exact standard
    deviations (issue W's bounds), or, given ``errors``, within that many Monte Carlo errors
    of a mean read on the model's effective particles (1 / sqrt(n_eff) exact sd each)."""
    p_exact, post = exact(seed, width)
    for name, p in p_exact.items():
        se = summary["model_probability_se"][name]
        assert abs(summary["model_probabilities"][name] - p) <= 3 * se + 0.002, (name, summary["model_probabilities"],
                                                                                   se, p_exact)
    for name in models:
        mean, sd = post[name]
        most = 0.25 if errors is None else errors / np.sqrt(summary["decision"]["effective_particles"][name])
        for j, (par, q) in enumerate(summary["posterior"][name].items()):
            ratio = (q["q97_5"] - q["q2_5"]) / (2 * 1.959964 * sd[j])
            shift = (q["mean"] - mean[j]) / sd[j]
            assert 0.8 <= ratio <= 1.25 and abs(shift) <= most, (name, par, ratio, shift, most)


@pytest.mark.slow
def test_nested_models_read_by_the_likelihood_match_exact_bayes():
    """Seed 25: the parabola fits this noise draw better than the line by chi^2 7.2 (the
    largest of seeds 1-40), more than the line's own spread at the floor (p + sqrt(2 p) =
    4.0), so the common decision tolerance lies below the line's best fit: read there, the
    line had no particle and p(line) = 0, against an exact 0.668. Read by the likelihood
    over all populations, both models' probabilities and intervals are exact Bayes's. Two
    sampler seeds on the same data agree within their standard errors (the answer does not
    hang on the sampler's seed)."""
    models, evaluate, noise = problem(25)
    answers = []
    for run_seed in (25, 26):
        r = abcns.run(models, evaluate, NSSettings(particles=1000, epsilon_initial=1000), StopRules(), seed=run_seed,
                      noise=noise)
        s = r.summary()
        assert s["decision"]["reading"] == "likelihood" and s["decision"]["rule"] == "noise_floor"
        check_against_exact(s, 25, 3.0, ("line", "parabola"))
        answers.append((s["model_probabilities"]["line"], s["model_probability_se"]["line"]))
    (p1, se1), (p2, se2) = answers
    assert abs(p1 - p2) <= 3 * math.hypot(se1, se2)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_a_rare_model_is_kept_and_its_probability_is_right(seed):
    """c ~ U(-30, 30): the parabola's exact probability is 0.0014-0.0058 on seeds 1-6, above
    the threshold of death by probability (1e-3). Before, it held 10-18 of 300 particles, its
    bounds were fitted to a handful of them and missed most of its region, its log evidence
    fell 5 below the truth with a standard error of 0.3, and it was removed in seeds 1, 4 and
    6 (p = 0 reported). Now it keeps 10 (d + 1) new particles a population, is not removed
    while the likelihood gives it a share, and its probability is the exact one within 3 of
    its standard errors."""
    models, evaluate, noise = problem(seed, width=30.0)
    r = abcns.run(models, evaluate, SETTINGS, StopRules(), seed=seed, noise=noise)
    assert "parabola" not in r.death_rules()
    check_against_exact(r.summary(), seed, 30.0, ("line",))


@pytest.mark.parametrize("seed", [1, 2])
def test_copies_are_read_from_both_copies_particles(seed):
    """The parabola declared again with c ~ U(-30, 30) (``wide``, ``same_model_as`` the one
    with c ~ U(-3, 3)): the same model under a prior ten times wider, whose posterior (c
    within 0.2 of 0) lies inside both boxes, so the exact split log Z_wide - log Z_parabola is
    -ln 10 on every data set. Read from both copies' particles (each weighted by its prior
    over the family's mixture: ``abcns.mixture.Mixture``), the split is that within 0.01
    (its standard error from the copies' covariance: 0.001); each copy read from its own
    particles alone (the code before) was off by -0.28 and -0.20 on seeds 1 and 2 (stated
    error 0.15; seeds 1-8: -0.28 to +0.14), the copies' probabilities 0.026 and 0.0026 here
    with independent errors. Each copy's probability within 3 of its standard errors of the
    exact (closed form), and the reading's effective particles the family's (164 and 156,
    against 71-86 alone)."""
    y = data(seed)
    models, _, nmse = linear(y, 3.0)
    wide = Model("wide", {"a": (0, 2), "b": (0, 4), "c": (-30, 30)}, same_model_as="parabola")

    def simulator(design):
        return lambda theta, _rng: (nmse(theta @ design.T), np.full(theta.shape[0], OK, np.int8))

    evaluate = per_model([simulator(DESIGNS["line"]), simulator(DESIGNS["parabola"]), simulator(DESIGNS["parabola"])])
    r = abcns.run([*models, wide], evaluate, SETTINGS, StopRules(), seed=seed, noise=nmse.noise(SIGMA))
    reading = r.reading()
    c = reading.covariance
    split, se = reading.log_z[2] - reading.log_z[1], math.sqrt(c[1, 1] + c[2, 2] - 2 * c[1, 2])
    assert abs(split + math.log(10)) < 0.01 and se < 0.01, (split, se)
    log_z, _ = closed_form(y, 3.0)
    exact_log = np.array([log_z["line"], log_z["parabola"], log_z["parabola"] - math.log(10)])
    p = np.exp(exact_log - exact_log.max())
    p /= p.sum()
    assert np.all(np.abs(reading.probabilities - p) <= 3 * reading.se), (reading.probabilities, reading.se, p)
    assert math.isclose(reading.ess[1], reading.ess[2]) and reading.ess[1] > 100, reading.ess


def test_the_answer_is_read_from_the_mixture_the_run_grew_not_grown_again(monkeypatch):
    """The reading weighs every particle by the mixture of the regions that proposed it
    (``abcns.mixture``), which the run grew one population at a time. The run's result now
    holds that mixture (``RunEnd.mixture``), and the answer is read from it: the same bits as
    growing it again over the stored populations, without doing so (the code before grew it
    again: a §4.1 job's summary 0.15 s of its 1.5 s). A result whose populations are not the
    ones it was grown over (one fewer here) grows its own."""
    models, evaluate, noise = problem(1)
    r = abcns.run(models, evaluate, SETTINGS, StopRules(), seed=1, noise=noise)
    again, fewer = dataclasses.replace(r, mixture=None), dataclasses.replace(r, populations=r.populations[:-1])
    grown_again = again.reading(), dataclasses.replace(fewer, mixture=None).reading()

    def grown(*args, **kwargs):
        raise AssertionError("the mixture was grown again")

    monkeypatch.setattr(Mixture, "grown", grown)
    reading = r.reading()
    for name in ("log_z", "log_z_se", "probabilities", "se", "covariance"):
        assert np.array_equal(getattr(reading, name), getattr(grown_again[0], name)), name
    assert r.summary() == again.summary()
    monkeypatch.undo()
    assert np.array_equal(fewer.reading().log_z, grown_again[1].log_z)
    assert not np.array_equal(grown_again[1].log_z, reading.log_z)


def test_noise_free_data_stop_by_the_paper_rule_and_say_there_is_no_floor():
    """Data a model fits exactly (the authors' demo data are such): the best fit falls with
    the tolerance, so the decision tolerance never holds still and waiting for it would never
    end. The decision tolerance halves within 5 populations (``abcns.noise.waited_for``): the
    paper's rule applies, the run stops, and the summary says there is no floor (not
    provisional). ``max_populations`` 200 is a guard: waiting, the run reached it."""
    y = 1.0 + 2.0 * X
    nmse = NMSE(y)
    line = lambda theta, _rng: (nmse(theta @ DESIGNS["line"].T), np.full(theta.shape[0], OK, np.int8))
    r = abcns.run([Model("line", {"a": (0, 2), "b": (0, 4)})], per_model([line]), SETTINGS,
                  StopRules(max_populations=200), seed=1, noise=nmse.noise())
    assert r.stop_reason is StopReason.MIN_EPSILON_DECREASE
    s = r.summary()
    assert s["decision"]["provisional"] is False and s["decision"]["reading"] == "tolerance"
    assert any(w.startswith("no noise floor") for w in s["warnings"])


def test_a_run_stopped_above_its_floor_reads_no_narrower_than_exact_bayes():
    """The cyclic test gill's BWBN run (issue Y) stopped at its population budget above its
    decision tolerance, and its likelihood reading rested on 2.7 effective particles: the
    last population's region is far wider than the posterior, so the weights fall on the
    few particles nearest the best fit, and the intervals were 0.35-1.24 of the exact width.
    Here the same on a linear toy of 6 parameters (a degree-5 Legendre series, 200 points,
    noise sd 0.1, estimated as gill's was), seed 1, stopped at 35 populations (the floor is
    reached at 48): before, 1.4 effective particles gave widths 0.46-1.08 of the exact ones
    and means up to 2.35 exact sd away. A reading on fewer than 2 (d + 1) effective particles
    now gives way to the last population's particles, the ABC posterior at its tolerance,
    which holds the exact posterior's region: widths at least the exact ones (measured
    2.5-2.9: the tolerance's region is sqrt((eps - d_min) / (v (p + 2))) = 2.6 times the
    posterior's sd), means within 0.5 exact sd (3 Monte Carlo errors of 300 particles, each
    0.16 exact sd at that width), and the summary says so. The same run taken to its floor
    (48 populations; 32 effective particles, fewer than 2 (d + 1) too, as at gill's floor:
    the weights there vary by a few e-folds only) keeps the likelihood reading, within issue
    W's bounds (widths 0.8-1.25 of the exact ones, means within 0.25 sd; measured 0.93-0.99
    and 0.13)."""
    x = np.linspace(-1, 1, 200)
    design = np.polynomial.legendre.legvander(x, 5)
    truth = np.linspace(1, 0.5, 6)
    y = design @ truth + SIGMA * np.random.default_rng(101).standard_normal(x.size)
    nmse = NMSE(y)
    poly = lambda theta, _rng: (nmse(theta @ design.T), np.full(theta.shape[0], OK, np.int8))
    model = Model("poly", {f"c{j}": (v - 1, v + 1) for j, v in enumerate(truth)})
    beta, rss = np.linalg.lstsq(design, y, rcond=None)[:2]
    sd = np.sqrt(np.diag(np.linalg.inv(design.T @ design)) * rss[0] / (x.size - 6))

    def ratios_and_shifts(summary):
        q = list(summary["posterior"]["poly"].values())
        return (np.array([(v["q97_5"] - v["q2_5"]) for v in q]) / (2 * 1.959964 * sd),
                np.abs(np.array([v["mean"] for v in q]) - beta) / sd)

    s = abcns.run([model], per_model([poly]), SETTINGS, StopRules(max_populations=35), seed=1,
                  noise=nmse.noise()).summary()
    assert s["decision"]["provisional"] is True and s["decision"]["effective_particles"]["poly"] < 14
    assert s["decision"]["posterior_reading"] == {"poly": "tolerance"}
    assert any(w.startswith("few effective particles: poly's") for w in s["warnings"])
    ratio, shift = ratios_and_shifts(s)
    assert np.all(ratio >= 1.0) and np.all(shift <= 0.5), (ratio, shift)

    s = abcns.run([model], per_model([poly]), SETTINGS, StopRules(), seed=1, noise=nmse.noise()).summary()
    assert s["decision"]["rule"] == "noise_floor" and s["decision"]["posterior_reading"] == {"poly": "likelihood"}
    ratio, shift = ratios_and_shifts(s)
    assert np.all((0.8 <= ratio) & (ratio <= 1.25)) and np.all(shift <= 0.25), (ratio, shift)


def legendre_toy(degree: int):
    """A degree-``degree`` Legendre series (200 points, noise sd 0.1 estimated from the best fit,
    priors truth +- 1): (model, evaluate, noise, exact means, exact sds)."""
    x = np.linspace(-1, 1, 200)
    design = np.polynomial.legendre.legvander(x, degree)
    truth = np.linspace(1, 0.5, degree + 1)
    y = design @ truth + SIGMA * np.random.default_rng(101).standard_normal(x.size)
    nmse = NMSE(y)
    poly = lambda theta, _rng: (nmse(theta @ design.T), np.full(theta.shape[0], OK, np.int8))
    model = Model("poly", {f"c{j}": (v - 1, v + 1) for j, v in enumerate(truth)})
    beta, rss = np.linalg.lstsq(design, y, rcond=None)[:2]
    sd = np.sqrt(np.diag(np.linalg.inv(design.T @ design)) * rss[0] / (x.size - degree - 1))
    return model, per_model([poly]), nmse.noise(), beta, sd


def test_a_run_at_its_floor_holds_the_decision_tolerance_until_its_reading_rests_on_enough_particles():
    """The cyclic test kunnath's BWBN (issue Y, 11 parameters) reached its floor with a reading
    on 4.0 effective particles, means up to 0.96 sd from exact Bayes, and no warning. The same
    on a degree-10 Legendre toy (11 parameters), seed 1: the first population at the decision
    tolerance (population 66) gave 1.8 effective particles, widths 0.41-0.81 of the exact ones,
    a mean 0.86 sd off. The weights in that region vary by ~e^9 and its prior mass lies near
    its edge, so one population holds few of the posterior's particles. The run now goes on
    at the decision tolerance until the reading rests on max(5 (d + 1), 64) = 64 (populations
    of one tolerance read together: ``abcns.likelihood.regions``): 75 populations against 66,
    12 % more simulations, 70.2 effective particles, widths 0.93-1.17, means within 0.23 sd.
    Bounds: widths 0.8-1.25 (issue W's), means within 0.35 sd (the largest of 11 means' Monte
    Carlo errors of 1 / sqrt(64) = 0.13 sd is ~2.3 of them). A run resumed inside the held
    populations ends identically, and one whose population budget ends the holding says so."""
    model, evaluate, noise, beta, sd = legendre_toy(10)
    r = abcns.run([model], evaluate, SETTINGS, StopRules(), seed=1, noise=noise)
    s = r.summary()
    assert s["decision"]["rule"] == "noise_floor" and s["decision"]["effective_particles"]["poly"] >= 64
    q = list(s["posterior"]["poly"].values())
    ratio = np.array([v["q97_5"] - v["q2_5"] for v in q]) / (2 * 1.959964 * sd)
    shift = np.abs(np.array([v["mean"] for v in q]) - beta) / sd
    assert np.all((0.8 <= ratio) & (ratio <= 1.25)) and np.all(shift <= 0.35), (ratio, shift)
    assert not [w for w in s["warnings"] if w.startswith("few effective particles")]
    first = r.decision_population().t
    assert r.final.t > first + 1 and r.final.standing is Standing.AT
    assert Standing.BELOW not in [p.standing for p in r.populations]

    resumed = list(iterate([model], SerialExecutor(evaluate), SETTINGS, StopRules(), 1, noise=noise,
                           history=r.populations[: first + 2]))
    assert [p.t for p in resumed] == [p.t for p in r.populations[first + 2:]]
    assert np.array_equal(resumed[-1].theta, r.final.theta)

    end = r.final.t - 1
    cut = abcns.run([model], evaluate, SETTINGS, StopRules(max_populations=end), seed=1, noise=noise).summary()
    assert cut["decision"]["rule"] == "noise_floor"
    assert any(w.startswith("few effective particles: poly's likelihood reading rests on") and
               f"after {end - first + 1} populations at the decision tolerance" in w for w in cut["warnings"]), cut["warnings"]


@pytest.mark.parametrize("seed", [5, 11])
def test_a_rare_model_alive_at_the_floor_is_read_on_enough_particles_whatever_its_dimension(seed):
    """The exact-Bayes benchmark's losing cubic-quintic (d = 4, p 6.6e-4, seed 1) was alive at
    the end on 50 effective particles, above the 5 (d + 1) = 25 the floor held for, and its c
    was 0.42 exact sd off: 3 Monte Carlo errors of 1 / sqrt(50). A mean's Monte Carlo error
    does not shrink with d, so the run now holds its decision tolerance until each alive
    model's reading rests on max(5 (d + 1), 64) effective particles (``HELD_LEAST``: 0.25 sd
    is 2 errors of 1 / sqrt(64)). The same here: the rare parabola (c ~ U(-30, 30), exact p
    0.0028 and 0.0014 on data seeds 5 and 11) was read on 20 and 28 effective particles
    (5 (d + 1) = 20), its means 0.27 and 0.29 exact sd off; now on 81 and 71, 0.05 and 0.14,
    for 17 % and 8 % more simulations. Issue W's bounds (:func:`check_against_exact`) for both
    models, the means within 3 Monte Carlo errors of their readings (issue Y's 2-means start
    moved seed 5's parabola b to 0.31 sd on 66 effective particles, 2.5 errors; over data seeds
    1-40 the largest mean error is 2.86 errors now, 3.72 before, the median 1.39 and 1.31, so
    the fixed 0.25 sd was a matter of which draw: 2 errors of each of 5 means)."""
    models, evaluate, noise = problem(seed, width=30.0)
    s = abcns.run(models, evaluate, SETTINGS, StopRules(), seed=seed, noise=noise).summary()
    assert s["decision"]["rule"] == "noise_floor" and "parabola" in s["posterior"]
    assert s["decision"]["effective_particles"]["parabola"] >= 64
    check_against_exact(s, seed, 30.0, ("line", "parabola"), errors=3.0)


def curved(seed: int):
    """(models, evaluate, noise, exact ln Bayes factor parabola / line) of a parabola truth
    (1 + 2 x + 1.5 x^2, noise sd 0.1 stated, 100 points) that the line misfits by a chi^2 of
    ~2000: the line leaves the run early, by ``no_particles``, ~1000 nats behind."""
    y = 1.0 + 2.0 * X + 1.5 * X**2 + SIGMA * np.random.default_rng(100 + seed).standard_normal(X.size)
    models, evaluate, nmse = linear(y)
    log_z, _ = closed_form(y)
    return models, evaluate, nmse.noise(SIGMA), log_z["parabola"] - log_z["line"]


@pytest.mark.parametrize("seed", [8, 28])
def test_a_model_that_leaves_early_is_read_on_enough_particles(seed):
    """The cyclic test chiu's Bouc-Wen left the joint run by ``no_particles`` with its evidence
    on 2.5 effective particles, 2.5 nats below its own run's: the common tolerance jumped far
    below its best fit, and its last region, {d < eps_t}, read uncut, spans many e-folds of
    its likelihood, whose weight sits on the few particles nearest its best fit. The same
    here: the line, ~1000 nats behind the parabola, left at population 10 on 1.0 and 1.6
    effective particles, ln BF 7.08 and 4.20 nats above the exact one (7.2 and 5.5 of its
    stated errors; data seeds 1-40: 5 beyond 2 errors, 4 beyond 3). While a leaving model's
    reading rests on fewer than 2 (d + 1) effective particles, the next tolerance now keeps
    its 2 (d + 1) best particles (``abcns.likelihood.kept``; a note says so), so it leaves on
    6 or more: seeds 1-40, errors within 2.05 of the stated ones (3 beyond 2), the largest
    1.13 nats, for 0.8 % more simulations. Read by the mixture of the proposal regions
    (``abcns.mixture``), the rule holds the line in 29 of seeds 1-40 (here 8 and 28), which
    leaves on 6.1-30.6 effective particles (median 9.8), errors within 2.31 stated (3
    beyond 2), the largest 0.78 nats, RMS 0.34. Bound: 3 stated errors. A run resumed after
    the raised tolerance ends as the run did."""
    models, evaluate, noise, exact_bf = curved(seed)
    r = abcns.run(models, evaluate, SETTINGS, StopRules(), seed=seed, noise=noise)
    s = r.summary()
    assert s["death_rules"] == {"line": "no_particles"} and s["decision"]["rule"] == "noise_floor"
    assert s["decision"]["effective_particles"]["line"] >= 6
    kept = [n for n in r.notes if "the next tolerance is held" in n and "for line" in n]
    assert kept
    z = s["log_evidence"]
    bf, se = z["parabola"]["log_z"] - z["line"]["log_z"], math.hypot(z["parabola"]["se"], z["line"]["se"])
    assert abs(bf - exact_bf) <= 3 * se, (bf, exact_bf, se)

    t = int(kept[0].split(":")[0].removeprefix("population "))
    resumed = list(iterate(models, SerialExecutor(evaluate), SETTINGS, StopRules(), seed, noise=noise,
                           history=r.populations[:t]))
    assert [p.t for p in resumed] == [p.t for p in r.populations[t:]]
    assert np.array_equal(resumed[-1].theta, r.final.theta)


def test_a_leaving_model_holds_the_tolerance_up_for_at_most_held_populations_in_a_row(monkeypatch):
    """A leaving model at its own floor can hold the tolerance up for ever: its best
    particles no longer shrink its region, and the mixture's weights stay on the earlier,
    wider regions' particles, so its reading never fills (the MR damper's Bouc-Wen held it
    at 15.668 for 130 populations and ran the job to ``max_populations``). So at most
    ``HELD_POPULATIONS`` populations in a row are held up. Seed 9 holds the line up at
    populations 10 and 11; with the cap at 1, only at 10, and a run resumed after population
    10 reads the count from the stored populations and ends as the run did."""
    from abcns import likelihood

    monkeypatch.setattr(likelihood, "HELD_POPULATIONS", 1)
    models, evaluate, noise, _ = curved(9)
    r = abcns.run(models, evaluate, SETTINGS, StopRules(), seed=9, noise=noise)
    held = sorted({int(n.split(":")[0].removeprefix("population ")) for n in r.notes
                   if "the next tolerance is held" in n})
    assert held == [10]
    resumed = list(iterate(models, SerialExecutor(evaluate), SETTINGS, StopRules(), 9, noise=noise,
                           history=r.populations[:10]))
    assert [p.t for p in resumed] == [p.t for p in r.populations[10:]]
    assert np.array_equal(resumed[-1].theta, r.final.theta)


def test_a_step_a_leaving_model_held_up_is_not_a_stall():
    """Above the decision tolerance (1.0), a population that closes less than 1e-3 of its
    distance to it has stalled and stops the run; a step that a leaving model's thin reading
    set (``abcns.likelihood.kept``) is that model's nested sampling near its own best fit,
    not the run's, and never stops it (nor does ``min_epsilon_decrease``)."""
    from abcns.nested import _stop_reason

    rules = StopRules()
    args = (rules, True, 10, 3.0, 3.0 - 1e-4, False, Standing.ABOVE, [1.0] * 10)
    assert _stop_reason(*args) is StopReason.STALLED
    assert _stop_reason(*args, False, True) is None


def test_a_model_is_spared_while_the_population_that_decides_would_thin_its_reading():
    """Death by probability waits while a model's reading rests on fewer than max(5 (d + 1),
    64) effective particles (``abcns.likelihood.spared``; the run's bar for holding its
    decision tolerance, ``thin``). At 2 (d + 1), the bar until issue Y's mixture, the cyclic
    test chiu's losing uniform copy (seed 4) died on 37 effective particles whose core was
    still thin (means up to 0.67 exact sd off, widths up to 1.49), its split against the log
    copy 1.39 nats off (7 stated errors); spared to 71, it is 0.07 off. So 50 equal
    particles no longer let a model die. It used to ask only the reading without
    the population that decides, though the model keeps that population's particles: a
    losing copy of the cyclic tests (gill, seed 1) died on a reading of 25 effective
    particles that its last population's particles, nearer its best fit, thinned to 3.2
    (its split against the other copy then off by 0.77 nats, se 0.60). Here a losing
    one-parameter model (its reading 25 nats below the winner's) has 100 particles of one
    likelihood (ESS 100 >= 64, ``HELD_LEAST``); a deciding population that brings one particle 20 noise
    variances nearer the best fit puts nearly all the weight on it (ESS ~1): the model is
    spared; without that population, or with one like the first, it is not."""
    from types import SimpleNamespace

    from abcns import bounds as bd
    from abcns import ellipsoid as ell
    from abcns import likelihood
    from abcns.mixture import Mixture
    from abcns.noise import METHODS, Floor

    floor = Floor(best=1.0, model=0, n_parameters=1, variance=0.01, method=METHODS.index("stated"), n_samples=100)
    models = [Model("winner", {"x": (0.0, 1.0)}), Model("loser", {"x": (0.0, 1.0)})]

    def population(loser: np.ndarray) -> tuple:
        d = np.concatenate([np.full(50, 1.0), loser])  # the winner's particles, then the loser's
        which = np.repeat([0, 1], [50, loser.size])
        return which, np.full((d.size, 1), 0.5), d, np.ones(d.size, bool)

    first = population(np.full(100, 1.5))
    before = Mixture.empty([bd.Frame(m, unit=True) for m in models], [1, 1]).grown(None, 2.0, *first,
                                                                                  np.array([100, 100]))
    box = (ell.from_box(np.zeros(1), np.ones(1)),)
    previous = SimpleNamespace(survivors=np.zeros(150, bool), ellipsoids=(box, box), held=None, models=first[0],
                               evidence=SimpleNamespace(log_volume=np.zeros(2), log_volume_se=np.zeros(2)))
    tight = before.grown(previous, 2.0, *population(np.array([1.5, 1.5, 1.1])), np.array([100, 100]))
    like = before.grown(previous, 2.0, *population(np.full(100, 1.5)), np.array([100, 100]))
    assert not likelihood.spared(before, [1, 1], floor, 1e-3)[1]
    fifty = Mixture.empty([bd.Frame(m, unit=True) for m in models], [1, 1]).grown(
        None, 2.0, *population(np.full(50, 1.5)), np.array([100, 100]))
    assert likelihood.spared(fifty, [1, 1], floor, 1e-3)[1]
    assert likelihood.spared(before, [1, 1], floor, 1e-3, tight)[1]
    assert not likelihood.spared(before, [1, 1], floor, 1e-3, like)[1]


def exact_bayes_case(case: str, data_seed: int, seed: int):
    """(the job of benchmarks.exact_bayes's ``case`` on data ``data_seed`` run with ``seed``,
    dynesty's log Z per model from the benchmark's cache, checked against what it was made
    from: a stale answer fails here, not as a wrong comparison)."""
    from benchmarks.exact_bayes import CACHE, cached, case_data, case_spec
    from service.spec import build, parse

    data = case_data(case, data_seed)
    raw, base = case_spec(case, data, seed, None)
    job = build(parse(raw), base)
    log_z = {}
    for exact, _, path, stored in cached(case, data_seed, 1000, job, data, CACHE):
        assert stored is not None, f"{path} is stale or missing: rerun benchmarks.exact_bayes"
        log_z[exact.model.name] = stored["log_z"]
    return job, log_z


@pytest.mark.parametrize(("data_seed", "seed"), [(4, 5), (3, 3)])
def test_a_rare_model_s_bound_keeps_the_end_of_its_curved_region(data_seed, seed):
    """benchmarks.exact_bayes's linear-vs-cubic (linear truth, 1 % noise): the cubic loses
    (exact p ~1e-4), so it is bounded on 24-50 points a population. Its region is a curved
    valley whose low end (k3 near 0, c near the linear's) holds its posterior. Bounded by 2-4
    ellipsoids of 10-16 points, it lost that end population after population: its particles
    stalled at NMSE 0.057 against the linear's 0.048 and it left with its log evidence 46 nats
    (data seed 4, seed 5) and 8,779 nats (data seed 3) low. One ellipsoid per 32 points keeps
    it (``bounds.POINTS_PER_ELLIPSOID``): on data seed 4, seeds 1-8, the ln Bayes factor is
    within 0.23 of dynesty's and the 15 runs of the benchmark within 0.46. The tolerance, 1
    nat, is three of the combined errors (dynesty's 0.2 per model, abcns's ~0.15)."""
    job, exact = exact_bayes_case("linear-vs-cubic", data_seed, seed)
    r = abcns.run(job.models, job.evaluate, job.settings, job.stop, seed=seed, noise=job.noise)
    log_z = {m: v["log_z"] for m, v in r.summary()["log_evidence"].items()}
    off = (log_z["cubic"] - log_z["linear"]) - (exact["cubic"] - exact["linear"])
    assert abs(off) < 1.0, f"the cubic's ln Bayes factor is {off:+.2f} nats off dynesty's"


def test_a_model_that_left_far_above_its_own_best_fit_says_its_evidence_is_a_lower_bound():
    """benchmarks.exact_bayes's paper41 (§4.1's data, seed 4): the cubic cannot fit the
    cubic-quintic truth and leaves early, read on 13 effective particles that never reached its
    own best fit: its ln Bayes factor against the cubic-quintic reads -242,123 with a standard
    error of 0.28, dynesty's is -167,775. The summary says so: ``lower_bound`` for a model read
    on fewer effective particles than ``likelihood.held_target``, not for the winner."""
    seed = 4
    job, exact = exact_bayes_case("paper41", seed, seed)
    ev = abcns.run(job.models, job.evaluate, job.settings, job.stop, seed=seed, noise=job.noise).summary()["log_evidence"]
    assert ev["cubic"]["lower_bound"] and ev["cubic"]["effective_particles"] < 64
    # what the flag is for: far below the truth, by more than its standard error says
    log_bf = ev["cubic"]["log_z"] - ev["cubic-quintic"]["log_z"]
    assert log_bf + 10 * ev["cubic"]["se"] < exact["cubic"] - exact["cubic-quintic"]
    assert not ev["cubic-quintic"]["lower_bound"] and ev["cubic-quintic"]["effective_particles"] > 500
