"""The potential closure as an ablation on trained checkpoints: each model's test errors without and with ΔṼ.

    python -m experiments.closure_ablation --ckpt outputs/studies/pareto-elastic/lnf_width/*/checkpoints/last.ckpt
    python -m experiments.closure_ablation --ckpt A.ckpt B.ckpt --degree 4 --out outputs/studies/closure

For each checkpoint (an lnf model, trained with or without ``model.closure_degree``, or POD-Galerkin's): its dataset (generated if
missing, as lnf.evaluate finds it), the test rollouts of the pure pullback, then the closure fitted exactly as
``python -m lnf.train ... model.closure_degree=<p>`` fits it after training (lnf.closure_choice.fit_closure:
the residual of the pulled-back equations along the encoded training trajectories, the regularizer, or none, chosen on
validation rollouts within the training horizon), and the test rollouts again. The rollouts use the run's own
integrator (its run.json beside the checkpoint folder; implicit midpoint if there is none). Writes closure.json and
summary.md into --out (default outputs/studies/closure_ablation).
"""
from __future__ import annotations

import argparse
import datetime
import json
import logging
import platform
import time
from pathlib import Path
from typing import Any, Optional

import torch

from experiments.scenes import snapshot_data_of
from lnf.closure import CLOSURE_MAX_TERMS, PotentialClosure
from lnf.evaluation_pipeline import EvaluationData, EvaluationSpec, evaluate_model
from lnf.model import load
from lnf.tempfiles import write_json_atomic, write_text_atomic
from lnf.closure_choice import fit_closure

ROOT = Path(__file__).resolve().parents[1]
KEYS = [("field_rel_l2/in_horizon/median", "in horizon"), ("field_rel_l2/extrapolation/median", "after horizon"),
        ("projection_rel_l2/all/median", "floor"), ("energy_drift/max", "energy drift, max"),
        ("energy_rel_err/max", "FEM energy error, max"), ("diverged_count", "diverged")]


def run_integrator(ckpt: Path) -> Any:
    """The integrator of the run that wrote `ckpt` (its run.json), else the implicit midpoint rule."""
    record = ckpt.resolve().parent.parent / "run.json"
    if record.is_file():
        spec = json.loads(record.read_text()).get("config", {}).get("integrator")
        if spec:
            return spec
    return "implicit_midpoint"


def ablate(ckpt: Path, degree: int, shooting_iterations: int = EvaluationSpec.closure_shooting_iterations,
           max_terms: Optional[int] = CLOSURE_MAX_TERMS) -> dict[str, Any]:
    """Test metrics of `ckpt` without and with a closure of `degree` (lowered to at most `max_terms` terms; fitted
    here, its shooting search bounded by `shooting_iterations` Levenberg–Marquardt iterations per term in each
    stage), and the fit's record."""
    model = load(ckpt)
    if getattr(model, "latent_dynamics", None) is not None or model.state_is_field:
        raise SystemExit(f"--ckpt {ckpt}: {type(model).__name__} has no reduced pulled-back dynamics to close")
    dm = snapshot_data_of(model)
    spec = EvaluationSpec(integrator=run_integrator(ckpt), label="test rollout", figures=0,
                          closure_shooting_iterations=shooting_iterations)
    test = EvaluationData.of_split(dm.split("test"), model.scene)
    model.eval()
    model.closure = None
    with torch.no_grad():
        plain = evaluate_model(model, test, spec).metrics
    model.closure = PotentialClosure(model.latent_dim, degree, max_terms)
    start = time.perf_counter()
    fit = fit_closure(model, dm, spec)
    fit_seconds = time.perf_counter() - start
    with torch.no_grad():
        closed = evaluate_model(model, test, spec).metrics if model.closure.active else plain
    return {"checkpoint": str(ckpt), "latent_dim": int(model.latent_dim), "degree": model.closure.degree,
            "plain": {k: float(plain[k]) for k, _ in KEYS if k in plain},
            "closed": {k: float(closed[k]) for k, _ in KEYS if k in closed}, "fit": fit, "fit_seconds": fit_seconds}


def summary(rows: list[dict[str, Any]], command: str) -> str:
    head = "| checkpoint | d | closure | " + " | ".join(label for _, label in KEYS) + " | λ | fit [s] |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for row in rows:
        for name in ("plain", "closed"):
            m = row[name]
            cells = [f"{m[k]:.4g}" if k in m else "–" for k, _ in KEYS]
            floor = row["fit"].get("closure_span_floor", 0.0)  # spans floored (lnf.closure.CODE_SPAN_FLOOR), or not
            extra = [f"{row['fit']['closure_regularizer']:.0e}" + (f", spans ≥ {floor:g} of the largest" if floor else ""),
                     f"{row['fit_seconds']:.0f}"] if name == "closed" else ["", ""]
            label = "none" if name == "plain" else f"degree {row['degree']}"
            lines.append(f"| `{row['checkpoint']}` | {row['latent_dim']} | {label} | " + " | ".join(cells + extra) + " |")
    when = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (f"Test errors of each checkpoint without and with the potential closure (lnf/closure.py). Command: "
            f"`{command}`; {when} on {platform.machine()}, {torch.get_num_threads()} torch threads.\n\n"
            + "\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", type=Path, nargs="+", required=True, help="lnf checkpoints (last.ckpt)")
    parser.add_argument("--degree", type=int, default=4, help="the closure's polynomial degree p ≥ 2 (default 4)")
    parser.add_argument("--max-terms", type=int, default=CLOSURE_MAX_TERMS,
                        help="the closure's degree is lowered (not below 2) until it has at most this many terms "
                             "(default %(default)s, as model.closure_max_terms); 0: no cap")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "studies" / "closure_ablation")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    parser.add_argument("--shooting-iterations", type=int, default=EvaluationSpec.closure_shooting_iterations,
                        help="Levenberg–Marquardt iterations per closure term in each stage of the shooting "
                             "search; 0 keeps the residual fit (default %(default)s, as "
                             "evaluation.closure_shooting_iterations)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(name)s] %(message)s")  # the fit's candidates and choice
    if args.degree < 2:
        raise SystemExit(f"--degree must be ≥ 2, got {args.degree}")
    if args.max_terms < 0:
        raise SystemExit(f"--max-terms must be ≥ 0 (0: no cap), got {args.max_terms}")
    if args.shooting_iterations < 0:
        raise SystemExit(f"--shooting-iterations must be ≥ 0, got {args.shooting_iterations}")
    missing = [str(c) for c in args.ckpt if not c.is_file()]
    if missing:
        raise SystemExit(f"--ckpt: no such file: {', '.join(missing)}")
    if args.threads:
        torch.set_num_threads(args.threads)
    command = "python -m experiments.closure_ablation " + " ".join(
        ["--ckpt", *map(str, args.ckpt), "--degree", str(args.degree)]
        + ([] if args.max_terms == CLOSURE_MAX_TERMS else ["--max-terms", str(args.max_terms)])
        + ([] if args.shooting_iterations == EvaluationSpec.closure_shooting_iterations
           else ["--shooting-iterations", str(args.shooting_iterations)]))
    rows = []
    args.out.mkdir(parents=True, exist_ok=True)
    for ckpt in args.ckpt:
        print(f"[closure_ablation] {ckpt}", flush=True)
        rows.append(ablate(ckpt, args.degree, args.shooting_iterations, args.max_terms or None))
        p, c = rows[-1]["plain"], rows[-1]["closed"]
        print(f"[closure_ablation]   after horizon {p['field_rel_l2/extrapolation/median']:.4g} → "
              f"{c['field_rel_l2/extrapolation/median']:.4g}", flush=True)
        write_json_atomic(args.out / "closure.json", {"command": command, "rows": rows})  # as each finishes
    write_text_atomic(args.out / "summary.md", summary(rows, command))
    print(f"  wrote {args.out / 'summary.md'}")


if __name__ == "__main__":
    main()
