"""Bouc-Wen vs Spencer et al.'s MR-damper models on S. Dyke's prototype MR damper
(NEES-2012-1158), from the user's own copy of the data (not in this repository: see README.md).

    python -m examples.mr_damper.run --data ranran_50_converted.csv [--seed 1] [--particles N]
                                     [--out out/mr_damper] [--model bw ...]
                                     [--predict ransim_u_converted.csv]

``--data`` is the record's CSV (header ``"t","A","D","Y","fs","V","F",``: displacement D in
cm, commanded voltage Y in V, force F in N, sampled at 3004.8 Hz). The script keeps its first
``ACTIVE_S`` seconds (the damper stands still afterwards), clips the voltage at 0 and takes the
force's mean over the fit window off it (models.yaml says why), fills ``models.yaml``'s
``data`` and runs ABC-NS (the evidence variant) in this process on the fit window. Then each
model's posterior mean is simulated over the whole record (``service.report.analysis``): the
NMSE on the fit window and on the held-out test window go to ``OUT/mr-damper-seed<N>.json``
with the summary (model probabilities, posteriors), and ``mr-damper-seed<N>.png`` shows the
measured and predicted forces on an excerpt of each window. ``--predict`` also simulates the
posterior means over another record of the damper (the source's second test, whose force
saturates at 4545 N in places: those samples are left out) and reports their NMSE there.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import yaml

import abcns
from examples.cyclic_tests.run import nmse
from service.report.analysis import job_data
from service.spec import DECIMATION_REACH, build, parse

HERE = Path(__file__).resolve().parent
FS = 3004.8
#: the record's first seconds, while the actuator moves the damper
ACTIVE_S = 21.0
#: the excerpts the figure shows (s): one in the fit window, one in the test window
EXCERPTS = ((1.0, 1.5), (12.0, 12.5))


def read_record(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(displacement D in cm, voltage Y in V, force F in N) of the record's active part."""
    if not path.is_file():
        raise SystemExit(f"{path} is not a file (README.md says where to get the data)")
    table = np.genfromtxt(path, delimiter=",", names=True)
    missing = {"D", "Y", "F"} - set(table.dtype.names or ())
    if missing:
        raise SystemExit(f"{path} has no column(s) {sorted(missing)}: is it ranran_50_converted.csv?")
    n = int(ACTIVE_S * FS)
    return table["D"][:n], table["Y"][:n], table["F"][:n]


def spec_for(x: np.ndarray, volts: np.ndarray, force: np.ndarray, seed: int, particles: int | None,
             only: list[str] | None = None) -> dict:
    """models.yaml over the records as the job uses them (voltage clipped at 0, the force less
    its mean over the fit window); ``only``: keep these models."""
    raw = yaml.safe_load((HERE / "models.yaml").read_text())
    if only:
        raw["models"] = [m for m in raw["models"] if m["name"] in only]
    q, (a, b) = raw["data"]["decimate"], raw["data"]["fit"]
    offset = float(np.mean(force[a * q : b * q]))
    raw["data"].update(input=x.tolist(), voltage=np.clip(volts, 0.0, None).tolist(), observed=(force - offset).tolist())
    if not any(m["simulator"] == "spencer_mr_voltage" for m in raw["models"]):
        raw["data"].pop("voltage")  # Bouc-Wen alone reads none (a voltage no model reads is refused)
    raw["seed"] = seed
    if particles is not None:
        raw["sampler"]["particles"] = particles
    return raw


def predictions(raw: dict, summary: dict) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(the observed force, decimated, and {model: its force at the posterior mean}) over the
    whole record."""
    data = job_data(raw, None)
    out = {}
    for name, post in summary["posterior"].items():
        theta = np.array([[v["mean"] for v in post.values()]])
        values, _status = data.simulate(name)(theta)
        out[name] = values[0]
    return data.observed, out


#: the force sensor's saturation in the source's second record (ransim_u_converted.csv, README.md)
CLIPPED_N = 4545.0


def predict_other(path: Path, summary: dict, seed: int) -> dict[str, float]:
    """{model: NMSE (%)} of each model's posterior mean on another record of the damper (the
    whole of it, simulated from rest), leaving out the samples that a saturated force
    sample (|F| >= ``CLIPPED_N``) reaches through the decimation filter."""
    x, volts, force = read_record(path)
    raw = spec_for(x, volts, force, seed, None, list(summary["posterior"]))
    raw["data"].update(fit=None, test=None)
    q = raw["data"]["decimate"]
    observed, predicted = predictions(raw, summary)
    keep = np.ones(observed.size, dtype=bool)
    for i in np.flatnonzero(np.abs(force) >= CLIPPED_N) // q:
        keep[max(i - DECIMATION_REACH, 0) : i + DECIMATION_REACH + 1] = False
    return {m: nmse(y[keep], observed[keep]) for m, y in predicted.items()}


def figure(observed: np.ndarray, predicted: dict[str, np.ndarray], dt: float, title: str, path: Path) -> None:
    """Measured and predicted (posterior mean) force on the two excerpts (matplotlib's object API)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 6))
    t = np.arange(observed.size) * dt
    for k, ((t0, t1), where) in enumerate(zip(EXCERPTS, ("fit window", "test window (predicted)"), strict=True)):
        ax = fig.add_subplot(2, 1, k + 1)
        sel = (t >= t0) & (t < t1)
        ax.plot(t[sel], observed[sel], "k-", lw=1.2, label="measured")
        for name, y in predicted.items():
            ax.plot(t[sel], y[sel], lw=0.9, label=name)
        ax.set(ylabel="force - preload (N)", title=f"{title}: {where}")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def run(path: Path, seed: int, particles: int | None, out: Path, only: list[str] | None = None,
        other: Path | None = None) -> dict:
    raw = spec_for(*read_record(path), seed, particles, only)
    job = build(parse(raw))
    t0 = time.perf_counter()
    result = abcns.run(job.models, job.evaluate, job.settings, job.stop, job.seed, noise=job.noise)
    summary = result.summary()
    summary["wall_s"] = time.perf_counter() - t0
    observed, predicted = predictions(raw, summary)
    (a, b), (c, d) = raw["data"]["fit"], raw["data"]["test"]
    summary["nmse_posterior_mean"] = {m: {"fit": nmse(y[a:b], observed[a:b]), "test": nmse(y[c:d], observed[c:d])}
                                      for m, y in predicted.items()}
    if other is not None:
        summary["nmse_other_record"] = {"record": other.name, **predict_other(other, summary, seed)}
    out.mkdir(parents=True, exist_ok=True)
    tag = "" if not only else "-" + "-".join(only)
    figure(observed, predicted, job.spec.data.sample_interval, f"MR damper, seed {seed}",
           out / f"mr-damper{tag}-seed{seed}.png")
    (out / f"mr-damper{tag}-seed{seed}.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="your copy of ranran_50_converted.csv (README.md)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--particles", type=int, default=None)
    parser.add_argument("--out", type=Path, default=Path("out/mr_damper"))
    parser.add_argument("--model", action="append", choices=("bw", "bw_v", "spencer"), help="only this model (repeatable)")
    parser.add_argument("--predict", type=Path, default=None,
                        help="another record of the damper (ransim_u_converted.csv) to predict with the posterior means")
    args = parser.parse_args(argv)
    s = run(args.data, args.seed, args.particles, args.out, args.model, args.predict)
    print(f"{s['stop_reason']} after {s['n_populations']} populations, {s['n_simulations']:,} simulations, "
          f"{s['wall_s']:.0f} s; p = {s['model_probabilities']}")
    for model, post in s["posterior"].items():
        err = s["nmse_posterior_mean"][model]
        other = f", {s['nmse_other_record'][model]:.3f} % ({args.predict.name})" if args.predict else ""
        print(f"  {model}: NMSE at the posterior mean {err['fit']:.3f} % (fit), {err['test']:.3f} % (test){other}")
        print("    " + ", ".join(f"{k} [{v['q2_5']:.4g}, {v['q97_5']:.4g}]" for k, v in post.items()))


if __name__ == "__main__":
    main()
