"""project.project: the fast product rule against a dense product rule, closed forms, errors.

The independent reference is a dense product quadrature: every basis function evaluated by
``basis.eval`` at every node of ``hemisphere_rule`` for both directions and the BRDF at every
pair, no FFT and no radial tables. For BRDFs that are polynomials in the direction components
both rules are exact, so they must agree to rounding.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from basis import (
    CoefficientMatrix,
    HemiHarmonics,
    HemiZernike,
    SphericalHarmonics,
    hemisphere_rule,
)
from project.brdf import BRDF, MirrorDelta, as_color
from project.quadrature import _z_nodes, default_quantity, project, radial_table


class Poly(BRDF):
    """A reciprocal polynomial BRDF; anisotropic unless ``aniso`` is 0."""

    def __init__(self, aniso: float = 0.3, scale=1.0, reciprocal=True):
        self.s = as_color(scale, "scale")
        self.channels, self._scalar = self.s.size, np.ndim(scale) == 0
        self.aniso = aniso
        self.isotropic = aniso == 0
        self.reciprocal = reciprocal

    def _eval(self, wi, wo):
        dot = np.sum(wi * wo, axis=-1)
        v = 1.0 + 0.5 * dot**2 + wi[:, 2] * wo[:, 2] + 0.25 * (wi[:, 2] + wo[:, 2]) ** 3
        xy = wi[:, 0] * wi[:, 1] * wo[:, 0] * wo[:, 1]
        v = v + self.aniso * (wi[:, 0] * wo[:, 0] - wi[:, 1] * wo[:, 1] + xy)
        if not self.reciprocal:
            v = v + 0.2 * wi[:, 2]
        return (v / 4.0)[:, None] * self.s


class Const(BRDF):
    def __init__(self, a):
        self.a = as_color(a, "a")
        self.channels, self._scalar = self.a.size, np.ndim(a) == 0

    def _eval(self, wi, wo):
        return np.broadcast_to(self.a / np.pi, (wi.shape[0], self.channels))


def dense(brdf, basis, quantity, n):
    rule = hemisphere_rule(n, 2 * n)
    p = rule.points
    bw = basis.eval(p) * rule.weights[:, None]
    f = brdf.eval(p[:, None, :], p[None, :, :])
    if f.ndim == 2:
        f = f[..., None]
    if quantity == "f_cos":
        f = f * (p[:, 2, None] * p[None, :, 2])[..., None]
    return np.einsum("aj,abc,bk->cjk", bw, f, bw)


@pytest.mark.filterwarnings("ignore:the expansion of Poly")  # low orders miss 20-30 %
@pytest.mark.parametrize("basis", [HemiZernike(5), HemiHarmonics(6), SphericalHarmonics(3)])
@pytest.mark.parametrize("quantity", ["f", "f_cos"])
@pytest.mark.parametrize("aniso", [0.0, 0.3])
def test_polynomial_brdf_matches_dense_rule(basis, quantity, aniso):
    brdf = Poly(aniso, scale=[1.0, 0.5, 2.0])
    cm = project(brdf, basis, quantity=quantity)
    # degree <= 2 * order + 6 in each direction: 12 Gauss nodes and 24 azimuths are exact
    ref = dense(brdf, basis, quantity, 12)
    assert cm.is_isotropic == (aniso == 0)
    assert cm.channels == 3
    # both exact; entries are sums of ~1e3 terms: rounding ~1e-14 relative to max |M|
    scale = np.max(np.abs(ref))
    np.testing.assert_allclose(cm.matrix, ref, rtol=0, atol=1e-13 * scale)
    # the estimate compares with the previous (inexact) rule, so it only has to meet tol
    assert cm.info["converged"] and cm.info["error_estimate"] <= 1e-6 * scale  # default tol
    assert cm.info["method"] == "quadrature"


def test_non_reciprocal_brdf_is_symmetrised_on_request():
    brdf = Poly(0.3, reciprocal=False)
    cm = project(brdf, HemiZernike(4), quantity="f_cos", reciprocal=True)
    assert cm.reciprocal and cm.info["reciprocal"]
    ref = dense(brdf, HemiZernike(4), "f_cos", 10)[0]
    # the reciprocal part is the orthogonal projection (M + M^T)/2; rounding as above
    np.testing.assert_allclose(cm.matrix, 0.5 * (ref + ref.T), rtol=0, atol=1e-13)
    assert cm.info["asymmetry"] > 1e-3


def test_lambert_is_one_coefficient():
    a = 0.5
    # f = a / pi = 2 a K_0^0(wi) K_0^0(wo) with K_0^0 = 1/sqrt(2 pi)
    cm = project(Const(a), HemiZernike(6), quantity="f")
    want = np.zeros((28, 28))
    want[0, 0] = 2 * a
    # sums of ~1e3 products of size ~1 that cancel: rounding ~1e-14
    np.testing.assert_allclose(cm.matrix, want, rtol=0, atol=1e-14)
    # Westin's form: f cos cos = (2a/3) b_10 b_10 for b_10 = sqrt(3/(2 pi)) z
    hb = HemiHarmonics(5)
    cm = project(Const(a), hb)
    k = hb.index(1, 0)
    want = np.zeros((hb.size, hb.size))
    want[k, k] = 2 * a / 3
    np.testing.assert_allclose(cm.matrix, want, rtol=0, atol=1e-14)


def test_mirror_term_albedo_exact_in_zernike():
    # constant 1 and z are in the span of HemiZernike(>= 2), so the projected albedo of
    # Lambert + mirror is exactly a + s at every incidence (see quadrature._add_deltas)
    brdf = Const([0.5, 0.3, 0.1])
    brdf.delta = (MirrorDelta([0.02, 0.2, 0.4]),)
    cm = project(brdf, HemiZernike(8))
    w = np.stack([np.sin(t := np.radians([0, 30, 60, 85, 89])), 0 * t, np.cos(t)], axis=-1)
    np.testing.assert_allclose(cm.albedo(w), np.tile([0.52, 0.5, 0.5], (5, 1)), rtol=0,
                               atol=1e-12)  # 1/cos theta_i <= 57 amplifies rounding ~1e-15


def test_mirror_term_coefficients_closed_form():
    # for the mirror, int_H b_j(w) b_k(mirror w) z dw = (-1)^m delta_{m_j m_k} int P_j P_k z:
    # check against a dense rule over one hemisphere
    brdf = Const(0.0)
    brdf.delta = (MirrorDelta(lambda c: (0.04 + 0.96 * (1 - c) ** 5)[:, None], channels=1),)
    zb = HemiZernike(6)
    cm = project(brdf, zb)
    rule = hemisphere_rule(200, 16)
    p = rule.points
    r = 0.04 + 0.96 * (1 - p[:, 2]) ** 5
    mirror = p * np.array([-1.0, -1.0, 1.0])
    ref = np.einsum("a,aj,ak->jk", rule.weights * r * p[:, 2], zb.eval(p), zb.eval(mirror))
    np.testing.assert_allclose(cm.matrix, ref, rtol=0, atol=1e-13)


def test_mirror_needs_f_cos():
    brdf = Const(0.5)
    brdf.delta = (MirrorDelta(0.1),)
    with pytest.raises(ValueError, match="quantity must be 'f_cos' for a BRDF with mirror"):
        project(brdf, HemiZernike(4), quantity="f")


def test_radial_table_separates_the_basis(rng):
    zb = HemiHarmonics(7)
    z = rng.uniform(0, 1, 20)
    phi = rng.uniform(0, 2 * np.pi, 20)
    s = np.sqrt(1 - z * z)
    d = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1)
    az = zb.azimuthal
    ang = np.where(az > 0, np.cos(np.abs(az) * phi[:, None]),
                   np.where(az < 0, np.sin(np.abs(az) * phi[:, None]), 1.0))
    np.testing.assert_allclose(radial_table(zb, z) * ang, zb.eval(d), rtol=0, atol=1e-13)


@pytest.mark.filterwarnings("ignore:the expansion of Poly")  # order 3 misses 19 %
def test_montecarlo_agrees_within_its_error():
    brdf = Poly(0.0)
    zb = HemiZernike(3)
    ref = project(brdf, zb).matrix
    cm = project(brdf, zb, method="montecarlo", samples=1 << 12, seed=3)
    err = np.abs(cm.matrix - ref)
    se = cm.info["standard_error"][..., 0]
    # randomised QMC: the spread of 8 scrambles; 6 sigma over 100 entries, floor for zeros
    assert np.all(err <= 6 * se + 1e-12)
    assert cm.info["error_estimate"] < 1e-2


@pytest.mark.filterwarnings("ignore:the expansion of Poly")
def test_lstsq_method_recovers_polynomial():
    brdf = Poly(0.0)
    zb = HemiZernike(6)  # f_cos of Poly is degree <= 8 in z: not exactly in the span
    ref = project(brdf, zb)
    cm = project(brdf, zb, method="lstsq")
    assert cm.info["method"] == "lstsq"
    # the least-squares fit to a function outside the span differs from the L2 projection
    # by about the truncation error; both are near
    assert np.max(np.abs(cm.matrix - ref.matrix)) < 0.05 * np.max(np.abs(ref.matrix))


def test_sharp_lobe_warns_gibbs_and_not_converged():
    class Spike(BRDF):
        def _eval(self, wi, wo):
            c = np.clip(np.sum(wi * np.array([-1.0, -1.0, 1.0]) * wo, axis=-1), 0, None)
            return (501 / (2 * np.pi) * c**500)[:, None]

    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        cm = project(Spike(), HemiZernike(4), max_nodes=64)
    msgs = [str(w.message) for w in rec]
    assert any("did not reach tol" in m for m in msgs)
    assert any("in HemiZernike(4) misses" in m and "too sharp" in m for m in msgs)
    assert not cm.info["converged"] and cm.info["truncation_error"] > 0.1


@pytest.mark.filterwarnings("ignore:the expansion of Poly")
def test_fixed_nodes_give_error_estimate():
    cm = project(Poly(0.0), HemiZernike(4), quantity="f_cos", nodes=(12, 24))
    # 12 nodes are exact (degree <= 14 in z, 8 in phi), but half of them (6) are not
    assert cm.info["nodes"] == (12, 24) and 1e-12 < cm.info["error_estimate"] < 1e-2
    np.testing.assert_allclose(cm.matrix, dense(Poly(0.0), HemiZernike(4), "f_cos", 12)[0],
                               rtol=0, atol=1e-13)


def test_sqrt_z_rule_is_exact_on_half_integer_powers():
    # int_0^1 z^(k - 1/2) dz = 2 / (2 k + 1): in t = sqrt(z) the integrand is 2 t^(2k), a
    # polynomial of degree 2k <= 2n - 1, so the n-point rule is exact up to rounding
    n = 8
    k = np.arange(n)
    z, w = _z_nodes(n, "sqrt")
    got = np.sum(w[:, None] * z[:, None] ** (k - 0.5), axis=0)
    np.testing.assert_allclose(got, 2.0 / (2 * k + 1), rtol=1e-14, atol=0)
    # Gauss in z misses 1/sqrt(z) by ~1 / n (this is what the sqrt rule is for)
    z, w = _z_nodes(n, "gauss")
    assert abs(np.sum(w / np.sqrt(z)) - 2.0) > 0.05


class SqrtSeparable(BRDF):
    """g(w_i) g(w_o) with g = (1 + x / 2 + x y / 4 + z) / sqrt(z): anisotropic, reciprocal,
    ~ 1/sqrt(cos theta) at the horizon like Ward's original lobe; M = c c^T exactly."""

    isotropic = False

    @staticmethod
    def g(w):
        x, y, z = w[..., 0], w[..., 1], w[..., 2]
        with np.errstate(divide="ignore"):
            return np.where(z > 0, (1 + x / 2 + x * y / 4 + z) / np.sqrt(z), 0.0)

    def _eval(self, wi, wo):
        return (self.g(wi) * self.g(wo))[:, None]


def _sqrt_separable_reference(basis):
    """c_j = int g b_j dw: azimuth by the uniform rule (exact: trigonometric polynomials of
    degree <= order + 2), z by QUADPACK's algebraic-weight rule (QAWS, weight z^(-1/2)),
    independent of the product rule under test."""
    from scipy.integrate import quad

    nphi = 2 * basis.order + 8
    phi = 2 * np.pi * np.arange(nphi) / nphi

    def h(z, j):  # sqrt(z) g(w) b_j(w) integrated over phi
        s = np.sqrt(max(0.0, 1 - z * z))
        w = np.stack([s * np.cos(phi), s * np.sin(phi), np.full(nphi, z)], axis=-1)
        x, y = w[:, 0], w[:, 1]
        return 2 * np.pi / nphi * np.sum((1 + x / 2 + x * y / 4 + z) * basis.eval(w)[:, j])

    return np.array([quad(h, 0, 1, args=(j,), weight="alg", wvar=(-0.5, 0.0),
                          epsabs=1e-14, epsrel=1e-13)[0] for j in range(basis.size)])


@pytest.mark.filterwarnings("ignore:the expansion of SqrtSeparable")  # ||q|| is infinite
def test_horizon_singularity_takes_the_sqrt_z_rule():
    zb = HemiZernike(4)
    c = _sqrt_separable_reference(zb)
    ref = np.outer(c, c)
    scale = np.max(np.abs(ref))
    cm = project(SqrtSeparable(), zb, quantity="f", tol=1e-9)
    assert cm.info["z_rule"] == "sqrt" and cm.info["converged"]
    # the sqrt rule is exact in z here and the azimuths are trigonometric polynomials: the
    # error is QUADPACK's (1e-13) plus rounding; 1e-11 leaves room without hiding 1/n errors
    np.testing.assert_allclose(cm.matrix, ref, rtol=0, atol=1e-11 * scale)
    # the fixed-node rule is Gauss in z: off by ~1/n (what the test would see without the
    # sqrt rule)
    fixed = project(SqrtSeparable(), zb, quantity="f", nodes=cm.info["nodes"])
    assert np.max(np.abs(fixed.matrix - ref)) > 1e-3 * scale


@pytest.mark.filterwarnings("ignore:the expansion of Poly")
def test_reciprocal_half_grid_equals_full_grid():
    # a reciprocal BRDF samples only z_i <= z_o; declaring it non-reciprocal samples all
    # pairs: same nodes (fixed), same sums up to rounding, norm included
    poly = Poly(0.3, scale=[1.0, 0.5])

    class Undeclared(BRDF):  # the same function, not declared reciprocal
        channels, isotropic, reciprocal, _scalar = 2, False, False, False

        def _eval(self, wi, wo):
            return poly._eval(wi, wo)

    half = project(poly, HemiZernike(5), nodes=(9, 24))
    full = project(Undeclared(), HemiZernike(5), nodes=(9, 24))
    scale = np.max(np.abs(full.matrix))
    np.testing.assert_allclose(half.matrix, full.matrix, rtol=0, atol=1e-13 * scale)
    assert half.info["asymmetry"] == 0.0
    # sqrt(1 - ||M||^2 / ||q||^2) resolves ~1e-8 (see truncation_error); a wrong weight of
    # the folded pairs in ||q||^2 would move it by > 0.1
    assert half.info["truncation_error"] == pytest.approx(full.info["truncation_error"],
                                                          rel=0, abs=1e-8)


class Twisted(BRDF):
    """(1 + (z_i - z_o) (w_i x w_o)_z / 2) / pi: isotropic and reciprocal (swapping the two
    directions flips both factors) but odd under the mirror y -> -y, like measured tables
    that are not bilaterally symmetric. Its even part in dphi is Lambert's 1 / pi."""

    isotropic = True

    def _eval(self, wi, wo):
        cross = wi[:, 0] * wo[:, 1] - wi[:, 1] * wo[:, 0]
        return ((1.0 + 0.5 * (wi[:, 2] - wo[:, 2]) * cross) / np.pi)[:, None]


def test_mirror_asymmetric_isotropic_brdf_projects_its_even_part():
    # the isotropic blocks hold cos(m dphi) terms only: the projection is that of the even
    # part, Lambert with albedo 1, whose only coefficient is 2 on b_0 b_0 (see
    # test_lambert_is_one_coefficient); the odd part integrates to exactly 0 against every
    # product of blocks, so any leak of it is an error
    zb = HemiZernike(6)
    cm = project(Twisted(), zb, quantity="f")
    want = np.zeros((zb.size, zb.size))
    want[0, 0] = 2.0
    # polynomial in the components: both triangles' rules are exact; rounding ~1e-14
    np.testing.assert_allclose(cm.matrix, want, rtol=0, atol=1e-13)
    # folding z_i >= z_o onto z_i <= z_o (right only for even BRDFs) leaks the odd part
    from project.quadrature import _iso_rule

    folded = _iso_rule(Twisted(), zb, "f", 12, 24, fold=True)[0]
    leak = max(np.max(np.abs(b[..., 0] - b[..., 0].T) + np.abs(b[..., 0])) for b in folded[1:])
    assert leak > 1e-3


@pytest.mark.parametrize("brdf", [Poly(0.0), Twisted()], ids=["even", "twisted"])
def test_diagonal_rule_matches_tensor_rule(brdf):
    # the diagonal rule in (s, d) is exact for polynomials once its n / 2 nodes per panel
    # cover the degree (d = D(s) tau^3 triples it); the tensor Gauss rule is exact too
    from project.quadrature import _iso_rule

    zb = HemiZernike(5)
    fold = isinstance(brdf, Poly)
    ref = _iso_rule(brdf, zb, "f", 16, 24, fold=fold)[0]
    got = _iso_rule(brdf, zb, "f", 48, 24, zmap="diagonal", fold=fold)[0]
    scale = max(np.max(np.abs(b)) for b in ref)
    for g, r in zip(got, ref, strict=True):  # blocks: sums of ~1e3 terms, rounding 1e-14
        np.testing.assert_allclose(0.5 * (g + g.swapaxes(0, 1)), 0.5 * (r + r.swapaxes(0, 1)),
                                   rtol=0, atol=1e-13 * scale)


@pytest.mark.parametrize("kwargs, exc, match", [
    (dict(quantity="g"), ValueError, r"quantity must be one of 'auto', 'f_cos', 'f', got 'g'"),
    (dict(method="mc"), ValueError, r"method must be one of"),
    (dict(tol=0.0), ValueError, r"tol must be a number in \(0, 1\), got 0.0"),
    (dict(nodes=(4, 3)), ValueError, r"nodes must be \(n_z >= 1, n_phi >= 2 \* order \+ 2"),
    (dict(method="montecarlo", samples=1), ValueError, r"samples must be >= 2"),
])
def test_bad_arguments(kwargs, exc, match):
    with pytest.raises(exc, match=match):
        project(Const(0.5), HemiZernike(4), **kwargs)


def test_bad_brdf_and_basis():
    with pytest.raises(TypeError, match="brdf must have eval"):
        project(object(), HemiZernike(2))
    with pytest.raises(TypeError, match="basis must be a basis object"):
        project(Const(0.5), "zernike")

    class Bad(BRDF):
        def _eval(self, wi, wo):
            return np.full((wi.shape[0], 1), np.nan)

    with pytest.raises(ValueError, match="returned non-finite values"):
        project(Bad(), HemiZernike(2))


# -- the analytic models and measured data ----------------------------------------------------
from project import models  # noqa: E402
from project.measured import read_merl  # noqa: E402


@pytest.mark.parametrize("k", [1, 2, 3])
def test_minnaert_with_integer_exponent_terminates(k):
    # f cos cos = c (z_i z_o)^k, and z^k = (1 - rho^2)^k is a combination of R_2j^0, j <= k:
    # every coefficient of degree > 2k vanishes and order 2k represents it exactly
    cm = project(models.Minnaert(k, 0.6), HemiZernike(2 * k + 4))
    deg = cm.basis.degree
    high = (deg[:, None] > 2 * k) | (deg[None, :] > 2 * k)
    scale = np.max(np.abs(cm.matrix))
    assert np.max(np.abs(cm.matrix[high])) <= 1e-14 * scale  # rounding of exact rules
    assert np.max(np.abs(cm.matrix[~high])) > 0.01 * scale
    # the Parseval estimate resolves ~1e-8 (a difference of squares, see truncation_error)
    assert cm.info["truncation_error"] < 1e-6


def test_lambert_model_is_one_mode():
    cm = project(models.Lambert([0.2, 0.5, 0.8]), HemiZernike(8), quantity="f")
    modes = cm.to_modes()
    # f = a / pi = 2 a K_0^0 K_0^0: the first mode is 2a, the rest rounding
    np.testing.assert_allclose(modes[:, 0], [0.4, 1.0, 1.6], rtol=1e-14)
    assert np.max(np.abs(modes[:, 1:])) < 1e-14


@pytest.mark.parametrize("distribution", ["beckmann", "ggx"])
def test_cook_torrance_error_falls_with_order(distribution):
    brdf = models.CookTorrance(0.3, 0.4, distribution=distribution, ior=1.5)
    errors = []
    for order in (2, 4, 8, 12):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # order 2 misses > 10 %
            cm = project(brdf, HemiZernike(order), quantity="f_cos")
        assert cm.info["converged"]
        errors.append(cm.info["truncation_error"])
    # a converging sequence (seen: 0.21, 0.15, 0.075, 0.039 Beckmann; 0.13, 0.091, 0.044,
    # 0.025 GGX): decreasing, and from order 4 on each step at least a factor 1.5
    assert all(b < a for a, b in zip(errors, errors[1:], strict=False)), errors
    assert errors[2] < errors[1] / 1.5 and errors[3] < errors[2] / 1.5, errors
    assert errors[-1] < 0.05


def test_projected_albedo_matches_the_model():
    brdf = models.Phong(0.3, 0.5, 20)
    cm = project(brdf, HemiZernike(16))
    assert cm.info["truncation_error"] < 0.03
    wi = np.stack([np.sin(t := np.radians([0.0, 30.0, 60.0])), 0 * t, np.cos(t)], axis=-1)
    # the albedo integrates the truncated expansion exactly; its error is the projection
    # error of a(theta) cos(theta), which is smooth: 2e-3 leaves ~5x margin over what is seen
    np.testing.assert_allclose(cm.albedo(wi), brdf.albedo(wi), rtol=0, atol=2e-3)


@pytest.mark.filterwarnings("ignore:the expansion of CookTorrance")  # order 8 misses 15 %
def test_projection_is_reciprocal_to_rounding(unit_vectors):
    cm = project(models.CookTorrance(0.2, 0.3, distribution="ggx", ior=1.5), HemiZernike(8),
                 tol=1e-6)
    wi, wo = unit_vectors(200, upper=True), unit_vectors(200, upper=True)
    a, b = cm.eval(wi, wo), cm.eval(wo, wi)
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)


def test_glossy_paint_mirror_is_exact_in_albedo():
    cm = project(models.GlossyPaint([0.5, 0.4, 0.3], 0.02), HemiZernike(8))
    wi = np.stack([np.sin(t := np.radians([0.0, 45.0, 80.0])), 0 * t, np.cos(t)], axis=-1)
    # see test_mirror_term_albedo_exact_in_zernike; 1 / cos(80 deg) = 5.8 amplifies rounding
    np.testing.assert_allclose(cm.albedo(wi), np.tile([0.52, 0.42, 0.32], (3, 1)), atol=1e-12)
    assert cm.info["truncation_error"] is None  # a delta has no finite L2 norm


@pytest.mark.filterwarnings("ignore:the expansion of MERLBRDF")  # order 8 misses 36 %
def test_merl_surrogate_projects_all_channels(merl_surrogate):
    brdf = read_merl(merl_surrogate("gold-metallic-paint"))
    cm = project(brdf, HemiZernike(8), tol=1e-3)
    assert cm.channels == 3 and cm.is_isotropic and cm.info["converged"]
    w = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, np.sqrt(0.75)]])
    # trilinear table data converge algebraically; the order-8 truncation misses ~36 % of
    # the L2 norm, but the albedo (an integral) is far more accurate: 5 % bound
    np.testing.assert_allclose(cm.albedo(w), brdf.albedo(w, n_theta=128, n_phi=256),
                               rtol=0.05)


# -- the default quantity: accurate on all of H x H --------------------------------------------
def _uniform_pairs(n, seed=12345):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(2):
        z, phi = rng.random(n), 2 * np.pi * rng.random(n)
        s = np.sqrt((1 - z) * (1 + z))
        out.append(np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1))
    return out


@pytest.mark.parametrize("b, want", [(HemiZernike(12), "f"), (HemiHarmonics(12), "f_cos"),
                                     (HemiHarmonics(12, parity="even"), "f")], ids=repr)
def test_default_is_accurate_over_the_whole_hemisphere(b, want):
    # Phong (0.3, 0.4, 20) evaluated as a user would, at pairs uniform in solid angle over all
    # of H x H (grazing included). The old default (f_cos in HemiZernike) gave a relative RMS
    # error of 84 and |f_hat| up to 5,000 max f (the negative control below).
    brdf = models.Phong(0.3, 0.4, 20)
    wi, wo = _uniform_pairs(100_000)
    f = brdf.eval(wi, wo)
    cm = project(brdf, b)
    assert cm.quantity == want == default_quantity(b, brdf)
    fh = cm.eval(wi, wo)
    rms = np.sqrt(np.mean((fh - f) ** 2) / np.mean(f**2))
    assert rms <= 0.2 and np.max(np.abs(fh)) <= 3 * np.max(f)
    if want == "f":
        # the L2 error of f over H x H is the Parseval truncation error; the Monte Carlo
        # estimate of it agrees within its sampling error (seen: 0.0606 vs 0.0602)
        assert rms == pytest.approx(cm.info["truncation_error"], rel=0.05)
    if isinstance(b, HemiZernike):
        with warnings.catch_warnings():  # negative control: misses 11 % of the norm of q
            warnings.simplefilter("ignore", RuntimeWarning)
            bad = project(brdf, b, quantity="f_cos").eval(wi, wo)
        assert np.sqrt(np.mean((bad - f) ** 2) / np.mean(f**2)) > 10


def test_default_keeps_mirror_terms_in_f_cos():
    brdf = models.GlossyPaint(0.5, 0.05)
    assert default_quantity(HemiZernike(4), brdf) == "f_cos"
    assert project(brdf, HemiZernike(4)).quantity == "f_cos"


# -- general (non-reciprocal) projection ------------------------------------------------------
@pytest.mark.parametrize("aniso", [0.0, 0.3])
def test_non_reciprocal_brdf_gets_the_general_matrix(aniso):
    # reference: the dense product rule, not symmetrised; both exact for the polynomial
    brdf = Poly(aniso, reciprocal=False)
    b = HemiZernike(4)
    cm = project(brdf, b, quantity="f_cos")  # reciprocal=None follows brdf.reciprocal
    ref = dense(brdf, b, "f_cos", 10)[0]
    assert not cm.reciprocal and cm.is_isotropic == (aniso == 0)
    # rounding of sums of ~1e3 terms: 1e-13 relative to max |M| (~1)
    np.testing.assert_allclose(cm.matrix, ref, rtol=0, atol=1e-13)
    assert np.max(np.abs(ref - ref.T)) > 1e-3
    forced = project(Poly(aniso), b, quantity="f_cos", reciprocal=False)
    # a reciprocal BRDF in the general form: symmetric to rounding
    assert not forced.reciprocal
    np.testing.assert_allclose(forced.matrix, forced.matrix.T, rtol=0, atol=1e-13)


class Products(BRDF):
    """q = f cos(theta_i) cos(theta_o) = b(w_i)^T M0 b(w_o) for a general isotropic M0 in
    the odd HemiHarmonics(5) (which vanish on the horizon like cos theta, so f is finite),
    evaluated from ``basis.eval`` (not from the fused evaluator): the exact expansion of q
    is M0."""

    isotropic, reciprocal = True, False

    def __init__(self, seed=3):
        rng = np.random.default_rng(seed)
        self.basis = HemiHarmonics(5)
        blocks = [rng.normal(size=(i.size, i.size)) * 0.3 ** np.arange(i.size)
                  for i in self.basis.azimuthal_blocks().cos]
        blocks[0][0, 0] = 4.0
        from basis import CoefficientMatrix

        self.m0 = CoefficientMatrix.from_blocks(self.basis, blocks, reciprocal=False).matrix

    def _eval(self, wi, wo):
        b = self.basis
        q = np.einsum("nj,jk,nk->n", b.eval(wi), self.m0, b.eval(wo))
        zz = wi[:, 2] * wo[:, 2]
        return np.divide(q, zz, out=np.zeros_like(q), where=zz > 0)[:, None]


@pytest.mark.filterwarnings("ignore:the expansion of Products")  # the symmetric one: floor
def test_general_projection_is_exact_and_the_symmetric_one_stops_at_the_floor():
    from project import reciprocity

    brdf = Products()
    b = brdf.basis
    gen = project(brdf, b, quantity="f_cos")
    sym = project(brdf, b, quantity="f_cos", reciprocal=True)
    # a polynomial of degree 5 per direction: the Gauss rules are exact; rounding 1e-13
    np.testing.assert_allclose(gen.matrix, brdf.m0, rtol=0, atol=1e-13 * np.abs(brdf.m0).max())
    np.testing.assert_allclose(sym.matrix, 0.5 * (brdf.m0 + brdf.m0.T), rtol=0,
                               atol=1e-13 * np.abs(brdf.m0).max())
    # Parseval: ||q - q_sym|| / ||q|| = ||(M0 - M0^T) / 2|| / ||M0|| (the subtraction in
    # truncation_error resolves ~1e-8)
    floor = np.linalg.norm(0.5 * (brdf.m0 - brdf.m0.T)) / np.linalg.norm(brdf.m0)
    assert gen.info["truncation_error"] < 1e-6
    assert sym.info["truncation_error"] == pytest.approx(floor, rel=1e-6)
    assert gen.info["antisymmetric_part"] == pytest.approx(floor, rel=1e-10)
    # the independent estimate of the floor from sampled pairs: within 3 standard errors
    rec = reciprocity(brdf, n=2**15)
    assert abs(sym.info["truncation_error"] - rec.floor) <= 3 * rec.floor_stderr + 1e-9


class TwistedNonReciprocal(BRDF):
    """(1 + 0.3 z_i + (z_i + z_o) (w_i x w_o)_z / 2) / pi: isotropic, neither reciprocal nor
    mirror symmetric (the last term is odd under y -> -y and under swapping). Its even part
    in dphi is (1 + 0.3 z_i) / pi."""

    isotropic, reciprocal = True, False

    def _eval(self, wi, wo):
        cross = wi[:, 0] * wo[:, 1] - wi[:, 1] * wo[:, 0]
        return ((1.0 + 0.3 * wi[:, 2] + 0.5 * (wi[:, 2] + wo[:, 2]) * cross) / np.pi)[:, None]


class EvenPart(BRDF):
    isotropic, reciprocal = True, False

    def _eval(self, wi, wo):
        return ((1.0 + 0.3 * wi[:, 2] + 0.0 * wo[:, 2]) / np.pi)[:, None]


@pytest.mark.filterwarnings("ignore:the expansion of TwistedNonReciprocal")  # the odd part
def test_non_mirror_non_reciprocal_isotropic_projects_its_even_part():
    # without the mirror the blocks need both signs of dphi: the odd part integrates to 0
    # against every cos(m dphi) only over the whole turn. Reference: the dense rule on the
    # even part (a polynomial: exact)
    zb = HemiZernike(4)
    cm = project(TwistedNonReciprocal(), zb, quantity="f")
    ref = dense(EvenPart(), zb, "f", 10)[0]
    assert not cm.reciprocal and np.max(np.abs(ref - ref.T)) > 1e-3
    np.testing.assert_allclose(cm.matrix, ref, rtol=0, atol=1e-12)
    sym = project(TwistedNonReciprocal(), zb, quantity="f", reciprocal=True)
    np.testing.assert_allclose(sym.matrix, 0.5 * (ref + ref.T), rtol=0, atol=1e-12)


def test_general_montecarlo_agrees_with_quadrature():
    brdf = Poly(0.0, reciprocal=False)
    b = HemiZernike(3)
    mc = project(brdf, b, quantity="f", method="montecarlo", samples=2**12)
    ref = project(brdf, b, quantity="f")
    assert not mc.reciprocal
    # 5 standard errors of the 8-scramble estimate (entrywise max)
    assert np.max(np.abs(mc.matrix - ref.matrix)) <= 5 * mc.info["error_estimate"]


def test_reciprocal_argument_errors():
    with pytest.raises(TypeError, match="reciprocal must be None, True or False, got 1"):
        project(Poly(0.0), HemiZernike(2), reciprocal=1)


class GeneralMatrix(BRDF):
    """q = b(w_i)^T M b(w_o) for a fixed non-symmetric M: in the span of the basis."""

    channels, isotropic, reciprocal = 1, False, False

    def __init__(self, cm):
        self.cm = cm

    def _eval(self, wi, wo):
        return self.cm.eval(wi, wo)[:, None]


def test_general_lstsq_recovers_a_matrix_in_the_span():
    # independent reference: the known matrix itself; quadrature gives it too (exact rule)
    zb = HemiZernike(3)
    m = np.random.default_rng(5).normal(size=(zb.size, zb.size))
    truth = CoefficientMatrix(zb, m, "f", isotropic=False, reciprocal=False)
    got = project(GeneralMatrix(truth), zb, quantity="f", method="lstsq")
    assert not got.reciprocal and got.info["reciprocal"] is False
    # noise-free data in the span: rounding amplified by the condition number
    tol = 100 * got.info["condition_number"] * np.finfo(float).eps * np.abs(m).max()
    np.testing.assert_allclose(got.matrix, m, rtol=0, atol=tol)
    # m's antisymmetric half is as large as its symmetric half: the symmetric fit predicts
    # held-out pairs no better than zero, and says so
    with pytest.warns(RuntimeWarning, match="predicts held-out samples"):
        sym = project(GeneralMatrix(truth), zb, quantity="f", method="lstsq", reciprocal=True)
    # a symmetric matrix cannot hold the antisymmetric half of m
    assert sym.reciprocal and np.array_equal(sym.matrix, sym.matrix.T)
    assert np.linalg.norm(sym.matrix - m) > 0.5 * np.linalg.norm(0.5 * (m - m.T))


# -- nested azimuth rules and the error estimates ----------------------------------------------
class Counting(BRDF):
    """Poly(0) that records every pair it is evaluated at."""

    def __init__(self):
        self.inner, self.seen = Poly(0.0), []

    def _eval(self, wi, wo):
        self.seen.append(np.concatenate([wi, wo], axis=1))
        return self.inner._eval(wi, wo)


@pytest.mark.parametrize("zmap, grading", [("gauss", 1), ("diagonal", 6)])
def test_azimuth_refinement_evaluates_only_the_new_nodes(zmap, grading):
    from project.quadrature import _iso_rule, _IsoGrid

    zb, brdf = HemiZernike(5), Counting()
    grid = _IsoGrid(brdf, zb, "f", 8, zmap, grading, nd=12)
    grid.sample(24)  # 12 intervals: 13 azimuths per pair
    pairs = grid.zi.size
    assert grid.evaluations == pairs * 13 == sum(len(s) for s in brdf.seen)
    grid.refine()  # 24 intervals: the 12 new (odd) azimuths only
    assert grid.evaluations == pairs * 25 == sum(len(s) for s in brdf.seen)
    # the samples are exactly the nodes of the 48-azimuth rule, each evaluated once: the
    # independent reference is that rule sampled from scratch (rows compared bit for bit)
    fresh = Counting()
    want, ev, _ = _iso_rule(fresh, zb, "f", 8, 48, grading, zmap, nd=12)
    seen, ref = np.concatenate(brdf.seen), np.concatenate(fresh.seen)
    assert ev == pairs * 25 and len(np.unique(seen, axis=0)) == len(seen)
    np.testing.assert_array_equal(np.unique(seen, axis=0), np.unique(ref, axis=0))
    got, err, _ = grid.result()
    scale = max(np.max(np.abs(b)) for b in want)
    for g, w in zip(got, want, strict=True):  # same sums in another order: rounding 1e-14
        np.testing.assert_allclose(g, w, rtol=0, atol=1e-13 * scale)
    # the estimate is the change from the rule of the even nodes, the 24-azimuth rule
    half = _iso_rule(Poly(0.0), zb, "f", 8, 24, grading, zmap, nd=12)[0]
    change = max(np.max(np.abs(g - h)) for g, h in zip(got, half, strict=True))
    assert abs(err - change) <= 1e-13 * scale


class Bessel(BRDF):
    """f = exp(kappa (x_i x_o + y_i y_o)) = exp(kappa s_i s_o cos(dphi)).

    Its azimuthal transforms are known in closed form: F_m = 2 pi I_m(kappa s_i s_o)
    (Abramowitz & Stegun 9.6.19), so the azimuth rules' error can be measured exactly.
    """

    def __init__(self, kappa):
        self.kappa = kappa

    def _eval(self, wi, wo):
        return np.exp(self.kappa * (wi[:, 0] * wo[:, 0] + wi[:, 1] * wo[:, 1]))[:, None]


def bessel_blocks(kappa, basis, nz):
    """Blocks c_m P^T W F_m W P with the exact F_m and Gauss-Legendre in z (numpy only)."""
    from scipy.special import iv

    t, w = np.polynomial.legendre.leggauss(nz)
    z, w = 0.5 * (t + 1.0), 0.5 * w
    s = np.sqrt(1.0 - z * z)
    p = basis.radial(z) * w[:, None]
    az = basis.azimuthal
    out = []
    for m in range(basis.order + 1):
        f = 2.0 * np.pi * iv(m, kappa * np.outer(s, s))
        pm = p[:, az == m]
        out.append((2.0 * np.pi if m == 0 else np.pi) * (pm.T @ f @ pm))
    return out


@pytest.mark.parametrize("grading", [1, 6])
def test_azimuth_estimate_bounds_the_azimuth_error(grading):
    # same z rule in both, so the difference is the azimuth rule's error alone; the
    # estimate (change from the rule of its even nodes) must bound it at every level, and
    # the rules must converge (kappa = 12 is sharp in dphi: e^12 at 0 against e^-12 at pi)
    from project.quadrature import _IsoGrid

    zb, kappa = HemiZernike(6), 12.0
    ref = bessel_blocks(kappa, zb, 20)
    scale = max(np.max(np.abs(b)) for b in ref)
    grid = _IsoGrid(Bessel(kappa), zb, "f", 20, "gauss", grading)
    grid.sample(8)
    errors = []
    for _ in range(5):
        grid.refine()
        got, est, _ = grid.result()
        true = max(np.max(np.abs(g[..., 0] - r)) for g, r in zip(got, ref, strict=True))
        # converged rules differ by rounding (sums of ~1e3 terms): 1e-13 allowance
        assert true <= est + 1e-13 * scale, (2 * grid.half, true / scale, est / scale)
        errors.append(true / scale)
    assert errors[-1] < 1e-10 and errors[0] > 1e-6  # the test covers the converging range


@pytest.mark.parametrize("tol", [1e-2, 1e-4, 1e-7])
def test_projection_estimate_bounds_the_true_error(tol):
    # reference: 40 Gauss nodes in z (the integrand is smooth in z: converged to ~1e-15, see
    # the check below) and the exact azimuthal transforms
    zb, kappa = HemiZernike(6), 12.0
    ref = bessel_blocks(kappa, zb, 40)
    scale = max(np.max(np.abs(b)) for b in ref)
    assert max(np.max(np.abs(a - b)) for a, b in zip(ref, bessel_blocks(kappa, zb, 30),
                                                      strict=True)) < 1e-13 * scale
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # e^12 lobes: truncation warning
        cm = project(Bessel(kappa), zb, quantity="f", tol=tol)
    got = cm.stored
    true = max(np.max(np.abs(g - r)) for g, r in zip(got, ref, strict=True))
    assert cm.info["converged"] and cm.info["rel_error"] <= tol
    # rounding allowance as in test_azimuth_estimate_bounds_the_azimuth_error
    assert true <= cm.info["error_estimate"] + 1e-13 * scale, (true / scale,
                                                               cm.info["rel_error"])


def test_diagonal_rule_refines_across_the_ridge_on_its_own():
    # (s, d) nodes (32, 48): 16 Gauss nodes per s panel and 24 in tau, exact for the
    # polynomial like the square rule of test_diagonal_rule_matches_tensor_rule
    from project.quadrature import _iso_rule

    zb = HemiZernike(5)
    ref = _iso_rule(Poly(0.0), zb, "f", 16, 24, fold=True)[0]
    got, ev, _ = _iso_rule(Poly(0.0), zb, "f", 32, 24, zmap="diagonal", fold=True, nd=48)
    assert ev == 32 * 24 * 13  # s nodes x d nodes x azimuths
    scale = max(np.max(np.abs(b)) for b in ref)
    for g, r in zip(got, ref, strict=True):
        np.testing.assert_allclose(0.5 * (g + g.swapaxes(0, 1)), 0.5 * (r + r.swapaxes(0, 1)),
                                   rtol=0, atol=1e-13 * scale)



class Ridge(BRDF):
    """1 + a G (1 - cos dphi) / 2 with G = exp(-((z_i - z_o) / w)^2): a ridge on z_i = z_o.

    Only F_0 = 2 pi + a G pi and F_1 = -a G pi / 2 are non-zero, so its coefficients are
    2-D integrals that panel Gauss rules resolve (:func:`ridge_reference`).
    """

    channels, isotropic, _scalar = 1, True, True

    def __init__(self, width, height=50.0):
        self.w, self.a = width, height

    def _eval(self, wi, wo):
        g = np.exp(-(((wi[:, 2] - wo[:, 2]) / self.w) ** 2))
        s = np.sqrt((1.0 - wi[:, 2] ** 2) * (1.0 - wo[:, 2] ** 2))
        dot = wi[:, 0] * wo[:, 0] + wi[:, 1] * wo[:, 1]
        cos = np.divide(dot, s, out=np.zeros_like(s), where=s > 0)
        return (1.0 + self.a * g * 0.5 * (1.0 - cos))[:, None]


def _panels(edges, n):
    t, w = _z_nodes(n, "gauss")
    keep = edges[1:] > edges[:-1]
    a, b = edges[:-1][keep, None], edges[1:][keep, None]
    return (a + (b - a) * t).ravel(), ((b - a) * w).ravel()


def ridge_reference(basis, brdf):
    """Dense matrix of Ridge by composite Gauss-Legendre (20 nodes per panel) in z_o and,
    for each z_o, in z_i with panels ending at z_o +- w (1, 2, 4, 8); no diagonal rule."""
    w, az = brdf.w, basis.azimuthal
    near = w * np.array([1.0, 2.0, 4.0, 8.0, 16.0])
    zo, wo = _panels(np.concatenate([[0.0], near, [0.5], 1.0 - near[::-1], [1.0]]), 20)
    f0, f1 = np.zeros((basis.size, basis.size)), np.zeros((basis.size, basis.size))
    po = basis.radial(zo)
    for k in range(zo.size):
        e = np.clip(zo[k] + w * np.array([-8, -4, -2, -1, 0, 1, 2, 4, 8]), 0.0, 1.0)
        zi, wi = _panels(np.unique(np.concatenate([[0.0], e, [1.0]])), 20)
        g = np.exp(-(((zi - zo[k]) / w) ** 2))
        pi = basis.radial(zi)
        f0 += wo[k] * np.outer((wi * (2.0 * np.pi + brdf.a * g * np.pi)) @ pi, po[k])
        f1 += wo[k] * np.outer((wi * (-brdf.a * g * np.pi / 2.0)) @ pi, po[k])
    same = az[:, None] == az[None, :]
    return (np.where(same & (az[:, None] == 0), 2.0 * np.pi * f0, 0.0)
            + np.where(same & (np.abs(az[:, None]) == 1), np.pi * f1, 0.0))


@pytest.mark.filterwarnings("ignore:the expansion of Ridge")  # order 8 misses the ridge
def test_combination_of_diagonal_rules_is_bounded_by_its_estimate():
    # A ridge 0.003 wide in z_i - z_o (blue-acrylic's is about as wide) takes the diagonal
    # rule and, at tol 1e-7, a combination of rules (info["combination"]). Its estimate must
    # bound the error against the panel reference, which agrees with itself with 40 nodes
    # per panel to 3e-10 (the estimate here is ~3e-8, the error ~5e-11).
    zb = HemiZernike(8)
    brdf = Ridge(0.003)
    cm = project(brdf, zb, tol=1e-7)
    info = cm.info
    ref = ridge_reference(zb, brdf)
    err = np.max(np.abs(cm.matrix - ref)) / np.max(np.abs(ref))
    assert info["z_rule"] == "diagonal" and " - " in info["combination"]
    assert info["converged"]
    assert err <= info["rel_error"]
    assert info["rel_error"] <= 1e-7


def test_phi_estimate_takes_a_third_only_under_second_order_convergence():
    from project.quadrature import _phi_estimate

    def blocks(x):
        return [np.full((2, 2, 1), x), np.zeros((1, 1, 1))]

    # changes 1e-2 then 1e-4 (rate 100 >= 4): the finer rule's error is at most 1e-4 / 3
    assert _phi_estimate((blocks(1e-4), blocks(1e-2))) == pytest.approx(1e-4 / 3, rel=1e-15)
    # 3e-3 then 1e-3 (rate 3 < 4): no such bound, the change itself
    assert _phi_estimate((blocks(1e-3), blocks(3e-3))) == 1e-3
    # a single change (no quarter rule sampled): the change itself
    assert _phi_estimate((blocks(1e-3), None)) == 1e-3
    assert _phi_estimate((None, None)) == np.inf


def test_radial_tables_and_block_reuse_change_nothing():
    # Reference: the same diagonal rule with its radial tables recomputed for every call
    # (TABLE_BYTES 0) and its blocks formed from F_m directly, pair by pair in numpy.
    from project import quadrature as q

    zb = HemiZernike(6)
    brdf = Poly(0.0, scale=[1.0, 0.5, 2.0], reciprocal=False)
    grid = q._IsoGrid(brdf, zb, "f", 12, "diagonal", fold=False, nd=8)
    grid.sample(28)
    blocks, _, _ = grid.result()
    f = grid._sums * (2.0 / grid.half)
    az = zb.azimuthal
    pi_, po_ = zb.radial(grid.zi), zb.radial(grid.zo)
    for m, b in enumerate(blocks):
        a, c = pi_[:, az == m], po_[:, az == m]
        cm = 2.0 * np.pi if m == 0 else np.pi
        ref = cm * np.einsum("p,pj,pc,pk->jkc", grid.pw, a, f[:, :, m], c)
        # sums of ~100 terms in another order: rounding ~1e-15 relative
        np.testing.assert_allclose(b, ref, rtol=0, atol=1e-13 * np.max(np.abs(ref)))
    saved = q.TABLE_BYTES
    try:
        q.TABLE_BYTES = 0
        again = q._IsoGrid(brdf, zb, "f", 12, "diagonal", fold=False, nd=8)
        again.sample(28)
        for x, y in zip(again.result()[0], blocks, strict=True):
            np.testing.assert_array_equal(x, y)
    finally:
        q.TABLE_BYTES = saved
