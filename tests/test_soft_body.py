"""The 3-D soft body (lnf.scenes.SoftBody): a Neo-Hookean finger on a scikit-fem mesh, its Lagrangian and its
finite-element reference (small meshes)."""
import meshio
import numpy as np
import pytest
import torch

from lnf.fem.body import box_mesh
from lnf.quadrature import MeshElements, gauss_legendre_rule
from lnf.scenes import SoftBody

SMALL = dict(box=(0.5, 0.15, 0.1), cells=(6, 2, 2))


@pytest.fixture(scope="module")
def finger():
    return SoftBody(**SMALL)


def test_the_finger_declares_its_parts_and_fields_in_three_dimensions(finger, rng):
    caps = finger.capabilities()
    assert caps["simulator"] and caps["fields"] and caps["clamp"] and caps["field_gradients"] and caps["conservative"]
    assert finger.field_dim == 3 and finger.body_dim == 3 and finger.name == "soft_body"
    assert finger.provides("element_quadrature") and finger.provides("observation_points")
    states = finger.sample_initial_states(2, rng)
    u, v, _ = finger.unpack(states)
    assert u.shape == (2, finger.n_nodes, 3) and np.abs(u[:, finger.body.clamped]).max() == 0.0
    q, qdot = finger.fields(states, finger.body.nodes[:5])
    np.testing.assert_allclose(q, u[:, :5], atol=1e-12)
    np.testing.assert_allclose(qdot, v[:, :5], atol=1e-12)
    points = finger.observation_points(12)
    assert points.shape == (12 * 4 * 2, 3)  # cells in proportion to the box: 12 × round(3.6) × round(2.4)
    quad = MeshElements().build_for(finger)
    assert quad.weights.sum().item() == pytest.approx(0.5 * 0.15 * 0.1)
    with pytest.raises(ValueError, match="quadrature=mesh: scene 'pendulum' has no mesh"):
        from lnf.scenes import LiftedPendulum
        MeshElements().build_for(LiftedPendulum())


def test_the_reduced_potential_of_an_affine_field_is_the_fems(finger):
    """u = A X: the FEM's energy and the continuum potential on any quadrature are both exact."""
    A = np.array([[0.02, -0.01, 0.03], [0.01, 0.015, -0.02], [-0.03, 0.02, 0.01]])
    u = (finger.body.nodes @ A.T)[None]
    _, fem = finger.true_energy_parts(finger.pack(u, np.zeros_like(u), np.zeros((1, 2))))
    for quad in (gauss_legendre_rule([3, 2, 2], finger.bounds).to(torch.float64), MeshElements().build_for(finger)):
        q = (quad.points.double() @ torch.as_tensor(A).T)[None]
        G = torch.as_tensor(A).expand(1, len(quad.points), 3, 3)
        V = finger.potential(quad.to(torch.float64))(q, G)
        np.testing.assert_allclose(V.item(), fem[0], rtol=1e-10)


def test_verlet_conserves_the_fingers_energy_and_the_modal_release_sags_under_gravity(finger, rng):
    u_g, mode, _ = finger.modal_reference()
    assert u_g[finger._tip, 2].mean() < 0  # gravity along −X₃
    assert mode[finger._tip, 2].mean() == pytest.approx(1.0)
    states = finger.simulate(finger.sample_initial_states(2, rng), 0.05 * np.arange(11))
    energy = finger.true_energy(states)
    assert np.abs(energy - energy[:, :1]).max() < 1e-3 * finger.energy_scale


def test_a_mesh_file_gives_the_body_its_clamp_set_and_cable_load(tmp_path, rng):
    box = box_mesh([0.5, 0.15, 0.1], [4, 2, 1], "tet")
    base = np.flatnonzero(box.p[0] == 0.0)
    path = tmp_path / "finger.vtu"
    meshio.write(path, meshio.Mesh(box.p.T, [("tetra", box.t.T)]))
    with pytest.raises(ValueError, match="scene.clamp='base': .*has no such point or cell set"):
        SoftBody(mesh_file=str(path), clamp="base")
    path = tmp_path / "finger.msh"  # Gmsh keeps the named physical groups as point sets
    meshio.write(path, meshio.Mesh(box.p.T, [("tetra", box.t.T)], point_sets={"base": base}), file_format="gmsh22")
    scene = SoftBody(mesh_file=str(path), clamp=None, damping=0.5, load_amplitude_range=(1.0, 2.0))
    assert scene.body.clamped.sum() == len(base)
    assert not scene.is_conservative and scene.has_controls
    np.testing.assert_allclose(scene.observation_points(8), scene.body.nodes)
    quad = MeshElements().build_for(scene)
    force = scene.generalized_force(quad)
    t_peak = 0.25 / 1.0  # sin(2π f t) = 1 at f = 1 Hz
    n = len(quad.points)
    f = force.field_force(t_peak, torch.zeros(1, n, 3), torch.zeros(1, n, 3), torch.tensor([[1.0, 1.0]]))
    assert f.shape == (1, n, 3) and torch.all(f[..., 0] <= 0) and torch.all(f[..., 2] >= 0)  # back and up
    assert f[..., 2].max() > 0
    with pytest.raises(ValueError, match="scene.load_direction"):
        SoftBody(**SMALL, load_direction=[1.0, 0.0])
    with pytest.raises(ValueError, match="scene.cell_kind"):
        SoftBody(box=(0.5, 0.1, 0.1), cells=(2, 1, 1), cell_kind="quad")


def test_an_expensive_reference_is_simulated_in_chunks_under_a_progress_bar(finger, rng, monkeypatch):
    """generate_dataset simulates an FEM scene a few trajectories at a time (a progress bar's steps): the same
    states as one call."""
    from lnf import dataset

    seen = []
    real = finger.simulate
    monkeypatch.setattr(finger, "simulate", lambda states, times: seen.append(len(states)) or real(states, times))
    initial = finger.sample_initial_states(dataset.SIMULATION_CHUNK + 2, rng)
    times = 0.05 * np.arange(3)
    chunked = dataset._simulate(finger, initial, times, "train")
    assert seen == [dataset.SIMULATION_CHUNK, 2]
    np.testing.assert_allclose(chunked, real(initial, times), rtol=0, atol=1e-12)


def test_check_scene_passes_the_finger_on_its_own_element_rule():
    from lnf.scenes.check import check_scene

    report = check_scene(SoftBody(box=(0.5, 0.15, 0.1), cells=(4, 2, 1)))
    assert not report.problems and "potential V against the scene's own potential energy" in report.passed
