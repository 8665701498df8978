"""Running a job: the run loop (runner), the Dask executor, the zarr result store."""
