"""Top frames of py-spy raw (collapsed-stack) profiles: own and total samples per function, and per group.

    .venv/bin/python -m haa.lab.bench.collapsed_top FILE [FILE ...] [--top 25]
"""

from __future__ import annotations

import argparse
import re
from collections import Counter

_LOC = re.compile(r" \(([^:]*):\d+\)$")

#: frame groups, first match wins (matched on "function (file)")
GROUPS = [
    ("wire codec / protobuf", ("haa/core/wire", "haa/wire", "google/protobuf", "_pb2", "FromString", "Serialize")),
    ("tcp carrier (tcplink)", ("haa/hostd/tcplink",)),
    ("transport (link logic)", ("haa/hostd/transport",)),
    ("grpc.aio / cygrpc", ("grpc/", "cygrpc", "_cython", "grpc_")),
    ("ddb apply / global state", ("haa/core/ddb", "haa/core/globalstate", "haa/core/gstate")),
    ("sequencer", ("haa/core/sequencer",)),
    ("OAC (Alg. 2)", ("haa/core/oac",)),
    ("membership node", ("haa/core/membership", "haa/core/group")),
    ("runtime / daemon", ("haa/hostd/", "haa/runtime")),
    ("asyncio / uvloop", ("asyncio/", "uvloop")),
]


def parse(path: str) -> Counter[tuple[str, ...]]:
    stacks: Counter[tuple[str, ...]] = Counter()
    with open(path) as f:
        for line in f:
            line = line.rstrip("\n")
            if not line:
                continue
            stack, _, n = line.rpartition(" ")
            stacks[tuple(stack.split(";"))] += int(n)
    return stacks


def fn(frame: str) -> str:
    m = _LOC.search(frame)
    return frame[: m.start()] + f" ({m.group(1)})" if m else frame


def group(frame: str) -> str:
    for name, keys in GROUPS:
        if any(k in frame for k in keys):
            return name
    return "other"


def report(path: str, top: int) -> None:
    stacks = parse(path)
    total = sum(stacks.values())
    own: Counter[str] = Counter()
    incl: Counter[str] = Counter()
    own_group: Counter[str] = Counter()
    for st, n in stacks.items():
        leaf = fn(st[-1])
        own[leaf] += n
        # the leaf's group; a leaf in the stdlib/uvloop is charged to the nearest haa/grpc caller's group
        g = group(leaf)
        if g in ("asyncio / uvloop", "other"):
            for fr in reversed(st[:-1]):
                gg = group(fn(fr))
                if gg not in ("asyncio / uvloop", "other", "runtime / daemon"):
                    g = gg
                    break
        own_group[g] += n
        for f in {fn(x) for x in st}:
            incl[f] += n
    print(f"== {path}: {total} samples")
    print("-- own time")
    for f, n in own.most_common(top):
        print(f"{100 * n / total:5.1f} %  {f}")
    print("-- total time")
    for f, n in incl.most_common(top):
        print(f"{100 * n / total:5.1f} %  {f}")
    print("-- own time by group (stdlib leaves charged to their nearest haa/grpc caller)")
    for g, n in own_group.most_common():
        print(f"{100 * n / total:5.1f} %  {g}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("files", nargs="+")
    ap.add_argument("--top", type=int, default=25)
    a = ap.parse_args()
    for p in a.files:
        report(p, a.top)


if __name__ == "__main__":
    main()
