"""Sweeps through Hydra's plugins: Optuna search, the local parallel launcher, the SLURM launcher config."""
import csv
import json

import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from helpers import CONF, METRICS_ONLY, TINY, run_cli
from lnf.train import optimized_value

pytestmark = pytest.mark.slow

TINY_RUN = ["+experiment=pendulum", "trainer=smoke", "logger=csv", "threads=1", *TINY]


def test_optuna_search_minimises_the_validation_metric(tmp_path):
    run_cli(["-m", *TINY_RUN, "hparams_search=pendulum_optuna", "hydra.sweeper.n_trials=3",
             # the validation metric is optimised (rollouts kept); no figures or long-horizon check
             "evaluation.figures=0", "evaluation.long_steps=0"], tmp_path)
    (result,) = tmp_path.glob("outputs/pendulum/multiruns/*/optimization_results.yaml")
    best = yaml.safe_load(result.read_text())
    trials = [json.loads(p.read_text()) for p in sorted(result.parent.glob("*/metrics.json"))]
    assert len(trials) == 3
    values = [t["val/field_rel_l2/all/median"] for t in trials]
    assert best["best_value"] == pytest.approx(min(values), rel=1e-6)
    assert set(best["best_params"]) == {"optimizer.lr", "model.reduction_steps", "model.w0"}
    # each trial ran with the parameters Optuna suggested
    configs = [yaml.safe_load((p.parent / ".hydra" / "overrides.yaml").read_text())
               for p in sorted(result.parent.glob("*/metrics.json"))]
    assert all(any(o.startswith("optimizer.lr=") for o in c) for c in configs)
    # the sweep's table: one row per trial, the optimised metric among the Markdown table's columns
    with open(result.parent / "sweep_table.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["job"] for r in rows] == ["0", "1", "2"] and all(r["status"] == "ok" for r in rows)
    assert sorted(float(r["val/field_rel_l2/all/median"]) for r in rows) == pytest.approx(sorted(values))
    assert "val/field_rel_l2/all/median" in (result.parent / "sweep_table.md").read_text()


def test_local_parallel_launcher_runs_jobs_with_dataloader_workers(tmp_path):
    run_cli(["-m", *TINY_RUN, "hydra/launcher=local_parallel", "data.num_workers=1", "model.latent_dim=1,2",
             # checks the jobs' metrics and table: no figures, validation rollouts or long-horizon check
             *METRICS_ONLY], tmp_path)
    runs = sorted(tmp_path.glob("outputs/pendulum/multiruns/*/*/metrics.json"))
    assert len(runs) == 2
    dims = sorted(json.loads((p.parent / "run.json").read_text())["config"]["model"]["latent_dim"] for p in runs)
    assert dims == [1, 2]
    # the jobs ran in other processes (joblib): the sweep dir still gets one table of both
    with open(runs[0].parent.parent / "sweep_table.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["job"], r["model.latent_dim"], r["status"]) for r in rows] == [("0", "1", "ok"), ("1", "2", "ok")]
    assert float(rows[0]["epochs_run"]) == 2.0
    assert "| 0 | 1 | ok |" in (runs[0].parent.parent / "sweep_table.md").read_text()


def test_slurm_launcher_config_composes():
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("train", overrides=["+experiment=pendulum", "hydra/launcher=slurm",
                                          "hydra.launcher.partition=gpu", "hydra.launcher.gpus_per_node=4",
                                          "hydra.launcher.tasks_per_node=4", "trainer=ddp", "trainer.devices=4"],
                      return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert launcher._target_ == "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
    assert launcher.partition == "gpu"
    assert launcher.tasks_per_node == cfg.trainer.devices == 4 and cfg.trainer.strategy == "ddp"
    assert launcher.max_num_timeout > 0  # a timed-out job is requeued and resumes from its checkpoint


def test_missing_optimized_metric_is_a_clear_error():
    assert optimized_value({"a": 1.0}, None) is None and optimized_value({"a": 1.0}, "a") == 1.0
    with pytest.raises(KeyError, match="optimized_metric=val/x is not among"):
        optimized_value({"a": 1.0}, "val/x")
