"""A job's description, what a worker builds the job from: :class:`JobDescription` (its
models :class:`ModelDescription`), plain typed data that ``service.spec.build`` makes once, and
its records, made into :func:`model_of` (-> :class:`abcns.Model`), :func:`simulator_for` (the
registry's factory over the record) and :func:`job_parts` (models, simulators, distance).
Errors: :class:`abcns.errors.InvalidSetting` at the description's paths (``("models", 0,
"substeps")``, ``("force",)``: the input record), which ``service.spec`` maps to the spec's.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from abcns.distances import NMSE, Distance, SummaryEuclidean
from abcns.errors import InvalidSetting
from abcns.priors import Model
from worker import registry
from worker.simulators import Simulator


@dataclass(frozen=True)
class ModelDescription:
    """One candidate model: the registered simulator's name (or ``package.module:factory``
    where imports are allowed), the priors ``{name: (low, high)}`` (``(low, high, "log")``:
    log-uniform), fixed values, the integrator's RK4 ``substeps`` per sample (None: chosen
    from the priors) and ``output``, and ``same_model_as`` (:class:`abcns.Model`'s)."""

    name: str
    simulator: str
    priors: Mapping[str, tuple[Any, ...]]
    fixed: Mapping[str, float] = field(default_factory=dict)
    substeps: int | None = None
    output: str = "displacement"
    same_model_as: str | None = None


@dataclass(frozen=True)
class JobDescription:
    """What a worker builds a job's evaluator from, besides its records: the models, the
    distance (``nmse`` or ``summary_euclidean`` with its ``summaries``, None: ``gk``), the
    sample interval ``dt`` (None without an input record), the NMSE's ``fit`` window
    (None: the whole record) and how the input is read between samples."""

    models: tuple[ModelDescription, ...]
    distance: str = "nmse"
    summaries: str | None = None
    dt: float | None = None
    fit: tuple[int, int] | None = None
    input_interpolation: str = "hold"


#: the paths a simulator's factory raises at that belong to its model (behind ``("models", i)``):
#: the model's fields and the integrator's other keyword; the rest name the job's records and fields
MODEL_FIELDS = frozenset({"name", "simulator", "priors", "fixed", "substeps", "output", "backend"})


def model_of(desc: ModelDescription, index: int) -> Model:
    """The :class:`abcns.Model` of the job's model ``index`` (errors at ``("models", index, ...)``)."""
    priors: dict[str, Any] = dict(desc.priors)  # [low, high] or [low, high, "log"]: Model checks them
    try:
        return Model(desc.name, priors, dict(desc.fixed), config={"simulator": desc.simulator},
                     same_model_as=desc.same_model_as)
    except InvalidSetting as err:
        raise err.within("models", index) from None


def parameter_bounds(desc: ModelDescription, factory: Any) -> dict[str, tuple[float, float]]:
    """Each simulator parameter's range in the model: its prior, or its fixed or default value."""
    b = {k: (float(v), float(v)) for k, v in getattr(factory, "defaults", {}).items()}
    b.update({k: (float(v), float(v)) for k, v in desc.fixed.items()})
    b.update({k: (float(prior[0]), float(prior[1])) for k, prior in desc.priors.items()})
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


def simulator_for(desc: ModelDescription, force: np.ndarray | None, dt: float | None, observed: np.ndarray,
                  index: int, allow_import: bool = False, input_interpolation: str = "hold",
                  voltage: np.ndarray | None = None) -> Simulator:
    """The simulator a job builds for its model ``index``, over the record given (the
    evaluator passes the record up to the fit end; the analysis the whole record).

    How the factory is called depends on its ``needs_input`` attribute:

    - False (g-and-k): ``factory(n_samples=observed.size)``;
    - True (the oscillators): the input is required (an InvalidSetting at ``("force",)``
      without it) and the factory gets those of :data:`INPUT_KEYWORDS` (``force``, ``dt``,
      ``n_samples``, ``substeps``, ``output``, ``state_bound``, ``input_interpolation``) its
      signature names, e.g. ``Linear`` (exact, no substeps) gets no ``substeps``, and
      ``voltage`` (the second input channel, or None) when its signature names it
      explicitly (not through ``**kwargs``: plugins written before it); a factory that does
      not take ``input_interpolation`` cannot be asked for anything but ``hold`` (an
      InvalidSetting at ``("input_interpolation",)``);
    - absent (a plugin written before ``needs_input``): as True, except that the input may
      be missing (``force=None``), as plugins have always been called.

    Errors at a model's field (:data:`MODEL_FIELDS`) are put behind ``("models", index)``.
    """
    try:
        factory = registry.get(desc.simulator, allow_import=allow_import)
        needs_input = getattr(factory, "needs_input", None)
        if needs_input is False:
            return factory(**_accepted(factory, {"n_samples": int(observed.size)}))
        if needs_input and force is None:
            raise InvalidSetting(("force",), f"simulator {desc.simulator!r} needs an input force")
        substeps = _substeps(desc, factory, dt)
        # the divergence guard: 1000 x the observed scale (for a displacement output)
        bound = 1e3 * float(np.max(np.abs(observed))) if desc.output == "displacement" else np.inf
        offered = dict(zip(INPUT_KEYWORDS, (force, dt, int(observed.size), substeps, desc.output, bound,
                                            input_interpolation), strict=True))
        accepted = _accepted(factory, offered)
        if _names_explicitly(factory, "voltage"):
            accepted["voltage"] = voltage
        if input_interpolation != "hold" and "input_interpolation" not in accepted:
            raise InvalidSetting(("input_interpolation",), f"simulator {desc.simulator!r} does not take "
                                 f"input_interpolation; only 'hold' (the default) is possible with it")
        return factory(**accepted)
    except InvalidSetting as err:
        raise (err.within("models", index) if err.path[0] in MODEL_FIELDS else err) from None


def _substeps(desc: ModelDescription, factory: Any, dt: float | None) -> int | None:
    """The model's RK4 substeps per sample: given (at most :data:`MAX_SUBSTEPS`), or chosen
    from the priors for a factory with ``omega_max`` (``worker.kernels.choose_substeps``), else 1."""
    if desc.substeps is not None:
        if isinstance(desc.substeps, int) and desc.substeps > MAX_SUBSTEPS:
            raise InvalidSetting(("substeps",), f"at most {MAX_SUBSTEPS:.0e} RK4 substeps per sample (no simulation "
                                                f"of more ends), got {_many(desc.substeps)}")
        return desc.substeps
    if dt is None or not callable(getattr(factory, "omega_max", None)):
        return 1
    from worker.kernels import choose_substeps

    try:
        chosen = choose_substeps(factory.omega_max(parameter_bounds(desc, factory)), dt)
    except (KeyError, ValueError, OverflowError) as err:  # Overflow: dt x omega past any int
        raise InvalidSetting(("substeps",), f"cannot be chosen from the priors ({err}); give it") from None
    if chosen > MAX_SUBSTEPS:
        raise InvalidSetting(("substeps",), f"the priors' highest natural frequency and the sample interval {dt:.6g} "
                             f"s ask for {_many(chosen)} RK4 substeps per sample, more than {MAX_SUBSTEPS:.0e}, which "
                             "no simulation ends: check the sample interval (decimate the records) and the priors")
    return chosen


def _aligned(array: np.ndarray | None) -> np.ndarray | None:
    return None if array is None else np.require(array, dtype=float, requirements=("C", "A"))


def _distance(description: JobDescription, force: np.ndarray | None, observed: np.ndarray,
              voltage: np.ndarray | None) -> tuple[Distance, np.ndarray | None, np.ndarray, np.ndarray | None]:
    """The job's distance, and the records cut to the NMSE's fit window's end (nothing after
    it is scored: only that much is simulated)."""
    if description.distance == "summary_euclidean":
        return SummaryEuclidean(observed, description.summaries or "gk"), force, observed, voltage
    if description.distance != "nmse":
        raise InvalidSetting(("distance",), f"unknown distance {description.distance!r}")
    nmse = NMSE(observed, description.fit)
    if force is not None and np.size(force) == observed.size and nmse.stop < observed.size:
        if voltage is not None and voltage.size == observed.size:
            voltage = voltage[: nmse.stop]
        force, observed = force[: nmse.stop], observed[: nmse.stop]
        nmse = NMSE(observed, (nmse.start, nmse.stop))
    return nmse, force, observed, voltage


def job_parts(description: JobDescription, arrays: Mapping[str, np.ndarray | None],
              allow_import: bool = False) -> tuple[list[Model], list[Simulator], Distance]:
    """(models, simulators, distance) of a job description and its data.

    ``arrays``: ``{"force": array | None, "observed": array, "voltage": array (optional: the
    second input channel of the simulators that read it; refused when none does)}``.
    ``allow_import`` lets a model name a ``package.module:factory`` simulator (the CLI; never
    HTTP). Without ``substeps`` a simulator with ``omega_max`` gets substeps from
    ``worker.kernels.choose_substeps`` (RK4 error below 1e-4 per radian at the highest
    natural frequency the priors allow). Raises InvalidSetting at the description's path.

    The arrays are copied into aligned memory when they are not (data that came over the
    wire can sit at any byte offset): numpy's reductions take another loop on unaligned
    data and round differently, which made a worker's distances differ from the runner's
    in the last bit.
    """
    observed = _aligned(arrays["observed"])
    assert observed is not None
    distance, force, observed, voltage = _distance(description, _aligned(arrays.get("force")), observed,
                                                   _aligned(arrays.get("voltage")))
    interpolation = description.input_interpolation
    if force is None and interpolation != "hold":
        raise InvalidSetting(("input_interpolation",), f"{interpolation!r} applies to an input record only, and the job has none")
    models, simulators = [], []
    for i, desc in enumerate(description.models):
        models.append(model_of(desc, i))
        simulators.append(simulator_for(desc, force, description.dt, observed, i, allow_import, interpolation, voltage))
    if voltage is not None and not any(getattr(sim, "voltage", None) is not None for sim in simulators):
        raise InvalidSetting(("voltage",), "no model's simulator reads a voltage record (spencer_mr_voltage does): "
                                           "remove it, or use a simulator that takes it")
    return models, simulators, distance
