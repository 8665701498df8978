"""Synthetic truths for the displacement-driven restoring-force models (issue Y, point 5):
parameter recovery and Bouc-Wen vs Bouc-Wen-Baber-Noori model selection, seeds 1-5.

Run: ``python -m benchmarks.restoring [--seeds 1 2 3 4 5] [--particles 500] [--samples 400]``.

The problem (shared with ``tests/test_restoring.py``, which runs seed 1 with a smaller
population and a shorter record): the displacement is a sine of 4 cycles whose amplitude
grows from 0.75 to 3 (about 0.8 to 3 yield displacements ``z_u = (A / (beta + gamma))^(1/2)``
= 1.07), sampled ``n_samples`` times; the force of the true model plus Gaussian noise of
1 % of the clean force's standard deviation (the spec's ``noise_std``, so the stop rule knows
the noise floor). Bouc-Wen infers k, alpha, beta, gamma (A = 1, n = 2, c = 0 fixed: A and
alpha are redundant); BWBN infers those and delta_nu, delta_eta, zeta_s (p, psi, lambda, q
fixed at the truth: the pinching shape; its severity zeta_s is inferred). The priors hold
the Bouc-Wen model inside BWBN (delta_nu = delta_eta = zeta_s = 0 at the boxes' corner).

For each seed it prints, per true model: whether every true value lies inside the 95 %
posterior interval (the recovery run, the true model alone), the intervals' widths, and the
probability of the true model in the selection run (both models).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import abcns
from abcns import Model, NSSettings, StopRules
from abcns.distances import NMSE
from abcns.result import Result
from worker.compose import evaluator
from worker.restoring import BoucWenRestoring, BWBNRestoring

DT = 0.01
SUBSTEPS = 2
NOISE = 0.01  # of the clean force's standard deviation
BW_TRUE = {"c": 0.0, "k": 0.1, "alpha": 1.0, "A": 1.0, "beta": 0.6, "gamma": 0.1, "n": 2.0}
BWBN_TRUE = {**BW_TRUE, "delta_nu": 0.05, "delta_eta": 0.05, "p": 1.0, "zeta_s": 0.6, "psi": 0.2, "delta_psi": 0.0,
             "lambda": 0.5, "q": 0.1}
BW_PRIORS = {"k": (0.0, 0.3), "alpha": (0.5, 2.0), "beta": (0.2, 1.0), "gamma": (-0.2, 0.4)}
BW_FIXED = {"c": 0.0, "A": 1.0, "n": 2.0}
BWBN_PRIORS = {**BW_PRIORS, "delta_nu": (0.0, 0.2), "delta_eta": (0.0, 0.2), "zeta_s": (0.0, 0.9)}
BWBN_FIXED = {**BW_FIXED, "p": 1.0, "psi": 0.2, "lambda": 0.5, "q": 0.1}
TRUTHS = {"bw": BW_TRUE, "bwbn": BWBN_TRUE}


def displacement(n_samples: int) -> np.ndarray:
    """4 cycles of a sine whose amplitude grows linearly from 0.75 to 3."""
    t = np.arange(n_samples) / n_samples * 4.0
    return 3.0 * (0.25 + 0.75 * t / t[-1]) * np.sin(2 * np.pi * t)


def simulators(x: np.ndarray) -> dict:
    return {"bw": BoucWenRestoring(x, DT, substeps=SUBSTEPS), "bwbn": BWBNRestoring(x, DT, substeps=SUBSTEPS)}


def models() -> dict[str, Model]:
    return {"bw": Model("bw", BW_PRIORS, BW_FIXED), "bwbn": Model("bwbn", BWBN_PRIORS, BWBN_FIXED)}


def data(truth: str, n_samples: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """(displacement, observed force, noise std) of the true model ``truth`` ("bw" or "bwbn")."""
    x = displacement(n_samples)
    sim = simulators(x)[truth]
    clean = sim.simulate(np.array([[TRUTHS[truth][p] for p in sim.parameter_names]])).values[0]
    noise_std = NOISE * float(np.std(clean))
    return x, clean + noise_std * rng.standard_normal(n_samples), noise_std


def run(truth: str, names: list[str], n_samples: int, particles: int, seed: int) -> Result:
    """ABC-NS (the default, evidence variant) on data of ``truth`` with the models ``names``;
    one Generator from ``seed`` makes the noise, the run is seeded by ``seed`` too."""
    x, observed, noise_std = data(truth, n_samples, np.random.default_rng(seed))
    sims, mods = simulators(x), models()
    nmse = NMSE(observed)
    chosen = [mods[n] for n in names]
    evaluate = evaluator(chosen, [sims[n] for n in names], nmse)
    # the noise floor ends the run (the paper's rule, an absolute 0.01 % NMSE, is the size of
    # a 1 % noise's floor itself and stopped two BWBN runs of five early, intervals 10x wide)
    stop = StopRules(min_epsilon_decrease=None, max_populations=80)
    return abcns.run(chosen, evaluate, NSSettings(particles=particles, batch_size=50), stop, seed=seed,
                     noise=nmse.noise(noise_std))


def coverage(result: Result, truth: str, truths: dict = TRUTHS) -> dict[str, tuple[float, float, bool]]:
    """{parameter: (q2.5, q97.5, truth inside)} of the true model's posterior (``truths``:
    {model: {parameter: true value}})."""
    post = result.summary()["posterior"][truth]
    return {p: (v["q2_5"], v["q97_5"], v["q2_5"] <= truths[truth][p] <= v["q97_5"]) for p, v in post.items()}


def arguments(doc: str, particles: int, samples: int) -> argparse.Namespace:
    """The command line of a synthetic-truth benchmark: --seeds, --particles, --samples."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--particles", type=int, default=particles)
    parser.add_argument("--samples", type=int, default=samples)
    return parser.parse_args()


def main() -> None:
    args = arguments(__doc__ or "", 500, 400)
    print(f"particles {args.particles}, {args.samples} samples, noise {NOISE:.0%} of the force's std, "
          f"substeps {SUBSTEPS}")
    for truth in ("bw", "bwbn"):
        for seed in args.seeds:
            t0 = time.perf_counter()
            rec = run(truth, [truth], args.samples, args.particles, seed)
            cov = coverage(rec, truth)
            sel = run(truth, ["bw", "bwbn"], args.samples, args.particles, seed)
            p = sel.summary()["model_probabilities"][truth]
            report(f"truth {truth:4s} seed {seed}", truth, (rec, cov), (sel, p), TRUTHS[truth], t0)


def report(label: str, truth: str, recovery: tuple, selection: tuple, truths: dict, t0: float) -> None:
    """One seed's lines: the recovery run's intervals against ``truths``, the selection's p(truth)."""
    (rec, cov), (sel, p) = recovery, selection
    inside = sum(c[2] for c in cov.values())
    widths = ", ".join(f"{k} {hi - lo:.3g}" for k, (lo, hi, _in) in cov.items())
    print(f"{label}: recovery {inside}/{len(cov)} inside the 95 % intervals "
          f"({rec.stop_reason.value}, {rec.n_simulations} sims); p({truth}) = {p:.4f} "
          f"({sel.stop_reason.value}, {sel.n_simulations} sims); {time.perf_counter() - t0:.1f} s")
    print(f"    95 % widths: {widths}")
    for k, (lo, hi, ok) in cov.items():
        if not ok:
            print(f"    OUT: {k} [{lo:.4g}, {hi:.4g}], truth {truths[k]}")


if __name__ == "__main__":
    main()
