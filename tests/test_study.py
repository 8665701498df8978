"""Studies (issue V; service/run/study.py, service/report/study.py, docs/studies.md): data
sets made with the spec's own simulator, each run as a job on the cluster; the report's numbers
recomputed here from the stores; a killed study resumed; bad input refused before any job;
the figures read back from their matplotlib objects. The spec is cheap: two linear
oscillators (the exact ``linear`` simulator) of mass 1 and 3, 300 samples, 100 particles, at
most 6 populations (~1 s a job)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from distributed import Client
from figure_checks import record_saved

from abcns.result import weighted_quantiles
from service.report.study import plot_study, study_report
from service.run.dask_executor import local_cluster
from service.run.runner import result_from_store
from service.run.store import Store
from service.run.study import parse_request, read_study, run_study, store_paths
from service.spec import load
from worker.simulators import Linear

pytestmark = pytest.mark.distributed
ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
N_SAMPLES, FS = 300, 100.0
MODELS = {"light": 1.0, "heavy": 3.0}  # name: fixed mass
REQUEST = {"datasets": 6, "noise_share": 0.01, "seed": 5}


@pytest.fixture(scope="module")
def client():
    """2 single-threaded worker processes."""
    with local_cluster(2) as c, Client(c) as client:
        client.wait_for_workers(2, timeout=120)
        yield client


def write_spec(folder: Path) -> Path:
    """The cheap spec; its own observed record is only the template's (a study replaces it)."""
    rng = np.random.default_rng(1)
    force = 10 * rng.standard_normal(N_SAMPLES)
    folder.mkdir(parents=True, exist_ok=True)
    np.savez(folder / "data.npz", force=force, observed=force * 0.01)
    spec = {"name": "cheap", "seed": 3,
            "data": {"fs": FS, "input": "data.npz:force", "observed": "data.npz:observed", "fit": [0, N_SAMPLES]},
            "models": [{"name": name, "simulator": "linear", "fixed": {"m": m},
                        "priors": {"c": [0.05, 0.5], "k": [20, 200]}} for name, m in MODELS.items()],
            "sampler": {"particles": 100, "batch_size": 100}, "stop": {"max_populations": 6}}
    path = folder / "spec.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def study_in(client, folder: Path, **request) -> tuple[dict, dict]:
    """(study.json, report) of the cheap study run into ``folder`` (each job whole on a worker)."""
    spec, base = load(write_spec(folder / "spec"))
    outcomes = run_study(client, spec, base, parse_request({**REQUEST, **request}), folder / "study", local_s=1e3)
    assert [o.status for o in outcomes] == ["finished"] * len(outcomes), [o.error for o in outcomes]
    held = read_study(folder / "study")
    return held, study_report(held, store_paths(folder / "study", held))


def test_a_study_of_six_data_sets_and_its_report_recomputed_from_the_stores(client, tmp_path):
    """Each data set is the spec's simulator at its truth plus Gaussian noise of 1 % of the
    clean RMS, seeded by the study's SeedSequence child; each job ran with the child's seed;
    the confusion matrix, the ECE, the 50 / 95 % coverage and the SBC ranks equal those
    computed here from the stores' results (the summary's own 95 % quantiles for the 95 %
    intervals)."""
    held, report = study_in(client, tmp_path)
    force = np.load(tmp_path / "spec" / "data.npz")["force"]
    models = list(MODELS)
    counts = np.zeros((2, 2), dtype=int)
    pairs, in50, in95, ranks = [], 0, 0, {}
    for ds, child in zip(held["datasets"], np.random.SeedSequence(5).spawn(6), strict=True):
        rec = np.load(tmp_path / "study" / "data" / f"ds-{ds['index']:04d}.npz")
        p = ds["parameters"]
        clean = Linear(force, 1 / FS).simulate(np.array([[MODELS[ds["model"]], p["c"], p["k"]]])).values[0]
        np.testing.assert_allclose(rec["clean"], clean, rtol=1e-12)
        assert ds["noise_std"] == pytest.approx(0.01 * np.sqrt(np.mean(clean**2)), rel=1e-12)
        # 300 residuals of std noise_std: their sample variance / noise_std^2 ~ chi2_300 / 300, within
        # [0.72, 1.31] with probability 1 - 2e-5 (scipy.stats.chi2(300).ppf(1e-5) / 300, ppf(1 - 1e-5) / 300)
        assert 0.72 < np.var(rec["observed"] - clean) / ds["noise_std"] ** 2 < 1.31
        assert ds["seed"] == int(child.generate_state(1, np.uint64)[0] >> np.uint64(1))
        store = Store.open(tmp_path / "study" / "jobs" / f"ds-{ds['index']:04d}.zarr")
        assert store.attrs["spec"]["seed"] == ds["seed"]
        result = result_from_store(store)
        s = result.summary()
        probs = [s["model_probabilities"][m] for m in models]
        truth = models.index(ds["model"])
        counts[truth, int(np.argmax(probs))] += 1
        pairs += [(q, float(j == truth)) for j, q in enumerate(probs)]
        theta, w, _ = result.answer_draws(truth)  # the answer's particles: the likelihood reading's, or
        # a provisional run's tolerance's where its reading is thin (these runs stop at 6 populations)
        for j, name in enumerate(("c", "k")):
            post = s["posterior"][ds["model"]][name]
            in95 += post["q2_5"] <= p[name] <= post["q97_5"]
            lo, hi = weighted_quantiles(theta[:, j], w, (0.25, 0.75))
            in50 += lo <= p[name] <= hi
            ranks.setdefault(f"{ds['model']}.{name}", []).append(float(np.sum(w[theta[:, j] < p[name]]) / np.sum(w)))
    assert report["confusion_matrix"]["counts"] == counts.tolist()
    assert report["coverage"]["all"]["n"] == 12
    assert report["coverage"]["all"]["cover95"] == pytest.approx(in95 / 12)
    assert report["coverage"]["all"]["cover50"] == pytest.approx(in50 / 12)
    for key, r in ranks.items():
        np.testing.assert_allclose(report["sbc"][key]["ranks"], r, atol=1e-12)
    bins: dict[int, list] = {}
    for q, y in pairs:
        bins.setdefault(min(int(q * 10), 9), []).append((q, y))
    ece = sum(abs(sum(y for _, y in b) - sum(q for q, _ in b)) for b in bins.values()) / len(pairs)
    assert report["calibration"]["ece"] == pytest.approx(ece, abs=1e-12)
    lo, hi = report["calibration"]["ece_interval"]
    assert lo <= report["calibration"]["ece"] <= hi or hi - lo < 1e-12


def _fingerprint(store: Path) -> dict:
    return {str(f.relative_to(store)): (f.stat().st_mtime_ns, f.read_bytes()) for f in sorted(store.rglob("*"))
            if f.is_file()}


def _finished(folder: Path) -> list[Path]:
    out = []
    for path in sorted((folder / "jobs").glob("ds-*.zarr")):
        with contextlib.suppress(Exception):  # a store being made: not finished
            if Store.open(path).attrs.get("status") == "finished":
                out.append(path)
    return out


def abcns(*args, **kw) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "ABCNS_LOCAL_POPULATION_S": "1000"}
    return subprocess.Popen([BIN / "abcns", *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, **kw)


def without_cost(report: dict) -> dict:
    out = {k: v for k, v in report.items() if k != "cost"}
    out["rows"] = [{k: v for k, v in r.items() if k != "wall_time_s"} for r in report["rows"]]
    return out


def test_a_killed_study_reruns_no_finished_job_and_ends_identical(client, tmp_path):
    """`abcns study` (on the module's cluster) killed (SIGKILL) once 2 of its 8 jobs have
    finished; run again, it leaves every store that had finished untouched (each file's
    bytes and mtime) and ends with the report of the same study run without a kill."""
    spec = write_spec(tmp_path / "spec")
    folder = tmp_path / "killed"
    args = ("study", spec, "--datasets", 8, "--noise-share", 0.01, "--seed", 5, "--out", folder,
            "--scheduler", client.scheduler_info()["address"])
    proc = abcns(*args)
    deadline = time.monotonic() + 300
    while len(_finished(folder)) < 2 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    done = {p: _fingerprint(p) for p in _finished(folder)}
    assert 2 <= len(done) < 8, len(done)  # killed in the middle
    again = abcns(*args, "--json")
    out, err = again.communicate(timeout=600)
    assert again.returncode == 0, err
    assert {p: _fingerprint(p) for p in done} == done
    _, reference = study_in(client, tmp_path / "reference", datasets=8)
    assert without_cost(json.loads(out)) == without_cost(json.loads(json.dumps(reference)))
    summary = abcns("summary", folder, "--json")
    assert json.loads(summary.communicate(timeout=120)[0]) == json.loads(out)
    plot = abcns("plot", folder, "--out", tmp_path / "figures")
    listed = plot.communicate(timeout=120)[0].split()
    assert sorted(Path(p).name for p in listed) == [f"study-{k}.png" for k in ("confusion", "coverage", "reliability", "sbc")]
    assert all(Path(p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in listed)


BAD_INPUT = [
    (("--noise-share", "-0.1"), "noise_share"),
    (("--noise-std", "nan"), "noise_std"),
    ((), "noise_std"),
    (("--noise-std", "0.1", "--noise-share", "0.01"), "noise_std or noise_share, not both"),
    (("--noise-share", "0.01", "--truth", "quintic"), "truth: 'quintic' is not one of the spec's models"),
    (("--noise-share", "0.01", "--truth-param", "k=1e6"), "truth_parameters.k: 1e+06 lies outside the prior"),
    (("--noise-share", "0.01", "--truth-param", "k3=1"), "truth_parameters.k3: is not a free parameter"),
    (("--noise-share", "0.01", "--datasets", "0"), "datasets"),
]


def study_argv(tmp_path: Path, args: tuple) -> list[str]:
    argv = ["study", write_spec(tmp_path / "spec"), "--out", tmp_path / "study", *args]
    return [str(a) for a in (argv if "--datasets" in args else [*argv, "--datasets", "3"])]


@pytest.mark.parametrize(("args", "field"), BAD_INPUT)
def test_bad_input_is_refused_with_its_field_before_any_job(tmp_path, args, field):
    """Exit 2, the field named on stderr, and no data set or job made. In this process
    (typer's CliRunner, stdout and stderr apart): the refusal is the command's own code; what
    the installed command's process adds (its exit status, its stderr) is the next test's."""
    from typer.testing import CliRunner

    from service.cli import app

    done = CliRunner().invoke(app, study_argv(tmp_path, args), prog_name="abcns")
    assert done.exit_code == 2, (done.stderr, done.exception)
    assert field in done.stderr
    assert not list((tmp_path / "study").glob("*/*"))


def test_the_installed_command_refuses_bad_input_with_exit_status_2(tmp_path):
    """The last case above as a process of the installed `abcns`: exit status 2, the field on stderr."""
    args, field = BAD_INPUT[-1]
    proc = abcns(*study_argv(tmp_path, args))
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 2, err
    assert field in err
    assert not list((tmp_path / "study").glob("*/*"))


def test_the_figures_draw_the_report(client, tmp_path, monkeypatch):
    """The confusion matrix's cells show each count and rate; the reliability diagram's
    points are the bins' (mean p, frequency); each rank histogram's bars are its counts;
    the coverage bars are the 50 and 95 % coverages."""
    _, report = study_in(client, tmp_path)
    saved = record_saved(monkeypatch)
    files = plot_study(report, tmp_path / "figures")
    figs = {p.stem: saved[p] for p in files}
    conf = report["confusion_matrix"]
    texts = {(round(t.get_position()[1]), round(t.get_position()[0])): t.get_text()
             for t in figs["study-confusion"].axes[0].texts}
    for i, row in enumerate(conf["counts"]):
        for j, c in enumerate(row):
            rate = conf["rates"][i][j]
            assert texts[(i, j)] == f"{c}\n{'-' if rate is None else format(rate, '.2f')}"
    ax = figs["study-reliability"].axes[0]
    points = next(line for line in ax.lines if line.get_marker() == "o")
    np.testing.assert_allclose(points.get_xdata(), [b["mean_p"] for b in report["calibration"]["bins"]])
    np.testing.assert_allclose(points.get_ydata(), [b["frequency"] for b in report["calibration"]["bins"]])
    assert f"ECE {report['calibration']['ece']:.3f}" in ax.get_title()
    sbc = [(k, s) for k, s in report["sbc"].items() if s["ranks"]]
    for ax, (key, s) in zip(figs["study-sbc"].axes, sbc, strict=False):
        assert [p.get_height() for p in ax.patches] == s["histogram"]
        assert ax.get_title().startswith(key)
    ax = figs["study-coverage"].axes[0]
    keys = [k for k in report["coverage"] if k != "all"]
    heights = [p.get_height() for p in ax.patches]
    assert heights == [report["coverage"][k]["cover50"] for k in keys] + [report["coverage"][k]["cover95"] for k in keys]


def study_body(folder: Path, **fields) -> dict:
    """POST /studies' body: the cheap spec with its data inline, and the study's fields."""
    spec = yaml.safe_load(write_spec(folder).read_text())
    data = np.load(folder / "data.npz")
    spec["data"].update(input=data["force"].tolist(), observed=data["observed"].tolist())
    return {"spec": spec, **fields}


def test_a_study_over_http_queues_its_jobs_and_reports_as_in_process(client, tmp_path):
    """POST /studies refuses a wrong noise, truth or truth value with 422 naming the field, and
    a study larger than the queue's room with 429, and queues nothing; a study of 4 data sets
    is queued as 4 jobs of the service, and its report
    (GET /studies/ID) gives the same model probabilities, choices and coverage as the same
    study run here (the determinism contract: the same data sets and seeds, the same answers)."""
    import httpx

    from benchmarks.harness import TOKEN, Service

    service = Service(tmp_path / "jobs", client.scheduler_info()["address"], max_running=None,
                      env={"ABCNS_LOCAL_POPULATION_S": "1000"})
    try:
        with httpx.Client(base_url=service.url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60) as http:
            for fields, field in (({"noise_share": -1}, "noise_share"), ({"noise_std": 0.1, "truth": "quintic"}, "truth"),
                                  ({"noise_std": 0.1, "truth_parameters": {"c": 9}}, "truth_parameters.c"),
                                  ({"datasets": 0, "noise_std": 0.1}, "datasets")):
                answer = http.post("/studies", json=study_body(tmp_path / "spec", **{"datasets": 2, **fields}))
                assert answer.status_code == 422, answer.text
                assert answer.json()["detail"][0]["field"] == field, answer.text
            answer = http.post("/studies", json=study_body(tmp_path / "spec", datasets=65, noise_std=0.1))
            assert answer.status_code == 429 and "room for 64 jobs" in answer.text, answer.text  # ABCNS_MAX_QUEUED 64
            assert http.get("/jobs").json() == []
            answer = http.post("/studies", json=study_body(tmp_path / "spec", datasets=4, noise_share=0.01, seed=5))
            assert answer.status_code == 201, answer.text
            study_id = answer.json()["id"]
            deadline = time.monotonic() + 300
            while not (out := http.get(f"/studies/{study_id}").json())["done"] and time.monotonic() < deadline:
                time.sleep(0.5)
            page = http.get(f"/studies/{study_id}/view")
            assert page.status_code == 200 and "confusion matrix" in page.text
            assert http.get(f"/studies/{'0' * 32}").status_code == 404
        assert out["counts"] == {"finished": 4}, out["counts"]
    finally:
        service.close()
    _, here = study_in(client, tmp_path / "here", datasets=4)
    keep = ("model", "probabilities", "chosen", "parameters")
    assert [{k: r[k] for k in keep} for r in out["rows"]] == [{k: r[k] for k in keep} for r in here["rows"]]
    assert out["confusion_matrix"] == here["confusion_matrix"]


def test_the_report_flags_miscalibration_it_is_shown():
    """Rows made here (no jobs): probabilities of 0.9 for a model right half the time give an
    ECE of 0.4 that the calibrated reference (outcomes drawn from the same probabilities) does
    not reach; truths always below every draw give ranks 0, a rank histogram rejected at 1 %,
    and no 50 / 95 % interval holding them. Seeded (default_rng(0) for the bootstrap)."""
    from service.report.study import calibration, parameter_checks

    rows = [{"model": "a" if i % 2 else "b", "probabilities": [0.9, 0.1],
             "parameters": {"x": {"truth": 0.0, "rank": 0.0, "in50": False, "in95": False}}} for i in range(40)]
    cal = calibration(rows, ["a", "b"], seed=0)
    assert cal["ece"] == pytest.approx(0.4)  # bins 0.9 and 0.1 each at frequency 0.5
    assert cal["ece_if_calibrated"]["q95"] < 0.2 < cal["ece_interval"][0]
    assert [(b["mean_p"], b["frequency"], b["n"]) for b in cal["bins"]] == [(0.1, 0.5, 40), (0.9, 0.5, 40)]
    coverage, sbc = parameter_checks(rows)
    assert coverage["a.x"]["cover95"] == coverage["b.x"]["cover50"] == 0.0
    assert sbc["a.x"]["histogram"][0] == 20 and sbc["a.x"]["p_value"] < 0.01 and sbc["a.x"]["ks_p_value"] < 0.01
