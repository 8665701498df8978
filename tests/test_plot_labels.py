"""The figures' axes say what they show, with units: the tolerance and the distance in %
for the NMSE (and no unit for a summary distance), the predictive response by name; each
model has the colour it has on the live page."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from matplotlib.colors import to_hex

from abcns import Model, Population, Result, StopReason
from service.report.colours import model_colour
from service.report.plots import model_probability_figure, pairs_figure, response_label, tolerance_figure
from service.spec import ModelSpec


def two_model_result(n: int = 200, seed: int = 0) -> Result:
    rng = np.random.default_rng(seed)
    models = (Model("linear", {"c": (0.0, 1.0), "k": (0.0, 100.0)}), Model("cubic", {"c": (0.0, 1.0), "k": (0.0, 100.0)}))
    which = np.repeat([0, 1], n // 2)
    pops = tuple(Population(t=t, epsilon=10.0 / t, epsilon_next=10.0 / (t + 1), models=which,
                            theta=np.column_stack([rng.uniform(0, 1, n), rng.uniform(0, 100, n)]),
                            distances=rng.uniform(0, 10.0 / t, n), weights=np.full(n, 1.0 / n), n_accepted=n,
                            n_simulations=2 * n, n_failed=0, n_redraws=0, elapsed_s=float(t),
                            model_probabilities=np.array([0.5, 0.5])) for t in (1, 2, 3))
    return Result("abc-ns", models, pops, StopReason.MAX_POPULATIONS, 0, {}, "given", 6 * n, 0, 3.0)


@pytest.mark.parametrize(("unit", "label"), [("%", "tolerance $\\varepsilon_t$ (%)"), ("", "tolerance $\\varepsilon_t$")])
def test_the_tolerance_and_the_distance_carry_their_unit(unit, label):
    result = two_model_result()
    assert tolerance_figure(result, unit).axes[0].get_ylabel() == label
    colorbar = pairs_figure(result, 1, unit=unit).axes[-1]
    assert colorbar.get_ylabel() == ("distance (%)" if unit else "distance")


def test_each_model_has_its_page_colour():
    fig = model_probability_figure(two_model_result())
    bars = fig.axes[0].containers
    assert [to_hex(c.patches[0].get_facecolor()) for c in bars] == [model_colour(0), model_colour(1)]


def test_the_response_is_named():
    spec = SimpleNamespace(models=[ModelSpec(name="m", simulator="duffing", priors={"k": (1, 2)},
                                             integrator={"output": "velocity"})])
    assert response_label(SimpleNamespace(force=np.zeros(3), spec=spec), "m") == "velocity (unit of data.observed)"
    assert response_label(SimpleNamespace(force=None, spec=spec), "m") == "observed value"


def test_the_probabilities_against_the_tolerance_mark_the_floor_and_the_decision():
    """Issue T: the model-probability figure draws p_m(eps) against the tolerance, with
    vertical lines at the noise floor (2.8) and the decision tolerance (3.2) named in the
    legend, and marks the decision population (3) among the populations."""
    from toy_results import floored_result

    fig = model_probability_figure(floored_result(), "%")
    bars, curve = fig.axes
    assert curve.get_xscale() == "log" and curve.get_xlabel() == "tolerance $\\varepsilon$ (%)"
    lines = {line.get_label(): line for line in curve.get_lines()}
    assert [to_hex(lines[m].get_color()) for m in ("linear", "cubic")] == [model_colour(0), model_colour(1)]
    assert list(lines["linear"].get_xdata()) == pytest.approx([10, 5, 10 / 3, 2.5, 2])
    assert list(lines["linear"].get_ydata()) == pytest.approx([0.9, 0.9, 0.9, 0.1, 0.1])
    floor, decision = lines["noise floor 2.8 % (estimated)"], lines["decision tolerance 3.2 %"]
    assert list(floor.get_xdata()) == pytest.approx([2.8, 2.8]) and list(decision.get_xdata()) == pytest.approx([3.2, 3.2])
    assert [t.get_text() for t in curve.get_legend().get_texts()] == [
        "linear", "cubic", "noise floor 2.8 % (estimated)", "decision tolerance 3.2 %"]
    labels = [t.get_text() for t in bars.get_legend().get_texts()]
    assert labels == ["decision: population 3", "linear (answer 0.90, final 0.10)", "cubic (answer 0.10, final 0.90)"]
    assert [list(line.get_xdata()) for line in bars.get_lines()] == [[3, 3]]


def test_without_a_floor_the_figure_draws_no_floor_lines():
    from toy_results import floored_result

    _, curve = model_probability_figure(floored_result(floor=None)).axes
    assert [line.get_label() for line in curve.get_lines()] == ["linear", "cubic"]
