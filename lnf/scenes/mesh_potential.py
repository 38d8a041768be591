"""The potential energy of a field sampled at a mesh's nodes, as the mesh's own finite elements define it.

A continuum potential V = ∫ W(I + ∇_X u) + ρ g u_v dX read at quadrature points takes ∇_X u from the field itself
(lnf.scenes.elastic.ElasticPotential). The full-order reference does not: it interpolates its nodal displacements
u_a with the elements' shape functions N_a, so ∇_X u_h = Σ_a u_a ∇N_a, and lumps its mass and loads on the nodes.
Low-order elements (Q1, P1) are stiffer than the continuum, more so in bending, and a reduced model that pulls back
the continuum's Lagrangian then has other frequencies than the data. Pulled back through φ at the nodes
(``quadrature=mesh_nodes``: u_a = φ(q̃, X_a)), this potential makes the reduced model that of the reference's own
discrete Lagrangian (with the lumped kinetic energy ½ Σ_a m_a ‖u̇_a‖², which a :class:`lnf.quadrature.NodeQuadrature`
of lumped volumes gives). Shapes: nodal fields q (B, nn, d).
"""
from __future__ import annotations

from typing import Any, Optional

import numpy as np
import torch
from torch import Tensor

from lnf.scenes.base import DiscretePotential


class MeshStrainPotential(DiscretePotential):
    """V(u) = Σ_{e,g} w_eg W(I + (𝒢u)_eg) + Σ_a ρ g V_a u_{a,v}: the body's strain energy through its elements'
    gradient operator 𝒢 (:attr:`lnf.fem.body.ElasticBody.gradient_operator`) and the lumped gravity, v the vertical
    (last) axis; the same sums as the reference's ``strain_energy`` and nodal gravity force.

    Args:
        body: the :class:`lnf.fem.body.ElasticBody` whose nodes the fields are sampled at (in its node order).
        rho_g: ρ g [N/m³] of the lumped gravity load.
    """

    needs_gradient = False

    def __init__(self, body: Any, rho_g: float) -> None:
        operator = body.gradient_operator.tocoo()
        self.dim, self.n_nodes = int(body.dim), int(body.n_nodes)
        self._indices = torch.as_tensor(np.stack([operator.row, operator.col]), dtype=torch.long)
        self._values = torch.as_tensor(operator.data, dtype=torch.float64)
        self._shape = operator.shape
        self._operators: dict[tuple[torch.dtype, torch.device], Tensor] = {}
        self.weights = torch.as_tensor(body.basis.dx.reshape(-1), dtype=torch.float64)  # w_eg (Q,) [m^d]
        self.gravity_weights = rho_g * torch.as_tensor(body.volume_per_node, dtype=torch.float64)  # (nn,) [N/m]
        self.material = body.material

    def _operator(self, like: Tensor) -> Tensor:
        key = (like.dtype, like.device)
        if key not in self._operators:
            self._operators[key] = torch.sparse_coo_tensor(self._indices, self._values.to(like.dtype), self._shape,
                                                           check_invariants=True,
                                                           device=like.device).coalesce()
        return self._operators[key]

    def _check(self, q: Tensor) -> None:
        if q.ndim != 3 or q.shape[1:] != (self.n_nodes, self.dim):
            raise ValueError(f"MeshStrainPotential takes fields at the mesh's {self.n_nodes} nodes, shape "
                             f"(B, {self.n_nodes}, {self.dim}); got {tuple(q.shape)} (quadrature=mesh_nodes builds them)")

    def _deformation(self, q: Tensor) -> Tensor:
        """F = I + 𝒢u (B, Q, d, d) at the elements' quadrature points."""
        B, d = q.shape[0], self.dim
        grads = torch.sparse.mm(self._operator(q), q.reshape(B, -1).T)  # (d·d·Q, B), rows (i, j, e, g)
        return grads.reshape(d, d, -1, B).permute(3, 2, 0, 1) + torch.eye(d, dtype=q.dtype, device=q.device)

    def __call__(self, q: Tensor, G: Optional[Tensor] = None) -> Tensor:
        self._check(q)
        W = self.material.energy_density(self._deformation(q))  # (B, Q)
        return W @ self.weights.to(q) + q[..., -1] @ self.gravity_weights.to(q)

    def gradient(self, q: Tensor, G: Optional[Tensor] = None) -> tuple[Tensor, None]:
        """(∂V/∂u_a (B, nn, d), None): 𝒢ᵀ(w ⊙ P(F)) plus the gravity load, in closed form (the reference's
        internal force, negated)."""
        self._check(q)
        B, d = q.shape[0], self.dim
        P = self.material.first_piola(self._deformation(q)) * self.weights.to(q)[None, :, None, None]  # (B, Q, d, d)
        flat = P.permute(2, 3, 1, 0).reshape(-1, B)  # rows (i, j, e, g), as the operator's
        dq = torch.sparse.mm(self._operator(q).t(), flat).T.reshape(B, self.n_nodes, d)
        gravity = torch.zeros_like(dq)
        gravity[..., -1] = self.gravity_weights.to(q)
        return dq + gravity, None
