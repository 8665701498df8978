"""The simulator registry: built-ins, plugins by entry point, local module:factory (CLI only),
substeps chosen from the priors, the simulator protocols and the keywords factories get."""

import math
from dataclasses import replace

import numpy as np
import pytest

from abcns import InvalidSetting, Model
from abcns.distances import NMSE, CallableDistance, SummaryEuclidean
from worker import description as description_module
from worker import registry
from worker.compose import model_function
from worker.description import JobDescription, ModelDescription, simulator_for
from worker.kernels import choose_substeps
from worker.simulators import BoucWen, Duffing, GAndK, Linear, NMSECapable, Oscillator, Simulator
from worker.tasks import job_evaluator


def description(simulator="duffing", substeps=None, priors=None, input_interpolation="hold"):
    model = ModelDescription("m", simulator, priors or {"c": (0.1, 1.0), "k": (100.0, 10000.0)},
                             {"m": 1, "k3": 0, "k5": 0}, substeps)
    return JobDescription((model,), dt=0.01, input_interpolation=input_interpolation)


ARRAYS = {"force": np.sin(np.arange(200) * 0.1), "observed": np.cos(np.arange(200) * 0.1)}


def built_simulators(monkeypatch) -> list:
    """The simulators job_evaluator builds, recorded on their way out of simulator_for."""
    built, build = [], description_module.simulator_for

    def record(*args, **kwargs):
        built.append(build(*args, **kwargs))
        return built[-1]

    monkeypatch.setattr(description_module, "simulator_for", record)
    return built


def test_substeps_are_chosen_from_the_priors(monkeypatch):
    built = built_simulators(monkeypatch)
    job_evaluator(description(), ARRAYS)
    omega = Duffing.omega_max({"m": (1, 1), "c": (0.1, 1.0), "k": (100, 1e4), "k3": (0, 0), "k5": (0, 0)})
    assert omega == pytest.approx(0.5 + math.sqrt(0.25 + 1e4))
    expected = choose_substeps(omega, 0.01)
    assert expected == math.ceil(0.01 * omega / (120 * 1e-4) ** 0.25) == 4  # ceil(1.005 / 0.331)
    assert [type(s) for s in built] == [Duffing] and built[0].substeps == expected
    # an explicit integrator.substeps wins over the choice (3, not the 4 the priors give)
    job_evaluator(description(substeps=3), ARRAYS)
    assert len(built) == 2 and built[1].substeps == 3


def test_module_factory_only_when_imports_are_allowed():
    with pytest.raises(InvalidSetting, match="only registered simulators") as err:
        job_evaluator(description("worker.simulators:Duffing"), ARRAYS)
    assert err.value.path == ("models", 0, "simulator")
    models, _ = job_evaluator(description("worker.simulators:Duffing"), ARRAYS, allow_import=True)
    assert models[0].name == "m"
    with pytest.raises(InvalidSetting, match="cannot load"):
        job_evaluator(description("no_such_module:f"), ARRAYS, allow_import=True)


def test_entry_point_plugins_are_found(monkeypatch):
    class EP:
        name = "mine"

        def load(self):
            return Duffing

    monkeypatch.setattr(registry, "plugins", lambda: {"mine": EP()})
    assert "mine" in registry.names()
    assert registry.get("mine") is Duffing


def test_builtins_follow_the_protocols():
    f = np.sin(np.arange(50) * 0.1)
    oscillators = (Duffing(f, 0.01), BoucWen(f, 0.01), Linear(f, 0.01))
    for sim in (*oscillators, GAndK(50)):
        assert isinstance(sim, Simulator) and sim.n_samples == 50
    assert all(isinstance(sim, NMSECapable) and isinstance(sim, Oscillator) for sim in oscillators)
    assert not isinstance(GAndK(50), NMSECapable)
    assert [cls.needs_input for cls in (Duffing, BoucWen, Linear, GAndK)] == [True, True, True, False]
    # config() keeps its keys (provenance): substeps for RK4, the method for the exact ZOH
    assert list(Duffing(f, 0.01, substeps=3).config()) == [
        "simulator", "substeps", "output", "dt", "n_samples", "state_bound", "backend", "input_interpolation"]
    assert Linear(f, 0.01).config()["method"] == "exact-zoh" and "substeps" not in Linear(f, 0.01).config()


def test_factories_get_the_keywords_they_take():
    obs = ARRAYS["observed"]
    desc = ModelDescription("m", "linear", {"c": (0.1, 1.0)}, substeps=4)
    lin = simulator_for(desc, ARRAYS["force"], 0.01, obs, 0)  # Linear takes no substeps
    assert type(lin) is Linear and lin.state_bound == 1e3 * np.max(np.abs(obs))
    gk = simulator_for(replace(desc, simulator="gandk"), ARRAYS["force"], 0.01, obs, 0)
    assert type(gk) is GAndK and gk.n_samples == obs.size
    with pytest.raises(InvalidSetting, match="needs an input force") as err:
        simulator_for(replace(desc, simulator="bouc_wen"), None, None, obs, 0)
    assert err.value.path == ("force",)  # the job's input record, not the model's


def test_plugins_without_needs_input_are_called_as_before(monkeypatch):
    """A plugin without ``needs_input`` gets every keyword, and ``force=None`` without an input."""
    calls = []

    def legacy(force, dt, n_samples, substeps, output, state_bound):
        calls.append(dict(force=force, dt=dt, n_samples=n_samples, substeps=substeps, output=output,
                          state_bound=state_bound))
        return GAndK(n_samples)

    def needs(force, dt, output):  # declares needs_input: gets only what it names
        calls.append(dict(force=force, dt=dt, output=output))
        return GAndK(force.size)

    needs.needs_input = True
    monkeypatch.setattr(registry, "plugins", lambda: {"legacy": EPOf(legacy), "needs": EPOf(needs)})
    obs = ARRAYS["observed"]
    desc = ModelDescription("m", "legacy", {"A": (0, 1)})
    assert simulator_for(desc, None, None, obs, 0).n_samples == obs.size
    assert calls[-1] == dict(force=None, dt=None, n_samples=obs.size, substeps=1, output="displacement",
                             state_bound=1e3 * np.max(np.abs(obs)))
    simulator_for(replace(desc, simulator="needs"), ARRAYS["force"], 0.01, obs, 0)
    assert list(calls[-1]) == ["force", "dt", "output"]
    with pytest.raises(InvalidSetting) as err:
        simulator_for(replace(desc, simulator="needs"), None, None, obs, 0)
    assert err.value.path == ("force",)


def test_the_input_interpolation_reaches_the_simulators_that_take_it(monkeypatch):
    """P.4: ``data.input_interpolation`` goes to every oscillator (default ``hold``, the
    behaviour before the option); a factory that does not take it gets ``hold`` only, and the
    option needs an input record."""
    for interpolation in ("hold", "linear"):
        built = built_simulators(monkeypatch)
        job_evaluator(description(input_interpolation=interpolation), ARRAYS)
        assert [sim.input_interpolation for sim in built] == [interpolation]
        assert built[0].config()["input_interpolation"] == interpolation
        monkeypatch.undo()
    built = built_simulators(monkeypatch)
    job_evaluator(description(), ARRAYS)  # the default: hold
    assert built[0].input_interpolation == "hold"

    def needs(force, dt, output):  # a plugin that holds its input its own way
        return Duffing(force, dt, output=output)

    needs.needs_input = True
    monkeypatch.setattr(registry, "plugins", lambda: {"needs": EPOf(needs)})
    desc = ModelDescription("m", "needs", {"c": (0.1, 1.0)})
    simulator_for(desc, ARRAYS["force"], 0.01, ARRAYS["observed"], 0)
    with pytest.raises(InvalidSetting, match="does not take input_interpolation") as err:
        simulator_for(desc, ARRAYS["force"], 0.01, ARRAYS["observed"], 0, input_interpolation="linear")
    assert err.value.path == ("input_interpolation",)
    gk = JobDescription((ModelDescription("g", "gandk", {"A": (0, 1)}),), input_interpolation="linear")
    with pytest.raises(InvalidSetting, match="applies to an input record") as err:
        job_evaluator(gk, {"force": None, "observed": ARRAYS["observed"]})
    assert err.value.path == ("input_interpolation",) and "data." not in err.value.message  # the spec's names: service.spec


class EPOf:
    def __init__(self, factory):
        self.factory = factory

    def load(self):
        return self.factory


def test_fast_path_needs_an_nmse_distance_and_a_capable_simulator():
    f, obs = ARRAYS["force"], ARRAYS["observed"]
    model = Model("m", {"c": (0.1, 1.0)}, {"m": 1.0, "k": 100.0})
    calls = []

    class Capable(Linear):
        def distance_nmse(self, *args, **kwargs):
            calls.append("fast")
            return super().distance_nmse(*args, **kwargs)

    theta, rng = np.array([[0.5]]), np.random.default_rng(0)
    d_fast, _ = model_function(model, Capable(f, 0.01), NMSE(obs))(theta, rng)
    assert calls == ["fast"]
    d_generic, _ = model_function(model, Linear(f, 0.01, backend="numpy"), CallableDistance(
        obs, lambda s, o: NMSE(o)(s)))(theta, rng)
    model_function(model, Capable(f, 0.01), SummaryEuclidean(obs))(theta, rng)
    assert calls == ["fast"]  # not for another distance
    np.testing.assert_allclose(d_fast, d_generic, rtol=1e-12)
