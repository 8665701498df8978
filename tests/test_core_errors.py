"""Issue X, item 3: one typed job description from the spec to the worker, and the core's
errors in its own terms (``abcns.InvalidSetting``: a path of the argument or field it was
given) mapped to the spec's fields in one place (``service.spec.spec_path``)."""

from __future__ import annotations

import copy
import dataclasses
import json
import pickle
from pathlib import Path
from typing import Any, get_args, get_origin

import numpy as np
import pytest
import yaml
from pydantic import BaseModel

from abcns import InvalidSetting, SpecError
from abcns.errors import dotted
from benchmarks.harness import duffing_spec
from service.run.jobs import pilot_batch
from service.spec import SPEC_NAMES, JobSpec, build, description, job_arrays, parse, spec_path, spec_text
from worker.compose import evaluator
from worker.description import JobDescription, ModelDescription, job_parts

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def base() -> dict:
    return duffing_spec(max_populations=1, particles=200)


def in_schema(path: tuple) -> bool:
    """Whether ``path`` names a field of the job spec's schema (a list position for models)."""
    kind: Any = JobSpec
    for part in path:
        if isinstance(part, int):  # models: list[ModelSpec]
            kind = get_args(kind)[0]
            continue
        if get_origin(kind) is dict:  # priors, fixed: any parameter's name
            return True
        options = [a for a in (get_args(kind) or (kind,)) if isinstance(a, type) and issubclass(a, BaseModel)]
        hits = [a for a in options if part in a.model_fields]  # the sampler: a union of one model per algorithm
        if not hits:
            return False
        kind = hits[0].model_fields[part].annotation
    return True


def test_every_core_name_maps_to_a_field_of_the_spec():
    """The description's fields, the records' names and the renamed ones all land on a field
    the spec has; a name the mapping misses would send the user to a field that is not there."""
    job_names = [f.name for f in dataclasses.fields(JobDescription) if f.name != "models"]
    model_names = [f.name for f in dataclasses.fields(ModelDescription)]
    paths = [(name,) for name in [*job_names, *SPEC_NAMES, "seed"] if SPEC_NAMES.get(name, ())[:1] != ("integrator",)]
    paths += [("models", 1, name) for name in model_names] + [("models", 0, "priors", "k"), ("models", 2, "fixed", "m")]
    paths += [("settings", "particles"), ("settings", "alpha"), ("stop", "max_populations"), ("stop",), ("models",)]
    for path in paths:
        assert in_schema(spec_path(path)), (path, spec_path(path))


@pytest.mark.parametrize(("path", "field"), [
    (("force",), "data.input"), (("observed",), "data.observed"), (("voltage",), "data.voltage"),
    (("fit",), "data.fit"), (("test",), "data.test"), (("noise_std",), "data.noise_std"),
    (("input_interpolation",), "data.input_interpolation"), (("distance",), "distance.name"),
    (("summaries",), "distance.summaries"), (("settings", "particles"), "sampler.particles"), (("settings",), "sampler"),
    (("stop", "max_populations"), "stop.max_populations"), (("seed",), "seed"), (("models",), "models"),
    (("models", 1, "name"), "models[1].name"), (("models", 0, "substeps"), "models[0].integrator.substeps"),
    (("models", 2, "output"), "models[2].integrator.output"), (("models", 0, "priors", "k"), "models[0].priors.k"),
    (("models", 1, "fixed", "n"), "models[1].fixed.n"), (("models", 0, "simulator"), "models[0].simulator"),
])
def test_a_core_path_is_the_spec_field_it_came_from(path, field):
    assert dotted(spec_path(path)) == field


@pytest.mark.parametrize(("change", "field", "core", "words"), [
    # each raised by the core (abcns, worker) in its own terms, named by the spec's field
    (lambda s: s["models"][0]["priors"].update(q=[0, 1]), "models[0].priors.q", ("models", 0, "priors", "q"),
     "is not a parameter of duffing"),
    (lambda s: s["models"][1].update(simulator="nope"), "models[1].simulator", ("models", 1, "simulator"),
     "unknown simulator 'nope'"),
    (lambda s: s["models"][1]["integrator"].update(substeps=10**30), "models[1].integrator.substeps",
     ("models", 1, "substeps"), "at most 1e+09 RK4 substeps"),
    (lambda s: s["data"].update(fit=[0, 10**6]), "data.fit", ("fit",), "must satisfy 0 <= start < stop"),
    (lambda s: s["data"].update(test=[0, 10**6]), "data.test", ("test",), "must satisfy 0 <= start < stop"),
    (lambda s: s["data"].update(observed=s["data"]["observed"][:-1]), "data.observed", ("observed",),
     "input and observed records must have the same length"),
    (lambda s: s["data"].update(noise_std=1e200), "data.noise_std", ("noise_std",), "too large for this record"),
    (lambda s: s["sampler"].update(alpha=0.5, beta=0.6), "sampler.beta", ("settings", "beta"),
     "must not exceed 1 - alpha"),
    (lambda s: s["models"][1].update(name=s["models"][0]["name"]), "models[1].name", ("models", 1, "name"),
     "duplicate model name"),
])
def test_the_core_errors_reach_the_user_as_the_spec_field(base, change, field, core, words):
    """Through ``build``: a SpecError naming the spec's field, the message the core's."""
    raw = copy.deepcopy(base)
    change(raw)
    with pytest.raises(SpecError) as err:
        build(parse(raw))
    assert err.value.field == field and words in err.value.message, str(err.value)
    assert str(err.value) == f"{field}: {err.value.message}"
    assert dotted(spec_path(core)) == field  # the core's path, mapped


def plain(value: Any) -> bool:
    """Plain data only: no arrays, callables or objects of the service's."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return all(plain(getattr(value, f.name)) for f in dataclasses.fields(value))
    if isinstance(value, (tuple, list)):
        return all(plain(v) for v in value)
    if isinstance(value, dict):
        return all(isinstance(k, str) and plain(v) for k, v in value.items())
    return value is None or type(value) in (str, int, float, bool)


def test_the_worker_gets_a_typed_description_and_builds_the_same_evaluator(base):
    """What goes to the cluster is plain typed data (no code over the wire), the one the
    spec's job was built from; a worker's rebuild from it (pickled, as Dask sends it)
    computes the job's own distances, bit for bit."""
    raw = copy.deepcopy(base)
    raw["models"][0]["integrator"] = {"substeps": 3}
    job = build(parse(raw))
    assert isinstance(job.description, JobDescription) and job.description == description(job.spec)
    assert plain(job.description)
    sent = pickle.loads(pickle.dumps(job.description))  # noqa: S301 (its own bytes)
    assert sent == job.description and sent.models[0].substeps == 3 and sent.fit == tuple(raw["data"]["fit"])
    models, simulators, distance = job_parts(sent, job_arrays(job))
    assert [m.config_dict() for m in models] == [m.config_dict() for m in job.models]
    batch = pilot_batch(job, 16, np.random.default_rng(7))  # any points of the priors: the same distances
    ours, theirs = job.evaluate(batch), evaluator(models, simulators, distance)(batch)
    np.testing.assert_array_equal(theirs.distances, ours.distances)
    np.testing.assert_array_equal(theirs.status, ours.status)


def test_an_error_crosses_the_wire_with_its_path():
    """A worker's error reaches the client as it was raised (Dask pickles it): the core's
    with its path, the spec's with its field."""
    core = InvalidSetting(("models", 0, "substeps"), "must be a positive integer")
    back = pickle.loads(pickle.dumps(core))  # noqa: S301 (its own bytes)
    assert type(back) is InvalidSetting and back.path == core.path and str(back) == str(core)
    assert str(back) == "models[0].substeps: must be a positive integer"
    spec = pickle.loads(pickle.dumps(SpecError("data.input", "needs an input force")))  # noqa: S301 (its own bytes)
    assert type(spec) is SpecError and spec.field == "data.input" and str(spec) == "data.input: needs an input force"


def test_the_spec_means_the_same_after_it_crossed():
    """A spec that names ``stop.min_epsilon_decrease`` alone ends as the user's rule says
    (``decrease_above_floor``: stop_rules reads which rules were named). Read back from a
    full JSON dump it meant the other rule: the job loop on a worker (``abcns run
    --out-dir``) and an HTTP job (its spec.json, ``abcns submit``'s upload) ran with
    ``decrease_above_floor`` false while ``abcns run`` ran with true. The typed spec (what
    run_one now gets) and ``spec_text`` (spec.json, the upload) keep its meaning and its job key."""
    from service.run.runner import job_key
    from service.spec import stop_rules

    raw = yaml.safe_load((ROOT / "examples" / "authors_demo" / "spec.yaml").read_text())
    assert set(raw["stop"]) == {"min_epsilon_decrease"}
    spec = parse(raw)
    assert stop_rules(spec.stop).decrease_above_floor
    sent = pickle.loads(pickle.dumps(spec))  # noqa: S301 (its own bytes): run_one's argument, as Dask sends it
    stored = JobSpec.model_validate(json.loads(json.dumps(spec_text(spec))))  # spec.json, read back
    for crossed in (sent, stored):
        assert stop_rules(crossed.stop) == stop_rules(spec.stop)
        assert job_key(crossed, crossed.seed, "data") == job_key(spec, spec.seed, "data")
