"""The cyclic tests with the exact Gaussian likelihood (dynesty) beside abcns.

    python -m examples.cyclic_tests.exact --data DIR [--specimen daniel ...] [--seed 1]
                                          [--nlive 300] [--sample rwalk] [--model bwbn] [--abcns OUT] [--out OUT]
                                          [--stored OUT]
                                          [--mcmc STEPS]

Per specimen: the records, scaling, models, priors and simulators of ``run.py`` (the same
job, built from ``models.yaml``), and per model ``dynesty.NestedSampler`` with the Gaussian
log-likelihood of the load residuals (i.i.d., std ``sigma``), through the machinery of
:mod:`benchmarks.exact_bayes` (``run_dynesty``, ``gaussian_loglike``,
``model_probabilities``). Needs the optional extra ``.[bench]`` (dynesty).

The noise std is a **free parameter** of each model, log-uniform on
[:data:`SIGMA_LOW`, :data:`SIGMA_HIGH`] (scaled units: the load's peak is 1), the same prior
for both: there is no measured noise level here (the residuals are model error, NMSE 1-10 %),
and abcns's noise floor is an estimate read from its own run (an NMSE level), so fixing
sigma at it would import abcns's answer into the exact one; with sigma free each model's
evidence integrates over its own misfit level, the usual exact treatment of an unknown
error scale.

abcns's side is ``run.py``'s summary ``OUT/<name>-seed<N>.json`` (``--abcns``, default
``out/cyclic_tests``): read when it exists, else made (``run.run_specimen``). Printed per
specimen: log Z ± err per model, p(model) exact (delta-method se) and abcns's, the NMSE and
the residuals' whiteness (``abcns.noise.whiteness``) at the exact posterior mean, and per
parameter the exact posterior mean and 95 % interval beside abcns's; ``--out`` gets the JSON,
``--stored`` prints such a JSON's answers again (specimens not in it are run).

``--mcmc STEPS``: a second exact method on the same target, to check dynesty's posterior:
per model :data:`CHAINS` adaptive random-walk Metropolis chains (numpy only) on the
likelihood with sigma integrated out (Jeffreys), started over-dispersed around dynesty's
answer; their second halves' intervals and split R-hat are printed beside dynesty's.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.exact_bayes import gaussian_loglike, model_probabilities, run_dynesty
from examples.cyclic_tests.run import MODELS, SPECIMENS, read_specimen, run_specimen, spec_for

#: the noise std's log-uniform prior (scaled load units)
SIGMA_LOW, SIGMA_HIGH = 1e-3, 0.5
#: Metropolis chains of ``--mcmc`` (the second exact method)
CHAINS = 16


class GaussianRestoring:
    """One model's exact log-likelihood and prior transform for dynesty, sigma free.

    ``theta``: the model's free parameters (its prior order), then sigma;
    ``loglike``: log N(observed[window] | simulated[window], sigma^2 I), -inf where the
    simulation fails (abcns rejects those too). ``low`` and ``width`` are the prior box's in
    the coordinates the prior is uniform in (``Model.to_coordinates``: log theta for a
    log-uniform prior), which :meth:`rss`, :meth:`log_marginal` and the chains and importance
    sampling work in; :meth:`natural` maps back."""

    def __init__(self, model: Any, simulator: Any, observed: np.ndarray, window: tuple[int, int]):
        from worker.compose import full_parameters
        from worker.simulators import OK

        self.simulator, self.expand, self.ok = simulator, full_parameters(model, simulator), OK
        self.window = window
        self.observed = np.asarray(observed[window[0]:window[1]], dtype=float)
        self.names = [*model.priors, "sigma"]
        self.model = model
        self.low, self.width = model.coordinate_low, model.coordinate_width

    def natural(self, u: np.ndarray) -> np.ndarray:
        """Points in the prior's coordinates, in the parameters' own units."""
        return self.model.from_coordinates(u)

    def coordinates(self, mean: np.ndarray, sd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A mean and sd in the parameters' units, in the prior's coordinates (sd / mean for
        log theta: the delta method)."""
        logs = self.model.log_columns
        return self.model.to_coordinates(mean), np.where(logs, sd / np.where(logs, mean, 1.0), sd)

    def prior_transform(self, u: np.ndarray) -> np.ndarray:
        sigma = SIGMA_LOW * (SIGMA_HIGH / SIGMA_LOW) ** u[-1]
        return np.append(self.natural(self.low + u[:-1] * self.width), sigma)

    def residual(self, params: np.ndarray) -> np.ndarray | None:
        """simulated - observed on the window at the model's parameters ``params`` (no
        sigma); None where the simulation fails."""
        out = self.simulator.simulate(self.expand(params))
        if out.status[0] != self.ok:
            return None
        return out.values[0, self.window[0]:self.window[1]] - self.observed

    def loglike(self, theta: np.ndarray) -> float:
        r = self.residual(theta[:-1])
        return -np.inf if r is None else gaussian_loglike(r, float(theta[-1]))

    def rss(self, params: np.ndarray) -> np.ndarray:
        """The sum of squared residuals of a batch of the model's parameters (k, d) in the
        prior's coordinates, one batch simulation; inf outside the prior box or where the
        simulation fails."""
        params = np.atleast_2d(params)
        out = np.full(params.shape[0], np.inf)
        inside = np.all((params >= self.low) & (params <= self.low + self.width), axis=1)
        if np.any(inside):
            sim = self.simulator.simulate(self.expand(self.natural(params[inside])))
            r = sim.values[:, self.window[0]:self.window[1]] - self.observed
            out[inside] = np.where(sim.status == self.ok, np.sum(r**2, axis=1), np.inf)
        return out

    def log_marginal(self, params: np.ndarray) -> np.ndarray:
        """The log posterior (up to a constant) of a batch of the model's parameters (k, d; in
        the prior's coordinates, where the prior is uniform),
        sigma integrated out under Jeffreys' prior (the log-uniform one, its bounds far from
        the posterior's sigma): -(n / 2) log(sum of squared residuals), -inf outside the
        prior box or where the simulation fails. The target of :func:`metropolis`."""
        return -0.5 * self.observed.size * np.log(self.rss(params))

    def diagnose(self, posterior: dict[str, dict[str, float]]) -> dict[str, Any]:
        """At the posterior mean: the NMSE (%) and the residuals' whiteness (Ljung-Box, lag-1
        autocorrelation): whether the i.i.d. Gaussian errors the likelihood assumes are there."""
        from abcns.noise import whiteness

        r = self.residual(np.array([posterior[n]["mean"] for n in self.names[:-1]]))
        if r is None:
            return {}
        test = whiteness(r)
        return {"nmse_pct": float(100 * np.mean(r**2) / np.var(self.observed)),
                "residual_lag1": None if test is None else test.autocorrelation[0],
                "ljung_box_p": None if test is None else test.p_value}


def metropolis(log_target: Any, starts: np.ndarray, steps: int, rng: np.random.Generator,
               adapt_every: int = 200) -> tuple[np.ndarray, float]:
    """Parallel random-walk Metropolis chains, one per row of ``starts`` (k, d), the second
    exact method beside dynesty: Gaussian proposals of covariance s^2 C, C the chains' pooled
    covariance (first the starts'), s^2 = 2.38^2 / d scaled towards an acceptance of 0.234
    (Haario et al. 2001; Roberts & Rosenthal 2001). Adapted every ``adapt_every`` steps in the
    first half only, so the second half is a Markov chain with a fixed kernel. Returns the
    chains (steps, k, d) and the second half's acceptance rate."""
    k, d = starts.shape
    x, lp = starts.copy(), log_target(starts)
    cov, log_s = np.cov(starts.T), np.log(2.38**2 / d)
    chain, acc = np.empty((steps, k, d)), np.zeros(steps)
    for step in range(steps):
        chol = np.linalg.cholesky(np.exp(log_s) * cov + 1e-14 * np.eye(d))
        prop = x + rng.standard_normal((k, d)) @ chol.T
        lp_prop = log_target(prop)
        with np.errstate(invalid="ignore"):  # -inf - -inf: a chain outside stays until a proposal is inside
            ok = np.log(rng.random(k)) < lp_prop - lp
        x[ok], lp[ok] = prop[ok], lp_prop[ok]
        chain[step], acc[step] = x, np.mean(ok)
        if (step + 1) % adapt_every == 0 and step < steps // 2:
            cov = np.cov(chain[step // 2: step + 1].reshape(-1, d).T)
            log_s += np.mean(acc[step + 1 - adapt_every: step + 1]) - 0.234
    return chain, float(np.mean(acc[steps // 2:]))


def split_rhat(chain: np.ndarray) -> np.ndarray:
    """Gelman-Rubin's R-hat per parameter over the halves of each chain ((steps, k, d))."""
    n = chain.shape[0] // 2
    halves = np.concatenate([chain[:n], chain[n: 2 * n]], axis=1)
    within = np.mean(np.var(halves, axis=0, ddof=1), axis=0)
    between = n * np.var(np.mean(halves, axis=0), axis=0, ddof=1)
    return np.sqrt(((n - 1) / n * within + between / n) / within)


def chains(exact: GaussianRestoring, posterior: dict, steps: int, seed: int) -> tuple[np.ndarray, dict]:
    """:data:`CHAINS` chains of :func:`metropolis` on ``exact.log_marginal``, started
    over-dispersed at N(mean, (2 sd)^2) of ``posterior`` (a summary: dynesty's, abcns's;
    clipped into the prior box; both in the prior's coordinates, :meth:`GaussianRestoring.coordinates`):
    their second halves (steps / 2, chains, d; in those coordinates), and the split R-hat per
    parameter and the acceptance."""
    rng = np.random.default_rng(seed)
    names = exact.names[:-1]
    mean, sd = exact.coordinates(*(np.array([posterior[n][k] for n in names]) for k in ("mean", "std")))
    starts = np.clip(mean + 2 * sd * rng.standard_normal((CHAINS, len(names))), exact.low, exact.low + exact.width)
    chain, acceptance = metropolis(exact.log_marginal, starts, steps, rng)
    second = chain[steps // 2:]
    return second, {"steps": steps, "chains": CHAINS, "rhat": dict(zip(names, split_rhat(second).tolist(), strict=True)),
                    "acceptance": acceptance}


def mcmc_check(exact: GaussianRestoring, posterior: dict, steps: int, seed: int) -> dict:
    """The second exact method on one model: :func:`chains` started around dynesty's
    ``posterior``; the second halves' posterior summary, split R-hat and acceptance."""
    from abcns.result import posterior_summary

    second, info = chains(exact, posterior, steps, seed)
    return {"posterior": posterior_summary(exact.natural(second.reshape(-1, second.shape[-1])), None, exact.names[:-1]),
            **info}


def with_mcmc(folder: Path, answer: dict, steps: int) -> dict:
    """``answer`` (one specimen's exact answers) with each model's :func:`mcmc_check` added."""
    job = specimen_job(folder, answer["specimen"], answer["seed"], list(answer["models"]))
    for model, simulator in zip(job.models, job.simulators, strict=True):
        exact = GaussianRestoring(model, simulator, job.observed, tuple(answer["window"]))
        ans = answer["models"][model.name]
        ans["mcmc"] = mcmc_check(exact, ans["posterior"], steps, answer["seed"])
        print(f"  {answer['specimen']} {model.name}: {steps} Metropolis steps x {CHAINS} chains, acceptance "
              f"{ans['mcmc']['acceptance']:.3f}, R-hat <= {max(ans['mcmc']['rhat'].values()):.3f}", flush=True)
    return answer


def specimen_job(folder: Path, name: str, seed: int, only: list[str] | None = None) -> Any:
    """run.py's job of specimen ``name`` (the scaled records, models.yaml's models; ``only``:
    these models alone)."""
    from service.spec import build, parse

    x, load = read_specimen(folder, name)
    return build(parse(spec_for(x / np.max(np.abs(x)), load / np.max(np.abs(load)), seed, None, only)))


def solve(exact: GaussianRestoring, method: argparse.Namespace, seed: int, start: list[dict]) -> dict:
    """One model's exact answer: dynesty (``method.sample`` its proposal, ``method.nlive``), or
    with ``--sample importance`` importance sampling (``method.draws`` draws, after chains of
    ``method.mcmc`` or 4000 steps started around each of ``start``, abcns's posteriors; the
    prior box's middle, sd a quarter of its width, where abcns has none)."""
    if method.sample != "importance":
        return run_dynesty(exact, method.nlive, seed, method.sample)
    from examples.cyclic_tests.importance import importance_answer

    if not start:  # the box's middle in the prior's coordinates, in the parameters' units
        mid = exact.natural(exact.low + exact.width / 2)
        sd = np.where(exact.model.log_columns, mid * exact.width / 4, exact.width / 4)
        start = [{n: {"mean": m, "std": s} for n, m, s in zip(exact.names[:-1], mid, sd, strict=True)}]
    return importance_answer(exact, start if len(start) > 1 else start[0], method.mcmc or 4000, method.draws, seed)


def start_of(model: Any, starts: dict) -> list[dict]:
    """abcns's posteriors of ``model`` and of the models over the same parameters (bwbn's and
    bwbn_log's: the same model under another prior, whose best fits are its best fits, and
    which may hold another mode: daniel's copies do), its own first; empty where the run left
    none."""
    own = [starts[model.name]] if model.name in starts else []
    twins = [s for name, s in starts.items() if name != model.name and set(s) == set(model.priors)]
    return own + [s for s in twins if s not in own]


def exact_specimen(folder: Path, name: str, seed: int, method: argparse.Namespace, only: list[str] | None = None,
                   starts: dict | None = None) -> dict:
    """Every model's (``only``: these models') exact answer (:func:`solve`; ``starts``: abcns's
    posterior per model) on specimen ``name`` and the exact model probabilities (among the
    models run)."""
    job = specimen_job(folder, name, seed, only)
    window = tuple(job.spec.data.fit) if job.spec.data.fit else (0, len(job.observed))
    models = {}
    for model, simulator in zip(job.models, job.simulators, strict=True):
        exact = GaussianRestoring(model, simulator, job.observed, window)
        models[model.name] = solve(exact, method, seed, start_of(model, starts or {}))
        models[model.name]["at_mean"] = exact.diagnose(models[model.name]["posterior"])
        print(f"  {name} {model.name}: log Z {models[model.name]['log_z']:.2f} ± {models[model.name]['log_z_err']:.2f}, "
              f"{models[model.name]['n_evaluations']:,} evaluations, {models[model.name]['wall_s']:.0f} s", flush=True)
    return {"specimen": name, "seed": seed, "nlive": method.nlive, "sample": method.sample,
            "observed_var": float(np.var(exact.observed)), "window": list(window), "models": models,
            **model_probabilities(models)}


def diagnosed(folder: Path, stored: dict) -> dict:
    """A stored answer (``--out``'s JSON) with ``at_mean`` filled in where it is missing."""
    job = specimen_job(folder, stored["specimen"], stored["seed"], list(stored["models"]))
    for model, simulator in zip(job.models, job.simulators, strict=True):
        ans = stored["models"][model.name]
        if not ans.get("at_mean"):
            exact = GaussianRestoring(model, simulator, job.observed, tuple(stored["window"]))
            ans["at_mean"] = exact.diagnose(ans["posterior"])
    window = slice(*stored["window"])
    stored.setdefault("observed_var", float(np.var(job.observed[window])))
    return stored


def abcns_summary(folder: Path, name: str, seed: int, out: Path, only: list[str] | None = None) -> dict:
    """run.py's summary of specimen ``name`` (``only``: of the run of these models,
    ``<name>-bw-bwbn-bwbn_log-seed<N>.json``): its JSON when there, else made now. A model
    the joint run left without a posterior (p ~ 0) takes the one of its run alone
    (``run.py --model bw``: ``<name>-bw-seed<N>.json``) when that is there, in
    ``summary["alone"]``."""
    path = out / f"{name}{'-'.join(['', *only]) if only else ''}-seed{seed}.json"
    summary = json.loads(path.read_text()) if path.is_file() else run_specimen(folder, name, seed, None, out, only)
    summary["alone"] = {}
    for model in summary.get("model_probabilities") or {}:
        alone = out / f"{name}-{model}-seed{seed}.json"
        if model not in (summary.get("posterior") or {}) and alone.is_file():
            summary["alone"][model] = json.loads(alone.read_text())["posterior"][model]
    return summary


def interval(q: dict | None) -> str:
    if not q:
        return "-"
    return f"{q['mean']:.4g} [{q['q2_5']:.4g}, {q['q97_5']:.4g}]"


def _g(x: float | None) -> str:
    return "-" if x is None else f"{x:.3g}"


def floor_sigma(floor: dict, observed_var: float) -> float:
    """abcns's noise floor as a noise std in the load's units: its ``noise_variance`` is one
    sample's noise in NMSE units (``abcns.noise``: d = 100 / (n s^2) sum r^2), so
    sigma^2 = noise_variance n s^2 / 100."""
    return math.sqrt(floor["noise_variance"] * floor["n_samples"] * observed_var / 100)


def mcmc_lines(exact: dict) -> list[str]:
    """Markdown lines: per model with a :func:`mcmc_check`, its intervals beside dynesty's."""
    lines = []
    for m, ans in exact["models"].items():
        if "mcmc" in ans:
            lines += ["", f"| {m}: parameter | dynesty mean [95 %] | Metropolis mean [95 %] | R-hat |", "|---|---|---|---|"]
            lines += [f"| {par} | {interval(q)} | {interval(ans['mcmc']['posterior'][par])} | "
                      f"{ans['mcmc']['rhat'][par]:.3f} |" for par, q in ans["posterior"].items() if par != "sigma"]
    return lines


def report(exact: dict, abcns: dict) -> list[str]:
    """Markdown lines: per model log Z, p exact ± se, p abcns; per parameter both intervals."""
    lines = ["| model | exact log Z ± err | p exact ± se | p abcns | likelihood evaluations | NMSE % at the exact mean | "
             "residual lag-1 autocorrelation | Ljung-Box p |", "|---|---|---|---|---|---|---|---|"]
    for m, ans in exact["models"].items():
        p_abcns = (abcns.get("model_probabilities") or {}).get(m)
        at = ans.get("at_mean") or {}
        lines.append(f"| {m} | {ans['log_z']:.2f} ± {ans['log_z_err']:.2f} | {exact['p'][m]:.4g} ± "
                     f"{exact['p_se'][m]:.2g} | {'-' if p_abcns is None else format(p_abcns, '.4g')} | "
                     f"{ans['n_evaluations']:,} | {_g(at.get('nmse_pct'))} | {_g(at.get('residual_lag1'))} | "
                     f"{_g(at.get('ljung_box_p'))} |")
    lines += ["", "| model | parameter | exact mean [95 %] | abcns mean [95 %] |", "|---|---|---|---|"]
    for m, ans in exact["models"].items():
        post = (abcns.get("posterior") or {}).get(m)
        alone = post is None and m in abcns.get("alone", {})
        post = abcns["alone"][m] if alone else post or {}
        for par, q in ans["posterior"].items():
            lines.append(f"| {m} | {par} | {interval(q)} | {interval(post.get(par))}{' (alone)' if alone else ''} |")
    lines += mcmc_lines(exact)
    floor = abcns.get("noise_floor") or {}
    if floor.get("noise_variance") is not None:
        lines.append(f"| ({floor.get('model')}) | sigma | | {floor_sigma(floor, exact['observed_var']):.4g} "
                     f"(abcns's noise floor, {floor.get('method')}) |")
    return lines


def starts(args: argparse.Namespace, name: str) -> dict | None:
    """abcns's posterior per model (its joint run's, else its run alone) where importance
    sampling needs somewhere to start its chains; None for dynesty."""
    if args.sample != "importance":
        return None
    summary = abcns_summary(args.data, name, args.seed, args.abcns, args.model)
    return {**summary["alone"], **(summary.get("posterior") or {})}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="your copy of the data (README.md)")
    parser.add_argument("--specimen", nargs="+", default=["daniel"], choices=SPECIMENS)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--nlive", type=int, default=300)
    parser.add_argument("--sample", default="rwalk", choices=("unif", "rwalk", "rslice", "slice", "importance"),
                        help="dynesty's proposal (rwalk: BWBN's 12 dimensions fill the ellipsoids badly for unif), "
                             "or importance sampling instead of dynesty (importance.py)")
    parser.add_argument("--draws", type=int, default=50_000, help="--sample importance: its draws per model")
    parser.add_argument("--model", action="append", choices=MODELS,
                        help="run only this model (repeatable): each model's log Z alone")
    parser.add_argument("--mcmc", type=int, default=0, metavar="STEPS",
                        help="also run 16 Metropolis chains of STEPS steps per model (the second exact method)")
    parser.add_argument("--abcns", type=Path, default=Path("out/cyclic_tests"), help="run.py's --out")
    parser.add_argument("--out", type=Path, default=None, help="write the exact answers here (JSON)")
    parser.add_argument("--stored", type=Path, default=None, help="print the answers of an earlier --out (no dynesty)")
    args = parser.parse_args(argv)
    stored = {} if args.stored is None else {a["specimen"]: a for a in json.loads(args.stored.read_text())}
    answers = []
    for name in args.specimen:
        if name in stored:
            exact = diagnosed(args.data, stored[name])
        else:
            exact = exact_specimen(args.data, name, args.seed, args, args.model, starts(args, name))
        if args.mcmc and args.sample != "importance":
            exact = with_mcmc(args.data, exact, args.mcmc)
        answers.append(exact)
        how = (f"importance sampling, {args.draws:,} draws" if exact.get("sample") == "importance"
               else f"{exact['nlive']} live points, {exact.get('sample', 'unif')}")
        print(f"\n### {name}, seed {args.seed}, {how}\n")
        if args.out is not None:  # after each specimen: a long run keeps what it has
            args.out.write_text(json.dumps(answers, indent=1))
        print("\n".join(report(exact, abcns_summary(args.data, name, args.seed, args.abcns, args.model))), flush=True)


if __name__ == "__main__":
    main()
