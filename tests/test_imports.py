"""The import contract (`.importlinter`, explained in docs/architecture.md) holds, and it would catch a breach.

The contract: the core (the sans-I/O state machines, their messages, effects and wire codecs) imports no
runtime; `haa` never imports `haactl`; the three products import downwards only (lab -> team -> framework) and
packages inside them only lower layers; agents use the SDK, not the host runtime; no import cycles. It is checked with
import-linter on the real import graph (grimp; imports inside functions and under TYPE_CHECKING count). The
breach tests add one import to that same graph and check that the contract guarding against it breaks — so
a contract that silently matched nothing would fail here.
"""

from __future__ import annotations

import configparser
import copy
import subprocess
import sys
from pathlib import Path

import grimp
import pytest
from importlinter.application import use_cases
from importlinter.application.app_config import settings
from importlinter.configuration import configure

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / ".importlinter"


def test_import_contract_is_kept():
    """`lint-imports` as a developer runs it: every contract kept, every named exception still needed."""
    exe = Path(sys.executable).with_name("lint-imports")
    r = subprocess.run([str(exe), "--no-cache", "--no-logo", str(CONFIG)], cwd=ROOT, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout


def test_no_contract_has_exceptions():
    """No arrow of the code is excused — no `ignore_imports` in any contract."""
    ini = configparser.ConfigParser()
    ini.read(CONFIG)
    excused = {name: ini[name]["ignore_imports"] for name in ini.sections() if "ignore_imports" in ini[name]}
    assert excused == {}


def test_every_package_has_a_layer_and_is_forbidden_to_the_core():
    """A new package of haa is placed in the layers on purpose, and the core may not import it."""
    import pkgutil

    import haa
    import haa.lab

    ini = configparser.ConfigParser()
    ini.read(CONFIG)
    layers = ini["importlinter:contract:layers"]["layers"]
    placed = {m.strip() for line in layers.split("\n") for m in line.split("|") if m.strip()}
    forbidden = set(ini["importlinter:contract:core-is-sans-io"]["forbidden_modules"].split())
    children = {f"haa.{m.name}" for m in pkgutil.iter_modules(haa.__path__)}
    assert children - placed == set(), "packages without a layer in .importlinter"
    assert children - {"haa.core", "haa.pb"} - forbidden == set(), "packages the core could import"
    lab = ini["importlinter:contract:lab-layers"]["layers"]
    placed = {m.strip() for line in lab.split("\n") for m in line.split("|") if m.strip()}
    children = {m.name for m in pkgutil.iter_modules(haa.lab.__path__)}
    assert children - placed == set(), "lab packages without a layer in .importlinter"


_GRAPHS: dict[tuple[tuple[str, ...], bool, bool], grimp.ImportGraph] = {}


class _GraphWithExtraImport:
    """import-linter's graph builder, plus one import that the code does not have (the real graph is built
    once per test session and copied)."""

    def __init__(self, importer: str, imported: str) -> None:
        self.importer, self.imported = importer, imported

    def build(self, root_package_names: list[str], cache_dir: str | None, include_external_packages: bool = False,
              exclude_type_checking_imports: bool = False) -> grimp.ImportGraph:
        key = (tuple(root_package_names), include_external_packages, exclude_type_checking_imports)
        if key not in _GRAPHS:
            _GRAPHS[key] = grimp.build_graph(*root_package_names, include_external_packages=include_external_packages,
                                             exclude_type_checking_imports=exclude_type_checking_imports,
                                             cache_dir=None)
        g = copy.deepcopy(_GRAPHS[key])
        g.add_import(importer=self.importer, imported=self.imported, line_number=1, line_contents="import x")
        return g


def _broken_contracts(importer: str, imported: str) -> set[str]:
    configure()
    use_cases._register_built_in_contract_types()  # what `lint-imports` does before reading contracts
    saved = settings.GRAPH_BUILDER
    settings.configure(GRAPH_BUILDER=_GraphWithExtraImport(importer, imported))
    try:
        report = use_cases.create_report(use_cases.read_user_options(str(CONFIG)), cache_dir=None)
    finally:
        settings.configure(GRAPH_BUILDER=saved)
    assert not report.could_not_run and not report.invalid_contract_options
    return {c.name for c, check in report.get_contracts_and_checks() if not check.kept}


@pytest.mark.parametrize(
    ("importer", "imported", "contract"),
    [
        # the core reaching for a clock, the event loop, the runtime or grpc (directly or through a helper)
        ("haa.core.oac.oac", "time", "The core imports no runtime"),
        ("haa.core.membership.membership", "asyncio", "The core imports no runtime"),
        ("haa.core.agents.agentnode", "haa.hostd.runtime", "The core imports no runtime"),
        ("haa.core.wire", "haa.pb.hostlink_pb2_grpc", "The core imports no runtime"),
        ("haa.core.ddb.ddb", "haa.files", "The core imports no runtime"),
        # the library reaching up into the CLI
        ("haa.lab.experiments.agents", "haactl.bench", "haa never imports haactl"),
        # a back-arrow between packages, and a cycle between two modules of one package
        ("haa.hostd.transport", "haa.cluster.backend", "Packages import only lower layers"),
        # an agent reaching into the host's runtime (the agents use the core's op builders, never the runtime)
        ("haa.sdk.base", "haa.hostd.runtime", "Packages import only lower layers"),
        ("haa.agents.team", "haa.hostd.agentproc", "Agents are written with the SDK"),
        ("haa.slam.filter", "haa.cluster.backend", "Agents are written with the SDK"),
        # the products: the framework reaching into the team or the lab, the team into the lab
        ("haa.hostd.daemon", "haa.agents.team", "Packages import only lower layers"),
        ("haa.sdk.registry", "haa.lab.demoagents", "Packages import only lower layers"),
        ("haa.cluster.backend", "haa.mission.runner", "Packages import only lower layers"),
        ("haa.mission.runner", "haa.lab.chaos.inject", "Packages import only lower layers"),
        ("haa.agents.executive_mission", "haa.lab.stats.collect", "Packages import only lower layers"),
        # inside the lab
        ("haa.lab.dsim.cluster", "haa.lab.experiments.ap1", "Lab packages import only lower lab layers"),
        ("haa.lab.stats.collect", "haa.lab.chaos.plan", "Lab packages import only lower lab layers"),
        # the core reaching up into the agents
        ("haa.core.ddb.ops", "haa.sdk.base", "The core imports no runtime"),
        ("haa.core.ufd.qos", "haa.core.ufd.ufd", "No import cycles"),
        # a cycle between two subpackages of the core: the DDB reaching up into membership, or membership into
        # the agent layer (each is below the other's importer)
        ("haa.core.ddb.ddb", "haa.core.membership.globalstate", "No import cycles"),
        ("haa.core.membership.globalstate", "haa.core.agents.agentnode", "No import cycles"),
        # arrows the contracts forbid without a named exception: each breaks a contract
        ("haa.sdk.runner", "haa.hostd.agentproc", "Packages import only lower layers"),
        ("haa.sdk.tap", "haa.lab.experiments.localhosts", "Packages import only lower layers"),
        ("haa.sim.actions", "haa.sim.world", "No import cycles"),
        ("haa.lab.stats.figures", "haa.lab.stats.report", "No import cycles"),
        ("haa.lab.stats.run", "haa.lab.stats.report", "No import cycles"),
        ("haa.slam.events", "haa.slam.recording", "No import cycles"),
    ],
)
def test_contract_catches_a_breach(importer, imported, contract):
    broken = _broken_contracts(importer, imported)
    assert any(name.startswith(contract) for name in broken), (importer, imported, broken)
