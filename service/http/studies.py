"""Studies over HTTP (``POST /studies``, ``GET /studies/{id}``; docs/studies.md): a study's data
sets (:mod:`service.run.study`) each queued as a job of the service's own queue
(:class:`service.http.jobs.JobManager`), the report (:mod:`service.report.study`) read from
their stores. A study's folder is ``STORE_DIR/studies/ID``: ``study.json`` (as the CLI's, plus
the ids of its jobs) and ``data.npz`` (the spec's arrays). Every data set's job is built and
admitted (the service's limits, what a job must mean) before the first is queued, and the
queue must have room for them all: a study is queued whole or not at all.
"""

from __future__ import annotations

import json
import shutil
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from abcns import SpecError
from service.http.jobs import DATA_FILE, TERMINAL, JobManager, QueueFull
from service.http.limits import admit
from service.report.study import study_report
from service.run.runner import with_records
from service.run.study import STUDY_FILE, StudyRequest, check_request, dataset_spec, make_datasets, study_record
from service.spec import JobSpec, build

STUDIES = "studies"


def study_folder(manager: JobManager, study_id: str) -> Path:
    return manager.store_dir / STUDIES / study_id


def _checked(manager: JobManager, spec: JobSpec, folder: Path, request: StudyRequest) -> tuple[list, list]:
    """The data sets and their job specs, each built and admitted (SpecError naming the field)."""
    check_request(spec, request)
    build(spec, folder, allow_import=False)
    sets, records = make_datasets(spec, folder, request)
    specs = []
    for ds, records_ in zip(sets, records, strict=True):
        arrays = {k: v for k, v in records_.items() if k in ("input", "observed")}
        job_spec = with_records(dataset_spec(spec, ds), arrays)  # inline: built here without a folder
        try:
            admit(job_spec, build(job_spec, None, allow_import=False), manager.limits)
        except SpecError as err:
            raise SpecError(err.field, f"data set {ds.index} ({ds.model} at {ds.parameters}): {err.message}") from None
        specs.append((job_spec, arrays))
    return sets, specs


def check_room(manager: JobManager, n: int) -> None:
    """QueueFull unless the queue can take ``n`` more jobs (``ABCNS_MAX_QUEUED``)."""
    with manager.lock:
        room = None if manager.max_queued is None else manager.max_queued - len(manager.queue) - manager.admitting
    if room is not None and room < n:
        raise QueueFull(f"the queue has room for {room} jobs; this study has {n} (the limit is {manager.max_queued}, "
                        "ABCNS_MAX_QUEUED): try again later, or with fewer data sets")


def submit_study(manager: JobManager, spec: JobSpec, arrays: dict[str, np.ndarray], request: StudyRequest) -> str:
    """Make and check the study's data sets, then queue a job each; the study's id. SpecError
    naming the field, QueueFull when the queue cannot take them all; nothing is queued then."""
    check_room(manager, request.datasets)  # before any data set is made
    study_id = uuid.uuid4().hex
    folder = study_folder(manager, study_id)
    folder.mkdir(parents=True)
    try:
        np.savez(folder / DATA_FILE, **arrays)  # type: ignore[arg-type]  # numpy takes the arrays as **kwds
        sets, specs = _checked(manager, spec, folder, request)
        check_room(manager, len(specs))
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    ids = [manager.submit(job_spec, arrays).id for job_spec, arrays in specs]
    record = {**study_record(spec, request, sets), "id": study_id, "jobs": ids}
    (folder / STUDY_FILE).write_text(json.dumps(record))
    return study_id


def study_status(manager: JobManager, study_id: str) -> dict[str, Any] | None:
    """The study's progress (its jobs' statuses) and its report over the jobs finished so far;
    None when there is no such study."""
    path = study_folder(manager, study_id) / STUDY_FILE
    if not path.is_file():
        return None
    held = json.loads(path.read_text())
    jobs = [manager.get(j) for j in held["jobs"]]
    statuses = [job.status if job is not None else "purged" for job in jobs]  # once: counts and done agree
    counts: dict[str, int] = {}
    for status in statuses:
        counts[status] = counts.get(status, 0) + 1
    stores = [job.store_path if job is not None else study_folder(manager, study_id) / "purged" for job in jobs]
    report = study_report(held, stores)
    return {"id": study_id, "datasets": len(jobs), "jobs": held["jobs"], "counts": counts,
            "done": all(status in (*TERMINAL, "purged") for status in statuses), **report}
