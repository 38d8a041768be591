"""A hyperelastic body discretised by scikit-fem: any mesh of triangles, quadrilaterals, tetrahedra or hexahedra.

:class:`ElasticBody` holds a scikit-fem mesh with linear (P1 / Q1) vector elements and gives what the rest of lnf
needs of a finite-element body, for nodal displacements u (B, n_nodes, d):

- the quadrature of its elements (points and weights, for the pulled-back Lagrangian and for evaluation);
- the lumped (row-sum) mass, the internal force −∂/∂u ∫ W(I + ∇_X u) dX and the strain energy, and the exact
  tangent stiffness K = ∂²/∂u² ∫ W dX, from the material's stress P(F) and moduli A = ∂P/∂F
  (:mod:`lnf.fem.materials`) at the elements' quadrature points. scikit-fem gives the elements, their maps,
  quadrature and basis gradients; the sums over elements are sparse products with its discrete gradient G
  (f = −Gᵀ(w P), K = Gᵀ(w A)G), batched over trajectories and 2–4× faster than its own assembly of the weak
  forms, which :meth:`ElasticBody.assembled_internal_force` and :meth:`ElasticBody.assembled_tangent_stiffness`
  keep as the check (equal to rounding, ``tests/test_fem.py``);
- interpolation of nodal vectors, and of their gradients, to any points inside the mesh.

Degrees of freedom are node-major: u.reshape(-1)[d·n + k] is component k of node n. The clamped nodes' rows are
the caller's to drop (``free_dofs``).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import numpy as np
import scipy.sparse as sp
import skfem
import torch
from skfem.helpers import ddot, grad

from lnf.fem.materials import HyperelasticMaterial, determinant
from lnf.threads import one_torch_thread

log = logging.getLogger("lnf.fem")

# scikit-fem mesh type → the linear element on it
ELEMENTS: dict[type, type] = {
    skfem.MeshTri1: skfem.ElementTriP1,
    skfem.MeshQuad1: skfem.ElementQuad1,
    skfem.MeshTet1: skfem.ElementTetP1,
    skfem.MeshHex1: skfem.ElementHex1,
}


@skfem.LinearForm
def _stress_form(v: Any, w: Any) -> Any:
    """∫ P : ∇v dX, P the first Piola–Kirchhoff stress at the quadrature points."""
    return ddot(w["P"], grad(v))


@skfem.BilinearForm
def _tangent_form(u: Any, v: Any, w: Any) -> Any:
    """∫ ∇v : A : ∇u dX, A = ∂P/∂F at the quadrature points."""
    return np.einsum("ijkl...,kl...,ij...->...", w["A"], grad(u), grad(v), optimize=True)


@skfem.LinearForm
def _volume_form(v: Any, w: Any) -> Any:
    return v


class ElasticBody:
    """A hyperelastic body of mass density ρ [kg/m³] on a scikit-fem mesh (units: m, kg, s, Pa).

    Args:
        mesh: a scikit-fem mesh of linear cells (MeshTri1, MeshQuad1, MeshTet1, MeshHex1).
        material: the stored energy W(F).
        density: ρ (per unit area and depth in 2-D).
        clamped: boolean mask (n_nodes,) of the nodes held at u = 0, or None.
        intorder: the quadrature's polynomial order (default 1 for simplices, where ∇u is constant per cell, and 2
            for quadrilaterals and hexahedra: 2 Gauss points per axis).
    """

    def __init__(self, mesh: skfem.Mesh, material: HyperelasticMaterial, density: float,
                 clamped: Optional[np.ndarray] = None, intorder: Optional[int] = None) -> None:
        element = next((e for kind, e in ELEMENTS.items() if isinstance(mesh, kind)), None)
        if element is None:
            raise ValueError(f"ElasticBody needs a mesh of linear triangles, quadrilaterals, tetrahedra or hexahedra, "
                             f"got a {type(mesh).__name__}")
        if not (np.isfinite(density) and density > 0):
            raise ValueError(f"density must be a finite number > 0 [kg/m³], got {density!r}")
        self.mesh, self.material, self.density = mesh, material, float(density)
        self.dim = mesh.dim()
        if intorder is None:
            intorder = 1 if isinstance(mesh, (skfem.MeshTri1, skfem.MeshTet1)) else 2
        self.basis = skfem.Basis(mesh, skfem.ElementVector(element()), intorder=int(intorder))
        self.scalar_basis = skfem.Basis(mesh, element(), quadrature=self.basis.quadrature)
        self.nodes = np.ascontiguousarray(mesh.p.T, dtype=np.float64)  # (nn, d)
        self._dof = self.basis.nodal_dofs.T.copy()  # (nn, d): scikit-fem's dof of component k of node n
        if self.basis.N != self.dim * self.n_nodes:
            raise ValueError(f"ElasticBody: {self.basis.N} degrees of freedom for {self.n_nodes} nodes in {self.dim}-D "
                             "(a mesh with unused nodes?)")
        # scikit-fem's dofs → node-major order (d·n + k); identity for its vector elements, kept general
        self._order = self._dof.reshape(-1)
        self.volume_per_node = skfem.asm(_volume_form, self.scalar_basis)  # ∫ N_a dX (nn,)
        self.nodal_mass = self.density * self.volume_per_node
        mask = np.zeros(self.n_nodes, bool) if clamped is None else np.asarray(clamped, bool)
        if mask.shape != (self.n_nodes,):
            raise ValueError(f"clamped must be a mask of shape ({self.n_nodes},), got {mask.shape}")
        self.clamped = mask
        self._gradient_operator: Optional[sp.csr_matrix] = None
        self._probes: dict[tuple[bytes, bool], Any] = {}  # the last interpolation matrices, by their points
        self.free_dofs = np.flatnonzero(np.repeat(~mask, self.dim))

    # ------------------------------------------------------------------ geometry
    @property
    def n_nodes(self) -> int:
        return self.nodes.shape[0]

    @property
    def quadrature_points(self) -> np.ndarray:
        """The elements' quadrature points X_q (Q, d)."""
        x = self.basis.mapping.F(self.basis.X)  # (d, nel, nq)
        return np.ascontiguousarray(x.reshape(self.dim, -1).T)

    @property
    def quadrature_weights(self) -> np.ndarray:
        """Their weights (Q,) [m^d]: Σ w = the body's volume."""
        return np.ascontiguousarray(self.basis.dx.reshape(-1))

    @property
    def bounds(self) -> list[list[float]]:
        return [[float(lo), float(hi)] for lo, hi in zip(self.nodes.min(0), self.nodes.max(0))]

    # ------------------------------------------------------------------ mechanics
    def _skfem_vector(self, u: np.ndarray) -> np.ndarray:
        x = np.empty(self.basis.N)
        x[self._order] = np.asarray(u, dtype=np.float64).reshape(-1)
        return x

    def deformation_gradients(self, u: np.ndarray) -> np.ndarray:
        """F = I + ∇_X u at every quadrature point, (d, d, nel, nq) as scikit-fem lays it out, for u (nn, d)."""
        G = self.basis.interpolate(self._skfem_vector(u)).grad  # (d, d, nel, nq)
        return G + np.eye(self.dim)[:, :, None, None]

    def _material(self, F: np.ndarray, what: str) -> np.ndarray:
        """W, P or A of the material at F (d, d, nel, nq), in scikit-fem's layout (components first)."""
        d = self.dim
        Ft = torch.from_numpy(np.ascontiguousarray(np.moveaxis(F, (0, 1), (-2, -1))))  # (nel, nq, d, d)
        with torch.no_grad(), one_torch_thread():
            if what == "W":
                return self.material.energy_density(Ft).numpy()
            if what == "P":
                return np.moveaxis(self.material.first_piola(Ft).numpy(), (-2, -1), (0, 1))
        with one_torch_thread():
            A = self.material.tangent(Ft).detach().numpy()  # (nel, nq, d, d, d, d)
        return np.moveaxis(A, (-4, -3, -2, -1), (0, 1, 2, 3)).reshape(d, d, d, d, *F.shape[2:])

    def _check_inverted(self, F: np.ndarray, where: str, components_last: bool = False) -> None:
        """Raise where det F ≤ 0 and the material needs det F > 0; F (d, d, …) as scikit-fem lays it out, or
        (…, d, d) with `components_last`."""
        if not self.material.needs_positive_jacobian:
            return
        with one_torch_thread():
            Ft = torch.from_numpy(F if components_last else np.ascontiguousarray(np.moveaxis(F, (0, 1), (-2, -1))))
            J = determinant(Ft).numpy()
        low = self.material.min_jacobian
        if not np.all(J >= low) or not np.all(J > 0):
            bad = int((~((J >= low) & (J > 0))).sum())
            raise FloatingPointError(f"ElasticBody.{where}: {bad} quadrature points with det F < {low:g} (an element "
                                     f"crushed or inverted): the displacement is too large for the mesh")

    @property
    def gradient_operator(self) -> sp.csr_matrix:
        """The sparse matrix (d·d·nel·nq, d·nn) that maps node-major nodal displacements to ∇_X u at every
        quadrature point, built once from scikit-fem's basis gradients and element dofs (the discrete gradient
        that its assembly sums over): Gᵀ(w ⊙ P) is the assembled ∫ P : ∇v dX, for a whole batch at once."""
        if self._gradient_operator is None:
            basis, d = self.basis, self.dim
            nel, nq = basis.nelems, basis.X.shape[-1]
            grads = np.stack([basis.basis[a][0].grad for a in range(basis.Nbfun)])  # (a, d, d, nel, nq)
            rows = np.broadcast_to(np.arange(d * d * nel * nq).reshape(1, d, d, nel, nq), grads.shape)
            inverse = np.empty_like(self._order)
            inverse[self._order] = np.arange(len(self._order))
            cols = np.broadcast_to(inverse[basis.element_dofs][:, None, None, :, None], grads.shape)
            keep = grads != 0
            self._gradient_operator = sp.csr_matrix((grads[keep], (rows[keep], cols[keep])),
                                                    shape=(d * d * nel * nq, self.basis.N))
        return self._gradient_operator

    def _batched_gradients(self, u: np.ndarray) -> np.ndarray:
        """F = I + ∇_X u (B, nel, nq, d, d) for u (B, nn, d), through :attr:`gradient_operator`."""
        B, d = u.shape[0], self.dim
        flat = np.asarray(u, dtype=np.float64).reshape(B, -1).T  # (d·nn, B)
        G = (self.gradient_operator @ flat).reshape(d, d, *self.basis.dx.shape, B)
        return np.ascontiguousarray(G.transpose(4, 2, 3, 0, 1)) + np.eye(d)

    def internal_force(self, u: np.ndarray) -> np.ndarray:
        """f = −∂/∂u ∫ W(I + ∇_X u) dX (B, nn, d) [N] for u (B, nn, d): −Gᵀ(w ⊙ P(F)), the same sum as
        scikit-fem's assembly of ∫ P : ∇v dX (checked in the tests), for the whole batch in two sparse products."""
        u = np.asarray(u, dtype=np.float64)
        B, d = u.shape[0], self.dim
        F = self._batched_gradients(u)  # (B, nel, nq, d, d)
        if self.material.needs_positive_jacobian:
            self._check_inverted(F, "internal_force", components_last=True)
        with torch.no_grad(), one_torch_thread():
            P = self.material.first_piola(torch.from_numpy(F)).numpy()
        weighted = (P * self.basis.dx[None, :, :, None, None]).transpose(3, 4, 1, 2, 0).reshape(-1, B)
        return -(self.gradient_operator.T @ weighted).T.reshape(B, self.n_nodes, d)

    def assembled_internal_force(self, u: np.ndarray) -> np.ndarray:
        """The same force as :meth:`internal_force` for one state u (nn, d), by scikit-fem's own assembly."""
        F = self.deformation_gradients(u)
        self._check_inverted(F, "assembled_internal_force")
        return -skfem.asm(_stress_form, self.basis, P=self._material(F, "P"))[self._order].reshape(self.n_nodes,
                                                                                                   self.dim)

    def strain_energy(self, u: np.ndarray) -> np.ndarray:
        """∫ W(I + ∇_X u) dX (B,) [J] for u (B, nn, d)."""
        F = self._batched_gradients(np.asarray(u, dtype=np.float64))
        with torch.no_grad(), one_torch_thread():
            W = self.material.energy_density(torch.from_numpy(F)).numpy()  # (B, nel, nq)
        return (W * self.basis.dx[None]).sum((1, 2))

    def tangent_stiffness(self, u: np.ndarray) -> sp.csr_matrix:
        """K = ∂²/∂u² ∫ W dX (d·nn × d·nn, sparse, node-major) at one state u (nn, d): exact, Gᵀ D G with D the
        block-diagonal w A = w ∂P/∂F at the quadrature points (the sum scikit-fem's assembly of ∫ ∇v : A : ∇u dX
        makes, :meth:`assembled_tangent_stiffness`, in one sparse product)."""
        d = self.dim
        F = self._batched_gradients(np.asarray(u, dtype=np.float64)[None])[0]  # (nel, nq, d, d)
        if self.material.needs_positive_jacobian:
            self._check_inverted(F, "tangent_stiffness", components_last=True)
        with one_torch_thread():
            A = self.material.tangent(torch.from_numpy(F)).detach().numpy()  # (nel, nq, d, d, d, d)
        nel, nq = self.basis.dx.shape
        wA = A * self.basis.dx[:, :, None, None, None, None]
        # row (i, j, e, q) of G ↔ index ((i·d + j)·nel + e)·nq + q; D couples (i, j) and (k, l) at the same (e, q)
        point = np.arange(nel * nq).reshape(nel, nq)
        ij = np.arange(d * d).reshape(d, d)
        rows = (ij[None, None, :, :, None, None] * nel * nq + point[:, :, None, None, None, None])
        cols = (ij[None, None, None, None, :, :] * nel * nq + point[:, :, None, None, None, None])
        rows, cols = np.broadcast_to(rows, wA.shape).reshape(-1), np.broadcast_to(cols, wA.shape).reshape(-1)
        D = sp.csr_matrix((wA.reshape(-1), (rows, cols)), shape=(d * d * nel * nq,) * 2)
        G = self.gradient_operator
        K = (G.T @ (D @ G)).tocsr()
        return (0.5 * (K + K.T)).tocsr()  # symmetric up to rounding; exactly so for the eigen- and linear solvers

    def assembled_tangent_stiffness(self, u: np.ndarray) -> sp.csr_matrix:
        """The same K as :meth:`tangent_stiffness`, by scikit-fem's own assembly of ∫ ∇v : A : ∇u dX (slower)."""
        F = self.deformation_gradients(u)
        self._check_inverted(F, "assembled_tangent_stiffness")
        K = skfem.asm(_tangent_form, self.basis, A=self._material(F, "A")).tocsr()
        if np.array_equal(self._order, np.arange(len(self._order))):
            return K
        return K[self._order][:, self._order].tocsr()

    # ------------------------------------------------------------------ interpolation
    def _probe(self, points: np.ndarray, gradient: bool) -> Union[sp.csr_matrix, list[sp.csr_matrix]]:
        x = np.asarray(points, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise ValueError(f"points must be (N, {self.dim}), got {x.shape}")
        basis = self.scalar_basis
        try:
            cells = self.mesh.element_finder(mapping=basis.mapping)(*x.T)
        except ValueError as err:
            raise ValueError(f"points outside the mesh (bounds {self.bounds}): {err}") from err
        local = basis.mapping.invF(x.T[:, :, None], tind=cells)
        fields = [basis.elem.gbasis(basis.mapping, local, k, tind=cells)[0] for k in range(basis.Nbfun)]
        cols = basis.element_dofs[:, cells].reshape(-1)
        rows = np.tile(np.arange(len(x)), basis.Nbfun)
        shape = (len(x), basis.N)
        if not gradient:
            vals = np.concatenate([f.value.reshape(-1) for f in fields])
            return sp.csr_matrix((vals, (rows, cols)), shape=shape)
        return [sp.csr_matrix((np.concatenate([f.grad[j].reshape(-1) for f in fields]), (rows, cols)), shape=shape)
                for j in range(self.dim)]

    def _cached_probe(self, points: np.ndarray, gradient: bool) -> Any:
        x = np.ascontiguousarray(points, dtype=np.float64)
        key = (x.tobytes(), gradient)
        if key not in self._probes:
            if len(self._probes) >= 8:  # a few point sets recur (the grids of a run); keep the last ones
                self._probes.pop(next(iter(self._probes)))
            self._probes[key] = self._probe(x, gradient)
        return self._probes[key]

    def interpolation(self, points: np.ndarray) -> sp.csr_matrix:
        """Sparse (N, nn) interpolation of nodal values to points (N, d) inside the mesh (cached by points)."""
        return self._cached_probe(points, gradient=False)

    def interpolation_gradient(self, points: np.ndarray) -> list[sp.csr_matrix]:
        """∂/∂X_j of the interpolant at points (N, d): d sparse (N, nn) matrices (on a cell face: one cell's)."""
        return self._cached_probe(points, gradient=True)

    def stable_time_step(self) -> float:
        """CFL estimate h_min / c_p of explicit time stepping (h_min the shortest edge, c_p the dilatational
        wave speed of the material's small-strain moduli)."""
        edges = self.mesh.p[:, self.mesh.edges] if self.dim == 3 else self.mesh.p[:, self.mesh.facets]
        h = float(np.min(np.linalg.norm(edges[:, 1] - edges[:, 0], axis=0)))
        return h / np.sqrt((self.material.lam + 2 * self.material.mu) / self.density)


def box_mesh(lengths: Sequence[float], cells: Sequence[int], kind: str = "quad") -> skfem.Mesh:
    """A structured mesh of the box [0, L₁] × … (2-D: ``quad`` or ``tri``; 3-D: ``hex`` or ``tet``)."""
    axes = [np.linspace(0.0, float(L), int(n) + 1) for L, n in zip(lengths, cells)]
    kinds = {2: {"quad": skfem.MeshQuad1, "tri": skfem.MeshTri1}, 3: {"hex": skfem.MeshHex1, "tet": skfem.MeshTet1}}
    if len(lengths) != len(cells) or len(axes) not in kinds:
        raise ValueError(f"box_mesh: lengths and cells must both have 2 or 3 entries, got {list(lengths)}, {list(cells)}")
    if kind not in kinds[len(axes)]:
        raise ValueError(f"box_mesh: kind must be one of {sorted(kinds[len(axes)])} in {len(axes)}-D, got {kind!r}")
    return kinds[len(axes)][kind].init_tensor(*axes)


def read_mesh(path: Union[str, Path], units: Optional[str] = None,
              key: str = "units") -> tuple[skfem.Mesh, dict[str, np.ndarray]]:
    """A mesh file that meshio reads, as a scikit-fem mesh of its cells (see :func:`from_meshio`) in metres, and its
    named point sets (boolean node masks, from meshio point sets and from the nodes of its cell sets).

    `units`: the length unit of the file's coordinates (a key of :data:`MESH_UNITS`: ``m``, ``cm``, ``mm``, …);
    the nodes are scaled to metres. None: metres, when the mesh's largest extent is a plausible body's
    (:data:`PLAUSIBLE_EXTENT` [m]); otherwise a ValueError asks for the unit (a mesh drawn in millimetres is not
    taken for one 1000 times larger). The mesh, its extent and its unit are logged (``lnf.fem``): as a warning
    when the unit is not stated (read as metres, a guess: an 8 mm part drawn in mm passes as an 8 m body), and
    when a stated unit gives an implausible extent. The body's cells are checked (:func:`check_body_cells`: no
    surface or off-plane mesh, no degenerate or repeated cells). `key`: the setting named in messages
    (``scene.mesh_units``)."""
    from lnf.mesh_io import read_meshio

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file {path}: not found")
    if units is not None and str(units) not in MESH_UNITS:
        raise ValueError(f"{key}={units!r}: not a length unit lnf knows; expected one of {', '.join(MESH_UNITS)} "
                         f"(the unit of the coordinates in {path})")
    raw = read_meshio(path)
    mesh, sets = from_meshio(raw, str(path))
    extent = np.ptp(mesh.p, axis=1)  # in the file's unit
    size = " × ".join(f"{e:.4g}" for e in extent)
    lo, hi = PLAUSIBLE_EXTENT
    if units is None:
        if not lo <= extent.max() <= hi:
            raise ValueError(
                f"{path}: {key} is not set and the mesh spans {size} in its own unit: as metres, a "
                f"{extent.max():.4g} m body, outside the {lo:g}–{hi:g} m lnf expects; state the unit of its "
                f"coordinates, e.g. {key}=mm (then {extent.max() * MESH_UNITS['mm']:.4g} m) or {key}=m to take it as it is "
                f"(one of {', '.join(MESH_UNITS)})")
        unit, stated = "m", (f"read as metres ({key} not set: metres by default); set {key} if it is not (e.g. "
                             f"{key}=mm: a {extent.max() * MESH_UNITS['mm']:.4g} m body)")
    else:
        unit = str(units)
        stated = "read as metres" if unit == "m" else f"read as {UNIT_NAMES[unit]}, scaled to metres"
    scale = MESH_UNITS[unit]
    if scale != 1.0:
        mesh = type(mesh)(mesh.p * scale, mesh.t)
    cells = f"{mesh.t.shape[1]} {MESHIO_NAMES[type(mesh)]}"
    in_metres = " × ".join(f"{e:.4g}" for e in extent * scale)
    # an unstated unit is a guess (a mesh drawn in mm with an extent of 8 passes as an 8 m body): a warning
    log.log(logging.INFO if units is not None else logging.WARNING, "mesh %s: %d nodes, %s, extent %s %s -> %s%s",
            path, mesh.p.shape[1], cells, size, unit, stated, "" if scale == 1.0 else f" ({in_metres} m)")
    if units is not None and not lo <= extent.max() * scale <= hi:
        log.warning("mesh %s: extent %s %s%s, read with %s=%s, is outside the %g–%g m of a plausible body: are its "
                    "coordinates in %s? If not, set %s to their unit (one of %s)", path, size, unit,
                    "" if scale == 1.0 else f" = {in_metres} m", key, unit, lo, hi, UNIT_NAMES[unit], key,
                    ", ".join(MESH_UNITS))
    return mesh, sets


# length units of a mesh file's coordinates, as metres
MESH_UNITS: dict[str, float] = {"m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 1e-3, "um": 1e-6, "in": 0.0254,
                                "ft": 0.3048}
UNIT_NAMES = {"m": "metres", "dm": "decimetres", "cm": "centimetres", "mm": "millimetres", "um": "micrometres",
              "in": "inches", "ft": "feet"}
# the largest extent [m] of a body lnf's scenes expect (a soft finger: 0.5 m); outside: an error when the unit is
# not stated, a warning when it is
PLAUSIBLE_EXTENT = (1e-3, 10.0)

MESHIO_CELLS = ("tetra", "hexahedron", "triangle", "quad")
# the linear cells of lnf's finite-element body (meshio's names), by the dimension they fill
FEM_CELLS = {3: ("tetra", "hexahedron"), 2: ("triangle", "quad")}
MESHIO_NAMES = {skfem.MeshTri1: "triangle", skfem.MeshQuad1: "quad", skfem.MeshTet1: "tetra",
                skfem.MeshHex1: "hexahedron"}


def body_cell_type(raw: Any, source: str = "mesh") -> str:
    """The meshio type of the cells that fill a meshio mesh's body (those of its highest dimension; lower ones are
    boundaries and named sets). A ValueError naming the file, the cell types and their counts when the body is
    not all of one linear type lnf supports: a body is never kept in part."""
    counts: dict[str, int] = {}
    dims: dict[str, int] = {}
    for block in raw.cells:
        counts[block.type] = counts.get(block.type, 0) + len(block.data)
        dims[block.type] = int(block.dim)  # meshio's topological dimension of the cell type
    listed = ", ".join(f"{n} {t}" for t, n in counts.items()) or "none"
    top = max([d for t, d in dims.items() if counts[t] > 0], default=0)
    if top < 2:
        raise ValueError(f"{source}: no triangles, quadrilaterals, tetrahedra or hexahedra (cells: {listed}); lnf "
                         f"needs a body of linear cells: {' or '.join(FEM_CELLS[3])} in 3-D, "
                         f"{' or '.join(FEM_CELLS[2])} in 2-D")
    body = {t: n for t, n in counts.items() if dims[t] == top and n > 0}
    supported = FEM_CELLS.get(top, ())
    unknown = [t for t in body if t not in supported]
    if unknown:
        higher = [t for t in unknown if t.rstrip("0123456789") != t]
        raise ValueError(
            f"{source}: its {top}-D body has {', '.join(f'{body[t]} {t}' for t in unknown)} cells, which lnf cannot "
            f"use (cells: {listed}); lnf's finite-element body is made of linear {' or '.join(supported)} cells "
            f"(and {' or '.join(FEM_CELLS[5 - top])} in {5 - top}-D), all of one type: re-mesh or convert it"
            + (" (first-order elements: the mesher's element order 1, e.g. gmsh -order 1)" if higher else
               f" (e.g. all {supported[0]})"))
    if len(body) > 1:
        raise ValueError(
            f"{source}: its {top}-D body mixes {' and '.join(f'{n} {t}' for t, n in body.items())} cells; lnf's "
            f"finite-element body is of one cell type ({' or '.join(supported)}) and would keep only part of it: "
            f"re-mesh or convert it to one type (e.g. all {supported[0]})")
    return next(iter(body))


BODY_NEEDS = (f"lnf's soft body needs volume cells ({' or '.join(FEM_CELLS[3])}) that fill a 3-D body (mesh the "
              f"volume, e.g. gmsh -3), or, for a 2-D body, {' or '.join(FEM_CELLS[2])} cells in the x-y plane")
# a cell whose measure is at most this fraction of the median cell's (or of the body's box) is degenerate
DEGENERATE_FRACTION = 1e-10


def check_body_cells(mesh: skfem.Mesh, points: np.ndarray, kind: str, source: str = "mesh") -> None:
    """Refuse, naming `source`, a body lnf would use wrongly: cells of a lower dimension than the space their nodes
    span (a surface of triangles in 3-D, or a planar mesh outside the x-y plane: scikit-fem keeps only x and y),
    degenerate cells (zero volume: corners in a plane, or a repeated node) and repeated cells (the same nodes: their
    mass and stiffness would count twice). `mesh`: scikit-fem's conversion, its cells numbered by the file's nodes;
    `points`: the file's coordinates of the nodes its cells use (as written, all columns)."""
    dim, n_cells = mesh.p.shape[0], mesh.t.shape[1]
    extent = np.ptp(points, axis=0) if len(points) else np.zeros(points.shape[1])
    shown = " × ".join(f"{e:.4g}" for e in extent)
    scale = float(extent.max()) if extent.size else 0.0
    if points.shape[1] > dim and scale > 0:
        sv = np.linalg.svd(points - points.mean(0), compute_uv=False)
        spans = int((sv > 1e-9 * sv[0]).sum())
        if spans > dim:
            raise ValueError(f"{source}: its body is {n_cells} {kind} cells, {dim}-D cells whose nodes span {spans}-D "
                             f"space (extent {shown}): a surface, not a body; {BODY_NEEDS}")
        off = [a for a in range(dim, points.shape[1]) if extent[a] > 1e-9 * scale]
        if off:
            axis = "xyz"[off[0]] if off[0] < 3 else f"coordinate {off[0]}"
            raise ValueError(f"{source}: its body is {n_cells} {kind} cells, a {dim}-D mesh lying in a plane that is not "
                             f"the x-y plane (extent {shown}; its {axis} varies by {extent[off[0]]:.4g}): a {dim}-D "
                             f"body is read from x and y only and would be flattened; {BODY_NEEDS} (rotate it into "
                             f"that plane, z constant)")
    from skfem.quadrature import get_quadrature

    X, W = get_quadrature(mesh.refdom, 2)
    with np.errstate(divide="ignore", invalid="ignore"):  # a degenerate cell's inverse map: found below, by name
        volumes = np.abs(mesh.mapping().detDF(X)) @ W  # (n_cells,), in the file's unit^dim
    typical = float(np.median(volumes)) if n_cells else 0.0
    bad = np.flatnonzero(volumes <= DEGENERATE_FRACTION * max(typical, scale ** dim))
    if len(bad):
        i = int(bad[0])
        raise ValueError(f"{source}: {len(bad)} of its {n_cells} {kind} cells have zero volume (degenerate: corners in a "
                         f"plane or a repeated node), e.g. cell {i} of its {kind} cells, counted from 0 in the file's "
                         f"order (nodes {sorted(int(v) for v in mesh.t[:, i])}, volume {volumes[i]:.3g} against a "
                         f"median {typical:.3g}); a degenerate cell has no stiffness or mass lnf can use: remove it or "
                         f"re-mesh")
    keys = np.sort(mesh.t, axis=0).T
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = np.asarray(inverse).reshape(-1)
    repeats = np.flatnonzero(first[inverse] != np.arange(n_cells))
    if len(repeats):
        i = int(repeats[0])
        raise ValueError(f"{source}: {len(repeats)} of its {n_cells} {kind} cells repeat another cell (the same "
                         f"nodes), e.g. cell {i} repeats cell {int(first[inverse[i]])} of its {kind} cells, counted "
                         f"from 0 in the file's order (nodes {sorted(int(v) for v in mesh.t[:, i])}); a repeated "
                         f"cell counts its mass and stiffness twice: remove the duplicates")


def from_meshio(raw: Any, source: str = "mesh") -> tuple[skfem.Mesh, dict[str, np.ndarray]]:
    """(scikit-fem mesh, named node masks) of a meshio mesh (see :func:`read_mesh`): its body is all its cells of
    the highest dimension, which must be of one type of :data:`FEM_CELLS` (:func:`body_cell_type`); scikit-fem
    converts them (and reorders a hexahedron's corners); the nodes stay in float64; nodes that no cell uses (a
    mesher's geometry points) are dropped."""
    import skfem.io.meshio

    kind = body_cell_type(raw, source)
    try:
        full = skfem.io.meshio.from_meshio(raw, force_meshio_type=kind)
    except Exception as err:
        raise ValueError(f"{source}: scikit-fem cannot convert its {kind} cells ({type(err).__name__}: {err})") from err
    if type(full) not in ELEMENTS:
        raise ValueError(f"{source}: a {type(full).__name__}; lnf needs linear cells {list(MESHIO_CELLS)}")
    used = np.unique(full.t)
    check_body_cells(full, np.asarray(raw.points, dtype=np.float64)[used], kind, source)
    renumber = -np.ones(full.p.shape[1], dtype=np.int64)
    renumber[used] = np.arange(len(used))
    mesh = type(full)(np.asarray(full.p[:, used], dtype=np.float64).copy(), renumber[full.t].copy())
    n_raw = len(raw.points)
    sets: dict[str, np.ndarray] = {}
    for name, idx in (getattr(raw, "point_sets", None) or {}).items():
        mask = np.zeros(n_raw, bool)
        mask[np.asarray(idx, dtype=np.int64)] = True
        sets[name] = mask[used]
    for name, per_block in (getattr(raw, "cell_sets", None) or {}).items():
        mask = np.zeros(n_raw, bool)
        for block, idx in zip(raw.cells, per_block):
            if idx is not None and len(idx):
                mask[np.asarray(block.data)[np.asarray(idx, dtype=np.int64)].reshape(-1)] = True
        sets.setdefault(name, mask[used])
    return mesh, sets
