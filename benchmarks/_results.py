"""Shared helper for benchmarks: append a titled markdown table, with the command that made it, to RESULTS.md."""
from __future__ import annotations

import datetime
import platform
import sys
from pathlib import Path

RESULTS = Path(__file__).with_name("RESULTS.md")


def markdown_table(header: list[str], rows: list[list]) -> str:
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def append_results(title: str, table_md: str, notes: str = "", command: str | None = None) -> None:
    """Append one section to benchmarks/RESULTS.md (and print it)."""
    command = command or "python " + " ".join(sys.argv)
    stamp = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
    section = (f"\n## {title}\n\n`{command}` — {stamp}, {platform.machine()}, "
               f"{platform.python_version()}\n\n{table_md}\n")
    if notes:
        section += f"\n{notes}\n"
    print(section)
    with open(RESULTS, "a") as f:
        f.write(section)
