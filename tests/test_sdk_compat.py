"""Agents written against the old paths keep working: `haa.agents.base` and `haa.agents.registry` re-export the
SDK (`haa.sdk.base`, `haa.sdk.registry`) and say once that they are deprecated."""

from __future__ import annotations

import subprocess
import sys

PROBE = """
import warnings
warnings.simplefilter("always")
with warnings.catch_warnings(record=True) as caught:
    from haa.agents.base import AgentBase, AgentContext
    from haa.agents.registry import REGISTRY, get, register
import haa.sdk.base, haa.sdk.registry
assert AgentBase is haa.sdk.base.AgentBase and AgentContext is haa.sdk.base.AgentContext
assert register is haa.sdk.registry.register and REGISTRY is haa.sdk.registry.REGISTRY
assert get("counter").__module__ == "haa.lab.demoagents"
print(sorted(str(w.message) for w in caught if w.category is DeprecationWarning))
"""


def test_the_old_agent_paths_re_export_the_sdk_with_a_deprecation_warning():
    r = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(["haa.agents.base is deprecated: import from haa.sdk.base",
                                    "haa.agents.registry is deprecated: import from haa.sdk.registry"])
