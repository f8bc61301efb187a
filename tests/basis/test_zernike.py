"""HemiZernike and zernike_radial: sizes and ordering, the radial polynomials against exact
high-precision sums and closed forms, the basis against its defining formula, orthonormality
on the hemisphere by exact quadrature, moments, edge cases and input validation."""

from __future__ import annotations

import math
from fractions import Fraction

import mpmath
import numpy as np
import pytest

import basis.validation as validate
from basis import HemiZernike, zernike_radial

EPS = float(np.finfo(np.float64).eps)


# -- size and ordering ------------------------------------------------------------------------

@pytest.mark.parametrize("order", [0, 1, 2, 3, 8, 15, 200])
def test_size(order):
    assert HemiZernike(order).size == (order + 1) * (order + 2) // 2
    assert HemiZernike(order).order == order


def test_degree_and_azimuthal_ordering():
    zb = HemiZernike(6)
    expect = [(n, l) for n in range(7) for l in range(-n, n + 1, 2)]
    assert list(zip(zb.degree.tolist(), zb.azimuthal.tolist(), strict=True)) == expect
    for k, (n, l) in enumerate(expect):
        assert zb.index(n, l) == k == n * (n + 1) // 2 + (l + n) // 2
    assert np.all(np.diff(zb.degree) >= 0)  # ordered by degree: truncation is a prefix


def test_index_of_missing_function_raises():
    # n - l odd: no such function
    with pytest.raises(ValueError, match=r"HemiZernike\(4\) has no function with degree 3 and "
                                         r"azimuthal order 2"):
        HemiZernike(4).index(3, 2)


def test_truncate_is_prefix(unit_vectors):
    zb = HemiZernike(12)
    low = zb.truncate(5)
    assert low == HemiZernike(5) and repr(low) == "HemiZernike(5)"
    d = unit_vectors(30, upper=True)
    # the same kernel runs the same recurrence steps for the kept functions: bitwise equal
    np.testing.assert_array_equal(zb.eval(d)[:, :low.size], low.eval(d))
    with pytest.raises(ValueError, match=r"order must be <= 12 \(the order of HemiZernike\(12\)"
                                         r"\), got 13"):
        zb.truncate(13)


# -- the radial polynomials -------------------------------------------------------------------

def _radial_mp(n, l, rho):
    """R_n^l(rho) by the textbook factorial sum, integer coefficients, rho taken exactly.

    The terms reach ~1e89 at n = 300 and cancel to |R| <= 1, so 300 digits leave > 200 to
    spare.
    """
    k = (n - l) // 2
    with mpmath.workdps(300):
        r = mpmath.mpf(float(rho))
        total = mpmath.mpf(0)
        for s in range(k + 1):
            c = math.factorial(n - s) // (math.factorial(s) * math.factorial((n + l) // 2 - s)
                                          * math.factorial(k - s))
            total += (-1) ** s * c * r ** (n - 2 * s)
        return total


def _radial_atol(n, l):
    """Absolute error bound for zernike_radial(n, l, rho), |R| <= 1 on [0, 1].

    R = rho^l P_k^(0,l)(x), k = (n - l)/2, x = 2 rho^2 - 1 is rounded (|dx| <= 2 eps). The
    derivative of P_k^(0,l) is largest at the end points, P'(1) = k (k + l + 1)/2 (and the same
    at x = -1 when l = 0), so the conditioning alone allows k (k + l + 1) eps; rho^l adds up to
    n roundings. Observed <= 0.21 of this bound (6.6e-13 at n = 300, bound 5.1e-12).
    """
    k = (n - l) // 2
    return (k * (k + l + 1) + n + 1) * EPS


RHOS = np.array([0.0, 1e-8, 1e-3, 0.05,                      # near the centre (the pole)
                 0.3, 0.5, 0.7071067811865476, 0.8,          # interior
                 0.95, 0.999, 1 - 1e-6, 1 - 1e-12, 1 - 2.0**-53, 1.0])  # near the rim


def _ls(n):
    cands = {0, 1, 10, n // 2 - 1, n // 2, n // 2 + 1, n}
    return sorted(l for l in cands if 0 <= l <= n and (n - l) % 2 == 0)


@pytest.mark.parametrize("n", [0, 1, 2, 5, 10, 11, 40, 41, 100, 101, 299, 300])
def test_radial_matches_exact_sum(n):
    for l in _ls(n):
        got = zernike_radial(n, l, RHOS)
        ref = np.array([float(_radial_mp(n, l, r)) for r in RHOS])
        np.testing.assert_allclose(got, ref, rtol=0, atol=_radial_atol(n, l),
                                   err_msg=f"n = {n}, l = {l}")


@pytest.mark.parametrize("n, l", [(300, 0), (300, 150), (41, 21), (10, 4)])
def test_exact_sum_matches_mpmath_jacobi(n, l):
    # validate the reference with a second formula: R_n^l = rho^l P_k^(0,l)(2 rho^2 - 1)
    k = (n - l) // 2
    with mpmath.workdps(60):
        for rho in (0.05, 0.5, 0.999):
            r = mpmath.mpf(rho)
            jac = r**l * mpmath.jacobi(k, 0, l, 2 * r * r - 1)
            # two high-precision evaluations, 60 digits asked: agreement to 1e-40 absolute
            assert abs(jac - _radial_mp(n, l, rho)) < mpmath.mpf("1e-40")


def test_radial_low_order_closed_forms():
    rho = np.linspace(0.0, 1.0, 101)
    closed_forms = {  # coefficients of rho^0, rho^1, ...
        (0, 0): [1],
        (1, 1): [0, 1],
        (2, 0): [-1, 0, 2],
        (2, 2): [0, 0, 1],
        (3, 1): [0, -2, 0, 3],
        (3, 3): [0, 0, 0, 1],
        (4, 0): [1, 0, -6, 0, 6],
        (4, 2): [0, 0, -3, 0, 4],
        (6, 0): [-1, 0, 12, 0, -30, 0, 20],
    }
    for (n, l), coeffs in closed_forms.items():
        # evaluated exactly (rationals) at the float64 rho, then rounded once
        expect = [float(sum(c * Fraction(r) ** i for i, c in enumerate(coeffs))) for r in rho]
        np.testing.assert_allclose(zernike_radial(n, l, rho), expect, rtol=0,
                                   atol=_radial_atol(n, l), err_msg=f"R_{n}^{l}")


@pytest.mark.parametrize("n", [0, 1, 7, 30, 120, 300])
def test_radial_top_order_is_power(n):
    rho = np.linspace(0.0, 1.0, 33)
    # R_n^n = rho^n, computed as a power: up to ~n roundings relative
    np.testing.assert_allclose(zernike_radial(n, n, rho), rho**n, rtol=(n + 1) * EPS, atol=0)


@pytest.mark.parametrize("n", [0, 1, 2, 9, 40, 151, 300])
def test_radial_is_one_on_the_rim(n):
    got = np.array([zernike_radial(n, l, 1.0) for l in range(n % 2, n + 1, 2)])
    # x = 1 exactly, so only the recurrence coefficients round: observed 3.5 (n + 1) eps
    np.testing.assert_allclose(got, 1.0, rtol=0, atol=8 * (n + 1) * EPS)


def test_radial_bounded_by_one(rng):
    # |R_n^l| <= 1 on the unit disk (|P_k^(0,l)(x)| rho^l <= 1); allow the rounding bound above
    rho = np.concatenate([rng.uniform(0, 1, 400), np.linspace(0, 1, 101)])
    for n in range(0, 61):
        for l in range(n % 2, n + 1, 2):
            assert np.abs(zernike_radial(n, l, rho)).max() <= 1.0 + _radial_atol(n, l)


def test_radial_shapes():
    assert zernike_radial(2, 0, 0.5).shape == ()
    assert zernike_radial(2, 0, np.full((2, 3), 0.5)).shape == (2, 3)
    assert zernike_radial(2, 0, []).shape == (0,)


@pytest.mark.parametrize("args, exc, match", [
    ((-1, 0, 0.5), ValueError, r"n must be >= 0, got -1"),
    ((2.0, 0, 0.5), TypeError, r"n must be an integer, got 2\.0"),
    (("2", 0, 0.5), TypeError, r"n must be an integer, got '2'"),
    ((True, 0, 0.5), TypeError, r"n must be an integer, got True"),
    ((1001, 1, 0.5), ValueError, r"n must be <= 1000, got 1001"),
    ((3, 5, 0.5), ValueError, r"l must be <= 3 \(n\), got 5"),
    ((3, -1, 0.5), ValueError, r"l must be >= 0, got -1"),
    ((3, 1.0, 0.5), TypeError, r"l must be an integer, got 1\.0"),
    ((3, 0, 0.5), ValueError, r"n - l must be even, got n = 3, l = 0"),
    ((2, 0, 1.5), ValueError, r"rho must lie in \[0, 1\]"),
    ((2, 0, -0.1), ValueError, r"rho must lie in \[0, 1\]"),
    ((2, 0, [0.5, np.nan]), ValueError, r"rho must lie in \[0, 1\]"),
    ((2, 0, np.inf), ValueError, r"rho must lie in \[0, 1\]"),
])
def test_radial_bad_input(args, exc, match):
    with pytest.raises(exc, match=match):
        zernike_radial(*args)


# -- the basis functions ----------------------------------------------------------------------

def _formula(order, dirs):
    """K_n^l from its definition, with theta, phi from arctan2 and R from zernike_radial."""
    theta = np.arctan2(np.hypot(dirs[:, 0], dirs[:, 1]), dirs[:, 2])
    phi = np.arctan2(dirs[:, 1], dirs[:, 0])
    rho = np.minimum(np.sqrt(2.0) * np.sin(theta / 2), 1.0)
    cols = []
    for n in range(order + 1):
        for l in range(-n, n + 1, 2):
            r = zernike_radial(n, abs(l), rho)
            if l == 0:
                cols.append(np.sqrt((n + 1) / (2 * np.pi)) * r)
            elif l > 0:
                cols.append(np.sqrt((n + 1) / np.pi) * r * np.cos(l * phi))
            else:
                cols.append(np.sqrt((n + 1) / np.pi) * r * np.sin(-l * phi))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("order", [0, 1, 4, 20, 60])
def test_eval_matches_definition(order, unit_vectors):
    d = np.concatenate([unit_vectors(60, upper=True),
                        [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.6, 0.0, 0.8]]])
    zb = HemiZernike(order)
    got, ref = zb.eval(d), _formula(order, d)
    # rho is obtained two ways (sqrt(2) sin(theta/2) vs (x^2 + y^2)/(1 + z)), differing by a
    # few eps relative, which the radial conditioning amplifies as in _radial_atol; cos/sin of
    # l phi by recurrence vs np.cos add ~ l eps; the normalisation is <= sqrt((order+1)/pi)
    for k, (n, l) in enumerate(zip(zb.degree, zb.azimuthal, strict=True)):
        atol = 4 * np.sqrt((n + 1) / np.pi) * (_radial_atol(n, abs(l)) + (abs(l) + 1) * EPS)
        np.testing.assert_allclose(got[:, k], ref[:, k], rtol=0, atol=atol,
                                   err_msg=f"n = {n}, l = {l}")


def test_pole_only_zonal_functions():
    order = 30
    zb = HemiZernike(order)
    y = zb.eval([0.0, 0.0, 1.0])
    zonal = zb.azimuthal == 0
    # rho = 0: R_n^l(0) = 0 for l > 0 exactly (a factor rho^l = 0) ...
    assert np.all(y[~zonal] == 0.0)
    # ... and R_n^0(0) = P_(n/2)(-1) = (-1)^(n/2); the recurrence at x = -1 rounds O(n) times
    n = zb.degree[zonal]
    expect = np.sqrt((n + 1) / (2 * np.pi)) * (-1.0) ** (n // 2)
    np.testing.assert_allclose(y[zonal], expect, rtol=8 * (order + 1) * EPS, atol=0)


def test_horizon_values(rng):
    order = 20
    zb = HemiZernike(order)
    phi = rng.uniform(0, 2 * np.pi, 9)
    d = np.stack([np.cos(phi), np.sin(phi), np.zeros(9)], axis=-1)
    y = zb.eval(d)
    n, l = zb.degree, zb.azimuthal
    # rho = 1 on the horizon, R = 1 there: K = sqrt((n+1)/(2 pi)), sqrt((n+1)/pi) cos / sin
    trig = np.where(l > 0, np.cos(np.outer(phi, np.abs(l))), np.sin(np.outer(phi, np.abs(l))))
    expect = np.where(l == 0, np.sqrt((n + 1) / (2 * np.pi)), np.sqrt((n + 1) / np.pi) * trig)
    # R(1) = 1 up to 8 (n + 1) eps (test above) and cos/sin by recurrence up to ~ l eps
    np.testing.assert_allclose(y, expect, rtol=0, atol=16 * (order + 1) * EPS)


# -- orthonormality ---------------------------------------------------------------------------

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


def _gram_atol(order):
    # the rule's nodes are rounded (|dz| ~ eps) and the products are polynomials of degree
    # <= order in z: Markov's bound gives ~ order^2 eps; observed <= (order + 1)^2 eps / 1.0
    return 2 * (order + 1) ** 2 * EPS


@pytest.mark.parametrize("order", [0, 1, 2, 8, 40])
def test_orthonormal_exact_rule(order):
    zb = HemiZernike(order)
    rule = zb.exact_rule()
    assert rule.domain == "hemisphere"
    assert rule.degree_z >= order and rule.degree_phi >= 2 * order
    np.testing.assert_allclose(_gram(zb), np.eye(zb.size), rtol=0, atol=_gram_atol(order))


def test_orthonormal_order200_radial_blocks():
    # The exact rule is a product: over its n_phi = 401 equispaced azimuths,
    # (1/n_phi) sum_p cos(l phi_p) cos(l' phi_p) is exactly delta_ll' / 2 (1 for l = l' = 0)
    # for l + l' <= 400, so the Gram block of the cosine functions of order l is the z-rule
    # applied to their values on the meridian phi = 0. That checks every radial function of
    # every l at order 200 cheaply; the full-rule check is the slow test below.
    order = 200
    zb = HemiZernike(order)
    rule = zb.exact_rule()
    n_theta, n_phi = rule.shape
    meridian = rule.points.reshape(n_theta, n_phi, 3)[:, 0]
    assert np.all(meridian[:, 1] == 0.0) and np.all(meridian[:, 0] >= 0.0)  # phi = 0 exactly
    ring_w = rule.weights.reshape(n_theta, n_phi).sum(axis=1)
    y = zb.eval(meridian)
    for l in range(order + 1):
        block = y[:, zb.azimuthal == l]
        trig = 1.0 if l == 0 else 0.5
        g = block.T @ ((ring_w * trig)[:, None] * block)
        np.testing.assert_allclose(g, np.eye(g.shape[0]), rtol=0, atol=_gram_atol(order),
                                   err_msg=f"l = {l}")


@pytest.mark.slow
def test_orthonormal_exact_rule_order200_randomized(rng):
    # 20301 functions on 40501 nodes: the full Gram matrix is out of reach (1.7e13 flops);
    # check (G - I) V = 0 for Gaussian V (every entry of G - I enters the result with a
    # weight ~1) plus the exact columns of a few top-order functions
    zb = HemiZernike(200)
    picks = [zb.index(200, l) for l in (-200, 0, 200)]
    v = np.zeros((zb.size, 3 + len(picks)))
    v[:, :3] = rng.normal(size=(zb.size, 3))
    v[picks, 3 + np.arange(len(picks))] = 1.0  # unit columns: exact columns of G
    r = _gram(zb, v) - v
    # entries of G - I are <= _gram_atol(200) = 1.8e-11; a row of 2e4 of them times N(0, 1)
    # gives ~3e-9 at worst; a wrong function or normalisation gives O(1)
    assert np.abs(r).max() <= 1e-8


# -- moments ----------------------------------------------------------------------------------

@pytest.mark.parametrize("order", [0, 1, 2, 5, 30])
def test_moments(order):
    zb = HemiZernike(order)
    # int_H K_n^l dw = 2 int_D K dA: only K_0^0 = 1/sqrt(2 pi) survives (orthogonality to R_0),
    # giving 2 pi / sqrt(2 pi) = sqrt(2 pi)
    none = np.zeros(zb.size)
    none[0] = np.sqrt(2 * np.pi)
    # cos(theta) = 1 - rho^2 = (R_0 - R_2^0)/2 = sqrt(pi/2) K_0^0 - sqrt(pi/6) K_2^0
    # (R_0 = sqrt(2 pi) K_0^0, R_2^0 = sqrt(2 pi / 3) K_2^0), so by orthonormality:
    cos = np.zeros(zb.size)
    cos[0] = np.sqrt(np.pi / 2)
    if order >= 2:
        cos[zb.index(2, 0)] = -np.sqrt(np.pi / 6)
    # exact quadrature, rounding ~ (order + 1) eps (observed 2.8 (order + 1) eps at order 100)
    np.testing.assert_allclose(zb.moments("none"), none, rtol=0, atol=8 * (order + 1) * EPS)
    np.testing.assert_allclose(zb.moments("cos"), cos, rtol=0, atol=8 * (order + 1) * EPS)
    # and the cosine itself: int_H cos = pi (a dot product of two vectors of O(1) entries,
    # at most two of them non-zero: a few roundings)
    assert zb.moments("cos") @ zb.moments("none") == pytest.approx(np.pi, rel=4 * EPS)


def test_moments_bad_weight():
    with pytest.raises(ValueError, match=r"weight must be 'cos' or 'none', got None"):
        HemiZernike(2).moments(None)


# -- edge cases -------------------------------------------------------------------------------

def test_order_zero(unit_vectors):
    zb = HemiZernike(0)
    d = unit_vectors(5, upper=True)
    np.testing.assert_allclose(zb.eval(d), np.full((5, 1), 1 / np.sqrt(2 * np.pi)),
                               rtol=2 * EPS, atol=0)  # one product and one rounding


def test_zero_points():
    zb = HemiZernike(3)
    assert zb.eval(np.empty((0, 3))).shape == (0, 10)
    assert zb.eval(np.empty((0, 4, 3))).shape == (0, 4, 10)


def test_batch_shape(unit_vectors):
    zb = HemiZernike(4)
    d = unit_vectors((2, 3), upper=True)
    y = zb.eval(d)
    assert y.shape == (2, 3, 15)
    np.testing.assert_array_equal(y.reshape(6, 15), zb.eval(d.reshape(6, 3)))  # same kernel
    assert zb.eval(d[1, 2]).shape == (15,)


@pytest.mark.parametrize("order", [0, 2, 5, 7, 8, 12, 33])
def test_blocks_give_the_bits_of_one_direction(order, unit_vectors):
    # Reference: each direction evaluated alone, which runs the scalar per-direction routine;
    # blocks of LANES directions (lane operations, transposed tile writes, below and from
    # order 8) run the same operations in the same order, so equality is bitwise.
    # 2 _TASK + 3 LANES + 5 directions: full blocks, two parallel tasks (on two threads) and
    # a partial last block; the pole, the horizon and near-unit vectors among them.
    from basis.jit import LANES
    from basis.zernike import _TASK

    d = unit_vectors(2 * _TASK + 3 * LANES + 5, upper=True)
    d[:4] = [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [1e-300, 0.0, 1.0]]
    d[4:8] *= 1 + 1e-7
    zb = HemiZernike(order)
    got = zb.eval(d)
    ref = np.stack([zb.eval(w) for w in d])
    np.testing.assert_array_equal(got, ref)
    assert np.array_equal(np.signbit(got), np.signbit(ref))
    out = np.full((d.shape[0], 2 * zb.size), np.nan)[:, ::2]  # not contiguous: a copy
    zb._eval_flat(d, out)
    np.testing.assert_array_equal(out, got)


def test_near_pole_and_tiny_negative_z():
    zb = HemiZernike(6)
    # 1e-300 off the pole is the pole to float64 accuracy
    np.testing.assert_allclose(zb.eval([1e-300, 0.0, 1.0]), zb.eval([0.0, 0.0, 1.0]), rtol=0,
                               atol=1e-15)
    # z = -1e-13 is accepted as rounding and is the horizon to ~1e-13
    np.testing.assert_allclose(zb.eval([1.0, 0.0, -1e-13]), zb.eval([1.0, 0.0, 0.0]), rtol=0,
                               atol=1e-11)


# -- input validation -------------------------------------------------------------------------

@pytest.mark.parametrize("value, exc, match", [
    (-1, ValueError, r"order must be >= 0, got -1"),
    (2.0, TypeError, r"order must be an integer, got 2\.0"),
    ("2", TypeError, r"order must be an integer, got '2'"),
    (True, TypeError, r"order must be an integer, got True"),
    (None, TypeError, r"order must be an integer, got None"),
    (1001, ValueError, r"order must be <= 1000 for HemiZernike, got 1001"),
    (10**12, ValueError, r"order must be <= 1000 for HemiZernike, got 1000000000000"),
])
def test_bad_order(value, exc, match):
    with pytest.raises(exc, match=match):
        HemiZernike(value)


@pytest.mark.parametrize("dirs, exc, match", [
    (np.zeros((4, 2)), ValueError, r"dirs must have shape \(\.\.\., 3\), got shape \(4, 2\)"),
    (0.5, ValueError, r"dirs must have shape \(\.\.\., 3\), got shape \(\)"),
    ([np.nan, 0.0, 1.0], ValueError, r"dirs must be finite: 1 of 1 vectors hold NaN or inf"),
    ([[0.0, 0.0, 1.0], [0.0, -np.inf, 0.0]], ValueError, r"dirs must be finite: 1 of 2"),
    ([0.0, 0.0, 0.0], ValueError, r"zero-length vectors have no direction"),
    ([0.0, 0.0, 2.0], ValueError, r"dirs must be unit vectors: 1 of 1 are not \(first at flat "
                                  r"index 0, norm 2\)"),
    ([0.0, 0.6, -0.8], ValueError, r"dirs must lie in the upper hemisphere z >= 0: 1 of 1 do "
                                   r"not \(first at flat index 0, z = -0\.8\)"),
    ([0.0, 0.0, -1.0], ValueError, r"upper hemisphere"),
    ("x", TypeError, r"dirs must be an array of floats with shape \(\.\.\., 3\), got str"),
])
def test_bad_directions(dirs, exc, match):
    with pytest.raises(exc, match=match):
        HemiZernike(3).eval(dirs)


def test_allocation_limit(monkeypatch, unit_vectors):
    zb = HemiZernike(3)
    d = unit_vectors(11, upper=True)
    # checked before allocating: 10 rows of 10 float64 fit in 800 bytes, 11 do not
    monkeypatch.setattr(validate, "MAX_BYTES", 8 * 10 * zb.size)
    assert zb.eval(d[:10]).shape == (10, zb.size)
    with pytest.raises(MemoryError, match=r"evaluating HemiZernike\(3\) at 11 directions would "
                                          r"need .* \(basis\.validation\.MAX_BYTES\)"):
        zb.eval(d)
    with pytest.raises(MemoryError, match=r"MAX_BYTES"):
        HemiZernike(40).moments("cos")  # moments evaluate on a rule: the same guard applies
