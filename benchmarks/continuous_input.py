"""A continuous input, sampled: which ``data.input_interpolation``, and does the model-error
check see a wrong one? (issues P.4, AA)

    python -m benchmarks.continuous_input [--seeds 1-5] [--systems duffing,bouc_wen]
        [--interpolations hold,linear,bandlimited,exact] [--processes 2] [--particles 300]
    python -m benchmarks.continuous_input --rule [--seeds 1-5]   # own error vs sampling rate
    python -m benchmarks.continuous_input --speed                # simulations per second

The data are made as a user's own measurement would be, not by our simulators: the system
is driven by a *continuous* random-phase multisine (``tones`` tones up to ``top`` Hz, i.e.
0.12-0.15 of the sampling rate), integrated by scipy's DOP853 (rtol 1e-10) through the
continuous force, from rest, sampled at ``fs``; Gaussian noise of ``NOISE`` (1 %) of the
clean response's RMS is added. The force given to the spec is the multisine at the sample
times. Seed s draws the phases and the noise.

- ``duffing``: ``x'' + c x' + k x + k3 x^3 = u(t)`` (m = 1 fixed; c, k, k3 inferred), 30
  tones 0.2-15 Hz at 100 Hz (6.7 samples per period of the top tone), resonance 3.2 Hz,
  1000 samples;
- ``bouc_wen``: the Bouc-Wen benchmark's published parameters (m = 2, c = 10, k = 5e4,
  A = 5e4, alpha = 800, beta = -1100, n = 1; k and n fixed, the other five inferred), 50 N
  RMS, 40 tones 1-60 Hz at 500 Hz (8.3 samples per period of the top tone, the issue's
  case), resonance 35.6 Hz,
  1500 samples.

Each data set is fitted by ABC-NS (the default evidence variant, ``--particles``, the
default noise-floor stop, at most ``MAX_POPULATIONS``) with the true model under each input
interpolation; ``exact`` fits data made by the simulator itself (the held force, the same
substeps) plus i.i.d. Gaussian noise with ``hold``: there is no model error, so the model-error
warning's rate there is its false-alarm rate. The table gives, per run, the simulator's own
error at the truth (its NMSE against the clean response over the noise floor's, %/%), the
Ljung-Box p-value of the best fit's residuals, how far the simulator's own error would move
the best fit (``shift sd``: the largest of service.run.model_error.parameter_shift's, in the
fit's standard deviations), whether the model-error warning fired, and how many 95 %
intervals hold the truth.
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from benchmarks.model_selection import seeds_of

NOISE = 0.01
MAX_POPULATIONS = 80


@dataclass(frozen=True)
class System:
    simulator: str
    fs: float
    n_samples: int
    tones: int
    band_hz: tuple[float, float]
    force_rms: float
    truth: dict[str, float]  # every parameter of the simulator's equation
    priors: dict[str, list[float]]
    substeps: int


SYSTEMS = {
    "duffing": System("duffing", 100.0, 1000, 30, (0.2, 15.0), 10.0, {"m": 1.0, "c": 1.0, "k": 400.0, "k3": 1000.0, "k5": 0.0},
                      {"c": [0.1, 5.0], "k": [200.0, 800.0], "k3": [0.0, 5000.0]}, 4),
    "bouc_wen": System("bouc_wen", 500.0, 1500, 40, (1.0, 60.0), 50.0,
                       {"m": 2.0, "c": 10.0, "k": 5e4, "alpha": 800.0, "beta": -1100.0, "A": 5e4, "n": 1.0},
                       {"m": [1.0, 3.0], "c": [2.0, 30.0], "A": [3e4, 7e4], "alpha": [0.0, 3000.0],
                        "beta": [-3000.0, 0.0]}, 4),
}


def multisine(system: System, rng: np.random.Generator):
    """The continuous force u(t) of a seed (random phases)."""
    freqs = np.linspace(*system.band_hz, system.tones)
    phases = rng.uniform(0.0, 2.0 * np.pi, system.tones)
    amp = system.force_rms * np.sqrt(2.0 / system.tones)

    def force(t):
        return amp * np.sum(np.cos(2.0 * np.pi * freqs[:, None] * np.atleast_1d(t)[None, :] + phases[:, None]), axis=0)

    return force


def rhs(system: System, force):
    """The continuous-time equation for DOP853."""
    p = system.truth
    if system.simulator == "duffing":
        return lambda t, s: [s[1], (force(t)[0] - p["c"] * s[1] - p["k"] * s[0] - p["k3"] * s[0] ** 3) / p["m"]]
    n = int(p["n"])

    def bouc_wen(t, s):
        y, v, z = s
        zdot = p["A"] * v - p["alpha"] * abs(v) * abs(z) ** (n - 1) * z - p["beta"] * v * abs(z) ** n
        return [v, (force(t)[0] - p["c"] * v - p["k"] * y - z) / p["m"], zdot]

    return bouc_wen


def simulator(system: System, force: np.ndarray, interpolation: str):
    from worker.simulators import BoucWen, Duffing

    cls = Duffing if system.simulator == "duffing" else BoucWen
    return cls(force, 1.0 / system.fs, substeps=system.substeps, input_interpolation=interpolation)


def truth_vector(system: System, sim) -> np.ndarray:
    return np.array([[system.truth.get(name, sim.defaults.get(name, 0.0)) for name in sim.parameter_names]])


def make_data(name: str, seed: int, exact: bool = False, system: System | None = None) -> dict:
    """(force, observed, clean, noise floor in %) of seed ``seed``: through DOP853 and the
    continuous force, or (``exact``) by the simulator itself with the held force."""
    from scipy.integrate import solve_ivp

    system = system or SYSTEMS[name]
    rng = np.random.default_rng(seed)
    u = multisine(system, rng)
    t = np.arange(system.n_samples) / system.fs
    force = u(t)
    if exact:
        sim = simulator(system, force, "hold")
        clean = sim.simulate(truth_vector(system, sim)).values[0]
    else:
        sol = solve_ivp(rhs(system, u), (0.0, t[-1]), np.zeros(2 if name == "duffing" else 3), method="DOP853",
                        t_eval=t, rtol=1e-10, atol=1e-12 * system.force_rms)
        clean = sol.y[0]
    observed = clean + NOISE * np.sqrt(np.mean(clean**2)) * rng.standard_normal(clean.size)
    floor = 100.0 * np.sum((clean - observed) ** 2) / (clean.size * np.var(observed, ddof=1))  # Eq. 7
    return {"force": force, "observed": observed, "clean": clean, "floor": float(floor)}


def model_error(name: str, data: dict, interpolation: str, system: System | None = None) -> float:
    """The simulator's own error at the truth: its NMSE against the clean response, over the
    noise's (both Eq. 7 with the observed record's variance)."""
    system = system or SYSTEMS[name]
    sim = simulator(system, data["force"], interpolation)
    y = sim.simulate(truth_vector(system, sim)).values[0]
    own = 100.0 * np.mean((y - data["clean"]) ** 2) / np.var(data["observed"], ddof=1)
    return float(own / data["floor"])


def spec(name: str, data: dict, interpolation: str, seed: int, particles: int) -> dict:
    system = SYSTEMS[name]
    fixed = {k: v for k, v in system.truth.items() if k not in system.priors}
    return {
        "name": f"continuous-input-{name}-{interpolation}-{seed}",
        "data": {"dt": 1.0 / system.fs, "input": data["force"].tolist(), "observed": data["observed"].tolist(),
                 "input_interpolation": interpolation},
        "models": [{"name": name, "simulator": system.simulator, "fixed": fixed, "priors": system.priors,
                    "integrator": {"substeps": system.substeps}}],
        "sampler": {"particles": particles},
        "stop": {"max_populations": MAX_POPULATIONS},
        "seed": seed,
    }


def one(name: str, seed: int, interpolation: str, particles: int) -> dict:
    import tempfile
    from pathlib import Path

    from service.run.runner import run_job, summary
    from service.run.store import Store
    from service.spec import parse

    exact = interpolation == "exact"
    used = "hold" if exact else interpolation
    data = make_data(name, seed, exact)
    start = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        run_job(parse(spec(name, data, used, seed, particles)), None, Path(tmp) / "store", None)
        s = summary(Store.open(Path(tmp) / "store"))
    post = s["posterior"].get(name, {})
    truth = SYSTEMS[name].truth
    intervals = {p: (post[p]["q2_5"], post[p]["q97_5"]) for p in SYSTEMS[name].priors}
    res = s.get("residuals") or {}
    return {"system": name, "seed": seed, "interpolation": interpolation, "floor": data["floor"],
            "own_error": model_error(name, data, used), "stop": s["stop_reason"], "populations": s["n_populations"],
            "p_value": res.get("p_value", np.nan), "shift_sd": max([o["sd"] for o in res.get("own_error", [])] or [np.nan]),
            "fired": any(w.startswith("model error") for w in s.get("warnings", [])),
            "intervals": intervals, "holds": {p: bool(lo <= truth[p] <= hi) for p, (lo, hi) in intervals.items()},
            "wall_s": time.monotonic() - start}


def table(rows: list[dict]) -> str:
    head = ("| system | input | seed | own error / noise | stop | pops | Ljung-Box p | shift sd | warning | intervals holding "
            "the truth | missed |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        missed = ", ".join(f"{p} [{lo:.5g}, {hi:.5g}]" for p, (lo, hi) in r["intervals"].items() if not r["holds"][p])
        lines.append(f"| {r['system']} | {r['interpolation']} | {r['seed']} | {r['own_error']:.3g} | {r['stop']} | "
                     f"{r['populations']} | {r['p_value']:.2g} | {r['shift_sd']:.2g} | {'FIRED' if r['fired'] else '-'} | "
                     f"{sum(r['holds'].values())} of {len(r['holds'])} | {missed or '-'} |")
    return "\n".join(lines)


def totals(rows: list[dict]) -> list[str]:
    out = []
    for system in dict.fromkeys(r["system"] for r in rows):
        for interpolation in dict.fromkeys(r["interpolation"] for r in rows):
            mine = [r for r in rows if r["system"] == system and r["interpolation"] == interpolation]
            if mine:
                held = sum(sum(r["holds"].values()) for r in mine)
                pairs = sum(len(r["holds"]) for r in mine)
                out.append(f"{system} {interpolation}: intervals hold the truth in {held} of {pairs} (seed, parameter) "
                           f"pairs ({100 * held / pairs:.0f} %); the warning fired in {sum(r['fired'] for r in mine)} of "
                           f"{len(mine)} runs; {np.mean([r['wall_s'] for r in mine]):.0f} s per run")
    return out


#: samples per period of the highest tone that ``--rule`` samples each system at
RULE_SAMPLES_PER_PERIOD = (4, 5, 6.7, 8.3, 10, 15, 20, 30)


def rule(names: list[str], seeds: list[int]) -> str:
    """The simulator's own error at the truth over the noise's (mean over ``seeds``) against
    the samples per period of the highest input tone, each system's record kept as long in
    seconds (the substeps scaled to keep the RK4 step)."""
    from dataclasses import replace

    head = "| system | samples per period of the top tone | fs Hz | hold | linear | bandlimited |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name in names:
        base = SYSTEMS[name]
        for spp in RULE_SAMPLES_PER_PERIOD:
            fs = spp * base.band_hz[1]
            system = replace(base, fs=fs, n_samples=round(base.n_samples * fs / base.fs),
                             substeps=max(1, round(base.substeps * base.fs / fs)))
            datas = [make_data(name, s, system=system) for s in seeds]
            cells = [f"{np.mean([model_error(name, d, i, system) for d in datas]):.3g}"
                     for i in ("hold", "linear", "bandlimited")]
            lines.append(f"| {name} | {spp:g} | {fs:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def speed(names: list[str], repeats: int = 30) -> str:
    """Simulations per second of each input interpolation: the in-kernel NMSE of 1000
    particles near the truth, best of ``repeats`` taken in turn (a busy machine slows each
    alike); the band-limited input is made when the simulator is built, outside the timing."""
    head = "| system | hold sims/s | linear sims/s | bandlimited sims/s |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name in names:
        system, data = SYSTEMS[name], make_data(name, 1)
        sims = [simulator(system, data["force"], i) for i in ("hold", "linear", "bandlimited")]
        truth = truth_vector(system, sims[0])
        params = truth * (1 + 0.01 * np.random.default_rng(0).standard_normal((1000, truth.shape[1])))
        if "n" in sims[0].parameter_names:  # Bouc-Wen's exponent stays an integer
            params[:, sims[0].parameter_names.index("n")] = system.truth["n"]
        for sim in sims:
            sim.distance_nmse(params[:10], data["observed"], 0, data["observed"].size)  # compiled
        times = [[_timed(sim, params, data["observed"]) for sim in sims] for _ in range(repeats)]
        lines.append(f"| {name} | " + " | ".join(f"{params.shape[0] / t:,.0f}" for t in np.min(times, axis=0)) + " |")
    return "\n".join(lines)


def _timed(sim, params: np.ndarray, observed: np.ndarray) -> float:
    start = time.perf_counter()
    sim.distance_nmse(params, observed, 0, observed.size)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="1-5")
    parser.add_argument("--systems", default="duffing,bouc_wen")
    parser.add_argument("--interpolations", default="hold,linear,bandlimited,exact")
    parser.add_argument("--particles", type=int, default=300)
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--rule", action="store_true", help="only the simulator's own error against the sampling rate")
    parser.add_argument("--speed", action="store_true", help="only the simulations per second of each interpolation")
    args = parser.parse_args()
    if args.speed:
        print(speed(args.systems.split(",")))
        return
    if args.rule:
        print(rule(args.systems.split(","), seeds_of(args.seeds)))
        return
    jobs = [(n, s, i, args.particles) for n in args.systems.split(",") for i in args.interpolations.split(",")
            for s in seeds_of(args.seeds)]
    with ProcessPoolExecutor(args.processes) as pool:
        rows = list(pool.map(one, *zip(*jobs)))
    print(table(rows))
    print("\n".join(totals(rows)))


if __name__ == "__main__":
    main()
