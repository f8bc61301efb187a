"""CoefficientMatrix: exact representations (Lambert), albedo against quadrature, reciprocity,
isotropic storage, truncation, modes round trip, channels and bad input."""

import numpy as np
import pytest

from basis import (
    CoefficientMatrix,
    HelmholtzModes,
    HemiHarmonics,
    HemiZernike,
    SphericalHarmonics,
    from_angles,
    hemisphere_rule,
)


def _unit_upper(rng, n):
    w = rng.normal(size=(n, 3))
    w[:, 2] = np.abs(w[:, 2])
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def _random_symmetric(rng, size, channels=None):
    shape = (size, size) if channels is None else (channels, size, size)
    a = rng.normal(size=shape)
    return a + np.swapaxes(a, -1, -2)


def lambert_zernike(albedo):
    """f = a/pi = 2a K_0^0 K_0^0, one coefficient in HemiZernike, quantity 'f'."""
    zb = HemiZernike(4)
    m = np.zeros((zb.size, zb.size))
    m[0, 0] = 2 * albedo
    return CoefficientMatrix(zb, m, quantity="f")


def lambert_westin(albedo):
    """f cos cos = (a/pi) z_i z_o = (2a/3) b_10 b_10 with b_10 = sqrt(2) Y_10 (Westin's
    4a/3 for full-sphere coefficients, divided by the factor 2 of the hemisphere basis)."""
    hb = HemiHarmonics(5)
    m = np.zeros((hb.size, hb.size))
    k = hb.index(1, 0)
    m[k, k] = 2 * albedo / 3
    return CoefficientMatrix(hb, m, quantity="f_cos")


@pytest.mark.parametrize("make", [lambert_zernike, lambert_westin])
def test_lambert_exact(make, rng):
    cm = make(0.7)
    wi, wo = _unit_upper(rng, 100), _unit_upper(rng, 100)
    # one coefficient: only rounding (values ~0.2, sums of a few terms)
    np.testing.assert_allclose(cm.eval(wi, wo), 0.7 / np.pi, rtol=1e-13)
    grazing = from_angles(np.radians([0.0, 45.0, 89.0, 89.9, 90.0]), 0.3)
    np.testing.assert_allclose(cm.albedo(grazing), 0.7, rtol=1e-12)
    assert cm.is_isotropic
    assert cm.nbytes < cm.matrix.nbytes


def test_horizon_limit_with_odd_harmonics():
    # q vanishes on the horizon for the odd completion; at z = 0 eval returns the limit
    cm = lambert_westin(0.5)
    assert cm.eval([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]) == pytest.approx(0.5 / np.pi, rel=1e-12)


def test_below_horizon_is_zero(rng):
    cm = CoefficientMatrix(HemiZernike(3), _random_symmetric(rng, 10), quantity="f")
    v = cm.eval([[0, 0, 1.0], [0, 0, -1.0], [0.6, 0, -0.8]], [0, 0, 1.0])
    assert v[0] != 0 and v[1] == 0 and v[2] == 0
    assert cm.albedo([0.0, 0.0, -1.0]) == 0


@pytest.mark.parametrize("basis", [HemiZernike(5), HemiHarmonics(6), HemiHarmonics(5, "even")])
@pytest.mark.parametrize("quantity", ["f", "f_cos"])
def test_reciprocal_and_albedo_against_quadrature(basis, quantity, rng):
    cm = CoefficientMatrix(basis, _random_symmetric(rng, basis.size), quantity=quantity)
    wi, wo = _unit_upper(rng, 50), _unit_upper(rng, 50)
    # b_i^T M b_o vs b_o^T M b_i: different summation order, values ~10
    np.testing.assert_allclose(cm.eval(wi, wo), cm.eval(wo, wi), rtol=1e-12, atol=1e-12)
    # albedo: for 'f' the integrand f cos is polynomial-like of degree <= order + 1 in z for
    # HemiHarmonics, and of degree <= order/2 + 1 in rho^2 for Zernike: this rule is exact
    wi = wi[:5] if quantity == "f" else wi[:5] * [1, 1, 1]
    rule = hemisphere_rule(basis.order + 2, 2 * basis.order + 2)
    integrand = cm.eval(wi[:, None, :], rule.points) * rule.points[:, 2]
    if quantity == "f_cos":  # f cos(theta_o) = q / cos(theta_i): also exact per direction
        pass
    expect = integrand @ rule.weights
    np.testing.assert_allclose(cm.albedo(wi), expect, rtol=1e-11, atol=1e-11)


def test_symmetry_required_and_symmetrize(rng):
    zb = HemiZernike(2)
    a = rng.normal(size=(zb.size, zb.size))
    with pytest.raises(ValueError, match=r"matrix must be symmetric \(reciprocity\)"):
        CoefficientMatrix(zb, a)
    cm = CoefficientMatrix(zb, a, symmetrize=True)
    np.testing.assert_array_equal(cm.matrix, 0.5 * (a + a.T))


def test_isotropic_detection_and_projection(rng):
    zb = HemiZernike(4)
    dense = CoefficientMatrix(zb, _random_symmetric(rng, zb.size))
    assert not dense.is_isotropic
    iso = dense.to_isotropic()
    assert iso.is_isotropic
    # the projection is the average over a common rotation of both directions; a uniform
    # rule with more angles than twice the highest azimuthal order averages exactly
    wi, wo = _unit_upper(rng, 20), _unit_upper(rng, 20)
    angles = 2 * np.pi * np.arange(9) / 9

    def rot(w, a):
        c, s = np.cos(a), np.sin(a)
        return np.stack([c * w[:, 0] - s * w[:, 1], s * w[:, 0] + c * w[:, 1], w[:, 2]], -1)

    avg = np.mean([dense.eval(rot(wi, a), rot(wo, a)) for a in angles], axis=0)
    # mirror symmetry is also part of isotropy (|dphi|): average over the reflection too
    flip = np.array([1.0, -1.0, 1.0])
    avg = 0.5 * (avg + np.mean([dense.eval(rot(wi * flip, a), rot(wo * flip, a))
                                for a in angles], axis=0))
    np.testing.assert_allclose(iso.eval(wi, wo), avg, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="matrix is not isotropic"):
        CoefficientMatrix(zb, dense.matrix, isotropic=True)
    assert not CoefficientMatrix(zb, iso.matrix, isotropic=False).is_isotropic
    assert CoefficientMatrix(zb, iso.matrix).is_isotropic


def test_isotropic_storage_is_smaller(rng):
    zb = HemiZernike(8)
    iso = CoefficientMatrix(zb, _random_symmetric(rng, zb.size)).to_isotropic()
    expect = sum(((8 - m) // 2 + 1) ** 2 for m in range(9)) * 8
    assert iso.nbytes == expect
    assert iso.nbytes < zb.size**2 * 8 / 10


@pytest.mark.parametrize("iso", [True, False])
def test_truncate_is_prefix(rng, iso):
    zb = HemiZernike(6)
    cm = CoefficientMatrix(zb, _random_symmetric(rng, zb.size))
    if iso:
        cm = cm.to_isotropic()
    t = cm.truncate(3)
    assert t.basis == HemiZernike(3) and t.is_isotropic == iso
    np.testing.assert_array_equal(t.matrix, cm.matrix[:10, :10])
    with pytest.raises(ValueError, match="order must be <= 6"):
        cm.truncate(7)


@pytest.mark.parametrize("isotropic", [True, False])
def test_modes_round_trip_and_parseval(rng, isotropic):
    hm = HelmholtzModes(5, isotropic=isotropic)
    a = rng.normal(size=hm.size)
    cm = CoefficientMatrix.from_modes(a, 5, isotropic=isotropic)
    np.testing.assert_allclose(cm.to_modes(isotropic=isotropic), a, rtol=0, atol=1e-15)
    # Parseval: both expansions are orthonormal, so the squared norms agree
    assert np.sum(a**2) == pytest.approx(np.sum(cm.matrix**2), rel=1e-13)
    # and the matrix evaluates to the mode sum (for quantity f_cos: q = f cos cos)
    wi, wo = _unit_upper(rng, 30), _unit_upper(rng, 30)
    q = cm.eval(wi, wo, min_cos=1e-9) * wi[:, 2] * wo[:, 2]
    np.testing.assert_allclose(q, hm.eval(wi, wo) @ a, rtol=1e-11, atol=1e-12)


def test_modes_errors(rng):
    hb = HemiHarmonics(3)
    with pytest.raises(ValueError, match="to_modes needs a HemiZernike basis"):
        CoefficientMatrix(hb, _random_symmetric(rng, hb.size)).to_modes()
    zb = HemiZernike(3)
    with pytest.raises(ValueError, match="matrix is not isotropic; use to_isotropic"):
        CoefficientMatrix(zb, _random_symmetric(rng, zb.size)).to_modes(isotropic=True)
    with pytest.raises(ValueError, match=r"modes must have shape \(14,\)"):
        CoefficientMatrix.from_modes(np.zeros(13), 4)


def test_channels(rng):
    zb = HemiZernike(3)
    m = _random_symmetric(rng, zb.size, channels=3)
    cm = CoefficientMatrix(zb, m, quantity="f")
    assert cm.channels == 3
    wi, wo = _unit_upper(rng, 8), _unit_upper(rng, 8)
    v = cm.eval(wi, wo)
    assert v.shape == (8, 3)
    for c in range(3):
        one = CoefficientMatrix(zb, m[c], quantity="f")
        np.testing.assert_allclose(v[:, c], one.eval(wi, wo), rtol=1e-14, atol=1e-14)
    assert cm.albedo(wi).shape == (8, 3)
    assert cm.to_isotropic().to_modes().shape == (3, HelmholtzModes(3).size)


def test_broadcasting(rng):
    cm = lambert_zernike(0.3)
    assert cm.eval([0, 0, 1.0], _unit_upper(rng, 5)).shape == (5,)
    assert cm.eval(_unit_upper(rng, 4)[:, None], _unit_upper(rng, 5)).shape == (4, 5)
    with pytest.raises(ValueError, match="broadcastable batch shapes"):
        cm.eval(_unit_upper(rng, 4), _unit_upper(rng, 5))


def test_full_sphere_basis_allowed(rng):
    sh = SphericalHarmonics(2)
    cm = CoefficientMatrix(sh, _random_symmetric(rng, sh.size), quantity="f")
    assert cm.eval(_unit_upper(rng, 3), _unit_upper(rng, 3)).shape == (3,)


@pytest.mark.parametrize("kwargs, exc, match", [
    ({"basis": "zernike"}, TypeError, "basis must be a basis object"),
    ({"matrix": np.zeros((3, 3))}, ValueError, r"matrix must have shape \(6, 6\)"),
    ({"matrix": np.full((6, 6), np.nan)}, ValueError, "matrix must be finite"),
    ({"matrix": "abc"}, TypeError, "matrix must be an array of floats"),
    ({"quantity": "g"}, ValueError, "quantity must be one of 'f', 'f_cos'"),
    ({"matrix": np.eye(6) * (1 + 1e-3j)}, TypeError,
     r"matrix must be real \(float\), got complex128"),
])
def test_bad_construction(kwargs, exc, match):
    args = {"basis": HemiZernike(2), "matrix": np.eye(6), "quantity": "f"} | kwargs
    with pytest.raises(exc, match=match):
        CoefficientMatrix(args["basis"], args["matrix"], args["quantity"])


def test_complex_blocks_and_modes_are_refused():
    # numpy would drop the imaginary part with only a ComplexWarning
    hz = HemiZernike(2)
    blocks = [np.eye(k) * 1j for k in (2, 1, 1)]
    with pytest.raises(TypeError, match=r"blocks\[0\] must be real \(float\), got complex"):
        CoefficientMatrix.from_blocks(hz, blocks)
    with pytest.raises(TypeError, match=r"modes must be real \(float\), got complex"):
        CoefficientMatrix.from_modes(np.zeros(5, dtype=complex), 2)


def test_bad_eval():
    cm = lambert_westin(0.5)
    with pytest.raises(TypeError, match=r"wi must be real \(float\), got complex"):
        cm.eval([0, 0, 1.0 + 0j], [0, 0, 1.0])
    with pytest.raises(ValueError, match="min_cos must lie in"):
        cm.eval([0, 0, 1.0], [0, 0, 1.0], min_cos=0.0)
    with pytest.raises(ValueError, match=r"wi must have shape \(\.\.\., 3\)"):
        cm.eval([0, 1.0], [0, 0, 1.0])
    with pytest.raises(ValueError, match="wo must be unit vectors"):
        cm.eval([0, 0, 1.0], [0, 0, 2.0])


def _turn(w, angle):
    """R^-1 w for R the turn by ``angle`` about z."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * w[..., 0] + s * w[..., 1], -s * w[..., 0] + c * w[..., 1], w[..., 2]],
                    -1)


@pytest.mark.parametrize("basis", [HemiZernike(6), HemiHarmonics(6), HemiHarmonics(5, "even"),
                                   SphericalHarmonics(4)], ids=repr)
@pytest.mark.parametrize("angle", [0.3, np.pi / 2, -2.1, 17.0])
def test_rotated_matches_turned_directions(basis, angle, rng):
    # reference: direct evaluation at R^-1 w_i, R^-1 w_o; entries O(1) / size so values are
    # O(1): observed max error 6e-15, the bound is ~50 eps of sums of ~size^2 terms
    m = _random_symmetric(rng, basis.size, channels=2) / basis.size
    cm = CoefficientMatrix(basis, m, quantity="f")
    rot = cm.rotated(angle)
    assert not rot.is_isotropic and rot.channels == 2 and rot.quantity == "f"
    wi, wo = _unit_upper(rng, 200), _unit_upper(rng, 200)
    want = cm.eval(_turn(wi, angle), _turn(wo, angle))
    np.testing.assert_allclose(rot.eval(wi, wo), want, rtol=0,
                               atol=1e-13 * np.max(np.abs(want)))
    # orthogonal action: the Frobenius norm is kept
    assert np.sum(rot.matrix**2) == pytest.approx(np.sum(m**2), rel=1e-13)


def test_rotated_quarter_turns_and_least_squares_action(rng):
    zb = HemiZernike(5)
    cm = CoefficientMatrix(zb, _random_symmetric(rng, zb.size), quantity="f_cos")
    four = cm
    for _ in range(4):
        four = four.rotated(np.pi / 2)
    # four products with cos/sin(m pi / 2) that are 0 only to 6e-17: ~1e-15 on entries ~5
    np.testing.assert_allclose(four.matrix, cm.matrix, rtol=0, atol=1e-13)
    # independent action: least squares b(R^-1 w) = A b(w) on random directions (as
    # tests/project/test_scene.rotation_action, here for a generic angle)
    angle = 0.9
    w = _unit_upper(rng, 400)
    at = np.linalg.lstsq(zb.eval(w), zb.eval(_turn(w, angle)), rcond=None)[0]
    np.testing.assert_allclose(cm.rotated(angle).matrix, at @ cm.matrix @ at.T, rtol=0,
                               atol=1e-11)  # lstsq of a well-conditioned 21-column system


def test_rotated_isotropic_is_unchanged(rng):
    zb = HemiZernike(4)
    iso = CoefficientMatrix(zb, _random_symmetric(rng, zb.size)).to_isotropic()
    assert iso.rotated(1.234) is iso


@pytest.mark.parametrize("angle, exc, match", [
    ("a", TypeError, "angle must be a number"),
    (np.inf, ValueError, "angle must be finite, got inf"),
])
def test_rotated_bad_angle(angle, exc, match, rng):
    cm = CoefficientMatrix(HemiZernike(2), _random_symmetric(rng, 6))
    with pytest.raises(exc, match=match):
        cm.rotated(angle)


@pytest.mark.parametrize("iso", [True, False])
@pytest.mark.parametrize("channels", [None, 2])
def test_stored_views(iso, channels, rng):
    b = HemiZernike(4)
    shape = (b.size, b.size) if channels is None else (channels, b.size, b.size)
    x = rng.normal(size=shape)
    cm = CoefficientMatrix(b, x + np.swapaxes(x, -1, -2), isotropic=False)
    cm = cm.to_isotropic() if iso else cm
    stored = cm.stored
    assert cm.is_scalar == (channels is None)
    assert sum(a.nbytes for a in stored) == cm.nbytes
    assert all(a.ndim == 3 and a.shape[0] == cm.channels for a in stored)
    if iso:
        assert [a.shape[-1] for a in stored] == b.azimuthal_blocks().sizes.tolist()
        for got, want in zip(stored, cm.blocks, strict=True):
            assert np.array_equal(got.reshape(want.shape), want)
    else:
        assert len(stored) == 1 and np.array_equal(stored[0].reshape(shape), cm.matrix)
    with pytest.raises(ValueError, match="read-only"):
        stored[0][..., 0, 0] = 1.0


# -- general (non-reciprocal) matrices --------------------------------------------------------
def _general_iso(rng, b, channels=2):
    blocks = [rng.normal(size=(channels, i.size, i.size)) for i in b.azimuthal_blocks().cos]
    return CoefficientMatrix.from_blocks(b, blocks, "f", reciprocal=False)


_GENERAL_BASES = [HemiZernike(8), HemiHarmonics(7), HemiHarmonics(6, parity="even"),
                  SphericalHarmonics(6)]


@pytest.mark.parametrize("b", _GENERAL_BASES, ids=repr)
@pytest.mark.parametrize("quantity", ["f", "f_cos"])
def test_general_eval_matches_direct_product(rng, b, quantity):
    # reference: b(w_i)^T M b(w_o) from basis.eval, no fused kernel, no symmetry assumed
    cm = _general_iso(rng, b)
    cm = CoefficientMatrix.from_blocks(b, cm.blocks, quantity, reciprocal=False)
    wi, wo = _unit_upper(rng, 500), _unit_upper(rng, 500)
    wi[:, 2] += 0.05
    wo[:, 2] += 0.05  # keep away from the min_cos lift of f_cos
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    m = cm.matrix
    ref = np.einsum("nj,cjk,nk->nc", b.eval(wi), m, b.eval(wo))
    if quantity == "f_cos":
        ref /= (wi[:, 2] * wo[:, 2])[:, None]
    dense = CoefficientMatrix(b, m, quantity, isotropic=False, reciprocal=False)
    assert cm.is_isotropic and not dense.is_isotropic
    scale = np.max(np.abs(ref))
    # the fused kernel's Chebyshev change of basis: ~1e-14 relative (module notes); dense
    # products: rounding of ~size terms
    np.testing.assert_allclose(cm.eval(wi, wo), ref, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(dense.eval(wi, wo), ref, rtol=0, atol=1e-12 * scale)
    # the antisymmetric part is really there: f(w_i, w_o) != f(w_o, w_i)
    assert np.max(np.abs(cm.eval(wi, wo) - cm.eval(wo, wi))) > 1e-3 * scale


@pytest.mark.parametrize("dense", [False, True])
def test_transpose_and_parts(rng, dense):
    b = HemiZernike(6)
    cm = _general_iso(rng, b)
    if dense:
        cm = CoefficientMatrix(b, cm.matrix, "f", isotropic=False, reciprocal=False)
    wi, wo = _unit_upper(rng, 300), _unit_upper(rng, 300)
    t = cm.transpose()
    assert not t.reciprocal and t.is_isotropic == cm.is_isotropic
    np.testing.assert_array_equal(t.matrix, np.swapaxes(cm.matrix, -1, -2))
    # f^T(w_i, w_o) = f(w_o, w_i); both evaluations round alike: 1e-12 relative
    scale = np.max(np.abs(cm.eval(wi, wo)))
    np.testing.assert_allclose(t.eval(wi, wo), cm.eval(wo, wi), rtol=0, atol=1e-12 * scale)
    s, a = cm.symmetric_part(), cm.antisymmetric_part()
    assert s.reciprocal and not a.reciprocal
    np.testing.assert_allclose(s.matrix + a.matrix, cm.matrix, rtol=0, atol=1e-15 * 8)
    np.testing.assert_array_equal(s.matrix, np.swapaxes(s.matrix, -1, -2))
    # a reciprocal matrix is its own transpose and symmetric part
    assert s.transpose() is s and s.symmetric_part() is s


def test_general_albedo_integrates_over_the_outgoing_direction(rng):
    # a(w_i) = int f(w_i, w_o) cos(theta_o) dw_o by a hemisphere rule: f is a polynomial of
    # degree <= 4 in w_o (HemiZernike(4)), times z_o: degree 5, exact with 6 x 12 nodes
    b = HemiZernike(4)
    cm = _general_iso(rng, b)
    rule = hemisphere_rule(6, 12)
    wi = _unit_upper(rng, 7)
    f = cm.eval(wi[:, None, :], rule.points[None, :, :])  # (7, nodes, channels)
    ref = np.einsum("inc,n->ic", f, rule.weights * rule.points[:, 2])
    np.testing.assert_allclose(cm.albedo(wi), ref, rtol=0, atol=1e-13)
    # the other direction (light from w_o) is the transpose's albedo, and differs here
    f_t = cm.eval(rule.points[None, :, :], wi[:, None, :])
    ref_t = np.einsum("inc,n->ic", f_t, rule.weights * rule.points[:, 2])
    np.testing.assert_allclose(cm.transpose().albedo(wi), ref_t, rtol=0, atol=1e-13)
    assert np.max(np.abs(ref - ref_t)) > 1e-3


def test_general_derived_matrices_keep_the_form(rng):
    b = HemiZernike(6)
    cm = _general_iso(rng, b)
    t = cm.truncate(3)
    assert not t.reciprocal and t.basis == HemiZernike(3)
    idx = np.arange(t.basis.size)  # a prefix of the functions
    np.testing.assert_array_equal(t.matrix, cm.matrix[:, idx[:, None], idx])
    # rotation: A^T M A with the exact action A; a general dense matrix stays general
    d = CoefficientMatrix(b, rng.normal(size=(b.size, b.size)), "f", isotropic=False,
                          reciprocal=False)
    wi, wo = _unit_upper(rng, 200), _unit_upper(rng, 200)
    ang = 0.7
    rot = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    r = d.rotated(ang)
    assert not r.reciprocal
    # f'(w_i, w_o) = f(R^-1 w_i, R^-1 w_o); rounding of the dense products: 1e-12
    np.testing.assert_allclose(r.eval(wi, wo), d.eval(wi @ rot, wo @ rot), rtol=0,
                               atol=1e-12 * np.max(np.abs(d.matrix)))
    assert cm.rotated(ang) is cm
    # isotropic projection of a general dense matrix: blocks averaged, not symmetrised
    iso = CoefficientMatrix(b, cm.matrix[0], "f", isotropic=False, reciprocal=False)
    back = iso.to_isotropic()
    assert back.is_isotropic and not back.reciprocal
    np.testing.assert_array_equal(back.matrix, cm.matrix[0])
    assert "reciprocal=False" in repr(cm) and "reciprocal" not in repr(cm.symmetric_part())


def test_to_isotropic_drops_the_mirror_odd_blocks(rng):
    # sin(dphi) coupling: b_c(w_i) b_s(w_o) - b_s(w_i) b_c(w_o) for the m = 1 pair of
    # degree 1, an isotropic BRDF odd under the mirror y -> -y: no isotropic block holds it
    b = HemiZernike(3)
    c, s = b.azimuthal_blocks().cos[1][0], b.azimuthal_blocks().sin[1][0]
    m = np.zeros((b.size, b.size))
    m[0, 0] = 1.0
    m[c, s], m[s, c] = 0.4, -0.4
    cm = CoefficientMatrix(b, m, "f", reciprocal=False)
    assert not cm.is_isotropic  # the cos-sin blocks are not block form
    np.testing.assert_array_equal(cm.to_isotropic().matrix, np.where(m == 1.0, 1.0, 0.0))


def test_general_errors(rng):
    b = HemiZernike(2)
    a = rng.normal(size=(b.size, b.size))
    with pytest.raises(ValueError, match="matrix must be symmetric .* reciprocal=False"):
        CoefficientMatrix(b, a)
    with pytest.raises(ValueError, match="symmetrize must be False with reciprocal=False"):
        CoefficientMatrix(b, a, symmetrize=True, reciprocal=False)
    with pytest.raises(TypeError, match="reciprocal must be True or False, got 'no'"):
        CoefficientMatrix(b, a, reciprocal="no")
    with pytest.raises(TypeError, match="reciprocal must be True or False, got None"):
        CoefficientMatrix.from_blocks(b, [np.eye(2), np.eye(1), np.eye(1)], reciprocal=None)
    cm = CoefficientMatrix(b, a, reciprocal=False)
    assert not cm.reciprocal
    with pytest.raises(ValueError, match="to_modes needs a reciprocal matrix"):
        cm.to_modes()
    np.testing.assert_array_equal(CoefficientMatrix(b, a, reciprocal=False).matrix, a)
