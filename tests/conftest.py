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
def stock_cluster(tmp_path):
    cluster = StockCluster(tmp_path)
    yield cluster.address
    cluster.close()


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A stock cluster shared by the tests of one module."""
    c = StockCluster(tmp_path_factory.mktemp("dask"))
    yield c
    c.close()


@pytest.fixture(scope="module")
def module_service(cluster, tmp_path_factory):
    """One `abcns serve` on the module's cluster, for the module's tests that only submit and
    read (through ``service``): starting one costs ~2 s a test."""
    s = Service(tmp_path_factory.mktemp("service") / "jobs", cluster.address)
    yield s
    s.close()


@pytest.fixture
def service(module_service):
    """The module's service, reset around each test (``settle``): no job queued or running
    when the test starts, none of its own left moving after it. A test that kills, restarts
    or stops its service, edits its store directory, reads its whole log, or measures its
    memory from its start takes ``fresh`` instead."""
    settle(module_service)
    yield module_service
    settle(module_service)


@pytest.fixture
def fresh(cluster, tmp_path):
    """A service of its own, on the module's cluster."""
    s = Service(tmp_path / "jobs", cluster.address)
    yield s
    s.close()
