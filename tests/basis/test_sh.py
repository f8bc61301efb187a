"""SphericalHarmonics and HemiHarmonics: pyshtools and mpmath references, orthonormality by
exact quadrature, the clamped-cosine closed form, pyshtools interoperability, the hemisphere
parity subsets, edge cases and input validation."""

from __future__ import annotations

import math
from fractions import Fraction

import mpmath
import numpy as np
import pyshtools
import pytest

import basis.validation as validate
from basis import HemiHarmonics, SphericalHarmonics, hemisphere_rule, sphere_rule

EPS = float(np.finfo(np.float64).eps)


def _dirs(theta, phi):
    theta, phi = np.asarray(theta, dtype=float), np.asarray(phi, dtype=float)
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)


def _gram(b, cols=None):
    """Y^T W Y (times ``cols`` if given) on ``b.exact_rule()``, over chunks of ~128 MB."""
    rule = b.exact_rule()
    chunk = max(64, 16_000_000 // max(b.size, 1))
    out = None
    for s in range(0, rule.weights.size, chunk):
        y = b.eval(rule.points[s:s + chunk])
        right = y if cols is None else y @ cols
        part = y.T @ (rule.weights[s:s + chunk, None] * right)
        out = part if out is None else out + part
    return out


# -- indexing ---------------------------------------------------------------------------------

@pytest.mark.parametrize("lmax", [0, 1, 12])
def test_index_is_l_squared_plus_l_plus_m(lmax):
    sh = SphericalHarmonics(lmax)
    assert sh.size == (lmax + 1) ** 2
    assert sh.order == sh.lmax == lmax
    for l in range(lmax + 1):
        for m in range(-l, l + 1):
            k = sh.index(l, m)
            assert k == l * l + l + m
            assert (sh.degree[k], sh.azimuthal[k]) == (l, m)


def test_index_of_missing_function_raises():
    with pytest.raises(ValueError, match=r"SphericalHarmonics\(3\) has no function with degree "
                                         r"3 and azimuthal order 4"):
        SphericalHarmonics(3).index(3, 4)


def test_degree_and_azimuthal_are_copies():
    sh = SphericalHarmonics(2)
    sh.degree[:] = 7
    sh.azimuthal[:] = 7
    assert list(sh.degree) == [0, 1, 1, 1, 2, 2, 2, 2, 2]
    assert list(sh.azimuthal) == [0, -1, 0, 1, -2, -1, 0, 1, 2]


# -- independent references -------------------------------------------------------------------

@pytest.mark.parametrize("lmax", [0, 1, 7, 30, 60])
def test_matches_pyshtools(lmax, unit_vectors):
    dirs = unit_vectors(50)
    theta = np.arctan2(np.hypot(dirs[:, 0], dirs[:, 1]), dirs[:, 2])
    phi = np.arctan2(dirs[:, 1], dirs[:, 0])
    sh = SphericalHarmonics(lmax)
    ref = np.array([
        sh.from_cilm(pyshtools.expand.spharm(lmax, t, p, normalization="ortho", csphase=1,
                                             kind="real", degrees=False))
        for t, p in zip(theta, phi, strict=True)])
    # both libraries run O(l)-step recurrences and build cos/sin(m phi) with O(m) rounding;
    # observed max error 3.4 (lmax + 1) eps at lmax = 60, the bound leaves 3x headroom
    np.testing.assert_allclose(sh.eval(dirs), ref, rtol=0, atol=10 * (lmax + 1) * EPS)


def _legendre_mp(l, m, z, s):
    """Orthonormal P_l^m (no Condon-Shortley phase) from the Ferrers hypergeometric form.

    P_l^m(z) = (l+m)! / ((l-m)! 2^m m!) s^m 2F1(m-l, l+m+1; m+1; (1-z)/2), s = sqrt(1-z^2),
    times the orthonormal factor sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!). The series terminates and
    mpmath raises its working precision when the terms cancel (checked against
    mpmath.legenp in test_mpmath_reference_matches_legenp).
    """
    f = mpmath.hyp2f1(m - l, m + l + 1, m + 1, (1 - z) / 2)
    log_c = (mpmath.loggamma(l + m + 1) - mpmath.loggamma(l - m + 1)) / 2 \
        - mpmath.loggamma(m + 1)
    return mpmath.sqrt((2 * l + 1) / (4 * mpmath.pi)) * mpmath.exp(log_c) \
        * mpmath.ldexp(1, -m) * s**m * f


def _exact_angles(d):
    """z, sin(theta) and phi of the float64 vector d, computed exactly from its components."""
    x, y, z = (mpmath.mpf(float(v)) for v in d)
    r = mpmath.sqrt(x * x + y * y + z * z)
    return z / r, mpmath.sqrt(x * x + y * y) / r, mpmath.atan2(y, x)


def _ylm_mp(l, m, d):
    """Real Y_lm at the float64 direction d (the exact vector, not a rounded angle)."""
    z, s, phi = _exact_angles(d)
    p = _legendre_mp(l, abs(m), z, s)
    if m == 0:
        return p
    trig = mpmath.cos(m * phi) if m > 0 else mpmath.sin(-m * phi)
    return mpmath.sqrt(2) * p * trig


@pytest.mark.parametrize("l, m, theta_deg", [
    (2000, 0, "0.01"), (2000, 1, "0.01"), (2000, 3, "0.01"), (1000, 2, "1"),
    (1000, 1, "53"), (1000, 500, "53"), (2000, 0, "89.97"), (2000, 2000, "89.97"),
])
def test_mpmath_reference_matches_legenp(l, m, theta_deg):
    with mpmath.workdps(40):
        theta = mpmath.radians(mpmath.mpf(theta_deg))
        z, s = mpmath.cos(theta), mpmath.sin(theta)
        # legenp (type 2, Ferrers) carries the Condon-Shortley phase (-1)^m: remove it
        ferrers = (-1) ** m * mpmath.legenp(l, m, z, type=2)
        ortho = ferrers * mpmath.sqrt((2 * l + 1) / (4 * mpmath.pi)
                                      * mpmath.factorial(l - m) / mpmath.factorial(l + m))
        ours = _legendre_mp(l, m, z, s)
        # two high-precision evaluations by different formulas: 40 digits asked, 25 required
        assert abs(ours - ortho) <= mpmath.mpf("1e-25") * abs(ortho)


def _allowed_error(l, ref):
    """Error bound for float64 Y_lm against the exact value at the same float64 direction.

    - The kernel rounds z = cos(theta) (|dz| <= eps). Near the pole P_l^m(z) is conditioned
      like a degree-l polynomial at its end point, so the relative change is up to about
      l^2 eps (Markov); away from the pole the functions oscillate with wavenumber ~ l and the
      error is ~ l eps times their amplitude sqrt((2l+1)/(4 pi)).
    - Exponentially small values (outside the oscillatory zone, reached with a carried
      exponent) keep the relative bound only.
    - Values below 2^-600 may be flushed to zero (the kernel's carried-exponent threshold).
    Observed: <= 0.2 l^2 eps relative near the pole, <= 2 l eps absolute elsewhere.
    """
    amp = math.sqrt((2 * l + 1) / (4 * math.pi))
    size = abs(float(ref))
    if size < 2.0**-600:
        return 2.0**-600
    if size < 1e-30 * amp:
        return 2 * l * l * EPS * size
    return 2 * l * l * EPS * size + 4 * l * EPS * amp


@pytest.mark.parametrize("lmax", [1000, 2000])
@pytest.mark.parametrize("theta_deg", [0.01, 1.0, 53.0, 89.97])
def test_high_degree_matches_mpmath(lmax, theta_deg):
    d = _dirs(np.radians(theta_deg), 0.7)
    sh = SphericalHarmonics(lmax)
    got = sh.eval(d)
    ms = [0, 1, 2, 3, 10, 30, 48, 60, 150, 206, 500, lmax // 2 + 1, lmax - 1]
    with mpmath.workdps(40):
        for l, mlist in [(lmax, ms + [lmax]), (lmax - 1, [0, 1, 48, 500, lmax - 1])]:
            for am in mlist:
                for m in ([0] if am == 0 else [am, -am]):
                    ref = _ylm_mp(l, m, d)
                    err = abs(got[sh.index(l, m)] - float(ref))
                    assert err <= _allowed_error(l, ref), (l, m, got[sh.index(l, m)], ref)


def test_pole_values():
    # at the poles only m = 0 survives: Y_l0(+-z) = (+-1)^l sqrt((2l+1)/(4 pi)); the m != 0
    # functions carry sin(theta)^|m| = 0 exactly
    lmax = 40
    sh = SphericalHarmonics(lmax)
    y = sh.eval([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    l = np.arange(lmax + 1)
    zonal = np.array([sh.index(k, 0) for k in l])
    expect = np.sqrt((2 * l + 1) / (4 * np.pi))
    # the recurrence with z = +-1 is exact up to O(l) rounding steps
    np.testing.assert_allclose(y[0, zonal], expect, rtol=4 * (lmax + 1) * EPS, atol=0)
    np.testing.assert_allclose(y[1, zonal], (-1.0) ** l * expect, rtol=4 * (lmax + 1) * EPS,
                               atol=0)
    others = np.setdiff1d(np.arange(sh.size), zonal)
    assert np.all(y[:, others] == 0.0)


def test_accepts_near_unit_vectors_and_renormalises(unit_vectors):
    d = unit_vectors(20)
    sh = SphericalHarmonics(10)
    # lengths within UNIT_ATOL = 1e-6 of 1 are renormalised inside the kernel: the results
    # agree up to the rounding of the division (a few eps times l)
    np.testing.assert_allclose(sh.eval(d * (1 + 5e-7)), sh.eval(d), rtol=0, atol=100 * EPS)


# -- orthonormality ---------------------------------------------------------------------------

def _gram_atol(order):
    """Tolerance on G - I for a rule with float64 nodes and weights.

    The nodes are rounded (|dz| ~ eps): the products Y_l Y_l' are polynomials of degree
    2 lmax in z, whose derivative is bounded by (2 lmax)^2 / 2 times their size (Markov), so
    the rule is exact only up to ~ lmax^2 eps. Observed <= 0.5 (lmax + 1)^2 eps for every
    basis and order tried (0 .. 1000), 1.0 at order 0 (a single rounding).
    """
    return 2 * (order + 1) ** 2 * EPS


@pytest.mark.parametrize("lmax", [0, 1, 10, 30])
def test_orthonormal_exact_rule(lmax):
    sh = SphericalHarmonics(lmax)
    rule = sh.exact_rule()
    assert rule.domain == "sphere"
    assert rule.degree_z >= 2 * lmax and rule.degree_phi >= 2 * lmax
    np.testing.assert_allclose(_gram(sh), np.eye(sh.size), rtol=0, atol=_gram_atol(lmax))


def test_orthonormal_exact_rule_lmax100_randomized(rng):
    # the full Gram matrix (10201^2 entries over 20301 nodes) costs ~2e12 flops; instead check
    # (G - I) V = 0 for Gaussian V (each entry of G - I enters some output with weight ~1) plus
    # the exact columns of the sectoral and zonal functions of the top degree
    sh = SphericalHarmonics(100)
    picks = [sh.index(100, m) for m in (-100, 0, 1, 100)]
    v = np.zeros((sh.size, 4 + len(picks)))
    v[:, :4] = rng.normal(size=(sh.size, 4))
    v[picks, 4 + np.arange(len(picks))] = 1.0  # unit columns: exact columns of G
    r = _gram(sh, v) - v
    # rounding: entries of G - I are <= _gram_atol(100) = 4.5e-12 (observed 3.4e-13); a row
    # of 10^4 of them times N(0, 1) gives ~3e-11 (observed 6e-12); a wrong function or
    # normalisation would give O(1)
    assert np.abs(r).max() <= 1e-9


@pytest.mark.slow
def test_orthonormal_lmax1000_legendre_blocks():
    # At lmax = 1000 even evaluating the basis on its exact rule (2e6 nodes x 1e6 functions) is
    # out of reach. The rule is a product: the azimuthal sum of cos(m phi) cos(m' phi) over
    # n_phi = 2001 equispaced nodes is exactly n_phi/2 delta_mm' (n_phi for m = 0), so the
    # Gram block of the cosine functions of order m reduces to the z-rule applied to the
    # values on the meridian phi = 0. Check those blocks for a few m.
    lmax = 1000
    sh = SphericalHarmonics(lmax)
    rule = sh.exact_rule()
    n_theta, n_phi = rule.shape
    meridian = rule.points.reshape(n_theta, n_phi, 3)[:, 0]
    ring_w = rule.weights.reshape(n_theta, n_phi).sum(axis=1)
    orders = [0, 1, 2, 500, 999, 1000]
    cols = np.concatenate([[sh.index(l, m) for l in range(m, lmax + 1)] for m in orders])
    y = np.concatenate([sh.eval(meridian[s:s + 32])[:, cols] for s in range(0, n_theta, 32)])
    start = 0
    for m in orders:
        block = y[:, start:start + lmax + 1 - m]
        start += lmax + 1 - m
        trig_sum = 1.0 if m == 0 else 0.5  # (1/n_phi) sum_p cos^2(m phi_p)
        g = block.T @ ((ring_w * trig_sum)[:, None] * block)
        # node rounding, as in _gram_atol (observed 0.13 (lmax + 1)^2 eps)
        np.testing.assert_allclose(g, np.eye(g.shape[0]), rtol=0, atol=_gram_atol(lmax),
                                   err_msg=f"m = {m}")


# -- the clamped cosine -----------------------------------------------------------------------

def _legendre_coefficients(l):
    """P_l(z) = sum_k c_k z^(l - 2k), exact rationals (Rodrigues expanded)."""
    return [(l - 2 * k, Fraction((-1) ** k * math.comb(l, k) * math.comb(2 * l - 2 * k, l),
                                 2**l)) for k in range(l // 2 + 1)]


def _int01(l, power):
    """int_0^1 z^power P_l(z) dz, exact."""
    return sum(c / (e + power + 1) for e, c in _legendre_coefficients(l))


def _clamped_cosine_coefficient(l):
    """int_S max(z, 0) Y_l0 = 2 pi sqrt((2l+1)/(4 pi)) int_0^1 z P_l(z) dz."""
    return math.sqrt(math.pi * (2 * l + 1)) * float(_int01(l, 1))


def test_clamped_cosine_reference_values():
    # the exact rationals against the values in the literature (Ramamoorthi & Hanrahan 2001,
    # eq. 8: A_l = 2 pi (-1)^(l/2 - 1) l! / ((l+2)(l-1) 2^l (l/2)!^2) for even l >= 2)
    assert _int01(0, 1) == Fraction(1, 2) and _int01(1, 1) == Fraction(1, 3)
    for l in range(3, 30, 2):
        assert _int01(l, 1) == 0
    for l in range(2, 30, 2):
        rh = Fraction((-1) ** (l // 2 + 1) * math.factorial(l),
                      (l + 2) * (l - 1) * 2**l * math.factorial(l // 2) ** 2)
        assert _int01(l, 1) == rh
    expected = [math.sqrt(math.pi) / 2, math.sqrt(math.pi / 3), math.sqrt(5 * math.pi) / 8, 0.0,
                -math.sqrt(math.pi) / 16]
    got = [_clamped_cosine_coefficient(l) for l in range(5)]
    assert got == pytest.approx(expected, rel=1e-15, abs=1e-15)  # exact rationals, one rounding
    assert got == pytest.approx([0.886227, 1.023327, 0.495416, 0.0, -0.110778], abs=5e-7)


@pytest.mark.parametrize("lmax", [0, 4, 20])
def test_clamped_cosine_by_hemisphere_quadrature(lmax):
    # int_S max(z, 0) Y_lm = int_H z Y_lm: z Y_lm is a polynomial of degree lmax + 1 in z
    # (after the azimuthal sum) and of azimuthal degree lmax, so this rule is exact
    sh = SphericalHarmonics(lmax)
    rule = hemisphere_rule(lmax // 2 + 1, lmax + 1)
    assert rule.degree_z >= lmax + 1
    coef = rule.integrate(rule.points[:, 2:] * sh.eval(rule.points))
    expect = np.zeros(sh.size)
    for l in range(lmax + 1):
        expect[sh.index(l, 0)] = _clamped_cosine_coefficient(l)
    # one weighted sum of O(1) terms: ~ (number of nodes) eps; observed < 1e-15
    np.testing.assert_allclose(coef, expect, rtol=0, atol=1e-14)
    # moments("cos") is the same integral and returns exact zeros off the zonal functions
    np.testing.assert_allclose(sh.moments("cos"), expect, rtol=0, atol=1e-14)
    assert np.all(sh.moments("cos")[sh.azimuthal != 0] == 0.0)


def test_clamped_cosine_is_not_exact_on_sphere_rule():
    # max(z, 0) has a kink at z = 0: Gauss-Legendre on [-1, 1] converges only algebraically.
    # This is why the closed form is compared with hemisphere_rule above.
    lmax = 4
    sh = SphericalHarmonics(lmax)
    rule = sphere_rule(lmax + 2, lmax + 1)
    coef = rule.integrate(np.maximum(rule.points[:, 2:], 0.0) * sh.eval(rule.points))
    errors = [abs(coef[sh.index(l, 0)] - _clamped_cosine_coefficient(l)) for l in range(5)]
    assert max(errors) > 1e-4  # not rounding noise: a quadrature error


def test_moments_none_closed_form():
    # int_H Y_l0 = 2 pi sqrt((2l+1)/(4 pi)) int_0^1 P_l(z) dz (exact rationals)
    lmax = 15
    sh = SphericalHarmonics(lmax)
    expect = np.zeros(sh.size)
    for l in range(lmax + 1):
        expect[sh.index(l, 0)] = math.sqrt(math.pi * (2 * l + 1)) * float(_int01(l, 0))
    assert expect[sh.index(2, 0)] == 0.0 and expect[sh.index(3, 0)] != 0.0
    np.testing.assert_allclose(sh.moments("none"), expect, rtol=0, atol=1e-14)  # as above


def test_moments_bad_weight():
    with pytest.raises(ValueError, match=r"weight must be 'cos' or 'none', got 'sin'"):
        SphericalHarmonics(2).moments("sin")


# -- pyshtools interoperability ---------------------------------------------------------------

def test_cilm_round_trip(rng):
    sh = SphericalHarmonics(9)
    c = rng.normal(size=sh.size)
    cilm = sh.to_cilm(c)
    assert cilm.shape == (2, 10, 10)
    np.testing.assert_array_equal(sh.from_cilm(cilm), c)  # pure copies: exact
    # unused slots (m > l, and the sine part of m = 0) stay zero
    l, m = np.meshgrid(np.arange(10), np.arange(10), indexing="ij")
    assert np.all(cilm[:, m > l] == 0.0) and np.all(cilm[1, :, 0] == 0.0)
    # a larger pyshtools array is truncated to this basis
    big = np.zeros((2, 15, 15))
    big[:, :10, :10] = cilm
    big[0, 12, 3] = 1.0
    np.testing.assert_array_equal(sh.from_cilm(big), c)


def test_cilm_evaluates_like_pyshtools(rng, unit_vectors):
    # the same expansion evaluated by pyshtools (orthonormal, no CS phase) and by us
    sh = SphericalHarmonics(12)
    c = rng.normal(size=sh.size)
    d = unit_vectors(30)
    lat = np.degrees(np.arcsin(np.clip(d[:, 2], -1, 1)))
    lon = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    ref = pyshtools.expand.MakeGridPoint(sh.to_cilm(c), lat, lon, norm=4, csphase=1)
    # sum of 169 terms of size ~ |c| sqrt(l): ~ 169 * 12 eps, plus the lat/lon round trip
    np.testing.assert_allclose(sh.eval(d) @ c, ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("lmax", [0, 1, 5, 30])
def test_grid_synthesize_expand_round_trip(lmax, rng):
    sh = SphericalHarmonics(lmax)
    c = rng.normal(size=sh.size)
    grid = sh.grid()
    assert grid.shape == (lmax + 1, 2 * lmax + 1, 3)
    np.testing.assert_allclose(np.linalg.norm(grid, axis=-1), 1.0, rtol=0, atol=4 * EPS)
    values = sh.synthesize(c)
    assert values.shape == (lmax + 1, 2 * lmax + 1)
    # pyshtools' synthesis against our evaluation on its grid: each function value agrees to
    # 10 (lmax + 1) eps (test_matches_pyshtools), so by Cauchy-Schwarz the sums agree to
    # 10 (lmax + 1) eps sqrt(size) |c|; observed ~100x below
    bound = 10 * (lmax + 1) * EPS * np.sqrt(sh.size) * np.linalg.norm(c)
    np.testing.assert_allclose(sh.eval(grid) @ c, values, rtol=0, atol=bound)
    # Gauss-Legendre analysis is exact for band-limited functions: c back up to rounding of
    # sums over the (lmax+1)(2 lmax+1) nodes (observed <= 0.1 (lmax + 1)^2 eps |c|_max)
    np.testing.assert_allclose(sh.expand(values), c, rtol=0,
                               atol=2 * (lmax + 1) ** 2 * EPS * np.abs(c).max())


@pytest.mark.parametrize("values, match", [
    (np.zeros((4, 6)), r"values must have the grid shape \(4, 7\), got \(4, 6\)"),
    (np.full((4, 7), np.nan), r"values must be finite"),
])
def test_expand_bad_values(values, match):
    with pytest.raises(ValueError, match=match):
        SphericalHarmonics(3).expand(values)


@pytest.mark.parametrize("method, args", [
    ("to_cilm", (np.zeros(6),)), ("from_cilm", (np.zeros((2, 4, 4)),)), ("grid", ()),
    ("expand", (np.zeros((4, 7)),)), ("synthesize", (np.zeros(6),)),
])
def test_hemi_has_no_full_sphere_transforms(method, args):
    # a parity subset is not a full-sphere expansion: the methods do not exist at all
    hb = HemiHarmonics(3)
    assert not hasattr(hb, method)
    assert not isinstance(hb, SphericalHarmonics)
    assert hasattr(SphericalHarmonics(3), method)


@pytest.mark.parametrize("shape, match", [
    ((10,), r"coeffs must have shape \(16,\), got shape \(10,\)"),
    ((2, 16), r"coeffs must have shape \(16,\), got shape \(2, 16\)"),
])
def test_to_cilm_bad_shape(shape, match):
    with pytest.raises(ValueError, match=match):
        SphericalHarmonics(3).to_cilm(np.zeros(shape))


@pytest.mark.parametrize("shape", [(2, 3, 3), (1, 4, 4), (2, 4, 5), (4, 4)])
def test_from_cilm_bad_shape(shape):
    with pytest.raises(ValueError, match=r"cilm must have shape \(2, L\+1, L\+1\) with L >= 3"):
        SphericalHarmonics(3).from_cilm(np.zeros(shape))


# -- HemiHarmonics ----------------------------------------------------------------------------

@pytest.mark.parametrize("lmax", range(0, 13))
def test_hemi_sizes(lmax):
    assert HemiHarmonics(lmax).size == lmax * (lmax + 1) // 2
    assert HemiHarmonics(lmax, parity="odd").size == lmax * (lmax + 1) // 2
    assert HemiHarmonics(lmax, parity="even").size == (lmax + 1) * (lmax + 2) // 2


@pytest.mark.parametrize("parity, rest", [("odd", 1), ("even", 0)])
@pytest.mark.parametrize("lmax", [0, 1, 6, 25])
def test_hemi_is_sqrt2_times_parity_subset(lmax, parity, rest, unit_vectors):
    hb, sh = HemiHarmonics(lmax, parity=parity), SphericalHarmonics(lmax)
    keep = (sh.degree + np.abs(sh.azimuthal)) % 2 == rest
    # same functions, same order
    np.testing.assert_array_equal(hb.degree, sh.degree[keep])
    np.testing.assert_array_equal(hb.azimuthal, sh.azimuthal[keep])
    for l, m in zip(hb.degree, hb.azimuthal, strict=True):
        assert hb.index(l, m) == np.flatnonzero(keep).tolist().index(sh.index(l, m))
    d = unit_vectors(100, upper=True)
    # the same recurrence seeded with sqrt(2)/sqrt(4 pi) instead of 1/sqrt(4 pi): the two
    # runs round independently over O(l) steps, values are O(1); observed 2.5 (lmax + 1) eps
    np.testing.assert_allclose(hb.eval(d), np.sqrt(2.0) * sh.eval(d)[:, keep], rtol=0,
                               atol=8 * (lmax + 1) * EPS)


@pytest.mark.parametrize("parity", ["odd", "even"])
@pytest.mark.parametrize("lmax", [0, 1, 2, 10, 40])
def test_hemi_orthonormal_exact_rule(lmax, parity):
    hb = HemiHarmonics(lmax, parity=parity)
    rule = hb.exact_rule()
    assert rule.domain == "hemisphere"
    assert np.all(rule.points[:, 2] >= 0)
    np.testing.assert_allclose(_gram(hb), np.eye(hb.size), rtol=0, atol=_gram_atol(lmax))


def test_hemi_odd_vanish_on_horizon_even_do_not(rng):
    phi = rng.uniform(0, 2 * np.pi, 50)
    horizon = _dirs(np.full(50, np.pi / 2), phi)
    horizon[:, 2] = 0.0  # cos(pi/2) is 6e-17 in float64: make it exactly the horizon
    odd = HemiHarmonics(15, parity="odd").eval(horizon)
    # l + |m| odd: P_l^m is odd in z, and the recurrence multiplies by z = 0 exactly
    assert np.all(odd == 0.0)
    even = HemiHarmonics(15, parity="even").eval(horizon)
    assert np.abs(even).max(axis=0).min() > 1e-3  # each even function is non-zero somewhere


def test_hemi_rejects_below_horizon():
    hb = HemiHarmonics(4)
    with pytest.raises(ValueError, match=r"dirs must lie in the upper hemisphere z >= 0: 1 of 2 "
                                         r"do not \(first at flat index 1, z = -0\.8\)"):
        hb.eval([[0.0, 0.0, 1.0], [0.0, 0.6, -0.8]])
    # rounding-level negative z (documented -1e-12) is accepted
    assert hb.eval([np.sqrt(1 - 1e-26), 0.0, -1e-13]).shape == (hb.size,)


@pytest.mark.parametrize("parity", ["odd", "even"])
def test_hemi_truncate_is_prefix(parity, unit_vectors):
    hb = HemiHarmonics(10, parity=parity)
    low = hb.truncate(4)
    assert low == HemiHarmonics(4, parity=parity) and low.parity == parity
    assert low != HemiHarmonics(4, parity="even" if parity == "odd" else "odd")
    np.testing.assert_array_equal(hb.degree[:low.size], low.degree)
    np.testing.assert_array_equal(hb.azimuthal[:low.size], low.azimuthal)
    d = unit_vectors(20, upper=True)
    # same kernel, same recurrence steps for the kept functions: bitwise equal
    np.testing.assert_array_equal(hb.eval(d)[:, :low.size], low.eval(d))


def test_full_truncate_is_prefix(unit_vectors):
    sh = SphericalHarmonics(12)
    low = sh.truncate(5)
    assert low == SphericalHarmonics(5)
    d = unit_vectors(20)
    np.testing.assert_array_equal(sh.eval(d)[:, :low.size], low.eval(d))  # bitwise, as above


@pytest.mark.parametrize("make", [lambda: SphericalHarmonics(10),
                                  lambda: HemiHarmonics(10, parity="even")])
@pytest.mark.parametrize("order, exc, match", [
    (11, ValueError, r"order must be <= 10 \(the order of .*\(10.*\)\), got 11"),
    (-1, ValueError, r"order must be >= 0, got -1"),
    (2.0, TypeError, r"order must be an integer, got 2\.0"),
])
def test_truncate_bad_order(make, order, exc, match):
    with pytest.raises(exc, match=match):
        make().truncate(order)


def test_hemi_repr_and_equality():
    assert repr(HemiHarmonics(3)) == "HemiHarmonics(3, parity='odd')"
    assert HemiHarmonics(3) == HemiHarmonics(3, parity="odd")
    assert HemiHarmonics(3) != SphericalHarmonics(3)
    assert len({HemiHarmonics(3), HemiHarmonics(3, "odd"), HemiHarmonics(3, "even")}) == 2


# -- edge cases -------------------------------------------------------------------------------

BASES = [
    pytest.param(lambda n: SphericalHarmonics(n), id="sh"),
    pytest.param(lambda n: HemiHarmonics(n, parity="odd"), id="hemi-odd"),
    pytest.param(lambda n: HemiHarmonics(n, parity="even"), id="hemi-even"),
]


@pytest.mark.parametrize("make", BASES)
def test_zero_points(make):
    b = make(4)
    assert b.eval(np.empty((0, 3))).shape == (0, b.size)
    assert b.eval(np.empty((2, 0, 3))).shape == (2, 0, b.size)


@pytest.mark.parametrize("make", BASES)
def test_batch_shape(make, unit_vectors):
    b = make(5)
    d = unit_vectors((2, 3), upper=True)
    y = b.eval(d)
    assert y.shape == (2, 3, b.size)
    np.testing.assert_array_equal(y.reshape(6, b.size), b.eval(d.reshape(6, 3)))  # same kernel
    assert b.eval(d[0, 0]).shape == (b.size,)  # a single direction gives a single row


def test_order_zero(unit_vectors):
    d = unit_vectors(7, upper=True)
    # Y_00 = 1/sqrt(4 pi); sqrt(2) Y_00 = 1/sqrt(2 pi); the odd subset of degree 0 is empty
    np.testing.assert_allclose(SphericalHarmonics(0).eval(d), np.full((7, 1), 0.5 / np.sqrt(np.pi)),
                               rtol=2 * EPS, atol=0)
    np.testing.assert_allclose(HemiHarmonics(0, parity="even").eval(d),
                               np.full((7, 1), 1 / np.sqrt(2 * np.pi)), rtol=2 * EPS, atol=0)
    assert HemiHarmonics(0).eval(d).shape == (7, 0)


@pytest.mark.parametrize("make", BASES)
def test_pole_and_horizon_directions(make):
    b = make(8)
    y = b.eval([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [1e-300, 0.0, 1.0]])
    assert np.all(np.isfinite(y))
    pole_nonzero = np.flatnonzero(y[0] != 0.0)
    assert np.all(b.azimuthal[pole_nonzero] == 0)  # only zonal functions at the pole
    # a vector 1e-300 off the pole is the pole to float64 accuracy
    np.testing.assert_allclose(y[3], y[0], rtol=0, atol=1e-15)



@pytest.mark.parametrize("make", BASES)
@pytest.mark.parametrize("lmax", [0, 3, 11, 12, 13, 25])
def test_fast_kernels_give_the_reference_bits(make, lmax, unit_vectors):
    # The pair kernel (lmax < 13; for one parity class it stores only that class) and the
    # lane kernel (LANES directions per block) promise the bits of _sh_point, the
    # per-direction routine with the carried exponent: same operations in the same order.
    # 37 directions: full blocks, a partial one, and a block with sin(theta) below the seed
    # floor (it falls back to _sh_point as a whole).
    from basis._base import triangular_offsets
    from basis.sh import _PARITY_CODE, _sh_point

    b = make(lmax)
    d = unit_vectors(37, upper=True)
    d[9] = [0.0, 0.0, 1.0]
    d[10] = [1e-300, 0.0, 1.0]  # 0 < sin(theta) < the seed floor
    d[11] = [1.0, 0.0, 0.0]
    ref = np.empty((37, b.size))
    off = triangular_offsets(lmax)
    for i in range(37):
        _sh_point(d, i, lmax, _PARITY_CODE[b._parity], b._norm, b._a, b._b, b._d, off, ref[i])
    np.testing.assert_array_equal(b.eval(d), ref)  # bitwise: no tolerance

# -- input validation -------------------------------------------------------------------------

CONSTRUCTORS = [
    pytest.param(lambda n: SphericalHarmonics(n), "SphericalHarmonics", id="sh"),
    pytest.param(lambda n: HemiHarmonics(n), "HemiHarmonics", id="hemi-odd"),
    pytest.param(lambda n: HemiHarmonics(n, parity="even"), "HemiHarmonics", id="hemi-even"),
]


@pytest.mark.parametrize("make, name", CONSTRUCTORS)
@pytest.mark.parametrize("value, exc, match", [
    (-1, ValueError, r"lmax must be >= 0, got -1"),
    (2.0, TypeError, r"lmax must be an integer, got 2\.0"),
    ("2", TypeError, r"lmax must be an integer, got '2'"),
    (True, TypeError, r"lmax must be an integer, got True"),
    (None, TypeError, r"lmax must be an integer, got None"),
])
def test_bad_lmax(make, name, value, exc, match):
    with pytest.raises(exc, match=match):
        make(value)


@pytest.mark.parametrize("make, name", CONSTRUCTORS)
def test_lmax_above_maximum(make, name):
    with pytest.raises(ValueError, match=rf"lmax must be <= 2800 for {name}, got 2801"):
        make(2801)


@pytest.mark.parametrize("make, name", CONSTRUCTORS)
def test_numpy_integer_lmax_accepted(make, name):
    assert make(np.int64(3)).order == 3


@pytest.mark.parametrize("parity", ["bogus", "ODD", None, 1])
def test_bad_parity(parity):
    with pytest.raises(ValueError, match=r"parity must be one of 'odd', 'even', got "):
        HemiHarmonics(3, parity=parity)


@pytest.mark.parametrize("make", BASES)
@pytest.mark.parametrize("dirs, match", [
    (np.zeros((4, 2)), r"dirs must have shape \(\.\.\., 3\), got shape \(4, 2\)"),
    (1.0, r"dirs must have shape \(\.\.\., 3\), got shape \(\)"),
    ([[0.0, 0.0, 1.0], [np.nan, 0.0, 1.0]], r"dirs must be finite: 1 of 2 vectors hold NaN or "
                                            r"inf \(first at flat index 1\)"),
    ([np.inf, 0.0, 0.0], r"dirs must be finite: 1 of 1"),
    ([0.0, 0.0, 0.0], r"dirs must be unit vectors: 1 of 1 are not .*zero-length vectors have "
                      r"no direction"),
    ([0.0, 0.0, 2.0], r"dirs must be unit vectors: 1 of 1 are not \(first at flat index 0, "
                      r"norm 2\); normalise them first"),
    ([0.0, 0.0, 1.0 + 2e-6], r"dirs must be unit vectors: 1 of 1 are not"),
])
def test_bad_directions(make, dirs, match):
    with pytest.raises(ValueError, match=match):
        make(3).eval(dirs)


@pytest.mark.parametrize("make", BASES)
@pytest.mark.parametrize("dirs", ["abc", [[1.0, 0.0, 0.0], [0.0, 1.0]], {"x": 1}])
def test_non_numeric_directions(make, dirs):
    with pytest.raises(TypeError, match=r"dirs must be an array of floats with shape \(\.\.\., "
                                        r"3\), got "):
        make(3).eval(dirs)


@pytest.mark.parametrize("make", BASES[1:])
def test_hemi_bad_direction_below_horizon(make):
    with pytest.raises(ValueError, match=r"upper hemisphere z >= 0"):
        make(3).eval([0.0, 0.0, -1.0])


def test_full_sphere_accepts_lower_hemisphere():
    assert SphericalHarmonics(3).eval([0.0, 0.0, -1.0]).shape == (16,)


@pytest.mark.parametrize("make", BASES)
def test_allocation_limit(make, monkeypatch, unit_vectors):
    b = make(3)
    d = unit_vectors(11, upper=True)
    # the limit is checked before allocating: 10 rows of b.size float64 fit, 11 do not
    monkeypatch.setattr(validate, "MAX_BYTES", 8 * 10 * b.size)
    assert b.eval(d[:10]).shape == (10, b.size)
    with pytest.raises(MemoryError, match=r"would need .* GiB, more than the limit of .* GiB "
                                          r"\(basis\.validation\.MAX_BYTES\); use a lower order"):
        b.eval(d)
