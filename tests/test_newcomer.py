"""Issue AA: the newcomer's list (points 1-9), each checked where it can fail."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from service.cli import app

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def test_3_serve_prints_its_address_with_the_token_to_open(monkeypatch, tmp_path):
    """``abcns serve --token`` prints the address in the ``#token=`` form the README says to
    open (the page keeps the token; without it the charts stay empty, events 401)."""
    served = []
    monkeypatch.setattr("service.http.server.serve", lambda *args: served.append(args))
    out = CliRunner().invoke(app, ["serve", "--token", "s3 cret/x", "--port", "8123", "--store-dir", str(tmp_path)])
    assert out.exit_code == 0, out.output
    assert "serving http://127.0.0.1:8123/#token=s3%20cret%2Fx " in out.output and served
    plain = CliRunner().invoke(app, ["serve", "--port", "8123", "--store-dir", str(tmp_path)], env={"ABCNS_TOKEN": ""})
    assert "serving http://127.0.0.1:8123/ (API docs" in plain.output


def test_3_the_job_link_carries_the_token():
    """``abcns submit``'s job link (the same function) opens with the token (tests/test_submit.py
    checks the printed line of a real submit)."""
    from service.cli import page_link

    assert page_link("http://h:1/jobs/ab/view", "t") == "http://h:1/jobs/ab/view#token=t"
    assert page_link("http://h:1/jobs/ab/view", None) == "http://h:1/jobs/ab/view"


def test_1_the_bouc_wen_equation_units_and_prior_scaling_are_documented():
    """The docs give Bouc-Wen's equation, its units and the |z|^(1-n) prior scaling; the
    README's simulator table gives linear's parameters."""
    design = (ROOT / "docs" / "design.md").read_text()
    assert "z' = A y' - alpha \\|y'\\| \\|z\\|^(n-1) z - beta y' \\|z\\|^n" in design
    assert "alpha and beta (1/(m N^(n-1)))" in design and "Bouc-Wen priors scale with |z|^(1-n)" in design
    assert "`linear` (m c k;" in README


def test_2_the_local_cluster_recipe_binds_localhost():
    """Every `dask scheduler` / `dask worker` line of the README's recipe listens on 127.0.0.1, and says why."""
    lines = [line for line in README.splitlines() if line.startswith(("dask scheduler", "dask worker"))]
    assert len(lines) == 2 and all("--host 127.0.0.1" in line for line in lines)
    assert "a scheduler runs the code its clients send" in " ".join(README.split())


def test_5_truth_values_are_each_a_flag_and_stray_words_are_not_stores(tmp_path):
    """The synopsis repeats the flag (not one flag with several values); `--truth m=1 c=2`
    names c=2 as the mistake, not a --spec count."""
    assert "[--truth NAME=VALUE ...]" not in README and "[--truth NAME=VALUE]..." in README
    out = CliRunner().invoke(app, ["plot", str(tmp_path / "run.zarr"), "--out", str(tmp_path / "f"), "--spec",
                                   str(tmp_path / "s.yaml"), "--truth", "m=1", "c=2"])
    assert out.exit_code == 2
    assert "'c=2' is not a store: give each known value its own --truth" in out.output and "--spec" not in out.output


def raw_spec(data: dict) -> dict:
    return {"data": data, "models": [{"name": "a", "simulator": "duffing", "fixed": {"m": 1, "k2": 0, "k5": 0},
                                      "priors": {"c": [0, 1], "k": [1, 2], "k3": [0, 1]}}]}


def test_6_a_misspelt_rate_gets_did_you_mean_and_the_rate_required():
    from abcns import SpecError
    from service.spec import parse

    with pytest.raises(SpecError) as err:
        parse(raw_spec({"fz": 100, "input": [1.0, 2.0, 3.0], "observed": [1.0, 2.0, 3.0]}))
    assert err.value.field == "data.fz"
    assert "did you mean `fs`?" in err.value.message and "fs, in Hz, or dt, in s" in err.value.message


def test_7_a_nan_says_its_sample_counts_from_0_and_why_a_test_window_gap_is_refused(tmp_path):
    """No "rescale the record" for a gap; the index's base said; a NaN in the test window
    only (after the fit window) is refused, and the message says why."""
    import numpy as np

    from abcns import SpecError
    from service.spec import build, parse

    x = np.sin(np.arange(200) / 7.0)
    observed = x.copy()
    observed[150] = np.nan
    raw = raw_spec({"dt": 0.01, "input": x.tolist(), "observed": "obs.npy", "fit": [0, 100], "test": [100, 200]})
    np.save(tmp_path / "obs.npy", observed)
    with pytest.raises(SpecError) as err:
        build(parse(raw), tmp_path)
    message = err.value.message
    assert err.value.field == "data.observed" and "sample 150 (counting from 0) is nan" in message
    assert "rescale" not in message and "a gap in the test window alone is refused too" in message


def test_8_a_null_inline_names_its_sample_on_the_command_line_too():
    """The CLI's parse gives the sample, not pydantic's string branch (HTTP: tests/test_http.py)."""
    from abcns import SpecError
    from service.spec import parse

    with pytest.raises(SpecError) as err:
        parse(raw_spec({"dt": 0.01, "input": [1.0, 2.0, 3.0], "observed": [1.0, None, 3.0]}))
    assert err.value.field == "data.observed[1]" and err.value.message.startswith("sample 1 (counting from 0) is null")


def test_9_the_readme_says_what_make_test_takes_and_starts():
    tests = README.split("## Tests", 1)[1]
    assert re.search(r"about \d+ min", tests) and "Chromium" in tests and "Docker" in tests
