"""The page: which section each bench-results file gets (a file it does not know gets a generic one), and
`generate` / `main`."""

from __future__ import annotations

import argparse
import difflib
import json
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from haa.lab.results.commit import (
    render_ap1,
    render_commit_goals,
    render_ddb,
    render_hostd_oac,
    render_hostlink_ab,
    render_lazy_ab,
    render_seq_inflight_ab,
    render_seq_profile,
    render_transport,
    render_write_path_ab,
)
from haa.lab.results.common import (
    PAGE,
    RESULTS_DIR,
    Json,
    Lines,
    num,
    table,
)
from haa.lab.results.group import (
    render_agents,
    render_alloc_quality,
    render_ap2,
    render_ap3,
    render_ap4,
)
from haa.lab.results.missions import (
    command_experiment,
    command_r1,
    render_mission,
    render_r1,
)
from haa.lab.results.parts import (
    command_restructure_ab,
    render_dashboard,
    render_idle,
    render_memory,
    render_restructure_ab,
    render_sim,
    render_soak,
    render_ufd,
)
from haa.lab.results.slam import (
    command_ap51,
    render_ap51,
    render_ap52,
    render_slam,
)

# ----- unknown files -----------------------------------------------------------------------------------------


def render_generic(d: Any, name: str) -> Lines:
    if not isinstance(d, dict):
        return [f"A JSON {type(d).__name__} of {len(d) if hasattr(d, '__len__') else 1} items; no section layout "
                "is known for this file yet (add one to haa/lab/results/page.py)."]
    scalars = [[f"`{k}`", num(v)] for k, v in d.items() if not isinstance(v, dict | list)]
    nested = [f"`{k}` ({type(v).__name__} of {len(v)})" for k, v in d.items() if isinstance(v, dict | list)]
    lines = ["No section layout is known for this file yet (add one to haa/lab/results/page.py); its top-level "
             "fields:", ""]
    lines += table(["field", "value"], scalars) if scalars else ["(no scalar fields)"]
    if nested:
        lines += ["", "Also holds: " + ", ".join(nested) + "."]
    return lines


# ----- the page -----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Known:
    part: str
    title: str
    render: Callable[[Json, str], Lines]
    command: str | Callable[[Json, str], str]


PARTS = [
    ("missions", "The robot team's missions (thesis §7.1, §7.3)"),
    ("commit", "Atomic commit, transport and the DDB (thesis §7.2.1)"),
    ("group", "Membership, allocation and agents (thesis §7.2.2-7.2.4)"),
    ("slam", "JC-SLAM (thesis §7.2.5)"),
    ("parts", "The failure detector, the simulator and running costs"),
    ("other", "Other results"),
]

KNOWN: dict[str, Known] = {
    "af1": Known("missions", "Exploration and mapping, AF-1 (Table 7.1-1)", render_mission, command_experiment),
    "af1-frontier": Known("missions", "Exploration and mapping with coordinated frontiers (AF-1 set-up)",
                          render_mission, command_experiment),
    "af1-cruise0.2": Known("missions", "Exploration and mapping at eight times the cruise speed (AF-1 set-up)",
                           render_mission, command_experiment),
    "af2": Known("missions", "Congregation, AF-2 (Table 7.1-2)", render_mission, command_experiment),
    "r1": Known("missions", "Agent failure, R-1 (Table 7.3-1)", render_r1, command_r1),
    "ap1": Known("commit", "Ordered atomic commit on real processes, AP-1", render_ap1, "haactl bench ap1"),
    "hostd_oac_latency": Known("commit", "One commit and one hop inside haa-hostd (2-3 hosts)", render_hostd_oac,
                               ".venv/bin/python -m haa.lab.bench.hostd_oac_latency"),
    "transport": Known("commit", "Host link: gRPC stream against unary calls", render_transport,
                       ".venv/bin/python -m haa.lab.bench.transport_stream_vs_unary"),
    "hostlink-ab": Known("commit", "Commit cost per host-link carrier: gRPC stream against plain TCP",
                         render_hostlink_ab, ".venv/bin/python -m haa.lab.bench.hostlink_ab --runs 3 --hosts 10 "
                         "-n 100 --out bench-results/hostlink-ab.json"),
    "issue14-final": Known("commit", "Commit-path goals per host-link carrier (10 hosts)", render_commit_goals,
                           "flock /tmp/haa-bench.lock env .venv/bin/python -m haa.lab.bench.carriers "
                           "--runs 3 --out bench-results/issue14-final.json"),
    "issue14-ab": Known("commit", "Lazy OAC messages, before and after (10 hosts)", render_lazy_ab,
                        "alternate the two trees with `haactl bench ap1 --hosts 10 --min-hosts 10 -n 200`, "
                        "`haactl bench idle --hosts 10`, `haactl bench ap4 --hosts 10 --reps 3`, "
                        "`haactl bench ddb --hosts 10 --all-writing`"),
    "issue14-seq-profile": Known("commit", "The sequencer leader profiled: carriers and batches in flight (10 hosts)",
                                 render_seq_profile, ".venv/bin/python -m haa.lab.bench.seq_ab --hosts 10 "
                                 "--writers 32 --writers 8 --variant grpc:2 --variant grpc:1 --variant tcp:2 "
                                 "--variant tcp:1 --runs 3 --out bench-results/issue14-seq-profile.json "
                                 "(`--profile DIR` for py-spy)"),
    "ddb-seq-inflight-ab": Known("commit", "Sequencer batches in flight, one against two (5 hosts)",
                                 render_seq_inflight_ab, "`haactl bench ddb --hosts 5 --all-writing --sequencer on` "
                                 "with `membership: seq_inflight: 1` or `2` in the hosts' hostd.yaml, alternating"),
    "ddb-write-path-ab": Known("commit", "One DDB write path against the group commit (5 hosts)",
                               render_write_path_ab, "alternate the two trees (PYTHONPATH=<tree>) with "
                               "`.venv/bin/python -m haa.lab.bench.seq_ab --hosts 5 --writers 1 --writers 8 "
                               "--writers 32 --variant grpc:1 --runs 1 --out FILE` and `haactl bench ap1 --hosts 5 "
                               "--min-hosts 3 -n 150`"),
    "ddb": Known("commit", "DDB writes: batching and clients", render_ddb, "haactl bench ddb"),
    "ap2": Known("group", "Join, leave and removal, AP-2", render_ap2, "haactl bench ap2"),
    "ap3": Known("group", "Time to allocation consensus, AP-3", render_ap3,
                 "haactl bench ap3; haactl bench ap3 --real"),
    "alloc_quality": Known("group", "Allocation quality against the exhaustive optimum", render_alloc_quality,
                           "haactl bench alloc-quality"),
    "ap4": Known("group", "Spawn, freeze, transfer and recovery delays, AP-4", render_ap4, "haactl bench ap4"),
    "agents": Known("group", "The agent runtime: spawn, freeze, kill and message throughput", render_agents,
                    "haactl bench agents"),
    "ap5.1": Known("slam", "SLAM strategies at nominal and constrained capacity, AP-5.1", render_ap51, command_ap51),
    "ap5.1-quick": Known("slam", "SLAM strategies on short recordings, AP-5.1 quick", render_ap51, command_ap51),
    "ap5.2": Known("slam", "Operations saved by delayed weight updates, AP-5.2 (Table 7.2-3)", render_ap52,
                   "haactl bench ap5.2"),
    "slam": Known("slam", "JC-SLAM library speed and history memory", render_slam, "haactl bench slam"),
    "ufd": Known("parts", "Failure detector QoS and heartbeat cost", render_ufd, "haactl bench ufd"),
    "sim": Known("parts", "Avatar simulator speed: stepping, camera frames, sonar", render_sim, "haactl bench sim"),
    "idle": Known("parts", "Idle cost of a 10-host cluster, processes and containers", render_idle,
                  "haactl bench idle --hosts 10 --duration 60; haactl bench idle --hosts 10 --duration 60 --compose"),
    "memory": Known("parts", "Memory and event-loop stalls under maximum-size requests", render_memory,
                    "haactl bench memory"),
    "soak": Known("parts", "A soak under a mission-like load", render_soak, "haactl bench soak --minutes 20"),
    "dashboard": Known("parts", "Dashboard: commit to painted page", render_dashboard,
                       ".venv/bin/python -m haa.lab.bench.dashboard_latency"),
    "issue17-ab": Known("parts", "Before and after splitting the core and the runtime into machines (AP-1, AP-2, "
                        "AP-4, idle)", render_restructure_ab, command_restructure_ab),
}


def slug(title: str) -> str:
    """GitHub's anchor for a heading."""
    s = re.sub(r"[^\w\- ]", "", title.lower())
    return s.replace(" ", "-")


def load(results: Path) -> dict[str, Any]:
    return {p.stem: json.loads(p.read_text()) for p in sorted(results.glob("*.json"))}


def section(name: str, data: Any) -> tuple[str, str, Lines]:
    """(part, title, body lines) of one file's section."""
    k = KNOWN.get(name)
    if k is None:
        return "other", f"`{name}.json`", [f"Source: `bench-results/{name}.json`.", "", *render_generic(data, name)]
    try:
        body = k.render(data, name)
        cmd = k.command if isinstance(k.command, str) else k.command(data, name)
    except (KeyError, TypeError, IndexError, ValueError, AttributeError, ZeroDivisionError) as exc:
        raise RuntimeError(f"bench-results/{name}.json does not have the shape haa/lab/results/ expects: "
                           f"{type(exc).__name__}: {exc}") from exc
    cmd_text = cmd if "`" in cmd else f"`{cmd}`"
    head = f"Source: `bench-results/{name}.json`. Reproduce: {cmd_text}."
    body = [ln for i, ln in enumerate(body) if ln or (i and body[i - 1])]  # no double blank lines
    return k.part, k.title, [head, "", *body]


def generate(results: Path = RESULTS_DIR) -> str:
    files = load(results)
    sections = {name: section(name, data) for name, data in files.items()}
    order = [n for n in KNOWN if n in sections] + sorted(n for n in sections if n not in KNOWN)
    out = [
        "# Results",
        "",
        "<!-- Generated by `python -m haa.lab.results` (`make results`) from bench-results/*.json. Do not edit: "
        "`make test` fails when this page and the JSON files disagree. -->",
        "",
        "Every measured number on this page is read from the JSON file its section names (`bench-results/`), "
        "written by the command the section gives. The thesis' values stand beside ours where the thesis has "
        "them, with the line of the thesis text they come from (L*n*). Timings were taken on the shared machine "
        "each section describes, beside other jobs: single runs scatter, and the A/B sections alternate their "
        "variants run by run for that reason. What the numbers led to, and when, is in CHANGELOG.md.",
        "",
    ]
    for part, heading in PARTS:
        names = [n for n in order if sections[n][0] == part]
        if not names:
            continue
        out.append(f"* {heading}")
        out += [f"  * [{sections[n][1]}](#{slug(sections[n][1])})" for n in names]
    for part, heading in PARTS:
        names = [n for n in order if sections[n][0] == part]
        if not names:
            continue
        out += ["", f"## {heading}"]
        for n in names:
            _part, title, body = sections[n]
            out += ["", f"### {title}", "", *body]
    return "\n".join(out).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m haa.lab.results", description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if the page differs from what would be written")
    ap.add_argument("--results", type=Path, default=RESULTS_DIR, help="the JSON files (default bench-results/)")
    ap.add_argument("--out", type=Path, default=PAGE, help="the page (default docs/results.md)")
    args = ap.parse_args(argv)
    text = generate(args.results)
    if args.check:
        old = args.out.read_text() if args.out.exists() else ""
        if old == text:
            print(f"{args.out} is up to date with {args.results}/*.json")
            return 0
        diff = list(difflib.unified_diff(old.splitlines(), text.splitlines(), str(args.out), "generated", lineterm=""))
        print(f"{args.out} differs from what {args.results}/*.json give ({len(diff)} diff lines); run `make results` "
              "(python -m haa.lab.results) and commit the page. First lines of the diff:", file=sys.stderr)
        print("\n".join(diff[:40]), file=sys.stderr)
        return 1
    args.out.write_text(text)
    print(f"wrote {args.out} ({len(text.splitlines())} lines, {len(load(args.results))} result files)")
    return 0
