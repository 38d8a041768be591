"""Evaluation entry point: ``python -m lnf.evaluate ckpt_path=... [integrator=rk4 dt=... horizon=... grid.kind=...]``.

Loads a checkpoint without training, rolls out the test trajectories with any integrator, time step,
horizon, quadrature and evaluation grid, writes metrics.json and Figure 3 into the Hydra output dir.
``evaluate(cfg)`` is a pure function of the composed config; ``main()`` only adds ``@hydra.main``. The settings
are checked and priced by :mod:`lnf.evaluation_settings`; the evaluation is :mod:`lnf.evaluation_pipeline`'s.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional

import hydra
import torch
from omegaconf import DictConfig

from lnf.allocator import keep_freed_memory
from lnf.closure import PotentialClosure
from lnf.dataset import load_split
from lnf.dataset.snapshots import checkpoint_snapshot_data
from lnf.evaluation_pipeline import checkpoint_data, ensure_code_range, evaluate_model, write_report
from lnf.evaluation_settings import (check_budget, check_settings, choose_dynamics, planned_cost, rollout_request,
                                     trust_setting)
from lnf.model import load
from lnf.run_lock import EVALUATION_RESULTS, run_folder_lock, set_aside
from lnf.tempfiles import write_json_atomic
from lnf.training.console import quiet_console
from lnf.closure_choice import fit_closure
from lnf.utils import print_summary, run_metadata

log = logging.getLogger("lnf.evaluate")


def evaluate(cfg: DictConfig) -> dict[str, float]:
    """Evaluate `cfg.ckpt_path`; returns the metrics (also written to metrics.json).

    Unknown keys and bad settings are refused first (:func:`lnf.evaluation_settings.check_settings`), work over
    the time or memory budget before any data are loaded (:func:`lnf.evaluation_settings.check_budget`); a figure
    that cannot be drawn is a warning, after metrics.json and run.json are written. Another run in the same output
    folder at the same time is refused (:mod:`lnf.run_lock`); an earlier run's results there are moved aside
    (``previous/<time>/``) before any rollout, so the folder never mixes two commands' files.
    """
    with run_folder_lock(Path(cfg.paths.output_dir), "python -m lnf.evaluate"):
        return _evaluate(cfg)


def _evaluate(cfg: DictConfig) -> dict[str, float]:
    quiet_console()
    check_settings(cfg)
    keep_freed_memory()  # reuse freed decoding buffers (lnf/allocator.py)
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    output_dir = Path(cfg.paths.output_dir)
    model = load(cfg.ckpt_path, trust=trust_setting(cfg))  # a checkpoint's own classes run only if trusted
    choose_dynamics(model, cfg.get("dynamics"), cfg.ckpt_path)
    record = dict(model.checkpoint.get("data") or {})
    if not record:
        raise ValueError(f"checkpoint {cfg.ckpt_path} records no data settings; cannot find its test trajectories")
    check_budget(cfg, *planned_cost(cfg, model, record))  # before any data are loaded or simulated
    path, dcfg = checkpoint_data(model, Path(cfg.paths.data_dir))
    split = load_split(path, cfg.split, scene=model.scene, cfg=dcfg)
    ensure_code_range(model, path, dcfg)

    def provenance() -> None:  # a killed run says what it was, and never sits beside an earlier run's results
        set_aside(output_dir, EVALUATION_RESULTS)  # moved to previous/<time>/, nothing deleted
        write_json_atomic(output_dir / "run.json", run_metadata(cfg))

    data, spec = rollout_request(cfg, model, split, path, provenance)
    closure = {} if cfg.get("closure_degree") is None else fit_closure_first(model, int(cfg.closure_degree), path, spec,
                                                                                 cfg.get("closure_max_terms"))
    report = evaluate_model(model, data, spec)
    write_report(report, output_dir, extra=closure, logger=log)
    print_summary(report.metrics, title=f"{cfg.split} metrics of {cfg.ckpt_path}")
    return report.metrics


def fit_closure_first(model: Any, degree: int, path: Path, spec: Any,
                      max_terms: Optional[int] = None) -> dict[str, float]:
    """``closure_degree=p``: fit a potential closure of degree p (lowered to at most `max_terms` terms, lnf/closure.py)
    on the checkpoint's own training trajectories, exactly as ``lnf.train ... model.closure_degree=p`` does after
    training; returns its record."""
    if model.state_is_field or getattr(model, "latent_dynamics", None) is not None:
        raise ValueError(f"closure_degree={degree}: a closure corrects reduced pulled-back dynamics; the checkpoint "
                         f"holds a {type(model).__name__} without them")
    model.closure = PotentialClosure(model.latent_dim, degree, max_terms)
    return fit_closure(model, checkpoint_snapshot_data(model, path), spec)


@hydra.main(version_base="1.3", config_path="pkg://lnf.conf", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    evaluate(cfg)


if __name__ == "__main__":
    main()
