"""mypy, strict, on the core: the sans-I/O state machines, their messages, effects and wire codecs.

The configuration is pyproject's [tool.mypy]: `files` is the core package haa/core (so a bare `mypy` checks it)
and an override makes it strict. The tests below run it as a developer would, keep it, the import contract and
tests/test_sans_io.py naming the same package, keep the `# type: ignore` budget of the core, and check that the
strict flags do reach a core module (an unannotated function added to a copy of one is an error).
"""

from __future__ import annotations

import configparser
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MYPY = Path(sys.executable).with_name("mypy")
#: the issue's bound on `# type: ignore` comments in the core (issue 17)
IGNORE_BUDGET = 10


def _mypy_config() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]


def _core_files() -> list[str]:
    return list(_mypy_config()["files"])


def _strict_modules() -> set[str]:
    for o in _mypy_config()["overrides"]:
        if o.get("disallow_untyped_defs"):
            return set(o["module"])
    raise AssertionError("no strict override in [tool.mypy]")


def _mypy(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(MYPY), *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def test_core_type_checks_strict():
    r = _mypy()
    assert r.returncode == 0, r.stdout + r.stderr
    assert "Success: no issues found" in r.stdout


def test_core_lists_agree():
    """The core is one package, haa/core: mypy's `files`, the strict override, the import contract's
    `core-is-sans-io` and tests/test_sans_io.py (which globs the package) all name it whole, so a new machine
    is checked the moment its file exists."""
    assert _core_files() == ["haa/core"]
    assert _strict_modules() == {"haa.core", "haa.core.*"}
    ini = configparser.ConfigParser()
    ini.read(ROOT / ".importlinter")
    contract = {m.strip() for m in ini["importlinter:contract:core-is-sans-io"]["source_modules"].split()}
    assert contract == {"haa.core"}
    assert (ROOT / "haa/hostd/core.py").exists() is False  # no core module left behind in the runtime package


def test_type_ignore_budget_of_the_core():
    counts = {str(f.relative_to(ROOT)): len(re.findall(r"#\s*type:\s*ignore", f.read_text()))
              for d in _core_files() for f in sorted((ROOT / d).glob("*.py"))}
    assert sum(counts.values()) <= IGNORE_BUDGET, {f: n for f, n in counts.items() if n}


def test_strict_flags_reach_the_core(tmp_path):
    """A copy of a core module under its own name, with an unannotated function appended, fails."""
    pkg = tmp_path / "haa" / "core"
    pkg.mkdir(parents=True)
    (tmp_path / "haa" / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    shutil.copy(ROOT / "haa/core/qos.py", pkg / "qos.py")
    r = _mypy("--config-file", str(ROOT / "pyproject.toml"), "--cache-dir", str(tmp_path / "cache"),
              "haa/core/qos.py", cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr  # the copy alone is clean
    with (pkg / "qos.py").open("a") as f:
        f.write("\n\ndef untyped(x):\n    return x\n")
    r = _mypy("--config-file", str(ROOT / "pyproject.toml"), "--cache-dir", str(tmp_path / "cache"),
              "haa/core/qos.py", cwd=tmp_path)
    assert r.returncode == 1 and "[no-untyped-def]" in r.stdout, r.stdout + r.stderr
