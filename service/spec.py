"""The job spec (DESIGN.md): one pydantic schema for Python, the CLI and HTTP.

``load(path)`` reads YAML or JSON; ``build(spec, base_dir)`` validates everything that can
be checked before a simulation (files, windows, lengths, simulator parameters, sampler
settings) and returns a :class:`Job` ready for ``abcns.run``. Every error is an
``abcns.SpecError`` whose ``field`` names the place in the spec (``models[1].priors.k``).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, field_validator, model_validator

from abcns import Model, NSSettings, RejectionSettings, SMCSettings, SpecError, StopRules
from abcns.distances import check_window
from abcns.executor import Evaluate
from worker.evaluate import evaluator, job_parts
from worker.simulators import Simulator

Window = tuple[int, int]


def _prior_pair(value: Any) -> Any:
    """A prior is ``[low, high]``: a wrong shape is reported at the prior's own name
    (``models[0].priors.k``), not at a missing tuple element (``...priors.k[1]``)."""
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise ValueError(f"a prior is [low, high], got {value!r}"[:200])
    return value


Prior = Annotated[tuple[float, float], BeforeValidator(_prior_pair)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class DataSpec(_Strict):
    dt: Annotated[float, Field(gt=0)] | None = None
    fs: Annotated[float, Field(gt=0)] | None = None
    input: str | list[float] | None = None
    observed: str | list[float]
    fit: Window | None = None
    test: Window | None = None
    decimate: Annotated[int, Field(ge=1, le=1000)] = 1  # keep every q-th sample, anti-aliased; windows count kept samples

    @model_validator(mode="after")
    def _one_rate(self) -> DataSpec:
        if (self.dt is None) == (self.fs is None) and self.input is not None:
            raise ValueError("give exactly one of dt and fs")
        return self

    @property
    def sample_interval(self) -> float:
        """The interval between the samples used (after decimation)."""
        base = self.dt if self.dt is not None else 1.0 / self.fs  # type: ignore[operator]
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


class DistanceSpec(_Strict):
    name: Literal["nmse", "summary_euclidean"] = "nmse"
    summaries: Literal["gk", "order_statistics"] | None = None  # summary_euclidean only (default gk)


class SamplerSpec(_Strict):
    algorithm: Literal["abc-ns", "abc-smc", "rejection"] = "abc-ns"
    particles: int = 1000
    # null: the algorithm's default (abcns.NSSettings / SMCSettings); a field the chosen
    # algorithm does not read is an error (check_applicable)
    alpha: float | None = None  # abc-ns (0.3)
    beta: float | None = None  # abc-ns (0.6)
    enlargement: float | None = None  # abc-ns (1.1)
    weights: Literal["paper", "kernel"] | None = None  # abc-ns ("paper")
    epsilon_initial: float | None = None
    pilot_size: int | None = None
    pilot_quantile: float = 0.5
    batch_size: int = 25
    variant: Literal["evidence", "paper"] | None = None  # abc-ns ("evidence")
    max_ellipsoids: int | None = None  # abc-ns, evidence variant
    min_model_probability: float | None = None  # abc-ns, evidence variant
    min_proposal_share: float | None = None  # abc-ns, evidence variant
    quantile: float | None = None  # abc-smc without a schedule (0.5)
    schedule: list[float] | None = None  # abc-smc


class StopSpec(_Strict):
    min_epsilon_decrease: float | None = 0.01
    epsilon_target: float | None = None
    max_populations: int | None = None
    max_simulations: int | None = None
    max_seconds: float | None = None


class JobSpec(_Strict):
    name: str = "job"
    data: DataSpec
    models: list[ModelSpec] = Field(min_length=1)
    distance: DistanceSpec = DistanceSpec()
    sampler: SamplerSpec = SamplerSpec()
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


def _field(loc: tuple) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def parse(raw: dict) -> JobSpec:
    """Validate the structure; pydantic errors become one SpecError naming every field."""
    try:
        return JobSpec.model_validate(raw)
    except ValidationError as err:
        problems = [(_field(e["loc"]), e["msg"]) for e in err.errors()]
        raise SpecError(problems[0][0], "; ".join(f"{f}: {m}" for f, m in problems)) from None


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


def description(spec: JobSpec) -> dict:
    """The JSON-able part of a job a worker needs to build its evaluator."""
    return {
        "models": [m.model_dump() for m in spec.models],
        "distance": spec.distance.model_dump(),
        "data": {"dt": spec.data.sample_interval if spec.data.input is not None else None,
                 "fit": list(spec.data.fit) if spec.data.fit else None},
    }


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


# each algorithm's settings; the sampler fields an algorithm reads are its settings' fields
SETTINGS: dict[str, type[NSSettings] | type[SMCSettings] | type[RejectionSettings]] = {
    "abc-ns": NSSettings, "abc-smc": SMCSettings, "rejection": RejectionSettings}


def _reads(algorithm: str) -> set[str]:
    return {f.name for f in dataclasses.fields(SETTINGS[algorithm])}


def _given(section: BaseModel) -> set[str]:
    """Fields the spec gives a value (null is the default, so a spec written back by
    ``model_dump`` gives the same set)."""
    return {name for name in section.model_fields_set if getattr(section, name) is not None}


def check_applicable(spec: JobSpec) -> None:
    """A field that the chosen algorithm or distance does not read is an error, as an
    unknown field is."""
    algorithm = spec.sampler.algorithm
    for name in sorted(_given(spec.sampler) - {"algorithm"} - _reads(algorithm)):
        owners = [a for a in SETTINGS if name in _reads(a)]
        raise SpecError(f"sampler.{name}", f"does not apply to algorithm {algorithm!r} (it is read by {', '.join(owners)})")
    if "summaries" in _given(spec.distance) and spec.distance.name != "summary_euclidean":
        raise SpecError("distance.summaries", f"applies to distance 'summary_euclidean' only, not {spec.distance.name!r}")


def build(spec: JobSpec, base_dir: Path | None = None, allow_import: bool = False) -> Job:
    """Everything checkable before a simulation: raise SpecError or return a Job."""
    check_applicable(spec)
    data = spec.data
    force, observed = load_data(spec, base_dir)
    if data.test is not None:
        check_window(data.test, observed.size, "data.test")
    models, simulators, distance = job_parts(description(spec), {"force": force, "observed": observed}, allow_import)
    s = spec.sampler
    given = {name: getattr(s, name) for name in _given(s) - {"algorithm"}}
    if s.schedule is not None:
        given["schedule"] = tuple(s.schedule)
    settings = SETTINGS[s.algorithm](**given)
    settings.check_particles(models)
    stop = StopRules(**spec.stop.model_dump())
    return Job(spec, models, evaluator(models, simulators, distance), settings, stop, spec.seed, force, observed,
               simulators)
