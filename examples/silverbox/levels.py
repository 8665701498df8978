"""Silverbox, §5.4 of the paper: one model across excitation levels (confusion matrices).

    python -m examples.silverbox.levels [--out out/silverbox_levels] [--seed 1]

The "arrow" part of the ``SNLS80mV`` record is filtered noise whose amplitude grows along
the record. Three segments of 3200 samples (input std 7.5, 21 and 34 mV; output peaks
0.07, 0.18, 0.28 V) become three data sets ``low``, ``mid``, ``high``; each gets the spec
of ``spec.yaml`` (linear, cubic, cubic-quintic; same priors) and is run in-process into
``OUT/<level>.zarr``. The circuit is not at rest at a segment's start, so the fit window
is [200, 1700) and the test window [1700, 3200): the free response from the unknown
initial state dies out in ~30 samples (damping ratio 0.05 at 69 Hz). Then one command
draws every figure and the confusion matrices (the model fitted on level i, its posterior
mean scored by the NMSE on level j's test window)::

    abcns plot OUT/low.zarr OUT/mid.zarr OUT/high.zarr --out DIR \\
        --spec OUT/low/spec.yaml --spec OUT/mid/spec.yaml --spec OUT/high/spec.yaml

which this script runs for you (``--figures``, default ``examples/silverbox/figures/levels``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import yaml

from examples.silverbox.prepare import ARROW, ARROW_LENGTH, arrow
from service.report.analysis import run_to_store
from service.spec import load

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
LEVELS = ARROW
LENGTH = ARROW_LENGTH


def write_datasets(out: Path, particles: int | None = None, max_populations: int | None = None,
                   levels: tuple[str, ...] = tuple(LEVELS)) -> dict[str, Path]:
    segments = arrow()
    base = yaml.safe_load((HERE / "spec.yaml").read_text())
    specs = {}
    for name in levels:
        u, y = segments[name]
        d = out / name
        d.mkdir(parents=True, exist_ok=True)
        np.save(d / "force.npy", u)
        np.save(d / "displacement.npy", y)
        spec = {**base, "name": f"silverbox-{name}"}
        spec["data"] = {**base["data"], "fit": [200, 1700], "test": [1700, LENGTH]}
        if particles:
            spec["sampler"] = {**base["sampler"], "particles": particles}
        if max_populations:
            spec["stop"] = {**base["stop"], "max_populations": max_populations}
        (d / "spec.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
        specs[name] = d / "spec.yaml"
    return specs


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "silverbox_levels")
    parser.add_argument("--figures", type=Path, default=HERE / "figures" / "levels")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--particles", type=int, default=None)
    parser.add_argument("--max-populations", type=int, default=None)
    parser.add_argument("--levels", nargs="+", choices=list(LEVELS), default=list(LEVELS))
    args = parser.parse_args(argv)
    specs = write_datasets(args.out, args.particles, args.max_populations, tuple(args.levels))
    stores = []
    for name, path in specs.items():
        store = args.out / f"{name}.zarr"
        if not store.exists():
            print(f"running {path} -> {store}", flush=True)
            result = run_to_store(*load(path), store, seed=args.seed)
            print(f"  {len(result.populations)} populations, {result.n_simulations:,} simulations, "
                  f"model probabilities {result.model_probabilities()}", flush=True)
        stores.append(store)
    from typer.testing import CliRunner

    from service.cli import app

    cmd = ["plot", *map(str, stores), "--out", str(args.figures)]
    for name, path in specs.items():
        cmd += ["--spec", str(path), "--label", name]
    done = CliRunner().invoke(app, cmd)
    print(done.output)
    if done.exit_code != 0:
        raise SystemExit(done.exit_code)


if __name__ == "__main__":
    main()
