"""Run the authors' demo job spec (examples/authors_demo/spec.yaml: linear vs cubic Duffing
on data/authors-demo) and print the summary next to the authors' own run.

    python -m examples.authors_demo [--seed N] [--json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from abcns import run
from examples.paper import DATA
from service.spec import build, load

SPEC = Path(__file__).resolve().parent / "authors_demo" / "spec.yaml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=None, help="default: the spec's seed")
    parser.add_argument("--json", action="store_true", help="print the full JSON summary")
    args = parser.parse_args()
    problem = build(*load(SPEC))
    seed = problem.seed if args.seed is None else args.seed
    print(f"job spec: {SPEC.relative_to(Path.cwd()) if SPEC.is_relative_to(Path.cwd()) else SPEC} (seed {seed})")
    start = time.perf_counter()

    def progress(pop):
        probs = " ".join(f"{m.name}={p:.2f}" for m, p in zip(problem.models, pop.model_probabilities, strict=True))
        print(f"population {pop.t:3d}  eps {pop.epsilon:10.4f}  acceptance {pop.acceptance_rate:.2f}  "
              f"sims {pop.n_simulations:5d}  {probs}", flush=True)

    result = run(problem.models, problem.evaluate, problem.settings, problem.stop, seed=seed,
                 on_population=progress)
    summary = result.summary()
    if args.json:
        print(json.dumps(summary, indent=2))
        return
    ref = json.loads((DATA / "authors-demo" / "reference_run.json").read_text())
    print(f"\nstopped: {summary['stop_reason']} after {summary['n_populations']} populations, "
          f"{summary['n_simulations']} simulations, {time.perf_counter() - start:.1f} s")
    print(f"authors' run: {ref['populations']} populations, ~{ref['simulations_total_approx']} simulations, "
          f"{ref['reported_cpu_minutes']:.1f} min (MATLAB)")
    print("model probabilities:", {k: round(v, 3) for k, v in summary["model_probabilities"].items()})
    print("dead models (population of death):", summary["dead_models"])
    ref_post = ref["final_posterior_cubic"]
    print(f"\n{'cubic':6s} {'mean':>12s} {'std':>10s} {'2.5%':>10s} {'97.5%':>10s}   authors' mean / std")
    for i, (name, s) in enumerate(summary["posterior"].get("cubic", {}).items()):
        print(f"{name:6s} {s['mean']:12.5g} {s['std']:10.4g} {s['q2_5']:10.5g} {s['q97_5']:10.5g}   "
              f"{ref_post['mean'][i]:.5g} / {ref_post['std'][i]:.4g}")


if __name__ == "__main__":
    main()
