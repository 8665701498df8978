"""The result store: one zarr 3 directory per job, appended population by population.

Layout: every array is declared once, in :data:`SCHEMA` (name, dimensions, dtype, fill,
``long_name``, ``description``, units); :meth:`Store.create`, the rows an append writes and
the records read back are derived from it. Every array but the static coordinates grows along
``population``, in chunks of at most ~64 KiB (one population of a large particle array, up to
256 of a scalar):

- particle level (population, particle[, parameter]): ``model_index`` (an index along
  ``model``), ``theta`` with one column per parameter *name* (NaN where the particle's model
  has no such parameter), ``distance``, ``weight``, ``survivor``;
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
``ds.to_netcdf()`` works);
:attr:`Store.attrs` decodes them. An append (of one population or several consecutive ones)
resizes and writes every array first, then rewrites the consolidated metadata (the arrays'
new shapes) and bumps the counter last: a reader that trusts the counter never sees half a
population, a reader of the consolidated metadata (plain ``xarray.open_zarr``) sees only
whole populations, and rows a crash left beyond the counter are ignored and overwritten by
the next append. zarr's local store writes each file atomically (temporary file, then
rename).

Written for one writer of populations (the job's runner) and any number of readers, in any
process: every call re-reads the metadata from disk, so a ``Store`` object never goes stale.
Attribute updates (counter, status) are read-modify-writes of the group metadata done under
an exclusive ``flock`` on the store's directory (POSIX), so a status set by the scheduler
while the runner appends is not lost; each is one write of the metadata file (zarr's
``attrs.update`` writes it once per key), so a process killed in a status change leaves
the old attributes or the new ones, never a status without its stop reason.
"""

from __future__ import annotations

import asyncio
import datetime
import fcntl
import functools
import hashlib
import importlib.metadata
import json
import math
import os
import platform
import subprocess
import threading
import time
import uuid
import warnings
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
import scipy
import xarray as xr
import zarr
import zarr.api.asynchronous
import zarr.storage
from zarr.core.sync import sync

import abcns
from abcns.ellipsoid import Ellipsoid, from_matrix
from abcns.evidence import Evidence
from abcns.noise import Floor
from abcns.priors import Model
from abcns.result import Population, Result
from abcns.settings import StopReason

FORMAT_VERSION = 4  # 4: the noise floor per population (floor_*), simulations and failures per model
CHUNK_BYTES = 64 * 1024
# zarr writes each metadata file through a temporary "zarr.<uuid>.partial" next to it; a
# reader listing the group (xarray.open_zarr in Store.dataset) while the writer updates the
# attributes meets that file and warns. Ignored there only, not process-wide.
PARTIAL_WARNING = r"Object at zarr\.[0-9a-f]+\.partial is not recognized as a component of a Zarr hierarchy"
STATUSES = ("running", "finished", "failed", "cancelled")
NOTE_CODES = {"": 0, "repaired": 1, "fallback": 2, "box": 3}  # -1: no ellipsoid (dead model)
_NOTES = {code: note for note, code in NOTE_CODES.items()}
_RESERVED = frozenset({
    "format_version", "spec", "seed", "versions", "data_hash", "algorithm", "model_names",
    "parameter_names", "n_particles", "status", "stop_reason", "n_populations", "ellipsoid_note_codes",
    "created_at", "updated_at", "max_ellipsoids", "ellipsoid_frame",
})
#: the group attribute ``ellipsoid_frame``: the coordinates ellipsoid_centre and _matrix are in
FRAMES = ("unit prior box", "parameters")

_P, _N, _D, _DB, _M, _E = "population", "particle", "parameter", "parameter_b", "model", "ellipsoid"


@dataclass(frozen=True)
class Variable:
    """One array of the store, declared once: everything else (the arrays :meth:`Store.create`
    makes, the row :meth:`Store._rows` writes, what :meth:`Store._population` reads back, the
    attributes xarray shows) is derived from :data:`SCHEMA`.

    ``dims`` follow ``population`` for the arrays that grow (``grows``; the static coordinates
    have their own); ``fill`` is what an unwritten element reads as (NaN, -1 or False by
    dtype unless given). ``units`` may say ``{distance_units}`` (filled from the spec's
    distance: ``%`` for the NMSE of Eq. 7), ``description`` ``{frame}`` (:data:`FRAMES`).
    ``field`` is the :class:`abcns.Population` attribute the array holds as it is (``"floor.best"``:
    the attribute ``best`` of ``pop.floor``; fill where that is None); None: built by its own
    code in ``_rows`` and ``_population``. ``derived``: written for readers only, not read back
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
    _V("evidence_coverage", (_M,), "float64", "bound coverage", "share of the accepted region the bound holds", "1",
       field="evidence.coverage"),
    _V("evidence_allocation", (_M,), "float64", "proposal share", "probability that a proposal of population t+1 is of "
       "model m", "1", field="evidence.allocation"),
    _V("evidence_n_coverage", (_M,), "int64", "coverage points", "points the coverage was measured on", "1",
       field="evidence.n_coverage"),
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
_PARTS = {"evidence": Evidence, "floor": Floor}
_EVIDENCE_ARRAYS = {f"evidence_{name}": dtype for name, dtype in
                    [(n, "float64") for n in Evidence.FLOATS] + [(n, "int64") for n in Evidence.INTS]}
assert {v.name: v.dtype for v in SCHEMA if v.name.startswith("evidence_")} == _EVIDENCE_ARRAYS, \
    "one array per field of abcns.evidence.Evidence, of its dtype"
# the per-model counters of a Population: empty there when not recorded (-1 in the store)
_BY_MODEL = ("n_simulations_by_model", "n_failed_by_model")
# the arrays a Population is read back from
_POPULATION_ARRAYS = tuple(v.name for v in SCHEMA if v.grows and not v.derived)
_GROWING = frozenset(v.name for v in SCHEMA if v.grows)


class StoreError(Exception):
    """A path that is not a usable result store (missing, not a store, other format, exists)."""


class StoreNotFound(StoreError, FileNotFoundError):
    """No result store at the path."""


class StoreIncomplete(StoreError):
    """A zarr group whose creation did not finish (no ``format_version``, which
    :meth:`Store.create` writes last): the process died while creating it; nothing in it
    was ever part of a store."""


def data_hash(*arrays: Any) -> str:
    """``"sha256:<hex>"`` over each array's dtype, shape and bytes (C order), in order."""
    h = hashlib.sha256()
    h.update(f"{len(arrays)} arrays;".encode())
    for a in arrays:
        a = np.ascontiguousarray(a)
        if a.dtype.hasobject:
            raise TypeError("data_hash needs numeric arrays, got dtype object")
        h.update(f"{a.dtype.str}{a.shape};".encode())
        h.update(a.tobytes())
    return "sha256:" + h.hexdigest()


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def _jsonable(value: Any, what: str) -> Any:
    """``value`` as plain JSON types (round-tripped), or a StoreError naming ``what``."""
    try:
        return json.loads(json.dumps(value, allow_nan=False))
    except (TypeError, ValueError) as err:
        raise StoreError(f"{what} must be JSON-able (finite numbers, str, list, dict): {err}") from None


def _git_commit() -> str | None:
    """The commit of the checkout abcns runs from (an editable install), else None."""
    root = Path(abcns.__file__).resolve().parent.parent
    if not (root / ".git").exists():
        return None
    try:
        out = subprocess.run(["git", "-C", str(root), "describe", "--always", "--dirty", "--abbrev=12"],  # noqa: S603, S607 - no shell, fixed arguments
                             capture_output=True, text=True, timeout=5, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def _versions() -> dict[str, str]:
    return dict(_versions_once())


@functools.cache
def _versions_once() -> dict[str, str]:
    """The versions of the code this process runs, found once (the commit asks ``git``: ~10 ms)."""
    versions = {
        "abcns": abcns.__version__, "numpy": np.__version__, "scipy": scipy.__version__,
        "zarr": zarr.__version__, "xarray": xr.__version__, "python": platform.python_version(),
    }
    for dist in ("numba", "dask", "distributed"):
        try:
            versions[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            pass
    commit = _git_commit()
    if commit:
        versions["git"] = commit
    return versions


JSON_PREFIX = "json:"


def _encode_attrs(update: Mapping[str, Any]) -> dict[str, Any]:
    """Attributes as netCDF can hold them: strings and numbers as they are, anything else
    (dicts, lists, None, booleans) as JSON text marked by the prefix ``json:`` (as is a
    string that starts with it)."""
    out: dict[str, Any] = {}
    for key, value in update.items():
        plain = isinstance(value, (int, float)) and not isinstance(value, bool)
        if plain or (isinstance(value, str) and not value.startswith(JSON_PREFIX)):
            out[key] = value
        else:
            out[key] = JSON_PREFIX + json.dumps(value, allow_nan=False)
    return out


def _decode_attrs(attrs: Mapping[str, Any]) -> dict[str, Any]:
    return {key: json.loads(value[len(JSON_PREFIX):]) if isinstance(value, str) and value.startswith(JSON_PREFIX)
            else value for key, value in attrs.items()}


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


def _distance_units(spec: Mapping[str, Any]) -> str:
    distance = spec.get("distance", "nmse")
    name = distance.get("name", "nmse") if isinstance(distance, Mapping) else distance
    return "%" if name == "nmse" else "1"


class Store:
    """One job's result store. Build with :meth:`create` or :meth:`open`."""

    def __init__(self, path: Path, attrs: Mapping[str, Any]):
        self.path = path
        self._n_models = len(attrs["model_names"])
        self._dims = [len(p) for p in attrs["parameter_names"]]
        self._d_max = max(self._dims)
        union = _union(attrs["parameter_names"])
        self._d_union = len(union)
        self._columns = [np.array([union.index(n) for n in names]) for names in attrs["parameter_names"]]
        self._n_particles = int(attrs["n_particles"])
        self._n_ellipsoids = int(attrs.get("max_ellipsoids", 1))

    # ------------------------------------------------------------------ creation, opening

    @classmethod
    def create(
        cls,
        path: str | Path,
        *,
        spec: Mapping[str, Any],
        seed: int,
        model_names: list[str],
        parameter_names: list[list[str]],
        n_particles: int,
        data_hash: str,
        algorithm: str,
        max_ellipsoids: int = 1,
        job_key: str | None = None,
    ) -> Store:
        """A new, empty store at ``path`` (status "running", and the runner's ``job_key``
        when given); refuses an existing non-empty path."""
        path = Path(path)
        model_names, parameter_names = list(model_names), [list(p) for p in parameter_names]
        _check_new(path, model_names, parameter_names, n_particles, max_ellipsoids)
        if hasattr(spec, "model_dump"):  # a pydantic JobSpec
            spec = spec.model_dump(mode="json")
        spec = _jsonable(dict(spec), "spec")  # checked before anything is written
        union = _union(parameter_names)
        n, k = int(n_particles), int(max_ellipsoids)
        # made in memory, then written out in one go: zarr costs ~2 ms of its I/O thread per
        # array on disk, and a job's workers wait for the store before population 1 starts
        files: dict[str, Any] = {}
        group = zarr.open_group(zarr.storage.MemoryStore(files), mode="w-", zarr_format=3)
        frame = ellipsoid_frame(spec, str(algorithm))
        _create_arrays(group, spec, frame, model_names, parameter_names, union,
                       {_N: n, _M: len(model_names), _E: k, _D: len(union), _DB: len(union)})
        attrs = {
            "spec": spec,
            "seed": int(seed),
            "versions": _versions(),
            "data_hash": str(data_hash),
            "algorithm": str(algorithm),
            "model_names": model_names,
            "parameter_names": parameter_names,
            "n_particles": n,
            "max_ellipsoids": k,
            "ellipsoid_note_codes": NOTE_CODES,
            "ellipsoid_frame": frame,
            "status": "running",
            "stop_reason": None,
            "created_at": _now(),
            "updated_at": _now(),
            "n_populations": 0,
            **({"job_key": str(job_key)} if job_key is not None else {}),
        }
        group.update_attributes(_encode_attrs(attrs))
        # the group first (a store whose creation was cut is then "incomplete", not "no
        # store"), the arrays, and last the format version with the consolidated metadata: it
        # marks a complete store
        path.mkdir(parents=True, exist_ok=True)
        _replace(path / "zarr.json", files.pop("zarr.json").to_bytes())
        for key, data in files.items():
            file = path / key
            file.parent.mkdir(parents=True, exist_ok=True)
            file.write_bytes(data.to_bytes())
        _rewrite_group(path, {"format_version": FORMAT_VERSION}, consolidate=True)
        return cls(path, attrs)

    @classmethod
    def open(cls, path: str | Path) -> Store:
        """An existing store; StoreError if missing, not a store, or another format version."""
        path = Path(path)
        attrs = _read_attrs(path)
        return cls(path, attrs)

    def __repr__(self) -> str:
        return f"Store({str(self.path)!r}, n_populations={self.n_populations})"

    # ------------------------------------------------------------------ attributes

    def _group(self, mode: Literal["r", "r+"] = "r") -> zarr.Group:
        return _group(self.path, mode)

    @property
    def attrs(self) -> dict:
        """Every group attribute, read fresh from disk."""
        return _read_attrs(self.path)

    @property
    def n_populations(self) -> int:
        """Populations complete (the counter; rows beyond it are not part of the store)."""
        return int(self.attrs["n_populations"])

    def set_status(self, status: str, stop_reason: Any = None, **extra: Any) -> None:
        """Record the job's status (running | finished | failed | cancelled), its stop
        reason (a StopReason or str) and any JSON-able run information (``n_simulations``,
        ``n_pilot_simulations``, ``epsilon_initial_source``, ``wall_time_s``, ``notes``, ...)."""
        if status not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}, got {status!r}")
        clash = sorted(_RESERVED & set(extra))
        if clash:
            raise ValueError(f"set_status cannot set the reserved attributes {clash}")
        reason = getattr(stop_reason, "value", stop_reason)
        update = _jsonable({"status": status, "stop_reason": None if reason is None else str(reason), **extra},
                           "run information")
        update["updated_at"] = _now()
        self._update_attrs(update)

    # ------------------------------------------------------------------ writing

    def append(self, pop: Population, *, n_simulations_total: int) -> None:
        """Write population ``pop`` (its t must be n_populations + 1), then bump the counter."""
        self.append_many([(pop, n_simulations_total)])

    def append_many(self, pops: Sequence[tuple[Population, int]]) -> None:
        """Write consecutive populations, each with its cumulative simulation count, then bump
        the counter once: one resize per array whatever their number (a zarr operation costs
        about a millisecond per array, so a fast job's appends are coalesced)."""
        if not pops:
            return
        n = self.n_populations
        for i, (pop, _) in enumerate(pops):
            if pop.t != n + 1 + i:
                raise StoreError(f"population {pop.t} cannot follow population {n + i} in {self.path}")
        rows = [self._rows(pop, int(total)) for pop, total in pops]  # all validated before any write
        stacked = {name: np.stack([np.asarray(r[name]) for r in rows]) for name in rows[0]}
        # every array resized first (the population dimension disagrees between arrays only
        # during this step), to exactly n + k rows (rows a crash left are overwritten), then
        # every row written; each step is one concurrent batch of zarr operations
        sync(self._write_rows(stacked, n))
        self._commit(n + len(pops))

    async def _write_rows(self, rows: dict[str, np.ndarray], n: int) -> None:
        k = len(rows["population"])
        _, arrays = await self._arrays("r+", list(rows))
        await asyncio.gather(*(arr.resize((n + k, *arr.shape[1:])) for arr in arrays))
        await asyncio.gather(*(arr.setitem(slice(n, n + k), value) for arr, value in zip(arrays, rows.values(), strict=True)))

    def _commit(self, n_populations: int) -> None:
        """Consolidate the metadata (the arrays' new shapes), then bump the counter: the
        population is part of the store from here on."""
        self._update_attrs({"n_populations": n_populations, "updated_at": _now()}, consolidate=True)

    def _update_attrs(self, update: dict[str, Any], consolidate: bool = False) -> None:
        """Read-modify-write of the group attributes under an exclusive lock, so a status
        change from another process and a counter bump cannot overwrite each other (nor the
        consolidated metadata, which lives in the same file and is kept by an update).

        One write of the group's metadata for the whole update: zarr's ``attrs.update``
        writes it once per key, and a process killed between two of those writes left a
        store "finished" with no stop reason and the run information of its first
        population (CI's chaos run; the resumed job then ended "cancelled")."""
        fd = os.open(self.path, os.O_RDONLY)  # flock(2) on the store's directory: no extra file in the hierarchy
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            _rewrite_group(self.path, _encode_attrs(update), consolidate)
        finally:
            os.close(fd)  # releases the lock

    def _rows(self, pop: Population, n_simulations_total: int) -> dict[str, Any]:
        """The new row of every growing array (validated before anything is written)."""
        n, m, d, du = self._n_particles, self._n_models, self._d_max, self._d_union
        if np.shape(pop.theta) != (n, d):
            raise StoreError(f"population {pop.t}: theta has shape {np.shape(pop.theta)}, the store expects {(n, d)}")
        if pop.survivors is not None and np.shape(pop.survivors) != (n,):
            raise StoreError(f"population {pop.t}: survivors has shape {np.shape(pop.survivors)}, expected ({n},)")
        if pop.ellipsoids and len(pop.ellipsoids) != m:
            raise StoreError(f"population {pop.t}: {len(pop.ellipsoids)} bounds for {m} models")
        sizes = {_N: n, _M: m}
        row: dict[str, Any] = {}
        for v in SCHEMA:
            if v.field is None:
                continue
            part, _, name = v.field.rpartition(".")
            owner = getattr(pop, part) if part else pop
            shape = tuple(sizes[dim] for dim in v.dims)
            value = np.full(shape, v.fill_value) if owner is None else np.asarray(getattr(owner, name))
            if v.name in _BY_MODEL and value.shape == (0,):  # not recorded
                value = np.full(shape, -1)
            if value.shape != shape:
                raise StoreError(f"population {pop.t}: {v.field} has shape {value.shape}, the store expects {shape}")
            row[v.name] = value.astype(v.dtype)
        kmax = self._n_ellipsoids
        centre = np.full((m, kmax, du), np.nan)
        matrix = np.full((m, kmax, du, du), np.nan)
        note = np.full((m, kmax), -1, dtype=np.int8)
        for i, bound in enumerate(pop.ellipsoids):
            if len(bound) > kmax:
                raise StoreError(f"population {pop.t}: {len(bound)} ellipsoids for model {i}; the store holds {kmax}")
            k = self._dims[i]
            for j, e in enumerate(bound):
                if e.centre.shape != (k,) or e.matrix.shape != (k, k):
                    raise StoreError(f"population {pop.t}: ellipsoid of model {i} has dimension {e.n_dim}, expected {k}")
                if e.note not in NOTE_CODES:
                    raise StoreError(f"population {pop.t}: unknown ellipsoid note {e.note!r}")
                cols = self._columns[i]
                centre[i, j, cols], note[i, j] = e.centre, NOTE_CODES[e.note]
                matrix[i, j, cols[:, None], cols[None, :]] = e.matrix
        row |= {
            "theta": self._to_named(np.asarray(pop.models), np.asarray(pop.theta, dtype=np.float64)),
            "survivor": np.zeros(n, bool) if pop.survivors is None else np.asarray(pop.survivors, dtype=bool),
            "n_simulations_total": n_simulations_total,
            "has_survivors": pop.survivors is not None,
            "has_ellipsoids": bool(pop.ellipsoids),
            "ellipsoid_centre": centre,
            "ellipsoid_matrix": matrix,
            "ellipsoid_note": note,
            **{f"has_{part}": getattr(pop, part) is not None for part in _PARTS},
        }
        row["population"] = row.pop("population")  # last: xarray's index shows t only once the row is written
        assert set(row) == _GROWING, "every growing array has its row"
        return row

    # ------------------------------------------------------------------ named columns

    def _to_named(self, models: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """(n, widest model) in each model's own order -> (n, all parameter names)."""
        out = np.full((theta.shape[0], self._d_union), np.nan)
        for i, cols in enumerate(self._columns):
            rows = np.flatnonzero(models == i)
            out[np.ix_(rows, cols)] = theta[rows, : len(cols)]
        return out

    def _from_named(self, models: np.ndarray, named: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`_to_named` (NaN padding to the widest model)."""
        out = np.full((named.shape[0], self._d_max), np.nan)
        for i, cols in enumerate(self._columns):
            rows = np.flatnonzero(models == i)
            out[rows, : len(cols)] = named[np.ix_(rows, cols)]
        return out

    # ------------------------------------------------------------------ reading

    def _read(self, rows: slice, names: Sequence[str] = _POPULATION_ARRAYS) -> dict[str, np.ndarray]:
        """``rows`` of the arrays ``names`` (those the store has), read as one concurrent batch
        of zarr operations (one after another, each waits ~1 ms for zarr's I/O thread)."""
        return sync(self._read_rows(rows, names))

    async def _read_rows(self, rows: slice, names: Sequence[str]) -> dict[str, np.ndarray]:
        names, arrays = await self._arrays("r", names, present_only=True)
        values = await asyncio.gather(*(arr.getitem(rows) for arr in arrays))
        return {name: np.asarray(value) for name, value in zip(names, values, strict=True)}

    async def _arrays(self, mode: Literal["r", "r+"], names: Sequence[str],
                      present_only: bool = False) -> tuple[list[str], list[zarr.AsyncArray[Any]]]:
        """The store's arrays ``names`` (with ``present_only``, those of them it has), opened
        together: (their names, the arrays)."""
        group = await zarr.api.asynchronous.open_group(store=str(self.path), mode=mode, zarr_format=3)
        if present_only:
            present = {name async for name in group.array_keys()}
            names = [name for name in names if name in present]
        members = await asyncio.gather(*(group.getitem(name) for name in names))
        return list(names), cast(list[zarr.AsyncArray[Any]], members)  # a store's group holds arrays only

    def _population(self, a: dict[str, np.ndarray], i: int) -> Population:
        fields: dict[str, Any] = {}
        parts: dict[str, dict[str, Any]] = {part: {} for part in _PARTS}
        for v in SCHEMA:
            if v.field is None or v.derived or v.name not in a:
                continue
            value = a[v.name][i]
            if v.name in _BY_MODEL and not np.all(value >= 0):  # not recorded
                continue
            value = value.copy() if v.dims else int(value) if np.dtype(v.dtype).kind == "i" else float(value)
            part, _, name = v.field.rpartition(".")
            (parts[part] if part else fields)[name] = value
        ellipsoids: tuple[tuple[Ellipsoid, ...], ...] = ()
        if a["has_ellipsoids"][i]:
            bounds = []
            for j, cols in enumerate(self._columns):
                codes = a["ellipsoid_note"][i, j]
                bounds.append(tuple(
                    from_matrix(np.ascontiguousarray(a["ellipsoid_centre"][i, j, e, cols]),
                                np.ascontiguousarray(a["ellipsoid_matrix"][i, j, e][np.ix_(cols, cols)]),
                                _NOTES[int(codes[e])])
                    for e in range(codes.shape[0]) if codes[e] >= 0
                ))
            ellipsoids = tuple(bounds)
        optional: dict[str, Any] = {part: cls(**parts[part]) if a[f"has_{part}"][i] else None
                                    for part, cls in _PARTS.items()}
        return Population(
            **fields,
            theta=self._from_named(a["model_index"][i], a["theta"][i]),
            survivors=a["survivor"][i].copy() if a["has_survivors"][i] else None,
            ellipsoids=ellipsoids,
            **optional,
        )

    def populations(self) -> list[Population]:
        """Every complete population, exactly as appended (ellipsoids rebuilt by from_matrix)."""
        return self._records(self.n_populations)[0]

    def _records(self, n: int, names: Sequence[str] = _POPULATION_ARRAYS) -> tuple[list[Population], dict[str, np.ndarray]]:
        """The first ``n`` populations, and the arrays ``names`` they were read from."""
        if n == 0:
            return [], {}
        a = self._read(slice(0, n), names)
        return [self._population(a, i) for i in range(n)], a

    def population(self, t: int) -> Population:
        """Population ``t`` (1-based)."""
        n = self.n_populations
        if not 1 <= t <= n:
            raise IndexError(f"population {t} is not in {self.path} (it holds populations 1..{n})")
        a = self._read(slice(t - 1, t))
        return self._population(a, 0)

    def page(self, t: int, rows: slice) -> dict[str, Any]:
        """Particles ``rows`` of population ``t`` (1-based) and its scalars, read alone (one
        page never reads the whole population); theta in each model's own parameter order."""
        n = self.n_populations
        if not 1 <= t <= n:
            raise IndexError(f"population {t} is not in {self.path} (it holds populations 1..{n})")
        group = self._group("r")
        out: dict[str, Any] = {k: _values(group, k, t - 1).item()
                               for k in ("epsilon", "epsilon_next", "n_accepted", "n_simulations")}
        out |= {k: _values(group, k, (t - 1, rows)) for k in ("model_index", "theta", "distance", "weight")}
        out["theta"] = self._from_named(out["model_index"], out["theta"])
        out["model_probability"] = _values(group, "model_probability", t - 1)
        return out

    def dataset(self, retries: int = 20) -> xr.Dataset:
        """The store as an xarray Dataset (lazy), cut to the complete populations.

        ``xarray.open_zarr(path, consolidated=False)`` reads the store directly; this also
        hides a row being written (or left by a crash) and retries while an append is
        resizing the arrays."""
        for attempt in range(retries + 1):
            n = self.n_populations  # before the data: rows below the counter are complete
            try:
                with _ignoring(PARTIAL_WARNING):
                    ds = xr.open_zarr(str(self.path), consolidated=False)
                return ds.isel(population=slice(0, n))
            except ValueError:  # conflicting sizes of "population" during a resize
                if attempt == retries:
                    raise
                time.sleep(0.05)
        raise AssertionError("unreachable")

    def model(self, name: str) -> xr.Dataset:
        """One model's part of the store (:func:`model_view` of :meth:`dataset`):
        ``store.model("cubic").theta`` holds model cubic's particles, with its parameters."""
        return model_view(self.dataset(), name)

    def totals(self) -> np.ndarray:
        """``n_simulations_total`` of the complete populations (zarr only: no xarray, whose
        first use imports dask.array, which two threads importing at once can find half made)."""
        return _values(self._group("r"), "n_simulations_total", slice(None, self.n_populations))

    def run_state(self) -> dict[str, Any]:
        """What a resume needs: the counters after the last complete population."""
        n = self.n_populations
        if n == 0:
            return {"n_populations": 0, "t": 0, "n_simulations_total": 0, "elapsed_s": 0.0}
        group = self._group("r")
        return {
            "n_populations": n,
            "t": int(_values(group, "population", n - 1)),
            "n_simulations_total": int(_values(group, "n_simulations_total", n - 1)),
            "elapsed_s": float(_values(group, "elapsed_s", n - 1)),
        }


def _group(path: Path, mode: Literal["r", "r+"] = "r") -> zarr.Group:
    return zarr.open_group(str(path), mode=mode, zarr_format=3)


def _values(group: zarr.Group, name: str, selection: int | slice | tuple[int, slice]) -> np.ndarray:
    """``group[name][selection]`` as a numpy array (a store's group holds arrays only)."""
    return np.asarray(cast(zarr.Array, group[name])[selection])


_WARNING_FILTERS = threading.Lock()


@contextmanager
def _ignoring(message: str) -> Iterator[None]:
    """Ignore one zarr warning for the duration. The warning filters are process-wide before
    Python 3.14 (and zarr warns from its own I/O thread, so the scope covers that thread), and
    ``catch_warnings`` restores the list it saw on entry: two overlapping scopes in two threads
    (two readers' Store.dataset) would drop each other's filter, hence one scope at a time in
    this process. Only readers need it: writing a store warns of nothing (:func:`_rewrite_group`)."""
    with _WARNING_FILTERS, warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=message, category=zarr.errors.ZarrUserWarning)
        yield


def _rewrite_group(path: Path, attributes: Mapping[str, Any], consolidate: bool) -> None:
    """One write of the group's metadata (its ``zarr.json``): ``attributes`` merged into its
    attributes and, with ``consolidate``, the consolidated metadata made again.

    Consolidated metadata is every array's metadata (their shapes included) in the group's
    own ``zarr.json``, as ``zarr.consolidate_metadata`` writes it: ``{"kind": "inline",
    "must_understand": false, "metadata": {name: the array's zarr.json}}``. Written here with
    the attributes in one go, it costs ~2 ms instead of zarr's ~20 (a group opened, every
    member listed and parsed, then the group written again for the attributes), and it is
    free of zarr's note that zarr 3 has not standardised it (a warning that only a
    process-wide filter could hide, while another thread's scope of ``catch_warnings``
    might drop it). The file is replaced as zarr replaces its own: a temporary
    ``zarr.<uuid>.partial`` beside it, renamed over it."""
    meta = path / "zarr.json"
    doc = json.loads(meta.read_bytes())
    doc["attributes"] = {**doc.get("attributes", {}), **attributes}
    if consolidate:
        members = {child.name: json.loads((child / "zarr.json").read_bytes())
                   for child in sorted(path.iterdir()) if (child / "zarr.json").is_file()}
        doc["consolidated_metadata"] = {"kind": "inline", "must_understand": False, "metadata": members}
    _replace(meta, json.dumps(doc, indent=2, allow_nan=True).encode())


def _replace(file: Path, data: bytes) -> None:
    """``file`` now holds ``data``, written atomically as zarr writes its own files: a
    temporary ``<stem>.<uuid>.partial`` beside it, renamed over it."""
    partial = file.with_suffix(f".{uuid.uuid4().hex}.partial")
    try:
        partial.write_bytes(data)
        partial.replace(file)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


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


def _read_attrs(path: Path) -> dict:
    """The group's attributes, decoded, from its ``zarr.json`` read as JSON: zarr's
    ``open_group`` also parses the consolidated metadata of every array (~5 ms a call, on
    every append and every status request)."""
    if not path.exists():
        raise StoreNotFound(f"no result store at {path}: the path does not exist")
    try:
        doc = json.loads((path / "zarr.json").read_bytes())
        if not isinstance(doc, dict) or doc.get("zarr_format") != 3 or doc.get("node_type") != "group":
            raise ValueError("zarr.json is not a zarr 3 group's metadata")
        attributes = doc.get("attributes", {})
    except (OSError, ValueError) as err:
        raise StoreError(f"{path} is not a result store (no zarr 3 group: {err})") from None
    attrs = _decode_attrs(attributes)
    version = attrs.get("format_version")
    if version is None:
        raise StoreIncomplete(f"{path} is not a result store (no format_version attribute: its creation did not finish)")
    if version != FORMAT_VERSION:
        raise StoreError(f"{path} has result-store format_version {version}; this abcns reads version {FORMAT_VERSION}")
    return dict(attrs)


def dataset_attrs(ds: xr.Dataset) -> dict[str, Any]:
    """The attributes of a dataset of the store's schema, decoded (as :attr:`Store.attrs`)."""
    return _decode_attrs(ds.attrs)


def dataset_populations(ds: xr.Dataset) -> list[Population]:
    """The populations a dataset of the store's schema holds (``Store.dataset()``,
    ``xarray.open_zarr`` of a store, or ``service.report.export.to_dataset``)."""
    reader = Store(Path(str(ds.encoding.get("source", "<dataset>"))), dataset_attrs(ds))
    arrays = {name: np.asarray(ds[name].values) for name in _POPULATION_ARRAYS if name in ds}
    return [reader._population(arrays, i) for i in range(ds.sizes["population"])]


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
    pops, a = store._records(int(attrs["n_populations"]), (*_POPULATION_ARRAYS, "n_simulations_total"))
    total, elapsed = (int(a["n_simulations_total"][-1]), float(a["elapsed_s"][-1])) if pops else (0, 0.0)
    return result_of(attrs, pops, total, elapsed)


def dataset_result(ds: xr.Dataset) -> Result:
    """The :class:`abcns.Result` a dataset of the store's schema holds (as :func:`result_from_store`)."""
    last = ds.isel(population=-1) if ds.sizes["population"] else None
    return result_of(dataset_attrs(ds), dataset_populations(ds),
                     0 if last is None else int(last["n_simulations_total"]), 0.0 if last is None else float(last["elapsed_s"]))


def _union(parameter_names: Sequence[Sequence[str]]) -> list[str]:
    """Every model's parameter names, each once, in first-seen order."""
    return list(dict.fromkeys(name for names in parameter_names for name in names))



def _check_new(path: Path, model_names: list[str], parameter_names: list[list[str]], n_particles: int,
               max_ellipsoids: int) -> None:
    """What :meth:`Store.create` refuses (StoreError): a non-empty path, or names and sizes
    that make no store."""
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise StoreError(f"{path} already exists and is not empty; refusing to overwrite it")
    if not model_names or len(parameter_names) != len(model_names):
        raise StoreError(f"need one list of parameter names per model: {len(model_names)} models, "
                         f"{len(parameter_names)} lists")
    if len(set(model_names)) != len(model_names):
        raise StoreError(f"duplicate model names {model_names}")
    if min(len(p) for p in parameter_names) < 1:
        raise StoreError("every model needs at least one parameter")
    if int(n_particles) < 1:
        raise StoreError(f"n_particles must be >= 1, got {n_particles}")
    if int(max_ellipsoids) < 1:
        raise StoreError(f"max_ellipsoids must be >= 1, got {max_ellipsoids}")


def _create_arrays(group: zarr.Group, spec: Mapping[str, Any], frame: str | None, model_names: list[str],
                   parameter_names: list[list[str]], union: list[str], sizes: dict[str, int]) -> None:
    """Every array of :data:`SCHEMA` in a new store: the static ones written, the growing
    ones empty along population, each with its attributes (one metadata write each)."""
    units = _distance_units(spec)
    prior_low, prior_width = _priors(spec, model_names, union)

    def meta(v: Variable) -> dict[str, Any]:
        out = {"long_name": v.long_name, "description": v.description.replace("{frame}", _FRAME_TEXT[frame])
               or v.long_name}
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

__all__ = ["FORMAT_VERSION", "FRAMES", "NOTE_CODES", "SCHEMA", "STATUSES", "Store", "StoreError", "StoreIncomplete",
           "StoreNotFound", "Variable", "data_hash", "dataset_result", "ellipsoid_frame", "model_view", "result_from_store",
           "result_of"]
