"""Per-host stats bundles: what one is made of, writing one, reading one back (docs/stats.md).

A bundle `DIR/<host>.tar.gz` holds, under `<host>/`:

    manifest.json   host, state at collection (alive, killed, ...), when, from which cluster, the files and
                    their sizes, counts (samples, log records, events, views), time range, incarnations,
                    anything that could not be read (`errors`)
    log.jsonl       the host's JSON-lines log as persisted in its data dir (every line names the host)
    stats.jsonl     the sampler's time series (haa.hostd.sampler; the rotated stats.1.jsonl first)
    config.json     the host's settings (the token left out), as the sampler wrote them at start
    views.jsonl     the host's view history: one line per view it installed (ts, host, view, members, added,
                    removed)
    events.jsonl    the agent events that happened on this host, from the merged timeline of every host's
                    log (haa.cluster.events): a crash the group recorded is here, on the host that ran the
                    agent, with `reporter` the host that logged it
    latency.json    histograms (bounds in ms: haa.hostd.sampler.HIST_BOUNDS_MS) and raw values (ms) of the
                    phases this host timed: spawn, freeze, thaw, recover, allocation (leader only), OAC
                    propose->decide and decide->deliver (from the samples)
    agents/<id>.log the agent processes' own logs (the last MAX_AGENT_LOG bytes of each)
    stderr.txt      the host process's stderr (the last MAX_STDERR bytes)

`read_bundle(path)` gives a `Bundle`; `load_bundles(dir)` every bundle of a directory. Anything wrong — no
such directory, no bundle in it, a file that is not a gzip'd tar, a bundle without its manifest, a line
that is not JSON in a JSON-lines member — raises `BundleError` with one line naming the file and the reason
(a broken line is skipped silently only in log.jsonl, where a host's stderr may have left a traceback).
"""

from __future__ import annotations

import io
import json
import tarfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from haa.cluster.backend import natural_key
from haa.files import FileError, check_regular, read_text

FORMAT = 1
SUFFIX = ".tar.gz"
SUMMARY_FILE = "summary.json"
#: the last this many bytes of each agent log and of the host's stderr go into the bundle
MAX_AGENT_LOG = 1 << 20
MAX_STDERR = 256 << 10
#: what reading one bundle may take (a bundle is ours, but it may be damaged or not ours at all: a 1 MB file
#: can expand to gigabytes). A member, its JSON lines parsed, takes ~10x its bytes in Python objects, so 64 MiB
#: keeps one under a GiB; a host's log of a day-long run is ~20-40 MiB
MAX_MEMBER = 64 << 20
#: ... all members together (decompressed, the skipped ones included), and how many
MAX_BUNDLE_BYTES = 256 << 20
MAX_MEMBERS = 4096
#: JSON lines in one member (real lines are 100-300 bytes; a member of tiny lines would make tens of millions of
#: objects out of MAX_MEMBER bytes)
MAX_LINES = 2_000_000
#: the cluster summary (summary.json) `read_summary` reads
MAX_SUMMARY = 16 << 20


class BundleError(Exception):
    """A bundle or bundle directory that cannot be used; `str()` is one line."""


def jsonl(records: list[dict[str, Any]]) -> bytes:
    return "".join(json.dumps(r, separators=(",", ":"), default=str) + "\n" for r in records).encode()


def write_bundle(path: Path, host: str, members: dict[str, bytes], mtime: float | None = None) -> None:
    """Write `members` (name inside `<host>/` -> content) as `path` (a .tar.gz), atomically."""
    tmp = path.with_name(path.name + ".tmp")
    t = mtime if mtime is not None else time.time()
    with tarfile.open(tmp, "w:gz", compresslevel=6) as tar:
        for name, data in members.items():
            info = tarfile.TarInfo(f"{host}/{name}")
            info.size = len(data)
            info.mtime = int(t)
            info.mode = 0o644
            tar.addfile(info, io.BytesIO(data))
    tmp.replace(path)


def _parse_jsonl(text: str, where: str, strict: bool) -> list[dict[str, Any]]:
    out = []
    if text.count("\n") > MAX_LINES:
        raise BundleError(f"{where}: more than {MAX_LINES:,} lines (MAX_LINES)")
    for i, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line:
            continue
        try:
            obj = json.loads(line)
        except ValueError:
            if strict:
                raise BundleError(f"{where}: line {i} is not JSON") from None
            continue
        if isinstance(obj, dict):
            out.append(obj)
        elif strict:
            raise BundleError(f"{where}: line {i} is not a JSON object")
    return out


@dataclass
class Bundle:
    """One host's bundle, read."""

    path: Path
    host: str
    manifest: dict[str, Any]
    files: dict[str, bytes] = field(repr=False)

    def text(self, name: str) -> str:
        return self.files.get(name, b"").decode("utf-8", "replace")

    def records(self, name: str) -> list[dict[str, Any]]:
        """The JSON objects of a JSON-lines member (log.jsonl: lines that are not JSON are skipped)."""
        return _parse_jsonl(self.text(name), f"{self.path}: {self.host}/{name}", strict=name != "log.jsonl")

    def json(self, name: str, default: Any = None) -> Any:
        if name not in self.files:
            return default
        try:
            return json.loads(self.files[name])
        except ValueError:
            raise BundleError(f"{self.path}: {self.host}/{name} is not JSON") from None

    @property
    def samples(self) -> list[dict[str, Any]]:
        """The sampler's samples (the config lines left out), in file order."""
        return [r for r in self.records("stats.jsonl") if r.get("kind") != "config"]

    @property
    def log(self) -> list[dict[str, Any]]:
        return self.records("log.jsonl")

    @property
    def events(self) -> list[dict[str, Any]]:
        return self.records("events.jsonl")

    @property
    def views(self) -> list[dict[str, Any]]:
        return self.records("views.jsonl")

    @property
    def latency(self) -> dict[str, Any]:
        return self.json("latency.json", {}) or {}


def read_bundle(path: Path) -> Bundle:
    """Read one bundle (`BundleError` with one line if it cannot be): a regular file, at most `MAX_MEMBERS`
    members, `MAX_MEMBER` bytes each and `MAX_BUNDLE_BYTES` in all, decompressed."""
    try:
        check_regular(path)
        tar = tarfile.open(path, "r:gz")  # noqa: SIM115 - closed by the `with tar` below
    except FileError as e:
        raise BundleError(str(e)) from None
    except FileNotFoundError:
        raise BundleError(f"{path}: no such file") from None
    except (tarfile.TarError, OSError, EOFError) as e:
        raise BundleError(f"{path}: not a stats bundle (not a gzip'd tar file: {e})") from None
    files: dict[str, bytes] = {}
    host = ""
    total = count = 0
    try:
        with tar:
            for m in tar:
                count += 1
                if count > MAX_MEMBERS:
                    raise BundleError(f"{path}: more than {MAX_MEMBERS} members (MAX_MEMBERS)")
                if tar.offset > MAX_BUNDLE_BYTES:  # (the decompressed stream so far, skipped members included)
                    raise BundleError(f"{path}: expands to more than {MAX_BUNDLE_BYTES >> 20} MiB (MAX_BUNDLE_BYTES)")
                if not m.isfile():
                    continue
                top, _, name = m.name.partition("/")
                if not name or ".." in name.split("/"):
                    continue
                if host and top != host:
                    raise BundleError(f"{path}: holds files of two hosts ({host}, {top})")
                host = top
                if m.size > MAX_MEMBER:
                    raise BundleError(f"{path}: {m.name} expands to {m.size >> 20} MiB, more than "
                                      f"{MAX_MEMBER >> 20} MiB (MAX_MEMBER)")
                total += m.size
                if total > MAX_BUNDLE_BYTES:
                    raise BundleError(f"{path}: expands to more than {MAX_BUNDLE_BYTES >> 20} MiB (MAX_BUNDLE_BYTES)")
                f = tar.extractfile(m)
                if f is not None:
                    files[name] = f.read(MAX_MEMBER + 1)
    except (tarfile.TarError, OSError, EOFError, ValueError) as e:
        raise BundleError(f"{path}: damaged stats bundle ({type(e).__name__}: {e})") from None
    if "manifest.json" not in files:
        raise BundleError(f"{path}: not a stats bundle (no manifest.json)")
    try:
        manifest = json.loads(files["manifest.json"])
    except ValueError:
        raise BundleError(f"{path}: {host}/manifest.json is not JSON") from None
    if not isinstance(manifest, dict) or manifest.get("host") != host:
        raise BundleError(f"{path}: {host}/manifest.json does not describe host {host}")
    return Bundle(path, host, manifest, files)


def bundle_paths(d: Path) -> list[Path]:
    if not d.exists():
        raise BundleError(f"{d}: no such directory")
    if not d.is_dir():
        raise BundleError(f"{d}: not a directory (give the directory `haactl stats collect -o` wrote)")
    paths = sorted(d.glob(f"*{SUFFIX}"), key=lambda p: natural_key(p.name[: -len(SUFFIX)]))
    if not paths:
        raise BundleError(f"{d}: no stats bundles (*{SUFFIX}) in it; write some with `haactl stats collect -o {d}`")
    return paths


def load_bundles(d: Path) -> list[Bundle]:
    """Every bundle of directory `d`, in host order (`BundleError` if there is none or one is broken)."""
    return [read_bundle(p) for p in bundle_paths(d)]


def read_summary(d: Path) -> dict[str, Any] | None:
    p = d / SUMMARY_FILE
    if not p.exists():
        return None
    try:
        data = json.loads(read_text(p, what="cluster summary", max_bytes=MAX_SUMMARY))
    except FileError as e:
        raise BundleError(str(e)) from None
    except ValueError as e:
        raise BundleError(f"{p}: not a cluster summary ({e})") from None
    return data if isinstance(data, dict) else None
