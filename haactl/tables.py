"""The one table helper of haactl: every table the CLI shows is a `rich.table.Table` built by `table()`.

A command either prints it to the terminal (`out.print(t)`, rich draws the box and fits the columns) or, for
the benchmarks whose output is pasted into the docs and the README, renders it as a GitHub markdown table with
`markdown(t)`:

    ### Title                        (only when the table has a title)

    | header | header |
    |---|---|
    | cell | cell |

Cells are given as text (the caller formats its numbers: "12.3 ms", "n/a"), or as a `rich.text.Text` to be
styled on the terminal (`markdown()` prints its plain text). A cell that is `None` prints as an empty cell.
`markdown()` prints a text cell exactly as given; the terminal reads it as rich markup, as `Table` does.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from rich.table import Table
from rich.text import Text

Cell = str | int | float | Text | None


def table(
    headers: Sequence[str],
    rows: Iterable[Sequence[Cell]] = (),
    *,
    title: str | None = None,
    right: Iterable[str] = (),
) -> Table:
    """A table with these column `headers` and `rows` (each at most as long as `headers`: a shorter row ends
    in empty cells); the columns named in `right` are right-justified on the terminal (numbers)."""
    right = set(right)
    unknown = right - set(headers)
    if unknown:
        raise ValueError(f"right-justified columns {sorted(unknown)} are not among the headers {list(headers)}")
    t = Table(title=title, title_justify="left")
    for h in headers:
        t.add_column(h, justify="right" if h in right else "left")
    for r in rows:
        add_row(t, r)
    return t


def add_row(t: Table, row: Sequence[Cell]) -> None:
    """Append one row; a row longer than the table is wide is a bug of the caller (ValueError)."""
    if len(row) > len(t.columns):
        raise ValueError(f"a row of {len(row)} cells for a table of {len(t.columns)} columns: {row!r}")
    t.add_row(*("" if c is None else c if isinstance(c, Text) else str(c) for c in row))


def _plain(cell: object) -> str:
    return cell.plain if isinstance(cell, Text) else str(cell)


def markdown(t: Table) -> str:
    """`t` as a markdown table: a `### title` line and a blank line if it has a title, the header row, the
    `|---|` separator, one line per row; no padding (a diff shows the changed cells only)."""
    cols = t.columns
    lines = [f"### {t.title}\n"] if t.title else []
    lines.append("| " + " | ".join(_plain(c.header) for c in cols) + " |")
    lines.append("|---" * len(cols) + "|")
    cells = [list(c.cells) for c in cols]
    for i in range(t.row_count):
        lines.append("| " + " | ".join(_plain(col[i]) if i < len(col) else "" for col in cells) + " |")
    return "\n".join(lines)
