"""One model under two priors, where the exact split of their evidence is known: is abcns's
split between ``same_model_as`` copies right?

    python -m benchmarks.copies [--seeds 1-20] [--processes 2] [--particles 500] [--evidence]

The model: y = X theta + noise, 11 parameters, X the first 11 cosines of a 400-sample record
(orthogonal columns), the noise Gaussian with a stated sd of 0.5; the truths 0.02-1.2, some
near the prior's lower edge, as the cyclic tests' pinching parameters are. Two copies: every
parameter uniform on [0.001, 3], or (``same_model_as`` it) log-uniform on the same range. The
likelihood is Gaussian in theta around the least-squares fit, independent per parameter, so
the two copies' evidences differ only in their priors' integrals against it: the exact split
log Z_uniform - log Z_log is a sum of 11 one-dimensional integrals (quadrature). abcns runs
the default spec with the noise stated (the answer is its likelihood reading, each copy read
from both copies' particles, the split's standard error from their covariance); each seed
makes its own data set. The cyclic tests ask the same question against importance sampling
(docs/benchmarks.md, "The evidence from the mixture"); here the answer is exact.

``--evidence`` checks each copy's ABC evidence instead: abcns's log Z(eps_t) against the
exact (the accepted region is a ball in theta: a Monte Carlo of 10^6 points, weighted by the
copy's prior) over the last 10 populations before the decision.
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
    s, reading = r.summary(), r.reading()
    z, ess, c = s["log_evidence"], s["decision"]["effective_particles"], reading.covariance
    # the copies are read from the same particles: the split's variance takes their covariance
    return {"seed": seed, "exact": exact_split(y), "split": z["uniform"]["log_z"] - z["log"]["log_z"],
            "se": math.sqrt(max(c[0, 0] + c[1, 1] - 2 * c[0, 1], 0.0)), "ess": (ess["uniform"], ess["log"]),
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


def exact_abc(y: np.ndarray, epsilon: float, rng: np.random.Generator,
              n: int = 200_000) -> tuple[tuple[float, float], tuple[float, float]]:
    """(each copy's exact log Z(epsilon), its Monte Carlo standard error): the log copy's
    prior density over the uniform copy's, 1 / (theta log(HIGH / LOW)) per parameter, makes
    its evidence a Monte Carlo mean of heavy-tailed weights over the accepted ball."""
    x, log_volume = accepted_ball(y, epsilon, rng, n)
    density = np.exp(-np.sum(np.log(x), axis=1) - N_PARAMETERS * math.log(math.log(HIGH / LOW)) +
                     N_PARAMETERS * math.log(HIGH - LOW))
    log_z = log_volume - N_PARAMETERS * math.log(HIGH - LOW)
    return (log_z, log_z + math.log(density.mean())), (0.0, float(density.std() / density.mean() / math.sqrt(density.size)))


def evidence_rows(seed: int, particles: int) -> list[tuple]:
    """(copy, error of abcns's log Z(eps_t) against the exact, its stated standard error, the
    exact's own Monte Carlo standard error, seed, t) over the last 10 populations before the
    decision."""
    y, r = run_seed(seed, particles)
    rng = np.random.default_rng(seed)
    decision = r.summary()["decision"]["population"]
    rows = []
    for t in range(max(2, decision - 9), decision + 1):
        ev = r.populations[t - 1].evidence
        exact, noise = exact_abc(y, r.populations[t - 1].epsilon, rng, 1_000_000)
        rows += [(m, ev.log_z[m] - exact[m], ev.log_z_se[m], noise[m], seed, t) for m in (0, 1)
                 if np.isfinite(ev.log_z[m])]
    return rows


def evidence_report(seeds: list[int], particles: int, processes: int) -> None:
    start = time.monotonic()
    with ProcessPoolExecutor(processes) as pool:
        rows = np.array([row for rs in pool.map(evidence_rows, seeds, [particles] * len(seeds)) for row in rs])
    print(f"## Each copy's log Z(eps_t) against the exact: the last 10 populations before the decision, seeds "
          f"{seeds[0]}-{seeds[-1]} ({time.monotonic() - start:.0f} s on {processes} processes)\n")
    print("| copy | checks | error, mean | z, mean / sd | stated se, median | the exact's own se, median |")
    print("|---|---|---|---|---|---|")
    for m, name in enumerate(("uniform", "log")):
        b = rows[rows[:, 0] == m]
        z = b[:, 1] / b[:, 2]
        print(f"| {name} | {len(b)} | {b[:, 1].mean():+.4f} ± {b[:, 1].std(ddof=1) / math.sqrt(len(b)):.4f} | "
              f"{z.mean():+.2f} / {z.std(ddof=1):.2f} | {np.median(b[:, 2]):.4f} | {np.median(b[:, 3]):.4f} |")
    pairs = {(r[4], r[5]): r for r in rows[rows[:, 0] == 1]}
    both = [(r, pairs[(r[4], r[5])]) for r in rows[rows[:, 0] == 0] if (r[4], r[5]) in pairs]
    split = np.array([a[1] - b[1] for a, b in both])
    z = split / np.array([math.hypot(a[2], b[2]) for a, b in both])
    print(f"\nThe split (uniform minus log), {len(split)} checks: {split.mean():+.4f} ± "
          f"{split.std(ddof=1) / math.sqrt(len(split)):.4f}, RMS {math.sqrt(np.mean(split**2)):.4f}, "
          f"z mean {z.mean():+.2f} sd {z.std(ddof=1):.2f}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", default="1-20")
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--particles", type=int, default=500)
    parser.add_argument("--evidence", action="store_true", help="each copy's log Z against the exact (see above)")
    args = parser.parse_args()
    seeds = seeds_of(args.seeds)
    if args.evidence:
        evidence_report(seeds, args.particles, args.processes)
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
