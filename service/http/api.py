"""The HTTP job service: settings -> dependencies -> routers -> schemas.

``create_app(settings)`` builds the FastAPI app; its lifespan connects the Dask client (a
scheduler address, or an embedded LocalCluster) and starts the job manager. Only registry
simulators are accepted over HTTP (no code over the wire), data come inline or as an
uploaded ``.npz``, job ids are checked against ``[0-9a-f]{32}`` so no path leaves the store
directory, and with a token every API request needs ``Authorization: Bearer TOKEN``.

A submitted body is read only once the token has been checked, and checked in this order:
its media type (415), JSON (400), every string valid Unicode text and every number finite,
the job's and models' names (422 naming the field), the schema (422, ``detail[i].field``
a dotted path), then everything the spec builder checks; an upload's arrays are read only
when the spec names them, and only after their declared shape and dtype passed. Every 422
shows the offending value as text. The pages carry a strict Content-Security-Policy.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import math
import os
import re
import unicodedata
import zipfile
from collections.abc import AsyncIterable
from contextlib import asynccontextmanager
from pathlib import Path as FilePath
from typing import IO, Annotated, Any

import numpy as np
from distributed import Client, LocalCluster
from fastapi import APIRouter, Depends, FastAPI, Header, HTTPException, Path, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from fastapi.sse import EventSourceResponse, ServerSentEvent
from pydantic import ValidationError
from starlette.datastructures import UploadFile
from starlette.requests import ClientDisconnect

from abcns import SpecError
from service.http import page
from service.http.jobs import JobManager, JobRecord, QueueFull, clean_text
from service.http.schemas import NAME_MAX_CHARS, PAGE_MAX, Health, JobCreated, JobInfo, PopulationOut, Status, Summary
from service.http.settings import Settings
from service.run.dask_executor import local_cluster
from service.run.store import Store, StoreError
from service.spec import JobSpec, _field, spec_loc

JOB_ID = Annotated[str, Path(pattern="^[0-9a-f]{32}$", description="a job id (32 hex digits)")]
_bearer = HTTPBearer(auto_error=False)
TEXT_MAX = 200  # characters of an offending value shown in a 422


# ---------------------------------------------------------------------------- errors
def problem(status: int, field: str, msg: str, kind: str, value: Any = None) -> HTTPException:
    """An error naming the field: ``detail[0].field`` (``sampler.particles``, ``models[0].name``)."""
    field = clean_text(field)  # a key may be what is wrong
    loc = ["body", *[p for p in re.split(r"[.\[\]]+", field) if p]]
    item = {"loc": loc, "field": field, "msg": msg, "type": kind}
    if value is not None:
        item["input"] = as_text(value)
    return HTTPException(status, [item])


def spec_error(err: SpecError) -> HTTPException:
    return problem(422, err.field, err.message, "spec")


def as_text(value: Any) -> str:
    """A value as a short text: NaN and Infinity included, long values cut."""
    if isinstance(value, str):
        text = value
    elif isinstance(value, float) and not math.isfinite(value):
        text = "NaN" if math.isnan(value) else ("Infinity" if value > 0 else "-Infinity")
    else:
        try:
            text = json.dumps(value, default=str)
        except ValueError:  # NaN inside a container
            text = repr(value)
    text = clean_text(text)
    return text if len(text) <= TEXT_MAX else text[:TEXT_MAX] + f"... ({len(text)} characters)"


def validation_errors(errors: Any) -> list[dict]:
    """pydantic's errors with ``field`` (the dotted path) and the input as text."""
    out = []
    for e in errors:
        loc = [p if isinstance(p, int | str) else str(p) for p in e.get("loc", ())]
        where = loc[:1] if loc and loc[0] in ("body", "query", "path", "header", "cookie") else []
        path = list(spec_loc(tuple(loc[len(where):])))  # sampler.alpha, not sampler.abc-ns.alpha
        loc = where + path
        item = {"loc": [clean_text(p) if isinstance(p, str) else p for p in loc],
                "field": clean_text(_field(tuple(path)) or (str(loc[0]) if loc else "")),
                "msg": clean_text(str(e.get("msg"))), "type": str(e.get("type"))}
        if "input" in e:
            item["input"] = as_text(e["input"])
        out.append(item)
    return out


async def on_validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    return JSONResponse({"detail": validation_errors(exc.errors())}, status_code=422)


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


def parse_json(body: bytes, field: str) -> Any:
    """JSON text -> value; 400 for anything that is not UTF-8 JSON (or nests too deeply)."""
    try:
        return json.loads(body.decode("utf-8"))
    except UnicodeDecodeError as err:
        raise HTTPException(400, f"{field}: not UTF-8 ({err.reason} at byte {err.start})") from None
    except json.JSONDecodeError as err:
        raise HTTPException(400, f"{field}: not JSON: {err}") from None
    except RecursionError:
        raise HTTPException(400, f"{field}: nested too deeply") from None


def _walk(x: Any, path: tuple = ()):
    yield path, x
    if isinstance(x, dict):
        for k, v in x.items():
            yield (*path, k), k  # the key itself
            yield from _walk(v, (*path, k))
    elif isinstance(x, list):
        for i, v in enumerate(x):
            yield from _walk(v, (*path, i))


def check_input(raw: Any) -> None:
    """Every string Unicode text (a lone surrogate is valid JSON but no text), every number
    finite (JSON has no NaN or Infinity), and the names short text without control
    characters; 422 naming the field."""
    for path, v in _walk(raw):
        if isinstance(v, str):
            try:
                v.encode("utf-8")
            except UnicodeEncodeError:
                raise problem(422, _field(path) or "body", "not valid Unicode text (a lone surrogate)", "text",
                              v) from None
        elif isinstance(v, float) and not math.isfinite(v):
            raise problem(422, _field(path) or "body", "must be a finite number (JSON has no NaN or Infinity)",
                          "finite_number", v)
    if not isinstance(raw, dict):
        return
    names = [("name", raw.get("name"))]
    if isinstance(raw.get("models"), list):
        names += [(f"models[{i}].name", m.get("name")) for i, m in enumerate(raw["models"]) if isinstance(m, dict)]
    for field, name in names:
        if not isinstance(name, str):
            continue  # the schema says what is wrong
        if len(name) > NAME_MAX_CHARS:
            raise problem(422, field, f"at most {NAME_MAX_CHARS} characters, got {len(name)}", "name", name)
        bad = next((c for c in name if unicodedata.category(c) == "Cc"), None)
        if bad is not None:
            raise problem(422, field, f"must not hold control characters (found U+{ord(bad):04X})", "name", name)


def validate_spec(raw: Any) -> JobSpec:
    if not isinstance(raw, dict):
        raise problem(422, "body", "the job spec must be a JSON object", "json", raw)
    check_input(raw)
    try:
        return JobSpec.model_validate(raw)
    except ValidationError as err:
        raise RequestValidationError([{**e, "loc": ("body", *e["loc"])} for e in err.errors()]) from None


def inline_arrays(spec: JobSpec) -> dict[str, np.ndarray]:
    """The inline data of a spec as arrays; a string (a file name) is refused."""
    out = {}
    for key in ("input", "observed"):
        value = getattr(spec.data, key)
        if isinstance(value, str):
            raise problem(422, f"data.{key}", "files are not allowed here; give the data inline", "spec", value)
        if value is not None:
            out[key] = np.asarray(value, dtype=float)
    return out


def npz_array(file: IO[bytes], name: str, field: str, max_samples: int) -> np.ndarray:
    """One array of an uploaded .npz: its npy header (shape, dtype) is read and checked
    against ``max_samples`` before its data are decompressed."""
    try:
        archive = zipfile.ZipFile(file)
    except (zipfile.BadZipFile, OSError, ValueError) as err:
        raise problem(422, "data", f"not a readable .npz (a zip of .npy files): {err}", "npz") from None
    with archive:
        members = {m[:-4]: m for m in archive.namelist() if m.endswith(".npy")}
        if name not in members:
            raise problem(422, field, f"the upload has no array {name!r}; it has {sorted(members)[:20]}", "npz")
        try:
            with archive.open(members[name]) as f:
                version = np.lib.format.read_magic(f)
                read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shape, _, dtype = read_header(f)
                size = math.prod(shape)
                if dtype.hasobject or dtype.kind not in "biuf":
                    raise problem(422, field, f"the array {name!r} has dtype {dtype}; numbers only", "npz")
                if size > max_samples:
                    raise problem(422, field, f"the array {name!r} has shape {shape} ({size} samples); the limit is "
                                              f"{max_samples} samples", "npz")
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
            raise problem(422, field, f"the array {name!r} is not a readable .npy: {err}", "npz") from None
        try:
            with archive.open(members[name]) as f:
                return np.asarray(np.lib.format.read_array(f, allow_pickle=False), dtype=float)
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
            raise problem(422, field, f"the array {name!r} is not a readable .npy: {err}", "npz") from None


# ---------------------------------------------------------------------------- routers
api = APIRouter(dependencies=[Depends(check_token)])

_JOB_BODY = {"requestBody": {"required": True, "content": {
    "application/json": {"schema": {"$ref": "#/components/schemas/JobSpec"}}}}}
_UPLOAD_BODY = {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
    "type": "object", "required": ["spec", "data"],
    "properties": {
        "spec": {"type": "string", "description": "the job spec as JSON (a text field or a file part); data fields "
                                                  "may name 'npz:KEY' of the file"},
        "data": {"type": "string", "format": "binary", "description": "an .npz file with the arrays"}}}}}}}


@api.post("/jobs", status_code=201, response_model=JobCreated, openapi_extra=_JOB_BODY,
          responses={400: {"description": "not UTF-8 JSON"}, 415: {"description": "not application/json"}})
async def submit(request: Request, manager: Annotated[JobManager, Depends(get_manager)]) -> JobCreated:
    """Queue a job. Data inline; only registry simulators; invalid specs -> 422 naming the field."""
    media_type(request, "application/json")
    spec = validate_spec(parse_json(await read_body(request), "body"))
    return await queue_job(manager, request, spec, inline_arrays(spec))


async def queue_job(manager: JobManager, request: Request, spec: JobSpec, arrays: dict[str, np.ndarray]) -> JobCreated:
    """Validated against the service's limits and queued; 422 naming the field, 429 when the queue is full."""
    try:
        job = await asyncio.to_thread(manager.submit, spec, arrays)
    except SpecError as err:
        raise spec_error(err) from None
    except QueueFull as err:
        retry = str(request.app.state.settings.retry_after_s)
        raise HTTPException(429, str(err), headers={"Retry-After": retry}) from None
    return JobCreated(id=job.id, status=job.status)  # type: ignore[arg-type]


@api.post("/jobs/upload", status_code=201, response_model=JobCreated, openapi_extra=_UPLOAD_BODY,
          responses={400: {"description": "not UTF-8 JSON"}, 415: {"description": "not multipart/form-data"}})
async def submit_upload(request: Request, manager: Annotated[JobManager, Depends(get_manager)],
                        settings: Annotated[Settings, Depends(get_settings)]) -> JobCreated:
    """Queue a job whose arrays come in an uploaded ``.npz`` (``input: npz:force``):
    ``curl -F spec=@spec.json -F data=@x.npz`` or ``-F spec='{...}'``."""
    media_type(request, "multipart/form-data")
    try:
        form = await request.form(max_files=4, max_fields=4, max_part_size=settings.max_request_bytes)
    except ClientDisconnect:
        raise HTTPException(408, "the body did not arrive") from None
    try:
        spec_part, data = form.get("spec"), form.get("data")
        if spec_part is None:
            raise problem(422, "spec", "missing: the job spec as JSON (-F spec=@spec.json)", "missing")
        text = await spec_part.read() if isinstance(spec_part, UploadFile) else spec_part.encode("utf-8", "surrogatepass")
        spec = validate_spec(parse_json(text, "spec"))
        if not isinstance(data, UploadFile):
            raise problem(422, "data", "missing: the arrays as an .npz file part (-F data=@x.npz)", "missing")
        arrays = {}
        for key in ("input", "observed"):
            value = getattr(spec.data, key)
            if isinstance(value, str):
                if not value.startswith("npz:"):
                    raise problem(422, f"data.{key}", "give the data inline or as npz:KEY of the upload", "spec", value)
                arrays[key] = await asyncio.to_thread(npz_array, data.file, value[4:], f"data.{key}",
                                                      settings.max_array_samples)
            elif value is not None:
                arrays[key] = np.asarray(value, dtype=float)
    finally:
        await form.close()
    return await queue_job(manager, request, spec, arrays)


@api.get("/jobs", response_model=list[JobInfo])
def list_jobs(manager: Annotated[JobManager, Depends(get_manager)], status: Status | None = None) -> list[dict]:
    return [_finite(j.public()) for j in manager.list(status)]


@api.get("/jobs/{job_id}", response_model=JobInfo)
def job_status(job: Annotated[JobRecord, Depends(get_job)]) -> dict:
    """Status and the progress of the last complete population."""
    return _finite(job.public())


@api.get("/jobs/{job_id}/result", response_model=Summary)
def job_result(job: Annotated[JobRecord, Depends(get_job)], manager: Annotated[JobManager, Depends(get_manager)]):
    """The summary of DESIGN.md (so far, while the job runs)."""
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
    ``?purge=true``: delete an ended job and everything of it (``204``); 409 while it runs."""
    if purge:
        if not manager.purge(job.id):
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


@api.get("/jobs/{job_id}/events", response_class=EventSourceResponse, responses={400: {"description": "bad Last-Event-ID"}})
async def job_events(
    job: Annotated[JobRecord, Depends(get_job)],
    manager: Annotated[JobManager, Depends(get_manager)],
    start: Annotated[int, Depends(event_start)],
) -> AsyncIterable[ServerSentEvent]:
    """Server-sent events: queued, started, one ``population`` per finished population, then
    finished / failed / cancelled. Reconnect with ``Last-Event-ID`` to get what was missed;
    on an ended job the stream ends at once after what is left."""
    async for e in job.events.follow(start, manager.closing):  # type: ignore[union-attr]
        if e is None:
            yield ServerSentEvent(comment="keep-alive")
        else:
            yield ServerSentEvent(data=_finite(e["data"]), event=e["event"], id=str(e["id"]))


public = APIRouter()


@public.get("/health", response_model=Health)
@public.head("/health", response_model=Health, include_in_schema=False)
async def health(request: Request, manager: Annotated[JobManager, Depends(get_manager)]) -> Health:
    """Never waits for anything: the job counts and the workers as last seen (every 2 s),
    and the admission limits."""
    return Health(status="ok", workers=request.app.state.workers, jobs=manager.counts(), limits=limits_of(request))


def limits_of(request: Request) -> dict:
    settings = request.app.state.settings
    return {**settings.limits.public(), "max_queued": settings.max_queued, "max_running": settings.max_running,
            "max_request_bytes": settings.max_request_bytes, "max_array_samples": settings.max_array_samples}


@public.get("/limits")
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
    return len(client.scheduler_info(n_workers=-1).get("workers", {}))


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        client, cluster = await asyncio.to_thread(_connect, settings)
        manager = await asyncio.to_thread(JobManager, settings.store_dir, client, settings.max_running,
                                          asyncio.get_running_loop(), settings.max_resumes, settings.limits,
                                          settings.max_queued, settings.scheduler)
        app.state.client, app.state.manager = client, manager
        app.state.workers = await asyncio.to_thread(count_workers, client)

        async def watch_workers() -> None:
            while True:
                await asyncio.sleep(2.0)
                try:  # the manager's client: a new one when the old gave up on a restarted scheduler
                    app.state.workers = await asyncio.to_thread(count_workers, manager.client)
                except Exception:  # noqa: BLE001 - no scheduler now: no workers
                    app.state.workers = 0

        watcher = asyncio.create_task(watch_workers())
        try:
            yield
        finally:
            watcher.cancel()
            await asyncio.to_thread(manager.shutdown, settings.shutdown_timeout_s)
            await asyncio.to_thread(client.close)
            if manager.client is not client:
                await asyncio.to_thread(manager.client.close)
            if cluster is not None:
                await asyncio.to_thread(cluster.close)

    app = FastAPI(title="abcns", version="0.1.0", lifespan=lifespan, max_body_size=settings.max_request_bytes,
                  docs_url=None, redoc_url=None,
                  description="ABC-NS model selection and parameter estimation jobs for dynamical systems.")
    app.state.settings = settings
    app.add_exception_handler(RequestValidationError, on_validation_error)  # type: ignore[arg-type]
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

    app.openapi = openapi  # type: ignore[method-assign]
    return app


def begin_shutdown(app: FastAPI) -> None:
    """SIGTERM: end the event streams and stop the jobs at once (before uvicorn waits for
    open connections); called from the signal handler, so only scheduled here."""
    manager = getattr(app.state, "manager", None)
    if manager is not None and manager.loop is not None and not manager.loop.is_closed():
        manager.loop.call_soon_threadsafe(manager.begin_shutdown)
