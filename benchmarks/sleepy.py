"""A latency-bound plugin simulator for the scale-out benchmark (benchmarks/scale.py).

``benchmarks.sleepy:factory`` in a spec (CLI or ``run_job(..., allow_import=True)``; never
HTTP) gives the built-in Duffing oscillator that then sleeps ``SECONDS`` (2 ms by default) per
simulation, ``time.sleep(SECONDS * n_rows)`` per batch: the stand-in for an expensive model
whose cost is wall time, not this machine's cores, so many workers on few cores still scale.

It offers only ``simulate`` (no ``distance_nmse`` fast path), so every row of every batch
is simulated in full and sleeps: no early rejection. ``simulated()`` is the number of rows
this process has simulated (the benchmark asks every worker with ``client.run`` to count the
surplus work the executor cancelled too late).
"""

from __future__ import annotations

import os
import time
from typing import ClassVar

import numpy as np

from worker.simulators import Duffing, SimOutput

#: sleep per simulation: 2 ms, or ABCNS_SLEEPY_MS (``benchmarks.scale --sleep-ms`` sets it before any
#: worker starts; the worker processes inherit it)
SECONDS = float(os.environ.get("ABCNS_SLEEPY_MS", "2")) / 1e3
NAME = "benchmarks.sleepy:factory"

_simulated = 0


def simulated() -> int:
    """Rows simulated by this process so far."""
    return _simulated


class SleepyDuffing:
    """:class:`worker.simulators.Duffing`, then ``SECONDS`` of sleep per simulated row."""

    name = NAME
    parameter_names = Duffing.parameter_names
    defaults: ClassVar[dict[str, float]] = dict(Duffing.defaults)

    def __init__(self, seconds: float | None = None, n_samples: int | None = None, **kwargs):
        self.inner = Duffing(**kwargs)  # the oscillator's length is its force's (n_samples: the registry's, unused)
        self.seconds = SECONDS if seconds is None else float(seconds)

    @property
    def n_samples(self) -> int:
        return self.inner.n_samples

    def simulate(self, params: np.ndarray, rng: np.random.Generator | None = None) -> SimOutput:
        global _simulated
        out = self.inner.simulate(params, rng)
        n = int(np.atleast_2d(params).shape[0])
        time.sleep(self.seconds * n)
        _simulated += n
        return out

    def config(self) -> dict:
        return {**self.inner.config(), "simulator": NAME, "sleep_s_per_simulation": self.seconds}


def factory(**kwargs) -> SleepyDuffing:
    """The registry's factory: the Duffing keyword arguments (force, dt, n_samples, substeps,
    output, state_bound)."""
    return SleepyDuffing(**kwargs)
