"""What a user sees from the `abcns` command: `--version`, `run` ending with a short human
summary (with or without the per-population lines), `--json`, `summary`, and the NMSE
marked as a percentage (Eq. 7: 100 / (n s^2) ...)."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest
import yaml

from benchmarks.harness import StockCluster

pytestmark = pytest.mark.distributed
ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
DEMO = ROOT / "data" / "authors-demo" / "demo_data.npz"
POPULATIONS = 3


def abcns(*args, timeout: float = 300) -> subprocess.CompletedProcess:
    done = subprocess.run([BIN / "abcns", *map(str, args)], capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr
    return done


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    c = StockCluster(tmp_path_factory.mktemp("dask"), n_workers=1)
    yield c.address
    c.close()


@pytest.fixture(scope="module")
def spec(tmp_path_factory) -> Path:
    """The authors' demo, shortened to a few populations of 200 particles."""
    raw = yaml.safe_load((ROOT / "examples" / "authors_demo" / "spec.yaml").read_text())
    raw["data"].update(input=f"{DEMO}:force", observed=f"{DEMO}:displacement")
    raw["sampler"].update(particles=200, batch_size=100)
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": POPULATIONS}
    path = tmp_path_factory.mktemp("spec") / "spec.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def assert_human_summary(lines: list[str]) -> None:
    assert lines[0].startswith("status finished  stop max_populations  populations 3  simulations ")
    assert lines[1].startswith("tolerance (NMSE) 100 % -> ") and "%; mean acceptance" in lines[1]
    assert lines[2].startswith("model probabilities: linear ") and ", cubic " in lines[2]
    assert not any(line.lstrip().startswith(("{", "}", '"')) for line in lines), "JSON in the human summary"


def test_version():
    done = abcns("--version", timeout=60)
    assert done.stdout.strip() == f"abcns {version('abcns')}"


def test_run_prints_populations_then_a_short_summary(spec, cluster, tmp_path):
    lines = abcns("run", spec, "--out", tmp_path / "a.zarr", "--scheduler", cluster).stdout.splitlines()
    pops = [line for line in lines if line.startswith("population ")]
    assert len(pops) == POPULATIONS and all("eps" in p and " %  acceptance" in p for p in pops)
    rest = lines[len(pops):]
    assert rest[0] == ""  # a blank line, then the summary
    assert_human_summary(rest[1:])
    assert rest[-1].startswith("store: ") and "abcns summary" in rest[-1] and "--json" in rest[-1]
    assert len(lines) < 30  # no screens of JSON


def test_run_quiet_still_prints_the_summary(spec, cluster, tmp_path):
    lines = abcns("run", spec, "--out", tmp_path / "q.zarr", "--scheduler", cluster, "--quiet").stdout.splitlines()
    assert not any(line.startswith("population ") for line in lines)
    assert lines[0] == ""
    assert_human_summary(lines[1:])


def test_run_json_and_summary_of_the_store(spec, cluster, tmp_path):
    out = tmp_path / "j.zarr"
    s = json.loads(abcns("run", spec, "--out", out, "--scheduler", cluster, "--quiet", "--json").stdout)
    assert s["status"] == "finished" and s["n_populations"] == POPULATIONS and len(s["epsilon"]) == POPULATIONS
    assert json.loads(abcns("summary", out, "--json").stdout) == s
    assert_human_summary(abcns("summary", out).stdout.splitlines())
    # run again on the finished store: nothing recomputed, the same short summary
    again = abcns("run", spec, "--out", out, "--scheduler", cluster, "--quiet").stdout.splitlines()
    assert_human_summary(again[1:])


def test_summary_lines_show_the_uncertainty_the_death_rule_and_every_warning():
    from service.cli import summary_lines

    s = {"status": "finished", "stop_reason": "min_epsilon_decrease", "n_populations": 3, "n_simulations": 1234,
         "wall_time_s": 1.0, "epsilon": [100.0, 7.87], "acceptance_rate": [0.5, 0.3],
         "model_probabilities": {"cubic": 0.55, "cubic-quintic": 0.45},
         "model_probability_se": {"cubic": 0.04, "cubic-quintic": 0.04},
         "dead_models": {"linear": 2}, "death_rules": {"linear": "probability"},
         "warnings": ["undecided: cubic (p = 0.55), cubic-quintic (p = 0.45) are all above 0.1"], "posterior": {}}
    lines = summary_lines(s)
    assert "model probabilities: cubic 0.550 ± 0.040, cubic-quintic 0.450 ± 0.040" in lines
    assert any(line.endswith("linear 2 (probability)") for line in lines)
    assert "warning: undecided: cubic (p = 0.55), cubic-quintic (p = 0.45) are all above 0.1" in lines
    assert any("7.87 %" in line for line in lines)  # the NMSE is in percent


def test_an_impossible_fixed_value_is_refused_before_the_run_with_exit_2(tmp_path):
    """P.3: ``bouc_wen`` with ``fixed: {n: 1.5}`` ran (exit 0) and every simulation failed;
    it is now refused naming the field, with the CLI's error exit, and no store is made."""
    raw = yaml.safe_load((ROOT / "examples" / "boucwen" / "spec.yaml").read_text())
    raw["data"].update(input=str(ROOT / "examples" / "boucwen" / "force.npy"),
                       observed=str(ROOT / "examples" / "boucwen" / "displacement.npy"))
    raw["models"][1]["fixed"]["n"] = 1.5
    path = tmp_path / "n.yaml"
    path.write_text(yaml.safe_dump(raw))
    done = subprocess.run([BIN / "abcns", "run", path, "--out", tmp_path / "n.zarr", "--workers", "1"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("error: models[1].fixed.n: must be an integer in 1..4"), done.stderr
    assert not (tmp_path / "n.zarr").exists()


def test_a_bug_in_a_simulator_names_the_batch_and_the_exception(spec, tmp_path):
    """Issue M: an unexpected exception inside a worker (tests/faulty_plugin.py raises a
    RuntimeError in population 1) fails the run with the batch, the model (P.1) and the
    exception's type, in the CLI's message, the store's status and the summary; numerical
    failures stay counted rejections."""
    raw = yaml.safe_load(spec.read_text())
    for model in raw["models"]:
        model["simulator"] = "tests.faulty_plugin:Faulty"
    path = tmp_path / "faulty.yaml"
    path.write_text(yaml.safe_dump(raw))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}  # the plugin is importable on the workers
    done = subprocess.run([BIN / "abcns", "run", path, "--out", tmp_path / "f.zarr", "--workers", "1"],
                          capture_output=True, text=True, timeout=300, env=env)
    assert done.returncode == 2, done.stderr  # the CLI's error exit
    assert re.search(r"error: the job failed in population 1, batch \d+: model '(linear|cubic)' \(simulator "
                     r"'tests\.faulty_plugin:Faulty'\): RuntimeError: a bug in the user's simulator",
                     done.stderr), done.stderr[-2000:]
    assert "Traceback (most recent call last)" not in done.stderr  # a message, not a Python traceback
    s = json.loads(abcns("summary", tmp_path / "f.zarr", "--json").stdout)
    assert s["status"] == "failed" and "RuntimeError: a bug in the user's simulator" in s["error"], s
    assert "population 1, batch" in s["error"]


def test_on_a_terminal_the_progress_is_one_line_rewritten_and_the_dashboard_link_is_printed(spec, tmp_path):
    """J.5: with a terminal on stdout (a pseudo-terminal here) each population rewrites one
    line (carriage return, erase line) that names the workers; --dashboard prints the Dask
    dashboard's link; the summary follows on its own lines."""
    import pty

    primary, secondary = pty.openpty()
    done = subprocess.run([BIN / "abcns", "run", spec, "--out", tmp_path / "t.zarr", "--workers", "1", "--dashboard"],
                          stdout=secondary, stderr=subprocess.PIPE, timeout=300)
    os.close(secondary)
    chunks = []
    while True:
        try:
            data = os.read(primary, 65536)
        except OSError:  # the terminal closed
            break
        if not data:
            break
        chunks.append(data)
    os.close(primary)
    out = b"".join(chunks).decode()
    assert done.returncode == 0, done.stderr.decode()[-2000:]
    assert out.count("\r\x1b[2Kpopulation ") == POPULATIONS and "workers 1" in out
    assert "status finished" in out and "model probabilities: " in out
    if importlib.util.find_spec("bokeh") is None:  # the dev extra does not install it
        assert "the Dask dashboard needs bokeh" in done.stderr.decode()
    else:
        assert re.search(r"Dask dashboard: http://\S+:\d+/status", done.stderr.decode())
