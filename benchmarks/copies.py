"""One model under two priors, where the exact split of their evidence is known: is abcns's
split between ``same_model_as`` copies right?

    python -m benchmarks.copies [--seeds 1-20] [--processes 2] [--particles 500] [--coverage]

The model: y = X theta + noise, 11 parameters, X the first 11 cosines of a 400-sample record
(orthogonal columns), the noise Gaussian with a stated sd of 0.5; the truths 0.02-1.2, some
near the prior's lower edge, as the cyclic tests' pinching parameters are. Two copies: every
parameter uniform on [0.001, 3], or (``same_model_as`` it) log-uniform on the same range. The
likelihood is Gaussian in theta around the least-squares fit, independent per parameter, so
the two copies' evidences differ only in their priors' integrals against it: the exact split
log Z_uniform - log Z_log is a sum of 11 one-dimensional integrals (quadrature). abcns runs
the default spec with the noise stated (the answer is its likelihood reading); each seed
makes its own data set. The cyclic tests (docs/benchmarks.md, "The prediction's coverage,
measured") show a split 0.16 nats low on average against importance sampling; this is the
same question where the answer is exact.

``--coverage`` measures instead what the direct estimate divides by: over the last 10
populations before the decision, each bound's cross-validated coverage c against its true
coverage of the accepted region (a ball in theta: Monte Carlo, weighted by the copy's prior),
and the two things that part them (docs/benchmarks.md, "The coverage's two biases"): what the
half-fits miss against what the bound misses, and the test points' restriction to the bound
before (B_{t-2}), which the region partly leaves.
"""

from __future__ import annotations

import argparse
import math
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
from scipy import integrate, stats
from scipy.special import gammaln

from abcns import OK, Model, NSSettings, StopRules, per_model, run
from abcns import bounds as bd
from abcns import ellipsoid as ell
from abcns.distances import NMSE
from benchmarks.model_selection import seeds_of

N_SAMPLES, N_PARAMETERS = 400, 11
TIME = np.linspace(0.0, 1.0, N_SAMPLES, endpoint=False)
DESIGN = np.stack([np.cos(2 * np.pi * (j + 1) * TIME) for j in range(N_PARAMETERS)], axis=1)  # X^T X = n/2 I
TRUTH = np.array([0.02, 0.05, 0.1, 0.2, 0.4, 0.8, 1.2, 0.03, 0.3, 0.6, 1.0])
SIGMA = 0.5
LOW, HIGH = 0.001, 3.0


def data(seed: int) -> np.ndarray:
    return DESIGN @ TRUTH + SIGMA * np.random.default_rng(1000 + seed).standard_normal(N_SAMPLES)


def exact_split(y: np.ndarray) -> float:
    """log Z_uniform - log Z_log on ``y``: per parameter, the Gaussian likelihood's integral
    against each prior (the constants common to both cancel)."""
    scale = N_SAMPLES / 2
    fit, sd = DESIGN.T @ y / scale, SIGMA / math.sqrt(scale)
    out = 0.0
    for b in fit:
        a, c = max(LOW, b - 10 * sd), min(HIGH, b + 10 * sd)
        points = [b] if a < b < c else None
        like = stats.norm(b, sd).pdf
        uniform = integrate.quad(lambda x, f=like: f(x) / (HIGH - LOW), a, c, points=points, limit=200)[0]
        log = integrate.quad(lambda x, f=like: f(x) / (x * math.log(HIGH / LOW)), a, c, points=points, limit=200)[0]
        out += math.log(uniform) - math.log(log)
    return out


def copies() -> list[Model]:
    return [Model("uniform", {f"a{j}": (LOW, HIGH) for j in range(N_PARAMETERS)}),
            Model("log", {f"a{j}": (LOW, HIGH, "log") for j in range(N_PARAMETERS)}, same_model_as="uniform")]


def run_seed(seed: int, particles: int):
    """(data, abcns's run of the default spec with the noise stated) of one seed."""
    y = data(seed)
    nmse = NMSE(y)

    def simulate(theta: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        return nmse(theta @ DESIGN.T), np.full(theta.shape[0], OK, np.int8)

    return y, run(copies(), per_model([simulate, simulate]), NSSettings(particles=particles), StopRules(), seed=seed,
                  noise=nmse.noise(SIGMA))


def one(seed: int, particles: int) -> dict:
    start = time.monotonic()
    y, r = run_seed(seed, particles)
    s = r.summary()
    z, ess = s["log_evidence"], s["decision"]["effective_particles"]
    return {"seed": seed, "exact": exact_split(y), "split": z["uniform"]["log_z"] - z["log"]["log_z"],
            "se": math.hypot(z["uniform"]["se"], z["log"]["se"]), "ess": (ess["uniform"], ess["log"]),
            "populations": s["n_populations"], "simulations": s["n_simulations"], "wall_s": time.monotonic() - start}


def accepted_ball(y: np.ndarray, epsilon: float, rng: np.random.Generator, n: int = 200_000):
    """(points uniform in the accepted region at ``epsilon`` inside the prior box, log of its
    volume): the region {NMSE < epsilon} is the ball of squared radius (RSS(eps) - RSS_min) /
    (n / 2) around the least-squares fit."""
    scale = N_SAMPLES / 2
    fit = DESIGN.T @ y / scale
    rss_min = float(np.sum((y - DESIGN @ fit) ** 2))
    radius = math.sqrt(max(epsilon * N_SAMPLES * np.var(y, ddof=1) / 100 - rss_min, 0.0) / scale)
    g = rng.standard_normal((n, N_PARAMETERS))
    g /= np.linalg.norm(g, axis=1)[:, None]
    x = fit + radius * g * (rng.random(n) ** (1 / N_PARAMETERS))[:, None]
    inside = np.all((x > LOW) & (x < HIGH), axis=1)
    log_ball = N_PARAMETERS / 2 * math.log(math.pi) - gammaln(N_PARAMETERS / 2 + 1) + N_PARAMETERS * math.log(radius)
    return x[inside], log_ball + math.log(inside.mean())


def exact_abc(y: np.ndarray, epsilon: float, rng: np.random.Generator, n: int = 200_000):
    """(points uniform in the accepted region at ``epsilon``, each copy's prior density over
    the uniform copy's at them, each copy's exact log Z(epsilon), its Monte Carlo standard
    error): the log copy's density, 1 / (theta log(HIGH / LOW)) per parameter, makes its
    evidence a Monte Carlo mean of heavy-tailed weights."""
    x, log_volume = accepted_ball(y, epsilon, rng, n)
    density = np.exp(-np.sum(np.log(x), axis=1) - N_PARAMETERS * math.log(math.log(HIGH / LOW)) +
                     N_PARAMETERS * math.log(HIGH - LOW))
    log_z = log_volume - N_PARAMETERS * math.log(HIGH - LOW)
    return (x, (np.ones(len(x)), density), (log_z, log_z + math.log(density.mean())),
            (0.0, float(density.std() / density.mean() / math.sqrt(density.size))))


def coverage_rows(seed: int, particles: int) -> list[tuple]:
    """Per population of the last 10 before the decision and per copy m (B = its bound that
    proposed population t, A = the one before): (m, points tested, true c = P(B | R_t), the
    cross-validated c, the half-fits' true miss, q = P(A | R_t), c_r = P(B | R_t and A),
    u = P(B | R_t not in A), the direct estimate's error with the cross-validated c and with
    the true c against the exact log Z(eps_t))."""
    y, r = run_seed(seed, particles)
    models, rng = copies(), np.random.default_rng(seed)
    frames = [bd.Frame(m, unit=True) for m in models]
    decision = r.summary()["decision"]["population"]
    out = []
    for t in range(max(3, decision - 9), decision + 1):
        older, prev, pop = r.populations[t - 3], r.populations[t - 2], r.populations[t - 1]
        x, densities, exacts, _ = exact_abc(y, pop.epsilon, rng)
        for m, model in enumerate(models):
            bound, before, ev = prev.ellipsoids[m], older.ellipsoids[m], prev.evidence
            if not bound or not before or ev.n_coverage[m] == 0 or pop.evidence.n_accepted[m] == 0:
                continue
            w, exact = densities[m], exacts[m]
            u = frames[m].to_frame(x)
            in_b, in_a = ell.n_containing(bound, u) > 0, ell.n_containing(before, u) > 0
            share = lambda s, w=w: float(np.sum(w * s) / np.sum(w))
            true_c, q = share(in_b), share(in_a)
            below = prev.distances < pop.epsilon
            mine = prev.theta[below & (prev.models == m), :N_PARAMETERS]
            twins = prev.theta[below & (prev.models != m), :N_PARAMETERS]
            points = frames[m].to_frame(np.vstack([mine, twins[model.in_prior(twins)]]))
            _, [(_, halves), _] = bd.half_fits(points, bound, NSSettings().enlargement, rng)
            half_miss = 1 - share(ell.n_containing(halves, u) > 0)
            log_a = math.log(pop.evidence.n_accepted[m] / pop.evidence.n_proposed[m])
            direct = log_a + ev.log_volume[m] - math.log(max(ev.coverage[m], 1e-12))
            out.append((m, int(ev.n_coverage[m]), true_c, float(ev.coverage[m]), half_miss, q, share(in_b & in_a) / q,
                        share(in_b & ~in_a) / (1 - q) if q < 1 else np.nan, direct - exact,
                        direct + math.log(ev.coverage[m] / true_c) - exact))
    return out


def coverage_report(seeds: list[int], particles: int, processes: int) -> None:
    start = time.monotonic()
    with ProcessPoolExecutor(processes) as pool:
        rows = np.array([row for rs in pool.map(coverage_rows, seeds, [particles] * len(seeds)) for row in rs])
    print(f"## The coverage the direct estimate divides by, against the true one: the last 10 populations "
          f"before the decision, seeds {seeds[0]}-{seeds[-1]} ({time.monotonic() - start:.0f} s on {processes} processes)\n")
    print("| copy | checks | points tested | true c | cross-validated c | log(c_cv / c) | half-fits' miss / B's | "
          "q = P(A \\| R) | c_r = P(B \\| R, A) | u = P(B \\| R, not A) | log(c_r / c) | direct, c_cv | direct, true c |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for m, name in enumerate(("uniform", "log")):
        b = rows[rows[:, 0] == m]

        def mean(c: int, b: np.ndarray = b) -> str:
            v = b[:, c][np.isfinite(b[:, c])]
            return f"{v.mean():+.3f} ± {v.std(ddof=1) / math.sqrt(len(v)):.3f}"

        print(f"| {name} | {len(b)} | {np.median(b[:, 1]):.0f} | {b[:, 2].mean():.3f} | {b[:, 3].mean():.3f} | "
              f"{mean_log(b[:, 3], b[:, 2])} | {np.mean(b[:, 4]) / np.mean(1 - b[:, 2]):.2f} | {b[:, 5].mean():.3f} | "
              f"{b[:, 6].mean():.3f} | {np.nanmean(b[:, 7]):.3f} | {mean_log(b[:, 6], b[:, 2])} | {mean(8)} | {mean(9)} |")


def mean_log(a: np.ndarray, b: np.ndarray) -> str:
    v = np.log(a / b)
    return f"{v.mean():+.3f} ± {v.std(ddof=1) / math.sqrt(len(v)):.3f}"


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", default="1-20")
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--particles", type=int, default=500)
    parser.add_argument("--coverage", action="store_true", help="the coverage against the true one (see above)")
    args = parser.parse_args()
    seeds = seeds_of(args.seeds)
    if args.coverage:
        coverage_report(seeds, args.particles, args.processes)
        return
    start = time.monotonic()
    with ProcessPoolExecutor(args.processes) as pool:
        rows = list(pool.map(one, seeds, [args.particles] * len(seeds)))
    print(f"## Two copies of an 11-parameter linear-Gaussian model, seeds {args.seeds} "
          f"({time.monotonic() - start:.0f} s on {args.processes} processes)\n")
    print("| seed | exact split | abcns split (se) | off (se units) | effective particles, uniform / log | "
          "populations | simulations |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        off = r["split"] - r["exact"]
        print(f"| {r['seed']} | {r['exact']:.3f} | {r['split']:.3f} ({r['se']:.3f}) | {off:+.3f} ({off / r['se']:+.2f}) | "
              f"{r['ess'][0]:.1f} / {r['ess'][1]:.1f} | {r['populations']} | {r['simulations']:,} |")
    off = np.array([r["split"] - r["exact"] for r in rows])
    z = off / np.array([r["se"] for r in rows])
    error = off.std(ddof=1) / math.sqrt(len(off)) if len(off) > 1 else 0.0
    spread = f", sd {z.std(ddof=1):.2f}" if len(rows) > 1 else ""
    print(f"\nsplit off the exact: mean {off.mean():+.3f} (± {error:.3f}), RMS {math.sqrt(np.mean(off**2)):.3f}; "
          f"z-scores mean {z.mean():+.2f}{spread}")


if __name__ == "__main__":
    main()
