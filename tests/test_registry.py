"""The simulator registry: built-ins, plugins by entry point, local module:factory (CLI only),
and substeps chosen from the priors."""

import math

import numpy as np
import pytest

from abcns import SpecError
from worker import registry
from worker.evaluate import job_evaluator
from worker.kernels import choose_substeps
from worker.simulators import Duffing


def description(simulator="duffing", integrator=None, priors=None):
    return {
        "models": [{"name": "m", "simulator": simulator, "fixed": {"m": 1, "k3": 0, "k5": 0},
                    "priors": priors or {"c": [0.1, 1.0], "k": [100.0, 10000.0]}, "integrator": integrator or {}}],
        "distance": {"name": "nmse"},
        "data": {"dt": 0.01, "fit": None},
    }


ARRAYS = {"force": np.sin(np.arange(200) * 0.1), "observed": np.cos(np.arange(200) * 0.1)}


def test_substeps_are_chosen_from_the_priors():
    models, evaluate = job_evaluator(description(), ARRAYS)
    omega = Duffing.omega_max({"m": (1, 1), "c": (0.1, 1.0), "k": (100, 1e4), "k3": (0, 0), "k5": (0, 0)})
    assert omega == pytest.approx(0.5 + math.sqrt(0.25 + 1e4))
    expected = choose_substeps(omega, 0.01)
    assert expected == math.ceil(0.01 * omega / (120 * 1e-4) ** 0.25)
    given = job_evaluator(description(integrator={"substeps": 3}), ARRAYS)
    assert given is not None


def test_module_factory_only_when_imports_are_allowed():
    with pytest.raises(SpecError, match="only registered simulators") as err:
        job_evaluator(description("worker.simulators:Duffing"), ARRAYS)
    assert err.value.field == "models[0].simulator"
    models, _ = job_evaluator(description("worker.simulators:Duffing"), ARRAYS, allow_import=True)
    assert models[0].name == "m"
    with pytest.raises(SpecError, match="cannot load"):
        job_evaluator(description("no_such_module:f"), ARRAYS, allow_import=True)


def test_entry_point_plugins_are_found(monkeypatch):
    class EP:
        name = "mine"

        def load(self):
            return Duffing

    monkeypatch.setattr(registry, "plugins", lambda: {"mine": EP()})
    assert "mine" in registry.names()
    assert registry.get("mine") is Duffing
