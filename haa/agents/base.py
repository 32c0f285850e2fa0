"""Deprecated: the agent SDK moved to `haa.sdk` — import `from haa.sdk.base import AgentBase`.

Kept so that agents written against `haa.agents.base` keep working; it re-exports `haa.sdk.base` and warns once.
"""

import warnings

from haa.sdk.base import *  # noqa: F403
from haa.sdk.base import AgentBase as AgentBase
from haa.sdk.base import AgentContext as AgentContext
from haa.sdk.base import AgentFatal as AgentFatal
from haa.sdk.base import RemoteError as RemoteError

warnings.warn("haa.agents.base is deprecated: import from haa.sdk.base", DeprecationWarning, stacklevel=2)
