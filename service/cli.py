"""The ``abcns`` command line.

    abcns run SPEC --out STORE [--scheduler tcp://HOST:PORT | --workers N] [--seed N] [--quiet] [--json] [--dashboard]
    abcns run SPEC [SPEC ...] --out-dir DIR [the same options]
    abcns summary STORE [--json]
    abcns plot STORE [STORE ...] --out DIR [--spec SPEC ...]
    abcns serve [...]
    abcns submit SPEC [--url URL] [--token TOKEN] [--quiet] [--json]
    abcns --version

``run`` and ``submit`` print a line per population (not with ``--quiet``) and end with a
short summary (the full JSON summary with ``--json``, or later with ``abcns summary STORE
--json``). ``run`` with ``--out-dir`` runs each spec as a job of its own on the cluster's
workers (:mod:`service.run.jobs`), a store per job, a line per population of each job
prefixed with its store's name, then each job's summary. With the paper's NMSE (Eq. 7) the
tolerances and distances are in percent and marked ``%``. Errors are one line on stderr,
with an exit code per kind (:data:`EXIT_CODES`).
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import socket
import sys
import time
from collections.abc import Callable, Mapping
from contextlib import ExitStack
from functools import partial
from pathlib import Path
from typing import Annotated, Any, NoReturn, cast

import typer

from abcns import SpecError
from abcns.executor import BatchError

#: the exit codes of every command (README, Command line)
BAD_INPUT, UNREACHABLE, JOB_FAILED, REFUSED = 2, 3, 4, 5
EXIT_CODES = {0: "done", 1: "an unexpected error (a bug: please report it)",
              BAD_INPUT: "the spec, its data or an option is wrong (here, or as the service says)",
              UNREACHABLE: "the scheduler or the service cannot be reached",
              JOB_FAILED: "the job failed or was cancelled", REFUSED: "the service refused the request (token, full queue)"}

app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode=None,
                  help="ABC-NS inference for dynamical systems. Exit codes: "
                       + "; ".join(f"{k} {v}" for k, v in EXIT_CODES.items()) + ".")


def _fail(message: str, code: int = BAD_INPUT) -> NoReturn:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            typer.echo(f"abcns {version('abcns')}")
        except PackageNotFoundError:  # run from a checkout that is not installed
            from abcns import __version__

            typer.echo(f"abcns {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
) -> None:
    """ABC-NS inference for dynamical systems."""


def percent(distance: str | None) -> str:
    """The unit of a distance: the NMSE of Eq. 7 is in percent (100 / (n s^2) ...)."""
    return " %" if distance in (None, "nmse") else ""


def distance_of(spec: dict | None) -> str:
    return ((spec or {}).get("distance") or {}).get("name", "nmse")


def summary_lines(s: dict, distance: str = "nmse") -> list[str]:
    """The human summary of a job's JSON summary: status, tolerances, model probabilities,
    the posterior of every model still alive; for a run that stopped before its first
    population, why (its notes)."""
    unit = percent(distance)
    lines = [f"status {s['status']}  stop {s.get('stop_reason') or '-'}  populations {s['n_populations']}  "
             f"simulations {s.get('n_simulations') or 0:,}  wall {s.get('wall_time_s') or 0:.1f} s"]
    if s.get("epsilon"):
        what = "tolerance (NMSE)" if unit else "tolerance"
        lines.append(f"{what} {s['epsilon'][0]:.4g}{unit} -> {s['epsilon'][-1]:.4g}{unit}; "
                     f"mean acceptance {sum(s['acceptance_rate']) / len(s['acceptance_rate']):.2f}")
    se = s.get("model_probability_se") or {}
    if s.get("model_probabilities"):
        lines.append("model probabilities: " + ", ".join(
            f"{k} {v:.3f}" + (f" ± {se[k]:.3f}" if se.get(k) is not None and se[k] == se[k] else "")
            for k, v in s["model_probabilities"].items()) + where_decided(s, unit))
        lines += decision_lines(s, unit)
    if not s.get("n_populations"):  # no population: the run's notes say why it stopped (nothing_accepted)
        lines += [f"note: {note}" for note in s.get("notes", [])]
    if s.get("dead_models"):
        lines.append("models out: " + "; ".join(f"{k} from population {t} ({death_rule(s, k)})"
                                                 for k, t in s["dead_models"].items()))
    lines += [f"warning: {w}" for w in s.get("warnings", [])]
    if s.get("error"):
        lines.append(f"error: {s['error']}")
    for model, params in s.get("posterior", {}).items():
        lines.append(f"{model}:")
        for name, q in params.items():
            lines.append(f"  {name:8s} mean {q['mean']:12.6g}  std {q['std']:10.4g}  95% [{q['q2_5']:.6g}, {q['q97_5']:.6g}]")
    return lines


def print_summary(s: dict, distance: str, as_json: bool, footer: str | None = None) -> None:
    """A job's JSON summary ``s`` as JSON, or as :func:`summary_lines`; with a ``footer`` (where
    the full summary is), a blank line before the lines and the footer after them."""
    if as_json:
        typer.echo(json.dumps(s, indent=2))
        return
    if footer is not None:
        typer.echo("")
    for text in summary_lines(s, distance):
        typer.echo(text)
    if footer is not None:
        typer.echo(footer)


def where_decided(s: dict, unit: str) -> str:
    """Where the answer is read: the decision population and its tolerance (``summary.decision``)."""
    dec = s.get("decision")
    if not dec:
        return ""
    if s.get("noise_floor") is None:
        return f"  (final population {dec['population']}, eps {dec['epsilon']:.4g}{unit}; no noise floor for this distance)"
    state = (f"PROVISIONAL: stopped ({dec['rule']}) above the decision tolerance, at " if dec.get("provisional")
             else "the answer: ")
    if dec.get("reading") == "likelihood":
        return (f"  ({state}every population to {dec['population']}, eps {dec['epsilon']:.4g}{unit}, weighted by the "
                "likelihood of the noise)")
    return f"  ({state}population {dec['population']}, eps {dec['epsilon']:.4g}{unit})"


def decision_lines(s: dict, unit: str) -> list[str]:
    """The noise floor and the decision tolerance (docs/design.md, "The noise floor and the
    decision tolerance"), and the final population's probabilities when it is another."""
    floor, dec, final = s.get("noise_floor"), s.get("decision"), s.get("final")
    if floor is None or not dec:
        return []
    how = ("estimated from the run's best fit" if floor["method"] == "estimated"
           else "from the stated noise, data.noise_std")
    where = ("the run stops there and its populations are read by the likelihood" if dec.get("reading") == "likelihood"
             else "the answer is read at the lowest tolerance at or above it")
    lines = [f"noise floor {floor['floor']:.4g}{unit} ({how}); decision tolerance {floor['decision_tolerance']:.4g}{unit} "
             f"(floor + its spread): {where}"]
    if dec.get("effective_particles"):
        lines.append("effective particles of the reading: " + ", ".join(
            f"{k} {v:.0f}" for k, v in dec["effective_particles"].items()))
    if final and final["population"] != dec["population"] and dec.get("reading") != "likelihood":
        probs = ", ".join(f"{k} {v:.3f}" for k, v in final["model_probabilities"].items())
        lines.append(f"model probabilities at the final population {final['population']}, eps {final['epsilon']:.4g}{unit} "
                     f"(below the decision tolerance, where the noise decides; not the answer): {probs}")
    return lines


def death_rule(s: dict, model: str) -> str:
    """Why a model is out, in words: the rule that ended it (``death_rules``; the evidence
    variant), else it had no particle left (the paper's variant)."""
    rule = (s.get("death_rules") or {}).get(model)
    if rule == "probability":
        floor = ((s.get("settings") or {}).get("sampler") or {}).get("min_model_probability") or 1e-3
        return f"its probability + 3 standard errors fell below {floor:g}"
    if rule == "no_particles":
        return "no particle below the next tolerance"
    return rule or "no particle left"


def memory_warning(job) -> None:
    """No admission limits on the user's own machine: a warning when the job's memory
    estimate (service.http.limits.memory_estimate) exceeds half of this machine's memory."""
    import psutil

    from service.http.limits import memory_estimate

    need, have = memory_estimate(job)["total"], psutil.virtual_memory().total
    if need > have / 2:
        typer.echo(f"warning: this job may need about {need / 2**30:.1f} GiB (particles x parameters x populations; "
                   f"this machine has {have / 2**30:.1f} GiB): fewer particles or stop.max_populations", err=True)


class ProgressLine:
    """The line per population of ``run`` and ``submit``: the population, its tolerance (and
    the decision tolerance once the run has a noise floor) and acceptance, the simulations so
    far, the population's own rate (its simulations over the wall time since the previous
    population ended; the first population's also counts the pilot and compiling the
    kernels), the model probabilities and the workers now. On a terminal one line is
    rewritten in place; otherwise a line per population."""

    def __init__(self, unit: str, quiet: bool, workers: Callable[[], int | None],
                 start: tuple[int, float] = (0, 0.0), prefix: str = ""):
        """``prefix`` starts every line (a job's name among several: then a line per
        population, never one rewritten)."""
        self.unit, self.quiet, self.prefix = unit, quiet, prefix
        self.live = sys.stdout.isatty() and not quiet and not prefix
        self.workers = workers
        self.last = start  # (simulations, elapsed s) when the previous population ended
        self.n_workers: int | None = None
        self.asked = -math.inf
        self.shown = False

    def workers_now(self) -> int | None:
        """The cluster's workers, asked at most once a second (a round trip to the scheduler)."""
        now = time.monotonic()
        if now - self.asked >= 1.0:
            self.asked = now
            try:
                self.n_workers = self.workers()
            except Exception:
                self.n_workers = None
        return self.n_workers

    def show(self, event: Mapping[str, Any]) -> None:
        """A population event (``service.run.runner.Progress.event``): its decision tolerance
        once the run has a noise floor, its efficiency (the workers' share of time spent on the
        run's simulations over the population) when it ran on a cluster."""
        simulations, elapsed_s = event["simulations"], event["elapsed_s"]
        before, self.last = self.last, (simulations, elapsed_s)
        if self.quiet:
            return
        wall = elapsed_s - before[1]
        rate = f"{(simulations - before[0]) / wall:9.0f}" if wall > 0 else f"{'-':>9}"
        probs = " ".join(f"{name}={'-' if p is None else format(p, '.2f')}"
                         for name, p in event["model_probabilities"].items())
        workers = self.workers_now()
        decision, efficiency = event.get("decision_tolerance"), event.get("efficiency")
        dec = "" if decision is None else f"  decision {decision:.4g}{self.unit}"
        line = (f"{self.prefix}population {event['population']:4d}  eps {event['epsilon']:11.5g}{self.unit}{dec}  "
                f"acceptance {event['acceptance_rate']:5.2f}  sims {simulations:8d}  {rate} sims/s  {probs}  "
                f"workers {'-' if workers is None else workers}"
                + ("" if efficiency is None else f"  efficiency {efficiency:.2f}"))
        if self.live:
            sys.stdout.write(f"\r\x1b[2K{line}")
            sys.stdout.flush()
            self.shown = True
        else:
            typer.echo(line)

    def end(self) -> None:
        if self.shown:
            sys.stdout.write("\n")


def _unreachable(address: str, err: Exception) -> NoReturn:
    reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err) or type(err).__name__
    _fail(f"cannot reach the scheduler at {address}: {reason}", UNREACHABLE)


def reach_scheduler(address: str, timeout: float = 5.0) -> None:
    """One line and exit 3 unless a TCP connection to the scheduler's address opens: a refused
    or unknown address fails at once, not after Dask's 30 s of retries and a traceback."""
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        if scheme in ("tcp", "tls"):
            socket.create_connection(parse_host_port(location, 8786), timeout=timeout).close()
    except (OSError, ValueError) as err:  # TimeoutError and socket.gaierror are OSErrors
        _unreachable(address, err)


def connect(address: str, timeout: float = 30.0):
    """A Dask client of the scheduler at ``address`` (:func:`reach_scheduler` first)."""
    from distributed import Client

    reach_scheduler(address)
    try:
        return Client(address, timeout=timeout)
    except (OSError, ValueError) as err:
        _unreachable(address, err)


def dashboard_link(client) -> str | None:
    """The scheduler's dashboard link when it serves a dashboard. A scheduler always has an
    HTTP server: started with --no-dashboard its link answers 404, and without bokeh it
    answers with distributed's page "Dask needs bokeh ... for the dashboard"."""
    import urllib.request

    try:
        link = client.dashboard_link
        opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # straight to it, never a proxy
        with opener.open(link, timeout=5) as answer:
            return link if answer.status == 200 and b"needs bokeh" not in answer.read(4096) else None
    except Exception:
        return None


def resume_point(out: Path) -> tuple[int, float]:
    """(simulations, elapsed s) of the store's last complete population, (0, 0) for a new store:
    where the first population's rate starts."""
    from service.run.store import Store

    try:
        state = Store.open(out).run_state()
        return int(state["n_simulations_total"]), float(state["elapsed_s"])
    except Exception:
        return 0, 0.0


SIMS_HELP = ("The line per population shows the tolerance (eps; the NMSE in %), the acceptance rate, the simulations "
             "so far, sims/s (this population's simulations over the wall time since the previous one ended; the "
             "first also counts the pilot and compiling the kernels), the model probabilities and the workers now. "
             "stop.min_epsilon_decrease is an absolute difference in the tolerance's unit: with the NMSE, 0.01 "
             "stops when eps falls by less than 0.01 percentage points.")


MANY_HELP = ("Several specs (or one, with --out-dir) run as one job each on the cluster's workers, at most one job per "
             "worker process at a time, a store per job in --out-dir named after the spec's name (a name given twice: "
             "NAME.zarr, then NAME-2.zarr, ...); a job whose populations are cheap runs whole on its worker, one "
             "with dear simulations spreads its batches over the cluster. A line per population of each job, "
             "prefixed with its store's name; the exit code is 0 when every job finished, else the worst of "
             "theirs (1 over 4 over 2). The stores are written by the workers: --out-dir must be a folder they "
             "can write (the embedded cluster; a --scheduler cluster on a shared file system).")


@app.command(help="Run (or resume) a job and print its summary. On a terminal one progress line is rewritten in "
                  "place; otherwise a line per population. " + MANY_HELP + " " + SIMS_HELP)
def run(
    specs: Annotated[list[Path], typer.Argument(metavar="SPEC...", help="The job spec(s), YAML or JSON.")],
    out: Annotated[Path | None, typer.Option("--out", help="The job's zarr store (created, or resumed if "
                                                           "unfinished); one spec.")] = None,
    out_dir: Annotated[Path | None, typer.Option("--out-dir", help="A folder of stores, one per spec (created, "
                                                                   "or resumed if unfinished).")] = None,
    scheduler: Annotated[str | None, typer.Option(help="The address of a running Dask scheduler "
                                                       "(tcp://HOST:PORT).")] = None,
    workers: Annotated[int | None, typer.Option(help="Worker processes of the embedded cluster "
                                                     "(default: one per core).")] = None,
    seed: Annotated[int | None, typer.Option(help="Override the spec's seed.")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", help="No line per population (the summary is still printed).")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="End with the full JSON summary instead of the short one.")] = False,
    dashboard: Annotated[bool, typer.Option("--dashboard", help="Serve the embedded cluster's Dask dashboard and print "
                                                                "its link (needs bokeh).")] = False,
) -> None:
    from service.run.runner import Progress, run_job, summary
    from service.run.store import Store
    from service.spec import build, load

    if scheduler and workers:
        _fail("give --scheduler or --workers, not both")
    if out is not None and out_dir is not None:
        _fail("give --out (one spec's store) or --out-dir (a store per spec), not both")
    if out_dir is not None:
        run_many(specs, out_dir, scheduler, workers, seed, quiet, as_json, dashboard)
        return
    if out is None:
        _fail("give --out STORE for one spec, or --out-dir DIR for a store per spec")
    if len(specs) > 1:
        _fail(f"--out names one store, for one spec; {len(specs)} specs need --out-dir DIR (a store per spec)")
    spec = specs[0]
    try:
        job_spec, base = load(spec)
        built = build(job_spec.model_copy(update={"seed": seed}) if seed is not None else job_spec, base,
                      allow_import=True)
    except SpecError as err:
        _fail(str(err))
    memory_warning(built)
    names = [m.name for m in job_spec.models]
    with ExitStack() as stack:
        client = open_client(stack, scheduler, workers, dashboard)
        line = ProgressLine(percent(job_spec.distance.name), quiet, lambda: len(client.nthreads()), resume_point(out))

        def progress(p: Progress) -> None:
            line.show(p.event(names))

        try:
            result = run_job(job_spec, base, out, client, seed=seed, on_population=progress, allow_import=True)
        except SpecError as err:
            _fail(str(err))
        except BatchError as err:  # a bug in a simulator: which batch, which exception; the store keeps the rest
            _fail(f"the job failed in {err}; the populations before it are in {out} (abcns summary {out})", JOB_FAILED)
    line.end()
    print_summary(summary(Store.open(out), result), job_spec.distance.name, as_json,
                  f"store: {out}  (full JSON summary: abcns summary {out} --json)")


def open_client(stack: ExitStack, scheduler: str | None, workers: int | None, dashboard: bool):
    """A client of the scheduler at ``scheduler``, else of an embedded cluster of ``workers``
    processes (one per core by default), closed with ``stack``; the dashboard's link printed
    when there is one (``--dashboard``, or a scheduler's)."""
    from distributed import Client

    from service.run.dask_executor import local_cluster

    if dashboard and importlib.util.find_spec("bokeh") is None:
        typer.echo("warning: the Dask dashboard needs bokeh (pip install 'abcns[dashboard]'); running without it", err=True)
        dashboard = False
    if scheduler:
        client = stack.enter_context(connect(scheduler))
    else:
        cluster = stack.enter_context(local_cluster(workers or os.cpu_count() or 1, dashboard))
        client = stack.enter_context(Client(cluster))
    if dashboard or scheduler:
        link = dashboard_link(client)
        if link:
            typer.echo(f"Dask dashboard: {link}", err=True)
    return client


#: a job's outcome (service.run.jobs.Outcome.status) as an exit code, and the order of the
#: codes from the best to the worst (a run of several jobs exits with its worst job's)
OUTCOME_CODES = {"finished": 0, "refused": BAD_INPUT, "failed": JOB_FAILED, "cancelled": JOB_FAILED, "error": 1}
WORST = (0, BAD_INPUT, JOB_FAILED, 1)


def worst_code(outcomes: list) -> int:
    """The exit code of a run of several jobs: its worst job's (0 when every job finished)."""
    return max((OUTCOME_CODES.get(o.status, 1) for o in outcomes), key=WORST.index, default=0)


def run_many(specs: list[Path], out_dir: Path, scheduler: str | None, workers: int | None, seed: int | None,
             quiet: bool, as_json: bool, dashboard: bool) -> None:
    """``abcns run SPEC... --out-dir DIR``: every spec checked here first (one wrong: exit 2,
    nothing runs), then each job on the cluster (service.run.jobs), a line per population
    of each, prefixed with its store's name; then each job's summary, its failure on stderr;
    the exit code is the worst job's."""
    from service.run.jobs import JobRun, placement_text, run_jobs, store_names
    from service.run.runner import local_population_s
    from service.spec import build, load

    loaded = []
    for path in specs:
        try:
            job_spec, base = load(path)
            if seed is not None:
                job_spec = job_spec.model_copy(update={"seed": seed})
            built = build(job_spec, base, allow_import=True)
        except SpecError as err:
            _fail(f"{path}: {err}")
        memory_warning(built)
        loaded.append((path, job_spec, base))
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        local_s = local_population_s()
        jobs = [JobRun.of(job_spec, base, out_dir / f"{stem}.zarr", stem)
                for (_, job_spec, base), stem in zip(loaded, store_names([s.name for _, s, _ in loaded]), strict=True)]
    except (OSError, SpecError) as err:
        _fail(str(err))
    seen_workers: dict[int, int | None] = {}
    lines = [ProgressLine(percent(job.spec.distance.name), quiet, partial(seen_workers.get, i),
                          resume_point(job.store), prefix=f"[{job.label}] ") for i, job in enumerate(jobs)]

    def on_event(i: int, event: dict) -> None:
        job = jobs[i]
        if event["kind"] == "start":
            whole = (event.get("placement") or {}).get("mode") == "whole"
            seen_workers[i] = 1 if whole else None
            if not quiet:
                typer.echo(f"[{job.label}] {placement_text(event.get('placement'))}")
        elif event["kind"] == "requeued" and not quiet:
            typer.echo(f"[{job.label}] {event.get('reason', 'requeued')}: it waits for a free worker and resumes")
        elif event["kind"] == "population":
            if event["event"]["workers"] is not None:
                seen_workers[i] = event["event"]["workers"]
            lines[i].show(event["event"])

    with ExitStack() as stack:
        client = open_client(stack, scheduler, workers, dashboard)
        try:
            outcomes = run_jobs(client, jobs, allow_import=True, local_s=local_s, on_event=on_event)
        except KeyboardInterrupt:
            typer.echo("stopped: each job stops at its next batch; run again to resume", err=True)
            raise typer.Exit(130) from None
    if as_json:
        typer.echo(json.dumps([{"spec": str(path), "store": str(job.store), "outcome": o.status, "error": o.error,
                                **(o.summary or {"status": o.status, "n_populations": 0})}
                               for (path, _, _), job, o in zip(loaded, jobs, outcomes, strict=True)], indent=2))
    else:
        for (path, _, _), job, o in zip(loaded, jobs, outcomes, strict=True):
            typer.echo("")
            typer.echo(f"== {job.label} ({path}): {job.store} ({placement_text(o.placement)})")
            if o.summary is not None:
                for text in summary_lines(o.summary, job.spec.distance.name):
                    typer.echo(text)
        counts = {status: sum(o.status == status for o in outcomes) for status in OUTCOME_CODES}
        typer.echo("")
        typer.echo(f"{len(jobs)} jobs: " + ", ".join(f"{n} {status}" for status, n in counts.items() if n)
                   + f"  (full JSON summaries: abcns summary {out_dir}/NAME.zarr --json)")
    for job, o in zip(jobs, outcomes, strict=True):
        if o.status != "finished":
            where = f"; the populations before it are in {job.store}" if o.summary else ""
            typer.echo(f"error: job {job.label}: {o.error}{where}", err=True)
    worst = worst_code(outcomes)
    if worst:
        raise typer.Exit(worst)


@app.command(name="summary")
def summary_cmd(
    store: Annotated[Path, typer.Argument(help="a job's zarr store")],
    as_json: Annotated[bool, typer.Option("--json", help="the full JSON summary")] = False,
) -> None:
    """Print the summary of a job's store (finished or running), or the report of a study's folder."""
    from service.run.runner import summary
    from service.run.store import Store, StoreError
    from service.run.study import is_study

    if is_study(store):
        study_summary(store, as_json)
        return
    try:
        opened = Store.open(store)
        s = summary(opened)
    except StoreError as err:
        _fail(str(err))
    print_summary(s, distance_of(opened.attrs.get("spec")), as_json)


@app.command()
def serve(
    host: Annotated[str, typer.Option(help="listen address (localhost by default)")] = "127.0.0.1",
    port: Annotated[int, typer.Option()] = 8000,
    scheduler: Annotated[str | None, typer.Option(help="a Dask scheduler; default: an embedded LocalCluster")] = None,
    workers: Annotated[int | None, typer.Option(help="LocalCluster worker processes")] = None,
    store_dir: Annotated[Path | None, typer.Option(help="one folder per job [default: abcns-jobs]")] = None,
    token: Annotated[str | None, typer.Option(envvar="ABCNS_TOKEN", help="require Authorization: Bearer TOKEN")] = None,
    max_running: Annotated[int | None, typer.Option(help="jobs running at once [default: one per worker]")] = None,
    turn_s: Annotated[float | None, typer.Option(help="a job's turn while others wait, seconds [default: 30]")] = None,
    max_request_mb: Annotated[float | None, typer.Option(help="request size limit [default: 32]")] = None,
    max_queued: Annotated[int | None, typer.Option(help="jobs waiting; beyond: 429 [default: 64]")] = None,
    max_particles: Annotated[int | None, typer.Option(help="admission limit [default: 20000]")] = None,
    max_batch_size: Annotated[int | None, typer.Option(help="admission limit [default: 10000]")] = None,
    max_substeps: Annotated[int | None, typer.Option(help="admission limit [default: 1000]")] = None,
    max_samples: Annotated[int | None, typer.Option(help="admission limit on a record's length [default: 2^25]")] = None,
    max_models: Annotated[int | None, typer.Option(help="admission limit [default: 16]")] = None,
    max_memory_mb: Annotated[float | None, typer.Option(help="limit on a job's memory estimate [default: 2048]")] = None,
    max_job_seconds: Annotated[float | None, typer.Option(help="a job's time budget, default and most [default: 3600]")] = None,
    max_job_simulations: Annotated[int | None, typer.Option(help="a job's simulation budget: likewise [default: 1e9]")] = None,
    access_log: Annotated[bool, typer.Option(help="log every request (uvicorn's access log, on stderr)")] = True,
) -> None:
    """Serve the HTTP job API and the live pages (prints the address; logs every request).
    Every option left out but --host, --port and --access-log comes from its ABCNS_* variable
    (ABCNS_MAX_RUNNING, ...; --max-request-mb: ABCNS_MAX_REQUEST_BYTES), else its default."""
    from pydantic import ValidationError

    from service.http.server import serve as run_server
    from service.http.settings import Settings

    given: dict[str, Any] = {"store_dir": store_dir, "scheduler": scheduler, "workers": workers, "token": token,
                             "max_running": max_running, "turn_s": turn_s, "max_queued": max_queued,
                             "max_particles": max_particles,
                             "max_batch_size": max_batch_size, "max_substeps": max_substeps, "max_samples": max_samples,
                             "max_models": max_models, "max_memory_mb": max_memory_mb, "max_job_seconds": max_job_seconds,
                             "max_job_simulations": max_job_simulations,
                             "max_request_bytes": None if max_request_mb is None else int(max_request_mb * 1024 * 1024)}
    try:  # only what was given: the rest from ABCNS_* variables (README, The HTTP API) or the defaults
        settings = Settings(**{k: v for k, v in given.items() if v is not None})
    except ValidationError as err:
        _fail("; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in err.errors()))
    if settings.scheduler:
        reach_scheduler(settings.scheduler)
    typer.echo(f"abcns: serving {page_link(f'http://{host}:{port}/', settings.token)} (API docs at /docs), jobs in "
               f"{settings.store_dir.resolve()}, "
               f"{'scheduler ' + settings.scheduler if settings.scheduler else 'an embedded cluster'}"
               f"{', token required' if settings.token else ''}; limits at /limits", err=True)
    run_server(settings, host, port, access_log)


def page_link(address: str, token: str | None) -> str:
    """A live page's address as a browser opens it: with ``#token=TOKEN`` when the service has
    a token (the page keeps it for the tab and strips it from the address bar; without it the
    page's calls get 401 and its charts stay empty)."""
    from urllib.parse import quote

    return f"{address}#token={quote(token, safe='')}" if token else address


def _service_error(answer) -> tuple[str, int]:
    """A refusal of the service as one line and its exit code: a bad spec or data (400, 413,
    415, 422: the field and the message), the token (401, 403), a full queue (429), else the
    status and its text."""
    try:
        detail = answer.json().get("detail")
    except ValueError:
        detail = answer.text[:300]
    if isinstance(detail, list) and detail and isinstance(detail[0], dict):
        text = "; ".join(f"{d.get('field') or '.'.join(map(str, d.get('loc', [])))}: {d.get('msg')}"
                         + (f" (got {d['input']})" if d.get("input") else "") for d in detail[:5])
    else:
        text = str(detail)
    status = answer.status_code
    if status in (401, 403):
        return f"the service refused the token ({status}: {text}); give --token or ABCNS_TOKEN", REFUSED
    if status == 429:
        return f"the service's queue is full ({text}); try again in {answer.headers.get('retry-after', '?')} s", REFUSED
    if status in (400, 413, 415, 422):
        return f"the service refused the job: {text}", BAD_INPUT
    return f"the service answered {status}: {text}", REFUSED


def events(http, url: str, job_id: str, after: int = 0):
    """The job's server-sent events as (id, event, data), from after ``after`` to its terminal
    event; a dropped stream is resumed with Last-Event-ID (the service restarted, ...), and
    after 60 s without the service it is an error (exit 3)."""
    import httpx

    last, lost = after, None
    while True:
        try:
            headers = {"Accept": "text/event-stream", **({"Last-Event-ID": str(last)} if last else {})}
            with http.stream("GET", f"/jobs/{job_id}/events", headers=headers,
                             timeout=httpx.Timeout(30, read=60)) as answer:  # a keep-alive every 15 s
                if answer.status_code != 200:
                    answer.read()
                    _fail(*_service_error(answer))
                lost = None
                block: dict[str, str] = {}
                for text in answer.iter_lines():
                    if text:
                        field, _, value = text.partition(":")
                        block[field] = block.get(field, "") + value.removeprefix(" ")
                        continue
                    if "event" in block:
                        last = int(block.get("id") or last)
                        yield last, block["event"], json.loads(block.get("data") or "{}")
                        if block["event"] in ("finished", "failed", "cancelled"):
                            return
                    block = {}
        except httpx.TransportError as err:
            lost = lost or time.monotonic()
            if time.monotonic() - lost > 60:
                _fail(f"lost the service at {url} ({err}); the job goes on there: {url}/jobs/{job_id}/view", UNREACHABLE)
        time.sleep(1)


@app.command(help="Send a job to a running service (abcns serve) and follow it like run: the spec (YAML or JSON) "
                  "is checked here, its data files are read and uploaded with it (POST /jobs/upload), then a line "
                  "per population and the summary at the end. Stopping submit (Ctrl-C) leaves the job running "
                  "on the service. " + SIMS_HELP)
def submit(
    spec: Annotated[Path, typer.Argument(metavar="SPEC", help="The job spec, YAML or JSON; its data files relative "
                                                              "to it.")],
    url: Annotated[str, typer.Option(envvar="ABCNS_URL", help="The service.")] = "http://127.0.0.1:8000",
    token: Annotated[str | None, typer.Option(envvar="ABCNS_TOKEN", help="The service's token, if it has one.")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", help="No line per population (the summary is still printed).")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="End with the full JSON summary instead of the short one.")] = False,
) -> None:
    import io

    import httpx
    import numpy as np

    from service.spec import build, load, load_array, spec_text

    try:
        job_spec, base = load(spec)
        build(job_spec, base, allow_import=False)  # what the service checks too (registry simulators only)
        arrays = {key: load_array(value, base, f"data.{key}") for key in ("input", "observed")
                  if (value := getattr(job_spec.data, key)) is not None}
    except SpecError as err:
        _fail(str(err))
    data = job_spec.data.model_copy(update={key: f"npz:{key}" for key in arrays})  # the arrays go in the upload
    body = json.dumps(spec_text(job_spec.model_copy(update={"data": data})))
    npz = io.BytesIO()
    np.savez(npz, **arrays)  # type: ignore[arg-type]  # mypy checks **arrays against allow_pickle (bool) too
    url = url.rstrip("/")
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"} if token else {},
                      timeout=httpx.Timeout(60, connect=10)) as http:
        try:
            answer = http.post("/jobs/upload", files={"spec": ("spec.json", body, "application/json"),
                                                      "data": ("data.npz", npz.getvalue(), "application/octet-stream")})
        except httpx.TransportError as err:
            _fail(f"cannot reach the service at {url}: {err}", UNREACHABLE)
        if answer.status_code != 201:
            _fail(*_service_error(answer))
        job_id = answer.json()["id"]
        view = page_link(f"{url}/jobs/{job_id}/view", token)
        typer.echo(f"job {job_id}: {view}", err=True)

        def workers() -> int:
            return int(http.get("/health", timeout=5).json()["workers"])

        line = ProgressLine(percent(job_spec.distance.name), quiet, workers)
        end, error = "", None
        try:
            for _, event, info in events(http, url, job_id):
                if event == "population":
                    line.show(info)
                elif event in ("finished", "failed", "cancelled"):
                    end, error = event, info.get("error")
        except KeyboardInterrupt:
            line.end()
            typer.echo(f"the job goes on: {view}", err=True)
            raise typer.Exit(130) from None
        line.end()
        result = http.get(f"/jobs/{job_id}/result")
        s = result.json() if result.status_code == 200 else {"status": end, "n_populations": 0}
    print_summary(s, job_spec.distance.name, as_json,
                  f"job: {url}/jobs/{job_id}  (full JSON summary: {url}/jobs/{job_id}/result)")
    if end != "finished":
        _fail(f"the job {'was cancelled' if end == 'cancelled' else end}" + (f": {error}" if error else ""), JOB_FAILED)


def main() -> None:
    app(prog_name="abcns")


@app.command(name="plot")
def plot_cmd(
    stores: Annotated[list[Path], typer.Argument(
        help="finished job stores; two or more, each with its --spec, also give the §5.4 confusion matrices")],
    out: Annotated[Path, typer.Option("--out", help="directory for the PNG figures (created)")],
    spec: Annotated[list[Path] | None, typer.Option(
        "--spec", help="the spec file each store was run from (in the stores' order); its directory holds the data. "
                       "Without it: no predictive bands")] = None,
    truth: Annotated[list[str] | None, typer.Option("--truth", help="known value, NAME=VALUE (repeatable)")] = None,
    draws: Annotated[int | None, typer.Option(help="predictive draws (default: every particle)")] = None,
    labels: Annotated[list[str] | None, typer.Option("--label", help="data-set names for the confusion matrix")] = None,
) -> None:
    """Write the figures of finished stores: tolerance, acceptance, model probabilities,
    marginals and pairs, predictive bands (with --spec) and confusion matrices; of a study's
    folder (abcns study), its confusion matrix, reliability diagram, coverage and SBC ranks."""
    from service.report.analysis import JobData, confusion_of, store_job_data
    from service.report.plots import confusion_figure, plot_result, save
    from service.run.runner import result_from_store
    from service.run.store import Store, StoreError
    from service.run.study import is_study

    if len(stores) == 1 and is_study(stores[0]):
        study_plot(stores[0], out)
        return
    stray = [str(p) for p in stores if "=" in p.name and not p.exists()]
    if stray:  # `--truth m=1 c=2`: c=2 was read as a store
        _fail(f"{stray[0]!r} is not a store: give each known value its own --truth (--truth m=1 --truth c=2)")
    known = named_values(truth, "--truth")
    if spec and len(spec) != len(stores):
        _fail(f"{len(spec)} --spec for {len(stores)} stores: give one per store, in order")
    results, datas = [], []
    for k, path in enumerate(stores):
        try:
            store = Store.open(path)
            result = result_from_store(store)
            data = store_job_data(store, spec[k].parent) if spec else None
        except (StoreError, SpecError, ValueError) as err:
            _fail(str(err))
        if not result.populations:
            _fail(f"{path} has no complete population")
        target = out if len(stores) == 1 else out / path.stem
        files = plot_result(result, target, known or None, data, draws,
                            unit=percent(distance_of(store.attrs.get("spec"))).strip())
        results.append(result)
        datas.append(data)
        for f in files.values():
            typer.echo(str(f))
    if len(stores) > 1 and spec:
        conf = confusion_of(results, cast(list[JobData], datas),  # with spec, every store's data was read
                            labels or [p.stem for p in stores])
        typer.echo(str(save(confusion_figure(conf), out / "confusion.png")))
        typer.echo(f"confusion: best {conf.best}; mean NMSE " + ", ".join(f"{k} {v:.4g} %" for k, v in conf.mean.items())
                   + (f"; eliminated {', '.join(conf.eliminated)}" if conf.eliminated else ""))



# ---------------------------------------------------------------------------- studies (docs/studies.md)


def named_values(items: list[str] | None, option: str) -> dict[str, float]:
    """NAME=VALUE options as a dict (exit 2 naming the option for a malformed one)."""
    out: dict[str, float] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep or not key.strip():
            _fail(f"{option} {item!r}: expected NAME=VALUE")
    return out


@app.command(help="Run a study: N data sets made with the spec's own simulators, input and windows (a true model "
                  "drawn uniformly from the spec's models unless --truth, its parameters from their priors unless "
                  "--truth-param, Gaussian noise of --noise-std or --noise-share of the clean response's RMS), each "
                  "run as a job with the spec's settings on the cluster (as abcns run --out-dir). Run again on the "
                  "same --out to resume. Then the report: confusion matrix, calibration of the model probabilities, "
                  "coverage and SBC ranks of the truth (abcns summary DIR, abcns plot DIR). docs/studies.md.")
def study(
    spec: Annotated[Path, typer.Argument(metavar="SPEC", help="The job spec, YAML or JSON.")],
    datasets: Annotated[int, typer.Option("--datasets", help="Data sets (jobs) to make and run.")],
    out: Annotated[Path, typer.Option("--out", help="The study's folder (created, or resumed).")],
    noise_std: Annotated[float | None, typer.Option("--noise-std", help="Gaussian noise, the data's units.")] = None,
    noise_share: Annotated[float | None, typer.Option("--noise-share", help="Gaussian noise, a share of the clean "
                                                                            "response's RMS (0.01: 1 %).")] = None,
    truth: Annotated[str | None, typer.Option("--truth", help="The true model (default: drawn uniformly).")] = None,
    truth_param: Annotated[list[str] | None, typer.Option("--truth-param", help="A fixed true value, NAME=VALUE "
                                                                                "(repeatable).")] = None,
    seed: Annotated[int | None, typer.Option(help="The study's seed (default: the spec's).")] = None,
    scheduler: Annotated[str | None, typer.Option(help="A running Dask scheduler (tcp://HOST:PORT).")] = None,
    workers: Annotated[int | None, typer.Option(help="Worker processes of the embedded cluster.")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", help="No line per job as it starts.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="End with the JSON report.")] = False,
) -> None:
    from service.run.runner import local_population_s
    from service.run.study import parse_request, prepare
    from service.spec import load

    if scheduler and workers:
        _fail("give --scheduler or --workers, not both")
    try:
        job_spec, base = load(spec)
        request = parse_request({"datasets": datasets, "noise_std": noise_std, "noise_share": noise_share,
                                 "truth": truth, "truth_parameters": named_values(truth_param, "--truth-param"),
                                 "seed": seed})
        out.mkdir(parents=True, exist_ok=True)
        jobs = prepare(job_spec, base, request, out)
    except SpecError as err:
        _fail(str(err))
    except OSError as err:
        _fail(f"out: {err}")
    worst = run_study_jobs(jobs, out, scheduler, workers, quiet, local_population_s())
    study_summary(out, as_json)
    if worst:
        raise typer.Exit(worst)


def run_study_jobs(jobs: list, out: Path, scheduler: str | None, workers: int | None, quiet: bool,
                   local_s: float) -> int:
    """The study's jobs on the cluster, a line per job as it starts; the worst job's exit
    code (as ``run --out-dir``: 0 when every job finished)."""
    from service.run.jobs import placement_text, run_jobs

    def on_event(i: int, event: dict) -> None:
        if not quiet and event["kind"] == "start":
            typer.echo(f"[{jobs[i].label}] {i + 1} of {len(jobs)}: {placement_text(event.get('placement'))}", err=True)
        if not quiet and event["kind"] == "requeued":
            typer.echo(f"[{jobs[i].label}] {event.get('reason', 'requeued')}: it waits for a free worker", err=True)

    with ExitStack() as stack:
        client = open_client(stack, scheduler, workers, False)
        try:
            outcomes = run_jobs(client, jobs, allow_import=True, local_s=local_s, on_event=on_event)
        except KeyboardInterrupt:
            typer.echo(f"stopped: run the same command again to resume the study in {out}", err=True)
            raise typer.Exit(130) from None
    failed = [(j, o) for j, o in zip(jobs, outcomes, strict=True) if o.status != "finished"]
    if not quiet:
        typer.echo(f"{len(jobs) - len(failed)} of {len(jobs)} jobs finished", err=True)
    for j, o in failed:
        typer.echo(f"error: job {j.label}: {o.status}: {o.error}", err=True)
    return worst_code(outcomes)


def study_summary(folder: Path, as_json: bool) -> None:
    """The report of a study's folder (finished jobs so far)."""
    from service.report.study import folder_report, report_lines

    report = folder_report(folder)
    if as_json:
        typer.echo(json.dumps(report, indent=1))
        return
    for line in report_lines(report):
        typer.echo(line)


def study_plot(folder: Path, out: Path) -> None:
    from service.report.study import folder_report, plot_study

    for path in plot_study(folder_report(folder), out):
        typer.echo(str(path))


if __name__ == "__main__":
    main()
