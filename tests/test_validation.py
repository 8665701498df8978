"""Bad input: a clear error naming the field, raised before any simulation runs."""

import numpy as np
import pytest

from abcns import NMSE, Model, NSSettings, SMCSettings, SpecError, StopRules, Uniform, run
from abcns.executor import OK, Evaluated
from worker.compose import evaluator
from worker.simulators import Duffing, GAndK


class CountingEvaluate:
    def __init__(self):
        self.calls = 0

    def __call__(self, batch):
        self.calls += 1
        return Evaluated(np.zeros(len(batch)), np.full(len(batch), OK, np.int8))


def expect(field, fn, match=None):
    with pytest.raises(SpecError, match=match) as err:
        fn()
    assert err.value.field == field, str(err.value)
    return err.value


@pytest.mark.parametrize(
    ("prior", "field"),
    [((1.0, 0.0), "models[m].priors.c"), ((0.0, np.inf), "models[m].priors.c"), ((np.nan, 1.0), "models[m].priors.c"),
     ((2.0, 2.0), "models[m].priors.c"), ("x", "models[m].priors.c")],
)
def test_bad_priors(prior, field):
    expect(field, lambda: Model("m", {"c": prior}))


def test_uniform_itself_names_its_bound():
    expect("low", lambda: Uniform(3, 1))
    expect("high", lambda: Uniform(0, float("inf")))


def test_prior_on_a_fixed_parameter():
    expect("models[m].fixed.c", lambda: Model("m", {"c": (0, 1)}, {"c": 0.5}))


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"alpha": 0.0}, "sampler.alpha"), ({"alpha": 1.0}, "sampler.alpha"), ({"beta": 1.2}, "sampler.beta"),
     ({"beta": 0.0}, "sampler.beta"), ({"alpha": 0.5, "beta": 0.6}, "sampler.beta"),
     ({"particles": 1}, "sampler.particles"), ({"enlargement": 0.5}, "sampler.enlargement"),
     ({"weights": "magic"}, "sampler.weights"), ({"epsilon_initial": -1.0}, "sampler.epsilon_initial"),
     ({"batch_size": 0}, "sampler.batch_size")],
)
def test_bad_sampler_settings(kwargs, field):
    expect(field, lambda: NSSettings(**kwargs))


def test_bad_stop_rules():
    expect("stop.max_populations", lambda: StopRules(max_populations=0))
    expect("stop.epsilon_target", lambda: StopRules(epsilon_target=-1.0))
    expect("stop", lambda: StopRules(min_epsilon_decrease=None))


def test_bad_smc_schedule():
    expect("sampler.schedule", lambda: SMCSettings(schedule=(1.0, 2.0)))


def test_too_few_particles_for_the_dimension_before_any_simulation():
    models = [Model(f"m{i}", {f"p{j}": (0, 1) for j in range(5)}) for i in range(2)]
    ev = CountingEvaluate()
    err = expect("sampler.particles", lambda: run(models, ev, NSSettings(particles=12, epsilon_initial=1.0), seed=0))
    assert "needs at least 6" in err.message
    assert ev.calls == 0


def test_duplicate_model_names():
    m = Model("same", {"c": (0, 1)})
    expect("models[1].name", lambda: run([m, m], CountingEvaluate(), NSSettings(particles=100), seed=0))


def test_observed_with_nan():
    obs = np.ones(10)
    obs[3] = np.nan
    expect("data.observed", lambda: NMSE(obs), match="index 3")


def test_bad_window():
    expect("data.fit", lambda: NMSE(np.arange(10.0), window=(5, 20)))
    expect("data.fit", lambda: NMSE(np.arange(10.0), window=(5, 5)))


def test_mismatched_input_and_observed_lengths():
    force = np.ones(100)
    models = [Model("m", {"c": (0, 1), "k": (1, 2)}, {"m": 1, "k3": 0, "k5": 0})]
    expect("data.observed", lambda: evaluator(models, [Duffing(force, 0.01)], NMSE(np.arange(90.0))))


def test_unknown_and_missing_simulator_parameters():
    force = np.ones(50)
    obs = np.arange(50.0)
    expect("models[0].priors.q", lambda: evaluator([Model("m", {"q": (0, 1)})], [Duffing(force, 0.01)], NMSE(obs)))
    expect("models[0].priors", lambda: evaluator([Model("m", {"c": (0, 1)})], [Duffing(force, 0.01)], NMSE(obs)),
           match="need a prior or a fixed value")


def test_bad_simulator_data():
    expect("data.input", lambda: Duffing(np.array([1.0, np.nan, 2.0]), 0.01))
    expect("data.dt", lambda: Duffing(np.ones(5), 0.0))
    expect("integrator.substeps", lambda: Duffing(np.ones(5), 0.01, substeps=0))
    expect("data.observed", lambda: GAndK(1))
