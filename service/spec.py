"""The job spec (DESIGN.md): one pydantic schema for Python, the CLI and HTTP.

``load(path)`` reads YAML or JSON; ``build(spec, base_dir)`` validates everything that can
be checked before a simulation (files, windows, lengths, simulator parameters, sampler
settings) and returns a :class:`Job` ready for ``abcns.run``. Every error is an
``abcns.SpecError`` whose ``field`` names the place in the spec (``models[1].priors.k``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from abcns import Model, NSSettings, RejectionSettings, SMCSettings, SpecError, StopRules
from abcns.distances import check_window
from abcns.executor import Evaluate
from worker.evaluate import job_evaluator

Window = tuple[int, int]


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
    priors: dict[str, tuple[float, float]]
    integrator: IntegratorSpec = IntegratorSpec()


class DistanceSpec(_Strict):
    name: Literal["nmse", "summary_euclidean"] = "nmse"
    summaries: Literal["gk", "order_statistics"] = "gk"


class SamplerSpec(_Strict):
    algorithm: Literal["abc-ns", "abc-smc", "rejection"] = "abc-ns"
    particles: int = 1000
    alpha: float = 0.3
    beta: float = 0.6
    enlargement: float = 1.1
    weights: Literal["paper", "kernel"] = "paper"
    epsilon_initial: float | None = None
    pilot_size: int | None = None
    pilot_quantile: float = 0.5
    batch_size: int = 200
    quantile: float = 0.5  # abc-smc without a schedule
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
    seed: int = 0

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


def build(spec: JobSpec, base_dir: Path | None = None, allow_import: bool = False) -> Job:
    """Everything checkable before a simulation: raise SpecError or return a Job."""
    data = spec.data
    force, observed = load_data(spec, base_dir)
    if data.test is not None:
        check_window(data.test, observed.size, "data.test")
    models, evaluate = job_evaluator(description(spec), {"force": force, "observed": observed}, allow_import)
    s = spec.sampler
    common = dict(particles=s.particles, epsilon_initial=s.epsilon_initial, pilot_size=s.pilot_size,
                  pilot_quantile=s.pilot_quantile, batch_size=s.batch_size)
    if s.algorithm == "abc-ns":
        settings: NSSettings | SMCSettings | RejectionSettings = NSSettings(
            alpha=s.alpha, beta=s.beta, enlargement=s.enlargement, weights=s.weights, **common)
    elif s.algorithm == "abc-smc":
        settings = SMCSettings(quantile=s.quantile, schedule=tuple(s.schedule) if s.schedule else None, **common)
    else:
        settings = RejectionSettings(**common)
    settings.check_models(models)
    stop = StopRules(**spec.stop.model_dump())
    return Job(spec, models, evaluate, settings, stop, spec.seed, force, observed)
