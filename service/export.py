"""Export a run to xarray and ArviZ.

``to_dataset(result)`` gives one xarray Dataset of every population (particles padded to
the widest model, as in the store); ``from_dataset`` reads it back into an
:class:`abcns.Result` (particles, weights, counters and model probabilities; ellipsoids and
survivors are not part of the export). ``to_inference_data(result)`` gives one ArviZ
InferenceData per model alive in the final population: the ``posterior`` group holds its
particles as one chain (``chain`` 1, ``draw`` n_m, one variable per parameter) and
``sample_stats`` their ``distance`` and ``weight``. ArviZ is an optional dependency
(``pip install abcns[arviz]``) imported only here, on call.
"""

from __future__ import annotations

import json
import warnings
from typing import Any

import numpy as np
import xarray as xr

from abcns import Model, Population, Result, StopReason

FORMAT = "abcns-result"


def to_dataset(result: Result) -> xr.Dataset:
    """Every population of ``result`` as labelled arrays (dims population, particle,
    parameter, model); run metadata in ``attrs`` (JSON strings where nested)."""
    pops = result.populations
    if not pops:
        raise ValueError("the result has no complete population")
    n = max(p.n_particles for p in pops)
    d = max(m.n_dim for m in result.models)

    def pad(values: np.ndarray, fill: float, width: int | None = None) -> np.ndarray:
        out = np.full((n,) + (() if width is None else (width,)), fill, dtype=float)
        out[: values.shape[0], ...] = values if width is None else values[:, :width]
        return out

    names = [m.name for m in result.models]
    ds = xr.Dataset(
        {
            "model_index": (("population", "particle"), np.stack([pad(p.models.astype(float), -1) for p in pops]).astype(int)),
            "theta": (("population", "particle", "parameter"), np.stack([pad(p.theta, np.nan, d) for p in pops])),
            "distance": (("population", "particle"), np.stack([pad(p.distances, np.nan) for p in pops])),
            "weight": (("population", "particle"), np.stack([pad(p.weights, np.nan) for p in pops])),
            "epsilon": ("population", [p.epsilon for p in pops]),
            "epsilon_next": ("population", [p.epsilon_next for p in pops]),
            "acceptance_rate": ("population", [p.acceptance_rate for p in pops]),
            "n_accepted": ("population", [p.n_accepted for p in pops]),
            "n_simulations": ("population", [p.n_simulations for p in pops]),
            "n_failed": ("population", [p.n_failed for p in pops]),
            "n_redraws": ("population", [p.n_redraws for p in pops]),
            "elapsed_s": ("population", [p.elapsed_s for p in pops]),
            "model_probability": (("population", "model"), np.stack([p.model_probabilities for p in pops])),
        },
        coords={"population": [p.t for p in pops], "model": names},
        attrs={
            "format": FORMAT,
            "algorithm": result.algorithm,
            "models": json.dumps([m.config_dict() for m in result.models]),
            "stop_reason": result.stop_reason.value,
            "seed": result.seed,
            "settings": json.dumps(result.settings),
            "epsilon_initial_source": result.epsilon_initial_source,
            "n_simulations": result.n_simulations,
            "n_pilot_simulations": result.n_pilot_simulations,
            "wall_time_s": result.wall_time_s,
            "weighted_posterior": int(result.weighted_posterior),
            "notes": json.dumps(list(result.notes)),
        },
    )
    return ds


def _model(config: dict[str, Any]) -> Model:
    priors = {k: tuple(v) for k, v in config["priors"].items()}
    return Model(config["name"], priors, config.get("fixed", {}), config=config.get("config", {}))


def from_dataset(ds: xr.Dataset) -> Result:
    """The :class:`abcns.Result` a :func:`to_dataset` export holds."""
    if ds.attrs.get("format") != FORMAT:
        raise ValueError(f"not an abcns result export (attrs['format'] = {ds.attrs.get('format')!r})")
    models = tuple(_model(c) for c in json.loads(ds.attrs["models"]))
    pops = []
    for i, t in enumerate(ds["population"].values):
        idx = ds["model_index"].values[i]
        keep = idx >= 0
        pops.append(Population(
            t=int(t), epsilon=float(ds["epsilon"].values[i]), epsilon_next=float(ds["epsilon_next"].values[i]),
            models=idx[keep].astype(np.int64), theta=ds["theta"].values[i][keep], distances=ds["distance"].values[i][keep],
            weights=ds["weight"].values[i][keep], n_accepted=int(ds["n_accepted"].values[i]),
            n_simulations=int(ds["n_simulations"].values[i]), n_failed=int(ds["n_failed"].values[i]),
            n_redraws=int(ds["n_redraws"].values[i]), elapsed_s=float(ds["elapsed_s"].values[i]),
            model_probabilities=ds["model_probability"].values[i].copy(),
        ))
    a = ds.attrs
    return Result(
        algorithm=a["algorithm"], models=models, populations=tuple(pops), stop_reason=StopReason(a["stop_reason"]),
        seed=int(a["seed"]), settings=json.loads(a["settings"]), epsilon_initial_source=a["epsilon_initial_source"],
        n_simulations=int(a["n_simulations"]), n_pilot_simulations=int(a["n_pilot_simulations"]),
        wall_time_s=float(a["wall_time_s"]), weighted_posterior=bool(a["weighted_posterior"]),
        notes=tuple(json.loads(a["notes"])),
    )


def to_inference_data(result: Result, t: int | None = None) -> dict[str, Any]:
    """{model: arviz.InferenceData} for every model alive in population t (default: final).

    ``posterior``: one chain, one draw per particle, a variable per free parameter;
    ``sample_stats``: ``distance`` and ``weight`` (normalised within the model) per draw;
    attrs name the population, its tolerance and the model probability.
    """
    try:
        with warnings.catch_warnings():  # arviz 0.2x announces its 1.0 refactor on import
            warnings.simplefilter("ignore", FutureWarning)
            import arviz as az
    except ImportError as err:  # pragma: no cover - depends on the installation
        raise ImportError("the ArviZ export needs arviz: pip install 'abcns[arviz]'") from err
    pop = result.final if t is None else result.populations[t - 1]
    out = {}
    for i in result.alive(pop.t):
        model = result.models[i]
        theta, dist, w = result.particles(i, pop.t)
        out[model.name] = az.from_dict(
            posterior={name: theta[None, :, j] for j, name in enumerate(model.parameter_names)},
            sample_stats={"distance": dist[None, :], "weight": w[None, :]},
            posterior_attrs=(attrs := {"model": model.name, "population": pop.t, "epsilon": pop.epsilon,
                   "model_probability": float(pop.model_probabilities[i]), "algorithm": result.algorithm}),
            sample_stats_attrs=attrs,
        )
    return out
