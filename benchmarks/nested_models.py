"""Nested candidate models at the noise floor: is the right model chosen, and do the
posterior intervals hold the truth?

    python -m benchmarks.nested_models [--family duffing|linear-cubic|paper41 ...]
                                       [--truth simple|complex] [--noise 0.01,0.03]
                                       [--seeds 1-20] [--processes 2] [--no-floor] [--json OUT]

Each (family, truth, noise level, seed) makes its own data set (seed = data seed = run
seed): a Duffing oscillator driven by a Gaussian force (std 10 N, 1000 samples at 100 Hz,
m = 1, c = 0.05, k = 50), integrated with 64 RK4 steps per sample by the numpy reference
simulator, plus Gaussian noise of the given share of the response's RMS; fit on the first
500 samples. The run: the evidence variant with §4.1's settings (1000 particles, alpha 0.3,
beta 0.6, f0 1.1, eps_1 100, batch 200, the paper's stop rule at 1e-7, 4 RK4 substeps),
stopped at the decision tolerance (``abcns.noise``) unless ``--no-floor``.

Families (the simpler model is nested in the more complex one):

- ``duffing``: cubic (c, k, k3) vs cubic-quintic (c, k, k3, k5 with k5 ~ U(0, 1e6), a prior
  that holds k5 = 0); truth k3 = 1e3 and k5 = 0 (simple) or 1e5 (complex);
- ``linear-cubic``: linear (c, k) vs cubic (c, k, k3 with k3 ~ U(0, 1e4)); truth k3 = 0
  (simple) or 1e3 (complex);
- ``paper41``: §4.1's models and priors (cubic vs cubic-quintic, k5 ~ U(1e4, 1e6), which
  excludes 0), truth cubic-quintic (k5 = 1e5): the paper's own problem on fresh data.

Printed: per run the probability of the true model in the answer (``summary()``: every
population weighted by the likelihood, ``abcns.likelihood``), the decision
tolerance and the noise floor, the final tolerance and the probability there; then the
share of runs choosing the true model with p >= 0.9 and, over (parameter, run) pairs of the
true model, how often its 50 % and 95 % posterior intervals (the answer's particles)
hold the truth.
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from benchmarks.model_selection import seeds_of

FORCE_STD, N_SAMPLES, FS, FIT = 10.0, 1000, 100.0, (0, 500)
BASE = {"m": 1.0, "c": 0.05, "k": 50.0, "k2": 0.0}
PRIORS = {"c": [0.005, 0.5], "k": [5, 500]}
FAMILIES = {
    # name: (simple model, complex model, truth simple, truth complex)
    "duffing": (
        {"name": "cubic", "fixed": {"m": 1, "k5": 0}, "priors": {**PRIORS, "k3": [100, 10000]}},
        {"name": "cubic-quintic", "fixed": {"m": 1}, "priors": {**PRIORS, "k3": [100, 10000], "k5": [0, 1e6]}},
        {"k3": 1e3, "k5": 0.0}, {"k3": 1e3, "k5": 1e5}),
    "linear-cubic": (
        {"name": "linear", "fixed": {"m": 1, "k3": 0, "k5": 0}, "priors": dict(PRIORS)},
        {"name": "cubic", "fixed": {"m": 1, "k5": 0}, "priors": {**PRIORS, "k3": [0, 10000]}},
        {"k3": 0.0, "k5": 0.0}, {"k3": 1e3, "k5": 0.0}),
    "paper41": (
        {"name": "cubic", "fixed": {"m": 1, "k5": 0}, "priors": {**PRIORS, "k3": [100, 10000]}},
        {"name": "cubic-quintic", "fixed": {"m": 1}, "priors": {**PRIORS, "k3": [100, 10000], "k5": [1e4, 1e6]}},
        None, {"k3": 1e3, "k5": 1e5}),
}


def make_data(truth: dict[str, float], noise: float, seed: int) -> dict[str, np.ndarray]:
    """Force, noisy and clean displacement of the Duffing oscillator at ``truth``."""
    from worker.simulators import Duffing

    rng = np.random.default_rng(seed)
    force = FORCE_STD * rng.standard_normal(N_SAMPLES)
    p = {**BASE, **truth}
    row = np.array([[p["m"], p["c"], p["k"], p["k2"], p["k3"], p["k5"]]])
    clean = Duffing(force, 1.0 / FS, substeps=64, backend="numpy").simulate(row).values[0]
    noisy = clean + noise * np.sqrt(np.mean(clean**2)) * rng.standard_normal(clean.size)
    return {"force": force, "observed": noisy, "clean": clean}


def spec_of(family: str, data: dict[str, np.ndarray], floor: bool) -> dict:
    simple, complex_, *_ = FAMILIES[family]
    models = [{**m, "simulator": "duffing", "integrator": {"substeps": 4}} for m in (simple, complex_)]
    return {
        "name": f"nested-{family}",
        "data": {"fs": FS, "input": data["force"].tolist(), "observed": data["observed"].tolist(), "fit": list(FIT)},
        "models": models,
        "distance": "nmse",
        "sampler": {"algorithm": "abc-ns", "particles": 1000, "alpha": 0.3, "beta": 0.6, "enlargement": 1.1,
                    "epsilon_initial": 100, "batch_size": 200},
        "stop": {"min_epsilon_decrease": 1e-7, "max_populations": 400, "noise_floor": floor},
    }


def one(family: str, truth: str, noise: float, seed: int, floor: bool) -> dict:
    from abcns import run
    from abcns.distances import NMSE
    from service.spec import build, parse

    simple, complex_, truth_simple, truth_complex = FAMILIES[family]
    values = truth_simple if truth == "simple" else truth_complex
    true_model = simple if truth == "simple" else complex_
    data = make_data(values, noise, seed)
    job = build(parse(spec_of(family, data, floor)))
    start = time.monotonic()
    r = run(job.models, job.evaluate, job.settings, job.stop, seed=seed, noise=job.noise)
    answer = r.decision_population()
    name = true_model["name"]
    truth_values = {**BASE, **values}
    noise_nmse = float(NMSE(data["observed"], FIT)(data["clean"][None, :])[0])
    cover: dict[str, dict[str, bool]] = {}
    i = r.model_names.index(name)
    if r.reading() is not None or i in r.alive(answer.t):  # the answer's particles
        theta, weights, _ = r.answer_draws(i)
    else:
        theta, weights = np.zeros((0, r.models[i].n_dim)), np.zeros(0)
    if theta.shape[0]:
        from abcns.result import weighted_quantiles

        for j, par in enumerate(r.models[i].parameter_names):
            q = weighted_quantiles(theta[:, j], weights, (0.025, 0.25, 0.75, 0.975))
            x = truth_values[par]
            cover[par] = {"50": bool(q[1] <= x <= q[2]), "95": bool(q[0] <= x <= q[3])}
    floor_ = r.floor
    return {
        "family": family, "truth": truth, "noise": noise, "seed": seed, "true_model": name,
        "p_true": r.summary()["model_probabilities"][name], "p_true_final": r.model_probabilities()[name],
        "decision_epsilon": answer.epsilon, "decision_t": answer.t, "final_epsilon": r.final.epsilon,
        "populations": len(r.populations), "stop": r.stop_reason.value, "simulations": r.n_simulations,
        "floor": floor_.floor if floor_ else None, "noise_nmse": noise_nmse,
        "cover": cover, "wall_s": time.monotonic() - start,
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--family", nargs="+", default=["duffing", "linear-cubic"], choices=sorted(FAMILIES))
    parser.add_argument("--truth", nargs="+", default=["simple", "complex"], choices=("simple", "complex"))
    parser.add_argument("--noise", default="0.01,0.03", help="noise levels, shares of the response's RMS")
    parser.add_argument("--seeds", default="1-20")
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--no-floor", action="store_true", help="run past the noise floor (stop.noise_floor: false)")
    parser.add_argument("--json", default=None, help="also write the rows as JSON")
    args = parser.parse_args()
    cases = [(f, t, float(n), s) for f in args.family for t in args.truth for n in args.noise.split(",")
             for s in seeds_of(args.seeds) if not (t == "simple" and FAMILIES[f][2] is None)]
    start = time.monotonic()
    with ProcessPoolExecutor(args.processes) as pool:
        rows = list(pool.map(one, *zip(*cases), [not args.no_floor] * len(cases)))
    print(f"# nested models at the noise floor ({time.monotonic() - start:.0f} s on {args.processes} processes; "
          f"stop at the floor: {not args.no_floor})\n")
    print("| family | truth | noise | seed | p(true), the answer | decision ε (t) | noise floor | noise alone | "
          "final ε | p(true) final | stop | simulations |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['family']} | {r['true_model']} | {r['noise']:g} | {r['seed']} | {r['p_true']:.3f} | "
              f"{r['decision_epsilon']:.5g} ({r['decision_t']}) | {r['floor'] or float('nan'):.5g} | {r['noise_nmse']:.5g} | "
              f"{r['final_epsilon']:.5g} | {r['p_true_final']:.3f} | {r['stop']} | {r['simulations']:,} |")
    print("\n| family | truth | noise | runs | true model with p >= 0.9 | 50 % intervals hold the truth | "
          "95 % intervals hold the truth |")
    print("|---|---|---|---|---|---|---|")
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["family"], r["true_model"], r["noise"]), []).append(r)
    for (family, model, noise), rs in groups.items():
        pairs = [c for r in rs for c in r["cover"].values()]
        right = sum(r["p_true"] >= 0.9 for r in rs)
        c50 = sum(c["50"] for c in pairs) / max(len(pairs), 1)
        c95 = sum(c["95"] for c in pairs) / max(len(pairs), 1)
        print(f"| {family} | {model} | {noise:g} | {len(rs)} | {right} of {len(rs)} | {c50:.0%} of {len(pairs)} | "
              f"{c95:.0%} of {len(pairs)} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
