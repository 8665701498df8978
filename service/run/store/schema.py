"""The result store's layout (its format): one zarr 3 directory per job, appended population
by population.

Layout: every array is declared once, in :data:`SCHEMA` (name, dimensions, dtype, fill,
``long_name``, ``description``, units); :meth:`Store.create`, the rows an append writes and
the records read back are derived from it. Every array but the static coordinates grows along
``population``, in chunks of at most ~64 KiB (one population of a large particle array, up to
256 of a scalar):

- particle level (population, particle[, parameter]): ``model_index`` (an index along
  ``model``), ``theta`` with one column per parameter *name* (NaN where the particle's model
  has no such parameter), ``distance``, ``weight``, ``survivor``, ``held``;
- population level: ``population`` (the population number t, 1-based; xarray's index), the
  tolerances, counters and elapsed time, ``has_survivors`` and ``has_ellipsoids`` (False for
  the baselines, whose records carry no survivors and no ellipsoids), the noise floor
  (``floor_*``, ``noise_floor``, ``decision_tolerance``; ``has_floor``);
- per model (population, model[, ellipsoid, parameter, parameter_b]): ``model_probability``,
  the counters split by model (-1: not recorded), the bounds ``ellipsoid_centre``,
  ``ellipsoid_matrix`` (in the same named columns, NaN where there is none and in the rows
  and columns of parameters the model does not have) and ``ellipsoid_note`` (``NOTE_CODES``;
  -1: none), up to ``max_ellipsoids`` per model; the ABC-NS evidence bookkeeping
  ``evidence_<field>`` for every field of :class:`abcns.evidence.Evidence` (``has_evidence``);
- coordinates: ``model`` the model names, ``parameter`` and ``parameter_b`` the parameter
  names of all models, in first-seen order, ``model_has_parameter`` (model, parameter), and
  each model's uniform prior ``prior_low`` and ``prior_width`` (model, parameter; NaN where
  the model has no such parameter, or the spec names no prior).

The ellipsoids' geometry (the group attribute ``ellipsoid_frame`` and the two variables'
descriptions say it too): an ellipsoid is ``{x : (x - c)^T M^-1 (x - c) <= 1}`` with ``c``
= ``ellipsoid_centre`` and ``M`` = ``ellipsoid_matrix`` (:mod:`abcns.ellipsoid`'s
convention: M is the scaled covariance, not its inverse). ``x`` is in the frame the
algorithm fits the bounds in: ``"unit prior box"`` (ABC-NS's evidence variant, the default):
``x = (theta - prior_low) / prior_width`` per parameter, so a centre of 0.5 is the middle of
the prior; ``"parameters"`` (the paper variant): ``x = theta``, in the parameters' own units;
in both, a parameter whose prior the spec gives as log-uniform (``[low, high, "log"]``) has
log theta in place of theta, log(prior_low) and log(1 + prior_width / prior_low) in place of
prior_low and prior_width (the two descriptions name those parameters);
None for the baselines, which store no ellipsoids.

Parameters (``theta``, the priors) are in the units of the simulator's equations for the
data as given: the spec states no units (with the force in N and the displacement in m, a
Duffing oscillator's m is in kg, c in N s/m, k in N/m, k3 in N/m^3). The distances and the
tolerances are in ``%`` for the NMSE (Eq. 7).

So ``xarray.open_zarr(path)`` is self-describing (the store keeps consolidated metadata, so
xarray opens it without a warning): ``ds.model_probability.sel(model="cubic")``,
``ds.theta.sel(parameter="k")`` (NaN for the particles of models without ``k``;
``ds.model_index`` says whose particle it is) and ``ds.ellipsoid_centre.sel(model="cubic",
parameter="k")`` work; every variable carries ``long_name``, ``description`` and, where it
has one, ``units``. One model's particles: :func:`model_view` (``Store.model("cubic")``, or
``model_view(xr.open_zarr(path), "cubic")``) gives its ``theta`` with its own parameters
only, NaN for the other models' particles, and its slices of the per-model variables.

The group attributes hold ``format_version``, the spec, seed, package versions (numba,
dask, distributed and the code's git commit included), the data hash, algorithm, model and
parameter names (in each model's own order), status, stop reason, run information, the
counter ``n_populations`` and ``ellipsoid_frame``. Attributes that are not a string or a
number (the spec, lists, None) are stored as JSON text after the prefix ``json:`` (so
``ds.to_netcdf()`` works); :attr:`Store.attrs` decodes them
(:mod:`service.run.store.metadata`).

The other modules of the store derive from :data:`SCHEMA`: :mod:`~service.run.store.rows`
(a population to the arrays' rows and back), :mod:`~service.run.store.job_store` (the
:class:`Store`: create, append, read) and :mod:`~service.run.store.results` (a store or its
dataset read back as an :class:`abcns.Result`, one model's view).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import zarr

from abcns.evidence import Evidence
from abcns.noise import Floor
from abcns.priors import Uniform

# 4: the noise floor per population (floor_*), simulations and failures per model; 5: coverage_test;
# 6: held in coverage_test's place, evidence_coverage and evidence_n_coverage gone (the mixture's evidence);
# 7: held per particle and model (a copy's bound is fitted to its twins' particles too)
FORMAT_VERSION = 7
CHUNK_BYTES = 64 * 1024

NOTE_CODES = {"": 0, "repaired": 1, "fallback": 2, "box": 3}  # -1: no ellipsoid (dead model)
NOTES = {code: note for note, code in NOTE_CODES.items()}

#: the group attribute ``ellipsoid_frame``: the coordinates ellipsoid_centre and _matrix are in
FRAMES = ("unit prior box", "parameters")

_P, _N, _D, _DB, _M, _E = "population", "particle", "parameter", "parameter_b", "model", "ellipsoid"


@dataclass(frozen=True)
class Variable:
    """One array of the store, declared once: everything else (the arrays :meth:`Store.create`
    makes, the row :func:`~service.run.store.rows.row` writes, what :func:`~service.run.store.rows.population` reads back, the
    attributes xarray shows) is derived from :data:`SCHEMA`.

    ``dims`` follow ``population`` for the arrays that grow (``grows``; the static coordinates
    have their own); ``fill`` is what an unwritten element reads as (NaN, -1 or False by
    dtype unless given). ``units`` may say ``{distance_units}`` (filled from the spec's
    distance: ``%`` for the NMSE of Eq. 7), ``description`` ``{frame}`` (:data:`FRAMES`).
    ``field`` is the :class:`abcns.Population` attribute the array holds as it is (``"floor.best"``:
    the attribute ``best`` of ``pop.floor``; fill where that is None); None: built by its own
    code in :mod:`~service.run.store.rows`. ``derived``: written for readers only, not read back
    (it follows from the arrays that are)."""

    name: str
    dims: tuple[str, ...]
    dtype: str
    long_name: str
    description: str
    units: str | None = None
    field: str | None = None
    fill: Any = None
    grows: bool = True
    derived: bool = False

    @property
    def fill_value(self) -> Any:
        if self.fill is not None:
            return self.fill
        return {"f": np.nan, "i": -1, "b": False}[np.dtype(self.dtype).kind]


_V = Variable
#: every array of the store, in the order :meth:`Store.create` makes them
SCHEMA: tuple[Variable, ...] = (
    _V("population", (), "int32", "population", "the population number t (1-based)", field="t", fill=0),
    _V("model_index", (_N,), "int16", "model of the particle", "index along the model dimension", field="models"),
    _V("theta", (_N, _D), "float64", "parameter values", "the particle's free parameters, in the units of the spec's "
       "priors, which are those of the simulator's equations for the data as given (the spec states no units); NaN for "
       "parameters its model does not have (model_index says whose particle it is; one model: model_view)"),
    _V("distance", (_N,), "float64", "distance", "the particle's distance to the data", "{distance_units}",
       field="distances"),
    _V("weight", (_N,), "float64", "weight", "normalised to sum to 1 within each model (ABC-NS: survivor selection)", "1",
       field="weights"),
    _V("survivor", (_N,), "bool", "survivor", "kept for the next population: carried into t+1 as it is (ABC-NS)"),
    _V("held", (_N, _M), "int8", "held by the bounds", "the particle's part in each model's new bound (ABC-NS, read "
       "with has_evidence; a model's bound is fitted to its particles and its same_model_as copies'): -1 not fitted "
       "to it, 0 outside the bound refitted without it, 1 held"),
    _V("epsilon", (), "float64", "tolerance", "the tolerance the population was accepted under", "{distance_units}",
       field="epsilon"),
    _V("epsilon_next", (), "float64", "next tolerance", "the tolerance chosen for the next population (NaN: none, as "
       "after rejection or at the end of an ABC-SMC schedule)", "{distance_units}", field="epsilon_next"),
    _V("acceptance_rate", (), "float64", "acceptance rate", "accepted / simulated in this population", "1",
       field="acceptance_rate", derived=True),
    _V("elapsed_s", (), "float64", "elapsed time", "wall time from the start of the run to the end of the population",
       "s", field="elapsed_s"),
    _V("n_accepted", (), "int64", "accepted simulations", "in this population", "1", field="n_accepted"),
    _V("n_simulations", (), "int64", "simulations", "in this population (failed ones included)", "1",
       field="n_simulations"),
    _V("n_failed", (), "int64", "failed simulations", "diverged or failed in this population (counted rejections)", "1",
       field="n_failed"),
    _V("n_redraws", (), "int64", "redraws", "proposals outside the prior box, drawn again without a simulation", "1",
       field="n_redraws"),
    _V("n_simulations_total", (), "int64", "simulations so far", "cumulative over the run, pilot included", "1",
       derived=True),
    _V("has_survivors", (), "bool", "has survivors", "False for the baselines (SMC, rejection)"),
    _V("has_ellipsoids", (), "bool", "has ellipsoids", "False for the baselines (SMC, rejection)"),
    _V("model_probability", (_M,), "float64", "model probability", "p(model | data) at this population", "1",
       field="model_probabilities"),
    _V("n_simulations_by_model", (_M,), "int64", "simulations per model", "n_simulations split by model (-1: not "
       "recorded)", "1", field="n_simulations_by_model"),
    _V("n_failed_by_model", (_M,), "int64", "failed simulations per model", "n_failed split by model: simulations that "
       "failed or diverged (counted rejections; -1: not recorded)", "1", field="n_failed_by_model"),
    _V("ellipsoid_centre", (_M, _E, _D), "float64", "ellipsoid centre", "c of the bounding ellipsoids {x : (x - c)^T "
       "M^-1 (x - c) <= 1} of each model (unused slots NaN), {frame}"),
    _V("ellipsoid_matrix", (_M, _E, _D, _DB), "float64", "ellipsoid matrix", "M in {x : (x - c)^T M^-1 (x - c) <= 1} "
       "(the scaled covariance, not its inverse), in the named columns, {frame}"),
    _V("ellipsoid_note", (_M, _E), "int8", "ellipsoid note", "codes of ellipsoid_note_codes; -1 none"),
    _V("has_evidence", (), "bool", "has evidence", "ABC-NS evidence bookkeeping present"),
    _V("has_floor", (), "bool", "has noise floor", "the run knows its distance's noise model (abcns.noise)"),
    _V("floor_best", (), "float64", "best distance", "the lowest distance any particle reached up to this population",
       "{distance_units}", field="floor.best"),
    _V("floor_noise_variance", (), "float64", "noise per sample", "one sample's noise variance in distance units (v)",
       "{distance_units}", field="floor.variance"),
    _V("noise_floor", (), "float64", "noise floor", "floor_best + p v: the distance expected at the true parameters",
       "{distance_units}", field="floor.floor", derived=True),
    _V("decision_tolerance", (), "float64", "decision tolerance", "noise_floor + sqrt(2 p) v: model probabilities are "
       "read at the lowest population tolerance at or above it", "{distance_units}", field="floor.decision", derived=True),
    _V("floor_model", (), "int64", "best model", "index along model of the model that reached floor_best (-1: no floor)",
       field="floor.model"),
    _V("floor_n_parameters", (), "int64", "parameters of the best model", "p, its number of free parameters", "1",
       field="floor.n_parameters"),
    _V("floor_method", (), "int64", "noise floor method", "0: v estimated as floor_best / (n - p); 1: v from the spec's "
       "data.noise_std", field="floor.method"),
    _V("floor_n_samples", (), "int64", "samples", "n, the samples the distance sums over", "1", field="floor.n_samples"),
    # the ABC-NS evidence bookkeeping: one per field of abcns.evidence.Evidence (checked below)
    _V("evidence_log_z", (_M,), "float64", "log ABC evidence", "log Z_m(eps_t), the prior mass of {d < eps_t} "
       "(-inf: dead)", field="evidence.log_z"),
    _V("evidence_log_z_se", (_M,), "float64", "standard error of log_z", "", field="evidence.log_z_se"),
    _V("evidence_log_z_next", (_M,), "float64", "predicted log ABC evidence", "log Z_m(eps_t+1), predicted from this "
       "population", field="evidence.log_z_next"),
    _V("evidence_log_z_next_se", (_M,), "float64", "standard error of log_z_next", "", field="evidence.log_z_next_se"),
    _V("evidence_log_volume", (_M,), "float64", "log bound volume", "log prior mass of the bound proposing model m at "
       "t+1 (NaN: none)", field="evidence.log_volume"),
    _V("evidence_log_volume_se", (_M,), "float64", "standard error of log_volume", "", field="evidence.log_volume_se"),
    _V("evidence_allocation", (_M,), "float64", "proposal share", "probability that a proposal of population t+1 is of "
       "model m", "1", field="evidence.allocation"),
    _V("evidence_n_proposed", (_M,), "int64", "proposals", "model m's new proposals simulated in this population", "1",
       field="evidence.n_proposed"),
    _V("evidence_n_accepted", (_M,), "int64", "accepted proposals", "model m's new proposals accepted in this "
       "population", "1", field="evidence.n_accepted"),
    _V("evidence_death", (_M,), "int64", "death code", "why model m has no particles from t+1 on: 0 alive, 1 no "
       "particles, 2 improbable, 3 dead before, 4 every simulation failed", field="evidence.death"),
    # the static coordinates (zarr's default fill: nothing is left unwritten)
    _V("model", (_M,), "str", "model", "the candidate models' names", grows=False),
    _V("parameter", (_D,), "str", "parameter", "the free parameters of all models, by name", grows=False),
    _V("parameter_b", (_DB,), "str", "parameter", "second parameter axis of ellipsoid_matrix", grows=False),
    _V("model_has_parameter", (_M, _D), "bool", "model has parameter", "whether the model infers that parameter",
       grows=False),
    _V("prior_low", (_M, _D), "float64", "prior low", "the low end of the model's uniform prior on the parameter (NaN: "
       "none)", grows=False),
    _V("prior_width", (_M, _D), "float64", "prior width", "high - low of the model's uniform prior on the parameter "
       "(NaN: none)", grows=False),
)
del _V
# the groups of a Population stored field by field (None in the Population: has_<name> False)
PARTS = {"evidence": Evidence, "floor": Floor}
_EVIDENCE_ARRAYS = {f"evidence_{name}": dtype for name, dtype in
                    [(n, "float64") for n in Evidence.FLOATS] + [(n, "int64") for n in Evidence.INTS]}
assert {v.name: v.dtype for v in SCHEMA if v.name.startswith("evidence_")} == _EVIDENCE_ARRAYS, \
    "one array per field of abcns.evidence.Evidence, of its dtype"
# the per-model counters of a Population: empty there when not recorded (-1 in the store)
BY_MODEL = ("n_simulations_by_model", "n_failed_by_model")
# the arrays a Population is read back from
POPULATION_ARRAYS = tuple(v.name for v in SCHEMA if v.grows and not v.derived)
GROWING = frozenset(v.name for v in SCHEMA if v.grows)

# what {frame} says in the descriptions of ellipsoid_centre and ellipsoid_matrix
_FRAME_TEXT = {
    "unit prior box": "with x in the model's unit prior box: x = (theta - prior_low) / prior_width",
    "parameters": "with x = theta, in the parameters' own units",
    None: "(none: this algorithm stores no ellipsoids)",
}


def ellipsoid_frame(spec: Mapping[str, Any], algorithm: str) -> str | None:
    """The frame ABC-NS fits its bounds in (:data:`FRAMES`): the unit prior box in the
    evidence variant, the parameters in the paper variant; None for the baselines."""
    if algorithm != "abc-ns":
        return None
    sampler = spec.get("sampler") or {}
    return "parameters" if sampler.get("variant") == "paper" else "unit prior box"


def _priors(spec: Mapping[str, Any], model_names: Sequence[str], union: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """(prior_low, prior_width) (model, parameter) from the spec's models (NaN where none)."""
    low = np.full((len(model_names), len(union)), np.nan)
    width = np.full_like(low, np.nan)
    described = {m.get("name"): m for m in spec.get("models") or () if isinstance(m, Mapping)}
    for i, name in enumerate(model_names):
        for key, bounds in ((described.get(name) or {}).get("priors") or {}).items():
            if key in union:
                low[i, union.index(key)] = float(bounds[0])
                width[i, union.index(key)] = float(bounds[1]) - float(bounds[0])
    return low, width


def _log_text(spec: Mapping[str, Any]) -> str:
    """What the frame's text adds for the parameters with a log-uniform prior (none: nothing)."""
    logs = [f"{m.get('name')}.{key}" for m in spec.get("models") or () if isinstance(m, Mapping)
            for key, bounds in (m.get("priors") or {}).items() if Uniform.parse(bounds).log]
    if not logs:
        return ""
    return (f"; for {', '.join(logs)} (log-uniform priors) log theta in place of theta, and log(prior_low) and "
            "log(1 + prior_width / prior_low) in place of prior_low and prior_width")


def _distance_units(spec: Mapping[str, Any]) -> str:
    distance = spec.get("distance", "nmse")
    name = distance.get("name", "nmse") if isinstance(distance, Mapping) else distance
    return "%" if name == "nmse" else "1"


def parameter_union(parameter_names: Sequence[Sequence[str]]) -> list[str]:
    """Every model's parameter names, each once, in first-seen order."""
    return list(dict.fromkeys(name for names in parameter_names for name in names))


def create_arrays(group: zarr.Group, spec: Mapping[str, Any], frame: str | None, model_names: list[str],
                  parameter_names: list[list[str]], n_particles: int, max_ellipsoids: int) -> None:
    """Every array of :data:`SCHEMA` in a new store: the static ones written, the growing
    ones empty along population, each with its attributes (one metadata write each)."""
    union = parameter_union(parameter_names)
    sizes = {_N: n_particles, _M: len(model_names), _E: max_ellipsoids, _D: len(union), _DB: len(union)}
    units = _distance_units(spec)
    prior_low, prior_width = _priors(spec, model_names, union)
    frame_text = _FRAME_TEXT[frame] + (_log_text(spec) if frame else "")

    def meta(v: Variable) -> dict[str, Any]:
        out = {"long_name": v.long_name, "description": v.description.replace("{frame}", frame_text) or v.long_name}
        if v.units is not None:
            out["units"] = v.units.format(distance_units=units)
        if v.name == "model_index":
            out["flag_meanings"] = " ".join(model_names)  # CF: index i is model_names[i]
        return out

    static = {
        "model": np.array(model_names, dtype=str),
        "parameter": np.array(union, dtype=str),
        "parameter_b": np.array(union, dtype=str),
        "model_has_parameter": np.array([[u in p for u in union] for p in parameter_names]),
        "prior_low": prior_low,
        "prior_width": prior_width,
    }
    for v in SCHEMA:
        if not v.grows:
            values = static[v.name]
            arr = group.create_array(v.name, shape=values.shape, dtype=str if v.dtype == "str" else v.dtype,
                                     dimension_names=list(v.dims), attributes=meta(v))
            arr[...] = values
            continue
        tail = tuple(sizes[dim] for dim in v.dims)
        # rows per chunk along population: a chunk of ~64 KiB at most (one population of
        # theta, 256 of a scalar), so an append of several populations writes few files
        rows = int(np.clip(CHUNK_BYTES // (np.dtype(v.dtype).itemsize * math.prod(tail)), 1, 256))
        group.create_array(v.name, shape=(0, *tail), chunks=(rows, *tail), dtype=v.dtype, fill_value=v.fill_value,
                           dimension_names=[_P, *v.dims], attributes=meta(v))
