"""No function in ``abcns/``, ``worker/`` or ``service/`` is over 80 lines (issue 28: each
function reads as one idea).

A function's length runs from its ``def`` line to its last line, docstring included. Every
function counts: methods, nested functions, and the numba kernels of ``abcns/compiled.py``
(``@njit`` is no exemption: a long kernel is split into ``@njit`` helpers, which numba
compiles and calls as it does any other).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 80


def function_lengths(source: str) -> dict[str, int]:
    """Lines of each function of ``source`` (nested ones as ``outer.inner``), from its
    ``def`` line to its last line."""
    out: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                assert child.end_lineno is not None
                out[prefix + child.name] = child.end_lineno - child.lineno + 1
                visit(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            else:
                visit(child, prefix)

    visit(ast.parse(source), "")
    return out


@pytest.mark.parametrize("package", ["abcns", "worker", "service"])
def test_no_function_is_over_80_lines(package):
    long = [f"{path.relative_to(ROOT)}:{name}: {n} lines"
            for path in sorted((ROOT / package).rglob("*.py"))
            for name, n in function_lengths(path.read_text()).items() if n > MAX_LINES]
    assert not long, "over 80 lines (split into helpers, one idea each):\n" + "\n".join(long)


def test_the_count_sees_kernels_methods_and_nested_functions():
    source = ("@njit(cache=True)\ndef kernel(x):\n    return x\n\n\n"
              "class A:\n    @property\n    def p(self):\n        def inner():\n            pass\n\n"
              "        return 1\n")
    assert function_lengths(source) == {"kernel": 2, "A.p": 5, "A.p.inner": 2}
    kernels = function_lengths((ROOT / "abcns" / "compiled.py").read_text())
    assert {"tree_rows", "mixture_weights", "count_inside"} <= set(kernels)
