"""The sweep table (lnf.training.sweep_table): one CSV and one Markdown table per multirun, from the job folders."""
import csv
import json
from pathlib import Path
from types import SimpleNamespace

import yaml
from omegaconf import OmegaConf

from lnf.training.sweep_table import CSV_NAME, MARKDOWN_NAME, SweepTable, override_items, write_sweep_table

COMMON = ["+experiment=pendulum", "trainer=smoke"]


def _job(sweep: Path, num: int, overrides: list[str], metrics: dict | None = None, status: dict | None = None) -> Path:
    job = sweep / str(num)
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    (job / ".hydra" / "hydra.yaml").write_text(yaml.safe_dump({"hydra": {"job": {"num": num}}}))
    if metrics is not None:
        (job / "metrics.json").write_text(json.dumps(metrics))
    if status is not None:
        (job / ".hydra" / "job_status.json").write_text(json.dumps(status))
    return job


def _rows(sweep: Path) -> list[dict]:
    with open(sweep / CSV_NAME, newline="") as fh:
        return list(csv.DictReader(fh))


def test_two_jobs_one_without_metrics_make_one_table(tmp_path):
    sweep = tmp_path / "multirun"
    _job(sweep, 0, [*COMMON, "model.latent_dim=1"], {"field_rel_l2/all/median": 0.0123456, "energy_rel_err/max": 0.5,
                                                     "train_seconds": 12.0, "epochs_run": 2.0, "val/loss": 1e-4})
    _job(sweep, 1, [*COMMON, "model.latent_dim=2"])  # killed or still running: no metrics.json
    csv_path, md_path = write_sweep_table(sweep, optimized_metric="val/loss")
    assert csv_path == sweep / CSV_NAME and md_path == sweep / MARKDOWN_NAME
    rows = _rows(sweep)
    assert [r["job"] for r in rows] == ["0", "1"]
    assert [r["model.latent_dim"] for r in rows] == ["1", "2"] and {r["experiment"] for r in rows} == {"pendulum"}
    assert rows[0]["status"] == "ok" and float(rows[0]["field_rel_l2/all/median"]) == 0.0123456
    assert float(rows[0]["val/loss"]) == 1e-4
    assert rows[1]["status"] == "missing metrics" and rows[1]["field_rel_l2/all/median"] == ""
    md = md_path.read_text()
    header = next(line for line in md.splitlines() if line.startswith("| job"))
    assert header.split(" | ")[1] == "model.latent_dim"  # only the override that varies is a column
    for metric in ("field_rel_l2/all/median", "energy_rel_err/max", "train_seconds", "epochs_run", "val/loss"):
        assert metric in header
    assert "| 0 | 1 | ok | 0.01235 | 0.5 | 12 | 2 | 0.0001 |" in md
    assert "| 1 | 2 | missing metrics | — | — | — | — | — |" in md
    assert "`experiment=pendulum`" in md and "1 ok, 0 failed, 1 missing metrics" in md
    assert not [p for p in sweep.iterdir() if ".tmp-" in p.name]  # written under a temporary name, then renamed


def test_a_failed_job_says_so_and_the_table_is_rewritten_when_the_multirun_ends(tmp_path):
    sweep = tmp_path / "multirun"
    _job(sweep, 0, [*COMMON, "model.latent_dim=1"], {"epochs_run": 2.0})
    failed = _job(sweep, 1, [*COMMON, "model.latent_dim=0"])
    cfg = OmegaConf.create({"optimized_metric": None, "hydra": {
        "mode": "MULTIRUN", "sweep": {"dir": str(sweep)}, "runtime": {"output_dir": str(failed)}}})
    callback = SweepTable()
    job_return = SimpleNamespace(status=SimpleNamespace(name="FAILED"),
                                 _return_value=ValueError("model.latent_dim must be ≥ 1, got 0"))
    callback.on_job_end(cfg, job_return=job_return)  # the failed job records its status and writes the table
    assert json.loads((failed / ".hydra" / "job_status.json").read_text())["status"] == "failed"
    rows = _rows(sweep)
    assert rows[1]["status"] == "failed: ValueError: model.latent_dim must be ≥ 1, got 0"
    _job(sweep, 2, [*COMMON, "model.latent_dim=2"], {"epochs_run": 2.0})
    callback.on_multirun_end(cfg)
    assert [r["status"] for r in _rows(sweep)] == ["ok", "failed: ValueError: model.latent_dim must be ≥ 1, got 0", "ok"]
    assert "2 ok, 1 failed, 0 missing metrics" in (sweep / MARKDOWN_NAME).read_text()


def test_a_single_run_writes_no_table(tmp_path):
    job = _job(tmp_path, 0, COMMON, {"epochs_run": 2.0})
    cfg = OmegaConf.create({"hydra": {"mode": "RUN", "sweep": {"dir": str(tmp_path)},
                                      "runtime": {"output_dir": str(job)}}})
    SweepTable().on_job_end(cfg, job_return=SimpleNamespace(status=SimpleNamespace(name="COMPLETED")))
    assert not (tmp_path / CSV_NAME).exists() and not (job / ".hydra" / "job_status.json").exists()


def test_overrides_become_key_value_columns():
    assert override_items(["+experiment=pendulum", "++seed=3", "model.lr=1e-3", "~logger", "x=a=b"]) == {
        "experiment": "pendulum", "seed": "3", "model.lr": "1e-3", "logger": "(deleted)", "x": "a=b"}
