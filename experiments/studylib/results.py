"""Collecting a study's results: one row per finished job of a sweep (read as the sweep table reads its jobs,
:mod:`lnf.training.sweep_table`), the study's CSV, and which rows are best."""
from __future__ import annotations

import csv
import io
import json
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np

from experiments.studylib.jobs import ROOT
from experiments.studylib.tables import write_text_atomic


def keep_aside(folder: Path) -> Path:
    """Rename `folder` to `<name>.replaced-<UTC time>[-n]` beside it, so that a rerun never deletes results (a sweep
    run from another checkout, with other settings, or interrupted); returns the new path."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    target, n = folder.with_name(f"{folder.name}.replaced-{stamp}"), 1
    while target.exists():
        target, n = folder.with_name(f"{folder.name}.replaced-{stamp}-{n}"), n + 1
    folder.rename(target)
    return target


def all_done(folder: Path) -> bool:
    """Whether `folder` holds job folders (``<folder>/<number>/``) and each has its metrics.json."""
    jobs = [p for p in folder.iterdir() if p.is_dir() and p.name.isdigit()] if folder.is_dir() else []
    return bool(jobs) and all((j / "metrics.json").is_file() for j in jobs)


def _override(key: str, value: str) -> tuple[str, Any]:
    """An override as a row holds it: the value parsed as JSON where it parses; a deleted key as ``~key``, with the
    value Hydra records for it (``~model.w0=null``: None; ``~model.w0``: empty)."""
    if value.startswith("(deleted"):  # lnf.training.sweep_table.override_items: "(deleted)", "(deleted <value>)"
        key, value = f"~{key}", value[len("(deleted "):-1]
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def collect(folder: Path, sweep: str, label: Optional[dict[str, Any]] = None) -> list[dict[str, Any]]:
    """One row per job of `folder` with a metrics.json: sweep, job, dir, the `label`, its command-line overrides
    (:func:`_override`) and its metrics. The jobs are read by :func:`lnf.training.sweep_table.find_jobs`."""
    from lnf.training.sweep_table import find_jobs

    rows = []
    for job in find_jobs(folder):
        if not (job.path / "metrics.json").is_file():
            continue  # unfinished, or failed before it wrote its metrics
        if job.status == "missing metrics":
            raise ValueError(f"{job.path / 'metrics.json'}: not a JSON object")
        where = job.path.relative_to(ROOT) if job.path.is_relative_to(ROOT) else job.path
        over = dict(_override(k, v) for k, v in job.overrides.items())
        rows.append({"sweep": sweep, "job": job.num, "dir": str(where), **(label or {}), **over, **job.metrics})
    return rows


def write_csv(path: Path, rows: list[dict[str, Any]]) -> Path:
    """All rows (union of keys; empty where a row lacks one), written atomically; returns the path."""
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))
    writer.writeheader()
    writer.writerows(rows)
    return write_text_atomic(path, text.getvalue())


def method_of(row: dict[str, Any]) -> str:
    """The method of a row: its `method` label, else the one its overrides select (``METHODS``)."""
    if row.get("method"):
        return row["method"]
    if row.get("dynamics") == "latent_mlp":
        return "latent_mlp"
    return {"pod": "pod", "full_order": "full_order"}.get(row.get("model"), "lnf")


def pareto_mask(cost: np.ndarray, error: np.ndarray) -> np.ndarray:
    """True where no other point has both lower-or-equal cost and error (and one strictly lower)."""
    cost, error = np.asarray(cost, float), np.asarray(error, float)
    ok = np.isfinite(cost) & np.isfinite(error)
    mask = np.zeros(len(cost), bool)
    for i in np.flatnonzero(ok):
        dominated = ok & (cost <= cost[i]) & (error <= error[i]) & ((cost < cost[i]) | (error < error[i]))
        mask[i] = not dominated.any()
    return mask


def dominates(front_cost: np.ndarray, front_error: np.ndarray, cost: float, error: float) -> bool:
    """Whether some point of a front has cost ≤ `cost` and error ≤ `error`."""
    return bool(np.any((np.asarray(front_cost) <= cost) & (np.asarray(front_error) <= error)))

