"""A hyperelastic soft body on any mesh, 3-D by default: a soft finger clamped at its base, under gravity, bent
by a cable, with the finite-element reference of :mod:`lnf.fem` (scikit-fem).

Body B: the cells of a mesh, from a file that meshio reads (tetrahedra or hexahedra; triangles or quadrilaterals
for a 2-D body) or a box [0, L₁] × [0, L₂] × [0, L₃] of hexahedra or tetrahedra. The field is the displacement
u: B → ℝ^d (positions X + u). The Lagrangian is the cantilever's (:mod:`lnf.scenes.elastic`), in d dimensions:

    T = ½ ∫ ρ ‖u̇‖² dX,   V = ∫ W(I + ∇_X u) dX + ∫ ρ g u_d dX,

W St Venant–Kirchhoff or compressible Neo-Hookean (:mod:`lnf.fem.materials`), gravity along −X_d. The nodes of a
named point or cell set of the mesh file (``clamp``), or else those at the smallest X₁, are clamped.

Optional non-conservative forces: mass-proportional damping −α ρ u̇ and the cable's pull, a body force
b(X, t) = A sin(2π f t) s(X) ê, s = ((X₁ − X₁,min)/L)^p concentrated at the tip for large p (the pull of a
tendon anchored in the last part of the finger, spread over it), ê its direction, with per-trajectory
amplitude A and frequency f (the scene's controls).

Initial states: the releases of :class:`lnf.scenes.ElasticCantilever` (``modal`` by default: the FEM's own
equilibrium under gravity and the first mode's inertial load, with a tip speed along that mode).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch

from lnf.fem.body import ElasticBody, box_mesh, read_mesh
from lnf.quadrature import Quadrature, midpoint_grid
from lnf.scenes.base import StabilityCases
from lnf.scenes.elastic import ElasticCantilever


class SoftBody(ElasticCantilever):
    """A hyperelastic soft body on a mesh (units: m, kg, s, Pa).

    Args:
        mesh_file: a mesh file that meshio reads; null: the box below. Its body is all its cells of the highest
            dimension, all tetrahedra or all hexahedra (triangles or quadrilaterals in 2-D); a mesh with other
            cells there (wedges, pyramids, quadratic cells) or a mix of types is refused, never used in part.
        box: the box's lengths (L₁, …, L_d) [m]; cells: its cells per axis; cell_kind: ``hex`` or ``tet``
            (``quad`` or ``tri`` in 2-D).
        clamp: the name of a point set or cell set of the mesh file whose nodes are clamped; null: the nodes at
            the smallest X₁.
        quadrature_order: the polynomial order of the elements' quadrature (the reference's and ``quadrature=mesh``'s;
            null: scikit-fem's default for the element).
        density, young, poisson, material, gravity, damping, time_step, cfl_fraction, integrator, release: as
            :class:`lnf.scenes.ElasticCantilever`.
        deflection_range, tip_speed_range: of the release, as the cantilever's (deflections along X_d).
        load_amplitude_range, load_frequency_range, load_direction, load_power: the cable's pull, A [N/m³], f [Hz],
            ê (d numbers) and p.
        mesh_units: the length unit of mesh_file's coordinates (``m``, ``cm``, ``mm``, …
            :data:`lnf.fem.body.MESH_UNITS`), scaled to metres; null: metres, unless the mesh's extent is implausible as metres (then an error asks
            for the unit). The mesh, its extent and unit are logged when it is read: a warning when null (read as
            metres; set mesh_units if it is not).
    A mesh file is refused, naming it, when its cells do not fill a body (triangles spanning 3-D space: a
    surface; a 2-D mesh outside the x-y plane), or when some of them are degenerate (zero volume) or repeated.
    """

    name = "soft_body"

    def __init__(self, mesh_file: Optional[str] = None, box: Sequence[float] = (0.5, 0.15, 0.1),
                 cells: Sequence[int] = (20, 6, 4), cell_kind: str = "hex", clamp: Optional[str] = None,
                 quadrature_order: Optional[int] = None, density: float = 1.0, young: float = 240.0,
                 poisson: float = 0.3, material: str = "neo_hookean", gravity: float = 1.0, damping: float = 0.0,
                 time_step: Optional[float] = None, cfl_fraction: float = 0.5, integrator: str = "verlet",
                 release: str = "modal", deflection_range: Sequence[float] = (-0.05, 0.05),
                 tip_speed_range: Sequence[float] = (-0.2, 0.2), load_amplitude_range: Sequence[float] = (0.0, 0.0),
                 load_frequency_range: Sequence[float] = (0.5, 1.0), load_direction: Optional[Sequence[float]] = None,
                 load_power: float = 4.0, mesh_units: Optional[str] = None) -> None:
        if not (np.isfinite(load_power) and load_power >= 0):
            raise ValueError(f"scene.load_power must be a finite number ≥ 0, got {load_power!r}")
        self._set_physics(density, young, poisson, gravity, damping, cfl_fraction, material, integrator, release,
                          deflection_range, tip_speed_range, load_amplitude_range, load_frequency_range)
        self.mesh_file = str(mesh_file) if mesh_file else None
        self.mesh_units = None if mesh_units is None else str(mesh_units)
        self.box, self.cells, self.cell_kind = [float(v) for v in box], [int(n) for n in cells], str(cell_kind)
        self.clamp = clamp
        self.quadrature_order = None if quadrature_order is None else int(quadrature_order)
        self.load_power = float(load_power)
        mesh, sets = self._mesh()
        if self.clamp is not None:
            if self.clamp not in sets:
                raise ValueError(f"scene.clamp={self.clamp!r}: {self.mesh_file or 'the box mesh'} has no such point or "
                                 f"cell set (it has {sorted(sets) or 'none'})")
            clamped = sets[self.clamp]
        else:
            clamped = np.isclose(mesh.p[0], mesh.p[0].min())
        if not clamped.any():
            raise ValueError("scene.clamp: no node is clamped; the body would float free")
        self._set_body(ElasticBody(mesh, self.material, self.rho, clamped=clamped, intorder=self.quadrature_order),
                       time_step)
        self.load_direction_spec = None if load_direction is None else [float(v) for v in load_direction]
        direction = np.zeros(self.dim) if load_direction is None else np.asarray(load_direction, dtype=np.float64)
        if load_direction is None:  # a tendon along the top pulling the tip back and up
            direction[0], direction[-1] = -1.0, 1.0
        if direction.shape != (self.dim,) or not np.linalg.norm(direction) > 0:
            raise ValueError(f"scene.load_direction must be a nonzero vector of {self.dim} numbers, got {load_direction!r}")
        self.load_direction = (direction / np.linalg.norm(direction)).tolist()

    def _mesh(self) -> tuple[Any, dict[str, np.ndarray]]:
        if self.mesh_file is not None:
            path = Path(self.mesh_file).expanduser()
            if not path.is_file():
                raise ValueError(f"scene.mesh_file={self.mesh_file!r}: no such file (a mesh file that meshio reads)")
            return read_mesh(path, self.mesh_units, key="scene.mesh_units")
        if len(self.box) != len(self.cells) or len(self.box) not in (2, 3):
            raise ValueError(f"scene.box and scene.cells must both have 2 or 3 entries, got {self.box}, {self.cells}")
        if any(L <= 0 for L in self.box) or any(n < 1 for n in self.cells):
            raise ValueError(f"scene.box must be lengths > 0 [m] and scene.cells integers ≥ 1, got {self.box}, "
                             f"{self.cells}")
        try:
            return box_mesh(self.box, self.cells, self.cell_kind), {}
        except ValueError as err:
            raise ValueError(f"scene.cell_kind: {err}") from err

    def params(self) -> dict[str, Any]:
        # the unit a mesh file was read in (null read it as metres); none for the box, whose spec predates it
        units = {} if self.mesh_file is None else dict(mesh_units=self.mesh_units or "m")
        return dict(mesh_file=self.mesh_file, **units, box=self.box, cells=self.cells, cell_kind=self.cell_kind,
                    clamp=self.clamp, quadrature_order=self.quadrature_order, density=self.rho, young=self.young,
                    poisson=self.poisson, material=self.material_name, gravity=self.gravity, damping=self.damping,
                    time_step=self.time_step, cfl_fraction=self.cfl_fraction, integrator=self.integrator,
                    release=self.release, deflection_range=self.deflection_range,
                    tip_speed_range=self.tip_speed_range, load_amplitude_range=self.load_amplitude_range,
                    load_frequency_range=self.load_frequency_range, load_direction=self.load_direction_spec,
                    load_power=self.load_power)

    def observation_points(self, resolution: int) -> np.ndarray:
        """A box body: the midpoint grid with `resolution` cells along its longest side and as many per axis as
        keep them near cubes. A body from a mesh file: its nodes (the only points known to lie inside it)."""
        if self.mesh_file is not None:
            return self.body.nodes.copy()
        lengths = np.asarray([hi - lo for lo, hi in self.bounds])
        counts = [max(1, int(round(resolution * L / lengths.max()))) for L in lengths]
        return midpoint_grid(counts, self.bounds).cpu().numpy()

    def element_quadrature(self) -> Quadrature:
        """The mesh's element quadrature (the reference's own): points (Q, d), weights (Q,) [m^d]."""
        return Quadrature(torch.as_tensor(self.body.quadrature_points), torch.as_tensor(self.body.quadrature_weights))

    def stability_cases(self) -> StabilityCases:
        """Releases at rest, unloaded, from the edge of the training range to 2.67× it."""
        edge = max(abs(v) for v in self.deflection_range)
        levels = tuple(round(edge * k, 6) for k in (1.0, 1.33, 1.67, 2.0, 2.67))
        return StabilityCases(levels, "tip deflection of the release at rest δ [m]", edge,
                              f"training range |δ| ≤ {edge:g} m")

    def _inside(self, points: np.ndarray) -> np.ndarray:
        if self.mesh_file is not None:
            return np.asarray(points, dtype=np.float64)  # a point outside the mesh is an error, not a clip
        return super()._inside(points)
