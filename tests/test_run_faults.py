"""Faults of a training run that must lose nothing: failed checkpoint writes, damaged checkpoints, a figure
that cannot be drawn, a time limit, a checkpoint of another scene, settings that fail only at test time.
Tiny pendulum runs in-process; a test that resumes a finished run resumes its own copy of it."""
import errno
import json
import logging
import os
import shutil
from pathlib import Path

import pytest
import torch

from helpers import METRICS_ONLY, TINY, compose_config, result_metrics
from lnf.train import train
from lnf.training import checkpoints as C

pytestmark = pytest.mark.slow

BASE = ["+experiment=pendulum", "trainer=smoke", "logger=csv", *TINY]


def _cfg(tmp_path: Path, *overrides: str):
    return compose_config("train", [*BASE, *overrides], tmp_path)


def _out(tmp_path: Path) -> Path:
    return tmp_path / "out"


def _loads(path: Path) -> bool:
    return C.read_checkpoint(path)[0] is not None


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished 2-epoch run (folder with out/ and data/) and its metrics; tests copy it, never change it."""
    root = tmp_path_factory.mktemp("finished")
    return root, train(_cfg(root, "trainer.max_epochs=2", *METRICS_ONLY))


def _copy_of(finished, tmp_path: Path) -> Path:
    shutil.copytree(finished[0], tmp_path, dirs_exist_ok=True)
    return tmp_path


# ----------------------------------------------------------------------------------------- writing checkpoints
def _failing_save(fail_on: int):
    """torch.save that writes half its bytes and then raises ENOSPC on call number `fail_on` (1-based)."""
    real, calls = torch.save, {"n": 0}

    def save(obj, fh, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == fail_on:
            fh.write(b"\0" * 1000)
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(obj, fh, *args, **kwargs)

    return save


def test_a_failed_checkpoint_write_keeps_the_old_file_and_names_the_cause(tmp_path, monkeypatch):
    path = tmp_path / "last.ckpt"
    C.save_atomic({"state_dict": {}, "epoch": 1}, path)
    before = path.read_bytes()
    monkeypatch.setattr(C.torch, "save", _failing_save(1))
    with pytest.raises(C.CheckpointWriteError, match=r"last\.ckpt.*disk is full"):
        C.save_atomic({"state_dict": {}, "epoch": 2}, path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["last.ckpt"], "a temporary was left behind"


def test_temporaries_of_killed_checkpoint_writers_are_removed_on_resume(tmp_path):
    import subprocess
    import sys

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    stale, live = folder / f"last.ckpt.tmp-{gone.stdout.strip()}", folder / f"last.ckpt.tmp-{os.getpid()}"
    stale.write_bytes(b"\0" * 10)
    live.write_bytes(b"\0" * 10)
    assert C.resume_checkpoint(None, tmp_path) == (None, None)
    assert not stale.exists() and live.exists()


def test_disk_full_while_training_leaves_only_loadable_checkpoints_and_the_run_resumes(tmp_path, monkeypatch):
    cfg = _cfg(tmp_path, "trainer.max_epochs=2", *METRICS_ONLY)
    monkeypatch.setattr(C.torch, "save", _failing_save(3))  # epoch 0: best + last; epoch 1: the best's write fails
    with pytest.raises(C.CheckpointWriteError, match="disk is full"):
        train(cfg)
    folder = _out(tmp_path) / "checkpoints"
    assert sorted(folder.iterdir()) and all(_loads(p) for p in folder.iterdir()), sorted(folder.iterdir())
    monkeypatch.undo()
    metrics = train(_cfg(tmp_path, "trainer.max_epochs=2", *METRICS_ONLY))  # the same command picks the valid checkpoint up
    assert metrics["epochs_run"] == 2 and (_out(tmp_path) / "metrics.json").is_file()


def test_resume_skips_a_truncated_checkpoint_for_the_newest_valid_one(finished, tmp_path, caplog):
    _copy_of(finished, tmp_path)
    folder = _out(tmp_path) / "checkpoints"
    last = folder / "last.ckpt"
    last.write_bytes(last.read_bytes()[:500])  # truncated, as a full disk left it with Lightning's own writer
    (_out(tmp_path) / "metrics.json").unlink()
    with caplog.at_level(logging.WARNING, logger="lnf.train"):
        metrics = train(_cfg(tmp_path, "trainer.max_epochs=3", *METRICS_ONLY))
    assert "skipping checkpoint" in caplog.text and "last.ckpt" in caplog.text
    assert metrics["epochs_run"] == 3 and _loads(last)
    # ckpt_path=last falls back the same way; an explicit file that does not load is an error naming it
    bad = folder / "bad.ckpt"
    bad.write_bytes(b"\0" * 64)
    assert C.resume_checkpoint("last", _out(tmp_path))[0] == last
    with pytest.raises(ValueError, match=r"ckpt_path=.*bad\.ckpt.*does not load"):
        C.resume_checkpoint(str(bad), _out(tmp_path))


# ------------------------------------------------------------------------------------------- results first
def test_a_figure_that_cannot_be_drawn_is_a_warning_after_the_results_are_written(tmp_path, monkeypatch, caplog):
    import lnf.plotting

    def broken(*args, **kwargs):
        raise ValueError("grid_shape must be a pair of positive ints")  # what a 1-D body raised

    monkeypatch.setattr(lnf.plotting, "figure3", broken)
    with caplog.at_level(logging.WARNING, logger="lnf.evaluation"):  # Figure 3 drawn, without the rest of METRICS_ONLY
        metrics = train(_cfg(tmp_path, "evaluation.every_n_epochs=0", "evaluation.long_steps=0"))
    out = _out(tmp_path)
    assert json.loads((out / "metrics.json").read_text()).keys() == metrics.keys()
    assert _loads(out / "checkpoints" / "last.ckpt")
    assert "could not draw Figure 3" in caplog.text and "grid_shape" in caplog.text


# -------------------------------------------------------------------------------------- budgets are epochs
def test_no_experiment_has_a_time_limit_by_default(tmp_path):
    for experiment in ("pendulum", "double_pendulum", "bump", "elastic", "elastic_actuated"):
        cfg = compose_config("train", [f"+experiment={experiment}"], tmp_path)
        assert cfg.trainer.max_time is None, experiment


def test_a_time_limit_that_stops_training_is_recorded_and_said(finished, tmp_path, capsys):
    train(_cfg(tmp_path, "trainer.max_epochs=3", 'trainer.max_time="00:00:00:00"', *METRICS_ONLY))
    saved = json.loads((_out(tmp_path) / "metrics.json").read_text())
    assert saved["stopped_by_time_limit"] == 1.0 and saved["epochs_run"] < saved["max_epochs"] == 3
    assert "STOPPED by the time limit" in capsys.readouterr().out
    full = finished[1]
    assert full["stopped_by_time_limit"] == 0.0 and full["epochs_run"] == full["max_epochs"] == 2
    assert full["global_steps"] == 2 * 3  # 3 batches of 8 of the 30 training snapshots, drop_last


# ------------------------------------------------------------------------------------------------- resuming
def test_resuming_a_checkpoint_of_another_scene_is_refused_unless_asked_for(finished, tmp_path, caplog):
    _copy_of(finished, tmp_path)
    (_out(tmp_path) / "metrics.json").unlink()
    other = ["trainer.max_epochs=3", "scene.length=1.5", *METRICS_ONLY]  # same shapes, another pendulum
    with pytest.raises(ValueError, match=r"trained on another scene.*scene\.length.*resume_other_scene=true"):
        train(_cfg(tmp_path, *other))
    assert not (_out(tmp_path) / "metrics.json").exists()
    with caplog.at_level(logging.WARNING, logger="lnf.train"):
        metrics = train(_cfg(tmp_path, *other, "resume_other_scene=true"))
    assert metrics["epochs_run"] == 3 and "trained on another scene" in caplog.text


def test_a_resumed_run_keeps_its_log_and_provenance_history(finished, tmp_path):
    _copy_of(finished, tmp_path)
    train(_cfg(tmp_path, "trainer.max_epochs=3", *METRICS_ONLY))
    out = _out(tmp_path)
    assert [p.name for p in (out / "csv").iterdir()] == ["version_0"]
    rows = (out / "csv" / "version_0" / "metrics.csv").read_text().splitlines()
    header = rows[0].split(",")
    epoch_col = header.index("epoch")
    assert {r.split(",")[epoch_col] for r in rows[1:]} >= {"0", "1", "2"}, "the first run's rows were lost"
    run = json.loads((out / "run.json").read_text())
    assert len(run["previous_runs"]) == 1 and run["config"]["trainer"]["max_epochs"] == 3
    assert run["previous_runs"][0]["config"]["trainer"]["max_epochs"] == 2


# --------------------------------------------------------------------------------------- settings checked first
@pytest.mark.parametrize("overrides, match", [
    (["quadrature.order=0", "evaluation.every_n_epochs=0"], r"quadrature=.*order"),
    (["evaluation.every_n_epochs=-1"], r"evaluation\.every_n_epochs must be an integer ≥ 0, got -1"),
    (["evaluation.long_dt=0"], r"evaluation\.long_dt must be a finite number > 0"),
    (["evaluation.figures=1.5"], r"evaluation\.figures must be an integer"),
    (["trainer.max_epochs=0"], r"trainer\.max_epochs must be an integer ≥ 1"),
])
def test_settings_that_would_fail_at_test_time_fail_before_training(overrides, match, tmp_path):
    with pytest.raises(ValueError, match=match):
        train(_cfg(tmp_path, *overrides))
    assert not (_out(tmp_path) / "checkpoints").exists(), "training ran before the error"


def test_a_damaged_test_split_is_regenerated_before_training(finished, tmp_path, caplog):
    """An inf in the test split used to surface after every epoch had run; the file is checked first and
    regenerated like any damaged file."""
    import h5py

    _copy_of(finished, tmp_path)
    shutil.rmtree(_out(tmp_path))
    (data,) = (tmp_path / "data").glob("*.h5")
    with h5py.File(data, "r+") as f:
        f["test/fields"][0, 3, 5, 0] = float("inf")
    with caplog.at_level(logging.WARNING, logger="lnf.dataset"):
        metrics = train(_cfg(tmp_path, "trainer.max_epochs=2", *METRICS_ONLY))
    assert "regenerating" in caplog.text and "/test/fields" in caplog.text
    assert result_metrics(metrics) == result_metrics(finished[1])


def test_a_resumed_checkpoint_of_other_settings_is_refused_unless_asked_for(finished, tmp_path, caplog):
    """Resuming with model.w0=30 continued weights trained at w0=10, and the new checkpoint recorded w0=30; a new
    lr was silently replaced by the checkpoint's optimizer state; other data relabelled last.ckpt's data record."""
    _copy_of(finished, tmp_path)
    (_out(tmp_path) / "metrics.json").unlink()
    for other, named in [(["model.w0=30", "quadrature.order=6"], r"model\.w0: checkpoint 10\.0, config 30.*"
                                                                 r"quadrature\.order: checkpoint 4, config 6"),
                         (["optimizer.lr=0.1"], r"optimizer\.lr: checkpoint 0\.0003, config 0\.1"),
                         (["data.seed=5"], r"data\.seed: checkpoint 0, config 5")]:
        with pytest.raises(ValueError, match=rf"trained with other settings \({named}.*resume_other_settings=true"):
            train(_cfg(tmp_path, "trainer.max_epochs=3", *other, *METRICS_ONLY))
        assert not (_out(tmp_path) / "metrics.json").exists()
    with caplog.at_level(logging.WARNING, logger="lnf.train"):
        metrics = train(_cfg(tmp_path, "trainer.max_epochs=3", "optimizer.lr=0.1", "resume_other_settings=true",
                             *METRICS_ONLY))
    assert metrics["epochs_run"] == 3 and "optimizer.lr: checkpoint 0.0003, config 0.1" in caplog.text


def test_a_resumed_checkpoint_cannot_make_training_delete_files_outside_its_folder(finished, tmp_path, caplog):
    """ModelCheckpoint deletes the files its restored state lists when it keeps its top k: a crafted state listing
    ../../victim.txt deleted that file on resume."""
    _copy_of(finished, tmp_path)
    out = _out(tmp_path)
    (out / "metrics.json").unlink()
    victim, notes = tmp_path / "victim.txt", out / "checkpoints" / "my_notes.txt"
    mine = out / "checkpoints" / "mine.ckpt"  # a user's own checkpoint beside the run's: not the callback's to delete
    victim.write_text("a user's file")
    notes.write_text("a user's notes beside the checkpoints")
    mine.write_text("a user's checkpoint")
    ckpt = torch.load(out / "checkpoints" / "last.ckpt", weights_only=True)
    for key, state in ckpt["callbacks"].items():
        if key.startswith("ModelCheckpoint"):
            outside = str(out / "checkpoints" / ".." / ".." / "victim.txt")
            state.update(dirpath=str(out / "checkpoints"), best_model_path=outside, kth_best_model_path=str(notes),
                         last_model_path=outside, best_k_models={outside: torch.tensor(1e9), str(notes): torch.tensor(1e9),
                                                                 str(mine): torch.tensor(1e9)},
                         best_model_score=torch.tensor(1e9), kth_value=torch.tensor(1e9))
    for name in ("last.ckpt", *[p.name for p in (out / "checkpoints").glob("epoch*.ckpt")]):
        torch.save(ckpt, out / "checkpoints" / name)
    with caplog.at_level(logging.WARNING, logger="lnf.train"):
        metrics = train(_cfg(tmp_path, "trainer.max_epochs=3", *METRICS_ONLY))
    assert metrics["epochs_run"] == 3
    assert victim.read_text() == "a user's file" and notes.read_text() == "a user's notes beside the checkpoints"
    assert mine.read_text() == "a user's checkpoint"
    assert "not this callback's own checkpoints" in caplog.text and "victim.txt" in caplog.text


def test_a_fresh_run_in_a_folder_with_earlier_results_keeps_them(tmp_path):
    """lnf.train in a folder holding an earlier evaluation's metrics.json (no checkpoint to resume) overwrote it."""
    out = _out(tmp_path)
    out.mkdir(parents=True)
    (out / "metrics.json").write_text('{"an earlier": "evaluation"}')
    (out / "run.json").write_text("not json, a user's notes")
    train(_cfg(tmp_path, "trainer.max_epochs=1", *METRICS_ONLY))
    (previous,) = (out / "previous").iterdir()
    assert json.loads((previous / "metrics.json").read_text()) == {"an earlier": "evaluation"}
    assert (previous / "run.json").read_text() == "not json, a user's notes"
    assert "epochs_run" in json.loads((out / "metrics.json").read_text())


def test_no_samples_after_the_training_horizon_is_refused_before_any_data(tmp_path):
    """data.train_times = data.n_times scored trained samples as 'extrapolation' (and lnf.evaluate crashed)."""
    with pytest.raises(ValueError, match=r"data\.train_times=20 must be below data\.n_times=20"):
        train(_cfg(tmp_path, "data.train_times=20"))
    assert not (tmp_path / "data").exists()



_SIGTERM_IN_TEST_PHASE = """
import os, signal, sys, time
import torch, lightning.pytorch as pl
from lnf.training.signals import ended_by_sigterm

class Module(pl.LightningModule):
    def __init__(self):
        super().__init__()
        self.layer = torch.nn.Linear(1, 1)

    def test_step(self, batch, index):
        return None

class SlowRollouts(pl.Callback):  # as lnf's evaluation callback: the test rollouts run after the last batch
    def on_test_epoch_end(self, trainer, module):
        os.kill(os.getpid(), signal.SIGTERM)
        start = time.monotonic()
        while time.monotonic() - start < 30:
            sum(range(1000))
        print("the rollouts ran to their end", flush=True)

trainer = pl.Trainer(logger=False, enable_progress_bar=False, enable_model_summary=False, callbacks=[SlowRollouts()])
data = torch.utils.data.DataLoader(torch.zeros(2, 1), batch_size=1)
with ended_by_sigterm():
    trainer.test(Module(), data, verbose=False)
"""


def test_sigterm_stops_a_run_in_its_test_rollouts():
    """Lightning's SIGTERM handler only sets a flag its loops read between batches: in the test rollouts (after the
    last batch) a `kill` went unheeded for as long as they took. Under lnf.train's ended_by_sigterm it stops."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "SLURM_JOB_ID"}
    proc = subprocess.run([sys.executable, "-c", _SIGTERM_IN_TEST_PHASE], capture_output=True, text=True,
                          timeout=120, env=env)
    assert proc.returncode == 143, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "the rollouts ran to their end" not in proc.stdout


def test_sigterm_handling_is_lightnings_under_slurm_and_restored_after_the_run(monkeypatch):
    import signal

    from lnf.training.signals import ended_by_sigterm

    monkeypatch.delenv("SLURM_JOB_ID", raising=False)  # a CI machine under SLURM: its value is restored afterwards
    before = signal.getsignal(signal.SIGTERM)
    with ended_by_sigterm():
        assert signal.getsignal(signal.SIGTERM) is not before
    assert signal.getsignal(signal.SIGTERM) is before
    monkeypatch.setenv("SLURM_JOB_ID", "1")
    with ended_by_sigterm():
        assert signal.getsignal(signal.SIGTERM) is before  # SLURM's auto-requeue keeps the signal
