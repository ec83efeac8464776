"""The style rule of the project (issue 25): no function over 80 lines and no class over 400 in
foamlab/, drivers/ and simulator/ - each concern in a room a newcomer can read."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_FUNCTION, MAX_CLASS = 80, 400


def _oversized() -> list[str]:
    out = []
    for package in ("foamlab", "drivers", "simulator"):
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                limit = (MAX_FUNCTION if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
                         else MAX_CLASS if isinstance(node, ast.ClassDef) else None)
                if limit is not None and node.end_lineno - node.lineno + 1 > limit:
                    out.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} "
                               f"({node.end_lineno - node.lineno + 1} lines > {limit})")
    return out


def test_no_function_over_80_lines_and_no_class_over_400():
    assert _oversized() == []
