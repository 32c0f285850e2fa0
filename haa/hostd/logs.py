"""Structured JSON-lines logging for haa-hostd (one JSON object per line: ts, host, inc, level, event, fields).

Modules log through the standard `logging` package with two extra attributes, `event` (a short snake_case
name) and `fields` (a dict), using `log_event`. `JsonFormatter` renders a record as one line:

    {"ts": 1732170000.123456, "host": "h1", "inc": 1732170000123456789, "level": "info",
     "event": "suspicion", "fields": {"peer": "h2", "inc": 17321..., "suspected": true}}

`setup_logging` attaches a file handler (the daemon's `--data-dir`) and optionally stderr to the
`haa.hostd` logger. The host name and incarnation come from a mutable `HostIdentity` so that a reincarnation
shows up in every later line. `RateLimiter` keeps an attacker that floods a host with bad input from
flooding its log as well (the counters still count every rejection).
"""

from __future__ import annotations

import json
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

LOGGER_NAME = "haa.hostd"


@dataclass
class HostIdentity:
    """Who is logging; updated in place when the host reincarnates."""

    name: str = ""
    inc: int = 0


class JsonFormatter(logging.Formatter):
    """Render a record as one JSON object (see the module docstring)."""

    def __init__(self, ident: HostIdentity) -> None:
        super().__init__()
        self.ident = ident

    def format(self, record: logging.LogRecord) -> str:
        event = getattr(record, "event", None) or "message"
        fields: dict[str, Any] = dict(getattr(record, "fields", None) or {})
        if event == "message":
            fields["message"] = record.getMessage()
        if record.exc_info:
            fields["exception"] = self.formatException(record.exc_info)
        obj = {
            "ts": round(record.created, 6),
            "host": self.ident.name,
            "inc": self.ident.inc,
            "level": record.levelname.lower(),
            "event": event,
            "fields": fields,
        }
        return json.dumps(obj, default=str, separators=(",", ":"))


def log_event(logger: logging.Logger, level: int, event: str, **fields: Any) -> None:
    """Log a structured event (cheap when the level is disabled)."""
    if logger.isEnabledFor(level):
        logger.log(level, event, extra={"event": event, "fields": fields})


class RateLimiter:
    """Allow one event per key every `interval` seconds (monotonic clock)."""

    def __init__(self, interval: float = 1.0) -> None:
        self.interval = interval
        self._last: dict[str, float] = {}

    def allow(self, key: str) -> bool:
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last < self.interval:
            return False
        self._last[key] = now
        return True


def setup_logging(
    ident: HostIdentity, log_file: Path | None, level: int = logging.INFO, stderr: bool = False
) -> list[logging.Handler]:
    """Send the `haa.hostd` logger's records, as JSON lines, to `log_file` and optionally stderr.

    Returns the handlers it added (the caller closes them on shutdown)."""
    logger = logging.getLogger(LOGGER_NAME)
    logger.setLevel(level)
    logger.propagate = False
    fmt = JsonFormatter(ident)
    handlers: list[logging.Handler] = []
    if log_file is not None:
        log_file.parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.FileHandler(log_file, encoding="utf-8"))
    if stderr:
        handlers.append(logging.StreamHandler(sys.stderr))
    if not handlers:
        handlers.append(logging.NullHandler())  # not Python's "last resort" stderr handler
    for h in handlers:
        h.setFormatter(fmt)
        logger.addHandler(h)
    return handlers


def teardown_logging(handlers: list[logging.Handler]) -> None:
    logger = logging.getLogger(LOGGER_NAME)
    for h in handlers:
        logger.removeHandler(h)
        h.close()
