"""The job spec: a valid spec runs like the same problem built in code; malformed specs
are refused before anything runs, naming the field."""

import copy
import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from pydantic import ValidationError

from abcns import NSSettings, RejectionSettings, SMCSettings, SpecError, StopRules, run
from examples.paper import authors_demo
from service.run.dask_executor import LOCAL_POPULATION_S
from service.run.runner import local_population_s, write_interval
from service.spec import JobSpec, build, load, parse

ROOT = Path(__file__).resolve().parents[1]


def demo_data():
    with np.load(ROOT / "data" / "authors-demo" / "demo_data.npz") as f:
        return dict(f)
SPEC = ROOT / "examples" / "authors_demo" / "spec.yaml"


def test_spec_run_equals_the_problem_built_in_code():
    spec, base = load(SPEC)
    job = build(spec, base)
    code = authors_demo()
    short = StopRules(max_populations=3)
    a = run(job.models, job.evaluate, job.settings, short, seed=job.seed)
    b = run(code.models, code.evaluate, code.settings, short, seed=job.seed)
    for p, q in zip(a.populations, b.populations):
        np.testing.assert_array_equal(p.theta, q.theta)
        np.testing.assert_array_equal(p.distances, q.distances)


@pytest.fixture
def raw():
    return yaml.safe_load(SPEC.read_text())


def refuse(raw, base, field, match=None):
    with pytest.raises(SpecError, match=match) as err:
        build(parse(raw), base)
    assert err.value.field == field, str(err.value)


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda r: r["models"][1].update(simulator="nope"), "models[1].simulator"),
        (lambda r: r["models"][1]["priors"].pop("k"), "models[1].priors"),
        (lambda r: r["models"][0]["priors"].update(k3=[0, 1]), "models[0].fixed.k3"),
        (lambda r: r["models"][0]["priors"].update(c=[1, 0]), "models[0].priors.c"),
        (lambda r: r["models"][0]["priors"].update(q=[0, 1]), "models[0].priors.q"),
        (lambda r: r["models"][0]["priors"].update(c=[0, 1, "log"]), "models[0].priors.c"),
        (lambda r: r["models"][1].update(same_model_as="nope"), "models[1].same_model_as"),
        (lambda r: r["models"][1].update(same_model_as=r["models"][0]["name"]), "models[1].same_model_as"),
        (lambda r: r["models"][0]["priors"].update(c=[0.1, 1, "ln"]), "models[0].priors.c"),
        (lambda r: r["models"][0]["priors"].update(c=[0.1, 1, "log", 2]), "models[0].priors.c"),
        (lambda r: r["data"].update(fit=[400, 900]), "data.fit"),
        (lambda r: r["data"].update(test=[-1, 10]), "data.test"),
        (lambda r: r["data"].update(observed="missing.npy"), "data.observed"),
        (lambda r: r["data"].update(input=r["data"]["input"].replace(":force", ":nope")), "data.input"),
        (lambda r: r["sampler"].update(beta=0.9), "sampler.beta"),
        (lambda r: r["sampler"].update(particles="many"), "sampler.particles"),
        (lambda r: r["stop"].update(max_populations=0), "stop.max_populations"),
        (lambda r: r.update(colour="blue"), "colour"),
        (lambda r: r["models"][0]["integrator"].update(substeps=0), "models[0].integrator.substeps"),
    ],
)
def test_malformed_specs_name_the_field(raw, mutate, field):
    bad = copy.deepcopy(raw)
    mutate(bad)
    refuse(bad, SPEC.parent, field)


def test_a_log_uniform_prior_is_read_and_refused_naming_the_field(raw):
    """``[low, high, "log"]``: a log-uniform prior, which needs low > 0 (the message says so)."""
    raw["models"][0]["priors"]["c"] = [0.01, 1, "log"]
    job = build(parse(raw), SPEC.parent)
    assert job.models[0].priors["c"].log and not job.models[0].priors["k"].log
    raw["models"][0]["priors"]["c"] = [0, 1, "log"]
    refuse(raw, SPEC.parent, "models[0].priors.c", match="log-uniform prior needs low > 0")


def test_a_model_declared_the_same_as_another_is_read_and_checked(raw):
    """``same_model_as``: the model under other priors; its simulator, fixed values and
    integrator must be the other's (the message names the field)."""
    copy_of = copy.deepcopy(raw["models"][0])
    copy_of.update(name="again", same_model_as=copy_of["name"])
    copy_of["priors"] = {k: [lo if lo > 0 else 0.001, hi, "log"] for k, (lo, hi) in copy_of["priors"].items()}
    raw["models"].append(copy_of)
    job = build(parse(raw), SPEC.parent)
    assert job.models[2].same_model_as == raw["models"][0]["name"]
    copy_of["integrator"] = {**copy_of.get("integrator", {}), "substeps": 7}
    refuse(raw, SPEC.parent, "models[2].same_model_as", match="integrator")


def test_observed_with_nan_and_length_mismatch(raw, tmp_path):
    d = demo_data()
    obs = d["displacement"].copy()
    obs[7] = np.nan
    np.save(tmp_path / "obs.npy", obs)
    np.save(tmp_path / "short.npy", d["displacement"][:400])
    np.save(tmp_path / "force.npy", d["force"])
    raw["data"].update(input="force.npy", observed="obs.npy")
    refuse(raw, tmp_path, "data.observed", match=r"sample 7 \(counting from 0\) is nan")
    raw["data"].update(observed="short.npy")
    refuse(raw, tmp_path, "data.observed", match="same length")


def test_csv_and_inline_data(raw, tmp_path):
    d = demo_data()
    np.savetxt(tmp_path / "rec.csv", np.column_stack([d["force"], d["displacement"]]), delimiter=",",
               header="force,x", comments="")
    raw["data"].update(input="rec.csv:force", observed=d["displacement"].tolist())
    job = build(parse(raw), tmp_path)
    np.testing.assert_array_equal(job.force, d["force"])
    shutil.rmtree(tmp_path)


def test_decimation_is_anti_aliased_and_scales_dt(raw, tmp_path):
    """q = 4: a tone well below the new Nyquist frequency survives (amplitude within 1 %),
    one above it is removed (below 1 % of its amplitude: the FIR filter's stop band); dt
    grows by q, windows count kept samples, and the job builds and runs."""
    n, dt = 4000, 0.001
    t = np.arange(n) * dt
    slow = np.sin(2 * np.pi * 5 * t)  # 5 Hz; new Nyquist 125 Hz
    fast = np.sin(2 * np.pi * 300 * t)  # 300 Hz: above it, must not alias in
    np.save(tmp_path / "f.npy", slow + fast)
    np.save(tmp_path / "x.npy", 1e-3 * slow)
    raw["data"] = {"dt": dt, "input": "f.npy", "observed": "x.npy", "decimate": 4, "fit": [0, 800]}
    raw["models"] = raw["models"][:1]
    raw["sampler"].update(particles=100, batch_size=50, epsilon_initial=None)  # the pilot sets it
    raw["stop"] = {"max_populations": 1, "max_simulations": 5000}
    job = build(parse(raw), tmp_path)
    assert job.force.size == n // 4 and job.spec.data.sample_interval == pytest.approx(4 * dt)
    kept = slice(100, 900)  # away from the record's ends
    t4 = t[::4][kept]
    np.testing.assert_allclose(job.force[kept], np.sin(2 * np.pi * 5 * t4), atol=0.01)
    r = run(job.models, job.evaluate, job.settings, job.stop, seed=0)
    assert len(r.populations) == 1 and r.epsilon_initial_source == "pilot"
    raw["data"]["decimate"] = 0
    with pytest.raises(SpecError) as err:
        parse(raw)
    assert err.value.field == "data.decimate"


@pytest.mark.parametrize("raw", ["soon", "-1", "nan", "1e9"])
def test_a_bad_store_interval_is_refused_naming_the_variable(monkeypatch, raw):
    monkeypatch.setenv("ABCNS_STORE_INTERVAL_S", raw)
    with pytest.raises(SpecError) as err:
        write_interval()
    assert err.value.field == "ABCNS_STORE_INTERVAL_S"


def test_the_store_interval_defaults_to_a_second(monkeypatch):
    monkeypatch.delenv("ABCNS_STORE_INTERVAL_S", raising=False)
    assert write_interval() == 1.0
    monkeypatch.setenv("ABCNS_STORE_INTERVAL_S", "0")
    assert write_interval() == 0.0


def test_the_local_population_time_is_read_like_the_store_interval(monkeypatch):
    """``ABCNS_LOCAL_POPULATION_S``: unset or empty (docker/compose.yaml passes it on empty)
    is the default, a bad value an error naming the variable, before the job starts."""
    for unset in (None, ""):
        if unset is None:
            monkeypatch.delenv("ABCNS_LOCAL_POPULATION_S", raising=False)
        else:
            monkeypatch.setenv("ABCNS_LOCAL_POPULATION_S", unset)
        assert local_population_s() == LOCAL_POPULATION_S == 0.025
    monkeypatch.setenv("ABCNS_LOCAL_POPULATION_S", "0")
    assert local_population_s() == 0.0
    for bad in ("fast", "-1", "nan"):
        monkeypatch.setenv("ABCNS_LOCAL_POPULATION_S", bad)
        with pytest.raises(SpecError) as err:
            local_population_s()
        assert err.value.field == "ABCNS_LOCAL_POPULATION_S"


# ---------------------------------------------------------------------------- issue L: one definition of the settings
SAMPLERS = {"abc-ns": NSSettings, "abc-smc": SMCSettings, "rejection": RejectionSettings}


def with_sampler(raw, sampler):
    return {**raw, "sampler": sampler}


@pytest.mark.parametrize(("algorithm", "name", "value", "owners"), [
    ("abc-ns", "quantile", 0.3, "abc-smc"), ("abc-ns", "schedule", [2.0, 1.0], "abc-smc"),
    ("abc-smc", "alpha", 0.2, "abc-ns"), ("abc-smc", "variant", "paper", "abc-ns"),
    ("rejection", "beta", 0.5, "abc-ns"), ("rejection", "quantile", 0.3, "abc-smc"),
])
def test_a_field_the_algorithm_does_not_read_is_refused_naming_it(raw, algorithm, name, value, owners):
    bad = with_sampler(raw, {"algorithm": algorithm, "epsilon_initial": 100, name: value})
    with pytest.raises(SpecError, match=rf"does not apply to algorithm '{algorithm}' \(it is read by {owners}\)") as err:
        parse(bad)
    assert err.value.field == f"sampler.{name}"


@pytest.mark.parametrize("algorithm", list(SAMPLERS))
def test_a_field_no_algorithm_reads_is_an_unknown_field(raw, algorithm):
    # max_redraws: a safety bound of abcns, not a spec field; carry_over: a field removed (issue X)
    for name in ("colour", "max_redraws", "carry_over"):
        with pytest.raises(SpecError, match="Extra inputs are not permitted") as err:
            parse(with_sampler(raw, {"algorithm": algorithm, name: 3}))
        assert err.value.field == f"sampler.{name}"
    with pytest.raises(SpecError, match="removed") as err:  # and says it was removed
        parse(with_sampler(raw, {"algorithm": algorithm, "carry_over": 3}))


@pytest.mark.parametrize(("change", "field", "match"), [
    ({"algorithm": "abc-nest"}, "sampler.algorithm", "'abc-ns', 'abc-smc' or 'rejection'"),
    ({"algorithm": "abc-smc", "quantile": "half"}, "sampler.quantile", "valid number"),
    ({"algorithm": "abc-smc", "schedule": [3.0, 5.0]}, "sampler.schedule", "must not increase"),
    ({"algorithm": "rejection", "pilot_quantile": 1.5}, "sampler.pilot_quantile", r"\(0, 1\)"),
    ({"weights": "magic"}, "sampler.weights", "'paper' or 'kernel'"),
    ({"variant": "other"}, "sampler.variant", "'evidence' or 'paper'"),
    ({"particles": 2.5}, "sampler.particles", "integer"),
])
def test_sampler_errors_name_the_field_without_the_algorithm(raw, change, field, match):
    sampler = {"epsilon_initial": 100, **change} if "algorithm" in change else {**raw["sampler"], **change}
    refuse(with_sampler(raw, sampler), SPEC.parent, field, match=match)


def test_an_http_error_location_has_no_algorithm_in_it():
    from service.http.api import validation_errors

    try:
        JobSpec.model_validate({"data": {"observed": [0.0]}, "models": [],
                                "sampler": {"algorithm": "abc-smc", "quantile": "half"}})
    except ValidationError as err:
        items = validation_errors([{**e, "loc": ("body", *e["loc"])} for e in err.errors()])
    assert [(i["loc"], i["field"]) for i in items] == [(["body", "models"], "models"),
                                                       (["body", "sampler", "quantile"], "sampler.quantile")]


@pytest.mark.parametrize("sampler", [
    {}, {"algorithm": "abc-ns", "variant": "paper", "weights": "kernel", "alpha": 0.2, "epsilon_initial": 100},
    {"max_ellipsoids": 3, "min_model_probability": 0.01, "min_proposal_share": 0.1, "pilot_size": 300},
    {"algorithm": "abc-smc", "schedule": [100, 50, 20], "particles": 500},
    {"algorithm": "abc-smc", "quantile": 0.4, "epsilon_initial": 100, "batch_size": 100},
    {"algorithm": "rejection", "epsilon_initial": 100, "pilot_quantile": 0.2},
])
def test_a_spec_written_back_validates_to_the_same_spec_and_settings(raw, sampler):
    """The service stores ``model_dump(mode="json")`` (spec.json, the store) and validates it
    again on a restart; the settings are the dataclass built from the fields given."""
    spec = parse(with_sampler(raw, sampler))
    for dumped in (spec.model_dump(), spec.model_dump(mode="json"), json.loads(spec.model_dump_json())):
        again = parse(dumped)
        assert again == spec and again.model_dump(mode="json") == spec.model_dump(mode="json")
    given = {k: tuple(v) if k == "schedule" else v for k, v in sampler.items() if k != "algorithm"}
    settings = build(spec, SPEC.parent).settings
    assert settings == SAMPLERS[sampler.get("algorithm", "abc-ns")](**given)
    assert build(parse(spec.model_dump(mode="json")), SPEC.parent).settings == settings


def old_dump(sampler: dict) -> dict:
    """A sampler section as the flat SamplerSpec of earlier versions wrote it: every field of
    every algorithm, null where not given."""
    names = ("particles", "alpha", "beta", "enlargement", "weights", "epsilon_initial", "pilot_size",
             "pilot_quantile", "batch_size", "variant", "max_ellipsoids", "min_model_probability",
             "min_proposal_share", "quantile", "schedule")
    return {"algorithm": "abc-ns", **{n: None for n in names}, "particles": 1000, "pilot_quantile": 0.5,
            "batch_size": 200, **sampler}


@pytest.mark.parametrize("sampler", [
    {"epsilon_initial": 100.0}, {"variant": "paper", "alpha": 0.2},
    {"algorithm": "abc-smc", "schedule": [100.0, 50.0]}, {"algorithm": "rejection", "epsilon_initial": 100.0},
])
def test_a_spec_stored_by_an_earlier_version_loads(raw, sampler):
    """Its nulls (fields of other algorithms, or left to their default) are the defaults; a
    value for a field of another algorithm is still refused. Earlier versions wrote their
    default batch size (200) out, so such a job keeps its random stream."""
    old = parse(with_sampler(raw, old_dump(sampler)))
    assert old == parse(with_sampler(raw, {**sampler, "batch_size": 200}))
    assert build(old, SPEC.parent).settings == build(parse(with_sampler(raw, {**sampler, "batch_size": 200})),
                                                     SPEC.parent).settings
    assert old.sampler.batch_size == 200
    other = "quantile" if sampler.get("algorithm", "abc-ns") == "abc-ns" else "alpha"
    with pytest.raises(SpecError) as err:
        parse(with_sampler(raw, {**old_dump(sampler), other: 0.3}))
    assert err.value.field == f"sampler.{other}"


def test_the_json_schema_has_one_sampler_per_algorithm_generated_from_the_settings():
    schema = JobSpec.model_json_schema()
    defs, sampler = schema["$defs"], schema["properties"]["sampler"]
    assert sampler["discriminator"]["propertyName"] == "algorithm"
    variants = {tag: defs[ref.rsplit("/", 1)[1]] for tag, ref in sampler["discriminator"]["mapping"].items()}
    assert set(variants) == set(SAMPLERS) and len(sampler["oneOf"]) == 3
    for tag, settings in SAMPLERS.items():
        fields = [f.name for f in dataclasses.fields(settings) if f.name != "max_redraws"]
        assert list(variants[tag]["properties"]) == ["algorithm", *fields], tag
        assert variants[tag]["additionalProperties"] is False
        assert variants[tag]["properties"]["algorithm"]["const"] == tag
        assert variants[tag]["properties"]["particles"] == {"default": 1000, "title": "Particles", "type": "integer"}
    ns = variants["abc-ns"]["properties"]
    assert ns["weights"]["enum"] == ["paper", "kernel"] and ns["variant"]["enum"] == ["evidence", "paper"]
    assert ns["alpha"] == {"default": 0.3, "title": "Alpha", "type": "number"}
    assert "required" not in variants["abc-ns"]  # algorithm left out is abc-ns
    smc = variants["abc-smc"]["properties"]
    assert smc["schedule"]["anyOf"][0] == {"items": {"type": "number"}, "type": "array"}
    stop = defs["StopSpec"]["properties"]
    assert list(stop) == [f.name for f in dataclasses.fields(StopRules)]
    assert stop["min_epsilon_decrease"]["default"] == 0.01 and defs["StopSpec"]["additionalProperties"] is False


def test_a_named_min_epsilon_decrease_is_the_users_own_rule(raw):
    """Without it, the paper's rule waits for the decision tolerance (abcns.StopRules); named
    in the spec, it may end the run above it (issue W)."""
    raw.pop("stop", None)
    assert build(parse(raw), SPEC.parent).stop.decrease_above_floor is False
    raw["stop"] = {"min_epsilon_decrease": 0.01}
    assert build(parse(raw), SPEC.parent).stop.decrease_above_floor is True
    raw["stop"] = {"min_epsilon_decrease": 0.01, "decrease_above_floor": False}
    assert build(parse(raw), SPEC.parent).stop.decrease_above_floor is False


def test_stop_rules_come_from_the_dataclass(raw):
    """null is a value of a stop rule (off), not its default."""
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": 3}
    spec = parse(raw)
    assert build(spec, SPEC.parent).stop == StopRules(min_epsilon_decrease=None, max_populations=3)
    assert parse(spec.model_dump(mode="json")).stop == spec.stop
    raw["stop"] = {"max_populations": 2.5}
    refuse(raw, SPEC.parent, "stop.max_populations")


# ---------------------------------------------------------------- P.3: the simulators' valid ranges
BOUC_WEN = ROOT / "examples" / "boucwen" / "spec.yaml"


@pytest.fixture
def bouc_wen_raw():
    raw = yaml.safe_load(BOUC_WEN.read_text())
    raw["models"] = raw["models"][:2]  # linear, bw-n1
    return raw


@pytest.mark.parametrize(("mutate", "field", "match"), [
    (lambda m: m["fixed"].update(n=1.5), "models[1].fixed.n", r"must be an integer in 1\.\.4 for simulator bouc_wen"),
    (lambda m: m["fixed"].update(n=5), "models[1].fixed.n", r"integer in 1\.\.4"),
    (lambda m: m["fixed"].update(n=0), "models[1].fixed.n", r"integer in 1\.\.4"),
    (lambda m: (m["fixed"].pop("n"), m["priors"].update(n=[1, 4])), "models[1].priors.n",
     r"is an integer in 1\.\.4: fix it"),
    (lambda m: m["priors"].update(m=[-1, 5]), "models[1].priors.m", r"\[-1, 5\] leaves the valid range of m .*> 0"),
    (lambda m: (m["priors"].pop("m"), m["fixed"].update(m=0)), "models[1].fixed.m", r"must be a number > 0"),
])
def test_a_value_outside_the_simulators_range_is_refused_naming_the_field(bouc_wen_raw, mutate, field, match):
    """P.3: Bouc-Wen's n is an integer the kernels have (1..4), a mass is positive; a fixed
    value outside, or a prior leaving the range, is refused before anything runs (it used
    to be accepted, and every simulation failed)."""
    mutate(bouc_wen_raw["models"][1])
    refuse(bouc_wen_raw, BOUC_WEN.parent, field, match)


def test_the_ranges_hold_every_example_and_the_gandk_bounds(bouc_wen_raw):
    """The ranges refuse nothing the examples use (n 1..4, the paper's g-and-k priors
    U(0, 10), which touch B > 0 and k > -1/2 only at a bound); the g-and-k's B and k
    are checked too."""
    for n in (1, 4):
        bouc_wen_raw["models"][1]["fixed"]["n"] = n
        build(parse(bouc_wen_raw), BOUC_WEN.parent)
    for path in sorted((ROOT / "examples").glob("*/spec.yaml")):
        spec, base = load(path)
        build(spec, base)
    gk = yaml.safe_load((ROOT / "examples" / "gandk_32" / "spec.yaml").read_text())
    base = ROOT / "examples" / "gandk_32"
    for name, prior in (("B", [-1, 10]), ("k", [-1, 10])):
        bad = copy.deepcopy(gk)
        bad["models"][0]["priors"][name] = prior
        refuse(bad, base, f"models[0].priors.{name}", "leaves the valid range")


def test_the_input_interpolation_is_a_data_option(raw):
    """P.4: ``data.input_interpolation``: ``hold`` (the default, as before) or ``linear``; the
    job's simulators get it; anything else is refused naming the field."""
    base = SPEC.parent
    assert {sim.input_interpolation for sim in build(parse(raw), base).simulators} == {"hold"}
    raw["data"]["input_interpolation"] = "linear"
    assert {sim.input_interpolation for sim in build(parse(raw), base).simulators} == {"linear"}
    raw["data"]["input_interpolation"] = "cubic"
    refuse(raw, base, "data.input_interpolation")
