"""`haactl record ls DIR`: what an AgentPlayback recording holds (docs/playback.md).

Argument parsing and printing only; reading is haa.lab.playback.reader.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from haactl.cliopts import err, out
from haactl.tables import table

record_app = typer.Typer(help="AgentPlayback recordings: what they hold (docs/playback.md).", no_args_is_help=True)


def _size(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)  # pragma: no cover


@record_app.command("ls")
def record_ls(
    folder: Annotated[Path, typer.Argument(help="a recording folder (haactl mission run --record DIR), one "
                                           "agent's folder or one segment file")],
    agent: Annotated[str | None, typer.Option("--agent", help="only this agent (display name or id)")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="one JSON object per agent instead of the table")] = False,
) -> None:
    """Agents recorded: type, instances (lives: a transfer or recovery starts a new one), segments, inputs,
    outputs, the time span, bytes on disk, hosts."""
    from haa.lab.playback.reader import RecordingError, summarize

    try:
        rows = summarize(folder, agent)
    except RecordingError as e:
        err.print(f"[bold red]error:[/bold red] {escape(str(e))}")
        raise typer.Exit(1) from None
    if as_json:
        for r in rows:
            out.print(json.dumps({"agent": r.name, "id": r.agent_id, "type": r.type_name, "instances": r.instances,
                                  "segments": r.segments, "inputs": r.inputs, "outputs": r.outputs,
                                  "first_ns": r.first_ns, "last_ns": r.last_ns, "span_s": round(r.span_s, 3),
                                  "bytes": r.bytes, "hosts": r.hosts, "truncated_segments": r.truncated}),
                      soft_wrap=True)
        return
    t = table(["agent", "type", "instances", "segments", "inputs", "outputs", "from", "span s", "size", "hosts"],
              title=f"recording {folder}", right=["instances", "segments", "inputs", "outputs", "span s", "size"])
    for r in rows:
        segs = f"{r.segments}" + (f" ({r.truncated} cut)" if r.truncated else "")
        t.add_row(escape(r.name), escape(r.type_name), str(r.instances), segs, str(r.inputs), str(r.outputs),
                  time.strftime("%H:%M:%S", time.localtime(r.first_ns / 1e9)), f"{r.span_s:.1f}", _size(r.bytes),
                  escape(",".join(r.hosts)))
    out.print(t)
    total = sum(r.bytes for r in rows)
    out.print(f"{len(rows)} agents, {sum(r.inputs for r in rows)} inputs, {sum(r.outputs for r in rows)} outputs, "
              f"{_size(total)}")
