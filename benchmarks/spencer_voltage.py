"""Synthetic truths for Spencer's MR-damper model with the coil voltage as an input
(``spencer_mr_voltage``, worker/restoring.py; issue Y item 1 of its 3b): parameter recovery,
and Bouc-Wen vs Spencer model selection on Spencer data, seeds 1-5.

Run: ``python -m benchmarks.spencer_voltage [--seeds 1 2 3 4 5] [--particles 400] [--samples 1000]``.

The problem (shared with ``tests/test_restoring.py``, which runs seed 1 with a smaller
population and a shorter record), in Spencer et al.'s units (N, cm, s) and around their
identified values (J. Eng. Mech. 123(3), 1997, Table 1): the displacement is two sines (2.5 Hz,
0.3 cm and 6.1 Hz, 0.15 cm) sampled at 500 Hz, the commanded voltage a square wave between 0
and 2.25 V switched every 0.1 s (the filter's time constant 1 / eta = 5 ms), ``n_samples``
samples; the force of the true model plus Gaussian noise of 1 % of the clean force's standard
deviation (the spec's ``noise_std``). Spencer infers alpha_a, alpha_b, c0a, c0b and eta (the
others fixed at the truth); Bouc-Wen (``bouc_wen_restoring``, no voltage) infers c, k, alpha,
beta, gamma (A = 1, n = 2 fixed).

For each seed it prints whether every true value lies inside the 95 % posterior interval
(the recovery run, Spencer alone), the intervals' widths, and p(Spencer) in the selection run.
"""

from __future__ import annotations

import time

import numpy as np

import abcns
from abcns import Model, NSSettings, StopRules
from abcns.distances import NMSE
from abcns.result import Result
from benchmarks.restoring import arguments, coverage, report
from worker.compose import evaluator
from worker.restoring import BoucWenRestoring, SpencerMRVoltage

FS = 500.0
SUBSTEPS = 16
NOISE = 0.01  # of the clean force's standard deviation
#: Spencer et al. (1997)'s identified values, in N, cm, s and V
SPENCER_TRUE = {"alpha_a": 140.0, "alpha_b": 695.0, "c0a": 21.0, "c0b": 3.50, "c1a": 283.0, "c1b": 2.95, "k0": 46.9,
                "k1": 5.00, "x0": 14.3, "gamma": 363.0, "beta": 363.0, "A": 301.0, "n": 2.0, "eta": 190.0}
SPENCER_PRIORS = {"alpha_a": (50.0, 400.0), "alpha_b": (200.0, 1500.0), "c0a": (5.0, 60.0), "c0b": (0.0, 15.0),
                  "eta": (50.0, 600.0)}
SPENCER_FIXED = {k: v for k, v in SPENCER_TRUE.items() if k not in SPENCER_PRIORS}
BW_PRIORS = {"c": (0.0, 100.0), "k": (-50.0, 200.0), "alpha": (0.0, 2000.0), "beta": (0.0, 500.0),
             "gamma": (-100.0, 500.0)}
BW_FIXED = {"A": 1.0, "n": 2.0}
TRUTHS = {"spencer": SPENCER_TRUE}


def records(n_samples: int) -> tuple[np.ndarray, np.ndarray]:
    """(displacement in cm, commanded voltage in V) at ``FS``."""
    t = np.arange(n_samples) / FS
    x = 0.3 * np.sin(2 * np.pi * 2.5 * t) + 0.15 * np.sin(2 * np.pi * 6.1 * t + 1.0)
    return x, np.where(np.floor(t / 0.1) % 2 == 1, 2.25, 0.0)


def simulators(x: np.ndarray, e: np.ndarray) -> dict:
    return {"spencer": SpencerMRVoltage(x, 1 / FS, substeps=SUBSTEPS, voltage=e),
            "bw": BoucWenRestoring(x, 1 / FS, substeps=2)}


def models() -> dict[str, Model]:
    return {"spencer": Model("spencer", SPENCER_PRIORS, SPENCER_FIXED), "bw": Model("bw", BW_PRIORS, BW_FIXED)}


def data(n_samples: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(displacement, voltage, observed force, noise std) of Spencer's model at the truth."""
    x, e = records(n_samples)
    sim = simulators(x, e)["spencer"]
    clean = sim.simulate(np.array([[SPENCER_TRUE[p] for p in sim.parameter_names]])).values[0]
    noise_std = NOISE * float(np.std(clean))
    return x, e, clean + noise_std * rng.standard_normal(n_samples), noise_std


def run(names: list[str], n_samples: int, particles: int, seed: int) -> Result:
    """ABC-NS on Spencer data with the models ``names``; one Generator from ``seed`` makes the
    noise, and the run is seeded by ``seed`` too. The stop rule is the noise floor (the data's
    noise std given), as in benchmarks.restoring."""
    x, e, observed, noise_std = data(n_samples, np.random.default_rng(seed))
    sims, mods = simulators(x, e), models()
    nmse = NMSE(observed)
    chosen = [mods[n] for n in names]
    evaluate = evaluator(chosen, [sims[n] for n in names], nmse)
    stop = StopRules(min_epsilon_decrease=None, max_populations=80)
    return abcns.run(chosen, evaluate, NSSettings(particles=particles, batch_size=50), stop, seed=seed,
                     noise=nmse.noise(noise_std))


def main() -> None:
    args = arguments(__doc__ or "", 400, 1000)
    print(f"particles {args.particles}, {args.samples} samples at {FS:g} Hz, noise {NOISE:.0%} of the force's std, "
          f"substeps {SUBSTEPS}")
    for seed in args.seeds:
        t0 = time.perf_counter()
        rec = run(["spencer"], args.samples, args.particles, seed)
        cov = coverage(rec, "spencer", TRUTHS)
        sel = run(["bw", "spencer"], args.samples, args.particles, seed)
        p = sel.summary()["model_probabilities"]["spencer"]
        report(f"seed {seed}", "spencer", (rec, cov), (sel, p), SPENCER_TRUE, t0)

if __name__ == "__main__":
    main()
