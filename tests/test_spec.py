"""The job spec: a valid spec runs like the same problem built in code; malformed specs
are refused before anything runs, naming the field."""

import copy
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from abcns import SpecError, StopRules, run
from examples.paper import authors_demo
from service.run.runner import write_interval
from service.spec import build, load, parse

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
    "mutate, field",
    [
        (lambda r: r["models"][1].update(simulator="nope"), "models[1].simulator"),
        (lambda r: r["models"][1]["priors"].pop("k"), "models[1].priors"),
        (lambda r: r["models"][0]["priors"].update(k3=[0, 1]), "models[0].fixed.k3"),
        (lambda r: r["models"][0]["priors"].update(c=[1, 0]), "models[0].priors.c"),
        (lambda r: r["models"][0]["priors"].update(q=[0, 1]), "models[0].priors.q"),
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


def test_observed_with_nan_and_length_mismatch(raw, tmp_path):
    d = demo_data()
    obs = d["displacement"].copy()
    obs[7] = np.nan
    np.save(tmp_path / "obs.npy", obs)
    np.save(tmp_path / "short.npy", d["displacement"][:400])
    np.save(tmp_path / "force.npy", d["force"])
    raw["data"].update(input="force.npy", observed="obs.npy")
    refuse(raw, tmp_path, "data.observed", match="index 7")
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
