"""benchmarks.exact_bayes (dynesty's exact Bayes beside abcns) as a smoke run: one tiny case
(linear-vs-cubic, seed 1, 50 live points, 200 particles) prints its tables, writes its cache,
and a second run reads dynesty's answer back from it. Marked ``peers``: `make bench-peers`
installs the optional extra .[bench] (dynesty); `make test` deselects it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.slow, pytest.mark.peers]

COLUMNS = {
    "runs": ["case", "seed", "exact winner", "abcns winner", "losing model", "p abcns ± se", "p exact ± se",
             "(abcns - exact) / se", "rule", "reading", "stop", "warnings", "abcns simulations", "dynesty evaluations",
             "simulations / evaluations", "abcns wall s", "dynesty wall s"],
    "models": ["case", "seed", "model", "exact log Z ± err", "p exact ± se", "p abcns ± se", "dynesty evaluations",
               "iterations", "effective samples", "dynesty wall s", "abcns effective particles",
               "ln BF against the exact winner, abcns - exact"],
    "parameters": ["case", "seed", "model", "parameter", "exact mean ± sd", "abcns mean ± sd",
                   "95 % width abcns / exact", "exact width rse", "mean shift (exact sd)", "within"],
    "cases": ["case", "runs", "winner agrees", "losing p within max(0.005, 2 se)", "width ratio min", "width ratio max",
              "max abs mean shift (exact sd)", "simulations / evaluations"],
}


def tables(text: str) -> list[list[list[str]]]:
    """The markdown tables of ``text``: rows of cells, the separator rows left out."""
    out: list[list[list[str]]] = []
    previous = False
    for line in text.splitlines():
        row = line.startswith("|")
        if row and not previous:
            out.append([])
        if row and not line.startswith("|---"):
            out[-1].append([c.strip() for c in line.strip().strip("|").split("|")])
        previous = row
    return out


def smoke(tmp_path: Path, json_out: Path) -> str:
    done = subprocess.run([sys.executable, "-m", "benchmarks.exact_bayes", "--case", "linear-vs-cubic", "--seeds", "1",
                           "--nlive", "50", "--particles", "200", "--cache", str(tmp_path / "cache"),
                           "--json", str(json_out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_tiny_case_prints_the_tables_and_caches_dynesty(tmp_path: Path) -> None:
    pytest.importorskip("dynesty")
    text = smoke(tmp_path, tmp_path / "rows.json")
    found = tables(text)
    assert [t[0] for t in found] == list(COLUMNS.values()), text
    runs, models, params, cases = found
    assert len(runs) == 2 and runs[1][:2] == ["linear-vs-cubic", "1"] and runs[1][2] in ("linear", "cubic")
    assert sorted(r[2] for r in models[1:]) == ["cubic", "linear"]
    assert len(params) >= 3 and {r[3] for r in params[1:]} <= {"c", "k", "k3"}
    assert len(cases) == 2 and cases[1][1] == "1"
    assert text.splitlines()[-1].startswith("Done when: exact winner every time")
    assert "(cached)" not in text
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == [
        "linear-vs-cubic-s1-cubic-n50.json", "linear-vs-cubic-s1-linear-n50.json"]
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert rows[0]["exact"]["models"]["linear"]["n_evaluations"] > 0
    again = smoke(tmp_path, tmp_path / "again.json")
    assert again.count("(cached)") == 3, again  # both models in the model table, the run's total
    first = json.loads((tmp_path / "again.json").read_text())[0]["exact"]["models"]
    assert {m: a["log_z"] for m, a in first.items()} == {m: a["log_z"] for m, a in rows[0]["exact"]["models"].items()}
