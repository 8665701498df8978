"""Export a run to xarray and ArviZ.

``to_dataset(result)`` gives one xarray Dataset of every population in the result store's
schema (``service/run/store/schema.py``, format 4: model and parameter labelled by name, units and
descriptions, ``format_version``), so a run from ``abcns.run`` and a store opened with
``xarray.open_zarr`` read alike; ``from_dataset`` reads either back into an
:class:`abcns.Result` (particles, weights, counters, model probabilities, survivors,
ellipsoids and evidence). ``to_inference_data(result)`` gives one ArviZ InferenceData per
model alive in the final population: the ``posterior`` group holds its particles as one
chain (``chain`` 1, ``draw`` n_m, one variable per parameter) and ``sample_stats`` their
``distance`` and ``weight``. ArviZ is an optional dependency (``pip install abcns[arviz]``)
imported only here, on call.
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path
from typing import Any

import xarray as xr

from abcns import Result
from service.run.store import FORMAT_VERSION, Store, dataset_result


def to_dataset(result: Result) -> xr.Dataset:
    """Every population of ``result`` as the store's labelled arrays (in memory)."""
    pops = result.populations
    if not pops:
        raise ValueError("the result has no complete population")
    spec = {"models": [m.config_dict() for m in result.models], **result.settings}
    with tempfile.TemporaryDirectory() as tmp:
        store = Store.create(Path(tmp) / "result.zarr", spec=spec, seed=result.seed, model_names=list(result.model_names),
                             parameter_names=[list(m.parameter_names) for m in result.models],
                             n_particles=pops[0].n_particles, data_hash="", algorithm=result.algorithm,
                             max_ellipsoids=max([len(b) for p in pops for b in p.ellipsoids] + [1]))
        total = result.n_pilot_simulations
        rows = []
        for pop in pops:
            total += pop.n_simulations
            rows.append((pop, total))
        store.append_many(rows)
        store.set_status("finished", result.stop_reason, run={
            "epsilon_initial_source": result.epsilon_initial_source, "n_pilot_simulations": result.n_pilot_simulations,
            "n_simulations": result.n_simulations, "wall_time_s": result.wall_time_s, "notes": list(result.notes)})
        return store.dataset().load()


def from_dataset(ds: xr.Dataset) -> Result:
    """The :class:`abcns.Result` a dataset of the store's schema holds."""
    if ds.attrs.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"not an abcns result of format {FORMAT_VERSION} (format_version = {ds.attrs.get('format_version')!r})")
    return dataset_result(ds)


def to_inference_data(result: Result, t: int | None = None) -> dict[str, Any]:
    """{model: arviz.InferenceData} for every model alive in population t (default: the
    decision population, :meth:`abcns.Result.decision_population`, where the run's answer is read).

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
    pop = result.decision_population() if t is None else result.populations[t - 1]
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
