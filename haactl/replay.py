"""`haactl replay DIR --agent NAME [--instance K] [--break-at N]`: re-run one agent offline from its
AgentPlayback recording and compare everything it does with what it did live (docs/playback.md).

Argument parsing and printing only; the replay is haa.lab.playback.replay.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from haactl.cliopts import err, out


def replay(
    recording: Annotated[Path, typer.Argument(help="a recording folder (haactl mission run --record DIR), one "
                                              "agent's folder or one segment file")],
    agent: Annotated[str, typer.Option("--agent", help="the agent to replay: display name (A3.1) or id")],
    instance: Annotated[int | None, typer.Option("--instance", min=1,
                                                 help="only its K-th recorded life (haactl record ls counts them; "
                                                 "default: every one, in order)")] = None,
    break_at: Annotated[int | None, typer.Option("--break-at", min=0,
                                                 help="stop in the debugger (pdb; PYTHONBREAKPOINT is not used) just "
                                                 "before input N of the first replayed instance")] = None,
) -> None:
    """Replay an agent offline; prints `replay identical: N inputs, M outputs` or the first divergence (exit 1)."""
    from haa.lab.playback.reader import RecordingError
    from haa.lab.playback.replay import replay_agent

    try:
        results = replay_agent(recording, agent, instance, break_at)
    except (RecordingError, LookupError) as e:
        why = str(e.args[0]) if isinstance(e, LookupError) and e.args else str(e)  # a KeyError quotes its text
        err.print(f"[bold red]error:[/bold red] {escape(why)}")
        raise typer.Exit(2) from None
    n_in = n_out = 0
    for k, ir in enumerate(results, start=instance or 1):
        r = ir.result
        n_in += r.inputs
        n_out += r.outputs
        cut = (f" (its recording is damaged and was read up to there: {r.damage})" if r.damage
               else " (its recording was cut: the writer died)" if r.truncated else "")
        label = f"instance {k} {ir.instance} ({ir.how or '?'} on {ir.host}, epoch {ir.epoch})"
        if r.identical:
            out.print(f"{escape(label)}: identical, {r.inputs} inputs, {r.outputs} outputs{cut}")
        else:
            out.print(f"{escape(label)}{cut}")
            out.print(escape(str(r.divergence)), soft_wrap=True)
            raise typer.Exit(1)
    out.print(f"replay identical: {n_in} inputs, {n_out} outputs")
