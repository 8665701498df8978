"""The paper's figures from a result (matplotlib, object API: no pyplot state, any backend).

Each ``*_figure`` function returns a :class:`matplotlib.figure.Figure`; :func:`plot_result`
writes every figure of a finished store to a directory (``abcns plot``).

- :func:`tolerance_figure`: tolerance and acceptance rate per population (Figs. 2, 12, 21);
- :func:`model_probability_figure`: model probabilities per population (Figs. 11, 19, 23) and
  against the tolerance, with the noise floor and the decision tolerance;
- :func:`marginals_figure`, :func:`pairs_figure`: one model's final population, with the
  truth when known (Figs. 9, 13);
- :func:`predictive_figure`: observed record with the predictive median, 50 % and 99 %
  bands, fit and test windows side by side (Figs. 14, 20, 22);
- :func:`confusion_figure`: the §5.4 confusion matrices as heat maps (Fig. 27).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.axis import Axis
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.ticker import LogFormatter, MaxNLocator, ScalarFormatter

from abcns import Result
from abcns.analysis import Confusion, Predictive
from abcns.noise import METHODS
from service.report.colours import model_colour


def _with_unit(label: str, unit: str) -> str:
    """``label (unit)``, or the label alone when the quantity has no unit."""
    return f"{label} ({unit})" if unit else label


def tolerance_figure(result: Result, unit: str = "") -> Figure:
    """``unit``: the distance's unit ("%" for the NMSE of Eq. 7, "" for a summary distance)."""
    pops = result.populations
    t = [p.t for p in pops]
    fig = Figure(figsize=(9, 3.6), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    ax1.semilogy(t, [p.epsilon for p in pops], "o-", ms=3)
    ax1.set(xlabel="population", ylabel=_with_unit("tolerance $\\varepsilon_t$", unit), title="tolerance per population")
    ax1.grid(True, which="both", alpha=0.3)
    ax2.plot(t, [p.acceptance_rate for p in pops], "o-", ms=3, color="tab:green")
    ax2.set(xlabel="population", ylabel="acceptance rate", ylim=(0, 1.02), title="acceptance per population")
    ax2.grid(True, alpha=0.3)
    fig.suptitle(f"{result.algorithm}: {len(pops)} populations, {result.n_simulations:,} simulations, "
                 f"stop: {result.stop_reason.value}", fontsize=10)
    return fig


def model_probability_figure(result: Result, unit: str = "") -> Figure:
    """Model probabilities per population (the paper's figures, stacked bars) and p_m(eps)
    against the tolerance, with the noise floor and the decision tolerance (docs/design.md,
    "The noise floor and the decision tolerance") as vertical lines; the answer is read at the
    decision population, marked in both panels. ``unit``: the distance's ("%" for the NMSE)."""
    pops = result.populations
    t = np.array([p.t for p in pops])
    eps = np.array([p.epsilon for p in pops])
    probs = np.stack([p.model_probabilities for p in pops])
    answer = result.decision_population()
    k = answer.t - 1
    fig = Figure(figsize=(12, 3.8), layout="constrained")
    ax, ax_eps = fig.subplots(1, 2)
    width = 0.8 if len(t) < 60 else 1.0
    bottom = np.zeros(len(t))
    for i, name in enumerate(result.model_names):
        at = f"answer {probs[k, i]:.2f}" + ("" if answer is result.final else f", final {probs[-1, i]:.2f}")
        ax.bar(t, probs[:, i], width, bottom=bottom, label=f"{name} ({at})", color=model_colour(i), linewidth=0)
        bottom += probs[:, i]
    if answer is not result.final:
        ax.axvline(answer.t, color="k", ls="--", lw=1, label=f"decision: population {answer.t}")
    ax.set(xlabel="population", ylabel="model probability", ylim=(0, 1), xlim=(t[0] - 0.5, t[-1] + 0.5),
           title="model probabilities per population")
    ax.legend(loc="upper left", fontsize=8, framealpha=0.9)

    shown = np.isfinite(eps) & (eps > 0)  # a log axis (a baseline's first tolerance may be infinite)
    for i, name in enumerate(result.model_names):
        ax_eps.plot(eps[shown], probs[shown, i], "o-", ms=3, color=model_colour(i), label=name)
    floor = result.floor
    if floor is not None:
        ax_eps.axvline(floor.floor, color="0.3", ls=":", lw=1.5,
                       label=f"noise floor {floor.floor:.4g}{' ' + unit if unit else ''} ({METHODS[floor.method]})")
        ax_eps.axvline(floor.decision, color="k", ls="--", lw=1.2,
                       label=f"decision tolerance {floor.decision:.4g}{' ' + unit if unit else ''}")
    if shown.any():
        ax_eps.set_xscale("log")
        ax_eps.xaxis.set_major_formatter(LogFormatter())  # 3, 4, 6 rather than 3x10^0 on a short range
        ax_eps.xaxis.set_minor_formatter(LogFormatter(minor_thresholds=(2, 0.5)))
    ax_eps.invert_xaxis()  # the run goes from left to right
    ax_eps.set(xlabel=_with_unit("tolerance $\\varepsilon$", unit), ylabel="model probability", ylim=(-0.02, 1.02),
               title="$p_m(\\varepsilon)$: the answer is read at the decision tolerance")
    ax_eps.grid(True, which="both", alpha=0.3)
    ax_eps.legend(loc="best", fontsize=8, framealpha=0.9)
    return fig


def _truth(names: Sequence[str], truth: Mapping[str, float] | None) -> list[float | None]:
    return [None if truth is None else truth.get(n) for n in names]


def marginals_figure(result: Result, model: int | str, truth: Mapping[str, float] | None = None,
                     bins: int = 30) -> Figure:
    i = result.model_names.index(model) if isinstance(model, str) else model
    m = result.models[i]
    theta, _, w = result.particles(i)
    d = m.n_dim
    ncol = min(d, 4)
    nrow = -(-d // ncol)
    fig = Figure(figsize=(3.2 * ncol, 2.8 * nrow), layout="constrained")
    axes = np.atleast_1d(fig.subplots(nrow, ncol)).ravel()
    weights = w if result.weighted_posterior else None
    for j, (name, tv) in enumerate(zip(m.parameter_names, _truth(m.parameter_names, truth), strict=True)):
        ax = axes[j]
        ax.hist(theta[:, j], bins=bins, weights=weights, color=model_colour(i), alpha=0.8)
        q = np.quantile(theta[:, j], [0.025, 0.975]) if weights is None else None
        if q is not None:
            for v in q:
                ax.axvline(v, color="k", ls=":", lw=1)
        if tv is not None:
            ax.axvline(tv, color="tab:red", lw=2, label=f"truth {tv:g}")
            ax.legend(fontsize=7)
        ax.set(xlabel=name, yticks=[])
        ax.ticklabel_format(axis="x", style="sci", scilimits=(-3, 4))
        ax.xaxis.set_major_locator(MaxNLocator(5))
    for ax in axes[d:]:
        ax.set_visible(False)
    fig.suptitle(f"{m.name}: marginal posteriors, population {result.final.t} ({theta.shape[0]} particles; "
                 "dotted: 95 % interval)", fontsize=10)
    return fig


def _limits(values: np.ndarray, truth: float | None) -> tuple[float, float]:
    """The axis range of one parameter: its samples (and the truth, when given) with a 5 % margin."""
    v = values[np.isfinite(values)]
    if truth is not None and np.isfinite(truth):
        v = np.append(v, truth)
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = float(v.min()), float(v.max())
    pad = 0.05 * (hi - lo) if hi > lo else (0.05 * abs(lo) or 0.5)
    return lo - pad, hi + pad


class _NamedOffsetFormatter(ScalarFormatter):
    """A :class:`ScalarFormatter` whose offset / power of ten goes into the axis label
    ("c (1e-5+1.0000503e3)") instead of the offset text, which would sit on the label."""

    def __init__(self, name: str):
        super().__init__(useOffset=True)
        self.name = name
        self.set_powerlimits((-3, 4))

    def set_locs(self, locs):
        super().set_locs(locs)
        off = super().get_offset()
        if isinstance(self.axis, Axis):  # always: set by Axis.set_major_formatter (_compact_ticks)
            self.axis.set_label_text(f"{self.name} ({off})" if off else self.name)

    def get_offset(self) -> str:
        return ""


def _compact_ticks(axis, name: str) -> None:
    """At most 4 ticks on round steps, labelled by :class:`_NamedOffsetFormatter` (so
    0.050362..0.050398 does not print as long labels that run together)."""
    axis.set_major_locator(MaxNLocator(3, steps=[1, 2, 5, 10]))
    axis.set_major_formatter(_NamedOffsetFormatter(name))
    axis.set_label_text(name)


def pairs_figure(result: Result, model: int | str, truth: Mapping[str, float] | None = None, unit: str = "") -> Figure:
    """Corner plot of one model's final population: the diagonal is the histogram of
    parameter i (its y axis is counts, unlabelled and tied to nothing); panel (i, j), j < i,
    scatters parameter j (x) against parameter i (y), coloured by distance. Every panel of
    column j shares parameter j's x axis, every off-diagonal panel of row i shares parameter
    i's y axis; tick labels and names only on the bottom row and the first column. ``unit``:
    the distance's (as :func:`tolerance_figure`)."""
    i = result.model_names.index(model) if isinstance(model, str) else model
    m = result.models[i]
    theta, dist, _ = result.particles(i)
    d = m.n_dim
    names = m.parameter_names
    tv = _truth(names, truth)
    fig = Figure(figsize=(2.4 * d + 0.8, 2.4 * d), layout="constrained")
    axes = np.array(fig.subplots(d, d, squeeze=False))
    # shared axes share their locator and formatter: never hide labels with set_*ticklabels
    # (that would put one panel's labels on the others), only with tick_params
    for r in range(d):
        for c in range(r + 1):
            if r < d - 1:
                axes[r, c].sharex(axes[d - 1, c])
            if 0 < c < r:
                axes[r, c].sharey(axes[r, 0])
    sc = None
    for r in range(d):
        for c in range(d):
            ax = axes[r, c]
            if c > r:
                ax.set_visible(False)
                continue
            if r == c:
                ax.hist(theta[:, c], bins=25, color=model_colour(i), alpha=0.8)
                ax.set_yticks([])
                ax.tick_params(axis="y", left=False, labelleft=False)
                if tv[c] is not None:
                    ax.axvline(tv[c], color="tab:red", lw=1.5)
            else:
                sc = ax.scatter(theta[:, c], theta[:, r], c=dist, s=4, cmap="viridis_r")
                if tv[c] is not None and tv[r] is not None:
                    ax.plot(tv[c], tv[r], "r+", ms=12, mew=2)
                elif tv[c] is not None:
                    ax.axvline(tv[c], color="tab:red", lw=1)
                elif tv[r] is not None:
                    ax.axhline(tv[r], color="tab:red", lw=1)
                ax.tick_params(axis="y", labelleft=c == 0)
            ax.tick_params(axis="x", labelbottom=r == d - 1, labelsize=8)
            ax.tick_params(axis="y", labelsize=8)
    for c in range(d):
        bottom = axes[d - 1, c]
        _compact_ticks(bottom.xaxis, names[c])
        bottom.set_xlim(*_limits(theta[:, c], tv[c]))
        bottom.tick_params(axis="x", labelrotation=45)
        if c > 0:
            first = axes[c, 0]
            _compact_ticks(first.yaxis, names[c])
            first.set_ylim(*_limits(theta[:, c], tv[c]))
    if sc is not None:
        fig.colorbar(sc, ax=axes[:, -1].tolist(), label=_with_unit("distance", unit), shrink=0.6)
    fig.suptitle(f"{m.name}: pairs, population {result.final.t} (red: truth)", fontsize=10)
    return fig


def predictive_figure(pred: Predictive, observed: np.ndarray, dt: float | None, fit: tuple[int, int],
                      test: tuple[int, int] | None = None, scores: Mapping[str, Mapping[str, float]] | None = None,
                      ylabel: str = "response") -> Figure:
    """Observed data and the predictive median with 50 % and 99 % bands on the fit window
    and, when given, the test window; ``ylabel`` names the response (:func:`response_label`)."""
    windows = [("fit", fit)] + ([("test", test)] if test is not None else [])
    fig = Figure(figsize=(6.5 * len(windows), 3.8), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(windows), squeeze=False)).ravel()
    b = pred.bands
    scale = dt if dt is not None else 1.0
    for ax, (label, (a, z)) in zip(axes, windows, strict=True):
        x = np.arange(a, z) * scale
        ax.fill_between(x, b["lower_99"][a:z], b["upper_99"][a:z], color="tab:blue", alpha=0.25, lw=0, label="99 % band")
        ax.fill_between(x, b["lower_50"][a:z], b["upper_50"][a:z], color="tab:blue", alpha=0.45, lw=0, label="50 % band")
        ax.plot(x, observed[a:z], "k.", ms=2, label="observed")
        ax.plot(x, b["median"][a:z], color="tab:red", lw=1, label="predictive median")
        title = f"{label} window [{a}, {z})"
        if scores is not None and label in scores.get("posterior_mean", {}):
            title += f"  NMSE mean {scores['posterior_mean'][label]:.3g} %, best {scores['best'][label]:.3g} %"
        ax.set(xlabel=f"time (sample interval {dt:g} in the spec's time unit)" if dt is not None else "sample",
               ylabel=ylabel, title=title)
        ax.title.set_fontsize(9)
    axes[0].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{pred.model}: posterior predictive ({pred.trajectories.shape[0]} simulations"
                 + (f", {pred.n_failed} failed" if pred.n_failed else "") + ")", fontsize=10)
    return fig


def confusion_figure(conf: Confusion, log: bool = True) -> Figure:
    n = len(conf.models)
    fig = Figure(figsize=(3.6 * n + 0.6, 3.4), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, n, squeeze=False)).ravel()
    finite = np.concatenate([m[np.isfinite(m)].ravel() for m in conf.matrices.values()] + [np.ones(0)])
    lo, hi = (finite.min(), finite.max()) if finite.size else (1e-3, 1.0)
    norm = LogNorm(max(lo, 1e-6), max(hi, lo * 10, 1e-5)) if log else None
    im = None
    cmap = colormaps["viridis"].with_extremes(bad="0.85")  # grey: the model died in that fit, or its simulation failed
    for ax, name in zip(axes, conf.models, strict=True):
        mat = conf.matrices[name]
        im = ax.imshow(np.where(np.isfinite(mat), mat, np.nan), cmap=cmap, norm=norm)
        for (r, c), v in np.ndenumerate(mat):
            ax.text(c, r, f"{v:.3g}" if np.isfinite(v) else "no fit /\nfailed", ha="center", va="center", fontsize=8,
                    color="w" if np.isfinite(v) else "k")
        k = len(conf.datasets)
        ax.set(xticks=range(k), yticks=range(k), xlabel="tested on", ylabel="fitted on")
        ax.set_xticklabels(conf.datasets, fontsize=7, rotation=30)
        ax.set_yticklabels(conf.datasets, fontsize=7)
        tag = " (best)" if name == conf.best else (" (eliminated)" if name in conf.eliminated else "")
        ax.set_title(f"{name}{tag}\nmean NMSE {conf.mean[name]:.3g} %", fontsize=9)
    if im is not None:
        fig.colorbar(im, ax=axes.tolist(), label="NMSE (%, Eq. 7)", shrink=0.8)
    return fig


def save(fig: Figure, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path


def response_label(data, model: str) -> str:
    """What a model's simulated record is, for an axis: the spec's ``integrator.output``
    (displacement, velocity, acceleration) of an input-driven model, in the unit of the
    observed record (the spec does not name it); "observed value" for a model without input."""
    if data.force is None:
        return "observed value"
    spec = next(m for m in data.spec.models if m.name == model)
    return f"{spec.integrator.output} (unit of data.observed)"


def plot_result(result: Result, out: str | Path, truth: Mapping[str, float] | None = None,
                data=None, n_draws: int | None = None, seed: int = 0, unit: str = "") -> dict[str, Path]:
    """Write the figures of one result to ``out``; with ``data`` (a
    :class:`service.report.analysis.JobData`) also the predictive bands and an ``nmse.json``.
    ``unit``: the distance's ("%" for the NMSE; ``abcns plot`` passes the store's)."""
    import json

    out = Path(out)
    files = {"tolerance": save(tolerance_figure(result, unit), out / "tolerance.png"),
             "model_probabilities": save(model_probability_figure(result, unit), out / "model_probabilities.png")}
    for i in result.alive():
        name = result.models[i].name
        files[f"marginals_{name}"] = save(marginals_figure(result, i, truth), out / f"marginals_{name}.png")
        if result.models[i].n_dim > 1:
            files[f"pairs_{name}"] = save(pairs_figure(result, i, truth, unit), out / f"pairs_{name}.png")
    if data is not None:
        from service.report.analysis import predictions

        preds, scores = predictions(result, data, n_draws, seed)
        for name, pred in preds.items():
            files[f"predictive_{name}"] = save(
                predictive_figure(pred, data.observed, data.dt, data.fit, data.test, scores[name],
                                  response_label(data, name)),
                out / f"predictive_{name}.png")
        (out / "nmse.json").write_text(json.dumps(scores, indent=2))
        files["nmse"] = out / "nmse.json"
    return files


__all__ = ["confusion_figure", "marginals_figure", "model_probability_figure", "pairs_figure",
           "plot_result", "predictive_figure", "response_label", "tolerance_figure"]
