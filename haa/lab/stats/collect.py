"""`haactl stats collect`: one bundle per host and a cluster summary, from what every host persisted.

`collect_bundles(backend, out_dir)` reads every host's data dir — whatever the host's state: alive (the
files are read as they are; a line being written is left out), killed, paused, left, or stopped by
`cluster down` — and writes `out_dir/<host>.tar.gz` (haa.lab.stats.bundle) and `out_dir/summary.json`
(haa.lab.stats.summary). Where the data dirs are:

* local clusters (haa.cluster.local_backend): `<root>/<host>/`, recorded in the cluster's state file (also
  after `cluster down`, which keeps it as `cluster.last.json`);
* the compose cluster (haa.cluster.compose_backend): inside each container, the `--data-dir` of its service
  (`/var/lib/haa/<host>`), read through the docker SDK (`get_archive`, which works on running, paused and
  stopped containers alike); if the log file is missing there, the container's log (the host logs to
  stderr too) is used.

The agent events of every host's log are merged once for the whole cluster (haa.cluster.events.Merger), so
that each bundle's `events.jsonl` holds the events that happened on that host — a crash the group recorded
after the host died is in the dead host's bundle, with the member that reported it.

`haactl mission run -o DIR` and `haactl chaos run` call `collect_bundles` at the end (the cluster is down by
then: its data dirs remain).
"""

from __future__ import annotations

import functools
import io
import json
import re
import tarfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from haa.cluster.backend import Backend, ClusterError, HostInfo
from haa.cluster.events import Merger, TimelineEvent, parse_lines, timeline_events, view_events
from haa.hostd.sampler import CONFIG_FILE, HIST_BOUNDS_MS, OLD_STATS_FILE, STATS_FILE
from haa.lab.stats import phases
from haa.lab.stats.bundle import (
    FORMAT,
    MAX_AGENT_LOG,
    MAX_STDERR,
    SUFFIX,
    SUMMARY_FILE,
    jsonl,
    load_bundles,
    write_bundle,
)

Progress = Callable[[str], None]


@dataclass
class HostFiles:
    """The raw files of one host's data dir: `log`, `stats`, `config`, `stderr`, `agents/<id>.log`."""

    info: HostInfo
    files: dict[str, bytes] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    source: str = ""  # where they were read


@dataclass
class CollectResult:
    out_dir: Path
    bundles: list[Path] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)  # host -> what could not be read


# ---------------------------------------------------------------------------------------------- reading


def _read_file(path: Path, limit: int | None) -> bytes:
    return path.read_bytes() if limit is None else _tail(path, limit)


def _read_bytes(data: bytes, limit: int | None) -> bytes:
    return data if limit is None else data[-limit:]


def _tail(path: Path, limit: int) -> bytes:
    with open(path, "rb") as f:
        f.seek(0, 2)
        size = f.tell()
        f.seek(max(0, size - limit))
        data = f.read()
    if size > limit:  # from the first whole line
        nl = data.find(b"\n")
        data = b"[... cut ...]\n" + (data[nl + 1:] if nl >= 0 else data)
    return data


def complete_lines(data: bytes) -> bytes:
    """`data` without a last line still being written (no newline yet)."""
    if not data or data.endswith(b"\n"):
        return data
    nl = data.rfind(b"\n")
    return data[: nl + 1] if nl >= 0 else b""


def _from_dir_listing(name: str, listing: dict[str, Callable[[int | None], bytes]]) -> dict[str, bytes]:
    """The files of a data dir given as relative path -> reader(limit)."""
    out: dict[str, bytes] = {}
    if f"{name}.jsonl" in listing:
        out["log"] = complete_lines(listing[f"{name}.jsonl"](None))
    stats = b""
    for fn in (OLD_STATS_FILE, STATS_FILE):
        if fn in listing:
            stats += complete_lines(listing[fn](None))
    if stats:
        out["stats"] = stats
    if CONFIG_FILE in listing:
        out["config"] = listing[CONFIG_FILE](None)
    errs = sorted((k for k in listing if re.fullmatch(r"stderr\.\d+\.txt", k)),
                  key=lambda k: int(k.split(".")[1]))
    err = b"".join(listing[k](MAX_STDERR) for k in errs)
    if err.strip():
        out["stderr"] = err[-MAX_STDERR:]
    for k in sorted(listing):
        if k.startswith("agents/") and k.endswith(".log") and k.count("/") == 1:
            out[k] = listing[k](MAX_AGENT_LOG)
    return out


def local_data_dir(backend: Backend, name: str) -> Path | None:
    state = getattr(backend, "state", None)
    if not isinstance(state, dict):
        return None
    rec = state.get("hosts", {}).get(name)
    return Path(rec["data_dir"]) if isinstance(rec, dict) and rec.get("data_dir") else None


def read_local(d: Path, name: str) -> dict[str, bytes]:
    listing: dict[str, Callable[[int | None], bytes]] = {}
    if not d.is_dir():
        raise ClusterError(f"data dir {d} is gone")
    for p in [*d.iterdir(), *((d / "agents").iterdir() if (d / "agents").is_dir() else [])]:
        if p.is_file():
            rel = p.relative_to(d).as_posix()
            listing[rel] = functools.partial(_read_file, p)
    return _from_dir_listing(name, listing)


def compose_data_dir(backend: Backend, name: str) -> str:
    """The --data-dir of a compose service's command (default /var/lib/haa/<name>)."""
    svc = (getattr(backend, "services", None) or {}).get(name) or {}
    cmd = svc.get("command") or []
    if isinstance(cmd, str):
        cmd = cmd.split()
    for i, arg in enumerate(cmd):
        if arg == "--data-dir" and i + 1 < len(cmd):
            return str(cmd[i + 1])
        if isinstance(arg, str) and arg.startswith("--data-dir="):
            return arg.split("=", 1)[1]
    return f"/var/lib/haa/{name}"


def read_container(container: Any, data_dir: str, name: str) -> dict[str, bytes]:
    """The data dir of a container (running, paused or stopped) through the docker SDK's get_archive."""
    stream, _stat = container.get_archive(data_dir)
    buf = io.BytesIO(b"".join(stream))
    listing: dict[str, Callable[[int | None], bytes]] = {}
    with tarfile.open(fileobj=buf, mode="r:*") as tar:
        for m in tar:
            if not m.isfile():
                continue
            _, _, rel = m.name.partition("/")
            f = tar.extractfile(m)
            if f is None or not rel:
                continue
            data = f.read()
            listing[rel] = functools.partial(_read_bytes, data)
    return _from_dir_listing(name, listing)


def read_host(backend: Backend, h: HostInfo) -> HostFiles:
    """The data-dir files of one host, by whichever way this backend reaches them."""
    hf = HostFiles(h)
    d = local_data_dir(backend, h.name)
    try:
        if d is not None:
            hf.source = str(d)
            hf.files = read_local(d, h.name)
        elif hasattr(backend, "container"):
            dd = compose_data_dir(backend, h.name)
            hf.source = f"container {h.container or h.name}:{dd}"
            hf.files = read_container(backend.container(h.name), dd, h.name)
    except (ClusterError, OSError, tarfile.TarError) as e:
        hf.errors.append(f"data dir not read: {e}")
    except Exception as e:  # the docker SDK's own errors (no such container, path not found, ...)
        hf.errors.append(f"data dir not read: {type(e).__name__}: {e}")
    if "log" not in hf.files:
        try:  # e.g. a container whose data dir is not there: its log through the backend (docker logs)
            lines = [ln for _, ln in backend.log_records([h.name], follow=False)]
            if lines:
                hf.files["log"] = ("\n".join(lines) + "\n").encode()
                hf.source += " (log: backend log records)"
        except Exception as e:
            hf.errors.append(f"log not read: {type(e).__name__}: {e}")
    return hf


def backend_hosts(backend: Backend) -> tuple[Backend, list[HostInfo]]:
    """The backend's hosts; for a local cluster that `cluster down` stopped, the ones of its last state."""
    hosts = backend.hosts()
    root = getattr(backend, "root", None)
    if not hosts and root is not None:
        from haa.cluster.local_backend import LocalBackend

        last = LocalBackend(Path(root), last=True)
        return last, last.hosts()
    return backend, hosts


# ---------------------------------------------------------------------------------------------- building


def _event_json(e: TimelineEvent) -> dict[str, Any]:
    rec = {"ts": round(e.time, 6), "host": e.host or e.reporter, "agent": e.agent, "name": e.name,
           "type": e.type, "event": e.event, "detail": e.detail}
    if e.reporter and e.reporter != rec["host"]:
        rec["reporter"] = e.reporter
    return rec


def merged_events(logs: dict[str, list[dict[str, Any]]]) -> list[TimelineEvent]:
    """Agent events and view changes of every host's log, de-duplicated and attributed (haa.cluster.events)."""
    return Merger().merge(timeline_events(logs) + view_events(logs))


def _views(host: str, records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    for r in records:
        f = r.get("fields")
        if r.get("event") == "view" and isinstance(f, dict):
            out.append({"ts": r.get("ts"), "host": host, "inc": r.get("inc"), "view": f.get("view"),
                        "members": [str(m).split(".")[0] for m in f.get("members") or []],
                        "added": list(f.get("added") or []), "removed": list(f.get("removed") or [])})
    return out


def _latency(records: list[dict[str, Any]], samples: list[dict[str, Any]]) -> dict[str, Any]:
    vals = phases.host_phases(records)
    out: dict[str, Any] = {"bounds_ms": list(HIST_BOUNDS_MS)}
    for k, v in vals.items():
        out[k] = {**phases.summary(v), "values_ms": [round(x, 3) for x in v]}
    for key, name in (("p2d", "oac_propose_decide"), ("d2d", "oac_decide_deliver")):
        h: list[int] | None = None
        for s in samples:
            o = s.get("oac")
            if isinstance(o, dict) and isinstance(o.get(key), list):
                h = phases.add_hist(h, o[key])
        out[name] = phases.summary([], h)
    return out


def build_members(hf: HostFiles, events: list[TimelineEvent], backend_desc: str) -> dict[str, bytes]:
    """The members of one host's bundle (haa.lab.stats.bundle)."""
    name = hf.info.name
    log_recs = parse_lines(hf.files.get("log", b"").decode("utf-8", "replace").splitlines())
    stats_recs = parse_lines(hf.files.get("stats", b"").decode("utf-8", "replace").splitlines())
    samples = [r for r in stats_recs if r.get("kind") != "config"]
    mine = [_event_json(e) for e in events if e.agent and (e.host or e.reporter) == name]
    views = _views(name, log_recs)
    members: dict[str, bytes] = {
        "log.jsonl": hf.files.get("log", b""),
        "stats.jsonl": jsonl(stats_recs),  # the lines that parse (a killed host may have left half a line)
        "views.jsonl": jsonl(views),
        "events.jsonl": jsonl(mine),
        "latency.json": json.dumps(_latency(log_recs, samples), indent=1).encode(),
    }
    if "config" in hf.files:
        members["config.json"] = hf.files["config"]
    if "stderr" in hf.files:
        members["stderr.txt"] = hf.files["stderr"]
    for k, v in hf.files.items():
        if k.startswith("agents/"):
            members[k] = v
    ts = [float(r["ts"]) for r in (*log_recs, *samples) if isinstance(r.get("ts"), int | float)]
    incs = sorted({r["inc"] for r in (*log_recs, *samples) if isinstance(r.get("inc"), int) and r["inc"]})
    info = hf.info
    manifest = {
        "format": FORMAT, "host": name, "collected_at": round(time.time(), 3), "cluster": backend_desc,
        "state": info.state, "detail": info.detail, "address": info.address, "core": info.core,
        "source": hf.source, "errors": hf.errors, "incarnations": incs,
        "first_ts": min(ts) if ts else None, "last_ts": max(ts) if ts else None,
        # graceful leaves this host asked for (SIGTERM, `host retire`, `cluster down`): its removals that follow
        # are not faults
        "leaves": [r["ts"] for r in log_recs if r.get("event") == "leave_requested" and isinstance(r.get("ts"), float)],
        "counts": {"log_records": len(log_recs), "samples": len(samples), "events": len(mine), "views": len(views)},
        "files": {k: len(v) for k, v in members.items()},
    }
    members = {"manifest.json": json.dumps(manifest, indent=1).encode(), **members}
    return members


def collect_bundles(backend: Backend, out_dir: Path, names: list[str] | None = None,
                    progress: Progress | None = None) -> CollectResult:
    """Write `out_dir/<host>.tar.gz` for every host (or the named ones) and `out_dir/summary.json`."""
    from haa.lab.stats.summary import summarize

    say = progress or (lambda _s: None)
    backend, hosts = backend_hosts(backend)
    if names:
        known = {h.name for h in hosts}
        unknown = [n for n in names if n not in known]
        if unknown:
            raise ClusterError(f"unknown host {unknown[0]!r} in the {backend.describe()} "
                               f"(hosts: {', '.join(sorted(known)) or 'none'})")
        hosts = [h for h in hosts if h.name in names]
    if not hosts:
        raise ClusterError(f"no hosts to collect from in the {backend.describe()}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    res = CollectResult(out_dir)
    read = []
    for h in hosts:
        say(f"reading {h.name} ({h.state})")
        hf = read_host(backend, h)
        if hf.errors:
            res.errors[h.name] = "; ".join(hf.errors)
        read.append(hf)
    logs = {hf.info.name: parse_lines(hf.files.get("log", b"").decode("utf-8", "replace").splitlines())
            for hf in read}
    events = merged_events(logs)
    desc = backend.describe()
    for hf in read:
        path = out_dir / f"{hf.info.name}{SUFFIX}"
        write_bundle(path, hf.info.name, build_members(hf, events, desc))
        res.bundles.append(path)
    say("writing the cluster summary")
    only = {p.name for p in res.bundles}
    bundles = [b for b in load_bundles(out_dir) if b.path.name in only]
    res.summary = summarize(bundles, cluster=desc)
    tmp = out_dir / (SUMMARY_FILE + ".tmp")
    tmp.write_text(json.dumps(res.summary, indent=1, default=str) + "\n")
    tmp.replace(out_dir / SUMMARY_FILE)
    return res


def collect_quietly(backend: Backend, out_dir: Path) -> CollectResult | str:
    """`collect_bundles`, for the end of a run: the result, or the reason it failed (never raises)."""
    try:
        return collect_bundles(backend, out_dir)
    except ClusterError as e:
        return str(e)
    except Exception as e:  # a bundle that could not be written (disk full, ...): the run's result stands
        return f"{type(e).__name__}: {e}"
