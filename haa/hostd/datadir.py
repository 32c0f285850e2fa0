"""HostDataDir: what one haa-hostd keeps in its `--data-dir` across restarts (besides its logs and statistics).

* `incarnation` — the last incarnation number this host used. A new one is `time.time_ns()`, bumped above
  this file's value and above the previous incarnation, so incarnations increase strictly across restarts
  even if the clock steps back (thesis §4.3: a restarted process is a new process).
* `known_hosts.json` — the members of the last view this host saw (`{"members": [[name, address], ...]}`,
  without itself), written at every view change and removed when the host leaves gracefully. A restarted
  host applies to them as well as to the core processes, so it never founds a group of its own while its
  old group lives on (docs/membership.md, "restarts"). The file is read with the limits of every file HAA
  reads (haa.files): a corrupt or huge one is ignored with a warning.

Without a data directory (tests, `--data-dir` unset in-process) nothing is read or written.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Protocol

from haa import files
from haa.hostd.logs import LOGGER_NAME, log_event

log = logging.getLogger(LOGGER_NAME + ".runtime")

#: hosts taken from a previous incarnation's known_hosts.json (as many as --core accepts)
MAX_KNOWN_HOSTS = 1000


class _Member(Protocol):
    @property
    def name(self) -> str: ...

    @property
    def addr(self) -> str: ...


class HostDataDir:
    """See the module docstring."""

    def __init__(self, name: str, path: Path | None) -> None:
        self.name = name
        self.path = path

    @property
    def known_hosts_file(self) -> Path | None:
        return self.path / "known_hosts.json" if self.path is not None else None

    def new_incarnation(self, above: int) -> int:
        """A fresh incarnation number, greater than `above` and than the last one recorded; recorded."""
        inc = max(time.time_ns(), above + 1)
        d = self.path
        if d is not None:
            f = d / "incarnation"
            with contextlib.suppress(OSError, ValueError):
                inc = max(inc, int(f.read_text().strip()) + 1)
            try:
                f.write_text(f"{inc}\n")
            except OSError as e:
                log_event(log, logging.WARNING, "incarnation_not_saved", error=str(e))
        return inc

    def load_known_hosts(self) -> list[tuple[str, str]]:
        """Hosts a previous incarnation had as fellow members (docs/membership.md, "restarts")."""
        f = self.known_hosts_file
        if f is None or not f.exists():
            return []
        try:
            # a file of our own, read with the limits of every file HAA reads (a corrupt or huge one is ignored)
            data = files.load_json(f, what="known hosts file", max_bytes=1 << 20)
            out = [(str(n), str(a)) for n, a in data["members"] if n != self.name][:MAX_KNOWN_HOSTS]
        except (OSError, ValueError, KeyError, TypeError) as e:
            log_event(log, logging.WARNING, "known_hosts_unreadable", file=str(f), error=str(e))
            return []
        log_event(log, logging.INFO, "known_hosts", hosts=[n for n, _ in out])
        return out

    def save_known_hosts(self, members: Iterable[_Member]) -> None:
        f = self.known_hosts_file
        if f is None:
            return
        data = {"members": [[m.name, m.addr] for m in members if m.name != self.name]}
        tmp = f.with_suffix(".tmp")
        try:
            tmp.write_text(json.dumps(data))
            os.replace(tmp, f)
        except OSError as e:
            log_event(log, logging.WARNING, "known_hosts_not_saved", error=str(e))

    def forget_known_hosts(self) -> None:
        f = self.known_hosts_file
        if f is not None:
            with contextlib.suppress(OSError):
                f.unlink()
