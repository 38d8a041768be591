"""Robustness across seeds: a scene's run over several seeds, the spread of its test errors and divergences.

    python -m experiments.seeds --scene bump               # reduced settings, seeds 0…4
    python -m experiments.seeds --scene elastic --seeds 8  # more seeds
    python -m experiments.seeds --full --scene pendulum    # the default model size and training budget

A Hydra multirun of `python -m lnf.train +experiment=<scene> seed=0,…,n−1` (the seed draws the network's
initialisation and the batch order; the dataset is the scene's default one, the same for every seed). For each
test-error window it reports the median over the seeds, the worst seed and worst ÷ median, and every seed's
diverged test rollouts. A scene's default is robust when the worst seed is within 2× the median and no test
rollout diverged. Writes seeds.csv and summary.md into outputs/studies/seeds[-<scene>]/.
"""
from __future__ import annotations

import numpy as np

from experiments import studylib as S

WINDOWS = ("all", "in_horizon", "extrapolation")
WORST_OVER_MEDIAN = 2.0  # the robustness bar: worst seed ≤ 2× the median seed


def spread(rows: list[dict]) -> list[dict]:
    """One row per error window: median and worst over the seeds (a diverged seed's error is inf), worst ÷ median,
    the worst seed, and the seeds with diverged test rollouts."""
    out = []
    for window in WINDOWS:
        key = f"field_rel_l2/{window}/median"
        errors = np.array([float(r.get(key, np.nan)) for r in rows])
        errors = np.where(np.isnan(errors), np.inf, errors)
        median = float(np.median(errors))
        worst = int(np.argmax(errors))
        diverged = [int(r["seed"]) for r in rows if float(r.get("diverged_count", 0)) > 0]
        out.append({"window": window, "median": median, "worst": float(errors[worst]),
                    "worst_over_median": float(errors[worst] / median) if median > 0 else np.inf,
                    "worst_seed": int(rows[worst]["seed"]), "seeds": len(rows),
                    "diverged_seeds": (("seed " if len(diverged) == 1 else "seeds ") + ", ".join(map(str, diverged)))
                    if diverged else "none"})
    return out


def main(argv=None) -> None:
    def extra(p):
        p.add_argument("--seeds", type=int, default=5, help="number of seeds, 0 … n−1 (default 5)")

    study, args = S.parse_args("seeds", __doc__, argv, extra)
    if args.seeds < 2:
        raise SystemExit(f"--seeds must be ≥ 2 (a spread needs two runs), got {args.seeds}")
    seeds = ",".join(map(str, range(args.seeds)))
    rows = study.multirun("seeds", study.method("lnf", [f"seed={seeds}"]), label={"method": "lnf"})
    table = spread(rows)
    robust = all(r["worst_over_median"] <= WORST_OVER_MEDIAN for r in table) and \
        all(float(r.get("diverged_count", 0)) == 0 for r in rows)
    verdict = (f"**Robust**: every window's worst seed within {WORST_OVER_MEDIAN:g}× the median, no diverged test "
               "rollout." if robust else
               f"**Not robust**: a window's worst seed is beyond {WORST_OVER_MEDIAN:g}× the median, or a test rollout "
               "diverged (see below).")
    command = study.command() + (f" --seeds {args.seeds}" if args.seeds != 5 else "")
    per_seed = [("seed", "seed"), ("field_rel_l2/all/median", "error, all"),
                ("field_rel_l2/in_horizon/median", "in horizon"), ("field_rel_l2/extrapolation/median", "after"),
                ("projection_rel_l2/all/median", "projection floor"), ("diverged_count", "diverged"),
                ("energy_drift_long/max", "energy drift (long)"), ("train_seconds", "train s")]
    text = (f"# Seeds ({study.scene}, {study.mode} settings, {len(rows)} seeds)\n\n"
            f"Machine: {study.machine()}. Command: `{command}`.\n\n{verdict}\n\n"
            + S.markdown_table(table, [("window", "window"), ("median", "median over seeds"), ("worst", "worst"),
                                       ("worst_over_median", "worst ÷ median"), ("worst_seed", "worst seed"),
                                       ("diverged_seeds", "seeds with diverged test rollouts")])
            + "\n" + S.markdown_table(sorted(rows, key=lambda r: int(r["seed"])), per_seed))
    csv_path = study.write_csv("seeds.csv")
    summary = S.write_text_atomic(study.out / "summary.md", text)
    print(verdict.replace("**", ""))
    study.finish([csv_path, summary])


if __name__ == "__main__":
    main()
