"""What a figure shows, read back from its matplotlib objects (the project's rule: a test of
what a person sees looks at the drawn bars, lines and axes, not at a file's size).

:func:`record_saved` keeps every :class:`~matplotlib.figure.Figure` a test's code saves (the
file is still written), so a test checks the very figures behind the PNG files; the
``check_*`` functions compare one figure of :mod:`service.report.plots` with the result it
was drawn from."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.colors import to_hex
from matplotlib.figure import Figure

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
RED = to_hex("tab:red")


def is_red(line) -> bool:
    return to_hex(line.get_color()) in (RED, to_hex("r"))


def is_png(path: Path) -> bool:
    """The file was written as a PNG (its signature); what it shows is checked on the figure."""
    return path.read_bytes()[:8] == PNG_SIGNATURE


def record_saved(monkeypatch) -> dict[Path, Figure]:
    """From now until the test ends, every figure saved through ``Figure.savefig`` (which
    still writes the file), keyed by the path it was saved to."""
    saved: dict[Path, Figure] = {}
    real = Figure.savefig

    def spy(self, fname, *args, **kwargs):
        saved[Path(fname)] = self
        return real(self, fname, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", spy)
    return saved


def xy(line) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(line.get_xdata(), dtype=float), np.asarray(line.get_ydata(), dtype=float)


def vertical_lines(ax, colour: str | None = None) -> list[float]:
    """The x of each ``axvline`` (a Line2D whose xdata are [v, v]), of one colour if given."""
    return [float(x[0]) for line in ax.lines for x, _ in [xy(line)]
            if x.size == 2 and x[0] == x[1] and (colour is None or to_hex(line.get_color()) == colour)]


def horizontal_lines(ax, colour: str | None = None) -> list[float]:
    """The y of each ``axhline`` (xdata [0, 1] in axes coordinates, ydata [v, v])."""
    return [float(y[0]) for line in ax.lines for x, y in [xy(line)]
            if list(x) == [0.0, 1.0] and y[0] == y[1] and (colour is None or to_hex(line.get_color()) == colour)]


def band_bounds(collection, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper edge of a ``fill_between`` band at each x: its polygon's vertices there."""
    v = np.concatenate([p.vertices for p in collection.get_paths()])
    at = [v[v[:, 0] == xi, 1] for xi in x]
    assert all(a.size for a in at), "the band does not cover every x"
    return np.array([a.min() for a in at]), np.array([a.max() for a in at])


def contains(lim: tuple[float, float], *values) -> bool:
    lo, hi = sorted(lim)
    v = np.concatenate([np.ravel(np.asarray(a, dtype=float)) for a in values])
    v = v[np.isfinite(v)]
    return bool(lo <= v.min() and v.max() <= hi)


def check_tolerance_figure(fig: Figure, result, unit: str) -> None:
    """Left: each population's tolerance (log axis, in ``unit``); right: its acceptance rate."""
    pops = result.populations
    t = [p.t for p in pops]
    eps_ax, acc_ax = fig.axes
    (eps_line,) = eps_ax.lines
    np.testing.assert_array_equal(xy(eps_line)[0], t)
    np.testing.assert_allclose(xy(eps_line)[1], [p.epsilon for p in pops], rtol=1e-12)
    assert eps_ax.get_yscale() == "log" and eps_ax.get_xlabel() == "population"
    assert eps_ax.get_ylabel() == "tolerance $\\varepsilon_t$" + (f" ({unit})" if unit else "")
    assert contains(eps_ax.get_ylim(), [p.epsilon for p in pops]) and contains(eps_ax.get_xlim(), t)
    (acc_line,) = acc_ax.lines
    np.testing.assert_array_equal(xy(acc_line)[0], t)
    np.testing.assert_allclose(xy(acc_line)[1], [p.acceptance_rate for p in pops], rtol=1e-12)
    assert acc_ax.get_ylabel() == "acceptance rate" and acc_ax.get_ylim() == (0, 1.02)
    assert f"{len(pops)} populations, {result.n_simulations:,} simulations" in fig.get_suptitle()


def check_model_probability_figure(fig: Figure, result, unit: str) -> None:
    """Stacked bars of each population's model probabilities (summing to 1), the decision
    population marked when it is not the final one, the legend's answer read there; right:
    p_m against the tolerance with the noise floor and the decision tolerance."""
    pops = result.populations
    t = np.array([p.t for p in pops])
    probs = np.stack([p.model_probabilities for p in pops])
    answer = result.decision_population()
    bars_ax, eps_ax = fig.axes
    assert len(bars_ax.containers) == len(result.model_names)
    top = np.zeros(len(t))
    for i, bars in enumerate(bars_ax.containers):
        assert [r.get_x() + r.get_width() / 2 for r in bars] == list(t)
        np.testing.assert_allclose([r.get_y() for r in bars], top, atol=1e-12)  # stacked on the models before
        np.testing.assert_allclose([r.get_height() for r in bars], probs[:, i], rtol=1e-12)
        top += [r.get_height() for r in bars]
    np.testing.assert_allclose(top, 1.0, rtol=1e-9)  # each population's bar reaches 1
    assert vertical_lines(bars_ax) == ([] if answer is result.final else [answer.t])
    k = answer.t - 1  # the legend gives each model's probability there (and the final one's when later)
    final = "" if answer is result.final else ", final {:.2f}"
    labels = [f"{n} (answer {probs[k, i]:.2f}{final.format(probs[-1, i])})" for i, n in enumerate(result.model_names)]
    decision = [] if answer is result.final else [f"decision: population {answer.t}"]
    assert [tx.get_text() for tx in bars_ax.get_legend().get_texts()] == decision + labels
    assert contains(bars_ax.get_xlim(), t) and bars_ax.get_ylim() == (0, 1)

    eps = np.array([p.epsilon for p in pops])
    shown = np.isfinite(eps) & (eps > 0)
    curves = eps_ax.lines[:len(result.model_names)]
    for i, line in enumerate(curves):
        np.testing.assert_allclose(xy(line)[0], eps[shown], rtol=1e-12)
        np.testing.assert_allclose(xy(line)[1], probs[shown, i], rtol=1e-12)
    floor = result.floor
    expected = [] if floor is None else [floor.floor, floor.decision]
    np.testing.assert_allclose(vertical_lines(eps_ax), expected, rtol=1e-12)
    assert eps_ax.get_xscale() == "log" and eps_ax.xaxis_inverted()
    assert eps_ax.get_xlabel() == "tolerance $\\varepsilon$" + (f" ({unit})" if unit else "")
    assert contains(eps_ax.get_xlim(), eps[shown], expected)


def posterior(result, model: str):
    i = result.model_names.index(model)
    theta, dist, w = result.particles(i)
    return result.models[i], theta, dist, (w if result.weighted_posterior else None)


def check_marginals_figure(fig: Figure, result, model: str, truth: Mapping[str, float], bins: int = 30) -> None:
    """One histogram per parameter holding the final population (its weights when the
    posterior is weighted), a red line at the truth where one is given, the 95 % interval
    dotted (unweighted), and an x range holding the samples and the truth."""
    m, theta, _, weights = posterior(result, model)
    d = m.n_dim
    assert all(ax.get_visible() for ax in fig.axes[:d]) and not any(ax.get_visible() for ax in fig.axes[d:])
    for j, (ax, name) in enumerate(zip(fig.axes[:d], m.parameter_names, strict=True)):
        assert ax.get_xlabel() == name
        counts, edges = np.histogram(theta[:, j], bins=bins, weights=weights)
        assert len(ax.patches) == bins
        np.testing.assert_allclose([r.get_height() for r in ax.patches], counts, rtol=1e-12)
        np.testing.assert_allclose([r.get_x() for r in ax.patches], edges[:-1], rtol=1e-12)
        total = theta.shape[0] if weights is None else weights.sum()
        assert np.isclose(sum(r.get_height() for r in ax.patches), total)  # every particle is in a bar
        tv = truth.get(name)
        assert vertical_lines(ax, RED) == ([] if tv is None else [tv]), name
        if weights is None:
            np.testing.assert_allclose(vertical_lines(ax, to_hex("k")), np.quantile(theta[:, j], [0.025, 0.975]))
        assert contains(ax.get_xlim(), theta[:, j], [] if tv is None else [tv]), name


def pairs_grid(fig: Figure, d: int) -> np.ndarray:
    """The d x d panels of a pairs figure by their grid position (the colorbar left out)."""
    at = {(ax.get_subplotspec().rowspan.start, ax.get_subplotspec().colspan.start): ax
          for ax in fig.axes if ax.get_subplotspec() is not None and ax.get_label() != "<colorbar>"}
    return np.array([[at[r, c] for c in range(d)] for r in range(d)], dtype=object)


def check_pairs_figure(fig: Figure, result, model: str, truth: Mapping[str, float]) -> None:
    """Diagonal: parameter c's histogram (25 bins) with its truth in red; panel (r, c):
    parameter c (x) against r (y) for every particle, coloured by distance, with the truth
    as a red cross (or a red line when only one coordinate is known); every panel's limits
    hold its samples and the truth."""
    m, theta, dist, _ = posterior(result, model)
    names = m.parameter_names
    d = len(names)
    tv = [truth.get(n) for n in names]
    axes = pairs_grid(fig, d)
    for r in range(d):
        for c in range(r + 1):
            ax = axes[r, c]
            assert contains(ax.get_xlim(), theta[:, c], [tv[c]] if tv[c] is not None else [])
            if r == c:
                counts, _ = np.histogram(theta[:, c], bins=25)
                np.testing.assert_array_equal([p.get_height() for p in ax.patches], counts)
                assert vertical_lines(ax, RED) == ([] if tv[c] is None else [tv[c]]), names[c]
                continue
            (points,) = ax.collections
            np.testing.assert_array_equal(points.get_offsets(), np.column_stack([theta[:, c], theta[:, r]]))
            np.testing.assert_array_equal(points.get_array(), dist)
            assert contains(ax.get_ylim(), theta[:, r], [tv[r]] if tv[r] is not None else [])
            red = [xy(line) for line in ax.lines if is_red(line)]
            if tv[c] is not None and tv[r] is not None:
                assert [(list(x), list(y)) for x, y in red] == [([tv[c]], [tv[r]])], (names[c], names[r])
            else:
                assert vertical_lines(ax, RED) == ([] if tv[c] is None else [tv[c]]), (names[c], names[r])
                assert horizontal_lines(ax, RED) == ([] if tv[r] is None else [tv[r]]), (names[c], names[r])
                assert len(red) == (tv[c] is not None) + (tv[r] is not None)


def check_predictive_figure(fig: Figure, observed: np.ndarray, dt: float | None, windows: dict,
                            pred=None, ylabel: str | None = None) -> None:
    """One panel per window (fit, test): the observed record as black dots, the predictive
    median inside the 50 % band inside the 99 % band (the bands of ``pred`` when given), at
    the sample times; the limits hold the data and the bands."""
    axes = fig.axes
    assert len(axes) == len(windows)
    for ax, (label, (a, z)) in zip(axes, windows.items(), strict=True):
        x = np.arange(a, z) * (1.0 if dt is None else dt)
        assert ax.get_title().startswith(f"{label} window [{a}, {z})")
        lines = {line.get_label(): line for line in ax.lines}
        assert lines["observed"].get_marker() == "." and to_hex(lines["observed"].get_color()) == to_hex("k")
        np.testing.assert_array_equal(xy(lines["observed"])[0], x)
        np.testing.assert_array_equal(xy(lines["observed"])[1], observed[a:z])
        mx, median = xy(lines["predictive median"])
        np.testing.assert_array_equal(mx, x)
        band = {coll.get_label(): band_bounds(coll, x) for coll in ax.collections}
        (lo99, hi99), (lo50, hi50) = band["99 % band"], band["50 % band"]
        assert np.all(lo99 <= lo50) and np.all(lo50 <= median) and np.all(median <= hi50) and np.all(hi50 <= hi99)
        if pred is not None:
            b = pred.bands
            for key, got in (("median", median), ("lower_99", lo99), ("upper_99", hi99), ("lower_50", lo50),
                             ("upper_50", hi50)):
                np.testing.assert_allclose(got, b[key][a:z], rtol=1e-12, err_msg=key)
        assert contains(ax.get_xlim(), x) and contains(ax.get_ylim(), observed[a:z], lo99, hi99)
        if ylabel is not None:
            assert ax.get_ylabel() == ylabel


def check_confusion_figure(fig: Figure, conf) -> None:
    """One heat map per model holding its confusion matrix (fitted on row i, tested on
    column j), each cell's value written in it, the best model named in its title."""
    for ax, name in zip(fig.axes, conf.models, strict=False):
        mat = conf.matrices[name]
        (image,) = ax.images
        shown = np.ma.filled(np.ma.asarray(image.get_array(), dtype=float), np.nan)
        np.testing.assert_array_equal(shown, np.where(np.isfinite(mat), mat, np.nan))  # grey: no fit / failed
        cells = {(round(tx.get_position()[1]), round(tx.get_position()[0])): tx.get_text() for tx in ax.texts}
        assert cells == {(r, c): f"{v:.3g}" if np.isfinite(v) else "no fit /\nfailed" for (r, c), v in np.ndenumerate(mat)}
        assert [tx.get_text() for tx in ax.get_xticklabels()] == list(conf.datasets)
        assert [tx.get_text() for tx in ax.get_yticklabels()] == list(conf.datasets)
        assert ax.get_xlabel() == "tested on" and ax.get_ylabel() == "fitted on"
        tag = " (best)" if name == conf.best else (" (eliminated)" if name in conf.eliminated else "")
        assert ax.get_title().startswith(f"{name}{tag}\nmean NMSE {conf.mean[name]:.3g} %")
    assert len(fig.axes) == len(conf.models) + 1 and fig.axes[-1].get_ylabel() == "NMSE (%, Eq. 7)"
