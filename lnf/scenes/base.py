"""What a scene is: a body B, a mass density ω0, a potential V, a full-order simulator, an energy scale."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch
from scipy.integrate import solve_ivp
from torch import Tensor

from lnf.quadrature import NodeQuadrature, Quadrature
from lnf.utils import require


class DiscretePotential:
    """V restricted to fields sampled at fixed quadrature points.

    Call with q (B, N, A) and, when ``needs_gradient``, G = ∇_X q (B, N, A, dim_B); returns V (B,).
    """

    needs_gradient: bool = False

    def __call__(self, q: Tensor, G: Optional[Tensor] = None) -> Tensor:  # pragma: no cover - interface
        raise NotImplementedError

    def gradient(self, q: Tensor, G: Optional[Tensor] = None) -> tuple[Tensor, Optional[Tensor]]:
        """(∂V/∂q_j (B, N, A), ∂V/∂G_j (B, N, A, dim_B) or None): derivatives w.r.t. nodal values.

        Default: exact, by torch.func (works under no_grad and inference_mode). Override with a closed
        form where one is cheap.
        """
        from torch.func import grad, vmap

        if self.needs_gradient:
            dq, dG = vmap(grad(lambda a, b: self(a[None], b[None])[0], argnums=(0, 1)))(q, G)
            return dq, dG
        return vmap(grad(lambda a: self(a[None])[0]))(q), None


class ModalKinetic:
    """Kinetic energy beyond the flat ½∫ω0‖q̇‖²: ½ aᵀ C(θ) a with θ = P q and a = P q̇ (mode projections).

    For a finite-dimensional mechanical system lifted into a field along m modes (the double pendulum),
    T(q, q̇) = ½∫ω0‖q̇‖² + ½ aᵀ (M(θ) − κ I) a, so that on the modes the metric is M(θ) and off them the
    flat κ = ω0. Subclasses give C(θ) = M(θ) − κI, its Coriolis vector and ∂T_C/∂θ in closed form.

    Attributes:
        weighted_modes: P (m, N, A), θ_i = Σ_{j,a} P_{ija} q_{ja} (quadrature weights folded in).
    """

    def __init__(self, weighted_modes: Tensor) -> None:
        self.weighted_modes = weighted_modes

    def angles(self, x: Tensor) -> Tensor:
        """θ = P x for fields x (B, N, A) → (B, m); for a jet's J (B, N, A, d) → (B, m, d) etc."""
        return torch.einsum("mna,bna...->bm...", self.weighted_modes.to(x), x)

    def matrix(self, theta: Tensor) -> Tensor:  # pragma: no cover - interface
        """C(θ) (B, m, m)."""
        raise NotImplementedError

    def coriolis(self, theta: Tensor, theta_dot: Tensor) -> Tensor:  # pragma: no cover - interface
        """(dC/dt) θ̇ − ∂T_C/∂θ (B, m): the Coriolis/centrifugal vector of T_C = ½ θ̇ᵀ C(θ) θ̇."""
        raise NotImplementedError

    def gradient(self, theta: Tensor, theta_dot: Tensor) -> Tensor:  # pragma: no cover - interface
        """∂T_C/∂θ at fixed θ̇ (B, m)."""
        raise NotImplementedError


class GeneralizedForce:
    """Non-conservative generalized forces (damping, actuation) on fields sampled at quadrature points.

    ``field_force(t, q, v, controls)`` returns the force density f (B, N, A) per unit reference volume at the
    points, so that the reduced generalized force is τ̃ = Σ_j w_j J_jᵀ f_j (B, d). `controls` (B, c) are the
    per-trajectory load parameters of :meth:`Scene.controls` (or None). A force that gives :meth:`separated` needs
    no ``field_force`` of its own: the default reads it from there.
    """

    def __init__(self, weights: Tensor) -> None:
        self.weights = weights

    def field_force(self, t: float, q: Tensor, v: Tensor, controls: Optional[Tensor]) -> Tensor:
        """f = −c(X) u̇ + Σ_k a_k(t) s_k(X) (B, N, A) of :meth:`separated`; a force that is not separated overrides
        this."""
        parts = self.separated()
        if parts is None:  # pragma: no cover - interface
            raise NotImplementedError(f"{type(self).__name__} defines neither field_force nor separated")
        amplitudes = parts.amplitudes(t, controls, v.shape[0]).to(v)  # (B, K)
        return -parts.damping.to(v)[None, :, None] * v + torch.einsum("bk,kna->bna", amplitudes, parts.shapes.to(v))

    def separated(self) -> Optional["SeparatedForce"]:
        """The force as f = −c(X) u̇ + Σ_k a_k(t) s_k(X) (:class:`SeparatedForce`), if it has that form: its reduced
        parts are then functions of q̃ alone, which a table holds (``dynamics=tabulated``). None (the default): not
        separable; such a scene rolls out on the exact pullback."""
        return None


@dataclass(frozen=True)
class SeparatedForce:
    """A force density f = −c(X) u̇ + Σ_k a_k(t, controls) s_k(X) at the quadrature points of its
    :class:`GeneralizedForce`: a velocity-proportional damping and loads of fixed shape with time-varying amplitudes.

    Attributes:
        damping: c_j ≥ 0 (N,) [kg/(m³ s)]: the damping density (e.g. α ρ for mass-proportional damping).
        shapes: s_k (K, N, A): the loads' shapes (force per unit reference volume per unit amplitude).
        amplitudes: (t, controls (B, c) or None, batch B) → a_k (B, K): zeros where there are no controls.

    The reduced force is then τ̃ = −D̃(q̃) q̃̇ + Σ_k a_k ∂W_k/∂q̃ with D̃ = Σ_j w_j c_j J_jᵀJ_j and
    W_k = Σ_j w_j s_kj · φ_j.
    """

    damping: Tensor
    shapes: Tensor
    amplitudes: Callable[[float, Optional[Tensor], int], Tensor]


@dataclass(frozen=True)
class StabilityCases:
    """The high-energy question of the stability study (experiments/stability.py) for one scene: releases at rest
    beyond the training range, one per value of `levels`, and optionally one state that leaves the training
    regime altogether (`rotation`).

    Attributes:
        levels: the release amplitudes, in units of `unit` (the x values of the chart, e.g. θ0 / π).
        xlabel: the chart's label of a level (what is released, and its unit).
        train_edge: the level where the training range ends (the chart shades [0, train_edge]).
        train_text: the legend of that shading (e.g. "training range |θ0| ≤ π/2").
        rotation: a full-order state (S,) evaluated as one more case (the pendulum rotating above the
            separatrix), or None.
        unit: the scene's release amplitude of level 1, so that a level's state is
            ``scene.released_at_rest(level * unit)`` (π when levels are θ0 / π; 1 when they are the amplitude).
    """

    levels: tuple[float, ...]
    xlabel: str
    train_edge: float
    train_text: str
    rotation: Optional[tuple[float, ...]] = None
    unit: float = 1.0

    def states(self, scene: "Scene", level: float) -> np.ndarray:
        """The full-order initial state (S,) of `level` for `scene`: its release at rest."""
        return scene.released_at_rest(level * self.unit)


class SceneMethodMissing(NotImplementedError):
    """A scene was asked for an optional part it does not define; the message names the scene, the method
    and what needs it."""


_REQUIRED_ATTRIBUTES = {
    "field_dim": "dim_A, the number of components of the field's values (1 for a scalar field)",
    "bounds": "[[lo, hi], ...], the box that holds the body B, one row per material dimension",
    "energy_scale": "the energy [J, or the scene's unit] that energy errors are divided by (e.g. m g ℓ)",
}


class Scene:
    """Base class of scenes: a continuum body with a known Lagrangian.

    **Required core** (a scene cannot be trained without it):

    - ``field_dim`` (int): dim_A, components of the field values q(X) ∈ ℝ^A.
    - ``bounds`` (list of [lo, hi]): the box holding the body B, one row per material dimension
      (dim_B = 1, 2 or 3).
    - ``energy_scale`` (float > 0): the energy that energy errors are divided by.
    - :meth:`density`: ω0 (mass per unit reference volume) at material points.
    - :meth:`potential`: V restricted to fields sampled on a quadrature rule.
    - :meth:`params`: the constructor arguments (the scene is rebuilt from them in checkpoints and datasets).

    **Optional parts** (each method's docstring says what needs it; asking a scene for one it lacks raises
    :class:`SceneMethodMissing` naming the scene and the method): :meth:`simulate` and
    :meth:`sample_initial_states` (a full-order reference, to generate data), :meth:`fields` (fields of full-order
    states), :meth:`true_energy_parts` (the reference energies), :meth:`kinetic_correction`,
    :meth:`generalized_force` and :meth:`controls` (non-conservative forces and loads), :meth:`clamp_factor`,
    :meth:`field_gradients`, :meth:`released_at_rest` (the stability study's release cases), :meth:`with_damping`
    (the same body with a damping added: energy behaviour under damping, without retraining).

    :meth:`capabilities` says which optional parts a scene has: code asks it, never a scene's name.

    **What the benchmark studies ask** (experiments/; each has a default derived from the parts above, which a
    scene may override): :meth:`baselines` (which baseline methods can run it), ``expensive_reference`` (whether
    its full-order reference is itself a costly discretisation), :meth:`stability_cases` (the stability study's
    high-energy releases; None by default) and :attr:`has_controls` (per-trajectory loads).

    Attributes:
        name: the scene's name in file names and plots (default: the class name, lower case).
        state_names: names of the full-order state's components (for files and error messages).
    """

    state_names: tuple[str, ...] = ()
    #: Whether the full-order reference (:meth:`simulate`) is itself a costly discretisation of the body (an FEM
    #: model, not the ODE of a few angles). The studies then treat it as the full-order model: pareto.py times it
    #: per trajectory and draws its cost as the full-order line, and stability.py does not re-simulate a 500 s
    #: reference per job (its 200× horizon measures the energy drift alone). Default False.
    expensive_reference: bool = False

    def __getattr__(self, key: str) -> Any:  # only reached when the attribute is not set
        if key in _REQUIRED_ATTRIBUTES:
            raise AttributeError(f"scene {type(self).__qualname__} sets no {key}: {_REQUIRED_ATTRIBUTES[key]}; set it "
                                 f"as a class attribute or in __init__ (every scene needs it)")
        if key == "name":
            return type(self).__name__.lower()
        raise AttributeError(f"{type(self).__qualname__!r} object has no attribute {key!r}")

    @property
    def body_dim(self) -> int:
        """dim_B, the dimension of the body (the rows of ``bounds``)."""
        return len(self.bounds)

    # -- what the scene can do -----------------------------------------------------------------
    def provides(self, method: str) -> bool:
        """Whether the scene's class defines `method` itself (not only the base class's default)."""
        base = getattr(Scene, method, None)
        if base is None:
            raise ValueError(f"Scene has no method {method!r}; its optional parts are {', '.join(OPTIONAL_PARTS)}")
        return getattr(type(self), method) is not base

    @property
    def is_conservative(self) -> bool:
        """True when no non-conservative force acts (energy is conserved): the default when the scene defines no
        :meth:`generalized_force`; a scene whose forces can be switched off overrides this."""
        return not self.provides("generalized_force")

    def capabilities(self) -> dict[str, bool]:
        """What the scene declares it can do, by name: ``simulator`` (a full-order reference that can generate
        data), ``fields``, ``true_energies``, ``conservative`` (False: damping or loads act), ``kinetic_correction``,
        ``clamp``, ``field_gradients``, ``release_at_rest``, ``damping`` (:meth:`with_damping`)."""
        return {
            "simulator": self.provides("simulate") and self.provides("sample_initial_states"),
            "fields": self.provides("fields"),
            "true_energies": self.provides("true_energy_parts"),
            "conservative": bool(self.is_conservative),
            "kinetic_correction": self.provides("kinetic_correction"),
            "clamp": self.provides("clamp_factor"),
            "field_gradients": self.provides("field_gradients"),
            "release_at_rest": self.provides("released_at_rest"),
            "damping": self.provides("with_damping"),
        }

    @property
    def has_controls(self) -> bool:
        """Whether full-order states carry per-trajectory load parameters (:meth:`controls` returns an (n, c) array,
        not None), which a rollout then takes. Default: the scene defines :meth:`controls` and is not conservative;
        a scene whose controls do not follow that rule overrides this."""
        return self.provides("controls") and not self.is_conservative

    def baselines(self) -> dict[str, bool]:
        """Which baseline methods of the studies (METHODS of experiments/studylib/study.py) can run this scene, by name:

        - ``full_order``: the nodal full-order model (:class:`lnf.baselines.FullOrderModel`, ω0 w q̈ = −∂V/∂q on a
          grid of nodes) has only the flat kinetic energy ½∫ω0‖q̇‖², no ∇_X q and no external forces, and
          interpolates 2-D bodies only. Default: True iff the body is 2-D, :meth:`kinetic_correction` and
          :meth:`generalized_force` are None and the potential does not need ∇_X q (asked on a 2-point-per-axis
          Gauss–Legendre rule).
        - ``latent_mlp``: the black-box latent MLP takes no per-trajectory loads. Default: ``not has_controls``.
        - ``pod``: POD-Galerkin pulls back any Lagrangian. Default: True.
        - ``opinf``: Operator Inference reads only the dataset's fine-grid fields and velocities: not listed, so able.

        Override to exclude a baseline the defaults allow, e.g. ``return {**super().baselines(), "pod": False}``.
        A method missing from the dict counts as able to run the scene.
        """
        from lnf.quadrature import GaussLegendre

        quadrature = GaussLegendre(2).build(self.bounds)
        full_order = (self.body_dim == 2 and not self.potential(quadrature).needs_gradient
                      and self.kinetic_correction(quadrature) is None and self.generalized_force(quadrature) is None)
        return {"full_order": bool(full_order), "latent_mlp": not self.has_controls, "pod": True}

    def stability_cases(self) -> Optional[StabilityCases]:
        """The stability study's high-energy releases (:class:`StabilityCases`: the amplitudes to release at rest
        with :meth:`released_at_rest`, their label and the edge of the training range), or None (the default):
        experiments/stability.py then skips its high-energy part with a note."""
        return None

    def _missing(self, method: str, needed_for: str) -> SceneMethodMissing:
        cls = type(self)
        return SceneMethodMissing(f"scene {self.name!r} ({cls.__module__}.{cls.__qualname__}) does not define "
                                  f"{method}(), which {needed_for}; define it in the scene's class (see the "
                                  f"docstring of lnf.scenes.Scene.{method} for its shapes and units)")

    # -- the Lagrangian (required) -------------------------------------------------------------
    def density(self, points: Tensor) -> Tensor:
        """ω0 [mass per unit reference volume] at material points (..., N, dim_B) → (..., N), positive."""
        raise self._missing("density", "every scene needs (the kinetic energy ½∫ω0‖q̇‖² and the reductions)")

    def potential(self, quadrature: Quadrature) -> DiscretePotential:
        """V on fields sampled at the quadrature rule's points (see :class:`DiscretePotential`)."""
        raise self._missing("potential", "every scene needs (the reduced dynamics pull it back)")

    # -- optional parts of the Lagrangian ------------------------------------------------------
    def kinetic_correction(self, quadrature: Quadrature) -> Optional[ModalKinetic]:
        """Kinetic energy beyond ½∫ω0‖q̇‖² (None: the flat metric is the whole kinetic energy)."""
        return None

    def generalized_force(self, quadrature: Quadrature) -> Optional[GeneralizedForce]:
        """Non-conservative forces (None: the scene is conservative)."""
        return None

    def controls(self, states: np.ndarray) -> Optional[np.ndarray]:
        """Per-trajectory load parameters (n, c) read from full-order initial states (n, S), or None."""
        return None

    def input_signals(self, controls: np.ndarray, times: np.ndarray) -> np.ndarray:
        """The known load inputs u(t) (n, T, m) of trajectories with load parameters `controls` (n, c) at `times`
        (T,) [s]: what an input-affine reduced model (Operator Inference's B u) is given. Default: the parameters
        held constant (an affine load scaled per trajectory); a scene whose loads vary in time says how."""
        controls = np.asarray(controls, dtype=np.float64)
        return np.repeat(controls[:, None, :], len(np.asarray(times)), axis=1)

    def clamp_factor(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """(s, ∇s) at points (…, N, dim_B) → (…, N), (…, N, dim_B): a factor vanishing where the field is
        clamped, for a field that meets the clamp exactly (:class:`lnf.boundary.ClampedField`)."""
        raise ValueError(f"scene {self.name!r} has no clamped boundary; set model.clamp=false")

    def observation_points(self, resolution: int) -> np.ndarray:
        """Points (N, dim_B) of a generated dataset at `resolution` (``data.fine_resolution`` and
        ``data.coarse_resolution``). Default: the midpoint grid of `resolution` cells per axis of ``bounds``; a
        body that does not fill its box, or whose box is far from a cube, gives its own points inside it."""
        from lnf.quadrature import midpoint_grid

        return midpoint_grid(resolution, self.bounds).cpu().numpy()

    def element_quadrature(self) -> Quadrature:
        """The quadrature (points, weights) of the scene's own discretisation of its body, such as the elements of its
        mesh: what ``quadrature=mesh`` integrates the pulled-back Lagrangian with."""
        raise self._missing("element_quadrature", "quadrature=mesh needs (the quadrature of the scene's own mesh)")

    def nodal_quadrature(self) -> NodeQuadrature:
        """The nodes of the scene's own mesh with their lumped volumes (:class:`lnf.quadrature.NodeQuadrature`); the
        scene's :meth:`potential` on it is the mesh's own discrete strain energy (``quadrature=mesh_nodes``)."""
        raise self._missing("nodal_quadrature", "quadrature=mesh_nodes needs (the nodes of the scene's own mesh)")

    def with_damping(self, rate: float) -> "Scene":
        """A copy of the scene with mass-proportional damping −α ω0 q̇ of `rate` α [1/s] (its full-order reference
        and its :meth:`generalized_force` both damped). Pulled back through any embedding φ this force is exactly
        −α M̃(q̃) q̃̇, so a model trained on the undamped scene predicts the damped one without retraining."""
        raise self._missing("with_damping", "the damped-energy measurement (python -m experiments.scenes --measure "
                            "damped) needs")

    # -- the full-order model (optional) -------------------------------------------------------
    def sample_initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """`n` full-order initial states (n, S) drawn with `rng`: the trajectories of a generated dataset."""
        raise self._missing("sample_initial_states", "generating a dataset needs (or bring your own trajectories)")

    def released_at_rest(self, amplitude: float) -> np.ndarray:
        """The full-order state (S,) released at rest with `amplitude`, in the scene's own measure of how far
        from rest it starts (an angle in rad, a tip deflection in m): the high-energy states of the stability
        study."""
        raise self._missing("released_at_rest", "the stability study's high-energy releases need")

    def simulate(self, initial_states: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Ground-truth full-order states (n, T, S) at `times` [s] from initial states (n, S)."""
        raise self._missing("simulate", "generating a dataset, or evaluating at other times or initial states, needs")

    def fields(self, states: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Configuration field q and velocity field q̇ (…, N, A) of full-order states (…, S) at points (N, dim_B);
        must broadcast over the leading axes of `states`."""
        raise self._missing("fields", "generating a dataset, or evaluating on other points, needs")

    def field_gradients(self, states: np.ndarray, points: np.ndarray) -> np.ndarray:
        """∇_X q (…, N, A, dim_B) of full-order states (…, S) at points (N, dim_B): the target of the
        optional gradient (Sobolev) loss ``model.gradient_weight``."""
        raise ValueError(f"scene {self.name!r} gives no field gradients; set model.gradient_weight=0")

    def true_energy_parts(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(kinetic, potential) energy of full-order states (…, S) → each (…); must broadcast over leading axes."""
        raise self._missing("true_energy_parts", "the reference energies of a dataset and the energy loss need")

    def true_energy(self, states: np.ndarray) -> np.ndarray:
        """Total energy of full-order states (…, S) → (…)."""
        kinetic, potential = self.true_energy_parts(states)
        return kinetic + potential

    # -- description ---------------------------------------------------------------------------
    def params(self) -> dict[str, Any]:
        """Constructor arguments: rebuild with ``type(scene)(**scene.params())``."""
        raise self._missing("params", "checkpoints and datasets need to rebuild the scene (return {} if the "
                            "constructor takes no arguments)")

    def spec(self) -> dict[str, Any]:
        """Self-describing spec, ``{"_target_": "module.Class", **params}``. A class defined in a script run as
        ``python -m pkg.mod`` is recorded as ``pkg.mod.Class``, never ``__main__.Class``."""
        return {"_target_": importable_name(type(self)), **self.params()}

    def __repr__(self) -> str:
        try:
            args = ", ".join(f"{k}={v!r}" for k, v in self.params().items())
        except NotImplementedError:
            args = "…"
        return f"{type(self).__name__}({args})"


OPTIONAL_PARTS = ("simulate", "sample_initial_states", "fields", "true_energy_parts", "kinetic_correction",
                  "generalized_force", "controls", "clamp_factor", "field_gradients", "released_at_rest",
                  "observation_points", "element_quadrature", "nodal_quadrature", "with_damping")


def importable_name(cls: type) -> str:
    """``module.Qualname`` of `cls` under which another process can import it: a class of the ``__main__`` module
    gets the module name the script was run as (``python -m pkg.mod``); a script run by its path has none, which
    is an error saying to move the class into an importable module."""
    module = cls.__module__
    if module == "__main__":
        import sys

        main_spec = getattr(sys.modules.get("__main__"), "__spec__", None)
        if main_spec is None or not main_spec.name or main_spec.name == "__main__":
            raise ValueError(f"{cls.__qualname__} is defined in a script run by its path (module __main__): a "
                             f"dataset or checkpoint could not rebuild it. Put it in an importable module (a .py "
                             f"file on the Python path) and import it, or run the script as python -m <module>")
        module = main_spec.name
    return f"{module}.{cls.__qualname__}"


def check_positive(**values: float) -> None:
    """Raise a ValueError naming ``scene.<key>`` unless every value is a positive finite number."""
    for key, value in values.items():
        require(f"scene.{key}", value, (">", 0, None, ""))


def check_range(**ranges: Sequence[float]) -> None:
    """Raise a ValueError naming ``scene.<key>`` unless every range is [low, high] with low ≤ high."""
    for key, rng in ranges.items():
        if len(rng) != 2 or not rng[0] <= rng[1]:
            raise ValueError(f"scene.{key} must be [low, high] with low ≤ high, got {list(rng)!r}")


def solve_trajectories(rhs: Callable[[float, np.ndarray], np.ndarray], initial_states: np.ndarray,
                       times: np.ndarray, rtol: float, atol: float, what: str) -> np.ndarray:
    """Ground truth of an ODE y' = rhs(t, y) by DOP853: states (n, T, S) at `times` from initial states (n, S)."""
    initial_states = np.asarray(initial_states, dtype=np.float64)
    out = np.empty((len(initial_states), len(times), initial_states.shape[-1]))
    for i, y0 in enumerate(initial_states):
        sol = solve_ivp(rhs, (times[0], times[-1]), y0, method="DOP853", t_eval=times, rtol=rtol, atol=atol)
        if not sol.success:
            raise RuntimeError(f"{what} ground truth failed for initial state {y0}: {sol.message}")
        out[i] = sol.y.T
    return out


def as_tensor(x: np.ndarray, like: Tensor) -> Tensor:
    return torch.as_tensor(x, dtype=like.dtype, device=like.device)
