"""The algorithm cores are sans-I/O: no asyncio, grpc, clock, sockets, threads or global randomness.

DESIGN.md's core rule. The simulator can only be deterministic (and the proofs only apply to the code the
real runtime runs) if the state machines take time and randomness as inputs and never reach out."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: every module of the core package (a new machine is covered the moment it is added)
CORE_MODULES = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "haa" / "core").glob("*.py"))
FORBIDDEN = {
    "asyncio",
    "grpc",
    "time",
    "socket",
    "threading",
    "multiprocessing",
    "subprocess",
    "select",
    "selectors",
    "random",
    "datetime",
    "os",
    "signal",
}


def _parse(path: Path) -> ast.Module:
    try:
        return ast.parse(path.read_text(), filename=str(path))
    except SystemError:
        # CPython 3.11.7's "AST constructor recursion depth mismatch" (python/cpython#106905, fixed in 3.11.8):
        # a failed parse elsewhere leaves the depth counter off and the next parse raises spuriously (seen once
        # in a loaded CI run); a second parse of the same file is exact
        return ast.parse(path.read_text(), filename=str(path))


def _imports(path: Path) -> set[str]:
    tree = _parse(path)
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("module", CORE_MODULES)
def test_core_module_does_no_io(module):
    bad = _imports(ROOT / module) & FORBIDDEN
    assert not bad, f"{module} imports {sorted(bad)}: algorithm cores must be sans-I/O"


def _haa_imports(tree: ast.AST) -> list[str]:
    """Every `haa...` module a file imports (`from haa.pb import x_pb2` counts as `haa.pb.x_pb2`)."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("haa"):
            if node.module in ("haa.pb", "haa.core"):
                out += [f"{node.module}.{a.name}" for a in node.names]
            else:
                out.append(node.module)
        elif isinstance(node, ast.Import):
            out += [a.name for a in node.names if a.name.startswith("haa")]
    return out


def test_core_modules_only_import_each_other_and_generated_messages():
    """Cores may use each other and the generated protobuf message classes (plain data, no I/O); never
    the `_grpc` service stubs."""
    allowed_haa = {"haa.core"} | {f"haa.core.{Path(m).stem}" for m in CORE_MODULES}
    for module in CORE_MODULES:
        for name in _haa_imports(ast.parse((ROOT / module).read_text())):
            ok = name in allowed_haa or (name.startswith("haa.pb.") and name.endswith("_pb2"))
            assert ok, f"{module} imports {name}"


def test_checker_catches_a_forbidden_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("import time\nfrom asyncio import sleep\n")
    assert _imports(bad) & FORBIDDEN == {"time", "asyncio"}
