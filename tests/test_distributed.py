"""The runner on real Dask processes: determinism across worker counts (1, 2 and 8), workers
killed mid-population (on 2 and on 8), a job stopped and resumed on 8 workers, the CLI killed
with SIGKILL and resumed, xarray reading a running store."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import yaml
from cli_in_process import invoke
from distributed import Client, LocalCluster

from service.run.dask_executor import DaskExecutor, local_cluster
from service.run.runner import run_job
from service.run.store import Store, StoreError
from service.spec import parse

pytestmark = pytest.mark.distributed
ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
DEMO = ROOT / "data" / "authors-demo" / "demo_data.npz"


def small_spec(tmp_path: Path, **stop) -> Path:
    """The authors' demo, shortened: 500 particles, a few populations."""
    raw = yaml.safe_load((ROOT / "examples" / "authors_demo" / "spec.yaml").read_text())
    raw["data"]["input"] = f"{DEMO}:force"
    raw["data"]["observed"] = f"{DEMO}:displacement"
    raw["sampler"].update(particles=500, batch_size=100)
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": 6, **stop}
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def run_local(spec_path: Path, out: Path, n_workers: int, on_population=None):
    with local_cluster(n_workers) as cluster, \
            Client(cluster) as client:
        return run_on(client, spec_path, out, on_population)


@pytest.fixture(scope="module")
def clusters():
    """LocalClusters of 2 and 8 workers, each started once for the module (on first use):
    a test connects a client of its own (its keys go with it) and waits for every worker,
    those a kill test took included (their nannies start others)."""
    started: dict[int, LocalCluster] = {}

    @contextmanager
    def connect(n_workers: int) -> Iterator[Client]:
        if n_workers not in started:
            started[n_workers] = local_cluster(n_workers)
        with Client(started[n_workers]) as client:
            client.wait_for_workers(n_workers, timeout=120)
            yield client

    yield connect
    for cluster in started.values():
        cluster.close()


def run_on(client: Client, spec_path: Path, out: Path, on_population=None, cancel=None):
    spec = parse(yaml.safe_load(spec_path.read_text()))
    return run_job(spec, spec_path.parent, out, client, on_population=on_population, cancel=cancel)


def assert_same_store(a: Path, b: Path):
    sa, sb = Store.open(a), Store.open(b)
    assert sa.n_populations == sb.n_populations > 0
    for p, q in zip(sa.populations(), sb.populations()):
        for name in ("models", "theta", "distances", "weights", "survivors"):
            np.testing.assert_array_equal(getattr(p, name), getattr(q, name), err_msg=f"population {p.t} {name}")
        assert (p.epsilon, p.epsilon_next, p.n_simulations, p.n_redraws) == (q.epsilon, q.epsilon_next,
                                                                              q.n_simulations, q.n_redraws)
    assert sa.attrs["stop_reason"] == sb.attrs["stop_reason"]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """One undisturbed run on one worker: the result every other run must equal."""
    tmp = tmp_path_factory.mktemp("ref")
    spec = small_spec(tmp)
    reads = []

    def check_xarray(progress):  # a reader between populations sees every complete one
        ds = xr.open_zarr(tmp / "ref.zarr", consolidated=False)
        reads.append((progress.population.t, ds.sizes["population"], float(ds["epsilon"].values[-1]),
                      Store.open(tmp / "ref.zarr").attrs["status"]))

    run_local(spec, tmp / "ref.zarr", 1, on_population=check_xarray)
    return spec, tmp / "ref.zarr", reads


def test_reference_run_is_readable_with_xarray_while_running(reference):
    _, store, reads = reference
    assert len(reads) == 6
    eps = Store.open(store).populations()
    # the runner coalesces the appends of populations that come within a second of each
    # other, so a reader may already see later populations; never fewer, never half of one
    assert reads[0][:2] == (1, 1)  # the first population is written as soon as it is done
    for t, size, last_eps, status in reads:
        assert t <= size <= len(eps)
        assert last_eps == eps[size - 1].epsilon
        assert status == "running"


def test_two_workers_give_the_one_worker_result(reference, clusters, tmp_path):
    spec, ref_store, _ = reference
    with clusters(2) as client:
        run_on(client, spec, tmp_path / "two.zarr")
    assert_same_store(ref_store, tmp_path / "two.zarr")


def test_eight_workers_give_the_one_worker_result_also_when_stopped_and_resumed(reference, clusters, tmp_path):
    """On 8 worker processes: an undisturbed run; then a run cancelled as it opens its fourth
    population (the budget's cancel says yes at the third check the run makes between two
    populations, in the run's own order: the store keeps the three populations done, status
    "cancelled") and run again on the same store: it resumes and ends as the one-worker run.
    The cancel counts only the checks between populations: the run also asks its budget
    between batches and while the executor waits for a task, as often as the machine is slow
    and wherever a cheap population is evaluated, and half of such a count once fell inside
    population 1 on a busy CI machine."""
    spec, ref_store, _ = reference
    opened = [0]

    def at_population_4() -> bool:
        # this <- Budget.reason <- Budget.check <- the ABC-NS loop, between two populations
        opened[0] += (sys._getframe(2).f_code.co_name, sys._getframe(3).f_code.co_name) == ("check", "populations")
        return opened[0] >= 3

    with clusters(8) as client:
        run_on(client, spec, tmp_path / "eight.zarr")
        assert_same_store(ref_store, tmp_path / "eight.zarr")
        out = tmp_path / "resumed8.zarr"
        run_on(client, spec, out, cancel=at_population_4)
        stopped = Store.open(out)
        assert stopped.attrs["status"] == "cancelled"
        assert stopped.n_populations == 3, "the job was not stopped as it opened population 4"
        run_on(client, spec, out)
        assert_same_store(ref_store, out)


def run_killing_workers(clusters, spec, out, n_victims: int, n_workers: int = 2) -> list[int]:
    """Run the job on ``n_workers`` worker processes and SIGKILL ``n_victims`` of them as
    population 3 draws its first batch, before its tasks go to the cluster; the nannies start
    new ones. Returns the killed pids. (The kill came from a thread 50 ms after population
    2's progress callback: once the runs got faster, a run could end first, and nothing was
    killed.)"""
    killed: list[int] = []
    with pytest.MonkeyPatch.context() as mp, \
            clusters(n_workers) as client:
        victims = sorted(client.run(os.getpid).values())[:n_victims]
        map_ = DaskExecutor.map

        def map_killing(executor, draws):
            def watched():
                for draw in draws:
                    if draw.population == 3 and not killed:
                        for victim in victims:
                            os.kill(victim, signal.SIGKILL)
                            killed.append(victim)
                    yield draw
            return map_(executor, watched())

        mp.setattr(DaskExecutor, "map", map_killing)
        run_job(parse(yaml.safe_load(spec.read_text())), spec.parent, out, client)
        assert len(killed) == n_victims
        alive = set(client.run(os.getpid).values())
        assert not alive & set(killed)  # they really died (the nannies started others)
    return killed


def test_a_worker_killed_mid_population_changes_nothing(reference, clusters, tmp_path):
    spec, ref_store, _ = reference
    run_killing_workers(clusters, spec, tmp_path / "killed.zarr", n_victims=1)
    assert_same_store(ref_store, tmp_path / "killed.zarr")


def test_three_of_eight_workers_killed_mid_population_change_nothing(reference, clusters, tmp_path):
    spec, ref_store, _ = reference
    run_killing_workers(clusters, spec, tmp_path / "killed8.zarr", n_victims=3, n_workers=8)
    assert_same_store(ref_store, tmp_path / "killed8.zarr")


def test_every_worker_killed_at_once_changes_nothing(reference, clusters, tmp_path):
    """The job's data lives on the cluster as a task: with every worker that held it dead,
    the scheduler computes it again (scattered data would be lost, and the job with it)."""
    spec, ref_store, _ = reference
    run_killing_workers(clusters, spec, tmp_path / "all-killed.zarr", n_victims=2)
    assert_same_store(ref_store, tmp_path / "all-killed.zarr")


def test_cli_killed_with_sigkill_resumes_to_the_same_store(reference, tmp_path, stock_cluster):
    spec, ref_store, _ = reference
    out = tmp_path / "resumed.zarr"
    cmd = [BIN / "abcns", "run", str(spec), "--out", str(out), "--scheduler", stock_cluster, "--quiet"]
    for _attempt in range(5):  # on a loaded machine the 6 populations may all land between two polls
        shutil.rmtree(out, ignore_errors=True)
        interrupted = _run_and_kill_after_a_population(cmd, out)
        if interrupted.n_populations < 6 and interrupted.attrs["status"] != "finished":
            break
    assert 1 <= interrupted.n_populations < 6, "the run was not interrupted mid-job in 5 tries"
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert_same_store(ref_store, out)  # same as one local worker: a remote cluster, 2 workers, a kill, a resume


def _run_and_kill_after_a_population(cmd: list, out: Path) -> Store:
    """Start ``abcns run``, SIGKILL its process group once its store holds a population, and
    open what it left."""
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if out.exists():
            try:
                if Store.open(out).n_populations >= 1:  # later ones come in one append a second later
                    break
            except StoreError:  # still being created
                pass
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    return Store.open(out)


def test_cli_refuses_a_bad_spec_naming_the_field(tmp_path):
    spec = small_spec(tmp_path)
    raw = yaml.safe_load(spec.read_text())
    raw["models"][1]["simulator"] = "nope"
    spec.write_text(yaml.safe_dump(raw))
    out = tmp_path / "never.zarr"
    done = invoke("run", spec, "--out", out, code=2)
    assert "models[1].simulator" in done.stderr
    assert not out.exists()


def test_cli_summary_json(reference):
    _, store, _ = reference
    s = json.loads(invoke("summary", store, "--json").stdout)
    assert s["status"] == "finished" and s["stop_reason"] == "max_populations" and s["n_populations"] == 6
    assert len(s["epsilon"]) == 6 and set(s["model_probabilities"]) == {"linear", "cubic"}
