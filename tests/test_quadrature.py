import pytest
import torch

from lnf.quadrature import GaussLegendre, GivenPoints, Quadrature, UniformGrid, gauss_legendre_rule, uniform_grid


def _integrate_monomial(quad, px, py):
    x, y = quad.points.double().T
    return float((quad.weights.double() * x**px * y**py).sum())


def _exact(px, py, lo=-1.0, hi=1.0):
    def one(p):
        return (hi ** (p + 1) - lo ** (p + 1)) / (p + 1)
    return one(px) * one(py)


@pytest.mark.parametrize("order", [1, 2, 4, 8, 12])
def test_gauss_legendre_exact_to_stated_degree(order):
    quad = gauss_legendre_rule(order, [[-1, 1], [-1, 1]])
    assert len(quad) == order**2
    deg = 2 * order - 1
    for px in range(deg + 1):
        for py in (0, deg - px, deg):
            assert _integrate_monomial(quad, px, py) == pytest.approx(_exact(px, py), abs=2e-5)


def test_gauss_legendre_not_exact_beyond_degree():
    quad = gauss_legendre_rule(3, [[-1, 1], [-1, 1]])
    assert abs(_integrate_monomial(quad, 6, 0) - _exact(6, 0)) > 1e-3


def test_gauss_legendre_on_other_bounds():
    quad = gauss_legendre_rule((3, 5), [[0, 2], [-3, 1]])
    x, y = quad.points.double().T
    assert float(quad.weights.sum()) == pytest.approx(8.0, rel=1e-6)
    assert float((quad.weights.double() * x**5 * y**9).sum()) == pytest.approx(
        (2**6 / 6) * ((1 - 3**10) / 10), rel=1e-5)


def test_uniform_grid_is_second_order():
    errs = []
    for n in (8, 16, 32):
        quad = uniform_grid(n, [[-1, 1], [-1, 1]])
        errs.append(abs(_integrate_monomial(quad, 4, 2) - _exact(4, 2)))
    assert errs[0] / errs[1] == pytest.approx(4.0, rel=0.1)
    assert errs[1] / errs[2] == pytest.approx(4.0, rel=0.1)


def test_rules_build_and_describe():
    for rule in (GaussLegendre(4), UniformGrid(8), GivenPoints([[0.0, 0.0]], [4.0])):
        quad = rule.build([[-1, 1], [-1, 1]])
        assert float(quad.weights.sum()) == pytest.approx(4.0, rel=1e-6)
        assert rule.describe()


def test_bad_quadratures_raise():
    with pytest.raises(ValueError, match="no points"):
        Quadrature(torch.zeros(0, 2), torch.zeros(0))
    with pytest.raises(ValueError, match="resolution"):
        UniformGrid(0).build([[-1, 1], [-1, 1]])
    with pytest.raises(ValueError, match="order"):
        GaussLegendre(0).build([[-1, 1], [-1, 1]])
    with pytest.raises(ValueError, match="dim"):
        GivenPoints([[0.0, 0.0, 0.0]], [1.0]).build([[-1, 1], [-1, 1]])
    with pytest.raises(ValueError, match="bounds"):
        GaussLegendre(2).build([[1, -1]])
