"""The report's figures (matplotlib, Agg backend: no display needed), one PNG each.

Each function takes the run's data (haa.lab.stats.run.RunData) and a path, draws, saves and returns the path;
`xlim`/`ylim` let a comparison draw two runs on the same scales. Time is seconds since the run's first
record (cluster time), except for the mission figure (mission time, as the mission's results use).

* `allocation` — Fig. 7.1-2: one row per agent per host that ran it, grouped by host; the colours of
  `STATE_COLOURS`; a host's band ends where its records end (a killed host).
* `hosts_agents` — hosts sampling, members of the largest view, agent processes running.
* `cpu_hosts` / `cpu_types` — Fig. 7.1-8 / 7.1-9: CPU per host (haa-hostd and its agents) and per agent type,
  averaged over SMOOTH_S seconds.
* `ddb` — Fig. 7.1-7: DDB bytes by kind, stacked.
* `faults` — faults (injected ones when the run has a faults.json or chaos.json, else agent crashes and host
  removals — not graceful leaves — as the hosts saw them) against recoveries (agents recovered, hosts joining
  again), cumulative.
* `mission` — explored share (and coverage / accuracy when sampled) and each avatar's position error.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from haa.lab.stats.summary import removals

if TYPE_CHECKING:
    from haa.lab.stats.run import RunData

STATE_COLOURS = {
    "spawning": "#f2c12e",
    "active": "#3a9d23",
    "freezing": "#2b6cb0",
    "thawing": "#63b3ed",
    "crashed": "#d62728",
    "recovering": "#ff8c00",
}
#: the events that end a crash in the allocation timeline (not a start failure's backoff, not another report)
CRASH_ENDS = frozenset({"recovering", "recovered", "active", "spawning", "thawing", "removed", "failed"})
#: a host's records with a gap longer than this many sampler periods: it was down (or paused) in between
GAP_PERIODS = 3
#: CPU curves are averaged over this many seconds
SMOOTH_S = 5.0
#: injected faults labelled in the faults figure at most
MAX_FAULT_LABELS = 16
#: most agent rows drawn in the allocation timeline (the rest are counted in the title)
MAX_ROWS = 160


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    _plt().close(fig)
    return path


def smooth(values: list[float], period: float) -> list[float]:
    """A trailing mean over SMOOTH_S seconds (CPU shares sampled each second step by psutil's 10 ms ticks)."""
    n = max(1, round(SMOOTH_S / max(period, 1e-3)))
    out, acc = [], 0.0
    for i, v in enumerate(values):
        acc += v
        if i >= n:
            acc -= values[i - n]
        out.append(acc / min(i + 1, n))
    return out


def _limits(ax: Any, xlim: tuple[float, float] | None, ylim: tuple[float, float] | None) -> None:
    if xlim is not None:
        ax.set_xlim(*xlim)
    if ylim is not None:
        ax.set_ylim(*ylim)


def allocation_segments(run: RunData) -> dict[str, dict[str, list[tuple[float, float, str]]]]:
    """host -> agent label -> [(start, end, state)] in seconds since t0 (module docstring)."""
    t0 = run.t0
    ends = {h: (float(b.manifest.get("last_ts") or run.t1) - t0) for h, b in run.by_host.items()}
    segs: dict[str, dict[str, list[tuple[float, float, str]]]] = defaultdict(lambda: defaultdict(list))
    open_: dict[tuple[str, str], tuple[float, str]] = {}  # (host, agent) -> (since, state)
    labels: dict[str, str] = {}
    by_agent_next: dict[int, float] = {}
    evs = [e for e in run.events if e.agent]
    nxt: dict[str, float] = {}
    for i in range(len(evs) - 1, -1, -1):  # when each crash ended: the agent's next step towards running again
        e = evs[i]
        by_agent_next[i] = nxt.get(e.agent, run.t1 - t0)
        if e.event in CRASH_ENDS:
            nxt[e.agent] = e.time - t0
    state_of = {"spawning": "spawning", "active": "active", "freezing": "freezing", "thawing": "thawing",
                "thawed": "active", "recovering": "recovering", "recovered": "active"}
    spans = {h: host_spans(run, h) for h in run.by_host}
    for h, sp in spans.items():  # a host still up when collected: its last run of records goes on
        if sp and run.by_host[h].manifest.get("state") in ("alive", "paused"):
            sp[-1] = (sp[-1][0], run.t1 - t0)
    min_crash = max(0.05, (run.t1 - t0) / 400)

    def until(host: str, since: float, t: float) -> float:
        """`t`, or the end of the host's run of records that `since` is in, if that is earlier (it died)."""
        for a, b in spans.get(host, []):
            if a - 1.0 <= since <= b + 1.0:
                return max(since, min(t, b))
        return t

    for i, e in enumerate(evs):
        host = e.host or e.reporter
        if not host:
            continue
        t = e.time - t0
        labels[e.agent] = f"{e.name} ({e.type})" if e.type else e.name
        key = (host, e.agent)
        cur = open_.pop(key, None)
        start = t
        if cur is not None:
            start = until(host, cur[0], t)
            segs[host][e.agent].append((cur[0], start, cur[1]))
        if e.event in state_of:
            open_[key] = (t, state_of[e.event])
        elif e.event == "crashed":  # from the host's death (if it died) until the group recovered it
            for other in [k for k in open_ if k[1] == e.agent]:  # it ran nowhere else any more
                since, st = open_.pop(other)
                end = until(other[0], since, t)
                segs[other[0]][e.agent].append((since, end, st))
            segs[host][e.agent].append((start, max(t + min_crash, by_agent_next[i]), "crashed"))
    for (host, agent), (since, st) in open_.items():
        segs[host][agent].append((since, until(host, since, ends.get(host, run.t1 - t0)), st))
    return {h: {labels.get(a, a[:8]): v for a, v in sorted(d.items(), key=lambda kv: kv[1][0][0])}
            for h, d in segs.items()}


def allocation(run: RunData, path: Path, xlim: tuple[float, float] | None = None) -> Path:
    plt = _plt()
    segs = allocation_segments(run)
    hosts = sorted(set(run.by_host) | set(segs), key=run.host_key)
    rows: list[tuple[str, str]] = []
    for h in hosts:
        rows.append((h, ""))  # the host's band
        rows += [(h, label) for label in segs.get(h, {})]
    cut = max(0, len(rows) - MAX_ROWS)
    rows = rows[:MAX_ROWS]
    fig, ax = plt.subplots(figsize=(11, 1.2 + 0.22 * max(4, len(rows))))
    for y, (h, label) in enumerate(rows):
        if not label:
            for x0, x1 in host_spans(run, h):
                ax.barh(y, max(x1 - x0, 0.05), left=x0, height=0.5, color="#bbbbbb")
            continue
        for s, e, st in segs[h][label]:
            ax.barh(y, max(e - s, 0.05), left=s, height=0.7, color=STATE_COLOURS.get(st, "#999999"))
    ax.set_yticks(range(len(rows)))
    ax.set_yticklabels([f"{h}" if not lb else f"  {lb}" for h, lb in rows], fontsize=7)
    for y, (_h, lb) in enumerate(rows):
        if not lb:
            ax.get_yticklabels()[y].set_fontweight("bold")
    ax.invert_yaxis()
    ax.set_xlabel("time [s]")
    title = "allocation timeline per host (grey: the host's records)"
    ax.set_title(title + (f" — {cut} more rows not drawn" if cut else ""), fontsize=10)
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in STATE_COLOURS.values()]
    fig.legend(handles, list(STATE_COLOURS), ncol=6, fontsize=8, loc="lower center", frameon=False)
    _limits(ax, xlim, None)
    fig.tight_layout(rect=(0, 0.3 / (1.2 + 0.22 * max(4, len(rows))), 1, 1))
    return _save(fig, path)


def host_spans(run: RunData, host: str) -> list[tuple[float, float]]:
    """When the host was running, as its records show: its samples (and log lines), a gap of more than
    GAP_PERIODS sampler periods (a kill, a pause) splits them."""
    b = run.by_host.get(host)
    if b is None:
        return []
    ts = sorted(float(r["ts"]) - run.t0 for r in b.samples if isinstance(r.get("ts"), int | float))
    if not ts:
        first, last = b.manifest.get("first_ts"), b.manifest.get("last_ts")
        return [(float(first) - run.t0, float(last) - run.t0)] if first and last else []
    gap = GAP_PERIODS * run.series.period
    spans = [[ts[0], ts[0]]]
    for t in ts[1:]:
        if t - spans[-1][1] > gap:
            spans.append([t, t])
        else:
            spans[-1][1] = t
    return [(a, b_) for a, b_ in spans]


def hosts_agents(run: RunData, path: Path, xlim: tuple[float, float] | None = None,
                 ylim: tuple[float, float] | None = None) -> Path:
    plt = _plt()
    s = run.series
    fig, ax = plt.subplots(figsize=(9, 3.2))
    ax.step(s.t, s.hosts_up, where="mid", label="hosts sampling")
    ax.step(s.t, s.members, where="mid", label="members (largest view)", linestyle="--")
    ax.step(s.t, s.agents, where="mid", label="agent processes")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("count")
    ax.set_title("hosts and agents over time", fontsize=10)
    ax.legend(fontsize=8)
    _limits(ax, xlim, ylim)
    fig.tight_layout()
    return _save(fig, path)


def cpu_hosts(run: RunData, path: Path, xlim: tuple[float, float] | None = None,
              ylim: tuple[float, float] | None = None) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 3.2))
    drawn = False
    for h in sorted(run.series.host_cpu, key=run.host_key):
        pts = run.series.host_cpu[h]
        if pts:
            ax.plot([p[0] for p in pts], smooth([p[1] for p in pts], run.series.period), label=h, linewidth=1)
            drawn = True
    ax.set_xlabel("time [s]")
    ax.set_ylabel("% of one core")
    ax.set_title("CPU per host (haa-hostd + its agents; Fig. 7.1-8)", fontsize=10)
    if drawn:
        ax.legend(fontsize=7, ncol=5)
    _limits(ax, xlim, ylim)
    fig.tight_layout()
    return _save(fig, path)


def cpu_types(run: RunData, path: Path, xlim: tuple[float, float] | None = None,
              ylim: tuple[float, float] | None = None) -> Path:
    plt = _plt()
    s = run.series
    fig, ax = plt.subplots(figsize=(9, 3.2))
    types = [t for t in s.type_cpu if any(s.type_cpu[t])]
    if types:
        ax.stackplot(s.t, [smooth(s.type_cpu[t], s.period) for t in types], labels=types)
        ax.legend(fontsize=7, ncol=4, loc="upper left")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("% of one core")
    ax.set_title("CPU per agent type, all hosts (Fig. 7.1-9)", fontsize=10)
    _limits(ax, xlim, ylim)
    fig.tight_layout()
    return _save(fig, path)


def ddb(run: RunData, path: Path, xlim: tuple[float, float] | None = None,
        ylim: tuple[float, float] | None = None) -> Path:
    plt = _plt()
    s = run.series
    fig, ax = plt.subplots(figsize=(9, 3.2))
    kinds = [k for k in s.ddb_kind if any(s.ddb_kind[k])]
    if kinds:
        ax.stackplot(s.t, [[v / 2**20 for v in s.ddb_kind[k]] for k in kinds], labels=kinds)
        ax.legend(fontsize=7, ncol=5, loc="upper left")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("MB")
    ax.set_title("DDB size by kind (Fig. 7.1-7; agents: keys of the team and the agents' backups)", fontsize=10)
    _limits(ax, xlim, ylim)
    fig.tight_layout()
    return _save(fig, path)


def fault_recovery_times(run: RunData) -> tuple[list[tuple[float, str]], list[float], str]:
    """(faults as (t, label), recovery times, where the faults come from)."""
    t0 = run.t0
    recov = [e.time - t0 for e in run.events if e.agent and e.event == "recovered"]
    gone: set[str] = set()
    for v in run.views:  # a host joining again after its removal
        gone |= set(v.get("removed") or ())
        for h in v.get("added") or ():
            if h in gone:
                recov.append(float(v.get("ts") or t0) - t0)
                gone.discard(h)
    if run.faults:
        return ([(float(f["ts"]) - t0, f"{f.get('action')} {f.get('target')}") for f in run.faults
                 if f.get("ok", True) and f.get("action") != "resume"], sorted(recov), "injected")
    seen = [(e.time - t0, f"{e.name} crashed") for e in run.events if e.agent and e.event == "crashed"]
    seen += [(ts - t0, f"{h} removed") for ts, h, left in removals(run.bundles, run.views) if not left]
    return sorted(seen), sorted(recov), "crashes and host removals the hosts saw"


def faults(run: RunData, path: Path, xlim: tuple[float, float] | None = None,
           ylim: tuple[float, float] | None = None) -> Path:
    plt = _plt()
    fs, rs, where = fault_recovery_times(run)
    fig, ax = plt.subplots(figsize=(9, 3.2))
    if fs:
        ax.step([0.0, *[t for t, _ in fs]], list(range(len(fs) + 1)), where="post", color="#d62728",
                label=f"faults ({where})")
        for t, label in fs[:MAX_FAULT_LABELS] if where == "injected" else []:
            ax.axvline(t, color="#d62728", alpha=0.15)
            ax.annotate(label, (t, len(fs) * 0.02), fontsize=6, rotation=90, va="bottom", ha="right", alpha=0.8)
    if rs:
        ax.step([0.0, *rs], list(range(len(rs) + 1)), where="post", color="#3a9d23",
                label="recoveries (agents recovered, hosts rejoined)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("cumulative count")
    ax.set_title("faults against recoveries", fontsize=10)
    if fs or rs:
        ax.legend(fontsize=8, loc="upper left")
    _limits(ax, xlim, ylim)
    fig.tight_layout()
    return _save(fig, path)


def mission(run: RunData, path: Path, xlim: tuple[float, float] | None = None) -> Path:
    plt = _plt()
    m = run.mission or {}
    samples = (m.get("samples") or {}).get("samples") or {}
    results = m.get("results") or {}
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 3.4))
    for key, label in (("explored", "explored"), ("coverage", "coverage"), ("accuracy", "accuracy")):
        pts = samples.get(key) or []
        if pts:
            a1.plot([p[0] for p in pts], [100 * float(p[1]) for p in pts], label=label)
    for key, style in (("coverage", ":"), ("accuracy", "--")):
        v = results.get(key)
        if isinstance(v, int | float) and not samples.get(key):
            a1.axhline(100 * v, linestyle=style, color="grey", linewidth=1, label=f"final {key} {100 * v:.1f} %")
    a1.set_xlabel("mission time [s]")
    a1.set_ylabel("%")
    a1.set_ylim(0, 105)
    a1.set_title("coverage and accuracy", fontsize=10)
    a1.legend(fontsize=8, loc="lower right")
    for avatar, pts in sorted(((m.get("samples") or {}).get("position_error") or {}).items()):
        if pts:
            a2.plot([p[0] for p in pts], [float(p[1]) for p in pts], label=avatar, linewidth=1)
    pe = results.get("position_error_m")
    a2.set_title("position error" + (f" (mean {pe:.3f} m)" if isinstance(pe, int | float) else ""), fontsize=10)
    a2.set_xlabel("mission time [s]")
    a2.set_ylabel("m")
    if (m.get("samples") or {}).get("position_error"):
        a2.legend(fontsize=7, ncol=2)
    for ax in (a1, a2):
        _limits(ax, xlim, None)
    fig.tight_layout()
    return _save(fig, path)
