"""Studies on the nested families (issue V): confusion matrix, calibration, coverage, SBC.

    python -m benchmarks.study --family duffing|boucwen --datasets 40 --out DIR [--workers 2]
                               [--noise-share 0.01] [--seed 1]

``duffing``: the nested Duffing family of benchmarks.nested_models (a Gaussian force, std 10 N,
1000 samples at 100 Hz, fit on the first 500, 4 RK4 substeps, §4.1's sampler settings, the
evidence variant to the decision tolerance) with three candidates, linear (c, k), cubic (c, k,
k3 ~ U(0, 1e4)) and cubic-quintic (c, k, k3, k5 ~ U(0, 1e6)): the extra coefficients' priors
hold 0. ``boucwen``: benchmarks.boucwen_exponents' default spec with the Bouc-Wen candidates
n = 1, 2, 3. Each data set's true model is drawn uniformly, its parameters from the priors, and
1 % noise of its clean response's RMS is added (``abcns study``, service/run/study.py);
``--noise-known``: the spec states ``data.noise_std`` (each data set's own), as
benchmarks.exact_bayes's runs do, else the noise floor is estimated from each run. The
study runs on an embedded cluster of ``--workers`` processes, one job per worker; run again
with the same arguments to resume. Printed: the report (``abcns summary DIR``), then the
targets (ECE <= 0.05, 95 % intervals holding the truth in 92-98 % of pairs, rank histograms
not rejected at 1 %) with the binomial standard error of the coverage.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from service.spec import parse


def duffing_spec() -> dict:
    from benchmarks import nested_models as nm

    data = nm.make_data({"k3": 1e3, "k5": 0.0}, 0.01, 1)  # the template: force, sampling, windows
    spec = nm.spec_of("duffing", data, True)
    base = {"fixed": {"m": 1}, "simulator": "duffing", "integrator": {"substeps": 4}}
    spec["models"] = [
        {**base, "name": "linear", "fixed": {"m": 1, "k3": 0, "k5": 0}, "priors": dict(nm.PRIORS)},
        {**base, "name": "cubic", "fixed": {"m": 1, "k5": 0}, "priors": {**nm.PRIORS, "k3": [0, 1e4]}},
        {**base, "name": "cubic-quintic", "priors": {**nm.PRIORS, "k3": [0, 1e4], "k5": [0, 1e6]}}]
    spec["name"] = "study-duffing"
    return spec


def boucwen_spec() -> dict:
    from benchmarks import boucwen_exponents as bw

    spec = bw.spec_of(bw.make_data(1, 1), 1)
    spec["models"] = spec["models"][1:]  # Bouc-Wen n = 1, 2, 3
    spec["name"] = "study-boucwen"
    return spec


def main(argv: list[str] | None = None) -> None:
    from distributed import Client

    from service.report.study import report_lines, study_report
    from service.run.dask_executor import local_cluster
    from service.run.study import parse_request, read_study, run_study, store_paths

    parser = argparse.ArgumentParser()
    parser.add_argument("--family", choices=("duffing", "boucwen"), default="duffing")
    parser.add_argument("--datasets", type=int, default=40)
    parser.add_argument("--noise-share", type=float, default=0.01)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--noise-known", action="store_true",
                        help="the spec states data.noise_std (each data set's own), as benchmarks.exact_bayes does")
    args = parser.parse_args(argv)
    raw = duffing_spec() if args.family == "duffing" else boucwen_spec()
    if args.noise_known:
        raw["data"]["noise_std"] = 1e-6  # replaced by each data set's own noise std (service/run/study.py)
    spec = parse(raw)
    request = parse_request({"datasets": args.datasets, "noise_share": args.noise_share, "seed": args.seed})
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    with local_cluster(args.workers) as cluster, Client(cluster) as client:
        outcomes = run_study(client, spec, None, request, args.out, local_s=0.025)
    wall = time.monotonic() - start
    held = read_study(args.out)
    report = study_report(held, store_paths(args.out, held))
    print("\n".join(report_lines(report)))
    print(f"study wall {wall:.0f} s on {args.workers} workers; {sum(o.status == 'finished' for o in outcomes)} finished")
    print_targets(report)


def print_targets(report: dict) -> None:
    cov = report["coverage"]["all"]
    n = cov["n"]
    if not n:
        return
    c95 = cov["cover95"]
    se = math.sqrt(c95 * (1 - c95) / n) if 0 < c95 < 1 else math.sqrt(0.95 * 0.05 / n)
    cal = report["calibration"]
    print(f"target ECE <= 0.05: {cal['ece']:.3f} (bootstrap 95 % {cal.get('ece_interval')}; calibrated would give "
          f"{cal.get('ece_if_calibrated')})")
    print(f"target 95 % coverage in 92-98 %: {100 * c95:.1f} % +- {100 * se:.1f} (binomial se) of {n} pairs; "
          f"50 %: {100 * cov['cover50']:.1f} %")
    for test in ("p_value", "ks_p_value"):
        rejected = [k for k, s in report["sbc"].items() if s[test] is not None and s[test] < 0.01]
        print(f"target rank histograms not rejected at 1 % ({'chi-square' if test == 'p_value' else 'KS'}): "
              f"{len(report['sbc']) - len(rejected)} of {len(report['sbc'])}"
              + (f"; rejected: {', '.join(rejected)}" if rejected else ""))


if __name__ == "__main__":
    main()
