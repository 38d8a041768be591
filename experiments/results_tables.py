"""Every results table of README.md and docs/, rebuilt from its source files.

A table lives in a Markdown file between two markers, and everything between them is generated::

    <!-- results:pareto-elastic -->
    | method, setting | ... |
    ...
    *Made on ..., by `python -m experiments.pareto --scene elastic` ...*
    <!-- /results:pareto-elastic -->

Its sources are committed under ``results/<name>/``: ``provenance.json`` (machine, date, command, commit) and the
data, which is one of

- a copy of the raw output of a study or run (``pareto.csv``, ``<study>.csv`` with the study's ``summary.md``, a
  run's ``metrics.json``), from which the table is computed: ``python -m experiments.results_tables --collect``
  copies it from ``outputs/`` after a study has run (raw ``outputs/`` is not committed);
- ``table.csv``, the table's cells as a report gave them, for a table whose raw outputs are not on this machine.
  Its ``provenance.json`` says ``"transcribed_from_docs": true``, and the table says so under it;
- ``cells.json``, a table made of other tables' cells (the front page's summary): each cell a template that quotes
  them, ``{TABLE|ROW|COLUMN}``, or gives the ratio of two, ``{A ÷ B}`` (:func:`fill_cell`); its provenance is
  theirs.

Commands (from the repository root)::

    python -m experiments.results_tables              # rewrite every table from results/
    python -m experiments.results_tables --check      # exit 1 if a table differs from what its sources give
    python -m experiments.results_tables --collect    # copy each study's raw outputs found under outputs/ first
    python -m experiments.results_tables --collect pendulum_default=outputs/pendulum/runs/<run>   # a run's folder
    python -m experiments.results_tables --list       # the tables, their sources and where they appear

Files are rewritten atomically (a temporary file in the same folder, then a rename), and only when they change.
The script needs only the standard library to render and check; ``--collect`` of a Pareto study imports
``experiments.pareto``. What each table is made from is registered in :mod:`experiments.results_specs`; its
Markdown text is made by :mod:`experiments.results_markdown`.
"""
from __future__ import annotations

import argparse
import csv
import datetime as dt
import json
import os
import platform
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any, Optional

from experiments.results_markdown import (fmt, markdown_table, parse_markdown_tables, provenance_line,
                                          rerun_command)  # noqa: F401 (rerun_command: the tests' RT.rerun_command)
from experiments.results_specs import SPECS, Spec, spec_of

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"
MARKDOWN = ["README.md", "docs"]  # files, or folders searched for *.md
BEGIN = re.compile(r"^(?P<indent>[ \t]*)<!-- results:(?P<name>[A-Za-z0-9_.-]+) -->\s*$")
END = "<!-- /results:{name} -->"
FENCE = re.compile(r"^\s*(```|~~~)")
MAX_COPY_BYTES = 4 << 20  # a raw file larger than this is not copied into results/


class TableError(RuntimeError):
    """A marker, a source file or a table that cannot be made; the message names the file and the table."""


# ---------------------------------------------------------------------------------------------------
# sources → table
# ---------------------------------------------------------------------------------------------------
def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise TableError(f"{path.relative_to(ROOT)}: missing") from None
    except json.JSONDecodeError as exc:
        raise TableError(f"{path.relative_to(ROOT)}: not valid JSON ({exc})") from None


def _parse(text: str) -> Any:
    try:
        return json.loads(text)
    except (json.JSONDecodeError, ValueError):
        return {"inf": float("inf"), "-inf": float("-inf"), "nan": float("nan")}.get(text, text)


def _flat(values: Any, prefix: str = "") -> dict[str, Any]:
    """A JSON object with its nested objects' keys joined by ``/`` (a flat one unchanged)."""
    if not isinstance(values, dict):
        return {prefix: values} if prefix else {}
    out: dict[str, Any] = {}
    for key, value in values.items():
        name = f"{prefix}/{key}" if prefix else str(key)
        out.update(_flat(value, name) if isinstance(value, dict) else {name: value})
    return out


def read_study_csv(path: Path) -> list[dict[str, Any]]:
    """A study's CSV as the study's own rows: parsed values, no key where a cell is empty."""
    with open(path, newline="") as fh:
        return [{k: _parse(v) for k, v in row.items() if v not in ("", None)} for row in csv.DictReader(fh)]


def _pareto_rows(folder: Path, prov: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    from experiments import pareto  # the study's own choice of each method's most accurate point
    rows = read_study_csv(folder / "pareto.csv")
    best = pareto.best_of_each_method(rows, int(prov.get("body_dim", 2)))
    header = ["method", "setting", "extrapolation error", "in-horizon error", "energy drift",
              "latent rollout [s/traj]", "rollout + decoding [s/traj]", "training [s]"]
    keys = [pareto.ERR, "field_rel_l2/in_horizon/median", "energy_drift/max", "rollout_seconds_per_trajectory",
            pareto.COST, "train_seconds"]
    return header, [[r["label"], r["setting"], *(fmt(r.get(k)) for k in keys)] for r in best]


def _scaled(value: Any, factor: list[float]) -> Any:
    """`value` × factor[0] when a factor is given and the value is a number; otherwise `value` as it is."""
    return value * factor[0] if factor and isinstance(value, (int, float)) else value


def _joined(provs: list[dict[str, Any]], key: str) -> Optional[str]:
    """The distinct values of `key` over several provenances, in order, joined by commas (None if none)."""
    values = list(dict.fromkeys(str(p[key]) for p in provs if p.get(key)))
    return ", ".join(values) if values else None


def _commands(provs: list[dict[str, Any]]) -> list[str]:
    """The distinct commands of several provenances (each a string or a list of them), in order."""
    return list(dict.fromkeys(c for p in provs for c in ([p["command"]] if isinstance(p.get("command"), str)
                                                          else p.get("command") or [])))


def _stacked(spec: Spec) -> tuple[list[str], list[list[str]], dict[str, Any]]:
    """A stack's rows, one block per part, and the provenance its parts share (their dates, commands, commits)."""
    rows, provs = [], []
    for label, part in spec.parts:
        folder = RESULTS / part
        prov = _read_json(folder / "provenance.json")
        path = folder / (SPECS[part].csv or "")
        if not path.is_file():
            raise TableError(f"results/{part}/{path.name}: missing (table stack lists {part!r})")
        found = [r for r in read_study_csv(path) if str(r.get(spec.where[0])) == spec.where[1]]
        if not found:
            raise TableError(f"results/{part}/{path.name}: no row with {spec.where[0]} = {spec.where[1]}")
        for r in found:
            rows.append([label, *(fmt(_scaled(r.get(key), factor)) for _, key, *factor in spec.columns)])
        provs.append(prov)

    prov = {"machine": _joined(provs, "machine"), "date": _joined(provs, "date"),
            "command": _commands(provs) or spec.command, "commit": _joined(provs, "commit"),
            "note": "one row per study, each divided by the matmul peak of its own run",
            "transcribed_from_docs": any(p.get("transcribed_from_docs") for p in provs)}
    return ["scene", *(column[0] for column in spec.columns)], rows, prov


CELL_REF = re.compile(r"\{([^{}]+)\}")


def _quoted_cell(ref: str, where: str, tables: dict[str, Any]) -> tuple[str, str]:
    """(text, table) of a reference ``TABLE|ROW|COLUMN``: the cell of table TABLE (as rendered) in the row whose
    first cell is ROW (``ROW@SECOND``: and whose second cell is SECOND) and the column headed COLUMN;
    ``COLUMN#k``: the k-th (from 1) of the values a cell joins with " / " or " · " ("0.070 / 0.062"). `tables`
    holds the tables rendered so far (name → table_of), so that each is rendered once."""
    parts = [p.strip() for p in ref.split("|")]
    if len(parts) != 3:
        raise TableError(f"{where}: {{{ref}}} is not TABLE|ROW|COLUMN")
    name, row_key, column = parts
    column, _, pick = column.partition("#")
    if name not in SPECS and not (RESULTS / name).is_dir():
        raise TableError(f"{where}: {{{ref}}} quotes table {name!r}, which has no results/{name}/")
    if name not in tables:
        tables[name] = table_of(name)
    header, rows, _, _ = tables[name]
    if column not in header:
        raise TableError(f"{where}: {{{ref}}}: table {name} has no column {column!r} (it has {header})")
    first, _, second = row_key.partition("@")
    found = [r for r in rows if r and r[0] == first and (not second or (len(r) > 1 and r[1] == second))]
    if len(found) != 1:
        raise TableError(f"{where}: {{{ref}}}: table {name} has {len(found)} rows {row_key!r} (first cells: "
                         f"{[r[0] for r in rows]}); name one with ROW@SECOND-CELL")
    row = found[0]
    k = header.index(column)
    text = row[k] if k < len(row) else ""
    if pick:
        values = re.split(r" / | · ", text)
        if not pick.isdigit() or not 1 <= int(pick) <= len(values):
            raise TableError(f"{where}: {{{ref}}}: the cell is {text!r}, which has no value #{pick}")
        text = values[int(pick) - 1]
    return text, name


def _number(text: str, ref: str, where: str) -> float:
    try:
        return float(text.replace(" ", ""))
    except ValueError:
        raise TableError(f"{where}: {{{ref}}} is {text!r}, not a number to divide") from None


def cell_references(template: str) -> list[str]:
    """The references ``TABLE|ROW|COLUMN`` of a cell template, those of a ratio ``{A ÷ B}`` included."""
    return [ref for match in CELL_REF.finditer(template) for ref in match.group(1).split(" ÷ ", 1)]


def fill_cell(template: str, where: str, tables: Optional[dict[str, Any]] = None) -> tuple[str, list[str]]:
    """A cell of a ``cells`` table: `template` with every ``{TABLE|ROW|COLUMN}`` replaced by that cell of that
    table, and every ``{A ÷ B}`` (two such references) by the ratio of their numbers to 2 significant digits
    (e.g. "1.8", "2 100"); returns the text and the tables it quotes (`tables`: see :func:`_quoted_cell`)."""
    quoted: list[str] = []
    tables = {} if tables is None else tables

    def replace(match: "re.Match[str]") -> str:
        ref = match.group(1)
        if " ÷ " in ref:
            a, b = ref.split(" ÷ ", 1)
            (ta, na), (tb, nb) = _quoted_cell(a, where, tables), _quoted_cell(b, where, tables)
            quoted.extend([na, nb])
            x = _number(ta, a, where) / _number(tb, b, where)
            return fmt(float(f"{x:.2g}")) if abs(x) < 1e3 else f"{float(f'{x:.2g}'):,.0f}".replace(",", " ")
        text, name = _quoted_cell(ref, where, tables)
        quoted.append(name)
        return text

    return CELL_REF.sub(replace, template), quoted


def _cells(name: str, spec: Spec) -> tuple[list[str], list[list[str]], dict[str, Any]]:
    """The rows of a ``cells`` table, and the provenance of the tables its cells quote."""
    source = RESULTS / name / "cells.json"
    cells = _read_json(source)
    if not isinstance(cells, dict) or not isinstance(cells.get("header"), list) or not isinstance(cells.get("rows"), list):
        raise TableError(f"results/{name}/cells.json: expected {{\"header\": [...], \"rows\": [[...], ...]}}")
    rows, quoted, tables = [], [], {}
    for i, row in enumerate(cells["rows"]):
        filled = [fill_cell(str(t), f"results/{name}/cells.json, row {i + 1}", tables) for t in row]
        rows.append([text for text, _ in filled])
        quoted += [q for _, qs in filled for q in qs]
    parts = list(dict.fromkeys(quoted))
    provs = {part: tables[part][2] for part in parts}
    transcribed = [part for part, p in provs.items() if p.get("transcribed_from_docs")]

    dates = sorted(d for p in provs.values() for d in re.findall(r"\d{4}-\d{2}-\d{2}", str(p.get("date", ""))))
    note = cells.get("note", "")
    if transcribed:
        note += (f"{'; ' if note else ''}quoting tables still transcribed from reports ({', '.join(transcribed)}): "
                 f"they follow when those are regenerated")
    machines = list(dict.fromkeys(re.sub(r"\), .*$", ")", str(p["machine"])) for p in provs.values() if p.get("machine")))
    span = None if not dates else dates[0] if dates[0] == dates[-1] else f"{dates[0]} to {dates[-1]}"
    prov = {"machine": " and ".join(machines) or None, "date": span,
            "command": _commands(list(provs.values())) or spec.command, "commit": _joined(list(provs.values()), "commit"),
            "note": note, "parts": parts}
    if cells.get("command"):  # the commands in short (a summary of many tables): each source keeps its own
        prov.update(command=cells["command"], commit=None)
        prov["note"] += "; each source's provenance gives its exact command and commit"
    return [str(h) for h in cells["header"]], rows, prov


def table_parts(name: str) -> list[str]:
    """The tables whose sources table `name` is made from (a stack's or a cells table's), else []."""
    spec = SPECS.get(name)
    if spec is None:
        return []
    if spec.kind == "stack":
        return [part for _, part in spec.parts]
    if spec.kind == "cells":  # read from the templates: rendering the table again would render every part again
        cells = _read_json(RESULTS / name / "cells.json")
        refs = [ref for row in cells.get("rows", []) for t in row for ref in cell_references(str(t))]
        return list(dict.fromkeys(ref.split("|", 1)[0].strip() for ref in refs))
    return []


def table_of(name: str) -> tuple[list[str], list[list[str]], dict[str, Any], Spec]:
    """(header, rows, provenance, spec) of table `name` from results/<name>/ (a stack: from its parts' folders)."""
    spec = SPECS.get(name)
    if spec is not None and spec.kind == "stack":
        header, rows, prov = _stacked(spec)
        return header, rows, prov, spec
    if spec is not None and spec.kind == "cells":
        header, rows, prov = _cells(name, spec)
        return header, rows, prov, spec
    folder = RESULTS / name
    if not folder.is_dir():
        raise TableError(f"results/{name}/: no such folder (a marker names table {name!r}, which has no sources)")
    prov = _read_json(folder / "provenance.json")
    spec = spec_of(name, prov)
    if prov.get("transcribed_from_docs") or spec.kind == "transcribed":
        path = folder / "table.csv"
        if not path.is_file():
            raise TableError(f"results/{name}/table.csv: missing")
        with open(path, newline="") as fh:
            lines = list(csv.reader(fh))
        if not lines:
            raise TableError(f"results/{name}/table.csv: empty")
        return lines[0], lines[1:], prov, spec
    if spec.kind == "pareto":
        header, rows = _pareto_rows(folder, prov)
    elif spec.kind == "study":
        tables = parse_markdown_tables((folder / "summary.md").read_text())
        if len(tables) <= spec.table:
            raise TableError(f"results/{name}/summary.md: has {len(tables)} tables, table {spec.table} wanted")
        header, rows = tables[spec.table]
    elif spec.kind == "metrics":
        metrics = _flat(_read_json(folder / spec.file))
        header, rows = ["metric", "value"], []
        for label, keys in spec.metrics:
            values = [metrics.get(k) for k in keys.split("|")]
            if all(v is None for v in values):
                continue
            rows.append([label, " · ".join(fmt(v) for v in values)])
    else:
        raise TableError(f"table {name!r}: unknown kind {spec.kind!r}")
    return header, rows, prov, spec


def render(name: str) -> list[str]:
    header, rows, prov, spec = table_of(name)
    return [*markdown_table(header, rows), "", provenance_line(name, prov, spec)]


# ---------------------------------------------------------------------------------------------------
# Markdown files
# ---------------------------------------------------------------------------------------------------
def markdown_files() -> list[Path]:
    out = []
    for entry in MARKDOWN:
        path = ROOT / entry
        out += sorted(path.rglob("*.md")) if path.is_dir() else [path] if path.is_file() else []
    return out


def rebuild(text: str, where: str, used: Optional[dict[str, list[str]]] = None) -> str:
    """`text` with every marked table regenerated (indented as its opening marker is, e.g. inside a list item)."""
    lines, out, i, fenced = text.split("\n"), [], 0, False
    while i < len(lines):
        out.append(lines[i])
        if FENCE.match(lines[i]):
            fenced = not fenced  # a marker inside a code block is an example, not a table
        match = None if fenced else BEGIN.match(lines[i])
        i += 1
        if not match:
            continue
        name, indent = match.group("name"), match.group("indent")
        end = END.format(name=name)
        j = next((k for k in range(i, len(lines)) if lines[k].strip() == end), None)
        if j is None:
            raise TableError(f"{where}: <!-- results:{name} --> has no closing {end}")
        if any(BEGIN.match(line) for line in lines[i:j]):
            raise TableError(f"{where}: another results marker opens inside table {name!r}")
        out += [f"{indent}{line}" if line else "" for line in render(name)]
        out.append(f"{indent}{end}")
        if used is not None:
            used.setdefault(name, []).append(where)
            for part in table_parts(name):
                used.setdefault(part, []).append(f"{where} (in {name})")
        i = j + 1
    return "\n".join(out)


def run(check: bool) -> int:
    used: dict[str, list[str]] = {}
    stale = []
    for path in markdown_files():
        where = path.relative_to(ROOT).as_posix()
        text = path.read_text()
        new = rebuild(text, where, used)
        if new != text:
            stale.append(where)
            if not check:  # lnf only here: importing it loads torch, which rendering and checking do without
                from lnf.tempfiles import write_text_atomic

                write_text_atomic(path, new)
    unused = sorted(p.name for p in RESULTS.iterdir() if p.is_dir() and p.name not in used) if RESULTS.is_dir() else []
    for name in unused:
        print(f"note: results/{name}/ is not shown by any table marker", file=sys.stderr)
    if check:
        for where in stale:
            print(f"{where}: its results tables differ from what results/ gives; run "
                  f"python -m experiments.results_tables", file=sys.stderr)
        print(f"{len(used)} tables checked in {len(markdown_files())} files: "
              f"{'all up to date' if not stale else f'{len(stale)} files out of date'}")
        return 1 if stale else 0
    print(f"{len(used)} tables; rewrote {len(stale)} files" + (f": {', '.join(stale)}" if stale else ""))
    return 0


# ---------------------------------------------------------------------------------------------------
# raw outputs → results/
# ---------------------------------------------------------------------------------------------------
def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""


def _run_record(folder: Path) -> dict[str, Any]:
    """run.json of the first job of a study folder (or of a run folder): its commit, machine, start."""
    jobs = sorted(p for p in folder.glob("*/*/run.json") if ".replaced-" not in p.parent.parent.name)  # kept aside
    for path in [folder / "run.json", *jobs]:
        if path.is_file():
            try:
                return json.loads(path.read_text())
            except json.JSONDecodeError:
                continue
    return {}


def _body_dim(folder: Path) -> int:
    """The body dimension of a Pareto study's scene, as its summary.md states it ("Body dimension: 3.")."""
    stated = _summary_field(folder / "summary.md", "Body dimension")
    if stated is None or not stated.isdigit():
        raise TableError(f"{folder / 'summary.md'}: no 'Body dimension: <n>.' line (experiments/pareto.py "
                         "writes one: rerun the study, or add the line by hand)")
    return int(stated)


def _summary_field(summary: Path, label: str) -> Optional[str]:
    if not summary.is_file():
        return None
    match = re.search(rf"{label}: (.+?)\.(?: |$)", summary.read_text(), re.M)
    return match.group(1).strip("`") if match else None


def collect(name: str, raw: Optional[Path]) -> Path:
    """Copy the raw outputs of table `name` into results/<name>/ with their provenance; returns that folder."""
    spec = SPECS.get(name)
    if spec is None or spec.kind == "transcribed":
        raise TableError(f"table {name!r} has no collector: update results/{name}/table.csv by hand")
    if spec.kind in ("stack", "cells"):
        raise TableError(f"table {name!r} is made from other tables: collect those")
    folder = raw if raw is not None else (ROOT / spec.raw if spec.raw else None)
    if folder is None:
        raise TableError(f"table {name!r}: give the run's folder, --collect {name}=<folder>")
    wanted = {"pareto": ["pareto.csv", "summary.md"], "study": [spec.csv or "", "summary.md"],
              "metrics": [spec.file]}[spec.kind]
    needed = {"pareto": "pareto.csv", "study": "summary.md", "metrics": spec.file}[spec.kind]
    if not (folder / needed).is_file():
        raise TableError(f"{folder}: no {needed} (has the study or run finished?)")
    record = _run_record(folder)
    out = RESULTS / name
    staging = RESULTS / f".{name}.collect-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        for file in wanted:
            src = folder / file
            if file and src.is_file():
                if src.stat().st_size > MAX_COPY_BYTES:
                    raise TableError(f"{src}: {src.stat().st_size} bytes, over the {MAX_COPY_BYTES} copied into results/")
                shutil.copy2(src, staging / file)
        stamp = dt.datetime.fromtimestamp((folder / needed).stat().st_mtime, dt.timezone.utc)
        summary = folder / "summary.md"
        prov = {
            "machine": _summary_field(summary, "Machine") or record.get("platform") or platform.platform(),
            "date": stamp.strftime("%Y-%m-%d"),
            "command": _summary_field(summary, "Command") or spec.command,
            "commit": (record.get("git_commit") or "")[:7] + (" (uncommitted changes)" if record.get("git_dirty") else "")
            or None,
            "transcribed_from_docs": False,
            "collected_from": folder.relative_to(ROOT).as_posix() if folder.is_relative_to(ROOT) else str(folder),
            "collected_at_commit": _git("rev-parse", "--short", "HEAD") or None,
        }
        if spec.kind == "pareto":
            prov["body_dim"] = _body_dim(folder)
        old = RESULTS / name / "provenance.json"
        if old.is_file():  # keep a hand-written note about the conditions of the run (e.g. a shared CPU)
            note = json.loads(old.read_text()).get("note_for_reruns")
            if note:
                prov["note"] = note
        (staging / "provenance.json").write_text(json.dumps(prov, indent=1, ensure_ascii=False) + "\n")
        if out.exists():
            shutil.rmtree(out)
        os.replace(staging, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return out


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments.results_tables", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="change nothing; exit 1 if a table is out of date")
    parser.add_argument("--collect", nargs="*", metavar="NAME[=FOLDER]",
                        help="copy raw outputs into results/ first: every study found under outputs/, or the named "
                             "tables (a run's table needs its folder: NAME=FOLDER)")
    parser.add_argument("--list", action="store_true", help="list the tables and their sources")
    args = parser.parse_args(argv)
    try:
        if args.list:
            used: dict[str, list[str]] = {}
            for path in markdown_files():
                rebuild(path.read_text(), path.relative_to(ROOT).as_posix(), used)
            for name in sorted(used):
                _, _, prov, spec = table_of(name)
                state = "transcribed" if prov.get("transcribed_from_docs") else f"from raw ({spec.kind})"
                print(f"{name:34s} {state:22s} raw: {spec.raw or '-':42s} in: {', '.join(used[name])}")
            return 0
        if args.collect is not None:
            names = args.collect or [n for n, s in SPECS.items() if s.raw and (ROOT / s.raw).is_dir()]
            for item in names:
                name, _, folder = item.partition("=")
                try:
                    out = collect(name, Path(folder).resolve() if folder else None)
                    print(f"collected {out.relative_to(ROOT)}")
                except TableError as exc:
                    if args.collect:  # named: an error; found by themselves: skip the unfinished
                        raise
                    print(f"skipped {name}: {exc}", file=sys.stderr)
        return run(args.check)
    except TableError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
