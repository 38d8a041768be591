"""Opening a checkpoint runs no code it carries: no unpickled objects, and only lnf's classes or trusted ones."""
from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

import pytest
import torch

import lnf
from lnf.model import build_model
from lnf.training.checkpoints import resume_checkpoint
from lnf.trust import UnsafeCheckpointError, UntrustedTargetError, check_spec_targets

SPECS = {
    "scene": {"_target_": "lnf.scenes.LiftedPendulum"},
    "model": {"_target_": "lnf.model.LagrangianNeuralField", "latent_dim": 1, "width": 8, "depth": 1,
              "hyper_width": 4},
    "quadrature": {"_target_": "lnf.quadrature.GaussLegendre", "order": 2},
}


def _checkpoint(path: Path, **changes: dict) -> Path:
    """A small lnf checkpoint (what lnf.train writes, without training), with `changes` to its specs."""
    model = build_model(SPECS["scene"], SPECS["model"], SPECS["quadrature"])
    specs = {k: {**v, **changes.get(k, {})} for k, v in SPECS.items()}
    torch.save({"epoch": 0, "global_step": 0, "hyper_parameters": {**specs, "data": None},
                "state_dict": {f"model.{k}": v for k, v in model.state_dict().items()}}, path)
    return path


class _Payload:
    """Unpickling this runs `touch <marker>`: what a hostile checkpoint carries."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_a_checkpoint_of_lnf_classes_loads(tmp_path):
    model = lnf.load(_checkpoint(tmp_path / "ok.ckpt"))
    assert type(model).__name__ == "LagrangianNeuralField"


def test_a_pickled_payload_is_never_run_by_load_or_resume(tmp_path, caplog):
    marker = tmp_path / "ran"
    ckpt = torch.load(_checkpoint(tmp_path / "ok.ckpt"), weights_only=True)
    ckpt["callbacks"] = {"x": _Payload(marker)}
    bad = tmp_path / "bad.ckpt"
    torch.save(ckpt, bad)
    with pytest.raises(UnsafeCheckpointError, match=r"bad\.ckpt holds pickled Python objects.*posix\.system|system"):
        lnf.load(bad)
    assert not marker.exists()
    # a resumed run skips such a file (named in a warning) and never unpickles it
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    torch.save(ckpt, run / "checkpoints" / "last.ckpt")
    with caplog.at_level(logging.WARNING, logger="lnf.train"):
        assert resume_checkpoint(None, run) == (None, None)
    assert "skipping checkpoint" in caplog.text and "pickled Python objects" in caplog.text
    with pytest.raises(ValueError, match="pickled Python objects"):
        resume_checkpoint(str(run / "checkpoints" / "last.ckpt"), run)
    assert not marker.exists()


@pytest.mark.parametrize("key, target, message", [
    ("scene", "os.system", r"scene\._target_ = 'os\.system' names a class outside lnf, from module 'os'"),
    ("quadrature", "lnf.tempfiles.write_text_atomic", r"not one of lnf's scene, model, quadrature"),
    ("model", "lnf.model.Path", r"not one of lnf's scene, model, quadrature"),
    ("scene", "os.system; rm", r"not a class path"),
])
def test_a_target_outside_lnf_is_refused_before_anything_is_called(tmp_path, key, target, message):
    path = _checkpoint(tmp_path / "c.ckpt", **{key: {"_target_": target}})
    with pytest.raises(UntrustedTargetError, match=message):
        lnf.load(path)


def test_a_module_of_ones_own_is_imported_only_when_trusted_by_name(tmp_path, monkeypatch):
    marker = tmp_path / "imported"
    (tmp_path / "ownpkg_lnf_test.py").write_text(
        f"from pathlib import Path\nPath({str(marker)!r}).touch()\n"
        "from lnf.scenes import LiftedPendulum\n\nclass Mine(LiftedPendulum):\n    pass\n\n"
        "def function():\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delenv("LNF_TRUST", raising=False)
    path = _checkpoint(tmp_path / "c.ckpt", scene={"_target_": "ownpkg_lnf_test.Mine"})
    with pytest.raises(UntrustedTargetError, match=r"trust=\['ownpkg_lnf_test'\].*LNF_TRUST=ownpkg_lnf_test"):
        lnf.load(path)
    assert not marker.exists() and "ownpkg_lnf_test" not in sys.modules  # refused before import
    assert type(lnf.load(path, trust=["ownpkg_lnf_test"]).scene).__name__ == "Mine"
    monkeypatch.setenv("LNF_TRUST", "other, ownpkg_lnf_test")
    assert type(lnf.load(path).scene).__name__ == "Mine"
    # trusting a module trusts its classes, not any callable in it
    with pytest.raises(UntrustedTargetError, match="is a function, not a class"):
        check_spec_targets({"scene": {"_target_": "ownpkg_lnf_test.function"}}, "x.ckpt", ["ownpkg_lnf_test"])
    # nor a module whose name merely starts the same
    with pytest.raises(UntrustedTargetError, match="outside lnf"):
        check_spec_targets({"scene": {"_target_": "ownpkg_lnf_test_evil.Mine"}}, "x.ckpt", ["ownpkg_lnf_test"])
    with pytest.raises(ValueError, match="is not a module name"):
        check_spec_targets({}, "x.ckpt", ["not a module"])


def test_nested_targets_are_checked_too(tmp_path):
    path = _checkpoint(tmp_path / "c.ckpt", model={"dynamics": {"_target_": "subprocess.Popen", "args": ["true"]}})
    with pytest.raises(UntrustedTargetError, match=r"model\.dynamics\._target_ = 'subprocess\.Popen'"):
        lnf.load(path)


@pytest.mark.parametrize("value, expected", [("mypkg", ["mypkg"]), (["a", "b.c"], ["a", "b.c"]), (None, []),
                                             ([], [])])
def test_evaluate_reads_trust_as_module_names_never_as_characters(value, expected):
    """`lnf.evaluate trust=mypkg` once became ['m', 'y', ...]: every one-letter module was trusted."""
    from omegaconf import OmegaConf

    from lnf.evaluation_settings import trust_setting

    assert trust_setting(OmegaConf.create({"trust": value})) == expected
    with pytest.raises(ValueError, match="trust must be a module name"):
        trust_setting(OmegaConf.create({"trust": {"a": 1}}))
