"""A study's report and figures (docs/studies.md): from each data set's truth
(``study.json``, :mod:`service.run.study`) and its job's store.

- **confusion matrix**: rows the true model, columns the model of highest probability in the
  job's answer (``summary()["model_probabilities"]``), counts and row rates (§5.4);
- **calibration** of the model probabilities: every (data set, model) pair gives (p, whether
  the model made the data); binned in ``CALIBRATION_BINS`` equal bins of p, the reliability
  diagram plots each bin's mean p against its frequency, and the expected calibration error
  is ``sum_b n_b / N |freq_b - mean p_b|``; its ``BOOTSTRAP`` interval resamples the data
  sets (default_rng(seed)); ``ece_if_calibrated`` is the ECE the same probabilities give when
  the true models are drawn from them (calibrated by construction: the part of the ECE that
  is the data sets' number, not miscalibration);
- **coverage**: per parameter of the true model, the share of data sets whose central 50 %
  and 95 % posterior intervals (the answer's particles and weights, :func:`answer_draws`)
  hold the truth; a data set whose true model has no particle in the answer counts as a miss;
- **SBC** (simulation-based calibration, Talts et al. 2018): the truth's rank among the
  answer's draws as a fraction (the weighted share of draws below it, ties counted half),
  uniform on [0, 1] when the posteriors are calibrated; histogram in ``sbc_bins(n)`` bins
  and a chi-square test of uniformity (``p_value``), and the Kolmogorov-Smirnov test of the
  ranks themselves (``ks_p_value``: no bins, so no binning artefact); data sets with no draw of the true
  model are left out (counted in ``without_draws``);
- **cost**: wall time and simulations per job.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from abcns import Result
from abcns.result import weighted_quantiles
from service.run.store import Store, StoreError, result_from_store

CALIBRATION_BINS = 10
BOOTSTRAP = 1000
LEVELS = (0.5, 0.95)
PERCENTS = tuple(round(100 * lv) for lv in LEVELS)  # the keys' names: in50, cover95, ...


def answer_draws(result: Result, model: int) -> tuple[np.ndarray, np.ndarray]:
    """(theta (n, d), weights (n,)) of one model in the run's answer
    (:meth:`abcns.result.Result.answer_draws`)."""
    theta, w, _ = result.answer_draws(model)
    return theta, w


def rank_fraction(x: np.ndarray, w: np.ndarray, truth: float) -> float:
    """The weighted share of draws below ``truth`` (ties counted half)."""
    w = w / np.sum(w)
    return float(np.sum(w[x < truth]) + 0.5 * np.sum(w[x == truth]))


def dataset_row(ds: Mapping[str, Any], store: Path, models: Sequence[str]) -> dict | None:
    """What one finished job says about its data set; None when it has not finished."""
    try:
        opened = Store.open(store)
    except (StoreError, OSError):
        return None
    if opened.attrs.get("status") != "finished" or not opened.n_populations:
        return None
    result = result_from_store(opened)
    s = result.summary()
    probs = [float(s["model_probabilities"].get(m, 0.0)) for m in models]
    i = models.index(ds["model"])
    theta, w = answer_draws(result, i)
    params = {}
    for j, name in enumerate(result.models[i].parameter_names):
        truth = float(ds["parameters"][name])
        if theta.shape[0] == 0 or np.sum(w) <= 0:
            params[name] = {"truth": truth, "rank": None, "in50": False, "in95": False}
            continue
        q = weighted_quantiles(theta[:, j], w, (0.025, 0.25, 0.75, 0.975))
        params[name] = {"truth": truth, "rank": rank_fraction(theta[:, j], w, truth),
                        "in50": bool(q[1] <= truth <= q[2]), "in95": bool(q[0] <= truth <= q[3])}
    return {"index": ds["index"], "model": ds["model"], "probabilities": probs, "chosen": models[int(np.argmax(probs))],
            "parameters": params, "wall_time_s": float(s.get("wall_time_s") or 0.0),
            "simulations": int(s.get("n_simulations") or 0)}


def confusion_matrix(rows: Sequence[dict], models: Sequence[str]) -> dict:
    counts = np.zeros((len(models), len(models)), dtype=int)
    for r in rows:
        counts[models.index(r["model"]), models.index(r["chosen"])] += 1
    totals = counts.sum(axis=1, keepdims=True)
    rates = np.divide(counts, totals, out=np.full(counts.shape, np.nan), where=totals > 0)
    return {"models": list(models), "counts": counts.tolist(),
            "rates": [[None if np.isnan(v) else float(v) for v in row] for row in rates]}


def _pairs(rows: Sequence[dict], models: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """(p (n, M), outcome (n, M)): each data set's model probabilities and true model."""
    p = np.array([r["probabilities"] for r in rows], dtype=float).reshape(len(rows), len(models))
    y = np.array([[m == r["model"] for m in models] for r in rows], dtype=float).reshape(p.shape)
    return p, y


def bin_of(p: np.ndarray, bins: int = CALIBRATION_BINS) -> np.ndarray:
    """Each probability's equal-width bin (p = 1 in the last)."""
    return np.minimum((p * bins).astype(int), bins - 1)


def ece(p: np.ndarray, y: np.ndarray, bins: int = CALIBRATION_BINS) -> float:
    """Expected calibration error of the pairs (p, y), equal-width bins of p."""
    p, y = p.ravel(), y.ravel()
    if not p.size:
        return float("nan")
    b = bin_of(p, bins)
    n = np.bincount(b, minlength=bins)
    gap = np.abs(np.bincount(b, y, bins) - np.bincount(b, p, bins))
    return float(np.sum(gap[n > 0]) / p.size)


def calibration(rows: Sequence[dict], models: Sequence[str], seed: int = 0) -> dict:
    """The reliability diagram's bins, the ECE, its bootstrap interval and the ECE of
    calibrated outcomes drawn from the same probabilities (module docstring)."""
    p, y = _pairs(rows, models)
    flat_p, flat_y = p.ravel(), y.ravel()
    b = bin_of(flat_p)
    bins = [{"low": k / CALIBRATION_BINS, "high": (k + 1) / CALIBRATION_BINS, "n": int(np.sum(b == k)),
             "mean_p": float(np.mean(flat_p[b == k])), "frequency": float(np.mean(flat_y[b == k]))}
            for k in range(CALIBRATION_BINS) if np.any(b == k)]
    out: dict[str, Any] = {"bins": bins, "ece": ece(p, y), "pairs": int(flat_p.size)}
    if len(rows) > 1:
        rng = np.random.default_rng(seed)
        boot = [ece(p[idx], y[idx]) for idx in rng.integers(len(rows), size=(BOOTSTRAP, len(rows)))]
        out["ece_interval"] = [float(v) for v in np.quantile(boot, (0.025, 0.975))]
        cum = np.cumsum(p / np.sum(p, axis=1, keepdims=True), axis=1)
        null = []
        for _ in range(BOOTSTRAP // 5):
            pick = np.minimum((rng.random((len(rows), 1)) > cum).sum(axis=1), len(models) - 1)
            null.append(ece(p, np.eye(len(models))[pick]))
        out["ece_if_calibrated"] = {"mean": float(np.mean(null)), "q95": float(np.quantile(null, 0.95))}
    return out


def sbc_bins(n: int) -> int:
    """Rank-histogram bins for ``n`` ranks: about 5 expected a bin, from 2 to 20."""
    return int(max(2, min(20, n // 5)))


def parameter_checks(rows: Sequence[dict]) -> tuple[dict, dict]:
    """(coverage, sbc) per ``model.parameter`` of the true models, and over all pairs."""
    keys = sorted({(r["model"], name) for r in rows for name in r["parameters"]})
    coverage: dict[str, Any] = {}
    sbc: dict[str, Any] = {}
    for model, name in keys:
        cells = [r["parameters"][name] for r in rows if r["model"] == model]
        coverage[f"{model}.{name}"] = {"n": len(cells), **{f"in{pc}": sum(c[f"in{pc}"] for c in cells) for pc in PERCENTS}}
        ranks = [c["rank"] for c in cells if c["rank"] is not None]
        k = sbc_bins(len(ranks))
        hist = np.histogram(ranks, bins=k, range=(0.0, 1.0))[0]
        p_value = float(stats.chisquare(hist).pvalue) if len(ranks) >= 2 else None
        ks = float(stats.kstest(ranks, "uniform").pvalue) if len(ranks) >= 2 else None
        sbc[f"{model}.{name}"] = {"ranks": ranks, "histogram": hist.tolist(), "bins": k, "p_value": p_value,
                                  "ks_p_value": ks, "without_draws": len(cells) - len(ranks)}
    for c in coverage.values():
        c.update({f"cover{pc}": c[f"in{pc}"] / c["n"] for pc in PERCENTS})
    pairs = sum(c["n"] for c in coverage.values())
    coverage["all"] = {"n": pairs, **{f"cover{pc}": sum(c[f"in{pc}"] for c in coverage.values()) / pairs if pairs else None
                                      for pc in PERCENTS}}
    return coverage, sbc


def study_report(study: Mapping[str, Any], stores: Sequence[Path], seed: int = 0) -> dict:
    """The report of a study (``study.json``'s content) whose data sets' stores are ``stores``
    (in data-set order), over the jobs finished so far."""
    models = list(study["models"])
    rows = [r for ds, path in zip(study["datasets"], stores, strict=True)
            if (r := dataset_row(ds, Path(path), models)) is not None]
    coverage, sbc = parameter_checks(rows)
    walls = [r["wall_time_s"] for r in rows]
    sims = [r["simulations"] for r in rows]
    request = study["request"]
    return {
        "datasets": len(study["datasets"]), "finished": len(rows), "models": models, "request": request,
        "noise": "gaussian",
        "confusion_matrix": confusion_matrix(rows, models),
        "calibration": calibration(rows, models, seed) if rows else {"bins": [], "ece": None, "pairs": 0},
        "coverage": coverage, "sbc": sbc,
        "cost": {"jobs": len(rows), "wall_s_mean": float(np.mean(walls)) if rows else None,
                 "wall_s_total": float(np.sum(walls)), "simulations_mean": float(np.mean(sims)) if rows else None,
                 "simulations_median": float(np.median(sims)) if rows else None},
        "rows": rows,
    }


def folder_report(folder: Path) -> dict:
    """The report of a study's folder as ``abcns study`` lays it out (:mod:`service.run.study`)."""
    from service.run.study import read_study, store_paths

    held = read_study(folder)
    return study_report(held, store_paths(folder, held))


def report_lines(report: Mapping[str, Any]) -> list[str]:
    """The report in words (``abcns summary`` of a study)."""
    conf, cal, cov = report["confusion_matrix"], report["calibration"], report["coverage"]
    lines = [f"study: {report['finished']} of {report['datasets']} data sets finished", "confusion matrix (rows: true "
             "model; columns: the model of highest probability): counts (row rate)"]
    width = max(len(m) for m in conf["models"]) + 2
    lines.append(" " * width + "".join(f"{m:>16s}" for m in conf["models"]))
    for m, counts, rates in zip(conf["models"], conf["counts"], conf["rates"], strict=True):
        lines.append(f"{m:<{width}s}" + "".join(f"{c:>8d} ({'-' if r is None else format(r, '.2f')})".rjust(16)
                                                 for c, r in zip(counts, rates, strict=True)))
    if cal.get("ece") is not None:
        ci = cal.get("ece_interval")
        null = cal.get("ece_if_calibrated")
        lines.append(f"calibration: ECE {cal['ece']:.3f}" + (f" (95 % bootstrap [{ci[0]:.3f}, {ci[1]:.3f}])" if ci else "")
                     + (f"; calibrated probabilities would give {null['mean']:.3f} (95 % below {null['q95']:.3f})"
                        if null else "") + f" over {cal['pairs']} (data set, model) pairs")
    for key, c in cov.items():
        if c["n"]:
            line = f"coverage {key}: 50 % intervals {c['cover50']:.2f}, 95 % intervals {c['cover95']:.2f} of {c['n']}"
            s = report["sbc"].get(key)
            if s and s["p_value"] is not None:
                line += f"; SBC ranks {s['histogram']} (uniform: chi-square p = {s['p_value']:.3g}, KS p = {s['ks_p_value']:.3g})"
            lines.append(line)
    cost = report["cost"]
    if cost["jobs"]:
        lines.append(f"cost per job: {cost['wall_s_mean']:.1f} s, {cost['simulations_mean']:,.0f} simulations "
                     f"(median {cost['simulations_median']:,.0f}); {cost['wall_s_total']:.0f} s of jobs in all")
    return lines


# ---------------------------------------------------------------------------- figures


def confusion_figure(report: Mapping[str, Any]):
    """The confusion matrix: each cell's row rate as its colour, its count and rate as text."""
    from matplotlib.figure import Figure

    conf = report["confusion_matrix"]
    models = conf["models"]
    rates = np.array([[np.nan if v is None else v for v in row] for row in conf["rates"]], dtype=float)
    fig = Figure(figsize=(1.6 * len(models) + 2, 1.4 * len(models) + 1.5))
    ax = fig.subplots()
    ax.imshow(np.nan_to_num(rates), vmin=0, vmax=1, cmap="Blues")
    for i, row in enumerate(conf["counts"]):
        for j, c in enumerate(row):
            rate = "-" if np.isnan(rates[i, j]) else f"{rates[i, j]:.2f}"
            ax.text(j, i, f"{c}\n{rate}", ha="center", va="center",
                    color="white" if np.nan_to_num(rates[i, j]) > 0.5 else "black")
    ax.set_xticks(range(len(models)), models)
    ax.set_yticks(range(len(models)), models)
    ax.set_xlabel("chosen model (highest probability)")
    ax.set_ylabel("true model")
    ax.set_title(f"confusion matrix: {report['finished']} data sets (count, row rate)")
    fig.tight_layout()
    return fig


def reliability_figure(report: Mapping[str, Any]):
    """Reliability diagram: each bin's mean model probability against how often that model
    made the data, the diagonal, and the ECE with its bootstrap interval."""
    from matplotlib.figure import Figure

    cal = report["calibration"]
    fig = Figure(figsize=(5, 5))
    ax = fig.subplots()
    ax.plot([0, 1], [0, 1], color="grey", linestyle="--", label="calibrated")
    x = [b["mean_p"] for b in cal["bins"]]
    y = [b["frequency"] for b in cal["bins"]]
    ax.plot(x, y, marker="o", color="tab:blue", label="bins of p")
    for b in cal["bins"]:
        ax.annotate(str(b["n"]), (b["mean_p"], b["frequency"]), textcoords="offset points", xytext=(4, -10), fontsize=7)
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_xlabel("model probability (bin mean)")
    ax.set_ylabel("frequency the model made the data")
    ci = cal.get("ece_interval")
    title = "reliability" if cal.get("ece") is None else f"ECE {cal['ece']:.3f}"
    ax.set_title(title + (f" (95 % [{ci[0]:.3f}, {ci[1]:.3f}])" if ci else ""))
    ax.legend(loc="upper left")
    fig.tight_layout()
    return fig


def coverage_figure(report: Mapping[str, Any]):
    """Per parameter of the true model, the coverage of its 50 % and 95 % intervals (bars),
    the nominal levels (lines)."""
    from matplotlib.figure import Figure

    keys = [k for k in report["coverage"] if k != "all"]
    fig = Figure(figsize=(max(5, 0.9 * len(keys) + 2), 4))
    ax = fig.subplots()
    x = np.arange(len(keys))
    for off, lv, colour in ((-0.2, 50, "tab:orange"), (0.2, 95, "tab:blue")):
        ax.bar(x + off, [report["coverage"][k][f"cover{lv}"] for k in keys], width=0.4, color=colour,
               label=f"{lv} % intervals")
        ax.axhline(lv / 100, color=colour, linestyle="--")
    ax.set_xticks(x, keys, rotation=30, ha="right")
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("share holding the truth")
    ax.set_title("coverage of the posterior intervals")
    ax.legend(loc="lower right")
    fig.tight_layout()
    return fig


def sbc_figure(report: Mapping[str, Any]):
    """One rank histogram per parameter of the true models, the uniform count as a line,
    the chi-square p-value in each title."""
    from matplotlib.figure import Figure

    items = [(k, s) for k, s in report["sbc"].items() if s["ranks"]]
    cols = min(4, max(1, len(items)))
    rows = max(1, -(-len(items) // cols))
    fig = Figure(figsize=(3.2 * cols, 2.6 * rows))
    axes = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    for ax, (key, s) in zip(axes, items, strict=False):
        edges = np.linspace(0, 1, s["bins"] + 1)
        ax.bar(edges[:-1], s["histogram"], width=np.diff(edges), align="edge", color="tab:blue", edgecolor="white")
        ax.axhline(len(s["ranks"]) / s["bins"], color="grey", linestyle="--")
        ax.set_title(f"{key}: p = {s['p_value']:.2g}" if s["p_value"] is not None else key, fontsize=9)
        ax.set_xlabel("rank of the truth (fraction of draws)")
    for ax in axes[len(items):]:
        ax.set_visible(False)
    fig.tight_layout()
    return fig


def plot_study(report: Mapping[str, Any], out: Path) -> list[Path]:
    """The study's figures as PNG files in ``out``."""
    from service.report.plots import save

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figures = {"confusion": confusion_figure, "reliability": reliability_figure}
    if report["finished"]:
        figures.update(coverage=coverage_figure, sbc=sbc_figure)
    return [save(make(report), out / f"study-{name}.png") for name, make in figures.items()]
