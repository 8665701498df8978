"""Bouc-Wen vs Bouc-Wen-Baber-Noori on the cyclic tests of Ortiz, Alvarez & Bedoya-Ruiz (2015),
from the user's own copy of the data (not in this repository: see README.md).

    python -m examples.cyclic_tests.run --data DIR [--specimen daniel gill ...] [--seed 1]
                                        [--particles N] [--out out/cyclic_tests] [--model bw]

``DIR`` holds, per specimen, either ``<name>.csv`` (columns step, displacement, load_kn) or
the source repository's ``displ_<name>.txt`` and ``load_kN_<name>.txt`` (one number a line).
Both records are scaled to a peak of 1 (the scales are printed and stored), the models of
``models.yaml`` are run in this process (ABC-NS, the evidence variant), and per specimen
``OUT/<name>-seed<N>.json`` gets the summary (model probabilities, posteriors), the scales and
the NMSE of each model's posterior mean, and ``<name>-seed<N>.png`` the measured and predicted loops.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import yaml

import abcns
from service.spec import build, parse
from worker.registry import get

HERE = Path(__file__).resolve().parent
SPECIMENS = ("daniel", "kunnath", "gill", "chiu", "sharma")
MODELS = ("bw", "bwbn", "bwbn_log")  # models.yaml's: BW against BWBN under both priors (README.md, "Two priors")


def read_specimen(folder: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(displacement, load) of one specimen from the user's folder."""
    csv = folder / f"{name}.csv"
    if csv.is_file():
        table = np.loadtxt(csv, delimiter=",", skiprows=1)
        return table[:, 1], table[:, 2]
    displ, load = folder / f"displ_{name}.txt", folder / f"load_kN_{name}.txt"
    if displ.is_file() and load.is_file():
        return np.loadtxt(displ), np.loadtxt(load)
    raise SystemExit(f"{folder} has neither {csv.name} nor {displ.name} and {load.name} (README.md says where to get them)")


def spec_for(x: np.ndarray, force: np.ndarray, seed: int, particles: int | None, only: list[str] | None = None) -> dict:
    """models.yaml over the (scaled) records; ``only``: keep these models (e.g. one alone, to
    see its own best fit, or bw and bwbn: the uniform box alone)."""
    raw = yaml.safe_load((HERE / "models.yaml").read_text())
    if only:
        raw["models"] = [m for m in raw["models"] if m["name"] in only]
    kept = {m["name"] for m in raw["models"]}
    for m in raw["models"]:  # a copy run without the model it copies is a model of its own
        if m.get("same_model_as") not in kept:
            m.pop("same_model_as", None)
    raw["data"].update(input=x.tolist(), observed=force.tolist())
    raw["seed"] = seed
    if particles is not None:
        raw["sampler"]["particles"] = particles
    return raw


def posterior_mean_force(job, summary: dict, name: str) -> np.ndarray:
    """The force simulated at the posterior mean (the summary's) of model ``name``."""
    i = [m.name for m in job.models].index(name)
    model, sim = job.models[i], job.simulators[i]
    post = summary["posterior"][name]
    values = {**get(job.spec.models[i].simulator).defaults, **model.fixed, **{k: v["mean"] for k, v in post.items()}}
    return sim.simulate(np.array([[values[p] for p in sim.parameter_names]])).values[0]


def nmse(simulated: np.ndarray, observed: np.ndarray) -> float:
    """Paper Eq. 7, in %."""
    return float(100 * np.mean((simulated - observed) ** 2) / np.var(observed))


def loop_figure(x: np.ndarray, observed: np.ndarray, predicted: dict[str, np.ndarray], title: str, path: Path) -> None:
    """Measured and predicted (posterior mean) loops, scaled units (matplotlib's object API)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 5))
    ax = fig.add_subplot()
    ax.plot(x, observed, "k-", lw=0.8, label="measured")
    for name, y in predicted.items():
        ax.plot(x, y, lw=0.8, label=f"{name}, posterior mean (NMSE {nmse(y, observed):.2f} %)")
    ax.set(xlabel="displacement / max|displacement|", ylabel="load / max|load|", title=title)
    ax.legend(loc="upper left")
    fig.savefig(path, dpi=90)


def progress(name: str):
    """A line per population on stderr, so that a long run can be followed (never part of the answer)."""
    def report(pop) -> None:
        print(f"{name}: population {pop.t}, epsilon {pop.epsilon:.4g}, {pop.n_simulations:,} simulations, "
              f"p = {np.round(pop.model_probabilities, 4).tolist()}, {pop.elapsed_s:.0f} s", file=sys.stderr, flush=True)
    return report


def run_specimen(folder: Path, name: str, seed: int, particles: int | None, out: Path,
                 only: list[str] | None = None) -> dict:
    x, load = read_specimen(folder, name)
    x_scale, f_scale = float(np.max(np.abs(x))), float(np.max(np.abs(load)))
    job = build(parse(spec_for(x / x_scale, load / f_scale, seed, particles, only)))
    t0 = time.perf_counter()
    result = abcns.run(job.models, job.evaluate, job.settings, job.stop, job.seed, noise=job.noise,
                       on_population=progress(name))
    summary = result.summary()
    summary["scales"] = {"displacement": x_scale, "load": f_scale}
    summary["wall_s"] = time.perf_counter() - t0
    predicted = {m: posterior_mean_force(job, summary, m) for m in summary["posterior"]}
    summary["nmse_posterior_mean"] = {m: nmse(y, job.observed) for m, y in predicted.items()}
    out.mkdir(parents=True, exist_ok=True)
    tag = "" if not only else "-" + "-".join(only)
    loop_figure(job.force, job.observed, predicted, f"{name}, seed {seed}", out / f"{name}{tag}-seed{seed}.png")
    (out / f"{name}{tag}-seed{seed}.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="your copy of the data (README.md)")
    parser.add_argument("--specimen", nargs="+", default=["daniel", "gill"], choices=SPECIMENS)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--particles", type=int, default=None)
    parser.add_argument("--out", type=Path, default=Path("out/cyclic_tests"))
    parser.add_argument("--model", action="append", choices=MODELS,
                        help="run only this model (repeatable; default: all of models.yaml's)")
    args = parser.parse_args(argv)
    for name in args.specimen:
        s = run_specimen(args.data, name, args.seed, args.particles, args.out, args.model)
        print(f"{name}: {s['stop_reason']} after {s['n_populations']} populations, {s['n_simulations']:,} simulations, "
              f"{s['wall_s']:.0f} s; p = {s['model_probabilities']}; NMSE at the posterior mean (%): "
              f"{ {k: round(v, 3) for k, v in s['nmse_posterior_mean'].items()} }")
        for model, post in s["posterior"].items():
            print(f"  {model}: " + ", ".join(f"{k} [{v['q2_5']:.4g}, {v['q97_5']:.4g}]" for k, v in post.items()))


if __name__ == "__main__":
    main()
