"""Tabulated reduced dynamics (lnf/tabulated.py): Chebyshev tables of M̃ and Ṽ against the exact pullback."""
import numpy as np
import pytest
import torch

from lnf.integrators import get_integrator
from lnf.tabulated import ChebyshevTable, TabulatedDynamics, force_separates, start_nodes
from test_dynamics import _nonlinear_setup, _pendulum_dynamics


def test_chebyshev_table_reproduces_a_smooth_function_and_its_derivatives():
    low, high = [-1.0, 0.5], [2.0, 1.5]
    n = 24
    x = np.polynomial.chebyshev.chebpts1(n)
    axes = [lo + (hi - lo) * (x + 1) / 2 for lo, hi in zip(low, high)]
    a, b = np.meshgrid(*axes, indexing="ij")
    f = np.stack([np.sin(a) * np.cos(2 * b), a**2 + b], -1)
    table = ChebyshevTable(f, low, high)
    q = torch.tensor([[0.3, 0.7], [-0.9, 1.4], [1.9, 0.6]], dtype=torch.float64)
    out = table(q)
    q1, q2 = q[:, 0], q[:, 1]
    torch.testing.assert_close(out[:, 0, 0], torch.sin(q1) * torch.cos(2 * q2), atol=1e-10, rtol=0)
    torch.testing.assert_close(out[:, 0, 1], q1**2 + q2, atol=1e-10, rtol=0)
    torch.testing.assert_close(out[:, 1, 0], torch.cos(q1) * torch.cos(2 * q2), atol=1e-8, rtol=0)
    torch.testing.assert_close(out[:, 2, 0], -2 * torch.sin(q1) * torch.sin(2 * q2), atol=1e-8, rtol=0)
    torch.testing.assert_close(out[:, 1, 1], 2 * q1, atol=1e-8, rtol=0)
    torch.testing.assert_close(out[:, 2, 1], torch.ones_like(q1), atol=1e-8, rtol=0)


def test_a_table_of_three_or_four_codes_is_evaluated_as_one_product_on_the_tensor_basis(monkeypatch):
    """From d = 3 the interpolant is one matrix product on the tensor-product basis, in chunks of rows: the same
    values and derivatives as contracting axis by axis, and exact on a polynomial it can hold."""
    from lnf import tabulated

    for d in (3, 4):
        low, high = [-1.0, 0.0, 0.5, -2.0][:d], [1.0, 2.0, 1.5, 0.0][:d]
        n = 6
        axes = [lo + (hi - lo) * (np.polynomial.chebyshev.chebpts1(n) + 1) / 2 for lo, hi in zip(low, high)]
        grid = np.meshgrid(*axes, indexing="ij")
        f = np.stack([grid[0] ** 2 * grid[1] + grid[-1] ** 3, np.prod(grid, 0)], -1)  # degrees < n per axis
        table = ChebyshevTable(f, low, high)
        q = torch.tensor(np.random.default_rng(d).uniform(low, high, (7, d)))
        monkeypatch.setattr(tabulated, "TENSOR_BASIS_ELEMENTS", 2 * n ** d)  # chunks of 2 rows
        out = table(q)
        monkeypatch.setattr(tabulated, "TENSOR_BASIS_FROM_DIM", 99)  # axis by axis
        torch.testing.assert_close(out, table(q), atol=1e-12, rtol=0)
        monkeypatch.undo()
        v = q.numpy()
        torch.testing.assert_close(out[:, 0, 0], torch.tensor(v[:, 0] ** 2 * v[:, 1] + v[:, -1] ** 3), atol=1e-10,
                                   rtol=0)
        torch.testing.assert_close(out[:, 1 + d - 1, 0], torch.tensor(3 * v[:, -1] ** 2), atol=1e-8, rtol=0)
        torch.testing.assert_close(out[:, 2, 1], torch.tensor(np.prod(np.delete(v, 1, 1), 1)), atol=1e-8, rtol=0)


def test_chebyshev_table_rejects_a_bad_box():
    with pytest.raises(ValueError, match="high > low"):
        ChebyshevTable(np.zeros((4, 1)), [1.0], [1.0])


def test_the_table_is_built_in_batches_bounded_by_codes_times_quadrature_points():
    """A fine rule must not multiply the build's memory: 256 codes at once on a 16³ rule held 22 GB of jets."""
    _, exact, _ = _nonlinear_setup(n=4096)
    sizes = []
    static_terms = exact.static_terms
    exact.static_terms = lambda rows: sizes.append(len(rows)) or static_terms(rows)
    tab = TabulatedDynamics(exact, [-1.0, -1.0], [1.5, 1.0], tol=1e-6)
    assert max(sizes) == TabulatedDynamics.CHUNK_POINTS // 4096 == tab.chunk and sum(sizes) >= 16 ** 2
    _, small, _ = _nonlinear_setup()
    assert TabulatedDynamics(small, [-1.0, -1.0], [1.5, 1.0], tol=1e-6).chunk == 256  # a coarse rule: as before


def test_tabulated_matches_the_exact_nonlinear_pullback_in_2d():
    _, exact, _ = _nonlinear_setup()
    tab = TabulatedDynamics(exact, [-1.0, -1.0], [1.5, 1.0], tol=1e-10)
    assert tab.info["table_error"] <= 1e-10 and tab.info["table_nodes"] <= 64
    q = torch.tensor([[0.3, -0.7], [1.1, 0.2], [-0.5, 0.9]], dtype=torch.float64)
    v = torch.tensor([[0.5, 1.5], [-2.0, 0.7], [0.1, -0.3]], dtype=torch.float64)
    torch.testing.assert_close(tab.acceleration(q, v), exact.acceleration(q, v), atol=1e-8, rtol=1e-8)
    extra = torch.tensor([[0.4, -1.0], [2.0, 0.3], [-0.7, 0.0]], dtype=torch.float64)  # e.g. a closure's −∇ΔṼ
    torch.testing.assert_close(tab.acceleration(q, v, extra_force=extra), exact.acceleration(q, v, extra_force=extra),
                               atol=1e-8, rtol=1e-8)
    for a, b in zip(tab.hamiltonian_derivatives(q, v), exact.hamiltonian_derivatives(q, v)):
        torch.testing.assert_close(a, b, atol=1e-8, rtol=1e-8)
    for a, b in zip(tab.energies(q, v), exact.energies(q, v)):
        torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-9)
    assert tab.fallback_rows == 0


def test_chebyshev_table_takes_a_different_number_of_nodes_on_each_axis(monkeypatch):
    """Nodes per axis may differ (an axis along which f varies slowly needs fewer): the values and derivatives of a
    polynomial it can hold, the same axis by axis and on the tensor basis, and the last axis's tail far below the
    first's when f needs more degrees along the first."""
    from lnf import tabulated

    for nodes in ((9, 4), (9, 3, 5)):
        d = len(nodes)
        low, high = [-1.0, 0.0, 0.5][:d], [1.0, 2.0, 1.5][:d]
        axes = [lo + (hi - lo) * (np.polynomial.chebyshev.chebpts1(n) + 1) / 2 for n, lo, hi in zip(nodes, low, high)]
        grid = np.meshgrid(*axes, indexing="ij")
        f = np.stack([grid[0] ** 8 * grid[1] + grid[-1], grid[0] * grid[1]], -1)  # degrees < n_i per axis
        table = ChebyshevTable(f, low, high)
        assert table.nodes == nodes and table.size == np.prod(nodes) and table.n == 9
        q = torch.tensor(np.random.default_rng(d).uniform(low, high, (5, d)))
        out = table(q)
        v = q.numpy()
        torch.testing.assert_close(out[:, 0, 0], torch.tensor(v[:, 0] ** 8 * v[:, 1] + v[:, -1]), atol=1e-9,
                                   rtol=0)
        torch.testing.assert_close(out[:, 1, 0], torch.tensor(8 * v[:, 0] ** 7 * v[:, 1]), atol=1e-8, rtol=0)
        torch.testing.assert_close(out[:, 2, 1], torch.tensor(v[:, 0]), atol=1e-9, rtol=0)
        monkeypatch.setattr(tabulated, "TENSOR_BASIS_FROM_DIM", 2 if d == 2 else 99)  # the other path
        torch.testing.assert_close(table(q), out, atol=1e-10, rtol=0)
        monkeypatch.undo()
        tails = table.axis_tails()
        assert tails[0] > 1e-3 and tails[-1] < 1e-6  # degree 8 along the first axis, at most 1 along the last


def test_a_table_refines_only_the_axes_that_need_it_and_reads_no_more_terms_than_its_tolerance_needs():
    """Codes that span a wide range on one axis and a narrow one on the other (as the soft body's do): the nodes
    double along the wide axis only, the table meets its tolerance with far fewer nodes than a square one, and its
    series is then cut to the terms that tolerance needs (an evaluation costs their product), still within it."""
    _, exact, _ = _nonlinear_setup()
    tab = TabulatedDynamics(exact, [-3.0, -0.05], [3.0, 0.05], tol=1e-10, min_nodes=8)
    assert tab.info["table_error"] <= 1e-10
    wide, narrow = tab.info["table_shape"]  # the nodes built
    assert narrow == 8 and wide >= 32 and tab.info["table_nodes"] == wide and tab.info["table_points"] == wide * narrow
    cut = tab.info["table_terms_shape"]  # the terms read
    assert cut[0] <= wide and cut[1] <= narrow and cut != [wide, narrow] and tab.info["table_terms"] == np.prod(cut)
    assert repr(tab).startswith(f"TabulatedDynamics(d=2, {cut[0]} × {cut[1]} ")
    q = torch.tensor([[0.3, -0.01], [2.1, 0.04], [-2.5, 0.0]], dtype=torch.float64)
    v = torch.tensor([[0.5, 1.5], [-2.0, 0.7], [0.1, -0.3]], dtype=torch.float64)
    torch.testing.assert_close(tab.acceleration(q, v), exact.acceleration(q, v), atol=1e-7, rtol=1e-7)
    square = TabulatedDynamics(exact, [-3.0, -0.05], [3.0, 0.05], tol=1e-10, min_nodes=wide, max_nodes=wide)
    assert square.info["table_shape"] == [wide, wide] and wide ** 2 >= 4 * wide * narrow


def test_a_table_of_four_codes_starts_with_fewer_nodes_per_axis_so_that_one_axis_can_grow():
    """16 nodes per axis up to d = 3; at d = 4, 16⁴ would be the whole default cap of 65 536: 8, so one axis can
    double three times (the soft body's d = 4 table needs 128 nodes along its wide axis); never below 4."""
    assert [start_nodes(16, d, 65536) for d in (1, 2, 3, 4, 5, 6)] == [16, 16, 16, 8, 4, 4]
    assert start_nodes(16, 4, 1 << 20) == 16 and start_nodes(3, 4, 65536) == 3


def test_a_table_that_misses_its_tolerance_is_cut_only_as_far_as_its_error_allows(monkeypatch):
    """A table above its tolerance (here out of reach) is still read through fewer terms where they cost its error at
    most TABLE_TRIM_SLACK more than the whole table's."""
    from lnf import tabulated

    _, exact, _ = _nonlinear_setup()

    def table() -> TabulatedDynamics:
        return TabulatedDynamics(exact, [-3.0, -0.05], [3.0, 0.05], tol=1e-300, min_nodes=8, max_nodes=16)

    cut = table().info
    monkeypatch.setattr(tabulated, "TABLE_TRIM_SHARES", ())  # read whole
    whole = table().info
    assert whole["table_terms_shape"] == whole["table_shape"] == cut["table_shape"] == [16, 8]
    assert cut["table_terms"] < whole["table_terms"]
    assert cut["table_error"] <= (1 + tabulated.TABLE_TRIM_SLACK) * whole["table_error"]


def test_a_slow_table_build_logs_each_round(monkeypatch, caplog):
    """A build past TABLE_LOG_SECONDS says each round's nodes and error (the soft body's d = 4 table takes minutes);
    a quick one says nothing."""
    from lnf import tabulated

    _, exact, _ = _nonlinear_setup()
    with caplog.at_level("INFO", logger="lnf.tabulated"):
        TabulatedDynamics(exact, [-3.0, -0.05], [3.0, 0.05], tol=1e-10, min_nodes=8)
    assert "table of the reduced dynamics" not in caplog.text
    monkeypatch.setattr(tabulated, "TABLE_LOG_SECONDS", 0.0)
    with caplog.at_level("INFO", logger="lnf.tabulated"):
        TabulatedDynamics(exact, [-3.0, -0.05], [3.0, 0.05], tol=1e-10, min_nodes=8)
    rounds = [r.getMessage() for r in caplog.records if "table of the reduced dynamics" in r.getMessage()]
    assert len(rounds) >= 3 and "8 nodes per axis" in rounds[0] and "16 × 8 nodes" in rounds[1]


def test_rows_off_the_box_use_the_exact_pullback():
    _, exact, _ = _nonlinear_setup()
    tab = TabulatedDynamics(exact, [-0.2, -0.2], [0.2, 0.2])
    q = torch.tensor([[0.1, 0.0], [1.1, 0.2], [-0.5, 0.9]], dtype=torch.float64)
    v = torch.tensor([[0.5, 1.5], [-2.0, 0.7], [0.1, -0.3]], dtype=torch.float64)
    torch.testing.assert_close(tab.acceleration(q, v), exact.acceleration(q, v), atol=1e-8, rtol=1e-8)
    torch.testing.assert_close(tab.mass_matrix(q), exact.mass_matrix(q), atol=1e-9, rtol=1e-9)
    assert tab.fallback_rows == 4  # two rows, in two calls
    extra = torch.ones_like(q)
    torch.testing.assert_close(tab.acceleration(q, v, extra_force=extra), exact.acceleration(q, v, extra_force=extra),
                               atol=1e-8, rtol=1e-8)


def test_within_continued_off_box_rows_off_the_box_read_its_edge_without_a_jet():
    """The closure's shooting tries rollouts that leave the box: there they read the table's edge (no jet)."""
    _, exact, _ = _nonlinear_setup()
    tab = TabulatedDynamics(exact, [-0.2, -0.2], [0.2, 0.2])
    off, edge = (torch.tensor([[1.1, -0.1]], dtype=torch.float64), torch.tensor([[0.2, -0.1]], dtype=torch.float64))
    v = torch.tensor([[0.5, 1.5]], dtype=torch.float64)
    with tab.continued_off_box():
        torch.testing.assert_close(tab.acceleration(off, v), tab.acceleration(edge, v))
        torch.testing.assert_close(tab.mass_matrix(off), tab.mass_matrix(edge))
    assert tab.fallback_rows == 0
    torch.testing.assert_close(tab.acceleration(off, v), exact.acceleration(off, v), atol=1e-8, rtol=1e-8)
    assert tab.fallback_rows == 1


def test_the_automatic_substeps_read_the_stiffness_of_a_tables_box_without_leaving_it():
    """box_frequency's grid stands inside the box by its difference stencil: none of its evaluations falls back to
    the exact pullback (at the edges some did: 1 000 of the grid's 5 000 rows at d = 4), and the frequency is the
    exact pullback's on that grid."""
    from lnf.integrators.base import box_frequency

    _, exact, _ = _nonlinear_setup()
    for low, high in (([-0.2, -0.2], [0.2, 0.2]), ([0.3, -0.6], [0.7, -0.5])):  # one box away from 0
        tab = TabulatedDynamics(exact, low, high, tol=1e-10)
        q = torch.tensor([[sum(b) / 2 for b in zip(low, high)]], dtype=torch.float64)
        omega = box_frequency(tab, q, torch.zeros_like(q))
        assert tab.fallback_rows == 0 and tab.evaluated_rows > 0
        assert omega == pytest.approx(box_frequency(_Boxed(exact, low, high), q, torch.zeros_like(q)), rel=1e-6)


class _Boxed:
    """The exact pullback with a table's box, for box_frequency."""

    def __init__(self, exact, low, high):
        self.exact, self.low, self.high = exact, low, high

    def acceleration(self, q, v, t=0.0):
        return self.exact.acceleration(q, v, t)


def test_a_rollout_read_off_the_box_is_told_how_far_along_which_code():
    _, exact, _ = _nonlinear_setup()
    tab = TabulatedDynamics(exact, [-0.2, -0.2], [0.2, 0.2])
    q = torch.tensor([[[0.1, 0.0], [0.15, 0.5]], [[-0.1, -0.3], [float("nan"), float("nan")]]], dtype=torch.float64)
    text = tab.off_box_text(q, 0.3)
    assert "30% of the rollout's evaluations" in text and "2.5 along code 2" in text and "code 1" not in text
    assert "dynamics.margin" in text
    assert "recorded codes stayed in the box" in tab.off_box_text(q[:1, :1], 0.05)


def test_tabulated_pendulum_rollout_follows_the_exact_one_and_conserves_its_energy(pendulum):
    exact = _pendulum_dynamics(pendulum)
    tab = TabulatedDynamics(exact, [-2.0], [2.0])
    q0 = torch.tensor([[1.2], [-0.4], [0.1]], dtype=torch.float64)
    v0 = torch.tensor([[0.5], [-1.0], [0.9]], dtype=torch.float64)
    midpoint = {"name": "implicit_midpoint", "order": 4}
    for q, extra in ((q0, 0.3 * q0), (q0 + 3.0, -q0)):  # the d = 1 path on the box and the fallback off it
        torch.testing.assert_close(tab.acceleration(q, v0, extra_force=extra),
                                   exact.acceleration(q, v0, extra_force=extra), atol=1e-7, rtol=1e-7)
        assert not torch.allclose(tab.acceleration(q, v0, extra_force=extra), tab.acceleration(q, v0))
    a = get_integrator(midpoint).integrate(tab, q0, v0, 0.05, 400)
    b = get_integrator(midpoint).integrate(exact, q0, v0, 0.05, 400)
    assert (a.q - b.q).abs().max() < 1e-6
    drift = [(E - E[:, :1]).abs().max() for E in (sum(tab.energies(a.q, a.v)), sum(exact.energies(b.q, b.v)))]
    assert drift[0] < 1e-4 * 6.4 and drift[0] < 1.01 * drift[1] + 1e-9  # the integrator's, not the table's


def test_tabulated_refuses_forced_scenes_unbounded_boxes_and_large_tables():
    _, exact, _ = _nonlinear_setup()
    with pytest.raises(ValueError, match="finite"):
        TabulatedDynamics(exact, [float("nan"), 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="max_table_points"):
        TabulatedDynamics(exact, [0.0, 0.0], [1.0, 1.0], min_nodes=300, max_nodes=400)
    exact.force_fn = object()  # a scene with damping / loads
    with pytest.raises(ValueError, match="conservative"):
        TabulatedDynamics(exact, [0.0, 0.0], [1.0, 1.0])


def test_a_separated_force_is_tabulated_beside_the_mass_and_potential():
    """A damped, loaded scene (the actuated cantilever's force −α ρ u̇ + A sin(2π f t) s(X) ê) tabulates: the table's
    accelerations and Hamiltonian forces equal the exact pullback's, on the box and off it, with and without loads."""
    from lnf.scenes.elastic import CantileverLoad

    _, exact, _ = _nonlinear_setup()
    exact.force_fn = CantileverLoad(exact.quadrature.weights, exact.points[:, 0] ** 2, [1.0], rho=1.3, damping=0.7)
    tab = TabulatedDynamics(exact, [-1.0, -1.0], [1.5, 1.0], tol=1e-10)
    assert tab.info["table_error"] <= 1e-10 and tab.channels == 3 + 1 + 3 + 1  # M̃, Ṽ, D̃, W
    q = torch.tensor([[0.3, -0.7], [1.1, 0.2], [2.0, 0.9]], dtype=torch.float64)  # the last row off the box
    v = torch.tensor([[0.5, 1.5], [-2.0, 0.7], [0.1, -0.3]], dtype=torch.float64)
    loads = torch.tensor([[0.8, 1.5], [2.0, 0.3], [-1.0, 2.0]], dtype=torch.float64)  # (A, f) per row
    for controls in (None, loads):
        exact.controls = tab.controls = controls
        for t in (0.0, 0.37):
            force = exact.terms(q, v, t).force
            assert force.abs().max() > 0.1  # the force matters
            torch.testing.assert_close(tab.acceleration(q, v, t), exact.acceleration(q, v, t), atol=1e-8, rtol=1e-8)
            for a, b in zip(tab.hamiltonian_derivatives(q, v, t), exact.hamiltonian_derivatives(q, v, t)):
                torch.testing.assert_close(a, b, atol=1e-8, rtol=1e-8)
    assert tab.fallback_rows > 0


def test_force_separates_says_which_forced_scenes_a_table_holds():
    from lnf.scenes.base import GeneralizedForce
    from lnf.scenes.elastic import ElasticCantilever

    class Unseparated:  # a forced scene whose GeneralizedForce says nothing of its form
        is_conservative, bounds = False, [[0.0, 1.0]]

        def generalized_force(self, quadrature):
            return GeneralizedForce(quadrature.weights)

    assert force_separates(ElasticCantilever())  # conservative
    assert force_separates(ElasticCantilever(damping=0.2, load_amplitude_range=(0.1, 0.3)))
    assert not force_separates(Unseparated())


def test_model_tracks_training_codes_and_tabulates_on_their_range(pendulum, tmp_path):
    from lnf.model import LagrangianNeuralField

    model = LagrangianNeuralField(pendulum, width=16, hyper_width=8)
    model.set_tabulation({"margin": 0.5})
    with pytest.raises(ValueError, match="range of the training codes"):
        model.dynamics()
    model.track_code_range(torch.tensor([[0.2], [-0.1]]), reset=True)
    model.track_code_range(torch.tensor([[0.4]]))
    assert model.code_low.item() == pytest.approx(-0.1) and model.code_high.item() == pytest.approx(0.4)
    dyn = model.dynamics()
    assert isinstance(dyn, TabulatedDynamics) and model.dynamics() is dyn  # cached
    assert dyn.low[0] == pytest.approx(-0.35) and dyn.high[0] == pytest.approx(0.65)
    q = torch.tensor([[0.0], [0.3]])
    v = torch.tensor([[1.0], [-0.5]])
    exact = model.lagrangian_dynamics()
    torch.testing.assert_close(dyn.acceleration(q, v), exact.acceleration(q, v), atol=1e-4, rtol=1e-4)
    with torch.no_grad():
        model.field.hyper[-1].bias.add_(0.01)
    assert model.dynamics() is not dyn  # parameters changed: rebuilt
    with pytest.raises(ValueError, match="unknown keys"):
        model.set_tabulation({"nodes": 3})
    # a state dict without the range (older checkpoints) loads with an unknown range
    state = {k: v for k, v in model.state_dict().items() if not k.startswith("code_")}
    fresh = LagrangianNeuralField(pendulum, width=16, hyper_width=8)
    fresh.load_state_dict(state)
    assert torch.isnan(fresh.code_low).all()


def test_a_table_too_coarse_to_trust_leaves_the_model_on_the_exact_pullback(pendulum, caplog, monkeypatch):
    """A table whose error stays above TABLE_MAX_ERROR (its nodes capped) is not used: the model rolls out on the
    exact pullback and says why, naming the error; one within it is used as before."""
    from lnf import tabulated
    from lnf.model import LagrangianNeuralField
    from lnf.dynamics import ReducedDynamics

    model = LagrangianNeuralField(pendulum, width=16, hyper_width=8)
    model.track_code_range(torch.tensor([[-2.0], [2.0]]), reset=True)
    model.set_tabulation({"min_nodes": 2, "max_nodes": 2, "margin": 0.0})  # 2 nodes cannot hold sin over ±2 rad
    with caplog.at_level("WARNING", logger="lnf.model"):
        dyn = model.dynamics()
    assert isinstance(dyn, ReducedDynamics) and not isinstance(dyn, TabulatedDynamics)
    assert "off the exact pullback" in caplog.text and "TABLE_MAX_ERROR" in caplog.text
    monkeypatch.setattr(tabulated, "TABLE_MAX_ERROR", float("inf"))  # the same table, trusted: used
    model.set_tabulation({"min_nodes": 2, "max_nodes": 2, "margin": 0.01})
    assert isinstance(model.dynamics(), TabulatedDynamics)


def test_a_table_too_rough_at_its_point_cap_grows_past_it_before_it_is_left(pendulum, monkeypatch):
    """A table stops at dynamics.max_table_points when it is within TABLE_MAX_ERROR there; one still more than
    TABLE_MAX_ERROR off may grow to TABLE_ROUGH_GROWTH times as many nodes."""
    from lnf import tabulated
    from lnf.model import LagrangianNeuralField

    exact = LagrangianNeuralField(pendulum, width=16, hyper_width=8).lagrangian_dynamics()

    def nodes() -> int:  # sin over ±2 rad: 2 nodes are far more than 1 % off
        return TabulatedDynamics(exact, [-2.0], [2.0], min_nodes=2, max_table_points=2).info["table_nodes"]

    assert nodes() == 2 * tabulated.TABLE_ROUGH_GROWTH  # 8 nodes, past the cap of 2
    monkeypatch.setattr(tabulated, "TABLE_ROUGH_GROWTH", 1)
    assert nodes() == 2
    monkeypatch.setattr(tabulated, "TABLE_ROUGH_GROWTH", 4)
    monkeypatch.setattr(tabulated, "TABLE_MAX_ERROR", float("inf"))  # any error trusted: the cap holds
    assert nodes() == 2


def test_a_tabulated_rollout_runs_on_one_torch_thread_and_restores_the_callers_count(pendulum):
    from lnf.integrators.rk4 import RK4
    from lnf.model import LagrangianNeuralField

    seen = []

    class Recording(RK4):  # notes the thread count the integration runs on
        def integrate(self, *args, **kwargs):
            seen.append(torch.get_num_threads())
            return super().integrate(*args, **kwargs)

    model = LagrangianNeuralField(pendulum, width=16, hyper_width=8)
    model.track_code_range(torch.tensor([[-0.3], [0.3]]), reset=True)
    q0, v0 = torch.tensor([[0.1]]), torch.zeros(1, 1)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        exact = model.rollout(q0, v0, 0.05, 3, integrator=Recording())
        model.set_tabulation({})
        table = model.rollout(q0, v0, 0.05, 3, integrator=Recording())
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(threads)
    assert seen == [2, 1]  # the exact pullback keeps the caller's threads, the table runs on one
    torch.testing.assert_close(table.q, exact.q, atol=1e-4, rtol=0)


def test_the_off_box_parts_from_one_jet_equal_forward_mode_differentiation_of_the_mass():
    """∂M̃/∂q̃ from J and H of one second-order jet (the flat kinetic energy) against jvp of M̃."""
    _, exact, _ = _nonlinear_setup()
    tab = TabulatedDynamics(exact, [-0.2, -0.2], [0.2, 0.2])
    q = torch.tensor([[1.1, 0.2], [-0.5, 0.9], [0.3, -1.4]], dtype=torch.float64)
    one_jet = tab._exact_parts(q)
    assert one_jet.shape == (3, 3, 4)  # (B, 1 + d, M̃'s 3 entries + Ṽ)
    eye = torch.eye(2, dtype=q.dtype)
    slope = torch.stack([torch.func.jvp(exact.mass_matrix, (q,), (eye[k].expand_as(q),))[1] for k in range(2)], 1)
    mass, potential, gravity = exact.static_terms(q)
    a, b = zip(*tab.pairs)
    by_jvp = torch.cat([torch.cat([mass[:, a, b], potential[:, None]], -1)[:, None],
                        torch.cat([slope[:, :, a, b], gravity[:, :, None]], -1)], 1)
    torch.testing.assert_close(one_jet, by_jvp, atol=1e-10, rtol=1e-10)


def test_a_table_that_misses_its_tolerance_says_the_pullback_is_not_smooth(pendulum, caplog):
    """dynamics.tol out of reach of the largest table: a warning that names the error and, at d = 1, the range of
    the stiffness Ṽ''/M̃ on the box (the pendulum's: −1 … 1 on [−2.5, 2.5] up to its mass's scale)."""
    exact = _pendulum_dynamics(pendulum)
    with caplog.at_level("WARNING", logger="lnf.tabulated"):
        TabulatedDynamics(exact, [-2.5], [2.5], tol=1e-300, min_nodes=8, max_nodes=8)
    text = caplog.text
    assert "not smooth in q̃" in text and "8 nodes per axis" in text and "changes sign" in text
    caplog.clear()
    with caplog.at_level("WARNING", logger="lnf.tabulated"):
        TabulatedDynamics(exact, [-2.5], [2.5])  # the default tolerance is met: nothing to say
    assert "not smooth" not in caplog.text



@pytest.mark.parametrize("pod_subspace", [True, False])
def test_a_tables_box_gives_a_barely_moving_pod_code_a_floor_of_the_largest_span(monkeypatch, pod_subspace):
    """POD codes share one unit: a code that barely moves in training gets a margin of CODE_SPAN_FLOOR of the largest
    span (the soft body's 4th, 0.3 % of its 1st, ran 1.6 to 4.1 half-widths off a box of its own span, into the exact
    pullback); a SIREN's codes, each in its own unit, keep their own spans."""
    from lnf import tabulated
    from lnf.closure import CODE_SPAN_FLOOR
    from lnf.model import LagrangianNeuralField
    from lnf.scenes import ElasticCantilever

    class Built(Exception):
        pass

    def capture(exact, low, high, **kwargs):
        raise Built(low, high)

    model = LagrangianNeuralField(ElasticCantilever(mesh=(4, 2)), latent_dim=2, width=16, hyper_width=8, w0=3.0,
                                  pod_subspace=pod_subspace, pod_degree=4)
    model.track_code_range(torch.tensor([[-2.0, -0.003], [2.0, 0.003]]), reset=True)
    model.set_tabulation({"margin": 0.25})
    monkeypatch.setattr(tabulated, "TabulatedDynamics", capture)
    with pytest.raises(Built) as built:
        model.dynamics()
    low, high = built.value.args
    assert low[0] == pytest.approx(-3.0) and high[0] == pytest.approx(3.0)  # 0.25 of the span 4 on each side
    pad = 0.25 * (CODE_SPAN_FLOOR * 4.0 if pod_subspace else 0.006)
    assert low[1] == pytest.approx(-0.003 - pad) and high[1] == pytest.approx(0.003 + pad)
