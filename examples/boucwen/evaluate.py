"""Bouc-Wen benchmark: test-set RMSE of the selected model beside a fitted linear model's.

    python -m examples.analyse examples/boucwen/spec.yaml --out out/boucwen --seed 1 \\
        --truth m=2 c=10 k=5e4 A=5e4 alpha=800 beta=-1100 --figures examples/boucwen/figures
    python -m examples.boucwen.evaluate [--seed 1]

Needs the first command's store (``out/boucwen/seed<N>.zarr``). Fits the linear model alone
(the joint run kills it early, so it has no posterior there) into
``out/boucwen/linear_seed<N>.zarr``, then simulates the posterior mean and the best particle
of both on the benchmark's official test records (inputs read as the spec's ``data.input_interpolation`` says:
band-limited; the multisine is one steady-state period, so two periods are simulated from
rest and the second is scored) and writes ``figures/seed<N>/test_rmse.md`` and
``figures/seed<N>/test_*.png``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from abcns.analysis import bands, point_estimates
from examples.boucwen.prepare import FS, NOISE_RMS, load
from service.report.analysis import JobData, fit_alone, open_run
from service.spec import model_description
from worker.description import simulator_for

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]


def on_record(data: JobData, force: np.ndarray, observed: np.ndarray) -> JobData:
    """The same models with simulators driven by another input record (read as the spec's
    ``data.input_interpolation`` says)."""
    sims = {}
    for i, desc in enumerate(map(model_description, data.spec.models)):
        sims[desc.name] = simulator_for(desc, force, data.dt, np.resize(observed, force.size), i,
                                        input_interpolation=data.spec.data.input_interpolation)
    return JobData(data.spec, force, observed, data.dt, (0, observed.size), None, data.models, sims)


def colour(label: str) -> str:
    return "tab:orange" if label.startswith("linear") else "tab:blue"


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "boucwen")
    parser.add_argument("--figures", type=Path, default=HERE / "figures")
    args = parser.parse_args(argv)
    # the run's own spec (particles, stop) serves the linear fit too
    spec, base, _store, result, data = open_run(HERE / "spec.yaml", args.out / f"seed{args.seed}.zarr")
    probs = result.model_probabilities()
    selected = max(probs, key=probs.get)

    linear, linear_data = fit_alone(spec, base, "linear", args.out / f"linear_seed{args.seed}.zarr",
                                    name="boucwen-linear", seed=args.seed)

    records = load()
    rows = []
    target = args.figures / f"seed{args.seed}"
    target.mkdir(parents=True, exist_ok=True)
    for name, rec in (("multisine", records["test_multisine"]), ("sine sweep", records["test_sinesweep"])):
        y = rec["y"]
        scored = slice(y.size, 2 * y.size) if name == "multisine" else slice(0, y.size)
        sims = {}
        for label, res, dat, model in (("selected " + selected, result, data, selected),
                                       ("linear (fitted alone)", linear, linear_data, "linear")):
            d = on_record(dat, rec["force"], y)
            pts = point_estimates(res, model)
            values, status = d.simulate(model)(np.stack([pts["posterior_mean"], pts["best"]]))
            r = [rmse(values[k, scored], y) if status[k] == 0 else float("inf") for k in range(2)]
            rows.append((name, label, r[0], r[1]))
            sims[label] = values[0, scored]
            if name == "multisine" and model == selected:
                theta, _, _ = res.particles(model)
                vals, st = d.simulate(model)(theta[:: max(1, theta.shape[0] // 200)])
                band = bands(vals[st == 0][:, scored])
                sims["band"] = band
        fig = Figure(figsize=(11, 4.2), layout="constrained")
        ax1, ax2 = fig.subplots(1, 2, width_ratios=[2, 1])
        t = np.arange(y.size) / FS
        for label, v in reversed(list(sims.items())):  # the selected model's small error on top
            if label != "band":
                ax1.plot(t, (v - y) * 1e3, lw=0.6, color=colour(label), label=f"{label}: error, RMSE {rmse(v, y) * 1e3:.4f} mm")
        ax1.axhline(NOISE_RMS * 1e3, color="k", ls=":", lw=1, label=f"training noise RMS {NOISE_RMS * 1e3:g} mm")
        ax1.axhline(-NOISE_RMS * 1e3, color="k", ls=":", lw=1)
        ax1.set(xlabel="time [s]", ylabel="simulation error [mm]", title=f"official test record: {name}")
        ax1.legend(fontsize=7, loc="upper right")
        zoom = slice(0, int(0.3 * FS))
        ax2.plot(t[zoom], y[zoom] * 1e3, "k.", ms=2, label="test output")
        if "band" in sims:
            b = sims["band"]
            ax2.fill_between(t[zoom], b["lower_99"][zoom] * 1e3, b["upper_99"][zoom] * 1e3, alpha=0.3, lw=0,
                             label="99 % predictive band")
        for label, v in sims.items():
            if label != "band":
                ax2.plot(t[zoom], v[zoom] * 1e3, lw=0.8, color=colour(label), label=label)
        ax2.set(xlabel="time [s]", ylabel="y [mm]", title="first 0.3 s")
        ax2.legend(fontsize=7)
        fig.savefig(target / f"test_{name.replace(' ', '_')}.png", dpi=110)

    lines = [f"Bouc-Wen benchmark, seed {args.seed}: selected **{selected}** (p = {probs[selected]:.3f}); "
             f"noise on the training output: {NOISE_RMS:g} m RMS (test records are noiseless).", "",
             "| test record | model | RMSE posterior mean [m] | RMSE best particle [m] |", "|---|---|---|---|"]
    lines += [f"| {r[0]} | {r[1]} | {r[2]:.4g} | {r[3]:.4g} |" for r in rows]
    text = "\n".join(lines) + "\n"
    (target / "test_rmse.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
