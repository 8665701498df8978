"""A pytest plugin that runs the collected tests in reverse order (modules, and the tests in
each): ``python -m pytest -p tests.reverse_order``. That the suite passes both ways shows that no
test depends on what an earlier one left (a shared cluster's or service's state, a file, a
compiled cache)."""

from __future__ import annotations


def pytest_collection_modifyitems(items: list) -> None:
    items.reverse()
