"""The code's shape: packages in data-flow order (import-linter), short modules and functions."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from importlinter.cli import lint_imports

import fallkit

ROOT = Path(fallkit.__file__).parent
SOURCES = sorted(ROOT.rglob("*.py"))
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 60


def test_packages_import_only_packages_before_them_in_the_data_flow():
    """pyproject.toml's [tool.importlinter] layers contract: no circle, no upward import."""
    assert lint_imports(config_filename=str(ROOT.parent / "pyproject.toml"), no_cache=True) == 0


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
