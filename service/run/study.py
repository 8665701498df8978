"""Studies: is the answer trustworthy for *this* problem? (docs/studies.md)

A study makes ``datasets`` data sets with the spec's own simulators, input, sampling and
windows, and runs each as a job with the spec's own settings (:func:`service.run.jobs.run_jobs`,
one job per worker; over HTTP, the service's queue). Data set ``i`` is made from the
``i``-th child of ``SeedSequence(seed)`` (the study's ``seed``, else the spec's): one
generator draws, in this order, the true model (uniform over the spec's models, unless
``truth`` names it), its free parameters (from their priors, except those ``truth_parameters``
fixes), a seed for a stochastic simulator, then the Gaussian noise; the job's own seed is
the child's first 63-bit word. So the data sets and their jobs depend on the spec, the request
and the seed only, never on the cluster or on which ran first.

A study's folder holds ``study.json`` (the spec, the request and each data set's truth, noise
and seed), ``data/ds-NNNN.npz`` (input, observed, clean response) and ``jobs/ds-NNNN.zarr``
(each job's store). Run again on the same folder with the same spec and request it resumes:
a finished job is not run again (``run_one`` returns its store's result), an unfinished one
resumes from its store, and the study ends as it would have uninterrupted. Another spec or
request on that folder is refused (field ``out``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from abcns import OK, SpecError
from service.run.jobs import JobRun, Outcome, run_jobs
from service.spec import JobSpec, build

STUDY_FILE = "study.json"
MAX_DATASETS = 100_000
#: redraws of a prior draw whose simulation fails (diverges) before the study refuses the priors
MAX_REDRAWS = 100


class StudyRequest(BaseModel):
    """What a study makes: ``datasets`` data sets, Gaussian noise of ``noise_std`` (the data's
    units) or ``noise_share`` of the clean response's RMS (exactly one), the true model
    ``truth`` (None: drawn uniformly), fixed ``truth_parameters`` (others drawn from the
    priors), the ``seed`` (None: the spec's)."""

    model_config = ConfigDict(extra="forbid")
    datasets: Annotated[int, Field(ge=1, le=MAX_DATASETS)]
    noise_std: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    noise_share: Annotated[float, Field(gt=0, le=10, allow_inf_nan=False)] | None = None
    truth: str | None = None
    truth_parameters: dict[str, Annotated[float, Field(allow_inf_nan=False)]] = {}
    seed: Annotated[int, Field(ge=0, le=2**63 - 1)] | None = None

    @model_validator(mode="after")
    def _one_noise(self) -> StudyRequest:
        if self.noise_std is not None and self.noise_share is not None:
            raise ValueError("give noise_std or noise_share, not both")
        if self.noise_std is None and self.noise_share is None:
            raise ValueError("give noise_std (the data's units) or noise_share (of the clean response's RMS)")
        return self


def parse_request(raw: Mapping[str, Any]) -> StudyRequest:
    """The request, validated; SpecError naming the first wrong field."""
    try:
        return StudyRequest.model_validate(dict(raw))
    except ValidationError as err:
        e = err.errors()[0]
        loc = ".".join(str(p) for p in e["loc"]) or "noise_std"
        raise SpecError(loc, str(e["msg"]).removeprefix("Value error, ")) from None


def check_request(spec: JobSpec, request: StudyRequest) -> None:
    """The truth against the spec: a model it has, parameters some candidate infers (its free
    parameters), values inside the prior of every model that infers them. SpecError naming
    the field (``truth``, ``truth_parameters.NAME``)."""
    names = [m.name for m in spec.models]
    if request.truth is not None and request.truth not in names:
        raise SpecError("truth", f"{request.truth!r} is not one of the spec's models ({', '.join(names)})")
    candidates = [m for m in spec.models if request.truth in (None, m.name)]
    for name, value in request.truth_parameters.items():
        field = f"truth_parameters.{name}"
        having = [m for m in candidates if name in m.priors]
        if not having:
            raise SpecError(field, f"is not a free parameter of {request.truth or 'any model'} (those have priors: "
                                   f"{', '.join(sorted({p for m in candidates for p in m.priors}))})")
        for m in having:
            low, high = m.priors[name][:2]
            if not low <= value <= high:
                raise SpecError(field, f"{value:.6g} lies outside the prior [{low:.6g}, {high:.6g}] of model "
                                       f"{m.name!r}: a truth the priors exclude cannot be recovered")


@dataclass
class DataSet:
    """One data set of a study: its true model and parameters, its noise and its job's seed."""

    index: int
    model: str
    parameters: dict[str, float]
    noise_std: float
    clean_rms: float
    seed: int

    @property
    def label(self) -> str:
        return f"ds-{self.index:04d}"


def _draw(data, request: StudyRequest, rng: np.random.Generator, names: list[str]):
    """(model, parameters, clean response) of one data set: a prior draw whose simulation runs."""
    model = request.truth or names[int(rng.integers(len(names)))]
    m = data.models[model]
    for _ in range(MAX_REDRAWS):
        theta = m.sample_prior(1, rng)[0]
        for j, p in enumerate(m.parameter_names):
            theta[j] = request.truth_parameters.get(p, theta[j])
        values, status = data.simulate(model, int(rng.integers(2**31)))(theta[None, :])
        if status[0] == OK and np.all(np.isfinite(values[0])):
            return model, dict(zip(m.parameter_names, map(float, theta), strict=True)), values[0]
    raise SpecError("truth_parameters" if request.truth_parameters else f"models[{names.index(model)}].priors",
                    f"{MAX_REDRAWS} truths drawn for {model} all failed to simulate (diverged)")


def make_datasets(spec: JobSpec, base: Path | None, request: StudyRequest) -> tuple[list[DataSet], list[dict]]:
    """The data sets (their truths) and their records ({input, observed, clean}): the spec's
    simulators over its whole record, decimated as the job would (``job_data``)."""
    from service.report.analysis import job_data

    data = job_data(spec, base)
    names = [m.name for m in spec.models]
    seed = spec.seed if request.seed is None else request.seed
    sets, records = [], []
    for i, child in enumerate(np.random.SeedSequence(seed).spawn(request.datasets)):
        rng = np.random.default_rng(child)
        model, params, clean = _draw(data, request, rng, names)
        rms = float(np.sqrt(np.mean(clean**2)))
        std = request.noise_std if request.noise_std is not None else request.noise_share * rms  # type: ignore[operator]
        observed = clean + std * rng.standard_normal(clean.size)
        job_seed = int(child.generate_state(1, np.uint64)[0] >> np.uint64(1))
        sets.append(DataSet(i, model, params, float(std), rms, job_seed))
        records.append({"observed": observed, "clean": clean,
                        **({"input": data.force} if data.force is not None else {})})
    return sets, records


def dataset_spec(spec: JobSpec, ds: DataSet) -> JobSpec:
    """The job of one data set: the spec with its records (``ds-NNNN.npz``, already decimated:
    ``decimate`` 1 at the decimated sample interval), its seed and name; a stated
    ``data.noise_std`` becomes the data set's own (the noise is known)."""
    d = spec.data
    file = f"{ds.label}.npz"
    update: dict[str, Any] = {"observed": f"{file}:observed", "decimate": 1,
                              "noise_std": ds.noise_std if d.noise_std is not None else None}
    if d.input is not None:
        update.update(input=f"{file}:input", dt=d.sample_interval, fs=None)
    return spec.model_copy(update={"name": f"{spec.name}-{ds.label}", "seed": ds.seed,
                                   "data": d.model_copy(update=update)})


def study_record(spec: JobSpec, request: StudyRequest, sets: Sequence[DataSet]) -> dict:
    return {"version": 1, "spec": spec.model_dump(mode="json"), "request": request.model_dump(mode="json"),
            "models": [m.name for m in spec.models], "datasets": [asdict(s) for s in sets]}


def prepare(spec: JobSpec, base: Path | None, request: StudyRequest, out: Path,
            allow_import: bool = True) -> list[JobRun]:
    """Check everything, make (or find) the study's data sets in ``out``, and return its
    jobs. Nothing runs: SpecError naming the field for a wrong spec, request or folder."""
    check_request(spec, request)
    build(spec, base, allow_import)
    sets, records = make_datasets(spec, base, request)
    record = study_record(spec, request, sets)
    path = out / STUDY_FILE
    if path.exists():
        check_same_study(json.loads(path.read_text()), record, out)
    (out / "data").mkdir(parents=True, exist_ok=True)
    (out / "jobs").mkdir(exist_ok=True)
    jobs = []
    for ds, arrays in zip(sets, records, strict=True):
        file = out / "data" / f"{ds.label}.npz"
        if not file.exists():
            np.savez(file, **arrays)
        job_spec = dataset_spec(spec, ds)
        if ds.index == 0:
            build(job_spec, out / "data", allow_import)  # the data sets' jobs are valid too
        jobs.append(JobRun.of(job_spec, out / "data", out / "jobs" / f"{ds.label}.zarr", ds.label))
    path.write_text(json.dumps(record, indent=1))
    return jobs


def _but_datasets(record: Mapping[str, Any]) -> dict:
    return {k: v for k, v in record["request"].items() if k != "datasets"}


def check_same_study(held: Mapping[str, Any], record: Mapping[str, Any], out: Path) -> None:
    """A folder's study is resumed, or extended by a larger ``datasets`` (the first data sets
    are the same: ``SeedSequence.spawn`` gives child ``i`` whatever their number); another
    spec or request is refused (SpecError at ``out``)."""
    if held.get("spec") != record["spec"] or _but_datasets(held) != _but_datasets(record):
        raise SpecError("out", f"{out} holds another study (another spec or request); give a new folder")
    n = min(len(held["datasets"]), len(record["datasets"]))
    if held["datasets"][:n] != record["datasets"][:n]:
        raise SpecError("out", f"{out} holds data sets this version of abcns makes otherwise; give a new folder")


def run_study(client, spec: JobSpec, base: Path | None, request: StudyRequest, out: Path, *,
              local_s: float | None = None, on_event: Callable[[int, dict], None] | None = None) -> list[Outcome]:
    """Make the study's data sets in ``out`` (:func:`prepare`) and run their jobs on the
    cluster of ``client`` (:func:`run_jobs`); their outcomes in data-set order."""
    jobs = prepare(spec, base, request, Path(out))
    return run_jobs(client, jobs, allow_import=True, local_s=local_s, on_event=on_event)


def is_study(path: Path) -> bool:
    return (Path(path) / STUDY_FILE).is_file()


def read_study(path: Path) -> dict:
    return json.loads((Path(path) / STUDY_FILE).read_text())


def store_paths(path: Path, study: Mapping[str, Any]) -> list[Path]:
    """Each data set's store (a CLI study's layout)."""
    return [Path(path) / "jobs" / f"ds-{d['index']:04d}.zarr" for d in study["datasets"]]
