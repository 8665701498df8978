"""Physical validity (issue R.2): what the schema lets through but no simulation can use is
refused before a job starts, naming the field; and a job that accepts nothing stops with
its own reason and says why.

- a sampling rate whose sample interval (decimated) is not a normal positive float;
- a mass that is not positive, fixed or as a prior's low end;
- a prior whose width ``high - low`` overflows a float;
- input or observed samples beyond ``MAX_MAGNITUDE``, an observed record too small for the
  NMSE's scale;
- two models of one name;
- RK4 substeps per sample, given or chosen from the priors and the sample interval, past
  ``worker.description.MAX_SUBSTEPS``;
- a population that runs ``stop.max_simulations_without_acceptance`` simulations and keeps
  none stops with ``nothing_accepted`` and a sentence in the run's notes;
- the records an upload or inline data hold are cut to the samples the job reads, and the
  cut changes nothing the job computes (decimation included).
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

import abcns
from abcns import InvalidSetting, Model, SpecError, StopReason, StopRules
from abcns.executor import OK, Evaluated
from benchmarks.harness import duffing_spec
from service.spec import build, load_data, parse

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def base() -> dict:
    return duffing_spec(max_populations=1, particles=200)


def refused(spec: dict) -> SpecError:
    with pytest.raises(SpecError) as err:
        build(parse(spec))
    return err.value


@pytest.mark.parametrize(("change", "field", "words"), [
    (lambda s: s["data"].update(fs=1e308), "data.fs", "sample interval 1/fs is 1e-308"),  # subnormal
    (lambda s: s["data"].update(fs=5e-324), "data.fs", "sample interval 1/fs is inf"),
    (lambda s: s["data"].pop("fs") and s["data"].update(dt=1e306, decimate=1000), "data.dt", "x decimate (1000)"),
    (lambda s: s["models"][0]["fixed"].update(m=0), "models[0].fixed.m", "must be a number > 0"),
    (lambda s: s["models"][1]["fixed"].update(m=-1), "models[1].fixed.m", "must be a number > 0"),
    (lambda s: s["models"][0]["fixed"].pop("m") and s["models"][0]["priors"].update(m=[-1, 2]),
     "models[0].priors.m", "leaves the valid range of m"),
    (lambda s: s["models"][1]["priors"].update(k=[-1e308, 1e308]), "models[1].priors.k", "width high - low overflows"),
    (lambda s: s["data"].update(input=[2e100] * len(s["data"]["input"])), "data.input", "at most 1e+100"),
    (lambda s: s["data"].update(observed=[x * 1e160 for x in s["data"]["observed"]]), "data.observed",
     "at most 1e+100"),
    (lambda s: s["data"].update(observed=[x * 1e-160 for x in s["data"]["observed"]]), "data.observed",
     "too small for the NMSE"),
    (lambda s: s["models"][1].update(name="cubic"), "models[1].name", "duplicate model name"),
    # a sampling rate of 1e-300 Hz (interval 1e300 s) with the substeps chosen from the priors:
    # 7 x 10^301 substeps, which failed at run time (numba: "Int value is too large")
    (lambda s: s["data"].update(fs=1e-300) or s["models"][0].pop("integrator"), "models[0].integrator.substeps",
     "sample interval 1e+300 s ask for 6.83e+301 RK4 substeps per sample"),
    (lambda s: s["models"][1]["integrator"].update(substeps=10**30), "models[1].integrator.substeps",
     "at most 1e+09 RK4 substeps per sample"),
])
def test_what_no_simulation_can_use_is_refused_naming_the_field(base, change, field, words):
    spec = copy.deepcopy(base)
    change(spec)
    err = refused(spec)
    assert err.field == field and words in err.message, str(err)


def test_the_worker_s_substeps_message_names_no_spec_field(base):
    """Issue X.3: the worker raises in its own terms (the sample interval), ``service.spec``
    names the spec's fields: the message does not name data.fs or data.dt."""
    spec = copy.deepcopy(base)
    spec["data"].update(fs=1e-300)
    spec["models"][0].pop("integrator")
    err = refused(spec)
    assert err.field == "models[0].integrator.substeps" and "data." not in err.message, str(err)


def test_a_wide_prior_is_refused_by_the_library_too():
    with pytest.raises(InvalidSetting, match="width high - low overflows") as err:
        Model("m", {"k": (-1e308, 1e308)})
    assert err.value.path == ("priors", "k")
    Model("m", {"k": (-1e307, 1e307)})  # wide but finite: fine
    assert np.isfinite(Model("m", {"k": (-1e307, 1e307)}).log_prior_volume())


def far_away(batch) -> Evaluated:
    """Every simulation OK at distance 1e6: nothing comes below any tolerance used here."""
    n = len(batch)
    return Evaluated(np.full(n, 1e6), np.full(n, OK, np.int8))


@pytest.mark.parametrize("settings", [abcns.NSSettings(particles=50, epsilon_initial=10.0, batch_size=40),
                                      abcns.SMCSettings(particles=50, epsilon_initial=10.0, batch_size=40),
                                      abcns.RejectionSettings(particles=50, epsilon_initial=10.0, batch_size=40)],
                         ids=["abc-ns", "abc-smc", "rejection"])
def test_a_population_that_accepts_nothing_stops_and_says_why(settings):
    """With the limit at 1,000 simulations and batches of 40, the run stops after batch 25
    (the first at or past the limit), with nothing_accepted and a sentence naming the
    population, the simulations, the tolerance and the setting."""
    stop = StopRules(max_populations=3, max_simulations_without_acceptance=1000)
    result = abcns.run([Model("far", {"a": (0, 1)})], far_away, settings, stop, seed=1)
    assert result.stop_reason is StopReason.NOTHING_ACCEPTED and result.populations == ()
    assert result.n_simulations == 1000
    (note,) = result.notes
    assert note.startswith("nothing accepted: population 1 ran 1,000 simulations") and "tolerance 10" in note
    assert "stop.max_simulations_without_acceptance" in note


def test_the_limit_is_a_safety_net_not_a_stop_rule():
    """It is on by default (10^6) and does not count as the one stop rule a run needs; a
    healthy run never meets it (one accepted particle resets nothing: the count is per
    population and only while nothing is kept)."""
    assert StopRules().max_simulations_without_acceptance == 1_000_000
    with pytest.raises(InvalidSetting, match="at least one stop rule"):
        StopRules(min_epsilon_decrease=None, max_simulations_without_acceptance=10)
    with pytest.raises(InvalidSetting) as err:
        StopRules(max_simulations_without_acceptance=0)
    assert err.value.field == "stop.max_simulations_without_acceptance"
    # one particle in ten accepted: no stop at a limit of 30 simulations per population
    def some(batch) -> Evaluated:
        d = np.where(np.arange(len(batch)) % 10 == 0, 0.0, 1e6)
        return Evaluated(d, np.full(len(batch), OK, np.int8))
    result = abcns.run([Model("near", {"a": (0, 1)})], some, abcns.RejectionSettings(particles=20, epsilon_initial=1.0,
                                                                                     batch_size=10),
                       StopRules(max_populations=1, max_simulations_without_acceptance=30), seed=1)
    assert result.stop_reason is StopReason.COMPLETED


@pytest.mark.parametrize("decimate", [1, 2, 7])
def test_cutting_the_records_to_what_the_job_reads_changes_nothing_it_computes(decimate):
    """The records (here tiled to 12,000 samples) are cut to the end of the later window,
    plus the decimation filter's reach: the decimated samples the job uses are bit for bit
    those of the whole record, and so are the distances of a batch."""
    from service.spec import cut_to_read, samples_read

    raw = duffing_spec(max_populations=1, particles=200)
    force, x = np.tile(raw["data"]["input"], 12), np.tile(raw["data"]["observed"], 12)
    raw["data"].update(input=force.tolist(), observed=x.tolist(), decimate=decimate, fit=[0, 300], test=[300, 600])
    spec = parse(raw)
    n = samples_read(spec)
    assert n == (600 if decimate == 1 else (600 + 11) * decimate) < force.size
    cut = cut_to_read(spec, {"input": force, "observed": x})
    assert cut["input"].size == cut["observed"].size == n
    whole_f, whole_x = load_data(spec, None)
    short = spec.model_copy(update={"data": spec.data.model_copy(update={"input": cut["input"].tolist(),
                                                                          "observed": cut["observed"].tolist()})})
    part_f, part_x = load_data(short, None)
    np.testing.assert_array_equal(part_f[:600], whole_f[:600])
    np.testing.assert_array_equal(part_x[:600], whole_x[:600])
    a, b = build(spec), build(short)
    theta = np.column_stack([np.full(8, 0.05), np.linspace(20, 200, 8), np.full(8, 1000.0)])
    batch = abcns.executor.Batch(1, 1, np.zeros(8, np.int64), np.column_stack([theta, np.full(8, np.nan)]),
                                 np.inf, np.random.SeedSequence(1), np.zeros(8, np.int64))
    np.testing.assert_array_equal(a.evaluate(batch).distances, b.evaluate(batch).distances)


def test_records_are_kept_whole_where_the_job_reads_them_whole():
    from service.spec import cut_to_read, samples_read

    raw = duffing_spec(max_populations=1, particles=200)
    raw["data"].pop("fit")
    assert samples_read(parse(raw)) is None  # the NMSE over the whole record
    raw = duffing_spec(max_populations=1, particles=200)
    raw["distance"] = "summary_euclidean"
    assert samples_read(parse(raw)) is None
    raw = duffing_spec(max_populations=1, particles=200)
    spec = parse(raw)
    arrays = {"input": np.zeros(1500), "observed": np.zeros(1499)}  # lengths differ: build says so, uncut
    assert cut_to_read(spec, arrays) is arrays
