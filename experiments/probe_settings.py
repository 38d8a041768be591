"""Quick probe of model settings on the lifted pendulum at a fixed budget of training steps.

Trains a LagrangianNeuralField with the given settings for `--steps` steps on freshly generated
trajectories (same protocol as the main experiment: 25 % of a 32×32 grid per trajectory, first 50
samples), then reports on held-out trajectories:
  - projection error on the 32×32 training-resolution grid and on the 64×64 test grid,
  - the share of the 64×64 squared error in the boundary ring outside the 32×32 grid's hull,
  - the rollout field_rel_l2 with Gauss–Legendre 8×8 and 32×32 quadrature inside the dynamics,
  - ε = ‖J‖²/⟨J,u⟩² − 1 along the code range (the tangent's misalignment with the mode u, which sets the
    reduced pendulum's frequency error ≈ ε/2).
This is what docs/choices.md quotes (w0, hypernetwork, quadrature order, tangent loss).

    python -m experiments.probe_settings --steps 600 --w0 10
    python -m experiments.probe_settings --steps 600 --lr 1e-3 --observe uniform
"""
from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
import torch

from lnf.evaluation_pipeline import EvaluationData, EvaluationSpec, evaluate_model
from lnf.model import LagrangianNeuralField
from lnf.quadrature import GaussLegendre, gauss_legendre_rule, midpoint_grid
from lnf.scenes import LiftedPendulum


def main() -> None:
    p = argparse.ArgumentParser(prog="python -m experiments.probe_settings", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=600, help="training steps (the budget; cosine decay over them)")
    p.add_argument("--observe", choices=["grid", "vertex", "uniform"], default="grid",
                   help="grid: 25 %% of the 32×32 midpoint grid (cell centres) per trajectory (the protocol); vertex: "
                        "of a 32×32 grid whose outer points lie on the boundary; uniform: as many points drawn "
                        "uniformly over the whole body per trajectory")
    p.add_argument("--w0", type=float, default=10.0)
    p.add_argument("--hyper-depth", type=int, default=1)
    p.add_argument("--velocity-weight", type=float, default=0.1)
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--train", type=int, default=32, help="training trajectories")
    p.add_argument("--test", type=int, default=4, help="held-out trajectories")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, metavar="FILE",
                   help="also write the report there (JSON, atomically), e.g. for results_tables.py --collect")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)

    scene = LiftedPendulum()
    times = 0.05 * np.arange(100)
    train = scene.simulate(scene.sample_initial_states(args.train, rng), times)
    test = scene.simulate(scene.sample_initial_states(args.test, rng), times)
    coarse = midpoint_grid(32, scene.bounds).numpy()
    if args.observe == "vertex":
        axis = np.linspace(-1.0, 1.0, 32)
        coarse = np.stack(np.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
    masks = np.stack([rng.permutation(1024)[:256] for _ in range(args.train)])
    q, v = scene.fields(train[:, :50], coarse)
    pts = torch.tensor(coarse[masks], dtype=torch.float32)
    vals = torch.tensor(np.take_along_axis(q, masks[:, None, :, None], axis=2), dtype=torch.float32)
    vels = torch.tensor(np.take_along_axis(v, masks[:, None, :, None], axis=2), dtype=torch.float32)
    if args.observe == "uniform":
        scattered = rng.uniform(-1.0, 1.0, (args.train, 256, 2))
        fields = [scene.fields(train[i, :50], scattered[i]) for i in range(args.train)]
        pts = torch.tensor(scattered, dtype=torch.float32)
        vals = torch.tensor(np.stack([f[0] for f in fields]), dtype=torch.float32)
        vels = torch.tensor(np.stack([f[1] for f in fields]), dtype=torch.float32)

    model = LagrangianNeuralField(scene, w0=args.w0, hyper_depth=args.hyper_depth, width=args.width,
                                  velocity_weight=args.velocity_weight)
    opt = torch.optim.Adam([{"params": model.field.parameters(), "lr": args.lr},
                            {"params": [model.log_step_size], "lr": 1e-2}])
    start = time.time()
    for steps in range(1, args.steps + 1):
        idx = torch.randint(0, args.train * 50, (args.batch,))
        ti, ki = idx // 50, idx % 50
        out = model.losses(pts[ti], vals[ti, ki], vels[ti, ki])
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        frac = steps / args.steps
        for group, base in zip(opt.param_groups, [args.lr, 1e-2]):
            group["lr"] = base * 0.5 * (1 + math.cos(math.pi * frac))
    model.eval()

    report: dict[str, float] = {"steps": args.steps, "train_seconds": time.time() - start}
    # the embedding on points drawn uniformly over the whole body (boundary included), not only on grids
    anywhere = rng.uniform(-1.0, 1.0, (4096, 2))

    def evaluate_rollouts(points, quadrature, grid_shape=None, max_reduction_points=None):
        """The test rollouts on `points` with the reduced dynamics on `quadrature` (through lnf's one pipeline)."""
        data = EvaluationData(test, times, points, 2.5, grid_shape=grid_shape)
        spec = EvaluationSpec(quadrature=quadrature, max_reduction_points=max_reduction_points, label="rollout")
        return evaluate_model(model, data, spec).rollouts

    ru = evaluate_rollouts(anywhere, GaussLegendre(8))
    report["projection_rel_l2_uniform"] = ru.metrics["projection_rel_l2/all/median"]
    report["rollout_rel_l2_uniform_GL8"] = ru.metrics["field_rel_l2/all/median"]
    for res in (32, 64):
        grid = midpoint_grid(res, scene.bounds).numpy()
        r = evaluate_rollouts(grid, GaussLegendre(32), grid_shape=(res, res))
        report[f"projection_rel_l2_{res}"] = r.metrics["projection_rel_l2/all/median"]
        if res == 64:
            report["rollout_rel_l2_64_GL32"] = r.metrics["field_rel_l2/all/median"]
            report["energy_rel_err_GL32"] = r.metrics["energy_rel_err/max"]
            finite = np.isfinite(r.pred_fields).all(axis=(1, 2, 3))  # a diverged rollout is reported, not summed
            report["diverged_test_trajectories"] = int((~finite).sum())
            err2 = ((r.pred_fields[finite] - r.true_fields[finite]) ** 2).sum((0, 1, 3))
            ring = np.abs(grid).max(-1) > np.abs(coarse).max()
            report["ring_share_of_sq_error"] = float(err2[ring].sum() / err2.sum()) if finite.any() else float("nan")
            r8 = evaluate_rollouts(grid, GaussLegendre(8), grid_shape=(res, res), max_reduction_points=1024)
            report["rollout_rel_l2_64_GL8"] = r8.metrics["field_rel_l2/all/median"]
            codes = np.linspace(r.q_ref.min(), r.q_ref.max(), 7)
    quad = gauss_legendre_rule(32, scene.bounds)
    u = torch.tensor(scene.mode(quad.points.numpy()), dtype=torch.float32)
    w = quad.weights.float()
    with torch.no_grad():
        J = model.field.jet(torch.tensor(codes, dtype=torch.float32)[:, None], quad.points.float(), order=1).J[..., 0, 0]
    eps = ((w * J * J).sum(-1) / ((w * u * J).sum(-1)) ** 2 - 1).numpy()
    report["eps_interior_min"], report["eps_interior_max"] = float(eps[1:-1].min()), float(eps[1:-1].max())
    text = json.dumps({"settings": vars(args), **{k: round(float(x), 5) for k, x in report.items()},
                       "eps_along_codes": [round(float(e), 5) for e in eps]}, indent=1)
    print(text)
    if args.out:
        from lnf.tempfiles import write_text_atomic

        write_text_atomic(args.out, text + "\n")


if __name__ == "__main__":
    main()
