"""The worked examples: committed data are what their prepare scripts make, and a shortened
run of each (few particles, few populations) goes through to its figures and tables."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from examples import analyse, hyperparameters
from examples.boucwen import evaluate as bw_evaluate
from examples.boucwen import prepare as bw_prepare
from examples.silverbox import evaluate as sb_evaluate
from examples.silverbox import prepare as sb_prepare
from service.analysis import run_to_store
from service.spec import load

ROOT = Path(__file__).resolve().parents[1]
needs_boucwen = pytest.mark.skipif(not bw_prepare.SOURCE.exists(), reason="shared Bouc-Wen data not present")
needs_silverbox = pytest.mark.skipif(not sb_prepare.SOURCE.exists(), reason="shared Silverbox data not present")


@needs_boucwen
def test_boucwen_data_is_what_prepare_makes():
    d = bw_prepare.load()
    for key in ("force", "displacement"):
        np.testing.assert_array_equal(np.load(ROOT / "examples" / "boucwen" / f"{key}.npy"), d[key])
    assert d["test_multisine"]["force"].size == 2 * d["test_multisine"]["y"].size == 16384


@needs_silverbox
def test_silverbox_data_is_what_prepare_makes():
    u, y = sb_prepare.segments()[sb_prepare.FIT]
    np.testing.assert_array_equal(np.load(ROOT / "examples" / "silverbox" / "force.npy"), u)
    np.testing.assert_array_equal(np.load(ROOT / "examples" / "silverbox" / "displacement.npy"), y)


def rmse_cells(text: str) -> list[float]:
    """The two RMSE columns of every test-record row of test_rmse.md."""
    rows = [line.split("|")[3:5] for line in text.splitlines() if line.startswith(("| multisine", "| sine sweep"))]
    return [float(c) for row in rows for c in row]


@needs_boucwen
def test_boucwen_short_run_and_test_rmse(tmp_path):
    # the store only (analyse.py's figures are exercised by the Silverbox test)
    spec, base = load(ROOT / "examples" / "boucwen" / "spec.yaml")
    spec = spec.model_copy(update={"sampler": spec.sampler.model_copy(update={"particles": 100}),
                                   "stop": spec.stop.model_copy(update={"max_populations": 3})})
    run_to_store(spec, base, tmp_path / "seed3.zarr", seed=3)
    bw_evaluate.main(["--seed", "3", "--out", str(tmp_path), "--figures", str(tmp_path / "figures")])
    text = (tmp_path / "figures" / "seed3" / "test_rmse.md").read_text()
    assert "multisine" in text and "sine sweep" in text and "linear (fitted alone)" in text
    values = rmse_cells(text)
    assert len(values) == 8 and all(np.isfinite(v) and v > 0 for v in values)
    assert (tmp_path / "figures" / "seed3" / "test_sine_sweep.png").stat().st_size > 5000


@needs_silverbox
def test_silverbox_short_run_and_heldout_nmse(tmp_path):
    analyse.main([str(ROOT / "examples" / "silverbox" / "spec.yaml"), "--out", str(tmp_path), "--seed", "3",
                  "--particles", "100", "--max-populations", "3"])
    sb_evaluate.main(["--seed", "3", "--out", str(tmp_path), "--figures", str(tmp_path / "figures")])
    text = (tmp_path / "figures" / "seed3" / "heldout.md").read_text()
    assert "| r9 |" in text.replace(" r9 |", "| r9 |") and (tmp_path / "figures" / "seed3" / "heldout.png").exists()


def test_hyperparameter_study_quick(tmp_path):
    hyperparameters.main(["--quick", "--out", str(tmp_path)])
    names = {p.name for p in tmp_path.iterdir()}
    assert names == {"fig4_f0_acceptance.png", "fig5_f0_posterior.png", "fig6_pairs_acceptance.png",
                     "fig7_pairs_posterior.png", "table.md"}
    assert (tmp_path / "table.md").read_text().count("\n") == 2 + len(hyperparameters.F0) + len(hyperparameters.PAIRS)


@needs_silverbox
def test_silverbox_levels_confusion_quick(tmp_path):
    from examples.silverbox import levels

    levels.main(["--out", str(tmp_path / "runs"), "--figures", str(tmp_path / "fig"), "--particles", "60",
                 "--max-populations", "2", "--levels", "low", "high"])
    assert (tmp_path / "fig" / "confusion.png").stat().st_size > 5000
    assert {p.name for p in (tmp_path / "fig").iterdir()} == {"low", "high", "confusion.png"}
