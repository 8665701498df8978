"""Bouc-Wen benchmark (Noël & Schoukens 2016) data for the example spec, from the part of
the benchmark committed in ``data/boucwen/boucwen_subset.npz`` (source, licence:
``data/boucwen/README.md``).

    python -m examples.boucwen.prepare                       # from the committed subset
    python -m examples.boucwen.prepare --source boucwen.npz  # remake the subset first

``--source`` names the full benchmark converted to one npz (``train_multisine_u``/``_y``,
``test_multisine_u``/``_y``, ``test_sinesweep_u``/``_y``, ``fs_hz``; see the data README for
where the records come from); only that regeneration needs it.

Writes, next to this file:

- ``force.npy``, ``displacement.npy``: the first 3000 samples (4 s at 750 Hz) of the training
  multisine record (the system starts at rest: |y[0]| = 8e-6 m, the noise level); the spec
  fits on [0, 1500) and holds out [1500, 3000);
and :func:`load` gives the official test records the same way: ``test_multisine`` (``force``:
two periods of the test input, ``y``: its one steady-state period, compared with the second
simulated period) and ``test_sinesweep`` (``force``, ``y``: the full record, from rest).

**The input is as published** (not shifted); the spec reads it with ``data.input_interpolation:
bandlimited`` (``worker.simulators.band_limited``): the benchmark's integrator ran at 20x the
rate on the band-limited input, which a plain hold lags by dt/2 (8.4 degrees at the 35.6 Hz
resonance). Until issue AA the input was advanced here by half a sample with the FFT over the
whole record and held; both are measured in ``README.md``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SUBSET = HERE.parents[1] / "data" / "boucwen" / "boucwen_subset.npz"
WINDOW = 3000
FS = 750.0
# published parameters (benchmark PDF, Table 1) in the simulator's form (data README)
TRUTH = {"m": 2.0, "c": 10.0, "k": 5e4, "A": 5e4, "alpha": 800.0, "beta": -1100.0}
NOISE_RMS = 8e-6  # m, stated in the data README (test records are noiseless)


def subset(source: Path) -> dict[str, np.ndarray]:
    """The arrays the example uses, from the full benchmark npz: the first ``WINDOW`` samples
    of the training record, both test records whole, values as published."""
    with np.load(source) as z:
        d = dict(z)
    if float(d["fs_hz"]) != FS:
        raise ValueError(f"{source}: expected fs 750 Hz, got {d['fs_hz']}")
    return {
        "train_force": d["train_multisine_u"][:WINDOW],
        "train_y": d["train_multisine_y"][:WINDOW],
        "test_multisine_force": d["test_multisine_u"],
        "test_multisine_y": d["test_multisine_y"],
        "test_sinesweep_force": d["test_sinesweep_u"],
        "test_sinesweep_y": d["test_sinesweep_y"],
        "fs_hz": d["fs_hz"],
    }


def load(path: Path = SUBSET) -> dict[str, np.ndarray]:
    """The training window and the two official test records (the multisine's input as two
    periods: simulated from rest, the second period is scored)."""
    with np.load(path) as z:
        d = dict(z)
    if float(d["fs_hz"]) != FS:
        raise ValueError(f"{path}: expected fs 750 Hz, got {d['fs_hz']}")
    out = {"force": d["train_force"], "displacement": d["train_y"]}
    u = d["test_multisine_force"]
    out["test_multisine"] = {"force": np.concatenate([u, u]), "y": d["test_multisine_y"]}
    out["test_sinesweep"] = {"force": d["test_sinesweep_force"], "y": d["test_sinesweep_y"]}
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--source", type=Path, help="the full benchmark npz: remake data/boucwen/boucwen_subset.npz from it")
    args = parser.parse_args(argv)
    if args.source:
        np.savez_compressed(SUBSET, **subset(args.source))
        print(f"wrote {SUBSET}")
    d = load()
    np.save(HERE / "force.npy", d["force"])
    np.save(HERE / "displacement.npy", d["displacement"])
    print(f"wrote {HERE}/force.npy, displacement.npy ({WINDOW} samples)")


if __name__ == "__main__":
    main()
