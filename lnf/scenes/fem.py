"""A small, fast finite-element model of a 2-D St Venant–Kirchhoff body (plane strain), in numpy.

Bilinear (Q1) elements on a structured nx × ny grid of the box [0, L] × [0, H], 2×2 Gauss quadrature,
row-sum lumped mass. Displacements u (B, n_nodes, 2) are batched over trajectories; nodes are numbered
i·(ny+1) + j for the node at (i·hx, j·hy). The stored energy is W(F) = μ E:E + ½ λ (tr E)² with
E = ½(FᵀF − I), F = I + ∇_X u; the first Piola–Kirchhoff stress P = F (λ tr E I + 2 μ E) is written out per
component in :meth:`StructuredQ1Mesh.internal_force`.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

GAUSS = np.array([-1.0, 1.0]) / np.sqrt(3.0)
CORNERS = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)  # counter-clockwise


def lame(young: float, poisson: float) -> tuple[float, float]:
    """(λ, μ) from Young's modulus and Poisson's ratio."""
    return young * poisson / ((1 + poisson) * (1 - 2 * poisson)), young / (2 * (1 + poisson))


def svk_energy_density(F: np.ndarray, lam: float, mu: float) -> np.ndarray:
    """W(F) for F (…, 2, 2) → (…)."""
    E = 0.5 * (np.swapaxes(F, -1, -2) @ F - np.eye(2))
    trace = E[..., 0, 0] + E[..., 1, 1]
    return mu * np.sum(E * E, axis=(-1, -2)) + 0.5 * lam * trace**2


class StructuredQ1Mesh:
    """Nodes, elements, shape-function gradients, lumped areas and interpolation of a Q1 box mesh."""

    def __init__(self, length: float, height: float, nx: int, ny: int) -> None:
        self.length, self.height, self.nx, self.ny = float(length), float(height), int(nx), int(ny)
        self.hx, self.hy = self.length / nx, self.height / ny
        ii, jj = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), indexing="ij")
        self.nodes = np.stack([ii.ravel() * self.hx, jj.ravel() * self.hy], -1)  # (nn, 2)
        ei, ej = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
        ei, ej = ei.ravel(), ej.ravel()
        corner = lambda di, dj: (ei + di) * (ny + 1) + ej + dj  # noqa: E731
        self.elements = np.stack([corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1)], -1)  # (ne, 4)
        # ∂N_a/∂X at the 4 Gauss points (identical for every element of a structured mesh): (4g, 4a, 2)
        gp = np.array([[x, y] for x in GAUSS for y in GAUSS])
        dN = np.empty((4, 4, 2))
        for g, (xi, eta) in enumerate(gp):
            dN[g, :, 0] = 0.25 * CORNERS[:, 0] * (1 + CORNERS[:, 1] * eta) * 2 / self.hx
            dN[g, :, 1] = 0.25 * CORNERS[:, 1] * (1 + CORNERS[:, 0] * xi) * 2 / self.hy
        self.dN = dN
        self.D = dN.transpose(1, 0, 2).reshape(4, 8)  # (4a, 4g·2j): the same gradients as one matrix
        self.gauss_weight = self.hx * self.hy / 4.0
        ne = len(self.elements)
        self.assembly = sp.csr_matrix((np.ones(4 * ne), (self.elements.ravel(), np.arange(4 * ne))),
                                      shape=(len(self.nodes), 4 * ne))
        self.nodal_area = self.assembly @ np.full(4 * ne, self.hx * self.hy / 4.0)  # (nn,)
        self.clamped = self.nodes[:, 0] == 0.0

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    def _displacement_gradient(self, u: np.ndarray) -> np.ndarray:
        """∇_X u at every Gauss point as (B, ne, 4g, 2k, 2j) via two BLAS products."""
        ue = u[:, self.elements]  # (B, ne, 4a, 2k)
        G = np.stack([ue[..., 0] @ self.D, ue[..., 1] @ self.D], -2)  # (B, ne, 2k, 8)
        return G.reshape(*G.shape[:2], 2, 4, 2).transpose(0, 1, 3, 2, 4)

    def deformation_gradient(self, u: np.ndarray) -> np.ndarray:
        """F = I + ∇_X u at every Gauss point: u (B, nn, 2) → (B, ne, 4, 2, 2)."""
        return np.eye(2) + self._displacement_gradient(u)

    def internal_force(self, u: np.ndarray, lam: float, mu: float) -> np.ndarray:
        """−∂/∂u Σ_g w W(F_g) (B, nn, 2), the SVK stress written out per component (fast for 2×2)."""
        G = self._displacement_gradient(u)
        a, b, c, d = 1 + G[..., 0, 0], G[..., 0, 1], G[..., 1, 0], 1 + G[..., 1, 1]  # F = [[a, b], [c, d]]
        e00 = 0.5 * (a * a + c * c - 1)
        e11 = 0.5 * (b * b + d * d - 1)
        e01 = 0.5 * (a * b + c * d)
        tr = lam * (e00 + e11)
        s00, s11, s01 = tr + 2 * mu * e00, tr + 2 * mu * e11, 2 * mu * e01
        P = np.stack([a * s00 + b * s01, a * s01 + b * s11, c * s00 + d * s01, c * s01 + d * s11], -1)
        P = P.reshape(*P.shape[:3], 2, 2)  # (B, ne, 4g, 2k, 2j)
        Pk = P.transpose(0, 1, 3, 2, 4).reshape(*P.shape[:2], 2, 8)  # (B, ne, 2k, 4g·2j)
        fe = -self.gauss_weight * (Pk @ self.D.T)  # (B, ne, 2k, 4a)
        B = u.shape[0]
        flat = fe.transpose(1, 3, 0, 2).reshape(-1, B * 2)  # (ne·4a, B·2k)
        return (self.assembly @ flat).reshape(self.n_nodes, B, 2).transpose(1, 0, 2)

    def tangent_stiffness(self, u: np.ndarray, lam: float, mu: float, eps: float = 1e-6) -> sp.csr_matrix:
        """K = −∂f/∂u (2 nn × 2 nn, sparse, symmetrised) of the internal force at one state u (nn, 2).

        Central differences with a 3 × 3 colouring of the nodes: nodes three apart in both directions share
        no element, so all of one colour and one component are perturbed together (18 pairs of force
        evaluations in one batch, whatever the mesh size)."""
        ii, jj = np.divmod(np.arange(self.n_nodes), self.ny + 1)
        colour = (ii % 3) * 3 + jj % 3
        batch = np.repeat(np.asarray(u, dtype=np.float64)[None], 36, 0)  # (9 colours × 2 components × ±)
        for c in range(9):
            for k in range(2):
                batch[4 * c + 2 * k, colour == c, k] += eps
                batch[4 * c + 2 * k + 1, colour == c, k] -= eps
        force = self.internal_force(batch, lam, mu)
        df = -(force[0::2] - force[1::2]) / (2 * eps)
        # each perturbed node's column: the responses at the nodes of its own elements (|Δi|, |Δj| ≤ 1)
        rows, cols, vals = [], [], []
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                src_i, src_j = ii - di, jj - dj  # the perturbed node whose neighbour is (ii, jj)
                ok = (src_i >= 0) & (src_i <= self.nx) & (src_j >= 0) & (src_j <= self.ny)
                tgt = np.flatnonzero(ok)
                src = src_i[ok] * (self.ny + 1) + src_j[ok]
                for k in range(2):
                    response = df[2 * colour[src] + k, tgt]  # (m, 2): force on the target node
                    for a in range(2):
                        rows.append(2 * tgt + a)
                        cols.append(2 * src + k)
                        vals.append(response[:, a])
        n = 2 * self.n_nodes
        K = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
        return (0.5 * (K + K.T)).tocsr()

    def strain_energy(self, u: np.ndarray, lam: float, mu: float) -> np.ndarray:
        """Σ_g w W(F_g) (B,) for u (B, nn, 2)."""
        return self.gauss_weight * svk_energy_density(self.deformation_gradient(u), lam, mu).sum((1, 2))

    def _cells(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Rows and node columns (4 per point) of the cells holding points (N, 2), and local (s, t) ∈ [0, 1]²."""
        x = np.clip(points[:, 0] / self.hx, 0, self.nx)
        y = np.clip(points[:, 1] / self.hy, 0, self.ny)
        i = np.minimum(np.floor(x).astype(int), self.nx - 1)
        j = np.minimum(np.floor(y).astype(int), self.ny - 1)
        rows = np.repeat(np.arange(len(points)), 4)
        cols = np.stack([i * (self.ny + 1) + j, (i + 1) * (self.ny + 1) + j, (i + 1) * (self.ny + 1) + j + 1,
                         i * (self.ny + 1) + j + 1], -1).ravel()
        return rows, cols, x - i, y - j

    def interpolation(self, points: np.ndarray) -> sp.csr_matrix:
        """Sparse (N, nn) bilinear interpolation matrix to points (N, 2) (clipped to the box)."""
        rows, cols, s, t = self._cells(points)
        vals = np.stack([(1 - s) * (1 - t), s * (1 - t), s * t, (1 - s) * t], -1).ravel()
        return sp.csr_matrix((vals, (rows, cols)), shape=(len(points), self.n_nodes))

    def interpolation_gradient(self, points: np.ndarray) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """(∂/∂X₁, ∂/∂X₂) of the bilinear interpolant at points (N, 2): two sparse (N, nn) matrices
        (the element's gradient, piecewise: on a cell edge the cell found by :meth:`interpolation`)."""
        rows, cols, s, t = self._cells(points)
        dx = np.stack([-(1 - t), 1 - t, t, -t], -1).ravel() / self.hx
        dy = np.stack([-(1 - s), -s, s, 1 - s], -1).ravel() / self.hy
        shape = (len(points), self.n_nodes)
        return sp.csr_matrix((dx, (rows, cols)), shape=shape), sp.csr_matrix((dy, (rows, cols)), shape=shape)

    def stable_time_step(self, lam: float, mu: float, density: float) -> float:
        """CFL estimate h_min / c_p of explicit time stepping (c_p the dilatational wave speed)."""
        return min(self.hx, self.hy) / np.sqrt((lam + 2 * mu) / density)
