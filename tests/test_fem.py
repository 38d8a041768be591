"""The finite-element reference (lnf.fem): materials, scikit-fem bodies of any linear cell, meshes from meshio,
time stepping (small meshes)."""
import meshio
import numpy as np
import pytest
import skfem
import torch

from lnf.fem.body import ElasticBody, box_mesh, from_meshio, read_mesh
from lnf.fem.materials import NeoHookean, StVenantKirchhoff, get_material, lame
from lnf.fem.time_stepping import implicit_midpoint, verlet

LAM, MU = lame(200.0, 0.3)
MESHES = {"tri": ([1.0, 0.4], [4, 2]), "quad": ([1.0, 0.4], [4, 2]), "tet": ([1.0, 0.3, 0.2], [3, 2, 1]),
          "hex": ([1.0, 0.3, 0.2], [3, 2, 1])}


def body_of(kind, material=None, **kw):
    lengths, cells = MESHES[kind]
    mesh = box_mesh(lengths, cells, kind)
    return ElasticBody(mesh, material or StVenantKirchhoff(LAM, MU), 1.0, clamped=mesh.p[0] == 0.0, **kw)


@pytest.mark.parametrize("material", [StVenantKirchhoff(LAM, MU), NeoHookean(LAM, MU)], ids=["svk", "nh"])
@pytest.mark.parametrize("d", [2, 3])
def test_material_stress_is_the_energy_gradient_and_tangent_its_jacobian(material, d):
    gen = torch.Generator().manual_seed(0)
    F = (torch.eye(d) + 0.1 * torch.randn(5, d, d, generator=gen, dtype=torch.float64)).requires_grad_(True)
    (auto,) = torch.autograd.grad(material.energy_density(F).sum(), F)
    torch.testing.assert_close(material.first_piola(F), auto)
    A = material.tangent(F.detach())
    jac = torch.autograd.functional.jacobian(lambda x: material.first_piola(x).sum(0), F.detach())  # (d, d, 5, d, d)
    torch.testing.assert_close(A, jac.permute(2, 0, 1, 3, 4))


def test_neo_hookean_and_svk_share_their_small_strain_limit_and_differ_beyond():
    svk, nh = StVenantKirchhoff(LAM, MU), NeoHookean(LAM, MU)
    I = torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(svk.tangent(I), nh.tangent(I))  # the same Lamé moduli
    assert float(nh.energy_density(I)) == pytest.approx(0.0, abs=1e-12)
    squeeze = torch.diag(torch.tensor([0.3, 1.0, 1.0], dtype=torch.float64))
    assert float(nh.energy_density(squeeze)) > 2 * float(svk.energy_density(squeeze))  # NH stiffens under compression
    # inverted: finite and large (the continuation of ln J below min_jacobian), with P still ∂W/∂F
    inverted = torch.diag(torch.tensor([-0.5, 1.0, 1.0], dtype=torch.float64)).requires_grad_(True)
    W = nh.energy_density(inverted)
    assert torch.isfinite(W) and float(W.detach()) > float(nh.energy_density(squeeze))
    (auto,) = torch.autograd.grad(W, inverted)
    torch.testing.assert_close(nh.first_piola(inverted.detach()), auto)
    body = body_of("tet", nh)
    crushed = np.zeros((1, body.n_nodes, 3))
    crushed[0, :, 0] = -0.95 * body.nodes[:, 0]  # J = 0.05 < min_jacobian everywhere
    with pytest.raises(FloatingPointError, match="det F < 0.1 .*crushed or inverted"):
        body.internal_force(crushed)
    with pytest.raises(ValueError, match="scene.material must be one of"):
        get_material("rubber", 1.0, 0.3)
    with pytest.raises(ValueError, match="Poisson's ratio"):
        lame(1.0, 0.5)


@pytest.mark.parametrize("kind", sorted(MESHES))
def test_batched_force_is_scikit_fems_assembly_and_minus_the_energy_gradient(kind, rng):
    body = body_of(kind)
    u = 0.01 * rng.standard_normal((2, body.n_nodes, body.dim))
    force = body.internal_force(u)
    for b in range(2):
        np.testing.assert_allclose(force[b], body.assembled_internal_force(u[b]), atol=1e-10)
    d, eps = rng.standard_normal(u.shape), 1e-6
    slope = (body.strain_energy(u + eps * d) - body.strain_energy(u - eps * d)) / (2 * eps)
    np.testing.assert_allclose(-(force * d).sum((1, 2)), slope, rtol=1e-6)
    assert body.quadrature_weights.sum() == pytest.approx(np.prod(MESHES[kind][0]))
    assert body.nodal_mass.sum() == pytest.approx(np.prod(MESHES[kind][0]))
    assert body.quadrature_points.shape == (len(body.quadrature_weights), body.dim)


@pytest.mark.parametrize("kind", ["quad", "tet"])
@pytest.mark.parametrize("material", [StVenantKirchhoff(LAM, MU), NeoHookean(LAM, MU)], ids=["svk", "nh"])
def test_tangent_stiffness_is_the_exact_force_jacobian(kind, material, rng):
    body = body_of(kind, material)
    u = 0.02 * rng.standard_normal((body.n_nodes, body.dim))
    n, eps = body.dim * body.n_nodes, 1e-6
    bumps = np.eye(n).reshape(n, body.n_nodes, body.dim) * eps
    columns = -(body.internal_force(u + bumps) - body.internal_force(u - bumps)) / (2 * eps)
    K = body.tangent_stiffness(u).toarray()
    np.testing.assert_allclose(K, columns.reshape(n, n).T, atol=1e-5 * np.abs(K).max())
    np.testing.assert_allclose(K, K.T, atol=1e-10 * np.abs(K).max())
    np.testing.assert_allclose(K, body.assembled_tangent_stiffness(u).toarray(), atol=1e-12 * np.abs(K).max())


@pytest.mark.parametrize("kind", sorted(MESHES))
def test_interpolation_reproduces_affine_fields_and_their_gradients(kind, rng):
    body = body_of(kind)
    A = rng.standard_normal((body.dim, body.dim))
    nodal = body.nodes @ A.T + 0.3
    points = rng.random((20, body.dim)) * np.array(MESHES[kind][0])
    np.testing.assert_allclose(body.interpolation(points) @ nodal, points @ A.T + 0.3, atol=1e-12)
    G = np.stack([D @ nodal for D in body.interpolation_gradient(points)], -1)  # (N, a, j)
    np.testing.assert_allclose(G, np.broadcast_to(A, G.shape), atol=1e-10)
    with pytest.raises(ValueError, match="points outside the mesh"):
        body.interpolation(np.full((1, body.dim), 5.0))
    with pytest.raises(ValueError, match=r"points must be \(N, "):
        body.interpolation(np.zeros((3, body.dim + 1)))


def test_meshes_come_from_meshio_with_their_named_sets(tmp_path):
    """A tetrahedral mesh with an unused node (a mesher's geometry point), a point set and a cell set, written by
    meshio and read back: the body keeps its cells, drops the unused node and names its regions by node."""
    box = box_mesh([1.0, 0.3, 0.2], [3, 2, 1], "tet")
    points = np.vstack([box.p.T, [[9.0, 9.0, 9.0]]])
    clamp = np.flatnonzero(points[:, 0] == 0.0)
    tip_cells = np.flatnonzero(box.p[0, box.t].mean(0) > 0.9)
    raw = meshio.Mesh(points, [("tetra", box.t.T)], point_sets={"clamp": clamp}, cell_sets={"tip": [tip_cells]})
    mesh, sets = from_meshio(raw)
    assert mesh.p.shape[1] == box.p.shape[1]
    np.testing.assert_array_equal(sets["clamp"], box.p[0] == 0.0)
    assert sets["tip"].sum() > 0 and box.p[0][sets["tip"]].min() > 0.6
    body = ElasticBody(mesh, StVenantKirchhoff(LAM, MU), 1.0, clamped=sets["clamp"])
    assert body.quadrature_weights.sum() == pytest.approx(0.06)
    path = tmp_path / "body.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra", box.t.T)]))
    again, _ = read_mesh(path)
    np.testing.assert_allclose(again.p, mesh.p)
    # hexahedra in meshio's (VTK) corner order become positive-volume scikit-fem cells
    hexes = box_mesh([1.0, 0.3, 0.2], [2, 1, 1], "hex")
    raw_hex = skfem.io.meshio.to_meshio(hexes)
    hex_body = ElasticBody(from_meshio(raw_hex)[0], StVenantKirchhoff(LAM, MU), 1.0)
    assert np.all(hex_body.basis.dx > 0) and hex_body.quadrature_weights.sum() == pytest.approx(0.06)
    (tmp_path / "bad.vtu").write_text("not a mesh")
    with pytest.raises(ValueError, match="bad.vtu: meshio cannot read it"):
        read_mesh(tmp_path / "bad.vtu")
    with pytest.raises(FileNotFoundError, match="missing.msh"):
        read_mesh(tmp_path / "missing.msh")
    with pytest.raises(ValueError, match="no triangles, quadrilaterals"):
        from_meshio(meshio.Mesh(points[:2], [("line", np.array([[0, 1]]))]))


def _cantilever(kind="quad", material=None):
    body = body_of(kind, material)
    weight = body.nodal_mass * 1.0

    def force(u, t, index):
        f = body.internal_force(u)
        f[..., -1] -= weight
        return f

    return body, force


def _energy(body, u, v):
    kinetic = 0.5 * np.einsum("n,bnk,bnk->b", body.nodal_mass, v, v)
    return kinetic + body.strain_energy(u) + (body.nodal_mass * u[..., -1]).sum(-1)


def test_implicit_midpoint_takes_steps_far_above_the_cfl_limit_and_agrees_with_verlet(rng):
    body, force = _cantilever()
    u0 = np.zeros((1, body.n_nodes, 2))
    v0 = np.zeros_like(u0)
    v0[..., 1] = -0.3 * body.nodes[:, 0] ** 2
    times = np.linspace(0.0, 2.0, 5)
    cfl = body.stable_time_step()
    fine_u, _ = verlet(body, force, u0, v0, times, 0.5 * cfl)
    scale = np.abs(fine_u).max()
    motion = 0.5 * np.einsum("n,bnk,bnk->", body.nodal_mass, v0, v0)  # the release's kinetic energy
    errors = []
    for factor in (20, 10):
        us, vs, newton = implicit_midpoint(body, force, u0, v0, times, factor * cfl)
        assert newton <= 8
        assert np.ptp(_energy(body, us[0], vs[0])) < 0.02 * motion
        errors.append(np.abs(us - fine_u).max())
    assert errors[1] < 0.1 * scale  # 20× Verlet's step
    assert errors[1] < 0.3 * errors[0]  # second order: 4× smaller at half the step
    assert np.abs(us[:, :, body.clamped]).max() == 0.0
    with pytest.raises(FloatingPointError, match="velocity Verlet diverged"):
        verlet(body, force, u0, v0, times, 5 * cfl)


def test_damping_takes_energy_out_in_both_integrators():
    body, force = _cantilever()
    u0 = np.zeros((1, body.n_nodes, 2))
    v0 = np.zeros_like(u0)
    v0[..., 1] = -0.3 * body.nodes[:, 0] ** 2
    times = np.linspace(0.0, 1.0, 6)
    for run in (lambda: verlet(body, force, u0, v0, times, 0.5 * body.stable_time_step(), damping=2.0)[:2],
                lambda: implicit_midpoint(body, force, u0, v0, times, 0.02, damping=2.0)[:2]):
        us, vs = run()
        energy = _energy(body, us[0], vs[0])
        assert np.all(np.diff(energy) < 0)
