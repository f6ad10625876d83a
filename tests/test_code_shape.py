"""Procedures stay at their seams: no function of the package is longer than 80 lines
(docstring included), argparse builders aside (issue 20)."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "vislam"
MAX_LINES = 80


def _is_argparse_builder(name: str) -> bool:
    return name == "register" or name == "build_parser" or (name.startswith("add_") and name.endswith("_arguments"))


def test_no_function_over_80_lines():
    long = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not _is_argparse_builder(node.name):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_LINES:
                    long.append(f"{path.relative_to(PACKAGE)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, "functions over 80 lines: " + "; ".join(long)
