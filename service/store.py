"""The result store: one zarr 3 directory per job, appended population by population.

Layout (every array but the static coordinates grows along ``population``, in chunks of
at most ~64 KiB: one population of a large particle array, up to 256 of a scalar):

- particle level: ``model`` (population, particle) int16, ``theta`` (population, particle,
  parameter) float64 NaN-padded to the widest model, ``distance``, ``weight`` (population,
  particle) float64, ``survivor`` (population, particle) bool;
- population level: ``population`` (the population number t, 1-based; xarray's index),
  ``epsilon``, ``epsilon_next``, ``acceptance_rate``, ``elapsed_s`` float64, ``n_accepted``,
  ``n_simulations``, ``n_failed``, ``n_redraws``, ``n_simulations_total`` (cumulative,
  pilot included) int64, ``has_survivors`` and ``has_ellipsoids`` bool (False for the
  baselines, whose records carry no survivors and no ellipsoids);
- per model: ``model_probability`` (population, model), ``ellipsoid_centre`` (population,
  model, parameter), ``ellipsoid_matrix`` (population, model, parameter, parameter_b) NaN
  for a dead model, ``ellipsoid_note`` (population, model) int8 (``NOTE_CODES``; -1: none);
- static coordinates: ``model_name`` (model), ``parameter`` (parameter) indices,
  ``parameter_name`` (model, parameter), ``n_parameters`` (model).

The group attributes hold ``format_version``, the spec, seed, package versions, the data
hash, algorithm, model and parameter names, status, stop reason, run information and the
counter ``n_populations``. An append (of one population or several consecutive ones)
resizes and writes every array first and bumps the counter last: a reader that trusts the
counter never sees half a population, and rows a crash left beyond the counter are ignored
and overwritten by the next append. zarr's local store writes each file atomically
(temporary file, then rename).

Written for one writer of populations (the job's runner) and any number of readers, in any
process: every call re-reads the metadata from disk, so a ``Store`` object never goes stale.
Attribute updates (counter, status) are read-modify-writes of the group metadata done under
an exclusive ``flock`` on the store's directory (POSIX), so a status set by the scheduler
while the runner appends is not lost.
"""

from __future__ import annotations

import asyncio
import datetime
import fcntl
import hashlib
import json
import math
import os
import platform
import time
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import scipy
import xarray as xr
import zarr
import zarr.api.asynchronous
from zarr.core.sync import sync

import abcns
from abcns.ellipsoid import Ellipsoid, from_matrix
from abcns.result import Population

FORMAT_VERSION = 1
CHUNK_BYTES = 64 * 1024
# zarr writes each metadata file through a temporary "zarr.<uuid>.partial" next to it; a
# reader listing the group while the writer updates the attributes meets that file and warns.
PARTIAL_WARNING = r"Object at zarr\.[0-9a-f]+\.partial is not recognized as a component of a Zarr hierarchy"
warnings.filterwarnings("ignore", message=PARTIAL_WARNING, category=zarr.errors.ZarrUserWarning)
STATUSES = ("running", "finished", "failed", "cancelled")
NOTE_CODES = {"": 0, "repaired": 1, "fallback": 2, "box": 3}  # -1: no ellipsoid (dead model)
_NOTES = {code: note for note, code in NOTE_CODES.items()}
_RESERVED = frozenset({
    "format_version", "spec", "seed", "versions", "data_hash", "algorithm", "model_names",
    "parameter_names", "n_particles", "status", "stop_reason", "n_populations", "ellipsoid_note_codes",
    "created_at", "updated_at",
})

_P, _N, _D, _DB, _M = "population", "particle", "parameter", "parameter_b", "model"


class StoreError(Exception):
    """A path that is not a usable result store (missing, not a store, other format, exists)."""


class StoreNotFound(StoreError, FileNotFoundError):
    """No result store at the path."""


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


def _versions() -> dict[str, str]:
    return {
        "abcns": abcns.__version__, "numpy": np.__version__, "scipy": scipy.__version__,
        "zarr": zarr.__version__, "python": platform.python_version(),
    }


class Store:
    """One job's result store. Build with :meth:`create` or :meth:`open`."""

    def __init__(self, path: Path, attrs: Mapping[str, Any]):
        self.path = path
        self._n_models = len(attrs["model_names"])
        self._dims = [len(p) for p in attrs["parameter_names"]]
        self._d_max = max(self._dims)
        self._n_particles = int(attrs["n_particles"])

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
    ) -> Store:
        """A new, empty store at ``path`` (status "running"); refuses an existing non-empty path."""
        path = Path(path)
        if path.exists() and (not path.is_dir() or any(path.iterdir())):
            raise StoreError(f"{path} already exists and is not empty; refusing to overwrite it")
        model_names, parameter_names = list(model_names), [list(p) for p in parameter_names]
        if not model_names or len(parameter_names) != len(model_names):
            raise StoreError(f"need one list of parameter names per model: {len(model_names)} models, "
                             f"{len(parameter_names)} lists")
        if len(set(model_names)) != len(model_names):
            raise StoreError(f"duplicate model names {model_names}")
        if min(len(p) for p in parameter_names) < 1:
            raise StoreError("every model needs at least one parameter")
        if int(n_particles) < 1:
            raise StoreError(f"n_particles must be >= 1, got {n_particles}")
        if hasattr(spec, "model_dump"):  # a pydantic JobSpec
            spec = spec.model_dump(mode="json")  # type: ignore[union-attr]
        spec = _jsonable(dict(spec), "spec")  # checked before anything is written
        n, m, d = int(n_particles), len(model_names), max(len(p) for p in parameter_names)

        group = zarr.open_group(str(path), mode="w-", zarr_format=3)

        def grow(name, tail, dtype, fill, dims):
            # rows per chunk along population: a chunk of ~64 KiB at most (one population of
            # theta, 256 of a scalar), so an append of several populations writes few files
            row_bytes = np.dtype(dtype).itemsize * math.prod(tail)
            rows = int(np.clip(CHUNK_BYTES // row_bytes, 1, 256))
            group.create_array(name, shape=(0, *tail), chunks=(rows, *tail), dtype=dtype,
                               fill_value=fill, dimension_names=[_P, *dims])

        grow("population", (), "int32", 0, [])
        grow("model", (n,), "int16", -1, [_N])
        grow("theta", (n, d), "float64", np.nan, [_N, _D])
        grow("distance", (n,), "float64", np.nan, [_N])
        grow("weight", (n,), "float64", np.nan, [_N])
        grow("survivor", (n,), "bool", False, [_N])
        for name in ("epsilon", "epsilon_next", "acceptance_rate", "elapsed_s"):
            grow(name, (), "float64", np.nan, [])
        for name in ("n_accepted", "n_simulations", "n_failed", "n_redraws", "n_simulations_total"):
            grow(name, (), "int64", -1, [])
        grow("has_survivors", (), "bool", False, [])
        grow("has_ellipsoids", (), "bool", False, [])
        grow("model_probability", (m,), "float64", np.nan, [_M])
        grow("ellipsoid_centre", (m, d), "float64", np.nan, [_M, _D])
        grow("ellipsoid_matrix", (m, d, d), "float64", np.nan, [_M, _D, _DB])
        grow("ellipsoid_note", (m,), "int8", -1, [_M])

        static = {
            "model_name": (np.array(model_names, dtype=str), [_M]),
            "parameter": (np.arange(d, dtype=np.int32), [_D]),
            "parameter_b": (np.arange(d, dtype=np.int32), [_DB]),
            "n_parameters": (np.array([len(p) for p in parameter_names], dtype=np.int32), [_M]),
            "parameter_name": (np.array([p + [""] * (d - len(p)) for p in parameter_names], dtype=str), [_M, _D]),
        }
        for name, (values, dims) in static.items():
            arr = group.create_array(name, shape=values.shape, dtype=values.dtype if values.dtype.kind != "U" else str,
                                     dimension_names=dims)
            arr[...] = values
        # xarray: show names next to the model dimension
        group["model_probability"].attrs["coordinates"] = "model_name"

        attrs = {
            "spec": spec,
            "seed": int(seed),
            "versions": _versions(),
            "data_hash": str(data_hash),
            "algorithm": str(algorithm),
            "model_names": model_names,
            "parameter_names": parameter_names,
            "n_particles": n,
            "ellipsoid_note_codes": NOTE_CODES,
            "status": "running",
            "stop_reason": None,
            "created_at": _now(),
            "updated_at": _now(),
            "n_populations": 0,
        }
        group.attrs.update(attrs)
        group.attrs["format_version"] = FORMAT_VERSION  # last: marks a complete store
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

    def _group(self, mode: str = "r") -> zarr.Group:
        return zarr.open_group(str(self.path), mode=mode, zarr_format=3)  # type: ignore[arg-type]

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
        group = await zarr.api.asynchronous.open_group(store=str(self.path), mode="r+", zarr_format=3)
        arrays = await asyncio.gather(*(group.getitem(name) for name in rows))
        await asyncio.gather(*(arr.resize((n + k, *arr.shape[1:])) for arr in arrays))
        await asyncio.gather(*(arr.setitem(slice(n, n + k), value) for arr, value in zip(arrays, rows.values())))

    def _commit(self, n_populations: int) -> None:
        """Bump the counter: the population is part of the store from here on."""
        self._update_attrs({"n_populations": n_populations, "updated_at": _now()})

    def _update_attrs(self, update: dict[str, Any]) -> None:
        """Read-modify-write of the group attributes under an exclusive lock, so a status
        change from another process and a counter bump cannot overwrite each other."""
        fd = os.open(self.path, os.O_RDONLY)  # flock(2) on the store's directory: no extra file in the hierarchy
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            self._group("r+").attrs.update(update)
        finally:
            os.close(fd)  # releases the lock

    def _rows(self, pop: Population, n_simulations_total: int) -> dict[str, Any]:
        """The new row of every growing array (validated before anything is written)."""
        n, m, d = self._n_particles, self._n_models, self._d_max
        shapes = {"models": (n,), "theta": (n, d), "distances": (n,), "weights": (n,), "model_probabilities": (m,)}
        for field, shape in shapes.items():
            got = np.shape(getattr(pop, field))
            if got != shape:
                raise StoreError(f"population {pop.t}: {field} has shape {got}, the store expects {shape}")
        if pop.survivors is not None and np.shape(pop.survivors) != (n,):
            raise StoreError(f"population {pop.t}: survivors has shape {np.shape(pop.survivors)}, expected ({n},)")
        if pop.ellipsoids and len(pop.ellipsoids) != m:
            raise StoreError(f"population {pop.t}: {len(pop.ellipsoids)} ellipsoids for {m} models")
        centre = np.full((m, d), np.nan)
        matrix = np.full((m, d, d), np.nan)
        note = np.full(m, -1, dtype=np.int8)
        for i, e in enumerate(pop.ellipsoids):
            if e is None:
                continue
            k = self._dims[i]
            if e.centre.shape != (k,) or e.matrix.shape != (k, k):
                raise StoreError(f"population {pop.t}: ellipsoid of model {i} has dimension {e.n_dim}, expected {k}")
            if e.note not in NOTE_CODES:
                raise StoreError(f"population {pop.t}: unknown ellipsoid note {e.note!r}")
            centre[i, :k], matrix[i, :k, :k], note[i] = e.centre, e.matrix, NOTE_CODES[e.note]
        return {
            "model": np.asarray(pop.models, dtype=np.int16),
            "theta": np.asarray(pop.theta, dtype=np.float64),
            "distance": np.asarray(pop.distances, dtype=np.float64),
            "weight": np.asarray(pop.weights, dtype=np.float64),
            "survivor": np.zeros(n, bool) if pop.survivors is None else np.asarray(pop.survivors, dtype=bool),
            "epsilon": float(pop.epsilon),
            "epsilon_next": float(pop.epsilon_next),
            "acceptance_rate": float(pop.acceptance_rate),
            "elapsed_s": float(pop.elapsed_s),
            "n_accepted": int(pop.n_accepted),
            "n_simulations": int(pop.n_simulations),
            "n_failed": int(pop.n_failed),
            "n_redraws": int(pop.n_redraws),
            "n_simulations_total": n_simulations_total,
            "has_survivors": pop.survivors is not None,
            "has_ellipsoids": bool(pop.ellipsoids),
            "model_probability": np.asarray(pop.model_probabilities, dtype=np.float64),
            "ellipsoid_centre": centre,
            "ellipsoid_matrix": matrix,
            "ellipsoid_note": note,
            "population": pop.t,  # last: xarray's index shows t only once the row is written
        }

    # ------------------------------------------------------------------ reading

    def _read(self, rows: slice) -> dict[str, np.ndarray]:
        group = self._group("r")
        names = ("population", "model", "theta", "distance", "weight", "survivor", "epsilon", "epsilon_next",
                 "elapsed_s", "n_accepted", "n_simulations", "n_failed", "n_redraws", "has_survivors",
                 "has_ellipsoids", "model_probability", "ellipsoid_centre", "ellipsoid_matrix", "ellipsoid_note")
        return {name: np.asarray(group[name][rows]) for name in names}

    def _population(self, a: dict[str, np.ndarray], i: int) -> Population:
        ellipsoids: tuple[Ellipsoid | None, ...] = ()
        if a["has_ellipsoids"][i]:
            ells: list[Ellipsoid | None] = []
            for j, k in enumerate(self._dims):
                code = int(a["ellipsoid_note"][i, j])
                if code < 0:
                    ells.append(None)
                    continue
                centre = np.ascontiguousarray(a["ellipsoid_centre"][i, j, :k])
                matrix = np.ascontiguousarray(a["ellipsoid_matrix"][i, j, :k, :k])
                ells.append(from_matrix(centre, matrix, _NOTES[code]))
            ellipsoids = tuple(ells)
        return Population(
            t=int(a["population"][i]),
            epsilon=float(a["epsilon"][i]),
            epsilon_next=float(a["epsilon_next"][i]),
            models=a["model"][i].copy(),
            theta=a["theta"][i].copy(),
            distances=a["distance"][i].copy(),
            weights=a["weight"][i].copy(),
            n_accepted=int(a["n_accepted"][i]),
            n_simulations=int(a["n_simulations"][i]),
            n_failed=int(a["n_failed"][i]),
            n_redraws=int(a["n_redraws"][i]),
            elapsed_s=float(a["elapsed_s"][i]),
            survivors=a["survivor"][i].copy() if a["has_survivors"][i] else None,
            ellipsoids=ellipsoids,
            model_probabilities=a["model_probability"][i].copy(),
        )

    def populations(self) -> list[Population]:
        """Every complete population, exactly as appended (ellipsoids rebuilt by from_matrix)."""
        n = self.n_populations
        if n == 0:
            return []
        a = self._read(slice(0, n))
        return [self._population(a, i) for i in range(n)]

    def population(self, t: int) -> Population:
        """Population ``t`` (1-based)."""
        n = self.n_populations
        if not 1 <= t <= n:
            raise IndexError(f"population {t} is not in {self.path} (it holds populations 1..{n})")
        a = self._read(slice(t - 1, t))
        return self._population(a, 0)

    def dataset(self, retries: int = 20) -> xr.Dataset:
        """The store as an xarray Dataset (lazy), cut to the complete populations.

        ``xarray.open_zarr(path, consolidated=False)`` reads the store directly; this also
        hides a row being written (or left by a crash) and retries while an append is
        resizing the arrays."""
        for attempt in range(retries + 1):
            n = self.n_populations  # before the data: rows below the counter are complete
            try:
                ds = xr.open_zarr(str(self.path), consolidated=False)
                return ds.isel(population=slice(0, n))
            except ValueError:  # conflicting sizes of "population" during a resize
                if attempt == retries:
                    raise
                time.sleep(0.05)
        raise AssertionError("unreachable")

    def run_state(self) -> dict[str, Any]:
        """What a resume needs: the counters after the last complete population."""
        n = self.n_populations
        if n == 0:
            return {"n_populations": 0, "t": 0, "n_simulations_total": 0, "elapsed_s": 0.0}
        group = self._group("r")
        return {
            "n_populations": n,
            "t": int(group["population"][n - 1]),
            "n_simulations_total": int(group["n_simulations_total"][n - 1]),
            "elapsed_s": float(group["elapsed_s"][n - 1]),
        }


def _read_attrs(path: Path) -> dict:
    if not path.exists():
        raise StoreNotFound(f"no result store at {path}: the path does not exist")
    try:
        group = zarr.open_group(str(path), mode="r", zarr_format=3)
    except (FileNotFoundError, ValueError, TypeError, KeyError, zarr.errors.BaseZarrError) as err:
        raise StoreError(f"{path} is not a result store (no zarr 3 group: {err})") from None
    attrs = group.attrs.asdict()
    version = attrs.get("format_version")
    if version is None:
        raise StoreError(f"{path} is not a result store (no format_version attribute)")
    if version != FORMAT_VERSION:
        raise StoreError(f"{path} has result-store format_version {version}; this abcns reads version {FORMAT_VERSION}")
    return dict(attrs)


__all__ = ["FORMAT_VERSION", "NOTE_CODES", "STATUSES", "Store", "StoreError", "StoreNotFound", "data_hash"]
