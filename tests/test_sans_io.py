"""The algorithm cores are sans-I/O: no asyncio, grpc, clock, sockets, threads or global randomness.

DESIGN.md's core rule. The simulator can only be deterministic (and the proofs only apply to the code the
real runtime runs) if the state machines take time and randomness as inputs and never reach out."""

import ast
from pathlib import Path

import pytest
from helpers import parse_source

ROOT = Path(__file__).resolve().parents[1]
#: every module of the core package and of its subpackages (a new machine is covered the moment it is added)
CORE_MODULES = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "haa" / "core").rglob("*.py"))


def _dotted(module: str) -> str:
    """haa/core/ddb/ops.py -> haa.core.ddb.ops; haa/core/ddb/__init__.py -> haa.core.ddb."""
    parts = Path(module).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


#: the core's packages (`from haa.core.ddb import ops` imports the module haa.core.ddb.ops)
CORE_PACKAGES = {_dotted(m) for m in CORE_MODULES if m.endswith("__init__.py")}
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
    tree = parse_source(path)
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
            if node.module == "haa.pb" or node.module in CORE_PACKAGES:
                out += [f"{node.module}.{a.name}" for a in node.names]
            else:
                out.append(node.module)
        elif isinstance(node, ast.Import):
            out += [a.name for a in node.names if a.name.startswith("haa")]
    return out


def _not_allowed(tree: ast.AST) -> list[str]:
    """The `haa...` imports of a core module that are neither core modules nor generated message modules."""
    allowed_haa = {_dotted(m) for m in CORE_MODULES}
    return [name for name in _haa_imports(tree)
            if not (name in allowed_haa or (name.startswith("haa.pb.") and name.endswith("_pb2")))]


def test_core_modules_only_import_each_other_and_generated_messages():
    """Cores may use each other and the generated protobuf message classes (plain data, no I/O); never
    the `_grpc` service stubs."""
    for module in CORE_MODULES:
        bad = _not_allowed(parse_source(ROOT / module))
        assert not bad, f"{module} imports {bad}"


def test_checker_catches_a_forbidden_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("import time\nfrom asyncio import sleep\n")
    assert _imports(bad) & FORBIDDEN == {"time", "asyncio"}


def test_the_subpackages_are_covered_and_a_forbidden_haa_import_is_caught():
    """The glob reaches the modules of the core's subpackages, and the import whitelist refuses what a core
    module may not import (the runtime, a `_grpc` stub, a name the package does not define as a module)."""
    assert {"haa/core/ufd/ufd.py", "haa/core/membership/update.py", "haa/core/ddb/ops.py",
            "haa/core/agents/agentnode.py", "haa/core/ddb/__init__.py"} <= set(CORE_MODULES)
    ok = "from haa.core.ddb import ops as ddb\nfrom haa.core.membership.globalstate import GlobalState\n"
    assert _not_allowed(parse_source(ok)) == []
    bad = ("from haa.hostd import runtime\nfrom haa.pb import hostlink_pb2_grpc\nimport haa.sdk.base\n"
           "from haa.core.agents import AgentNode\n")
    assert sorted(_not_allowed(parse_source(bad))) == ["haa.core.agents.AgentNode", "haa.hostd",
                                                    "haa.pb.hostlink_pb2_grpc", "haa.sdk.base"]
