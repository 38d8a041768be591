"""One table per sweep: ``python -m lnf.train -m ...`` leaves ``sweep_table.csv`` and ``sweep_table.md`` in its
sweep dir.

The CSV has one row per job: its number, its status (``ok``, ``failed: <error>`` or ``missing metrics``), its
overrides as columns (``model.latent_dim`` → ``2``) and every value of its metrics.json. The Markdown table shows
the overrides that vary between the jobs against a few headline metrics (:data:`HEADLINE`, and the sweep's
``optimized_metric`` if it has one).

:class:`SweepTable` is a Hydra callback (``hydra.callbacks`` in conf/hydra/default.yaml), so it works with every
launcher (basic, joblib, submitit) and sweeper (basic, Optuna): each job records how it ended in
``.hydra/job_status.json`` of its folder and rewrites the table when it ends (under a lock, on the machine that ran
it), and the table is written once more when the multirun ends — a sweep whose jobs failed stops Hydra's basic
sweeper before that, and its table is then the one its last job wrote. Both files are written atomically (a
temporary name in the same folder, then a rename): a reader never sees half a table.
"""
from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Optional

import yaml

from lnf.tempfiles import write_text_atomic

log = logging.getLogger("lnf.sweep")

CSV_NAME = "sweep_table.csv"
MARKDOWN_NAME = "sweep_table.md"
STATUS_NAME = "job_status.json"  # in each job's .hydra folder
HEADLINE = ("field_rel_l2/all/median", "energy_rel_err/max", "train_seconds", "epochs_run")


@dataclass
class Job:
    """One job folder of a sweep: its number, overrides (key → value, in the order given), metrics and status."""

    num: int
    path: Path
    overrides: dict[str, str] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    status: str = "missing metrics"


def override_items(overrides: list[str]) -> dict[str, str]:
    """``["+experiment=pendulum", "model.latent_dim=2", "~logger"]`` → ``{"experiment": "pendulum",
    "model.latent_dim": "2", "logger": "(deleted)"}``: the key without Hydra's ``+``/``++``, the value as written."""
    items: dict[str, str] = {}
    for text in overrides:
        text = str(text)
        if text.startswith("~"):
            key, _, value = text[1:].partition("=")
            items[key] = "(deleted)" if not value else f"(deleted {value})"
            continue
        key, _, value = text.partition("=")
        items[key.lstrip("+")] = value
    return items


def _job_number(job_dir: Path) -> Optional[int]:
    """``hydra.job.num`` from the job's .hydra/hydra.yaml, else the folder's name if it is a number."""
    try:
        hydra_cfg = yaml.safe_load((job_dir / ".hydra" / "hydra.yaml").read_text()) or {}
        return int(hydra_cfg["hydra"]["job"]["num"])
    except (OSError, ValueError, TypeError, KeyError, yaml.YAMLError):
        return int(job_dir.name) if job_dir.name.isdigit() else None


def _read_json(path: Path) -> Optional[dict[str, Any]]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def read_job(job_dir: Path, num: Optional[int] = None) -> Job:
    """The job of one folder holding ``.hydra/overrides.yaml``: ``ok`` with the values of its metrics.json,
    ``failed: <error>`` where the job recorded a failure, else ``missing metrics`` (killed, still running, or
    metrics.json unreadable)."""
    try:
        overrides = yaml.safe_load((job_dir / ".hydra" / "overrides.yaml").read_text()) or []
    except (OSError, yaml.YAMLError):
        overrides = []
    number = _job_number(job_dir) if num is None else num
    job = Job(num=-1 if number is None else number, path=job_dir, overrides=override_items(list(overrides)))
    status = _read_json(job_dir / ".hydra" / STATUS_NAME) or {}
    metrics = _read_json(job_dir / "metrics.json")
    if status.get("status") == "failed":
        job.status = f"failed: {status.get('error') or 'unknown error'}"
        job.metrics = metrics or {}  # a job that failed after writing its metrics (a figure, the sweeper) keeps them
    elif metrics is not None:
        job.status, job.metrics = "ok", metrics
    return job


def find_jobs(sweep_dir: Path) -> list[Job]:
    """The jobs of a sweep dir: every folder up to two levels below it with a ``.hydra/overrides.yaml``, by number."""
    sweep_dir = Path(sweep_dir)
    dirs = {p.parent.parent for pattern in ("*/.hydra/overrides.yaml", "*/*/.hydra/overrides.yaml")
            for p in sweep_dir.glob(pattern) if ".submitit" not in p.parts}
    jobs = [read_job(d) for d in dirs]
    return sorted(jobs, key=lambda j: (j.num < 0, j.num, str(j.path)))


def _cell(value: Any) -> str:
    """A metric for the Markdown table: numbers to 4 significant digits, a missing one as an em dash."""
    if value is None or value == "":
        return "—"
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, (int, float)):
        return "inf" if isinstance(value, float) and math.isinf(value) else f"{value:.4g}"
    return str(value)


def _md_escape(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def csv_text(jobs: list[Job]) -> str:
    """One row per job: job, status, folder, the overrides, then every metric (sorted); empty where a job has none."""
    override_keys = list(dict.fromkeys(k for j in jobs for k in j.overrides))
    metric_keys = sorted({k for j in jobs for k in j.metrics})
    taken = {"job", "status", "folder", *override_keys}
    metric_cols = [f"metrics.{k}" if k in taken else k for k in metric_keys]
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["job", "status", "folder", *override_keys, *metric_cols])
    for j in jobs:
        writer.writerow([j.num, j.status, j.path.name, *(j.overrides.get(k, "") for k in override_keys),
                         *("" if j.metrics.get(k) is None else j.metrics[k] for k in metric_keys)])
    return out.getvalue()


def markdown_text(jobs: list[Job], sweep_dir: Path, optimized_metric: Optional[str] = None) -> str:
    """The overrides that vary between the jobs × the :data:`HEADLINE` metrics (and `optimized_metric`); the
    overrides common to all jobs are named above the table."""
    override_keys = list(dict.fromkeys(k for j in jobs for k in j.overrides))
    varying = [k for k in override_keys if len({j.overrides.get(k) for j in jobs}) > 1]
    common = [f"{k}={jobs[0].overrides[k]}" for k in override_keys if k not in varying and jobs]
    metrics = list(dict.fromkeys([*HEADLINE, *([optimized_metric] if optimized_metric else [])]))
    counts = {"ok": sum(j.status == "ok" for j in jobs), "failed": sum(j.status.startswith("failed") for j in jobs)}
    missing = len(jobs) - counts["ok"] - counts["failed"]
    lines = [f"# Sweep {sweep_dir}", "",
             f"{len(jobs)} jobs: {counts['ok']} ok, {counts['failed']} failed, {missing} missing metrics."]
    if common:
        lines.append("Overrides of every job: " + " ".join(f"`{c}`" for c in common) + ".")
    if optimized_metric:
        lines.append(f"optimized_metric: `{optimized_metric}`.")
    lines += ["", "| " + " | ".join(["job", *varying, "status", *metrics]) + " |",
              "|" + "|".join(["---:", *(["---"] * len(varying)), "---", *(["---:"] * len(metrics))]) + "|"]
    for j in jobs:
        cells = [str(j.num), *(j.overrides.get(k, "") for k in varying), j.status, *(_cell(j.metrics.get(m)) for m in metrics)]
        lines.append("| " + " | ".join(_md_escape(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


@contextlib.contextmanager
def _locked(sweep_dir: Path) -> Iterator[None]:
    """An exclusive lock of the sweep dir's table (jobs that end together write in turn, the last one seeing every
    job's result); without fcntl, or where the file system refuses locks, no lock."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    try:
        fh = open(sweep_dir / ".sweep_table.lock", "a")
    except OSError:
        yield
        return
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX)
        except OSError:
            pass
        yield


def write_sweep_table(sweep_dir: "str | Path", optimized_metric: Optional[str] = None) -> Optional[tuple[Path, Path]]:
    """Write ``sweep_table.csv`` and ``sweep_table.md`` into `sweep_dir` from its job folders (atomically);
    returns their paths, or None when the folder holds no job."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        return None
    with _locked(sweep_dir):
        jobs = find_jobs(sweep_dir)
        if not jobs:
            return None
        csv_path, md_path = sweep_dir / CSV_NAME, sweep_dir / MARKDOWN_NAME
        write_text_atomic(csv_path, csv_text(jobs))
        write_text_atomic(md_path, markdown_text(jobs, sweep_dir, optimized_metric))
    return csv_path, md_path


def _error_text(error: Any, limit: int = 200) -> str:
    text = f"{type(error).__name__}: {error}" if isinstance(error, BaseException) else str(error)
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


try:
    from hydra.experimental.callback import Callback as _HydraCallback
except ImportError:  # pragma: no cover - Hydra is a dependency
    _HydraCallback = object  # type: ignore[assignment,misc]


class SweepTable(_HydraCallback):  # type: ignore[misc,valid-type]
    """Hydra callback writing :func:`write_sweep_table` into the sweep dir of a multirun: after each job (which also
    records its status) and when the multirun ends. Does nothing in a single run. A failure to write the table is
    a warning, never a failed job."""

    def on_job_end(self, config: Any, job_return: Any = None, **kwargs: Any) -> None:
        if not _is_multirun(config):
            return
        job_dir = Path(str(config.hydra.runtime.output_dir))
        status = getattr(getattr(job_return, "status", None), "name", "UNKNOWN")
        record: dict[str, Any] = {"status": "failed" if status == "FAILED" else "ok" if status == "COMPLETED" else status.lower()}
        if status == "FAILED":
            record["error"] = _error_text(getattr(job_return, "_return_value", "unknown error"))
        try:
            write_text_atomic(job_dir / ".hydra" / STATUS_NAME, json.dumps(record, indent=2))
        except OSError as err:
            log.warning("could not record the status of job %s in %s: %s", job_dir.name, job_dir, err)
        self._write(config)

    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        paths = self._write(config)
        if paths:
            log.info("sweep table: %s and %s", paths[1], paths[0])

    @staticmethod
    def _write(config: Any) -> Optional[tuple[Path, Path]]:
        try:
            sweep_dir = Path(str(config.hydra.sweep.dir))
            return write_sweep_table(sweep_dir, _optimized_metric(config))
        except Exception as err:  # noqa: BLE001 - the table is a convenience; the jobs' results are written
            log.warning("could not write the sweep table: %s: %s", type(err).__name__, err)
            return None


def _is_multirun(config: Any) -> bool:
    try:
        return str(config.hydra.mode).endswith("MULTIRUN")
    except Exception:  # noqa: BLE001 - no hydra node: not a Hydra job
        return False


def _optimized_metric(config: Any) -> Optional[str]:
    try:
        value = config.get("optimized_metric")
    except Exception:  # noqa: BLE001
        return None
    return None if value is None else str(value)
