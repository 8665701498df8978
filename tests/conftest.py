"""Shared fixtures: real processes started as a user would (`dask scheduler`, `dask worker`,
`abcns serve`), on 127.0.0.1 only, stopped at the end."""

from __future__ import annotations

import pytest

from benchmarks.harness import StockCluster


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
