"""The worked example of docs/own_system.md: a scene kept outside the package (examples/), with its own config
folder, trains, evaluates, draws its 1-D Figure 3 and loads with lnf.load, with no change to lnf/."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import ROOT, TINY

pytestmark = pytest.mark.slow

EXAMPLES = ROOT / "examples"
SMOKE = [t for t in TINY if not t.startswith(("data.fine_resolution", "data.coarse_resolution", "quadrature."))] + [
    "data.fine_resolution=32", "data.coarse_resolution=16"]


def _env(tmp_path: Path, with_examples: bool = True) -> dict:
    path = [str(ROOT)] + ([str(EXAMPLES)] if with_examples else [])
    return {**os.environ, "PYTHONPATH": os.pathsep.join(path), "LNF_ROOT": str(tmp_path), "WANDB_MODE": "offline"}


def test_the_vibrating_string_passes_check_scene():
    from vibrating_string import VibratingString

    from lnf.scenes.check import check_scene

    assert check_scene(VibratingString()).ok and check_scene(VibratingString(modes=3)).ok
    caps = VibratingString().capabilities()
    assert caps["conservative"] and caps["clamp"] and caps["field_gradients"] and caps["release_at_rest"]


def test_the_vibrating_string_trains_evaluates_draws_and_loads_from_its_own_config_dir(tmp_path):
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "lnf.train", "--config-dir", str(EXAMPLES / "conf"), "+experiment=vibrating_string",
           "trainer=smoke", "trainer.max_epochs=2", "logger=csv", "threads=1", *SMOKE,
           # checks test metrics, the figure and loading: no validation rollouts or long-horizon check
           "evaluation.every_n_epochs=0", "evaluation.long_steps=0", f"hydra.run.dir={run}"]
    proc = subprocess.run(cmd, cwd=ROOT, env=_env(tmp_path), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    metrics = json.loads((run / "metrics.json").read_text())
    assert "field_rel_l2/all/median" in metrics and metrics["epochs_run"] == 2
    assert (run / "figures" / "test_trajectory0.png").stat().st_size > 0  # the 1-D Figure 3
    spec = json.loads((run / "run.json").read_text())["config"]["scene"]
    assert spec["_target_"] == "vibrating_string.VibratingString"

    ckpt = run / "checkpoints" / "last.ckpt"
    load = [sys.executable, "-c", f"import lnf; m = lnf.load({str(ckpt)!r}, trust=['vibrating_string']); "
            f"print(type(m.scene).__name__)"]
    ok = subprocess.run(load, cwd=tmp_path, env=_env(tmp_path), capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and ok.stdout.strip() == "VibratingString", ok.stderr[-2000:]
    # a scene of one's own is a module outside lnf: it is built only when trusted by name (here: not trusted)
    untrusted = subprocess.run([sys.executable, "-c", f"import lnf; lnf.load({str(ckpt)!r})"], cwd=tmp_path,
                               env=_env(tmp_path), capture_output=True, text=True, timeout=120)
    assert untrusted.returncode != 0 and "UntrustedTargetError" in untrusted.stderr
    assert "trust=['vibrating_string']" in untrusted.stderr and "LNF_TRUST=vibrating_string" in untrusted.stderr
    lost = subprocess.run(load, cwd=tmp_path, env=_env(tmp_path, with_examples=False), capture_output=True,
                          text=True, timeout=120)
    assert lost.returncode != 0 and "cannot import module 'vibrating_string'" in lost.stderr
    assert "PYTHONPATH" in lost.stderr

    # evaluated on scattered points, in this process (the example's folder on the path, as PYTHONPATH does: the
    # `pythonpath` of pyproject's pytest settings)
    from helpers import compose_config
    from lnf.evaluate import evaluate

    metrics = evaluate(compose_config("evaluate", [f"ckpt_path={ckpt}", "grid.kind=random", "grid.n_points=50",
                                                   "figures=0", "trust=[vibrating_string]"], tmp_path / "eval"))
    assert "field_rel_l2/all/median" in metrics and metrics["diverged_count"] >= 0


def test_precomputed_trajectories_from_arrays_train_with_a_scene_that_has_only_its_lagrangian(tmp_path):
    """The second example: a foreign simulator's arrays (a lumped-mass FEM string on a graded mesh) written with
    lnf.trajectories.write_dataset train a scene without simulate() or fields(), integrated on the mesh's own
    nodes (quadrature=stored); the file's settings are used, not data.*."""
    from helpers import compose_config
    from lnf.train import train

    import string_from_arrays

    caps = string_from_arrays.StringLagrangian().capabilities()
    assert not caps["simulator"] and not caps["fields"] and not caps["true_energies"]
    path = string_from_arrays.main([str(tmp_path / "string.h5"), "--trajectories", "3", "1", "2", "--times", "16",
                                    "--nodes", "17"])
    cfg = compose_config("train", ["+experiment=string_from_arrays", "hydra.searchpath=[file://" + str(EXAMPLES / "conf") + "]",
                                   f"data.path={path}", "trainer=smoke", "trainer.max_epochs=1", "logger=csv",
                                   "threads=1", "model.width=16", "model.hyper_width=8", "evaluation.long_steps=10",
                                   "evaluation.long_trajectories=1", "evaluation.every_n_epochs=1",
                                   "evaluation.val_trajectories=1", "evaluation.figures=1"], tmp_path)
    metrics = train(cfg)
    assert metrics["evaluation_points"] == 17 and metrics["frames"] == 16 and metrics["epochs_run"] == 1
    assert "energy_rel_err/max" in metrics  # the stored energies are the reference (absent without them)
    assert (tmp_path / "out" / "figures" / "test_trajectory0.png").stat().st_size > 0
