"""The ``abcns`` command line.

    abcns run SPEC --out STORE [--scheduler tcp://HOST:PORT | --workers N] [--seed N]
    abcns summary STORE [--json]
"""

from __future__ import annotations

import json
import os
import sys
from contextlib import ExitStack
from pathlib import Path
from typing import Annotated

import typer

from abcns import SpecError

app = typer.Typer(add_completion=False, no_args_is_help=True, help="ABC-NS inference for dynamical systems.")


def _fail(message: str) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(2)


@app.command()
def run(
    spec: Annotated[Path, typer.Argument(help="job spec, YAML or JSON")],
    out: Annotated[Path, typer.Option("--out", help="the job's zarr store (created, or resumed if unfinished)")],
    scheduler: Annotated[str | None, typer.Option(help="address of a running Dask scheduler")] = None,
    workers: Annotated[int | None, typer.Option(help="worker processes of the embedded cluster (default: one per core)")] = None,
    seed: Annotated[int | None, typer.Option(help="override the spec's seed")] = None,
    quiet: Annotated[bool, typer.Option(help="no progress lines")] = False,
) -> None:
    """Run (or resume) a job and print its summary."""
    from service.runner import Progress, run_job, summary
    from service.spec import build, load
    from service.store import Store

    if scheduler and workers:
        _fail("give --scheduler or --workers, not both")
    try:
        job_spec, base = load(spec)
        build(job_spec.model_copy(update={"seed": seed}) if seed is not None else job_spec, base, allow_import=True)
    except SpecError as err:
        _fail(str(err))
    names = [m.name for m in job_spec.models]

    def progress(p: Progress) -> None:
        if quiet:
            return
        pop = p.population
        probs = " ".join(f"{n}={v:.2f}" for n, v in zip(names, pop.model_probabilities))
        typer.echo(f"population {pop.t:4d}  eps {pop.epsilon:11.5g}  acceptance {pop.acceptance_rate:5.2f}  "
                   f"sims {p.n_simulations_total:8d}  {p.simulations_per_s:9.0f} sims/s  {probs}")

    from distributed import Client, LocalCluster

    with ExitStack() as stack:
        if scheduler:
            client = stack.enter_context(Client(scheduler))
        else:
            n = workers or os.cpu_count() or 1
            cluster = stack.enter_context(LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                       dashboard_address=None))
            client = stack.enter_context(Client(cluster))
        try:
            run_job(job_spec, base, out, client, seed=seed, on_population=progress, allow_import=True)
        except SpecError as err:
            _fail(str(err))
    if not quiet:
        typer.echo(json.dumps(summary(Store.open(out)), indent=2))


@app.command(name="summary")
def summary_cmd(
    store: Annotated[Path, typer.Argument(help="a job's zarr store")],
    as_json: Annotated[bool, typer.Option("--json", help="the full JSON summary")] = False,
) -> None:
    """Print the summary of a job's store (finished or running)."""
    from service.runner import summary
    from service.store import Store, StoreError

    try:
        s = summary(Store.open(store))
    except StoreError as err:
        _fail(str(err))
    if as_json:
        typer.echo(json.dumps(s, indent=2))
        return
    typer.echo(f"status {s['status']}  stop {s.get('stop_reason')}  populations {s['n_populations']}  "
               f"simulations {s.get('n_simulations', 0)}  wall {s.get('wall_time_s', 0):.1f} s")
    if s.get("epsilon"):
        typer.echo(f"epsilon {s['epsilon'][0]:.4g} -> {s['epsilon'][-1]:.4g}; "
                   f"mean acceptance {sum(s['acceptance_rate']) / len(s['acceptance_rate']):.2f}")
    typer.echo("model probabilities: " + ", ".join(f"{k} {v:.3f}" for k, v in s.get("model_probabilities", {}).items()))
    for model, params in s.get("posterior", {}).items():
        typer.echo(f"{model}:")
        for name, q in params.items():
            typer.echo(f"  {name:8s} mean {q['mean']:12.6g}  std {q['std']:10.4g}  95% [{q['q2_5']:.6g}, {q['q97_5']:.6g}]")


@app.command()
def serve(
    host: Annotated[str, typer.Option(help="listen address (localhost by default)")] = "127.0.0.1",
    port: Annotated[int, typer.Option()] = 8000,
    scheduler: Annotated[str | None, typer.Option(help="a Dask scheduler; default: an embedded LocalCluster")] = None,
    workers: Annotated[int | None, typer.Option(help="LocalCluster worker processes")] = None,
    store_dir: Annotated[Path, typer.Option(help="one folder per job")] = Path("abcns-jobs"),
    token: Annotated[str | None, typer.Option(envvar="ABCNS_TOKEN", help="require Authorization: Bearer TOKEN")] = None,
    max_running: Annotated[int, typer.Option(help="jobs running at once")] = 1,
    max_request_mb: Annotated[float, typer.Option(help="request size limit")] = 32.0,
) -> None:
    """Serve the HTTP job API and the live pages."""
    import uvicorn

    from service.api import create_app
    from service.settings import Settings

    settings = Settings(store_dir=store_dir, scheduler=scheduler, workers=workers, token=token,
                        max_running=max_running, max_request_bytes=int(max_request_mb * 1024 * 1024))
    uvicorn.run(create_app(settings), host=host, port=port, log_level="warning")


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
    from service.analysis import confusion_of, store_job_data
    from service.plots import confusion_figure, plot_result, save
    from service.runner import result_from_store
    from service.store import Store, StoreError

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
        typer.echo(f"confusion: best {conf.best}; mean NMSE " + ", ".join(f"{k} {v:.4g}" for k, v in conf.mean.items())
                   + (f"; eliminated {', '.join(conf.eliminated)}" if conf.eliminated else ""))


if __name__ == "__main__":
    sys.exit(main())
