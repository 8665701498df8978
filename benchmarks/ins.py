"""Importance nested sampling's evidence, computed after the run: the candidate to replace the
coverage the direct estimate divides by (docs/benchmarks.md, "The coverage's two biases").

    python -m benchmarks.ins [--problem copies|two_models|balls_4_and_5|line_and_disc] [--seeds 1-14] [--processes 2]

Every population of an ABC-NS run proposes model m's particles uniformly in a region: the prior
box (population 1), then the bound B_{i} of population i inside the box, of prior mass V_i
(``Evidence.log_volume``), n_{i+1} proposals. Over all of them the proposals come from the
mixture sum_i n_i q_i(x), q_i(x) = 1{x in B_i} / V_i, which holds the whole box (population 1's
term), so

    Z_m(eps_t) = sum over m's new particles x of populations 1..t with d(x) < eps_t of
                 1 / sum_{i < t} n_{i+1} q_i(x)        (importance nested sampling's estimator)

needs no coverage: a part of the region that B_{t-1} misses is counted through the older
bounds that held it. One correction: a particle that a bound was fitted to lies inside it by
construction, where a fresh point there might not; its membership of that bound is read
leave-one-out (its group of ``bounds.union_groups`` refitted without it, enlarged by f0). The
standard error is that of n = sum n_i independent draws from the mixture (an upper bound for
the deterministic mixture's).

Each check compares this estimate and abcns's own log Z with the exact ABC evidence at a
population's tolerance: the closed-form toys of ``tests/closed_form.py`` (the checks of
``benchmarks.evidence_calibration``), or the copies of ``benchmarks.copies`` over the last 10
populations before the decision (their exact evidence a Monte Carlo over the accepted ball,
whose own standard error is printed: the log copy's prior density, 1 / theta, makes it noisy).
An experiment, not abcns's estimator yet.
"""

from __future__ import annotations

import argparse
import math
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from abcns import NSSettings, Result, StopRules, run
from abcns import bounds as bd
from abcns import ellipsoid as ell
from abcns.likelihood import of_floor
from abcns.priors import Model, same_models
from benchmarks import copies as cp
from benchmarks.model_selection import seeds_of


def inside_without_each(x: np.ndarray, f0: float) -> np.ndarray | None:
    """For each of the n points ``x`` of one group: whether it lies inside the covariance
    ellipsoid of the other n - 1 scaled to hold them all and enlarged by ``f0`` (what
    ``ellipsoid.fit_many`` would fit to them, unless its covariance needs repair), by rank-one
    downdates: with u = x - mean, S = U^T U and G = U S^-1 U^T, removing point i moves the
    mean by u_i / (n - 1) and S by -n / (n - 1) u_i u_i^T (Sherman-Morrison), so every
    Mahalanobis distance under every leave-one-out fit comes from G (O(n^2) after one
    solve; 0.05 ms for 45 points in 11 dimensions against 0.1 ms per refit). None where
    n - 1 <= d or S is singular."""
    n, d = x.shape
    if n - 1 <= d:
        return None
    u = x - x.mean(axis=0)
    try:
        g = u @ np.linalg.solve(u.T @ u, u.T)
    except np.linalg.LinAlgError:
        return None
    k, c, h = n / (n - 1), 1.0 / (n - 1), np.diag(g)
    denom = 1.0 - k * h  # zero when point i alone spans a direction
    if not np.all(denom > 1e-12):
        return None
    quad = h[None, :] + 2 * c * g + c * c * h[:, None]  # [i, j]: w^T S^-1 w, w = u_j + u_i / (n - 1)
    cross = g + c * h[:, None]  # [i, j]: w^T S^-1 u_i
    others = (n - 2) * (quad + k * cross**2 / denom[:, None])  # x_j's squared distance without i
    np.fill_diagonal(others, -np.inf)
    own = (n - 2) * (k * k * h + k * (k * h) ** 2 / denom)  # x_i's, x_i - mean_i = k u_i
    return own <= f0 * others.max(axis=1) * (1.0 + 1e-10) * (1.0 + ell.CONTAINS_SLACK)


def held_without(points: np.ndarray, n_own: int, bound: bd.Union, enlargement: float, max_ellipsoids: int) -> np.ndarray:
    """Whether ``bound``, fitted to ``points``, holds each of the first ``n_own`` points when its
    ellipsoid is refitted without that point (the others as they are): by downdates
    (:func:`inside_without_each`) where the ellipsoid's covariance needed no repair, else by
    refitting."""
    held = ell.n_containing(bound, points[:n_own]) > 0
    _, groups = bd.union_groups(points, max_ellipsoids)
    if len(groups) != len(bound):  # not this fit's grouping (a fallback shape): in-sample
        return held
    for j, rows in enumerate(groups):
        own = rows[rows < n_own]
        if not own.size:
            continue
        fast = inside_without_each(points[rows], enlargement) if bound[j].note == "" else None
        if fast is not None:
            without = fast[rows < n_own]
        elif rows.size > 1:
            refits = ell.fit_many([points[rows[rows != i]] for i in own], [bound[j]] * own.size, enlargement=enlargement)
            without = np.array([bool(ell.n_containing((e,), points[i : i + 1])[0]) for e, i in zip(refits, own, strict=True)])
        else:
            without = np.zeros(own.size, bool)  # its ellipsoid goes with it
        rest = bound[:j] + bound[j + 1 :]
        in_rest = ell.n_containing(rest, points[own]) > 0 if rest else np.zeros(own.size, bool)
        held[own] = without | in_rest
    return held


@dataclass(frozen=True)
class Mixture:
    """One model's new particles over a whole run and the proposal densities at each:
    ``distances`` and ``births`` (the population, from 1, that drew each), ``terms[k, i]`` =
    n_{i+1} q_i(x_k), population i + 1's proposals times its region's density at particle k
    (column 0: population 1's, the prior box of mass 1), membership of a bound read
    leave-one-out for the particles it was fitted to; ``n_proposed`` per population."""

    distances: np.ndarray
    births: np.ndarray
    terms: np.ndarray
    n_proposed: np.ndarray

    def log_z(self, t: int, epsilon: float) -> tuple[float, float] | None:
        """(log Z(epsilon), its standard error) from the particles of populations 1..t below
        ``epsilon`` (<= eps_t), or None without one."""
        rows = np.flatnonzero((self.distances < epsilon) & (self.births <= t))
        if not rows.size:
            return None
        return log_total(-np.log(self.terms[rows, :t].sum(axis=1)), int(self.n_proposed[:t].sum()))


def log_total(log_w: np.ndarray, n: int) -> tuple[float, float]:
    """(log of the sum of the weights exp(``log_w``), its standard error) for an estimate over
    ``n`` proposals (the weights of those not kept are 0): that of ``n`` independent draws from
    the mixture, var(n w) / n."""
    top = float(np.max(log_w))
    w = np.exp(log_w - top)
    z = float(w.sum())
    return top + math.log(z), math.sqrt(max(float(np.sum((w * n) ** 2)) / n - z**2, 0.0) / n) / z


def mixtures(result: Result, models: list[Model], settings: NSSettings) -> list[Mixture]:
    """Each model's :class:`Mixture` over ``result``'s populations."""
    pops, twins = result.populations, same_models(models)
    frames = [bd.Frame(m, unit=True) for m in models]
    out = []
    for m, model in enumerate(models):
        d = model.n_dim

        def key(row: np.ndarray, d: int = d) -> bytes:
            return row[:d].tobytes()

        held = []  # per population i: {particle: held by B_i refitted without it}, for those B_i was fitted to
        for pop in pops[:-1]:
            below = pop.distances < pop.epsilon_next
            own = np.flatnonzero(below & (pop.models == m))
            other = np.flatnonzero(below & np.isin(pop.models, twins[m]))
            other = other[model.in_prior(pop.theta[other, :d])] if other.size else other
            table = {}
            if pop.ellipsoids[m] and own.size:
                points = frames[m].to_frame(np.vstack([pop.theta[own, :d], pop.theta[other, :d]]))
                inside = held_without(points, own.size, pop.ellipsoids[m], settings.enlargement, settings.n_ellipsoids)
                table = {key(pop.theta[r]): bool(h) for r, h in zip(own, inside, strict=True)}
            held.append(table)
        x, distance, born, keys = [], [], [], []
        for j, pop in enumerate(pops):
            n_survivors = int(np.count_nonzero(pops[j - 1].survivors)) if j else 0
            new = np.flatnonzero((np.arange(pop.n_particles) >= n_survivors) & (pop.models == m))
            x.append(frames[m].to_frame(pop.theta[new, :d]))
            distance.append(pop.distances[new])
            born.append(np.full(new.size, j + 1))
            keys += [key(pop.theta[r]) for r in new]
        points = np.vstack(x)
        n_proposed = np.array([int(p.evidence.n_proposed[m]) for p in pops])
        terms = np.zeros((points.shape[0], len(pops)))
        terms[:, 0] = n_proposed[0]
        for i in range(len(pops) - 1):  # population i + 1's bound proposed population i + 2
            bound = pops[i].ellipsoids[m]
            if not bound or not n_proposed[i + 1]:
                continue
            inside = ell.n_containing(bound, points) > 0
            for k, name in enumerate(keys):
                inside[k] = held[i].get(name, inside[k])
            terms[:, i + 1] = n_proposed[i + 1] * inside / math.exp(pops[i].evidence.log_volume[m])
        out.append(Mixture(np.concatenate(distance), np.concatenate(born), terms, n_proposed))
    return out


def log_evidence(result: Result, models: list[Model], settings: NSSettings) -> dict[tuple[int, int], tuple[float, float]]:
    """{(t, m): (log Z_m(eps_t), its standard error)} for every population t >= 2 where model m
    has a particle below eps_t."""
    out = {}
    for m, mix in enumerate(mixtures(result, models, settings)):
        for t in range(2, len(result.populations) + 1):
            estimate = mix.log_z(t, result.populations[t - 1].epsilon)
            if estimate is not None:
                out[(t, m)] = estimate
    return out


def read_answer(result: Result, models: list[Model], settings: NSSettings) -> list[tuple[float, float]]:
    """Each model's likelihood evidence (log, relative to the run's floor's best fit, as
    ``Result.reading``'s) and its standard error, read with the mixture's weights: every new
    particle in the shell between two tolerances where it lies, eps_{s+1} <= d < eps_s (the
    innermost, below eps_{T+1}, counted as shell T), weighted by L(d) / the mixture of
    populations 1..s, if population s or an earlier one drew it."""
    pops = result.populations
    log_l = of_floor(result.floor) if result.floor is not None else None
    if log_l is None:
        raise ValueError("the run has no floor to read by")
    tolerances = np.array([p.epsilon for p in pops] + [pops[-1].epsilon_next])
    out = []
    for mix in mixtures(result, models, settings):
        shell = np.clip(np.searchsorted(-tolerances, -mix.distances, side="left"), 1, len(pops))
        rows = np.flatnonzero(mix.births <= shell)
        if not rows.size:
            out.append((-math.inf, math.inf))
            continue
        log_w = log_l(mix.distances[rows]) - np.log(mix.terms[rows].cumsum(axis=1)[np.arange(rows.size), shell[rows] - 1])
        out.append(log_total(log_w, int(mix.n_proposed.sum())))
    return out


def toy_checks(toy: str, seed: int) -> list[tuple]:
    """(model, INS error, its se, abcns error, its se, 0, seed, t) of each check of a closed-form toy."""
    from benchmarks.evidence_calibration import MIN_PARTICLES, TOYS, problem

    models, evaluate, exact_log_z = problem(toy)
    ns, stop = TOYS[toy]
    settings = NSSettings(particles=1000, **ns)
    r = run(models, evaluate, settings, StopRules(min_epsilon_decrease=None, **stop), seed=seed)
    rows = []
    for (t, m), (log_z, se) in log_evidence(r, models, settings).items():
        pop = r.populations[t - 1]
        if t >= 3 and pop.model_counts(len(models))[m] >= MIN_PARTICLES:
            exact = exact_log_z(pop.epsilon)[m]
            rows.append((m, log_z - exact, se, pop.evidence.log_z[m] - exact, pop.evidence.log_z_se[m], 0.0, seed, t))
    return rows


def copies_checks(seed: int) -> list[tuple]:
    """(model, INS error, its se, abcns error, its se, the exact's Monte Carlo se, seed, t) over the last
    10 populations before the decision of ``benchmarks.copies``."""
    y, r = cp.run_seed(seed, 500)
    models, rng = cp.copies(), np.random.default_rng(seed)
    estimate = log_evidence(r, models, NSSettings(particles=500))
    decision = r.summary()["decision"]["population"]
    rows = []
    for t in range(max(2, decision - 9), decision + 1):
        pop = r.populations[t - 1]
        _, _, exact, noise = cp.exact_abc(y, pop.epsilon, rng, 1_000_000)
        for m in (0, 1):
            if (t, m) in estimate:
                log_z, se = estimate[(t, m)]
                rows.append((m, log_z - exact[m], se, pop.evidence.log_z[m] - exact[m], pop.evidence.log_z_se[m], noise[m],
                             seed, t))
    return rows


def checks(problem: str, seed: int) -> list[tuple]:
    return copies_checks(seed) if problem == "copies" else toy_checks(problem, seed)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--problem", default="copies", choices=["copies", "two_models", "balls_4_and_5", "line_and_disc"])
    parser.add_argument("--seeds", default="1-14")
    parser.add_argument("--processes", type=int, default=2)
    args = parser.parse_args()
    seeds, start = seeds_of(args.seeds), time.monotonic()
    with ProcessPoolExecutor(args.processes) as pool:
        rows = np.array([row for rs in pool.map(checks, [args.problem] * len(seeds), seeds) for row in rs])
    print(f"## Importance nested sampling's log Z against abcns's: {args.problem}, seeds {args.seeds} "
          f"({time.monotonic() - start:.0f} s on {args.processes} processes)\n")
    print("| model | checks | estimate | error, mean | z, mean / sd | stated se, median | reference's own se, median |")
    print("|---|---|---|---|---|---|---|")
    if args.problem == "copies":
        names = [m.name for m in cp.copies()]
    else:
        from benchmarks.evidence_calibration import problem

        names = [m.name for m in problem(args.problem)[0]]
    for m in np.unique(rows[:, 0]).astype(int):
        b = rows[rows[:, 0] == m]
        for name, err, se in (("importance NS", 1, 2), ("abcns", 3, 4)):
            z, error = b[:, err] / b[:, se], b[:, err].std(ddof=1) / math.sqrt(len(b))
            print(f"| {names[m]} | {len(b)} | {name} | {b[:, err].mean():+.4f} ± {error:.4f} | "
                  f"{z.mean():+.2f} / {z.std(ddof=1):.2f} | {np.median(b[:, se]):.4f} | {np.median(b[:, 5]):.4f} |")
    if len(names) == 2:  # the split, model 0's log Z minus model 1's, where both are checked
        first, second = rows[rows[:, 0] == 0], rows[rows[:, 0] == 1]
        pairs = {(s, t): r for s, t, r in zip(second[:, 6], second[:, 7], second, strict=True)}
        both = [(r, pairs[(r[6], r[7])]) for r in first if (r[6], r[7]) in pairs]
        if both:
            print(f"\nThe split ({names[0]} minus {names[1]}), {len(both)} checks:\n")
            for name, err, se in (("importance NS", 1, 2), ("abcns", 3, 4)):
                split = np.array([a[err] - b[err] for a, b in both])
                z = split / np.array([math.hypot(a[se], b[se]) for a, b in both])
                print(f"- {name}: {split.mean():+.4f} ± {split.std(ddof=1) / math.sqrt(len(split)):.4f}, "
                      f"RMS {math.sqrt(np.mean(split**2)):.4f}, z mean {z.mean():+.2f} sd {z.std(ddof=1):.2f}")


if __name__ == "__main__":
    main()
