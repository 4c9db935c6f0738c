"""Result tables from plain records (list of dicts): markdown, CSV and JSON, and a console print.

Shared by every score producer (detector metrics now, VLM scores later): a record is one row,
its keys are the columns.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

from lanevil_train.files.atomic import atomic_write_text


def _fmt(value, digits: int) -> str:
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def markdown_table(rows: list[dict], columns: list[str] | None = None, digits: int = 2) -> str:
    """A GitHub-markdown table of the rows (columns default to the first row's keys)."""
    if not rows:
        return "(no rows)"
    columns = columns or list(rows[0])
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    for row in rows:
        lines.append("| " + " | ".join(_fmt(row.get(c, ""), digits) for c in columns) + " |")
    return "\n".join(lines)


def write_table(rows: list[dict], out_dir: str | Path, name: str, digits: int = 2) -> dict[str, Path]:
    """Write rows as NAME.json, NAME.csv and NAME.md in out_dir; return the paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"json": out_dir / f"{name}.json", "csv": out_dir / f"{name}.csv", "md": out_dir / f"{name}.md"}
    # each file written whole or not at all: a report killed half-way leaves no torn table
    atomic_write_text(paths["json"], json.dumps(rows, indent=2) + "\n")
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=list(rows[0]) if rows else [])
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(paths["csv"], text.getvalue())
    atomic_write_text(paths["md"], markdown_table(rows, digits=digits) + "\n")
    return paths


def print_table(rows: list[dict], title: str, digits: int = 2) -> None:
    """Print rows as a table on the console (with rich)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title)
    columns = list(rows[0]) if rows else []
    for column in columns:
        values = [row.get(column) for row in rows]
        if all(isinstance(value, str) for value in values):  # names (model, category): never cut to "embedded-q…"
            table.add_column(column, no_wrap=True, min_width=max(len(value) for value in values))
        else:
            table.add_column(column, justify="right")
    for row in rows:
        table.add_row(*(_fmt(row.get(c, ""), digits) for c in columns))
    console = Console()
    if not console.is_terminal:  # logs and pipes: don't squeeze the columns into 80 characters
        console = Console(width=160)
    console.print(table)
