"""The side-by-side benchmark against pyABC (benchmarks/peers) as a smoke run: the command
with --quick writes its table. Marked ``peers``: `make bench-peers` runs it after installing the
optional extra .[bench] (pyABC), before the benchmark itself; `make test` deselects it."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [
    pytest.mark.slow,
    pytest.mark.peers,
    pytest.mark.skipif(importlib.util.find_spec("pyabc") is None, reason="pyABC not installed (pip install -e '.[bench]')"),
]


def test_quick_run_writes_the_table(tmp_path: Path) -> None:
    out = tmp_path / "RESULTS.md"
    done = subprocess.run([sys.executable, "-m", "benchmarks.peers", "--quick", "--out", str(out), "--json",
                           str(tmp_path / "runs.json"), "--db-dir", str(tmp_path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    text = out.read_text()
    assert "# abcns vs pyABC, side by side" in text and "## Summary" in text
    for key in ("§3.1", "§3.2", "§4.1"):
        assert f"| {key} |" in text
    assert text.count("| abcns | 1 |") == 3 and text.count("| pyABC | 1 |") == 3
    assert not list(tmp_path.glob("pyabc-*")), "pyABC's temporary databases are removed"
