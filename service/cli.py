"""The ``abcns`` command line.

    abcns run SPEC --out STORE [--scheduler tcp://HOST:PORT | --workers N] [--seed N] [--quiet] [--json]
    abcns summary STORE [--json]
    abcns plot STORE [STORE ...] --out DIR [--spec SPEC ...]
    abcns serve [...]
    abcns --version

``run`` prints a line per population (not with ``--quiet``) and ends with a short summary
(the full JSON summary with ``--json``, or later with ``abcns summary STORE --json``). With
the paper's NMSE (Eq. 7) the tolerances and distances are in percent and marked ``%``.
"""

from __future__ import annotations

import importlib.util
import json
import os
import sys
from contextlib import ExitStack
from pathlib import Path
from typing import Annotated

import typer

from abcns import SpecError
from abcns.executor import BatchError

app = typer.Typer(add_completion=False, no_args_is_help=True, help="ABC-NS inference for dynamical systems.")


def _fail(message: str) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(2)


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
                                          help="print the version and exit")] = False,
) -> None:
    """ABC-NS inference for dynamical systems."""


def percent(distance: str | None) -> str:
    """The unit of a distance: the NMSE of Eq. 7 is in percent (100 / (n s^2) ...)."""
    return " %" if distance in (None, "nmse") else ""


def distance_of(spec: dict | None) -> str:
    return ((spec or {}).get("distance") or {}).get("name", "nmse")


def summary_lines(s: dict, distance: str = "nmse") -> list[str]:
    """The human summary of a job's JSON summary: status, tolerances, model probabilities,
    the posterior of every model still alive."""
    unit = percent(distance)
    lines = [f"status {s['status']}  stop {s.get('stop_reason')}  populations {s['n_populations']}  "
             f"simulations {s.get('n_simulations', 0):,}  wall {s.get('wall_time_s') or 0:.1f} s"]
    if s.get("epsilon"):
        what = "tolerance (NMSE)" if unit else "tolerance"
        lines.append(f"{what} {s['epsilon'][0]:.4g}{unit} -> {s['epsilon'][-1]:.4g}{unit}; "
                     f"mean acceptance {sum(s['acceptance_rate']) / len(s['acceptance_rate']):.2f}")
    se = s.get("model_probability_se") or {}
    lines.append("model probabilities: " + ", ".join(
        f"{k} {v:.3f}" + (f" ± {se[k]:.3f}" if se.get(k) is not None and se[k] == se[k] else "")
        for k, v in s.get("model_probabilities", {}).items()))
    if s.get("dead_models"):
        rules = s.get("death_rules") or {}
        lines.append("died (first population without particles): " + ", ".join(
            f"{k} {v}" + (f" ({rules[k]})" if k in rules else "") for k, v in s["dead_models"].items()))
    lines += [f"warning: {w}" for w in s.get("warnings", [])]
    if s.get("error"):
        lines.append(f"error: {s['error']}")
    for model, params in s.get("posterior", {}).items():
        lines.append(f"{model}:")
        for name, q in params.items():
            lines.append(f"  {name:8s} mean {q['mean']:12.6g}  std {q['std']:10.4g}  95% [{q['q2_5']:.6g}, {q['q97_5']:.6g}]")
    return lines


def memory_warning(job) -> None:
    """No admission limits on the user's own machine: a warning when the job's memory
    estimate (service.http.limits.memory_estimate) exceeds half of this machine's memory."""
    import psutil

    from service.http.limits import memory_estimate

    need, have = memory_estimate(job)["total"], psutil.virtual_memory().total
    if need > have / 2:
        typer.echo(f"warning: this job may need about {need / 2**30:.1f} GiB (particles x parameters x populations; "
                   f"this machine has {have / 2**30:.1f} GiB): fewer particles or stop.max_populations", err=True)


@app.command()
def run(
    spec: Annotated[Path, typer.Argument(help="job spec, YAML or JSON")],
    out: Annotated[Path, typer.Option("--out", help="the job's zarr store (created, or resumed if unfinished)")],
    scheduler: Annotated[str | None, typer.Option(help="address of a running Dask scheduler")] = None,
    workers: Annotated[int | None, typer.Option(help="worker processes of the embedded cluster (default: one per core)")] = None,
    seed: Annotated[int | None, typer.Option(help="override the spec's seed")] = None,
    quiet: Annotated[bool, typer.Option(help="no line per population (the summary is still printed)")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="end with the full JSON summary instead of the short one")] = False,
    dashboard: Annotated[bool, typer.Option(help="serve the embedded cluster's Dask dashboard (its link is printed)")] = False,
) -> None:
    """Run (or resume) a job and print its summary. On a terminal one progress line is
    rewritten in place; otherwise a line per population."""
    from service.run.runner import Progress, run_job, summary
    from service.run.store import Store
    from service.spec import build, load

    if scheduler and workers:
        _fail("give --scheduler or --workers, not both")
    try:
        job_spec, base = load(spec)
        built = build(job_spec.model_copy(update={"seed": seed}) if seed is not None else job_spec, base,
                      allow_import=True)
    except SpecError as err:
        _fail(str(err))
    memory_warning(built)
    names = [m.name for m in job_spec.models]
    unit = percent(job_spec.distance.name)

    live = sys.stdout.isatty() and not quiet  # a terminal: one line rewritten in place
    workers_seen = [0]

    def progress(p: Progress) -> None:
        if quiet:
            return
        pop = p.population
        probs = " ".join(f"{n}={v:.2f}" for n, v in zip(names, pop.model_probabilities))
        line = (f"population {pop.t:4d}  eps {pop.epsilon:11.5g}{unit}  acceptance {pop.acceptance_rate:5.2f}  "
                f"sims {p.n_simulations_total:8d}  {p.simulations_per_s:9.0f} sims/s  {probs}")
        if live:
            sys.stdout.write(f"\r\x1b[2K{line}  workers {workers_seen[0]}")
            sys.stdout.flush()
        else:
            typer.echo(line)

    from distributed import Client

    from service.run.dask_executor import local_cluster

    if dashboard and importlib.util.find_spec("bokeh") is None:
        typer.echo("warning: the Dask dashboard needs bokeh (pip install 'abcns[dashboard]'); running without it", err=True)
        dashboard = False
    with ExitStack() as stack:
        if scheduler:
            client = stack.enter_context(Client(scheduler))
        else:
            n = workers or os.cpu_count() or 1
            cluster = stack.enter_context(local_cluster(n, dashboard))
            client = stack.enter_context(Client(cluster))
        if client.dashboard_link and (dashboard or scheduler):
            typer.echo(f"Dask dashboard: {client.dashboard_link}", err=True)
        workers_seen[0] = len(client.scheduler_info(n_workers=-1).get("workers", {}))
        try:
            run_job(job_spec, base, out, client, seed=seed, on_population=progress, allow_import=True)
        except SpecError as err:
            _fail(str(err))
        except BatchError as err:  # a bug in a simulator: which batch, which exception; the store keeps the rest
            _fail(f"the job failed in {err}; the populations before it are in {out} (abcns summary {out})")
    if live:
        sys.stdout.write("\n")
    s = summary(Store.open(out))
    if as_json:
        typer.echo(json.dumps(s, indent=2))
        return
    typer.echo("")
    for line in summary_lines(s, job_spec.distance.name):
        typer.echo(line)
    typer.echo(f"store: {out}  (full JSON summary: abcns summary {out} --json)")


@app.command(name="summary")
def summary_cmd(
    store: Annotated[Path, typer.Argument(help="a job's zarr store")],
    as_json: Annotated[bool, typer.Option("--json", help="the full JSON summary")] = False,
) -> None:
    """Print the summary of a job's store (finished or running)."""
    from service.run.runner import summary
    from service.run.store import Store, StoreError

    try:
        opened = Store.open(store)
        s = summary(opened)
    except StoreError as err:
        _fail(str(err))
    if as_json:
        typer.echo(json.dumps(s, indent=2))
        return
    for line in summary_lines(s, distance_of(opened.attrs.get("spec"))):
        typer.echo(line)


@app.command()
def serve(
    host: Annotated[str, typer.Option(help="listen address (localhost by default)")] = "127.0.0.1",
    port: Annotated[int, typer.Option()] = 8000,
    scheduler: Annotated[str | None, typer.Option(help="a Dask scheduler; default: an embedded LocalCluster")] = None,
    workers: Annotated[int | None, typer.Option(help="LocalCluster worker processes")] = None,
    store_dir: Annotated[Path | None, typer.Option(help="one folder per job [default: abcns-jobs]")] = None,
    token: Annotated[str | None, typer.Option(envvar="ABCNS_TOKEN", help="require Authorization: Bearer TOKEN")] = None,
    max_running: Annotated[int | None, typer.Option(help="jobs running at once [default: 1]")] = None,
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
    Every option left out comes from its ABCNS_* variable (ABCNS_MAX_RUNNING, ...), else its default."""
    from pydantic import ValidationError

    from service.http.server import serve as run_server
    from service.http.settings import Settings

    given = {"store_dir": store_dir, "scheduler": scheduler, "workers": workers, "token": token,
             "max_running": max_running, "max_queued": max_queued, "max_particles": max_particles,
             "max_batch_size": max_batch_size, "max_substeps": max_substeps, "max_samples": max_samples,
             "max_models": max_models, "max_memory_mb": max_memory_mb, "max_job_seconds": max_job_seconds,
             "max_job_simulations": max_job_simulations,
             "max_request_bytes": None if max_request_mb is None else int(max_request_mb * 1024 * 1024)}
    try:  # only what was given: the rest from ABCNS_* variables (README, HTTP service) or the defaults
        settings = Settings(**{k: v for k, v in given.items() if v is not None})
    except ValidationError as err:
        _fail("; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in err.errors()))
    typer.echo(f"abcns: serving http://{host}:{port}/ (API docs at /docs), jobs in {settings.store_dir.resolve()}, "
               f"{'scheduler ' + settings.scheduler if settings.scheduler else 'an embedded cluster'}"
               f"{', token required' if settings.token else ''}; limits at /limits", err=True)
    run_server(settings, host, port, access_log)


def main() -> None:
    app(prog_name="abcns")


@app.command(name="plot")
def plot_cmd(
    stores: Annotated[list[Path], typer.Argument(help="finished job stores; two or more also give the §5.4 confusion matrices")],
    out: Annotated[Path, typer.Option("--out", help="directory for the PNG figures (created)")],
    spec: Annotated[list[Path] | None, typer.Option(
        "--spec", help="the spec file each store was run from (in the stores' order); its directory holds the data. "
                       "Without it: no predictive bands")] = None,
    truth: Annotated[list[str] | None, typer.Option("--truth", help="known value, NAME=VALUE (repeatable)")] = None,
    draws: Annotated[int | None, typer.Option(help="predictive draws (default: every particle)")] = None,
    labels: Annotated[list[str] | None, typer.Option("--label", help="data-set names for the confusion matrix")] = None,
) -> None:
    """Write the figures of finished stores: tolerance, acceptance, model probabilities,
    marginals and pairs, predictive bands (with --spec) and confusion matrices."""
    from service.report.analysis import confusion_of, store_job_data
    from service.report.plots import confusion_figure, plot_result, save
    from service.run.runner import result_from_store
    from service.run.store import Store, StoreError

    known: dict[str, float] = {}
    for item in truth or []:
        key, sep, value = item.partition("=")
        try:
            known[key.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep:
            _fail(f"--truth {item!r}: expected NAME=VALUE")
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
        files = plot_result(result, target, known or None, data, draws)
        results.append(result)
        datas.append(data)
        for f in files.values():
            typer.echo(str(f))
    if len(stores) > 1 and spec:
        conf = confusion_of(results, datas, labels or [p.stem for p in stores])
        typer.echo(str(save(confusion_figure(conf), out / "confusion.png")))
        typer.echo(f"confusion: best {conf.best}; mean NMSE " + ", ".join(f"{k} {v:.4g} %" for k, v in conf.mean.items())
                   + (f"; eliminated {', '.join(conf.eliminated)}" if conf.eliminated else ""))


if __name__ == "__main__":
    sys.exit(main())
