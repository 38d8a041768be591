"""A results table as Markdown text: its numbers, its rows, and the provenance line under it (read by
:mod:`experiments.results_tables`)."""
from __future__ import annotations

import re
from typing import Any

from experiments.results_specs import Spec


def fmt(value: Any, digits: int = 3) -> str:
    """A number as the studies print it (3 significant digits, "diverged" for inf/NaN); text as it is."""
    if value is None or value == "":
        return ""
    if isinstance(value, bool):
        return str(value).lower()
    try:
        x = float(value)
    except (TypeError, ValueError):
        return str(value)
    if x != x or x in (float("inf"), float("-inf")):
        return "diverged"
    if isinstance(value, int) or (isinstance(value, str) and re.fullmatch(r"-?\d+", value.strip())):
        return str(int(x))
    if 1e3 <= abs(x) < 1e6:  # 1 052, not 1.05e+03
        return f"{x:,.0f}".replace(",", " ")
    return f"{x:.{digits}g}"


def markdown_table(header: list[str], rows: list[list[str]]) -> list[str]:
    def line(cells: list[str]) -> str:
        return "| " + " | ".join(c.replace("|", "\\|").replace("\n", " ") for c in cells) + " |"

    return [line(header), "|" + "---|" * len(header), *(line(r + [""] * (len(header) - len(r))) for r in rows)]


def parse_markdown_tables(text: str) -> list[tuple[list[str], list[list[str]]]]:
    """Every pipe table of a Markdown text: (header, rows), cells stripped."""
    tables, block = [], []

    def cells(line: str) -> list[str]:
        inner = line.strip()[1:-1] if line.strip().endswith("|") else line.strip()[1:]
        return [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", inner)]

    for line in [*text.splitlines(), ""]:
        if line.strip().startswith("|"):
            block.append(line)
            continue
        if len(block) >= 2 and re.fullmatch(r"\|?(\s*:?-+:?\s*\|)+\s*:?-*:?\s*\|?", block[1].strip()):
            tables.append((cells(block[0]), [cells(b) for b in block[2:]]))
        block = []
    return tables


SCRIPT_COMMAND = re.compile(r"\bpython experiments/(\w+)\.py\b")


def rerun_command(command: str) -> str:
    """A recorded command as it is run today: `python experiments/<study>.py ...`, as runs before the studies became
    the package `experiments` recorded it, becomes `python -m experiments.<study> ...`; any other command (e.g.
    `python -m experiments.pareto ...` or `python -m lnf.train ...`) is returned as it is."""
    return SCRIPT_COMMAND.sub(r"python -m experiments.\1", command)


def provenance_line(name: str, prov: dict[str, Any], spec: Spec) -> str:
    """The line under a table: machine, date, command(s) as the run recorded them, commit, note, where its sources
    are; the command of a rerun it suggests is spelled as it is run today (:func:`rerun_command`)."""
    commands = prov.get("command") or spec.command
    commands = [commands] if isinstance(commands, str) else list(commands)
    shown = "; ".join(f"`{c}`" for c in commands)
    text = f"Made on {prov.get('machine') or 'an unrecorded machine'}"
    text += f", {prov['date']}" if prov.get("date") else ""
    text += f", by {shown}"
    text += f", at commit {prov['commit']}" if prov.get("commit") else ""
    text += "."
    if prov.get("note"):
        note = prov["note"].rstrip(".")
        text += f" {note[:1].upper()}{note[1:]}."
    if spec.kind == "stack":
        text += " Sources: " + ", ".join(f"`results/{part}/`" for _, part in spec.parts)
    elif spec.kind == "cells":
        text += f" Cells: `results/{name}/cells.json`; sources: " + ", ".join(f"`results/{p}/`" for p in prov["parts"])
    else:
        text += f" Source: `results/{name}/`"
    if prov.get("transcribed_from_docs"):
        rerun = f"rerun `{rerun_command(commands[0])}`" if len(commands) == 1 else "rerun the commands above"
        if spec.kind == "transcribed":
            text += f" (transcribed from the run's report; {rerun} and update `results/{name}/table.csv` from its output)"
        else:
            collect = "--collect" if spec.raw else f"--collect {name}=<its output folder>"
            text += (f" (transcribed from the run's report; {rerun} to regenerate from raw outputs, then "
                     f"`python -m experiments.results_tables {collect}`)")
    return f"*{text}.*"
