"""The HTTP job service: settings -> dependencies -> routers -> schemas.

``create_app(settings)`` builds the FastAPI app; its lifespan connects the Dask client (a
scheduler address, or an embedded LocalCluster) and starts the job manager. Only registry
simulators are accepted over HTTP (no code over the wire), data come inline or as an
uploaded ``.npz``, job ids are checked against ``[0-9a-f]{32}`` so no path leaves the store
directory, and with a token every API request needs ``Authorization: Bearer TOKEN``.

A submitted body is read only once the token has been checked, and only while one of a
bounded number of submission slots is free (``ABCNS_MAX_SUBMISSIONS``; uploads one at a
time). It is checked in this order: its media type (415), then, in a child process
(``service.http.intake``: nothing CPU-bound runs on the event loop), its size, depth and count
of values (413), JSON or an upload's YAML (400 / 422), every string valid Unicode text
and every number finite, the job's and models' names (422 naming the field) and the schema
(422, ``detail[i].field`` a dotted path); then, in a thread, everything the spec builder
checks (physical sense included) and the admission limits. An upload's arrays are read
only when the spec names them, only after their declared shape and dtype passed, and only
the samples the job reads. Every 422 shows the offending value as text; a job that cannot
be stored (a full disk) gets 503 with Retry-After, a full queue 429; a 201 carries the
job's ``Location``. The pages carry a strict Content-Security-Policy.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
import math
import os
import re
import tokenize
import zipfile
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path as FilePath
from typing import IO, Annotated, Any

import anyio
import numpy as np
from distributed import Client, LocalCluster
from fastapi import APIRouter, Depends, FastAPI, Header, HTTPException, Path, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from fastapi.sse import format_sse_event
from starlette.datastructures import UploadFile
from starlette.requests import ClientDisconnect

import abcns
from abcns import SpecError
from service.http import page
from service.http.intake import Intake, Refused, as_text, name_key, problem, validation_errors
from service.http.jobs import JobManager, JobRecord, NoSpace, QueueFull
from service.http.schemas import PAGE_MAX, Health, JobCreated, JobInfo, LimitsOut, PopulationOut, Status, Summary
from service.http.settings import Settings
from service.run.dask_executor import local_cluster
from service.run.jobs import scheduler_identity
from service.run.store import Store, StoreError
from service.spec import JobSpec, samples_read

JOB_ID = Annotated[str, Path(pattern="^[0-9a-f]{32}$", description="a job id (32 hex digits)")]
_bearer = HTTPBearer(auto_error=False)
log = logging.getLogger("abcns.http")
__all__ = ["as_text", "create_app", "validation_errors"]  # as_text, validation_errors: service.http.intake's


# ---------------------------------------------------------------------------- errors
def spec_error(err: SpecError) -> Refused:
    return problem(422, err.field, err.message, "spec")


async def on_validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    return JSONResponse({"detail": validation_errors(exc.errors())}, status_code=422)


async def on_refused(request: Request, exc: Refused) -> JSONResponse:
    return JSONResponse({"detail": exc.detail}, status_code=exc.status, headers=exc.headers)


def _finite(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_finite(v) for v in x]
    return x


# ---------------------------------------------------------------------------- dependencies
def get_manager(request: Request) -> JobManager:
    return request.app.state.manager


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_intake(request: Request) -> Intake:
    return request.app.state.intake


def check_token(request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    token = request.app.state.settings.token
    if not token:
        return
    if credentials is None:
        raise HTTPException(401, "missing bearer token", headers={"WWW-Authenticate": "Bearer"})
    if not hmac.compare_digest(credentials.credentials.encode(), token.encode()):
        raise HTTPException(403, "wrong token")


def get_job(job_id: JOB_ID, manager: Annotated[JobManager, Depends(get_manager)]) -> JobRecord:
    job = manager.get(job_id)
    if job is None:
        raise HTTPException(404, f"no job {job_id}")
    return job


# ---------------------------------------------------------------------------- request bodies
def media_type(request: Request, *accepted: str) -> None:
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media not in accepted and not ("application/json" in accepted and media.endswith("+json")):
        raise HTTPException(415, f"the body must be {' or '.join(accepted)}, not {media or 'untyped'}")


async def read_body(request: Request) -> bytes:
    try:
        return await request.body()
    except ClientDisconnect:
        raise HTTPException(408, "the body did not arrive") from None


def spec_kind(part: UploadFile) -> str:
    """How an upload's spec file part is read: by its name or media type, else "any"."""
    name, media = (part.filename or "").lower(), (part.content_type or "").lower()
    if name.endswith((".yaml", ".yml")) or "yaml" in media:
        return "yaml"
    return "json" if name.endswith(".json") or media == "application/json" else "any"


def npz_arrays(file: IO[bytes], spec: JobSpec, max_samples: int) -> dict[str, np.ndarray]:
    """The arrays an upload's spec names (``input: npz:force``) from its .npz, as float64:
    each one's npy header (shape, dtype) is read and checked first, and only the samples
    the job reads (``service.spec.samples_read``) are then decompressed, in chunks, into
    an array allocated for them: at most ``max_samples`` x 8 bytes, whatever the file."""
    wanted = {key: value[4:] for key in ("input", "observed", "voltage")
              if isinstance(value := getattr(spec.data, key), str) and value.startswith("npz:")}
    if not wanted:
        return {}
    try:
        archive = zipfile.ZipFile(file)
    except (zipfile.BadZipFile, OSError, ValueError) as err:
        raise problem(422, "data", f"not a readable .npz (a zip of .npy files): {err}", "npz") from None
    with archive:
        members = {m[:-4]: m for m in archive.namelist() if m.endswith(".npy")}
        headers = {key: _npy_header(archive, members, name, f"data.{key}", max_samples)
                   for key, name in wanted.items()}
        sizes = {math.prod(shape) for shape, _, _ in headers.values()}
        flat = all(sum(d > 1 for d in shape) <= 1 for shape, _, _ in headers.values())
        n = samples_read(spec) if len(sizes) == 1 and flat else None  # records of one length: cut
        return {key: _npy_data(archive, members[name], f"data.{key}", *headers[key], n)
                for key, name in wanted.items()}


#: zip's compression methods an upload's member may use: stored (0) and deflated (8). A
#: deflated member is decompressed a bounded piece at a time; Python's bzip2 (12) and LZMA
#: (14) readers decompress each compressed block whole, so a 17 KB bzip2 member can become a
#: gigabyte in one read
COMPRESSIONS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflated"}


def _read_header(f: IO[bytes]) -> tuple[tuple, bool, np.dtype, int]:
    """(shape, fortran order, dtype, bytes of the magic and header) of an .npy stream; a
    ValueError for anything that is not a header numpy would write (numpy's own parse
    raises tokenize's TokenError for a header cut short, and takes negative dimensions)."""
    try:
        version = np.lib.format.read_magic(f)
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read_header(f)
    except (tokenize.TokenError, SyntaxError, TypeError, KeyError, IndexError, MemoryError, RecursionError) as err:
        raise ValueError(f"its header does not parse ({type(err).__name__}: {str(err)[:80]})") from None
    if not all(isinstance(d, int) and d >= 0 for d in shape):
        raise ValueError(f"its shape {shape} has a negative dimension")
    return shape, fortran, dtype, f.tell()


def _npy_header(archive: zipfile.ZipFile, members: dict, name: str, field: str,
                max_samples: int) -> tuple[tuple, bool, np.dtype]:
    """The array's shape, order and dtype, from its member's header; 422 naming ``field``
    for a member stored otherwise than :data:`COMPRESSIONS`, a header that does not parse,
    a dtype or size the service does not take, or a member whose size (from the zip's
    directory) is not its header plus the data the header declares."""
    if name not in members:
        raise problem(422, field, f"the upload has no array {name!r}; it has {sorted(members)[:20]}", "npz")
    info = archive.getinfo(members[name])
    if info.compress_type not in COMPRESSIONS:
        raise problem(422, field, f"the array {name!r} is compressed with zip method {info.compress_type}; only stored (0) "
                                  "or deflated (8) members are read (numpy.savez, numpy.savez_compressed)", "npz")
    try:
        with archive.open(info) as f:
            shape, fortran, dtype, start = _read_header(f)
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, RuntimeError) as err:
        raise problem(422, field, f"the array {name!r} is not a readable .npy: {err}", "npz") from None
    size = math.prod(shape)
    if dtype.hasobject or dtype.kind not in "biuf" or dtype.itemsize > 8:
        raise problem(422, field, f"the array {name!r} has dtype {dtype}; real numbers of at most 8 bytes only (float64, "
                                  "float32, integers)", "npz")
    if size > max_samples:
        raise problem(422, field, f"the array {name!r} has shape {shape} ({size} samples); the limit is {max_samples} "
                                  "samples", "npz")
    if info.file_size != start + size * dtype.itemsize:
        raise problem(422, field, f"the array {name!r} is {info.file_size:,} bytes uncompressed, but its header declares "
                                  f"{start:,} + {size * dtype.itemsize:,} ({shape} of {dtype}): a member holds one array "
                                  "and nothing after it", "npz")
    return shape, fortran, dtype


def _npy_data(archive: zipfile.ZipFile, member: str, field: str, shape: tuple, fortran: bool, dtype: np.dtype,
              n: int | None) -> np.ndarray:
    """The array's first ``n`` samples (all with None) as float64, decompressed a chunk at a
    time (its member's size was checked against its header: the reader stops there)."""
    size = math.prod(shape)
    count = size if n is None else min(n, size)
    out = np.empty(count)
    step = max(1, (4 << 20) // dtype.itemsize)
    try:
        with archive.open(member) as f:
            _read_header(f)
            for start in range(0, count, step):
                k = min(step, count - start)
                chunk = f.read(k * dtype.itemsize)
                if len(chunk) < k * dtype.itemsize:
                    raise ValueError(f"the data end after {start + len(chunk) // dtype.itemsize} of {size} samples")
                out[start:start + k] = np.frombuffer(chunk, dtype)
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, RuntimeError) as err:
        raise problem(422, field, f"the array {member[:-4]!r} is not a readable .npy: {err}", "npz") from None
    return out if n is not None else out.reshape(shape, order="F" if fortran else "C")


# ---------------------------------------------------------------------------- routers
api = APIRouter(dependencies=[Depends(check_token)])

_JOB_BODY = {"requestBody": {"required": True, "content": {
    "application/json": {"schema": {"$ref": "#/components/schemas/JobSpec"}}}}}
_UPLOAD_BODY = {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
    "type": "object", "required": ["spec", "data"],
    "properties": {
        "spec": {"type": "string", "description": "the job spec as JSON or YAML (a text field or a file part: "
                                                  "spec.yaml or spec.json); data fields may name 'npz:KEY' of the file"},
        "data": {"type": "string", "format": "binary", "description": "an .npz file with the arrays"}}}}}}}


@api.post("/jobs", status_code=201, response_model=JobCreated, openapi_extra=_JOB_BODY,
          responses={400: {"description": "not UTF-8 JSON"}, 413: {"description": "too large, too deep, too many values"},
                     415: {"description": "not application/json"}, 503: {"description": "cannot store it now"},
                     507: {"description": "no room on the disk for its first populations"}})
async def submit(request: Request, response: Response, manager: Annotated[JobManager, Depends(get_manager)],
                 intake: Annotated[Intake, Depends(get_intake)]) -> JobCreated:
    """Queue a job. Data inline; only registry simulators; invalid specs -> 422 naming the field."""
    media_type(request, "application/json")
    async with intake.slot():  # a bounded number of bodies read and handled at once
        spec, arrays = await intake.spec(await read_body(request), "body", "json")  # in a child process
        return await queue_job(manager, request, response, spec, arrays)


async def queue_job(manager: JobManager, request: Request, response: Response, spec: JobSpec,
                    arrays: dict[str, np.ndarray]) -> JobCreated:
    """Validated against the service's limits and queued; 422 naming the field (``name`` when it
    looks like another job's name but is not it), 429 when the queue is full, 503 when the
    job cannot be stored (a full disk); Location names the job."""
    retry = {"Retry-After": str(request.app.state.settings.retry_after_s)}
    alike = next((j for j in manager.list() if j.name != spec.name and name_key(j.name) == name_key(spec.name)), None)
    if alike is not None:
        raise problem(422, "name", f"differs from the name of job {alike.id} ({as_text(alike.name)}) only by case, width "
                                   "or surrounding space: give it that name or one that does not look alike",
                      "name", spec.name)
    try:
        job = await asyncio.to_thread(manager.submit, spec, arrays)
    except SpecError as err:
        raise spec_error(err) from None
    except QueueFull as err:
        raise HTTPException(429, str(err), headers=retry) from None
    except NoSpace as err:  # the disk has no room for its first populations (issue Z.6)
        raise Refused(507, str(err), retry) from None
    except (OSError, MemoryError) as err:
        what = err.strerror if isinstance(err, OSError) and err.strerror else type(err).__name__
        log.warning("a job could not be stored: %r", err)
        raise Refused(503, f"the service cannot store a job now ({what}); try again later", retry) from None
    response.headers["Location"] = f"{request.scope.get('root_path', '')}/jobs/{job.id}"
    return JobCreated(id=job.id, status=job.status)  # type: ignore[arg-type]  # a Status, held as str


@api.post("/jobs/upload", status_code=201, response_model=JobCreated, openapi_extra=_UPLOAD_BODY,
          responses={400: {"description": "not UTF-8 JSON"}, 413: {"description": "too large, too deep, too many values"},
                     415: {"description": "not multipart/form-data"}, 503: {"description": "cannot store it now"}})
async def submit_upload(request: Request, response: Response, manager: Annotated[JobManager, Depends(get_manager)],
                        settings: Annotated[Settings, Depends(get_settings)],
                        intake: Annotated[Intake, Depends(get_intake)]) -> JobCreated:
    """Queue a job whose arrays come in an uploaded ``.npz`` (``input: npz:force``), its spec
    JSON or YAML: ``curl -F spec=@spec.yaml -F data=@x.npz`` or ``-F spec='{...}'``."""
    media_type(request, "multipart/form-data")
    async with intake.slot(), intake.upload():  # uploads one at a time: their arrays are the largest
        try:
            form = await request.form(max_files=4, max_fields=4, max_part_size=settings.max_request_bytes)
        except ClientDisconnect:
            raise HTTPException(408, "the body did not arrive") from None
        try:
            spec_part, data = form.get("spec"), form.get("data")
            if spec_part is None:
                raise problem(422, "spec", "missing: the job spec, JSON or YAML (-F spec=@spec.yaml)", "missing")
            if isinstance(spec_part, UploadFile):
                text, kind = await spec_part.read(), spec_kind(spec_part)
            else:
                text, kind = spec_part.encode("utf-8", "surrogatepass"), "any"
            spec, arrays = await intake.spec(text, "spec", kind, upload=True)  # in a child process
            del text
            if not isinstance(data, UploadFile):
                raise problem(422, "data", "missing: the arrays as an .npz file part (-F data=@x.npz)", "missing")
            arrays.update(await asyncio.to_thread(npz_arrays, data.file, spec, settings.max_array_samples))
        finally:
            await form.close()
        return await queue_job(manager, request, response, spec, arrays)


@api.get("/jobs", response_model=list[JobInfo])
def list_jobs(manager: Annotated[JobManager, Depends(get_manager)], status: Status | None = None) -> list[dict]:
    return [_finite(j.public()) for j in manager.list(status)]


@api.get("/jobs/{job_id}", response_model=JobInfo)
def job_status(job: Annotated[JobRecord, Depends(get_job)]) -> dict:
    """Status and the progress of the last complete population."""
    return _finite(job.public())


@api.get("/jobs/{job_id}/result", response_model=Summary)
def job_result(job: Annotated[JobRecord, Depends(get_job)], manager: Annotated[JobManager, Depends(get_manager)]):
    """The summary of docs/design.md, "The summary" (so far, while the job runs)."""
    result = manager.result(job)
    if result is None:
        raise HTTPException(404, f"job {job.id} has no population yet ({job.status})")
    return JSONResponse(_finite({**result, "status": job.status}))


@api.get("/jobs/{job_id}/populations/{t}", response_model=PopulationOut)
def job_population(
    job: Annotated[JobRecord, Depends(get_job)],
    t: Annotated[int, Path(ge=1, le=1_000_000)],
    offset: Annotated[int, Query(ge=0, description="the first particle of the page")] = 0,
    limit: Annotated[int, Query(ge=1, le=PAGE_MAX, description=f"particles in the page (at most {PAGE_MAX})")] = PAGE_MAX,
) -> dict:
    """The particles ``offset .. offset + limit - 1`` of population t (read from the store
    alone: one page never reads the whole population)."""
    try:
        store = Store.open(job.store_path)
        attrs = store.attrs
        if t > int(attrs["n_populations"]):
            raise HTTPException(404, f"job {job.id} has {attrs['n_populations']} complete populations")
        n = int(attrs["n_particles"])
        rows = slice(min(offset, n), min(offset + limit, n))
        page_ = store.page(t, rows)
        scalar, probs = page_, page_["model_probability"]
    except (StoreError, FileNotFoundError):
        raise HTTPException(404, f"job {job.id} has no population yet") from None
    return _finite({
        "t": t, "epsilon": scalar["epsilon"], "epsilon_next": scalar["epsilon_next"],
        "acceptance_rate": scalar["n_accepted"] / scalar["n_simulations"] if scalar["n_simulations"] else 0.0,
        "n_simulations": scalar["n_simulations"], "n_particles": n, "offset": rows.start,
        "model_names": attrs["model_names"], "parameter_names": attrs["parameter_names"],
        "model_probabilities": probs.tolist(), "models": page_["model_index"].tolist(), "theta": page_["theta"].tolist(),
        "distances": page_["distance"].tolist(), "weights": page_["weight"].tolist(),
    })


@api.delete("/jobs/{job_id}", response_model=JobInfo, status_code=202,
            responses={204: {"description": "purged"}, 409: {"description": "already ended (cancel) or not ended (purge)"}})
def cancel_or_purge(
    job: Annotated[JobRecord, Depends(get_job)], manager: Annotated[JobManager, Depends(get_manager)],
    purge: Annotated[bool, Query(description="delete an ended job and its folder (store, events, data)")] = False,
):
    """Cancel (``202``): a queued job never starts, a running one stops between batches; what
    was done stays in the store; 409 for a job that has already ended. With
    ``?purge=true``: delete an ended job and everything of it (``204``); 409 while it runs,
    404 once it is gone (the second of two purges at once included)."""
    if purge:
        if not manager.purge(job.id):
            if manager.get(job.id) is None:  # purged meanwhile, by a request beside this one
                raise HTTPException(404, f"no job {job.id}")
            raise HTTPException(409, f"job {job.id} has not ended ({job.status}): cancel it first")
        return Response(status_code=204)
    if job.status in ("finished", "failed", "cancelled"):
        raise HTTPException(409, f"job {job.id} has already ended ({job.status})")
    return JSONResponse(_finite(manager.cancel(job.id).public()), status_code=202)


LAST_EVENT_ID = re.compile(r"[0-9]{1,18}")


def event_start(
    last_event_id: Annotated[str | None, Header(alias="Last-Event-ID")] = None,
    after: Annotated[int | None, Query(ge=0, le=10**18, description="like Last-Event-ID")] = None,
) -> int:
    """The id to resume after: Last-Event-ID (400 unless digits) or ?after=."""
    if last_event_id is None:
        return after or 0
    if not LAST_EVENT_ID.fullmatch(last_event_id.strip()):
        raise HTTPException(400, "Last-Event-ID must be an event id (up to 18 digits)")
    return int(last_event_id.strip())


def sse_bytes(e: dict) -> bytes:
    """One event as a server-sent event (made once per event for all of a job's streams)."""
    return format_sse_event(data_str=json.dumps(_finite(e["data"]), separators=(",", ":")), event=e["event"],
                            id=str(e["id"]))


@api.get("/jobs/{job_id}/events", response_class=StreamingResponse, responses={
    200: {"description": "server-sent events", "content": {"text/event-stream": {"schema": {"type": "string"}}}},
    400: {"description": "bad Last-Event-ID"}})
async def job_events(
    job: Annotated[JobRecord, Depends(get_job)],
    manager: Annotated[JobManager, Depends(get_manager)],
    start: Annotated[int, Depends(event_start)],
) -> StreamingResponse:
    """Server-sent events: queued, started, one ``population`` per finished population, then
    finished / failed / cancelled. Reconnect with ``Last-Event-ID`` to get what was missed;
    on an ended job the stream ends at once after what is left.

    Streamed as it is (a keep-alive comment every 15 s of silence comes from the log's
    follower), not through FastAPI's own server-sent events, whose keep-alive task raised
    anyio.BrokenResourceError into uvicorn's error log each time a client went away: a
    client that goes away is the normal end of a stream, logged at debug level."""

    async def stream() -> AsyncIterator[bytes]:
        try:
            async for chunk in job.log.follow(start, manager.closing, sse_bytes):
                yield format_sse_event(comment="keep-alive") if chunk is None else chunk
        except (asyncio.CancelledError, GeneratorExit, OSError, anyio.BrokenResourceError, ClientDisconnect):
            log.debug("the event stream of job %s closed by its client", job.id)
            raise

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


# ---------------------------------------------------------------------------- studies (docs/studies.md)
STUDY_ID = Annotated[str, Path(pattern="^[0-9a-f]{32}$", description="a study id (32 hex digits)")]


@api.post("/studies", status_code=201, responses={422: {"description": "the spec or the study is invalid"},
                                                   429: {"description": "the queue cannot take every data set"}})
async def submit_study(request: Request, response: Response, manager: Annotated[JobManager, Depends(get_manager)],
                       intake: Annotated[Intake, Depends(get_intake)]) -> dict:
    """A study: ``{"spec": {...}, "datasets": N, "noise_std": X | "noise_share": F, "truth": MODEL,
    "truth_parameters": {NAME: VALUE}, "seed": S}``; each data set queued as a job. 422 naming
    the field (nothing queued)."""
    from service.http.studies import submit_study as submit_it
    from service.run.study import parse_request

    media_type(request, "application/json")
    retry = {"Retry-After": str(request.app.state.settings.retry_after_s)}
    async with intake.slot():
        spec, arrays, rest = await intake.study(await read_body(request))  # in a child process
        try:
            study = parse_request(rest)
        except SpecError as err:
            raise spec_error(err) from None
        try:
            study_id = await asyncio.to_thread(submit_it, manager, spec, arrays, study)
        except SpecError as err:
            raise spec_error(err) from None
        except QueueFull as err:
            raise HTTPException(429, str(err), headers=retry) from None
        except (OSError, MemoryError) as err:  # a full disk: nothing was queued
            log.warning("a study could not be stored: %r", err)
            raise Refused(503, "the service cannot store a study now; try again later", retry) from None
    response.headers["Location"] = f"{request.scope.get('root_path', '')}/studies/{study_id}"
    return {"id": study_id, "datasets": study.datasets}


@api.get("/studies/{study_id}")
def study_status(study_id: STUDY_ID, manager: Annotated[JobManager, Depends(get_manager)]) -> JSONResponse:
    """The study's progress (its jobs' statuses) and its report over the jobs finished so far."""
    from service.http.studies import study_status as status_of

    out = status_of(manager, study_id)
    if out is None:
        raise HTTPException(404, f"no study {study_id}")
    return JSONResponse(_finite(out))


public = APIRouter()


@public.get("/health", response_model=Health)
@public.head("/health", response_model=Health, include_in_schema=False)
async def health(request: Request, manager: Annotated[JobManager, Depends(get_manager)]) -> Health:
    """Never waits for anything: the job counts and the workers as last seen (every 2 s),
    and the admission limits."""
    return Health(status="ok", workers=request.app.state.workers, jobs=manager.counts(), limits=limits_of(request),
                  running_on=manager.running_on(), utilization=manager.utilization(request.app.state.workers))


def limits_of(request: Request) -> dict:
    settings = request.app.state.settings
    running = {} if settings.max_running is None else {"max_running": settings.max_running}  # unset: one per worker
    return {**settings.limits.public(), "max_queued": settings.max_queued, **running,
            "max_request_bytes": settings.max_request_bytes, "max_array_samples": settings.max_array_samples,
            "max_json_values": settings.max_json_values}


@public.get("/limits", response_model=LimitsOut)
def limits(request: Request) -> dict:
    """The admission limits a job is checked against (422 naming the field when over one)."""
    return limits_of(request)


def html(text: str, csp: str) -> HTMLResponse:
    return HTMLResponse(text, headers={"Content-Security-Policy": csp, "X-Content-Type-Options": "nosniff",
                                       "Referrer-Policy": "no-referrer", "X-Frame-Options": "DENY"})


@public.api_route("/", methods=["GET", "HEAD"], response_class=HTMLResponse, include_in_schema=False)
def index() -> HTMLResponse:
    return html(page.INDEX, page.CSP)


@public.api_route("/jobs/{job_id}/view", methods=["GET", "HEAD"], response_class=HTMLResponse, include_in_schema=False)
def view(job_id: JOB_ID) -> HTMLResponse:
    return html(page.VIEW, page.CSP)


@public.api_route("/favicon.ico", methods=["GET", "HEAD"], include_in_schema=False)
def favicon() -> Response:
    """The pages' icon (a browser asks for it on every page: no 404 in its console)."""
    return Response(page.FAVICON, media_type="image/svg+xml",
                    headers={"Cache-Control": "max-age=86400", "X-Content-Type-Options": "nosniff"})


@public.api_route("/studies/{study_id}/view", methods=["GET", "HEAD"], response_class=HTMLResponse,
                  include_in_schema=False)
def study_view(study_id: STUDY_ID) -> HTMLResponse:
    """A study's progress and its confusion matrix filling in (polls GET /studies/{id})."""
    return html(page.STUDY, page.STUDY_CSP)


# ---------------------------------------------------------------------------- API docs, offline
# Swagger UI from the swagger-ui-bundle-v2 wheel: its files served here, nothing from a CDN
DOCS_ASSETS = {"swagger-ui.css": "text/css", "swagger-ui-bundle.js": "text/javascript", "favicon-32x32.png": "image/png"}


@public.get("/docs", response_class=HTMLResponse, include_in_schema=False)
def docs() -> HTMLResponse:
    return html(page.DOCS, page.DOCS_CSP)


@public.get("/docs/assets/{name}", include_in_schema=False)
def docs_asset(name: str) -> FileResponse:
    if name not in DOCS_ASSETS:
        raise HTTPException(404, f"no asset {name}")
    from swagger_ui_bundle import swagger_ui_path

    return FileResponse(FilePath(swagger_ui_path) / name, media_type=DOCS_ASSETS[name],
                        headers={"Cache-Control": "max-age=86400", "X-Content-Type-Options": "nosniff"})


# ---------------------------------------------------------------------------- the app
def _connect(settings: Settings) -> tuple[Client, LocalCluster | None]:
    if settings.scheduler:
        return Client(settings.scheduler, timeout=30), None
    cluster = local_cluster(settings.workers or os.cpu_count() or 1)
    return Client(cluster), cluster


def count_workers(client: Client) -> int:
    return len(scheduler_identity(client).get("workers", {}))


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        app.state.intake = intake = Intake(settings.max_submissions, settings.max_json_values)
        intake.start()  # the children that parse and validate bodies import their modules meanwhile
        client, cluster = await asyncio.to_thread(_connect, settings)
        manager = await asyncio.to_thread(JobManager, settings.store_dir, client, settings.max_running,
                                          asyncio.get_running_loop(), settings.max_resumes, settings.limits,
                                          settings.max_queued, settings.scheduler, settings.turn_s,
                                          settings.disk_reserve_mb)
        app.state.client, app.state.manager = client, manager
        app.state.workers = await asyncio.to_thread(count_workers, client)

        async def watch_workers() -> None:
            while True:
                await asyncio.sleep(2.0)
                try:  # the manager's client: a new one when the old gave up on a restarted scheduler
                    app.state.workers = await asyncio.to_thread(count_workers, manager.client)
                except Exception:
                    app.state.workers = 0

        watcher = asyncio.create_task(watch_workers())
        try:
            yield
        finally:
            watcher.cancel()
            intake.close()
            await asyncio.to_thread(manager.shutdown, settings.shutdown_timeout_s)
            await asyncio.to_thread(client.close)
            if manager.client is not client:
                await asyncio.to_thread(manager.client.close)
            if cluster is not None:
                await asyncio.to_thread(cluster.close)

    app = FastAPI(title="abcns", version=abcns.__version__, lifespan=lifespan, max_body_size=settings.max_request_bytes,
                  docs_url=None, redoc_url=None,
                  description="ABC-NS model selection and parameter estimation jobs for dynamical systems.")
    app.state.settings = settings
    # starlette types a handler as taking any Exception; these take the class they handle
    app.add_exception_handler(RequestValidationError, on_validation_error)  # type: ignore[arg-type]
    app.add_exception_handler(Refused, on_refused)  # type: ignore[arg-type]
    app.include_router(public)
    app.include_router(api)
    schema = app.openapi

    def openapi() -> dict:
        """The schema, with the job spec the two submit routes read themselves."""
        if app.openapi_schema is None:
            out = schema()
            spec = JobSpec.model_json_schema(ref_template="#/components/schemas/{model}")
            defs = spec.pop("$defs", {})
            out.setdefault("components", {}).setdefault("schemas", {}).update({**defs, "JobSpec": spec})
            app.openapi_schema = out
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]  # FastAPI's documented way to extend its schema
    return app


def begin_shutdown(app: FastAPI) -> None:
    """SIGTERM: end the event streams and stop the jobs at once (before uvicorn waits for
    open connections); called from the signal handler, so only scheduled here."""
    manager = getattr(app.state, "manager", None)
    if manager is not None and manager.loop is not None and not manager.loop.is_closed():
        manager.loop.call_soon_threadsafe(manager.begin_shutdown)
