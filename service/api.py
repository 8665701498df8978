"""The HTTP job service: settings -> dependencies -> routers -> schemas.

``create_app(settings)`` builds the FastAPI app; its lifespan connects the Dask client (a
scheduler address, or an embedded LocalCluster) and starts the job manager. Only registry
simulators are accepted over HTTP (no code over the wire), data come inline or as an
uploaded ``.npz``, job ids are checked against ``[0-9a-f]{32}`` so no path leaves the store
directory, and with a token every API request needs ``Authorization: Bearer TOKEN``.
"""

from __future__ import annotations

import asyncio
import hmac
import io
import json
import math
import os
from collections.abc import AsyncIterable
from contextlib import asynccontextmanager
from typing import Annotated, Any

import numpy as np
from distributed import Client, LocalCluster
from fastapi import APIRouter, Depends, FastAPI, File, Form, Header, HTTPException, Path, Query, Request, UploadFile
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from fastapi.sse import EventSourceResponse, ServerSentEvent

from abcns import SpecError
from service import page
from service.jobs import JobManager, JobRecord
from service.schemas import Health, JobCreated, JobInfo, PopulationOut, Status, Summary
from service.settings import Settings
from service.spec import JobSpec, parse
from service.store import Store, StoreError

JOB_ID = Annotated[str, Path(pattern="^[0-9a-f]{32}$", description="a job id (32 hex digits)")]
_bearer = HTTPBearer(auto_error=False)


# ---------------------------------------------------------------------------- dependencies
def get_manager(request: Request) -> JobManager:
    return request.app.state.manager


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


def spec_error(err: SpecError) -> HTTPException:
    loc = ["body", *err.field.replace("[", ".").replace("]", "").split(".")]
    return HTTPException(422, [{"loc": loc, "field": err.field, "msg": err.message, "type": "spec"}])


def _finite(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_finite(v) for v in x]
    return x


# ---------------------------------------------------------------------------- routers
api = APIRouter(dependencies=[Depends(check_token)])


@api.post("/jobs", status_code=201, response_model=JobCreated)
def submit(spec: JobSpec, manager: Annotated[JobManager, Depends(get_manager)]) -> JobCreated:
    """Queue a job. Data inline; only registry simulators; invalid specs -> 422 naming the field."""
    try:
        job = manager.submit(spec)
    except SpecError as err:
        raise spec_error(err) from None
    return JobCreated(id=job.id, status=job.status)  # type: ignore[arg-type]


@api.post("/jobs/upload", status_code=201, response_model=JobCreated)
async def submit_upload(
    manager: Annotated[JobManager, Depends(get_manager)],
    spec: Annotated[str, Form(description="the job spec as JSON; data fields may name 'npz:KEY' of the file")],
    data: Annotated[UploadFile, File(description="an .npz file with the arrays")],
) -> JobCreated:
    """Queue a job whose arrays come in an uploaded ``.npz`` (``input: npz:force``)."""
    try:
        raw = json.loads(spec)
    except json.JSONDecodeError as err:
        raise HTTPException(422, [{"loc": ["body", "spec"], "msg": f"not JSON: {err}", "type": "json"}]) from None
    if not isinstance(raw, dict):
        raise HTTPException(422, [{"loc": ["body", "spec"], "msg": "must be a JSON object", "type": "json"}])
    try:
        with np.load(io.BytesIO(await data.read()), allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError) as err:
        raise HTTPException(422, [{"loc": ["body", "data"], "msg": f"not a readable .npz: {err}", "type": "npz"}]) from None
    section = raw.get("data")
    if isinstance(section, dict):
        for key in ("input", "observed"):
            ref = section.get(key)
            if isinstance(ref, str) and ref.startswith("npz:"):
                name = ref[4:]
                if name not in arrays:
                    raise spec_error(SpecError(f"data.{key}", f"the upload has no array {name!r}; it has {sorted(arrays)}"))
                section[key] = np.asarray(arrays[name], dtype=float).ravel().tolist()
    try:
        job = await asyncio.to_thread(manager.submit, parse(raw))
    except SpecError as err:
        raise spec_error(err) from None
    return JobCreated(id=job.id, status=job.status)  # type: ignore[arg-type]


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
    result = manager.result(job) if job.status in ("finished", "failed", "cancelled") else None
    if result is None:
        try:
            from service.runner import summary

            result = summary(Store.open(job.store_path))
        except StoreError:
            raise HTTPException(404, f"job {job.id} has no population yet ({job.status})") from None
    return JSONResponse(_finite({**result, "status": job.status}))


@api.get("/jobs/{job_id}/populations/{t}", response_model=PopulationOut)
def job_population(job: Annotated[JobRecord, Depends(get_job)], t: Annotated[int, Path(ge=1, le=1_000_000)]) -> dict:
    try:
        store = Store.open(job.store_path)
    except StoreError:
        raise HTTPException(404, f"job {job.id} has no population yet") from None
    if t > store.n_populations:
        raise HTTPException(404, f"job {job.id} has {store.n_populations} complete populations")
    pop = store.population(t)
    names = [m["name"] for m in job.spec["models"]]
    return _finite({
        "t": pop.t, "epsilon": pop.epsilon, "epsilon_next": pop.epsilon_next, "acceptance_rate": pop.acceptance_rate,
        "n_simulations": pop.n_simulations, "model_names": names,
        "parameter_names": [list(m["priors"]) for m in job.spec["models"]],
        "model_probabilities": pop.model_probabilities.tolist(), "models": pop.models.tolist(),
        "theta": pop.theta.tolist(), "distances": pop.distances.tolist(), "weights": pop.weights.tolist(),
    })


@api.delete("/jobs/{job_id}", status_code=202, response_model=JobInfo)
def cancel(job: Annotated[JobRecord, Depends(get_job)], manager: Annotated[JobManager, Depends(get_manager)]) -> dict:
    """Cancel: a queued job never starts, a running one stops between batches; what was done
    stays in the store. 409 for a job that has already ended."""
    if job.status in ("finished", "failed", "cancelled"):
        raise HTTPException(409, f"job {job.id} has already ended ({job.status})")
    return _finite(manager.cancel(job.id).public())


@api.get("/jobs/{job_id}/events", response_class=EventSourceResponse)
async def job_events(
    job: Annotated[JobRecord, Depends(get_job)],
    last_event_id: Annotated[str | None, Header(alias="Last-Event-ID")] = None,
    after: Annotated[int | None, Query(ge=0, description="like Last-Event-ID")] = None,
) -> AsyncIterable[ServerSentEvent]:
    """Server-sent events: queued, started, one ``population`` per finished population, then
    finished / failed / cancelled. Reconnect with ``Last-Event-ID`` to get what was missed."""
    start = after or 0
    if last_event_id is not None and last_event_id.strip().isdigit():
        start = int(last_event_id.strip())
    async for e in job.events.follow(start):  # type: ignore[union-attr]
        if e is None:
            yield ServerSentEvent(comment="keep-alive")
        else:
            yield ServerSentEvent(data=_finite(e["data"]), event=e["event"], id=str(e["id"]))


public = APIRouter()


@public.get("/health", response_model=Health)
def health(request: Request, manager: Annotated[JobManager, Depends(get_manager)]) -> Health:
    counts: dict[str, int] = {}
    for j in manager.list():
        counts[j.status] = counts.get(j.status, 0) + 1
    workers = len(request.app.state.client.scheduler_info(n_workers=-1).get("workers", {}))
    return Health(status="ok", workers=workers, jobs=counts)


@public.get("/", response_class=HTMLResponse, include_in_schema=False)
def index() -> str:
    return page.INDEX


@public.get("/jobs/{job_id}/view", response_class=HTMLResponse, include_in_schema=False)
def view(job_id: JOB_ID) -> str:
    return page.VIEW


# ---------------------------------------------------------------------------- the app
def _connect(settings: Settings) -> tuple[Client, LocalCluster | None]:
    if settings.scheduler:
        return Client(settings.scheduler, timeout=30), None
    cluster = LocalCluster(n_workers=settings.workers or os.cpu_count() or 1, threads_per_worker=1, processes=True,
                           dashboard_address=None)
    return Client(cluster), cluster


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        client, cluster = await asyncio.to_thread(_connect, settings)
        manager = await asyncio.to_thread(JobManager, settings.store_dir, client, settings.max_running,
                                          asyncio.get_running_loop())
        app.state.client, app.state.manager = client, manager
        try:
            yield
        finally:
            await asyncio.to_thread(manager.shutdown)
            await asyncio.to_thread(client.close)
            if cluster is not None:
                await asyncio.to_thread(cluster.close)

    app = FastAPI(title="abcns", version="0.1.0", lifespan=lifespan, max_body_size=settings.max_request_bytes,
                  description="ABC-NS model selection and parameter estimation jobs for dynamical systems.")
    app.state.settings = settings
    app.include_router(public)
    app.include_router(api)
    return app
