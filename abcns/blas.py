"""One BLAS thread while a population iterator works.

The population step, the proposals and the bounds' geometry do linear algebra on tiny
matrices (a few parameters, a population's points), where a BLAS thread pool only spins:
on 16 cores, with numpy imported before anything set ``OPENBLAS_NUM_THREADS``, the runner
spent 1,418 µs of CPU per simulation instead of 110 (issue 24); on this project's 2-core
machine the default 2 threads make a serial §4.1 run take 5x its one-thread CPU time.
An environment variable only works when it is set before numpy is first imported, which a
Python-API user does not do; so the limit is set where the work runs, with threadpoolctl,
and only while it runs: :func:`limited` holds it across each step of a population
iterator (``next``), never across the caller's code between populations.

The limit is process-wide (OpenBLAS has one thread count per library). Several iterators
may run at once in one process (the HTTP service's jobs, each on its own thread), so it is
counted: the first to enter sets one thread, the last to leave restores what was there.
The :class:`threadpoolctl.ThreadpoolController` (which scans the loaded libraries, ~30 ms)
is made once, at the first use; entering and leaving the limit then costs ~40 µs, once
per population.
"""

from __future__ import annotations

import threading
from collections.abc import Generator, Iterator
from contextlib import contextmanager
from typing import TypeVar

from threadpoolctl import ThreadpoolController

Y = TypeVar("Y")
R = TypeVar("R")

_lock = threading.Lock()
_controller: ThreadpoolController | None = None
_depth = 0
_limiter = None  # what restores the thread counts found when the first holder entered


@contextmanager
def one_thread() -> Iterator[None]:
    """Hold the BLAS libraries loaded in this process to one thread (counted, see above)."""
    global _controller, _depth, _limiter
    with _lock:
        if _depth == 0:
            if _controller is None:
                _controller = ThreadpoolController()
            _limiter = _controller.limit(limits=1, user_api="blas")
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0 and _limiter is not None:
                _limiter.restore_original_limits()
                _limiter = None


def limited(gen: Generator[Y, None, R]) -> Generator[Y, None, R]:
    """``gen``, each of its steps run under :func:`one_thread`; closing this closes ``gen``."""
    try:
        while True:
            with one_thread():
                try:
                    item = next(gen)
                except StopIteration as done:
                    return done.value
            yield item
    finally:
        gen.close()
