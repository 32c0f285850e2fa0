"""A ceiling that catches giants: no module of haa/ (but the generated protobuf code) over 1,000 lines and no
class over 600. Not a size to aim at — modules are split by seam (docs/architecture.md) — but a module or class
that grows past these has more than one thing in it."""

from __future__ import annotations

import ast
from pathlib import Path

from helpers import parse_source

ROOT = Path(__file__).resolve().parents[1]
MAX_MODULE_LINES = 1000
MAX_CLASS_LINES = 600


def giants(path: Path, source: str | None = None) -> list[str]:
    """What in one module is over the ceiling, one line each."""
    text = path.read_text() if source is None else source
    out = []
    if (n := len(text.splitlines())) > MAX_MODULE_LINES:
        out.append(f"{path}: {n} lines > {MAX_MODULE_LINES}")
    for node in ast.walk(parse_source(text)):
        if isinstance(node, ast.ClassDef) and node.end_lineno is not None:
            if (n := node.end_lineno - node.lineno + 1) > MAX_CLASS_LINES:
                out.append(f"{path}: class {node.name} {n} lines > {MAX_CLASS_LINES}")
    return out


def test_no_module_or_class_is_a_giant():
    modules = [p for p in (ROOT / "haa").rglob("*.py") if "pb" not in p.relative_to(ROOT / "haa").parts[:1]]
    assert len(modules) > 250
    assert [g for p in sorted(modules) for g in giants(p.relative_to(ROOT))] == []


def test_the_ceiling_catches_a_giant_module_and_a_giant_class():
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_CLASS_LINES))
    assert giants(Path("big.py"), f"class Big:\n{body}\n") == [f"big.py: class Big {MAX_CLASS_LINES + 1} lines > 600"]
    lines = "\n".join(f"y{i} = {i}" for i in range(MAX_MODULE_LINES + 1))
    assert giants(Path("long.py"), lines) == [f"long.py: {MAX_MODULE_LINES + 1} lines > 1000"]
    assert giants(Path("fine.py"), "class Small:\n    pass\n") == []
