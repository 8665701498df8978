"""The exact split between the two BWBN copies (uniform and log-uniform priors), from one set of
importance draws for both.

    python -m examples.cyclic_tests.split --data DIR [--specimen gill ...] [--seed 1] [--draws 160000]
                                          [--abcns OUT] [--out OUT]

``exact.py --sample importance`` estimates each copy's log Z from its own draws, so the split
log Z_bwbn - log Z_bwbn_log carries both errors (gill: 675.96 +- 0.06 and 687.38 +- 0.01 from
a proposal with 291 effective draws, the split -11.42; the estimate here is -11.49 +- 0.01).
Here one proposal covers both copies' posteriors and every draw is weighted for each copy:
w_k = p_k(theta) m(theta) / q(theta), p_k the copy's prior density in the parameters' own
units (0 outside its box: the uniform copy's box reaches below the log copy's, to delta_nu,
p and q of 0), m the likelihood with sigma integrated out exactly
(:func:`importance.log_sigma_marginal`, dynesty's target). The split is log sum w_u - log
sum w_l; its variance from the shared draws, sum a^2 + sum b^2 - 2 sum a b (a, b each
copy's weights normalised), is far below either copy's own. The proposal is a mixture, in
equal shares, of :data:`COMPONENTS` multivariate t's per copy (:func:`importance.t_proposal`)
in that copy's coordinates (log theta on the log copy's log-uniform parameters), started from
abcns's posteriors (run.py's summary, ``--abcns``) and refitted :data:`ROUNDS` times to a
quarter of the draws weighted by that copy's weights (2-means clusters, one t each: daniel's
uniform copy holds two modes). Printed per specimen: each copy's log Z, its standard error and
effective draws, the split and its error, and the share of the uniform copy's evidence outside
the log copy's box (chiu: 0.79).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.special import logsumexp

from examples.cyclic_tests.exact import SIGMA_HIGH, SIGMA_LOW, GaussianRestoring, abcns_summary, specimen_job
from examples.cyclic_tests.importance import BATCH, log_sigma_marginal, t_proposal
from examples.cyclic_tests.run import SPECIMENS

#: t's per copy in the proposal, and its refits before the answer's draws
COMPONENTS, ROUNDS = 2, 3
#: the copies: the uniform box first, then the log-uniform one (models.yaml)
COPIES = ("bwbn", "bwbn_log")


class Proposal:
    """Equal shares of t's in each copy's coordinates (``coordinates[c]``: its model, mapping
    theta there and back); ``rvs`` and ``logpdf`` in the parameters' own units."""

    def __init__(self, models: list[Any], components: list[list[Any]]):
        self.models, self.components = models, components
        self.flat = [(c, t) for c, ts in enumerate(components) for t in ts]

    def rvs(self, n: int, rng: np.random.Generator) -> np.ndarray:
        which = rng.integers(0, len(self.flat), n)
        out = np.empty((n, self.models[0].n_dim))
        for j, (c, t) in enumerate(self.flat):
            rows = which == j
            if rows.any():
                out[rows] = self.models[c].from_coordinates(np.atleast_2d(t.rvs(size=int(rows.sum()), random_state=rng)))
        return out

    def logpdf(self, theta: np.ndarray) -> np.ndarray:
        parts = np.full((len(self.flat), theta.shape[0]), -np.inf)
        for j, (c, t) in enumerate(self.flat):
            model = self.models[c]
            logs = model.log_columns
            ok = np.all(theta[:, logs] > 0, axis=1)  # log coordinates exist
            if ok.any():
                u = model.to_coordinates(theta[ok])
                parts[j, ok] = t.logpdf(u) - np.sum(u[:, logs], axis=1)  # d log theta / d theta = 1 / theta
        return logsumexp(parts, axis=0) - math.log(len(self.flat))


def fitted(model: Any, theta: np.ndarray, weights: np.ndarray, k: int = COMPONENTS) -> list[Any]:
    """``k`` t's fitted to the weighted points ``theta`` in ``model``'s coordinates (2-means on
    the standardised points; a cluster of too few points is left out)."""
    u = model.to_coordinates(theta)
    labels = kmeans2(u / (u.std(axis=0) + 1e-300), k, seed=np.random.default_rng(0), minit="++")[1]
    out = [t_proposal(u[labels == j], weights[labels == j]) for j in range(k)
           if np.count_nonzero(labels == j) > 2 * u.shape[1] and weights[labels == j].sum() > 0]
    return out or [t_proposal(u, weights)]


def weighted(exact: GaussianRestoring, models: list[Any], proposal: Proposal, n: int,
             rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(``n`` draws of ``proposal``, each copy's log weight at each: (copies, n))."""
    theta = proposal.rvs(n, rng)
    rss = np.concatenate([exact.rss(exact.model.to_coordinates(theta[i:i + BATCH]))
                          for i in range(0, n, BATCH)])
    log_m = log_sigma_marginal(rss, exact.observed.size, SIGMA_LOW, SIGMA_HIGH)
    log_q = proposal.logpdf(theta)
    log_w = np.full((len(models), n), -np.inf)
    for c, model in enumerate(models):
        inside = model.in_prior(theta) & np.isfinite(log_m)
        log_w[c, inside] = model.log_prior_density(theta[inside]) + log_m[inside] - log_q[inside]
    return theta, log_w


def split_answer(folder: Path, name: str, seed: int, starts: dict, draws: int) -> dict:
    """Both copies' log Z and their split on specimen ``name`` (``starts``: abcns's posterior
    per copy, {parameter: {mean, std}}; a copy without one starts from its twin's)."""
    job = specimen_job(folder, name, seed, ["bwbn", "bwbn_log"])
    window = tuple(job.spec.data.fit) if job.spec.data.fit else (0, len(job.observed))
    models = [job.models[[m.name for m in job.models].index(c)] for c in COPIES]
    exact = GaussianRestoring(models[0], job.simulators[0], job.observed, window)
    rng = np.random.default_rng([seed, 7])
    components = []
    for model in models:  # abcns's posterior as a cloud of 4,000 points, in the copy's coordinates
        names = model.parameter_names
        start = starts.get(model.name) or next(starts[c] for c in COPIES if c in starts)  # else its twin's
        mean, sd = (np.array([start[p][key] for p in names]) for key in ("mean", "std"))
        u_mean = model.to_coordinates(mean[None])[0]
        u_sd = np.where(model.log_columns, sd / np.where(model.log_columns, mean, 1.0), sd)
        cloud = model.from_coordinates(u_mean + u_sd * rng.standard_normal((4000, model.n_dim)))
        components.append(fitted(model, cloud, np.ones(4000), 1))
    proposal = Proposal(models, components)
    for _ in range(ROUNDS):
        theta, log_w = weighted(exact, models, proposal, draws // 4, rng)
        refits = []
        for c, model in enumerate(models):
            w = np.exp(log_w[c] - np.max(log_w[c]))
            refits.append(fitted(model, theta[w > 0], w[w > 0]))
        proposal = Proposal(models, refits)
    theta, log_w = weighted(exact, models, proposal, draws, rng)
    shares = np.exp(log_w - logsumexp(log_w, axis=1, keepdims=True))
    out: dict[str, Any] = {"specimen": name, "seed": seed, "draws": draws}
    for c, copy in enumerate(COPIES):
        out[copy] = {"log_z": float(logsumexp(log_w[c]) - math.log(draws)),
                     "se": math.sqrt(max(float(np.sum(shares[c] ** 2)) - 1 / draws, 0.0)),
                     "effective": float(1 / np.sum(shares[c] ** 2))}
    a, b = shares
    out["split"] = out["bwbn"]["log_z"] - out["bwbn_log"]["log_z"]
    out["split_se"] = math.sqrt(max(float(np.sum(a * a) + np.sum(b * b) - 2 * np.sum(a * b)), 0.0))
    out["uniform_outside_log_box"] = float(np.sum(a[~models[1].in_prior(theta)]))
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="your copy of the data (README.md)")
    parser.add_argument("--specimen", nargs="+", default=["gill"], choices=SPECIMENS)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--draws", type=int, default=160_000)
    parser.add_argument("--abcns", type=Path, default=Path("out/cyclic_tests"), help="run.py's --out")
    parser.add_argument("--out", type=Path, default=None, help="write the answers here (JSON)")
    args = parser.parse_args(argv)
    answers = []
    print("| specimen | log Z, uniform (se, effective draws) | log Z, log (se, effective draws) | split (se) | "
          "uniform's evidence outside the log box |\n|---|---|---|---|---|")
    for name in args.specimen:
        summary = abcns_summary(args.data, name, args.seed, args.abcns)
        a = split_answer(args.data, name, args.seed, {**summary["alone"], **summary["posterior"]}, args.draws)
        answers.append(a)
        u, lg = a["bwbn"], a["bwbn_log"]
        print(f"| {name} | {u['log_z']:.3f} ({u['se']:.3f}, {u['effective']:,.0f}) | {lg['log_z']:.3f} ({lg['se']:.3f}, "
              f"{lg['effective']:,.0f}) | {a['split']:.3f} ({a['split_se']:.3f}) | {a['uniform_outside_log_box']:.3f} |",
              flush=True)
        if args.out is not None:
            args.out.write_text(json.dumps(answers, indent=1))


if __name__ == "__main__":
    main()
