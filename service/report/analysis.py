"""Store-level analysis: rebuild a finished job's data and simulators from the spec in its
store, then posterior predictive bands and NMSE on the fit and test windows
(:mod:`abcns.analysis` does the maths; this module only supplies the simulations).

The spec in a store names its data files relative to the spec file, which the store does
not know: pass ``base_dir`` (the spec file's directory). The data are checked against the
store's data hash, so a plot never mixes a run with other data.

A simulator that draws a sample rather than following an input (``needs_input`` False, the
g-and-k) is simulated with a seeded generator, and its records are compared as order
statistics: the observed record and every simulated one are sorted, so the predictive bands
and the NMSE are those of the quantile function (the draws' order means nothing).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from abcns import OK, Model, Result
from abcns.analysis import Confusion, Predictive, confusion, fit_test_nmse, nmse, predictive
from service.run.store import Store, data_hash
from service.spec import JobSpec, load_data, load_voltage, model_description, parse, spec_errors
from worker.compose import check_model, full_parameters
from worker.description import model_of, simulator_for
from worker.simulators import Simulator


@dataclass(frozen=True, eq=False)
class JobData:
    """A job's records, windows and one full-length simulator per model."""

    spec: JobSpec
    force: np.ndarray | None
    observed: np.ndarray
    dt: float | None
    fit: tuple[int, int]
    test: tuple[int, int] | None
    models: dict[str, Model]
    simulators: dict[str, Simulator]
    sorted_samples: bool = False  # the simulators draw samples: records compared sorted (order statistics)

    def simulate(self, model: str, seed: int = 0) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """``simulate(theta (n, d)) -> (values (n, T), status (n,))`` of one model over the
        whole record: its free parameters, then its fixed values, then the simulator's
        defaults, as the evaluator maps them. A stochastic simulator draws from
        ``default_rng(seed)`` afresh at each call; with ``sorted_samples`` each row is sorted."""
        sim = self.simulators[model]
        expand = full_parameters(self.models[model], sim)

        def simulate(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            out = sim.simulate(expand(theta), np.random.default_rng(seed))
            values = np.sort(out.values, axis=1) if self.sorted_samples else out.values
            return np.ascontiguousarray(values), out.status

        return simulate


def job_data(spec: dict | JobSpec, base_dir: str | Path | None, expect_hash: str | None = None,
             allow_import: bool = True) -> JobData:
    """The job's data and simulators (whole record, not cut at the fit window)."""
    spec = spec if isinstance(spec, JobSpec) else parse(spec)
    base = Path(base_dir) if base_dir is not None else None
    force, observed = load_data(spec, base)
    voltage = load_voltage(spec, base)
    if expect_hash is not None:
        got = data_hash(*(a for a in (force, observed, voltage) if a is not None))
        if got != expect_hash:
            raise ValueError(f"the data under {base} are not the data this store was run on (hash {got[:12]} != "
                             f"{expect_hash[:12]}); pass the directory of the spec the store was run from")
    dt = spec.data.sample_interval if spec.data.input is not None else None
    models, sims = {}, {}
    with spec_errors():
        for i, desc in enumerate(map(model_description, spec.models)):
            m = model_of(desc, i)
            sim = simulator_for(desc, force, dt, observed, i, allow_import, spec.data.input_interpolation, voltage)
            check_model(m, sim, ("models", i))
            models[m.name], sims[m.name] = m, sim
    fit = spec.data.fit or (0, observed.size)  # tuples already: the spec's Windows (pydantic)
    test = spec.data.test or None
    samples = all(getattr(s, "needs_input", None) is False for s in sims.values())
    return JobData(spec, force, np.sort(observed) if samples else observed, dt, fit, test, models, sims, samples)


def store_job_data(store: Store, base_dir: str | Path | None) -> JobData:
    return job_data(store.attrs["spec"], base_dir, store.attrs.get("data_hash"))


def open_run(spec_path: str | Path, store_path: str | Path) -> tuple[JobSpec, Path, Store, Result, JobData]:
    """A finished run of an example: (the spec it ran with, the spec file's folder, its
    store, its result, its data and simulators)."""
    from service.run.runner import result_from_store
    from service.spec import load

    _, base = load(spec_path)
    store = Store.open(store_path)
    return parse(store.attrs["spec"]), base, store, result_from_store(store), store_job_data(store, base)


def predictions(result: Result, data: JobData, n_draws: int | None = None, seed: int = 0
                ) -> tuple[dict[str, Predictive], dict[str, dict]]:
    """Per alive model of the final population: its posterior predictive over the whole
    record (every particle, or ``n_draws`` draws with ``default_rng(seed)``) and the NMSE
    of its posterior mean and best particle on the fit (and test) window."""
    preds, scores = {}, {}
    windows = {"fit": data.fit, "test": data.test}
    for i in result.alive():
        name = result.models[i].name
        sim = data.simulate(name, seed)
        preds[name] = predictive(result, name, sim, n_draws, np.random.default_rng(seed))
        scores[name] = fit_test_nmse(result, name, sim, data.observed, windows)
    return preds, scores


def confusion_of(results: list[Result], datas: list[JobData], labels: list[str] | None = None,
                 point: str = "posterior_mean") -> Confusion:
    """§5.4: the model fitted on data set i (``results[i]``, run on ``datas[i]``) scored by
    the NMSE of its ``point`` estimate on data set j's test window (its fit window when it
    has none), simulated with data set j's input."""

    def score(model: str, theta: np.ndarray, j: int) -> float:
        values, status = datas[j].simulate(model)(theta[None, :])
        window = datas[j].test or datas[j].fit
        return float(nmse(values[0], datas[j].observed, window)) if status[0] == OK else float("inf")

    return confusion(results, score, labels, point=point)


def run_to_store(spec: JobSpec, base_dir: str | Path | None, out: str | Path, seed: int | None = None,
                 on_population: Callable | None = None) -> Result:
    """:func:`service.run.runner.run_job` in this process (the serial executor, no Dask) into the
    store ``out``: the same store ``abcns run`` writes, the same populations. For the
    examples, the analysis and the tests; ``on_population`` gets each Population."""
    from service.run.runner import run_job

    progress = (lambda p: on_population(p.population)) if on_population is not None else None
    base = Path(base_dir) if base_dir is not None else None
    return run_job(spec, base, Path(out), None, seed=seed, on_population=progress, allow_import=True)


def fit_alone(spec: JobSpec, base_dir: str | Path | None, model: str, out: str | Path, *, name: str,
              seed: int | None = None) -> tuple[Result, JobData]:
    """Model ``model`` of ``spec`` fitted on its own (same data, sampler and stop rules, job
    ``name``), run into the store ``out`` unless it exists; its result and data."""
    from service.run.runner import result_from_store

    if not Path(out).exists():
        alone = spec.model_copy(update={"models": [m for m in spec.models if m.name == model], "name": name})
        run_to_store(alone, base_dir, out, seed=seed)
    store = Store.open(out)
    return result_from_store(store), store_job_data(store, base_dir)
