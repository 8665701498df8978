"""Shared fixtures: real processes started as a user would (`dask scheduler`, `dask worker`,
`abcns serve`), on 127.0.0.1 only, stopped at the end."""

from __future__ import annotations

import os

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
