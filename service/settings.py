"""Service settings (environment ``ABCNS_*`` or ``abcns serve`` options), created at app
start-up, never at import."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="ABCNS_", extra="forbid")

    store_dir: Path = Path("abcns-jobs")  # one folder per job: job.json, events.jsonl, store.zarr
    scheduler: str | None = None  # a Dask scheduler address; None: an embedded LocalCluster
    workers: int | None = Field(default=None, ge=1)  # LocalCluster worker processes (default: one per core)
    token: str | None = None  # with a token, every API request needs "Authorization: Bearer TOKEN"
    max_running: int = Field(default=1, ge=1)  # jobs running at once; the rest wait in the queue
    max_request_bytes: int = Field(default=32 * 1024 * 1024, ge=1024)
