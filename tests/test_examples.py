"""The examples' data are what their fixed-seed script makes (up to float64 rounding: the
script's numpy/scipy routines may round differently on another machine); every example spec
builds; the benchmarks run (their speed is reported, never tested)."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from floats import assert_equal_up_to_rounding

from examples import make_data
from service.spec import build, load

ROOT = Path(__file__).resolve().parents[1]


# The longest chain of sequential float64 operations behind each data set (tests/floats.py):
# §3.1: 500 steps of the exact zero-order-hold recursion (scipy's expm, then ~16 operations a
# step); §3.2: one closed-form quantile per draw (~20 operations, numpy's exp/power); §4.1:
# 1000 samples x 64 RK4 substeps x ~64 operations a substep. The normal draws are exact.
OPERATIONS = {"linear_31": 500 * 16, "gandk_32": 20, "duffing_41": 1000 * 64 * 64}


@pytest.mark.parametrize("name", ["linear_31", "gandk_32", "duffing_41"])
def test_committed_data_is_what_the_script_makes(name):
    for key, arr in getattr(make_data, name)().items():
        assert_equal_up_to_rounding(np.load(ROOT / "examples" / name / f"{key}.npy"), arr, OPERATIONS[name], f"{name}/{key}")


def test_duffing_41_noise_is_one_percent_rms():
    d = make_data.duffing_41()
    noise = d["displacement"] - d["displacement_clean"]
    rms = np.sqrt(np.mean(d["displacement_clean"] ** 2))
    assert abs(np.std(noise) / rms - 0.01) < 0.001  # 1000 draws: sd of the sample sd ~ 2 %


@pytest.mark.parametrize("spec", sorted((ROOT / "examples").glob("*/spec.yaml")), ids=lambda p: p.parent.name)
def test_every_example_spec_builds(spec):
    job = build(*load(spec))
    assert job.models and job.observed.size > 0


@pytest.mark.slow
def test_engine_benchmark_runs():
    done = subprocess.run([sys.executable, "-m", "benchmarks.engine", "--quick"], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "paper §3.1 linear" in done.stdout and "summary:" in done.stdout


@pytest.mark.slow
@pytest.mark.parametrize(("args", "expect"), [
    (["benchmarks.model_selection", "--seeds", "1", "--processes", "1", "--max-populations", "4"], "right model with p"),
    (["benchmarks.gandk", "--seeds", "1", "--budget", "3000"], "| 1 |"),
], ids=["model_selection", "gandk"])
def test_model_selection_benchmarks_run(args, expect):
    done = subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert expect in done.stdout
