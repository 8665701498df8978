"""Run an example spec in-process into a store, write its figures and a Table-4-style summary.

    python -m examples.analyse SPEC --out out/NAME [--seed N ...] [--truth NAME=VALUE ...]
                               [--figures DIR] [--particles N] [--max-populations N]

For each seed: ``out/NAME/seed<N>.zarr`` (the store ``abcns run SPEC --out ...`` would
write; an existing store is reused), ``abcns plot``'s figures in ``DIR/seed<N>/`` (default
``out/NAME/figures``) and ``summary.md`` there: stop reason, populations, simulations, model
probabilities, the selected model's posterior (mean, std, 95 % interval, truth, whether the
interval holds it) and the NMSE of the posterior mean and best particle on the fit and test
windows (Table 8).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from service.report.analysis import predictions, run_to_store, store_job_data
from service.report.plots import plot_result
from service.run.runner import result_from_store
from service.run.store import Store
from service.spec import load


def summary_markdown(result, scores: dict, truth: dict[str, float], wall_s: float) -> str:
    probs = result.model_probabilities()
    best = max(probs, key=probs.get)
    lines = [f"- stop: {result.stop_reason.value} after {len(result.populations)} populations, "
             f"{result.n_simulations:,} simulations, {wall_s:.1f} s; final tolerance {result.final.epsilon:.5g}",
             "- model probabilities: " + ", ".join(f"{k} {v:.3f}" for k, v in probs.items()),
             (f"- selected: **{best}**" if sum(v == probs[best] for v in probs.values()) == 1 else
              f"- no decision: tie at p = {probs[best]:.3f}; the table shows {best}, the first of the tied models"), "",
             "| parameter | mean | std | 95 % interval | truth | inside |", "|---|---|---|---|---|---|"]
    for name, q in result.posterior()[best].items():
        tv = truth.get(name)
        inside = "" if tv is None else ("yes" if q["q2_5"] <= tv <= q["q97_5"] else "**no**")
        lines.append(f"| {name} | {q['mean']:.6g} | {q['std']:.4g} | [{q['q2_5']:.6g}, {q['q97_5']:.6g}] | "
                     f"{'' if tv is None else f'{tv:g}'} | {inside} |")
    lines += ["", "| model | point | NMSE fit | NMSE test |", "|---|---|---|---|"]
    for model, s in scores.items():
        for point, v in s.items():
            lines.append(f"| {model} | {point} | {v.get('fit', float('nan')):.4g} | {v.get('test', float('nan')):.4g} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("spec", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seed", type=int, nargs="*", default=None)
    parser.add_argument("--truth", nargs="*", default=[])
    parser.add_argument("--figures", type=Path, default=None)
    parser.add_argument("--particles", type=int, default=None)
    parser.add_argument("--max-populations", type=int, default=None)
    args = parser.parse_args(argv)
    spec, base = load(args.spec)
    if args.particles:
        spec = spec.model_copy(update={"sampler": spec.sampler.model_copy(update={"particles": args.particles})})
    if args.max_populations:
        spec = spec.model_copy(update={"stop": spec.stop.model_copy(update={"max_populations": args.max_populations})})
    truth = {k: float(v) for k, v in (t.split("=") for t in args.truth)}
    figures = args.figures or args.out / "figures"
    for seed in args.seed or [spec.seed]:
        path = args.out / f"seed{seed}.zarr"
        start = time.perf_counter()
        if not path.exists():
            print(f"running {args.spec} seed {seed} -> {path}", flush=True)
            run_to_store(spec, base, path, seed=seed,
                         on_population=lambda p: print(f"  population {p.t:4d} eps {p.epsilon:10.5g} "
                                                       f"acceptance {p.acceptance_rate:.2f}", flush=True)
                         if p.t % 10 == 0 else None)
        store = Store.open(path)
        result, data = result_from_store(store), store_job_data(store, base)
        wall = result.wall_time_s if path.exists() else time.perf_counter() - start
        target = figures / f"seed{seed}"
        plot_result(result, target, truth or None, data)
        _, scores = predictions(result, data)
        text = f"## seed {seed}\n\n" + summary_markdown(result, scores, truth, wall)
        (target / "summary.md").write_text(text)
        (target / "summary.json").write_text(json.dumps(result.summary(), indent=1, default=str))
        print(text, flush=True)


if __name__ == "__main__":
    main()
