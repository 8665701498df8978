"""Analysis of a finished run: posterior predictive bands, NMSE on fit and test windows
(paper Table 8), and the confusion matrix of §5.4 (Fig. 27).

Pure numpy: simulation is a callable the caller passes in, ``simulate(theta (n, d)) ->
trajectories (n, T)`` or ``(trajectories, status)`` with ``abcns.OK`` for the usable rows.
Without a status, a row with a non-finite value is taken as not OK. Rows that are not OK
are counted and left out of every band and score, never averaged in.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from abcns.distances import NMSE
from abcns.executor import OK
from abcns.result import Result

Simulate = Callable[[np.ndarray], "np.ndarray | tuple[np.ndarray, np.ndarray]"]
LEVELS = (0.5, 0.99)


def _simulate(simulate: Simulate, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    out = simulate(np.atleast_2d(theta))
    if isinstance(out, tuple):
        values, status = out
        values = np.atleast_2d(np.asarray(values, dtype=float))
        ok = np.asarray(status) == OK
    else:
        values = np.atleast_2d(np.asarray(out, dtype=float))
        ok = np.ones(values.shape[0], dtype=bool)
    ok &= np.all(np.isfinite(values), axis=1)
    return values, ok


def bands(trajectories: np.ndarray, levels: Sequence[float] = LEVELS) -> dict[str, np.ndarray]:
    """Pointwise median and central bands of trajectories ``(n, T)``.

    Returns ``{"median": (T,), "lower_50": (T,), "upper_50": (T,), "lower_99": ..., ...}``:
    for level p the ``(1 - p) / 2`` and ``(1 + p) / 2`` quantiles (numpy's default linear
    interpolation) of the n values at each time step.
    """
    trajectories = np.atleast_2d(np.asarray(trajectories, dtype=float))
    if trajectories.shape[0] == 0:
        raise ValueError("no trajectories: every simulation failed")
    out = {"median": np.quantile(trajectories, 0.5, axis=0)}
    for p in levels:
        if not 0 < p < 1:
            raise ValueError(f"band levels must be in (0, 1), got {p}")
        lo, hi = np.quantile(trajectories, [(1 - p) / 2, (1 + p) / 2], axis=0)
        tag = f"{100 * p:g}".replace(".", "_")
        out[f"lower_{tag}"], out[f"upper_{tag}"] = lo, hi
    return out


@dataclass(frozen=True, eq=False)
class Predictive:
    """Posterior predictive of one model: the parameter draws, the usable trajectories and
    their pointwise bands (see :func:`bands`)."""

    model: str
    theta: np.ndarray  # (n_draws, d) parameter sets simulated
    ok: np.ndarray  # (n_draws,) bool: rows whose simulation is usable
    trajectories: np.ndarray  # (n_ok, T)
    bands: dict[str, np.ndarray]

    @property
    def n_failed(self) -> int:
        return int(np.sum(~self.ok))


def draw_parameters(result: Result, model: int | str, n_draws: int | None = None,
                    rng: np.random.Generator | None = None, t: int | None = None) -> np.ndarray:
    """Parameter sets ``(n, d)`` from one model's particles in population t (default: final).

    ``n_draws=None``: every particle, in population order (for ABC-NS and rejection the
    population is the posterior sample; no randomness). Otherwise ``n_draws`` draws with
    replacement, uniform over the particles, or by weight for a weighted posterior
    (ABC-SMC); this needs ``rng``.
    """
    theta, _, w = result.particles(model, t)
    if theta.shape[0] == 0:
        raise ValueError(f"model {model!r} has no particles in population {t or result.final.t}")
    if n_draws is None:
        return theta.copy()
    if rng is None:
        raise ValueError("n_draws needs an rng (numpy.random.Generator)")
    p = w / np.sum(w) if result.weighted_posterior else None
    return theta[rng.choice(theta.shape[0], size=int(n_draws), replace=True, p=p)]


def predictive(result: Result, model: int | str, simulate: Simulate, n_draws: int | None = None,
               rng: np.random.Generator | None = None, t: int | None = None,
               levels: Sequence[float] = LEVELS) -> Predictive:
    """Posterior predictive bands of one model (paper Figs. 14, 20, 22): draw parameter
    sets (:func:`draw_parameters`), simulate them, and take the pointwise median and the
    50 % and 99 % bands over the rows that simulated OK."""
    theta = draw_parameters(result, model, n_draws, rng, t)
    values, ok = _simulate(simulate, theta)
    name = model if isinstance(model, str) else result.models[model].name
    return Predictive(name, theta, ok, values[ok], bands(values[ok], levels))


def nmse(simulated: np.ndarray, observed: np.ndarray, window: tuple[int, int] | None = None) -> np.ndarray:
    """Paper Eq. (7) on the half-open window: ``100 / (n var(obs)) sum (sim - obs)^2``
    (var with ddof = 1, as in :class:`abcns.NMSE`); simulated ``(T,)`` or ``(n, T)``."""
    d = NMSE(observed, window)(np.atleast_2d(simulated))
    return d if np.ndim(simulated) > 1 else d[0]


def point_estimates(result: Result, model: int | str, t: int | None = None) -> dict[str, np.ndarray]:
    """``{"posterior_mean": (d,), "best": (d,)}``: the (weighted, for ABC-SMC) mean of the
    model's particles and the particle with the smallest distance."""
    theta, d, w = result.particles(model, t)
    if theta.shape[0] == 0:
        raise ValueError(f"model {model!r} has no particles")
    w = w / np.sum(w) if result.weighted_posterior else np.full(theta.shape[0], 1.0 / theta.shape[0])
    return {"posterior_mean": w @ theta, "best": theta[int(np.argmin(d))].copy()}


def fit_test_nmse(result: Result, model: int | str, simulate: Simulate, observed: np.ndarray,
                  windows: Mapping[str, tuple[int, int] | None]) -> dict[str, dict[str, float]]:
    """NMSE (Eq. 7) of the posterior mean and the best particle on each named window
    (Table 8): ``{"posterior_mean": {"fit": ..., "test": ...}, "best": {...}}``; a point
    whose simulation is not OK scores +inf."""
    points = point_estimates(result, model)
    values, ok = _simulate(simulate, np.stack(list(points.values())))
    out = {}
    for i, key in enumerate(points):
        out[key] = {name: float(nmse(values[i], observed, w)) if ok[i] else float("inf")
                    for name, w in windows.items() if w is not None}
    return out


@dataclass(frozen=True, eq=False)
class Confusion:
    """Confusion matrices of §5.4: ``matrices[model][i, j]`` is the score (NMSE) of the
    model fitted on data set i and predicting data set j.

    Rule for ``best`` (the paper compares "the MSE values considering all the testing data
    sets" and drops a model with numerical instability): a model with any non-finite entry
    is eliminated; among the rest, the smallest mean over all (i, j) entries wins, ties
    broken by the smaller worst entry."""

    models: tuple[str, ...]
    datasets: tuple[str, ...]
    matrices: dict[str, np.ndarray]
    mean: dict[str, float]
    worst: dict[str, float]
    eliminated: tuple[str, ...]
    best: str | None


def confusion(fits: Sequence[Result], score: Callable[[str, np.ndarray, int], float],
              datasets: Sequence[str] | None = None, models: Sequence[str] | None = None,
              point: str = "posterior_mean") -> Confusion:
    """The confusion matrices of §5.4 (Fig. 26-27).

    ``fits[i]`` is a run on data set i (the same candidate models in every run);
    ``score(model_name, theta (d,), j)`` scores that model with that parameter vector on
    data set j (e.g. the NMSE of its simulation on j's test window). The parameter vector
    is the ``point`` estimate (``posterior_mean`` or ``best``) of the model in ``fits[i]``;
    a model with no particle left in ``fits[i]`` scores +inf on row i.
    """
    if not fits:
        raise ValueError("confusion needs at least one fitted data set")
    names = tuple(models) if models is not None else tuple(fits[0].model_names)
    labels = tuple(datasets) if datasets is not None else tuple(str(i) for i in range(len(fits)))
    if len(labels) != len(fits):
        raise ValueError(f"{len(labels)} data set names for {len(fits)} fits")
    n = len(fits)
    matrices = {}
    for name in names:
        mat = np.full((n, n), np.inf)
        for i, res in enumerate(fits):
            if name not in res.model_names or res.model_names.index(name) not in res.alive():
                continue
            theta = point_estimates(res, name)[point]
            for j in range(n):
                s = float(score(name, theta, j))
                mat[i, j] = s if np.isfinite(s) else np.inf
        matrices[name] = mat
    mean = {k: float(np.mean(m)) for k, m in matrices.items()}
    worst = {k: float(np.max(m)) for k, m in matrices.items()}
    eliminated = tuple(k for k, m in matrices.items() if not np.all(np.isfinite(m)))
    contenders = [k for k in names if k not in eliminated]
    best = min(contenders, key=lambda k: (mean[k], worst[k])) if contenders else None
    return Confusion(names, labels, matrices, mean, worst, eliminated, best)
