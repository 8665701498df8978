"""One job's result store (:class:`Store`): made (:meth:`Store.create`), opened, appended to
population by population by its one writer (the job's runner), its status set, and read by
any number of readers in any process: the populations, a page of one, the counters a resume
needs (:meth:`Store.run_state`), the xarray dataset.

Its layout is :mod:`service.run.store.schema`'s; a population's rows, :mod:`~service.run.store.rows`';
the group's metadata, the lock and the atomic writes, :mod:`~service.run.store.metadata`'s.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
import xarray as xr
import zarr
import zarr.api.asynchronous
import zarr.storage
from zarr.core.sync import sync

from abcns.result import Population
from service.run.store import metadata
from service.run.store.metadata import PARTIAL_WARNING, StoreError
from service.run.store.results import model_view
from service.run.store.rows import Layout, population, row
from service.run.store.schema import FORMAT_VERSION, NOTE_CODES, POPULATION_ARRAYS, create_arrays, ellipsoid_frame

STATUSES = ("running", "finished", "failed", "cancelled")
_RESERVED = frozenset({
    "format_version", "spec", "seed", "versions", "data_hash", "algorithm", "model_names",
    "parameter_names", "n_particles", "status", "stop_reason", "n_populations", "ellipsoid_note_codes",
    "created_at", "updated_at", "max_ellipsoids", "ellipsoid_frame",
})


class Store:
    """One job's result store. Build with :meth:`create` or :meth:`open`."""

    def __init__(self, path: Path, attrs: Mapping[str, Any]):
        self.path = path
        self._layout = Layout.of(attrs)

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
        spec = metadata.jsonable(dict(spec), "spec")  # checked before anything is written
        n, k = int(n_particles), int(max_ellipsoids)
        # made in memory, then written out in one go: zarr costs ~2 ms of its I/O thread per
        # array on disk, and a job's workers wait for the store before population 1 starts
        files: dict[str, Any] = {}
        group = zarr.open_group(zarr.storage.MemoryStore(files), mode="w-", zarr_format=3)
        frame = ellipsoid_frame(spec, str(algorithm))
        create_arrays(group, spec, frame, model_names, parameter_names, n, k)
        attrs = {
            "spec": spec,
            "seed": int(seed),
            "versions": metadata.versions(),
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
            "created_at": metadata.now(),
            "updated_at": metadata.now(),
            "n_populations": 0,
            **({"job_key": str(job_key)} if job_key is not None else {}),
        }
        group.update_attributes(metadata.encode_attrs(attrs))
        # the group first (a store whose creation was cut is then "incomplete", not "no
        # store"), the arrays, and last the format version with the consolidated metadata: it
        # marks a complete store
        path.mkdir(parents=True, exist_ok=True)
        metadata.replace(path / "zarr.json", files.pop("zarr.json").to_bytes())
        for key, data in files.items():
            file = path / key
            file.parent.mkdir(parents=True, exist_ok=True)
            file.write_bytes(data.to_bytes())
        metadata.rewrite_group(path, {"format_version": FORMAT_VERSION}, consolidate=True)
        return cls(path, attrs)

    @classmethod
    def open(cls, path: str | Path) -> Store:
        """An existing store; StoreError if missing, not a store, or another format version."""
        path = Path(path)
        attrs = metadata.read_attrs(path)
        return cls(path, attrs)

    def __repr__(self) -> str:
        return f"Store({str(self.path)!r}, n_populations={self.n_populations})"

    # ------------------------------------------------------------------ attributes

    def _group(self, mode: Literal["r", "r+"] = "r") -> zarr.Group:
        return zarr.open_group(str(self.path), mode=mode, zarr_format=3)

    @property
    def attrs(self) -> dict:
        """Every group attribute, read fresh from disk."""
        return metadata.read_attrs(self.path)

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
        update = metadata.jsonable({"status": status, "stop_reason": None if reason is None else str(reason), **extra},
                                   "run information")
        update["updated_at"] = metadata.now()
        metadata.update_attrs(self.path, update)

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
        rows = [row(self._layout, pop, int(total)) for pop, total in pops]  # all validated before any write
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
        metadata.update_attrs(self.path, {"n_populations": n_populations, "updated_at": metadata.now()}, consolidate=True)

    # ------------------------------------------------------------------ reading

    def _read(self, rows: slice, names: Sequence[str] = POPULATION_ARRAYS) -> dict[str, np.ndarray]:
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


    def populations(self) -> list[Population]:
        """Every complete population, exactly as appended (ellipsoids rebuilt by from_matrix)."""
        return self._records(self.n_populations)[0]

    def _records(self, n: int, names: Sequence[str] = POPULATION_ARRAYS) -> tuple[list[Population], dict[str, np.ndarray]]:
        """The first ``n`` populations, and the arrays ``names`` they were read from."""
        if n == 0:
            return [], {}
        a = self._read(slice(0, n), names)
        return [population(self._layout, a, i) for i in range(n)], a

    def population(self, t: int) -> Population:
        """Population ``t`` (1-based)."""
        n = self.n_populations
        if not 1 <= t <= n:
            raise IndexError(f"population {t} is not in {self.path} (it holds populations 1..{n})")
        a = self._read(slice(t - 1, t))
        return population(self._layout, a, 0)

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
        out["theta"] = self._layout.from_named(out["model_index"], out["theta"])
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
                with metadata.ignoring(PARTIAL_WARNING):
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


def _values(group: zarr.Group, name: str, selection: int | slice | tuple[int, slice]) -> np.ndarray:
    """``group[name][selection]`` as a numpy array (a store's group holds arrays only)."""
    return np.asarray(cast(zarr.Array, group[name])[selection])
