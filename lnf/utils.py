"""Small helpers shared by the entry points: config checks, run metadata, the summary table."""
from __future__ import annotations

import math
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path
from typing import Any, Optional

import numpy as np
from omegaconf import DictConfig, OmegaConf

SUMMARY_KEYS = [
    "field_rel_l2/all/median", "field_rel_l2/in_horizon/median", "field_rel_l2/extrapolation/median",
    "field_rel_l2/all/max", "projection_rel_l2/all/median", "latent_rmse/median", "energy_rel_err/max",
    "energy_drift/max", "energy_drift_long/max", "vpt/median", "rollout_seconds_per_trajectory",
    "rollout_seconds_per_step", "fields_seconds_per_trajectory", "train_seconds", "total_seconds",
]


# The numeric settings whose range lnf knows, by dotted key: (kind, low, high, what it is). kind "int": an integer
# (an integral float such as 4.0 passes) in [low, high]; ">": a finite number > low; "≥": a finite number ≥ low
# (≤ high where high is given). A key absent from the config, or null, is not checked here (null means a default
# where the key allows it). Every other number in the config must still be finite (:func:`check_numbers`).
NUMBER_RULES: dict[str, tuple[str, float, Optional[float], str]] = {
    "seed": ("int", 0, 2 ** 32 - 1, "the random seed"),
    "threads": ("int", 1, None, "torch CPU threads"),
    "model.latent_dim": ("int", 1, None, "the latent dimension d"),
    "model.width": ("int", 1, None, "neurons per layer of φ"),
    "model.depth": ("int", 1, None, "hidden layers of φ"),
    "model.hyper_width": ("int", 1, None, "neurons per layer of the hypernetwork"),
    "model.hyper_depth": ("int", 0, None, "layers of the hypernetwork"),
    "model.hyper_init_scale": ("≥", 0, None, "the hypernetwork's initial scale"),
    "model.w0": (">", 0, None, "the SIREN frequency, or auto: chosen by a short search on the data"),
    "model.reduction_steps": ("int", 1, None, "K, the steps of ρ̃"),
    "model.reduction_starts": ("int", 1, None, "start codes per axis of ρ̃"),
    "model.start_radius": (">", 0, None, "the half-width of ρ̃'s start codes"),
    "model.step_size": (">", 0, None, "α0, the step of ρ̃"),
    "model.velocity_weight": ("≥", 0, None, "λ_v of the velocity loss"),
    "model.energy_weight": ("≥", 0, None, "λ_E of the energy loss"),
    "model.gradient_weight": ("≥", 0, None, "λ_G of the gradient loss"),
    "model.dynamics_weight": ("≥", 0, None, "λ_D of the dynamics-residual loss"),
    "model.closure_degree": ("int", 0, 6, "the degree of the fitted potential closure (0: none)"),
    "model.closure_max_terms": ("int", 1, None, "the most terms of the fitted potential closure"),
    "model.mass_condition_weight": ("≥", 0, None, "λ_M of the mass-conditioning loss"),
    "model.mass_condition_max": ("≥", 1, None, "κ, the largest condition number of M̃ the mass-conditioning loss allows"),
    "model.resolution": ("int", 1, None, "grid points per axis of the full-order model"),
    "model.degree": ("int", 0, None, "the Legendre degree per axis"),
    "model.pod_degree": ("int", 0, None, "the Legendre degree per axis of the POD part"),
    "model.pod_residual_scale": (">", 0, None, "ε, the scale of the learned part ψ of φ = m + Φ q̃ + ε ψ"),
    "model.ridge": ("≥", 0, None, "the Tikhonov weight"),
    "model.max_condition": (">", 0, None, "the largest condition number of the fits"),
    "optimizer.lr": (">", 0, None, "the learning rate of the field; 0 trains nothing"),
    "optimizer.step_size_lr": ("≥", 0, None, "the learning rate of log α"),
    "optimizer.weight_decay": ("≥", 0, None, "Adam's weight decay"),
    "optimizer.warmup_steps": ("int", 0, None, "steps of learning-rate warm-up"),
    "optimizer.min_lr_ratio": ("≥", 0, 1, "the floor of the cosine schedule, a fraction of lr"),
    "optimizer.energy_warmup_epochs": ("int", 0, None, "epochs without the energy loss"),
    "integrator.substeps": ("int", 1, None, "integration steps per sample"),
    "integrator.max_substeps": ("int", 1, None, "the most automatic substeps per sample; 1: fixed substeps"),
    "integrator.order": ("int", 2, None, "the order of the integrator"),
    "integrator.tol": (">", 0, None, "the tolerance of the implicit solve"),
    "integrator.max_iter": ("int", 1, None, "iterations of the implicit solve"),
    "integrator.rtol": (">", 0, None, "the relative tolerance of the adaptive step"),
    "integrator.atol": (">", 0, None, "the absolute tolerance of the adaptive step"),
    "integrator.max_abs": (">", 0, None, "the largest |q̃| or |q̃̇| that is not a divergence"),
    "dynamics.tol": (">", 0, None, "the interpolation tolerance of the table"),
    "dynamics.min_nodes": ("int", 2, None, "Chebyshev nodes per axis"),
    "dynamics.max_nodes": ("int", 2, None, "Chebyshev nodes per axis"),
    "dynamics.max_table_points": ("int", 1, None, "points of the table"),
    "dynamics.margin": ("≥", 0, None, "the widening of the table's box"),
    "dynamics.lr": (">", 0, None, "the learning rate of the latent dynamics"),
    "dynamics.width": ("int", 1, None, "neurons per layer of the latent dynamics"),
    "dynamics.depth": ("int", 1, None, "layers of the latent dynamics"),
    "dynamics.iterations": ("int", 0, None, "fitting iterations of the latent dynamics"),
    "dynamics.batch_size": ("int", 1, None, "the batch size of the latent dynamics"),
    "dynamics.window": ("int", 1, None, "the rollout window of the latent dynamics"),
    # the data: a sample spacing no scene can mean (1e-300 s: trajectories that do not move; 1e300 s: a simulation
    # that never ends) is refused before any generation
    "data.dt": (">", 1e-12, 1e6, "the sample spacing of the generated trajectories [s]"),
    "data.n_times": ("int", 2, None, "samples per trajectory"),
    "data.train_times": ("int", 1, None, "the first samples used for training"),
    "data.n_train": ("int", 1, None, "training trajectories"),
    "data.n_val": ("int", 1, None, "validation trajectories"),
    "data.n_test": ("int", 1, None, "test trajectories"),
    "data.observed_fraction": (">", 0, 1, "the fraction of the coarse grid each trajectory observes"),
}


#: The evaluation settings that ``evaluation:`` of conf/train.yaml (as ``evaluation.<key>``) and conf/evaluate.yaml
#: (at its top level) share: one schema, checked by :class:`lnf.evaluation_pipeline.EvaluationSpec` and before any
#: work by both entry points.
EVALUATION_RULES: dict[str, tuple] = {
    "long_steps": ("int", 0, None, "steps of the long-horizon energy check; 0 skips it"),
    "long_trajectories": ("int", 1, None, "trajectories of the long-horizon energy check"),
    "figures": ("int", 0, None, "how many trajectories get a Figure 3; 0 draws none"),
    "max_reduction_points": ("int", 1, None, "evaluation points that ρ̃ uses", "", "all of them"),
    "closure_shooting_iterations": ("int", 0, None, "Levenberg–Marquardt iterations per closure term in each stage "
                                    "of a closure fit's shooting search; 0 keeps the residual fit"),
}
NUMBER_RULES.update({f"evaluation.{key}": rule for key, rule in EVALUATION_RULES.items()})
NUMBER_RULES.update({f"evaluation.{key}": ("int", low, None, "") for key, low in  # the training's validation rollouts
                     (("every_n_epochs", 0), ("val_trajectories", 1), ("val_resolution", 1))})

#: settings that also take the word ``auto`` (chosen from the body and the data when the run starts)
AUTO_SETTINGS = frozenset({"model.w0"})


def is_number(value: Any) -> bool:
    """An int or float (NumPy's too), not a bool (a YAML true is no number)."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def number_problem(key: str, value: Any, rule: Optional[tuple] = None) -> Optional[str]:
    """What is wrong with the setting `key` = `value` under `rule` (see :data:`NUMBER_RULES`; None: it must only be
    finite if it is a number), or None if nothing is. A rule may add a unit and what null means:
    ``(kind, low, high, what, unit, null)``; without a null text, null is refused."""
    if rule is None:
        if is_number(value) and not math.isfinite(value):
            return f"{key} must be a finite number, got {value!r}"
        return None
    kind, low, high, what, *more = rule
    unit, null = (*more, "", "")[:2]
    if value is None and null:
        return None
    if value == "auto" and key in AUTO_SETTINGS:
        return None
    low_s, high_s = (str(int(x)) if x is not None and float(x).is_integer() else f"{x}" for x in (low, high))
    if kind == "int":
        ok = is_number(value) and math.isfinite(value) and value == int(value) and low <= value \
            and (high is None or value <= high)
        expected = f"an integer ≥ {low_s}" + (f" and ≤ {high_s}" if high is not None else "")
    else:
        ok = is_number(value) and math.isfinite(value) and (value > low if kind == ">" else value >= low) \
            and (high is None or value <= high)
        expected = f"a finite number {kind} {low_s}" + (f" and ≤ {high_s}" if high is not None else "")
    expected += f" [{unit}]" if unit else ""
    expected += " or auto" if key in AUTO_SETTINGS else ""
    expected += f" ({what})" if what else ""
    expected += f" or null ({null})" if null else ""
    return None if ok else f"{key} must be {expected}, got {value!r}"


def require(key: str, value: Any, rule: Optional[tuple] = None, error: type = ValueError) -> Any:
    """`value` as an int (rule kind "int") or float, or `error` naming `key`, the range and what it is (`rule`: by
    default ``NUMBER_RULES[key]``; see :func:`number_problem`). Null passes where the rule says what it means."""
    rule = NUMBER_RULES[key] if rule is None else rule
    problem = number_problem(key, value, rule)
    if problem:
        raise error(problem)
    return value if value is None else int(value) if rule[0] == "int" else float(value)


def check_numbers(cfg: Any, rules: Optional[dict[str, tuple]] = None, prefix: str = "",
                  skip: tuple[str, ...] = ("hydra",)) -> None:
    """Refuse NaN, ±inf and out-of-range numbers anywhere in a config (a DictConfig or plain mapping), before any work.

    Every number, in nested mappings and lists too, must be finite; a key of `rules` (default
    :data:`NUMBER_RULES`; dotted, relative to the config's root) must also lie in its range. Raises one ValueError
    naming every bad key, its value and what was expected. Null values, strings and missing values pass here.
    """
    rules = NUMBER_RULES if rules is None else rules
    if OmegaConf.is_config(cfg):
        cfg = OmegaConf.to_container(cfg, resolve=False)
    problems: list[str] = []

    def visit(key: str, value: Any) -> None:
        if isinstance(value, dict):
            for k, v in value.items():
                if not (not key and k in skip):
                    visit(f"{key}.{k}" if key else str(k), v)
        elif isinstance(value, (list, tuple)):
            for i, v in enumerate(value):
                visit(f"{key}[{i}]", v)
        elif value is not None and not (isinstance(value, str) and (value == "???" or value.startswith("${"))):
            problem = number_problem(key, value, rules.get(key))
            if problem:
                problems.append(problem)

    visit(prefix.rstrip("."), cfg)
    if problems:
        raise ValueError("; ".join(problems) + " (settings are checked before any work starts)")


def check_config(cfg: DictConfig) -> None:
    """Clear errors for settings that would otherwise fail deep inside torch: missing values, and NaN, inf or
    out-of-range numbers (:func:`check_numbers`), each naming its key."""
    missing = {f"{k}.{m}" for k, v in cfg.items() if k != "hydra" and OmegaConf.is_config(v)
               for m in OmegaConf.missing_keys(v)}
    if missing:
        raise ValueError(f"missing required config values: {sorted(missing)}")
    check_numbers(cfg)
    model = cfg.model  # latent_dim, reduction_steps ≥ 1: NUMBER_RULES, in check_numbers above
    dynamics = cfg.get("dynamics")
    if dynamics is not None and _needs_codes(dynamics) and not _has_codes(model):
        raise ValueError(f"dynamics={dynamics._target_} (learned or tabulated latent dynamics) needs model=lnf "
                         f"(a neural field with codes to learn or tabulate on), got model={model.get('_target_')}; "
                         f"use dynamics=lagrangian with this model")


def _needs_codes(dynamics: Any) -> bool:
    """Whether the dynamics spec's class needs a learned field's codes (its declared kind, lnf.dynamics_kind)."""
    from lnf.dynamics_kind import dynamics_kind

    return dynamics_kind(dynamics).needs_codes


def _has_codes(model: Any) -> bool:
    """Whether the model spec's class has learned codes (its ``learned_codes``, lnf.reduced_model.ReducedModel)."""
    from lnf.model import target_class

    return bool(getattr(target_class(model.get("_target_"), key="model._target_"), "learned_codes", False))


def resolved_config(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config as plain containers, without Hydra's own `hydra` node (present under compose)."""
    return {k: OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v
            for k, v in cfg.items() if k != "hydra"}


def run_metadata(cfg: DictConfig) -> dict[str, Any]:
    """Package versions, git commit (and whether the tree had uncommitted changes), command line and the
    resolved config of a run."""
    versions = {}
    for pkg in ["lnf", "torch", "lightning", "hydra-core", "omegaconf", "wandb", "h5py", "numpy", "scipy", "torchdiffeq"]:
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = None
    here = Path(__file__).resolve().parent
    commit = _git(["rev-parse", "HEAD"], here)
    status = _git(["status", "--porcelain", "--untracked-files=no"], here) if commit else None
    return {"versions": versions, "git_commit": commit or None,
            "git_dirty": None if status is None else bool(status), "argv": sys.argv,
            "python": sys.version, "platform": platform.platform(), "config": resolved_config(cfg)}


def _git(args: list[str], cwd: Path) -> Optional[str]:
    """stdout of `git args` in `cwd`, or None when git or the repository is not there."""
    try:
        proc = subprocess.run(["git", *args], capture_output=True, text=True, timeout=5, cwd=str(cwd))
    except (OSError, subprocess.SubprocessError):
        return None
    return proc.stdout.strip() if proc.returncode == 0 else None


def summary_rows(metrics: dict[str, float]) -> list[tuple[str, str]]:
    """The rows of :func:`print_summary`: the headline metrics of :data:`SUMMARY_KEYS` (4 significant digits), and
    after a training the epochs run of the budget, and what stopped it early if anything did."""
    rows = [(k, f"{metrics[k]:.4g}") for k in SUMMARY_KEYS if k in metrics]
    if metrics.get("max_epochs"):
        rows.append(("epochs_run", f"{int(metrics.get('epochs_run', 0))} of {int(metrics['max_epochs'])}"))
        if metrics.get("stopped_by_time_limit"):
            rows.append(("stopped_by", "the time limit (trainer.max_time)"))
        elif metrics.get("stopped_early"):
            rows.append(("stopped_by", "a callback (early stopping)"))
    return rows


def print_summary(metrics: dict[str, float], title: str = "test metrics", caption: Optional[str] = None) -> None:
    """A short table of the headline metrics (rich if available), with `caption` in words below it."""
    rows = summary_rows(metrics)
    try:
        from rich.console import Console
        from rich.table import Table

        table = Table(title=title, caption=caption, caption_justify="left")
        table.add_column("metric")
        table.add_column("value", justify="right")
        for k, v in rows:
            table.add_row(k, v)
        Console().print(table)
    except ImportError:  # pragma: no cover
        print(title)
        for k, v in rows:
            print(f"  {k:40s} {v}")
        if caption:
            print(caption)
