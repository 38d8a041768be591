"""A quiet, informative console: `python -m lnf.train` prints lnf's lines, the progress bar and the end-of-run table,
without Lightning's tips, deprecation noise or wandb's banner, and still shows lnf's own warnings and errors."""
import logging
import os
import re
import subprocess
import sys
import warnings

import pytest

from helpers import ROOT, TINY
from lnf.training.console import format_metric, quiet_console
from lnf.training.progress_bar import MetricsProgressBar


def _run(args: list[str], root) -> subprocess.CompletedProcess:
    # wandb's own settings (conf/logger/wandb.yaml) must keep it quiet: not the WANDB_SILENT the test suite sets
    env = {k: v for k, v in os.environ.items() if k != "WANDB_SILENT"}
    env.update(LNF_ROOT=str(root), WANDB_MODE="offline", COLUMNS="200")
    return subprocess.run([sys.executable, "-m", "lnf.train", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=300)


@pytest.mark.slow
def test_a_training_run_prints_no_noise_and_still_warns(tmp_path):
    # the default trainer (progress bar on, log_every_n_steps=10 > the 1 batch per epoch) and the default logger
    # (offline wandb + CSV); a setting the model does not take provokes a real lnf warning
    proc = _run(["+experiment=pendulum", "trainer.max_epochs=2", "threads=1", *TINY, "evaluation.figures=0",
                 "+model.not_a_setting=1"], tmp_path)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    for noise in ("Tip:", "deprecated", "v_num", "LeafSpec", "smaller than the logging interval", "GPU available",
                  "Tracking run with wandb", "anonymous", "wandb leet", "weights_only", "Seed set to"):
        assert noise not in out, f"{noise!r} printed:\n{out}"
    assert len(re.findall(r"reusing dataset|generating \w+ dataset", out)) == 1, out  # the dataset, said once
    assert "LagrangianNeuralField takes no model.not_a_setting: dropped" in out  # lnf's warning still shows
    assert re.search(r"\d\.\d\de[-+]\d\d", out), out  # a loss in the progress bar, in scientific notation
    assert "field_rel_l2/all/median" in out and re.search(r"epochs_run\s*│\s*2 of 2", out), out  # the final table
    assert "all 2 epochs ran" in out and "wandb sync" in out  # how to upload the offline wandb run, once
    assert out.count("wandb sync") == 1, out


@pytest.mark.slow
def test_an_error_still_shows(tmp_path):
    proc = _run(["+experiment=pendulum", "trainer=smoke", "logger=csv", *TINY, "model.latent_dim=0"], tmp_path)
    assert proc.returncode != 0
    assert "model.latent_dim must be an integer ≥ 1 (the latent dimension d), got 0" in proc.stderr + proc.stdout


def test_only_the_known_noise_is_filtered(caplog):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        quiet_console()
        warnings.warn("`isinstance(treespec, LeafSpec)` is deprecated, use ...", FutureWarning)
        warnings.warn("The number of training batches (1) is smaller than the logging interval "
                      "Trainer(log_every_n_steps=10).", UserWarning)
        warnings.warn("Checkpoint directory /x/checkpoints exists and is not empty.", UserWarning)
        warnings.warn("another deprecation is deprecated", FutureWarning)  # not ours to hide
        warnings.warn("validation rollout: 1 of 1 trajectories diverged", UserWarning)
    assert [str(w.message) for w in caught] == ["another deprecation is deprecated",
                                                "validation rollout: 1 of 1 trajectories diverged"]
    lightning = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    with caplog.at_level(logging.INFO, logger="lightning.pytorch.utilities.rank_zero"):
        lightning.propagate, propagate = True, lightning.propagate
        try:
            lightning.info("💡 Tip: For seamless cloud logging ...")
            lightning.info("GPU available: False, used: False")
            lightning.info("`Trainer.fit` stopped: `max_epochs=2` reached.")
            lightning.info("`Trainer.fit` stopped: `max_steps=5` reached.")  # not the epoch budget: kept
            lightning.warning("💡 Tip: a warning is never dropped")
        finally:
            lightning.propagate = propagate
    assert [r.getMessage() for r in caplog.records] == ["`Trainer.fit` stopped: `max_steps=5` reached.",
                                                       "💡 Tip: a warning is never dropped"]


def test_progress_bar_metrics_are_in_scientific_notation_without_v_num():
    assert format_metric(1.234e-4) == "1.23e-04" and format_metric(3) == 3 and format_metric("x") == "x"

    class Trainer:
        progress_bar_metrics = {"train/loss": 1.234e-4, "val/loss": 0.5}
        loggers = [type("L", (), {"version": "abc"})()]

    bar = MetricsProgressBar()
    assert bar.get_metrics(Trainer(), None) == {"train/loss": "1.23e-04", "val/loss": "5.00e-01"}


def test_font_subsetting_of_pdf_figures_is_not_logged(monkeypatch):
    """matplotlib's PDF backend subsets fonts with fontTools, which logs every glyph list at INFO (an evaluation
    under Hydra's INFO root logger printed about 40 such lines per figure); a level the user chose is kept."""
    fonts = logging.getLogger("fontTools")
    monkeypatch.setattr(fonts, "level", logging.NOTSET)
    quiet_console()
    assert not logging.getLogger("fontTools.subset").isEnabledFor(logging.INFO)
    fonts.setLevel(logging.DEBUG)
    quiet_console()
    assert fonts.level == logging.DEBUG
    fonts.setLevel(logging.NOTSET)


def test_scikit_fems_assembly_log_is_not_shown(monkeypatch):
    """scikit-fem logs every basis it builds and every form it assembles at INFO (dozens of lines before an elastic
    scene's data are generated)."""
    fem = logging.getLogger("skfem")
    monkeypatch.setattr(fem, "level", logging.NOTSET)
    quiet_console()
    assert not logging.getLogger("skfem.assembly").isEnabledFor(logging.INFO)
