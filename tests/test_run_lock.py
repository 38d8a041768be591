"""One run at a time in an output folder, and a folder that never mixes two commands' results."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from helpers import METRICS_ONLY, TINY, compose_config
from lnf.run_lock import LOCK_NAME, RunFolderBusyError, run_folder_lock

HOLD = ("import sys, time; from lnf.run_lock import run_folder_lock\n"
        "with run_folder_lock(sys.argv[1], 'python -m lnf.train (test)'):\n"
        "    print('held', flush=True); time.sleep(60)\n")


def _holder(folder: Path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_run_in_a_held_folder_is_refused_naming_the_first(tmp_path):
    proc = _holder(tmp_path)
    try:
        with pytest.raises(RunFolderBusyError, match=rf"{tmp_path} is in use by another lnf run \(python -m "
                                                     rf"lnf\.train \(test\), process {proc.pid}.*hydra\.run\.dir"):
            with run_folder_lock(tmp_path, "python -m lnf.evaluate"):
                pass
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
    with run_folder_lock(tmp_path, "again"):  # released when its holder ended
        with run_folder_lock(tmp_path, "nested"):  # the same process may hold it twice (its Hydra run, then train)
            pass
    assert (tmp_path / LOCK_NAME).is_file()


def test_a_killed_run_leaves_no_stale_lock(tmp_path):
    proc = _holder(tmp_path)
    try:
        with pytest.raises(RunFolderBusyError, match=f"process {proc.pid}"):
            with run_folder_lock(tmp_path, "x"):
                pass
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    with run_folder_lock(tmp_path, "x"):  # the system released the dead process's lock
        pass


def test_train_refuses_a_folder_another_run_holds_before_any_work(tmp_path):
    from lnf.train import train

    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "logger=csv", *TINY], tmp_path)
    out = Path(cfg.paths.output_dir)
    proc = _holder(out)
    try:
        with pytest.raises(RunFolderBusyError, match="in use by another lnf run"):
            train(cfg)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert not (out / "checkpoints").exists() and not (tmp_path / "data").exists()


def test_an_evaluation_sets_earlier_results_aside_and_writes_its_provenance_first(tmp_path, monkeypatch):
    """A kill during the rollouts of an evaluation in a reused folder used to leave the old run.json beside the new
    metrics.json (or the reverse); now the old results move to previous/<time>/ and the new run.json comes first."""
    from lnf import evaluate as evaluate_module
    from lnf.train import train

    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "trainer.max_epochs=1", "logger=csv",
                                   *TINY,
                                   # the evaluation's files are checked, not the training's
                                   *METRICS_ONLY], tmp_path / "t")
    train(cfg)
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    ecfg = compose_config("evaluate", [f"ckpt_path={ckpt}", "figures=0", "split=val"], tmp_path / "e")
    out = Path(ecfg.paths.output_dir)
    out.mkdir(parents=True)
    (out / "metrics.json").write_text('{"old": 1}')
    (out / "run.json").write_text('{"command": "an older evaluation"}')

    def killed(*args, **kwargs):
        raise KeyboardInterrupt  # what a kill during the rollouts leaves

    monkeypatch.setattr("lnf.evaluation_pipeline.evaluate_rollouts", killed)
    with pytest.raises(KeyboardInterrupt):
        evaluate_module.evaluate(ecfg)
    assert not (out / "metrics.json").exists()
    run = json.loads((out / "run.json").read_text())
    assert run["config"]["split"] == "val" and run["config"]["ckpt_path"] == str(ckpt)  # the new command's
    (previous,) = (out / "previous").iterdir()
    assert json.loads((previous / "metrics.json").read_text()) == {"old": 1}  # nothing lost
    assert "an older evaluation" in (previous / "run.json").read_text()
    monkeypatch.undo()
    time.sleep(1.1)  # a second set-aside gets its own folder name
    metrics = evaluate_module.evaluate(ecfg)
    assert set(json.loads((out / "metrics.json").read_text())) == set(metrics)
    assert len(list((out / "previous").iterdir())) == 2


def test_a_refused_cli_run_leaves_the_first_runs_hydra_files_alone(tmp_path):
    """Hydra writes .hydra/ before it calls lnf.train: the folder is held from before that (RunFolderGuard)."""
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text("the first run's config\n")
    proc = _holder(run)
    try:
        env = {**os.environ, "LNF_ROOT": str(tmp_path), "WANDB_MODE": "offline"}
        for entry, args in [("lnf.train", ["+experiment=pendulum", "trainer=smoke", "logger=csv", *TINY]),
                            ("lnf.evaluate", ["ckpt_path=/nonexistent.ckpt"])]:
            cli = subprocess.run([sys.executable, "-m", entry, *args, f"hydra.run.dir={run}"], env=env,
                                 capture_output=True, text=True, timeout=300)
            assert cli.returncode != 0 and "is in use by another lnf run" in cli.stderr, cli.stderr[-2000:]
            assert (run / ".hydra" / "config.yaml").read_text() == "the first run's config\n"
            assert not (run / ".hydra" / "overrides.yaml").exists()
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)


@pytest.mark.slow
def test_an_evaluation_into_a_training_folder_keeps_the_trainings_files(tmp_path):
    """`lnf.evaluate hydra.run.dir=<a training run>` replaced the run's .hydra/ (and its metrics.json)."""
    run = tmp_path / "run"
    env = {**os.environ, "LNF_ROOT": str(tmp_path), "WANDB_MODE": "offline"}
    train = subprocess.run([sys.executable, "-m", "lnf.train", "+experiment=pendulum", "trainer=smoke",
                            "trainer.max_epochs=1", "logger=csv", *TINY,
                            *METRICS_ONLY,  # checks only which files are kept
                            f"hydra.run.dir={run}"], env=env, capture_output=True, text=True, timeout=300)
    assert train.returncode == 0, train.stderr[-2000:]
    trained = json.loads((run / "metrics.json").read_text())
    evaluate = subprocess.run([sys.executable, "-m", "lnf.evaluate", f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}",
                               "figures=0", "long_steps=0", f"hydra.run.dir={run}"], env=env, capture_output=True,
                              text=True, timeout=300)
    assert evaluate.returncode == 0, evaluate.stderr[-2000:]
    (previous,) = (run / "previous").iterdir()
    assert json.loads((previous / "metrics.json").read_text()) == trained
    assert "trainer:" in (previous / ".hydra" / "config.yaml").read_text()  # the training's config, kept
    assert "ckpt_path:" in (run / ".hydra" / "config.yaml").read_text()  # the evaluation's, beside its metrics
    assert (run / "checkpoints" / "last.ckpt").is_file()
