"""Shared fixtures: real processes started as a user would (`dask scheduler`, `dask worker`,
`abcns serve`), on 127.0.0.1 only, stopped at the end."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import httpx
import pytest
from http_helpers import settle

from benchmarks.harness import Service, StockCluster

# The tests' jobs are cheap: by default the runner would evaluate their populations after the
# first in its own process (service.run.dask_executor.LOCAL_POPULATION_S), and a test of the
# cluster (workers killed, resumed on another cluster, the same result on 1 or 3 workers)
# would no longer use it. So the suite keeps every population on the cluster (also in the
# `abcns serve` and `abcns run` processes it starts, which inherit this); the tests of
# tests/test_executor_contract.py that say so evaluate populations here, and one runs a job
# with the default.
os.environ.setdefault("ABCNS_LOCAL_POPULATION_S", "0")

# `httpx.get` and its kin build a client per call, and each client its TLS context (the CA
# bundle read and parsed): ~26 ms of CPU per request, though every request here is plain
# HTTP to 127.0.0.1; the tests' polls make thousands. One context, made once, serves them
# all (contexts are shared safely); the tests' requests are otherwise unchanged.
_ssl_context = functools.lru_cache(maxsize=None)(httpx._transports.default.create_ssl_context)
httpx._transports.default.create_ssl_context = _ssl_context

# The files that take longest (seconds of one pytest process, measured on the shared 2-core VM
# under load, 2026-11-29, less what issue X 5's cuts took from test_study and test_service_jobs;
# docs/benchmarks.md, "The test suite"). `make test` runs the files in
# two processes (`--dist loadfile --no-loadscope-reorder`), each taking the next file in
# collection order when it runs low: longest first, so that no long file starts near the end
# while the other process has nothing left (xdist's own order, most tests first, put the
# one-test files of a minute each last). Unlisted files follow, in their usual order. Only
# the order changes; a stale figure costs time, never a test. The container test (as root;
# 428 s at load 9, most of it dockerd, debootstrap and pip in the image, not this process)
# goes first: last, one process ran it alone for minutes after the other had finished.
LONG_FILES = {
    "test_container.py": 428, "test_http_hostile.py": 171, "test_http.py": 169, "test_distributed.py": 120, "test_paper.py": 118,
    "test_http_holds.py": 106, "test_study.py": 86, "test_many_jobs.py": 78, "test_plots.py": 70,
    "test_restoring.py": 62, "test_service_jobs.py": 62, "test_walkthrough.py": 61, "test_cli.py": 59,
    "test_chaos.py": 54, "test_browser.py": 53, "test_kernels.py": 50, "test_scale_benchmark.py": 48,
    "test_examples_analysis.py": 45, "test_examples.py": 44, "test_store.py": 38, "test_spec_property.py": 29,
    "test_closed_form.py": 25, "test_submit.py": 23, "test_http_z.py": 22, "test_cluster_model.py": 21,
    "test_http_z_holds.py": 20,
}


@pytest.hookimpl(tryfirst=True)  # before tests/reverse_order.py's, which then reverses this order
def pytest_collection_modifyitems(items: list) -> None:
    """The longest files first (:data:`LONG_FILES`); each file's tests in their own order."""
    gone = [name for name in LONG_FILES if not (Path(__file__).parent / name).is_file()]
    if gone:
        raise pytest.UsageError(f"tests/conftest.py's LONG_FILES names files that are not in tests/: {gone}")
    items.sort(key=lambda item: -LONG_FILES.get(item.path.name, 0))


@pytest.fixture
def private_cluster(tmp_path):
    """A stock cluster of the test's own (2 workers), for a test that kills, restarts or
    retires workers, or needs the cluster idle: nothing else runs on it."""
    c = StockCluster(tmp_path / "dask")
    yield c
    c.close()


@pytest.fixture
def stock_cluster(private_cluster):
    """The address of a :func:`private_cluster`."""
    return private_cluster.address


@pytest.fixture(scope="session")
def cluster(tmp_path_factory):
    """One stock cluster (2 workers) for the whole run, shared by the tests that submit
    independent jobs to it or only read it (its address, its workers' count and pids):
    none of them kills, restarts or retires a worker (those take ``private_cluster``), and
    no result depends on which cluster or worker computed it. Starting one costs ~4 s."""
    c = StockCluster(tmp_path_factory.mktemp("dask"))
    yield c
    c.close()


@pytest.fixture(scope="session")
def shared_service(cluster, tmp_path_factory):
    """One `abcns serve` on the shared cluster for the whole run, for the tests that only
    submit and read (through ``service``): starting one costs ~3.5 s."""
    s = Service(tmp_path_factory.mktemp("service") / "jobs", cluster.address)
    yield s
    s.close()


@pytest.fixture
def service(shared_service):
    """The shared service, reset around each test (``settle``): no job queued or running
    when the test starts, none of its own left moving after it; its store directory and
    log hold the jobs of earlier tests, so a test reads only its own jobs, or compares
    the job list before and after. A test that kills, restarts or stops its service,
    edits its store directory, reads its whole log, lists every job, or measures its
    memory from its start takes ``fresh`` instead."""
    settle(shared_service)
    yield shared_service
    settle(shared_service)


@pytest.fixture
def fresh(cluster, tmp_path):
    """A service of its own, on the shared cluster."""
    s = Service(tmp_path / "jobs", cluster.address)
    yield s
    s.close()
