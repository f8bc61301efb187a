"""HelmholtzModes: counts from the seed paper, orthonormality on H x H by exact quadrature,
reciprocity, isotropy, and the printed low-order formulas (with the paper's errors)."""

import numpy as np
import pytest

from basis import HelmholtzModes, HemiZernike, from_angles


def _pairs_rule(order):
    """Product of two exact hemisphere rules: exact for every product of two modes."""
    rule = HemiZernike(order).exact_rule()
    n = rule.weights.size
    wi = np.repeat(rule.points, n, axis=0)
    wo = np.tile(rule.points, (n, 1))
    return wi, wo, np.repeat(rule.weights, n) * np.tile(rule.weights, n)


def _unit_upper(rng, n):
    w = rng.normal(size=(n, 3))
    w[:, 2] = np.abs(w[:, 2])
    return w / np.linalg.norm(w, axis=1, keepdims=True)


@pytest.mark.parametrize("order, size", [(0, 1), (2, 5), (4, 14), (8, 55), (16, 285)])
def test_isotropic_counts_match_paper(order, size):
    # Koenderink et al. sec. 3.3: "five for order two, fourteen for order four, fiftyfive for
    # order eight ... 285 basis functions for order sixteen"
    assert HelmholtzModes(order).size == size


@pytest.mark.parametrize("order", [0, 1, 3, 5])
def test_general_count(order):
    s = (order + 1) * (order + 2) // 2
    assert HelmholtzModes(order, isotropic=False).size == s * (s + 1) // 2


def test_indices_rules_and_prefix():
    idx = HelmholtzModes(9).indices
    n, m, l = idx.T
    assert np.all((n >= m) & (m >= l) & (l >= 0))
    assert np.all((n - l) % 2 == 0) and np.all((m - l) % 2 == 0)
    assert len({tuple(r) for r in idx}) == len(idx)
    np.testing.assert_array_equal(HelmholtzModes(5).indices, idx[: HelmholtzModes(5).size])
    gen = HelmholtzModes(3, isotropic=False)
    np.testing.assert_array_equal(HelmholtzModes(2, isotropic=False).indices,
                                  gen.indices[: HelmholtzModes(2, isotropic=False).size])


@pytest.mark.parametrize("order, isotropic", [(0, True), (2, True), (5, True), (8, True),
                                               (2, False), (3, False)])
def test_orthonormal_on_hxh(order, isotropic):
    modes = HelmholtzModes(order, isotropic=isotropic)
    wi, wo, w = _pairs_rule(order)
    v = modes.eval(wi, wo)
    gram = v.T @ (w[:, None] * v)
    # exact rule: only rounding remains; 1e-13 is ~500 eps for sums of ~1e5 terms
    np.testing.assert_allclose(gram, np.eye(modes.size), rtol=0, atol=1e-13)


@pytest.mark.parametrize("isotropic", [True, False])
def test_reciprocal(rng, isotropic):
    modes = HelmholtzModes(4, isotropic=isotropic)
    wi, wo = _unit_upper(rng, 200), _unit_upper(rng, 200)
    # the symmetrised sum is computed in the same order both ways: exact equality
    np.testing.assert_array_equal(modes.eval(wi, wo), modes.eval(wo, wi))


def test_isotropic_modes_depend_on_azimuth_difference_only(rng):
    modes = HelmholtzModes(6)
    ti, to = rng.uniform(0, np.pi / 2, 50), rng.uniform(0, np.pi / 2, 50)
    pi_, po = rng.uniform(-np.pi, np.pi, 50), rng.uniform(-np.pi, np.pi, 50)
    shift = rng.uniform(-np.pi, np.pi, 50)
    a = modes.eval(from_angles(ti, pi_), from_angles(to, po))
    b = modes.eval(from_angles(ti, pi_ + shift), from_angles(to, po + shift))
    c = modes.eval(from_angles(ti, -pi_), from_angles(to, -po))  # mirror: |dphi| only
    # values are O(1); rounding of the rotated vectors moves them by ~1e-15
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a, c, rtol=0, atol=1e-12)


def test_printed_low_order_modes():
    """Seed sec. 3.3 prints unnormalised order-2 modes; three agree, two do not."""
    modes = HelmholtzModes(2)
    t1, t2, dphi = 0.7, 1.1, 0.4
    v = modes.eval(from_angles(t1, dphi), from_angles(t2, 0.0)) * modes.paper_norms
    c1, c2 = np.cos(t1), np.cos(t2)
    s1, s2 = np.sin(t1 / 2), np.sin(t2 / 2)
    got = dict(zip(map(tuple, modes.indices.tolist()), v, strict=True))
    # agree with the paper as printed (tolerance: rounding of O(1) values)
    assert got[(0, 0, 0)] == pytest.approx(1 / np.pi, abs=1e-14)
    assert got[(1, 1, 1)] == pytest.approx(4 / np.pi * s1 * s2 * np.cos(dphi), abs=1e-14)
    assert got[(2, 2, 2)] == pytest.approx(3 / np.pi * (1 - c1) * (1 - c2) * np.cos(2 * dphi),
                                           abs=1e-14)
    # printed S_20^0 has the opposite sign; printed S_22^0 is not a mode
    assert got[(2, 0, 0)] == pytest.approx(-np.sqrt(3) / np.pi * (c1 + c2 - 1), abs=1e-14)
    assert got[(2, 2, 0)] == pytest.approx(3 / np.pi * (1 - 2 * c1) * (1 - 2 * c2), abs=1e-14)
    assert abs(got[(2, 2, 0)] - 3 / np.pi * (1 + c1) * (1 + c2)) > 1.0


def test_lambert_is_first_mode():
    # f = 1/pi = 2 K_0^0 K_0^0 = 2 * mode (0, 0, 0): the paper's "initial term"
    v = HelmholtzModes(0).eval(from_angles(0.3, 0.1), from_angles(1.2, 2.0))
    assert v[0] * 2 == pytest.approx(1 / np.pi, rel=1e-15)


def test_batch_shapes(rng):
    modes = HelmholtzModes(2)
    wi = _unit_upper(rng, 6).reshape(2, 3, 3)
    assert modes.eval(wi, wi).shape == (2, 3, modes.size)
    assert modes.eval(wi[0, 0], _unit_upper(rng, 7)).shape == (7, modes.size)
    assert modes.eval(np.empty((0, 3)), np.empty((0, 3))).shape == (0, modes.size)


@pytest.mark.parametrize("args, exc, match", [
    ((-1,), ValueError, "order must be >= 0"),
    ((2.0,), TypeError, "order must be an integer"),
    ((61,), ValueError, "order must be <= 60 for isotropic"),
    ((25, False), ValueError, "order must be <= 24 for general"),
    ((2, "yes"), TypeError, "isotropic must be True or False"),
])
def test_bad_construction(args, exc, match):
    with pytest.raises(exc, match=match):
        HelmholtzModes(*args)


def test_bad_eval():
    modes = HelmholtzModes(2)
    up = np.array([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="wo must lie in the upper hemisphere"):
        modes.eval(up, [0.0, 0.0, -1.0])
    with pytest.raises(ValueError, match="broadcastable batch shapes"):
        modes.eval(np.tile(up, (3, 1)), np.tile(up, (4, 1)))
    with pytest.raises(ValueError, match="paper_norms is defined for the isotropic"):
        _ = HelmholtzModes(2, isotropic=False).paper_norms
