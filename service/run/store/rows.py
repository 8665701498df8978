"""One population to the store's rows and back: :func:`row` makes the new row of every growing
array of :data:`~service.run.store.schema.SCHEMA` from an :class:`abcns.Population`
(validated before anything is written), :func:`population` rebuilds the record exactly (bit
for bit; the ellipsoids by :func:`abcns.ellipsoid.from_matrices`). :class:`Layout` is what both
need of one store: its models' parameters as named columns, its particles and ellipsoid slots.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from abcns.ellipsoid import Ellipsoid, from_matrices
from abcns.result import Population
from service.run.store.metadata import StoreError
from service.run.store.schema import BY_MODEL, GROWING, NOTE_CODES, NOTES, PARTS, SCHEMA, parameter_union


@dataclass(frozen=True)
class Layout:
    """The sizes of one store's rows, from its attributes: ``dims`` each model's number of
    parameters, ``columns[i]`` model i's parameters as indices into the named columns (all
    models' parameter names, :func:`~service.run.store.schema.parameter_union`), ``d_union``
    their number, ``n_particles`` and ``n_ellipsoids`` (the most per model)."""

    dims: tuple[int, ...]
    columns: tuple[np.ndarray, ...]
    d_union: int
    n_particles: int
    n_ellipsoids: int

    @classmethod
    def of(cls, attrs: Mapping[str, Any]) -> Layout:
        names = attrs["parameter_names"]
        union = parameter_union(names)
        return cls(dims=tuple(len(p) for p in names),
                   columns=tuple(np.array([union.index(n) for n in p]) for p in names),
                   d_union=len(union), n_particles=int(attrs["n_particles"]),
                   n_ellipsoids=int(attrs.get("max_ellipsoids", 1)))

    @property
    def n_models(self) -> int:
        return len(self.dims)

    @property
    def d_max(self) -> int:
        return max(self.dims)

    def to_named(self, models: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """(n, widest model) in each model's own order -> (n, all parameter names)."""
        out = np.full((theta.shape[0], self.d_union), np.nan)
        for i, cols in enumerate(self.columns):
            rows = np.flatnonzero(models == i)
            out[np.ix_(rows, cols)] = theta[rows, : len(cols)]
        return out

    def from_named(self, models: np.ndarray, named: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`to_named` (NaN padding to the widest model)."""
        out = np.full((named.shape[0], self.d_max), np.nan)
        for i, cols in enumerate(self.columns):
            rows = np.flatnonzero(models == i)
            out[rows, : len(cols)] = named[np.ix_(rows, cols)]
        return out


def row(layout: Layout, pop: Population, n_simulations_total: int) -> dict[str, Any]:
    """The new row of every growing array (validated before anything is written)."""
    n, m, d = layout.n_particles, layout.n_models, layout.d_max
    if np.shape(pop.theta) != (n, d):
        raise StoreError(f"population {pop.t}: theta has shape {np.shape(pop.theta)}, the store expects {(n, d)}")
    if pop.survivors is not None and np.shape(pop.survivors) != (n,):
        raise StoreError(f"population {pop.t}: survivors has shape {np.shape(pop.survivors)}, expected ({n},)")
    if pop.held is not None and np.shape(pop.held) != (n, m):
        raise StoreError(f"population {pop.t}: held has shape {np.shape(pop.held)}, expected {(n, m)}")
    if pop.ellipsoids and len(pop.ellipsoids) != m:
        raise StoreError(f"population {pop.t}: {len(pop.ellipsoids)} bounds for {m} models")
    out = _fields(pop, {"particle": n, "model": m})
    out |= {
        "theta": layout.to_named(np.asarray(pop.models), np.asarray(pop.theta, dtype=np.float64)),
        "survivor": np.zeros(n, bool) if pop.survivors is None else np.asarray(pop.survivors, dtype=bool),
        "held": np.full((n, m), -1, np.int8) if pop.held is None else np.asarray(pop.held, np.int8),
        "n_simulations_total": n_simulations_total,
        "has_survivors": pop.survivors is not None,
        "has_ellipsoids": bool(pop.ellipsoids),
        **_ellipsoids(layout, pop),
        **{f"has_{part}": getattr(pop, part) is not None for part in PARTS},
    }
    out["population"] = out.pop("population")  # last: xarray's index shows t only once the row is written
    assert set(out) == GROWING, "every growing array has its row"
    return out


def _fields(pop: Population, sizes: dict[str, int]) -> dict[str, Any]:
    """The rows of the arrays that hold a field of ``pop`` as it is (``Variable.field``)."""
    out: dict[str, Any] = {}
    for v in SCHEMA:
        if v.field is None:
            continue
        part, _, name = v.field.rpartition(".")
        owner = getattr(pop, part) if part else pop
        shape = tuple(sizes[dim] for dim in v.dims)
        value = np.full(shape, v.fill_value) if owner is None else np.asarray(getattr(owner, name))
        if v.name in BY_MODEL and value.shape == (0,):  # not recorded
            value = np.full(shape, -1)
        if value.shape != shape:
            raise StoreError(f"population {pop.t}: {v.field} has shape {value.shape}, the store expects {shape}")
        out[v.name] = value.astype(v.dtype)
    return out


def _ellipsoids(layout: Layout, pop: Population) -> dict[str, np.ndarray]:
    """``ellipsoid_centre``, ``_matrix`` and ``_note`` of ``pop``'s bounds, in the named columns."""
    m, kmax, du = layout.n_models, layout.n_ellipsoids, layout.d_union
    centre = np.full((m, kmax, du), np.nan)
    matrix = np.full((m, kmax, du, du), np.nan)
    note = np.full((m, kmax), -1, dtype=np.int8)
    for i, bound in enumerate(pop.ellipsoids):
        if len(bound) > kmax:
            raise StoreError(f"population {pop.t}: {len(bound)} ellipsoids for model {i}; the store holds {kmax}")
        k = layout.dims[i]
        for j, e in enumerate(bound):
            if e.centre.shape != (k,) or e.matrix.shape != (k, k):
                raise StoreError(f"population {pop.t}: ellipsoid of model {i} has dimension {e.n_dim}, expected {k}")
            if e.note not in NOTE_CODES:
                raise StoreError(f"population {pop.t}: unknown ellipsoid note {e.note!r}")
            cols = layout.columns[i]
            centre[i, j, cols], note[i, j] = e.centre, NOTE_CODES[e.note]
            matrix[i, j, cols[:, None], cols[None, :]] = e.matrix
    return {"ellipsoid_centre": centre, "ellipsoid_matrix": matrix, "ellipsoid_note": note}


def population(layout: Layout, a: Mapping[str, np.ndarray], i: int) -> Population:
    """Population ``i`` (0-based) of the arrays ``a`` (rows along population), exactly as appended."""
    fields: dict[str, Any] = {}
    parts: dict[str, dict[str, Any]] = {part: {} for part in PARTS}
    for v in SCHEMA:
        if v.field is None or v.derived or v.name not in a:
            continue
        value = a[v.name][i]
        if v.name in BY_MODEL and not np.all(value >= 0):  # not recorded
            continue
        value = value.copy() if v.dims else int(value) if np.dtype(v.dtype).kind == "i" else float(value)
        part, _, name = v.field.rpartition(".")
        (parts[part] if part else fields)[name] = value
    optional: dict[str, Any] = {part: cls(**parts[part]) if a[f"has_{part}"][i] else None
                                for part, cls in PARTS.items()}
    return Population(
        **fields,
        theta=layout.from_named(a["model_index"][i], a["theta"][i]),
        survivors=a["survivor"][i].copy() if a["has_survivors"][i] else None,
        held=a["held"][i].copy() if a["has_evidence"][i] else None,
        ellipsoids=_bounds(layout, a, i) if a["has_ellipsoids"][i] else (),
        **optional,
    )


def _bounds(layout: Layout, a: Mapping[str, np.ndarray], i: int) -> tuple[tuple[Ellipsoid, ...], ...]:
    """Every model's ellipsoids in population ``i`` of the arrays ``a`` (a note of -1: no
    ellipsoid), each model's in one stacked call (:func:`from_matrices`: the bits of each
    alone; a §4.1 store read back in 61 ms, against 76 with one call per ellipsoid)."""
    bounds: list[tuple[Ellipsoid, ...]] = []
    for j, cols in enumerate(layout.columns):
        codes = a["ellipsoid_note"][i, j]
        kept = np.flatnonzero(codes >= 0)
        centres = a["ellipsoid_centre"][i, j][np.ix_(kept, cols)]
        matrices = a["ellipsoid_matrix"][i, j][np.ix_(kept, cols, cols)]
        bounds.append(tuple(from_matrices(list(centres), list(matrices), [NOTES[int(c)] for c in codes[kept]])))
    return tuple(bounds)
