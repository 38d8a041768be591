"""Model no more than a scene needs: the smallest latent dimension and network that meet an accuracy target.

    python -m experiments.model_size                     # reduced: d ∈ {1, 2}, width ∈ {16, 32, 64}, target 0.10
    python -m experiments.model_size --full --target 0.02 # d ∈ {1, 2, 3}, width ∈ {32 … 256}, default training
    python -m experiments.model_size --scene <scene> --target 0.05

A Hydra multirun of `python -m lnf.train` over `model.latent_dim` × `model.width`. The choice is the
smallest d for which some width meets the target on the test `field_rel_l2` (all, median), then the
smallest width at that d; it is reported with its cost (training and rollout wall-clock). Writes
model_size.csv, model_size.png and summary.md into outputs/studies/model_size/.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from experiments import operator_inference as OI
from experiments import studylib as S

ERR = "field_rel_l2/all/median"


def choose(rows: list[dict], target: float) -> Optional[dict]:
    """Smallest latent dimension with a run meeting `target`, then the smallest width at that dimension."""
    ok = [r for r in rows if np.isfinite(float(r[ERR])) and float(r[ERR]) <= target]
    if not ok:
        return None
    d = min(int(r["model.latent_dim"]) for r in ok)
    return min((r for r in ok if int(r["model.latent_dim"]) == d), key=lambda r: int(r["model.width"]))


DIM_STYLES = [("o", "-"), ("s", "--"), ("^", "-."), ("D", ":"), ("v", (0, (5, 1, 1, 1)))]  # (marker, line) per d


def plot(study: S.Study, rows: list[dict], others: list[dict], target: float, chosen: Optional[dict]) -> Path:
    plt = S.pyplot()

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 5.0), layout="constrained", sharey=True)
    pod = sorted((r for r in others if r["method"] in ("pod", "opinf", "opinf_observed")),
                 key=lambda r: int(r["model.latent_dim"]))
    for m in ("pod", "opinf", "opinf_observed"):  # diverged runs (inf error) are drawn at 10 and marked ×
        mine = [r for r in pod if r["method"] == m]
        if mine:
            S.plot_marking_failures(ax2, np.array([int(r["model.latent_dim"]) for r in mine]),
                                    np.array([float(r[ERR]) for r in mine]), np.zeros(len(mine), bool),
                                    marker=S.MARKERS[m], color=S.COLORS[m], ls=S.LINESTYLES[m], lw=1.6,
                                    label=S.LABELS[m])
    if chosen:  # under the baselines' lines (wide, light): a baseline at the same error stays visible on top
        ax2.axhline(float(chosen[ERR]), color=S.COLORS["lnf"], ls="-", lw=3.0, alpha=0.45, zorder=1,
                    label=f"LNF (ours), choice (d = {chosen['model.latent_dim']}, width {chosen['model.width']})")
    for m, ls in (("latent_mlp", (0, (1, 1.5))), ("full_order", (0, (5, 2)))):
        for r in (r for r in others if r["method"] == m and np.isfinite(float(r[ERR]))):
            ax2.axhline(float(r[ERR]), color=S.COLORS[m], ls=ls, lw=1.5, zorder=2,
                        label=f"{S.LABELS[m]}" + (f" (d = {r['model.latent_dim']}, width {r['model.width']})"
                                                  if m == "latent_mlp" else " (64² grid)"))
    ax2.axhline(target, color="k", ls="--", lw=1.0, label=f"target {target:g}")
    ax2.set_yscale("log")
    ax2.set_xlabel("latent dimension d (POD: number of modes k; OpInf: rank r = 2d, the same state dimension)")
    ax2.set_xticks(sorted({int(r["model.latent_dim"]) for r in pod} | {int(r["model.latent_dim"]) for r in rows}))
    ax2.grid(True, which="major", alpha=0.35)
    ax2.grid(True, which="minor", alpha=0.12)
    ax2.set_title("Baselines at the same target (× = diverged, drawn at 10)", fontsize=10)
    S.readable_log_ticks(ax2)
    S.legend_outside(ax2, "below", ncols=2)
    dims = sorted({int(r["model.latent_dim"]) for r in rows})
    for k, d in enumerate(dims):
        sel = sorted((r for r in rows if int(r["model.latent_dim"]) == d), key=lambda r: int(r["model.width"]))
        marker, ls = DIM_STYLES[k % len(DIM_STYLES)]
        dodge = 1.0 + 0.02 * (k - (len(dims) - 1) / 2)  # a small sideways offset keeps coincident curves apart
        S.plot_marking_failures(ax, np.array([int(r["model.width"]) for r in sel]) * dodge,
                                np.array([float(r[ERR]) for r in sel]), np.zeros(len(sel), bool), marker=marker,
                                ls=ls, lw=1.6, color=f"C{k}", label=f"latent d = {d}")
    ax.axhline(target, color="k", ls="--", lw=1.0, label=f"target {target:g}")
    if chosen:
        ax.scatter([int(chosen["model.width"])], [float(chosen[ERR])], s=250, facecolors="none", edgecolors="r", lw=2,
                   label=f"choice: d = {chosen['model.latent_dim']}, width {chosen['model.width']}", zorder=5)
    ax.set_xlabel(S.metric_label("model.width"))
    ax.set_ylabel(S.metric_label(ERR, wrap=True))
    S.log_axes(ax, x_base=2, legend="none")
    S.ticks_at(ax, [r["model.width"] for r in rows], fmt=lambda v: f"{v:g}")
    seen = sorted({int(r["model.width"]) for r in rows})
    if len(seen) == 1:  # one width: an octave either side, so the dodge stays small against the axis
        ax.set_xlim(seen[0] / 2, seen[0] * 2)
    ax.set_title(f"Model size, {study.scene} ({study.mode} settings)", fontsize=10)
    S.legend_outside(ax, "below", ncols=2)
    return S.save_figure(fig, study.out / "model_size.png")


def main(argv=None) -> None:
    def extra(p):
        p.add_argument("--target", type=float, default=None,
                       help="accuracy target on test field_rel_l2 (default 0.10 reduced, 0.02 full)")
        p.add_argument("--dims", default=None, help="latent dimensions to try, e.g. 1,2,3 (default by mode)")
        p.add_argument("--widths", default=None, help="SIREN widths to try, e.g. 32,64 (default by mode)")
        p.add_argument("--modes", default=None, help="POD mode counts to try (default 1,2,3,4)")

    study, args = S.parse_args("model_size", __doc__, argv, extra)
    target = args.target if args.target is not None else {"reduced": 0.10, "full": 0.02, "smoke": 10.0}[study.mode]
    dims, widths = {"smoke": ("1,2", "8,16"), "reduced": ("1,2", "16,32,64"),
                    "full": ("1,2,3", "32,64,128,256")}[study.mode]
    dims, widths = args.dims or dims, args.widths or widths
    rows = study.multirun("search", study.method("lnf", [f"model.latent_dim={dims}", f"model.width={widths}"]),
                          label={"method": "lnf"})
    chosen = choose(rows, target)
    # the baselines at the same question: POD's number of modes, the black box at the chosen size, the full-order model
    modes = args.modes or ("1,2" if study.mode == "smoke" else "1,2,3,4")
    pod = study.multirun("pod_modes", study.method("pod", [f"model.latent_dim={modes}"]), label={"method": "pod"})
    others = list(pod)
    if study.supports("opinf"):  # fitted here on the same dataset, at ranks r = 2k (POD-Galerkin's state dimension)
        others += OI.study_rows(study, [int(k) for k in modes.split(",")])
    if chosen is not None and study.supports("latent_mlp"):
        others += study.multirun("latent_mlp_choice", study.method("latent_mlp", [
            f"model.latent_dim={chosen['model.latent_dim']}", f"model.width={chosen['model.width']}"]),
            label={"method": "latent_mlp"})
    if study.supports("full_order"):
        others += study.multirun("full_order", study.method("full_order"), label={"method": "full_order"})
    pod_ok = [r for r in pod if float(r[ERR]) <= target]
    given = [f"--{key} {getattr(args, key)}" for key in ("target", "dims", "widths", "modes")
             if getattr(args, key) is not None]
    command = " ".join([study.command(), *given])
    csv_path = study.write_csv("model_size.csv")
    cols = [("model.latent_dim", "d"), ("model.width", "width"), (ERR, "field_rel_l2"),
            ("field_rel_l2/extrapolation/median", "extrapolation"), ("train_seconds", "train s"),
            ("rollout_seconds_per_trajectory", "rollout s/traj"), ("fields_seconds_per_trajectory", "rollout+decode s/traj")]
    verdict = ("no setting met the target" if chosen is None else
               f"choice: **d = {chosen['model.latent_dim']}, width {chosen['model.width']}** "
               f"(field_rel_l2 {S.fmt(chosen[ERR])}, training {S.fmt(chosen['train_seconds'])} s, rollout "
               f"{S.fmt(chosen['rollout_seconds_per_trajectory'])} s per trajectory)")
    pod_verdict = (f"POD-Galerkin meets the target from k = {min(int(r['model.latent_dim']) for r in pod_ok)} modes."
                   if pod_ok else "POD-Galerkin does not meet the target with the modes tried.")
    for m in ("opinf", "opinf_observed"):
        ok = [r for r in others if r["method"] == m and float(r[ERR]) <= target]
        if any(r["method"] == m for r in others):
            pod_verdict += (f" {S.LABELS[m]} meets it from r = {min(int(r['rank']) for r in ok)} (d = r/2)." if ok
                            else f" {S.LABELS[m]} does not meet it with the ranks tried.")
    text = (f"# Model size ({study.scene}, {study.mode} settings, target field_rel_l2 ≤ {target:g})\n\n"
            f"Machine: {study.machine()}. Command: `{command}`.\n\n{verdict}\n\n"
            f"{pod_verdict}\n\n"
            + S.markdown_table(sorted(rows, key=lambda r: (int(r["model.latent_dim"]), int(r["model.width"]))), cols)
            + "\nBaselines:\n\n" + S.markdown_table(others, [("method", "method"), ("rank", "OpInf rank r")] + cols))
    summary = S.write_text_atomic(study.out / "summary.md", text)
    print(verdict.replace("**", ""))
    study.finish([csv_path, plot(study, rows, others, target, chosen), summary])


if __name__ == "__main__":
    main()
