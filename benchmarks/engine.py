"""Engine benchmark: simulations and wall time to reach each tolerance, acceptance per
population, for the authors' demo and paper §3.1 (ABC-NS, and ABC-SMC on ABC-NS's own
tolerance schedule). Serial, in-process, reference numpy simulators.

    python -m benchmarks.engine [--seed N] [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from abcns import Result, SMCSettings, StopRules, run
from examples.paper import authors_demo, linear_31


def table(title: str, r: Result) -> None:
    print(f"\n## {title}: {r.algorithm}, stop {r.stop_reason.value}, {len(r.populations)} populations, "
          f"{r.n_simulations} simulations, {r.wall_time_s:.2f} s")
    print(f"{'t':>3} {'epsilon':>11} {'acceptance':>10} {'sims':>6} {'cum sims':>9} {'cum s':>7}  model probabilities")
    cum = r.n_pilot_simulations
    for p in r.populations:
        cum += p.n_simulations
        probs = " ".join(f"{v:.2f}" for v in p.model_probabilities)
        print(f"{p.t:3d} {p.epsilon:11.5g} {p.acceptance_rate:10.3f} {p.n_simulations:6d} {cum:9d} {p.elapsed_s:7.2f}  {probs}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--quick", action="store_true", help="3 populations each (a smoke run)")
    args = parser.parse_args()
    quick = StopRules(max_populations=3) if args.quick else None

    demo = authors_demo()
    r = run(demo.models, demo.evaluate, demo.settings, quick or demo.stop, seed=args.seed)
    table("authors' demo (N 1000, kernel weights, 1 RK4 step per sample)", r)

    lin = linear_31()
    ns = run(lin.models, lin.evaluate, lin.settings, quick or lin.stop, seed=args.seed)
    table("paper §3.1 linear", ns)
    smc = run(lin.models, lin.evaluate, SMCSettings(particles=1000, batch_size=200,
                                                    schedule=tuple(p.epsilon for p in ns.populations)),
              StopRules(max_simulations=2_000_000), seed=args.seed)
    table("paper §3.1 linear, ABC-SMC on the ABC-NS schedule", smc)
    start = time.perf_counter()
    print(f"\nsummary: §3.1 simulations ABC-NS {ns.n_simulations} vs ABC-SMC {smc.n_simulations} "
          f"(ratio {ns.n_simulations / smc.n_simulations:.2f}); mean acceptance "
          f"{np.mean([p.acceptance_rate for p in ns.populations[1:]] or [np.nan]):.2f} vs "
          f"{np.mean([p.acceptance_rate for p in smc.populations[1:]] or [np.nan]):.2f} (populations 2+)")
    del start


if __name__ == "__main__":
    main()
