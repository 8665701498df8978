"""abcns and pyABC side by side (issue G): paper §3.1, §3.2, §4.1, several seeds, one
markdown table.

    python -m benchmarks.peers [--seeds 3] [--problems 3.1 3.2 4.1] [--quick] [--out PATH] [--json PATH]

Needs ``pip install -e '.[bench]'`` (pyABC); ``make bench-peers`` installs it and runs this.
Each problem is run by abcns, then by pyABC, for seeds 1..S; per tolerance level, each
tool's simulations and wall time are those of its first population accepted at an epsilon
at or below the level (its own schedule, no interpolation), and the tables give the median
and range over the seeds. ``--quick``: 100 particles, a few thousand simulations and 20 s
per run, one seed by default, written to out/peers-quick.md unless --out says otherwise
(a smoke run; the figures mean nothing).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from benchmarks.peers.cases import CASES, Case
from benchmarks.peers.tools import run_abcns, run_pyabc, warm_up

HERE = Path(__file__).resolve().parent
TOOLS = ("abcns", "pyABC")


def reach(run: dict, level: float) -> tuple[int, float] | None:
    """(cumulative simulations, cumulative wall time) at the first population with epsilon <= level."""
    for p in run["populations"]:
        if p["epsilon"] <= level:
            return p["sims"], p["wall"]
    return None


def med(values: list[float]) -> float:
    return float(np.median(values)) if values else float("nan")


def fmt_n(x: float) -> str:
    if not np.isfinite(x):
        return "—"
    return f"{x:,.0f}" if abs(x) >= 100 else f"{x:.3g}"


def fmt_s(x: float) -> str:
    if not np.isfinite(x):
        return "—"
    return f"{x:.3g}" if x < 100 else f"{x:,.0f}"


def cell(values: list[float], n_seeds: int, f=fmt_n) -> str:
    if not values:
        return f"not reached (0/{n_seeds})"
    s = f(med(values))
    if len(values) > 1:
        s += f" [{f(min(values))}–{f(max(values))}]"
    if len(values) < n_seeds:
        s += f" ({len(values)}/{n_seeds})"
    return s


def ratio(a: list[float], b: list[float]) -> str:
    if not a or not b:
        return "—"
    r = med(a) / med(b)
    return f"{r:.2g}" if r < 1 else f"{r:.3g}"


def level_rows(case: Case, runs: dict[str, list[dict]]) -> tuple[list[str], list[dict]]:
    n = len(runs["abcns"])
    lines = ["| ε ≤ | abcns simulations | pyABC simulations | ratio | abcns wall (s) | pyABC wall (s) | ratio |",
             "|---|---|---|---|---|---|---|"]
    data = []
    for level in case.levels:
        got = {t: [reach(r, level) for r in runs[t]] for t in TOOLS}
        sims = {t: [g[0] for g in got[t] if g] for t in TOOLS}
        wall = {t: [g[1] for g in got[t] if g] for t in TOOLS}
        data.append({"level": level, "sims": sims, "wall": wall,
                     "sims_ratio": med(sims["abcns"]) / med(sims["pyABC"]) if sims["abcns"] and sims["pyABC"] else None,
                     "wall_ratio": med(wall["abcns"]) / med(wall["pyABC"]) if wall["abcns"] and wall["pyABC"] else None,
                     "both_all": len(sims["abcns"]) == n and len(sims["pyABC"]) == n})
        a, b = sims["abcns"], sims["pyABC"]
        wa, wb = wall["abcns"], wall["pyABC"]
        lines.append(f"| {level:g} | {cell(a, n)} | {cell(b, n)} | {ratio(a, b)} "
                     f"| {cell(wa, n, fmt_s)} | {cell(wb, n, fmt_s)} | {ratio(wa, wb)} |")
    return lines, data


def end_rows(case: Case, runs: dict[str, list[dict]]) -> list[str]:
    names = [m.name for m in case.models]
    lines = ["| tool | seed | populations | final ε | simulations | wall (s) | stop | model probabilities | "
             f"truth in 95 % interval ({case.truth_model}) | max relative error of the mean |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for t in TOOLS:
        for r in runs[t]:
            probs = ", ".join(f"{k} {r['probs'].get(k, 0):.2f}" for k in names)
            post = r["posterior"]
            inside = f"{post['inside']}/{post['n']}" if post else "model dead"
            rel = f"{post['max_rel_error']:.2%}" if post else "—"
            lines.append(f"| {t} | {r['seed']} | {len(r['populations'])} | {r['final_epsilon']:.4g} | {r['n_simulations']:,} "
                         f"| {r['wall']:.3g} | {r['stop'] or 'budget/target'} | {probs} | {inside} | {rel} |")
    return lines


def acceptance_lines(case: Case, runs: dict[str, list[dict]]) -> list[str]:
    out = []
    for t in TOOLS:
        for r in runs[t]:
            acc = ", ".join(f"{p['acceptance']:.2f}" for p in r["populations"])
            out.append(f"- {t}, seed {r['seed']}: {acc}")
    return out


def right_model(case: Case, runs: list[dict]) -> str:
    ok = sum(1 for r in runs if r["probs"] and max(r["probs"], key=r["probs"].get) == case.truth_model
             and r["probs"][case.truth_model] > 0.5)
    return f"{ok}/{len(runs)}"


def versions() -> str:
    import numba
    import pyabc

    return (f"Python {platform.python_version()}, numpy {np.__version__}, numba {numba.__version__}, "
            f"pyABC {pyabc.__version__}, {os.cpu_count()} cores ({platform.machine()})")


def report(cases: list[Case], all_runs: dict[str, dict[str, list[dict]]], seeds: list[int], total_s: float,
           quick: bool) -> tuple[str, list[dict]]:
    md = ["# abcns vs pyABC, side by side", ""]
    if quick:
        md += ["**Quick smoke run (`--quick`): 100 particles, tiny budgets. These figures mean nothing.**", ""]
    md += [
        f"`python -m benchmarks.peers --seeds {len(seeds)}{' --quick' if quick else ''}`, "
        f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {versions()}; "
        f"the whole command took {total_s / 60:.1f} min. Seeds {', '.join(map(str, seeds))}; every cell is the median "
        "over the seeds with the range in brackets (and how many seeds reached the level when not all did).",
        "",
        "- **Same problems, simulators and distances.** Both tools call the numba kernels of `worker/simulators.py` "
        "on the same data. pyABC's model function runs one particle (the kernel on one row) and returns the "
        "trajectory on the fit window (oscillators) or the five g-and-k summaries; its distance is abcns' own, "
        "fixed (`abcns.NMSE`, or the Euclidean distance of the summaries, as `abcns.SummaryEuclidean`).",
        "- **abcns**: `abcns.run`, the paper's ABC-NS settings (N = 1000, α 0.3, β 0.6, f0 1.1, ε1 = 100) with "
        "today's defaults otherwise (the evidence variant; with the NMSE, the noise floor a job's spec gives it), "
        "in this process with the serial executor: **one core**, batches of 200, the in-kernel NMSE with early "
        "rejection (its own machinery). Stops at the paper's rule, the target ε, the decision tolerance (the noise "
        "floor, NMSE problems), or the budget, whichever first.",
        "- **pyABC**: `pyabc.ABCSMC` with population 1000 and otherwise its defaults (MedianEpsilon, the first ε "
        "from a calibration sample of the prior predictive, MultivariateNormalTransition, model perturbation "
        "kernel with stay probability 0.7, uniform model prior), `MulticoreEvalParallelSampler` on "
        f"**all {os.cpu_count()} cores**, its history in a temporary **sqlite file** per run (its default usage; "
        "not in memory). Stops at `minimum_epsilon` (the target) or the budget (`max_total_nr_simulations`, "
        "`max_walltime`; checked between populations, so the last population may overshoot). Its multicore "
        "runs reseed each worker from the OS, so they are not reproducible by seed.",
        "- **To a tolerance level**: the cumulative simulations (abcns' and pyABC's initial samples included) and "
        "wall time at each tool's first population accepted at ε at or below the level, from its own schedule; "
        "ratio = median abcns / median pyABC. Wall time is from the start of the run (numba kernels compiled "
        "beforehand, outside both clocks).",
        "- **Posterior accuracy**: the final population of the true model (weighted for pyABC, uniform for "
        "ABC-NS): how many parameters' 95 % intervals (2.5-97.5 % quantiles) hold the truth, and the largest "
        "relative error of the posterior mean over the parameters.",
        "",
        "## Summary",
        "",
        "| problem | lowest level both reach in every seed | simulations abcns / pyABC | wall time abcns / pyABC "
        "| right model: abcns | right model: pyABC |",
        "|---|---|---|---|---|---|",
    ]
    summary, sections = [], []
    for case in cases:
        runs = all_runs[case.key]
        lines, data = level_rows(case, runs)
        common = [d for d in data if d["both_all"]]
        pick = common[-1] if common else None
        rm = {t: right_model(case, runs[t]) for t in TOOLS}
        if pick:
            md.append(f"| §{case.key} | ε ≤ {pick['level']:g} | {pick['sims_ratio']:.2g} | {pick['wall_ratio']:.2g} "
                      f"| {rm['abcns']} | {rm['pyABC']} |")
        else:
            md.append(f"| §{case.key} | none | — | — | {rm['abcns']} | {rm['pyABC']} |")
        summary.append({"problem": case.key, "level": pick and pick["level"],
                        "sims_ratio": pick and pick["sims_ratio"], "wall_ratio": pick and pick["wall_ratio"],
                        "right_model": rm, "levels": [{k: v for k, v in d.items()} for d in data]})
        sections += [f"## {case.title}", "", f"Budget: {case.budget_note}.", "", "### To each tolerance", "", *lines, "",
                     "### End of each run", "", *end_rows(case, runs), "", "### Acceptance rate per population", "",
                     *acceptance_lines(case, runs), ""]
    md += ["", *sections]
    return "\n".join(md) + "\n", summary


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.peers", description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=None, help="seeds 1..S (default 3; 1 with --quick)")
    parser.add_argument("--problems", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--quick", action="store_true", help="a smoke run: 100 particles, tiny budgets")
    parser.add_argument("--out", type=Path, default=None,
                        help="default benchmarks/peers/RESULTS.md (with --quick: out/peers-quick.md, never the committed table)")
    parser.add_argument("--json", type=Path, default=None, help="also write every run's record as JSON")
    parser.add_argument("--db-dir", default=None, help="where pyABC's temporary sqlite files go (default: the system temp)")
    args = parser.parse_args(argv)
    try:
        import pyabc  # noqa: F401
    except ImportError:
        sys.exit("pyABC is not installed: pip install -e '.[bench]' (or make bench-peers)")
    seeds = list(range(1, (args.seeds or (1 if args.quick else 3)) + 1))
    start = time.monotonic()
    cases, all_runs = [], {}
    failures: list[str] = []
    for key in args.problems:
        case = CASES[key](args.quick)
        warm_up(case)
        cases.append(case)
        runs: dict[str, list[dict]] = {t: [] for t in TOOLS}
        for seed in seeds:
            for tool, fn in (("abcns", run_abcns), ("pyABC", lambda c, s: run_pyabc(c, s, args.db_dir))):
                try:
                    r = fn(case, seed)
                except Exception as err:
                    if tool == "abcns":
                        raise
                    failures.append(f"§{key} pyABC seed {seed}: {type(err).__name__}: {err} (retried once)")
                    print(failures[-1], flush=True)
                    r = fn(case, seed)
                runs[tool].append(r)
                print(f"§{key} {tool:5s} seed {seed}: {len(r['populations'])} populations, final ε {r['final_epsilon']:.4g}, "
                      f"{r['n_simulations']:,} simulations, {r['wall']:.2f} s, p = "
                      + ", ".join(f"{k} {v:.2f}" for k, v in r["probs"].items()), flush=True)
        all_runs[key] = runs
    text, summary = report(cases, all_runs, seeds, time.monotonic() - start, args.quick)
    if failures:
        text += "\n## Runs that raised\n\n" + "".join(f"- {f}\n" for f in failures)
    if args.out is None:
        args.out = Path("out/peers-quick.md") if args.quick else HERE / "RESULTS.md"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out}")
    if args.json:
        args.json.write_text(json.dumps({"summary": summary, "runs": all_runs}, indent=1, default=float))


if __name__ == "__main__":
    main()
