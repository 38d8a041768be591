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
``experiments.pareto``.
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"
MARKDOWN = ["README.md", "docs"]  # files, or folders searched for *.md
BEGIN = re.compile(r"^(?P<indent>[ \t]*)<!-- results:(?P<name>[A-Za-z0-9_.-]+) -->\s*$")
END = "<!-- /results:{name} -->"
FENCE = re.compile(r"^\s*(```|~~~)")
MACHINE_2CORE = ("the project's CPU machine (Intel Xeon, 2 vCPUs, 24 GiB, no GPU; torch 2.13.0+cpu, "
                 "2 torch threads)")
MAX_COPY_BYTES = 4 << 20  # a raw file larger than this is not copied into results/


class TableError(RuntimeError):
    """A marker, a source file or a table that cannot be made; the message names the file and the table."""


# ---------------------------------------------------------------------------------------------------
# what each table is made from
# ---------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Spec:
    """Where a table's raw outputs appear and how the table is computed from them.

    kind:
        ``pareto``: ``pareto.csv`` of a Pareto study, the most accurate point of each method (as the study's own
        summary chooses it); ``study``: the ``table``-th Markdown table of the study's ``summary.md`` (the study's
        own reduction of its CSV, which is copied beside it); ``metrics``: rows ``metrics`` (label, key) of a
        run's ``metrics.json`` (or of the JSON file ``file``, nested keys joined by ``/``: e.g. ``results.json`` of
        ``experiments/scenes.py``); ``stack``: one row per table of ``parts`` (label, table name), the rows of
        each one's study CSV where column ``where[0]`` is ``where[1]``, cells ``columns`` (header, key, and
        optionally a factor the value is multiplied by: seconds → ms); its provenance is that of the parts; ``cells``: a
        table assembled from the cells of other tables (``results/<name>/cells.json``: a header and rows of text
        templates, see :func:`fill_cell`), with the provenance of the tables it quotes; ``transcribed``: no raw
        outputs known, ``table.csv`` only.
    raw: the folder of the raw outputs, relative to the repository (None: given on the command line, or none).
    command: the command that makes them.
    """

    kind: str
    command: str
    raw: Optional[str] = None
    table: int = 0
    csv: Optional[str] = None
    metrics: tuple[tuple[str, str], ...] = ()
    file: str = "metrics.json"
    parts: tuple[tuple[str, str], ...] = ()
    columns: tuple[tuple[Any, ...], ...] = ()  # (header, key) or (header, key, factor)
    where: tuple[str, str] = ("", "")


SCENES = ["pendulum", "double_pendulum", "bump", "elastic", "elastic_actuated", "soft_body"]


def _study(name: str, scene: str, kind: str = "study", table: int = 0) -> Spec:
    suffix = "" if scene == "pendulum" else f"-{scene}"
    flag = "" if scene == "pendulum" else f" --scene {scene}"
    return Spec(kind=kind, command=f"python -m experiments.{name}{flag}", raw=f"outputs/studies/{name}{suffix}",
                table=table, csv=f"{name}.csv")


PENDULUM_METRICS = (
    ("`field_rel_l2/all/median`", "field_rel_l2/all/median"),
    ("`field_rel_l2/in_horizon/median`", "field_rel_l2/in_horizon/median"),
    ("`field_rel_l2/extrapolation/median` (t ≥ 2.5 s)", "field_rel_l2/extrapolation/median"),
    ("`field_rel_l2/all/max`", "field_rel_l2/all/max"),
    ("`projection_rel_l2/all/median` (the embedding's own floor)", "projection_rel_l2/all/median"),
    ("`energy_rel_err/max` (m g ℓ units)", "energy_rel_err/max"),
    ("`energy_drift_long/max` (1 000 steps)", "energy_drift_long/max"),
    ("`vpt/median` [s]", "vpt/median"),
    ("`rollout_seconds_per_trajectory`", "rollout_seconds_per_trajectory"),
    ("data and training [s] · whole run [s]", "train_seconds|total_seconds"),
    ("epochs run (of the budget)", "epochs_run|max_epochs"),
)

# a scene's default run, in the scene's own energy unit (E_scale)
SCENE_METRICS = (
    ("`field_rel_l2/all/median` (the whole 5 s)", "field_rel_l2/all/median"),
    ("`field_rel_l2/in_horizon/median` · `/max`", "field_rel_l2/in_horizon/median|field_rel_l2/in_horizon/max"),
    ("`field_rel_l2/extrapolation/median` (after the training horizon)", "field_rel_l2/extrapolation/median"),
    ("`projection_rel_l2/all/median` (the embedding's own floor)", "projection_rel_l2/all/median"),
    ("`energy_rel_err/max` (E_scale units)", "energy_rel_err/max"),
    ("`energy_drift_long/max` (1 000 steps)", "energy_drift_long/max"),
    ("`vpt/median` [s]", "vpt/median"),
    ("`rollout_seconds_per_trajectory` · with decoding", "rollout_seconds_per_trajectory|fields_seconds_per_trajectory"),
    ("data and training [s] · whole run [s]", "train_seconds|total_seconds"),
    ("epochs run (of the budget)", "epochs_run|max_epochs"),
)

# experiments/scenes.py's results.json on a body with an expensive reference (speedup) and an added damping (damped)
FEM_SCENE_MEASUREMENTS = (
    ("test trajectories · training horizon [s] · FEM state entries (u and v of every node, the load)",
     "trajectories|horizon_s|fom_state_size"),
    ("FEM: largest step tried (× its own) · its seconds for all of them", "fom_step_factor|fom_seconds"),
    ("ours, Chebyshev table: step [s] · seconds · speed-up", "rom_dt|rom_seconds|speedup"),
    ("ours, exact pullback: seconds · speed-up", "rom_seconds_exact|speedup_exact"),
    ("ours, table, every stored frame decoded on the evaluation points: points · seconds · speed-up",
     "decoding_points|rom_seconds_with_decoding|speedup_with_decoding"),
    ("conservative: `field_rel_l2` in horizon (median · max) · after it", "ours/field_rel_l2/in_horizon/median|"
     "ours/field_rel_l2/in_horizon/max|ours/field_rel_l2/extrapolation/median"),
    ("conservative: `energy_drift_long/max` (1 000 steps) · diverged long rollouts",
     "ours/energy_drift_long/max|ours/diverged_count_long"),
    ("damped (α [1/s], trained undamped): α · `field_rel_l2` all (median · max) · in horizon · after",
     "damped/damping_per_second|damped/field_rel_l2/all/median|damped/field_rel_l2/all/max|"
     "damped/field_rel_l2/in_horizon/median|damped/field_rel_l2/extrapolation/median"),
    ("damped: dissipated energy, ours / FEM (median) · largest energy error / E_scale · diverged fraction",
     "damped/dissipated_ratio_ours_over_reference_median|damped/energy_error_max_over_scale|"
     "damped/diverged_fraction"),
    ("all measurements [s]", "seconds"),
)

# python -m experiments.probe_settings --out probe.json: the embedding after a fixed number of steps
PROBE_METRICS = (
    ("projection error, 32×32 (training grid)", "projection_rel_l2_32"),
    ("projection error, 64×64 (test grid)", "projection_rel_l2_64"),
    ("projection error, 4 096 points uniform over the body", "projection_rel_l2_uniform"),
    ("rollout error, 64×64: GL32 · GL8 in the dynamics", "rollout_rel_l2_64_GL32|rollout_rel_l2_64_GL8"),
    ("boundary ring's share of the squared 64×64 error", "ring_share_of_sq_error"),
    ("ε = ‖J‖²/⟨J, u⟩² − 1, interior codes: min · max", "eps_interior_min|eps_interior_max"),
    ("training steps · seconds", "steps|train_seconds"),
)

SPECS: dict[str, Spec] = {
    **{f"pareto-{s}": _study("pareto", s, "pareto") for s in SCENES},
    **{f"stability-{s}": _study("stability", s) for s in SCENES},
    "stability-pendulum-resolution": _study("stability", "pendulum", table=1),
    "stability-soft_body-resolution": _study("stability", "soft_body", table=1),
    **{f"sparse_noisy-{s}": _study("sparse_noisy", s) for s in SCENES},
    "model_size-pendulum": _study("model_size", "pendulum"),
    "model_size-elastic": _study("model_size", "elastic"),
    "model_size-elastic_actuated": _study("model_size", "elastic_actuated"),
    "model_size-soft_body": _study("model_size", "soft_body"),
    # the same studies' second table: the baselines (POD-Galerkin, Operator Inference, the black box) at the question
    **{f"model_size-{s}-baselines": _study("model_size", s, table=1) for s in ("elastic", "elastic_actuated",
                                                                               "soft_body")},
    **{f"seeds-{s}": _study("seeds", s) for s in SCENES},
    "cost_scaling-pendulum": _study("cost_scaling", "pendulum"),
    **{f"roofline-{s}": _study("roofline", s) for s in SCENES},
    "roofline-defaults": Spec("stack", "python -m experiments.roofline --scene <scene>",
                              parts=tuple((s.replace("_", " "), f"roofline-{s}") for s in SCENES),
                              where=("default", "True"), columns=(
        ("SIREN width", "width"), ("trajectories", "batch"), ("quadrature points", "points"),
        ("FLOPs per step", "flops"), ("ms per RK4 step", "seconds", 1e3), ("× the bound", "ratio"),
        ("matmul peak, same run [GFLOP/s]", "matmul_peak_gflops"))),
    "summary": Spec("cells", "python -m experiments.results_tables"),
    "pendulum_default": Spec("metrics", "python -m lnf.train +experiment=pendulum", metrics=PENDULUM_METRICS),
    "pendulum_acceptance": Spec("metrics", "python -m experiments.pendulum_acceptance", file="acceptance.json", metrics=(
        ("wall-clock of the train command [s] (data generation, training, test evaluation; target ≤ 1 200)",
         "train_wall_seconds"),
        ("`field_rel_l2/all/median` (target ≤ 0.02)", "field_rel_l2/all/median"),
        ("`field_rel_l2/extrapolation/median`, t ≥ 2.5 s (target ≤ 0.03)", "field_rel_l2/extrapolation/median"),
        ("`field_rel_l2/in_horizon/median` · `field_rel_l2/all/max`", "field_rel_l2/in_horizon/median|field_rel_l2/all/max"),
        ("`projection_rel_l2/all/median` (the embedding's own floor)", "projection_rel_l2/all/median"),
        ("`energy_rel_err/max` (m g ℓ units, 100-sample rollout; target ≤ 0.02)", "energy_rel_err/max"),
        ("`energy_drift_long/max` over 10 000 steps of 4 test trajectories (dt = 0.05 s, 200× the training horizon; "
         "target ≤ 1e-3)", "energy_drift_long/max"),
        ("`vpt/median` [s]", "vpt/median"),
        ("`rollout_seconds_per_trajectory` (100 steps, 16 trajectories at once)", "rollout_seconds_per_trajectory"),
        ("epochs run (of the budget)", "epochs_run|max_epochs"),
        ("every target met", "passed"),
    )),
    "soft_body_default": Spec("metrics", "python -m lnf.train +experiment=soft_body", metrics=SCENE_METRICS),
    "soft_body_scenes": Spec("metrics", "python -m experiments.scenes --scene soft_body --measure speedup shape damped",
                             metrics=FEM_SCENE_MEASUREMENTS, file="results.json"),
    **{f"pendulum_grid-{g}": Spec("metrics", f"python -m lnf.train +experiment=pendulum data.coarse_grid={g.split('-')[0]}",
                                  metrics=PENDULUM_METRICS) for g in ("centres", "vertices", "vertices-lr1e-3")},
    "pendulum_grid": Spec("cells", "python -m experiments.results_tables"),
    **{f"probe-w0-{w}": Spec("metrics", f"python -m experiments.probe_settings --steps 650 --hyper-depth 0 "
                                        f"--velocity-weight 0 --w0 {w} --out <folder>/probe.json",
                             metrics=PROBE_METRICS, file="probe.json") for w in (10, 30)},
    "probe-w0": Spec("cells", "python -m experiments.results_tables"),
    "bench_defaults-pendulum-vertices": Spec("study", "python -m experiments.bench_defaults --override data.coarse_grid=vertices "
                                         "--out outputs/studies/bench_defaults-vertices",
                                         raw="outputs/studies/bench_defaults-vertices", csv="bench_defaults.json"),
    "pendulum_lr1e-3": Spec("metrics", "python -m lnf.train +experiment=pendulum optimizer.lr=1e-3",
                            metrics=PENDULUM_METRICS),
    "evaluate_readme": Spec("metrics", "python -m lnf.evaluate ckpt_path=<the pendulum_lr1e-3 run>/checkpoints/last.ckpt "
                            "integrator=rk4 integrator.substeps=5 dt=0.05 horizon=20 grid.kind=uniform "
                            "grid.resolution=128 long_steps=10000 dynamics=tabulated", metrics=(
        ("evaluation points", "evaluation_points"),
        ("decoding table: nodes · error (of the largest field)", "decoding_table_nodes|decoding_table_error"),
        ("`field_rel_l2/all/median` · `/extrapolation/median`", "field_rel_l2/all/median|field_rel_l2/extrapolation/median"),
        ("rollout · rollout + decoding per trajectory [s]", "rollout_seconds_per_trajectory|fields_seconds_per_trajectory"),
        ("long-horizon check: steps · seconds", "energy_drift_long/steps|energy_drift_long/seconds"),
        ("`energy_drift_long/max`", "energy_drift_long/max"),
        ("rollouts, decoding and checks [s] (`evaluation_seconds`: without start-up, ground truth and figures)",
         "evaluation_seconds"),
    )),
    "elastic-oracle": Spec("study", "python -m experiments.elastic_diagnostics --oracle --degree 1 2 3",
                           raw="outputs/elastic_diagnostics/oracle", csv="oracle.json"),
    "elastic-release": Spec("study", "python -m experiments.elastic_diagnostics --content",
                            raw="outputs/elastic_diagnostics/content", csv="content.json"),
    "streaming": Spec("study", "python -m experiments.streaming", raw="outputs/streaming", csv="results.json"),
    "bench_training": Spec("study", "python -m experiments.bench_training --baseline <commit>",
                           raw="outputs/studies/bench_training", csv="bench_training.json"),
    "bench_training-tabulated": Spec("study", "python -m experiments.bench_training --baseline <commit>",
                                     raw="outputs/studies/bench_training", csv="bench_training.json", table=1),
    # the worked example of docs/own_system.md, a scene kept outside the package
    **{f"{name}-vibrating_string": Spec(kind, f"PYTHONPATH=examples python -m experiments.{name} --config-dir examples/conf "
                                              f"--scene vibrating_string", raw=f"outputs/studies/{name}-vibrating_string",
                                        csv=f"{name}.csv")
       for name, kind in [("pareto", "pareto"), ("stability", "study")]},
}


def spec_of(name: str, provenance: dict[str, Any]) -> Spec:
    """The registered spec of a table, or a transcribed one made from its provenance."""
    if name in SPECS:
        return SPECS[name]
    return Spec("transcribed", provenance.get("command", ""))


# ---------------------------------------------------------------------------------------------------
# formatting
# ---------------------------------------------------------------------------------------------------
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


def write_atomic(path: Path, text: str) -> None:
    """lnf.tempfiles.write_text_atomic's twin: this script renders and checks with the standard library alone, and
    importing anything from lnf loads torch."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def run(check: bool) -> int:
    used: dict[str, list[str]] = {}
    stale = []
    for path in markdown_files():
        where = path.relative_to(ROOT).as_posix()
        text = path.read_text()
        new = rebuild(text, where, used)
        if new != text:
            stale.append(where)
            if not check:
                write_atomic(path, new)
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
