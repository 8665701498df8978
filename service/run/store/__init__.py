"""The result store: one zarr 3 directory per job, appended population by population.

One concern a module:

- :mod:`~service.run.store.schema`: the layout (the format): every array declared once
  (:data:`SCHEMA`), the format version, the ellipsoids' frame, a new store's arrays;
- :mod:`~service.run.store.rows`: one population to the arrays' rows and back, bit for bit;
- :mod:`~service.run.store.metadata`: the group's attributes on disk, written atomically and
  updated under a lock; package versions and :func:`data_hash`; the store's errors;
- :mod:`~service.run.store.job_store`: :class:`Store`, one job's store: create, open, append,
  set the status, read (populations, a page, the counters a resume needs, the dataset);
- :mod:`~service.run.store.results`: a store or its dataset read back as an
  :class:`abcns.Result`; one model's view (:func:`model_view`).

The names callers use are importable from here (``from service.run.store import Store``).
"""

from service.run.store.job_store import STATUSES, Store
from service.run.store.metadata import PARTIAL_WARNING, StoreError, StoreIncomplete, StoreNotFound, data_hash
from service.run.store.results import dataset_result, model_view, result_from_store
from service.run.store.schema import FORMAT_VERSION, NOTE_CODES, SCHEMA, ellipsoid_frame

__all__ = ["FORMAT_VERSION", "NOTE_CODES", "PARTIAL_WARNING", "SCHEMA", "STATUSES", "Store", "StoreError",
           "StoreIncomplete", "StoreNotFound", "data_hash", "dataset_result", "ellipsoid_frame", "model_view",
           "result_from_store"]
