"""The job spec (docs/design.md, "The job spec"): one pydantic schema for Python, the CLI and HTTP.

``load(path)`` reads YAML or JSON; ``build(spec, base_dir)`` validates everything that can
be checked before a simulation (files, windows, lengths, simulator parameters, sampler
settings) and returns a :class:`Job` ready for ``abcns.run``, with the typed description a
worker builds it from (:func:`description`). Every error is an ``abcns.SpecError`` whose
``field`` names the place in the spec (``models[1].priors.k``): the core's errors
(``abcns.InvalidSetting``, a path in its own terms) are mapped to the spec's fields here,
in one place (:func:`spec_path`, :func:`spec_errors`).
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, get_args, get_type_hints

import numpy as np
import yaml
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    create_model,
    field_validator,
    model_validator,
)
from pydantic_core import InitErrorDetails, PydanticCustomError

from abcns import InvalidSetting, Model, NSSettings, RejectionSettings, SMCSettings, SpecError, StopRules
from abcns.distances import NMSE, check_window
from abcns.errors import dotted
from abcns.executor import Evaluate
from abcns.noise import Noise
from abcns.run import check_models
from worker.compose import evaluator
from worker.description import JobDescription, ModelDescription, job_parts, parameter_bounds
from worker.simulators import Simulator

Window = tuple[int, int]


def _prior_pair(value: Any) -> Any:
    """A prior is ``[low, high]`` (uniform) or ``[low, high, "log"]`` (log-uniform): a wrong
    shape is reported at the prior's own name (``models[0].priors.k``), not at a missing tuple
    element (``...priors.k[1]``)."""
    if not isinstance(value, (list, tuple)) or len(value) not in (2, 3):
        raise ValueError(f'a prior is [low, high] or [low, high, "log"], got {value!r}'[:200])
    if len(value) == 3 and value[2] != "log":
        raise ValueError(f'the third entry of a prior is "log" (log-uniform), got {value[2]!r}'[:200])
    return tuple(value)


Prior = Annotated[tuple[float, float] | tuple[float, float, Literal["log"]], BeforeValidator(_prior_pair)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _normal(x: float) -> bool:
    """A finite float that is not subnormal (an interval below ~2.2e-308 loses its digits)."""
    return math.isfinite(x) and abs(x) >= sys.float_info.min


class DataSpec(_Strict):
    dt: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    fs: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    input: str | list[float] | None = None
    # a second input channel, for the simulators that read it (spencer_mr_voltage: the coil's
    # commanded voltage, one sample per input sample); loaded, decimated and checked as input
    voltage: str | list[float] | None = None
    observed: str | list[float]
    fit: Window | None = None
    test: Window | None = None
    decimate: Annotated[int, Field(ge=1, le=1000)] = 1  # keep every q-th sample, anti-aliased; windows count kept samples
    # the measurement noise's standard deviation in the observed record's units (after decimation),
    # when known: it sets the noise floor (abcns.noise) instead of the estimate from the best fit
    noise_std: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    # the input between samples: held (zero-order hold, as the paper's data were made),
    # linearly interpolated (first-order hold) or band-limited (the signal through the samples,
    # for a measured continuous input; Duffing and Bouc-Wen); docs/design.md, "A continuous input"
    input_interpolation: Literal["hold", "linear", "bandlimited"] = "hold"

    @model_validator(mode="after")
    def _one_rate(self) -> DataSpec:
        if (self.dt is None) == (self.fs is None) and self.input is not None:
            raise ValueError("give exactly one of dt and fs")
        if self.dt is not None or self.fs is not None:
            # a sampling rate of physical sense: its sample interval, decimated, is a normal positive float
            rate = "dt" if self.dt is not None else "fs"
            base = self.dt if self.dt is not None else 1.0 / self.fs  # type: ignore[operator]  # fs: set without dt
            if not (_normal(base) and _normal(self.sample_interval)):
                what = "dt" if rate == "dt" else "1/fs"
                note = f" x decimate ({self.decimate})" if self.decimate > 1 and _normal(base) else ""
                message = (f"the sample interval {what}{note} is {base * self.decimate:.3g} s: it must be a finite "
                           "positive number of at least 2.2e-308")
                raise ValidationError.from_exception_data("data", [{
                    "type": PydanticCustomError("sample_interval", message), "loc": (rate,), "input": getattr(self, rate)}])
        return self


    @property
    def sample_interval(self) -> float:
        """The interval between the samples used (after decimation)."""
        base = self.dt if self.dt is not None else 1.0 / self.fs  # type: ignore[operator]  # fs: set without dt
        return base * self.decimate


class IntegratorSpec(_Strict):
    substeps: Annotated[int, Field(ge=1)] | None = None  # None: chosen from the priors
    output: Literal["displacement", "velocity", "acceleration"] = "displacement"


class ModelSpec(_Strict):
    name: str = Field(min_length=1)
    simulator: str
    fixed: dict[str, float] = {}
    priors: dict[str, Prior]
    integrator: IntegratorSpec = IntegratorSpec()
    same_model_as: str | None = None


class DistanceSpec(_Strict):
    name: Literal["nmse", "summary_euclidean"] = "nmse"
    summaries: Literal["gk", "order_statistics"] | None = None  # summary_euclidean only (default gk)


def _spec_fields(settings: type) -> dict[str, Any]:
    """The fields of an abcns settings dataclass as pydantic fields: the dataclass's own
    types (Literal choices included) and defaults, so each setting is defined once, in
    ``abcns/settings.py``. Ranges stay in the dataclass's ``__post_init__`` (``build``)."""
    hints = get_type_hints(settings)
    out: dict[str, Any] = {}
    for f in dataclasses.fields(settings):
        if f.metadata.get("spec", True):
            assert f.default is not dataclasses.MISSING, f"{settings.__name__}.{f.name} needs a default"
            out[f.name] = (hints[f.name], f.default)
    return out


def _admits_none(annotation: Any) -> bool:
    return type(None) in get_args(annotation)


class _Sampler(_Strict):
    """One algorithm's sampler section: ``algorithm`` and the fields of its settings
    dataclass (generated by :func:`_sampler`). A null is the field's default (so are nulls
    of fields another algorithm reads, which specs stored by earlier versions hold); a
    value for a field another algorithm reads is an error naming the field."""

    if TYPE_CHECKING:  # for mypy only: each generated sampler's own field (a Literal of its name)
        algorithm: str

    @model_validator(mode="before")
    @classmethod
    def _nulls_and_other_algorithms(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        out: dict[str, Any] = {}
        errors: list[InitErrorDetails] = []
        for name, value in data.items():
            if name in cls.model_fields:
                if value is not None or _admits_none(cls.model_fields[name].annotation):
                    out[name] = value
            elif name in _READ_BY:
                if value is not None:
                    (algorithm,) = get_args(cls.model_fields["algorithm"].annotation)  # Literal["abc-smc"]
                    message = f"does not apply to algorithm {algorithm!r} (it is read by {', '.join(_READ_BY[name])})"
                    errors.append({"type": PydanticCustomError("not_applicable", message), "loc": (name,),
                                   "input": value})
            else:
                out[name] = value  # unknown: extra="forbid" refuses it
        if errors:
            raise ValidationError.from_exception_data(cls.__name__, errors)
        return out

    def settings(self) -> NSSettings | SMCSettings | RejectionSettings:
        """The abcns settings of this section (range checks: SpecError naming the field)."""
        values = {name: getattr(self, name) for name in type(self).model_fields if name != "algorithm"}
        return _SETTINGS[self.algorithm](**values)


def _sampler(algorithm: str, settings: type) -> type[_Sampler]:
    default = algorithm if algorithm == DEFAULT_ALGORITHM else ...  # the default need not name itself
    field: tuple[Any, Any] = (Literal[algorithm], default)  # a Literal made at run time: no static type
    return create_model(
        settings.__name__.removesuffix("Settings") + "Sampler", __base__=_Sampler,
        __doc__=f"algorithm {algorithm!r}: the fields of abcns.{settings.__name__}",
        algorithm=field, **_spec_fields(settings))


DEFAULT_ALGORITHM = "abc-ns"
_SETTINGS: dict[str, type[NSSettings] | type[SMCSettings] | type[RejectionSettings]] = {
    "abc-ns": NSSettings, "abc-smc": SMCSettings, "rejection": RejectionSettings}
if TYPE_CHECKING:
    # mypy cannot see into the models create_model makes: what it checks of each is its base
    # and its ``algorithm`` (these classes never exist at run time; the settings' fields are
    # read through settings())
    class NSSampler(_Sampler):
        algorithm: Literal["abc-ns"] = "abc-ns"

    class SMCSampler(_Sampler):
        algorithm: Literal["abc-smc"]

    class RejectionSampler(_Sampler):
        algorithm: Literal["rejection"]
else:
    NSSampler, SMCSampler, RejectionSampler = (_sampler(a, s) for a, s in _SETTINGS.items())
# which algorithms read each field (the message of an inapplicable one)
_READ_BY = {name: [a for a, s in _SETTINGS.items() if name in _spec_fields(s)]
            for s in _SETTINGS.values() for name in _spec_fields(s)}


def _algorithm(value: Any) -> Any:
    """``algorithm`` left out is abc-ns; an unknown one is an error at ``sampler.algorithm``
    (not at ``sampler``, where the discriminated union would put it)."""
    if not isinstance(value, dict):
        return value
    algorithm = value.get("algorithm", DEFAULT_ALGORITHM)
    if not isinstance(algorithm, str) or algorithm not in _SETTINGS:
        *first, last = (repr(a) for a in _SETTINGS)
        expected = f"{', '.join(first)} or {last}"
        raise ValidationError.from_exception_data("sampler", [
            {"type": "literal_error", "loc": ("algorithm",), "input": algorithm, "ctx": {"expected": expected}}])
    return {**value, "algorithm": algorithm}


# the sampler section: one model per algorithm, chosen by ``algorithm``
SamplerSpec = Annotated[NSSampler | SMCSampler | RejectionSampler,
                        Field(discriminator="algorithm"), BeforeValidator(_algorithm)]
if TYPE_CHECKING:
    # what mypy checks of the model create_model makes: a pydantic model with the fields of
    # StopRules (frozen only because a frozen dataclass's subclass must be, for mypy)
    class StopSpec(BaseModel, StopRules, frozen=True): ...
else:
    StopSpec = create_model("StopSpec", __base__=_Strict, __doc__="the fields of abcns.StopRules",
                            **_spec_fields(StopRules))


class JobSpec(_Strict):
    name: str = "job"
    data: DataSpec
    models: list[ModelSpec] = Field(min_length=1)
    distance: DistanceSpec = DistanceSpec()
    sampler: SamplerSpec = NSSampler()
    stop: StopSpec = StopSpec()
    seed: Annotated[int, Field(ge=0, le=2**63 - 1)] = 0

    @field_validator("distance", mode="before")
    @classmethod
    def _distance_shorthand(cls, v: Any) -> Any:
        return {"name": v} if isinstance(v, str) else v


@dataclass
class Job:
    spec: JobSpec
    models: list[Model]
    evaluate: Evaluate
    settings: NSSettings | SMCSettings | RejectionSettings
    stop: StopRules
    seed: int
    force: np.ndarray | None
    observed: np.ndarray
    simulators: list[Simulator]  # the ones ``evaluate`` runs (their substeps as chosen)
    description: JobDescription  # what a worker builds ``evaluate`` from (with the records)
    noise: Noise | None = None  # the distance's noise model (abcns.noise): the NMSE's; None for the others
    voltage: np.ndarray | None = None  # the second input channel (data.voltage), as the job uses it


def spec_loc(loc: tuple) -> tuple:
    """A pydantic error location in the spec without the algorithm pydantic puts after
    ``sampler`` (``("sampler", "abc-smc", "alpha")`` is ``sampler.alpha``)."""
    loc = tuple(loc)
    return loc[:1] + loc[2:] if len(loc) > 1 and loc[0] == "sampler" and loc[1] in _SETTINGS else loc


def _field(loc: tuple) -> str:
    """A pydantic error location as the spec's field name (``models[1].priors.k``)."""
    return dotted(spec_loc(loc))


#: the core's names (abcns, worker: the job description's fields and the simulators'
#: keywords) where the spec names the field otherwise; a model's own (behind ``("models",
#: i)``) and the job's (at the top) alike
SPEC_NAMES: dict[str, tuple[str, ...]] = {
    "force": ("data", "input"), "observed": ("data", "observed"), "voltage": ("data", "voltage"),
    "dt": ("data", "dt"), "fit": ("data", "fit"), "test": ("data", "test"), "noise_std": ("data", "noise_std"),
    "input_interpolation": ("data", "input_interpolation"), "distance": ("distance", "name"),
    "summaries": ("distance", "summaries"), "settings": ("sampler",), "substeps": ("integrator", "substeps"),
    "output": ("integrator", "output"), "backend": ("integrator", "backend")}


def spec_path(path: tuple) -> tuple:
    """The spec's path of a core error's ``path`` (``("models", 0, "substeps")`` is
    ``models[0].integrator.substeps``, ``("force",)`` is ``data.input``)."""
    at = 2 if path[:1] == ("models",) and len(path) > 2 else 0
    return (*path[:at], *SPEC_NAMES.get(path[at], path[at:at + 1]), *path[at + 1:]) if len(path) > at else path


@contextmanager
def spec_errors() -> Iterator[None]:
    """The core's errors raised within, as SpecErrors naming the spec's field (:func:`spec_path`)."""
    try:
        yield
    except SpecError:
        raise
    except InvalidSetting as err:
        raise SpecError(dotted(spec_path(err.path)), err.message) from None


#: fields a spec may no longer name, and why (said after "Extra inputs are not permitted")
REMOVED = {("sampler", "carry_over"): "removed (issue X): carry-over measured no gain in the useful rate and was off "
           "by default; delete the field"}


def _closest(name: str, allowed: list[str]) -> str | None:
    """The allowed field name closest to a misspelt one: difflib's at 0.6, or, for a name of
    one or two letters (``fz``), one of as many letters that differs in one of them."""
    close = difflib.get_close_matches(name, allowed, n=1, cutoff=0.6)
    if close:
        return close[0]
    near = [a for a in allowed if len(name) <= 2 and len(a) == len(name)
            and sum(x != y for x, y in zip(a, name, strict=True)) == 1]
    return near[0] if near else None


def _rate_hint(raw: dict, loc: tuple) -> str:
    """For an unknown field of ``data`` while neither rate is given: that one is required."""
    data = raw.get("data") if isinstance(raw, dict) else None
    if loc[:-1] != ("data",) or not isinstance(data, dict) or "dt" in data or "fs" in data or "input" not in data:
        return ""
    return " (data needs its sampling rate: fs, in Hz, or dt, in s)"


_LIST_BRANCH = "list[float]"  # pydantic's tag of the inline branch of a record (``str | list[float]``)


def branch_errors(errors: list) -> list:
    """pydantic's errors of a record field (``data.input``/``data.observed``: a file name or
    the values inline) without the branch its input did not take: values given inline get
    their own errors, not "Input should be a valid string", located at the sample
    (``data.observed[5]``, 0-based) without the union's tag, a null named as such."""
    inline = {tuple(e["loc"][:i]) for e in errors for i, part in enumerate(e["loc"]) if part == _LIST_BRANCH}
    out = []
    for e in errors:
        loc = tuple(e["loc"])
        if len(loc) > 1 and loc[-1] == "str" and loc[:-1] in inline:
            continue
        if _LIST_BRANCH in loc:
            e = {**e, "loc": tuple(part for part in loc if part != _LIST_BRANCH)}
            if e.get("input", 0) is None and isinstance(loc[-1], int):
                e["msg"] = f"sample {loc[-1]} (counting from 0) is null: every sample must be a number"
        out.append(e)
    return out


def parse(raw: dict) -> JobSpec:
    """Validate the structure; pydantic errors become one SpecError naming every field (the
    first as its ``field``, each once). An unknown field gets the closest allowed name
    there ("did you mean `priors`?"), and a required field it misspells is not reported
    missing besides."""
    try:
        return JobSpec.model_validate(raw)
    except ValidationError as err:
        errors = branch_errors(err.errors())

    def allowed(loc: tuple) -> list[str]:  # the field names of the section at ``loc``
        kind: Any = JobSpec
        for part in loc:
            if isinstance(part, int):  # an item of list[ModelSpec]
                kind = (get_args(kind) or (None,))[0]
                continue
            options = [a for a in get_args(kind) if a is not type(None)] or [kind]  # X | None, unions
            if len(options) > 1:  # the sampler's union, tagged by its algorithm
                options = [a for a in options if part in get_args(a.model_fields["algorithm"].annotation)]
                kind = options[0] if options else None
            elif isinstance(options[0], type) and issubclass(options[0], BaseModel) and part in options[0].model_fields:
                kind = options[0].model_fields[part].annotation
            else:
                return []
        return list(kind.model_fields) if isinstance(kind, type) and issubclass(kind, BaseModel) else []

    missing = {tuple(e["loc"]) for e in errors if e["type"] == "missing"}
    problems, explained = [], set()
    for e in errors:
        loc, message = tuple(e["loc"]), e["msg"]
        if e["type"] == "extra_forbidden" and isinstance(loc[-1], str):
            close = _closest(loc[-1], allowed(loc[:-1]))
            if close:
                message += f"; did you mean `{close}`?"
                explained.add((*loc[:-1], close))
            message += "".join(f"; {why}" for at, why in REMOVED.items() if loc[:1] + loc[-1:] == at)
            message += _rate_hint(raw, loc)
        problems.append((loc, _field(loc), message))
    problems = [p for p in problems if p[0] not in explained or p[0] not in missing] or problems
    first, *rest = problems
    raise SpecError(first[1], "; ".join([first[2], *(f"{f}: {m}" for _, f, m in rest)])) from None


def load(path: str | Path) -> tuple[JobSpec, Path]:
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise SpecError("spec", f"cannot read {path}: {err.strerror}") from None
    try:
        raw = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as err:
        raise SpecError("spec", f"{path} is not valid {'JSON' if path.suffix == '.json' else 'YAML'}: {err}") from None
    if not isinstance(raw, dict):
        raise SpecError("spec", f"{path} must hold a mapping at the top level")
    return parse(raw), path.parent


def load_array(source: str | list[float], base_dir: Path | None, field: str) -> np.ndarray:
    """An inline list, or a file relative to the spec: ``x.npy``, ``x.npz:key``,
    ``x.csv:column`` (name or index), ``x.mat:variable``."""
    if isinstance(source, list):
        return np.asarray(source, dtype=float)
    if base_dir is None:
        raise SpecError(field, "files are not allowed here; give the data inline")
    name, _, key = source.partition(":")
    path = base_dir / name
    if not path.is_file():
        raise SpecError(field, f"file not found: {path}")
    try:
        if path.suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
        elif path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                if key not in z:
                    raise SpecError(field, f"{path.name} has no array {key!r}; it has {sorted(z.files)}")
                arr = z[key]
        elif path.suffix == ".csv":
            table = np.genfromtxt(path, delimiter=",", names=True)
            cols = table.dtype.names or ()
            col = cols[int(key)] if key.isdigit() else key
            if col not in cols:
                raise SpecError(field, f"{path.name} has no column {key!r}; it has {list(cols)}")
            arr = table[col]
        elif path.suffix == ".mat":
            from scipy.io import loadmat

            mat = loadmat(path)
            if key not in mat:
                raise SpecError(field, f"{path.name} has no variable {key!r}")
            arr = mat[key]
        else:
            raise SpecError(field, f"unsupported file type {path.suffix!r} (npy, npz:key, csv:column, mat:variable)")
    except (OSError, ValueError) as err:
        raise SpecError(field, f"cannot read {path.name}: {err}") from None
    arr = np.asarray(arr, dtype=float).squeeze()
    if arr.ndim != 1:
        raise SpecError(field, f"must be one record (1-d), got shape {arr.shape}")
    return arr


def check_copies(spec: JobSpec) -> None:
    """A model declared ``same_model_as`` another has its integrator too (the simulator, its
    parameters and fixed values: ``abcns.run.check_models``)."""
    named = {m.name: m for m in spec.models}
    for i, model in enumerate(spec.models):
        first = named.get(model.same_model_as or "")
        if first is not None and model.integrator != first.integrator:
            raise SpecError(f"models[{i}].same_model_as", f"{model.name!r} and {first.name!r} differ in their integrator "
                                                          f"({model.integrator} against {first.integrator}): only the "
                                                          "priors may")


def model_description(model: ModelSpec) -> ModelDescription:
    """A spec's model as a worker builds it."""
    return ModelDescription(model.name, model.simulator, dict(model.priors), dict(model.fixed),
                            model.integrator.substeps, model.integrator.output, model.same_model_as)


def description(spec: JobSpec) -> JobDescription:
    """What a worker needs, besides the records, to build the job's evaluator."""
    return JobDescription(
        tuple(model_description(m) for m in spec.models), spec.distance.name, spec.distance.summaries,
        spec.data.sample_interval if spec.data.input is not None else None, spec.data.fit,
        spec.data.input_interpolation)


def _decimate(x: np.ndarray, q: int, field: str) -> np.ndarray:
    from scipy.signal import decimate

    try:
        return np.ascontiguousarray(decimate(x, q, ftype="fir", zero_phase=True))
    except ValueError as err:
        raise SpecError("data.decimate", f"cannot decimate {field} ({x.size} samples) by {q}: {err}") from None


def load_data(spec: JobSpec, base_dir: Path | None) -> tuple[np.ndarray | None, np.ndarray]:
    """(input or None, observed) as the job uses them: loaded, then decimated by
    ``data.decimate`` (FIR low-pass, zero phase, every q-th sample kept)."""
    data = spec.data
    observed = load_array(data.observed, base_dir, "data.observed")
    force = load_array(data.input, base_dir, "data.input") if data.input is not None else None
    if data.decimate > 1:
        observed = _decimate(observed, data.decimate, "data.observed")
        force = _decimate(force, data.decimate, "data.input") if force is not None else None
    return force, observed


def load_voltage(spec: JobSpec, base_dir: Path | None) -> np.ndarray | None:
    """The second input channel (``data.voltage``) as the job uses it, decimated as the input
    is; None when the spec has none. It must come with an input (``data.input``)."""
    data = spec.data
    if data.voltage is None:
        return None
    if data.input is None:
        raise SpecError("data.voltage", "is a second input channel: it needs the input record (data.input) beside it")
    voltage = load_array(data.voltage, base_dir, "data.voltage")
    return _decimate(voltage, data.decimate, "data.voltage") if data.decimate > 1 else voltage


def job_arrays(job: Job) -> dict[str, np.ndarray | None]:
    """The records a worker builds the job from (:func:`worker.description.job_parts`):
    input (``force``), observed and, when the spec has one, the voltage."""
    arrays = {"force": job.force, "observed": job.observed}
    return arrays if job.voltage is None else {**arrays, "voltage": job.voltage}


def check_applicable(spec: JobSpec) -> None:
    """``distance.summaries`` applies to ``summary_euclidean`` only, as an unknown field is an
    error (a sampler field another algorithm reads is refused by the schema itself)."""
    if spec.distance.summaries is not None and spec.distance.name != "summary_euclidean":
        raise SpecError("distance.summaries", f"applies to distance 'summary_euclidean' only, not {spec.distance.name!r}")


#: the largest magnitude of an input or observed sample: the squared error of any trajectory
#: the divergence guard lets through (1000 x the observed scale) over the most samples a job
#: may hold stays finite, (2 x 1e3 x 1e100)^2 x 2^25 ~ 1e214 < 1.8e308, and so do the
#: observed record's variance and a force over any mass of 1e-100 or more
MAX_MAGNITUDE = 1e100
#: kept samples either side of one that scipy's decimation filter reads (``decimate(x, q,
#: ftype="fir", zero_phase=True)``: 20 q + 1 taps, centred), plus one
DECIMATION_REACH = 11


def samples_read(spec: JobSpec) -> int | None:
    """The leading samples of the data records (before decimation) that the job reads; None
    for all. With the NMSE and a fit window: up to the end of the fit or the test window,
    whichever is later, and with decimation the filter's reach beyond it (the samples after
    that change no simulation, distance or held-out check). The summary distances and an
    NMSE without a window read the whole record."""
    data = spec.data
    if spec.distance.name != "nmse" or data.fit is None:
        return None
    kept = max(data.fit[1], data.test[1] if data.test is not None else 0)
    return kept if data.decimate == 1 else (kept + DECIMATION_REACH) * data.decimate


def cut_to_read(spec: JobSpec, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The 1-d records of ``arrays`` cut to :func:`samples_read`; unchanged when the records
    differ in length (an error :func:`build` reports as it is)."""
    n = samples_read(spec)
    if n is None or len({a.shape for a in arrays.values()}) != 1 or any(a.ndim != 1 for a in arrays.values()):
        return arrays
    return {k: a[:n] for k, a in arrays.items()}


def check_records(force: np.ndarray | None, observed: np.ndarray, voltage: np.ndarray | None = None) -> None:
    """Input, observed (and voltage) samples finite and within ``MAX_MAGNITUDE`` (before a
    distance computes anything of them). SpecError naming the record."""
    for field, record in (("data.input", force), ("data.observed", observed), ("data.voltage", voltage)):
        if record is not None and record.size and not (-MAX_MAGNITUDE <= record.min() and record.max() <= MAX_MAGNITUDE):
            big = np.flatnonzero(~(np.abs(record) <= MAX_MAGNITUDE))  # (min and max: no copy of a long record)
            if big.size:
                raise SpecError(field, _bad_sample(field, big[0], float(record[big[0]])))


#: why a gap (NaN, inf) anywhere in a record is refused, the test window included
_GAP = {"data.input": "the input drives the simulation over the whole record",
        "data.voltage": "the voltage drives the simulation over the whole record, as the input does",
        "data.observed": "the simulation is scored over data.fit and compared over data.test (abcns analyse, "
                         "the figures), so a gap in the test window alone is refused too"}


def _bad_sample(field: str, i: int, value: float) -> str:
    """Why sample ``i`` of a record is refused: not finite (a gap), or too large."""
    where = f"sample {i} (counting from 0) is {value:.6g}"
    if not math.isfinite(value):
        return (f"{where}: every sample must be a finite number; {_GAP[field]}: fill the gap, or end the record "
                "(and its windows) before it")
    return (f"{where}: samples must be at most {MAX_MAGNITUDE:.0e} in magnitude (so no squared error or variance "
            "overflows); give the record in larger units")


def check_physical(distance: object) -> None:
    """What makes physical and numerical sense beyond the schema, once the job's parts are
    built: an NMSE scale that is a finite number (each parameter's valid range, a positive
    mass among them, is the simulator's: its ``ranges``, checked by
    ``worker.compose.check_ranges``). SpecError naming the field."""
    scale = getattr(distance, "scale", 1.0)
    if not (math.isfinite(scale) and scale > 0):
        raise SpecError("data.observed", f"its variance on the fit window is too small for the NMSE in floating point "
                                         f"(scale {scale:.3g}); rescale the record (its units)")


# ---------------------------------------------------------------------------- what a job must mean
# The HTTP service runs a job only if it can mean something (check_meaningful, called by
# service.http.limits.admit; docs/deploy.md, "What a job must mean"): each rule refuses a spec
# that the hostile client of issue Z got accepted and that then held the running slot for
# 14-47 s of simulations to end `nothing_accepted`.
#: samples of the window the distance reads (the fit window for the NMSE, else the record):
#: fewer cannot tell models apart (the noise floor has n - p degrees of freedom)
MIN_SAMPLES = 20
#: the largest magnitude of a meaningful input or observed sample: beyond it the units are
#: wrong (no measured force, displacement or acceleration is 1e15 in SI units), and the
#: simulators' polynomial terms and the squared errors leave float64's precision
RECORD_MAX = 1e15
#: the smallest peak magnitude of a meaningful observed record (a femtometre in metres)
RECORD_MIN = 1e-15
#: the observed record's standard deviation on its window, relative to its peak magnitude,
#: below which it is constant to the precision a simulation matches it (float64 rounding of
#: a constant record's mean leaves ~1e-16)
MIN_RELATIVE_STD = 1e-8
#: the lowest first tolerance of the NMSE (%): a relative RMS error of 1e-7, below which the
#: distance measures the rounding of an integrated trajectory, not the model
NMSE_EPSILON_FLOOR = 1e-12
#: with the noise stated, the lowest first tolerance as a share of the truth's own expected
#: NMSE (100 noise_std^2 / var): no simulation gets below a tenth of it (chi^2_n / n < 0.1 has
#: probability under 2e-4 for n >= 10)
NOISE_FLOOR_SHARE = 0.1


def _read_window(spec: JobSpec, observed: np.ndarray) -> tuple[tuple[int, int], str]:
    """The samples the distance reads and the field that sets them."""
    if spec.distance.name == "nmse" and spec.data.fit is not None:
        return (spec.data.fit[0], spec.data.fit[1]), "data.fit"
    return (0, int(observed.size)), "data.observed"


def _check_meaningful_records(spec: JobSpec, job: Job) -> None:
    """The record's length, scale and variation on the window the distance reads, the
    input's scale, and a stated noise no larger than the record."""
    (start, stop), where = _read_window(spec, job.observed)
    if stop - start < MIN_SAMPLES:
        raise SpecError(where, f"the distance reads {stop - start} samples; a job needs at least {MIN_SAMPLES} to tell "
                               "models apart")
    window = job.observed[start:stop]
    peak, std = float(np.max(np.abs(window))), float(np.std(window))
    if not RECORD_MIN <= peak <= RECORD_MAX:
        raise SpecError("data.observed", f"its largest sample is {peak:.3g} in magnitude; a measured record is between "
                                         f"{RECORD_MIN:.0e} and {RECORD_MAX:.0e}: give it in units where it is")
    if not std > MIN_RELATIVE_STD * peak:
        raise SpecError("data.observed", f"is constant on the samples the distance reads (standard deviation {std:.3g} "
                                         f"against a level of {peak:.3g}): there is nothing to fit")
    if job.force is not None and job.force.size:
        force_peak = float(np.max(np.abs(job.force)))
        if not 0 < force_peak <= RECORD_MAX:
            raise SpecError("data.input", f"its largest sample is {force_peak:.3g} in magnitude; an input is nonzero (a "
                                          f"system at rest with no input never moves) and at most {RECORD_MAX:.0e}: give "
                                          "it in units where it is")
    noise_std = spec.data.noise_std
    if noise_std is not None and noise_std > peak:
        raise SpecError("data.noise_std", f"{noise_std:.6g} exceeds the observed record's largest sample ({peak:.3g}) on "
                                          "the samples the distance reads: noise that large would show in them")


def _check_meaningful_rate(spec: JobSpec, job: Job) -> None:
    """The sampling rate against each model's natural frequencies (the simulators with
    ``omega_min`` and ``omega_max``): Nyquist for the slowest the priors allow, and one
    period of the fastest within the window the distance reads."""
    if spec.data.input is None:
        return
    dt, field = spec.data.sample_interval, "data.fs" if spec.data.fs is not None else "data.dt"
    (start, stop), _ = _read_window(spec, job.observed)
    for i, (model, sim) in enumerate(zip(job.description.models, job.simulators, strict=True)):
        kind: Any = type(sim)  # a simulator class, with or without the frequencies
        if not (callable(getattr(kind, "omega_min", None)) and callable(getattr(kind, "omega_max", None))):
            continue
        bounds = parameter_bounds(model, kind)
        try:
            slowest, fastest = kind.omega_min(bounds), kind.omega_max(bounds)
        except (KeyError, ValueError, ArithmeticError):
            continue  # the simulator's own checks say what is wrong
        if slowest * dt > math.pi:
            raise SpecError(field, f"a sample interval of {dt:.3g} s is too long for models[{i}]: the natural frequency "
                                   f"of every model its priors allow is at least {slowest / (2 * math.pi):.3g} Hz, above "
                                   f"the Nyquist frequency {0.5 / dt:.3g} Hz, so every simulation is aliased")
        if fastest * dt * (stop - start) < 2 * math.pi:
            raise SpecError(field, f"the {stop - start} samples the distance reads last {dt * (stop - start):.3g} s, less "
                                   f"than one period of the fastest natural frequency models[{i}]'s priors allow "
                                   f"({fastest / (2 * math.pi):.3g} Hz): no model they allow moves in that time")


def _check_meaningful_tolerance(spec: JobSpec, job: Job) -> None:
    """The NMSE's first tolerance above what a simulation can reach."""
    epsilon = getattr(job.settings, "epsilon_initial", None)
    if epsilon is None or spec.distance.name != "nmse":
        return
    floor, why = NMSE_EPSILON_FLOOR, "below it the NMSE measures float64 rounding, not the model"
    if job.noise is not None and job.noise.variance is not None:
        truth = job.noise.n_samples * job.noise.variance  # the truth's expected NMSE with the noise stated
        if NOISE_FLOOR_SHARE * truth > floor:
            floor, why = NOISE_FLOOR_SHARE * truth, (f"a tenth of the NMSE the true model is expected at with "
                                                     f"data.noise_std ({truth:.3g} %): no simulation reaches below")
    if epsilon < floor:
        raise SpecError("sampler.epsilon_initial", f"{epsilon:.3g} is below {floor:.3g} % ({why}); the first population "
                                                   "would never fill")


def check_meaningful(spec: JobSpec, job: Job) -> None:
    """What a job must satisfy to be worth running, beyond being valid (``build``): a record
    of at least MIN_SAMPLES samples where the distance reads it, of a measured scale
    (RECORD_MIN..RECORD_MAX) and not constant (MIN_RELATIVE_STD), a nonzero input within
    RECORD_MAX, a stated noise no larger than the record, a sampling rate that resolves the
    slowest natural frequency the priors allow (Nyquist) and a window that spans a period
    of the fastest, and an NMSE first tolerance above NMSE_EPSILON_FLOOR (and a tenth of the
    truth's expected NMSE when the noise is stated). SpecError naming the field."""
    _check_meaningful_records(spec, job)
    _check_meaningful_rate(spec, job)
    _check_meaningful_tolerance(spec, job)


def spec_text(spec: JobSpec) -> dict:
    """The spec as JSON to be read back (an HTTP job's spec.json, ``abcns submit``'s upload):
    the fields given, not the defaults, so that read back it means the same (:func:`stop_rules`
    reads which rules were named); its job key is the same (the defaults fill in again)."""
    return spec.model_dump(mode="json", exclude_unset=True)


def stop_rules(stop: BaseModel) -> StopRules:
    """The spec's stop rules. A ``min_epsilon_decrease`` the spec names is the user's own rule:
    it may end the run above its decision tolerance (``decrease_above_floor``, unless the spec
    says otherwise); the default one waits for the decision tolerance (abcns.StopRules)."""
    rules = stop.model_dump()
    named = stop.model_fields_set
    if "min_epsilon_decrease" in named and rules["min_epsilon_decrease"] is not None and "decrease_above_floor" not in named:
        rules["decrease_above_floor"] = True
    return StopRules(**rules)


def build(spec: JobSpec, base_dir: Path | None = None, allow_import: bool = False) -> Job:
    """Everything checkable before a simulation: raise SpecError (naming the spec's field,
    the core's errors mapped by :func:`spec_errors`) or return a Job."""
    with spec_errors():
        check_applicable(spec)
        data = spec.data
        force, observed = load_data(spec, base_dir)
        voltage = load_voltage(spec, base_dir)
        check_records(force, observed, voltage)  # before a distance computes anything of them
        arrays = {"force": force, "observed": observed, **({} if voltage is None else {"voltage": voltage})}
        job_description = description(spec)
        models, simulators, distance = job_parts(job_description, arrays, allow_import)
        evaluate = evaluator(models, simulators, distance)  # checks the records' lengths: before a window that misses
        if data.test is not None:
            check_window(data.test, observed.size, "test")
        check_models(models)  # duplicate names, same_model_as
        check_copies(spec)
        check_physical(distance)
        settings = spec.sampler.settings()
        settings.check_particles(models)
        stop = stop_rules(spec.stop)
        if isinstance(distance, NMSE):
            noise: Noise | None = distance.noise(data.noise_std)
        elif data.noise_std is not None:
            raise SpecError("data.noise_std", f"applies to distance 'nmse' only, not {spec.distance.name!r}")
        else:
            noise = None
        return Job(spec, models, evaluate, settings, stop, spec.seed, force, observed, simulators, job_description, noise,
                   voltage)
