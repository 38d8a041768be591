"""Full-order model: the scene's own Lagrangian integrated on a grid of nodes, no reduction at all.

The state is the field at every node of a midpoint grid (`resolution` per axis), with the lumped mass
ω0 w_j and the scene's discrete potential V on that grid (the same :class:`DiscretePotential` that the
reduced dynamics integrate):  ω0_j w_j q̈_j = −∂V/∂q_j. Run on the evaluation grid itself it is the
accuracy ceiling and the cost reference of every reduced model. It exposes the interface of
:class:`lnf.reduced_model.ReducedModel`, with "codes" = nodal values (B, N·A), so the same evaluation
code measures it. Off-node points are interpolated (bilinear, 2-D bodies).
"""
from __future__ import annotations

import math
from typing import Any, Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from lnf.quadrature import Quadrature, midpoint_grid
from lnf.reduced_model import ReducedModel, as_field
from lnf.scenes.base import Scene


class NodalDynamics:
    """ω0 w q̈ = −∂V/∂q on nodes; q, v, p (B, N·A). Same methods as :class:`lnf.dynamics.ReducedDynamics`."""

    def __init__(self, scene: Scene, quadrature: Quadrature) -> None:
        self.scene = scene
        self.potential_fn = scene.potential(quadrature)
        if self.potential_fn.needs_gradient:
            raise NotImplementedError(f"the nodal full-order model of scene {scene.name!r} needs ∇_X q on the grid; "
                                      "this scene provides its own full-order simulator instead")
        if scene.kinetic_correction(quadrature) is not None or scene.generalized_force(quadrature) is not None:
            raise NotImplementedError(f"the nodal full-order model has only the flat kinetic energy and no external "
                                      f"forces; scene {scene.name!r} needs more, and its own simulator is the reference")
        self.A = scene.field_dim
        mass = (quadrature.weights * scene.density(quadrature.points))  # (N,)
        self.mass = mass[:, None].expand(-1, self.A).reshape(-1)  # (N·A,)

    def _field(self, q: Tensor) -> Tensor:
        return q.reshape(q.shape[0], -1, self.A)

    def force(self, q: Tensor) -> Tensor:
        """−∂V/∂q (B, N·A)."""
        dVdq, _ = self.potential_fn.gradient(self._field(q))
        return -dVdq.reshape(q.shape)

    def acceleration(self, q: Tensor, v: Tensor, t: float = 0.0) -> Tensor:
        return self.force(q) / self.mass.to(q)

    def momentum(self, q: Tensor, v: Tensor) -> Tensor:
        return v * self.mass.to(v)

    def velocity(self, q: Tensor, p: Tensor) -> Tensor:
        return p / self.mass.to(p)

    def hamiltonian_derivatives(self, q: Tensor, p: Tensor, t: float = 0.0) -> tuple[Tensor, Tensor]:
        return self.velocity(q, p), self.force(q)

    def energies(self, q: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        shape = q.shape[:-1]
        q2, v2 = q.reshape(-1, q.shape[-1]), v.reshape(-1, v.shape[-1])
        kinetic = 0.5 * (self.mass.to(v2) * v2 * v2).sum(-1)
        return kinetic.reshape(shape), self.potential_fn(self._field(q2)).reshape(shape)


class FullOrderModel(ReducedModel):
    """The full-order model on a `resolution`^dim_B midpoint grid of the body (see the module docstring).

    Args:
        scene: the scene.
        resolution: nodes per axis; the evaluation uses the nodes as they are when they coincide with
            the evaluation points (e.g. resolution 64 on the stored 64×64 test grid).
    """

    trainable = False
    state_is_field = True
    collapse_advice = "Try a finer model.resolution: the grid does not resolve the fields"

    def __init__(self, scene: Scene, resolution: int = 64, quadrature: Any = None) -> None:
        super().__init__(scene, None)
        if int(resolution) != resolution or resolution < 2:
            raise ValueError(f"model.resolution (nodes per axis of the full-order grid) must be an integer ≥ 2, "
                             f"got {resolution!r}")
        self.resolution = int(resolution)
        nodes = midpoint_grid(self.resolution, scene.bounds).double()
        volume = math.prod(hi - lo for lo, hi in scene.bounds)
        self.register_buffer("nodes", nodes.float())
        self.register_buffer("weights", torch.full((nodes.shape[0],), volume / nodes.shape[0]))

    @property
    def latent_dim(self) -> int:
        return self.nodes.shape[0] * self.scene.field_dim

    def _on_nodes(self, points: Tensor) -> bool:
        return points.ndim == 2 and points.shape == self.nodes.shape and bool(
            torch.allclose(points.to(self.nodes), self.nodes, atol=1e-6))

    def _grid(self, values: Tensor) -> Tensor:
        """(B, N, A) nodal values → (B, A, H, W) image for grid_sample (nodes are 'ij' ordered: x rows, y columns)."""
        if self.scene.body_dim != 2:
            raise NotImplementedError("interpolating the full-order field off its nodes is implemented for 2-D bodies")
        r = self.resolution
        return values.reshape(values.shape[0], r, r, -1).permute(0, 3, 2, 1)  # (B, A, y, x)

    def _normalised(self, points: Tensor) -> Tensor:
        b = torch.as_tensor(self.scene.bounds, dtype=points.dtype, device=points.device)
        return 2.0 * (points - b[:, 0]) / (b[:, 1] - b[:, 0]) - 1.0

    def decode(self, codes: Tensor, points: Tensor, chunk: int = 65536) -> Tensor:
        """Nodal values (B, N·A) at `points` (N', dim_B): as they are on the nodes, else bilinear."""
        values = codes.reshape(codes.shape[0], -1, self.scene.field_dim)
        if self._on_nodes(points):
            return values
        if points.ndim != 2:
            raise ValueError(f"full-order decode needs shared points (N, dim_B), got {tuple(points.shape)}")
        grid = self._normalised(points.to(codes))[None, None].expand(codes.shape[0], 1, -1, -1)
        out = F.grid_sample(self._grid(values), grid, mode="bilinear", padding_mode="border", align_corners=False)
        return out[:, :, 0].transpose(1, 2)  # (B, N', A)

    def reduce(self, points: Tensor, values: Tensor, steps: Optional[int] = None) -> Tensor:
        """Nodal values of observed fields (B, N, A): as they are on the nodes, else interpolated
        (scipy Clough–Tocher, cubic; nearest outside the points' hull), all B fields at once."""
        values = as_field(values)
        self._check_observation(points, values, "values")
        if self._on_nodes(points):
            return values.reshape(values.shape[0], -1)
        if points.ndim != 2:
            raise ValueError(f"full-order reduce needs shared points (N, dim_B), got {tuple(points.shape)}")
        from scipy.interpolate import CloughTocher2DInterpolator, NearestNDInterpolator

        tri = self._triangulation(points)
        B, N, A = values.shape
        cols = values.double().cpu().numpy().transpose(1, 0, 2).reshape(N, B * A)
        nodes = self.nodes.double().cpu().numpy()
        out = CloughTocher2DInterpolator(tri, cols)(nodes)
        bad = ~np.isfinite(out).all(-1)
        if bad.any():
            out[bad] = NearestNDInterpolator(tri.points, cols)(nodes[bad])
        out = out.reshape(-1, B, A).transpose(1, 0, 2)
        return torch.as_tensor(out, dtype=values.dtype, device=values.device).reshape(B, -1)

    def _triangulation(self, points: Tensor) -> Any:
        """Delaunay triangulation of the observation points, cached (the same points recur for every frame)."""
        from scipy.spatial import Delaunay

        if self.scene.body_dim != 2:
            raise NotImplementedError("interpolating observations onto the full-order nodes is implemented for 2-D bodies")
        key = (points.data_ptr(), tuple(points.shape), points._version)
        cache = self.__dict__.setdefault("_tri_cache", {})
        if key not in cache:
            cache.clear()
            # the entry holds the points too: while it lives, no other tensor can take their address (a stale hit)
            cache[key] = (Delaunay(points.double().cpu().numpy()), points)
        return cache[key][0]

    def project_velocity(self, codes: Tensor, points: Tensor, velocities: Tensor,
                         weights: Optional[Tensor] = None) -> Tensor:
        return self.reduce(points, velocities)

    def fit_to_observations(self, points: Tensor, values: Tensor) -> dict[str, float]:
        """Nothing to fit: the full-order model is the scene's own equations."""
        return {}

    def lagrangian_dynamics(self, quadrature: Any = None) -> NodalDynamics:
        quad = Quadrature(self.nodes.to(torch.float64), self.weights.to(torch.float64))
        p = self.reference_tensor()
        return NodalDynamics(self.scene, quad.to(dtype=p.dtype, device=p.device))

    def extra_repr(self) -> str:
        return f"scene={self.scene!r}, resolution={self.resolution}"
