"""The algorithm cores are sans-I/O: no asyncio, grpc, clock, sockets, threads or global randomness.

DESIGN.md's core rule. The simulator can only be deterministic (and the proofs only apply to the code the
real runtime runs) if the state machines take time and randomness as inputs and never reach out."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORE_MODULES = [
    "haa/hostd/ufd.py",
    "haa/hostd/oac.py",
    "haa/hostd/core.py",
    "haa/hostd/qos.py",
    "haa/hostd/messages.py",
    "haa/hostd/effects.py",
    "haa/hostd/ddb.py",
]
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


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
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


def test_core_modules_only_import_each_other_and_stdlib_pure_modules():
    allowed_haa = {f"haa.hostd.{Path(m).stem}" for m in CORE_MODULES}
    for module in CORE_MODULES:
        tree = ast.parse((ROOT / module).read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("haa"):
                assert node.module in allowed_haa, f"{module} imports {node.module}"


def test_checker_catches_a_forbidden_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("import time\nfrom asyncio import sleep\n")
    assert _imports(bad) & FORBIDDEN == {"time", "asyncio"}
