"""Each run of a process logs into a wandb run of its own (a Hydra multirun runs its jobs in one process)."""
from __future__ import annotations

from pathlib import Path

import pytest

from helpers import TINY, compose_config


@pytest.mark.slow
def test_two_runs_in_one_process_log_into_two_wandb_runs(tmp_path, monkeypatch):
    """The second job of a multirun used to log into the first job's wandb run (Lightning reuses an open run)."""
    from lnf.train import train

    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    runs = []
    for k in range(2):
        cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "trainer.max_epochs=1",
                                       "logger=wandb", *TINY, "evaluation.figures=0", "evaluation.every_n_epochs=0",
                                       f"seed={k}"], tmp_path / f"job{k}")
        train(cfg)
        (found,) = (Path(cfg.paths.output_dir) / "wandb").glob("offline-run-*")  # its own run, in its own folder
        runs.append(found.name.rsplit("-", 1)[-1])
    assert runs[0] != runs[1]
    import wandb

    assert wandb.run is None  # nothing left open for the next job
