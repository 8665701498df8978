"""HTTP response schemas (the request schema is the job spec, ``service.spec.JobSpec``)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel

Status = Literal["queued", "running", "finished", "failed", "cancelled"]


class Progress(BaseModel):
    population: int
    epsilon: float
    epsilon_next: float | None = None
    acceptance_rate: float
    simulations: int
    model_probabilities: dict[str, float]
    elapsed_s: float
    simulations_per_s: float | None = None


class JobInfo(BaseModel):
    id: str
    name: str | None
    status: Status
    created_at: float
    error: str | None = None
    progress: Progress | None = None


class JobCreated(BaseModel):
    id: str
    status: Status


class PopulationOut(BaseModel):
    t: int
    epsilon: float
    epsilon_next: float | None
    acceptance_rate: float
    n_simulations: int
    model_names: list[str]
    parameter_names: list[list[str]]
    model_probabilities: list[float]
    models: list[int]
    theta: list[list[float | None]]  # NaN padding as null
    distances: list[float]
    weights: list[float]


class Health(BaseModel):
    status: Literal["ok"]
    workers: int
    jobs: dict[str, int]


Summary = dict[str, Any]
