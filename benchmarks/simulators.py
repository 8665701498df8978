"""Simulator throughput: simulations per second per core, numba kernels vs the numpy reference.

Run: ``python -m benchmarks.simulators [--repeats N] [--skip-numpy] [--skip-compile]``.

One thread (NUMBA_NUM_THREADS=1; the kernels are not parallel anyway), batch 1000, best of
``--repeats`` runs (the machine may be shared: the best run is the least disturbed one).
Figures are for the in-kernel NMSE path (what the evaluator uses; epsilon = inf, so no
early rejection) and for the full-trajectory path. On AVX-512 hosts the kernels use 512-bit
vectors (see ``worker.kernels._prefer_wide_vectors``); ``ABCNS_NUMBA_WIDE_VECTORS=0``
gives numba's default 256-bit code for comparison.

Share of the floating-point ceiling: flops per simulation (counted from the kernels' source,
an FMA = 2 flops, abs/compare = 0) times simulations per second, over ``CEILING`` = 57
GFLOP/s per core (AVX2, two FMA ports at ~3.5 GHz).

- Duffing RK4 step: 4 accelerations x 11 (x^2; 3 FMA of the Horner polynomial; 2 fused
  subtractions) + 1 (f/m) + 7 stage FMAs x 2 + 9 (final combination) = 68 flops.
- Bouc-Wen (n = 2) RK4 step: 4 x (6 acceleration + 8 dz/dt) + 1 + 10 stage FMAs x 2 + 15
  (final combination) = 92 flops.
- Linear exact ZOH sample: 2 x (mul + 2 FMA) = 10 for the recursion + 3 for the squared
  error = 13 flops; plus ~ 400 once per particle for the transition coefficients.
- Bouc-Wen restoring force (displacement-driven, one state z): RK4 step in x: 4 slopes x 4
  + 3 stage FMAs x 2 + 5 (final combination) = 27 flops, plus 4 ``pow`` (|z|^n, n real), not
  counted; the output F = c v + k x + alpha z: 4 flops per sample.
- Bouc-Wen-Baber-Noori restoring force (z and the energy e): 4 slopes x ~24 + 6 stage FMAs x 2
  + 10 = ~118 flops, plus 4 x (2 ``pow``, 2 ``exp``, 1 division), not counted.
- Spencer's MR damper (y and z, in time): 4 stages x ~14 + 4 stage FMAs x 2 + 10 = ~74 flops
  per RK4 step (n = 2), the output ~10 flops per sample.
- Spencer's MR damper with the voltage as an input (y, z and the filtered voltage u): 4
  stages x ~22 (the voltage laws, u's rate, a division) + 6 stage FMAs x 2 + 15 = ~115 flops
  per RK4 step, the output ~16 flops per sample.
The per-sample bookkeeping (checks, squared error: ~4 flops) is added for the RK4 models. The
restoring-force models run the same record length and substeps as Bouc-Wen, so their rates
compare per sample with it (their ``goal`` is Bouc-Wen's).
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from worker.restoring import BoucWenRestoring, BWBNRestoring, SpencerMR, SpencerMRVoltage
from worker.simulators import BoucWen, Duffing, Linear

ROOT = Path(__file__).resolve().parents[1]
CEILING = 57e9  # flop/s per core
BATCH = 1000


def flops_duffing(n_samples: int, substeps: int) -> float:
    return (n_samples - 1) * substeps * 68 + n_samples * 4


def flops_bouc_wen(n_samples: int, substeps: int) -> float:
    return (n_samples - 1) * substeps * 92 + n_samples * 4


def flops_bw_restoring(n_samples: int, substeps: int) -> float:
    return (n_samples - 1) * substeps * 27 + n_samples * 8


def flops_bwbn_restoring(n_samples: int, substeps: int) -> float:
    return (n_samples - 1) * substeps * 118 + n_samples * 8


def restoring_setups(rng: np.random.Generator, n: int):
    """The displacement-driven models over a growing sine (1500 samples, 5 cycles, amplitude
    to 3 yield displacements), 8 substeps as Bouc-Wen; n = 2 (fixed) and n real in 1..3."""
    t = np.arange(1500) / 300.0
    x = 3.0 * (0.2 + 0.8 * t / t[-1]) * np.sin(2 * np.pi * t)
    bw = np.column_stack([np.zeros(n), rng.uniform(0.05, 0.2, n), rng.uniform(0.5, 2.0, n), rng.uniform(0.5, 1.5, n),
                          rng.uniform(0.3, 0.8, n), rng.uniform(-0.2, 0.3, n), np.full(n, 2.0)])
    kw = dict(force=x, dt=1 / 300, substeps=8)
    yield ("bouc_wen_restoring", "1500 samples, 8 substeps, n = 2", BoucWenRestoring, kw, bw,
           flops_bw_restoring(1500, 8), 37_000)
    bw = bw.copy()
    bw[:, 6] = rng.uniform(1.0, 3.0, n)
    yield ("bouc_wen_restoring", "1500 samples, 8 substeps, n real in 1..3", BoucWenRestoring, kw, bw,
           flops_bw_restoring(1500, 8), 37_000)
    extra = np.column_stack([rng.uniform(0.0, 0.1, n), rng.uniform(0.0, 0.1, n), rng.uniform(0.5, 2.0, n),
                             rng.uniform(0.3, 0.9, n), rng.uniform(0.1, 0.5, n), np.zeros(n), rng.uniform(0.1, 1.0, n),
                             rng.uniform(0.0, 0.3, n)])
    bn = np.column_stack([bw[:, :6], np.full(n, 2.0), extra])
    yield ("bwbn_restoring", "1500 samples, 8 substeps, n = 2", BWBNRestoring, kw, bn,
           flops_bwbn_restoring(1500, 8), 37_000)
    bn = np.column_stack([bw, extra])
    yield ("bwbn_restoring", "1500 samples, 8 substeps, n real in 1..3", BWBNRestoring, kw, bn,
           flops_bwbn_restoring(1500, 8), 37_000)
    # Spencer's MR damper around his 0 V values: 2 cycles of a 10 Hz, 10 mm sine at 8 kHz
    x = 0.01 * np.sin(2 * np.pi * 10.0 * np.arange(1500) / 8000.0)
    sp = np.array([1.4e4, 2100.0, 28300.0, 4690.0, 500.0, 0.0, 3.63e6, 3.63e6, 301.0, 2.0]) * rng.uniform(0.7, 1.4, (n, 10))
    sp[:, 5] = 0.0
    sp[:, 9] = 2.0
    yield ("spencer_mr", "1500 samples at 8 kHz, 8 substeps, n = 2", SpencerMR, dict(force=x, dt=1 / 8000, substeps=8), sp,
           flops_spencer(1500, 8), 37_000)
    # the same with the coil voltage as an input: a square wave 0 / 2.25 V switched every 20 ms
    # (as the measured MR-damper record), Spencer's voltage-dependent values x 0.7..1.4
    e = np.where(np.floor(np.arange(1500) / 8000.0 / 0.02) % 2 == 1, 2.25, 0.0)
    spv = np.array([1.4e4, 6.95e4, 2100.0, 350.0, 28300.0, 295.0, 4690.0, 500.0, 0.0, 3.63e6, 3.63e6, 301.0, 2.0,
                    190.0]) * rng.uniform(0.7, 1.4, (n, 14))
    spv[:, 8] = 0.0
    spv[:, 12] = 2.0
    yield ("spencer_mr_voltage", "1500 samples at 8 kHz, 8 substeps, n = 2, voltage input", SpencerMRVoltage,
           dict(force=x, dt=1 / 8000, substeps=8, voltage=e), spv, flops_spencer_voltage(1500, 8), 37_000)


def flops_spencer(n_samples: int, substeps: int) -> float:
    return (n_samples - 1) * substeps * (4 * 14 + 8 + 10) + n_samples * 10


def flops_spencer_voltage(n_samples: int, substeps: int) -> float:
    return (n_samples - 1) * substeps * (4 * 22 + 12 + 15) + n_samples * 16


def flops_linear(n_samples: int) -> float:
    return n_samples * 13 + 400


def setups(rng: np.random.Generator):
    n = BATCH
    # Duffing: 1000 samples at 100 Hz, 8 substeps
    f = rng.standard_normal(1000)
    duffing = np.column_stack([np.ones(n), rng.uniform(0.5, 5.0, n), rng.uniform(1e3, 1e4, n), np.zeros(n),
                               rng.uniform(0.0, 1e5, n), np.zeros(n)])
    yield ("duffing", "1000 samples @ 100 Hz, 8 substeps", Duffing, dict(force=f, dt=0.01, substeps=8),
           duffing, flops_duffing(1000, 8), 80_000)
    # Bouc-Wen: 1500 samples at 4096 Hz, 8 substeps, n = 2 (around the benchmark's values)
    f = 10.0 * rng.standard_normal(1500)
    bw = np.column_stack([np.full(n, 2.0), rng.uniform(5.0, 15.0, n), np.zeros(n), rng.uniform(1e4, 5e4, n),
                          rng.uniform(5e2, 2e3, n), rng.uniform(3e4, 7e4, n), np.full(n, 2.0)])
    yield ("bouc_wen", "1500 samples @ 4096 Hz, 8 substeps, n = 2", BoucWen,
           dict(force=f, dt=1 / 4096, substeps=8), bw, flops_bouc_wen(1500, 8), 37_000)
    # linear: 500 samples, exact ZOH
    f = rng.standard_normal(500)
    lin = np.column_stack([np.ones(n), rng.uniform(0.5, 5.0, n), rng.uniform(1e3, 1e4, n)])
    yield "linear", "500 samples, exact ZOH", Linear, dict(force=f, dt=0.01), lin, flops_linear(500), 1_000_000
    yield from restoring_setups(rng, n)


def _timed(fn, *args) -> float:
    t = time.perf_counter()
    fn(*args)
    return time.perf_counter() - t


def best_time(fn, repeats: int) -> float:
    fn()  # warm up (compile or load from cache)
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


COMPILE_SNIPPET = """
import time, json, numpy as np
t0 = time.perf_counter()
from worker.simulators import Duffing, BoucWen, Linear
t1 = time.perf_counter()
f = np.random.default_rng(0).standard_normal(50)
Duffing(f, 0.01, substeps=2).simulate(np.array([[1.0, 1, 1, 0, 0, 0]]))
Duffing(f, 0.01, substeps=2).distance_nmse(np.array([[1.0, 1, 1, 0, 0, 0]]), f, 0, 50)
BoucWen(f, 0.01, substeps=2).simulate(np.array([[1.0, 1, 1, 1, 1, 1, 2]]))
BoucWen(f, 0.01, substeps=2).distance_nmse(np.array([[1.0, 1, 1, 1, 1, 1, 2]]), f, 0, 50)
Linear(f, 0.01).simulate(np.array([[1.0, 1, 1]]))
Linear(f, 0.01).distance_nmse(np.array([[1.0, 1, 1]]), f, 0, 50)
from worker.restoring import BoucWenRestoring, BWBNRestoring
BoucWenRestoring(f, 0.01).simulate(np.array([[0.0, 1, 1, 1, 1, 0, 2]]))
BoucWenRestoring(f, 0.01).distance_nmse(np.array([[0.0, 1, 1, 1, 1, 0, 2]]), f, 0, 50)
BWBNRestoring(f, 0.01).simulate(np.array([[0.0, 1, 1, 1, 1, 0, 2, 0, 0, 1, 0.5, 0.2, 0, 0.5, 0.1]]))
BWBNRestoring(f, 0.01).distance_nmse(np.array([[0.0, 1, 1, 1, 1, 0, 2, 0, 0, 1, 0.5, 0.2, 0, 0.5, 0.1]]), f, 0, 50)
t2 = time.perf_counter()
print(json.dumps({"import": t1 - t0, "first_calls": t2 - t1}))
"""


def compile_times() -> tuple[dict, dict]:
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "NUMBA_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
        runs = []
        for _ in range(2):  # cold (empty cache), then cached
            out = subprocess.run([sys.executable, "-c", COMPILE_SNIPPET], env=env, capture_output=True, text=True,
                                 check=True, cwd=ROOT)
            runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    return runs[0], runs[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--skip-numpy", action="store_true")
    parser.add_argument("--skip-compile", action="store_true")
    args = parser.parse_args()

    rng = np.random.default_rng(2024)
    print(f"batch {BATCH}, NUMBA_NUM_THREADS={os.environ['NUMBA_NUM_THREADS']}, best of {args.repeats}, "
          f"ceiling {CEILING / 1e9:.0f} GFLOP/s per core")
    for name, what, cls, kwargs, params, flops, goal in setups(rng):
        sim = cls(**kwargs)
        observed = sim.simulate(params[:1]).values[0] + 0.01 * rng.standard_normal(kwargs["force"].size)
        _d, status = sim.distance_nmse(params, observed, 0, observed.size)
        n_ok = int(np.count_nonzero(status == 0))
        t_nmse = best_time(lambda s=sim, o=observed, p=params: s.distance_nmse(p, o, 0, o.size), args.repeats)
        t_traj = best_time(lambda s=sim, p=params: s.simulate(p), args.repeats)
        rate = BATCH / t_nmse
        print(f"\n{name}: {what}; {flops:,.0f} flop/simulation; {n_ok}/{BATCH} OK")
        print(f"  numba, in-kernel NMSE : {rate:12,.0f} sims/s/core  ({rate * flops / CEILING:6.1%} of ceiling; "
              f"goal {goal:,}: {'met' if rate >= goal else 'NOT met'})")
        rate = BATCH / t_traj
        print(f"  numba, trajectories   : {rate:12,.0f} sims/s/core  ({rate * flops / CEILING:6.1%} of ceiling)")
        if not args.skip_numpy:
            ref = cls(**kwargs, backend="numpy")
            ref.simulate(params[:2])  # warm up (lazy imports)
            runs = 3 if name == "linear" else 1
            rate = BATCH / min(_timed(ref.simulate, params) for _ in range(runs))
            print(f"  numpy reference       : {rate:12,.0f} sims/s/core  ({rate * flops / CEILING:6.1%} of ceiling; "
                  f"best of {runs})")
    if not args.skip_compile:
        cold, cached = compile_times()
        print(f"\nnumba compile (all kernels, both modes; fresh NUMBA_CACHE_DIR in a subprocess): "
              f"cold {cold['first_calls']:.2f} s, cached {cached['first_calls']:.2f} s "
              f"(import of the simulators: {cold['import']:.2f} s / {cached['import']:.2f} s)")


if __name__ == "__main__":
    main()
