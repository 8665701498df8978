"""The Dask tasks' per-process evaluator cache (worker.tasks): one build per job, however
many of a worker's threads ask for it at once; the jobs used last are kept."""

import threading
import time
from collections import OrderedDict

import pytest

from worker import tasks


@pytest.fixture
def builds(monkeypatch) -> list:
    """An empty cache and a slow stand-in for job_evaluator that records each build."""
    built: list = []

    def build(description, arrays, allow_import=False):
        built.append(description["job"])
        time.sleep(0.05)  # long enough for every other thread to ask meanwhile
        return [], object()

    monkeypatch.setattr(tasks, "_CACHE", OrderedDict())
    monkeypatch.setattr(tasks, "job_evaluator", build)
    return built


def payload(job: str) -> dict:
    return tasks.job_payload({"job": job}, {})


def test_threads_asking_for_one_job_at_once_build_its_evaluator_once(builds):
    n = 8
    barrier, got = threading.Barrier(n), [None] * n

    def ask(i: int) -> None:
        barrier.wait()
        got[i] = tasks.cached_evaluator("job", payload("job"))

    threads = [threading.Thread(target=ask, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert builds == ["job"]
    assert all(e is got[0] for e in got) and got[0] is not None


def test_the_jobs_used_last_are_kept(builds):
    first = tasks.cached_evaluator("0", payload("0"))
    for i in range(1, tasks._CACHE_SIZE):
        tasks.cached_evaluator(str(i), payload(str(i)))
    assert tasks.cached_evaluator("0", payload("0")) is first  # used again: now the newest
    tasks.cached_evaluator("new", payload("new"))  # one past the size: "1", the oldest, goes
    assert list(tasks._CACHE) == [*map(str, range(2, tasks._CACHE_SIZE)), "0", "new"]
    tasks.cached_evaluator("1", payload("1"))
    assert builds == [*map(str, range(tasks._CACHE_SIZE)), "new", "1"]
