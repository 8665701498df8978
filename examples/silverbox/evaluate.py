"""Silverbox: predictive NMSE of the fitted models on held-out multisine realisations.

    python -m examples.analyse examples/silverbox/spec.yaml --out out/silverbox --seed 1 \\
        --figures examples/silverbox/figures
    python -m examples.silverbox.evaluate [--seed 1]

Needs the first command's store. Every model alive in the final population, and the linear
model fitted alone when the joint run killed it (``out/silverbox/linear_seed<N>.zarr``), is
simulated from rest with its posterior mean on realisations 2..9 of the multisine (the spec
fits on realisation 1; 8 and 9 lie in the benchmark's official test range) and scored by the
NMSE (Eq. 7) on the whole 3000-sample segment. Writes ``figures/seed<N>/heldout.md`` and
``heldout.png`` (NMSE per realisation, and the predictive bands on realisation 9).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from abcns.analysis import nmse, point_estimates, predictive
from examples.boucwen.evaluate import on_record
from examples.silverbox.prepare import segments
from service.report.analysis import fit_alone, open_run

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
HELD_OUT = tuple(range(2, 10))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "silverbox")
    parser.add_argument("--figures", type=Path, default=HERE / "figures")
    args = parser.parse_args(argv)
    # the run's own spec (particles, stop) serves the linear fit too
    spec, base, _store, result, data = open_run(HERE / "spec.yaml", args.out / f"seed{args.seed}.zarr")
    fits = {result.models[i].name: (result, data) for i in result.alive()}
    if "linear" not in fits:
        fits["linear (fitted alone)"] = fit_alone(spec, base, "linear", args.out / f"linear_seed{args.seed}.zarr",
                                                  name="silverbox-linear", seed=args.seed)
    seg = segments()
    table: dict[str, list[float]] = {}
    for label, (res, dat) in fits.items():
        model = label.split(" ")[0]
        theta = point_estimates(res, model)["posterior_mean"]
        row = []
        for r in HELD_OUT:
            u, y = seg[r]
            values, status = on_record(dat, u, y).simulate(model)(theta)
            row.append(float(nmse(values[0], y)) if status[0] == 0 else float("inf"))
        table[label] = row
    probs = result.model_probabilities()
    selected = max(probs, key=probs.get)
    lines = [f"Silverbox, seed {args.seed}: model probabilities "
             + ", ".join(f"{k} {v:.3f}" for k, v in probs.items()) + f"; selected **{selected}**.", "",
             "NMSE (Eq. 7) of the posterior mean, simulated from rest on held-out realisations (3000 samples each):", "",
             "| model | " + " | ".join(f"r{r}" for r in HELD_OUT) + " | mean |", "|---" * (len(HELD_OUT) + 2) + "|"]
    for label, row in table.items():
        lines.append(f"| {label} | " + " | ".join(f"{v:.4g}" for v in row) + f" | {np.mean(row):.4g} |")
    text = "\n".join(lines) + "\n"
    target = args.figures / f"seed{args.seed}"
    target.mkdir(parents=True, exist_ok=True)
    (target / "heldout.md").write_text(text)

    fig = Figure(figsize=(12, 4), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2, width_ratios=[1, 2])
    for label, row in table.items():
        ax1.semilogy(HELD_OUT, row, "o-", label=label)
    ax1.set(xlabel="held-out realisation", ylabel="NMSE of the posterior mean", title="prediction on other segments")
    ax1.legend(fontsize=7)
    u, y = seg[9]
    pred = predictive(result, selected, on_record(data, u, y).simulate(selected))
    t = np.arange(y.size) / (data.spec.data.fs * 1e3)  # the spec's rate is per ms
    zoom = slice(1000, 1300)
    b = pred.bands
    ax2.fill_between(t[zoom], b["lower_99"][zoom], b["upper_99"][zoom], alpha=0.3, lw=0, label="99 % band")
    ax2.plot(t[zoom], y[zoom], "k.", ms=3, label="measured")
    ax2.plot(t[zoom], b["median"][zoom], "tab:red", lw=1, label=f"{selected} predictive median")
    ax2.set(xlabel="time in segment [s]", ylabel="output [V]",
            title=f"realisation 9 (official test range), NMSE of the median {float(nmse(b['median'], y)):.3g}")
    ax2.legend(fontsize=7)
    fig.savefig(target / "heldout.png", dpi=110)
    print(text)


if __name__ == "__main__":
    main()
