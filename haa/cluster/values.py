"""DDB values as an operator reads them: `plain_value(type, bytes)` turns a record's canonical value bytes
(haa.core.ddb's types: json, blob, counter, list, log, ...) into a JSON-able Python value — text where the
bytes are UTF-8, "base64:..." where they are not. Used by `haactl ddb` (get, ls, watch) and the demo
(haa.lab.experiments.demo reads the counters the agents publish).
"""

from __future__ import annotations

import base64
from typing import Any

from haa.core.ddb import objects as ddb


def show_bytes(b: bytes) -> str:
    """UTF-8 text as it is; other bytes as "base64:<base64>"."""
    try:
        return b.decode("utf-8")
    except UnicodeDecodeError:
        return "base64:" + base64.b64encode(b).decode()


def plain_value(type_name: str, data: bytes) -> Any:
    """A record's canonical value bytes -> a JSON-able Python value."""
    t = ddb.TYPES.get(type_name)
    if t is None:
        return show_bytes(data)
    try:
        raw, _ = t.decode(data)
    except Exception:
        return show_bytes(data)
    value = t.public(raw)
    if isinstance(value, bytes):
        return show_bytes(value)
    if isinstance(value, tuple):
        return [show_bytes(i) for i in value]
    if type_name == "log":
        return {"first": value["first"], "items": [show_bytes(i) for i in value["items"]]}
    return value
