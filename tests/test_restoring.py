"""The displacement-driven restoring-force models (issue Y): ``bouc_wen_restoring`` and
``bwbn_restoring`` (worker/restoring.py).

- the numba kernels against the numpy reference, integer and real exponents;
- BWBN without degradation or pinching is Bouc-Wen; the velocity rule and rate independence;
- bad input refused before a run, naming the field (a displacement with NaN, a pinching
  parameter outside its range, an exponent outside 0.5..10, an interpolation it has not);
- synthetic truths (benchmarks/restoring.py's problem, smaller): each model recovers its
  own parameters from data with 1 % noise, the truth inside the 95 % intervals, and the
  selection Bouc-Wen vs BWBN picks the true model with p >= 0.9. Seed 1 by default
  (``ABCNS_TEST_SEED`` overrides it); seeds 1-5 with larger runs are the benchmark's
  (``python -m benchmarks.restoring``, figures in docs/benchmarks.md).
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from abcns import InvalidSetting, SpecError
from abcns.executor import DIVERGED, OK
from benchmarks import restoring as problem
from service.spec import build, parse
from worker.restoring import BoucWenRestoring, BWBNRestoring, SpencerMR

SEED = int(os.environ.get("ABCNS_TEST_SEED", "1"))


def bw_draw(rng: np.random.Generator, size: int, n: np.ndarray) -> np.ndarray:
    return np.column_stack([rng.uniform(0.0, 0.5, size), rng.uniform(0.0, 0.3, size), rng.uniform(0.5, 2.0, size),
                            rng.uniform(0.5, 1.5, size), rng.uniform(0.3, 0.8, size), rng.uniform(-0.2, 0.3, size), n])


def bwbn_draw(rng: np.random.Generator, size: int, n: np.ndarray) -> np.ndarray:
    return np.column_stack([bw_draw(rng, size, n), rng.uniform(0.0, 0.1, size), rng.uniform(0.0, 0.1, size),
                            rng.uniform(0.5, 2.0, size), rng.uniform(0.0, 0.9, size), rng.uniform(0.1, 0.5, size),
                            rng.uniform(0.0, 0.1, size), rng.uniform(0.1, 1.0, size), rng.uniform(0.0, 0.3, size)])


@pytest.mark.parametrize(("cls", "draw"), [(BoucWenRestoring, bw_draw), (BWBNRestoring, bwbn_draw)])
def test_the_kernels_match_the_numpy_reference(cls, draw):
    """Seed 0; 40 particles, the exponents mixed (1..4 specialised, real ones by pow) in one
    batch. Tolerance 1e-9 relative to the force's scale: the kernels contract multiply-adds
    (FMA), the reference does not; the differences are rounding (~1e-15) grown along the
    hysteresis loops."""
    rng = np.random.default_rng(0)
    x = problem.displacement(300)
    n = rng.choice([1.0, 2.0, 3.0, 4.0, 1.7, 2.5], 40)
    params = draw(rng, 40, n)
    fast = cls(x, 0.01, substeps=3).simulate(params)
    slow = cls(x, 0.01, substeps=3, backend="numpy").simulate(params)
    assert np.all(fast.status == OK) and np.all(slow.status == OK)
    scale = np.max(np.abs(slow.values))
    np.testing.assert_allclose(fast.values, slow.values, rtol=0, atol=1e-9 * scale)
    observed = slow.values[5] + 0.01 * rng.standard_normal(x.size)
    d, status = cls(x, 0.01, substeps=3).distance_nmse(params, observed, 0, x.size)
    d_ref, _ = cls(x, 0.01, substeps=3, backend="numpy").distance_nmse(params, observed, 0, x.size)
    assert np.all(status == OK)
    np.testing.assert_allclose(d, d_ref, rtol=1e-7)


#: Spencer et al. (1997)'s values at 0 V in SI units (N, m, s): alpha 1.4e4 N/m, c0 2100 N s/m,
#: c1 28300 N s/m, k0 4690 N/m, k1 500 N/m, x0 0, gamma = beta = 3.63e6 1/m^2, A 301, n 2
SPENCER_0V = (1.4e4, 2100.0, 28300.0, 4690.0, 500.0, 0.0, 3.63e6, 3.63e6, 301.0, 2.0)


def spencer_draw(rng: np.random.Generator, size: int, n: np.ndarray) -> np.ndarray:
    """Around Spencer's 0 V values, each within a factor 1.4 (x0 +-1 mm)."""
    p = np.array(SPENCER_0V)[None, :] * rng.uniform(0.7, 1.4, (size, 10))
    p[:, 5] = rng.uniform(-1e-3, 1e-3, size)
    p[:, 9] = n
    return p


def test_spencer_matches_its_reference_and_guards_a_coarse_step():
    """Seed 2; a 2.5 Hz, 15 mm sine at 1 kHz (Spencer's test); n = 2 (Spencer's) or 2.5 (the
    pow path; gamma and beta in units of 1/m^n: with n = 1 these values are ~100 times
    stiffer). 32 RK4 steps per sample are stable for all 20 particles (z's rate reaches ~1e4
    /s, so 1 ms steps are not): kernel and
    reference agree to 1e-9 of the force's scale (FMA rounding, as above); at 1 substep the
    |z| bound flags the unstable integration DIVERGED in both instead of returning garbage."""
    rng = np.random.default_rng(2)
    t = np.arange(1000) / 1000.0
    x = 0.015 * np.sin(2 * np.pi * 2.5 * t)
    params = spencer_draw(rng, 20, rng.choice([2.0, 2.5], 20))
    fast = SpencerMR(x, 1e-3, substeps=32).simulate(params)
    slow = SpencerMR(x, 1e-3, substeps=32, backend="numpy").simulate(params)
    assert np.all(fast.status == OK) and np.all(slow.status == OK)
    np.testing.assert_allclose(fast.values, slow.values, rtol=0, atol=1e-9 * np.max(np.abs(slow.values)))
    p0 = np.array([SPENCER_0V])
    for backend in ("numba", "numpy"):
        assert SpencerMR(x, 1e-3, substeps=1, backend=backend).simulate(p0).status[0] != OK
    peak = np.max(np.abs(SpencerMR(x, 1e-3, substeps=32).simulate(p0).values))
    assert 400 < peak < 800  # N: Spencer et al.'s Fig. 4 at 0 V peaks near 600 N (their 1.5 cm, 2.5 Hz test)


def test_bwbn_without_degradation_or_pinching_is_bouc_wen():
    """zeta_s = delta_nu = delta_eta = 0: h = 1, nu = eta = 1, so the same z (the energy
    state is computed but not used); equal to rounding."""
    rng = np.random.default_rng(1)
    x = problem.displacement(300)
    bw = bw_draw(rng, 20, np.full(20, 2.0))
    bwbn = bwbn_draw(rng, 20, np.full(20, 2.0))
    bwbn[:, :7] = bw
    bwbn[:, 7:9] = 0.0
    bwbn[:, 10] = 0.0
    a = BoucWenRestoring(x, 0.01, substeps=2).simulate(bw).values
    b = BWBNRestoring(x, 0.01, substeps=2).simulate(bwbn).values
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.max(np.abs(a)))


def test_the_velocity_rule_and_rate_independence():
    """The viscous term is c times numpy.gradient(x, dt) (central differences, one-sided at
    the ends); with c = 0 the sample interval changes nothing (the hysteresis is integrated
    in x), and integrating in x converges: 2 substeps per sample are within 1e-5 of 64 on
    this record (RK4 error ~ (dx/substeps)^4: measured 3e-7 of the force's scale)."""
    x = problem.displacement(300)
    p = np.array([[0.0, 0.1, 1.0, 1.0, 0.6, 0.1, 2.0]])
    f = BoucWenRestoring(x, 0.01).simulate(p).values[0]
    np.testing.assert_array_equal(f, BoucWenRestoring(x, 0.5).simulate(p).values[0])
    viscous = p.copy()
    viscous[0, 0] = 0.3
    fc = BoucWenRestoring(x, 0.01).simulate(viscous).values[0]
    np.testing.assert_allclose(fc - f, 0.3 * np.gradient(x, 0.01), rtol=1e-12, atol=1e-12)
    fine = BoucWenRestoring(x, 0.01, substeps=64).simulate(p).values[0]
    coarse = BoucWenRestoring(x, 0.01, substeps=2).simulate(p).values[0]
    assert np.max(np.abs(coarse - fine)) < 1e-5 * np.max(np.abs(fine))


#: sharma's former posterior mean under 4 fixed RK4 steps per sample (the pinching notch zeta_2 ~
#: 0.009 wide in z) with beta and gamma swapped (it lay outside the domain, beta + gamma = -2.16),
#: then a wide notch (psi 0.5) and a stiff Bouc-Wen law (beta + |gamma| = 60)
NARROW = dict(c=0.0, k=-0.497, alpha=3.48, A=1.0, beta=3.88, gamma=-1.72, n=1.0, delta_nu=0.0023, delta_eta=0.605,
              p=7.2, zeta_s=0.899, psi=0.01, delta_psi=0.0, q=0.018, **{"lambda": 0.0063})
WIDE = {**NARROW, "psi": 0.5, "lambda": 0.2, "q": 0.1}
STIFF = {**NARROW, "zeta_s": 0.0, "beta": 30.0, "gamma": 30.0}


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_the_step_control_resolves_a_narrow_pinching_notch_and_a_stiff_law(backend):
    """The record: the benchmark's sine at 80 samples, scaled to a peak of 1 (steps up to 0.30
    of it: sharma's reach 0.44). At 4 RK4 steps per sample in x, fixed, the notch of width
    zeta_2 ~ 0.009 in z is jumped over: 4.3 % of the force's peak off 512 steps (measured with
    the step control switched off), and the stiff law is 14 % off. With the step control each
    is within 1e-3 of the peak (measured: 1.3e-4 and 1.8e-4; tolerance: the integration error a
    distance of ~1 % NMSE may carry unnoticed), the wide notch, which needs no more than 4
    steps, is 5e-5 off, and the numba kernels match the numpy reference to 1e-9 of the peak."""
    x = problem.displacement(80)
    x = x / np.max(np.abs(x))
    p = np.array([[v[k] for k in BWBNRestoring.parameter_names] for v in (NARROW, WIDE, STIFF)])
    ref = BWBNRestoring(x, 0.01, substeps=512).simulate(p).values
    got = BWBNRestoring(x, 0.01, substeps=4, backend=backend).simulate(p)
    assert np.all(got.status == OK)
    peak = np.max(np.abs(ref), axis=1)
    assert np.all(np.max(np.abs(got.values - ref), axis=1) < 1e-3 * peak), np.max(np.abs(got.values - ref), axis=1) / peak
    other = BWBNRestoring(x, 0.01, substeps=4, backend="numpy" if backend == "numba" else "numba").simulate(p).values
    np.testing.assert_allclose(got.values, other, rtol=0, atol=1e-9 * peak.max())


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_a_particle_outside_the_domain_beta_plus_gamma_positive_is_diverged(backend):
    """beta + gamma <= 0: z has no bound and BWBN's z_u (the pinching's centre) is negative or
    undefined. Before, such a particle was integrated like any other (chiu's BWBN posterior
    sat at beta + gamma ~ -5, sharma's needle at -2.05, both with z_u < 0); now it is DIVERGED,
    never integrated, in trajectories and in the in-kernel NMSE alike, and the particles
    inside the domain are what they are when simulated alone (bit for bit)."""
    rng = np.random.default_rng(3)
    spencer_x = 0.015 * np.sin(2 * np.pi * 2.5 * np.arange(300) / 1000.0)  # Spencer's test (above)
    for cls, draw, x, dt, substeps in ((BoucWenRestoring, bw_draw, problem.displacement(120), 0.01, 4),
                                       (BWBNRestoring, bwbn_draw, problem.displacement(120), 0.01, 4),
                                       (SpencerMR, spencer_draw, spencer_x, 1e-3, 32)):
        p = draw(rng, 6, np.full(6, 2.0))
        # the coefficient of either sign (gamma in the Bouc-Wen family, beta in Spencer's) on
        # the edge and beyond it
        free, other = (cls.parameter_names.index(k) for k in (("gamma", "beta") if cls is not SpencerMR
                                                              else ("beta", "gamma")))
        p[1, free], p[3, free] = -p[1, other], -p[3, other] - 0.5
        sim = cls(x, dt, substeps=substeps, backend=backend)
        out = sim.simulate(p)
        assert out.status.tolist() == [OK, DIVERGED, OK, DIVERGED, OK, OK], (cls.__name__, out.status)
        assert not np.any(out.values[[1, 3]])
        inside = [0, 2, 4, 5]
        np.testing.assert_array_equal(out.values[inside], sim.simulate(p[inside]).values)
        d, status = sim.distance_nmse(p, out.values[0] * 1.01, 0, x.size)
        assert status.tolist() == out.status.tolist() and np.all(np.isinf(d[[1, 3]])) and np.all(np.isfinite(d[inside]))


def spec(x: np.ndarray, force: np.ndarray) -> dict:
    """Bouc-Wen vs BWBN over inline records (the test problem's priors)."""
    bw = {"name": "bw", "simulator": "bouc_wen_restoring", "fixed": dict(problem.BW_FIXED),
          "priors": {k: list(v) for k, v in problem.BW_PRIORS.items()}, "integrator": {"substeps": 2}}
    bwbn = {"name": "bwbn", "simulator": "bwbn_restoring", "fixed": dict(problem.BWBN_FIXED),
            "priors": {k: list(v) for k, v in problem.BWBN_PRIORS.items()}, "integrator": {"substeps": 2}}
    return {"name": "restoring", "data": {"dt": 0.01, "input": x.tolist(), "observed": force.tolist()},
            "models": [bw, bwbn], "distance": "nmse", "sampler": {"particles": 100}, "stop": {"max_populations": 2},
            "seed": 1}


@pytest.fixture(scope="module")
def records() -> tuple[np.ndarray, np.ndarray]:
    x, observed, _noise = problem.data("bwbn", 100, np.random.default_rng(SEED))
    return x, observed


def test_a_valid_spec_builds(records):
    job = build(parse(spec(*records)))
    assert [s.name for s in job.simulators] == ["bouc_wen_restoring", "bwbn_restoring"]
    assert job.simulators[1].config()["input"] == "displacement"


@pytest.mark.parametrize(("change", "field", "words"), [
    (lambda s: s["models"][1]["priors"].update(zeta_s=[0.0, 1.2]), "models[1].priors.zeta_s",
     "leaves the valid range of zeta_s"),
    (lambda s: s["models"][1]["fixed"].update(q=1.0), "models[1].fixed.q", "must be a number >= 0 and < 1"),
    (lambda s: s["models"][1]["fixed"].update(**{"lambda": 0.0}), "models[1].fixed.lambda", "must be a number > 0"),
    (lambda s: s["models"][1]["fixed"].update(psi=-0.1), "models[1].fixed.psi", "must be a number > 0"),
    (lambda s: s["models"][1]["priors"].update(delta_nu=[-0.1, 0.2]), "models[1].priors.delta_nu",
     "leaves the valid range"),
    (lambda s: s["models"][0]["fixed"].update(n=0.2), "models[0].fixed.n", "must be a number >= 0.5 and <= 10"),
    (lambda s: (s["models"][0]["fixed"].pop("A"), s["models"][0]["priors"].update(A=[-1.0, 2.0])),
     "models[0].priors.A", "leaves the valid range of A"),
    (lambda s: s["data"].update(input_interpolation="linear"), "data.input_interpolation", "does not take"),
    (lambda s: s["data"].pop("input"), "data.input", "needs an input"),
    (lambda s: s["models"].append({"name": "mr", "simulator": "spencer_mr", "fixed": {"n": 2, "c0": 0},
                                   "priors": {k: [0.5, 1] for k in ("alpha", "c1", "k0", "k1", "gamma", "beta", "A")}}),
     "models[2].fixed.c0", "must be a number > 0"),
    (lambda s: s["models"][1]["priors"].update(gamma=[-3.0, -1.0]), "models[1].priors.gamma",
     "needs beta + gamma > 0"),
])
def test_bad_input_is_refused_naming_the_field(records, change, field, words):
    raw = spec(*records)
    change(raw)
    with pytest.raises(SpecError) as err:
        build(parse(raw))
    assert err.value.field == field and words in err.value.message


def test_the_run_checks_a_restoring_model_s_own_error_at_twice_its_substeps(records):
    """The run's model-error check (``service/run/model_error.py``) simulates the best fit
    again at twice the substeps and projects the change on the fit: for the restoring-force
    models too (before, only the force-driven Duffing and Bouc-Wen: nothing was checked). At
    the test problem's BWBN truth (100 samples, 2 substeps, the step control) the move is
    below 0.1 of the fit's standard deviations (measured 0.034; the warning's level for 7
    parameters is 3.3)."""
    from service.run.model_error import parameter_shift

    job = build(parse(spec(*records)))
    theta = np.array([problem.BWBN_TRUE[k] for k in problem.BWBN_PRIORS])
    found = parameter_shift(job, 1, theta, (0, records[0].size))
    assert [f["field"] for f in found] == ["integrator.substeps"], found
    assert found[0]["sd"] < 0.1, found


def test_a_displacement_with_nan_is_refused_naming_the_field(records, tmp_path):
    """Through the spec (a file: JSON has no NaN) and through the library directly."""
    x, observed = records
    bad = x.copy()
    bad[7] = np.nan
    np.save(tmp_path / "x.npy", bad)
    np.save(tmp_path / "f.npy", observed)
    raw = spec(x, observed)
    raw["data"].update(input="x.npy", observed="f.npy")
    with pytest.raises(SpecError) as err:
        build(parse(raw), tmp_path)
    assert err.value.field == "data.input" and "sample 7 (counting from 0) is nan" in err.value.message
    for cls in (BoucWenRestoring, BWBNRestoring):
        with pytest.raises(InvalidSetting) as err:
            cls(bad, 0.01)
        assert err.value.path == ("force",) and "sample 7" in err.value.message  # the input: data.input


# ---------------------------------------------------------------- synthetic truths
# 200 samples, 200 particles (the benchmark: 400 and 500); each run ~1-2 s here.
N_SAMPLES, PARTICLES = 200, 200


@pytest.mark.slow
@pytest.mark.parametrize("truth", ["bw", "bwbn"])
def test_each_model_recovers_its_parameters(truth):
    """Data of the true model with 1 % noise (the noise std given, so the run stops at its
    decision tolerance): every true value inside its 95 % posterior interval (the issue's
    criterion). Its false-failure rate is the intervals' own: each misses 1 time in 20, so a
    test of 4 (7) parameters fails on ~19 % (30 %) of seeds if the intervals were exact and
    independent. Measured: the benchmark (seeds 1-5, 500 particles, 400 samples) held 53 of 55
    intervals (Bouc-Wen seed 4 missed k, BWBN seed 3 alpha); at this test's size seeds 1-5
    pass 7 runs of 10 (Bouc-Wen seed 5 and BWBN seeds 2 and 5 miss alpha, each by under a
    fifth of the interval's width). Seed 1, fixed, passes both; another seed given by
    ``ABCNS_TEST_SEED`` fails at the rate above, which is not a bug."""
    result = problem.run(truth, [truth], N_SAMPLES, PARTICLES, SEED)
    cov = problem.coverage(result, truth)
    assert set(cov) == set(problem.BW_PRIORS if truth == "bw" else problem.BWBN_PRIORS)
    assert all(inside for _lo, _hi, inside in cov.values()), cov


@pytest.mark.slow
@pytest.mark.parametrize("truth", ["bw", "bwbn"])
def test_model_selection_picks_the_true_model(truth):
    """Bouc-Wen vs BWBN (which holds Bouc-Wen at its priors' corner): p(truth) >= 0.9, the
    issue's threshold; measured 1.0000 on seeds 1-5 of the benchmark for both truths (the
    evidence pays for BWBN's three extra parameters when they buy nothing, and BW cannot fit
    pinched, degrading loops)."""
    result = problem.run(truth, ["bw", "bwbn"], N_SAMPLES, PARTICLES, SEED)
    assert result.summary()["model_probabilities"][truth] >= 0.9


def test_the_cyclic_example_reads_both_layouts_and_builds(tmp_path):
    """examples/cyclic_tests (its data are not in the repository): the script reads a user's
    folder in either layout (our CSV, the source's two text files) and its models.yaml builds
    over the scaled records."""
    from examples.cyclic_tests import run as cyclic

    x, f, _noise = problem.data("bwbn", 120, np.random.default_rng(SEED))
    np.savetxt(tmp_path / "daniel.csv", np.column_stack([np.arange(x.size), x, f]), delimiter=",",
               header="step,displacement,load_kn", comments="")
    np.savetxt(tmp_path / "displ_gill.txt", x)
    np.savetxt(tmp_path / "load_kN_gill.txt", f)
    for name in ("daniel", "gill"):
        xs, fs = cyclic.read_specimen(tmp_path, name)
        np.testing.assert_allclose(xs, x, rtol=1e-12)
        job = build(parse(cyclic.spec_for(xs / np.max(np.abs(xs)), fs / np.max(np.abs(fs)), 1, 100)))
        assert [m.name for m in job.models] == ["bw", "bwbn", "bwbn_log"]
    with pytest.raises(SystemExit, match=r"README\.md says where"):
        cyclic.read_specimen(tmp_path, "chiu")


def test_the_cyclic_example_stops_on_populations_never_on_the_clock():
    """Issue Y: a run stopped by ``max_seconds`` answers what the machine's speed allowed
    (kunnath stopped at population 70 of a collapsed posterior); the example's answer must be
    a property of the job, so its spec stops on populations (and the noise floor) only."""
    from examples.cyclic_tests import run as cyclic

    x = np.sin(np.linspace(0, 6, 50))
    job = build(parse(cyclic.spec_for(x, x, 1, 100)))
    assert job.stop.max_seconds is None
    assert job.stop.max_populations is not None and job.stop.max_populations >= 95  # gill's floor
