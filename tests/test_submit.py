"""`abcns submit`: a YAML spec and its data files become a job on a running `abcns serve`
(real processes: a stock Dask scheduler and worker, the service), followed like `abcns run`
and ending with the same result as `abcns run` of the same spec; each kind of error is one
line with its own exit code."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
import yaml
from cli_in_process import invoke

from benchmarks.harness import AUTH, TOKEN, Service, free_port

pytestmark = pytest.mark.http
ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
DEMO = ROOT / "data" / "authors-demo" / "demo_data.npz"
POPULATIONS = 3


def abcns(*args, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([BIN / "abcns", *map(str, args)], capture_output=True, text=True, timeout=300,
                          env={**os.environ, **(env or {})})


@pytest.fixture(scope="module")
def service(cluster, tmp_path_factory):
    """One service (at most 1,000 particles a job) for the module, on the run's shared
    cluster (2 workers)."""
    service = Service(tmp_path_factory.mktemp("submit") / "jobs", cluster.address, env={"ABCNS_MAX_PARTICLES": "1000"})
    yield service, cluster.address
    service.close()


@pytest.fixture(scope="module")
def spec(tmp_path_factory) -> Path:
    """The authors' demo, shortened, as a user writes it: YAML, the force in an .npz beside
    it, the response in a .csv column."""
    folder = tmp_path_factory.mktemp("spec")
    with np.load(DEMO) as d:
        np.savez(folder / "record.npz", force=d["force"])
        np.savetxt(folder / "response.csv", d["displacement"], header="displacement", comments="", delimiter=",")
    raw = yaml.safe_load((ROOT / "examples" / "authors_demo" / "spec.yaml").read_text())
    raw["data"].update(input="record.npz:force", observed="response.csv:displacement")
    raw["sampler"].update(particles=200, batch_size=100)
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": POPULATIONS}
    path = folder / "spec.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def test_submit_uploads_the_spec_and_its_files_and_follows_the_job_to_run_s_result(service, spec, tmp_path):
    svc, scheduler = service
    done = abcns("submit", spec, "--url", svc.url, "--token", TOKEN)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.splitlines()
    pops = [line for line in lines if line.startswith("population ")]
    assert [int(p.split()[1]) for p in pops] == list(range(1, POPULATIONS + 1)), lines
    assert all(" %  acceptance" in p and "sims/s" in p and re.search(r"workers 2\b", p) for p in pops), pops
    assert lines[len(pops)] == "" and lines[len(pops) + 1].startswith("status finished  stop max_populations")
    job_id = done.stderr.split("job ", 1)[1].split(":", 1)[0]
    assert lines[-1].startswith(f"job: {svc.url}/jobs/{job_id}")
    # the job link opens the live page with the token (AA, point 3): without it, empty charts and 401s
    assert f"job {job_id}: {svc.url}/jobs/{job_id}/view#token={TOKEN}\n" in done.stderr
    # the data the service ran on are the files' (the result is abcns run's, bit for bit)
    submitted = httpx.get(f"{svc.url}/jobs/{job_id}/result", headers=AUTH, timeout=60).json()
    ran = json.loads(invoke("run", spec, "--out", tmp_path / "run.zarr", "--scheduler", scheduler, "--json",
                            "--quiet").stdout)
    for key in ("epsilon", "acceptance_rate", "simulations", "model_probabilities", "posterior"):
        assert submitted[key] == ran[key], key


def test_each_error_is_one_line_with_its_exit_code(service, spec, tmp_path):
    svc, _ = service
    cases = []
    # the spec is checked here first (2), naming the field
    bad = yaml.safe_load(spec.read_text())
    bad["models"][1]["prior"] = bad["models"][1].pop("priors")
    (spec.parent / "bad.yaml").write_text(yaml.safe_dump(bad))
    cases.append((("submit", spec.parent / "bad.yaml", "--url", svc.url, "--token", TOKEN), 2,
                  "error: models[1].prior: Extra inputs are not permitted; did you mean `priors`?"))
    # the service's own limits (2): over its 1,000 particles
    big = yaml.safe_load(spec.read_text())
    big["sampler"]["particles"] = 2000
    (spec.parent / "big.yaml").write_text(yaml.safe_dump(big))
    cases.append((("submit", spec.parent / "big.yaml", "--url", svc.url, "--token", TOKEN), 2,
                  "error: the service refused the job: sampler.particles: "))
    # the token (5), and a service that is not there (3)
    cases.append((("submit", spec, "--url", svc.url, "--token", "wrong"), 5, "error: the service refused the token (403"))
    nowhere = f"http://127.0.0.1:{free_port()}"
    cases.append((("submit", spec, "--url", nowhere), 3, f"error: cannot reach the service at {nowhere}: "))
    for args, code, start in cases:  # in this process (submit's own code; test_submit_uploads... runs its process)
        done = invoke(*args, code=code, env={"ABCNS_TOKEN": ""})
        assert len(done.stderr.strip().splitlines()) == 1 and done.stderr.startswith(start), (args, done.stderr)


def test_a_job_cancelled_on_the_service_ends_submit_with_exit_4_and_its_summary(service, spec):
    """Q.4: the job is cancelled on the service while submit follows it (DELETE, as from the
    live page or another terminal): submit ends with exit code 4 and one error line, and
    --json still prints the job's summary, with its status."""
    svc, _ = service
    long = yaml.safe_load(spec.read_text())
    long["stop"]["max_populations"] = 400  # runs until cancelled
    (spec.parent / "long.yaml").write_text(yaml.safe_dump(long))
    with subprocess.Popen([BIN / "abcns", "submit", spec.parent / "long.yaml", "--url", svc.url, "--token", TOKEN,
                           "--quiet", "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        first = proc.stderr.readline()  # type: ignore[union-attr]  # "job ID: URL/jobs/ID/view", once it is queued
        job_id = first.split("job ", 1)[1].split(":", 1)[0]
        assert httpx.delete(f"{svc.url}/jobs/{job_id}", headers=AUTH, timeout=60).status_code == 202
        out, err = proc.communicate(timeout=300)
    assert proc.returncode == 4, (first, err)
    assert err.strip().splitlines() == ["error: the job was cancelled"], err
    assert json.loads(out)["status"] == "cancelled", out
