"""A store read back: as an :class:`abcns.Result` (:func:`result_from_store`, finished or
not; :func:`dataset_result` from its xarray dataset, or ``service.report.export``'s), its
dataset's populations and attributes, and one model's view of it (:func:`model_view`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import xarray as xr

from abcns.priors import Model
from abcns.result import Population, Result
from abcns.settings import StopReason
from service.run.store.metadata import decode_attrs
from service.run.store.rows import Layout, population
from service.run.store.schema import POPULATION_ARRAYS

if TYPE_CHECKING:
    from service.run.store.job_store import Store


def model_view(ds: xr.Dataset, model: str) -> xr.Dataset:
    """One model's part of a dataset of the store's schema (:meth:`Store.dataset`, or a plain
    ``xarray.open_zarr`` of a store): its particles' ``theta`` (its own parameters only),
    ``distance``, ``weight`` and ``survivor``, NaN (False) at the other models' particles;
    the population-level variables; and the per-model variables at ``model`` (its
    probability, counters, ellipsoids, evidence, prior). ``model_view(ds, "cubic").theta``
    is what ``ds.theta.sel(model="cubic")`` would mean."""
    names = [str(m) for m in ds["model"].values]
    if model not in names:
        raise KeyError(f"no model {model!r} in this store; its models are {names}")
    own = ds["parameter"].values[ds["model_has_parameter"].sel(model=model).values]
    mine = ds["model_index"] == names.index(model)
    out = ds.sel(model=model).sel(parameter=own)
    if "parameter_b" in out.dims:
        out = out.sel(parameter_b=own)
    for name in ("theta", "distance", "weight"):
        out[name] = out[name].where(mine)
    out["survivor"] = out["survivor"] & mine
    return out.assign_attrs(model=model)



def dataset_attrs(ds: xr.Dataset) -> dict[str, Any]:
    """The attributes of a dataset of the store's schema, decoded (as :attr:`Store.attrs`)."""
    return decode_attrs(ds.attrs)


def dataset_populations(ds: xr.Dataset) -> list[Population]:
    """The populations a dataset of the store's schema holds (``Store.dataset()``,
    ``xarray.open_zarr`` of a store, or ``service.report.export.to_dataset``)."""
    layout = Layout.of(dataset_attrs(ds))
    arrays = {name: np.asarray(ds[name].values) for name in POPULATION_ARRAYS if name in ds}
    return [population(layout, arrays, i) for i in range(ds.sizes["population"])]


def result_of(attrs: Mapping[str, Any], populations: Sequence[Population], n_simulations_total: int,
              elapsed_s: float) -> Result:
    """The :class:`abcns.Result` of a store's (decoded) attributes and populations, finished or
    not: a run still going, or one a crash ended, has no run information yet (set when the
    job ends), so its simulations and wall time are the store's last ``n_simulations_total``
    and ``elapsed_s`` (the caller's), and its stop reason is "cancelled"."""
    spec, run = attrs["spec"], attrs.get("run") or {}
    return Result(
        algorithm=attrs["algorithm"],
        models=tuple(Model.from_dict(m) for m in spec["models"]),
        populations=tuple(populations),
        stop_reason=StopReason(attrs.get("stop_reason") or StopReason.CANCELLED),
        seed=int(attrs["seed"]),
        settings={"sampler": spec.get("sampler", {}), "stop": spec.get("stop", {})},
        epsilon_initial_source=run.get("epsilon_initial_source", ""),
        n_simulations=int(run.get("n_simulations", n_simulations_total)),
        n_pilot_simulations=int(run.get("n_pilot_simulations", 0)),
        wall_time_s=float(run.get("wall_time_s", elapsed_s)),
        weighted_posterior=attrs["algorithm"] == "abc-smc",
        notes=tuple(run.get("notes", ())),
    )


def result_from_store(store: Store) -> Result:
    """The :class:`abcns.Result` of a store (finished or not): its attributes, then its
    complete populations and their counters in one read."""
    attrs = store.attrs
    pops, a = store._records(int(attrs["n_populations"]), (*POPULATION_ARRAYS, "n_simulations_total"))
    total, elapsed = (int(a["n_simulations_total"][-1]), float(a["elapsed_s"][-1])) if pops else (0, 0.0)
    return result_of(attrs, pops, total, elapsed)


def dataset_result(ds: xr.Dataset) -> Result:
    """The :class:`abcns.Result` a dataset of the store's schema holds (as :func:`result_from_store`)."""
    last = ds.isel(population=-1) if ds.sizes["population"] else None
    return result_of(dataset_attrs(ds), dataset_populations(ds),
                     0 if last is None else int(last["n_simulations_total"]), 0.0 if last is None else float(last["elapsed_s"]))
