"""Compose models, simulators and a distance into a batch evaluator.

``evaluator(models, simulators, distance)`` returns ``evaluate(batch) -> Evaluated``:
each model's rows are expanded to the simulator's full parameter vector (free values,
then fixed values, then the simulator's defaults), simulated as one batch, and scored
by the distance; rows that are not OK get distance +inf. A simulator that raises a numerical
error fails only the rows that raise it; any other exception fails the job with a message
naming the model and its simulator (:func:`abcns.executor.per_model`).

``job_evaluator(description, arrays)`` builds the same from a JSON-able job description
(the spec's models, distance and data settings) and the data arrays; it is what a Dask
worker runs, once per worker and job (:func:`evaluate_on_worker` caches it).

When the distance is an :class:`abcns.distances.NMSE` and the simulator is
:class:`~worker.simulators.NMSECapable` (the built-in oscillators), the NMSE is computed inside the simulator
(no trajectory array) with early rejection at the batch's epsilon: a particle whose partial
NMSE reaches epsilon stops and reports that partial NMSE (>= epsilon, so it is rejected as
it would have been). Other distances take the generic path.
"""

from __future__ import annotations

import inspect
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence

import numpy as np

from abcns.distances import NMSE, Distance, SummaryEuclidean
from abcns.executor import OK, Evaluate, SimulateDistanceEpsilon, pack_results, per_model, run_draw, unpack_draws
from abcns.priors import Model, SpecError
from worker import registry
from worker.simulators import NMSECapable, Range, Simulator


def check_model(model: Model, simulator: Simulator, where: str) -> None:
    """Every simulator parameter is inferred, fixed or defaulted; no unknown names."""
    names = tuple(simulator.parameter_names)
    for key in model.priors:
        if key not in names:
            raise SpecError(f"{where}.priors.{key}", f"is not a parameter of {simulator.name} {names}")
    for key in model.fixed:
        if key not in names:
            raise SpecError(f"{where}.fixed.{key}", f"is not a parameter of {simulator.name} {names}")
    missing = [p for p in names if p not in model.priors and p not in model.fixed and p not in simulator.defaults]
    if missing:
        raise SpecError(f"{where}.priors", f"parameters {missing} of {simulator.name} need a prior or a fixed value")


def check_ranges(model: Model, simulator: Simulator, where: str) -> None:
    """The model's fixed values and priors lie in the valid ranges its simulator states
    (``simulator.ranges``, :class:`worker.simulators.Range`); a SpecError naming the field
    (``models[1].fixed.n``) otherwise. A simulator without ``ranges`` states none."""
    ranges: dict[str, Range] = getattr(simulator, "ranges", None) or {}
    for key, value in model.fixed.items():
        valid = ranges.get(key)
        if valid is not None and not valid.holds(float(value)):
            raise SpecError(f"{where}.fixed.{key}", f"must be {valid} for simulator {simulator.name}, got {value!r}")
    for key, prior in model.priors.items():
        valid = ranges.get(key)
        if valid is None or valid.holds_prior(prior.low, prior.high):
            continue
        if valid.integer:
            raise SpecError(f"{where}.priors.{key}", f"{key} of simulator {simulator.name} is {valid}: fix it "
                            f"(fixed: {{{key}: ...}}), it cannot have a uniform prior")
        raise SpecError(f"{where}.priors.{key}", f"[{prior.low:g}, {prior.high:g}] leaves the valid range of {key} "
                        f"for simulator {simulator.name}: {valid}")


def full_parameters(model: Model, simulator: Simulator) -> Callable[[np.ndarray], np.ndarray]:
    """The one mapping from a model's free parameters (n, d) to the simulator's full
    parameter vectors (n, p): the free ones in the simulator's columns, then the model's
    fixed values, then the simulator's defaults for what the model neither fixes nor infers
    (a default never overrides an inferred parameter)."""
    names = tuple(simulator.parameter_names)
    free = [names.index(p) for p in model.priors]
    const = {p: v for p, v in {**simulator.defaults, **model.fixed}.items() if p not in model.priors}
    const_cols = [names.index(p) for p in const if p in names]
    const_vals = np.array([const[names[j]] for j in const_cols])

    def expand(theta: np.ndarray) -> np.ndarray:
        theta = np.atleast_2d(theta)
        full = np.empty((theta.shape[0], len(names)))
        full[:, free] = theta
        full[:, const_cols] = const_vals
        return full

    return expand


def model_function(model: Model, simulator: Simulator, distance: Distance) -> SimulateDistanceEpsilon:
    """``f(theta, rng, epsilon=inf) -> (distances, status)`` for one model."""
    expand = full_parameters(model, simulator)
    # the fast path needs both: the distance is the NMSE, and the simulator can compute it
    nmse = distance if isinstance(distance, NMSE) else None
    capable = simulator if isinstance(simulator, NMSECapable) else None

    def simulate_distance(theta: np.ndarray, rng: np.random.Generator,
                          epsilon: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        full = expand(theta)
        if nmse is not None and capable is not None:
            return capable.distance_nmse(full, nmse.observed, nmse.start, nmse.stop, epsilon)
        out = simulator.simulate(full, rng)
        d = np.full(theta.shape[0], np.inf)
        ok = out.status == OK
        if ok.any():
            d[ok] = distance(out.values[ok])
        return d, out.status

    # the in-kernel NMSE is deterministic: the batch's generator need not be made for it
    simulate_distance.uses_rng = nmse is None or capable is None  # type: ignore[attr-defined]
    return simulate_distance


def evaluator(models: Sequence[Model], simulators: Sequence[Simulator], distance: Distance,
              early_rejection: bool = True) -> Evaluate:
    """The batch evaluator; ``early_rejection`` passes each batch's epsilon to the simulators."""
    if len(models) != len(simulators):
        raise ValueError(f"{len(models)} models but {len(simulators)} simulators")
    n_observed = int(np.size(distance.observed))
    for i, (model, sim) in enumerate(zip(models, simulators, strict=True)):
        check_model(model, sim, f"models[{i}]")
        check_ranges(model, sim, f"models[{i}]")
        if sim.n_samples != n_observed:
            raise SpecError(
                "data.observed",
                f"has {n_observed} samples but model {model.name!r} simulates {sim.n_samples} "
                "(input and observed records must have the same length)",
            )
    pairs = list(zip(models, simulators, strict=True))
    return per_model([model_function(m, s, distance) for m, s in pairs], pass_epsilon=early_rejection,
                     names=[f"model {m.name!r} (simulator {m.config.get('simulator', s.name)!r})" for m, s in pairs])


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


def simulator_for(desc: dict, force: np.ndarray | None, dt: float | None, observed: np.ndarray, where: str,
                  allow_import: bool = False, input_interpolation: str = "hold") -> Simulator:
    """The simulator a job builds for one model description, over the record given (the
    evaluator passes the record up to the fit end; the analysis the whole record).

    How the factory is called depends on its ``needs_input`` attribute:

    - False (g-and-k): ``factory(n_samples=observed.size)``;
    - True (the oscillators): the input is required (a SpecError on ``data.input`` without
      it) and the factory gets those of :data:`INPUT_KEYWORDS` (``force``, ``dt``,
      ``n_samples``, ``substeps``, ``output``, ``state_bound``, ``input_interpolation``) its
      signature names, e.g. ``Linear`` (exact, no substeps) gets no ``substeps``; a factory
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
        if input_interpolation != "hold" and "input_interpolation" not in accepted:
            raise SpecError("data.input_interpolation", f"simulator {desc['simulator']!r} does not take "
                            f"input_interpolation; only 'hold' (the default) is possible with it")
        return factory(**accepted)
    except SpecError as err:
        field = err.field if err.field.startswith("data") else f"{where}.{err.field}"
        raise SpecError(field, err.message) from None


def job_evaluator(description: dict, arrays: dict, allow_import: bool = False) -> tuple[list[Model], Evaluate]:
    """(models, evaluate) from a job description and its data (:func:`job_parts`)."""
    models, simulators, distance = job_parts(description, arrays, allow_import)
    return models, evaluator(models, simulators, distance)


def job_parts(description: dict, arrays: dict,
              allow_import: bool = False) -> tuple[list[Model], list[Simulator], Distance]:
    """(models, simulators, distance) of a job description and its data.

    ``description``: ``{"models": [{name, simulator, priors, fixed, integrator}], "distance":
    {name: nmse | summary_euclidean, summaries}, "data": {"dt": float | None, "fit": [a, b] | None,
    "input_interpolation": "hold" | "linear" (default hold)}}``;
    ``arrays``: ``{"force": array | None, "observed": array}``. ``allow_import`` lets a
    model name a ``package.module:factory`` simulator (the CLI; never HTTP). Without
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
    data = description.get("data", {})
    dist = description.get("distance", {"name": "nmse"})
    if dist["name"] == "nmse":
        nmse = NMSE(observed, data.get("fit"))
        if force is not None and np.size(force) == observed.size and nmse.stop < observed.size:
            # nothing after the fit window is scored: simulate only up to its end
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
                                        interpolation))
    return models, simulators, distance


_CACHE: OrderedDict[str, Evaluate] = OrderedDict()
_CACHE_SIZE = 8


def job_payload(description: dict, arrays: dict, allow_import: bool = False) -> dict:
    """The Dask task that holds a job's description and data on the workers.

    It is a task, not scattered data, on purpose: the scheduler keeps its inputs, so when
    every worker holding the result dies it is computed again and the batches that need it
    wait instead of failing. (Scattered data has no such lineage, and the scheduler's active
    memory manager drops the replicas that ``broadcast=True`` made.)"""
    return {"description": description, "arrays": arrays, "allow_import": allow_import}


def anchor(_: int) -> None:
    """A no-op task: the Dask executor holds a few of them as the first tasks of a run's task
    group (``service.run.dask_executor``), so the scheduler queues the run's batches. Here, in
    the module every batch task comes from, so a worker imports nothing else to run it."""


def evaluate_on_worker(job_key: str, payload: dict, draws: bytes) -> tuple[bytes, float]:
    """The Dask task: run consecutive draws of job ``job_key`` (``abcns.executor.pack_draws``;
    proposals drawn here, then simulated); return their results (``pack_results``: one bytes
    object, which Dask sends as it is) and the seconds it took.
    ``payload`` (the result of :func:`job_payload`, sent once per job) is turned into an
    evaluator once per worker process and kept for the job's later batches."""
    start = time.perf_counter()
    evaluate = _CACHE.get(job_key)
    if evaluate is None:
        _, evaluate = job_evaluator(payload["description"], payload["arrays"], payload.get("allow_import", False))
        _CACHE[job_key] = evaluate
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    else:
        _CACHE.move_to_end(job_key)
    results = [run_draw(evaluate, draw) for draw in unpack_draws(draws)]
    return pack_results(results), time.perf_counter() - start
