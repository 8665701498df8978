"""HTTP response schemas and limits (the request schema is the job spec, ``service.spec.JobSpec``)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel

NAME_MAX_CHARS = 200  # a job's or a model's name: Unicode text without control characters, at most this long
PAGE_MAX = 10_000  # particles in one page of GET /jobs/{id}/populations/{t}

Status = Literal["queued", "running", "finished", "failed", "cancelled"]


class ProgressOut(BaseModel):
    """A population event's data and a job's ``progress`` (service.run.runner.Progress is the
    in-process record it is made from)."""

    population: int
    epsilon: float
    epsilon_next: float | None = None
    acceptance_rate: float
    simulations: int
    model_probabilities: dict[str, float]  # by model name
    elapsed_s: float
    simulations_per_s: float | None = None
    noise_floor: float | None = None  # abcns.noise.Floor.floor after this population; null without a floor
    decision_tolerance: float | None = None  # the floor plus its spread: the answer is read at or above it
    workers: int | None = None  # the cluster's worker threads after this population (null in-process)
    efficiency: float | None = None  # their share of time on the run's simulations over the population


class JobInfo(BaseModel):
    id: str
    name: str | None
    models: list[str]
    status: Status
    created_at: str  # ISO 8601, UTC: 2026-11-24T10:31:02.512Z
    error: str | None = None
    progress: ProgressOut | None = None
    # where a running job's loop runs (service.run.jobs.place): worker, mode ("whole": its
    # simulations in that process; "spread": its batches over the cluster), what it cost
    placement: dict[str, Any] | None = None


class JobCreated(BaseModel):
    id: str
    status: Status


class PopulationOut(BaseModel):
    t: int
    epsilon: float
    epsilon_next: float | None
    acceptance_rate: float
    n_simulations: int
    n_particles: int  # in the population; this page holds particles offset .. offset + len(distances) - 1
    offset: int
    model_names: list[str]
    parameter_names: list[list[str]]
    model_probabilities: list[float]
    models: list[int]
    theta: list[list[float | None]]  # NaN padding as null
    distances: list[float]
    weights: list[float]


LimitsOut = dict[str, int | float]  # the admission limits: integers where the limit is one


class Health(BaseModel):
    status: Literal["ok"]
    workers: int
    jobs: dict[str, int]
    limits: LimitsOut  # the admission limits (GET /limits)
    running_on: dict[str, str] = {}  # a running job's id -> the worker its loop was given
    # the workers' share of time on the jobs' simulations over the last minute (null: no workers)
    utilization: float | None = None


Summary = dict[str, Any]
