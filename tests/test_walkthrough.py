"""The README's "Your own data in 10 minutes" runs as printed: every ``sh`` block of that
section, in order, each in its own shell after the section's first block (the
virtualenv's activation), in a fresh folder that holds only the repository's ``data/`` and
``.venv`` (links). The blocks that start a server (``abcns serve``, ``dask scheduler``,
``dask worker``: "one terminal each") run in the background until the end. The printed
ports (8000, 8786) are replaced by free ones: nothing else is changed."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.harness import free_port, stop, wait_until

pytestmark = [pytest.mark.distributed, pytest.mark.http]
ROOT = Path(__file__).resolve().parents[1]
SERVERS = ("abcns serve", "dask scheduler", "dask worker")


def walkthrough() -> list[str]:
    text = (ROOT / "README.md").read_text()
    section = re.search(r"^## Your own data in 10 minutes\n(.*?)^## ", text, re.S | re.M)
    assert section, "the README has no section 'Your own data in 10 minutes'"
    return re.findall(r"^```sh\n(.*?)^```", section.group(1), re.S | re.M)


def listening(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
        return True
    except OSError:
        return False


def test_the_readme_walkthrough_runs_as_printed(tmp_path):
    blocks = walkthrough()
    activate, *steps = blocks
    assert activate.strip() == ". .venv/bin/activate"
    assert [s for s in steps if s.startswith(SERVERS)], "no server in the walk-through"
    (tmp_path / "data").symlink_to(ROOT / "data")
    (tmp_path / ".venv").symlink_to(Path(sys.prefix))
    ports = {"8000": str(free_port()), "8786": str(free_port())}
    env = {**os.environ, "NO_PROXY": "127.0.0.1,localhost", "no_proxy": "127.0.0.1,localhost"}
    servers: list[subprocess.Popen] = []
    try:
        for k, step in enumerate(steps):
            for printed, free in ports.items():
                step = step.replace(printed, free)
            script = activate + step
            if step.startswith(SERVERS):
                with (tmp_path / f"server-{k}.log").open("w") as log:
                    servers.append(subprocess.Popen(["bash", "-c", script], cwd=tmp_path, env=env, stdout=log,
                                                     stderr=log, start_new_session=True))
                port = next((int(free) for free in ports.values() if free in step), None)
                if port is not None and not step.startswith("dask worker"):
                    wait_until(lambda: listening(port) or servers[-1].poll() is not None, 120, step)
                    assert servers[-1].poll() is None, (tmp_path / f"server-{k}.log").read_text()[-3000:]
                continue
            done = subprocess.run(["bash", "-e", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True,
                                  timeout=600)
            assert done.returncode == 0, (step, done.stdout[-3000:], done.stderr[-3000:])
            if "abcns run" in step or "abcns submit" in step:
                assert "status finished" in done.stdout and "model probabilities: linear " in done.stdout, done.stdout
    finally:
        for p in servers:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)  # Ctrl-C, as the README says
        stop(servers)
    figures = {p.name for p in (tmp_path / "my-study" / "figures").iterdir()}
    assert {"tolerance.png", "model_probabilities.png", "nmse.json"} <= figures
    assert any(name.startswith("predictive_") for name in figures)
