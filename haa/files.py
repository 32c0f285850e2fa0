"""Reading the files users hand to HAA (host configs, arenas, schedules, missions, chaos plans) safely.

Every such file goes through `load_yaml` (or `load_json`, `read_text`), which refuses, before building any
Python object from it, a file that could make a process hang, blow its memory or die with a traceback:

* **kind**: only a regular file (symbolic links followed) is opened: a FIFO, whose open blocks until someone
  writes to it, a device such as `/dev/zero` (`/dev/null`, an empty file, excepted), a directory or a socket
  is refused by `check_regular` before anything is opened, naming what it is;
* **size**: at most `max_bytes` bytes are read (default `MAX_BYTES`, 1 MiB); a larger file is refused after
  reading `max_bytes + 1` bytes;
* **encoding**: the bytes must be strict UTF-8 (the error names the offset of the first bad byte);
* **depth**: collections nested at most `max_depth` levels (default `MAX_DEPTH`, 64). PyYAML composes
  documents recursively, so a 100,000-deep `[[[[...` would reach Python's recursion limit; the depth is
  therefore checked on the flat *event* stream of the parser first, before anything is composed;
* **nodes**: at most `max_nodes` scalars and collections (default `MAX_NODES`, 100,000) counted *after*
  expanding aliases, so that a "billion laughs" document (aliases of aliases of lists) is refused while it
  is still a few hundred bytes; an alias of a node that contains the alias itself (a cycle) is refused;
* **duplicate keys**: a mapping that gives the same key twice is refused, naming the key and both lines
  (YAML says keys are unique; PyYAML silently keeps the last one). Merge keys (`<<: *base`) may still be
  overridden, as YAML intends;
* **integers**: at most `MAX_INT_CHARS` (100) characters: converting a long sexagesimal integer
  (`1:2:3:...`) is quadratic in its length;
* YAML is parsed with PyYAML's *safe* loader (no Python objects from tags), libyaml's when it is installed.

Every refusal is a `FileError` (a `ValueError`) whose `str()` is one line, `<path>: <reason>`, e.g.
`cfg.yaml: duplicate key 'core' at line 7 (first at line 2)`; its attributes `path` and `reason` let a
caller phrase the line its own way. Command-line programs print it and exit with code 2. The limits are
listed in docs/limits.md ("Files").
"""

from __future__ import annotations

import errno as errno_mod
import json
import os
import stat
from typing import Any

import yaml

try:
    from yaml import CSafeLoader as _BaseLoader
except ImportError:  # pragma: no cover - PyYAML built without libyaml
    from yaml import SafeLoader as _BaseLoader

#: default limits of `load_yaml` / `load_json` (a caller may pass others for its kind of file)
MAX_BYTES = 1 << 20
MAX_DEPTH = 64
MAX_NODES = 100_000
#: longest integer scalar (characters); Python refuses decimal ints beyond 4,300 digits anyway
MAX_INT_CHARS = 100
#: token files and other one-line secrets
MAX_TOKEN_BYTES = 4096
#: the longest reason text kept in a FileError (a YAML problem may quote the file)
_MAX_REASON = 300

_CHUNK = 64 * 1024
_INT_TAG = "tag:yaml.org,2002:int"
_MERGE_TAG = "tag:yaml.org,2002:merge"


class FileError(ValueError):
    """A user file cannot be used; `str()` is one line `<path>: <reason>`."""

    def __init__(self, path: str | os.PathLike[str], reason: str, os_errno: int | None = None) -> None:
        self.path = one_line(str(path))
        self.reason = one_line(reason)
        #: the errno of a failed open/read (e.g. `errno.ENOENT`), else None
        self.os_errno = os_errno
        super().__init__(f"{self.path}: {self.reason}")


def one_line(text: str, limit: int = _MAX_REASON) -> str:
    """`text` with line breaks and other unprintable characters escaped, cut to `limit` characters."""
    if not text.isprintable():
        text = "".join(c if c.isprintable() else ascii(c)[1:-1] for c in text)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def field_path(loc: tuple[Any, ...]) -> str:
    """A pydantic error location as a field path: ("avatars", 0, "pose") -> "avatars[0].pose" ("" for the root)."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _size(n: int) -> str:
    if n >= 1 << 20 and n % (1 << 20) == 0:
        return f"{n >> 20} MiB"
    if n >= 1 << 10 and n % (1 << 10) == 0:
        return f"{n >> 10} KiB"
    return f"{n} bytes"


_KINDS = (
    (stat.S_ISDIR, "is a directory, not a file"),
    (stat.S_ISFIFO, "is a FIFO (a named pipe), not a regular file: its open would wait for a writer"),
    (stat.S_ISCHR, "is a character device, not a regular file"),
    (stat.S_ISBLK, "is a block device, not a regular file"),
    (stat.S_ISSOCK, "is a socket, not a regular file"),
)


def check_regular(path: str | os.PathLike[str]) -> os.stat_result:
    """`path`'s stat if it is a regular file (symbolic links followed); FileError naming what it is otherwise
    (no such file, a directory, a FIFO, a device, a socket) — without opening it."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise FileError(path, "no such file", errno_mod.ENOENT) from None
    except OSError as e:
        raise FileError(path, f"cannot read: {e.strerror or e}", e.errno) from None
    if stat.S_ISCHR(st.st_mode) and os.path.realpath(path) == os.devnull:
        return st  # (reads nothing: the usual way to hand over an empty file)
    for test, reason in _KINDS:
        if test(st.st_mode):  # (a directory keeps the errno an open would give: callers explain it their way)
            raise FileError(path, reason, errno_mod.EISDIR if test is stat.S_ISDIR else None)
    if not stat.S_ISREG(st.st_mode):
        raise FileError(path, "is not a regular file")
    return st


def read_bytes(path: str | os.PathLike[str], *, what: str = "file", max_bytes: int = MAX_BYTES) -> bytes:
    """The bytes of `path` (a regular file: `check_regular`), reading at most `max_bytes + 1` of them;
    FileError if it is larger or unreadable."""
    check_regular(path)
    try:
        with open(path, "rb", buffering=0) as f:
            chunks: list[bytes] = []
            total = 0
            while total <= max_bytes:
                chunk = f.read(min(_CHUNK, max_bytes + 1 - total))
                if not chunk:
                    break
                chunks.append(chunk)
                total += len(chunk)
    except FileNotFoundError:
        raise FileError(path, "no such file", errno_mod.ENOENT) from None
    except OSError as e:
        raise FileError(path, f"cannot read: {e.strerror or e}", e.errno) from None
    if total > max_bytes:
        raise FileError(path, f"larger than {_size(max_bytes)} ({what} limit)")
    return b"".join(chunks)


def decode(data: bytes, path: str | os.PathLike[str]) -> str:
    """Strict UTF-8 (a leading byte-order mark is dropped); FileError naming the first bad byte's offset."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise FileError(path, f"not UTF-8 text (byte 0x{data[e.start]:02x} at offset {e.start})") from None


def read_text(path: str | os.PathLike[str], *, what: str = "file", max_bytes: int = MAX_BYTES) -> str:
    """A small UTF-8 text file (size-limited like `load_yaml`); FileError otherwise."""
    return decode(read_bytes(path, what=what, max_bytes=max_bytes), path)


def read_token(path: str | os.PathLike[str], *, what: str = "token file") -> str:
    """A token file: at most `MAX_TOKEN_BYTES`, UTF-8, stripped, not empty; FileError otherwise."""
    token = read_text(path, what=what, max_bytes=MAX_TOKEN_BYTES).strip()
    if not token:
        raise FileError(path, "empty")
    return token


# --------------------------------------------------------------------------- YAML
def _mark(mark: Any) -> str:
    return f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""


#: explicitly tagged scalars PyYAML's constructors would crash on (AttributeError, KeyError) unless they
#: look like what the tag's implicit resolver accepts: checked against that resolver's pattern
_STRICT_TAGS = {
    tag: regexp
    for resolvers in yaml.resolver.Resolver.yaml_implicit_resolvers.values()
    for tag, regexp in resolvers
    if tag in ("tag:yaml.org,2002:bool", "tag:yaml.org,2002:timestamp")
}


class _Refused(Exception):
    """Internal: a limit was exceeded (turned into a FileError by `parse_yaml`)."""


def _check_events(loader: Any, max_depth: int, max_nodes: int) -> None:
    """Walk the parser's events (flat, no recursion) and refuse a document that is too deep or, with its
    aliases expanded, too large, before anything is composed."""
    #: per open collection: [nodes counted when it started, its anchor, the height of its tallest child]
    stack: list[list[Any]] = []
    #: anchor -> (expanded node count, height) of the node it names
    anchored: dict[str, tuple[int, int]] = {}
    nodes = 0

    def done(size: int, height: int, anchor: str | None) -> None:
        if anchor is not None:
            anchored[anchor] = (size, height)
        if stack:
            stack[-1][2] = max(stack[-1][2], height)

    while loader.check_event():
        ev = loader.get_event()
        if isinstance(ev, yaml.ScalarEvent):
            nodes += 1
            if ev.tag in _STRICT_TAGS and not _STRICT_TAGS[ev.tag].match(ev.value):
                name = ev.tag.rpartition(":")[2]
                raise _Refused(f"{one_line(repr(ev.value), 40)} is not a !!{name}{_mark(ev.start_mark)}")
            if len(ev.value) > MAX_INT_CHARS:
                tag = ev.tag
                if tag is None or tag == "!":
                    tag = loader.resolve(yaml.ScalarNode, ev.value, ev.implicit)
                if tag == _INT_TAG:
                    raise _Refused(f"an integer longer than {MAX_INT_CHARS} characters{_mark(ev.start_mark)}")
            done(1, 1, ev.anchor)
        elif isinstance(ev, yaml.CollectionStartEvent):
            nodes += 1
            if len(stack) + 1 > max_depth:
                raise _Refused(f"nested deeper than {max_depth} levels{_mark(ev.start_mark)}")
            stack.append([nodes - 1, ev.anchor, 0])
            if ev.anchor is not None:
                anchored.pop(ev.anchor, None)  # an alias inside it refers to it, not to an older namesake
        elif isinstance(ev, yaml.CollectionEndEvent):
            start, anchor, child = stack.pop()
            done(nodes - start, child + 1, anchor)
        elif isinstance(ev, yaml.AliasEvent):
            if ev.anchor not in anchored:
                if any(s[1] == ev.anchor for s in stack):
                    raise _Refused(f"alias *{ev.anchor} refers to a node that contains it{_mark(ev.start_mark)}")
                continue  # an undefined alias: the composer names it
            size, height = anchored[ev.anchor]
            nodes += size
            if len(stack) + height > max_depth:
                raise _Refused(f"nested deeper than {max_depth} levels (alias *{ev.anchor}){_mark(ev.start_mark)}")
            done(size, height, None)
        else:
            continue
        if nodes > max_nodes:
            raise _Refused(f"more than {max_nodes} nodes (counting aliases expanded){_mark(ev.start_mark)}")


class _Loader(_BaseLoader):
    """The safe loader, refusing duplicate mapping keys."""

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            first: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == _MERGE_TAG:
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    line = first.get(key)
                except TypeError:
                    continue  # unhashable: the base constructor says so
                if line is not None:
                    raise _Refused(
                        f"duplicate key {one_line(repr(key), 80)} at line {key_node.start_mark.line + 1} "
                        f"(first at line {line})"
                    )
                first[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


def parse_yaml(
    text: str,
    path: str | os.PathLike[str],
    *,
    max_depth: int = MAX_DEPTH,
    max_nodes: int = MAX_NODES,
) -> Any:
    """The value of one YAML document `text` (None when empty) within the limits; FileError otherwise.
    `path` only labels the errors (use it for text that did not come from a file, e.g. a network reply)."""
    try:
        scan = _Loader(text)
        try:
            _check_events(scan, max_depth, max_nodes)
        finally:
            scan.dispose()
        loader = _Loader(text)
        try:
            return loader.get_single_data()
        finally:
            loader.dispose()
    except _Refused as e:
        raise FileError(path, str(e)) from None
    except yaml.MarkedYAMLError as e:
        reason = f"not valid YAML{_mark(e.problem_mark or e.context_mark)}: {e.problem or 'cannot parse'}"
        if e.context:
            reason += f" ({e.context}{_mark(e.context_mark) if e.problem_mark else ''})"
        raise FileError(path, reason) from None
    except yaml.reader.ReaderError as e:
        char = e.character if isinstance(e.character, int) else ord(e.character)
        where = f"character #x{char:04x} at index {e.position}"
        raise FileError(path, f"not valid YAML: {where}: {e.reason}") from None
    except yaml.YAMLError as e:
        raise FileError(path, f"not valid YAML: {' '.join(str(e).split())}") from None
    except (ValueError, OverflowError, TypeError, KeyError, AttributeError, IndexError) as e:
        # a scalar PyYAML's constructors cannot convert (a date like 2001-02-30, a malformed !!omap, ...)
        raise FileError(path, f"bad value: {type(e).__name__}: {e}") from None


def load_yaml(
    path: str | os.PathLike[str],
    *,
    what: str = "file",
    max_bytes: int = MAX_BYTES,
    max_depth: int = MAX_DEPTH,
    max_nodes: int = MAX_NODES,
) -> Any:
    """Read, check and parse a YAML file (see the module docstring for the limits); FileError on anything
    wrong. `what` names the kind of file in the size error ("config file", "arena file", ...)."""
    text = read_text(path, what=what, max_bytes=max_bytes)
    return parse_yaml(text, path, max_depth=max_depth, max_nodes=max_nodes)


# --------------------------------------------------------------------------- JSON
def _json_depth(text: str, max_depth: int, path: str | os.PathLike[str]) -> None:
    """Refuse JSON nested deeper than `max_depth` before `json.loads` recurses into it."""
    depth = 0
    in_string = escaped = False
    for i, c in enumerate(text):
        if in_string:
            if escaped:
                escaped = False
            elif c == "\\":
                escaped = True
            elif c == '"':
                in_string = False
        elif c == '"':
            in_string = True
        elif c in "[{":
            depth += 1
            if depth > max_depth:
                raise FileError(path, f"nested deeper than {max_depth} levels (at offset {i})")
        elif c in "]}":
            depth -= 1


def _json_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise _Refused(f"duplicate key {one_line(repr(k), 80)}")
        out[k] = v
    return out


def _json_constant(name: str) -> Any:
    raise _Refused(f"{name} is not JSON")


def parse_json(
    text: str,
    path: str | os.PathLike[str],
    *,
    max_depth: int = MAX_DEPTH,
    max_nodes: int = MAX_NODES,
) -> Any:
    """The value of a JSON text within the limits (no NaN/Infinity, no duplicate keys); FileError otherwise."""
    _json_depth(text, max_depth, path)
    try:
        data = json.loads(text, object_pairs_hook=_json_pairs, parse_constant=_json_constant)
    except _Refused as e:
        raise FileError(path, str(e)) from None
    except json.JSONDecodeError as e:
        raise FileError(path, f"not valid JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None
    except (ValueError, RecursionError) as e:
        raise FileError(path, f"bad value: {e}") from None
    nodes, todo = 0, [data]
    while todo:
        v = todo.pop()
        nodes += 1
        if nodes > max_nodes:
            raise FileError(path, f"more than {max_nodes} nodes")
        if isinstance(v, dict):
            todo.extend(v.values())
            nodes += len(v)
        elif isinstance(v, list):
            todo.extend(v)
    return data


def load_json(
    path: str | os.PathLike[str],
    *,
    what: str = "file",
    max_bytes: int = MAX_BYTES,
    max_depth: int = MAX_DEPTH,
    max_nodes: int = MAX_NODES,
) -> Any:
    """Read, check and parse a JSON file with the same limits as `load_yaml`; FileError on anything wrong."""
    text = read_text(path, what=what, max_bytes=max_bytes)
    return parse_json(text, path, max_depth=max_depth, max_nodes=max_nodes)

