"""abcns: ABC-NS (Ben Abdessalem et al. 2019) for parameter estimation and model selection.

Numpy and scipy (numba for the bounds' compiled loops, threadpoolctl for the BLAS limit): priors,
ellipsoids, the ABC-NS population step, the ABC-SMC and rejection baselines, distances and
result values. No Dask, no files, no HTTP.
"""

from abcns.distances import NMSE, CallableDistance, SummaryEuclidean, gk_summaries, order_statistics
from abcns.errors import InvalidSetting, SpecError
from abcns.executor import DIVERGED, FAILED, OK, Batch, Evaluated, SerialExecutor, per_model
from abcns.nested import abc_ns
from abcns.priors import Model, Uniform
from abcns.rejection import abc_rejection
from abcns.result import Population, Result, RunEnd
from abcns.run import iterate, run
from abcns.settings import NSSettings, RejectionSettings, SMCSettings, StopReason, StopRules
from abcns.smc import abc_smc

__version__ = "0.1.0"  # the one place: pyproject.toml reads it (tool.setuptools.dynamic)

__all__ = [
    "DIVERGED", "FAILED", "NMSE", "OK", "Batch", "CallableDistance", "Evaluated", "InvalidSetting", "Model",
    "NSSettings", "Population", "RejectionSettings", "Result", "RunEnd", "SMCSettings",
    "SerialExecutor", "SpecError", "StopReason", "StopRules", "SummaryEuclidean", "Uniform",
    "abc_ns", "abc_rejection", "abc_smc", "gk_summaries", "iterate", "order_statistics",
    "per_model", "run",
]
