"""A second way to each model's exact evidence, beside dynesty: importance sampling.

``exact.py --sample importance``: per model, the :func:`exact.chains` (16 Metropolis chains on
the posterior, sigma integrated out) give the posterior's place and shape; a multivariate
Student t fitted to their second halves (mean, covariance times :data:`INFLATE` squared,
:data:`DF` degrees of freedom) is the proposal q, and ``draws`` points from it give

    Z = E_q[ prior(theta) m(theta) / q(theta) ],

``m(theta)`` the Gaussian likelihood of the residuals with sigma integrated out **exactly**
over the same log-uniform prior dynesty's sigma has (:func:`log_sigma_marginal`), so Z is the
quantity dynesty estimates (the same model, priors and data), reached without nested
sampling's proposals. The estimate is unbiased for any proposal that covers the posterior
(heavy tails, widened); its error is the weights' standard error, and the effective sample
size says how well q matched. Every likelihood is one batch simulation (the simulators run a
batch ~10 times faster per simulation than one by one, as dynesty calls them).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from scipy.special import gammaincc, gammaln, logsumexp

#: the proposal's degrees of freedom and its widening over the chains' covariance
DF, INFLATE = 5.0, 1.5
#: likelihoods per batch simulation
BATCH = 2000


def log_sigma_marginal(rss: np.ndarray, n: int, low: float, high: float) -> np.ndarray:
    """log of the integral over sigma, log-uniform on [low, high], of the Gaussian likelihood
    of n i.i.d. residuals with sum of squares ``rss``:

        int (2 pi s^2)^(-n/2) exp(-rss / 2 s^2) / (s ln(high / low)) ds
          = pi^(-n/2) Gamma(n/2) rss^(-n/2) / (2 ln(high / low)) * [Q(n/2, u_high) - Q(n/2, u_low)],

    u = rss / (2 s^2), Q the regularised upper incomplete gamma function. -inf where rss is
    inf (outside the prior box, a failed simulation), and where the bracket underflows (a
    sigma so far outside the prior that the integral is below e^-700 of its peak: such a theta
    has no weight beside the posterior's)."""
    a = n / 2
    rss = np.asarray(rss, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        inside = gammaincc(a, rss / (2 * high**2)) - gammaincc(a, rss / (2 * low**2))
        out = -a * np.log(np.pi) + gammaln(a) - np.log(2 * np.log(high / low)) - a * np.log(rss) + np.log(inside)
    return np.where(np.isfinite(rss), out, -np.inf)


def t_proposal(samples: np.ndarray, weights: np.ndarray | None = None) -> Any:
    """The multivariate t of :data:`DF` degrees of freedom whose mean is the (weighted)
    samples' and whose covariance is theirs times :data:`INFLATE` squared."""
    from scipy.stats import multivariate_t

    mean = np.average(samples, axis=0, weights=weights)
    cov = np.cov(samples.T, aweights=weights) * INFLATE**2
    # a direction the samples never moved in (chains stuck at a bound of the box) would make it
    # singular: 1e-9 of the largest variance added to each keeps it a distribution (scipy takes an
    # eigenvalue below ~2e-10 of the largest for zero)
    cov += np.eye(cov.shape[0]) * 1e-9 * max(float(np.max(np.diag(cov))), 1e-300)
    return multivariate_t(loc=mean, shape=cov * (DF - 2) / DF, df=DF)


def log_evidence(log_weights: np.ndarray) -> tuple[float, float, float]:
    """(log Z, its standard error, the effective sample size) from the log importance
    weights log(prior m / q) of N independent draws."""
    n = log_weights.size
    log_z = float(logsumexp(log_weights) - np.log(n))
    w = np.exp(log_weights - log_weights.max())
    se = float(np.std(w, ddof=1) / (np.mean(w) * np.sqrt(n)))
    return log_z, se, float(w.sum() ** 2 / np.sum(w**2))


def draw(exact: Any, proposal: Any, draws: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``draws`` points from ``proposal``: the points (N, d; in the prior's coordinates, where it
    is uniform), their log importance weights and their sums of squared residuals (inf outside
    the box or failed)."""
    from examples.cyclic_tests.exact import SIGMA_HIGH, SIGMA_LOW

    log_prior = -float(np.sum(np.log(exact.width)))
    points, log_w, rss = [], [], []
    for start in range(0, draws, BATCH):
        theta = np.atleast_2d(proposal.rvs(size=min(BATCH, draws - start), random_state=rng))
        r = exact.rss(theta)
        log_w.append(log_prior + log_sigma_marginal(r, exact.observed.size, SIGMA_LOW, SIGMA_HIGH) - proposal.logpdf(theta))
        points.append(theta)
        rss.append(r)
    return np.concatenate(points), np.concatenate(log_w), np.concatenate(rss)


class Modes:
    """A mixture of :func:`t_proposal`'s, one per mode, as one proposal (``rvs``, ``logpdf``)."""

    def __init__(self, components: list[Any], shares: np.ndarray):
        self.components, self.shares = components, np.asarray(shares, dtype=float) / np.sum(shares)

    def rvs(self, size: int, random_state: np.random.Generator) -> np.ndarray:
        which = random_state.choice(len(self.components), size=size, p=self.shares)
        out = np.empty((size, self.components[0].loc.size))
        for k, component in enumerate(self.components):
            if np.any(which == k):
                out[which == k] = np.atleast_2d(component.rvs(size=int(np.sum(which == k)), random_state=random_state))
        return out

    def logpdf(self, x: np.ndarray) -> np.ndarray:
        return logsumexp(np.stack([np.log(s) + c.logpdf(x) for s, c in zip(self.shares, self.components, strict=True)]),
                         axis=0)

    def refit(self, theta: np.ndarray, log_w: np.ndarray) -> Modes:
        """Each component refitted to the weighted draws it is the likeliest source of, its
        share their weight's (within [0.1, 0.9]: a mode the first draws missed is not dropped);
        a component left with too few draws keeps its fit."""
        ok = np.isfinite(log_w)
        w = np.where(ok, np.exp(log_w - np.max(log_w[ok])), 0.0)
        nearest = np.argmax(np.stack([c.logpdf(theta) for c in self.components]), axis=0)
        components, weight = [], []
        for k, component in enumerate(self.components):
            mine = ok & (nearest == k)
            fits = np.count_nonzero(mine) > 2 * theta.shape[1] and w[mine].sum() > 0
            components.append(t_proposal(theta[mine], w[mine]) if fits else component)
            weight.append(w[mine].sum())
        return Modes(components, np.clip(np.array(weight) / max(sum(weight), 1e-300), 0.1, 0.9))


def importance_answer(exact: Any, start: dict | list[dict], steps: int, draws: int, seed: int,
                      rounds: int = 4) -> dict[str, Any]:
    """One model's exact answer by importance sampling, in ``benchmarks.exact_bayes.run_dynesty``'s
    form (log Z and its error, the posterior with sigma, effective samples, evaluations, wall
    time) plus the chains' R-hat and the log Z of each quarter of the draws (a check of the
    error). ``start``: a posterior summary the chains start around (abcns's). The proposal is
    fitted twice: to the chains, then to a first round of ``draws / 2`` weighted draws (the
    chains' covariance is rough where they mix slowly); the answer is the second round's.

    Several starts (``start`` a list: the posteriors of a model's copies, which may sit in
    different modes): chains from each, a :class:`Modes` of one t per start, refitted
    ``rounds`` times to ``draws`` weighted draws (``first_round``: the first of them). One
    start held one of daniel's two BWBN modes under the uniform prior, at 98 effective draws
    of 50,000, its log Z 0.41 low (a stated error of 0.10); two starts give 541.23 +- 0.09 at
    200,000 draws (113 effective), against 541.12 +- 0.03 from a proposal fitted to abcns's
    particles of both modes (docs/benchmarks.md, "The coverage's two biases, measured")."""
    from abcns.result import posterior_summary
    from examples.cyclic_tests.exact import chains

    starts = start if isinstance(start, list) else [start]
    t0 = time.monotonic()
    runs = [chains(exact, s, steps, seed + k) for k, s in enumerate(starts)]
    rng = np.random.default_rng([seed, 1])
    if len(starts) == 1:
        second, info = runs[0]
        theta, log_w, _ = draw(exact, t_proposal(second.reshape(-1, second.shape[-1])), draws // 2, rng)
        first, round_one = np.isfinite(log_w), log_evidence(log_w)
        proposal: Any = t_proposal(theta[first], np.exp(log_w[first] - log_w[first].max()))
        extra = draws // 2
    else:
        info = {"chains": sum(r[1]["chains"] for r in runs), "starts": [r[1] for r in runs]}
        proposal = Modes([t_proposal(r[0].reshape(-1, r[0].shape[-1])) for r in runs], np.ones(len(runs)))
        for k in range(rounds):
            theta, log_w, _ = draw(exact, proposal, draws, rng)
            if k == 0:
                round_one = log_evidence(log_w)
            proposal = proposal.refit(theta, log_w)
        extra = rounds * draws
    theta, log_w, rss = draw(exact, proposal, draws, rng)
    log_z, se, ess = log_evidence(log_w)
    ok = np.isfinite(log_w)
    # sigma given theta: sigma^2 ~ inverse gamma(n / 2, rss / 2) (the prior's cut far from it)
    sigma = np.sqrt(rss[ok] / (2 * rng.gamma(exact.observed.size / 2, size=int(ok.sum()))))
    samples = np.column_stack([exact.natural(theta[ok]), sigma])
    out = {"log_z": log_z, "log_z_err": se, "ess": ess, "method": "importance", "draws": draws,
           "posterior": posterior_summary(samples, np.exp(log_w[ok] - log_w[ok].max()), exact.names),
           "quarters": [log_evidence(q)[0] for q in np.array_split(log_w, 4)], "chains": info,
           "first_round": dict(zip(("log_z", "log_z_err", "ess"), round_one, strict=True)),
           "n_evaluations": steps * info["chains"] + draws + extra, "wall_s": time.monotonic() - t0}
    if isinstance(proposal, Modes):
        out["mode_shares"] = proposal.shares.tolist()
    return out
