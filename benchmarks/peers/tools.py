"""One run of each tool on a case -> a plain record (per population: epsilon, cumulative
simulations, cumulative wall time, acceptance, model probabilities; final posterior).

abcns: ``abcns.run`` in this process with the serial executor (one core), the paper's
settings. pyABC: ``ABCSMC`` with its defaults (MedianEpsilon from a calibration sample of
the prior, MultivariateNormalTransition per model, ModelPerturbationKernel stay 0.7,
uniform model prior) except population size 1000, the MulticoreEvalParallelSampler on all
cores, the fixed distance of the case, and its history in a temporary sqlite file (its
default usage; not in memory).
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import replace
from datetime import datetime, timedelta

import numpy as np

from abcns import StopRules, run
from abcns.result import posterior_summary
from benchmarks.peers import cases
from benchmarks.peers.cases import Case


def warm_up(case: Case) -> None:
    """Compile (or load from numba's cache) every kernel both tools will call, outside the
    clocks: the simulators', and abcns's population step's (a two-population run of 100)."""
    run(case.models, case.evaluate, replace(case.settings, particles=100, batch_size=50),
        StopRules(min_epsilon_decrease=None, max_populations=2), seed=0, noise=case.noise)
    rng = np.random.default_rng(0)
    for m, sim in zip(case.models, case.simulators):
        pars = {p: 0.5 * (u.low + u.high) for p, u in m.priors.items()}
        row = cases.full_row(m, sim, pars)
        sim.simulate(row, rng)
        if hasattr(sim, "distance_nmse"):
            obs = case.observed["y"]
            sim.distance_nmse(np.repeat(row, 2, axis=0), obs, 0, obs.size, np.inf)


def _posterior(case: Case, theta: np.ndarray | None, weights: np.ndarray | None) -> dict | None:
    if theta is None or theta.shape[0] == 0:
        return None
    names = list(case.truth)
    post = posterior_summary(theta, weights, names)
    inside = sum(post[p]["q2_5"] <= v <= post[p]["q97_5"] for p, v in case.truth.items())
    rel = {p: abs(post[p]["mean"] - v) / abs(v) for p, v in case.truth.items()}
    return {"inside": int(inside), "n": len(names), "max_rel_error": max(rel.values()), "rel_error": rel,
            "mean": {p: post[p]["mean"] for p in names}}


def run_abcns(case: Case, seed: int) -> dict:
    r = run(case.models, case.evaluate, case.settings, case.stop, seed=seed, noise=case.noise)
    pops, cum = [], r.n_pilot_simulations
    for p in r.populations:
        cum += p.n_simulations
        pops.append({"t": p.t, "epsilon": float(p.epsilon), "sims": int(cum), "wall": float(p.elapsed_s),
                     "acceptance": float(p.acceptance_rate), "probs": [float(v) for v in p.model_probabilities]})
    names = [m.name for m in case.models]
    mi = names.index(case.truth_model)
    theta = None
    if r.populations and r.final.model_probabilities[mi] > 0:
        theta, _, _ = r.particles(mi)
    return {"tool": "abcns", "seed": seed, "populations": pops, "n_simulations": int(r.n_simulations),
            "wall": float(r.wall_time_s), "stop": r.stop_reason.value,
            "final_epsilon": pops[-1]["epsilon"] if pops else float("nan"),
            "probs": dict(zip(names, pops[-1]["probs"])) if pops else {},
            "posterior": _posterior(case, theta, None)}  # ABC-NS: each population's particles, uniformly


def run_pyabc(case: Case, seed: int, db_dir: str | None = None) -> dict:
    import logging

    import pyabc
    from pyabc.sampler import MulticoreEvalParallelSampler

    # pyABC logs every population at INFO (and near-zero total weights at WARNING): keep our one line per run
    logging.getLogger("ABC").setLevel(logging.ERROR)
    cases.SEED[0] = seed
    np.random.seed(seed)  # noqa: NPY002  pyABC draws from numpy's global state (its workers reseed themselves)
    priors = [pyabc.Distribution(**{p: pyabc.RV("loguniform", u.low, u.high) if u.log else pyabc.RV("uniform", u.low, u.width)
                                    for p, u in m.priors.items()}) for m in case.models]
    models = [cases.pyabc_model(case, i) for i in range(len(case.models))]
    tmp = tempfile.TemporaryDirectory(dir=db_dir, prefix="pyabc-")
    db = f"sqlite:///{os.path.join(tmp.name, f'run-{case.key}-{seed}.db')}"
    n_procs = os.cpu_count() or 1
    try:
        start_clock, start = time.monotonic(), datetime.now()
        abc = pyabc.ABCSMC(models, priors, case.distance, population_size=case.particles,
                           sampler=MulticoreEvalParallelSampler(n_procs=n_procs))
        abc.new(db, case.observed)
        h = abc.run(minimum_epsilon=case.target, max_total_nr_simulations=case.max_simulations,
                    max_walltime=timedelta(seconds=case.max_seconds))
        wall = time.monotonic() - start_clock
        table = h.get_all_populations().sort_values("t")
        probs = h.get_model_probabilities()
        pops, cum = [], 0
        for row in table.itertuples():
            cum += int(row.samples)
            if row.t < 0:  # the calibration sample (initial epsilon from the prior predictive)
                continue
            pr = [float(probs.loc[row.t].get(i, 0.0)) if row.t in probs.index else 0.0 for i in range(len(case.models))]
            pops.append({"t": int(row.t) + 1, "epsilon": float(row.epsilon), "sims": cum,
                         "wall": (row.population_end_time - start).total_seconds(),
                         "acceptance": case.particles / row.samples if row.samples else 0.0, "probs": pr})
        names = [m.name for m in case.models]
        mi = names.index(case.truth_model)
        theta = w = None
        if pops and pops[-1]["probs"][mi] > 0:
            df, w = h.get_distribution(m=mi, t=h.max_t)
            theta = df[list(case.truth)].to_numpy()
        return {"tool": "pyABC", "seed": seed, "populations": pops, "n_simulations": int(h.total_nr_simulations),
                "wall": wall, "stop": "", "final_epsilon": pops[-1]["epsilon"] if pops else float("nan"),
                "probs": dict(zip(names, pops[-1]["probs"])) if pops else {},
                "posterior": _posterior(case, theta, None if w is None else np.asarray(w)),
                "n_procs": n_procs, "db": "sqlite (temporary file)"}
    finally:
        tmp.cleanup()
