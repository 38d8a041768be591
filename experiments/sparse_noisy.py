"""Sparse and noisy observations in training, for our model and the baselines, measured in one run.

    python -m experiments.sparse_noisy          # reduced: 25 %, 5 %, 1 % of the grid; noise 0, 5 %, 10 % (< 30 min)
    python -m experiments.sparse_noisy --full   # 25 %, 10 %, 5 %, 1 %; noise 0, 1 %, 5 %, 10 %; default model size

Hydra multiruns of `python -m lnf.train` over `data.observed_fraction` (the share of the 32×32 coarse grid
each training trajectory observes) and `data.noise` (Gaussian noise on the observed training values and
velocities, std relative to their RMS). The test protocol is unchanged (clean initial fields on the
64×64 grid). The full-order model learns nothing from data and is shown once, as the reference.
Writes sparse_noisy.csv, sparse_noisy.png and summary.md into outputs/studies/sparse_noisy/.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from experiments import studylib as S

ERR = "field_rel_l2/all/median"


def sweeps(study: S.Study) -> None:
    smoke, full = study.mode == "smoke", study.mode == "full"
    fractions = "0.5,0.25" if smoke else "0.25,0.1,0.05,0.01" if full else "0.25,0.05,0.01"
    noises = "0.1" if smoke else "0.01,0.05,0.1" if full else "0.05,0.1"
    for m in ("lnf", "latent_mlp", "pod"):
        if not study.supports(m):
            print(f"[{study.name}] {S.LABELS[m]} cannot run scene {study.scene!r}: skipped")
            continue
        study.multirun(f"{m}_fraction", study.method(m, [f"data.observed_fraction={fractions}"]),
                       label={"method": m, "knob": "fraction"})
        study.multirun(f"{m}_noise", study.method(m, ["data.observed_fraction=0.25", f"data.noise={noises}"]),
                       label={"method": m, "knob": "noise"})
    if study.supports("full_order"):
        study.multirun("full_order", study.method("full_order"), label={"method": "full_order", "knob": "reference"})


def plot(study: S.Study, rows: list[dict]) -> Path:
    plt = S.pyplot()

    fig, axes = plt.subplots(1, 2, figsize=(11.5, 5.0), layout="constrained", sharey=True)
    percent = lambda v: f"{100 * v:g} %"  # noqa: E731
    for ax, knob, key in [(axes[0], "fraction", "data.observed_fraction"), (axes[1], "noise", "data.noise")]:
        xlabel = S.metric_label(key)
        shown = []
        for m in ("lnf", "latent_mlp", "pod"):
            sel = [r for r in rows if r["method"] == m and r["knob"] == knob]
            if knob == "noise":  # noise 0 is the 25 % point of the fraction sweep
                sel += [dict(r, **{"data.noise": 0.0}) for r in rows if r["method"] == m and r["knob"] == "fraction"
                        and float(r["data.observed_fraction"]) == 0.25]
            if not sel:  # a method the scene cannot run: no empty legend entry
                continue
            sel = sorted(sel, key=lambda r: float(r[key]))
            x = np.array([float(r[key]) for r in sel])
            shown += list(x)
            # coincident curves stay visible: each method its own line style and a small sideways dodge
            xd = S.dodged(x, m, log=knob == "fraction")
            S.plot_marking_failures(ax, xd, np.array([float(r[ERR]) for r in sel]),
                                    np.array([float(r.get("diverged_fraction", 0)) > 0 for r in sel], bool),
                                    marker=S.MARKERS[m], color=S.COLORS[m], ls=S.LINESTYLES[m], lw=1.6,
                                    label=S.LABELS[m])
        ref = [r for r in rows if r["method"] == "full_order"]
        if ref and np.isfinite(float(ref[0][ERR])):
            ax.axhline(float(ref[0][ERR]), color=S.COLORS["full_order"], ls=(0, (5, 3)), lw=1.2,
                       label="full order (no training data)")
        elif ref:  # no line at infinity: say so in the legend
            ax.plot([], [], color=S.COLORS["full_order"], ls=(0, (5, 3)), label="full order (no training data): diverged")
        ax.set_xlabel(xlabel)
        ax.set_yscale("log")
        ax.grid(True, which="major", alpha=0.35)
        ax.grid(True, which="minor", alpha=0.12)
        if knob == "fraction":
            ax.set_xscale("log")
            S.ticks_at(ax, shown, fmt=percent)
        elif shown:
            ticks = sorted(set(shown))
            ax.set_xticks(ticks, [percent(v) for v in ticks])
        S.readable_log_ticks(ax)
        S.legend_outside(ax, "below", ncols=2)
    axes[0].set_ylabel(S.metric_label(ERR, wrap=True))
    fig.suptitle(f"Sparse and noisy training data, {study.scene}"
                 " (× = at least one test rollout diverged; a diverged median is drawn at 10;\n"
                 f"{S.DODGE_NOTE})\n" + S.caption(study),
                 fontsize=9)
    return S.save_figure(fig, study.out / "sparse_noisy.png")


def summary(study: S.Study, rows: list[dict]) -> Path:
    cols = [("method", "method"), ("data.observed_fraction", "observed share"), ("data.noise", "noise"),
            (ERR, "field_rel_l2"), ("field_rel_l2/extrapolation/median", "extrapolation"),
            ("projection_rel_l2/all/median", "projection"), ("energy_rel_err/max", "energy err"),
            ("diverged_fraction", "diverged"), ("train_seconds", "train s")]
    text = (f"# Sparse and noisy observations ({study.scene}, {study.mode} settings)\n\n"
            f"Machine: {study.machine()}. Command: `{study.command()}`.\n\n" + S.markdown_table(rows, cols))
    return S.write_text_atomic(study.out / "summary.md", text)


def main(argv=None) -> None:
    study, _ = S.parse_args("sparse_noisy", __doc__, argv)
    sweeps(study)
    csv_path = study.write_csv("sparse_noisy.csv")
    study.finish([csv_path, plot(study, study.rows), summary(study, study.rows)])


if __name__ == "__main__":
    main()
