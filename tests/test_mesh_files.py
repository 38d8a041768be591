"""Mesh files read faithfully: a body is used whole or refused by name (cell types and counts), quadratic cells
get their nodal volumes, nodes stay in float64 from the file to the dataset, and a mesh's length unit is stated
or refused (tiny meshes, a few seconds in all)."""
import logging

import meshio
import numpy as np
import pytest
import skfem
import skfem.io.meshio
from omegaconf import OmegaConf

from helpers import compose_config
from lnf.dataset import DatasetConfig, DatasetError, generate_dataset, load_split
from lnf.fem.body import box_mesh, read_mesh
from lnf.mesh_io import nodal_volumes, read_mesh_series
from lnf.scenes import SoftBody

BOX = (0.5, 0.15, 0.1)  # [m]; 0.15 and 0.1 are not float32 numbers


def _hexes_and_wedges(lengths=BOX, cells=(4, 2, 1)):
    """Nodes of a box and its cells: hexahedra in its first half along X1, wedges (two per hexahedron) after."""
    nx, ny, nz = cells
    axes = [np.linspace(0.0, L, n + 1) for L, n in zip(lengths, cells)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)

    def node(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    hexes, wedges = [], []
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                a, b, c, d = node(i, j, k), node(i + 1, j, k), node(i + 1, j + 1, k), node(i, j + 1, k)
                A, B, C, D = (node(i, j, k + 1), node(i + 1, j, k + 1), node(i + 1, j + 1, k + 1),
                              node(i, j + 1, k + 1))
                if i < nx // 2:
                    hexes.append([a, b, c, d, A, B, C, D])
                else:
                    wedges += [[a, b, c, A, B, C], [a, c, d, A, C, D]]
    return nodes, np.array(hexes), np.array(wedges)


def _tetra10(lengths=BOX, cells=(2, 1, 1)):
    """A box of quadratic tetrahedra in meshio's (VTK's) node order: corners, then the nodes of the edges (0 1),
    (1 2), (0 2), (0 3), (1 3), (2 3), at their midpoints; a meshio.Mesh."""
    tets = box_mesh(list(lengths), list(cells), "tet")
    points, conn, mids = list(tets.p.T), [], {}
    for cell in tets.t.T:
        row = list(cell)
        for a, b in [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]:
            edge = tuple(sorted((cell[a], cell[b])))
            if edge not in mids:
                mids[edge] = len(points)
                points.append((tets.p[:, edge[0]] + tets.p[:, edge[1]]) / 2)
            row.append(mids[edge])
        conn.append(row)
    return meshio.Mesh(np.array(points), [("tetra10", np.array(conn))])


# -- 1. cells: the whole body or a refusal by name -------------------------------------------------------
def test_a_body_of_hexahedra_and_wedges_is_refused_by_name_never_kept_in_part(tmp_path):
    nodes, hexes, wedges = _hexes_and_wedges()
    path = tmp_path / "mixed.vtu"
    meshio.write(path, meshio.Mesh(nodes, [("hexahedron", hexes), ("wedge", wedges)]))
    with pytest.raises(ValueError, match=r"mixed.vtu: its 3-D body has 8 wedge cells, which lnf cannot use "
                                         r"\(cells: 4 hexahedron, 8 wedge\).*linear tetra or hexahedron"):
        SoftBody(mesh_file=str(path))
    # two supported types mixed: refused too (lnf's body is of one type), with both counts
    tets = box_mesh([0.25, 0.15, 0.1], [1, 1, 1], "tet")
    mix = meshio.Mesh(np.vstack([nodes, tets.p.T + [0.5, 0.0, 0.0]]),
                      [("hexahedron", hexes), ("tetra", tets.t.T + len(nodes))])
    meshio.write(path, mix)
    with pytest.raises(ValueError, match=r"mixed.vtu: its 3-D body mixes 4 hexahedron and \d+ tetra cells"):
        SoftBody(mesh_file=str(path))
    # quadratic cells: refused by name for the finite-element body
    quadratic = tmp_path / "quadratic.vtu"
    meshio.write(quadratic, _tetra10())
    with pytest.raises(ValueError, match=r"quadratic.vtu: its 3-D body has \d+ tetra10 cells.*first-order"):
        SoftBody(mesh_file=str(quadratic))
    # boundary cells of a lower dimension (a mesher's surface triangles) only name sets: the body is whole
    box = box_mesh(list(BOX), [2, 1, 1], "tet")
    faces = box.facets[:, box.boundary_facets()].T
    mesh, _ = read_mesh_file(tmp_path, meshio.Mesh(box.p.T, [("triangle", faces), ("tetra", box.t.T)]))
    assert mesh.t.shape[1] == box.t.shape[1]
    # the mesh series reader computes the measure of both kinds, and uses the mixed mesh whole
    weights = nodal_volumes(nodes, meshio.Mesh(nodes, [("hexahedron", hexes), ("wedge", wedges)]).cells, 3)
    assert weights.sum() == pytest.approx(np.prod(BOX)) and np.all(weights > 0)


def read_mesh_file(tmp_path, raw):
    path = tmp_path / "boundary.vtu"
    meshio.write(path, raw)
    return read_mesh(path, "m")


# -- 2. quadratic cells in a mesh series ----------------------------------------------------------------
def test_quadratic_tetrahedra_get_nodal_volumes_and_unknown_cells_are_refused_by_name(tmp_path):
    raw = _tetra10()
    files = []
    for k in range(3):
        files.append(tmp_path / f"step{k}.vtu")
        meshio.write(files[-1], meshio.Mesh(raw.points, raw.cells, point_data={"u": raw.points * 0.01 * k}))
    run = read_mesh_series(files, "u", times=[0.0, 0.1, 0.2])
    assert run.weights is not None and len(run.weights) == len(raw.points)
    assert np.all(run.weights > 0) and run.weights.sum() == pytest.approx(np.prod(BOX), rel=1e-12)
    # a distorted cell: the 8 sub-tetrahedra of its 10 nodes still fill exactly its volume (meshio's node order)
    rng = np.random.default_rng(0)
    corners = rng.random((4, 3))
    edges = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]
    cell = np.vstack([corners] + [(corners[a] + corners[b]) / 2 for a, b in edges])
    volume = abs(np.linalg.det(corners[1:] - corners[0])) / 6
    assert nodal_volumes(cell, meshio.Mesh(cell, [("tetra10", [list(range(10))])]).cells, 3).sum() == \
        pytest.approx(volume, rel=1e-12)
    # cells of the body whose measure lnf does not know: refused by name, file and count, never None
    cube = np.vstack([np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")).reshape(3, -1).T,
                      rng.random((12, 3))])
    serendipity = tmp_path / "hex20.vtu"
    meshio.write(serendipity, meshio.Mesh(cube, [("hexahedron20", [list(range(20))])], point_data={"u": cube}))
    with pytest.raises(DatasetError, match=r"1 hexahedron20 cells fill part of its 3-D body.*tetra10"):
        read_mesh_series([serendipity] * 3, "u", times=[0.0, 0.1, 0.2])
    # a body dimension below that of the cells: its weights would be the boundary's
    with pytest.raises(DatasetError, match=r"taken as 2-D, but the mesh has .*tetra10 cells of a higher dimension"):
        read_mesh_series(files, "u", times=[0.0, 0.1, 0.2], dim=2)


# -- 3. float64 nodes: a dataset from a mesh file, end to end --------------------------------------------
@pytest.mark.parametrize("kind", ["tet", "hex"])
def test_a_box_mesh_file_generates_a_dataset_end_to_end(tmp_path, kind):
    """An ordinary mesh file of the 0.5 × 0.15 × 0.1 m box, given as scene.mesh_file (through the config): the
    dataset is generated at its nodes (stored in float64, on the mesh), and loads against the scene."""
    box = box_mesh(list(BOX), [4, 2, 1], kind)
    path = tmp_path / f"finger_{kind}.vtu"
    meshio.write(path, skfem.io.meshio.to_meshio(box))
    cfg = compose_config("train", ["scene=soft_body", f"scene.mesh_file={path}", "scene.mesh_units=m",
                                   "scene.release=shape"], tmp_path)  # shape: no static solve (fast)
    from lnf.train import build_scene

    scene = build_scene(OmegaConf.to_container(cfg.scene, resolve=True))
    assert isinstance(scene, SoftBody) and scene.params()["mesh_units"] == "m"
    data = DatasetConfig(n_train=1, n_val=1, n_test=1, n_times=3, train_times=2, dt=0.01, fine_resolution=4,
                         coarse_resolution=4, observed_fraction=0.5)
    generate_dataset(scene, data, tmp_path / "data.h5")
    split = load_split(tmp_path / "data.h5", "test", scene=scene, cfg=data)
    assert split.fine_points.dtype == np.float64
    np.testing.assert_array_equal(split.fine_points, scene.body.nodes)  # the nodes exactly, not rounded
    assert split.fields.shape == (1, 3, scene.n_nodes, 3) and np.isfinite(split.fields).all()
    assert np.abs(split.fields[:, :, scene.body.clamped]).max() == 0.0
    np.testing.assert_allclose(split.fields[0, 0], scene.unpack(split.states[0, 0])[0], atol=1e-6)


# -- 4. units --------------------------------------------------------------------------------------------
def test_a_mesh_in_millimetres_needs_its_unit_stated_and_is_scaled_to_metres(tmp_path, caplog):
    box = box_mesh([1000 * L for L in BOX], [2, 1, 1], "tet")
    path = tmp_path / "finger_mm.vtu"
    meshio.write(path, meshio.Mesh(box.p.T, [("tetra", box.t.T)]))
    with pytest.raises(ValueError, match=r"finger_mm.vtu: scene.mesh_units is not set and the mesh spans "
                                         r"500 × 150 × 100 in its own unit.*scene.mesh_units=mm \(then 0.5 m\)"):
        SoftBody(mesh_file=str(path))
    with caplog.at_level(logging.INFO, logger="lnf.fem"):
        scene = SoftBody(mesh_file=str(path), mesh_units="mm")
    np.testing.assert_allclose(scene.bounds, [[0.0, 0.5], [0.0, 0.15], [0.0, 0.1]], rtol=1e-12)
    assert scene.params()["mesh_units"] == "mm"
    assert "12 nodes, 12 tetra, extent 500 × 150 × 100 mm -> read as millimetres, scaled to metres" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="lnf.fem"):
        SoftBody(mesh_file=str(path), mesh_units="m")  # stated: obeyed, with a warning
    warned = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert warned and "outside the 0.001–10 m of a plausible body" in warned[0].getMessage()
    with pytest.raises(ValueError, match=r"scene.mesh_units='furlong': not a length unit lnf knows; expected one "
                                         r"of m, dm, cm, mm"):
        SoftBody(mesh_file=str(path), mesh_units="furlong")
    with pytest.raises(ValueError, match=r"scene.mesh_file='.*nowhere.vtu': no such file"):
        SoftBody(mesh_file=str(tmp_path / "nowhere.vtu"))
    # a plausible extent with no unit stated is read as metres, and says so
    caplog.clear()
    meshio.write(tmp_path / "finger_m.vtu", meshio.Mesh(box.p.T / 1000, [("tetra", box.t.T)]))
    with caplog.at_level(logging.INFO, logger="lnf.fem"):
        assert SoftBody(mesh_file=str(tmp_path / "finger_m.vtu")).params()["mesh_units"] == "m"
    assert "read as metres (scene.mesh_units not set: metres by default)" in caplog.text
    assert OmegaConf.load(compose_config.__globals__["CONF"] + "/scene/soft_body.yaml").mesh_units is None


# -- 5. a body, whole and once: surfaces, degenerate and repeated cells are refused by name ------------------------
def _tet_box():
    box = box_mesh(list(BOX), [4, 2, 1], "tet")
    return box.p.T, box.t.T  # nodes (N, 3), cells (48, 4)


def test_repeated_cells_are_refused_naming_the_file_the_count_and_a_cell(tmp_path):
    """Three tetrahedra written twice (99 instead of 96) used to pass, with their mass and stiffness doubled
    (a body volume of 0.00773 m³ instead of 0.0075)."""
    nodes, tets = _tet_box()
    path = tmp_path / "repeated.vtu"
    meshio.write(path, meshio.Mesh(nodes, [("tetra", np.vstack([tets, tets[[5, 7, 9]][:, ::-1]]))]))
    with pytest.raises(ValueError, match=r"repeated.vtu: 3 of its 51 tetra cells repeat another cell \(the same "
                                         r"nodes\), e.g. cell 48 repeats cell 5 .*mass and stiffness twice"):
        SoftBody(mesh_file=str(path), mesh_units="m", release="shape")
    meshio.write(path, meshio.Mesh(nodes, [("tetra", tets)]))  # the same body, each cell once: accepted whole
    body = SoftBody(mesh_file=str(path), mesh_units="m", release="shape").body
    assert body.quadrature_weights.sum() == pytest.approx(np.prod(BOX), rel=1e-12)


@pytest.mark.parametrize("cell", [[0, 1, 2, 2], "flat"], ids=["repeated-node", "coplanar-corners"])
def test_degenerate_cells_are_refused_when_the_mesh_is_read(tmp_path, cell):
    """A zero-volume tetrahedron used to end in "det F < 0.1 … the displacement is too large for the mesh" or a
    time step of None, far from its cause."""
    nodes, tets = _tet_box()
    if cell == "flat":  # four corners of the box's bottom face: in one plane
        bottom = np.flatnonzero(nodes[:, 2] == 0.0)
        cell = [int(bottom[0]), int(bottom[1]), int(bottom[3]), int(bottom[4])]
    path = tmp_path / "flat.vtu"
    meshio.write(path, meshio.Mesh(nodes, [("tetra", np.vstack([tets[:40], [cell], tets[40:]]))]))
    with pytest.raises(ValueError, match=r"flat.vtu: 1 of its 49 tetra cells have zero volume \(degenerate.*\), "
                                         r"e.g. cell 40 of its tetra cells.*volume 0"):
        read_mesh(path, "m")


def test_a_surface_or_an_off_plane_mesh_is_refused_saying_what_it_is_and_what_the_body_needs(tmp_path):
    """Triangles of a box's surface, or a flat mesh in the y-z plane, used to end in "scene.time_step must be a
    positive number, got None" (scikit-fem keeps a triangle mesh's x and y only)."""
    box = box_mesh(list(BOX), [4, 2, 1], "tet")
    surface = tmp_path / "surface.vtu"
    meshio.write(surface, meshio.Mesh(box.p.T, [("triangle", box.facets[:, box.boundary_facets()].T)]))
    needs = r"volume cells \(tetra or hexahedron\) that fill a 3-D body"
    with pytest.raises(ValueError, match=rf"surface.vtu: its body is 56 triangle cells, 2-D cells whose nodes span "
                                         rf"3-D space \(extent 0.5 × 0.15 × 0.1\): a surface, not a body; .*{needs}"):
        SoftBody(mesh_file=str(surface), mesh_units="m")
    plate = box_mesh([0.5, 0.15], [4, 2], "tri")
    yz = tmp_path / "yz.vtu"
    meshio.write(yz, meshio.Mesh(np.stack([np.zeros(plate.p.shape[1]), *plate.p], 1), [("triangle", plate.t.T)]))
    with pytest.raises(ValueError, match=rf"yz.vtu: its body is 16 triangle cells, a 2-D mesh lying in a plane that "
                                         rf"is not the x-y plane \(extent 0 × 0.5 × 0.15; its z varies by 0.15\).*{needs}"):
        SoftBody(mesh_file=str(yz), mesh_units="m")
    # the same plate in the x-y plane (z = 0, written as 3-D points) is a 2-D body
    xy = tmp_path / "xy.vtu"
    meshio.write(xy, meshio.Mesh(np.stack([*plate.p, np.zeros(plate.p.shape[1])], 1), [("triangle", plate.t.T)]))
    assert SoftBody(mesh_file=str(xy), mesh_units="m", release="shape").dim == 2


def test_an_unstated_unit_is_a_warning_even_within_the_plausible_range(tmp_path, caplog):
    """An 8 mm part drawn in mm (extent 8) passes as an 8 m body: said as a warning, not an info line."""
    box = box_mesh([8.0, 2.0, 1.0], [2, 1, 1], "tet")
    path = tmp_path / "part_in_mm.vtu"
    meshio.write(path, meshio.Mesh(box.p.T, [("tetra", box.t.T)]))
    with caplog.at_level(logging.INFO, logger="lnf.fem"):
        read_mesh(path, key="scene.mesh_units")
    warned = [r.getMessage() for r in caplog.records if r.name == "lnf.fem" and r.levelno == logging.WARNING]
    assert len(warned) == 1 and "extent 8 × 2 × 1 m -> read as metres (scene.mesh_units not set: metres by " \
        "default); set scene.mesh_units if it is not (e.g. scene.mesh_units=mm: a 0.008 m body)" in warned[0], warned
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="lnf.fem"):
        read_mesh(path, "m", key="scene.mesh_units")  # stated: an info line only
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING] and "read as metres" in caplog.text
