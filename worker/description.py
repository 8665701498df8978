"""A job's JSON description (the spec's models, distance and data settings) and its data
arrays, made into objects: :func:`model_of` (a model description -> :class:`abcns.Model`),
:func:`simulator_for` (-> the simulator the registry's factory builds over the record) and
:func:`job_parts` (the whole description -> models, simulators and distance). Errors are
SpecErrors naming the spec's field.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable

import numpy as np

from abcns.distances import NMSE, Distance, SummaryEuclidean
from abcns.priors import Model, SpecError
from worker import registry
from worker.simulators import Simulator


def model_of(desc: dict, where: str = "models") -> Model:
    """The :class:`abcns.Model` of one spec model description (errors name ``where``)."""
    try:
        return Model.from_dict(desc)
    except SpecError as err:
        raise SpecError(err.field.replace(f"models[{desc['name']}]", where), err.message) from None


def _bounds(desc: dict, factory) -> dict[str, tuple[float, float]]:
    b = {k: (float(v), float(v)) for k, v in getattr(factory, "defaults", {}).items()}
    b.update({k: (float(v), float(v)) for k, v in desc.get("fixed", {}).items()})
    b.update({k: (float(lo), float(hi)) for k, (lo, hi) in desc["priors"].items()})
    return b


#: the keywords :func:`simulator_for` offers a factory driven by the input record
INPUT_KEYWORDS = ("force", "dt", "n_samples", "substeps", "output", "state_bound", "input_interpolation")
# RK4 substeps per sample, given or chosen: past a billion no simulation ends (a record of
# 500 samples is 5 x 10^11 steps, hours at the kernels' ~10^8 steps/s), and past 2^63 the
# kernels cannot even count them (a sampling rate of 1e-300 Hz asked for 7 x 10^301 and
# failed at run time with numba's TypingError)
MAX_SUBSTEPS = 10**9


def _many(n: int) -> str:
    try:
        return f"{float(n):.3g}"
    except OverflowError:  # past the float range
        return f"a number of {len(str(n)):,} digits"


def _accepted(factory: Callable, offered: dict) -> dict:
    """The keywords of ``offered`` that ``factory``'s signature names (all of them when it
    takes ``**kwargs`` or has no signature to inspect)."""
    try:
        params = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):
        return offered
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
        return offered
    names = {p.name for p in params if p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)}
    return {k: v for k, v in offered.items() if k in names}


def _names_explicitly(factory: Callable, name: str) -> bool:
    """Whether ``factory``'s signature names the keyword ``name`` itself (not ``**kwargs``)."""
    try:
        param = inspect.signature(factory).parameters.get(name)
    except (TypeError, ValueError):
        return False
    return param is not None and param.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                                inspect.Parameter.KEYWORD_ONLY)


def simulator_for(desc: dict, force: np.ndarray | None, dt: float | None, observed: np.ndarray, where: str,
                  allow_import: bool = False, input_interpolation: str = "hold",
                  voltage: np.ndarray | None = None) -> Simulator:
    """The simulator a job builds for one model description, over the record given (the
    evaluator passes the record up to the fit end; the analysis the whole record).

    How the factory is called depends on its ``needs_input`` attribute:

    - False (g-and-k): ``factory(n_samples=observed.size)``;
    - True (the oscillators): the input is required (a SpecError on ``data.input`` without
      it) and the factory gets those of :data:`INPUT_KEYWORDS` (``force``, ``dt``,
      ``n_samples``, ``substeps``, ``output``, ``state_bound``, ``input_interpolation``) its
      signature names, e.g. ``Linear`` (exact, no substeps) gets no ``substeps``, and
      ``voltage`` (the second input channel, ``data.voltage``, or None) when its signature
      names it explicitly (not through ``**kwargs``: plugins written before it); a factory
      that does not take ``input_interpolation`` cannot be asked for anything but ``hold``
      (a SpecError on ``data.input_interpolation``);
    - absent (a plugin written before ``needs_input``): as True, except that the input may
      be missing (``force=None``), as plugins have always been called.
    """
    factory = registry.get(desc["simulator"], f"{where}.simulator", allow_import=allow_import)
    needs_input = getattr(factory, "needs_input", None)
    integ = {"substeps": None, "output": "displacement", **(desc.get("integrator") or {})}
    try:
        if needs_input is False:
            return factory(**_accepted(factory, {"n_samples": int(observed.size)}))
        if needs_input and force is None:
            raise SpecError("data.input", f"simulator {desc['simulator']!r} needs an input force")
        if integ["substeps"] is None:
            integ["substeps"] = 1
            if dt is not None and callable(getattr(factory, "omega_max", None)):
                from worker.kernels import choose_substeps

                try:
                    chosen = choose_substeps(factory.omega_max(_bounds(desc, factory)), dt)
                except (KeyError, ValueError, OverflowError) as err:  # Overflow: dt x omega past any int
                    raise SpecError("integrator.substeps", f"cannot be chosen from the priors ({err}); give it") from None
                if chosen > MAX_SUBSTEPS:
                    raise SpecError("integrator.substeps", f"the priors' highest natural frequency and the sample "
                                    f"interval {dt:.6g} s ask for {_many(chosen)} RK4 substeps per sample, more "
                                    f"than {MAX_SUBSTEPS:.0e}, which no simulation ends: check data.fs or data.dt (and "
                                    "decimate), and the priors")
                integ["substeps"] = chosen
        elif isinstance(given := integ["substeps"], int) and given > MAX_SUBSTEPS:
            raise SpecError("integrator.substeps", f"at most {MAX_SUBSTEPS:.0e} RK4 substeps per sample (no simulation of "
                                                   f"more ends), got {_many(given)}")
        # the divergence guard: 1000 x the observed scale (for a displacement output)
        bound = 1e3 * float(np.max(np.abs(observed))) if integ["output"] == "displacement" else np.inf
        offered = dict(zip(INPUT_KEYWORDS, (force, dt, int(observed.size), integ["substeps"], integ["output"], bound,
                                            input_interpolation), strict=True))
        accepted = _accepted(factory, offered)
        if _names_explicitly(factory, "voltage"):
            accepted["voltage"] = voltage
        if input_interpolation != "hold" and "input_interpolation" not in accepted:
            raise SpecError("data.input_interpolation", f"simulator {desc['simulator']!r} does not take "
                            f"input_interpolation; only 'hold' (the default) is possible with it")
        return factory(**accepted)
    except SpecError as err:
        field = err.field if err.field.startswith("data") else f"{where}.{err.field}"
        raise SpecError(field, err.message) from None


def job_parts(description: dict, arrays: dict,
              allow_import: bool = False) -> tuple[list[Model], list[Simulator], Distance]:
    """(models, simulators, distance) of a job description and its data.

    ``description``: ``{"models": [{name, simulator, priors, fixed, integrator}], "distance":
    {name: nmse | summary_euclidean, summaries}, "data": {"dt": float | None, "fit": [a, b] | None,
    "input_interpolation": "hold" | "linear" | "bandlimited" (default hold)}}``;
    ``arrays``: ``{"force": array | None, "observed": array, "voltage": array (optional: the
    second input channel of the simulators that read it; refused when none does)}``.
    ``allow_import`` lets a model name a ``package.module:factory`` simulator (the CLI; never HTTP). Without
    ``integrator.substeps`` a simulator with ``omega_max`` gets substeps from
    ``worker.kernels.choose_substeps`` (RK4 error below 1e-4 per radian at the highest
    natural frequency the priors allow). Raises SpecError naming the field.

    The arrays are copied into aligned memory when they are not (data that came over the
    wire can sit at any byte offset): numpy's reductions take another loop on unaligned
    data and round differently, which made a worker's distances differ from the runner's
    in the last bit.
    """
    observed = np.require(arrays["observed"], dtype=float, requirements=("C", "A"))
    force = arrays.get("force")
    force = np.require(force, dtype=float, requirements=("C", "A")) if force is not None else None
    voltage = arrays.get("voltage")
    voltage = np.require(voltage, dtype=float, requirements=("C", "A")) if voltage is not None else None
    data = description.get("data", {})
    dist = description.get("distance", {"name": "nmse"})
    if dist["name"] == "nmse":
        nmse = NMSE(observed, data.get("fit"))
        if force is not None and np.size(force) == observed.size and nmse.stop < observed.size:
            # nothing after the fit window is scored: simulate only up to its end
            if voltage is not None and voltage.size == observed.size:
                voltage = voltage[: nmse.stop]
            force, observed = force[: nmse.stop], observed[: nmse.stop]
            nmse = NMSE(observed, (nmse.start, nmse.stop))
        distance: Distance = nmse
    elif dist["name"] == "summary_euclidean":
        distance = SummaryEuclidean(observed, dist.get("summaries") or "gk")
    else:
        raise SpecError("distance.name", f"unknown distance {dist['name']!r}")
    interpolation = data.get("input_interpolation", "hold")
    if force is None and interpolation != "hold":
        raise SpecError("data.input_interpolation", f"{interpolation!r} applies to an input record (data.input) only")
    models, simulators = [], []
    for i, desc in enumerate(description["models"]):
        models.append(model_of(desc, f"models[{i}]"))
        simulators.append(simulator_for(desc, force, data.get("dt"), observed, f"models[{i}]", allow_import,
                                        interpolation, voltage))
    if voltage is not None and not any(getattr(sim, "voltage", None) is not None for sim in simulators):
        raise SpecError("data.voltage", "no model's simulator reads a voltage record (spencer_mr_voltage does): "
                                        "remove it, or use a simulator that takes it")
    return models, simulators, distance
