"""docs/architecture.md is checked against the code: every module, path and `Class.method` it names exists, and
its pictures of the import layers are the ones `.importlinter` enforces. Each check is also shown to fail on a
name or a layer that is wrong."""

from __future__ import annotations

import ast
import configparser
import importlib
import re
from functools import cache
from pathlib import Path

from helpers import parse_source

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "architecture.md"

DOTTED = re.compile(r"\b(haa(?:\.[A-Za-z_][A-Za-z0-9_]*)+)")
PATH = re.compile(r"\b((?:haa|proto|tests|docs)/[A-Za-z0-9_/-]*[A-Za-z0-9_](?:\.[a-z]+)?)/?")
METHOD = re.compile(r"\b([A-Z][A-Za-z]+)\.([a-z_][a-z_]+)\b")


def _resolves(name: str) -> bool:
    parts = name.split(".")
    for n in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:n]))
        except ImportError:
            continue
        for attr in parts[n:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


@cache
def _classes() -> dict[str, set[str]]:
    """Every class defined in haa/ -> the names defined in its body (methods, attributes), merged by name."""
    out: dict[str, set[str]] = {}
    for f in (ROOT / "haa").rglob("*.py"):
        for node in ast.walk(parse_source(f)):
            if isinstance(node, ast.ClassDef):
                names = out.setdefault(node.name, set())
                for item in node.body:
                    if isinstance(item, ast.FunctionDef | ast.AsyncFunctionDef):
                        names.add(item.name)
                    elif isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                        names.add(item.target.id)
    return out


def unresolved(text: str) -> list[str]:
    """The names in `text` that the code does not have."""
    bad = [m for m in sorted(set(DOTTED.findall(text))) if "*" not in m and not _resolves(m)]
    bad += [p for p in sorted(set(PATH.findall(text))) if not (ROOT / p).exists()]
    for cls, attr in sorted(set(METHOD.findall(text))):
        if cls in _classes() and attr not in _classes()[cls]:
            bad.append(f"{cls}.{attr}")
    return bad


def _blocks(text: str) -> list[list[str]]:
    return [[ln.strip() for ln in b.strip("\n").splitlines() if ln.strip()]
            for b in re.findall(r"```\n(.*?)```", text, flags=re.S)]


def _layers(contract: str) -> list[str]:
    ini = configparser.ConfigParser()
    ini.read(ROOT / ".importlinter")
    lines = [ln.strip() for ln in ini[f"importlinter:contract:{contract}"]["layers"].splitlines()]
    return [" | ".join(p.strip() for p in ln.split("|")) for ln in lines if ln and not ln.startswith("#")]


def _picture(first: str) -> list[str]:
    pictures = [b for b in _blocks(DOC.read_text()) if b and b[0] == first]
    assert len(pictures) == 1, f"one picture of the layers starting with {first!r}"
    return pictures[0]


def test_every_module_path_and_method_the_page_names_exists():
    text = DOC.read_text()
    assert len(set(DOTTED.findall(text))) > 40  # the page does name the code
    assert unresolved(text) == []


def test_the_check_fails_on_a_name_the_code_does_not_have():
    assert unresolved("haa.core.nosuch") == ["haa.core.nosuch"]
    assert unresolved("haa.sdk.registry.no_such_function") == ["haa.sdk.registry.no_such_function"]
    assert unresolved("see haa/core/nosuch.py") == ["haa/core/nosuch.py"]
    assert unresolved("Router.nosuch") == ["Router.nosuch"]
    assert unresolved("haa.sdk.registry.known, haa/hostd/, Router.sent") == []


def test_the_pictures_of_the_layers_are_the_contract():
    assert _picture("haactl") == _layers("layers")
    assert _picture("bench") == _layers("lab-layers")


def test_the_layer_check_fails_on_a_picture_that_differs():
    picture = _picture("haactl")
    swapped = [picture[0], picture[2], picture[1], *picture[3:]]
    assert swapped != _layers("layers")
