"""``run()``: the thin loop that drives a population iterator to its end."""

from __future__ import annotations

import time
from collections.abc import Callable, Generator, Sequence
from dataclasses import asdict

from abcns.blas import limited
from abcns.errors import InvalidSetting
from abcns.executor import Evaluate, Executor, SerialExecutor
from abcns.nested import abc_ns
from abcns.priors import Model
from abcns.rejection import abc_rejection
from abcns.result import Population, Result, RunEnd
from abcns.settings import NSSettings, RejectionSettings, SMCSettings, StopRules, check_seed

Settings = NSSettings | SMCSettings | RejectionSettings


def algorithm_name(settings: Settings) -> str:
    return {NSSettings: "abc-ns", SMCSettings: "abc-smc", RejectionSettings: "rejection"}[type(settings)]


def check_models(models: Sequence[Model]) -> tuple[Model, ...]:
    models = tuple(models)
    if not models:
        raise InvalidSetting(("models",), "at least one model is needed")
    names = [m.name for m in models]
    for i, name in enumerate(names):
        if name in names[:i]:
            raise InvalidSetting(("models", i, "name"), f"duplicate model name {name!r}")
    for i, model in enumerate(models):
        if model.same_model_as is None:
            continue
        where = ("models", i, "same_model_as")
        if model.same_model_as not in names:
            raise InvalidSetting(where, f"names no model of the run: {model.same_model_as!r} (models: {', '.join(names)})")
        first = models[names.index(model.same_model_as)]
        if first.same_model_as is not None:
            raise InvalidSetting(where, f"{first.name!r} is itself the same model as {first.same_model_as!r}: name that one")
        for what in ("parameter_names", "fixed", "config"):
            if getattr(model, what) != getattr(first, what):
                raise InvalidSetting(where, f"{model.name!r} and {first.name!r} differ in {what.replace('_', ' ')} "
                                            f"({getattr(model, what)} against {getattr(first, what)}): only the priors may")
    return models


def iterate(
    models: Sequence[Model],
    executor: Executor,
    settings: Settings,
    stop: StopRules,
    seed: int,
    **kwargs,
) -> Generator[Population, None, RunEnd]:
    """The population iterator of the algorithm ``settings`` selects, each of its steps run
    with one BLAS thread (:func:`abcns.blas.limited`)."""
    from abcns.smc import abc_smc

    models = check_models(models)
    check_seed(seed)
    noise = kwargs.pop("noise", None)  # the noise floor is ABC-NS's (abcns.noise)
    if isinstance(settings, NSSettings):
        return limited(abc_ns(models, executor, settings, stop, seed, noise=noise, **kwargs))
    if isinstance(settings, SMCSettings):
        return limited(abc_smc(models, executor, settings, stop, seed, **kwargs))
    if isinstance(settings, RejectionSettings):
        return limited(abc_rejection(models, executor, settings, stop, seed, **kwargs))
    raise InvalidSetting(("settings",), f"unknown settings type {type(settings).__name__}")


def consume(gen: Generator[Population, None, RunEnd], on_population: Callable[[Population], None]) -> RunEnd:
    """Drive a population iterator to its end: ``on_population`` for each population, then
    the iterator's :class:`RunEnd`."""
    while True:
        try:
            pop = next(gen)
        except StopIteration as done:
            return done.value
        on_population(pop)


def run(
    models: Sequence[Model],
    evaluate: Evaluate | Executor,
    settings: Settings = NSSettings(),
    stop: StopRules = StopRules(),
    seed: int = 0,
    *,
    on_population: Callable[[Population], None] | None = None,
    **kwargs,
) -> Result:
    """Run to the end and return the :class:`Result`.

    ``evaluate`` is a batch evaluator (run in this process) or an executor.
    ``on_population`` is called with each population as it completes.
    """
    executor = evaluate if hasattr(evaluate, "map") else SerialExecutor(evaluate)
    start = time.monotonic()
    gen = iterate(models, executor, settings, stop, seed, **kwargs)
    populations: list[Population] = []

    def keep(pop: Population) -> None:
        populations.append(pop)
        if on_population is not None:
            on_population(pop)

    end = consume(gen, keep)
    return Result(
        algorithm=algorithm_name(settings),
        models=tuple(models),
        populations=tuple(populations),
        stop_reason=end.reason,
        seed=seed,
        settings={"sampler": asdict(settings), "stop": asdict(stop)},
        epsilon_initial_source=end.epsilon_initial_source,
        n_simulations=end.n_simulations,
        n_pilot_simulations=end.n_pilot_simulations,
        wall_time_s=time.monotonic() - start,
        weighted_posterior=isinstance(settings, SMCSettings),
        notes=end.notes,
        mixture=end.mixture,
    )
