"""Deprecated: the agent type registry moved to `haa.sdk.registry` — `from haa.sdk.registry import register`.

Kept so that agents written against `haa.agents.registry` keep working; it re-exports `haa.sdk.registry` and warns
once.
"""

import warnings

from haa.sdk.registry import *  # noqa: F403
from haa.sdk.registry import REGISTRY as REGISTRY
from haa.sdk.registry import get as get
from haa.sdk.registry import register as register

warnings.warn("haa.agents.registry is deprecated: import from haa.sdk.registry", DeprecationWarning, stacklevel=2)
