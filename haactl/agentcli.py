"""`haactl agent list|tree|spawn|kill|move|remove|events` and `haactl alloc status|pause|resume|run`.

The operator commands of the agent layer (issue 4 §5), written like `haactl ddb`: the cluster is the local
one (`--root`) or, with `--compose`, the docker compose cluster (`haactl.cliopts.ClusterOpts`), and
commands that change something go through one alive member (`--host`, default the first one).

What each host can tell (haa.hostd.agentcontrol): the replicated agent table (the same on every member, up
to the last few commits) and, for the instances it runs or prepares, their local phase (claiming, thawing,
recovering, active, freezing), measured CPU and pid. So the reading commands ask *every* alive host and
merge (`merge_agents`): an agent's state is the local phase of the host that runs or prepares it where one
reports it (a "recovering" of a never-started agent, life 0 or 1, is shown as "spawning", "claiming" as "thawing"), else
its table status (new, active, freezing, frozen, crashed); its host is that host, else the table owner.

`agent events` merges the allocation timelines of every host into one time-ordered transcript in the style of
the thesis' Fig. 7.1-3 ("00:51 A1 (counter) freezing on h4", "00:53 A1 (counter) thawed by h3"): what every
host persisted (its log: also hosts that were killed or stopped, and the lives before a restart), then with
`-f` the live `AgentEvents` streams of the alive hosts. `haa.cluster.feed.EventFeed` does the merging (`haactl
demo` prints it too); reading and attributing the records is haa.cluster.events. Events that every member
reports once for the same table change (created, removed, crashed by a host's removal) are shown once, a crash
that another host reported on the host that ran the agent ("A1 (counter) crashed on h10 (reported by h1)").
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable
from dataclasses import asdict
from typing import Annotated, Any

import grpc
import typer
from rich.markup import escape
from rich.table import Table
from rich.tree import Tree

from haa.cluster.agents import (
    AgentRow,
    active_row,
    agent_lists,
    answering,
    merge_agents,
    wait_rows,
)
from haa.cluster.backend import Backend, ClusterError, agreed_group, natural_key
from haa.cluster.events import TimelineEvent
from haa.cluster.feed import EventFeed
from haa.pb import control_pb2 as cpb
from haa.sdk.base import RECOVERY_STRATEGIES
from haactl.cliopts import (
    LOCAL,
    ClusterOpts,
    HostOpt,
    JsonOpt,
    cli_errors,
    cluster_options,
    err,
    out,
)
from haactl.tables import table

agent_app = typer.Typer(
    help="List, spawn, kill, move and remove agents; follow the allocation timeline.", no_args_is_help=True
)
alloc_app = typer.Typer(
    help="The agent allocation: status, pause/resume the periodic rebalancing, run a session now.",
    no_args_is_help=True,
)

WaitTimeoutOpt = Annotated[float, typer.Option("--timeout", min=0.5, help="seconds to wait")]

STATE_STYLE = {"active": "green", "spawning": "cyan", "thawing": "cyan", "recovering": "magenta",
               "freezing": "yellow", "frozen": "yellow", "crashed": "red", "new": "dim", "failed": "bold red"}


# ---------------------------------------------------------------------------------------------- reading




def resolve(rows: Iterable[AgentRow], ref: str) -> AgentRow:
    """An agent by id, display name or unique id prefix (>= 4 characters), like the hosts resolve it."""
    rows = list(rows)
    for r in rows:
        if ref in (r.id, r.name):
            return r
    hits = [r for r in rows if len(ref) >= 4 and r.id.startswith(ref)]
    if len(hits) == 1:
        return hits[0]
    if len(hits) > 1:
        raise ClusterError(f"agent id prefix {ref!r} is ambiguous ({', '.join(r.name for r in hits)})")
    known = ", ".join(r.name for r in rows[:12]) + (" ..." if len(rows) > 12 else "")
    raise ClusterError(f"unknown agent {ref!r} (agents: {known or 'none'})")


def row_json(r: AgentRow) -> dict[str, Any]:
    d = asdict(r)
    d["cpu"] = round(r.cpu, 4)
    return d


def where(r: AgentRow) -> str:
    """The host column: the running host, or for a frozen/new/crashed agent where the allocation puts it."""
    if r.state in ("frozen", "new", "crashed") and r.alloc and r.alloc != r.host:
        return f"{r.host or '-'} → {r.alloc}"
    return r.host or "-"


def agent_table(rows: list[AgentRow], title: str) -> Table:
    t = table(["name", "id", "type", "state", "host", "cpu %", "parent", "epoch", "backup"], title=title,
              right=["cpu %", "epoch"])
    for r in rows:
        t.add_row(
            r.name, r.id[:8], escape(r.type), f"[{STATE_STYLE.get(r.state, 'white')}]{r.state}[/]", where(r),
            f"{100 * r.cpu:.1f}", r.parent or "-", str(r.epoch),
            "yes" if r.backup else ("-" if r.recovery == "backup" else f"- ({r.recovery})"),
        )
    return t


def warn_unanswered(replies: dict[str, Any]) -> None:
    for n, r in replies.items():
        if not isinstance(r, cpb.AgentListReply):
            code = r.code().name if isinstance(r, grpc.RpcError) else type(r).__name__
            err.print(f"[yellow]warning:[/] {n} did not answer ({code}); its local phases are missing")


@agent_app.command("list")
@cli_errors
@cluster_options()
def agent_list(
    where: ClusterOpts = LOCAL,
    json_out: JsonOpt = False,
) -> None:
    """Every agent: name, id prefix, type, state, host, CPU, parent, epoch, backup (merged from every host)."""
    backend = where.backend()
    replies = agent_lists(backend)
    ok = answering(backend, replies)
    rows = merge_agents(ok)
    if json_out:
        print(json.dumps({"hosts": sorted(ok, key=natural_key),
                          "unanswered": sorted(set(replies) - set(ok), key=natural_key),
                          "agents": [row_json(r) for r in rows]}))
        return
    warn_unanswered(replies)
    out.print(agent_table(rows, f"{len(rows)} agents ({len(ok)} hosts answered)"))
    for r in rows:
        if r.state == "failed":  # not recovered any more: say why, and how to retry
            out.print(f"[bold red]{r.name} failed[/] after {r.failures} start failures: {escape(r.fail_reason)} "
                      f"(retry: haactl agent move {r.name} <host>)")
        elif r.waiting:  # allocated nowhere and nothing will change that by itself: say why
            out.print(f"[yellow]{r.name} waits:[/] {escape(r.waiting)}")


@agent_app.command("tree")
@cli_errors
@cluster_options()
def agent_tree(
    where: ClusterOpts = LOCAL,
) -> None:
    """The parentage tree (A1 -> A1.1 -> A1.1.1), each agent with its type, state and host."""
    backend = where.backend()
    replies = agent_lists(backend)
    rows = merge_agents(answering(backend, replies))
    warn_unanswered(replies)
    out.print(build_tree(rows))


def build_tree(rows: list[AgentRow]) -> Tree:
    ids = {r.id for r in rows}
    tree = Tree(f"[bold]{len(rows)} agents[/]")
    children: dict[str, list[AgentRow]] = {}
    for r in rows:
        children.setdefault(r.parent_id if r.parent_id in ids else "", []).append(r)

    def label(r: AgentRow) -> str:
        style = STATE_STYLE.get(r.state, "white")
        orphan = " [dim](parent gone)[/]" if r.parent_id and r.parent_id not in ids else ""
        return f"[bold]{r.name}[/] ({escape(r.type)}) [{style}]{r.state}[/] on {where(r)}{orphan}"

    def add(node: Tree, parent: str, seen: set[str]) -> None:
        for r in children.get(parent, []):
            if r.id in seen:  # a cycle cannot happen (a parent exists before its child); be safe anyway
                continue
            add(node.add(label(r)), r.id, seen | {r.id})

    add(tree, "", set())
    return tree


# ---------------------------------------------------------------------------------------------- changing


def load_rows(backend: Backend) -> tuple[dict[str, cpb.AgentListReply], list[AgentRow]]:
    ok = answering(backend, agent_lists(backend))
    return ok, merge_agents(ok)






def parse_config(text: str) -> bytes:
    if not text:
        return b""
    try:
        json.loads(text)
    except json.JSONDecodeError as e:
        raise ClusterError(f"--config is not JSON ({e.msg} at column {e.colno}): {text[:60]!r}") from None
    return text.encode()


@agent_app.command("spawn")
@cli_errors
@cluster_options()
def agent_spawn(
    type_name: Annotated[str, typer.Argument(metavar="TYPE", help="a registered agent type (counter, probe, ...)")],
    config: Annotated[str, typer.Option("--config", "-c", help="the agent's config, JSON")] = "",
    parent: Annotated[str, typer.Option("--parent", help="parent agent (name, id or id prefix)")] = "",
    recovery: Annotated[str, typer.Option("--recovery", help="backup | restart | none (default: the type's)")] = "",
    hardware: Annotated[str, typer.Option("--hardware", help="required hardware, comma separated")] = "",
    host: HostOpt = None,
    where: ClusterOpts = LOCAL,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="wait until it is active on some host")] = True,
    timeout: WaitTimeoutOpt = 30.0,
    json_out: JsonOpt = False,
) -> None:
    """Create an agent of a registered type; the allocation places it (committed before the command returns)."""
    if recovery and recovery not in RECOVERY_STRATEGIES:
        raise ClusterError(f"--recovery must be one of {', '.join(sorted(RECOVERY_STRATEGIES))}, not {recovery!r}")
    hw = tuple(h.strip() for h in hardware.split(",") if h.strip())
    cfg = parse_config(config)
    backend = where.backend()
    h = backend.pick_host(host)
    t0 = time.monotonic()
    reply: cpb.AgentOpReply = backend.call(
        h, lambda c: c.agent_spawn(type_name, cfg, parent=parent, recovery=recovery, hardware=hw, timeout=timeout),
        "AgentSpawn", timeout=timeout,
    )
    if not reply.ok:
        raise ClusterError(f"spawn {type_name}: {reply.reason}")
    row = None
    if wait:
        def up_or_failed(rows: list[AgentRow]) -> AgentRow | None:
            return active_row(rows, reply.id) or next((r for r in rows if r.id == reply.id and r.state == "failed"),
                                                      None)

        row = wait_rows(backend, up_or_failed, timeout, f"{reply.name} to become active")
        if row.state == "failed":  # committed, but it could not start (its type's start raised, ...)
            raise ClusterError(f"spawn {type_name}: {reply.name} failed after {row.failures} start failures: "
                               f"{row.fail_reason}")
    took = time.monotonic() - t0
    if json_out:
        print(json.dumps({"ok": True, "id": reply.id, "name": reply.name, "via": h,
                          "host": row.host if row else "", "seconds": round(took, 3)}))
        return
    tail = f": active on {row.host} after {took:.2f} s" if row else ""
    out.print(f"spawned {reply.name} ({type_name}, id {reply.id}) via {h}{tail}")


@agent_app.command("kill")
@cli_errors
@cluster_options()
def agent_kill(
    ref: Annotated[str, typer.Argument(help="agent name (A1.2), id or id prefix")],
    where: ClusterOpts = LOCAL,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="wait until the group has recovered it")] = True,
    timeout: WaitTimeoutOpt = 30.0,
) -> None:
    """SIGKILL the agent's process on the host running it: an agent failure that the group recovers (Alg. 8)."""
    backend = where.backend()
    _, rows = load_rows(backend)
    r = resolve(rows, ref)
    owner = next((h for h, p in r.phases.items() if p == "active"), r.owner)
    if not owner:
        raise ClusterError(f"{r.name} runs nowhere now (state {r.state}): nothing to kill")
    t0 = time.monotonic()
    reply: cpb.AgentOpReply = backend.call(owner, lambda c: c.agent_kill(r.id), "AgentKill")
    if not reply.ok and reply.owner and reply.owner != owner:  # it moved meanwhile: ask its owner once
        if reply.owner not in {h.name for h in backend.hosts()}:
            raise ClusterError(f"kill {r.name}: {reply.reason}")
        owner = reply.owner
        reply = backend.call(owner, lambda c: c.agent_kill(r.id), "AgentKill")
    if not reply.ok:
        raise ClusterError(f"kill {r.name} on {owner}: {reply.reason}")
    out.print(f"killed {r.name} on {owner} (SIGKILL{f' of pid {r.pid}' if r.pid else ''})")
    if not wait:
        return
    if r.recovery == "none":
        out.print(f"{r.name} has recovery strategy 'none': it is not recovered")
        return
    row = wait_rows(backend, lambda rows: active_row(rows, r.id, min_epoch=r.epoch + 1), timeout,
                    f"{r.name} to be recovered")
    out.print(f"{r.name} recovered on {row.host} (epoch {row.epoch}) {time.monotonic() - t0:.2f} s after the kill")


@agent_app.command("move")
@cli_errors
@cluster_options()
def agent_move(
    ref: Annotated[str, typer.Argument(help="agent name (A1.2), id or id prefix")],
    to: Annotated[str, typer.Argument(metavar="HOST", help="destination host (a member)")],
    host: HostOpt = None,
    where: ClusterOpts = LOCAL,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="wait until it is active there")] = True,
    timeout: WaitTimeoutOpt = 30.0,
) -> None:
    """Allocate an agent to HOST (until the next allocation session): frozen where it runs, thawed there."""
    backend = where.backend()
    backend.host(to)  # unknown host names get the list of hosts
    h = backend.pick_host(host)
    t0 = time.monotonic()
    reply: cpb.AgentOpReply = backend.call(h, lambda c: c.agent_move(ref, to, timeout=timeout), "AgentMove",
                                           timeout=timeout)
    if not reply.ok:
        if reply.reason == "unknown agent":
            _, rows = load_rows(backend)
            resolve(rows, ref)  # raises with the list of agents
        raise ClusterError(f"move {reply.name or ref} to {to}: {reply.reason}")
    if not wait:
        out.print(f"{reply.name} allocated to {to}")
        return
    wait_rows(backend, lambda rows: active_row(rows, reply.id, host=to), timeout, f"{reply.name} to be active on {to}")
    out.print(f"{reply.name} moved to {to} in {time.monotonic() - t0:.2f} s")


@agent_app.command("remove")
@cli_errors
@cluster_options()
def agent_remove(
    ref: Annotated[str, typer.Argument(help="agent name (A1.2), id or id prefix")],
    host: HostOpt = None,
    where: ClusterOpts = LOCAL,
    timeout: WaitTimeoutOpt = 30.0,
) -> None:
    """End an agent for good (its process is stopped; its children stay)."""
    backend = where.backend()
    h = backend.pick_host(host)
    reply: cpb.AgentOpReply = backend.call(h, lambda c: c.agent_remove(ref, timeout=timeout), "AgentRemove",
                                           timeout=timeout)
    if not reply.ok:
        if reply.reason == "unknown agent":
            _, rows = load_rows(backend)
            resolve(rows, ref)
        raise ClusterError(f"remove {reply.name or ref}: {reply.reason}")
    out.print(f"removed {reply.name or ref}")


@agent_app.command("request")
@cli_errors
@cluster_options()
def agent_request(
    ref: Annotated[str, typer.Argument(help="agent name (A1.2), id or id prefix")],
    payload: Annotated[str, typer.Argument(help="the request (text, given to the agent's on_request)")],
    host: HostOpt = None,
    where: ClusterOpts = LOCAL,
    timeout: WaitTimeoutOpt = 10.0,
) -> None:
    """Send an operator request to an agent and print its reply (e.g. `agent request A1 stats` for a counter).
    The reply comes back through the host asked, wherever the agent runs."""
    backend = where.backend()
    h = backend.pick_host(host)
    reply: cpb.AgentRequestReply = backend.call(
        h, lambda c: c.agent_request(ref, payload.encode(), timeout=timeout), "AgentRequest", timeout=timeout + 5
    )
    if not reply.ok:
        raise ClusterError(f"request to {ref}: {reply.error}")
    try:
        out.print(reply.payload.decode())
    except UnicodeDecodeError:
        out.print(f"{len(reply.payload)} bytes: {reply.payload[:64].hex()}...")


# ---------------------------------------------------------------------------------------------- timeline



EVENT_STYLE = {"freezing": "yellow", "frozen": "yellow", "thawing": "cyan", "thawed": "green", "active": "green",
               "spawning": "cyan", "crashed": "bold red", "recovering": "magenta", "recovered": "green",
               "removed": "dim", "created": "white", "backoff": "red", "failed": "bold red"}


def event_line(e: TimelineEvent, t0: float, absolute: bool = False) -> str:
    """The rich-markup transcript line of an event."""
    if not e.agent and e.event == "operator":
        return f"[dim]{e.clock(t0, absolute)}[/] [bold]▶ {escape(e.text)}[/]"
    if not e.agent and e.event == "note":
        return f"      [dim]{escape(e.text)}[/]"
    style = "bold blue" if not e.agent else EVENT_STYLE.get(e.event, "white")
    return f"[dim]{e.clock(t0, absolute)}[/] [{style}]{escape(e.text)}[/]"


def event_json(e: TimelineEvent, t0: float) -> dict[str, Any]:
    return {"time": e.time, "clock": e.clock(t0), "agent": e.agent, "name": e.name, "type": e.type,
            "event": e.event, "host": e.host, "reporter": e.reporter, "detail": e.detail, "text": e.text}


@agent_app.command("events")
@cli_errors
@cluster_options()
def agent_events(
    follow: Annotated[bool, typer.Option("--follow", "-f", help="keep following new events until Ctrl-C")] = False,
    where: ClusterOpts = LOCAL,
    absolute: Annotated[bool, typer.Option("--clock", help="wall-clock times instead of mm:ss")] = False,
    count: Annotated[int, typer.Option("--count", min=0, help="stop after this many lines (0 = no limit)")] = 0,
    json_out: Annotated[bool, typer.Option("--json", help="one JSON object per event")] = False,
) -> None:
    """The allocation timeline of the whole cluster (every host's events, merged, Fig. 7.1-3 style).

    Read from what every host persisted — its log in its data dir (compose: the container's log) — so hosts
    that were killed or stopped and the lives of restarted hosts are in it; every line names the host where it
    happened (a crash that another host reported says which). Times are mm:ss since the first line. With -f,
    new events follow as they happen (the alive hosts' AgentEvents streams), with hosts joining and leaving
    the group. Without -f it also works on the cluster that `cluster down` stopped (its logs are kept)."""
    backend = where.backend(last=not follow)
    backend.require_hosts()
    feed = EventFeed(backend, views=True)
    feed.load_persisted()
    for h, why in sorted(feed.unreadable.items()):
        err.print(f"[yellow]warning:[/] the log of {h} could not be read ({escape(why)}); its events are missing")
    if follow and not feed.start():
        raise ClusterError(f"no host is alive in the {backend.describe()}")
    printed = 0
    t0 = 0.0
    try:
        while True:
            evs = feed.poll(0.1, flush=not follow)
            failed = [h for h, why in feed.ended.items() if why == "UNAUTHENTICATED"]
            if failed:
                h = failed[0]
                raise ClusterError(f"host {h} ({backend.host(h).address}) rejected the cluster token")
            for e in evs:
                if not t0:
                    t0 = e.time
                if json_out:
                    print(json.dumps(event_json(e, t0)), flush=True)
                else:
                    out.print(event_line(e, t0, absolute))
                printed += 1
                if count and printed >= count:
                    return
            if not follow:
                if not printed and not json_out:
                    out.print("[dim](no agent events yet)[/]")
                return
    except KeyboardInterrupt:
        return
    finally:
        feed.close()


# ---------------------------------------------------------------------------------------------- alloc


def alloc_summary(reply: cpb.AgentListReply, rows: list[AgentRow]) -> dict[str, Any]:
    load: dict[str, dict[str, Any]] = {}
    for r in rows:
        if r.host and r.state in ("active", "freezing", "thawing", "recovering", "spawning"):
            d = load.setdefault(r.host, {"agents": 0, "cpu": 0.0})
            d["agents"] += 1
            d["cpu"] = round(d["cpu"] + r.cpu, 4)
    pending = [r.name for r in rows if r.alloc and r.alloc != r.host]
    return {"via": reply.host, "session": reply.session, "finished_session": reply.finished_session,
            "paused": reply.paused, "agent_types": list(reply.agent_types),
            "load": dict(sorted(load.items(), key=lambda kv: natural_key(kv[0]))),
            "to_move": pending, "agents": [row_json(r) for r in rows]}


def print_alloc(s: dict[str, Any], rows: list[AgentRow]) -> None:
    state = "[yellow]paused[/]" if s["paused"] else "[green]running[/]"
    sess = f"session {s['session']}" + ("" if s["finished_session"] >= s["session"] else " (in progress)")
    out.print(f"allocation {state}: last {sess}; via {s['via']}; agent types: {', '.join(s['agent_types'])}")
    if s["load"]:
        out.print("load: " + ", ".join(f"{h} {d['agents']} agents {100 * d['cpu']:.1f}% cpu"
                                       for h, d in s["load"].items()))
    if s["to_move"]:
        out.print(f"allocated elsewhere, not moved yet: {', '.join(s['to_move'])}")
    out.print(agent_table(rows, f"{len(rows)} agents"))


def leader_of(backend: Backend) -> str:
    """The leader of the group as the most advanced member sees it (it runs the allocation sessions)."""
    backend.require_hosts()
    replies = backend.statuses()
    backend.check_token(replies)
    _, leader, _ = agreed_group({n: r for n, r in replies.items() if isinstance(r, cpb.StatusReply)})
    if not leader:
        raise ClusterError(f"no group has formed in the {backend.describe()} (no member answers)")
    return leader


def _alloc(action: str, host: str | None, where: ClusterOpts, timeout: float) -> tuple[Backend, cpb.AgentListReply]:
    backend = where.backend()
    h = backend.pick_host(host)
    reply = backend.call(h, lambda c: c.alloc(action, timeout=timeout), f"Alloc({action})", timeout=timeout)
    return backend, reply


@alloc_app.command("status")
@cli_errors
@cluster_options()
def alloc_status(
    host: HostOpt = None,
    where: ClusterOpts = LOCAL,
    json_out: JsonOpt = False,
) -> None:
    """Session ids, paused or not, load per host and every agent's host, state, CPU and parent."""
    backend, reply = _alloc("status", host, where, 10.0)
    rows = merge_agents(answering(backend, agent_lists(backend)))
    s = alloc_summary(reply, rows)
    if json_out:
        print(json.dumps(s))
        return
    print_alloc(s, rows)


@alloc_app.command("pause")
@cli_errors
@cluster_options()
def alloc_pause(
    host: HostOpt = None,
    where: ClusterOpts = LOCAL,
) -> None:
    """Pause the periodic rebalancing (membership and agent-list changes still start sessions)."""
    _, reply = _alloc("pause", host, where, 15.0)
    out.print(f"allocation paused (committed via {reply.host}; last session {reply.session})")


@alloc_app.command("resume")
@cli_errors
@cluster_options()
def alloc_resume(
    host: HostOpt = None,
    where: ClusterOpts = LOCAL,
) -> None:
    """Resume the periodic rebalancing."""
    _, reply = _alloc("resume", host, where, 15.0)
    out.print(f"allocation resumed (committed via {reply.host}; last session {reply.session})")


@alloc_app.command("run")
@cli_errors
@cluster_options()
def alloc_run(
    host: HostOpt = None,
    where: ClusterOpts = LOCAL,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="wait until the session has finished")] = True,
    timeout: WaitTimeoutOpt = 30.0,
) -> None:
    """Start an allocation session now (Alg. 4; the group's leader starts sessions, so it is asked unless --host
    says otherwise); with --wait report the agents it moved."""
    backend = where.backend()
    h = host or leader_of(backend)
    before = backend.call(h, lambda c: c.alloc("status", timeout=timeout), "Alloc(status)", timeout=timeout)
    rows0 = {r.id: r for r in merge_agents(answering(backend, agent_lists(backend)))}
    t0 = time.monotonic()
    backend.call(h, lambda c: c.alloc("run", timeout=timeout), "Alloc(run)", timeout=timeout)
    if not wait:
        out.print(f"allocation session requested via {h} (last session {before.session})")
        return
    deadline = t0 + timeout
    while True:
        r = backend.call(h, lambda c: c.alloc("status", timeout=timeout), "Alloc(status)", timeout=timeout)
        if r.session > before.session and r.finished_session >= r.session:
            break
        if time.monotonic() > deadline:
            raise ClusterError(f"no allocation session finished within {timeout:g} s (last {r.session}, "
                               f"finished {r.finished_session})")
        time.sleep(0.1)
    rows = merge_agents(answering(backend, agent_lists(backend)))
    moves = [f"{x.name} {rows0[x.id].host or '-'}→{x.alloc}" for x in rows
             if x.id in rows0 and x.alloc and x.alloc != rows0[x.id].host]
    out.print(f"allocation session {r.session} finished in {time.monotonic() - t0:.2f} s: "
              + (f"{len(moves)} agents to move ({', '.join(moves)})" if moves else "no agent moves"))
