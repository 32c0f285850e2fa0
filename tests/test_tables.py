"""haactl.tables, the one table helper of the CLI: a rich Table rendered as markdown (benchmarks) or drawn on
the terminal (operator commands), and the experiments' tables built with it (haactl.benchtables)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest
from rich.console import Console
from rich.text import Text

from haa.lab.benchresults import MACHINE_FACTS, machine
from haactl import benchtables
from haactl.tables import add_row, markdown, table

RESULTS = Path(__file__).resolve().parents[1] / "bench-results"


def test_markdown_layout() -> None:
    t = table(["n", "load", "p50 (ms)"], [[2, "paced", "1.25"], [10, "concurrent", None]])
    assert markdown(t) == "\n".join([
        "| n | load | p50 (ms) |",
        "|---|---|---|",
        "| 2 | paced | 1.25 |",
        "| 10 | concurrent |  |",
    ])


def test_markdown_title_and_styled_cells() -> None:
    t = table(["state", "count"], title="Agents", right=["count"])
    add_row(t, [Text("active", style="green"), 3])
    # a cell is printed as given (no markup parsing in markdown); a Text cell by its plain text
    add_row(t, ["[x]", 0])
    assert markdown(t) == "### Agents\n\n| state | count |\n|---|---|\n| active | 3 |\n| [x] | 0 |"


def test_rows_must_fit_the_columns() -> None:
    t = table(["a", "b"])
    with pytest.raises(ValueError, match="3 cells for a table of 2 columns"):
        add_row(t, ["x", "y", "z"])
    add_row(t, ["only a"])  # a short row ends in empty cells
    assert markdown(t).splitlines()[-1] == "| only a |  |"
    with pytest.raises(ValueError, match="not among the headers"):
        table(["a"], right=["b"])


def test_the_same_table_draws_on_the_terminal() -> None:
    t = table(["host", "state", "cpu %"], [["h1", "[green]alive[/]", "12.5"], ["h2", "dead", "3.0"]],
              title="Cluster", right=["cpu %"])
    buf = io.StringIO()
    Console(file=buf, width=80, color_system=None).print(t)
    lines = buf.getvalue().splitlines()
    assert lines[0].strip() == "Cluster" and "|---" not in buf.getvalue()  # a box, not markdown
    h1 = next(x for x in lines if "h1" in x)
    assert "alive" in h1 and "[green]" not in h1  # markup drawn, not printed
    # right-justified: the two numbers end in the same column
    h2 = next(x for x in lines if "h2" in x)
    assert h1.index("12.5") + 4 == h2.index("3.0") + 3


def test_machine_description() -> None:
    assert set(machine()) == {"cpus", "load_avg"}
    m = machine("cpus", "python", "platform", "load_avg_at_end", "load_1min", "event_loop")
    assert list(m) == ["cpus", "python", "platform", "load_avg_at_end", "load_1min", "event_loop"]
    assert m["cpus"] >= 1 and len(m["load_avg_at_end"]) == 3 and isinstance(m["load_1min"], float)
    json.dumps(m)  # goes into the result files as it is
    with pytest.raises(ValueError, match="unknown machine facts"):
        machine("gpu")
    assert "cpus" in MACHINE_FACTS


@pytest.mark.skipif(not (RESULTS / "ap4.json").exists(), reason="no bench-results/ap4.json")
def test_experiment_tables_from_stored_results() -> None:
    """The tables of `haactl bench` laid out from the result files in the repository (the same dicts the
    experiments return): one line per row, the headers the docs quote."""
    ap4 = json.loads((RESULTS / "ap4.json").read_text())["rows"]
    text = benchtables.ap4(ap4)
    assert text.startswith("| action | hosts | median (ms) |")
    assert "| transfer (move request -> thawed) | 2 |" in text
    compact = benchtables.ap4_compact(ap4).splitlines()
    assert compact[2].startswith("| thesis (mean) |") and len(compact) == 4 + len(ap4)
    ap3 = json.loads((RESULTS / "ap3.json").read_text())["rows"]
    grid = benchtables.ap3(ap3).split("\n\n")
    assert grid[0] == "### Time from OAC(start) proposal to committed OAC(finish), ms"
    assert grid[1].startswith("| hosts \\ agents | 5 | 10 |")
