"""Traces: what a real run's populations cost, recorded once, replayed by the cluster model.

    python -m benchmarks.cluster_model record [--variant evidence] [--particles 1000] [--populations 10]

A trace is a small JSON file (``benchmarks/cluster_model/traces/``) written by running the job
of ``benchmarks.scale`` (the authors' demo, cubic model, simulated by ``benchmarks.sleepy``) in
this process with an instrumented serial executor. The populations are those of any run of
the job (the random stream is keyed by seed, population and batch, never by the cluster), so
one trace serves every worker count and every sleep per simulation. Per population it holds:

- ``accepted``: the particles each batch accepts (batch size ``job.batch_size`` rows each; the
  population is full at the row that brings the accepted count to ``n_needed``);
- ``evaluator_us``: per batch, the worker's CPU to draw the proposals and simulate them
  (thread CPU, the simulator's sleep left out: the replay adds ``rows x sleep`` itself);
- ``runner_s``: the runner's CPU (thread time) for the population's step: ``finish``
  (:func:`abcns.nested.finish_population`: tolerance, survivors, bounds), ``geometry``
  (:meth:`abcns.nested.Step.evidence`, measured after the next population is opened),
  ``record`` (the population's record), ``open`` (opening the next population) and
  ``consume`` (the filling loop's own work over all batches);
- ``codec_us``: per batch, the CPU to pack a batch's description (runner), unpack it (worker),
  pack its result (worker) and unpack it (runner);
- ``lookahead``: for population t >= 2, ``share``: the share of proposals drawn from
  population t - 1's bounds (its proposal: allocation and box) that fall inside population
  t's bounds (a model still alive), by Monte Carlo from the stored ellipsoids; and
  ``accept``: of ``simulated`` such proposals simulated, the share inside population t's
  bounds and below eps_t (``accept_inside``: the same among those inside), beside
  ``accept_regular``, the population's own acceptance.

And for the whole job: ``store_s``, the runner's CPU for its store: creating it, appending
one population (median) and all of them at once (the runner coalesces appends), a status
change and reading the result back;
``recorded``: this machine, with ``engine_us_per_sim`` and ``evaluator_us_per_sim`` (the same
job with the plain Duffing, serial, in this process: :func:`benchmarks.scale.engine_alone`),
the ratio that carries runner CPU measured here to another machine's figures.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from unittest import mock

import numpy as np

from abcns import bounds as bd
from abcns import ellipsoid as ell
from abcns import nested
from abcns.executor import Draw, Simulated, pack_draws, pack_results, run_draw, unpack_draws, unpack_results
from abcns.filling import Filling, draws
from abcns.rejection import prior_proposer

FORMAT = "abcns-cluster-trace/1"
TRACES = Path(__file__).resolve().parent / "traces"
#: proposals per population for the look-ahead share (its standard error is below 0.004)
SHARE_DRAWS = 20_000
#: look-ahead proposals simulated per population to check their acceptance
LOOKAHEAD_SIMULATED = 2_000


@dataclass
class PopulationTrace:
    """One population of a trace (see the module docstring)."""

    t: int
    epsilon: float
    n_needed: int
    accepted: list[int]
    evaluator_us: list[float]
    simulations: int
    runner_s: dict[str, float]
    codec_us: dict[str, float]
    lookahead: dict[str, float] | None = None


@dataclass
class Trace:
    label: str
    job: dict
    recorded: dict
    store_s: dict[str, float]
    populations: list[PopulationTrace]
    format: str = FORMAT

    @property
    def batch_size(self) -> int:
        return int(self.job["batch_size"])

    @property
    def simulations(self) -> int:
        """The run's simulations (consumed rows: what the algorithm counts)."""
        return sum(p.simulations for p in self.populations)

    def to_json(self) -> str:
        pops = [{k: v for k, v in vars(p).items()} for p in self.populations]
        return json.dumps({"format": self.format, "label": self.label, "job": self.job, "recorded": self.recorded,
                           "store_s": self.store_s, "populations": pops}, indent=1)

    @classmethod
    def from_json(cls, text: str) -> Trace:
        raw = json.loads(text)
        if raw.get("format") != FORMAT:
            raise ValueError(f"not a cluster-model trace of format {FORMAT}: format is {raw.get('format')!r}")
        pops = [PopulationTrace(**p) for p in raw["populations"]]
        for p in pops:
            if len(p.accepted) != len(p.evaluator_us):
                raise ValueError(f"population {p.t}: {len(p.accepted)} batches accepted but "
                                 f"{len(p.evaluator_us)} evaluator times")
        return cls(raw["label"], raw["job"], raw["recorded"], raw["store_s"], pops)

    def save(self, path: Path) -> None:
        path.write_text(self.to_json() + "\n")

    @classmethod
    def load(cls, name_or_path: str | Path) -> Trace:
        path = Path(name_or_path)
        if not path.exists():
            path = TRACES / f"{name_or_path}.json"
        return cls.from_json(path.read_text())


def consumed(accepted: Iterable[int], n_needed: int, batch_size: int) -> tuple[int, int]:
    """(batches consumed, rows consumed) to fill ``n_needed`` from batches accepting
    ``accepted`` particles each, the accepted rows taken as evenly spread in the last batch
    (the trace keeps counts, not rows: the recorder checks this against the real count)."""
    total = 0
    for b, a in enumerate(accepted, start=1):
        if total + a >= n_needed:
            return b, (b - 1) * batch_size + int(np.ceil((n_needed - total) / a * batch_size))
        total += a
    raise ValueError(f"the batches accept {total} particles, fewer than the {n_needed} needed")


# -- recording ---------------------------------------------------------------------------------

@dataclass
class _Log:
    """What the instrumented run saw, population by population."""

    batches: dict[int, list[tuple[int, float]]] = field(default_factory=dict)  # t -> [(accepted, cpu s)]
    runner: dict[int, dict[str, float]] = field(default_factory=dict)  # t -> {part: cpu s}
    codec: dict[int, list[tuple[float, float, float, float]]] = field(default_factory=dict)
    eps: dict[int, float] = field(default_factory=dict)
    needed: dict[int, int] = field(default_factory=dict)

    def add(self, t: int, part: str, seconds: float) -> None:
        parts = self.runner.setdefault(t, {})
        parts[part] = parts.get(part, 0.0) + seconds


class _RecordingExecutor:
    """The serial executor, timing each draw (thread CPU) and its four codec steps."""

    def __init__(self, evaluate, log: _Log):
        self.evaluate, self.log = evaluate, log

    def map(self, draws: Iterable[Draw]) -> Iterator[Simulated]:
        for draw in draws:
            c0 = time.thread_time()
            packed = pack_draws([draw])
            c1 = time.thread_time()
            (unpacked,) = unpack_draws(packed)
            c2 = time.thread_time()
            result = run_draw(self.evaluate, unpacked)
            c3 = time.thread_time()
            out = pack_results([result])
            c4 = time.thread_time()
            (back,) = unpack_results(out)
            c5 = time.thread_time()
            kept = int(np.count_nonzero(back.kept(draw.epsilon, draw.keep_all)))
            self.log.batches.setdefault(draw.population, []).append((kept, c3 - c2))
            self.log.codec.setdefault(draw.population, []).append((c1 - c0, c2 - c1, c4 - c3, c5 - c4))
            self.log.eps[draw.population] = draw.epsilon
            yield back


@contextmanager
def _instrumented(log: _Log) -> Iterator[None]:
    """Time the runner's parts of each population (thread CPU) without changing a result."""
    finish_population, evidence, population_from = nested.finish_population, nested.Step.evidence, nested.population_from
    filling_init, filling_finish = Filling.__init__, Filling.finish
    current = {"t": 0}  # the population being completed

    def timed(part: str, fn: Callable, t_of: Callable[..., int]) -> Callable:
        def wrapper(*args, **kwargs):
            c = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                log.add(t_of(*args, **kwargs), part, time.thread_time() - c)
        return wrapper

    def finish_population_t(*args, **kwargs) -> int:
        current["t"] = args[2]
        return args[2]

    def init(self, propose, n_needed, epsilon, executor, *, seed, t, **kwargs):
        log.needed[t] = int(n_needed)
        # opening population t is part of population t - 1's step (t = 1: the run's start)
        c = time.thread_time()
        filling_init(self, propose, n_needed, epsilon, executor, seed=seed, t=t, **kwargs)
        log.add(t - 1, "open", time.thread_time() - c)
        self._trace_t = t

    def finish(self, budget):
        t = self._trace_t
        before = sum(cpu for _, cpu in log.batches.get(t, []))
        before_codec = sum(sum(c) for c in log.codec.get(t, []))
        c = time.thread_time()
        try:
            return filling_finish(self, budget)
        finally:
            spent = time.thread_time() - c
            evaluated = sum(cpu for _, cpu in log.batches.get(t, [])) - before
            codec = sum(sum(c) for c in log.codec.get(t, [])) - before_codec
            log.add(t, "consume", spent - evaluated - codec)

    with ExitStack() as stack:
        stack.enter_context(mock.patch.object(nested, "finish_population",
                                              timed("finish", finish_population, finish_population_t)))
        stack.enter_context(mock.patch.object(nested.Step, "evidence",
                                              timed("geometry", evidence, lambda *a, **k: current["t"])))
        stack.enter_context(mock.patch.object(nested, "population_from",
                                              timed("record", population_from, lambda *a, **k: a[0])))
        stack.enter_context(mock.patch.object(Filling, "__init__", init))
        stack.enter_context(mock.patch.object(Filling, "finish", finish))
        yield


def _proposer(job, pops: list, t: int):
    """Population t's proposal (t >= 1; population 1: the priors)."""
    if t == 1:
        return prior_proposer(job.models)
    s = job.settings
    frames = tuple(bd.Frame(m, unit=s.evidence) for m in job.models)
    prev = pops[t - 2]
    allocation = prev.evidence.allocation if s.evidence else None
    return nested.BoundProposer(tuple(job.models), frames, prev.ellipsoids, allocation, s.max_redraws)


def _inside_next(job, pops: list, t: int, which: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Which proposals (of any population) lie inside population t's bounds, of a model alive there."""
    s = job.settings
    bounds = pops[t - 2].ellipsoids  # what population t proposes from
    inside = np.zeros(which.shape[0], dtype=bool)
    for m, model in enumerate(job.models):
        rows = np.flatnonzero(which == m)
        if rows.size == 0 or not bounds[m]:
            continue
        frame = bd.Frame(model, unit=s.evidence)
        inside[rows] = ell.n_containing(bounds[m], frame.to_frame(theta[rows, : model.n_dim])) > 0
    return inside


def lookahead(job, pops: list, t: int, rng: np.random.Generator) -> dict[str, float]:
    """Population t's look-ahead rows (t >= 2): drawn from population t - 1's proposal,
    counted when inside population t's bounds (see the module docstring)."""
    propose_prev = _proposer(job, pops, t - 1)
    which, theta, _ = propose_prev(SHARE_DRAWS, rng)
    share = float(np.mean(_inside_next(job, pops, t, which, theta)))
    # simulated: the rows inside, at population t's tolerance
    which, theta, _ = propose_prev(LOOKAHEAD_SIMULATED, rng)
    inside = _inside_next(job, pops, t, which, theta)
    from abcns.executor import Batch

    batch = Batch(t, 0, which, theta, pops[t - 1].epsilon, np.random.SeedSequence(0), np.zeros(which.shape[0], np.int64))
    ev = job.evaluate(batch)
    accepted = inside & (ev.status == 0) & (ev.distances < pops[t - 1].epsilon)
    pop = pops[t - 1]
    return {"share": round(share, 4), "draws": SHARE_DRAWS, "simulated": LOOKAHEAD_SIMULATED,
            "accept": round(float(np.mean(accepted)), 4),
            "accept_inside": round(float(np.count_nonzero(accepted) / max(np.count_nonzero(inside), 1)), 4),
            "accept_regular": round(pop.n_accepted / pop.n_simulations, 4)}


def _store_costs(spec, job, pops: list) -> dict[str, float]:
    """CPU (process: zarr writes on its own thread) of the runner's store work: creating the
    store, one-population appends (median), one append of every population, a status change
    and reading the result back (``run_job`` returns ``result_from_store``); medians of 3."""
    from service.run.store import Store

    def fresh(tmp: Path, name: str) -> Store:
        return Store.create(tmp / name, spec=spec.model_dump(mode="json"), seed=job.seed,
                            model_names=[m.name for m in job.models],
                            parameter_names=[list(m.parameter_names) for m in job.models],
                            n_particles=job.settings.particles, data_hash="trace", algorithm="abc-ns",
                            max_ellipsoids=getattr(job.settings, "n_ellipsoids", 1))

    runs = [_store_run(spec, job, pops, fresh) for _ in range(3)]
    return {k: (round(float(np.median([r[k] for r in runs])), 5) if k != "populations" else len(pops)) for k in runs[0]}


def _store_run(spec, job, pops: list, fresh) -> dict[str, float]:
    from service.run.runner import result_from_store

    with tempfile.TemporaryDirectory(prefix="abcns-trace-") as d:
        tmp = Path(d)
        c = time.process_time()
        store = fresh(tmp, "one.zarr")
        create = time.process_time() - c
        total, singles = 0, []
        for pop in pops:
            total += pop.n_simulations
            c = time.process_time()
            store.append(pop, n_simulations_total=total)
            singles.append(time.process_time() - c)
        store = fresh(tmp, "all.zarr")
        cum = np.cumsum([p.n_simulations for p in pops])
        c = time.process_time()
        store.append_many([(p, int(n)) for p, n in zip(pops, cum)])
        every = time.process_time() - c
        c = time.process_time()
        store.set_status("finished", "max_populations")
        status = time.process_time() - c
        c = time.process_time()
        result_from_store(store)
        read = time.process_time() - c
    return {"create": round(create, 5), "one": round(float(np.median(singles)), 5), "all": round(every, 5),
            "populations": len(pops), "status": round(status, 5), "read": round(read, 5)}


def _commit() -> str | None:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def record(variant: str, particles: int, populations: int, batch_size: int | None = None) -> Trace:
    """Run the job of ``benchmarks.scale`` serially in this process, instrumented; its trace."""
    from abcns import run
    from benchmarks.scale import engine_alone, sleepy_spec
    from service.spec import build

    spec, base = sleepy_spec(populations, batch_size, variant)
    spec = spec.model_copy(update={"sampler": spec.sampler.model_copy(update={"particles": particles})})
    job = build(spec, base, allow_import=True)
    for sim in job.simulators:
        sim.seconds = 0.0  # the sleep is the replay's parameter, not this run's time
    # the kernel loaded first (numba's cache), as on the benchmark's warmed workers, and the
    # engine's compiled parts by one population, as the benchmark's warm-up run loads them in
    # the runner (without it population 1's step carried ~130 ms of loading)
    job.evaluate(next(draws(prior_proposer(job.models), seed=0, t=1, epsilon=np.inf,
                            batch_size=job.settings.batch_size)).batch())
    run(job.models, job.evaluate, job.settings, replace(job.stop, max_populations=1), job.seed)
    log = _Log()
    with _instrumented(log):
        result = run(job.models, _RecordingExecutor(job.evaluate, log), job.settings, job.stop, job.seed)
    pops = list(result.populations)
    engine, evaluator = engine_alone(spec, base)
    rng = np.random.default_rng(np.random.SeedSequence(20261125))
    out = []
    for pop in pops:
        t = pop.t
        batches = log.batches[t]
        codec = np.mean(np.array(log.codec[t]), axis=0) * 1e6
        accepted = [a for a, _ in batches]
        n_batches, rows = consumed(accepted, log.needed[t], job.settings.batch_size)
        if n_batches != len(accepted):
            raise AssertionError(f"population {t}: {len(accepted)} batches run, {n_batches} by the trace's rule")
        if abs(rows - pop.n_simulations) >= job.settings.batch_size:
            raise AssertionError(f"population {t}: {pop.n_simulations} simulations, {rows} by the trace's rule")
        out.append(PopulationTrace(
            t=t, epsilon=float(pop.epsilon), n_needed=log.needed[t], accepted=accepted,
            evaluator_us=[round(1e6 * c) for _, c in batches], simulations=int(pop.n_simulations),
            runner_s={k: round(v, 6) for k, v in sorted(log.runner.get(t, {}).items())},
            codec_us={k: round(float(v), 1) for k, v in zip(("draws", "unpack_draws", "results", "unpack_results"), codec)},
            lookahead=lookahead(job, pops, t, rng) if t >= 2 else None,
        ))
    # the start (population 0: the run before population 1 opens) goes with population 1
    for part, seconds in log.runner.get(0, {}).items():
        out[0].runner_s[f"start_{part}"] = round(seconds, 6)
    import distributed
    import numba

    recorded = {
        "date": datetime.date.today().isoformat(), "commit": _commit(), "cpu_count": os.cpu_count(),
        "load": round(os.getloadavg()[0], 2), "python": platform.python_version(), "numpy": np.__version__,
        "numba": numba.__version__, "distributed": distributed.__version__,
        "engine_us_per_sim": round(engine, 2), "evaluator_us_per_sim": round(evaluator, 2),
    }
    jobinfo = {"name": spec.name, "variant": spec.sampler.variant, "particles": particles,
               "batch_size": job.settings.batch_size, "populations": len(pops), "seed": job.seed,
               "simulator": "benchmarks.sleepy (the built-in Duffing, then a sleep per simulation)"}
    bs = job.settings.batch_size
    label = f"{spec.sampler.variant}-{particles}" + ("" if bs == 25 else f"-b{bs}")
    return Trace(label, jobinfo, recorded, _store_costs(spec, job, pops), out)
