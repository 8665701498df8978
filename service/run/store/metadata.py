"""The store's group metadata on disk (its ``zarr.json``): the attributes, encoded as netCDF
can hold them and read back as JSON; every write of it atomic, and every update of it one
read-modify-write under a lock; what a store records of the code and data it was made with
(package versions, :func:`data_hash`); and the errors of a path that is no store.

An append (of one population or several consecutive ones) resizes and writes every array
first, then rewrites the consolidated metadata (the arrays' new shapes) and bumps the counter
last (:func:`update_attrs`): a reader that trusts the counter never sees half a population, a
reader of the consolidated metadata (plain ``xarray.open_zarr``) sees only whole populations,
and rows a crash left beyond the counter are ignored and overwritten by the next append.
zarr's local store writes each file atomically (temporary file, then rename), and so does
:func:`replace`.

Written for one writer of populations (the job's runner) and any number of readers, in any
process: every call re-reads the metadata from disk, so a ``Store`` object never goes stale.
Attribute updates (counter, status) are read-modify-writes of the group metadata done under
an exclusive ``flock`` on the store's directory (POSIX), so a status set by the scheduler
while the runner appends is not lost; each is one write of the metadata file (zarr's
``attrs.update`` writes it once per key), so a process killed in a status change leaves
the old attributes or the new ones, never a status without its stop reason.
"""

from __future__ import annotations

import datetime
import fcntl
import functools
import hashlib
import importlib.metadata
import json
import os
import platform
import subprocess
import threading
import uuid
import warnings
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import scipy
import xarray as xr
import zarr

import abcns
from service.run.store.schema import FORMAT_VERSION

# zarr writes each metadata file through a temporary "zarr.<uuid>.partial" next to it; a
# reader listing the group (xarray.open_zarr in Store.dataset) while the writer updates the
# attributes meets that file and warns. Ignored there only, not process-wide.
PARTIAL_WARNING = r"Object at zarr\.[0-9a-f]+\.partial is not recognized as a component of a Zarr hierarchy"


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


def now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def jsonable(value: Any, what: str) -> Any:
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


def versions() -> dict[str, str]:
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


def encode_attrs(update: Mapping[str, Any]) -> dict[str, Any]:
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


def decode_attrs(attrs: Mapping[str, Any]) -> dict[str, Any]:
    return {key: json.loads(value[len(JSON_PREFIX):]) if isinstance(value, str) and value.startswith(JSON_PREFIX)
            else value for key, value in attrs.items()}


_WARNING_FILTERS = threading.Lock()


@contextmanager
def ignoring(message: str) -> Iterator[None]:
    """Ignore one zarr warning for the duration. The warning filters are process-wide before
    Python 3.14 (and zarr warns from its own I/O thread, so the scope covers that thread), and
    ``catch_warnings`` restores the list it saw on entry: two overlapping scopes in two threads
    (two readers' Store.dataset) would drop each other's filter, hence one scope at a time in
    this process. Only readers need it: writing a store warns of nothing (:func:`rewrite_group`)."""
    with _WARNING_FILTERS, warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=message, category=zarr.errors.ZarrUserWarning)
        yield


def rewrite_group(path: Path, attributes: Mapping[str, Any], consolidate: bool) -> None:
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
    replace(meta, json.dumps(doc, indent=2, allow_nan=True).encode())


def replace(file: Path, data: bytes) -> None:
    """``file`` now holds ``data``, written atomically as zarr writes its own files: a
    temporary ``<stem>.<uuid>.partial`` beside it, renamed over it."""
    partial = file.with_suffix(f".{uuid.uuid4().hex}.partial")
    try:
        partial.write_bytes(data)
        partial.replace(file)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


def read_attrs(path: Path) -> dict:
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
    attrs = decode_attrs(attributes)
    version = attrs.get("format_version")
    if version is None:
        raise StoreIncomplete(f"{path} is not a result store (no format_version attribute: its creation did not finish)")
    if version != FORMAT_VERSION:
        raise StoreError(f"{path} has result-store format_version {version}; this abcns reads version {FORMAT_VERSION}")
    return dict(attrs)


def update_attrs(path: Path, update: dict[str, Any], consolidate: bool = False) -> None:
    """Read-modify-write of the group attributes of the store at ``path`` under an exclusive
    lock, so a status change from another process and a counter bump cannot overwrite each
    other (nor the consolidated metadata, which lives in the same file and is kept by an
    update).

    One write of the group's metadata for the whole update: zarr's ``attrs.update``
    writes it once per key, and a process killed between two of those writes left a
    store "finished" with no stop reason and the run information of its first
    population (CI's chaos run; the resumed job then ended "cancelled")."""
    fd = os.open(path, os.O_RDONLY)  # flock(2) on the store's directory: no extra file in the hierarchy
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        rewrite_group(path, encode_attrs(update), consolidate)
    finally:
        os.close(fd)  # releases the lock
