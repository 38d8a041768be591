"""The mesh's own discrete Lagrangian (lnf/scenes/mesh_potential.py, quadrature=mesh_nodes) against the full-order
reference's sums (lnf/fem/body.py)."""
import numpy as np
import pytest
import torch

from lnf.dynamics import ReducedDynamics
from lnf.quadrature import MeshNodes, NodeQuadrature, Quadrature
from lnf.scenes.elastic import ElasticCantilever, ElasticPotential
from lnf.scenes.mesh_potential import MeshStrainPotential
from lnf.scenes.soft_body import SoftBody
from lnf.siren import FieldJet


def _displacements(scene, batch=3, scale=1e-2, seed=0):
    u = np.random.default_rng(seed).normal(size=(batch, scene.body.n_nodes, scene.body.dim)) * scale
    u[:, scene.body.clamped] = 0.0
    return torch.as_tensor(u)


@pytest.mark.parametrize("scene", [ElasticCantilever(mesh=(8, 4)), ElasticCantilever(mesh=(6, 3), material="neo_hookean"),
                                   SoftBody(cells=(4, 2, 2))], ids=["svk-2d", "neo-hookean-2d", "soft-body-3d"])
def test_the_nodal_potential_is_the_references_strain_energy_and_gravity_with_its_force(scene):
    quad = scene.nodal_quadrature()
    potential = scene.potential(quad)
    assert isinstance(quad, NodeQuadrature) and isinstance(potential, MeshStrainPotential)
    assert not potential.needs_gradient  # the mesh's gradient comes from the nodal values, not ∇_X φ
    u = _displacements(scene)
    gravity = scene.nodal_mass * scene.gravity
    reference = scene.body.strain_energy(u.numpy()) + (gravity * u[..., -1].numpy()).sum(-1)
    np.testing.assert_allclose(potential(u).numpy(), reference, rtol=1e-12)
    force = scene.body.internal_force(u.numpy())
    force[..., -1] -= gravity
    dq, dG = potential.gradient(u)
    assert dG is None
    np.testing.assert_allclose(dq.numpy(), -force, atol=1e-10 * np.abs(force).max())
    leaf = u.clone().requires_grad_(True)  # autograd (the energy loss) through the sparse operator agrees
    potential(leaf).sum().backward()
    torch.testing.assert_close(leaf.grad, dq)
    np.testing.assert_allclose(quad.weights.numpy() * scene.rho, scene.nodal_mass)  # lumped mass from the weights


def test_the_reduced_mass_on_the_nodes_is_the_lumped_one():
    """A one-mode field φ = q̃ s(X): M̃ = Σ_a m_a ‖s_a‖², g̃ = s · ∂V/∂u — the reference's equations projected."""
    scene = ElasticCantilever(mesh=(6, 3))
    quad = scene.nodal_quadrature()
    shape = torch.stack([torch.zeros(len(quad)), (quad.points[:, 0] / scene.length) ** 2], -1)  # (nn, 2)

    def jet(q, points, order=2, spatial=False):
        J = shape[None, :, :, None].expand(q.shape[0], -1, -1, 1)  # (B, nn, 2, d = 1)
        return FieldJet(value=q[:, None, None, 0] * shape[None], J=J, H=torch.zeros(*J.shape, 1, dtype=J.dtype))

    dynamics = ReducedDynamics(jet, scene, quad)
    q = torch.tensor([[0.05], [-0.1]], dtype=torch.float64)
    mass = dynamics.mass_matrix(q)
    torch.testing.assert_close(mass[:, 0, 0], torch.full((2,), float((scene.nodal_mass * (shape ** 2).sum(-1).numpy()).sum()),
                                                         dtype=torch.float64))
    u = (q[:, None, :] * shape[None]).numpy()
    force = scene.body.internal_force(u)
    force[..., -1] -= scene.nodal_mass * scene.gravity
    expected = -(force * shape.numpy()[None]).sum((1, 2))
    _, _, gravity = dynamics.static_terms(q)
    np.testing.assert_allclose(gravity[:, 0].numpy(), expected, rtol=1e-10)


def test_mesh_nodes_refuses_scenes_without_a_mesh_and_keeps_its_kind_when_cast(pendulum):
    with pytest.raises(ValueError, match="quadrature=mesh_nodes: scene .* has no mesh of its own"):
        MeshNodes().build_for(pendulum)
    with pytest.raises(ValueError, match="build it with build_for"):
        MeshNodes(order=[12, 6]).build([[0.0, 1.0]])  # an experiment's order is accepted, the mesh sets the points
    scene = ElasticCantilever(mesh=(6, 3))
    quad = MeshNodes().build_for(scene)
    assert isinstance(quad.to(torch.float32), NodeQuadrature)  # a float32 model's copy stays the mesh's own
    assert isinstance(scene.potential(quad.to(torch.float32)), MeshStrainPotential)
    with pytest.raises(ValueError, match="not this body's mesh"):
        scene.potential(ElasticCantilever(mesh=(8, 4)).nodal_quadrature())
    assert isinstance(scene.potential(Quadrature(quad.points, quad.weights)), ElasticPotential)  # the continuum's
