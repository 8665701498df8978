"""Service settings (environment ``ABCNS_*`` or ``abcns serve`` options), created at app
start-up, never at import."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from service.http.limits import Limits


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="ABCNS_", extra="forbid", env_ignore_empty=True)

    store_dir: Path = Path("abcns-jobs")  # one folder per job: job.json, events.jsonl, store.zarr
    scheduler: str | None = None  # a Dask scheduler address; None: an embedded LocalCluster
    workers: int | None = Field(default=None, ge=1)  # LocalCluster worker processes (default: one per core)
    token: str | None = None  # with a token, every API request needs "Authorization: Bearer TOKEN"
    # jobs running at once, each its loop on a worker of its own; None (or ABCNS_MAX_RUNNING
    # empty): as many as the cluster has workers; the rest wait in the queue
    max_running: int | None = Field(default=None, ge=1)
    # a running job's turn: when jobs wait and every worker runs one, the job that has run
    # this long since it last started gives its worker back after its population (requeued)
    turn_s: float = Field(default=30.0, gt=0)
    max_request_bytes: int = Field(default=32 * 1024 * 1024, ge=1024)
    max_resumes: int = Field(default=1, ge=0)  # resumes of a job the service died under, before it is failed
    max_array_samples: int = Field(default=2**25, ge=1)  # samples of one uploaded array (32 Mi: 256 MiB as float64)
    max_submissions: int = Field(default=2, ge=1)  # submissions read, parsed and stored at once; the rest wait
    max_json_values: int = Field(default=4_000_000, ge=1000)  # JSON values in one body (a spec, inline data included)
    header_timeout_s: float = Field(default=5.0, gt=0)  # a request's headers must arrive within this
    body_timeout_s: float = Field(default=30.0, gt=0)  # and its body within this of its headers (else 408)
    min_body_rate: float = Field(default=8192.0, ge=0)  # bytes/s a body must average after body_grace_s (else 408); 0: none
    body_grace_s: float = Field(default=2.0, ge=0)
    shutdown_timeout_s: float = Field(default=10.0, gt=0)  # on SIGTERM: running jobs get this to stop between batches
    # admission limits (service/http/limits.py): a job over one is refused with 422 naming the field
    max_particles: int = Field(default=Limits.max_particles, ge=2)
    max_batch_size: int = Field(default=Limits.max_batch_size, ge=1)
    max_substeps: int = Field(default=Limits.max_substeps, ge=1)
    max_samples: int = Field(default=Limits.max_samples, ge=2)
    max_models: int = Field(default=Limits.max_models, ge=1)
    max_memory_mb: float = Field(default=Limits.max_memory_mb, gt=0)
    max_job_seconds: float = Field(default=Limits.max_job_seconds, gt=0)  # also the default budget of a job
    max_job_simulations: int = Field(default=Limits.max_job_simulations, ge=1)  # likewise
    max_queued: int = Field(default=64, ge=1)  # jobs waiting; beyond: 429 with Retry-After
    retry_after_s: int = Field(default=30, ge=1)
    disk_reserve_mb: float = Field(default=64.0, ge=0)  # left free on the job store's disk: beyond it, 507 / jobs wait

    @property
    def limits(self) -> Limits:
        return Limits(**{name: getattr(self, name) for name in Limits.__dataclass_fields__})
