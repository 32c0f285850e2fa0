"""The shared parts of docs/results.md's sections: where the files are, the thesis' values the files do not carry, and
the formatting of numbers and tables."""

from __future__ import annotations

import math
import statistics
from collections.abc import Iterable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[3]
RESULTS_DIR = ROOT / "bench-results"
PAGE = ROOT / "docs" / "results.md"

Json = dict[str, Any]
Lines = list[str]

# ----- the thesis' values that the JSON files do not carry (line numbers of the specification text) ------------

#: §7.2.1, L1603: "There is typically only a small delay, < 10 ms, between deciding and delivering"
THESIS_AP1 = "decide→deliver \"< 10 ms\" (L1603); messages per OAC plotted in Fig. 7.2-3 (L1605-1615)"
#: §7.2.2, L1629: joins "on the order of seconds", leaves "averaging close to 0.6 seconds", removal "in less
#: than 1.5 seconds after being suspected by the first member"
THESIS_AP2 = ("join: \"on the order of seconds\"; leave: \"close to 0.6 seconds\"; removal: \"less than 1.5 "
              "seconds after being suspected by the first member\" (L1629)")
#: §7.2.3, L1635: time grows with agents, not clearly with hosts; messages grow with both (figures only)
THESIS_AP3 = ("no strong correlation between time and the number of hosts, a clear increase with the number of "
              "agents; messages grow with hosts and agents (L1635; Fig. 7.2-5/7.2-6 give no table)")
#: §7.2.4, L1653: spawn 1-2 s, transfer 1.3-2.1 s (a third to a half of it freezing), recovery 0.7-2.9 s
THESIS_AP4 = {"spawn": "1-2 s", "freeze": "1/3-1/2 of transfer", "transfer": "1.3-2.1 s",
              "recovery": "0.7-2.9 s", "host_recovery": "0.7-2.9 s"}
#: Table 7.2-1 (L1670-1674): the AP-5.1 teams, their recorded length and uncorrected error [m]
THESIS_AP51 = {"Basic": ("4 Seekers", "2:56", 0.123), "Advanced A": ("4 Sweepers", "27:05", 0.804),
               "Advanced B": ("8 Sweepers", "15:22", 0.281)}
#: Table 7.2-3 (L1743-1747): N = 500, M observations between weight updates, operations saved
THESIS_AP52 = {"Basic": (2.93, "44 %"), "Advanced A": (3.97, "50 %"), "Advanced B": (4.89, "53 %")}
#: §7.2.5.3, L1758: JC-SLAM kept up with 24.0 readings/s (generation and processing) in the whole system
THESIS_SLAM = "the whole system processed 24.0 readings/s in AP-5.3 (L1758)"
#: §5.2, L968: 1000 particles, one prediction a second: ~12 KB/s, "less 42 MB after an hour"
THESIS_SLAM_MEMORY = "1000 particles at one prediction per second: \"42 MB after an hour\" (L968)"
#: §4.4, L535: the thesis' QoS (10 s, 1 week, 30 s) "cost roughly 12 messages/minute"
THESIS_UFD = "the thesis' QoS (T_D^U = 10 s, T_MR^L = 1 week, T_M^U = 30 s) \"cost roughly 12 messages/minute\" (L535)"

TABLE_REFS = {"af1": "Table 7.1-1 (L1390-1403)", "af2": "Table 7.1-2 (L1514-1527)", "r1": "Table 7.3-1 (L1794-1806)"}


# ----- formatting ---------------------------------------------------------------------------------------------


def num(x: Any, digits: int = 4) -> str:
    """A number as the tables show it: at most `digits` significant figures (trailing zeros dropped), thousands
    separated, `—` for none."""
    if x is None:
        return "—"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return f"{x:,}"
    if not isinstance(x, float):
        return str(x)
    if math.isnan(x):
        return "—"
    if math.isinf(x):
        return "∞"
    if x == 0:
        return "0"
    a = abs(x)
    if a >= 10 ** (digits - 1):
        return f"{x:,.0f}"
    decimals = max(0, digits - 1 - math.floor(math.log10(a)))
    text = f"{x:,.{decimals}f}"
    return text.rstrip("0").rstrip(".") if "." in text else text


def mean_std(xs: list[float], decimals: int = 1) -> str:
    """'mean ± sample STD' of a few runs ('—' for none; the mean alone for one)."""
    if not xs:
        return "—"
    m = sum(xs) / len(xs)
    if len(xs) == 1:
        return f"{m:,.{decimals}f}"
    sd = math.sqrt(sum((x - m) ** 2 for x in xs) / (len(xs) - 1))
    return f"{m:,.{decimals}f} ± {sd:,.{decimals}f}"


def ms(seconds: float | None) -> str:
    """Seconds as whole milliseconds."""
    return "—" if seconds is None else f"{seconds * 1e3:,.0f}"


def pct(share: float | None, decimals: int = 0) -> str:
    return "—" if share is None else f"{100 * share:.{decimals}f} %"


def table(headers: list[str], rows: Iterable[list[Any]]) -> Lines:
    out = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    for row in rows:
        out.append("| " + " | ".join(c if isinstance(c, str) else num(c) for c in row) + " |")
    return out


def machine_line(m: Json | None) -> str:
    """What the file says about the machine it was measured on."""
    if not m:
        return ""
    parts = []
    cpus = m.get("cpus", m.get("cpu_count"))
    if cpus is not None:
        parts.append(f"{cpus} CPUs")
    for key in ("load_avg", "load_avg_at_end", "load_1min", "load1"):
        if key in m:
            v = m[key]
            label = "load average at the end" if key == "load_avg_at_end" else "load average"
            parts.append(f"{label} " + (" / ".join(num(x, 3) for x in v) if isinstance(v, list) else num(v, 3)))
    if "python" in m:
        parts.append(f"Python {m['python']}")
    if "event_loop" in m:
        parts.append(f"event loop {m['event_loop']}")
    return "Machine: " + ", ".join(parts) + "." if parts else ""


def median(xs: list[float]) -> float | None:
    return statistics.median(xs) if xs else None


def mean_pstd(xs: list[float]) -> tuple[float | None, float | None]:
    xs = [x for x in xs if x == x]
    if not xs:
        return None, None
    return statistics.fmean(xs), statistics.pstdev(xs) if len(xs) > 1 else 0.0


def span(xs: Iterable[float]) -> str:
    v = [x for x in xs if x is not None]
    return f"{num(min(v), 3)}-{num(max(v), 3)}" if v else "—"


