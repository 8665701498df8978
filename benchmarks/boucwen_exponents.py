"""Which Bouc-Wen exponent? The question of the paper's §5 on synthetic data: linear against
Bouc-Wen n = 1, 2, 3, each n the truth in turn.

    python -m benchmarks.boucwen_exponents [--truth 1 2 3] [--seeds 1-20] [--processes 2]
                                           [--json OUT]

The system (:class:`worker.simulators.BoucWen`, paper Eqs. 14-15)::

    m y'' + c y' + k y + z = f,   z' = A y' - alpha |y'| |z|^(n-1) z - beta y' |z|^n

Candidates (every one a uniform prior box; the spec's ``models``):

- ``linear`` (simulator ``linear``): m, c, k;
- ``bw-n1``, ``bw-n2``, ``bw-n3`` (simulator ``bouc_wen``, n fixed): m, c, A, alpha, beta,
  with k fixed at 0 (the simulator's default): the paper folds the linear stiffness into A,
  and with k free the pair (k, A) is only told apart by the nonlinearity, a sixth
  dimension for nothing, since k = 0 is the truth.

Priors: m ~ U(0.5, 2), c ~ U(0.1, 2.5) for every model, k (linear) and A (Bouc-Wen) ~
U(20, 100); for n = 1 alpha ~ U(0, 10), beta ~ U(-5, 10) (beta < 0 allowed: stiffening
loops, as ``examples/boucwen``'s priors), and for exponent n those ranges times
``Z_TYP^(1 - n)``: alpha and beta have units 1 / (m N^(n-1)), so their priors scale with a
typical |z| per power of n, as ``examples/boucwen/spec.yaml`` does with 30 N. ``Z_TYP`` =
10 N, the force's std (a user knows the input; z carries the force at low frequency): a
fixed value, not the truth's own z, so that the candidates' priors do not depend on which
model made the data (the z RMS of each run's truth is printed: 2.5-5.0 N on seeds 1-3).

Truths (per n): m = 1, c = 0.5, A = 50 (small-amplitude natural frequency 1.1 Hz, 3.5 %
viscous damping), k = 0, alpha = 3 Z_TYP^(1-n), beta = 2 Z_TYP^(1-n): the same place in
every n's prior box, and the same loading bound |z| <= (A / (alpha + beta))^(1/n) = 10 N =
Z_TYP for every n, which a force of std 10 N approaches often: clearly hysteretic. On seeds
1-3 the best linear fit misses the clean response by 35-98 % NMSE, the best fit of another
exponent by 0.09-1.1 %, 7.5-47 times the noise's 0.012-0.023 % (printed per run: "best
linear", "best other n"; a local least-squares fit from a few starts, so an upper bound of
the best fit). With k = 0 the response drifts (no spring holds y at 0 once z has yielded):
this is the model.

Data (seed = data seed = run seed; the same force for every truth at a seed): a Gaussian
force, std 10 N, 1000 samples at 100 Hz, held over each sample (as the simulators hold it,
so the model sees the very force that made the data; the white force's band reaches the
Nyquist frequency, 45 times the resonance), the truth integrated by the same simulator with
64 RK4 substeps per sample (its z recovered exactly from the acceleration and velocity
outputs, z = f - m y'' - c y'), plus Gaussian noise of std 1 % of the clean displacement's
RMS. Fit window: all 1000 samples (``FIT``; ``benchmarks.nested_models`` fits 500 of 1000,
here five parameters and three hysteresis shapes to tell apart). Printed per run: the
NMSE of the noise alone ("noise"), and the integration error of the spec's own simulator
(its substeps, chosen from the priors since the spec names none) at the true parameters
against the 64-substep truth, as a ratio to the noise's NMSE ("integration / noise"): it
must be well below 1 for the data to be what the model can fit.

The spec: the default spec, no ``stop`` section (the default stop rules and the decision
at the noise floor), the default sampler (1000 particles; epsilon_1 from the pilot, the
default: the pilot's quantile of prior-predictive NMSEs) and no ``data.noise_std`` (a user
with real data does not know it; the noise floor is estimated from the best fit). The
pilot suits this problem: epsilon_1 86-154 % NMSE on seeds 1-3, finite (source "pilot").
The spec's substeps, chosen from the priors, are 1 per sample: integration / noise
4e-4 to 1e-2 on seeds 1-3. Built and run as :mod:`benchmarks.nested_models`
(``service.spec.build(service.spec.parse(spec))``, ``abcns.run`` in the worker process),
everything read from ``Result.summary()``.

Printed: per (truth n, seed) p(true model) ± se, the leading model, the decision rule,
provisional or not, the stop reason, populations, simulations, wall time, and which of the
true model's 95 % intervals hold the truth; the data checks; every probability, the
decision and the warnings of each run whose true model has p < 0.9; then per truth the
runs giving the true n with p >= 0.9 (the target: every run), the share of the true
model's (parameter, seed) 95 % intervals holding the truth, median simulations and wall.

Measured (``--truth 1 2 3 --seeds 1-3 --processes 1``, 2-core machine shared): every run
chose the true n with p = 1.0000 (rule noise_floor, not provisional, no warnings), 45 of
45 of the true model's 95 % intervals hold the truth; 78-85 populations, 62-70 k
simulations, 6-14 s a run (two runs of the command, bit-identical answers: 83 s and 78 s
in all, the data checks included).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

from benchmarks.model_selection import seeds_of

FORCE_STD, N_SAMPLES, FS, FIT = 10.0, 1000, 100.0, (0, 1000)
#: noise std as a share of the clean displacement's RMS
NOISE = 0.01
#: RK4 substeps per sample of the data's truth
TRUTH_SUBSTEPS = 64
#: the typical |z| (N) that scales alpha and beta per power of n (module docstring)
Z_TYP = 10.0
EXPONENTS = (1, 2, 3)
#: the truth's parameters but alpha and beta, and those two for n = 1
BASE = {"m": 1.0, "c": 0.5, "k": 0.0, "A": 50.0}
ALPHA_1, BETA_1 = 3.0, 2.0
#: priors shared by every model (k of the linear model takes A's range)
PRIORS = {"m": [0.5, 2.0], "c": [0.1, 2.5]}
STIFFNESS = [20.0, 100.0]
#: alpha, beta priors for n = 1 (times Z_TYP^(1 - n) for exponent n)
PRIORS_N1 = {"alpha": [0.0, 10.0], "beta": [-5.0, 10.0]}
#: p of the true model that counts as choosing it
CHOSEN = 0.9


def scale(n: int) -> float:
    """alpha, beta's factor for exponent n: Z_TYP^(1 - n)."""
    return Z_TYP ** (1 - n)


def name_of(n: int) -> str:
    return f"bw-n{n}"


def truth_of(n: int) -> dict[str, float]:
    """The Bouc-Wen truth with exponent n: every simulator parameter."""
    return {**BASE, "alpha": ALPHA_1 * scale(n), "beta": BETA_1 * scale(n), "n": float(n)}


def models() -> list[dict]:
    """The candidates of the spec: linear, then Bouc-Wen n = 1, 2, 3 (k = 0, the default)."""
    out = [{"name": "linear", "simulator": "linear", "priors": {**PRIORS, "k": STIFFNESS}}]
    for n in EXPONENTS:
        ab = {p: [lo * scale(n), hi * scale(n)] for p, (lo, hi) in PRIORS_N1.items()}
        out.append({"name": name_of(n), "simulator": "bouc_wen", "fixed": {"n": n},
                    "priors": {**PRIORS, "A": STIFFNESS, **ab}})
    return out


def row_of(p: dict[str, float]) -> np.ndarray:
    """The BoucWen simulator's parameter row (1, 7) of ``p``."""
    from worker.simulators import BoucWen

    return np.array([[p[name] for name in BoucWen.parameter_names]])


def make_data(n: int, seed: int) -> dict[str, np.ndarray]:
    """Force, noisy and clean displacement and the hysteretic force z of the truth with
    exponent ``n`` (64 RK4 substeps per sample)."""
    from worker.simulators import BoucWen

    rng = np.random.default_rng(seed)
    force = FORCE_STD * rng.standard_normal(N_SAMPLES)
    p = truth_of(n)
    row = row_of(p)
    out = {o: BoucWen(force, 1.0 / FS, substeps=TRUTH_SUBSTEPS, output=o).simulate(row)
           for o in ("displacement", "velocity", "acceleration")}
    if any(o.status[0] != 0 for o in out.values()):
        raise RuntimeError(f"the truth n = {n} diverged at {TRUTH_SUBSTEPS} substeps (seed {seed})")
    clean = np.array(out["displacement"].values[0])
    z = force - p["m"] * out["acceleration"].values[0] - p["c"] * out["velocity"].values[0] - p["k"] * clean
    noisy = clean + NOISE * np.sqrt(np.mean(clean**2)) * rng.standard_normal(clean.size)
    return {"force": force, "observed": noisy, "clean": clean, "z": np.array(z)}


def spec_of(data: dict[str, np.ndarray], seed: int) -> dict:
    """The default spec (no ``stop``, the default sampler, no ``noise_std``) on ``data``."""
    return {
        "name": "boucwen-exponents",
        "data": {"fs": FS, "input": data["force"].tolist(), "observed": data["observed"].tolist(), "fit": list(FIT)},
        "models": models(),
        "seed": seed,
    }


def best_fit(n: int | None, truth: dict[str, float], data: dict[str, np.ndarray]) -> float:
    """NMSE (% of the clean record's variance, on the fit window) of the best fit of the
    linear model (``n`` None) or of Bouc-Wen with exponent ``n`` to the truth's clean
    response: local least squares from a few starts, so an upper bound."""
    from scipy.optimize import least_squares

    from worker.simulators import BoucWen, Linear

    start, stop = FIT
    clean = data["clean"][start:stop]
    sd = float(np.std(clean, ddof=1))
    force = data["force"][:stop]

    def misfit(sim: Any, row: np.ndarray) -> np.ndarray:
        out = sim.simulate(row)
        with np.errstate(all="ignore"):
            r = (out.values[0, start:] - clean) / sd
        # a failed or runaway trial: a large constant misfit (its square sum stays finite)
        return r if out.status[0] == 0 and np.all(np.abs(r) < 1e3) else np.full(clean.size, 1e3)

    best = math.inf
    if n is None:
        lin = Linear(force, 1.0 / FS)
        starts = [[truth["m"], truth["c"], f * truth["A"]] for f in (0.25, 0.5, 1.0)]
        for x0 in starts:
            r = least_squares(lambda x: misfit(lin, x[None, :]), x0, x_scale=[1.0, 0.5, truth["A"]])
            best = min(best, 100 * float(np.mean(r.fun**2)))
        return best
    bw = BoucWen(force, 1.0 / FS, substeps=4)
    s = scale(n)
    for f in (0.5, 1.0, 2.0):
        x0 = [truth["m"], truth["c"], truth["A"], f * ALPHA_1, f * BETA_1]  # alpha, beta in n = 1 units
        r = least_squares(lambda x: misfit(bw, np.array([[x[0], x[1], 0.0, x[3] * s, x[4] * s, x[2], n]])), x0,
                          x_scale=[1.0, 0.5, truth["A"], ALPHA_1, ALPHA_1])
        best = min(best, 100 * float(np.mean(r.fun**2)))
    return best


def data_checks(n: int, data: dict[str, np.ndarray], job: Any) -> dict[str, Any]:
    """The noise's NMSE, the spec's simulator's integration error at the truth (against the
    64-substep truth, on the fit window), the best linear and other-exponent fits, z's RMS."""
    from abcns.distances import NMSE
    from worker.compose import full_parameters

    truth = truth_of(n)
    i = [m.name for m in job.models].index(name_of(n))
    model, sim = job.models[i], job.simulators[i]
    theta = np.array([[truth[p] for p in model.priors]])
    own = sim.simulate(full_parameters(model, sim)(theta)).values[0]
    noise_nmse = float(NMSE(data["observed"], FIT)(data["clean"][None, :])[0])
    integration = float(NMSE(data["clean"], FIT)(np.asarray(own)[None, :])[0])
    others = {name_of(k): best_fit(k, truth, data) for k in EXPONENTS if k != n}
    other = min(others, key=others.__getitem__)
    return {"noise_nmse": noise_nmse, "integration_nmse": integration, "substeps": sim.config()["substeps"],
            "best_linear_nmse": best_fit(None, truth, data), "best_other": other,
            "best_other_nmse": others[other], "z_rms": float(np.sqrt(np.mean(data["z"] ** 2)))}


def one(n: int, seed: int) -> dict:
    """One run: data with truth ``n`` and seed ``seed``, the default spec, ``abcns.run``."""
    from abcns import run
    from service.spec import build, parse

    data = make_data(n, seed)
    job = build(parse(spec_of(data, seed)))
    checks = data_checks(n, data, job)
    start = time.monotonic()
    r = run(job.models, job.evaluate, job.settings, job.stop, seed=seed, noise=job.noise)
    wall = time.monotonic() - start
    s = r.summary()
    name = name_of(n)
    truth = truth_of(n)
    p = s["model_probabilities"]
    post = s["posterior"].get(name, {})
    cover = {par: bool(q["q2_5"] <= truth[par] <= q["q97_5"]) for par, q in post.items()}
    decision = s["decision"] or {}
    return {
        "truth_n": n, "seed": seed, "true_model": name, "truth": truth,
        "p": p, "p_se": s["model_probability_se"], "p_true": p.get(name, 0.0),
        "p_true_se": s["model_probability_se"].get(name),
        "leading": max(p, key=p.__getitem__) if p else None,
        "rule": decision.get("rule"), "provisional": decision.get("provisional"), "reading": decision.get("reading"),
        "decision": decision, "stop": s["stop_reason"], "populations": s["n_populations"],
        "simulations": s["n_simulations"], "warnings": s["warnings"], "posterior": post, "cover": cover,
        "epsilon_initial": (s["epsilon"] or [None])[0], "epsilon_initial_source": s["epsilon_initial_source"],
        "noise_floor": s["noise_floor"],
        "wall_s": wall, **checks,
    }


def fmt(x: Any, spec: str = ".3g") -> str:
    """``x`` formatted, "-" when missing or not finite."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return format(x, spec)


def fmt_p(x: float | None) -> str:
    """A probability: 4 decimals, or 2 significant digits below 1e-3."""
    return fmt(x, ".1e" if x is not None and 0 < abs(x) < 1e-3 else ".4f")


def head(header: str) -> None:
    """A markdown table's header and its rule."""
    print(header)
    print("|" + "---|" * header.count(" | ") + "---|")


def print_runs(rows: list[dict]) -> None:
    head("| truth | seed | p(true) ± se | leading | rule | provisional | stop | populations | simulations | "
         "wall s | 95 % intervals hold the truth | warnings |")
    for r in rows:
        held = sum(r["cover"].values())
        missed = [k for k, v in r["cover"].items() if not v]
        cover = f"{held} of {len(r['cover'])}" + (f" (not {', '.join(missed)})" if missed else "")
        print(f"| {r['true_model']} | {r['seed']} | {fmt_p(r['p_true'])} ± {fmt_p(r['p_true_se'])} | "
              f"{r['leading'] or '-'} | {r['rule'] or '-'} | {r['provisional']} | {r['stop']} | {r['populations']} | "
              f"{r['simulations']:,} | {r['wall_s']:.1f} | {cover} | {len(r['warnings'])} |")


def print_checks(rows: list[dict]) -> None:
    head("| truth | seed | z RMS (N) | noise NMSE % | substeps | integration / noise | best linear NMSE % | "
         "best other n: NMSE % | best other / noise |")
    for r in rows:
        noise = r["noise_nmse"]
        print(f"| {r['true_model']} | {r['seed']} | {r['z_rms']:.2f} | {noise:.4f} | {r['substeps']} | "
              f"{r['integration_nmse'] / noise:.2e} | {r['best_linear_nmse']:.3g} | "
              f"{r['best_other']}: {r['best_other_nmse']:.3g} | {r['best_other_nmse'] / noise:.3g} |")


def print_misses(rows: list[dict]) -> None:
    """Every probability, the decision and the warnings of the runs that miss the truth."""
    misses = [r for r in rows if r["p_true"] < CHOSEN]
    if not misses:
        print(f"Every run gives the true model p >= {CHOSEN}.")
        return
    for r in misses:
        probs = ", ".join(f"{m} {fmt_p(p)} ± {fmt_p(r['p_se'].get(m))}" for m, p in r["p"].items())
        print(f"- {r['true_model']} seed {r['seed']}: {probs}; decision {r['decision']}; "
              f"warnings: {r['warnings'] or 'none'}")


def print_truths(rows: list[dict]) -> None:
    header = (f"| truth | runs | true n with p >= {CHOSEN} | 95 % intervals hold the truth | median simulations | "
              "median wall s |")
    print(header)
    print("|" + "---|" * header.count(" | ") + "---|")
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(r["true_model"], []).append(r)
    for name, rs in groups.items():
        pairs = [c for r in rs for c in r["cover"].values()]
        right = sum(r["p_true"] >= CHOSEN for r in rs)
        share = f"{sum(pairs) / len(pairs):.0%} of {len(pairs)}" if pairs else "-"
        print(f"| {name} | {len(rs)} | {right} of {len(rs)} | {share} | "
              f"{np.median([r['simulations'] for r in rs]):,.0f} | {np.median([r['wall_s'] for r in rs]):.1f} |")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--truth", nargs="+", type=int, default=list(EXPONENTS), choices=EXPONENTS)
    parser.add_argument("--seeds", default="1-20")
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--json", default=None, help="also write the rows as JSON")
    args = parser.parse_args(argv)
    cases = [(n, s) for n in args.truth for s in seeds_of(args.seeds)]
    start = time.monotonic()
    if args.processes > 1:
        with ProcessPoolExecutor(args.processes) as pool:
            rows = list(pool.map(one, *zip(*cases)))
    else:
        rows = [one(n, s) for n, s in cases]
    print(f"# Bouc-Wen exponents: linear vs n = {', '.join(map(str, EXPONENTS))}, the default spec "
          f"({time.monotonic() - start:.0f} s on {args.processes} process(es))\n")
    print_runs(rows)
    print()
    print_checks(rows)
    print()
    print_misses(rows)
    print()
    print_truths(rows)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
