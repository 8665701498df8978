"""Bad input: a clear error naming the field, raised before any simulation runs. The core
(abcns, worker) names it in its own terms (InvalidSetting's path: the argument or the
field it was given); service.spec maps those to the spec's fields (tests/test_spec*.py)."""

import numpy as np
import pytest

from abcns import NMSE, InvalidSetting, Model, NSSettings, SMCSettings, SpecError, StopRules, Uniform, run
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
    with pytest.raises(InvalidSetting, match=match) as err:
        fn()
    assert not isinstance(err.value, SpecError)  # the core's terms: a SpecError is the spec's
    assert err.value.field == field, str(err.value)
    return err.value


@pytest.mark.parametrize(
    ("prior", "field"),
    [((1.0, 0.0), "priors.c"), ((0.0, np.inf), "priors.c"), ((np.nan, 1.0), "priors.c"),
     ((2.0, 2.0), "priors.c"), ("x", "priors.c"), ((0.0, 1.0, "log"), "priors.c"), ((-1.0, 1.0, "log"), "priors.c"),
     ((0.1, 1.0, "ln"), "priors.c"), ((0.1, 1.0, "log", 1), "priors.c")],
)
def test_bad_priors(prior, field):
    expect(field, lambda: Model("m", {"c": prior}))


def test_uniform_itself_names_its_bound():
    expect("low", lambda: Uniform(3, 1))
    expect("high", lambda: Uniform(0, float("inf")))


@pytest.mark.parametrize(
    ("other", "match"),
    [(Model("b", {"c": (0, 1)}, same_model_as="x"), "names no model of the run"),
     (Model("b", {"k": (0, 1)}, same_model_as="a"), "differ in parameter names"),
     (Model("b", {"c": (0, 1)}, {"k": 1.0}, same_model_as="a"), "differ in fixed"),
     (Model("b", {"c": (0, 1)}, config={"simulator": "other"}, same_model_as="a"), "differ in config")],
)
def test_a_model_the_same_as_another_differs_from_it_in_its_priors_alone(other, match):
    from abcns.run import check_models

    expect("models[1].same_model_as", lambda: check_models([Model("a", {"c": (1, 2, "log")}), other]), match)


def test_same_model_as_names_the_first_of_its_copies_not_itself():
    from abcns.run import check_models

    a, b = Model("a", {"c": (0, 1)}), Model("b", {"c": (0, 2)}, same_model_as="a")
    expect("models[2].same_model_as", lambda: check_models([a, b, Model("c", {"c": (0, 3)}, same_model_as="b")]),
           "itself the same model as 'a'")
    expect("same_model_as", lambda: Model("a", {"c": (0, 1)}, same_model_as="a"))
    assert len(check_models([a, b, Model("c", {"c": (0, 3)}, same_model_as="a")])) == 3


def test_prior_on_a_fixed_parameter():
    expect("fixed.c", lambda: Model("m", {"c": (0, 1)}, {"c": 0.5}))


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"alpha": 0.0}, "settings.alpha"), ({"alpha": 1.0}, "settings.alpha"), ({"beta": 1.2}, "settings.beta"),
     ({"beta": 0.0}, "settings.beta"), ({"alpha": 0.5, "beta": 0.6}, "settings.beta"),
     ({"particles": 1}, "settings.particles"), ({"enlargement": 0.5}, "settings.enlargement"),
     ({"weights": "magic"}, "settings.weights"), ({"epsilon_initial": -1.0}, "settings.epsilon_initial"),
     ({"batch_size": 0}, "settings.batch_size")],
)
def test_bad_sampler_settings(kwargs, field):
    expect(field, lambda: NSSettings(**kwargs))


def test_bad_stop_rules():
    expect("stop.max_populations", lambda: StopRules(max_populations=0))
    expect("stop.epsilon_target", lambda: StopRules(epsilon_target=-1.0))
    expect("stop", lambda: StopRules(min_epsilon_decrease=None))


def test_bad_smc_schedule():
    expect("settings.schedule", lambda: SMCSettings(schedule=(1.0, 2.0)))


def test_too_few_particles_for_the_dimension_before_any_simulation():
    models = [Model(f"m{i}", {f"p{j}": (0, 1) for j in range(5)}) for i in range(2)]
    ev = CountingEvaluate()
    err = expect("settings.particles", lambda: run(models, ev, NSSettings(particles=12, epsilon_initial=1.0), seed=0))
    assert "needs at least 6" in err.message
    assert ev.calls == 0


def test_duplicate_model_names():
    m = Model("same", {"c": (0, 1)})
    expect("models[1].name", lambda: run([m, m], CountingEvaluate(), NSSettings(particles=100), seed=0))


def test_observed_with_nan():
    obs = np.ones(10)
    obs[3] = np.nan
    expect("observed", lambda: NMSE(obs), match="index 3")


def test_bad_window():
    expect("fit", lambda: NMSE(np.arange(10.0), window=(5, 20)))
    expect("fit", lambda: NMSE(np.arange(10.0), window=(5, 5)))


def test_mismatched_input_and_observed_lengths():
    force = np.ones(100)
    models = [Model("m", {"c": (0, 1), "k": (1, 2)}, {"m": 1, "k3": 0, "k5": 0})]
    expect("observed", lambda: evaluator(models, [Duffing(force, 0.01)], NMSE(np.arange(90.0))))


def test_unknown_and_missing_simulator_parameters():
    force = np.ones(50)
    obs = np.arange(50.0)
    expect("models[0].priors.q", lambda: evaluator([Model("m", {"q": (0, 1)})], [Duffing(force, 0.01)], NMSE(obs)))
    expect("models[0].priors", lambda: evaluator([Model("m", {"c": (0, 1)})], [Duffing(force, 0.01)], NMSE(obs)),
           match="need a prior or a fixed value")


def test_bad_simulator_data():
    expect("force", lambda: Duffing(np.array([1.0, np.nan, 2.0]), 0.01))
    expect("dt", lambda: Duffing(np.ones(5), 0.0))
    expect("substeps", lambda: Duffing(np.ones(5), 0.01, substeps=0))
    expect("observed", lambda: GAndK(1))


def test_a_log_uniform_prior_and_same_model_as_survive_the_stored_form():
    """What a store keeps of a model (config_dict, read back by from_dict on resume) holds
    the log-uniform priors and same_model_as; a model without them keeps its former form."""
    model = Model("b", {"c": (0.01, 1, "log"), "k": (0, 2)}, {"m": 1.0}, config={"simulator": "duffing"},
                  same_model_as="a")
    assert model.config_dict()["priors"] == {"c": [0.01, 1.0, "log"], "k": [0.0, 2.0]}
    assert Model.from_dict(model.config_dict()) == model
    assert Model.from_dict({"name": "b", "simulator": "duffing", "priors": {"c": [0.01, 1, "log"]},
                            "same_model_as": "a"}).same_model_as == "a"
    assert "same_model_as" not in Model("a", {"c": (0, 1)}).config_dict()
