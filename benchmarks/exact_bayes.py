"""Exact Bayes beside abcns: dynesty with the exact Gaussian likelihood, on the same data,
models, priors and simulator as an abcns run with the default spec.

    python -m benchmarks.exact_bayes [--case cubic-vs-cq linear-vs-cubic paper41] [--seeds 1-5]
                                     [--processes 1] [--nlive 1000] [--json OUT]
                                     [--cache DIR] [--particles N]

``--particles`` (abcns's particles) and ``--cache ''`` (no cache) are for smoke runs
(tests/test_exact_bayes_benchmark.py).

Needs ``pip install -e '.[bench]'`` (dynesty); ``make bench-peers`` installs it and runs this.

Cases (two nested Duffing models each; data seed = run seed for the synthetic ones):

- ``cubic-vs-cq``: cubic truth (k3 = 1e3, k5 = 0) against cubic (c, k, k3) and cubic-quintic
  (c, k, k3, k5 ~ U(0, 1e6), a prior that holds the truth k5 = 0): ``FAMILIES["duffing"]`` of
  :mod:`benchmarks.nested_models`;
- ``linear-vs-cubic``: linear truth (k3 = 0) against linear (c, k) and cubic (c, k,
  k3 ~ U(0, 1e4)): ``FAMILIES["linear-cubic"]``, truth simple;
- ``paper41``: §4.1's own data and spec (``examples/duffing_41``: cubic-quintic truth, the
  stored records, the same for every seed; the seed is abcns's and dynesty's only).

The synthetic data are :func:`benchmarks.nested_models.make_data`'s (Gaussian force, 1000
samples at 100 Hz, fit on the first 500) with Gaussian noise of 1 % of the clean response's
RMS; §4.1's records were made the same way (``examples/make_data.py``, ``duffing_41``), and
its stored clean record gives that std exactly. Both sides know the noise: the spec states
it (``data.noise_std``) and dynesty's likelihood uses it.

abcns: the case's data and models with the default spec (no ``stop`` section; the default
sampler but ``epsilon_initial: 100`` and 4 RK4 substeps, as :mod:`benchmarks.nested_models`),
``abcns.run`` in this process; everything it reports is read from ``Result.summary()`` only
(probabilities and their errors, posterior, decision rule, stop reason, warnings,
simulations), so this shows whatever the summary says.

Exact: per model, ``dynesty.NestedSampler`` (``bound="multi"``, ``sample="unif"``, ``dlogz``
0.1) with the exact log-likelihood of the observation on the fit window, Gaussian with the
known std, each evaluation one trajectory of the very simulator abcns runs (numba
:class:`worker.simulators.Duffing` built from the job's own simulator's settings: dt,
substeps, input hold, divergence bound; a simulation that fails is likelihood 0, as abcns
rejects it), priors the spec's (the unit cube mapped onto the uniform boxes). ``"unif"``
(points drawn uniformly in the multi-ellipsoid bound): these posteriors have 2-4 dimensions
and are close to Gaussian at 1 % noise, where it needs the fewest evaluations per
iteration (linear-vs-cubic seed 1, the linear model, 500 live points: ``unif`` 29.5 k
evaluations in 26 s, ``rslice`` 201 k in 66 s, log Z within 0.02 and widths within 3 % of
each other); each evaluation is one single-row simulation (~0.2 ms). From the run: log Z and
its error, p(model) = Z_m / sum Z (equal model priors) with a delta-method error, per
parameter the weighted mean, std and 2.5 / 97.5 % quantiles (``importance_weights``), the
likelihood evaluations and the wall time. ``--nlive`` 1000 (default): the 95 % interval
widths' own Monte Carlo error (the std over :data:`N_REPLICAS` resampled and jittered copies
of the run, ``jitter_run(resample_run(...))``, printed as "exact width rse") measured 1.7-2.0 %
of the width on linear-vs-cubic seed 1 (500: 2.2-3.4 %; it falls as 1 / sqrt(nlive), so 1 %
would take ~4000 live points, four times the evaluations), ten times below the 0.8-1.25 band
the check applies, and the mean's error ~0.02 exact sd (~4000 effective samples), ten times
below its 0.25; that run took 58 k evaluations and 46-49 s for the 2-parameter model, most of
it dynesty's own bookkeeping (its multi-ellipsoid updates). dynesty's answer does
not depend on abcns, so it is cached per (case, seed, model, nlive) in
``benchmarks/measurements/exact_bayes_cache/`` (with the data and settings it was made
from: a change of either reruns it); a rerun after a change to abcns redoes abcns only.

Printed: per (case, seed) the exact and abcns winners; for the models the exact answer
rejects, abcns's p ± se against the exact p, and their difference in abcns's se, and (per
model) abcns's effective particles and its ln Bayes factor against the exact winner less the
exact one (a model that left the run early is read on its last particles); abcns's
decision rule, stop reason and number of warnings; abcns's simulations against dynesty's
evaluations; wall times. Per parameter of every model in abcns's posterior, the 95 %
interval width ratio abcns / exact and the mean shift (abcns - exact) in exact posterior
sds. Then per case over seeds, and the Done-when line. Its tolerances:

- the winner: abcns chooses the exact winner, every run;
- the losing models' p within max(0.005, 2 se) of the exact p: 2 se is a 95 % band of
  abcns's own stated error; 0.005 a floor for where that se vanishes (a p near 0 or 1), a
  difference that changes no decision;
- every interval 0.8-1.25x the exact width (a band symmetric in log, 1.25 = 1 / 0.8):
  docs/design.md, "The noise floor and the decision tolerance": an ABC posterior uniform on
  the region below the decision tolerance has per-parameter variances (p + sqrt(2 p)) /
  (p + 2) = 0.8-1.2 of the Gaussian posterior's for p = 1..8 (widths 0.9-1.1), so the band
  holds a tolerance reading with room for both sides' Monte Carlo error;
- every mean within 0.25 exact sd: the Monte Carlo error of a weighted mean of ~100 or more
  effective particles is 0.1 sd or less, so 0.25 sd is 2.5 of those errors or more.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from benchmarks.model_selection import seeds_of
from benchmarks.nested_models import FAMILIES, FIT, FS, make_data

ROOT = Path(__file__).resolve().parents[1]
PAPER41 = ROOT / "examples" / "duffing_41"
CACHE = Path(__file__).resolve().parent / "measurements" / "exact_bayes_cache"
#: share of the clean response's RMS (the noise std of the synthetic cases and of §4.1's data)
NOISE = 0.01
#: the cases: (nested_models family, or None for §4.1's spec)
CASES = {"cubic-vs-cq": "duffing", "linear-vs-cubic": "linear-cubic", "paper41": None}
#: dynesty's settings (part of the cache key)
SAMPLE, BOUND, DLOGZ = "unif", "multi", 0.1
#: replicas of dynesty's run (resampled and jittered) for its own error on the interval widths
N_REPLICAS = 20
#: the Done-when tolerances (module docstring)
P_FLOOR, P_SE, WIDTH_BAND, SHIFT_MAX = 0.005, 2.0, (0.8, 1.25), 0.25


# -- the cases' data and specs ---------------------------------------------------------------

def case_data(case: str, seed: int) -> dict[str, Any]:
    """Force, observed and clean records of ``case`` and the noise std (observed units).

    The synthetic cases: :func:`benchmarks.nested_models.make_data` at the simple truth,
    seed ``seed``; §4.1: the stored records of ``examples/duffing_41`` (any seed)."""
    family = CASES[case]
    if family is None:
        data = {"force": np.load(PAPER41 / "force.npy"), "observed": np.load(PAPER41 / "displacement.npy"),
                "clean": np.load(PAPER41 / "displacement_clean.npy")}
    else:
        data = make_data(FAMILIES[family][2], NOISE, seed)
    # the generators' own std: NOISE x the clean record's RMS over the whole record
    data["noise_std"] = float(NOISE * np.sqrt(np.mean(data["clean"] ** 2)))
    return data


def case_spec(case: str, data: dict[str, Any], seed: int, particles: int | None) -> tuple[dict, Path | None]:
    """The abcns job spec of ``case`` (the default spec: no ``stop`` section, the default
    sampler but ``epsilon_initial: 100``) and the folder its paths are relative to."""
    import yaml

    sampler: dict[str, Any] = {"epsilon_initial": 100}
    if particles is not None:
        sampler["particles"] = particles
    family = CASES[case]
    if family is None:
        raw = yaml.safe_load((PAPER41 / "spec.yaml").read_text())
        raw.pop("stop", None)
        raw["data"]["noise_std"] = data["noise_std"]
        raw.update(name=f"exact-{case}", sampler=sampler, seed=seed)
        return raw, PAPER41
    simple, complex_, *_ = FAMILIES[family]
    models = [{**m, "simulator": "duffing", "integrator": {"substeps": 4}} for m in (simple, complex_)]
    return {
        "name": f"exact-{case}",
        "data": {"fs": FS, "input": data["force"].tolist(), "observed": data["observed"].tolist(), "fit": list(FIT),
                 "noise_std": data["noise_std"]},
        "models": models,
        "distance": "nmse",
        "sampler": sampler,
        "seed": seed,
    }, None


# -- exact Bayes: dynesty with the Gaussian likelihood ----------------------------------------

class Likelihood(Protocol):
    """What :func:`run_dynesty` runs: the parameters' names, dynesty's prior transform (the
    unit cube onto the priors) and the log-likelihood (:class:`ExactModel`,
    ``examples.cyclic_tests.exact.GaussianRestoring``)."""

    names: list[str]

    def prior_transform(self, u: np.ndarray) -> np.ndarray: ...

    def loglike(self, theta: np.ndarray) -> float: ...


class ExactModel:
    """One model's exact log-likelihood and prior transform for dynesty.

    ``loglike(theta)``: log N(observed[fit] | simulated[fit], sigma^2 I) of the free
    parameters ``theta`` (the model's prior order), -inf where the simulation fails (abcns
    rejects those too); ``prior_transform(u)``: the unit cube onto the uniform prior box."""

    def __init__(self, model: Any, simulator: Any, force: np.ndarray, observed: np.ndarray,
                 fit: tuple[int, int], sigma: float):
        from worker.compose import full_parameters
        from worker.simulators import OK, Duffing

        cfg = simulator.config()
        if cfg["simulator"] != "duffing":
            raise ValueError(f"model {model.name}: the exact side knows the Duffing simulator only, got {cfg['simulator']}")
        start, stop = fit
        # the job's own simulator settings, on the samples up to the fit window's end (the
        # integration is causal: the window's samples are those of the whole record's run)
        self.sim = Duffing(force[:stop], cfg["dt"], substeps=cfg["substeps"], output=cfg["output"],
                           state_bound=cfg["state_bound"], backend="numba",
                           input_interpolation=cfg["input_interpolation"])
        self.expand = full_parameters(model, simulator)
        self.ok = OK
        self.start, self.observed = start, np.asarray(observed[start:stop], dtype=float)
        self.sigma = float(sigma)
        self.names = list(model.priors)
        self.model = model
        self.low, self.width = model.coordinate_low, model.coordinate_width  # log theta's for a log-uniform prior

    def prior_transform(self, u: np.ndarray) -> np.ndarray:
        return self.model.from_coordinates(self.low + u * self.width)

    def loglike(self, theta: np.ndarray) -> float:
        out = self.sim.simulate(self.expand(theta))
        if out.status[0] != self.ok:
            return -np.inf
        return gaussian_loglike(out.values[0, self.start:] - self.observed, self.sigma)


def gaussian_loglike(residual: np.ndarray, sigma: float) -> float:
    """log N(residual | 0, sigma^2 I): the exact likelihood of i.i.d. Gaussian errors of std
    ``sigma``; -inf where the residuals are not finite (a failed simulation)."""
    chi2 = float(residual @ residual) / sigma**2
    if not math.isfinite(chi2):
        return -np.inf
    return -residual.size * math.log(sigma * math.sqrt(2 * math.pi)) - 0.5 * chi2


def weighted_summary(samples: np.ndarray, weights: np.ndarray, names: list[str]) -> dict[str, dict[str, float]]:
    """{parameter: {mean, std, q2_5, q97_5}} of weighted samples (n, d)."""
    from dynesty.utils import quantile

    w = weights / weights.sum()
    out = {}
    for j, name in enumerate(names):
        x = samples[:, j]
        mean = float(w @ x)
        lo, hi = quantile(x, [0.025, 0.975], weights=w)
        out[name] = {"mean": mean, "std": float(np.sqrt(w @ (x - mean) ** 2)), "q2_5": float(lo), "q97_5": float(hi)}
    return out


def width_rse(results: Any, names: list[str], rng: np.random.Generator) -> dict[str, float]:
    """dynesty's own relative error on each 95 % interval width: the std over
    :data:`N_REPLICAS` resampled and jittered copies of the run (no new evaluations)."""
    from dynesty.utils import jitter_run, resample_run

    widths = []
    for _ in range(N_REPLICAS):
        rep = jitter_run(resample_run(results, rstate=rng), rstate=rng)
        s = weighted_summary(rep.samples, rep.importance_weights(), names)
        widths.append([s[n]["q97_5"] - s[n]["q2_5"] for n in names])
    w = np.array(widths)
    return {n: float(w[:, j].std(ddof=1) / w[:, j].mean()) for j, n in enumerate(names)}


def run_dynesty(exact: Likelihood, nlive: int, seed: int, sample: str = SAMPLE) -> dict[str, Any]:
    """One model's exact answer: log Z and its error, the posterior summary, dynesty's own
    error on the interval widths, the likelihood evaluations and the wall time. ``sample``:
    dynesty's proposal inside the bound (``unif`` here; ``rwalk`` where a posterior of ~10
    dimensions or more fills its ellipsoids badly, as the cyclic tests' BWBN)."""
    import dynesty

    start = time.monotonic()
    sampler = dynesty.NestedSampler(exact.loglike, exact.prior_transform, len(exact.names), nlive=nlive,
                                    bound=BOUND, sample=sample, rstate=np.random.default_rng(seed))
    sampler.run_nested(dlogz=DLOGZ, print_progress=False)
    wall = time.monotonic() - start
    res = sampler.results
    weights = res.importance_weights()
    return {
        "log_z": float(res.logz[-1]), "log_z_err": float(res.logzerr[-1]),
        "posterior": weighted_summary(res.samples, weights, exact.names),
        "width_rse": width_rse(res, exact.names, np.random.default_rng(seed)),
        "ess": float(weights.sum() ** 2 / np.sum(weights**2)),
        "n_evaluations": int(np.sum(res.ncall)), "n_iterations": int(res.niter), "wall_s": wall,
    }


def cache_key(case: str, seed: int, nlive: int, exact: ExactModel, model: Any, force: np.ndarray) -> dict:
    """What dynesty's answer is made from: the data, the model, the simulator, its settings."""
    digest = hashlib.sha256()
    for a in (force[: exact.sim.n_samples], exact.observed):
        digest.update(np.ascontiguousarray(a, dtype=float).tobytes())
    return {"case": case, "seed": seed, "model": model.name, "nlive": nlive, "sample": SAMPLE, "bound": BOUND,
            "dlogz": DLOGZ, "replicas": N_REPLICAS, "sigma": exact.sigma, "data_sha256": digest.hexdigest(),
            "priors": {k: [p.low, p.high] for k, p in model.priors.items()},
            "fixed": {k: float(v) for k, v in model.fixed.items()}, "simulator": exact.sim.config()}


def cached(case: str, seed: int, nlive: int, job: Any, data: dict[str, Any],
           cache: Path | None) -> Iterator[tuple[ExactModel, dict, Path | None, dict | None]]:
    """Per model of ``job``: (its :class:`ExactModel`, its cache key, the cache file (None
    without a cache), dynesty's stored answer where the file's key is this one, else None)."""
    fit = tuple(job.spec.data.fit)
    for model, simulator in zip(job.models, job.simulators):
        exact = ExactModel(model, simulator, job.force, job.observed, fit, data["noise_std"])
        key = cache_key(case, seed, nlive, exact, model, job.force)
        path = None if cache is None else cache / f"{case}-s{seed}-{model.name}-n{nlive}.json"
        stored = json.loads(path.read_text()) if path is not None and path.exists() else None
        yield exact, key, path, stored["answer"] if stored is not None and stored.get("key") == key else None


def exact_answer(case: str, seed: int, nlive: int, job: Any, data: dict[str, Any], cache: Path | None) -> dict:
    """Every model's exact answer (cached) and the exact model probabilities with their
    delta-method errors (equal model priors)."""
    models: dict[str, dict] = {}
    for exact, key, path, stored in cached(case, seed, nlive, job, data, cache):
        model = exact.model
        exact.loglike(exact.prior_transform(np.full(len(exact.names), 0.5)))  # compiled kernels loaded
        if stored is not None:
            models[model.name] = {**stored, "cached": True}
            continue
        answer = run_dynesty(exact, nlive, seed)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps({"key": key, "answer": answer}, indent=1))
            os.replace(tmp, path)
        models[model.name] = {**answer, "cached": False}
    return {"models": models, **model_probabilities(models)}


def model_probabilities(models: dict[str, dict]) -> dict[str, dict[str, float]]:
    """``{"p": ..., "p_se": ...}``: p(model) = Z_m / sum Z (equal model priors) from each
    model's ``log_z`` and ``log_z_err``, with delta-method errors."""
    log_z = np.array([m["log_z"] for m in models.values()])
    err = np.array([m["log_z_err"] for m in models.values()])
    p = np.exp(log_z - log_z.max())
    p /= p.sum()
    # delta method: dp_i / dlogZ_j = p_i (delta_ij - p_j)
    jac = np.diag(p) - np.outer(p, p)
    se = np.sqrt((jac**2) @ err**2)
    names = list(models)
    return {"p": dict(zip(names, p.tolist())), "p_se": dict(zip(names, se.tolist()))}


# -- abcns, read through its summary ----------------------------------------------------------

def abcns_answer(job: Any, seed: int) -> dict:
    """abcns's answer, from ``Result.summary()`` only (a missing key is None)."""
    from abcns import run

    start = time.monotonic()
    r = run(job.models, job.evaluate, job.settings, job.stop, seed=seed, noise=job.noise)
    wall = time.monotonic() - start
    s = r.summary()
    decision = s.get("decision") or {}
    return {"p": s.get("model_probabilities") or {}, "p_se": s.get("model_probability_se") or {},
            "posterior": s.get("posterior") or {}, "rule": decision.get("rule"), "reading": decision.get("reading"),
            "stop_reason": s.get("stop_reason"), "warnings": s.get("warnings"),
            "n_simulations": s.get("n_simulations"), "wall_s": wall,
            "ess": decision.get("effective_particles") or {},
            "log_z": {m: v.get("log_z") for m, v in (s.get("log_evidence") or {}).items()}}


def one(case: str, seed: int, nlive: int, particles: int | None, cache: str | None) -> dict:
    """One (case, seed): the exact answer (cached) and abcns's."""
    from service.spec import build, parse

    data = case_data(case, seed)
    raw, base = case_spec(case, data, seed, particles)
    job = build(parse(raw), base)
    exact = exact_answer(case, seed, nlive, job, data, Path(cache) if cache else None)
    return {"case": case, "seed": seed, "nlive": nlive, "noise_std": data["noise_std"],
            "models": [m.name for m in job.models], "exact": exact, "abcns": abcns_answer(job, seed)}


# -- comparison and tables --------------------------------------------------------------------

def winner(p: dict[str, float]) -> str | None:
    finite = {k: v for k, v in p.items() if v is not None and math.isfinite(v)}
    return max(finite, key=finite.__getitem__) if finite else None


def compare(row: dict) -> dict:
    """The row's checks: winners, the losing models' p, and per parameter of every model in
    abcns's posterior the width ratio and the mean shift in exact sds."""
    ex, ab = row["exact"], row["abcns"]
    w_exact, w_abcns = winner(ex["p"]), winner(ab["p"])
    losers = []
    for m in row["models"]:
        if m == w_exact:
            continue
        p, se = ab["p"].get(m), ab["p_se"].get(m)
        diff = None if p is None else p - ex["p"][m]
        ok = diff is not None and abs(diff) <= max(P_FLOOR, P_SE * (se or 0.0))
        z = diff / se if diff is not None and se else None
        losers.append({"model": m, "p": p, "se": se, "p_exact": ex["p"][m], "p_exact_se": ex["p_se"][m],
                       "z": z, "ok": ok})
    params = []
    for m, post in ab["posterior"].items():
        exact_post = ex["models"].get(m, {}).get("posterior", {})
        for name, q in post.items():
            e = exact_post.get(name)
            if e is None:
                continue
            width = q.get("q97_5", math.nan) - q.get("q2_5", math.nan)
            ratio = width / (e["q97_5"] - e["q2_5"])
            shift = (q.get("mean", math.nan) - e["mean"]) / e["std"]
            ok = WIDTH_BAND[0] <= ratio <= WIDTH_BAND[1] and abs(shift) <= SHIFT_MAX
            params.append({"model": m, "parameter": name, "exact": e, "abcns": q, "ratio": ratio, "shift": shift,
                           "rse": ex["models"][m].get("width_rse", {}).get(name), "ok": ok})
    evals = sum(m["n_evaluations"] for m in ex["models"].values())
    sims = ab["n_simulations"]
    return {"winner_exact": w_exact, "winner_abcns": w_abcns, "winner_ok": w_abcns is not None and w_abcns == w_exact,
            "losers": losers, "params": params, "n_evaluations": evals,
            "sims_ratio": sims / evals if sims is not None and evals else None}


def fmt(x: Any, spec: str = ".3g") -> str:
    """``x`` formatted, "-" when missing or not finite."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return format(x, spec)


RUN_HEADER = ("| case | seed | exact winner | abcns winner | losing model | p abcns ± se | p exact ± se | "
              "(abcns - exact) / se | rule | reading | stop | warnings | abcns simulations | dynesty evaluations | "
              "simulations / evaluations | abcns wall s | dynesty wall s |")
PARAM_HEADER = ("| case | seed | model | parameter | exact mean ± sd | abcns mean ± sd | 95 % width abcns / exact | "
                "exact width rse | mean shift (exact sd) | within |")
MODEL_HEADER = ("| case | seed | model | exact log Z ± err | p exact ± se | p abcns ± se | dynesty evaluations | "
                "iterations | effective samples | dynesty wall s | abcns effective particles | "
                "ln BF against the exact winner, abcns - exact |")
CASE_HEADER = ("| case | runs | winner agrees | losing p within max(0.005, 2 se) | width ratio min | width ratio max | "
               "max abs mean shift (exact sd) | simulations / evaluations |")


def print_runs(rows: list[dict], checks: list[dict]) -> None:
    print(RUN_HEADER)
    print("|" + "---|" * RUN_HEADER.count(" | ") + "---|")
    for r, c in zip(rows, checks):
        ab, ex = r["abcns"], r["exact"]
        dyn_wall = sum(m["wall_s"] for m in ex["models"].values())
        cached = " (cached)" if all(m.get("cached") for m in ex["models"].values()) else ""
        warnings = ab["warnings"]
        for lo in c["losers"] or [{"model": "-", "p": None, "se": None, "p_exact": None, "p_exact_se": None, "z": None}]:
            print(f"| {r['case']} | {r['seed']} | {c['winner_exact'] or '-'} | {c['winner_abcns'] or '-'} | "
                  f"{lo['model']} | {fmt_p(lo['p'])} ± {fmt_p(lo['se'])} | "
                  f"{fmt_p(lo['p_exact'])} ± {fmt_p(lo['p_exact_se'])} | {fmt(lo['z'], '+.2f')} | "
                  f"{ab['rule'] or '-'} | {ab['reading'] or '-'} | {ab['stop_reason'] or '-'} | "
                  f"{'-' if warnings is None else len(warnings)} | {fmt(ab['n_simulations'], ',')} | "
                  f"{c['n_evaluations']:,} | {fmt(c['sims_ratio'], '.3f')} | {ab['wall_s']:.1f} | {dyn_wall:.1f}{cached} |")


def fmt_p(x: float | None) -> str:
    """A probability: 4 decimals, or 2 significant digits below 1e-3."""
    return fmt(x, ".1e" if x is not None and 0 < abs(x) < 1e-3 else ".4f")


def bayes_factor_error(row: dict, model: str) -> float | None:
    """abcns's ln Bayes factor of ``model`` against the exact winner less the exact one (None
    for the winner itself, or where abcns gives no log evidence)."""
    ex, log_z = row["exact"], row["abcns"].get("log_z", {})
    top = winner(ex["p"])
    if top is None or model == top or log_z.get(model) is None or log_z.get(top) is None:
        return None
    return (log_z[model] - log_z[top]) - (ex["models"][model]["log_z"] - ex["models"][top]["log_z"])


def print_models(rows: list[dict]) -> None:
    print(MODEL_HEADER)
    print("|" + "---|" * MODEL_HEADER.count(" | ") + "---|")
    for r in rows:
        ex, ab = r["exact"], r["abcns"]
        for name, m in ex["models"].items():
            print(f"| {r['case']} | {r['seed']} | {name} | {m['log_z']:.2f} ± {m['log_z_err']:.2f} | "
                  f"{fmt_p(ex['p'][name])} ± {fmt_p(ex['p_se'][name])} | {fmt_p(ab['p'].get(name))} ± "
                  f"{fmt_p(ab['p_se'].get(name))} | {m['n_evaluations']:,} | {m['n_iterations']:,} | {m['ess']:,.0f} | "
                  f"{m['wall_s']:.1f}{' (cached)' if m.get('cached') else ''} | {fmt(ab.get('ess', {}).get(name), '.1f')} | "
                  f"{fmt(bayes_factor_error(r, name), '+.2f')} |")


def print_params(rows: list[dict], checks: list[dict]) -> None:
    print(PARAM_HEADER)
    print("|" + "---|" * PARAM_HEADER.count(" | ") + "---|")
    for r, c in zip(rows, checks):
        for p in c["params"]:
            e, a = p["exact"], p["abcns"]
            print(f"| {r['case']} | {r['seed']} | {p['model']} | {p['parameter']} | {e['mean']:.6g} ± {e['std']:.3g} | "
                  f"{fmt(a.get('mean'), '.6g')} ± {fmt(a.get('std'))} | {fmt(p['ratio'], '.3f')} | "
                  f"{fmt(p['rse'], '.1%')} | {fmt(p['shift'], '+.2f')} | {'yes' if p['ok'] else 'no'} |")


def print_cases(rows: list[dict], checks: list[dict]) -> None:
    print(CASE_HEADER)
    print("|" + "---|" * CASE_HEADER.count(" | ") + "---|")
    groups: dict[str, list[dict]] = {}
    for r, c in zip(rows, checks):
        groups.setdefault(r["case"], []).append(c)
    for case, cs in groups.items():
        losers = [lo for c in cs for lo in c["losers"]]
        ratios = [p["ratio"] for c in cs for p in c["params"] if math.isfinite(p["ratio"])]
        shifts = [abs(p["shift"]) for c in cs for p in c["params"] if math.isfinite(p["shift"])]
        sims = [c["sims_ratio"] for c in cs if c["sims_ratio"] is not None]
        print(f"| {case} | {len(cs)} | {sum(c['winner_ok'] for c in cs)} of {len(cs)} | "
              f"{sum(lo['ok'] for lo in losers)} of {len(losers)} | {fmt(min(ratios, default=None), '.3f')} | "
              f"{fmt(max(ratios, default=None), '.3f')} | {fmt(max(shifts, default=None), '.2f')} | "
              f"{fmt(float(np.median(sims)) if sims else None, '.3f')} |")


def done_when(checks: list[dict]) -> str:
    """The Done-when line with PASS/FAIL counts."""
    winners = [c["winner_ok"] for c in checks]
    losers = [lo["ok"] for c in checks for lo in c["losers"]]
    params = [p["ok"] for c in checks for p in c["params"]]
    parts = [f"{label}: {sum(xs)} PASS, {len(xs) - sum(xs)} FAIL"
             for label, xs in (("winner", winners), ("losing p", losers), ("intervals", params))]
    verdict = "PASS" if all(winners) and all(losers) and all(params) and params else "FAIL"
    return ("Done when: exact winner every time; losing p within max(0.005, 2 se); every interval 0.8-1.25x "
            f"the exact width with mean within 0.25 exact sd. {'; '.join(parts)}. {verdict}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--case", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--seeds", default="1-5")
    parser.add_argument("--processes", type=int, default=1)
    parser.add_argument("--nlive", type=int, default=1000, help="dynesty's live points (default %(default)s)")
    parser.add_argument("--json", default=None, help="also write the rows as JSON")
    parser.add_argument("--cache", default=str(CACHE), help="dynesty's answers ('' for none; default %(default)s)")
    parser.add_argument("--particles", type=int, default=None, help="abcns's particles (smoke runs; default the spec's)")
    args = parser.parse_args(argv)
    cases = [(c, s) for c in args.case for s in seeds_of(args.seeds)]
    start = time.monotonic()
    call = (args.nlive, args.particles, args.cache or None)
    if args.processes > 1:
        with ProcessPoolExecutor(args.processes) as pool:
            rows = list(pool.map(one, *zip(*cases), *([v] * len(cases) for v in call)))
    else:
        rows = [one(c, s, *call) for c, s in cases]
    checks = [compare(r) for r in rows]
    print(f"# exact Bayes (dynesty, nlive {args.nlive}, {SAMPLE}, dlogz {DLOGZ}) beside abcns "
          f"({time.monotonic() - start:.0f} s on {args.processes} process(es))\n")
    print_runs(rows, checks)
    print()
    print_models(rows)
    print()
    print_params(rows, checks)
    print()
    print_cases(rows, checks)
    print()
    print(done_when(checks))
    if args.json:
        with open(args.json, "w") as f:
            json.dump([{**r, "checks": c} for r, c in zip(rows, checks)], f, indent=1)


if __name__ == "__main__":
    main()
