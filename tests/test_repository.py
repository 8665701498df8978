"""The repository stands alone: no tracked file reads a path outside it.

A user's clone has nothing beside it, so a spec, example, test, doc or script that reaches
for the reference folder beside the repository, the parent of the repository, a machine's
absolute path or a home directory works only on the machine it was written on. Every tracked text file (except the
changelog, which records history, and this file, which names the patterns) is scanned for:

- the reference folder that sat beside the repository during development (its name is
  ``REFERENCE`` below: after ``../``, or joined onto a ``parent``/``parents[k]`` path);
- absolute paths of a development machine (``/work/``) or of a home directory
  (``/home/NAME``, ``/Users/NAME``, ``/root/``);
- ``Path(__file__)...parents[k]`` (or ``HERE.parents[k]``, HERE the file's folder) that climbs
  above the repository's root, and ``ROOT.parent``;
- relative paths (``../..``) that, taken from the file's own folder, lead out of the
  repository (spec data paths and Markdown links are relative to the file).
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SKIP = {"CHANGELOG.md", "tests/test_repository.py"}
SKIP_DIRS = {".git", ".venv", "out", "__pycache__", ".pytest_cache", ".ruff_cache"}
# the reference folder's name, spelled so that this file does not itself hold the paths it forbids
REFERENCE = "sha" + "red"

PATTERNS = {
    "the reference folder beside the repository": re.compile(
        rf"\.\.[/\\]+{REFERENCE}\b|parents?(\[\d+\])?\s*/\s*[\"']{REFERENCE}[\"']|[\"']\.\.[\"']\s*,\s*[\"']{REFERENCE}[\"']"),
    "an absolute path of a development machine": re.compile(r"(?<![\w.~-])/work/"),
    "a home directory": re.compile(r"(?<![\w.~-])/(?:home|Users)/[A-Za-z_][\w.-]*|(?<![\w.~-])/root/"),
    "the repository's parent": re.compile(r"\bROOT\.parent\b(?!s)"),
}
FILE_PARENTS = re.compile(r"Path\(__file__\)(?:\.resolve\(\))?\.parents\[(\d+)\]")
HERE_PARENTS = re.compile(r"\bHERE\.parents\[(\d+)\]")
RELATIVE = re.compile(r"(?<![\w.])((?:\.\./)+)([\w.-][^\s\"'`)\]>,;:]*)?")


def tracked_files() -> list[str]:
    """``git ls-files`` of the repository; without git (an exported tree), every file but the
    usual build and cache folders."""
    try:
        done = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, timeout=60)
        names = [n for n in done.stdout.decode().split("\0") if n]
        if names:
            return names
    except (OSError, subprocess.CalledProcessError):
        pass
    return [str(p.relative_to(ROOT)) for p in ROOT.rglob("*")
            if p.is_file() and not SKIP_DIRS.intersection(p.relative_to(ROOT).parts)]


def problems_in(name: str, text: str) -> list[str]:
    depth = len(Path(name).parts) - 1  # folders between the root and the file
    found = []
    here = "HERE = Path(__file__)" in text  # once a file, not once a line (a 0.5 MB trace has ~20,000 lines)
    for number, line in enumerate(text.splitlines(), 1):
        where = f"{name}:{number}: {line.strip()[:120]}"
        for what, pattern in PATTERNS.items():
            if pattern.search(line):
                found.append(f"{where}  <- {what}")
        for m in FILE_PARENTS.finditer(line):
            if int(m.group(1)) > depth:  # parents[depth] is the root
                found.append(f"{where}  <- climbs above the repository")
        if here:
            for m in HERE_PARENTS.finditer(line):
                if int(m.group(1)) >= depth:  # HERE is the file's folder: HERE.parents[depth - 1] is the root
                    found.append(f"{where}  <- climbs above the repository")
        for m in RELATIVE.finditer(line):
            ups = m.group(1).count("../")
            if ups > depth:
                found.append(f"{where}  <- a relative path out of the repository")
    return found


def test_no_tracked_file_reads_outside_the_repository():
    problems = []
    for name in tracked_files():
        if name in SKIP or not (ROOT / name).is_file():
            continue
        raw = (ROOT / name).read_bytes()
        if b"\0" in raw[:8192]:
            continue  # binary (npy, npz, png)
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            continue
        problems += problems_in(name, text)
    assert not problems, "paths outside the repository:\n" + "\n".join(problems)


def test_the_guard_sees_what_it_should():
    bad = {
        "README.md": f"Scope: `../{REFERENCE}/DESIGN.md`.",
        "examples/x/spec.yaml": f"  input: ../../../{REFERENCE}/data/demo.npz:force",
        "examples/x/prepare.py": 'HERE = Path(__file__).resolve().parent\nSOURCE = HERE.parents[2] / "data.npz"',
        "tests/test_x.py": f'DEMO = ROOT.parent / "{REFERENCE}" / "demo.npz"',
        "tests/test_z.py": f'DEMO = HERE.parents[2] / "{REFERENCE}" / "demo.npz"',
        "tests/test_y.py": 'p = Path(__file__).resolve().parents[2] / "elsewhere"',
        "docs/x.md": "see /work/main/README.md or /home/alice/data.npz or /root/x",
    }
    for name, text in bad.items():
        assert problems_in(name, text), name
    good = {
        "examples/authors_demo/spec.yaml": "  input: ../../data/authors-demo/demo_data.npz:force",
        "examples/boucwen/README.md": "[`data/boucwen`](../../data/boucwen/README.md)",
        "examples/boucwen/prepare.py": 'HERE = Path(__file__).resolve().parent\nSUBSET = HERE.parents[1] / "data"',
        "tests/test_x.py": 'ROOT = Path(__file__).resolve().parents[1]\nDEMO = ROOT / "data"',
        "README.md": "a shared VM; workers need no shared file system; /usr/bin/docker",
    }
    for name, text in good.items():
        assert not problems_in(name, text), (name, problems_in(name, text))


def test_demo_installs_the_runtime_dependencies_only_and_test_the_dev_extra():
    def commands(target: str) -> str:
        done = subprocess.run(["make", "-n", "-B", target], cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        return done.stdout

    demo, test = commands("demo"), commands("test")
    assert "pip install --quiet --no-compile -e '.'\n" in demo and "[dev]" not in demo
    assert "-e '.[dev]'" in test and "python -m pytest" in test


def test_pyproject_license_is_an_spdx_string():
    """setuptools >= 77 warns, screen after screen, about a license table; an SPDX string
    needs setuptools >= 77 to build."""
    import tomllib

    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert isinstance(config["project"]["license"], str)
    assert "setuptools>=77" in config["build-system"]["requires"]


def test_the_version_is_written_once():
    """S: the version stood in pyproject.toml and in abcns/__init__.py, free to disagree. The
    package's metadata reads abcns.__version__ (setuptools' dynamic version, read without
    importing abcns), so a plain checkout and an install say the same."""
    import importlib.metadata
    import tomllib

    import abcns

    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "version" not in config["project"] and "version" in config["project"]["dynamic"]
    assert config["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "abcns.__version__"}
    assert importlib.metadata.version("abcns") == abcns.__version__


def test_the_service_says_the_version_the_package_holds(monkeypatch):
    """X: a second version written in service/http/api.py (a literal in ``FastAPI(version=...)``)
    passed the test above. The app's schema (what ``GET /openapi.json`` serves; the app made,
    nothing started) says the package's version, and follows ``abcns.__version__`` when that
    changes."""
    import importlib.metadata

    import abcns
    from service.http.api import create_app

    def served() -> str:
        return create_app().openapi()["info"]["version"]

    assert served() == importlib.metadata.version("abcns")
    monkeypatch.setattr(abcns, "__version__", "0.0.0+written-once")
    assert served() == "0.0.0+written-once"
