"""Write the synthetic example data (fixed seeds) next to their specs.

    python -m examples.make_data

- linear_31: paper §3.1, c = 20, k = 1e4, m = 1, Gaussian force (std 10), 500 samples at
  100 Hz, exact zero-order-hold response, noise-free.
- gandk_32: paper §3.2, 1e4 draws at (A, B, g, k) = (3, 1, 2, 0.5), c = 0.8.
- duffing_41: paper §4.1, cubic-quintic truth (c, k, k3, k5) = (0.05, 50, 1e3, 1e5), m = 1,
  Gaussian force (std 10) at 100 Hz, 1000 samples (500 training + 500 test), integrated with
  64 RK4 steps per sample, plus Gaussian noise of 1 % of the response's RMS.

The truths are simulated with the numpy reference simulators, so the data do not depend
on the machine's vector width.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from worker.simulators import Duffing, GAndK, Linear

HERE = Path(__file__).resolve().parent


def linear_31(seed: int = 31) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    force = 10.0 * rng.standard_normal(500)
    x = Linear(force, 0.01, backend="numpy").simulate(np.array([[1.0, 20.0, 1e4]])).values[0]
    return {"force": force, "displacement": x}


def gandk_32(seed: int = 32) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"observed": GAndK(10_000).simulate(np.array([[3.0, 1.0, 2.0, 0.5, 0.8]]), rng).values[0]}


def duffing_41(seed: int = 41) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    force = 10.0 * rng.standard_normal(1000)
    x = Duffing(force, 0.01, substeps=64, backend="numpy").simulate(np.array([[1.0, 0.05, 50.0, 0.0, 1e3, 1e5]])).values[0]
    noise = 0.01 * np.sqrt(np.mean(x**2)) * rng.standard_normal(x.size)
    return {"force": force, "displacement": x + noise, "displacement_clean": x}


def main() -> None:
    for name, make in (("linear_31", linear_31), ("gandk_32", gandk_32), ("duffing_41", duffing_41)):
        folder = HERE / name
        folder.mkdir(exist_ok=True)
        for key, arr in make().items():
            np.save(folder / f"{key}.npy", arr)
        print(f"wrote {folder.relative_to(HERE.parent)}")


if __name__ == "__main__":
    main()
