"""The scale-out benchmark runs (its speed is reported, never tested): a LocalCluster of one
worker, a stock ``dask scheduler``/``dask worker`` and the §4.1 part on one worker, each for
one population (every code path of ``--quick``, with one cluster size each instead of two,
and the sleepy simulator's sleep at 0.2 ms per simulation instead of 2 ms: the same calls,
a tenth of the sleeping), and prints its tables."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks import sleepy

ROOT = Path(__file__).resolve().parents[1]


def test_sleepy_plugin_is_duffing_plus_sleep():
    from worker import registry
    from worker.simulators import Duffing

    factory = registry.get(sleepy.NAME, allow_import=True)
    kwargs = dict(force=np.sin(np.arange(50) / 5), dt=0.01, n_samples=50, substeps=1, output="displacement",
                  state_bound=1e3)
    sim = factory(**kwargs)
    ref = Duffing(**{k: v for k, v in kwargs.items() if k != "n_samples"})  # an oscillator's length is its force's
    params = np.array([[1.0, 0.1, 50.0, 0.0, 1000.0, 0.0]] * 5)
    before = sleepy.simulated()
    out = sim.simulate(params, np.random.default_rng(0))
    np.testing.assert_array_equal(out.values, ref.simulate(params).values)
    assert sleepy.simulated() - before == 5
    assert (sim.parameter_names, sim.n_samples, sim.config()["simulator"]) == (ref.parameter_names, 50, sleepy.NAME)


@pytest.mark.slow
@pytest.mark.distributed
def test_scale_benchmark_runs():
    done = subprocess.run([sys.executable, "-m", "benchmarks.scale", "--workers", "1", "--stock-workers", "1",
                           "--populations", "1", "--d41-workers", "1", "--d41-populations", "1", "--sleep-ms", "0.2",
                           "--timeline"],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "| workers | simulations | executed | wall s | sims/s | ideal sims/s | efficiency |" in done.stdout
    assert "| steady | Dask floor | no-barrier floor |" in done.stdout  # both floors, measured (not nan)
    rows = [line.split("|") for line in done.stdout.splitlines() if line.startswith("| 1 | ")]
    floors = [row[9:11] for row in rows if len(row) >= 17]  # the sleepy tables' rows (15 or 16 columns)
    assert floors and all(0 < float(v) <= 1.05 for row in floors for v in row), floors
    assert "end to end / (N x kernel alone)" in done.stdout
    assert done.stdout.count("| workers | wall s | start ms | end ms | gaps ms | spans s / simulations s |") == 2


def test_timeline_takes_a_run_apart():
    """Two populations of batches of 10: population 1 used 25 simulations (batches 1-3; batch 4
    is surplus), population 2 used 10 (batch 1). Times in seconds after the run's start."""
    from benchmarks.scale import task_rows, timeline

    key = lambda t, first, last: ("abcns-0123456789ab-nonce", t, first, last)
    compute = lambda start, stop: {"startstops": [{"action": "transfer", "start": 0.0, "stop": 0.0},
                                                  {"action": "compute", "start": 100 + start, "stop": 100 + stop}]}
    records = [{"key": ("abcns-data-0123456789ab-nonce",), **compute(0.0, 0.01)},  # the job's data: left out
               {"key": key(0, 0, 0), **compute(0.01, 0.02)},  # an anchor: left out
               {"key": key(1, 1, 1), **compute(0.2, 0.3)}, {"key": key(1, 2, 3), **compute(0.21, 0.5)},
               {"key": key(1, 4, 4), **compute(0.3, 0.9)},  # surplus: runs past the last used task
               {"key": key(2, 1, 1), **compute(0.6, 0.7)}]
    rows = task_rows(records, epoch=100.0)
    assert [r[:2] for r in rows] == [(1, 1), (1, 2), (1, 4), (2, 1)]
    tl = timeline(rows, [25, 10], batch_size=10, wall=1.0)
    assert tl["start"] == pytest.approx(0.2)  # before population 1's first task
    assert tl["end"] == pytest.approx(0.3)  # after population 2's last used task (0.7)
    assert tl["gaps"] == pytest.approx([0.1])  # population 1's last used task ends 0.5, population 2 starts 0.6
    assert tl["spans"] == pytest.approx(0.3 + 0.1)


def test_pyabc_part_is_off_by_default_and_skipped_without_pyabc(monkeypatch, capsys):
    from benchmarks import scale

    monkeypatch.setitem(sys.modules, "pyabc", None)  # import pyabc raises ImportError
    monkeypatch.setattr(sys, "argv", ["scale", "--skip-local", "--skip-stock", "--skip-d41"])
    scale.main()
    assert "pyABC" not in capsys.readouterr().out
    monkeypatch.setattr(sys, "argv", ["scale", "--skip-local", "--skip-stock", "--skip-d41", "--pyabc-workers", "1"])
    scale.main()
    assert "## pyABC: skipped, pyABC cannot be imported" in capsys.readouterr().out


def test_pyabc_model_and_distance():
    from benchmarks import scale

    np.random.seed(0)  # noqa: NPY002
    x = scale.pyabc_model({"a": 1.0, "b": -0.5}, seconds=0.0)
    assert x["y"].shape == (2,)
    assert scale.pyabc_distance(x, {"y": np.array(scale.PYABC_OBSERVED)}) == float(np.sum((x["y"] - [1.0, -0.5]) ** 2))
