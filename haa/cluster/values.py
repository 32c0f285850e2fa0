"""DDB values as an operator reads them: `plain_value(type, bytes)` turns a record's canonical value bytes
(haa.core.ddb's types: json, blob, counter, list, log, ...) into a JSON-able Python value — text where the
bytes are UTF-8, "base64:..." where they are not. Decoded by haa.core.ddb.ops.decode_value (the one decoder);
bytes it cannot decode are shown as they are. Used by `haactl ddb` (get, ls, watch) and the demo
(haa.lab.experiments.demo reads the counters the agents publish).
"""

from __future__ import annotations

import base64
from typing import Any

from haa.core.ddb.objects import DdbError
from haa.core.ddb.ops import decode_value


def show_bytes(b: bytes) -> str:
    """UTF-8 text as it is; other bytes as "base64:<base64>"."""
    try:
        return b.decode("utf-8")
    except UnicodeDecodeError:
        return "base64:" + base64.b64encode(b).decode()


def plain_value(type_name: str, data: bytes) -> Any:
    """A record's canonical value bytes -> a JSON-able Python value (an unknown type or malformed bytes: the
    bytes, shown)."""
    try:
        value = decode_value(type_name, data)
    except DdbError:
        return show_bytes(data)
    if isinstance(value, bytes):
        return show_bytes(value)
    if isinstance(value, tuple):
        return [show_bytes(i) for i in value]
    if type_name == "log":
        return {"first": value["first"], "items": [show_bytes(i) for i in value["items"]]}
    return value
