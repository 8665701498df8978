"""Model selection on paper §4.1 (cubic vs cubic-quintic Duffing) over many seeds: how often
the right model wins with p >= 0.9, and the simulations to each tolerance.

    python -m benchmarks.model_selection [--seeds 1-20] [--data 41] [--variant evidence|paper]
                                         [--processes 2] [--max-populations N]

``--data 41`` is the committed ``examples/duffing_41`` data; any other number makes a new data
set the same way (``examples.make_data.duffing_41(seed)``: another force and noise), to check
that the defaults were not fitted to one data set. Each seed runs in-process (serial
executor) with the spec of ``examples/duffing_41/spec.yaml``; seeds run in parallel processes.
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

SPEC = Path(__file__).resolve().parents[1] / "examples" / "duffing_41" / "spec.yaml"
LEVELS = (10.0, 1.0, 0.1, 0.015)
TRUE_MODEL = "cubic-quintic"


def seeds_of(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def one(seed: int, data: int, variant: str, max_populations: int | None) -> dict:
    from abcns import run
    from examples.make_data import duffing_41
    from service.spec import build, load

    spec, base = load(SPEC)
    if data != 41:
        made = duffing_41(data)
        spec = spec.model_copy(update={"data": spec.data.model_copy(
            update={"input": made["force"].tolist(), "observed": made["displacement"].tolist()})})
    spec = spec.model_copy(update={"sampler": spec.sampler.model_copy(update={"variant": variant})})
    job = build(spec, base)
    stop = job.stop if max_populations is None else replace(job.stop, max_populations=max_populations)
    start = time.monotonic()
    r = run(job.models, job.evaluate, job.settings, stop, seed=seed)
    cum = r.n_pilot_simulations + np.cumsum([p.n_simulations for p in r.populations])
    to = {lvl: next((int(c) for p, c in zip(r.populations, cum) if p.epsilon <= lvl), None) for lvl in LEVELS}
    p = r.model_probabilities()
    return {"seed": seed, "p_true": p[TRUE_MODEL], "stop": r.stop_reason.value, "populations": len(r.populations),
            "simulations": r.n_simulations, "epsilon": r.final.epsilon, "to": to, "died": r.died_at(),
            "wall_s": time.monotonic() - start, "warnings": r.summary()["warnings"]}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", default="1-20")
    parser.add_argument("--data", type=int, default=41, help="41: the committed data; else a data set made with this seed")
    parser.add_argument("--variant", default="evidence", choices=("evidence", "paper"))
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--max-populations", type=int, default=None)
    parser.add_argument("--json", type=Path, default=None, help="also write the rows as JSON")
    args = parser.parse_args()
    seeds = seeds_of(args.seeds)
    start = time.monotonic()
    with ProcessPoolExecutor(args.processes) as pool:
        rows = list(pool.map(one, seeds, [args.data] * len(seeds), [args.variant] * len(seeds),
                             [args.max_populations] * len(seeds)))
    print(f"## §4.1 model selection, data {args.data}, variant {args.variant}, seeds {args.seeds} "
          f"({time.monotonic() - start:.0f} s on {args.processes} processes)\n")
    print("| seed | p(cubic-quintic) | stop | populations | final ε | simulations | to ε ≤ 10 | to ε ≤ 1 | to ε ≤ 0.1 "
          "| to ε ≤ 0.015 | cubic dies at | wall (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        to = " | ".join(f"{r['to'][lvl]:,}" if r["to"][lvl] is not None else "—" for lvl in LEVELS)
        print(f"| {r['seed']} | {r['p_true']:.3f} | {r['stop']} | {r['populations']} | {r['epsilon']:.4g} | "
              f"{r['simulations']:,} | {to} | {r['died'].get('cubic', '—')} | {r['wall_s']:.1f} |")
    right = sum(r["p_true"] >= 0.9 for r in rows)
    reached = [r["to"][0.015] for r in rows if r["to"][0.015] is not None]
    print(f"\nright model with p >= 0.9: {right} of {len(rows)}")
    if reached:
        print(f"simulations to ε ≤ 0.015: median {int(np.median(reached)):,} (range {min(reached):,}-{max(reached):,}, "
              f"{len(reached)} of {len(rows)} seeds reach it)")
    undecided = [r["seed"] for r in rows if r["warnings"]]
    if undecided:
        print(f"seeds with a warning: {undecided}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
