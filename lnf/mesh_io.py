"""Meshes with point data, from any simulator's output files, as :class:`lnf.trajectories.Trajectories` (meshio).

A simulator that writes one mesh file per time step (VTU, VTK, XDMF, Gmsh, … any format meshio reads) or one
XDMF time series gives, per run, the nodes and the field at the nodes. :func:`read_mesh_series` turns one run
into one trajectory: the nodes become the points (trailing coordinates that are the same for every node, such
as z = 0 of a 2-D mesh, are dropped), the named point data the field (and optionally the velocity), and the
cells the lumped nodal volumes that serve as quadrature weights (:func:`nodal_volumes`).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from lnf.dataset import DatasetError
from lnf.trajectories import Trajectories

# meshio cell types whose measure :func:`nodal_volumes` computes, by the body dimension they fill
SIMPLEX_CELLS = {"line": 1, "triangle": 2, "tetra": 3}
# linear cells split into simplices (meshio's, i.e. VTK's, corner order) for their measure; each node gets an
# equal share of the whole cell's
SPLIT_CELLS = {"quad": (2, [(0, 1, 2), (0, 2, 3)]),
               "hexahedron": (3, [(0, 1, 3, 4), (1, 2, 3, 6), (1, 4, 5, 6), (3, 4, 6, 7), (1, 3, 4, 6)]),
               "wedge": (3, [(0, 1, 2, 3), (1, 2, 3, 4), (2, 3, 4, 5)]),
               "pyramid": (3, [(0, 1, 2, 4), (0, 2, 3, 4)])}
# quadratic cells (meshio's node order, VTK's: corners, then the edges' nodes), split into the linear simplices of
# all their nodes; each gives an equal share of its measure to its own nodes (all > 0, summing to the cell's)
REFINED_CELLS = {"line3": (1, [(0, 2), (2, 1)]),
                 "triangle6": (2, [(0, 3, 5), (3, 1, 4), (5, 4, 2), (3, 4, 5)]),
                 "tetra10": (3, [(0, 4, 6, 7), (4, 1, 5, 8), (6, 5, 2, 9), (7, 8, 9, 3),
                                 (6, 8, 4, 5), (6, 8, 5, 9), (6, 8, 9, 7), (6, 8, 7, 4)])}
# the dimension of the cells meshio names (its CellBlock.dim; here for blocks that lack it)
CELL_DIMENSIONS = {"vertex": 0, **SIMPLEX_CELLS, **{k: v[0] for k, v in SPLIT_CELLS.items()},
                   **{k: v[0] for k, v in REFINED_CELLS.items()}}


def read_meshio(path: "str | os.PathLike[str]") -> Any:
    """meshio.read(path), with any failure a :class:`DatasetError` naming the file (meshio raises many kinds,
    and exits the interpreter for a file it cannot parse)."""
    import meshio

    try:
        return meshio.read(path)
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - see the docstring
        raise DatasetError(f"{path}: meshio cannot read it ({type(exc).__name__}: {exc})") from exc


def _simplex_measures(coords: np.ndarray) -> np.ndarray:
    """Measures (length, area, volume) of simplices with vertices coords (m, k+1, dim), k = 1, 2, 3."""
    edges = coords[:, 1:] - coords[:, :1]  # (m, k, dim)
    gram = np.einsum("mid,mjd->mij", edges, edges)
    k = edges.shape[1]
    return np.sqrt(np.clip(np.linalg.det(gram), 0, None)) / float(np.prod(np.arange(1, k + 1)))


def _cell_dimension(block: Any) -> Optional[int]:
    dim = getattr(block, "dim", None)
    return int(dim) if dim is not None else CELL_DIMENSIONS.get(block.type)


def nodal_volumes(points: np.ndarray, cells: Sequence[Any], dim: int, source: str = "mesh") -> Optional[np.ndarray]:
    """Lumped nodal volumes (N,): each cell of dimension `dim` gives an equal share of its measure to each of its
    nodes (quads, hexahedra, wedges and pyramids are split into simplices for their measure; quadratic lines,
    triangles and tetrahedra into the simplices of all their nodes, each sharing its measure among its own). None
    when the mesh has no cells of dimension `dim`; a :class:`DatasetError` naming `source` when it has cells of
    that dimension whose measure is not computed here (weights of part of the body would be wrong), or cells of a
    higher dimension (then `dim` is not the body's)."""
    weights = np.zeros(len(points))
    found = False
    unknown: dict[str, int] = {}
    higher: dict[str, int] = {}
    for block in cells:
        kind, conn = block.type, np.asarray(block.data)
        cell_dim = _cell_dimension(block)
        if cell_dim is not None and cell_dim > dim and len(conn):
            higher[kind] = higher.get(kind, 0) + len(conn)
            continue
        refined = False
        if SIMPLEX_CELLS.get(kind) == dim:
            pieces = [(conn, tuple(range(conn.shape[1])))]
        elif kind in SPLIT_CELLS and SPLIT_CELLS[kind][0] == dim:
            pieces = [(conn, split) for split in SPLIT_CELLS[kind][1]]
        elif kind in REFINED_CELLS and REFINED_CELLS[kind][0] == dim:
            pieces, refined = [(conn, split) for split in REFINED_CELLS[kind][1]], True
        else:
            if cell_dim == dim and len(conn):  # a cell of the body whose measure is not known here
                unknown[kind] = unknown.get(kind, 0) + len(conn)
            continue
        if len(conn) and (conn.min() < 0 or conn.max() >= len(points)):
            raise DatasetError(f"{source}: its {kind} cells refer to nodes {int(conn.min())}–{int(conn.max())}, but "
                               f"it has {len(points)} (0–{len(points) - 1}); the mesh file is inconsistent")
        found = True
        if refined:
            for c, split in pieces:
                share = _simplex_measures(points[c[:, list(split)]]) / len(split)
                np.add.at(weights, c[:, list(split)].reshape(-1), np.repeat(share, len(split)))
            continue
        share = np.zeros(len(conn))
        for c, split in pieces:
            share += _simplex_measures(points[c[:, list(split)]])
        np.add.at(weights, conn.reshape(-1), np.repeat(share / conn.shape[1], conn.shape[1]))
    known = sorted(k for k, d in CELL_DIMENSIONS.items() if d == dim)
    if higher:
        raise DatasetError(f"{source}: the body is taken as {dim}-D, but the mesh has "
                           f"{', '.join(f'{n} {t}' for t, n in higher.items())} cells of a higher dimension; give "
                           f"dim= the dimension of its cells (its nodes' coordinates that vary)")
    if unknown:
        raise DatasetError(f"{source}: {', '.join(f'{n} {t}' for t, n in unknown.items())} cells fill part of its "
                           f"{dim}-D body, and lnf cannot compute their nodal volumes (the quadrature weights); it "
                           f"computes them for {', '.join(known)} cells: convert the mesh (e.g. to first-order "
                           f"tetra), or write the trajectories with weights of your own (lnf.trajectories)")
    if not found:
        return None
    return weights


def _body_coordinates(points: np.ndarray, dim: Optional[int], source: str) -> np.ndarray:
    """The nodes' first `dim` coordinates; by default all but the trailing ones equal for every node."""
    if dim is None:
        dim = points.shape[1]
        while dim > 1 and np.ptp(points[:, dim - 1]) == 0:
            dim -= 1
    if not 1 <= dim <= points.shape[1]:
        raise DatasetError(f"{source}: dim={dim} must be between 1 and the {points.shape[1]} coordinates of its nodes")
    return np.asarray(points[:, :dim], dtype=np.float64)


def _point_data(mesh: Any, name: str, source: str) -> np.ndarray:
    if name not in mesh.point_data:
        raise DatasetError(f"{source}: no point data {name!r}; it has {sorted(mesh.point_data) or 'none'}")
    values = np.asarray(mesh.point_data[name], dtype=np.float64)
    return values[:, None] if values.ndim == 1 else values


def read_mesh_series(source: "str | os.PathLike | Sequence[str | os.PathLike]", field: str,
                     velocity: Optional[str] = None, times: Optional[Sequence[float]] = None,
                     dim: Optional[int] = None, components: Optional[int] = None) -> Trajectories:
    """One run of a simulator as one trajectory.

    Args:
        source: an XDMF time-series file (its times are read from it), or a sequence of mesh files, one per time
            step, in time order (then `times` are required).
        field: the name of the point data holding the configuration field q (e.g. "u", "displacement").
        velocity: the name of the point data holding q̇, or None (central differences in time of q).
        times: the times [s] of the files of a sequence (uniform, from 0).
        dim: the body dimension (default: the nodes' coordinates without trailing ones equal for all nodes).
        components: keep the first this many components of the field (e.g. 2 of a 3-component displacement of a
            2-D body); default all.

    Returns: Trajectories with 1 trajectory: points (N, dim), fields (1, T, N, A), weights = lumped nodal volumes
    of the cells of dimension `dim` (None if the mesh has none).
    """
    import meshio

    frames: list[tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]] = []
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        if not path.is_file():
            raise DatasetError(f"{path}: mesh time series not found")
        if path.suffix.lower() not in (".xdmf", ".xmf"):
            raise DatasetError(f"{path}: a single file must be an XDMF time series; give a list of mesh files (one "
                               f"per time step) with times= for other formats")
        stamp: list[float] = []
        with meshio.xdmf.TimeSeriesReader(str(path)) as reader:
            nodes, cells = reader.read_points_cells()
            for k in range(reader.num_steps):
                t, point_data, _ = reader.read_data(k)
                mesh = meshio.Mesh(nodes, cells, point_data=point_data)
                frames.append((_point_data(mesh, field, f"{path} step {k}"),
                               None if velocity is None else _point_data(mesh, velocity, f"{path} step {k}"), None))
                stamp.append(float(t))
        if times is None:
            times = stamp
        ref_points, ref_cells, name = np.asarray(nodes), cells, str(path)
    else:
        files = [Path(p) for p in source]
        if not files:
            raise DatasetError("read_mesh_series: no mesh files given")
        if times is None:
            raise DatasetError(f"read_mesh_series: {len(files)} mesh files need times= (one time [s] per file)")
        ref_points = ref_cells = None
        for p in files:
            mesh = read_meshio(p)
            if ref_points is None:
                ref_points, ref_cells = np.asarray(mesh.points), mesh.cells
            elif mesh.points.shape != ref_points.shape or not np.allclose(mesh.points, ref_points):
                raise DatasetError(f"{p}: its nodes differ from those of {files[0]} (a trajectory is sampled on fixed "
                                   f"material points; write the field on the reference mesh)")
            frames.append((_point_data(mesh, field, str(p)),
                           None if velocity is None else _point_data(mesh, velocity, str(p)), None))
        name = str(files[0].parent)
    if len(times) != len(frames):
        raise DatasetError(f"read_mesh_series: {len(frames)} time steps but {len(times)} times")
    points = _body_coordinates(ref_points, dim, name)
    q = np.stack([f[0] for f in frames])
    v = None if velocity is None else np.stack([f[1] for f in frames])
    if components is not None:
        q = q[..., :components]
        v = None if v is None else v[..., :components]
    weights = nodal_volumes(points, ref_cells, points.shape[1], name)
    return Trajectories(points=points, times=np.asarray(times, dtype=np.float64), fields=q[None],
                        velocities=None if v is None else v[None], weights=weights)
