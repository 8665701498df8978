"""Model error made visible: at a run's end, the best fit's residuals against what
independent noise would give (:func:`abcns.noise.whiteness`, docs/design.md "Model error
made visible"), and the words the summary, the CLI and the live page show when they are
correlated (the noise floor is then likely optimistic).

The statistic lives in :mod:`abcns.noise`; this module only simulates the best fit (the
lowest distance of the final population) over the fit window and words the result.
"""

from __future__ import annotations

import numpy as np

from abcns import OK, Result
from abcns.noise import whiteness
from service.spec import Job
from worker.compose import full_parameters


def best_fit(result: Result) -> tuple[int, np.ndarray] | None:
    """(model index, free parameters) of the final population's lowest distance; None
    without a population or a finite distance."""
    if not result.populations:
        return None
    pop = result.final
    finite = np.isfinite(pop.distances)
    if not finite.any():
        return None
    j = int(np.argmin(np.where(finite, pop.distances, np.inf)))
    m = int(pop.models[j])
    return m, np.asarray(pop.theta[j, : result.models[m].n_dim], dtype=float)


def residual_check(job: Job, result: Result) -> dict | None:
    """The whiteness test of the best fit's residuals on the fit window, as JSON for the
    run's record (``run.residuals``); None where it does not apply (a distance other than
    the NMSE, a simulator not driven by an input record, a best fit that does not simulate)."""
    best = best_fit(result) if job.noise is not None else None
    if best is None:
        return None
    m, theta = best
    sim = job.simulators[m]
    if getattr(sim, "needs_input", None) is not True:
        return None
    out = sim.simulate(full_parameters(job.models[m], sim)(theta), np.random.default_rng(job.seed))
    if out.status[0] != OK:
        return None
    start, stop = job.spec.data.fit or (0, job.observed.size)
    test = whiteness(job.observed[start:stop] - np.asarray(out.values)[0, start:stop])
    if test is None:
        return None
    return {**test.describe(), "model": job.models[m].name, "window": [int(start), int(stop)],
            "input_interpolation": job.spec.data.input_interpolation,
            "noise_stated": job.spec.data.noise_std is not None}


def model_error_warning(check: dict | None) -> str | None:
    """The summary's warning when the best fit's residuals are correlated; None otherwise."""
    if not check or not check.get("correlated"):
        return None
    tries = ["finer integrator.substeps"]
    if check.get("input_interpolation") != "bandlimited":
        tries.append("data.input_interpolation: bandlimited (a measured, continuous input)")
    if not check.get("noise_stated"):
        tries.append("data.noise_std if you know the measurement noise")
    return (f"model error: the best fit's residuals ({check['model']}) are correlated (Ljung-Box over lags "
            f"1-{check['lags']}: p = {check['p_value']:.2g}; lag-1 autocorrelation {check['autocorrelation'][0]:.2f}), "
            "which independent noise would not give: part of the misfit is the model's or the simulator's own error "
            "(or the noise is correlated), so the noise floor is likely optimistic and the intervals too narrow; "
            "try " + ", ".join(tries))
