"""What ``model.w0=auto`` chooses on each scene, against the w0 its experiment sets by hand.

    python -m experiments.w0_choice                                  # pendulum, elastic, soft_body
    python -m experiments.w0_choice --scenes pendulum bump --steps 100

For each scene: its experiment's config with `model.w0=auto`, the short search of lnf/w0_search.py on the scene's
default dataset (generated if absent), the projection error of every candidate, and the hand-chosen w0 beside the
chosen one. Writes w0_choice.csv and summary.md into outputs/studies/w0_choice/.
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from experiments import studylib as S
from lnf.model import build_model
from lnf.w0_search import SPANS, STEPS, choose_w0


def search(scene: str, steps: int) -> dict:
    with initialize_config_dir(config_dir=str(S.CONF), version_base="1.3"):
        cfg = compose("train", overrides=[f"+experiment={scene}"])
    hand = cfg.model.w0
    spec = lambda node: OmegaConf.to_container(node, resolve=True)  # noqa: E731
    scene_obj = instantiate(cfg.scene)
    datamodule = instantiate(cfg.data, scene=scene_obj, _convert_="all")
    datamodule.prepare_data()
    model = {k: v for k, v in spec(cfg.model).items()}
    datamodule.gradient_targets = float(model.get("gradient_weight") or 0) > 0
    datamodule.potential_targets = float(model.get("energy_weight") or 0) > 0
    build = lambda w0: build_model(spec(cfg.scene), {**model, "w0": w0}, spec(cfg.quadrature))  # noqa: E731
    start = time.perf_counter()
    outcome = choose_w0(build, scene_obj.bounds, datamodule, lr=float(cfg.optimizer.lr), seed=int(cfg.seed),
                        steps=steps)
    row = {"scene": scene, "hand_w0": hand, "chosen_w0": outcome.chosen, "seconds": time.perf_counter() - start}
    row.update({f"error_w0_{w0:.4g}": err for w0, err in outcome.scores.items()})
    print(f"[w0_choice] {scene}: chose {outcome.chosen:.4g} (hand {hand})\n{outcome.table()}", flush=True)
    return row


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m experiments.w0_choice", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=["pendulum", "elastic", "soft_body"])
    p.add_argument("--steps", type=int, default=STEPS, help=f"training steps per candidate (default {STEPS})")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", type=Path, default=S.ROOT / "outputs" / "studies" / "w0_choice")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = [search(scene, args.steps) for scene in args.scenes]
    S.write_csv(args.out / "w0_choice.csv", rows)
    columns = [("scene", "scene"), ("hand_w0", "w0 by hand"), ("chosen_w0", "w0=auto chose"),
               ("seconds", "search [s]")]
    spans = ", ".join(f"{s:g}" for s in SPANS)
    text = (f"# model.w0=auto against the hand-chosen w0\n\n{S.markdown_table(rows, columns)}\n\n"
            f"Candidates: phase spans {spans} rad over the body's longest side, {args.steps} steps each; scored by "
            f"the projection error on the validation fields' fine points (w0_choice.csv has every candidate's). "
            f"`python -m experiments.w0_choice --scenes {' '.join(args.scenes)} --steps {args.steps}`, "
            f"{time.strftime('%Y-%m-%d', time.gmtime())}, {platform.processor() or platform.machine()}, "
            f"{os.cpu_count()} cores, torch {torch.__version__}, {args.threads} threads.\n")
    S.write_text_atomic(args.out / "summary.md", text)
    print(f"[w0_choice] wrote {args.out / 'summary.md'}")


if __name__ == "__main__":
    main()
