"""Spencer's MR-damper model with the coil voltage as a second input channel
(``spencer_mr_voltage``, worker/restoring.py; the spec's ``data.voltage``).

- the numba kernel against the numpy reference (integer and real exponents), and the
  constant-voltage model as its special case (no voltage terms);
- the voltage laws (alpha, c0, c1 linear in the filtered voltage u, u' = -eta (u - e)) against
  the constant-voltage model at those values, independently of the reference;
- the channel through the spec, the worker's rebuild and the analysis; bad input refused
  before a run, naming the field (a voltage missing, NaN, of the wrong length, negative, with
  no input, or given to models that read none);
- synthetic truth (benchmarks/spencer_voltage.py's problem, smaller): its own parameters
  recovered at 1 % noise, the truth inside the 95 % intervals, and Bouc-Wen vs Spencer on
  Spencer data picks Spencer with p >= 0.9. Seed 1 (``ABCNS_TEST_SEED`` overrides it); seeds
  1-5 with larger runs are the benchmark's (``python -m benchmarks.spencer_voltage``).
"""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np
import pytest

from abcns import InvalidSetting, SpecError
from abcns.executor import OK
from benchmarks import spencer_voltage as problem
from service.report.analysis import job_data
from service.spec import build, description, job_arrays, parse
from worker.description import job_parts
from worker.restoring import SpencerMR, SpencerMRVoltage

SEED = int(os.environ.get("ABCNS_TEST_SEED", "1"))
TRUE = np.array([problem.SPENCER_TRUE[p] for p in SpencerMRVoltage.parameter_names])


def draw(rng: np.random.Generator, size: int, n: np.ndarray) -> np.ndarray:
    """Around Spencer's values, each within a factor 1.4 (x0 within +-1 cm)."""
    p = TRUE[None, :] * rng.uniform(0.7, 1.4, (size, TRUE.size))
    p[:, 8] = rng.uniform(-1.0, 1.0, size)
    p[:, 12] = n
    return p


def test_the_kernel_matches_the_numpy_reference():
    """Seed 3; 20 particles, n = 2 (specialised) and 2.5 (pow) in one batch, over the
    benchmark's records (square-wave voltage). Tolerance 1e-9 of the force's scale: the
    kernel contracts multiply-adds (FMA), the reference does not (measured 4.9e-16)."""
    rng = np.random.default_rng(3)
    x, e = problem.records(400)
    params = draw(rng, 20, rng.choice([2.0, 2.5], 20))
    fast = SpencerMRVoltage(x, 1 / problem.FS, substeps=16, voltage=e).simulate(params)
    slow = SpencerMRVoltage(x, 1 / problem.FS, substeps=16, voltage=e, backend="numpy").simulate(params)
    assert np.all(fast.status == OK) and np.all(slow.status == OK)
    np.testing.assert_allclose(fast.values, slow.values, rtol=0, atol=1e-9 * np.max(np.abs(slow.values)))
    observed = slow.values[4] + 5.0 * rng.standard_normal(x.size)
    d, status = SpencerMRVoltage(x, 1 / problem.FS, substeps=16, voltage=e).distance_nmse(params, observed, 0, x.size)
    d_ref, _ = SpencerMRVoltage(x, 1 / problem.FS, substeps=16, voltage=e,
                                backend="numpy").distance_nmse(params, observed, 0, x.size)
    assert np.all(status == OK)
    np.testing.assert_allclose(d, d_ref, rtol=1e-7)


def test_without_voltage_terms_it_is_the_constant_voltage_model():
    """alpha_b = c0b = c1b = 0: the voltage plays no part, and the force is spencer_mr's at
    (alpha_a, c0a, c1a) to rounding, whatever the voltage record; with the voltage terms the
    2.25 V half-periods raise the force (Spencer's 0 V and 2.25 V loops differ ~4x)."""
    x, e = problem.records(400)
    full = TRUE.copy()
    full[[1, 3, 5]] = 0.0
    const = full[[0, 2, 4, 6, 7, 8, 9, 10, 11, 12]][None, :]
    a = SpencerMR(x, 1 / problem.FS, substeps=16).simulate(const).values[0]
    for backend in ("numba", "numpy"):
        b = SpencerMRVoltage(x, 1 / problem.FS, substeps=16, voltage=e, backend=backend).simulate(full[None]).values[0]
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-12 * np.max(np.abs(a)))
    driven = SpencerMRVoltage(x, 1 / problem.FS, substeps=16, voltage=e).simulate(TRUE[None]).values[0]
    assert np.max(np.abs(driven)) > 2 * np.max(np.abs(a))


@pytest.mark.parametrize("volts", [0.0, 1.0, 2.25])
def test_the_voltage_laws_and_the_filter(volts):
    """A constant command e with a fast filter (eta = 2e4 /s: u is within 2e-9 e of e after the
    first 1 ms sample step, while the sine has moved 0.24 mm) is spencer_mr at alpha = alpha_a +
    alpha_b e, c0 = c0a + c0b e, c1 = c1a + c1b e from the second sample on (the first is at
    u(0) = 0): within 1e-4 of the force's scale (the filter's first steps are the difference;
    measured 1.5e-6). RK4 on u: eta h = 0.6 (< 2.78), 1e-3 s / 32."""
    t = np.arange(1000) / 1000.0
    x = 1.5 * np.sin(2 * np.pi * 2.5 * t)  # Spencer's 2.5 Hz, 1.5 cm test
    p = TRUE.copy()
    p[13] = 2e4
    v = SpencerMRVoltage(x, 1e-3, substeps=32, voltage=np.full(x.size, volts)).simulate(p[None]).values[0]
    al, c0, c1 = p[0] + p[1] * volts, p[2] + p[3] * volts, p[4] + p[5] * volts
    const = np.array([[al, c0, c1, p[6], p[7], p[8], p[9], p[10], p[11], p[12]]])
    a = SpencerMR(x, 1e-3, substeps=32).simulate(const).values[0]
    assert np.max(np.abs(v[1:] - a[1:])) < 1e-4 * np.max(np.abs(a))


def spec(x: np.ndarray, e: np.ndarray, force: np.ndarray) -> dict:
    """Bouc-Wen vs Spencer with the voltage over inline records (the problem's priors)."""
    sp = {"name": "spencer", "simulator": "spencer_mr_voltage", "fixed": dict(problem.SPENCER_FIXED),
          "priors": {k: list(v) for k, v in problem.SPENCER_PRIORS.items()}, "integrator": {"substeps": 16}}
    bw = {"name": "bw", "simulator": "bouc_wen_restoring", "fixed": dict(problem.BW_FIXED),
          "priors": {k: list(v) for k, v in problem.BW_PRIORS.items()}, "integrator": {"substeps": 2}}
    return {"name": "mr", "data": {"fs": problem.FS, "input": x.tolist(), "voltage": e.tolist(),
                                   "observed": force.tolist()},
            "models": [bw, sp], "sampler": {"particles": 100}, "stop": {"max_populations": 2}, "seed": 1}


@pytest.fixture(scope="module")
def records() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x, e, observed, _noise = problem.data(200, np.random.default_rng(SEED))
    return x, e, observed


def test_the_voltage_travels_to_the_worker_and_the_analysis(records):
    """The job built from the spec, the worker's rebuild from (description, job_arrays) and
    the analysis's whole-record simulators hold the same voltage and give the same forces;
    with a fit window the job's simulators hold its first samples only."""
    x, e, f = records
    job = build(parse(spec(x, e, f)))
    np.testing.assert_array_equal(job.voltage, e)
    _models, sims, _d = job_parts(description(job.spec), job_arrays(job))
    np.testing.assert_array_equal(sims[1].voltage, e)
    analysed = job_data(spec(x, e, f), None).simulators["spencer"]
    np.testing.assert_array_equal(analysed.voltage, e)
    np.testing.assert_array_equal(analysed.simulate(TRUE[None]).values, job.simulators[1].simulate(TRUE[None]).values)
    raw = spec(x, e, f)
    raw["data"]["fit"] = [0, 150]
    assert build(parse(raw)).simulators[1].voltage.size == 150


def _put(raw: dict, field: str, value) -> dict:
    raw["data"][field] = value
    return raw


@pytest.mark.parametrize(("change", "words"), [
    (lambda r: r["data"].pop("voltage"), "needs the coil voltage record"),
    (lambda r: _put(r, "voltage", r["data"]["voltage"][:-1]), "one sample per displacement sample (200)"),
    (lambda r: r.update(models=r["models"][:1]), "no model's simulator reads a voltage record"),
    (lambda r: (r["data"].pop("input"), r["data"].pop("fs")), "needs the input record"),
])
def test_bad_voltage_is_refused_naming_the_field(records, change, words):
    raw = spec(*records)
    change(raw)
    with pytest.raises(SpecError) as err:
        build(parse(raw))
    assert err.value.field == "data.voltage" and words in err.value.message, err.value
    assert "data.voltage" not in err.value.message, err.value  # the field named once, by service.spec (issue X.3)


def test_a_negative_voltage_enters_the_laws_and_c0_plus_c1_must_stay_positive():
    """A command below 0 (a measured one rings to -0.4 V) is taken as it is; a particle whose
    c0 + c1 = (c0a + c1a) + (c0b + c1b) u reaches 0 at a sample is DIVERGED, in the kernel and
    the reference, and the others are OK."""
    x, e = problem.records(400)
    e = e - 1.0  # -1 V and 1.25 V
    ok, bad = TRUE.copy(), TRUE.copy()
    bad[[2, 3, 4, 5]] = [1.0, 200.0, 1.0, 100.0]  # c0 + c1 = 2 + 300 u: negative once u < -1/150 V
    for backend in ("numba", "numpy"):
        out = SpencerMRVoltage(x, 1 / problem.FS, substeps=16, voltage=e, backend=backend).simulate(np.array([ok, bad]))
        assert out.status[0] == OK and out.status[1] != OK, backend


def test_a_voltage_with_nan_is_refused_naming_the_field(records, tmp_path):
    """Through the spec (a file: JSON has no NaN) and through the library directly."""
    x, e, f = records
    bad = e.copy()
    bad[7] = np.nan
    np.save(tmp_path / "e.npy", bad)
    raw = spec(x, e, f)
    raw["data"]["voltage"] = "e.npy"
    with pytest.raises(SpecError) as err:
        build(parse(raw), tmp_path)
    assert err.value.field == "data.voltage" and "sample 7 (counting from 0) is nan" in err.value.message
    with pytest.raises(InvalidSetting) as err:
        SpencerMRVoltage(x, 1 / problem.FS, voltage=bad)
    assert err.value.path == ("voltage",) and "sample 7 is nan" in err.value.message


@pytest.mark.parametrize(("field", "value", "words"), [
    ("c0a", 0.0, "must be a number > 0"), ("eta", -1.0, "must be a number > 0"),
    ("alpha_b", -10.0, "must be a number >= 0"), ("n", 0.2, "must be a number >= 0.5 and <= 10")])
def test_a_parameter_outside_its_range_is_refused(records, field, value, words):
    raw = spec(*records)
    raw["models"][1]["priors"].pop(field, None)
    raw["models"][1]["fixed"][field] = value
    with pytest.raises(SpecError) as err:
        build(parse(raw))
    assert err.value.field == f"models[1].fixed.{field}" and words in err.value.message


# ---------------------------------------------------------------- synthetic truth
# 500 samples (1 s), 200 particles (the benchmark: 1000 and 400); ~15-30 s each here.
N_SAMPLES, PARTICLES = 500, 200


@pytest.mark.slow
def test_spencer_recovers_its_parameters():
    """Spencer data with 1 % noise (the noise std given, so the run stops at its decision
    tolerance): every true value inside its 95 % posterior interval (the issue's criterion).
    Its false-failure rate is the intervals' own: five intervals that each miss 1 time in 20
    fail together on ~23 % of seeds if they were exact and independent. Measured: at this
    test's size seeds 1-5 all pass (~4 s each); the benchmark (1000 samples, 400 particles) held
    24 of 25 intervals (seed 1 missed eta, [187.9, 189.9] against 190). Seed 1, fixed, passes."""
    result = problem.run(["spencer"], N_SAMPLES, PARTICLES, SEED)
    cov = problem.coverage(result, "spencer", problem.TRUTHS)
    assert set(cov) == set(problem.SPENCER_PRIORS)
    assert all(inside for _lo, _hi, inside in cov.values()), cov


@pytest.mark.slow
def test_model_selection_picks_spencer_on_spencer_data():
    """Bouc-Wen (no voltage) vs Spencer with the voltage on Spencer data: p(spencer) >= 0.9,
    the issue's threshold (the benchmark measured 1.0000 on seeds 1-5: a model blind to the
    voltage cannot follow a force that changes ~4x with it)."""
    result = problem.run(["bw", "spencer"], N_SAMPLES, PARTICLES, SEED)
    assert result.summary()["model_probabilities"]["spencer"] >= 0.9


def _source_csv(path, t: np.ndarray, x: np.ndarray, volts: np.ndarray, force: np.ndarray) -> None:
    """A record in the source's layout (quoted header, trailing empty column)."""
    rows = "\n".join(f"{a:.7g},0,{b:.7g},{c:.7g},,0,{d:.7g}," for a, b, c, d in zip(t, x, volts, force, strict=True))
    path.write_text('"t","A","D","Y","fs","V","F",\n' + rows + "\n")


def test_the_mr_damper_example_reads_the_source_layout_and_builds(tmp_path):
    """examples/mr_damper (its data are not in the repository): the script reads a CSV in the
    source's layout, keeps the active 21 s, and its models.yaml builds over the records with
    the voltage clipped at 0 and the force less its fit-window mean; ``--predict`` scores the
    posterior means on another record without its saturated samples (a saturated sample's
    value, past the preload's window, plays no part); a file without the columns is refused
    saying so."""
    from examples.mr_damper import run as mr

    n = int(mr.ACTIVE_S * mr.FS) + 300
    t = np.arange(n) / mr.FS
    x = 0.2 * np.sin(2 * np.pi * 3.0 * t)
    volts = np.where(np.floor(t / 0.02) % 2 == 1, 2.25, -0.1)
    force = 800.0 * np.tanh(20 * x) - 129.0
    _source_csv(tmp_path / "ranran.csv", t, x, volts, force)
    xs, es, fs = mr.read_record(tmp_path / "ranran.csv")
    assert xs.size == int(mr.ACTIVE_S * mr.FS)
    np.testing.assert_allclose(es, volts[: xs.size], rtol=1e-6)
    raw = mr.spec_for(xs, es, fs, 1, 100)
    assert min(raw["data"]["voltage"]) == 0.0 and abs(np.mean(raw["data"]["observed"][:6000])) < 1e-6
    job = build(parse(raw))
    assert [m.name for m in job.models] == ["bw", "bw_v", "spencer"]
    assert job.simulators[2].voltage.size == 2000  # the fit window, decimated by 3
    post = {"spencer": {k: {"mean": problem.SPENCER_TRUE[k]} for k in raw["models"][2]["priors"]}}
    scores = []
    for peak in (5000.0, 1e6):  # 3 s of record
        force[7000] = peak
        _source_csv(tmp_path / "other.csv", t[:9000], x[:9000], volts[:9000], force[:9000])
        scores.append(mr.predict_other(tmp_path / "other.csv", {"posterior": post}, 1)["spencer"])
    assert np.isfinite(scores[0]) and scores[0] == scores[1]
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n3,4\n")
    with pytest.raises(SystemExit, match="no column"):
        mr.read_record(tmp_path / "bad.csv")


def test_a_run_stores_the_voltage_and_its_analysis_reads_it_back(records, tmp_path):
    """The runner (in this process) over a spec with the voltage in a file: the data hash it
    stores covers the voltage, so the analysis reads the same voltage back (store_job_data
    checks the hash) and a changed voltage is told apart."""
    from service.report.analysis import store_job_data
    from service.run.runner import run_job
    from service.run.store import Store

    x, e, f = records
    np.save(tmp_path / "e.npy", e)
    raw = spec(x, e, f)
    raw["data"]["voltage"] = "e.npy"
    raw["stop"] = {"max_populations": 1}
    run_job(parse(raw), tmp_path, tmp_path / "mr.zarr", None)
    store = Store.open(tmp_path / "mr.zarr")
    np.testing.assert_array_equal(store_job_data(store, tmp_path).simulators["spencer"].voltage, e)
    np.save(tmp_path / "e.npy", np.roll(e, 1))
    with pytest.raises(ValueError, match="not the data this store was run on"):
        store_job_data(store, tmp_path)


def test_the_http_intake_takes_an_inline_voltage_and_refuses_a_file_name(records):
    """Over HTTP the voltage comes inline (stored with the job's other arrays) or as npz:KEY of
    an upload, never as a file name on the server (422 naming data.voltage)."""
    import json

    from service.http.intake import Refused, spec_of

    x, e, f = records
    raw = spec(x, e, f)
    spec_obj, arrays = spec_of(json.dumps(raw).encode(), "spec", "json", 10**6)
    np.testing.assert_array_equal(arrays["voltage"], e)
    assert spec_obj.data.voltage.endswith(":voltage")
    raw["data"]["voltage"] = "/etc/passwd"
    with pytest.raises(Refused) as err:
        spec_of(json.dumps(raw).encode(), "spec", "json", 10**6)
    assert err.value.status == 422 and err.value.detail[0]["field"] == "data.voltage"


def test_a_factory_that_takes_only_kwargs_is_not_offered_the_voltage(records, monkeypatch):
    """A plugin written before the voltage channel (``factory(**kwargs)``, as
    benchmarks/sleepy.py) gets the keywords it always got, not ``voltage``; spencer_mr_voltage,
    which names it, gets the record."""
    from worker import description, registry

    seen: dict = {}

    def old_plugin(**kwargs):
        seen.update(kwargs)
        return SpencerMR(kwargs["force"], kwargs["dt"], substeps=2)

    monkeypatch.setitem(registry.BUILTINS, "old_plugin", old_plugin)
    x, e, f = records
    desc = description.ModelDescription("p", "old_plugin", {}, substeps=2)
    description.simulator_for(desc, x, 0.002, f, 0, voltage=e)
    assert "voltage" not in seen and set(seen) == set(description.INPUT_KEYWORDS)
    desc = replace(desc, simulator="spencer_mr_voltage")
    assert description.simulator_for(desc, x, 0.002, f, 0, voltage=e).voltage is e
