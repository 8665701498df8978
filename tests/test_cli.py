"""What a user sees from the `abcns` command: `--version` and `--help`, `run` ending with a
short human summary (with or without the per-population lines), `--json`, `summary`, the
NMSE marked as a percentage (Eq. 7: 100 / (n s^2) ...), each population's own rate, the
workers as they are now, and one line with its own exit code for a scheduler that cannot
be reached.

What only formats (help, the run's lines and summary, `summary`) runs in this process through
typer's CliRunner (:func:`here`), on the run's shared cluster; what a process adds something
to runs `abcns` for real: the installed entry point (--version), exit codes and their one
error line, a worker killed under a run, a plugin the workers import, a terminal."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import signal
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest
import yaml
from cli_in_process import invoke
from typer.testing import Result

from benchmarks.harness import StockCluster, free_port

pytestmark = pytest.mark.distributed
ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
DEMO = ROOT / "data" / "authors-demo" / "demo_data.npz"
POPULATIONS = 3


def abcns(*args, timeout: float = 300) -> subprocess.CompletedProcess:
    done = subprocess.run([BIN / "abcns", *map(str, args)], capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr
    return done


def here(*args, env: dict | None = None) -> Result:
    """`abcns ARGS` in this process: what it prints is what the command prints; it must exit 0."""
    return invoke(*args, env=env)


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


def test_help_shows_flags_as_flags_and_what_the_numbers_mean():
    """Q.14: --version is a flag (no ``<bool>``); Q.8 and Q.17: run's help says what sims/s
    is and that stop.min_epsilon_decrease is an absolute difference in % NMSE."""
    env = {"COLUMNS": "100"}
    top = here("--help", env=env).stdout
    assert re.search(r"^\s+--version\s+Print the version and exit\.$", top, re.M), top
    assert "<bool>" not in top and "submit" in top
    help_run = here("run", "--help", env=env).stdout
    text = " ".join(help_run.split())  # as one paragraph, whatever the width
    assert "<bool>" not in help_run and "--quiet " in help_run and "--no-quiet" not in help_run
    assert "sims/s (this population's simulations over the wall time since the previous one ended" in text
    assert "stop.min_epsilon_decrease is an absolute difference in the tolerance's unit" in text


def event(t: int, epsilon: float, acceptance: float, simulations: int, elapsed_s: float, probabilities: dict,
          decision: float | None = None) -> dict:
    """A population event (service.run.runner.Progress.event) with the fields a progress line shows."""
    return {"population": t, "epsilon": epsilon, "acceptance_rate": acceptance, "simulations": simulations,
            "elapsed_s": elapsed_s, "model_probabilities": probabilities, "decision_tolerance": decision,
            "efficiency": None}


def test_the_rate_is_each_population_s_own():
    """Q.8: sims/s is a population's simulations over the wall time since the previous one
    ended, not the average since the start (compilation included)."""
    from service.cli import ProgressLine

    shown: list[str] = []
    line = ProgressLine(" %", quiet=False, workers=lambda: 2)
    line.live = False
    import typer

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(typer, "echo", shown.append)
        line.show(event(1, 100.0, 0.5, 1000, 10.0, {"linear": 0.5, "cubic": 0.5}))  # 100/s: the first, compiling
        line.show(event(2, 50.0, 0.4, 3000, 11.0, {"linear": 0.3, "cubic": 0.7}))  # 2000/s (the average: 273/s)
        line.show(event(3, 20.0, 0.3, 3000, 11.0, {"linear": 0.1, "cubic": None}))  # no time passed: no rate
    rates = [re.search(r"sims\s+\d+\s+(\S+) sims/s", s).group(1) for s in shown]  # type: ignore[union-attr]
    assert rates == ["100", "2000", "-"], shown
    assert shown[1].endswith("linear=0.30 cubic=0.70  workers 2") and "cubic=-" in shown[2]


def test_the_summary_gives_the_answer_at_the_decision_tolerance():
    """Issue T: the human summary says where its answer is read (the decision population and
    its tolerance), the noise floor and how it was found, and, when the final population is
    another, its probabilities on their own line, labelled as not the answer. The toy result
    (tests/toy_results.py) turns from linear 0.9 to cubic 0.9 below its decision tolerance."""
    from dataclasses import replace

    from toy_results import FLOOR, floored_result

    from service.cli import summary_lines

    lines = summary_lines(floored_result().summary())
    assert "model probabilities: linear 0.900, cubic 0.100  (the answer: population 3, eps 3.333 %)" in lines
    assert ("noise floor 2.8 % (estimated from the run's best fit); decision tolerance 3.2 % (floor + its spread): "
            "the answer is read at the lowest tolerance at or above it") in lines
    assert ("model probabilities at the final population 5, eps 2 % (below the decision tolerance, where the noise "
            "decides; not the answer): linear 0.100, cubic 0.900") in lines
    stated = summary_lines(floored_result(floor=replace(FLOOR, method=1)).summary())
    assert any(line.startswith("noise floor 2.8 % (from the stated noise, data.noise_std)") for line in stated)
    # no floor (a summary distance): the final population is the answer, and the line says so
    plain = summary_lines(floored_result(floor=None).summary())
    assert ("model probabilities: linear 0.100, cubic 0.900  (final population 5, eps 2 %; no noise floor for "
            "this distance)") in plain
    assert not any(line.startswith(("noise floor", "model probabilities at the final")) for line in plain)


def test_the_summary_says_how_the_answer_is_read_and_when_it_is_provisional():
    """Issue W: read by the likelihood, the answer line says so (every population to the
    decision, weighted by the likelihood of the noise) with the reading's effective
    particles, and no line of the final population's probabilities (they are not another
    answer); a run stopped above its decision tolerance is PROVISIONAL, with the rule."""
    from toy_results import floored_result

    from service.cli import summary_lines

    s = floored_result().summary()
    s["decision"].update(reading="likelihood", population=5, epsilon=2.0, rule="noise_floor", provisional=False,
                         effective_particles={"linear": 412.4, "cubic": 37.0})
    lines = summary_lines(s)
    assert ("model probabilities: linear 0.900, cubic 0.100  (the answer: every population to 5, eps 2 %, weighted "
            "by the likelihood of the noise)") in lines
    assert "effective particles of the reading: linear 412, cubic 37" in lines
    assert not any(line.startswith("model probabilities at the final") for line in lines)
    s["decision"].update(rule="max_populations", provisional=True)
    assert ("model probabilities: linear 0.900, cubic 0.100  (PROVISIONAL: stopped (max_populations) above the decision "
            "tolerance, at every population to 5, eps 2 %, weighted by the likelihood of the noise)") in summary_lines(s)


def test_the_progress_line_shows_the_decision_tolerance_once_known():
    from service.cli import ProgressLine

    shown: list[str] = []
    line = ProgressLine(" %", quiet=False, workers=lambda: 2)
    line.live = False
    import typer

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(typer, "echo", shown.append)
        line.show(event(1, 100.0, 0.5, 1000, 10.0, {"linear": 0.5, "cubic": 0.5}))
        line.show(event(2, 50.0, 0.4, 3000, 11.0, {"linear": 0.3, "cubic": 0.7}, 0.012463))
    assert "decision" not in shown[0]
    assert re.search(r"eps\s+50 %  decision 0.01246 %  acceptance", shown[1]), shown[1]


def test_one_population_event_is_the_message_the_http_event_and_the_line():
    """Issue X: a population's event is built once (``runner.Progress.event``): in plain
    Python types (it crosses Dask's event log as a job loop's message and is written as JSON
    to a job's event log), in the HTTP schema's shape (``ProgressOut``), and it is what the
    progress line shows. The toy's population 2 (tests/toy_results.py): eps 10 / 2, linear
    0.9 / cubic 0.1, decision tolerance 2.8 + 0.4."""
    from toy_results import floored_result

    from service.cli import ProgressLine
    from service.http.schemas import ProgressOut
    from service.run.runner import Progress

    pop = floored_result().populations[1]
    event = Progress(pop, 4000, 12.0, 250.0, workers=2, efficiency=0.5).event(["linear", "cubic"])
    assert ProgressOut(**event).model_dump() == event and json.loads(json.dumps(event)) == event
    plain = [v for v in event.values() if v is not None] + list(event["model_probabilities"].values())
    assert all(type(v) in (int, float, dict) for v in plain), event
    shown: list[str] = []
    line = ProgressLine(" %", quiet=False, workers=lambda: 2, start=(2000, 10.0))
    line.live = False
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("typer.echo", shown.append)
        line.show(event)
    assert shown == ["population    2  eps           5 %  decision 3.2 %  acceptance  0.50  sims     4000       1000 "
                     "sims/s  linear=0.90 cubic=0.10  workers 2  efficiency 0.50"], shown


def test_run_prints_populations_then_a_short_summary(spec, cluster, tmp_path):
    lines = here("run", spec, "--out", tmp_path / "a.zarr", "--scheduler", cluster.address).stdout.splitlines()
    pops = [line for line in lines if line.startswith("population ")]
    assert len(pops) == POPULATIONS and all("eps" in p and " %  acceptance" in p for p in pops)
    # issue O.5: on a cluster each line gives the workers' efficiency over its population, a
    # share of their time (the workers' compute time of the tasks used over workers x wall)
    shares = [float(re.search(r"efficiency (\d\.\d\d)$", p).group(1)) for p in pops]  # type: ignore[union-attr]
    assert all(0 < e <= 1 for e in shares), pops
    rest = lines[len(pops):]
    assert rest[0] == ""  # a blank line, then the summary
    assert_human_summary(rest[1:])
    assert rest[-1].startswith("store: ") and "abcns summary" in rest[-1] and "--json" in rest[-1]
    assert len(lines) < 30  # no screens of JSON


def test_run_quiet_still_prints_the_summary(spec, cluster, tmp_path):
    done = here("run", spec, "--out", tmp_path / "q.zarr", "--scheduler", cluster.address, "--quiet")
    lines = done.stdout.splitlines()
    assert not any(line.startswith("population ") for line in lines)
    assert lines[0] == ""
    assert_human_summary(lines[1:])
    # Q.7: this scheduler serves no dashboard (no bokeh here): no link that would answer 404
    if importlib.util.find_spec("bokeh") is None:
        assert "Dask dashboard" not in done.stderr, done.stderr


def test_a_scheduler_that_cannot_be_reached_is_one_line_and_exit_3(spec, tmp_path):
    """Q.6: a wrong --scheduler address: one line naming it, exit code 3, no traceback (and
    at once for a refused connection, not after Dask's 30 s of retries)."""
    address = f"tcp://127.0.0.1:{free_port()}"  # nothing listens there
    done = invoke("run", spec, "--out", tmp_path / "x.zarr", "--scheduler", address, code=3)
    assert done.stderr.strip().splitlines() == [f"error: cannot reach the scheduler at {address}: Connection refused"]
    assert not (tmp_path / "x.zarr").exists()
    serve = invoke("serve", "--scheduler", address, "--store-dir", tmp_path / "jobs", code=3)
    assert serve.stderr.strip().splitlines() == done.stderr.strip().splitlines(), serve.stderr


def test_the_worker_count_is_the_cluster_s_now(tmp_path):
    """Q.5: one of two workers dies after population 2: the later lines say "workers 1". The
    populations are slowed by the sleepy plugin (2 ms per simulation), so the job runs for
    seconds after the kill while the count is asked again (at most once a second)."""
    from benchmarks import sleepy

    raw = yaml.safe_load((ROOT / "examples" / "authors_demo" / "spec.yaml").read_text())
    raw["data"].update(input=f"{DEMO}:force", observed=f"{DEMO}:displacement")
    raw["models"] = raw["models"][1:]  # the cubic model alone
    raw["models"][0]["simulator"] = sleepy.NAME
    raw["sampler"].update(particles=200, batch_size=25)
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": 10}
    path = tmp_path / "sleepy.yaml"
    path.write_text(yaml.safe_dump(raw))
    cluster = StockCluster(tmp_path / "dask", n_workers=2)
    try:
        env = {**os.environ, "PYTHONPATH": str(ROOT), "ABCNS_STORE_INTERVAL_S": "0"}
        lines = []
        with (tmp_path / "stderr").open("w") as err, \
                subprocess.Popen([BIN / "abcns", "run", path, "--out", tmp_path / "s.zarr", "--scheduler",
                                  cluster.address], stdout=subprocess.PIPE, stderr=err, text=True, env=env) as run:
            for line in run.stdout:  # type: ignore[union-attr]
                lines.append(line.rstrip("\n"))
                if line.startswith("population    2 "):
                    os.killpg(cluster.procs[-1].pid, signal.SIGKILL)  # a worker and its nanny
        assert run.returncode == 0, (tmp_path / "stderr").read_text()[-2000:]
    finally:
        cluster.close()
    pops = [line for line in lines if line.startswith("population ")]
    assert len(pops) == 10, lines
    counts = [re.search(r"workers (\d+)", line).group(1) for line in pops]  # type: ignore[union-attr]
    assert counts[0] == "2" and counts[-1] == "1", "\n".join(pops)


def test_run_json_and_summary_of_the_store(spec, cluster, tmp_path):
    out = tmp_path / "j.zarr"
    s = json.loads(here("run", spec, "--out", out, "--scheduler", cluster.address, "--quiet", "--json").stdout)
    assert s["status"] == "finished" and s["n_populations"] == POPULATIONS and len(s["epsilon"]) == POPULATIONS
    assert json.loads(here("summary", out, "--json").stdout) == s
    assert_human_summary(here("summary", out).stdout.splitlines())
    # run again on the finished store: nothing recomputed, the same short summary
    again = here("run", spec, "--out", out, "--scheduler", cluster.address, "--quiet").stdout.splitlines()
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
    # Q.9: the rule that ended the model, in words (not "first population without particles")
    assert "models out: linear from population 2 (its probability + 3 standard errors fell below 0.001)" in lines
    s["death_rules"] = {"linear": "no_particles"}
    assert "models out: linear from population 2 (no particle below the next tolerance)" in summary_lines(s)
    assert "warning: undecided: cubic (p = 0.55), cubic-quintic (p = 0.45) are all above 0.1" in lines
    assert any("7.87 %" in line for line in lines)  # the NMSE is in percent


def test_a_run_that_accepts_nothing_says_why(cluster, tmp_path):
    """R.2 as a user sees it: a force of 2^62 N (every simulation leaves the divergence
    guard) stops with nothing_accepted after stop.max_simulations_without_acceptance, and
    the summary says why in a sentence (before: the status line, then an empty "model
    probabilities: " and nothing else)."""
    duffing = ROOT / "examples" / "duffing_41"
    np.save(tmp_path / "force.npy", np.load(duffing / "force.npy") * 2.0**62)
    raw = yaml.safe_load((duffing / "spec.yaml").read_text())
    raw["data"].update(input="force.npy", observed=str(duffing / "displacement.npy"))
    raw["sampler"].update(particles=200, batch_size=250)
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": 2, "max_simulations_without_acceptance": 2000}
    (tmp_path / "spec.yaml").write_text(yaml.safe_dump(raw))
    lines = here("run", tmp_path / "spec.yaml", "--out", tmp_path / "n.zarr", "--scheduler", cluster.address,
                 "--quiet").stdout.splitlines()
    assert lines[1].startswith("status finished  stop nothing_accepted  populations 0  simulations 2,000"), lines
    assert lines[2].startswith("note: nothing accepted: population 1 ran 2,000 simulations and none came below"), lines
    assert not any(line.startswith("model probabilities:") for line in lines), lines
    assert here("summary", tmp_path / "n.zarr").stdout.splitlines() == lines[1:-1]


def test_an_impossible_fixed_value_is_refused_before_the_run_with_exit_2(tmp_path):
    """P.3: ``bouc_wen`` with ``fixed: {n: 1.5}`` ran (exit 0) and every simulation failed;
    it is now refused naming the field, with the CLI's error exit, and no store is made."""
    raw = yaml.safe_load((ROOT / "examples" / "boucwen" / "spec.yaml").read_text())
    raw["data"].update(input=str(ROOT / "examples" / "boucwen" / "force.npy"),
                       observed=str(ROOT / "examples" / "boucwen" / "displacement.npy"))
    raw["models"][1]["fixed"]["n"] = 1.5
    path = tmp_path / "n.yaml"
    path.write_text(yaml.safe_dump(raw))
    done = invoke("run", path, "--out", tmp_path / "n.zarr", "--workers", "1", code=2)
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
    assert done.returncode == 4, done.stderr  # the job failed
    assert re.search(r"error: the job failed in population 1, batch \d+: model '(linear|cubic)' \(simulator "
                     r"'tests\.faulty_plugin:Faulty'\): RuntimeError: a bug in the user's simulator",
                     done.stderr), done.stderr[-2000:]
    assert "Traceback (most recent call last)" not in done.stderr  # a message, not a Python traceback
    s = json.loads(here("summary", tmp_path / "f.zarr", "--json").stdout)
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
