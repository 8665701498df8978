"""The Dask tasks of a job and the per-process cache of its evaluator.

:func:`job_payload` holds a job's description and data on the workers; :func:`anchor` is the
no-op that keeps a run's task group queued; :func:`evaluate_on_worker` runs a group of
draws. ``job_evaluator(description, arrays)`` builds a job's batch evaluator from its
description (:class:`worker.description.JobDescription`: :func:`worker.description.job_parts`, then
:func:`worker.compose.evaluator`); a worker builds it once per process and job and keeps it
in a small cache, which a lock guards (a Dask worker runs tasks on several threads).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict

from abcns.executor import Evaluate, pack_results, run_draw, unpack_draws
from abcns.priors import Model
from worker.compose import evaluator
from worker.description import JobDescription, job_parts


def job_evaluator(description: JobDescription, arrays: dict, allow_import: bool = False) -> tuple[list[Model], Evaluate]:
    """(models, evaluate) from a job description and its data (:func:`worker.description.job_parts`)."""
    models, simulators, distance = job_parts(description, arrays, allow_import)
    return models, evaluator(models, simulators, distance)


_CACHE: OrderedDict[str, Evaluate] = OrderedDict()
_CACHE_SIZE = 8
# held while a job's evaluator is looked up or built: the threads of one worker that ask for
# the same job at once build it once, and the cache's order is never changed by two at a time
_CACHE_LOCK = threading.Lock()


def job_payload(description: JobDescription, arrays: dict, allow_import: bool = False) -> dict:
    """The Dask task that holds a job's description and data on the workers.

    It is a task, not scattered data, on purpose: the scheduler keeps its inputs, so when
    every worker holding the result dies it is computed again and the batches that need it
    wait instead of failing. (Scattered data has no such lineage, and the scheduler's active
    memory manager drops the replicas that ``broadcast=True`` made.)"""
    return {"description": description, "arrays": arrays, "allow_import": allow_import}


def anchor(_: int) -> None:
    """A no-op task: the Dask executor holds a few of them as the first tasks of a run's task
    group (``service.run.dask_executor``), so the scheduler queues the run's batches. Here, in
    the module every batch task comes from, so a worker imports nothing else to run it."""


def evaluate_on_worker(job_key: str, payload: dict, draws: bytes) -> tuple[bytes, float]:
    """The Dask task: run consecutive draws of job ``job_key`` (``abcns.executor.pack_draws``;
    proposals drawn here, then simulated); return their results (``pack_results``: one bytes
    object, which Dask sends as it is) and the seconds it took.
    ``payload`` (the result of :func:`job_payload`, sent once per job) is turned into an
    evaluator once per worker process and kept for the job's later batches."""
    start = time.perf_counter()
    evaluate = cached_evaluator(job_key, payload)
    results = [run_draw(evaluate, draw) for draw in unpack_draws(draws)]
    return pack_results(results), time.perf_counter() - start


def cached_evaluator(job_key: str, payload: dict) -> Evaluate:
    """Job ``job_key``'s evaluator, built from ``payload`` (:func:`job_payload`) on its first
    use in this process and kept for the :data:`_CACHE_SIZE` jobs used last. Thread-safe: a
    thread that asks while another builds the same job's evaluator waits for that one (and
    one that asks for another job waits too: a build comes once per job and process)."""
    with _CACHE_LOCK:
        evaluate = _CACHE.get(job_key)
        if evaluate is not None:
            _CACHE.move_to_end(job_key)
            return evaluate
        _, evaluate = job_evaluator(payload["description"], payload["arrays"], payload.get("allow_import", False))
        _CACHE[job_key] = evaluate
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
        return evaluate
