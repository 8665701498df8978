"""The batch evaluator under the name earlier versions of the README gave it
(``from worker.evaluate import evaluator``). It lives in :mod:`worker.compose`; the JSON
description is parsed in :mod:`worker.description` and the Dask tasks are in
:mod:`worker.tasks`."""

from worker.compose import evaluator

__all__ = ["evaluator"]
