"""`haactl ddb get|put|del|ls|watch`: inspect and write the DDB through any live host (docs/cluster.md).

Reads come from one host's replica (`--host`, default the first alive member); writes go through that
host, which proposes them to the group and replies once they are committed and applied there. `watch`
follows the host's mirror stream (thesis AgentMirror): a snapshot, then every applied batch and view change.
"""

from __future__ import annotations

import json
from typing import Annotated, Any

import grpc
import typer
from rich.markup import escape

from haa.cluster.backend import ClusterError, rpc_error_text
from haa.cluster.values import plain_value, show_bytes
from haa.core.ddb import ops as ddb
from haa.core.ddb.objects import DdbError
from haa.pb import control_pb2 as cpb
from haa.pb import ddb_pb2
from haactl.cliopts import (
    LOCAL,
    ClusterOpts,
    HostOpt,
    JsonOpt,
    cli_errors,
    cluster_options,
    out,
)
from haactl.tables import table

ddb_app = typer.Typer(help="Read, write and watch the replicated database (DDB).", no_args_is_help=True)

TYPE_NAMES = ("json", "blob", "counter", "list")


#: `ddb get` shows at most this many items of a log (the newest), each cut to LOG_ITEM_CHARS characters
LOG_SHOW_ITEMS = 10
LOG_ITEM_CHARS = 60


def show_log(value: dict[str, Any]) -> str:
    """A log's plain value -> readable lines: its index range and its newest items, cut."""
    first, items = value["first"], value["items"]
    lines = [f"log: first {first}, {len(items)} items, next {first + len(items)}"]
    if len(items) > LOG_SHOW_ITEMS:
        lines.append(f"... {len(items) - LOG_SHOW_ITEMS} older items")
    start = max(0, len(items) - LOG_SHOW_ITEMS)
    for k, item in enumerate(items[start:], start):
        text = item.replace("\n", "\\n")
        text = text if len(text) <= LOG_ITEM_CHARS else text[: LOG_ITEM_CHARS - 1] + "…"
        lines.append(f"[{first + k}] {text}")
    return "\n".join(lines)


def record_dict(r: ddb_pb2.DdbObjectRecord, keys_only: bool = False) -> dict[str, Any]:
    d: dict[str, Any] = {"key": r.key, "type": r.type, "version": r.version, "created": r.created}
    if not keys_only:
        d["value"] = plain_value(r.type, r.value)
    return d


def parse_value(type_name: str, text: str) -> Any:
    """The command-line VALUE -> the Python value `ddb.put` takes."""
    if type_name == "json":
        try:
            return json.loads(text)
        except json.JSONDecodeError as e:
            raise ClusterError(
                f"VALUE is not JSON ({e.msg}); quote a string as '\"text\"', or use --type blob for raw text"
            ) from None
    if type_name == "blob":
        return text.encode()
    if type_name == "counter":
        try:
            return int(text)
        except ValueError:
            raise ClusterError(f"a counter value is an integer, not {text!r}") from None
    try:
        items = json.loads(text)
    except json.JSONDecodeError:
        items = None
    if not isinstance(items, list) or not all(isinstance(i, str) for i in items):
        raise ClusterError('a list value is a JSON array of strings, e.g. \'["a", "b"]\'')
    return [i.encode() for i in items]


def _write(backend: Any, host: str, ops: list[Any], timeout: float) -> cpb.DdbWriteReply:
    reply: cpb.DdbWriteReply = backend.call(
        host, lambda c: c.ddb_write(ops, atomic=False, timeout=timeout), "DdbWrite", timeout=timeout
    )
    if not reply.committed:
        raise ClusterError(f"the write through {host} was not committed: {reply.reason or 'no reason given'}")
    return reply


@ddb_app.command("put")
@cli_errors
@cluster_options()
def ddb_put(
    key: Annotated[str, typer.Argument(help="object key")],
    value: Annotated[str, typer.Argument(help="value: JSON (default), text (blob), integer (counter), JSON array")],
    type_name: Annotated[str, typer.Option("--type", "-t", help="json | blob | counter | list")] = "json",
    host: HostOpt = None,
    where: ClusterOpts = LOCAL,
    timeout: Annotated[float, typer.Option("--timeout", min=0.1)] = 30.0,
    json_out: JsonOpt = False,
) -> None:
    """Create or replace one object (committed through the group before the command returns)."""
    if type_name not in TYPE_NAMES:
        raise ClusterError(f"--type must be one of {', '.join(TYPE_NAMES)}, not {type_name!r}")
    try:
        op = ddb.put(key, type_name, parse_value(type_name, value))
    except DdbError as e:
        raise ClusterError(str(e)) from None
    backend = where.backend()
    h = backend.pick_host(host)
    reply = _write(backend, h, [op], timeout)
    res = reply.results[0] if reply.results else None
    if json_out:
        print(
            json.dumps(
                {
                    "key": key,
                    "host": h,
                    "ok": bool(res and res.ok),
                    "reason": res.reason if res else "",
                    "version": res.version if res else 0,
                    "global_seq": reply.global_seq,
                    "ddb_seq": reply.ddb_seq,
                }
            )
        )
    if res is not None and not res.ok:
        raise ClusterError(f"put {key}: {res.reason}")
    if not json_out:
        version = res.version if res else reply.ddb_seq
        out.print(f"put {escape(key)} ({type_name}) via {h}: version {version}, global seq {reply.global_seq}")


@ddb_app.command("del")
@cli_errors
@cluster_options()
def ddb_del(
    keys: Annotated[list[str], typer.Argument(help="object keys")],
    host: HostOpt = None,
    where: ClusterOpts = LOCAL,
    timeout: Annotated[float, typer.Option("--timeout", min=0.1)] = 30.0,
) -> None:
    """Delete objects (one batch; each key succeeds or fails on its own)."""
    backend = where.backend()
    h = backend.pick_host(host)
    reply = _write(backend, h, [ddb.delete(k) for k in keys], timeout)
    failed = [f"{r.key}: {r.reason}" for r in reply.results if not r.ok]
    for r in reply.results:
        if r.ok:
            out.print(f"deleted {escape(r.key)}")
    if failed:
        raise ClusterError("; ".join(failed))


@ddb_app.command("get")
@cli_errors
@cluster_options()
def ddb_get(
    keys: Annotated[list[str], typer.Argument(help="object keys")],
    host: HostOpt = None,
    where: ClusterOpts = LOCAL,
    json_out: JsonOpt = False,
) -> None:
    """Read objects from one host's replica (exit code 1 if a key is missing)."""
    backend = where.backend()
    h = backend.pick_host(host)
    reply: cpb.DdbGetReply = backend.call(h, lambda c: c.ddb_get(keys=keys), "DdbGet")
    found = {r.key: r for r in reply.objects}
    missing = [k for k in keys if k not in found]
    if json_out:
        print(
            json.dumps(
                {
                    "host": h,
                    "ddb_seq": reply.ddb_seq,
                    "objects": [record_dict(r) for r in reply.objects],
                    "missing": missing,
                }
            )
        )
    else:
        t = table(["key", "type", "version", "value"], title=f"{h}: DDB #{reply.ddb_seq}")
        for k in keys:
            if k in found:
                r = found[k]
                v = record_dict(r)["value"]
                if r.type == "log" and isinstance(v, dict):
                    v = show_log(v)
                t.add_row(escape(k), r.type, str(r.version), escape(v if isinstance(v, str) else json.dumps(v)))
        out.print(t)
    if missing:
        raise ClusterError(f"not found on {h}: {', '.join(missing)}")


@ddb_app.command("ls")
@cli_errors
@cluster_options()
def ddb_ls(
    prefix: Annotated[str, typer.Argument(help="key prefix")] = "",
    host: HostOpt = None,
    where: ClusterOpts = LOCAL,
    limit: Annotated[int, typer.Option("--limit", min=0, help="at most this many (0 = all)")] = 0,
    values: Annotated[bool, typer.Option("--values", "-v", help="show values too")] = False,
    json_out: JsonOpt = False,
) -> None:
    """List the keys under a prefix (type, version; values with -v)."""
    backend = where.backend()
    h = backend.pick_host(host)
    reply: cpb.DdbGetReply = backend.call(
        h, lambda c: c.ddb_get(prefix=prefix, keys_only=not values, limit=limit), "DdbGet"
    )
    recs = [record_dict(r, keys_only=not values) for r in reply.objects]
    if json_out:
        print(
            json.dumps(
                {
                    "host": h,
                    "ddb_seq": reply.ddb_seq,
                    "ddb_hash": reply.ddb_hash,
                    "truncated": reply.truncated,
                    "objects": recs,
                }
            )
        )
        return
    t = table(
        ["key", "type", "version", *(["value"] if values else [])],
        title=f"{h}: {len(recs)} objects under {prefix!r} (DDB #{reply.ddb_seq}, hash {reply.ddb_hash[:12]})",
    )
    for r in recs:
        cells = [escape(r["key"]), r["type"], str(r["version"])]
        if values:
            v = r["value"]
            cells.append(escape(v if isinstance(v, str) else json.dumps(v)))
        t.add_row(*cells)
    out.print(t)
    if reply.truncated:
        out.print(f"[dim](more than {limit}; raise --limit)[/]")


def op_event(op: ddb_pb2.DdbOp) -> dict[str, Any]:
    kind = op.WhichOneof("op")
    body = getattr(op, kind)
    ev: dict[str, Any] = {"op": kind, "key": body.key}
    if kind in ("put", "cas"):
        ev["type"] = body.type
        ev["value"] = plain_value(body.type, body.value)
        if kind == "cas":
            ev["expected_version"] = body.expected_version
    elif kind == "append":
        ev["item"] = show_bytes(body.item)
    elif kind == "add":
        ev["delta"] = body.delta
    elif kind == "log_append":
        ev["items"] = [show_bytes(i) for i in body.items]
    elif kind == "log_trim":
        ev["upto"] = body.upto
    return ev


def mirror_events(ev: cpb.MirrorEvent, prefix: str) -> list[dict[str, Any]]:
    """One mirror event -> the printable events under `prefix` (a batch gives one per matching op)."""
    kind = ev.WhichOneof("event")
    if kind == "snapshot":
        objs = [o for o in ev.snapshot.objects if o.key.startswith(prefix)]
        return [{"event": "snapshot", "ddb_seq": ev.snapshot.seq, "objects": len(objs), "ddb_hash": ev.ddb_hash}]
    if kind == "batch":
        try:
            batch = ddb_pb2.DdbBatch.FromString(ev.batch.payload)
        except Exception:
            return [{"event": "batch", "ddb_seq": ev.batch.ddb_seq, "error": "undecodable batch"}]
        return [
            {
                "event": "write",
                "ddb_seq": ev.batch.ddb_seq,
                "global_seq": ev.batch.global_seq,
                "origin": batch.origin,
                **op_event(op),
            }
            for op in batch.ops
            if getattr(op, op.WhichOneof("op")).key.startswith(prefix)
        ]
    if kind == "view":
        v = ev.view
        return [
            {
                "event": "view",
                "view": v.view,
                "global_seq": v.global_seq,
                "leader": v.leader,
                "members": [m.name for m in v.members],
                "added": list(v.added),
                "removed": list(v.removed),
            }
        ]
    return []


def show_event(e: dict[str, Any]) -> str:
    kind = e["event"]
    if kind == "snapshot":
        return f"[cyan]snapshot[/] at DDB #{e['ddb_seq']}: {e['objects']} objects, hash {e['ddb_hash'][:12]}"
    if kind == "view":
        change = " ".join([*(f"[green]+{a}[/]" for a in e["added"]), *(f"[red]-{r}[/]" for r in e["removed"])])
        return f"[magenta]view {e['view']}[/] {change} members {' '.join(e['members'])}, leader {e['leader']}"
    if "error" in e:
        return f"[red]#{e['ddb_seq']} {e['error']}[/]"
    tail = ""
    if "value" in e:
        v = e["value"]
        tail = f" = {escape(v if isinstance(v, str) else json.dumps(v))} ({e['type']})"
    elif "item" in e:
        tail = f" += {escape(e['item'])}"
    elif "delta" in e:
        tail = f" {e['delta']:+d}"
    elif "items" in e:
        tail = f" += {len(e['items'])} item(s)"
    elif "upto" in e:
        tail = f" below {e['upto']}"
    origin = f" [dim]from {escape(e['origin'])}[/]" if e.get("origin") else ""
    return f"#{e['ddb_seq']} [bold]{e['op']}[/] {escape(e['key'])}{tail}{origin}"


@ddb_app.command("watch")
@cli_errors
@cluster_options()
def ddb_watch(
    prefix: Annotated[str, typer.Argument(help="only keys with this prefix")] = "",
    host: HostOpt = None,
    where: ClusterOpts = LOCAL,
    views: Annotated[bool, typer.Option("--views/--no-views", help="also show view changes")] = True,
    count: Annotated[int, typer.Option("--count", min=0, help="stop after this many events (0 = Ctrl-C)")] = 0,
    json_out: Annotated[bool, typer.Option("--json", help="one JSON object per event")] = False,
) -> None:
    """Follow the mirror stream of one host: a snapshot, then every write (and view change) until Ctrl-C."""
    backend = where.backend()
    h = backend.pick_host(host)
    c = backend.client(h, timeout=None)
    stream = c.mirror(views=views)
    printed = 0
    try:
        for ev in stream:
            for e in mirror_events(ev, prefix):
                if json_out:
                    print(json.dumps({"host": h, **e}), flush=True)
                else:
                    out.print(show_event(e))
                printed += 1
                if count and printed >= count:
                    return
        raise ClusterError(f"{h} ended the mirror stream (the host stopped?)")
    except grpc.RpcError as e:
        if e.code() == grpc.StatusCode.CANCELLED:
            return
        raise ClusterError(rpc_error_text(h, c.address, e, "Mirror")) from None
    except KeyboardInterrupt:
        return
    finally:
        stream.cancel()
        c.close()
