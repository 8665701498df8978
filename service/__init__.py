"""The runner's process (the Dask client) and everything with I/O (specs, runner, store, HTTP, CLI).

The runner's linear algebra is on small matrices (the ellipsoids of a few parameters, a
population's points), where BLAS threads only spin against the Dask workers on the same
cores: on this project's 2-core machine, under load, a multi-threaded OpenBLAS made the
runner's population step take 2.5 to 7 times its single-thread CPU time. So the runner's
process uses one BLAS thread unless the environment says otherwise (Dask's workers do the
same). It takes effect when ``service`` is imported before numpy, as by ``abcns``.
"""

import os

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
