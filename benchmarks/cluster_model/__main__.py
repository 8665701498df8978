"""python -m benchmarks.cluster_model {validate, study, record, costs, replay, queue}: see the package's docstring."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from benchmarks.cluster_model.trace import TRACES


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.cluster_model",
                                     description="The cluster model of issue O (docs/benchmarks.md).")
    sub = parser.add_subparsers(dest="command", required=True)
    val = sub.add_parser("validate", help="predicted vs measured efficiency, every measured row; exit 1 if one is off")
    val.add_argument("--sensitivity", action="store_true", help="also the 16-core rows with each assumed cost moved")
    study = sub.add_parser("study", help="the design study: predicted efficiency at 1-1,024 workers")
    study.add_argument("--workers", type=_ints, default=None, help="worker counts (default 1,2,4,...,1024)")
    study.add_argument("--quick", action="store_true", help="fewer designs and worker counts (a minute)")
    study.add_argument("--scenarios", default=None, help="scenario numbers to run, e.g. 1,3 (default: all)")
    rec = sub.add_parser("record", help="record a trace (benchmarks.scale's job, serial, in this process)")
    rec.add_argument("--variant", choices=["paper", "evidence"], default="evidence")
    rec.add_argument("--particles", type=int, default=1000)
    rec.add_argument("--populations", type=int, default=10)
    rec.add_argument("--batch-size", type=int, default=25)
    rec.add_argument("--out", type=Path, default=None, help=f"default: {TRACES}/<variant>-<particles>[-b<batch>].json")
    costs = sub.add_parser("costs", help="measure Dask's per-task costs on this machine")
    costs.add_argument("--workers", default="1,2")
    costs.add_argument("--rounds", type=int, default=40)
    one = sub.add_parser("replay", help="one replay: efficiency and where the time goes")
    one.add_argument("trace")
    one.add_argument("--workers", type=_ints, default=[1, 8, 14])
    one.add_argument("--sleep-ms", type=float, default=2.0)
    one.add_argument("--lookahead", type=float, default=0.0, help="look-ahead: a share of the expected batches")
    one.add_argument("--carry", type=float, default=0.0, help="carry-over: a share of the expected batches")
    one.add_argument("--task-batches", type=int, default=None)
    one.add_argument("--step-ms", type=float, default=None)
    one.add_argument("--scheduler", choices=["runner", "own"], default="runner")
    q = sub.add_parser("queue", help="a queue of jobs on one cluster (issue U): validation, predicted utilization")
    q.add_argument("--workers", type=_ints, default=[14, 64, 256])
    q.add_argument("--jobs", type=_ints, default=None, help="jobs in the queue, one count per worker count "
                   "(default: as many as workers)")
    q.add_argument("--trace", default=None, help="one trace (default: evidence-1000-warm at 2 and 20 ms)")
    q.add_argument("--sleep-ms", type=float, default=2.0, help="with --trace")
    q.add_argument("--dispatch-ms", type=float, default=None, help="from a slot freeing to the next job's start")
    q.add_argument("--turn-s", type=float, default=30.0, help="the service's turns (0: none)")
    q.add_argument("--skip-validation", action="store_true")
    q.add_argument("--share", type=float, default=None, metavar="EXPONENT",
                   help="each spread job's tasks in flight sized on its share of the worker threads, its tasks up to "
                   "(threads / share)^EXPONENT x MAX_TASK_SECONDS (a design, not built)")
    args = parser.parse_args(argv)
    if args.command == "queue":
        from benchmarks.cluster_model.queue import DISPATCH_S, QUEUES, print_queue
        from benchmarks.cluster_model.queue import print_validation as print_queue_validation

        ok = True if args.skip_validation else print_queue_validation()
        queues = QUEUES if args.trace is None else [(args.trace, args.sleep_ms)]
        dispatch = DISPATCH_S if args.dispatch_ms is None else args.dispatch_ms / 1e3
        print_queue(args.workers, args.jobs, queues, dispatch, args.turn_s or None, args.share)
        return 0 if ok else 1

    if args.command == "validate":
        from benchmarks.cluster_model.study import print_sensitivity, print_validation

        ok = print_validation()
        if args.sensitivity:
            print_sensitivity()
        return 0 if ok else 1
    if args.command == "study":
        from benchmarks.cluster_model.study import DESIGNS, QUICK, SCENARIOS, WORKERS, design_study

        workers = args.workers or ([1, 8, 14, 64, 256] if args.quick else WORKERS)
        designs = [DESIGNS[i] for i in QUICK] if args.quick else DESIGNS
        chosen = SCENARIOS if args.scenarios is None else [SCENARIOS[i - 1] for i in _ints(args.scenarios)]
        design_study(workers, designs, chosen)
        return 0
    if args.command == "record":
        from benchmarks.cluster_model.trace import record

        trace = record(args.variant, args.particles, args.populations, args.batch_size)
        out = args.out or TRACES / f"{trace.label}.json"
        trace.save(out)
        print(f"{out}: {trace.simulations} simulations in {len(trace.populations)} populations")
        return 0
    if args.command == "costs":
        from benchmarks.cluster_model import dask_costs

        dask_costs.main(["--workers", args.workers, "--rounds", str(args.rounds)])
        return 0
    if args.command == "replay":
        from benchmarks.cluster_model.model import Design, replay
        from benchmarks.cluster_model.study import BREAKDOWN_KEYS, design_costs, sixteen_costs
        from benchmarks.cluster_model.trace import Trace

        trace = Trace.load(args.trace)
        # the paper variant: its own session's costs; the evidence variant: the design study's
        costs = sixteen_costs("paper") if trace.job.get("variant") == "paper" else design_costs()
        design = Design(lookahead_share=args.lookahead, carry_share=args.carry, task_batches=args.task_batches,
                        step_s=None if args.step_ms is None else args.step_ms / 1e3, scheduler=args.scheduler)
        print(f"{trace.label}, {args.sleep_ms:g} ms per simulation, {design.label()}, costs: {costs.name}")
        print("| workers | efficiency | steady | wall s | executed | " + " | ".join(BREAKDOWN_KEYS) + " |")
        print("|---:|---:|---:|---:|---:|" + "---:|" * len(BREAKDOWN_KEYS))
        for w in args.workers:
            out = replay(trace, w, args.sleep_ms / 1e3, costs, design)
            sh = out.shares()
            print(f"| {w} | {out.efficiency:.3f} | {out.steady:.3f} | {out.wall:.2f} | {out.executed} | "
                  + " | ".join(f"{sh.get(k, 0.0):.2f}" for k in BREAKDOWN_KEYS) + " |")
        return 0
    return 2


if __name__ == "__main__":
    sys.exit(main())
