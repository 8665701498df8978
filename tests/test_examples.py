"""The examples' data are what their fixed-seed script makes; every example spec builds;
the benchmarks run (their speed is reported, never tested)."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from examples import make_data
from service.spec import build, load

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", ["linear_31", "gandk_32", "duffing_41"])
def test_committed_data_is_what_the_script_makes(name):
    for key, arr in getattr(make_data, name)().items():
        np.testing.assert_array_equal(np.load(ROOT / "examples" / name / f"{key}.npy"), arr, err_msg=f"{name}/{key}")


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
