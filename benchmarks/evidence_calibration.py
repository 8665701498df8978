"""Is the evidence's standard error right? The closed-form toys of ``tests/closed_form.py``
over many seeds: z-scores of log Z against the exact ABC evidence, and the model
probabilities against the exact ones.

    python -m benchmarks.evidence_calibration [--seeds 1-200] [--toys two_models,line_and_disc,balls_4_and_5]
                                              [--processes 2] [--batch 200] [--json rows.json]

A check is one model in one population, from the third population on (as
``tests/test_closed_form.py``'s ``check_evidence``), where the model holds at least 100
particles: z = (log Z - exact) / its standard error. If the standard error is right, z is
close to a standard normal: sd 1, |z| > 3 in 0.27 % of checks, |z| > 4 in 0.006 %. The
largest |p - exact| is over every model of every population from the third on, and p's own
z-scores, (p - exact) / its standard error, are those of the first model there. Deaths by
probability are counted with the exact probability of the model at that population's next
tolerance (a death is wrong when that exact p is above the threshold).
"""

from __future__ import annotations

import os

# one BLAS thread per process, before numpy (as service/__init__.py does for the runner: on
# small matrices and a shared 2-core machine, BLAS threads only spin: 0.8 s a seed against
# 10 s under load)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse
import json
import math
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from benchmarks.model_selection import seeds_of

#: toy -> (NSSettings keywords, StopRules keywords); the tests' settings
TOYS = {
    "two_models": (dict(epsilon_initial=2.0), dict(epsilon_target=0.1)),
    "line_and_disc": (dict(epsilon_initial=0.3), dict(epsilon_target=0.003)),
    "balls_4_and_5": (dict(epsilon_initial=0.45), dict(epsilon_target=0.03)),
}
MIN_PARTICLES = 100


def problem(toy: str):
    """(models, evaluate, exact log Z as a function of eps) of a toy."""
    from tests import closed_form as cf

    if toy == "two_models":
        models, evaluate = cf.two_models()
        return models, evaluate, lambda eps: np.log([cf.evidence_two_models(eps, a) for a in (5.0, 20.0)])
    if toy == "line_and_disc":
        models, evaluate = cf.line_and_disc()
        return models, evaluate, cf.line_and_disc_log_evidence
    models, evaluate = cf.balls_4_and_5()
    return models, evaluate, cf.balls_4_and_5_log_evidence


def one(toy: str, seed: int, batch: int) -> dict:
    """The checks of one toy and seed."""
    from abcns import NSSettings, StopRules, run
    from abcns.evidence import IMPROBABLE, probabilities

    models, evaluate, exact_log_z = problem(toy)
    ns, stop = TOYS[toy]
    settings = NSSettings(particles=1000, batch_size=batch, **ns)
    r = run(models, evaluate, settings, StopRules(min_epsilon_decrease=None, **stop), seed=seed)
    checks, p_err, p_z, deaths = [], 0.0, [], []
    for pop in r.populations:
        ev = pop.evidence
        exact = exact_log_z(pop.epsilon)
        p_exact = np.exp(exact - np.logaddexp.reduce(exact))
        counts = pop.model_counts(len(models))
        for m in np.flatnonzero(ev.death == IMPROBABLE):
            nxt = exact_log_z(pop.epsilon_next)
            deaths.append({"t": pop.t, "m": int(m), "p_exact_next": float(np.exp(nxt[m] - np.logaddexp.reduce(nxt)))})
        if pop.t < 3:
            continue
        p_err = max(p_err, float(np.max(np.abs(pop.model_probabilities - p_exact))))
        _, p_se = probabilities(ev.log_z, ev.log_z_se)
        if p_se[0] > 0:  # two models: the second's z is the first's, negated
            p_z.append(float((pop.model_probabilities[0] - p_exact[0]) / p_se[0]))
        for m in range(len(models)):
            if counts[m] >= MIN_PARTICLES:
                checks.append({"t": pop.t, "m": m, "n": int(counts[m]), "z": float((ev.log_z[m] - exact[m]) / ev.log_z_se[m]),
                               "se": float(ev.log_z_se[m]), "err": float(ev.log_z[m] - exact[m]),
                               "accepted": int(ev.n_accepted[m]), "proposed": int(ev.n_proposed[m])})
    return {"toy": toy, "seed": seed, "populations": len(r.populations), "checks": checks, "p_err": p_err,
            "p_z": p_z, "deaths": deaths}


def table(rows: list[dict], threshold: float) -> list[str]:
    out = ["| toy | seeds | checks | mean z | sd z | |z| > 3 | |z| > 4 | worst z (seed, t, model) "
           "| max |p - exact| | p: sd z, |z| > 3 | deaths by p (wrong) |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for toy in dict.fromkeys(r["toy"] for r in rows):
        mine = [r for r in rows if r["toy"] == toy]
        checks = [(r["seed"], c) for r in mine for c in r["checks"]]
        z = np.array([c["z"] for _, c in checks])
        worst_seed, worst = max(checks, key=lambda sc: abs(sc[1]["z"]))
        deaths = [d for r in mine for d in r["deaths"]]
        wrong = sum(d["p_exact_next"] > threshold for d in deaths)
        zp = np.array([v for r in mine for v in r.get("p_z", [])])
        p_cal = f"{zp.std(ddof=1):.3f}, {np.mean(np.abs(zp) > 3):.2%}" if zp.size > 1 else "—"
        out.append(f"| {toy} | {len(mine)} | {z.size:,} | {z.mean():+.3f} | {z.std(ddof=1):.3f} "
                   f"| {np.mean(np.abs(z) > 3):.2%} | {np.mean(np.abs(z) > 4):.2%} "
                   f"| {worst['z']:+.2f} ({worst_seed}, {worst['t']}, {worst['m']}) "
                   f"| {max(r['p_err'] for r in mine):.3f} | {p_cal} | {len(deaths)} ({wrong}) |")
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", default="1-200")
    parser.add_argument("--toys", default=",".join(TOYS))
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--batch", type=int, default=200, help="proposals per batch (the tests use 200)")
    parser.add_argument("--json", type=Path, default=None, help="also write every check as JSON")
    args = parser.parse_args()
    seeds, toys = seeds_of(args.seeds), args.toys.split(",")
    jobs = [(toy, s) for toy in toys for s in seeds]
    start = time.monotonic()
    with ProcessPoolExecutor(args.processes) as pool:
        rows = list(pool.map(one, [j[0] for j in jobs], [j[1] for j in jobs], [args.batch] * len(jobs),
                             chunksize=4))
    print(f"## Evidence calibration, seeds {args.seeds}, batch {args.batch} "
          f"({time.monotonic() - start:.0f} s on {args.processes} processes)\n")
    print(f"normal: |z| > 3 in {math.erfc(3 / math.sqrt(2)):.2%}, |z| > 4 in {math.erfc(4 / math.sqrt(2)):.3%}\n")
    print("\n".join(table(rows, 1e-3)))
    if args.json:
        args.json.write_text(json.dumps(rows))


if __name__ == "__main__":
    main()
