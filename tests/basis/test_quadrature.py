"""Product quadrature rules: structure, total weight, exactness at the stated degree for
monomials x^a y^b z^c (closed form) and failure one degree beyond, integrate(), bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from basis import HemisphereRule, hemisphere_rule, sphere_rule

EPS = float(np.finfo(np.float64).eps)
RULES = {"hemisphere": hemisphere_rule, "sphere": sphere_rule}


def _monomial_integral(a, b, c, domain):
    """int x^a y^b z^c d omega over the upper hemisphere or the sphere, in closed form.

    Azimuth: int_0^2pi cos^a sin^b = 2 G((a+1)/2) G((b+1)/2) / G((a+b)/2 + 1) for a, b even,
    else 0. Polar: int_0^1 (1 - z^2)^((a+b)/2) z^c dz = G((c+1)/2) G((a+b)/2 + 1)
    / (2 G((a+b+c+3)/2)); the sphere doubles it for even c and cancels it for odd c.
    """
    if a % 2 or b % 2:
        return 0.0
    g = math.gamma
    azimuth = 2 * g((a + 1) / 2) * g((b + 1) / 2) / g((a + b) / 2 + 1)
    polar = g((c + 1) / 2) * g((a + b) / 2 + 1) / (2 * g((a + b + c + 3) / 2))
    if domain == "sphere":
        polar *= 2.0 if c % 2 == 0 else 0.0
    return azimuth * polar


def _monomials(degree):
    return [(a, b, d - a - b) for d in range(degree + 1) for a in range(d + 1)
            for b in range(d - a + 1)]


def _error(rule, a, b, c):
    x, y, z = rule.points.T
    return abs(rule.integrate(x**a * y**b * z**c) - _monomial_integral(a, b, c, rule.domain))


def test_closed_form_reference():
    # sanity of the reference itself against integrals known by symmetry or by hand
    assert _monomial_integral(0, 0, 0, "hemisphere") == pytest.approx(2 * np.pi, rel=1e-15)
    assert _monomial_integral(0, 0, 0, "sphere") == pytest.approx(4 * np.pi, rel=1e-15)
    assert _monomial_integral(0, 0, 3, "hemisphere") == pytest.approx(np.pi / 2, rel=1e-15)
    for a, b, c in [(2, 0, 0), (0, 2, 0), (0, 0, 2)]:  # x^2 + y^2 + z^2 = 1: each a third
        assert _monomial_integral(a, b, c, "hemisphere") == pytest.approx(2 * np.pi / 3,
                                                                          rel=1e-15)
    # x^2 y^2 z^2 on the sphere: 4 pi / 105
    assert _monomial_integral(2, 2, 2, "sphere") == pytest.approx(4 * np.pi / 105, rel=1e-15)


# -- structure --------------------------------------------------------------------------------

@pytest.mark.parametrize("domain", ["hemisphere", "sphere"])
@pytest.mark.parametrize("n_theta, n_phi", [(1, 1), (2, 3), (7, 4), (50, 101), (1001, 3)])
def test_structure_and_total_weight(domain, n_theta, n_phi):
    rule = RULES[domain](n_theta, n_phi)
    assert isinstance(rule, HemisphereRule) and rule.domain == domain
    assert rule.shape == (n_theta, n_phi)
    assert rule.points.shape == (n_theta * n_phi, 3) and rule.weights.shape == (n_theta * n_phi,)
    assert (rule.degree_z, rule.degree_phi) == (2 * n_theta - 1, n_phi - 1)
    # theta-major: all azimuths of the first z node first
    np.testing.assert_array_equal(rule.points[:, 2], np.repeat(rule.z, n_phi))
    np.testing.assert_allclose(rule.phi, 2 * np.pi * np.arange(n_phi) / n_phi, rtol=0, atol=0)
    # unit vectors up to the rounding of sqrt, cos and sin
    np.testing.assert_allclose(np.linalg.norm(rule.points, axis=1), 1.0, rtol=0, atol=4 * EPS)
    # Gauss nodes are interior: no node on the pole or on the horizon
    lo = 0.0 if domain == "hemisphere" else -1.0
    assert np.all(rule.z > lo) and np.all(rule.z < 1.0) and np.all(np.diff(rule.z) > 0)
    assert np.all(rule.weights > 0)
    # total solid angle; a sum of n positive terms each accurate to a few eps
    total = 2 * np.pi if domain == "hemisphere" else 4 * np.pi
    assert rule.weights.sum() == pytest.approx(total, rel=1e-14)


def test_single_node_rule():
    rule = hemisphere_rule(1, 1)
    # one Gauss node at the midpoint z = 1/2 with the whole solid angle
    np.testing.assert_allclose(rule.points, [[np.sqrt(0.75), 0.0, 0.5]], rtol=0, atol=EPS)
    np.testing.assert_allclose(rule.weights, [2 * np.pi], rtol=EPS, atol=0)


# -- exactness --------------------------------------------------------------------------------

@pytest.mark.parametrize("domain", ["hemisphere", "sphere"])
@pytest.mark.parametrize("n_theta, n_phi", [(1, 1), (1, 2), (2, 3), (3, 6), (4, 5), (5, 12),
                                            (8, 17)])
def test_exact_to_stated_degree_and_not_beyond(domain, n_theta, n_phi):
    rule = RULES[domain](n_theta, n_phi)
    degree = min(rule.degree_z, rule.degree_phi)
    for a, b, c in _monomials(degree):
        # integrals are <= 4 pi; a weighted sum of <= 204 terms rounds at ~ 1e-14
        assert _error(rule, a, b, c) <= 1e-13, (a, b, c)
    # one degree beyond, some monomial is integrated wrongly: Gauss-Legendre fails on
    # z^(2 n_theta) and the equispaced azimuths alias cos(n_phi phi) onto the constant
    beyond = max(_error(rule, a, b, c) for a, b, c in _monomials(degree + 1)
                 if a + b + c == degree + 1)
    assert beyond > 1e-10, beyond  # >= 1000x the rounding bound above: a real quadrature error


@pytest.mark.parametrize("domain", ["hemisphere", "sphere"])
def test_degrees_are_separate(domain):
    # exactness is per variable: z^c up to degree_z even with a single azimuth, and
    # trigonometric terms up to degree_phi even with a single z node
    rule = RULES[domain](6, 1)
    z = rule.points[:, 2]
    for c in range(rule.degree_z + 1):
        assert _error(rule, 0, 0, c) <= 1e-14, c  # one sum of 6 terms <= 2 pi
    assert abs(rule.integrate(z ** (rule.degree_z + 1))
               - _monomial_integral(0, 0, rule.degree_z + 1, domain)) > 1e-9
    rule = RULES[domain](1, 9)
    phi = np.arctan2(rule.points[:, 1], rule.points[:, 0])
    for k in range(1, rule.degree_phi + 1):
        # int cos(k phi) = int sin(k phi) = 0; sums of 9 terms of size 4 pi / 9 ~ 1.4 whose
        # argument k phi (k <= 8, |phi| <= pi) carries an absolute rounding of ~ 8 pi eps:
        # bound 9 * 1.4 * 8 pi eps ~ 7e-14 (seen: 1.0e-14)
        assert abs(rule.integrate(np.cos(k * phi))) <= 1e-13
        assert abs(rule.integrate(np.sin(k * phi))) <= 1e-13
    total = rule.weights.sum()
    # cos(9 phi) is 1 at every node: the rule returns the total weight instead of 0
    assert rule.integrate(np.cos(9 * phi)) == pytest.approx(total, rel=1e-12)


def test_integrate_shapes_and_linearity(rng):
    rule = hemisphere_rule(3, 4)
    n = rule.weights.size
    v = rng.normal(size=(n, 2, 3))
    got = rule.integrate(v)
    assert got.shape == (2, 3)
    # the same weighted sum, term by term
    np.testing.assert_allclose(got, np.einsum("i,ijk->jk", rule.weights, v), rtol=1e-14,
                               atol=1e-14)
    assert np.ndim(rule.integrate(np.ones(n))) == 0
    assert rule.integrate(list(np.ones(n))) == pytest.approx(2 * np.pi, rel=1e-14)
    assert rule.integrate(np.ones((n, 5))).shape == (5,)


# -- bad input --------------------------------------------------------------------------------

@pytest.mark.parametrize("make", [hemisphere_rule, sphere_rule])
@pytest.mark.parametrize("args, exc, match", [
    ((0, 3), ValueError, r"n_theta and n_phi must be >= 1, got 0 and 3"),
    ((3, 0), ValueError, r"n_theta and n_phi must be >= 1, got 3 and 0"),
    ((-1, 3), ValueError, r"n_theta must be >= 0, got -1"),
    ((3, -2), ValueError, r"n_phi must be >= 0, got -2"),
    ((2.0, 3), TypeError, r"n_theta must be an integer, got 2\.0"),
    (("2", 3), TypeError, r"n_theta must be an integer, got '2'"),
    ((True, 3), TypeError, r"n_theta must be an integer, got True"),
    ((3, 1.5), TypeError, r"n_phi must be an integer, got 1\.5"),
    ((3, None), TypeError, r"n_phi must be an integer, got None"),
])
def test_bad_sizes(make, args, exc, match):
    with pytest.raises(exc, match=match):
        make(*args)


def test_numpy_integers_accepted():
    assert hemisphere_rule(np.int64(2), np.int32(3)).shape == (2, 3)
