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

**The input is advanced by half a sample** (exact band-limited shift with the FFT; the
training and multisine records are periodic, the sweep is zero-padded). Our simulators hold
``force[i]`` over ``[t_i, t_i+1)``; the benchmark's integrator ran at 20x the rate on the
band-limited input, so a plain hold lags it by dt/2 (8.4 degrees at the 35.6 Hz resonance).
Measured with the published parameters on the fit window: NMSE 2.81 with the plain hold,
0.0154 with the half-sample advance, against a noise floor of 0.0145 (100 x (8e-6 m)^2 /
var(y)). The advance is the midpoint rule for the held value.

Why not the spec's ``data.input_interpolation: linear`` on the plain input? Measured at the
published parameters: on the noiseless multisine test record (periodic, so the advance is
undone exactly) NMSE 0.0118 with ``linear``, 0.0030 with the advance and a hold, 2.68 with a
plain hold; on the fit window 0.026 against 0.0154. A band-limited input's midpoint value is
exact; a straight line between samples attenuates its upper band. The advance needs the whole
record (the FFT's ends), hence here and not in the spec.
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


def advance(x: np.ndarray, samples: float, pad: int = 0) -> np.ndarray:
    """``x(t + samples dt)`` by the FFT (exact for a periodic band-limited record; ``pad``
    zeros appended for a record that is not periodic)."""
    n = x.size + pad
    spectrum = np.fft.rfft(np.concatenate([x, np.zeros(pad)]))
    return np.fft.irfft(spectrum * np.exp(2j * np.pi * np.fft.rfftfreq(n) * samples), n)[: x.size]


def subset(source: Path) -> dict[str, np.ndarray]:
    """The arrays the example uses, from the full benchmark npz: the first ``WINDOW`` samples
    of the training record, both test records whole, every input advanced by half a sample
    (over the whole record: the training and multisine records are periodic, the sweep is
    zero-padded)."""
    with np.load(source) as z:
        d = dict(z)
    if float(d["fs_hz"]) != FS:
        raise ValueError(f"{source}: expected fs 750 Hz, got {d['fs_hz']}")
    return {
        "train_force": advance(d["train_multisine_u"], 0.5)[:WINDOW],
        "train_y": d["train_multisine_y"][:WINDOW],
        "test_multisine_force": advance(d["test_multisine_u"], 0.5),
        "test_multisine_y": d["test_multisine_y"],
        "test_sinesweep_force": advance(d["test_sinesweep_u"], 0.5, pad=4096),
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
