"""`haactl logs [-f] [--host NAME]`: the hosts' JSON-lines logs, merged by time and rich-formatted.

Local clusters: `<root>/<name>/<name>.jsonl`; compose: the containers' logs (haa-hostd runs with
--log-stderr there). Lines that are not JSON (a traceback, a start-up error) are shown as they are, in
their place in that host's log. With `-f` new lines are printed as they come (merged by time within each
short batch); hosts restarted meanwhile are followed again.
"""

from __future__ import annotations

import json
import queue
import threading
import time
import zlib
from collections.abc import Iterator
from datetime import datetime
from typing import Annotated, Any

import typer
from rich.markup import escape

from haa.cluster.backend import ClusterError
from haactl.cliopts import (
    LOCAL,
    ClusterOpts,
    cli_errors,
    cluster_options,
    out,
)

PALETTE = (
    "cyan",
    "magenta",
    "green",
    "yellow",
    "blue",
    "bright_cyan",
    "bright_magenta",
    "bright_green",
    "bright_yellow",
    "bright_blue",
)
LEVEL_STYLE = {"debug": "dim", "info": "", "warning": "yellow", "error": "bold red", "critical": "bold red"}


def parse_line(host: str, line: str, last_ts: float) -> dict[str, Any]:
    """A raw log line -> a record with `ts` (non-JSON lines inherit the previous line's time)."""
    try:
        rec = json.loads(line)
        if isinstance(rec, dict) and isinstance(rec.get("ts"), int | float):
            rec.setdefault("host", host)
            rec["_src"] = host
            return rec
    except json.JSONDecodeError:
        pass
    return {"ts": last_ts, "_src": host, "host": host, "raw": line}


def records(pairs: Iterator[tuple[str, str]]) -> Iterator[dict[str, Any]]:
    last: dict[str, float] = {}
    for host, line in pairs:
        rec = parse_line(host, line, last.get(host, 0.0))
        last[host] = rec["ts"]
        yield rec


def _value(v: Any) -> str:
    if isinstance(v, str):
        return v if v and " " not in v and "=" not in v else json.dumps(v)
    return json.dumps(v, separators=(",", ":"), default=str)


def render(rec: dict[str, Any]) -> str:
    src = rec.get("_src", rec.get("host", "?"))
    color = PALETTE[zlib.crc32(src.encode()) % len(PALETTE)]
    ts = datetime.fromtimestamp(rec["ts"]).strftime("%H:%M:%S.%f")[:-3] if rec.get("ts") else "--:--:--.---"
    head = f"[dim]{ts}[/] [{color}]{escape(src):>4}[/]"
    if "raw" in rec:
        return f"{head} {escape(rec['raw'])}"
    level = str(rec.get("level", "info"))
    style = LEVEL_STYLE.get(level, "")
    lvl = f"[{style}]{level[:4]:<4}[/]" if style else f"{level[:4]:<4}"
    fields = rec.get("fields") or {}
    body = " ".join(f"[dim]{escape(str(k))}=[/]{escape(_value(v))}" for k, v in fields.items())
    event = f"[bold]{escape(str(rec.get('event', '')))}[/]"
    return f"{head} {lvl} {event} {body}".rstrip()


def emit(rec: dict[str, Any], json_out: bool) -> None:
    if json_out:
        if "raw" in rec:
            print(json.dumps({"ts": rec["ts"], "host": rec["host"], "raw": rec["raw"]}), flush=True)
        else:
            print(json.dumps({k: v for k, v in rec.items() if k != "_src"}, separators=(",", ":")), flush=True)
    else:
        out.print(render(rec), soft_wrap=True)


@cli_errors
@cluster_options()
def logs(
    follow: Annotated[bool, typer.Option("--follow", "-f", help="keep printing new lines until Ctrl-C")] = False,
    host: Annotated[list[str] | None, typer.Option("--host", "-H", help="only these hosts (repeatable)")] = None,
    tail: Annotated[int, typer.Option("--tail", "-n", min=0, help="only the last N lines of the history")] = 0,
    event: Annotated[list[str] | None, typer.Option("--event", "-e", help="only these events (repeatable)")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="print the JSON lines as they are")] = False,
    where: ClusterOpts = LOCAL,
) -> None:
    """Show the hosts' JSON-lines logs merged by time (rich-formatted; -f follows)."""
    backend = where.backend(last=True)
    hosts = backend.require_hosts()
    names = [h.name for h in hosts]
    for n in host or []:
        if n not in names:
            raise ClusterError(f"unknown host {n!r} in the {backend.describe()} (hosts: {', '.join(names)})")
    wanted = list(host) if host else names
    events = set(event or [])

    def keep(rec: dict[str, Any]) -> bool:
        return not events or rec.get("event") in events

    lines: dict[str, list[str]] = {n: [] for n in wanted}
    for n, line in backend.log_records(wanted, follow=False):
        lines[n].append(line)
    history = [r for r in records((n, ln) for n in wanted for ln in lines[n]) if keep(r)]
    history.sort(key=lambda r: r["ts"])  # stable: a host's lines keep their order
    if tail:
        history = history[-tail:]
    for rec in history:
        emit(rec, json_out)
    if not follow:
        return
    # Follow: a reader thread feeds new lines; print them in time order within short batches.
    q: queue.Queue[dict[str, Any]] = queue.Queue()
    skip = {n: len(v) for n, v in lines.items()}  # the follow stream starts with the history printed above

    def reader() -> None:
        for rec in records(backend.log_records(wanted, follow=True)):
            src = rec["_src"]
            if skip.get(src, 0) > 0:
                skip[src] -= 1
                continue
            q.put(rec)

    threading.Thread(target=reader, daemon=True).start()
    while True:
        batch = [q.get()]
        deadline = time.monotonic() + 0.25
        while time.monotonic() < deadline:
            try:
                batch.append(q.get(timeout=max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                break
        for rec in sorted(batch, key=lambda r: r["ts"]):
            if keep(rec):
                emit(rec, json_out)
