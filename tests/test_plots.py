"""Store-level analysis, plots and ``abcns plot`` on a short §4.1 run (200 particles, 6
populations, seed 1; a few seconds in-process)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from abcns.analysis import nmse
from service.analysis import confusion_of, predictions, run_to_store, store_job_data
from service.cli import app
from service.runner import result_from_store
from service.spec import load
from service.store import Store

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "examples" / "duffing_41" / "spec.yaml"


def short_spec(seed: int = 1, particles: int = 200, populations: int = 6):
    spec, base = load(SPEC)
    return spec.model_copy(update={"sampler": spec.sampler.model_copy(update={"particles": particles}),
                                   "stop": spec.stop.model_copy(update={"max_populations": populations}),
                                   "seed": seed}), base


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    out = []
    for seed in (1, 2):
        spec, base = short_spec(seed)
        path = tmp_path_factory.mktemp("runs") / f"seed{seed}.zarr"
        run_to_store(spec, base, path)
        out.append(path)
    return out


def test_store_written_like_the_runner(stores):
    store = Store.open(stores[0])
    assert store.attrs["status"] == "finished" and store.attrs["stop_reason"] == "max_populations"
    assert store.n_populations == 6 and result_from_store(store).summary()["n_populations"] == 6


def test_rebuilt_simulators_reproduce_the_run_distances(stores):
    # the analysis simulates the whole record with the free + fixed + default mapping; on
    # the fit window its NMSE must be the distance the run accepted each particle with
    # (same kernels, same substeps; agreement to rounding)
    store = Store.open(stores[0])
    result, data = result_from_store(store), store_job_data(store, SPEC.parent)
    assert data.observed.size == 1000 and data.fit == (0, 500) and data.test == (500, 1000)
    for i in result.alive():
        name = result.models[i].name
        theta, dist, _ = result.particles(i)
        values, status = data.simulate(name)(theta)
        assert np.all(status == 0)
        np.testing.assert_allclose(nmse(values, data.observed, data.fit), dist, rtol=1e-9)


def test_predictions_nmse_matches_direct(stores):
    store = Store.open(stores[0])
    result, data = result_from_store(store), store_job_data(store, SPEC.parent)
    preds, scores = predictions(result, data)
    for name, pred in preds.items():
        theta, _, _ = result.particles(name)
        assert pred.trajectories.shape == (theta.shape[0], 1000)
        values, _ = data.simulate(name)(theta.mean(axis=0))
        assert scores[name]["posterior_mean"]["test"] == pytest.approx(nmse(values[0], data.observed, (500, 1000)))
        b = pred.bands
        assert np.all(b["lower_99"] <= b["lower_50"]) and np.all(b["lower_50"] <= b["median"])
        assert np.all(b["median"] <= b["upper_50"]) and np.all(b["upper_50"] <= b["upper_99"])


def test_wrong_data_dir_is_refused(stores, tmp_path):
    other = tmp_path / "spec.yaml"
    for f in ("force.npy", "displacement.npy"):
        np.save(tmp_path / f, np.load(SPEC.parent / f)[::-1].copy())
    with pytest.raises(ValueError, match="not the data this store was run on"):
        store_job_data(Store.open(stores[0]), other.parent)


def test_confusion_of_two_runs(stores):
    results = [result_from_store(Store.open(p)) for p in stores]
    datas = [store_job_data(Store.open(p), SPEC.parent) for p in stores]
    conf = confusion_of(results, datas, ["a", "b"])
    # same data twice: row i scores model i's posterior mean on the same test window, so
    # both columns of a row are equal
    for mat in conf.matrices.values():
        np.testing.assert_allclose(mat[:, 0], mat[:, 1])
    assert conf.best in conf.models


def png_ok(path: Path) -> bool:
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 5000


def test_cli_plot_writes_every_figure(stores, tmp_path):
    runner = CliRunner()
    done = runner.invoke(app, ["plot", str(stores[0]), "--out", str(tmp_path / "one"), "--spec", str(SPEC),
                               "--truth", "k=50", "--truth", "k3=1000"])
    assert done.exit_code == 0, done.output
    names = {p.name for p in (tmp_path / "one").iterdir()}
    result = result_from_store(Store.open(stores[0]))
    expected = {"tolerance.png", "model_probabilities.png", "nmse.json"}
    for i in result.alive():
        n = result.models[i].name
        expected |= {f"marginals_{n}.png", f"pairs_{n}.png", f"predictive_{n}.png"}
    assert names == expected
    assert all(png_ok(tmp_path / "one" / n) for n in names if n.endswith(".png"))
    assert set(json.loads((tmp_path / "one" / "nmse.json").read_text())) == {result.models[i].name for i in result.alive()}
    # two stores: per-store directories and the confusion matrices
    done = runner.invoke(app, ["plot", *map(str, stores), "--out", str(tmp_path / "two"), "--spec", str(SPEC),
                               "--spec", str(SPEC)])
    assert done.exit_code == 0, done.output
    assert png_ok(tmp_path / "two" / "confusion.png") and "confusion: best" in done.output
    # without --spec: no predictive figures; bad --truth is a usage error
    done = runner.invoke(app, ["plot", str(stores[0]), "--out", str(tmp_path / "nospec")])
    assert done.exit_code == 0 and not list((tmp_path / "nospec").glob("predictive_*"))
    done = runner.invoke(app, ["plot", str(stores[0]), "--out", str(tmp_path / "x"), "--truth", "k"])
    assert done.exit_code == 2 and "NAME=VALUE" in done.output
