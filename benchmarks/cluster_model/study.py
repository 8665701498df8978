"""The model's two uses: validation against measured runs, and the design study.

    python -m benchmarks.cluster_model validate
    python -m benchmarks.cluster_model study [--quick] [--workers 1,2,...] [--designs ...]
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from benchmarks.cluster_model import measured
from benchmarks.cluster_model.costs import Costs, fit_runner_cpu, from_dask_figures
from benchmarks.cluster_model.model import Design, Pattern, replay
from benchmarks.cluster_model.trace import Trace

#: the validation's bound: |predicted - measured| efficiency (issue O)
TOLERANCE = 0.05
#: the worker's overhead per task on the 16-core machine: its "Dask alone" run at W = 1 with
#: 50 ms tasks (156 tasks in 8.07 s: 51.7 ms each, two always at the worker) less the sleep's overshoot
SIXTEEN_WORKER_TASK = 8.07 / 156 - 0.05 - 0.1e-3


def sixteen_costs(variant: str) -> Costs:
    """The 16-core machine's costs in the session of ``variant``'s measurements."""
    session = measured.SIXTEEN[variant]
    trace = Trace.load(session.trace)
    per_call = measured.LOCAL_COSTS["per_call"]
    per_task, background = fit_runner_cpu(session, per_call)
    engine, evaluator = session.engine
    rec = trace.recorded
    runner_scale = (engine - evaluator) / (rec["engine_us_per_sim"] - rec["evaluator_us_per_sim"])
    worker_scale = evaluator / rec["evaluator_us_per_sim"]
    # the store's work (zarr: Python on an event loop, like Dask's) scales as Dask's per-task CPU
    # does between the session and the machine the trace was recorded on
    store_scale = per_task / fit_runner_cpu(measured.LOCAL[variant], per_call)[0]
    return from_dask_figures(
        f"16 cores, {variant} session", per_task, per_call, background, SIXTEEN_WORKER_TASK, runner_scale,
        worker_scale, store_scale=store_scale, sources={
            "per task, background": f"fitted (2 parameters) to the session's Dask-floor CPU per task "
                                    f"({len(session.floor)} rows)",
            "per call": "measured on the 2-core machine (Dask's Python costs per task agree on both machines: "
                        "floor CPU per task at 1 and 2 workers 3.5 and 2.7 ms there, 3.4 and 2.9 here)",
            "worker_task": "the 'Dask alone' run, 1 worker, 50 ms tasks (51.7 ms per task)",
            "runner_scale": f"the step's CPU: engine µs/sim less the evaluator's, 16 cores ({engine} - {evaluator}) "
                            "over the trace's",
            "worker_scale": "the evaluator's µs/sim, 16 cores over the trace's",
            "store_scale": "Dask's fitted CPU per task, this session over the 2-core machine's same-variant session",
            "the rest": "as costs.py says (latency, batching intervals, GIL switch interval, the loop's split)",
        })


def local_costs(variant: str) -> Costs:
    """This 2-core machine's costs in the session of ``variant``'s measurements: as for the
    16-core machine, Dask's CPU per task and per second fitted to the session's Dask floor;
    the rest measured here (``python -m benchmarks.cluster_model costs``); the trace was
    recorded here (no scaling)."""
    m = measured.LOCAL_COSTS
    per_task, background = fit_runner_cpu(measured.LOCAL[variant], m["per_call"])
    return from_dask_figures(
        f"2 cores, {variant} session", per_task, m["per_call"], background, m["worker_task"], 1.0, 1.0,
        sources={"per task, background": f"fitted (2 parameters) to the session's Dask-floor CPU per task "
                                         f"({len(measured.LOCAL[variant].floor)} rows)",
                 "per call, worker_task, sleep_overshoot": "measured: benchmarks/measurements/2026-11-25-2-cores.md",
                 "the rest": "as costs.py says"}
    ).scaled(sleep_overshoot=m["overshoot"])


@dataclass
class Row:
    what: str
    workers: int
    measured: float
    predicted: float
    detail: str = ""

    @property
    def ok(self) -> bool:
        return abs(self.predicted - self.measured) <= TOLERANCE


def validation_rows() -> list[Row]:
    rows: list[Row] = []
    for machine, sessions, costs_of in (("16 cores", measured.SIXTEEN, sixteen_costs),
                                        ("2 cores", measured.LOCAL, local_costs)):
        for variant, session in sessions.items():
            costs = costs_of(variant)
            trace = Trace.load(session.trace)
            for cluster in ("runner", "own") if machine == "2 cores" else ("runner",):
                jobs = session.jobs if cluster == "runner" else session.stock_jobs
                where = "LocalCluster" if cluster == "runner" else "stock scheduler"
                for w, (eff, executed, cpu_us) in jobs.items():
                    out = replay(trace, w, 0.002, costs, Design(scheduler=cluster))
                    rows.append(Row(f"{machine}, {variant}, job, {where}", w, eff, out.efficiency,
                                    f"steady {out.steady:.2f}; executed {executed} / {out.executed}; "
                                    f"runner CPU µs/sim {cpu_us:.0f} / {1e6 * out.runner_busy / trace.simulations:.0f}"))
            for w, (eff, cpu_ms) in session.floor.items():
                out = Pattern("floor", w, 0.05, costs, units=session.units, rounds=session.rounds).run()
                rows.append(Row(f"{machine}, {variant} session, Dask floor", w, eff, out.efficiency,
                                f"runner CPU ms/task {cpu_ms} / {1e3 * out.runner_busy / (session.units * session.rounds):.1f}"))
    costs = design_costs()  # what the README's "many cores" figures were predicted with
    for (trace_name, ms, w), (eff, executed) in measured.PREDICTED_THEN_MEASURED.items():
        trace = Trace.load(trace_name)
        out = replay(trace, w, ms / 1e3, costs)
        rows.append(Row(f"16 cores (second session), {trace_name}, {ms:g} ms, job, LocalCluster", w, eff,
                        out.efficiency, f"steady {out.steady:.2f}; executed {executed} / {out.executed}"))
    return rows


#: the assumed parameters, each moved within what is plausible: (label, change of the costs)
SENSITIVITY = [
    ("latency 0.1 ms", {"latency": 0.1e-3, "gather_latency": 0.4e-3}),
    ("latency 1 ms", {"latency": 1e-3, "gather_latency": 4e-3}),
    ("worker overhead x0.7", {"worker_task": 0.7 * SIXTEEN_WORKER_TASK}),
    ("worker overhead x1.3", {"worker_task": 1.3 * SIXTEEN_WORKER_TASK}),
    ("per call 6.6 ms (the 'Dask alone' fit)", {"sched_call": 6.6e-3 - 0.55e-3}),
    ("no GIL convoy (round robin)", {"convoy": False}),
    ("step CPU x0.8", {"runner_scale": 0.8}),
    ("step CPU x1.25", {"runner_scale": 1.25}),
    ("store CPU x0.5", {"store_scale": 0.5}),
    ("store CPU x2", {"store_scale": 2.0}),
]

#: the event loops' CPU per task, moved between submission and completion (the split is assumed)
SPLITS = [
    ("loop split 20/30/12/38 %", {"sched_submit": 0.20, "sched_finish": 0.30, "sched_release": 0.12, "gather": 0.38}),
    ("loop split 10/40/10/40 %", {"sched_submit": 0.10, "sched_finish": 0.40, "sched_release": 0.10, "gather": 0.40}),
]


def print_sensitivity() -> None:
    """The 16-core job rows again, each assumed parameter moved (runner_scale as a factor)."""
    print("\n## Sensitivity: the 16-core job rows with one assumed parameter moved (predicted efficiency)")
    cases = [(v, w, eff) for v, s in measured.SIXTEEN.items() for w, (eff, _, _) in s.jobs.items()]
    print("| change | " + " | ".join(f"{v} W={w} ({eff:.2f})" for v, w, eff in cases) + " | rows within 0.05 |")
    print("|---|" + "---:|" * (len(cases) + 1))
    for label, change in [("none", {}), *SENSITIVITY, *SPLITS]:
        cells, ok = [], 0
        for v, w, eff in cases:
            base = sixteen_costs(v)
            c = dict(change)
            for factor in ("runner_scale", "store_scale"):
                if factor in c:
                    c[factor] = getattr(base, factor) * float(c[factor])
            if "gather" in c:  # a split: shares of the loop's CPU per task
                total = base.sched_submit + base.sched_finish + base.sched_release + base.gather
                c = {k: v * total for k, v in c.items()}
            out = replay(Trace.load(measured.SIXTEEN[v].trace), w, 0.002, base.scaled(**c))
            cells.append(f"{out.efficiency:.2f}")
            ok += abs(out.efficiency - eff) <= TOLERANCE
        print(f"| {label} | " + " | ".join(cells) + f" | {ok} of {len(cases)} |", flush=True)


def fed_rows() -> list[Row]:
    """The 16-core "Dask alone" runs (not a bound of the validation: their code is not in
    the repository, so the pattern is replayed as described: one ``client.map`` per task)."""
    costs = sixteen_costs("paper")
    rows = []
    for (w, seconds), (n, eff) in measured.FED.items():
        p = Pattern("fed", w, seconds, costs, duration=measured.FED_DURATION_S)
        out = p.run()
        rows.append(Row(f"16 cores, Dask alone, {1e3 * seconds:g} ms tasks", w, eff, out.efficiency,
                        f"tasks {n} / {round(p.slept / seconds)}"))
    return rows


def print_costs(costs: Costs) -> None:
    print(f"\n### costs: {costs.name}")
    keys = ["submit_call", "submit_task", "release_task", "sched_call", "sched_submit", "sched_finish", "sched_release",
            "gather", "gather_latency", "worker_task", "latency", "background", "sleep_overshoot"]
    print("| " + " | ".join(keys) + " | runner_scale | worker_scale | store_scale |")
    print("|" + "---:|" * (len(keys) + 3))
    print("| " + " | ".join(f"{1e3 * getattr(costs, k):.3f}" for k in keys)
          + f" | {costs.runner_scale:.2f} | {costs.worker_scale:.2f} | {costs.store_scale:.2f} |")
    print("(ms; background in ms of CPU per second)")
    for k, v in costs.sources.items():
        print(f"- {k}: {v}")


def print_validation() -> bool:
    print("# Cluster model: predicted vs measured efficiency (bound: within "
          f"{TOLERANCE} on every row)")
    for variant in measured.SIXTEEN:
        print_costs(sixteen_costs(variant))
    for variant in measured.LOCAL:
        print_costs(local_costs(variant))
    rows = validation_rows()
    print("\n| run | workers | measured | predicted | difference | within | detail (measured / predicted) |")
    print("|---|---:|---:|---:|---:|---|---|")
    for r in rows:
        print(f"| {r.what} | {r.workers} | {r.measured:.2f} | {r.predicted:.2f} | {r.predicted - r.measured:+.2f} | "
              f"{'yes' if r.ok else '**no**'} | {r.detail} |")
    print("\nNot bound by the validation (the pattern's code is not in the repository):")
    print("\n| run | workers | measured | predicted | difference | detail (measured / predicted) |")
    print("|---|---:|---:|---:|---:|---|")
    for r in fed_rows():
        print(f"| {r.what} | {r.workers} | {r.measured:.2f} | {r.predicted:.2f} | {r.predicted - r.measured:+.2f} | "
              f"{r.detail} |")
    bad = [r for r in rows if not r.ok]
    print(f"\n{len(rows) - len(bad)} of {len(rows)} rows within {TOLERANCE}")
    return not bad


# -- the design study ------------------------------------------------------------------------------

WORKERS = [1, 2, 4, 8, 14, 16, 32, 64, 128, 256, 512, 1024]

#: (label, trace, seconds per simulation): traces recorded with today's step (the N = 1000 ones
#: at 3d82148, the rest at c90f968; `record --particles N [--batch-size B]`)
SCENARIOS = [
    ("N = 1000, 20 ms, batch 25", "evidence-1000-warm", 0.020),
    ("N = 1000, 2 ms, batch 25", "evidence-1000-warm", 0.002),
    ("N = 1000, 20 ms, batch 5", "evidence-1000-b5-warm", 0.020),
    ("N = 1000, 2 ms, batch 5", "evidence-1000-b5-warm", 0.002),
    ("N = 5000, 20 ms, batch 25", "evidence-5000", 0.020),
    ("N = 5000, 20 ms, batch 5", "evidence-5000-b5", 0.020),
    ("N = 20000, 20 ms, batch 25", "evidence-20000", 0.020),
    ("N = 50000, 20 ms, batch 25", "evidence-50000", 0.020),
]

#: today's design (a LocalCluster: the scheduler in the runner's process), then the scheduler
#: in its own process (as on any real cluster), then the look-ahead designs (shares of the next
#: population's expected batches), with task sizes; "carry": the surplus put to use (t + 1
#: first consumes t's next batches). The step is each trace's own (today's code).
DESIGNS = [
    Design(),
    Design(scheduler="own"),
    Design(lookahead_share=0.25, scheduler="own"),
    Design(lookahead_share=0.5, scheduler="own"),
    Design(lookahead_share=1.0, scheduler="own"),
    Design(lookahead_share=0.5, task_batches=4, scheduler="own"),
    Design(carry_share=0.25, scheduler="own"),
    Design(carry_share=0.5, scheduler="own"),
]
#: the designs of ``study --quick``: today's, its own scheduler, look-ahead 0.5x, carry-over 0.25x
QUICK = (0, 1, 3, 6)

#: issue O's targets: (scenario prefix, workers, efficiency at least)
TARGETS = [("N = 1000, 20 ms", 8, 0.9), ("N = 1000, 20 ms", 14, 0.85), ("N = 1000, 2 ms", 8, 0.9),
           ("N = 1000, 2 ms", 14, 0.85), ("N = 1000, 20 ms", 64, 0.8), ("N = 5000, 20 ms", 64, 0.8),
           ("N = 5000, 20 ms", 256, 0.7), ("N = 20000, 20 ms", 256, 0.7), ("N = 50000, 20 ms", 256, 0.7)]

BREAKDOWN_KEYS = ["useful", "surplus", "task overhead", "idle: dispatch", "idle: tail", "step", "start", "end"]


def design_costs() -> Costs:
    """The design study's costs: the 16-core machine in its paper session (the one the model
    validates best), with the evidence variant's step and evaluator ratios."""
    evidence = sixteen_costs("evidence")
    return sixteen_costs("paper").scaled(runner_scale=evidence.runner_scale, worker_scale=evidence.worker_scale)


def design_study(workers: list[int], designs: list[Design], scenarios=SCENARIOS, costs: Costs | None = None,
                 breakdown_at: tuple[int, ...] = (8, 64, 256)) -> dict:
    costs = costs or design_costs()
    print("# Design study: predicted efficiency (the 16-core machine's costs, paper session; evidence variant's "
          "traces; efficiency = today's simulations x their time / (W x wall); in brackets the steady figure, "
          "populations 2 on, without the run's start and end)")
    print_costs(costs)
    results = {}
    for label, trace_name, seconds in scenarios:
        trace = Trace.load(trace_name)
        print(f"\n## {label} ({trace.simulations} simulations, {trace.job['populations']} populations)")
        print("| design | " + " | ".join(f"W={w}" for w in workers) + " |")
        print("|---|" + "---:|" * len(workers))
        for d in designs:
            start = time.perf_counter()
            cells = []
            for w in workers:
                out = replay(trace, w, seconds, costs, d)
                results[(label, d.label(), w)] = out
                cells.append(f"{out.efficiency:.2f} ({_nan(out.steady)})")
            print(f"| {d.label()} | " + " | ".join(cells) + f" |  <!-- {time.perf_counter() - start:.0f} s -->",
                  flush=True)
        for w in breakdown_at:
            if w not in workers:
                continue
            print(f"\nwhere the workers' time goes at W={w} (share of W x wall; look-ahead rows beyond today's count "
                  "are in surplus):")
            print("| design | " + " | ".join(BREAKDOWN_KEYS) + " | runner CPU | scheduler CPU |")
            print("|---|" + "---:|" * (len(BREAKDOWN_KEYS) + 2))
            for d in designs:
                out = results[(label, d.label(), w)]
                sh = out.shares()
                busy = f"{out.runner_busy / out.wall:.2f} | {out.scheduler_busy / out.wall:.2f}"
                print(f"| {d.label()} | " + " | ".join(f"{sh.get(k, 0.0):.2f}" for k in BREAKDOWN_KEYS) + f" | {busy} |")
    print("\n## issue O's targets")
    for prefix, w, least in TARGETS:
        if w not in workers:
            continue
        best = sorted(((out.efficiency, key[1], key[0]) for key, out in results.items()
                       if key[0].startswith(prefix) and key[2] == w), reverse=True)
        reach = [f"{d} ({label.split(', ')[-1]}): {e:.2f}" for e, d, label in best if e >= least]
        print(f"- {prefix}, W={w}, >= {least}: " + ("; ".join(reach) if reach else
              f"none (best {best[0][0]:.2f}: {best[0][1]}, {best[0][2]})" if best else "not run"))
    return results


def _nan(x: float) -> str:
    return "" if math.isnan(x) else f"{x:.2f}"
