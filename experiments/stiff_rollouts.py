"""Stiff pulled-back dynamics: POD-Galerkin with k modes (lnf's own pullback through a linear basis) rolled out by
several integrator settings on the same test trajectories, with the error and the wall-clock of each, in one run.

    python -m experiments.stiff_rollouts --scene elastic --modes 8 --trajectories 4
    python -m experiments.stiff_rollouts --modes 2 --settings '{"_target_": "lnf.integrators.RK4", "substeps": 40}'

The model is fitted in closed form on the scene's training split (`+experiment=<scene> model=pod
dynamics=lagrangian`), each setting is an integrator config (JSON; default: the scene's midpoint rule with up to
4, 16 and 64 automatic substeps, and RK4 with 40 substeps). Prints a table and writes ``results.json`` into
outputs/studies/stiff_rollouts-<scene>/. The seconds are this machine's at the time: compare them within one run.
"""
from __future__ import annotations

import argparse
import json
import platform
import time

MIDPOINT = '{"_target_": "lnf.integrators.ImplicitMidpoint", "order": 2, "max_substeps": %d}'
DEFAULT_SETTINGS = [MIDPOINT % n for n in (4, 16, 64)] + ['{"_target_": "lnf.integrators.RK4", "substeps": 40}']


def main(argv: "list[str] | None" = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--scene", default="elastic", help="an experiment of conf/experiment/ (default elastic)")
    p.add_argument("--modes", type=int, default=8, help="POD modes k (default 8)")
    p.add_argument("--trajectories", type=int, default=4, help="the first n test trajectories (default 4)")
    p.add_argument("--settings", nargs="*", default=DEFAULT_SETTINGS, help="integrator configs, JSON each")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    for key in ("modes", "trajectories", "threads"):
        if getattr(args, key) < 1:
            p.error(f"--{key} must be an integer ≥ 1, got {getattr(args, key)}")
    settings = []
    for text in args.settings:
        try:
            settings.append(json.loads(text))
        except json.JSONDecodeError as err:
            raise SystemExit(f"--settings {text!r} is not JSON ({err}); e.g. {DEFAULT_SETTINGS[0]!r}")

    import hydra
    import torch
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from experiments.studylib import ROOT
    from lnf.evaluation_pipeline import EvaluationData, EvaluationSpec, evaluate_model
    from lnf.tempfiles import write_json_atomic
    from lnf.training.module import LNFModule
    from lnf.training.run_checks import build_scene
    from lnf.training.run_setup import model_settings

    torch.set_num_threads(args.threads)
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        cfg = compose("train", overrides=[f"+experiment={args.scene}", "model=pod", f"model.latent_dim={args.modes}",
                                          "dynamics=lagrangian", f"paths.data_dir={ROOT / 'data'}"])
    plain = lambda node: OmegaConf.to_container(node, resolve=True)  # noqa: E731
    scene = build_scene(plain(cfg.scene))
    datamodule = hydra.utils.instantiate(cfg.data, scene=scene, _convert_="all")
    module = LNFModule(scene=plain(cfg.scene), model=model_settings(plain(cfg.model), None),
                       quadrature=plain(cfg.quadrature), optimizer=plain(cfg.optimizer), data=datamodule.describe())
    datamodule.prepare_data()
    model = module.model
    points, values, _ = datamodule.observations("train")
    model.fit_to_observations(torch.as_tensor(points), torch.as_tensor(values))
    data = EvaluationData.of_split(datamodule.split("test"), scene, n=args.trajectories)
    rows = []
    print(f"POD-Galerkin k = {args.modes} on {args.scene}, {len(data.states)} test trajectories")
    for setting in settings:
        start = time.perf_counter()
        m = evaluate_model(model, data, EvaluationSpec(integrator=setting, label=json.dumps(setting))).metrics
        row = {"integrator": setting, "seconds": time.perf_counter() - start,
               **{k: float(m[k]) for k in ("field_rel_l2/in_horizon/median", "field_rel_l2/extrapolation/median",
                                           "projection_rel_l2/all/median", "diverged_fraction", "substeps") if k in m}}
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = ROOT / "outputs" / "studies" / f"stiff_rollouts-{args.scene}"
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "results.json", {"modes": args.modes, "trajectories": len(data.states), "rows": rows,
                                             "machine": f"{platform.processor() or platform.machine()}, "
                                                        f"torch {torch.__version__}, {args.threads} threads"})
    print(f"wrote {out / 'results.json'}")


if __name__ == "__main__":
    main()
