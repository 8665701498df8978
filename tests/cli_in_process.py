"""`abcns ARGS` in the test's own process: the typer app under click's CliRunner (stdout and
stderr apart), for the tests of what a command prints and its exit code. What the installed
command's process adds (the entry point, its exit status) is tested once, as a process, in
tests/test_study.py and by the README's walk-through (tests/test_walkthrough.py)."""

from __future__ import annotations

from typer.testing import Result


def invoke(*args, code: int = 0, env: dict | None = None) -> Result:
    """The command's result; it must exit ``code``."""
    from typer.testing import CliRunner

    from service.cli import app

    done = CliRunner().invoke(app, [str(a) for a in args], prog_name="abcns", env=env)
    assert done.exit_code == code, (done.exit_code, done.output[-2000:], done.exception)
    return done
