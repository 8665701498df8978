"""What runs on a Dask worker: batch simulators, their registry, and batch evaluation."""
