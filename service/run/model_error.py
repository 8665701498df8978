"""Model error made visible: at a run's end, the best fit's residuals against what
independent noise would give (:func:`abcns.noise.whiteness`, docs/design.md "Model error
made visible"), and the words the summary, the CLI and the live page show when they are
correlated (the noise floor is then likely optimistic).

The statistics live in :mod:`abcns.noise` (``whiteness``, ``projected_shift``); this module
only simulates the best fit (the lowest distance of the final population) over the fit window,
and finer versions of its simulator, and words the result.
"""

from __future__ import annotations

import math

import numpy as np

from abcns import OK, Result
from abcns.noise import projected_shift, whiteness
from service.spec import Job
from worker.compose import full_parameters
from worker.simulators import Simulator


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


#: the relative step of the finite differences of :func:`parameter_shift` (of each prior's width)
STEP = 1e-4


def shift_level(p: int) -> float:
    """The move (in the fit's standard deviations, jointly) past which the simulator's own
    error warns: sqrt(p + sqrt(2 p)), the radius of the region the run accepts at its decision
    tolerance around the best fit, in whitened units (abcns.noise: eps_dec - d_min = (p +
    sqrt(2 p)) v). A larger move puts the finer simulator's best fit outside the answer."""
    return math.sqrt(p + math.sqrt(2.0 * p))


def references(sim: Simulator, interpolation: str) -> list[tuple[str, Simulator]]:
    """Finer versions of a built-in RK4 oscillator: twice the substeps (the integration's
    error), and, for a ``linear`` input (one meant continuous), the band-limited input at twice
    the substeps (the interpolation's error); of a displacement-driven restoring-force model,
    twice the substeps. [] for other simulators."""
    from worker.restoring import _Restoring
    from worker.simulators import BoucWen, Duffing

    if isinstance(sim, _Restoring):
        return [("integrator.substeps", sim.finer())]
    if not (type(sim) is Duffing or type(sim) is BoucWen):
        return []
    rk4: Duffing | BoucWen = sim

    def finer(interp: str) -> Simulator:
        return type(rk4)(rk4.force, rk4.dt, substeps=2 * rk4.substeps, output=rk4.output, state_bound=rk4.state_bound,
                         backend=rk4.backend, input_interpolation=interp)

    out = [("integrator.substeps", finer(interpolation))]
    if interpolation == "linear":
        out.append(("data.input_interpolation", finer("bandlimited")))
    return out


def parameter_shift(job: Job, m: int, theta: np.ndarray, window: tuple[int, int]) -> list[dict]:
    """The simulator's own error at the best fit ``theta`` of model ``m``, for each of its
    :func:`references`: ``delta`` = the finer simulation minus the run's, projected on the
    fit's tangent space (the Jacobian J by finite differences, ``STEP`` of each prior's
    width): ``shift`` = J^+ delta, how far the fit would move, and ``sd`` = |J shift| / sigma
    (sigma the best fit's residual RMS), that move in the fit's standard deviations."""
    sim, model = job.simulators[m], job.models[m]
    refs = references(sim, job.spec.data.input_interpolation)
    if not refs:
        return []
    expand, (a, b) = full_parameters(model, sim), window
    steps = STEP * np.array([u.high - u.low for u in model.priors.values()])
    logs = model.log_columns  # a log-uniform prior's step is relative: STEP of its width in log theta
    steps[logs] = theta[logs] * np.expm1(STEP * model.coordinate_width[logs])
    rows = np.vstack([theta, theta + np.diag(steps)])
    out = sim.simulate(expand(rows), np.random.default_rng(job.seed))
    if np.any(out.status != OK):
        return []
    y = np.asarray(out.values)[:, a:b]
    jac = ((y[1:] - y[0]) / steps[:, None]).T
    sigma = float(np.sqrt(np.mean((job.observed[a:b] - y[0]) ** 2)))
    found = []
    for field, ref in refs:
        fine = ref.simulate(expand(theta[None, :]), np.random.default_rng(job.seed))
        if fine.status[0] != OK or not sigma > 0:
            continue
        delta = np.asarray(fine.values)[0, a:b] - y[0]
        shift, sd = projected_shift(jac, delta, sigma)
        found.append({"field": field, "sd": sd,
                      "own_error_sd": float(np.linalg.norm(delta) / sigma),
                      "shift": {name: float(v) for name, v in zip(model.priors, shift, strict=True)}})
    return found


def residual_check(job: Job, result: Result) -> dict | None:
    """The whiteness test of the best fit's residuals on the fit window and the simulator's
    own error at it (:func:`parameter_shift`), as JSON for the run's record
    (``run.residuals``); None where it does not apply (a distance other than the NMSE, a
    simulator not driven by an input record, a best fit that does not simulate) and where the
    best fit is not yet the data's: a run with no noise floor (noise-free data, an exact fit:
    its residuals are rounding) or a provisional one (stopped above its decision tolerance;
    both have their own warning)."""
    applies = job.noise is not None and result.floor is not None and result.floor_settled and not result.provisional
    best = best_fit(result) if applies else None
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
    own, level = parameter_shift(job, m, theta, (start, stop)), shift_level(job.models[m].n_dim)
    return {**test.describe(), "model": job.models[m].name, "window": [int(start), int(stop)],
            "input_interpolation": job.spec.data.input_interpolation,
            "noise_stated": job.spec.data.noise_std is not None, "own_error": own, "shift_level_sd": level,
            "warn": test.correlated or any(o["sd"] > level for o in own)}


_FINER = {"integrator.substeps": "twice the integrator.substeps",
          "data.input_interpolation": "the input band-limited (data.input_interpolation: bandlimited)"}


def _own_words(own: list[dict]) -> str:
    """What the simulator's own error would do to the fit, per finer simulation."""
    def moves(o: dict) -> str:
        return ", ".join(f"{k} {v:+.3g}" for k, v in o["shift"].items())

    return "; ".join(f"with {_FINER.get(o['field'], o['field'])} the best fit would move by {o['sd']:.2g} of its "
                     f"standard deviations, past the answer's region ({moves(o)})" for o in own)


def model_error_warning(check: dict | None) -> str | None:
    """The summary's warning when the best fit's residuals are correlated or the simulator's
    own error would move the fit (``check["warn"]``); None otherwise."""
    if not check or not (check.get("warn") or check.get("correlated")):
        return None
    found = []
    if check.get("correlated"):
        found.append(f"the best fit's residuals ({check['model']}) are correlated (Ljung-Box over lags 1-{check['lags']}: "
                     f"p = {check['p_value']:.2g}; lag-1 autocorrelation {check['autocorrelation'][0]:.2f}), which "
                     "independent noise would not give")
    own = [o for o in check.get("own_error") or [] if o["sd"] > check["shift_level_sd"]]
    if own:
        found.append(f"the simulator's own error matters: {_own_words(own)}")
    tries = ["finer integrator.substeps"]
    if check.get("input_interpolation") != "bandlimited":
        tries.append("data.input_interpolation: bandlimited (a measured, continuous input)")
    if not check.get("noise_stated"):
        tries.append("data.noise_std if you know the measurement noise")
    return ("model error: " + "; ".join(found) + ". Part of the misfit is the model's or the simulator's own error "
            "(or the noise is correlated), so the noise floor is likely optimistic and the intervals may miss the "
            "truth; try " + ", ".join(tries))
