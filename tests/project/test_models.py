"""Analytic BRDF models: the contract properties for every model (reciprocity, non-negativity,
horizon, shapes, isotropy, energy), closed forms and limits, reference albedos (printed in
the papers or computed independently by quadrature, with the ones found wrong), the Fresnel
and Smith helpers, and parameter validation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate
from scipy.special import erfc

from basis import from_angles
from basis.quadrature import hemisphere_rule
from project.brdf import MirrorDelta
from project.models import (
    AshikhminShirley,
    BlinnPhong,
    CookTorrance,
    GlossyPaint,
    Lafortune,
    Lambert,
    Minnaert,
    OrenNayar,
    Phong,
    Ward,
    fresnel,
    smith_lambda,
)

EPS = float(np.finfo(np.float64).eps)

#: Lafortune et al. 1997, Table 1: blue paint, 3-D fit at 550 nm (C_x = C_y, C_z, n).
BLUE_PAINT = [(0.86, 0.86, 0.77, 18.6), (-0.41, -0.41, 0.018, 2.58), (-1.03, -1.03, 0.70, 63.8)]

#: id -> (factory, promises energy conservation, albedo rule (n_theta, n_phi) that resolves
#: its lobe; the energy test doubles it to estimate the quadrature error).
MODELS = {
    "lambert": (lambda: Lambert(0.7), True, (8, 8)),
    "minnaert": (lambda: Minnaert(3, 0.8), True, (8, 8)),
    "minnaert-frac": (lambda: Minnaert(1.5, 0.9), True, (64, 8)),
    "phong": (lambda: Phong(0.3, 0.6, 20), True, (96, 192)),
    "blinn-phong": (lambda: BlinnPhong(0.3, 0.6, 20), True, (96, 192)),
    "ward": (lambda: Ward(0.2, 0.3, 0.15, 0.3), False, (128, 256)),
    # a narrow lobe near the horizon needs many azimuths; see the dblquad test for alpha 0.2
    "ward-bounded": (lambda: Ward(0.2, 0.3, 0.3, 0.5, variant="bounded"), True, (128, 512)),
    "ct-beckmann": (lambda: CookTorrance(0.0, 0.3), True, (128, 256)),
    "ct-beckmann-hc": (lambda: CookTorrance(0.0, 0.4, shadowing="height-correlated"), True,
                       (128, 256)),
    "ct-he1991": (lambda: CookTorrance(0.0, 0.3, shadowing="he1991"), True, (128, 256)),
    "ct-ggx-glass": (lambda: CookTorrance(0.0, 0.25, "ggx", ior=1.5), True, (128, 256)),
    "ct-ggx-gold": (lambda: CookTorrance(0.0, 0.3, "ggx", ior=0.47, k=2.4), True, (128, 256)),
    "ashikhmin-shirley": (lambda: AshikhminShirley(0.8, 0.05, 10, 100), True, (64, 1024)),
    "lafortune": (lambda: Lafortune(0.4, BLUE_PAINT), False, (128, 256)),
    "lafortune-aniso": (lambda: Lafortune(0.2, [(-0.9, -0.7, 0.9, 12)]), False, (64, 128)),
    "oren-nayar": (lambda: OrenNayar(0.8, 0.5), False, (64, 128)),
    "oren-nayar-full": (lambda: OrenNayar(0.8, 0.5, form="full"), False, (64, 128)),
    "glossy-paint": (lambda: GlossyPaint(0.6, 0.3), True, (8, 8)),
}
IDS = list(MODELS)
ANISOTROPIC = {"ward", "ward-bounded", "ashikhmin-shirley", "lafortune-aniso"}

#: Per-channel (RGB) versions: every parameter kind given per channel at least once.
RGB_MODELS = {
    "lambert": lambda: Lambert([0.2, 0.5, 0.8]),
    "minnaert": lambda: Minnaert([1.0, 2.0, 3.5], 0.5),
    "phong": lambda: Phong([0.1, 0.2, 0.3], 0.5, [5, 20, 80]),
    "blinn-phong": lambda: BlinnPhong(0.2, [0.3, 0.4, 0.5], 30),
    "ward": lambda: Ward(0.1, 0.3, [0.05, 0.1, 0.2], 0.1),
    "cook-torrance": lambda: CookTorrance(0.0, [0.2, 0.3, 0.4], "ggx", ior=[0.18, 0.42, 1.37],
                                          k=[3.42, 2.35, 1.77]),
    "ashikhmin-shirley": lambda: AshikhminShirley([0.2, 0.5, 0.8], 0.05, 10, [10, 50, 100]),
    "lafortune": lambda: Lafortune([0.1, 0.2, 0.3], [([-1.0, -0.9, -0.8], -1.0, 0.95, 20)]),
    "oren-nayar": lambda: OrenNayar([0.2, 0.5, 0.8], [0.0, 0.3, 0.6], form="full"),
    "glossy-paint": lambda: GlossyPaint([0.2, 0.5, 0.6], 0.3),
}


def _edge_pairs() -> tuple[np.ndarray, np.ndarray]:
    """Direction pairs at the places where formulas divide by zero or take 0^0."""
    g = np.array([1.0, 0.0, 1e-9]) / np.hypot(1.0, 1e-9)  # just above the horizon
    t = np.array([1.0, 0.0, 1e-300])  # a unit vector in float64
    pairs = [
        ([0, 0, 1], [0, 0, 1]),            # both normal: h = z, tan = 0, azimuth undefined
        ([1, 0, 0], [0, 0, 1]),            # one on the horizon
        ([0, 0, 1], [0, 1, 0]),
        ([1, 0, 0], [1, 0, 0]),            # same grazing direction: h on the horizon
        ([1, 0, 0], [-1, 0, 0]),           # opposite grazing: wi + wo = 0
        ([1, 0, 0], [0, 1, 0]),            # both on the horizon, 90 degrees apart
        ([0.6, 0, 0.8], [-0.6, 0, 0.8]),   # mirror pair
        ([0.6, 0, 0.8], [0.6, 0, 0.8]),    # retro pair
        (g, g * [-1, -1, 1]),              # grazing mirror pair: the spikes of the lobes
        (g, g),
        (t, t * [-1, -1, 1]),              # within 1e-300: squares and 1/cos over/underflow
        (t, t),
        (t, [0, 1, 0]),
        (t, [-1, 0, 0]),
    ]
    wi, wo = (np.array(p, dtype=float) for p in zip(*pairs, strict=True))
    return wi, wo


def _rot_z(w: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return w @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def _albedo(model, degrees, n_theta, n_phi) -> np.ndarray:
    return model.albedo(from_angles(np.radians(degrees), 0.0), n_theta=n_theta, n_phi=n_phi)


# -- contract properties, every model ---------------------------------------------------------

@pytest.mark.parametrize("name", IDS)
def test_reciprocity(name, unit_vectors):
    f = MODELS[name][0]()
    assert f.reciprocal
    wi, wo = unit_vectors(2000, upper=True), unit_vectors(2000, upper=True)
    # both orders run the same operations on swapped operands (sums and products commute
    # exactly); allow a few roundings for the reassociated products
    np.testing.assert_allclose(f.eval(wi, wo), f.eval(wo, wi), rtol=8 * EPS, atol=0)
    ei, eo = _edge_pairs()
    np.testing.assert_allclose(f.eval(ei, eo), f.eval(eo, ei), rtol=8 * EPS, atol=0)


@pytest.mark.parametrize("name", IDS)
def test_nonnegative_and_finite(name, unit_vectors):
    f = MODELS[name][0]()
    wi, wo = unit_vectors(5000, upper=True), unit_vectors(5000, upper=True)
    ei, eo = _edge_pairs()
    for v in (f.eval(wi, wo), f.eval(ei, eo), f.eval(eo, ei)):
        assert np.all(np.isfinite(v)), f"{name}: non-finite values {v[~np.isfinite(v)]}"
        assert v.min() >= 0.0  # exact: every term is a product of non-negative factors


@pytest.mark.parametrize("name", IDS)
def test_below_horizon_is_zero(name, unit_vectors):
    f = MODELS[name][0]()
    up, down = unit_vectors(300, upper=True), -unit_vectors(300, upper=True)
    down[:, 2] = np.minimum(down[:, 2], -1e-3)  # strictly below
    down /= np.linalg.norm(down, axis=1, keepdims=True)
    assert np.all(f.eval(down, up) == 0.0)
    assert np.all(f.eval(up, down) == 0.0)
    assert np.all(f.eval(down, down) == 0.0)
    assert np.all(f.albedo(down[:3], n_theta=4, n_phi=4) == 0.0)


@pytest.mark.parametrize("name", IDS)
def test_isotropy_claim(name, unit_vectors, rng):
    f = MODELS[name][0]()
    assert f.isotropic == (name not in ANISOTROPIC)
    wi, wo = unit_vectors(500, upper=True), unit_vectors(500, upper=True)
    angle = rng.uniform(0.3, 1.2)
    base, turned = f.eval(wi, wo), f.eval(_rot_z(wi, angle), _rot_z(wo, angle))
    if f.isotropic:
        # the rotation changes x and y by a few ulps; lobes amplify that by their exponent
        np.testing.assert_allclose(turned, base, rtol=1e-11, atol=0)
    else:  # the claim must be meaningful: some pair changes by far more than rounding
        assert np.max(np.abs(turned - base) / np.maximum(base, 1e-300)) > 1e-2


def test_isotropy_follows_parameters():
    assert Ward(0.1, 0.2, 0.1, 0.1).isotropic and not Ward(0.1, 0.2, 0.1, 0.12).isotropic
    assert Ward(0.1, 0.2, [0.1, 0.2], [0.1, 0.2]).isotropic
    assert not Ward(0.1, 0.2, [0.1, 0.2], [0.1, 0.3]).isotropic
    assert AshikhminShirley(0.5, 0.05, 20, 20).isotropic
    assert not AshikhminShirley(0.5, 0.05, 20, 21).isotropic
    assert Lafortune(0.1, [(-1, -1, 1, 5), (0.5, 0.5, 0.2, 3)]).isotropic
    assert not Lafortune(0.1, [(-1, -1, 1, 5), (0.5, 0.4, 0.2, 3)]).isotropic
    assert Lafortune(0.1, []).isotropic


@pytest.mark.parametrize("name", [k for k in IDS if MODELS[k][1]])
def test_energy_conservation(name):
    f, _, (nt, nph) = MODELS[name]
    f = f()
    degrees = np.array([0.0, 30.0, 60.0, 85.0, 89.0, 89.9])
    coarse = np.atleast_1d(_albedo(f, degrees, nt, nph))
    fine = np.atleast_1d(_albedo(f, degrees, 2 * nt, 2 * nph))
    err = np.abs(fine - coarse)  # quadrature error estimate by doubling
    assert np.all(err < 0.02), f"{name}: rule too coarse, doubling changes {err}"
    assert np.all(fine <= 1.0 + err + 1e-12), f"{name}: albedo {fine}"


# -- shapes and broadcasting ---------------------------------------------------------------

@pytest.mark.parametrize("name", IDS)
def test_shapes_scalar(name, unit_vectors):
    f = MODELS[name][0]()
    assert f.channels == 1
    assert f.eval([0, 0, 1.0], [0.6, 0, 0.8]).shape == ()
    assert f.eval(unit_vectors(7, upper=True), [0, 0, 1.0]).shape == (7,)
    wi, wo = unit_vectors((4, 1), upper=True), unit_vectors(5, upper=True)
    v = f.eval(wi, wo)
    assert v.shape == (4, 5)
    # broadcasting is the same as evaluating the explicit pairs, exactly
    assert np.array_equal(v[2, 3], f.eval(wi[2, 0], wo[3]))
    assert f.eval(np.empty((0, 3)), np.empty((0, 3))).shape == (0,)


@pytest.mark.parametrize("name", list(RGB_MODELS))
def test_shapes_rgb(name, unit_vectors):
    f = RGB_MODELS[name]()
    assert f.channels == 3
    assert f.eval([0, 0, 1.0], [0.6, 0, 0.8]).shape == (3,)
    wi, wo = unit_vectors((4, 1), upper=True), unit_vectors(5, upper=True)
    v = f.eval(wi, wo)
    assert v.shape == (4, 5, 3)
    assert np.all(np.isfinite(v)) and v.min() >= 0.0
    np.testing.assert_allclose(f.eval(wo, wi.reshape(4, 1, 3)), v, rtol=8 * EPS, atol=0)
    assert f.albedo([[0, 0, 1.0], [0.6, 0, 0.8]], n_theta=16, n_phi=16).shape == (2, 3)
    assert f.eval(np.empty((0, 3)), np.empty((0, 3))).shape == (0, 3)


def test_rgb_channels_match_scalar_models(unit_vectors):
    wi, wo = unit_vectors(200, upper=True), unit_vectors(200, upper=True)
    rgb = RGB_MODELS["cook-torrance"]().eval(wi, wo)
    for c, (m, n, k) in enumerate(zip([0.2, 0.3, 0.4], [0.18, 0.42, 1.37],
                                      [3.42, 2.35, 1.77], strict=True)):
        one = CookTorrance(0.0, m, "ggx", ior=n, k=k).eval(wi, wo)
        np.testing.assert_array_equal(rgb[:, c], one)  # same operations, same order
    single = Lambert([0.4])  # a length-1 sequence keeps its channel axis
    assert single.eval([0, 0, 1.0], [0, 0, 1.0]).shape == (1,)


# -- closed forms and limits -------------------------------------------------------------------

def test_lambert_value_and_albedo():
    f = Lambert(0.7)
    assert f.eval([0.6, 0, 0.8], [0, 0.6, 0.8]) == 0.7 / np.pi
    # a constant times cos(theta_o) is integrated exactly by the product rule: rounding only
    a = _albedo(f, [0.0, 45.0, 89.9], 2, 1)
    np.testing.assert_allclose(a, 0.7, rtol=0, atol=4 * EPS)


@pytest.mark.parametrize("k", [1, 2, 5])
def test_minnaert_albedo_polynomial(k):
    f = Minnaert(k, 0.8)
    deg = np.array([0.0, 30.0, 60.0, 85.0, 89.9])
    # f cos(theta_o) is a degree-k polynomial in z: a (k+2)//2 + 1 node rule is exact
    a = _albedo(f, deg, k // 2 + 2, 1)
    np.testing.assert_allclose(a, 0.8 * np.cos(np.radians(deg)) ** (k - 1), rtol=1e-14,
                               atol=4 * EPS)


def test_minnaert_fractional_and_lambert_limit():
    a = _albedo(Minnaert(1.5, 0.9), np.array([0.0, 60.0]), 200, 1)
    # z^1.5 has a z^0.5 singular derivative at 0: Gauss-Legendre error ~1e-7 at 200 nodes
    np.testing.assert_allclose(a, 0.9 * np.cos(np.radians([0.0, 60.0])) ** 0.5, rtol=1e-6)
    w = from_angles([0.1, 1.2], [0.0, 2.0])
    assert np.array_equal(Minnaert(1, 0.6).eval(w, w[::-1]), Lambert(0.6).eval(w, w[::-1]))


@pytest.mark.parametrize("n", [0, 1, 10, 64])
def test_phong_albedo_at_normal_incidence_is_kd_plus_ks(n):
    # at normal incidence the lobe is cos^n theta_o: f cos is a polynomial of degree n + 1
    a = _albedo(Phong(0.3, 0.6, n), 0.0, n // 2 + 2, 1)
    # exact rule: rounding only, amplified by z^n near z = 1 (2.6e-14 seen at n = 64)
    assert a == pytest.approx(0.9, rel=0, abs=1e-13)


def test_phong_albedo_reference_values():
    # normalised lobe (n + 2)/(2 pi) cos^n alpha (Lafortune et al. 1997 eqs 1-2); albedos not
    # printed there, computed independently by adaptive quadrature (scipy dblquad, 1e-9) about
    # the mirror direction, rounded to three decimals: n = 10 at 0, 30, 60, 85 degrees and
    # n = 100 at 60, 85 degrees; quadrature error by doubling is < 1e-5 at these node counts
    a10 = _albedo(Phong(0.0, 1.0, 10), np.array([0.0, 30.0, 60.0, 85.0]), 64, 128)
    np.testing.assert_allclose(a10, [1.000, 0.866, 0.505, 0.171], rtol=0, atol=5e-4)
    a100 = _albedo(Phong(0.0, 1.0, 100), np.array([60.0, 85.0]), 256, 512)
    np.testing.assert_allclose(a100, [0.500, 0.098], rtol=0, atol=5e-4)


def test_blinn_phong_albedo_reference_values():
    # (n+1)/(8 pi)(n.h)^n with n = 1000 has albedo 0.995, 0.747, 0.250 at 0, 30, 60 degrees
    # (-> cos^2), computed independently by adaptive quadrature over the half vector (scipy
    # dblquad, 1e-9), three decimals; the 256 x 1024 rule is within 1e-4 of its doubling
    a = _albedo(BlinnPhong(0.0, 1.0, 1000), np.array([0.0, 30.0, 60.0]), 256, 1024)
    np.testing.assert_allclose(a, [0.995, 0.747, 0.250], rtol=0, atol=6e-4)


def test_ward_original_albedo_caveat():
    f = Ward(0.0, 1.0, 0.1, 0.1)
    deg = np.array([0.0, 30.0, 60.0, 80.0])
    a = _albedo(f, deg, 256, 512)
    # Ward 1992 eq 4, alpha = 0.1: albedos computed independently by adaptive quadrature over
    # the half vector (scipy dblquad, 1e-9), three decimals (not printed in the paper)
    np.testing.assert_allclose(a, [0.971, 0.842, 0.489, 0.184], rtol=0, atol=6e-4)
    # the caveat: albedo ~ ks cos(theta_i) for a narrow lobe (alpha = 0.05: within 1 % at
    # 30 and 60 degrees; the same quadrature gives 0.860, 0.497, i.e. 0.993 and 0.994 of
    # the cosine)
    narrow = _albedo(Ward(0.0, 1.0, 0.05, 0.05), np.array([30.0, 60.0]), 256, 512)
    np.testing.assert_allclose(narrow / np.cos(np.radians([30.0, 60.0])), 1.0, rtol=1e-2)


def test_ward_original_diverges_at_grazing_bounded_does_not():
    deg = np.array([89.9])
    orig = Ward(0.0, 1.0, 0.3, 0.3)
    coarse, fine = _albedo(orig, deg, 256, 512), _albedo(orig, deg, 512, 1024)
    # 1.04 at 89.9 degrees for alpha = 0.3 (adaptive half-vector quadrature, scipy dblquad:
    # 1.037); the doubling moves it by < 0.01
    assert abs(fine - coarse) < 0.01 and fine == pytest.approx(1.04, abs=0.01)
    assert fine - abs(fine - coarse) > 1.0
    bounded = Ward(0.0, 1.0, 0.3, 0.3, variant="bounded")
    # its grazing mirror spike needs many azimuths: doubling 4096 moves the value by 1.2e-4
    bc, bf = _albedo(bounded, deg, 128, 4096), _albedo(bounded, deg, 128, 8192)
    # adaptive half-vector quadrature (scipy dblquad, 1e-8) gives 0.98388 here
    assert abs(bf - bc) < 3e-4 and bf == pytest.approx(0.98388, abs=5e-4)


def test_ward_variants_agree_at_normal_incidence():
    z = [0, 0, 1.0]
    for ax, ay in [(0.1, 0.1), (0.05, 0.2)]:
        peak = 1.0 / (4.0 * np.pi * ax * ay)
        for variant in Ward.VARIANTS:
            v = Ward(0.0, 1.0, ax, ay, variant=variant).eval(z, z)
            assert v == pytest.approx(peak, rel=4 * EPS)


def test_ward_bounded_albedo_reference():
    """Bounded variant against an independent integral over the half vector (scipy dblquad):
    albedo = int D(h) cos(theta_o) / (w_i . h) d omega_h, D the Beckmann-like lobe."""
    alpha, deg = 0.2, 60.0
    t = np.radians(deg)
    wi = np.array([np.sin(t), 0.0, np.cos(t)])

    def integrand(phi, th):
        h = np.array([np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)])
        d = wi @ h
        co = 2 * d * h[2] - wi[2]
        if d <= 0 or co <= 0:
            return 0.0
        dist = np.exp(-np.tan(th) ** 2 / alpha**2) / (np.pi * alpha**2 * h[2] ** 4)
        return dist * co / d * np.sin(th)

    ref = integrate.dblquad(integrand, 0, 1.2, -np.pi, np.pi, epsabs=1e-9, epsrel=1e-9)[0]
    got = _albedo(Ward(0.0, 1.0, alpha, alpha, variant="bounded"), deg, 256, 512)
    assert got == pytest.approx(ref, abs=2e-5)  # product-rule error at 256 x 512


def test_oren_nayar_zero_roughness_is_lambert(unit_vectors):
    wi, wo = unit_vectors(500, upper=True), unit_vectors(500, upper=True)
    for form in OrenNayar.FORMS:
        # sigma = 0 makes B, C2, C3 and the interreflection term exactly 0 and A exactly 1
        assert np.array_equal(OrenNayar(0.8, 0.0, form=form).eval(wi, wo),
                              Lambert(0.8).eval(wi, wo))


def test_oren_nayar_albedo_closed_forms():
    rho, sigma = 0.9, 0.4
    s2 = sigma**2
    a_coef = 1 - 0.5 * s2 / (s2 + 0.33)
    # normal incidence: beta = 0 removes every tan(beta) term: exact for a constant integrand
    assert _albedo(OrenNayar(rho, sigma), 0.0, 4, 4) == pytest.approx(rho * a_coef, rel=1e-14)
    full = _albedo(OrenNayar(rho, sigma, form="full"), 0.0, 4, 4)
    assert full == pytest.approx(rho * (a_coef + 0.17 * rho * s2 / (s2 + 0.13)), rel=1e-14)
    # grazing (theta_i -> 90): rho (A + B/2), so the qualitative form exceeds rho for small
    # sigma (the documented energy caveat). At 89.99 degrees the limit is approached to
    # ~1e-4 and the 256 x 256 rule is converged to < 1e-5.
    graze = _albedo(OrenNayar(1.0, 0.2), 89.99, 256, 256)
    s2 = 0.04
    limit = 1 - 0.5 * s2 / (s2 + 0.33) + 0.225 * s2 / (s2 + 0.09)
    assert graze == pytest.approx(limit, abs=5e-4) and limit > 1.015


def test_oren_nayar_retroreflection():
    w = from_angles(np.radians(60.0), 0.0)
    for form in OrenNayar.FORMS:
        f = OrenNayar(0.8, 0.5, form=form)
        back, forward = f.eval(w, w), f.eval(w, w * [-1, -1, 1])
        assert back > 1.5 * forward  # rough diffuse: brighter towards the light


def test_glossy_paint_albedo_and_delta():
    f = GlossyPaint([0.2, 0.5, 0.6], 0.3)
    a = f.albedo(from_angles(np.radians([0.0, 45.0, 89.9]), 0.0), n_theta=2, n_phi=1)
    np.testing.assert_allclose(a, [[0.5, 0.8, 0.9]] * 3, rtol=0, atol=4 * EPS)
    assert len(f.delta) == 1 and isinstance(f.delta[0], MirrorDelta)
    assert np.array_equal(f.delta[0].constant, [0.3, 0.3, 0.3])
    # eval is the Lambert part only (the mirror is a delta, handled analytically)
    w = [0.6, 0, 0.8]
    np.testing.assert_array_equal(f.eval(w, [-0.6, 0, 0.8]), np.array([0.2, 0.5, 0.6]) / np.pi)


def test_lafortune_special_cases(unit_vectors):
    wi, wo = unit_vectors(500, upper=True), unit_vectors(500, upper=True)
    n = 15
    c = ((n + 2) / (2 * np.pi)) ** (1 / n)
    # classical lobe -C_x = -C_y = C_z = C_s^(1/n) is the normalised Phong lobe
    # (c^n rounds differently from (n + 2)/(2 pi): a few ulps times n)
    np.testing.assert_allclose(Lafortune(0.0, [(-c, -c, c, n)]).eval(wi, wo),
                               Phong(0.0, 1.0, n).eval(wi, wo), rtol=1e-13, atol=0)
    # C_x = C_y = 0 is Minnaert with exponent k = n + 1
    cz = (0.7 * (n + 2) / (2 * np.pi)) ** (1 / n)
    np.testing.assert_allclose(Lafortune(0.0, [(0, 0, cz, n)]).eval(wi, wo),
                               Minnaert(n + 1, 0.7).eval(wi, wo), rtol=1e-13, atol=0)
    np.testing.assert_array_equal(Lafortune(0.3, []).eval(wi, wo), Lambert(0.3).eval(wi, wo))


def test_lafortune_blue_paint_lobe_albedo():
    # the three lobes of Lafortune et al. 1997 Table 1 (blue paint): their albedo is not
    # printed there; computed independently by adaptive quadrature over the exit hemisphere
    # (scipy dblquad, 1e-9), rounded to 4 (then 3) decimals; this rule is within 2e-5 of its
    # doubling
    deg = np.array([0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 85.0])
    a = _albedo(Lafortune(0.0, BLUE_PAINT), deg, 256, 512)
    ref = np.array([0.0024, 0.0040, 0.0096, 0.0187, 0.0303, 0.069, 0.080])
    half_ulp = np.array([5e-5] * 5 + [5e-4] * 2)  # half a unit of the printed last digit
    assert np.all(np.abs(a - ref) <= half_ulp + 1e-5), a


# -- Ashikhmin-Shirley ----------------------------------------------------------------------

@pytest.mark.parametrize("n, expected", [
    (1, [0.250, 0.284, 0.375, 0.457, 0.496]),
    (10, [0.696, 0.688, 0.613, 0.539, 0.504]),
    (100, [0.961, 0.934, 0.846, 0.660, 0.517]),
    # at 89 degrees a previously quoted 0.703 is wrong: adaptive quadrature over the half
    # vector (scipy dblquad) gives 0.55455, and this rule converges to it (2048 x 8192:
    # 0.55455)
    (1000, [0.996, 0.983, 0.954, 0.856, 0.5546]),
])
def test_ashikhmin_shirley_specular_albedo(n, expected):
    # Ashikhmin & Shirley 2000 eq 10 with R_s = 1 (F = 1) at 0, 30, 60, 80 degrees: computed
    # independently by adaptive quadrature over the half vector (scipy dblquad, 1e-9), three
    # decimals (the paper prints only a furnace estimate, about 68 % at n = 10, Fig 2); the
    # 256 x 512 rule is within 1e-4 of its doubling
    f = AshikhminShirley(0.0, 1.0, n, n)
    a = _albedo(f, np.array([0.0, 30.0, 60.0, 80.0]), 256, 512)
    np.testing.assert_allclose(a, expected[:4], rtol=0, atol=6e-4)
    # at 89 degrees the lobe hugs the horizon and needs many azimuths: 128 x 8192 is within
    # 1.5e-4 of 256 x 16384 for every n here
    assert _albedo(f, 89.0, 128, 8192) == pytest.approx(expected[4], abs=4e-4)


def test_ashikhmin_shirley_anisotropic_and_total_albedo():
    deg = np.array([0.0, 60.0, 80.0])
    a = _albedo(AshikhminShirley(0.0, 1.0, 10, 1000), deg, 256, 1024)
    # both sets computed independently by adaptive half-vector quadrature (scipy dblquad,
    # 1e-9; n_u along x, k1 in the xz-plane), three decimals
    np.testing.assert_allclose(a, [0.839, 0.667, 0.557], rtol=0, atol=6e-4)
    deg = np.array([0.0, 30.0, 60.0, 80.0, 89.0])
    a = _albedo(AshikhminShirley(1.0, 0.05, 100, 100), deg, 256, 1024)
    np.testing.assert_allclose(a, [0.968, 0.941, 0.794, 0.568, 0.380], rtol=0, atol=6e-4)


def test_ashikhmin_shirley_diffuse_albedo_closed_form():
    deg = np.array([0.0, 30.0, 60.0, 89.9])
    mu = np.cos(np.radians(deg))
    both = _albedo(AshikhminShirley(1.0, 0.05, 20, 50), deg, 64, 256)
    spec = _albedo(AshikhminShirley(0.0, 0.05, 20, 50), deg, 64, 256)
    # the diffuse term times cos is a degree-6 polynomial in z, constant in phi: exact;
    # the identical specular parts cancel to rounding
    np.testing.assert_allclose(both - spec, 0.95 * (1 - (1 - mu / 2) ** 5), rtol=0,
                               atol=1e-13)
    assert (both - spec)[0] == pytest.approx(0.9203, abs=5e-5)  # 0.95 (1 - 2^-5) = 0.9203125


# -- Cook-Torrance, Smith and Fresnel -------------------------------------------------------

CT_DEGREES = np.array([0.0, 30.0, 45.0, 60.0, 75.0, 85.0])


def test_cook_torrance_he1991_single_scatter_albedo():
    # Beckmann m = 0.3077 (2 sigma/tau of Westin et al. 1992 section 5.1), F = 1: computed
    # independently by adaptive quadrature over the half vector (scipy dblquad, 1e-9), three
    # decimals. These are reproduced only with Smith's 1967 S = (1 - erfc(a)/2) / (1 + Lambda)
    # (He et al. 1991 eqs 23-24, eq 25 with the exp(-a^2) fix), i.e. shadowing="he1991"; the
    # rule is within 1e-4 of its doubling.
    f = CookTorrance(0.0, 0.3077, shadowing="he1991")
    np.testing.assert_allclose(_albedo(f, CT_DEGREES, 256, 512),
                               [0.999, 0.982, 0.947, 0.887, 0.766, 0.583], rtol=0, atol=6e-4)


@pytest.mark.parametrize("shadowing, expected", [
    ("separable", [0.99957, 0.98980, 0.96380, 0.92010, 0.90125, 0.93582]),
    ("height-correlated", [0.99957, 0.98980, 0.96380, 0.92011, 0.90241, 0.94810]),
])
def test_cook_torrance_microfacet_smith_albedo(shadowing, expected):
    # G1 = 1 / (1 + Lambda): computed for this library by adaptive quadrature over the half
    # vector (scipy dblquad, 1e-9), independent of BRDF.albedo; the 256 x 512 rule agrees to
    # 1e-4 near grazing
    f = CookTorrance(0.0, 0.3077, shadowing=shadowing)
    np.testing.assert_allclose(_albedo(f, CT_DEGREES, 256, 512), expected, rtol=0, atol=2e-4)


@pytest.mark.parametrize("distribution, r", [("beckmann", 0.1), ("beckmann", 0.5),
                                             ("ggx", 0.1), ("ggx", 0.5)])
def test_smith_masking_identity(distribution, r):
    """Smith's G1 = 1/(1 + Lambda) makes the visible projected facet area equal the projected
    macro area: int G1 (w . h)+ D(h) d omega_h = cos(theta). Checks D and Lambda together."""
    rule = hemisphere_rule(2048, 256)
    h = rule.points
    f = CookTorrance(0.0, r, distribution)
    # D(h) from the model: at w_i = w_o = h the lobe is D F G / (4 cos^2) with F = 1 and
    # separable G = G1(h)^2; divide the masking back out with the public Lambda
    g1 = 1.0 / (1.0 + smith_lambda(h[:, 2], r, distribution))
    dist = f.eval(h, h) * 4 * h[:, 2] ** 2 / np.where(g1 > 0, g1**2, 1.0)
    # normalisation int D cos = 1; the rule resolves the r = 0.1 peak to ~1e-8
    assert rule.integrate(dist * h[:, 2]) == pytest.approx(1.0, abs=1e-6)
    for theta in [0.0, 0.7, 1.3, 1.55]:
        v = from_angles(theta, 0.4)
        lhs = rule.integrate(dist * np.maximum(h @ v, 0.0)) / (
            1.0 + smith_lambda(np.cos(theta), r, distribution))
        assert lhs == pytest.approx(np.cos(theta), abs=2e-6)


@pytest.mark.parametrize("distribution", ["beckmann", "ggx"])
def test_smith_lambda_against_its_definition(distribution):
    """Lambda(mu) = (1/mu) int_mu^inf (q - mu) p(q) dq with p the one-axis slope density
    (Smith 1967): Beckmann exp(-q^2/m^2)/(m sqrt(pi)), GGX a^2 / (2 (a^2 + q^2)^(3/2))."""
    r = 0.35
    if distribution == "beckmann":
        def p(q):
            return np.exp(-q * q / r**2) / (r * np.sqrt(np.pi))
    else:
        def p(q):
            return r**2 / (2 * (r**2 + q * q) ** 1.5)
    for theta in [0.2, 0.8, 1.2, 1.5, 1.57]:
        mu = 1 / np.tan(theta)
        ref = integrate.quad(lambda q, mu=mu: (q - mu) * p(q), mu, np.inf, epsabs=1e-14,
                             epsrel=1e-12)[0] / mu
        got = smith_lambda(np.cos(theta), r, distribution)
        assert got == pytest.approx(ref, rel=1e-9, abs=1e-15)  # quad's tolerance


def test_smith_shadowing_values_and_erratum():
    # Smith S (He et al. 1991 eq 24, eq 25 with the exp(-a^2) fix) for m = 0.3077; the
    # expected values are that closed form evaluated independently, rounded to four decimals
    m = 0.3077
    theta = np.radians([60.0, 70.0, 80.0, 85.0, 89.0])
    a = 1 / (np.tan(theta) * m)
    s = (1 - 0.5 * erfc(a)) / (1 + smith_lambda(np.cos(theta), m))
    np.testing.assert_allclose(s, [0.9956, 0.9418, 0.6906, 0.4176, 0.0969], rtol=0, atol=6e-5)
    # the printed Lambda (He eq 25, Schlick) lacks exp(-a^2): 0.869 at 60 degrees, not 0.996
    printed = 0.5 * (1 / (a * np.sqrt(np.pi)) - erfc(a))
    s_printed = (1 - 0.5 * erfc(a)) / (1 + printed)
    assert s_printed[0] == pytest.approx(0.869, abs=6e-4)


def test_smith_lambda_limits():
    assert smith_lambda(1.0, 0.3) == 0.0 and smith_lambda(1.0, 0.3, "ggx") == 0.0
    assert np.isinf(smith_lambda(0.0, 0.3)) and np.isinf(smith_lambda(0.0, 0.3, "ggx"))
    # GGX closed form at tan(theta) = sqrt(3), alpha = 1: (sqrt(1 + 3) - 1)/2
    assert smith_lambda(0.5, 1.0, "ggx") == pytest.approx(0.5, rel=4 * EPS)


def _fresnel_reference(c, n, k):
    """Textbook complex-amplitude Fresnel, (|r_s|^2 + |r_p|^2)/2 with eta = n + ik."""
    eta = complex(n, k)
    ct = np.sqrt(1 - (1 - c * c) / eta**2 + 0j)
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return 0.5 * (abs(rs) ** 2 + abs(rp) ** 2)


@pytest.mark.parametrize("n, k", [(1.5, 0.0), (1.33, 0.0), (2.4, 0.0), (0.2, 3.0),
                                  (0.18, 3.42), (1.37, 1.77), (2.9, 3.1), (1.0, 0.5)])
def test_fresnel_against_textbook(n, k, rng):
    c = np.concatenate([[1.0, 0.5, 1e-3], rng.uniform(1e-3, 1, 50)])
    ref = np.array([_fresnel_reference(x, n, k) for x in c])
    # both are a few dozen roundings of O(1) quantities
    np.testing.assert_allclose(fresnel(c, n, k), ref, rtol=1e-12, atol=1e-14)
    normal = ((n - 1) ** 2 + k**2) / ((n + 1) ** 2 + k**2)
    assert fresnel(1.0, n, k) == pytest.approx(normal, rel=1e-14)
    assert fresnel(0.0, n, k) == 1.0  # grazing


def test_fresnel_known_values():
    assert fresnel(1.0, 1.5) == pytest.approx(0.04, rel=1e-14)
    # 60 degrees: textbook (|r_s|^2 + |r_p|^2)/2 evaluated independently, 0.0891867
    assert fresnel(0.5, 1.5) == pytest.approx(0.08919, abs=5e-6)
    assert np.all(fresnel([0.0, 0.3, 1.0], 1.0) <= 1e-30)  # index matched: 0 up to rounding
    # n < 1 (denser incident medium) beyond the critical angle: total reflection
    assert fresnel(np.cos(np.radians(60.0)), 1 / 1.5) == pytest.approx(1.0, abs=1e-15)
    assert fresnel([[1.0], [0.5]], [1.5, 2.0], [0.0, 1.0]).shape == (2, 2)


def test_cook_torrance_fresnel_and_normal_value():
    z = [0, 0, 1.0]
    m = 0.3
    # at w_i = w_o = z: D = 1/(pi m^2), G = 1, F = F(1): f = F0 / (4 pi m^2)
    n, k = np.array([0.18, 0.42, 1.37]), np.array([3.42, 2.35, 1.77])
    f0 = ((n - 1) ** 2 + k**2) / ((n + 1) ** 2 + k**2)
    got = CookTorrance(0.0, m, ior=n, k=k).eval(z, z)
    np.testing.assert_allclose(got, f0 / (4 * np.pi * m * m), rtol=1e-14)
    assert CookTorrance(0.0, m, "ggx").eval(z, z) == pytest.approx(1 / (4 * np.pi * m * m),
                                                                    rel=1e-14)
    # the Fresnel factor is taken at the half-vector angle: the ratio to F = 1 is F(w_i . h)
    wi, wo = from_angles(1.0, 0.0), from_angles(0.4, 2.5)
    cd = np.linalg.norm(wi + wo) / 2
    ratio = CookTorrance(0.0, m, ior=1.5).eval(wi, wo) / CookTorrance(0.0, m).eval(wi, wo)
    assert ratio == pytest.approx(float(fresnel(cd, 1.5)), rel=1e-13)


def test_cook_torrance_diffuse_term_adds():
    wi, wo = from_angles(0.5, 0.0), from_angles(0.9, 2.0)
    diff = CookTorrance(0.4, 0.3).eval(wi, wo) - CookTorrance(0.0, 0.3).eval(wi, wo)
    assert diff == pytest.approx(0.4 / np.pi, rel=1e-12)


# -- validation, warnings, repr -------------------------------------------------------------

@pytest.mark.parametrize("make, exc, match", [
    (lambda: Lambert(1.2), ValueError, r"albedo must be <= 1"),
    (lambda: Lambert(-0.1), ValueError, r"albedo must be >= 0"),
    (lambda: Lambert("red"), TypeError, r"albedo must be a number or a sequence"),
    (lambda: Lambert([[0.1, 0.2]]), ValueError, r"albedo must be a number or a 1-D"),
    (lambda: Lambert(np.nan), ValueError, r"albedo must be finite"),
    (lambda: Minnaert(0.5, 0.5), ValueError, r"k must be >= 1"),
    (lambda: Phong(0.3, 0.3, -1), ValueError, r"n must be >= 0"),
    (lambda: Phong([0.1, 0.2], [0.1, 0.2, 0.3], 5), ValueError,
     r"per-channel parameters must have the same length"),
    (lambda: BlinnPhong(0.3, 1.5, 5), ValueError, r"ks must be <= 1"),
    (lambda: Ward(0.1, 0.2, 0.0, 0.1), ValueError, r"alpha_x must be > 0"),
    (lambda: Ward(0.1, 0.2, 0.1, 0.1, variant="duer"), ValueError,
     r"variant must be one of 'original', 'bounded', got 'duer'"),
    (lambda: CookTorrance(0.1, 0.3, "phong"), ValueError,
     r"distribution must be one of 'beckmann', 'ggx', got 'phong'"),
    (lambda: CookTorrance(0.1, 0.0), ValueError, r"roughness must be > 0"),
    (lambda: CookTorrance(0.1, 0.3, ior=-1.5), ValueError, r"ior must be > 0"),
    (lambda: CookTorrance(0.1, 0.3, ior=1.5, k=-1), ValueError, r"k must be >= 0"),
    (lambda: CookTorrance(0.1, 0.3, k=2.0), ValueError, r"k must be 0 when ior is None"),
    (lambda: CookTorrance(0.1, 0.3, shadowing="v-cavity"), ValueError,
     r"shadowing must be one of 'separable', 'height-correlated', 'he1991'"),
    (lambda: CookTorrance(0.1, 0.3, "ggx", shadowing="he1991"), ValueError,
     r"shadowing 'he1991' must be used with distribution 'beckmann', got 'ggx'"),
    (lambda: AshikhminShirley(0.5, 0.05, -1, 10), ValueError, r"nu must be >= 0"),
    (lambda: Lafortune(0.1, 3), TypeError, r"lobes must be a sequence of \(Cx, Cy, Cz, n\)"),
    (lambda: Lafortune(0.1, "abc"), TypeError, r"lobes must be a sequence"),
    (lambda: Lafortune(0.1, [(1, 1, 1)]), TypeError,
     r"lobes\[0\] must be a sequence \(Cx, Cy, Cz, n\), got \(1, 1, 1\)"),
    (lambda: Lafortune(0.1, [(1, 1, 1, 2), (1, 1, 1, -2)]), ValueError,
     r"lobes\[1\] n must be >= 0"),
    (lambda: Lafortune(0.1, [(1, np.inf, 1, 2)]), ValueError, r"lobes\[0\] Cy must be finite"),
    (lambda: OrenNayar(0.5, 2.0), ValueError, r"sigma must be <= 1.57"),
    (lambda: OrenNayar(0.5, 0.3, form="exact"), ValueError,
     r"form must be one of 'qualitative', 'full', got 'exact'"),
    (lambda: GlossyPaint(0.5, 1.1), ValueError, r"specular must be <= 1"),
    (lambda: fresnel(1.1, 1.5), ValueError, r"cos_theta must lie in \[0, 1\]"),
    (lambda: fresnel(0.5, 0.0), ValueError, r"ior must be finite and > 0"),
    (lambda: fresnel(0.5, 1.5, -0.1), ValueError, r"k must be finite and >= 0"),
    (lambda: fresnel("x", 1.5), TypeError, r"cos_theta must be an array of floats"),
    (lambda: fresnel(0.5, "glass"), TypeError, r"ior must be a number or an array"),
    (lambda: smith_lambda(-0.5, 0.3), ValueError, r"cos_theta must lie in \[0, 1\]"),
    (lambda: smith_lambda(0.5, -0.3), ValueError, r"roughness must be finite and > 0"),
    (lambda: smith_lambda(0.5, 0.3, "blinn"), ValueError, r"distribution must be one of"),
    (lambda: smith_lambda(None, 0.3), TypeError, r"cos_theta must be an array of floats"),
])
def test_bad_parameters(make, exc, match):
    with pytest.raises(exc, match=match):
        make()


@pytest.mark.parametrize("make, match", [
    (lambda: Phong(0.6, 0.6, 10), r"kd \+ ks = \[1\.2\] exceeds 1"),
    (lambda: BlinnPhong([0.5, 0.2], 0.6, 10), r"kd \+ ks = \[1\.1 0\.8\] exceeds 1"),
    (lambda: Ward(0.8, 0.3, 0.1, 0.1), r"kd \+ ks = \[1\.1\] exceeds 1"),
    (lambda: GlossyPaint(0.8, 0.3), r"albedo \+ specular = \[1\.1\] exceeds 1"),
])
def test_energy_warning(make, match):
    with pytest.warns(UserWarning, match=match):
        make()


def test_bad_directions_are_refused_by_the_base_class():
    with pytest.raises(ValueError, match=r"wi must be unit vectors"):
        Phong(0.2, 0.5, 10).eval([0, 0, 2.0], [0, 0, 1.0])
    with pytest.raises(ValueError, match=r"wo must have shape \(\.\.\., 3\)"):
        Phong(0.2, 0.5, 10).eval([0, 0, 1.0], [0, 1.0])


def test_nearly_unit_directions_are_renormalised():
    w = np.array([0.6, 0.0, 0.8])
    f = Phong(0.0, 1.0, 50)
    # a length error of 5e-7 (accepted at the boundary) would move cos^50 by 5e-5 if used raw
    assert f.eval(w * (1 + 5e-7), w * [-1, -1, 1]) == pytest.approx(
        f.eval(w, w * [-1, -1, 1]), rel=1e-14)


def test_repr():
    assert repr(Lambert([0.2, 0.5, 0.8])) == "Lambert(albedo=[0.2, 0.5, 0.8])"
    assert repr(Ward(0.1, 0.2, 0.1, 0.3, variant="bounded")) == (
        "Ward(kd=0.1, ks=0.2, alpha_x=0.1, alpha_y=0.3, variant='bounded')")
    assert repr(CookTorrance(0.0, 0.3, "ggx", ior=1.5)) == (
        "CookTorrance(kd=0, roughness=0.3, ior=1.5, k=0, distribution='ggx', "
        "shadowing='separable')")
    assert repr(Lafortune(0.1, [(-1, -1, 1, 5)])) == "Lafortune(kd=0.1, lobes=[(-1, -1, 1, 5)])"
