"""The code's shape: packages in data-flow order (import-linter), short modules and functions."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import fallkit

ROOT = Path(fallkit.__file__).parent
SOURCES = sorted(ROOT.rglob("*.py"))
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 60


def test_packages_import_only_packages_before_them_in_the_data_flow():
    """pyproject.toml's [tool.importlinter] layers contract: no circle, no upward import.

    In a subprocess: import-linter's CLI reconfigures logging with disable_existing_loggers,
    which would silence fallkit's loggers for every later test of the session."""
    lint = Path(sys.executable).parent / "lint-imports"
    r = subprocess.run([str(lint), "--config", str(ROOT.parent / "pyproject.toml"), "--no-cache"],
                       capture_output=True, text=True, timeout=300)  # fmt: skip
    assert r.returncode == 0, r.stdout[-3000:]


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_modules_and_functions_stay_short(path):
    text = path.read_text()
    assert text.count("\n") <= MAX_MODULE_LINES, f"{path} has over {MAX_MODULE_LINES} lines: split it"
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            length = node.end_lineno - node.lineno + 1
            reason = "long because" in (ast.get_docstring(node) or "")
            assert length <= MAX_FUNCTION_LINES or reason, (
                f"{path}:{node.lineno} {node.name} has {length} lines: split it, or say in its docstring why it is "
                f"'long because …'"
            )
