"""LagrangianNeuralField: the embedding φ, the reduction ρ̃ and the pulled-back dynamics in one object.

The Python API of lnf (no Lightning or Hydra needed)::

    model = lnf.load("outputs/.../checkpoints/last.ckpt")
    q0 = model.reduce(points, values)                  # (B, N, dim_B), (B, N, A) -> (B, d)
    v0 = model.project_velocity(q0, points, velocities) # -> (B, d)
    traj = model.rollout(q0, v0, dt=0.05, steps=100, integrator="implicit_midpoint")
    fields = model.decode(traj.q[:, -1], grid)          # any points (N, dim_B) -> (B, N, A)
    T, V = model.energy(traj.q, traj.v)
"""
from __future__ import annotations

import difflib
import importlib
import inspect
import logging
import math
import pkgutil
from pathlib import Path
from collections.abc import Iterable
from typing import Any, Optional

import torch
from torch import Tensor, nn

from lnf.boundary import ClampedField
from lnf.closure import PotentialClosure, floored_spans
from lnf.dynamics_kind import dynamics_kind
from lnf.error_budget import SIREN_COLLAPSE_ADVICE
from lnf.quadrature import Quadrature, QuadratureRule
from lnf.reduced_model import ReducedModel, as_field
from lnf.baselines.pod import LinearEmbedding
from lnf.pod_subspace import SubspacePlusField, zero_output
from lnf.reduction import (best_start, project_velocity, projection_loss, pullback_mass_matrix, reconstruction_loss,
                           reduce, start_grid)
from lnf.scenes.base import Scene
from lnf.siren import ModulatedSiren
from lnf.trust import UnsafeCheckpointError, check_spec_targets, read_weights_only
from lnf.utils import require

log = logging.getLogger("lnf.model")


def target_class(target: Any, key: Optional[str] = None) -> Any:
    """The class a spec's ``_target_ = "pkg.mod.Class"`` names; a ValueError saying what to fix otherwise.

    `key`: the config key that gave `target` (``scene._target_``), named first in the error. The error says whether
    the module cannot be found, was found but failed to import, or has no such class, with close matches."""
    where = f"{key}={target}: " if key else ""
    if not target or "." not in str(target):
        raise ValueError(f"{where}spec needs a '_target_' of the form 'module.Class', got {target!r}")
    module, _, name = str(target).rpartition(".")
    try:
        imported = importlib.import_module(module)
    except ImportError as err:
        missing = getattr(err, "name", None)
        if isinstance(err, ModuleNotFoundError) and missing and (module == missing or module.startswith(missing + ".")):
            hint = _close_modules(missing)
            raise ValueError(f"{where}cannot import module {module!r} of {target!r} named in a spec (no module named "
                             f"{missing!r}{hint}): a scene or model of your own must be importable where it is "
                             f"loaded: run from the folder that holds {module.split('.')[0]!r}, add that folder to "
                             f"PYTHONPATH, or install it") from err
        raise ValueError(f"{where}cannot import module {module!r} of {target!r} named in a spec: the module was "
                         f"found, but importing it failed ({type(err).__name__}: {err}); fix that import") from err
    try:
        return getattr(imported, name)
    except AttributeError as err:
        names = [n for n in dir(imported) if not n.startswith("_") and isinstance(getattr(imported, n, None), type)]
        close = difflib.get_close_matches(name, names, n=3, cutoff=0.6)
        hint = f" Did you mean {' or '.join(repr(f'{module}.{c}') for c in close)}?" if close else ""
        named = "" if key else f", which a spec names as {target!r}"
        raise ValueError(f"{where}module {module!r} ({getattr(imported, '__file__', '?')}) has no {name!r}{named}: "
                         f"was it renamed?{hint}") from err


def _close_modules(missing: str) -> str:
    """'; did you mean ...?' with the modules beside `missing` (in its parent package, or top-level) whose names are
    close to it, or ''."""
    parent, _, leaf = missing.rpartition(".")
    try:
        path = importlib.import_module(parent).__path__ if parent else None
        names = [m.name for m in pkgutil.iter_modules(path)]
    except Exception:  # noqa: BLE001 - a hint only
        return ""
    close = difflib.get_close_matches(leaf, names, n=3, cutoff=0.75)
    return f"; did you mean {' or '.join(repr(f'{parent}.{c}' if parent else c) for c in close)}?" if close else ""


def build(spec: dict[str, Any]) -> Any:
    """Instantiate ``{"_target_": "pkg.mod.Class", **kwargs}`` without Hydra (for checkpoints)."""
    spec = dict(spec)
    return target_class(spec.pop("_target_", None))(**spec)


def build_model(scene: dict[str, Any], model: dict[str, Any], quadrature: dict[str, Any]) -> ReducedModel:
    """Model from plain specs (``{"_target_": ..., **kwargs}``): what checkpoints store. Settings the model does
    not take (an experiment's SIREN width given to POD-Galerkin) are dropped with a warning naming them."""
    spec = dict(model)
    spec.setdefault("_target_", "lnf.model.LagrangianNeuralField")
    dropped = dropped_settings(spec)
    spec = {k: v for k, v in spec.items() if k not in dropped}
    return build({**spec, "scene": build(scene), "quadrature": build(quadrature)})


def dropped_settings(spec: dict[str, Any]) -> list[str]:
    """Keys of a model spec that its ``_target_`` does not take (each named in a warning), e.g. the neural
    settings of an experiment (``model.width``) when ``model=pod`` is chosen."""
    try:
        cls = target_class(spec.get("_target_"))
        params = inspect.signature(cls).parameters
    except (ValueError, TypeError):
        return []  # build() reports a target that cannot be imported
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return []
    unknown = sorted(k for k in spec if k != "_target_" and k not in params)
    if unknown:
        log.warning("%s takes no %s: dropped (an experiment may have set them for another model)", cls.__name__,
                    ", ".join(f"model.{k}" for k in unknown))
    return unknown


def load(path: "str | Path", map_location: "str | torch.device" = "cpu",
         trust: "Iterable[str] | str | None" = None) -> ReducedModel:
    """Rebuild a trained model from a Lightning checkpoint in one call, without Hydra or Lightning.

    The checkpoint's ``hyper_parameters`` hold the scene, model and quadrature specs; the returned model
    is in eval mode and carries ``model.checkpoint = {"path", "data", "epoch", "global_step"}``.

    Opening a checkpoint runs no code it carries: it is read with ``weights_only=True`` and every ``_target_`` of
    its specs must be one of lnf's own classes or a class of a module named in `trust` (or ``$LNF_TRUST``), e.g.
    ``trust=["mypkg"]`` for a scene of your own (:mod:`lnf.trust`); anything else is refused before import.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        ckpt = read_weights_only(path, map_location=map_location)
    except UnsafeCheckpointError:
        raise
    except Exception as err:  # noqa: BLE001 - any other failure to read means "not a checkpoint"
        raise ValueError(f"{path} is not a readable torch checkpoint: {err}") from err
    hp = ckpt.get("hyper_parameters") if isinstance(ckpt, dict) else None
    if not isinstance(hp, dict) or not all(isinstance(hp.get(k), dict) for k in ("scene", "model", "quadrature")) \
            or "state_dict" not in ckpt:
        raise ValueError(f"{path} is not an lnf checkpoint: expected 'hyper_parameters' with scene/model/quadrature "
                         "and a 'state_dict' (as written by python -m lnf.train)")
    check_spec_targets({k: hp[k] for k in ("scene", "model", "quadrature")}, str(path), trust)
    model = build_model(hp["scene"], hp["model"], hp["quadrature"])
    state = {k[len("model."):]: v for k, v in ckpt["state_dict"].items() if k.startswith("model.")}
    model.load_state_dict(state)
    model.eval()
    # the content checksum of the data file it was trained on (lnf.dataset.content_checksum), where recorded: in the
    # data settings, or in the state the SnapshotDataModule keeps in the checkpoint
    data_state = ckpt.get("SnapshotDataModule")
    data_checksum = (hp.get("data") or {}).get("checksum") if isinstance(hp.get("data"), dict) else None
    if not data_checksum and isinstance(data_state, dict):
        data_checksum = data_state.get("checksum")
    model.checkpoint = {"path": str(path), "data": hp.get("data"), "epoch": ckpt.get("epoch"),
                        "global_step": ckpt.get("global_step"), "data_checksum": data_checksum}
    return model


class LagrangianNeuralField(ReducedModel):
    """φ (modulated SIREN), ρ̃ (K gradient steps with learned α > 0) and the scene's Lagrangian.

    Args:
        scene: the scene whose Lagrangian is pulled back (gives ω0, V, dim_A, B).
        latent_dim: d ≥ 1.
        width, depth, w0, hyper_width, hyper_depth, hyper_init_scale: see :class:`ModulatedSiren`.
        reduction_steps: K ≥ 1.
        reduction_starts, start_radius: with reduction_starts = S > 1 the K steps start from the best of
            S^d candidate codes on [−start_radius, start_radius]^d (a coarse search; 1 = from q̃ = 0, the paper).
        step_size: initial α of the reduction (learned as log α).
        velocity_weight: λ_v of the optional tangent (velocity) reconstruction loss, not in the paper;
            0 gives the paper's loss ℓ^r + ℓ^p exactly (see :meth:`losses`).
        energy_weight: λ_E of the optional potential-energy loss ℓ^E = huber((Ṽ(q̃) − V)/E_scale), Ṽ the pulled-back
            potential at the snapshot's code and V the full-order one (not in the paper; see :meth:`losses`).
        dynamics_weight: λ_D of the optional dynamics-residual loss ℓ^D: the pulled-back equations' acceleration at
            the snapshot's code and code velocity against the code acceleration of the observed motion (not in the
            paper; see :meth:`losses`).
        gradient_weight: λ_G of the optional gradient (Sobolev) loss ℓ^G = (1/N) Σ_j ω0 ‖∇_X φ − ∇_X q‖² against
            the full-order field gradient at the observed points (not in the paper; see :meth:`losses`).
        mass_condition_weight, mass_condition_max: λ_M and κ of the mass-conditioning loss
            ℓ^M = relu(log₁₀ cond M̃ − log₁₀ κ)², M̃ the pulled-back mass matrix of the snapshot's code on the observed
            points (not in the paper; see :meth:`losses`). Zero at d = 1 and wherever cond M̃ ≤ κ.
        clamp: φ = s(X) ψ with the scene's clamp factor s (:class:`lnf.boundary.ClampedField`), so the field
            meets a clamped boundary exactly; not in the paper (its scenes have none).
        pod_subspace: φ = m(X) + Φ(X) q̃ + ψ(q̃, X), the mean and d POD modes of the training observations (in a
            Legendre basis of degree `pod_degree` per axis, fitted by :meth:`fit_subspace` before training) plus the
            SIREN ψ, zero at initialisation (:mod:`lnf.pod_subspace`); not in the paper.
        pod_residual_scale: ε > 0, the fixed factor on ψ's output with `pod_subspace` (φ = m + Φ q̃ + ε ψ): ε < 1 moves
            ψ as a smaller learning rate would (1.0: checkpoints written before the option existed).
        quadrature: rule for the integrals of the reduced dynamics (default Gauss–Legendre 8×8).
        dynamics: None (the pulled-back Lagrangian, our model); a ``lnf.tabulated.TabulatedDynamics`` spec
            (the same Lagrangian with M̃ and Ṽ read from a Chebyshev table on the training codes' range widened
            by ``margin``, see :meth:`dynamics`); or a ``_target_`` spec of learned latent dynamics, e.g.
            ``lnf.baselines.latent_mlp.LatentMLPDynamics`` (the black-box baseline; it is fitted after the
            field, on the codes of the training trajectories).

    Defaults are those of ``conf/model/lnf.yaml`` (where w0 = auto: lnf.train searches it on the data; lnf's scenes
    set 10 or 30 rather than the paper's 30 everywhere) and λ_v = 0.1 (see docs/choices.md).
    """

    reduces_through_field = True  # reduce(field=...): the K steps iterate on any φ with a jet (a table of it, too)
    learned_codes = True  # a table of the pullback or a black-box dynamics can be built on its codes
    collapse_advice = SIREN_COLLAPSE_ADVICE

    def __init__(
        self,
        scene: Scene,
        latent_dim: int = 1,
        width: int = 256,
        depth: int = 2,
        w0: float = 10.0,
        hyper_width: int = 128,
        hyper_depth: int = 1,
        hyper_init_scale: float = 0.1,
        reduction_steps: int = 3,
        reduction_starts: int = 1,
        start_radius: float = 1.0,
        step_size: float = 0.1,
        velocity_weight: float = 0.1,
        clamp: bool = False,
        pod_subspace: bool = False,
        pod_degree: int = 12,
        pod_residual_scale: float = 1.0,
        energy_weight: float = 0.0,
        dynamics_weight: float = 0.0,
        closure_degree: int = 0,
        closure_max_terms: Optional[int] = None,
        gradient_weight: float = 0.0,
        mass_condition_weight: float = 1.0,
        mass_condition_max: float = 100.0,
        quadrature: Optional[QuadratureRule] = None,
        dynamics: Optional[dict[str, Any]] = None,
    ) -> None:
        super().__init__(scene, quadrature)
        if isinstance(w0, str):
            raise ValueError(f"model.w0={w0!r}: LagrangianNeuralField takes a number; w0=auto is resolved by "
                             "`python -m lnf.train` (a short search on the data, lnf/w0_search.py) before it builds "
                             "the model, so give the number when building it yourself")
        require("model.reduction_steps", reduction_steps)
        require("model.step_size", step_size)
        self.velocity_weight = require("model.velocity_weight", velocity_weight)
        self.energy_weight = require("model.energy_weight", energy_weight)
        self.gradient_weight = require("model.gradient_weight", gradient_weight)
        self.dynamics_weight = require("model.dynamics_weight", dynamics_weight)
        if self.dynamics_weight > 0 and not scene.is_conservative:
            raise ValueError(f"model.dynamics_weight={dynamics_weight}: the dynamics-residual loss needs the "
                             f"snapshots' loads, which training batches do not carry, and scene {scene.name!r} has "
                             f"non-conservative forces; set model.dynamics_weight=0")
        self.mass_condition_weight = require("model.mass_condition_weight", mass_condition_weight)
        self.mass_condition_max = require("model.mass_condition_max", mass_condition_max)
        self.field = ModulatedSiren(latent_dim=latent_dim, in_dim=scene.body_dim, out_dim=scene.field_dim,
                                    width=width, depth=depth, w0=w0, hyper_width=hyper_width,
                                    hyper_depth=hyper_depth, hyper_init_scale=hyper_init_scale)
        if clamp:  # φ = s(X) ψ: exactly zero on the scene's clamped boundary
            scene.clamp_factor(torch.zeros(1, scene.body_dim))  # a clear error for scenes without a clamp
            self.field = ClampedField(self.field, scene.clamp_factor)
        if pod_subspace:  # φ = m + Φ q̃ + ψ: training starts from POD-Galerkin of the same dimension
            zero_output(self.field)
            linear = LinearEmbedding(scene.bounds, int(latent_dim), scene.field_dim, pod_degree)
            self.field = SubspacePlusField(linear, self.field, require("model.pod_residual_scale", pod_residual_scale))
        require("model.closure_degree", closure_degree)
        # a potential closure ΔṼ fitted after training (lnf/closure.py); its buffers travel in the checkpoint. No cap
        # by default here: a checkpoint written before model.closure_max_terms rebuilds its closure's shapes as they were
        self.closure = (PotentialClosure(latent_dim, closure_degree, closure_max_terms) if int(closure_degree)
                        else None)
        self.reduction_steps = int(reduction_steps)
        require("model.reduction_starts", reduction_starts)
        require("model.start_radius", start_radius)
        self.register_buffer("starts", start_grid(int(latent_dim), int(reduction_starts), float(start_radius)),
                             persistent=False)
        self.log_step_size = nn.Parameter(torch.tensor(math.log(step_size)))
        self.latent_dynamics: Optional[nn.Module] = None
        self.tabulation: Optional[dict[str, Any]] = None
        kind = None if dynamics is None else dynamics_kind(dynamics)
        if kind is not None and kind.needs_codes and not kind.trained:  # a table of the pullback on the codes' range
            self.set_tabulation(dynamics)
        elif kind is not None and kind.trained:
            self.latent_dynamics = build({**dynamics, "latent_dim": int(latent_dim)})
        # range of the codes of the last training epoch (the box of a tabulated dynamics); NaN until trained
        self.register_buffer("code_low", torch.full((int(latent_dim),), float("nan")))
        self.register_buffer("code_high", torch.full((int(latent_dim),), float("nan")))
        self._register_load_state_dict_pre_hook(_fill_code_range, with_module=True)
        self._table_cache: tuple[Any, Any] = (None, None)

    @property
    def step_size(self) -> Tensor:
        return self.log_step_size.exp()

    def reduce(self, points: Tensor, values: Tensor, steps: Optional[int] = None, field: Any = None) -> Tensor:
        """ρ̃(q): observed field values (B, N, A) at points (N or B, N, dim_B) → codes (B, d).

        `field`: the φ the K steps iterate on, if not the model's own (e.g. a
        :class:`lnf.decoding_table.TabulatedField` of it on these points). Values and points of another dtype
        (float64) are converted to the model's; the codes are in the model's dtype (float32 once trained)."""
        values = as_field(self.as_model(values))
        points = self.as_model(points)
        self._check_observation(points, values, "values")
        density = self._density(points)
        return self._reduce(points, values, density, steps or self.reduction_steps, field)

    @property
    def needs_fit(self) -> bool:
        """Whether a part of φ is fitted in closed form before training (:meth:`fit_subspace`) and is not yet."""
        return isinstance(self.field, SubspacePlusField) and not bool(self.field.fitted)

    def fit_subspace(self, points: Tensor, values: Tensor) -> dict[str, float]:
        """The POD part of φ from training observations, points (n, Nobs, dim_B), values (n, T, Nobs, A)."""
        return self.field.fit(points, values)

    def share_fit(self, other: "LagrangianNeuralField") -> None:
        """The POD part of φ as `other` (a model of the same settings) fitted it: one fit for a w0 search."""
        self.field.take_fit(other.field)

    def _start(self, points: Tensor, values: Tensor, density: Tensor, field: Any = None) -> Optional[Tensor]:
        """The K steps' initial codes (B, d): the projection onto the POD subspace where φ contains one, else the
        best of the start grid, or None (q̃^0 = 0) with one start."""
        if isinstance(self.field, SubspacePlusField):
            return self.field.start(self.as_model(points), values, density)
        field = self.field if field is None else field
        return best_start(field, points, values, density, self.starts) if len(self.starts) > 1 else None

    def _reduce(self, points: Tensor, values: Tensor, density: Tensor, steps: int, field: Any = None) -> Tensor:
        field = self.field if field is None else field
        codes = self._start(points, values, density, field)
        return reduce(field, points, values, density, self.step_size, steps, codes=codes)

    def dynamics(self, quadrature: "Quadrature | QuadratureRule | None" = None) -> Any:
        """The pulled-back Lagrangian system (tabulated if ``tabulation`` is set; with its potential closure ΔṼ
        once fitted, lnf/closure.py), or the learned latent dynamics of the black-box baseline.

        A table is built once per quadrature and parameter state (cached until the parameters change)."""
        if self.latent_dynamics is not None:
            return self.latent_dynamics.as_dynamics(self.lagrangian_dynamics(quadrature))
        return self.closed(self._pullback(quadrature))

    def _pullback(self, quadrature: "Quadrature | QuadratureRule | None") -> Any:
        """The pulled-back Lagrangian system, from its table if ``tabulation`` is set."""
        if self.tabulation is None:
            return self.lagrangian_dynamics(quadrature)
        key = (id(quadrature), quadrature, tuple(p._version for p in self.parameters()),
               tuple(self.code_low.tolist()), tuple(self.code_high.tolist()), tuple(sorted(self.tabulation.items())))
        if self._table_cache[0] != key:
            self._table_cache = (key, self._build_table(quadrature))
        return self._table_cache[1]

    def _build_table(self, quadrature: "Quadrature | QuadratureRule | None") -> Any:
        from lnf.tabulated import TABLE_MARGIN, TABLE_MAX_ERROR, TabulatedDynamics, shape_text

        opts = dict(self.tabulation or {})
        margin = float(opts.pop("margin", TABLE_MARGIN))
        low, high = self.code_low.double(), self.code_high.double()
        if not (torch.isfinite(low).all() and torch.isfinite(high).all()):
            raise ValueError("dynamics=tabulated needs the range of the training codes, which this model does not "
                             "have (a checkpoint written before lnf recorded it, or an untrained model): retrain, "
                             "or call model.track_code_range(codes) with representative codes first")
        span = floored_spans(high - low, self.code_span_floor).clamp_min(1e-3)  # a barely moving POD code too
        # built from a float64 copy of φ: the table's derivatives would amplify float32 rounding by nodes²
        exact = self.lagrangian_dynamics(quadrature)
        table = TabulatedDynamics(exact, (low - margin * span).tolist(), (high + margin * span).tolist(),
                                  builder=self.lagrangian_dynamics(quadrature, dtype=torch.float64), **opts)
        if table.info["table_error"] > TABLE_MAX_ERROR:
            log.warning("dynamics=tabulated: the table of %s (%d points, dynamics.max_nodes and "
                        "dynamics.max_table_points × TABLE_ROUGH_GROWTH allow no more) is %.1e off the exact "
                        "pullback, over the %.0e a rollout can trust (lnf.tabulated.TABLE_MAX_ERROR): rolling out on "
                        "the exact pullback instead, slower", shape_text(table.info["table_shape"]),
                        table.info["table_points"],
                        table.info["table_error"], TABLE_MAX_ERROR)
            return exact
        return table

    def set_tabulation(self, spec: Optional[dict[str, Any]]) -> None:
        """Roll out with a Chebyshev table of M̃, Ṽ (`spec`: options of :class:`lnf.tabulated.TabulatedDynamics`
        plus ``margin``, with or without its ``_target_``), or with the exact pullback (None)."""
        if spec is None:
            self.tabulation = None
            return
        opts = {k: v for k, v in dict(spec).items() if k != "_target_"}
        allowed = {"tol", "min_nodes", "max_nodes", "max_table_points", "chunk", "margin"}
        unknown = sorted(set(opts) - allowed)
        if unknown:
            raise ValueError(f"dynamics (tabulated) got unknown keys {unknown}; expected some of {sorted(allowed)}")
        if "margin" in opts and not float(opts["margin"]) >= 0:
            raise ValueError(f"dynamics.margin must be ≥ 0, got {opts['margin']!r}")
        self.tabulation = opts

    @torch.no_grad()
    def track_code_range(self, codes: Tensor, reset: bool = False) -> None:
        """Widen the recorded range of training codes (B, d) by these codes (start afresh with `reset`)."""
        codes = codes.detach().to(self.code_low)
        finite = torch.isfinite(codes).all(-1)
        if not bool(finite.any()):
            return
        low, high = codes[finite].amin(0), codes[finite].amax(0)
        if not reset and bool(torch.isfinite(self.code_low).all()):
            low, high = torch.minimum(low, self.code_low), torch.maximum(high, self.code_high)
        self.code_low.copy_(low)
        self.code_high.copy_(high)

    # ------------------------------------------------------------------ training losses (docs/method.md §4)
    def losses(self, points: Tensor, values: Tensor, velocities: Optional[Tensor] = None,
               potential: Optional[Tensor] = None, energy_factor: float = 1.0,
               gradients: Optional[Tensor] = None, accelerations: Optional[Tensor] = None,
               acceleration_valid: Optional[Tensor] = None) -> dict[str, Tensor]:
        """Training losses of snapshots (B, N, A) observed at points (B, N, dim_B) (docs/method.md §4).

        ``loss = ℓ^r + ℓ^p`` (+ λ_v ℓ^v when ``velocity_weight`` > 0 and `velocities` (B, N, A) are given),
        with the optional tangent reconstruction loss ℓ^v = (1/|X|) Σ_j ω0 ‖J q̃̇ − q̇_j‖², q̃̇ the
        ω0-projection of the observed velocity onto the tangent space span J (the lifted reduction
        dρ = (dφ)† of the paper's eq. 14, † the ω0-weighted pseudo-inverse). ℓ^v is the part of the observed
        velocity that the embedding's tangent space misses; ℓ^r and ℓ^p do not constrain it.

        With ``energy_weight`` > 0 and the snapshots' full-order potential energies `potential` (B,), also
        `energy_factor` · λ_E ℓ^E (the factor is a training schedule's), ℓ^E the Huber loss (δ = 0.1) of the
        gap (Ṽ(q̃) − V)/E_scale, Ṽ the potential pulled back through φ on the model's
        quadrature. Where V depends on ∇_X q (elasticity, eq. 11), values alone leave ∇_X φ loose, and its
        error becomes stiffness in the reduced equations; ℓ^E ties the pulled-back energy to the true one.

        With ``gradient_weight`` > 0 and the snapshots' full-order field gradients `gradients` (B, N, A, dim_B),
        also λ_G ℓ^G with ℓ^G = (1/N) Σ_j ω0 ‖∇_X φ(q̃, X_j) − ∇_X q_j‖²: ∇_X φ itself fitted (Sobolev training).

        With ``dynamics_weight`` > 0 and the snapshots' observed acceleration fields `accelerations` (B, N, A) (valid
        where `acceleration_valid` (B,) says), also `energy_factor` · λ_D ℓ^D with ℓ^D the Huber loss (δ = 1) of
        ‖ã(q̃, q̃̇) − q̃̈‖ / rms_batch ‖q̃̈‖ (an untrained φ's accelerations are off by orders of magnitude): ã = M̃⁻¹(−c̃ − g̃)
        the pulled-back equations' acceleration on the model's quadrature, q̃̇ the ω0-projection of the observed
        velocity onto span J, and q̃̈ = (dφ)†(ü − H[q̃̇, q̃̇]) the code acceleration of the observed motion (u̇ = J q̃̇ and
        ü = J q̃̈ + H[q̃̇, q̃̇] on φ). ℓ^r, ℓ^p, ℓ^E and ℓ^G fit φ and Ṽ on the snapshots; ℓ^D fits the forces of the
        equations pulled back through φ to the motion the trajectories show.

        With ``mass_condition_weight`` > 0 and d ≥ 2, also λ_M ℓ^M, ℓ^M = relu(log₁₀(λ_max/λ_min) − log₁₀ κ)² over
        the eigenvalues of M̃(q̃) = Jᵀ W J on the observed points. A latent direction the data barely excite leaves a
        column of J near zero or parallel to another: M̃ near-singular, and the pulled-back dynamics stiff or
        running away along it (at d = 3 on the cantilever, cond M̃ ≈ 4·10⁴ and every test rollout diverged).
        ℓ^M keeps cond M̃ ≤ κ; it is zero at d = 1 and on well-conditioned codes.
        """
        density = self._density(points)
        K = self.reduction_steps
        start = self._start(points, values, density)
        # the jet at the start serves both reductions below (ρ̃(q) and ρ̃(φ(q̃)) begin at the same codes)
        first = self.field.jet(values.new_zeros(values.shape[0], self.field.latent_dim) if start is None else start,
                               points, order=1)
        codes = reduce(self.field, points, values, density, self.step_size, K, codes=start, first_jet=first)
        use_gradients = self.gradient_weight > 0 and gradients is not None
        jet = self.field.jet(codes, points, order=1, spatial=use_gradients)
        rec = reconstruction_loss(jet.value, values, density)
        volume = math.prod(hi - lo for lo, hi in self.scene.bounds)
        weights = volume * density / points.shape[-2]  # Monte-Carlo quadrature of the observed points
        mass = pullback_mass_matrix(jet.J, weights)
        # ρ̃(φ(q̃)) from the snapshot's own start: the search is a constant of the graph, and where ℓ^r is small
        # a second search over φ(q̃) lands on the same candidate at the cost of another S^d forward passes
        reprojected = reduce(self.field, points, jet.value, density, self.step_size, K, codes=start, first_jet=first)
        proj = projection_loss(codes, reprojected, mass)
        total = rec + proj
        out = {"reconstruction": rec.mean(), "projection": proj.mean()}
        if self.velocity_weight > 0 and velocities is not None:
            code_velocity = project_velocity(jet.J, weights, velocities)
            tangent = torch.einsum("bnai,bi->bna", jet.J, code_velocity)
            vel = reconstruction_loss(tangent, velocities, density)
            total = total + self.velocity_weight * vel
            out["velocity"] = vel.mean()
        if self.energy_weight > 0 and energy_factor > 0 and potential is not None:  # (0 · a NaN would be NaN)
            reduced = self.lagrangian_dynamics().potential_energy(codes)
            gap = (reduced - potential.to(reduced)) / self.scene.energy_scale
            energy = torch.nn.functional.huber_loss(gap, torch.zeros_like(gap), reduction="none", delta=0.1)
            total = total + energy_factor * self.energy_weight * energy
            out["energy"] = energy.mean()
        if self.dynamics_weight > 0 and energy_factor > 0 and accelerations is not None \
                and acceleration_valid is not None and bool(acceleration_valid.any()) and velocities is not None:
            residual = self._dynamics_residual(codes, points, weights, velocities, accelerations, acceleration_valid)
            total = total + energy_factor * self.dynamics_weight * residual
            out["dynamics"] = residual.sum() / acceleration_valid.sum()
        if self.mass_condition_weight > 0 and mass.shape[-1] > 1:
            eig = torch.linalg.eigvalsh(mass)  # ascending (B, d)
            tiny = torch.finfo(eig.dtype).tiny
            log_cond = torch.log10(eig[:, -1].clamp_min(tiny)) - torch.log10(eig[:, 0].clamp_min(tiny))
            condition = torch.relu(log_cond - math.log10(self.mass_condition_max)) ** 2
            total = total + self.mass_condition_weight * condition
            out["mass_condition"] = condition.mean()
        if use_gradients:
            grad = reconstruction_loss(jet.G.flatten(-2), gradients.to(jet.G).flatten(-2), density)
            total = total + self.gradient_weight * grad
            out["gradient"] = grad.mean()
        out["loss"] = total.mean()
        out["codes"] = codes.detach()
        return out

    def _dynamics_residual(self, codes: Tensor, points: Tensor, weights: Tensor, velocities: Tensor,
                           accelerations: Tensor, valid: Tensor) -> Tensor:
        """ℓ^D per snapshot (B,), zero where `valid` is False (see :meth:`losses`)."""
        keep = valid.nonzero().squeeze(-1)
        q, pts, w = codes[keep], points[keep], weights[keep]
        jet = self.field.jet(q, pts, order=2)
        code_velocity = project_velocity(jet.J, w, velocities[keep].to(jet.J))
        curvature = torch.einsum("bnaij,bi,bj->bna", jet.H, code_velocity, code_velocity)
        code_acceleration = project_velocity(jet.J, w, accelerations[keep].to(jet.J) - curvature)
        predicted = self.lagrangian_dynamics().acceleration(q, code_velocity)
        scale = code_acceleration.detach().pow(2).sum(-1).mean().clamp_min(torch.finfo(q.dtype).tiny).sqrt()
        gap = (predicted - code_acceleration).norm(dim=-1) / scale
        residual = torch.nn.functional.huber_loss(gap, torch.zeros_like(gap), reduction="none", delta=1.0)
        return codes.new_zeros(codes.shape[0]).index_put((keep,), residual)

    def extra_repr(self) -> str:
        kind = "lagrangian" if self.latent_dynamics is None else type(self.latent_dynamics).__name__
        kind = "tabulated lagrangian" if self.tabulation is not None and self.latent_dynamics is None else kind
        return f"{super().extra_repr()}, K={self.reduction_steps}, dynamics={kind}"


def _fill_code_range(module: "LagrangianNeuralField", state_dict: dict[str, Tensor], prefix: str, *args: Any) -> None:
    """Checkpoints written before lnf recorded the training codes' range load with an unknown (NaN) range."""
    for name in ("code_low", "code_high"):
        state_dict.setdefault(prefix + name, torch.full_like(getattr(module, name), float("nan")))
