"""Quadrature rules on a box-shaped reference body B.

Every integral over B in lnf is a quadrature sum Σ_j w_j f(X_j). The rule used inside the reduced
dynamics is a speed/accuracy knob of its own (docs/method.md §6.1): tensor Gauss–Legendre rules integrate
polynomials of degree 2n−1 per axis exactly; uniform midpoint grids converge only as O(h²).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

Bounds = Sequence[Sequence[float]]


@dataclass(frozen=True)
class Quadrature:
    """Points X_j (N, dim_B) and weights w_j (N,) with Σ_j w_j f(X_j) ≈ ∫_B f dX (float64 unless cast)."""

    points: Tensor
    weights: Tensor

    def __post_init__(self) -> None:
        if self.points.ndim != 2:
            raise ValueError(f"quadrature points must have shape (N, dim_B), got {tuple(self.points.shape)}")
        if self.points.shape[0] == 0:
            raise ValueError("quadrature has no points: an integral over B needs at least one point")
        if self.weights.shape != (self.points.shape[0],):
            raise ValueError(
                f"quadrature weights must have shape ({self.points.shape[0]},), got {tuple(self.weights.shape)}"
            )
        if not (torch.isfinite(self.points).all() and torch.isfinite(self.weights).all()):
            raise ValueError("quadrature points and weights must be finite")

    def __len__(self) -> int:
        return self.points.shape[0]

    def to(self, *args, **kwargs) -> "Quadrature":
        """The same rule (of the same kind) with points and weights cast or moved."""
        return dataclasses.replace(self, points=self.points.to(*args, **kwargs), weights=self.weights.to(*args, **kwargs))


@dataclass(frozen=True)
class NodeQuadrature(Quadrature):
    """The nodes X_a (N, dim_B) of a scene's own mesh, with their lumped volumes ∫ N_a dX (N,) as weights
    (``scene.nodal_quadrature()``). A scene that receives it pulls back its mesh's own discrete Lagrangian: the
    lumped kinetic energy ½ Σ_a m_a ‖φ̇(X_a)‖² and the strain energy of the mesh's interpolant of φ(·, X_a), the
    Lagrangian its full-order reference integrates (``quadrature=mesh_nodes``)."""


def _check_bounds(bounds: Bounds) -> np.ndarray:
    b = np.asarray(bounds, dtype=np.float64)
    if b.ndim != 2 or b.shape[1] != 2 or not np.all(b[:, 1] > b[:, 0]):
        raise ValueError(f"bounds must be [[lo, hi], ...] with hi > lo per axis, got {bounds!r}")
    return b


def _tensor_product(nodes: list[np.ndarray], weights: list[np.ndarray]) -> Quadrature:
    mesh = np.meshgrid(*nodes, indexing="ij")
    wmesh = np.meshgrid(*weights, indexing="ij")
    points = np.stack([m.reshape(-1) for m in mesh], axis=-1)
    w = np.prod(np.stack([m.reshape(-1) for m in wmesh], axis=-1), axis=-1)
    return Quadrature(torch.as_tensor(points, dtype=torch.float64), torch.as_tensor(w, dtype=torch.float64))


def midpoint_grid(resolution: int | Sequence[int], bounds: Bounds) -> Tensor:
    """Cell-centre points of a uniform grid, row-major ('ij'): (prod(resolution), dim_B)."""
    return uniform_grid(resolution, bounds).points


def vertex_grid(resolution: int | Sequence[int], bounds: Bounds) -> Tensor:
    """Equally spaced points from face to face of the box, `resolution` ≥ 2 per axis, row-major ('ij'):
    (prod(resolution), dim_B). Unlike :func:`midpoint_grid`, its hull is the whole box."""
    b = _check_bounds(bounds)
    res = [int(resolution)] * len(b) if np.isscalar(resolution) else [int(r) for r in resolution]
    if len(res) != len(b) or min(res) < 2:
        raise ValueError(f"vertex grid resolution must be an int ≥ 2 per axis of {len(b)}, got {resolution!r}")
    axes = [torch.linspace(lo, hi, n, dtype=torch.float64) for (lo, hi), n in zip(b, res)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, len(b))


def uniform_grid(resolution: int | Sequence[int], bounds: Bounds) -> Quadrature:
    """Midpoint rule on a uniform grid of `resolution` cells per axis (equal weights, O(h²))."""
    b = _check_bounds(bounds)
    res = [int(resolution)] * len(b) if np.isscalar(resolution) else [int(r) for r in resolution]
    if len(res) != len(b) or min(res) < 1:
        raise ValueError(f"grid resolution must be a positive int per axis of {len(b)}, got {resolution!r}")
    nodes, weights = [], []
    for (lo, hi), n in zip(b, res):
        h = (hi - lo) / n
        nodes.append(lo + h * (np.arange(n) + 0.5))
        weights.append(np.full(n, h))
    return _tensor_product(nodes, weights)


def grid_shape_of(points: "np.ndarray | Tensor", bounds: Bounds) -> tuple[int, ...] | None:
    """(res,)·dim_B when `points` (N, dim_B) are the row-major midpoint grid of `bounds` with res cells per axis
    (how generated datasets store their grids), else None: scattered points (mesh nodes, samples)."""
    pts = np.asarray(points, dtype=np.float64)
    b = _check_bounds(bounds)
    if pts.ndim != 2 or pts.shape[1] != len(b) or len(pts) == 0:
        return None
    res = int(round(len(pts) ** (1.0 / len(b))))
    if res ** len(b) != len(pts):
        return None
    grid = uniform_grid(res, bounds).points.numpy()
    tol = 1e-5 * float(np.max(b[:, 1] - b[:, 0]))
    return (res,) * len(b) if np.allclose(pts, grid, rtol=0, atol=tol) else None


def gauss_legendre_rule(order: int | Sequence[int], bounds: Bounds) -> Quadrature:
    """Tensor Gauss–Legendre rule, `order` nodes per axis: exact for degree ≤ 2·order − 1 per axis."""
    b = _check_bounds(bounds)
    orders = [int(order)] * len(b) if np.isscalar(order) else [int(o) for o in order]
    if len(orders) != len(b) or min(orders) < 1:
        raise ValueError(f"Gauss–Legendre order must be a positive int per axis of {len(b)}, got {order!r}")
    nodes, weights = [], []
    for (lo, hi), n in zip(b, orders):
        x, w = np.polynomial.legendre.leggauss(n)
        nodes.append(0.5 * (hi - lo) * x + 0.5 * (hi + lo))
        weights.append(0.5 * (hi - lo) * w)
    return _tensor_product(nodes, weights)


class QuadratureRule:
    """A recipe that builds a :class:`Quadrature` for given bounds (one class per Hydra option)."""

    def build(self, bounds: Bounds) -> Quadrature:  # pragma: no cover - interface
        raise NotImplementedError

    def build_for(self, scene: Any) -> Quadrature:
        """The rule on `scene`'s body (by default, on its bounds; a rule can ask the scene for more)."""
        return self.build(scene.bounds)

    def describe(self) -> str:  # pragma: no cover - interface
        raise NotImplementedError


class GaussLegendre(QuadratureRule):
    def __init__(self, order: int | Sequence[int] = 8) -> None:
        self.order = order

    def build(self, bounds: Bounds) -> Quadrature:
        return gauss_legendre_rule(self.order, bounds)

    def describe(self) -> str:
        return f"gauss_legendre(order={self.order})"


class UniformGrid(QuadratureRule):
    def __init__(self, resolution: int | Sequence[int] = 64) -> None:
        self.resolution = resolution

    def build(self, bounds: Bounds) -> Quadrature:
        return uniform_grid(self.resolution, bounds)

    def describe(self) -> str:
        return f"uniform_grid(resolution={self.resolution})"


class GivenPoints(QuadratureRule):
    """User-supplied points (N, dim_B) and weights (N,), e.g. mesh vertices with lumped areas."""

    def __init__(self, points: Sequence[Sequence[float]], weights: Sequence[float]) -> None:
        self.points = torch.as_tensor(np.asarray(points, dtype=np.float32))
        self.weights = torch.as_tensor(np.asarray(weights, dtype=np.float32))

    def build(self, bounds: Bounds) -> Quadrature:
        b = _check_bounds(bounds)
        quad = Quadrature(self.points, self.weights)
        if quad.points.shape[1] != len(b):
            raise ValueError(f"given quadrature points have dim {quad.points.shape[1]}, the body has dim {len(b)}")
        return quad

    def describe(self) -> str:
        return f"given_points(n={len(self.weights)})"


class _SceneMeshRule(QuadratureRule):
    """A rule whose points come from the scene's own mesh (``scene.<capability>()``), not from its bounds."""

    option = ""  # the quadrature= option
    capability = ""  # the Scene method that gives the rule

    def build(self, bounds: Bounds) -> Quadrature:
        raise ValueError(f"quadrature={self.option} takes its points from the scene's mesh: build it with "
                         "build_for(scene)")

    def build_for(self, scene: Any) -> Quadrature:
        if not (hasattr(scene, "provides") and scene.provides(self.capability)):
            raise ValueError(f"quadrature={self.option}: scene {getattr(scene, 'name', scene)!r} has no mesh of its "
                             f"own (it defines no {self.capability}()); choose quadrature=gauss_legendre")
        return getattr(scene, self.capability)()


class MeshElements(_SceneMeshRule):
    """The quadrature of the scene's own mesh (``scene.element_quadrature()``: its elements' points and weights),
    for a body that does not fill its box."""

    option, capability = "mesh", "element_quadrature"

    def build_for(self, scene: Any) -> Quadrature:
        quad = super().build_for(scene)
        return Quadrature(torch.as_tensor(quad.points), torch.as_tensor(quad.weights))

    def describe(self) -> str:
        return "mesh_elements"


class MeshNodes(_SceneMeshRule):
    """The nodes of the scene's own mesh with their lumped volumes (``scene.nodal_quadrature()``, a
    :class:`NodeQuadrature`): the reduced dynamics pull back the mesh's discrete Lagrangian (docs/method.md §6.1).
    `order` is accepted and not used (an experiment's Gauss–Legendre order stays in the config when
    ``quadrature=mesh_nodes`` replaces its rule: the mesh sets the points)."""

    option, capability = "mesh_nodes", "nodal_quadrature"

    def __init__(self, order: Any = None) -> None:
        del order

    def describe(self) -> str:
        return "mesh_nodes"


class StoredPoints(QuadratureRule):
    """The points and quadrature weights stored with trajectories written from arrays (``/grids/fine`` and
    ``/grids/weights`` of the file at `path`, see :func:`lnf.trajectories.write_dataset`): the reduced dynamics
    integrate over the user's own mesh nodes, whatever the body's shape inside its box."""

    def __init__(self, path: str | None = None) -> None:
        self.path = str(path) if path else None

    def build(self, bounds: Bounds) -> Quadrature:
        import h5py

        if self.path is None:
            raise ValueError("quadrature=stored reads the points and weights of the data file: set data.path=<file> "
                             "(trajectories written by lnf.trajectories.write_dataset with weights=)")
        b = _check_bounds(bounds)
        try:
            with h5py.File(self.path, "r") as f:
                if "grids/weights" not in f:
                    raise ValueError(f"quadrature=stored: {self.path} holds no quadrature weights (/grids/weights); "
                                     f"write the trajectories with weights= (e.g. lumped nodal volumes, "
                                     f"lnf.mesh_io.read_mesh_series gives them) or choose quadrature=gauss_legendre")
                points, weights = f["grids/fine"][...], f["grids/weights"][...]
        except OSError as exc:
            raise ValueError(f"quadrature=stored: cannot read {self.path} ({exc})") from exc
        if points.shape[1] != len(b):
            raise ValueError(f"quadrature=stored: the points of {self.path} have dim {points.shape[1]}, the body has "
                             f"dim {len(b)}")
        return Quadrature(torch.as_tensor(points, dtype=torch.float64), torch.as_tensor(weights, dtype=torch.float64))

    def describe(self) -> str:
        return f"stored_points(path={self.path})"
