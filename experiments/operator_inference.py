"""Operator Inference (OpInf) as a non-intrusive baseline: POD + a polynomial discrete-time reduced model, per rank.

    python -m experiments.operator_inference                             # the default scene, r ∈ {1, 2, 4, 8}
    python -m experiments.operator_inference --scene elastic --ranks 2 4 8 16
    python -m experiments.operator_inference --smoke --out /tmp/opinf   # tiny data (the test suite's)

Generates (or reuses) the scene's dataset exactly as `python -m lnf.train +experiment=<scene>` does (the same
composed `data` settings, the same file under LNF_DATA_DIR; --smoke: the studies' tiny data settings), fits
:class:`lnf.baselines.operator_inference.OperatorInference` at each rank on the fine-grid fields and velocities
of the training trajectories within the training horizon, chooses its form ("cA" / "cAH" / "cAHG") and regularizer on
the validation trajectories within the horizon, and rolls it out from the test trajectories' initial snapshots
over all samples. The test errors are lnf's own (lnf.metrics.field_metrics: relative L² field error over all
samples, within the training horizon and after it, median over trajectories, weighted by the points' quadrature
weights as lnf's evaluation weights them), so they compare with the `field_rel_l2/*` of lnf's runs on the same
dataset. Writes summary.md and operator_inference.json into --out (default
outputs/studies/operator_inference-<scene>[-smoke]).

OpInf reads more than lnf does: every fine-grid point of every training sample (fields and velocities), where
lnf learns from masked coarse observations.
"""
from __future__ import annotations

import datetime
import json
import os
import time
from typing import Any, Optional

import numpy as np

from experiments import studylib as S

ERR = "field_rel_l2"


def load_data(study: S.Study) -> tuple[Any, Any, dict[str, Any]]:
    """The scene, its dataset's handle (generated or reused as lnf.train does) and its three splits."""
    from omegaconf import OmegaConf

    from lnf.dataset.snapshots import SnapshotData

    for key, value in S.job_environment().items():  # LNF_ROOT = the repository, an absolute LNF_DATA_DIR
        if key in ("LNF_ROOT", "LNF_DATA_DIR"):
            os.environ[key] = value
    cfg = study.composed(S.SMOKE_DATA if study.mode == "smoke" else ())  # with the tiny data settings under --smoke
    scene = study.scene_object()
    datamodule = SnapshotData.from_settings(OmegaConf.to_container(cfg.data, resolve=True), scene)
    print(f"[operator_inference] dataset {datamodule.path} (generated if absent)", flush=True)
    datamodule.prepare_data()
    return scene, datamodule, {name: datamodule.split(name) for name in ("train", "val", "test")}


def split_controls(scene: Any, split: Any) -> Optional[np.ndarray]:
    """The loads of a split's trajectories as Operator Inference takes them, from the per-trajectory load parameters
    (stored ones, else the scene's from the initial states, as lnf's evaluation): the scene's input series u(t)
    (n, T, m) where it says how its loads vary in time (``Scene.input_signals``), else the parameters (n, c) as a
    constant input (a held series would give each step the same input twice); None for a scene without loads."""
    controls = split.loads(scene)
    if controls is None:
        return None
    controls = np.asarray(controls, dtype=np.float64)
    if not scene.provides("input_signals"):
        return controls
    return scene.input_signals(controls, np.asarray(split.times, dtype=np.float64))


def mass_weights(scene: Any, split: Any) -> np.ndarray:
    """Weights of the POD's inner product on the fine points: quadrature weight (equal if the file has none) ×
    the scene's mass density there."""
    import torch

    points = np.asarray(split.fine_points)
    w = np.ones(len(points)) if split.weights is None else np.asarray(split.weights, dtype=np.float64)
    try:
        density = scene.density(torch.as_tensor(points, dtype=torch.float64)).detach().cpu().numpy().reshape(-1)
    except (NotImplementedError, AttributeError, ValueError, TypeError):
        return w
    return w * density if density.shape == w.shape and np.all(np.isfinite(density)) and np.all(density > 0) else w


def evaluate(scene: Any, splits: dict[str, Any], rank: int) -> dict[str, Any]:
    """Fit at `rank`, roll out the test split, score it with lnf.metrics.field_metrics."""
    from lnf import metrics as M
    from lnf.baselines.operator_inference import OperatorInference

    train, val, test = splits["train"], splits["val"], splits["test"]
    T, K = len(test.times), train.train_times
    metric_weights = None if test.weights is None else np.asarray(test.weights, dtype=np.float64)
    model = OperatorInference(rank).fit(train.fields, train.velocities, K, val.fields, val.velocities,
                                        point_weights=mass_weights(scene, train), metric_weights=metric_weights,
                                        controls=split_controls(scene, train), val_controls=split_controls(scene, val))
    pred = model.predict(test.fields[:, 0], test.velocities[:, 0], T, controls=split_controls(scene, test))
    weights = np.full(test.fields.shape[2], 1.0 / test.fields.shape[2]) if metric_weights is None else \
        metric_weights / metric_weights.sum()
    times = np.asarray(test.times, dtype=np.float64)
    horizon = float(times[K]) if K < T else float(times[-1])  # as lnf's evaluation callback sets it
    true = np.asarray(test.fields, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        out: dict[str, Any] = dict(M.field_metrics(ERR, pred.fields, true, weights, times, horizon))
        out.update(M.field_metrics("velocity_rel_l2", pred.velocities, np.asarray(test.velocities, dtype=np.float64),
                                   weights, times, horizon))
        proj_f, _ = model.decode(model.encode(test.fields, test.velocities))  # the basis' best: POD projection
        out.update(M.field_metrics("projection_rel_l2", proj_f, true, weights, times, horizon))
    record = model.describe()
    out.update(rollout_seconds_per_trajectory=float(np.mean(pred.rollout_seconds)),
               decode_seconds_per_trajectory=float(np.mean(pred.decode_seconds)), frames=T,
               fields_seconds_per_trajectory=float(np.mean(pred.rollout_seconds + pred.decode_seconds)))
    out.update(method="OpInf", rank=rank, operators=record["operators"], regularizer=record["regularizer"],
               val_error=record["val_error"], velocity_weight=record["velocity_weight"],
               diverged=int(pred.diverged.sum()), trajectories=int(len(pred.diverged)),
               fit_seconds=record["fit_seconds"], basis_seconds=record["basis_seconds"],
               candidates=record["candidates"])
    return out


def observed_row(study: S.Study, scene: Any, splits: dict[str, Any], rank: int, cache: dict[str, Any]
                 ) -> Optional[dict[str, Any]]:
    """OpInf given only lnf's sparse observations at `rank` (experiments/opinf_observed.py). The gappy completion is
    computed at the first call and kept in `cache` for the next ranks (its rank cross-validated; fixed at 2 under
    --smoke). None, with a note, for a rank above the completion rank (its extra modes would be round-off)."""
    from experiments.opinf_observed import complete_observations, evaluate_observed

    if "completion" not in cache:
        cache["completion"] = complete_observations(scene, splits, 2 if study.mode == "smoke" else None)
        c = cache["completion"]
        print(f"[{study.name}] gappy completion: rank {c.rank} ({c.info['iterations']} sweeps, "
              f"{'converged' if c.info['converged'] else 'not converged'}), {c.seconds:.1f} s", flush=True)
    completion = cache["completion"]
    if rank > completion.rank:
        print(f"[{study.name}] OpInf (observed) r = {rank} left out: the completed observations have rank "
              f"{completion.rank}", flush=True)
        return None
    return evaluate_observed(scene, splits, rank, completion=completion)


def study_rows(study: S.Study, dims: list[int], sweep: str = "opinf_rank", observed: bool = True
               ) -> list[dict[str, Any]]:
    """Operator Inference as a baseline of a study (pareto.py, model_size.py) at each latent dimension d of `dims`:
    rank r = 2d, the state dimension of a d-dimensional Lagrangian model (q̃ and q̃̇), fitted and scored on the
    study's own dataset (the one its `lnf.train` jobs read). One row per rank in the columns of lnf's metrics.json
    (method "opinf", knob "r", ``model.latent_dim`` = d, ``rank`` = r, ``train_seconds`` = the fit incl. the POD,
    the rollout and decoding costs per test trajectory, ``frames``); with `observed`, also "opinf_observed" rows:
    OpInf given only lnf's sparse observations (experiments/opinf_observed.py: gappy POD; its completion rank
    cross-validated once (fixed at 2 under --smoke), then kept; a rank above it is left out, its extra modes would be
    round-off). Kept in
    study.rows and written to out/<sweep>/rows.json. A rank the training snapshots cannot give is left out with a
    note. Fits take seconds to minutes: rerun every time."""
    scene, _, splits = load_data(study)
    rows: list[dict[str, Any]] = []
    cache: dict[str, Any] = {}  # the gappy completion, shared by the ranks
    folder = study.out / sweep
    where = str(folder.relative_to(S.ROOT) if folder.is_relative_to(S.ROOT) else folder)  # as studylib.collect
    for d in dims:
        methods = ["opinf"] + (["opinf_observed"] if observed else [])
        for method in methods:
            try:
                row = evaluate(scene, splits, 2 * d) if method == "opinf" else \
                    observed_row(study, scene, splits, 2 * d, cache)
            except ValueError as err:
                print(f"[{study.name}] {method} r = {2 * d} left out: {err}", flush=True)
                continue
            if row is None:
                continue
            row.pop("candidates")
            rows.append({**row, "sweep": sweep, "job": len(rows), "dir": where, "method": method, "knob": "r",
                         "model.latent_dim": d, "train_seconds": row["fit_seconds"]})
    folder.mkdir(parents=True, exist_ok=True)
    S.write_text_atomic(folder / "rows.json", json.dumps(rows, indent=1, default=float) + "\n")
    print(f"[{study.name}] Operator Inference at r = {', '.join(str(r['rank']) for r in rows)}: fits "
          f"{S.fmt(sum(r['fit_seconds'] for r in rows))} s in all", flush=True)
    study.rows += rows
    return rows


COLUMNS = [("method", "method"), ("rank", "rank r"), ("operators", "operators"), ("regularizer", "regularizer λ"),
           (f"{ERR}/all/median", "field error, all"), (f"{ERR}/in_horizon/median", "in horizon"),
           (f"{ERR}/extrapolation/median", "after horizon"), ("projection_rel_l2/all/median", "POD projection, all"),
           ("diverged", "diverged"), ("fit_seconds", "fit [s]"), ("basis_seconds", "of which POD [s]"),
           ("rollout_seconds_per_trajectory", "rollout [s/traj]"), ("completion_rank", "gappy completion rank")]


def main(argv=None) -> None:
    def extra(p):
        p.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 4, 8], help="POD ranks r (default 1 2 4 8)")
        p.add_argument("--observed", action="store_true",
                       help="also OpInf given only lnf's sparse observations (gappy POD, experiments/opinf_observed.py)")

    study, args = S.parse_args("operator_inference", __doc__, argv, extra)
    if args.out is None:  # outputs/studies/operator_inference-<scene>[-smoke], whatever the scene
        study.out = S.ROOT / "outputs" / "studies" / "-".join(
            ["operator_inference", study.scene] + (["smoke"] if study.mode == "smoke" else []))
    bad = [r for r in args.ranks if r < 1]
    if bad:
        raise SystemExit(f"--ranks: a rank must be an integer ≥ 1, got {' '.join(map(str, bad))}")
    scene, datamodule, splits = load_data(study)
    train = splits["train"]
    print(f"[operator_inference] {study.scene}: {len(train)}/{len(splits['val'])}/{len(splits['test'])} train/val/test "
          f"trajectories, {len(train.times)} samples (the first {train.train_times} for training), "
          f"{train.fields.shape[2]} fine points", flush=True)
    rows, cache = [], {}
    for rank in args.ranks:
        t0 = time.perf_counter()
        try:
            row = evaluate(scene, splits, rank)
        except ValueError as err:  # a rank the training snapshots cannot give
            raise SystemExit(f"--ranks {rank}: {err}") from err
        new = [row]
        if args.observed:
            new += [r for r in [observed_row(study, scene, splits, rank, cache)] if r is not None]
        rows += new
        for r in new:
            print(f"[operator_inference] {r['method']} r = {rank}: {r['operators']}, λ = {r['regularizer']:.3g}, "
                  f"field error {S.fmt(r[f'{ERR}/all/median'])} (all), {S.fmt(r[f'{ERR}/in_horizon/median'])} "
                  f"(in horizon), {r['diverged']} diverged; fit {r['fit_seconds']:.3g} s", flush=True)
        print(f"[operator_inference] r = {rank}: {time.perf_counter() - t0:.1f} s in all", flush=True)
    given = (f" --ranks {' '.join(map(str, args.ranks))}" if args.ranks != [1, 2, 4, 8] else "") + \
        (" --observed" if args.observed else "")
    out_arg = "" if args.out is None else f" --out {args.out}"
    command = f"{study.command()}{given}{out_arg}"
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    text = (f"Machine: {study.machine()}. Command: `{command}`. Date: {date}.\n\n"
            f"# Operator Inference ({study.scene}, dataset {datamodule.path.name})\n\n"
            f"POD of [q, σ q̇] on the {train.fields.shape[2]} fine points of the {len(train)} training trajectories "
            f"(samples k < {train.train_times}), a discrete-time model s_(k+1) = c + A s_k "
            f"(+ H s_k ⊗ s_k + G s_k ⊗ s_k ⊗ s_k) fitted by Tikhonov least squares (opinf); form (cA, cAH, cAHG) and "
            f"λ chosen on the {len(splits['val'])} validation trajectories within the horizon. "
            + ("OpInf (observed): the same model fitted on lnf's sparse coarse observations completed by gappy POD "
               "(experiments/opinf_observed.py), started from each test trajectory's observed points. "
               if args.observed else "") + f"Test errors: "
            f"lnf.metrics.field_metrics (relative L², median over {len(splits['test'])} trajectories), comparable with lnf's `field_rel_l2/*` on this dataset.\n\n"
            + S.markdown_table(rows, COLUMNS))
    S.write_text_atomic(study.out / "summary.md", text)
    payload = {"scene": study.scene, "mode": study.mode, "command": command, "machine": study.machine(),
               "date": date, "dataset": str(datamodule.path), "rows": rows}
    S.write_text_atomic(study.out / "operator_inference.json", json.dumps(payload, indent=2, default=float) + "\n")
    study.finish([study.out / "summary.md", study.out / "operator_inference.json"])


if __name__ == "__main__":
    main()
