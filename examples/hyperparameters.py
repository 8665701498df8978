"""The paper's hyperparameter study (§3.1, Figs. 4-7) on the §3.1 linear problem.

    python -m examples.hyperparameters [--out examples/hyperparameters] [--seed 1] [--quick]

- f0 (ellipsoid enlargement) in 1.0, 1.05, 1.1, 1.15, 1.2 with (alpha0, beta0) = (0.3, 0.6):
  acceptance rate per population (Fig. 4) and the final posterior of c and k (Fig. 5);
- (alpha0, beta0) in (0.1, 0.8), (0.2, 0.7), (0.3, 0.6), (0.4, 0.5), (0.5, 0.4) with f0 = 1.1:
  acceptance rate per population (Fig. 6) and mean +- sd of c and k with the parameter MSE
  ``mean_i (theta_i - theta_true)^2`` over the final particles (Fig. 7).

Every run uses the same data, seed and stop rule (tolerance decrease below 1e-3, as in
``examples/paper.py``). Writes ``fig4_f0_acceptance.png`` ... ``fig7_pairs_posterior.png``
and ``table.md`` (populations, simulations, final tolerance, posterior per run).
``--quick`` (the test suite): 200 particles, at most 6 populations.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from abcns import StopRules, run
from examples.paper import linear_31

F0 = (1.0, 1.05, 1.1, 1.15, 1.2)
PAIRS = ((0.1, 0.8), (0.2, 0.7), (0.3, 0.6), (0.4, 0.5), (0.5, 0.4))


def study(seed: int = 1, quick: bool = False) -> dict[str, list]:
    """{"f0": [(f0, result)], "pairs": [((alpha, beta), result)]}."""
    problem = linear_31()
    base = problem.settings
    stop = problem.stop
    if quick:
        base = dataclasses.replace(base, particles=200)
        stop = StopRules(min_epsilon_decrease=stop.min_epsilon_decrease, max_populations=6)
    out: dict[str, list] = {"f0": [], "pairs": []}
    for f0 in F0:
        s = dataclasses.replace(base, enlargement=f0, alpha=0.3, beta=0.6)
        out["f0"].append((f0, run(problem.models, problem.evaluate, s, stop, seed=seed)))
    for a, b in PAIRS:
        s = dataclasses.replace(base, enlargement=1.1, alpha=a, beta=b)
        out["pairs"].append(((a, b), run(problem.models, problem.evaluate, s, stop, seed=seed)))
    return out


def acceptance_figure(runs: list, label: str, title: str) -> Figure:
    fig = Figure(figsize=(7, 3.8), layout="constrained")
    ax = fig.subplots()
    for key, res in runs:
        ax.plot([p.t for p in res.populations], [p.acceptance_rate for p in res.populations], "o-", ms=2.5,
                label=f"{label} = {key}")
    ax.set(xlabel="population", ylabel="acceptance rate", ylim=(0, 1.02), title=title)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def posterior_figure(runs: list, label: str, truth: dict[str, float], title: str, mse: bool) -> Figure:
    fig = Figure(figsize=(10, 3.8), layout="constrained")
    axes = fig.subplots(1, 2)
    keys = [str(k) for k, _ in runs]
    for j, (ax, name) in enumerate(zip(axes, ("c", "k"), strict=True)):
        means, sds, errs = [], [], []
        for _, res in runs:
            theta = res.particles(0)[0][:, j]
            means.append(theta.mean())
            sds.append(theta.std())
            errs.append(np.mean((theta - truth[name]) ** 2))
        x = np.arange(len(runs))
        ax.errorbar(x, means, yerr=sds, fmt="o", capsize=4, label="mean +- sd")
        ax.axhline(truth[name], color="tab:red", lw=1, label=f"truth {truth[name]:g}")
        ax.set_xticks(x, keys, fontsize=8)
        ax.set(xlabel=label, ylabel=name)
        ax.ticklabel_format(axis="y", useOffset=False)
        if mse:
            ax2 = ax.twinx()
            ax2.plot(x, errs, "s--", color="tab:green", label="MSE")
            ax2.set_ylabel(f"MSE of {name}", color="tab:green")
        ax.legend(fontsize=8, loc="upper left")
    fig.suptitle(title, fontsize=10)
    return fig


def table(out: dict[str, list]) -> str:
    lines = ["| setting | populations | simulations | mean acceptance (t >= 2) | final eps | c mean +- sd | k mean +- sd |",
             "|---|---|---|---|---|---|---|"]
    for group, label in (("f0", "f0"), ("pairs", "(alpha0, beta0)")):
        for key, res in out[group]:
            th = res.particles(0)[0]
            acc = np.mean([p.acceptance_rate for p in res.populations[1:]]) if len(res.populations) > 1 else float("nan")
            lines.append(f"| {label} = {key} | {len(res.populations)} | {res.n_simulations:,} | {acc:.2f} | "
                         f"{res.final.epsilon:.3g} | {th[:, 0].mean():.3f} +- {th[:, 0].std():.3f} | "
                         f"{th[:, 1].mean():.1f} +- {th[:, 1].std():.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "hyperparameters")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    out = study(args.seed, args.quick)
    truth = linear_31().truth["linear"]
    args.out.mkdir(parents=True, exist_ok=True)
    pair = "(alpha0, beta0)"
    figs = {
        "fig4_f0_acceptance.png": acceptance_figure(out["f0"], "f0", "effect of f0 on acceptance (alpha0 0.3, beta0 0.6)"),
        "fig5_f0_posterior.png": posterior_figure(out["f0"], "f0", truth, "effect of f0 on the final posterior", False),
        "fig6_pairs_acceptance.png": acceptance_figure(out["pairs"], pair, f"effect of {pair} on acceptance (f0 1.1)"),
        "fig7_pairs_posterior.png": posterior_figure(out["pairs"], pair, truth, f"effect of {pair} on the final posterior", True),
    }
    for name, fig in figs.items():
        fig.savefig(args.out / name, dpi=110)
    text = table(out)
    (args.out / "table.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
