"""What a user reads when a spec is wrong: a misspelt field is named once, with the closest
allowed name; a record one sample short is reported as that, before any window that no
longer fits it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from abcns import SpecError
from service.spec import build, load, parse

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "examples" / "authors_demo" / "spec.yaml"


@pytest.fixture
def raw():
    return yaml.safe_load(SPEC.read_text())


def test_a_misspelt_field_is_named_once_with_the_name_it_should_have(raw):
    raw["models"][1]["prior"] = raw["models"][1].pop("priors")
    with pytest.raises(SpecError) as err:
        parse(raw)
    assert str(err.value) == "models[1].prior: Extra inputs are not permitted; did you mean `priors`?"
    assert err.value.field == "models[1].prior"


@pytest.mark.parametrize(("where", "wrong", "right"), [
    (("stop",), "min_epsilon_decrase", "min_epsilon_decrease"),
    (("sampler",), "partcles", "particles"),
    (("models", 0), "integrater", "integrator"),
    ((), "seeed", "seed"),
])
def test_the_closest_allowed_name_is_offered_wherever_the_field_is(raw, where, wrong, right):
    section = raw
    for key in where:
        section = section[key]
    section[wrong] = section.pop(right, 1)
    with pytest.raises(SpecError, match=f"did you mean `{right}`") as err:
        parse(raw)
    assert err.value.field.endswith(wrong) and str(err.value).count(wrong) == 1


def test_a_name_like_no_allowed_one_gets_no_guess(raw):
    raw["sampler"]["colour"] = 3
    with pytest.raises(SpecError) as err:
        parse(raw)
    assert str(err.value) == "sampler.colour: Extra inputs are not permitted"


def test_a_record_one_sample_short_is_reported_before_the_test_window(raw, tmp_path):
    with np.load(ROOT / "data" / "authors-demo" / "demo_data.npz") as d:
        np.save(tmp_path / "force.npy", d["force"])
        np.save(tmp_path / "short.npy", d["displacement"][:-1])  # 500 samples against 501
    raw["data"].update(input="force.npy", observed="short.npy", fit=[0, 300], test=[300, 501])
    (tmp_path / "spec.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(SpecError) as err:
        build(*load(tmp_path / "spec.yaml"))
    assert err.value.field == "data.observed", str(err.value)
    assert "has 500 samples but model 'linear' simulates 501" in err.value.message
