"""trace.py: paths through height fields -- flat mirrors against closed forms, the lossless
limit, roulette, the odd-sized (pyramid-free) walk, and validation of the single-scattering
part against Beckmann + separable Smith (Westin Fig 6).

Monte Carlo assertions use k = 5 standard errors (two-sided tail 6e-7 per assertion for
Gaussian errors) unless stated otherwise; all seeds are fixed, so the outcomes are exact
regressions that only the stated tolerances guard against changes in the algorithm.
"""

from __future__ import annotations

import numpy as np
import pytest

from project.microgeometry import Diffuse, GaussianSurface, Heightfield, Mirror, trace
from project.models import CookTorrance, fresnel
from tests.project.mc import K_SIGMA, direction

# -- flat and lossless surfaces ---------------------------------------------------------------

@pytest.mark.parametrize("theta", [0.0, 30.0, 89.0])
def test_flat_mirror(theta):
    p = trace(Heightfield(np.zeros((8, 8)), 1.0), direction(theta, 30), 100, seed=2)
    mirror = direction(theta, 210)
    # one reflection on an exactly flat facet: rounding only
    np.testing.assert_allclose(p.directions, np.broadcast_to(mirror, (100, 3)), rtol=0,
                               atol=1e-14)
    assert np.all(p.bounces == 1) and np.all(p.weights == 1.0)


@pytest.mark.parametrize("ior, k", [(1.5, 0.0), (0.18, 3.42)])
def test_flat_fresnel_mirror(ior, k):
    wi = direction(60)
    p = trace(Heightfield(np.zeros((4, 4)), 1.0, material=Mirror(ior, k)), wi, 50, seed=2)
    f = float(fresnel(wi[2], ior, k))
    # F > roulette threshold, so every ray keeps weight F exactly (up to rounding of cos)
    np.testing.assert_allclose(p.weights, f, rtol=1e-13)
    np.testing.assert_allclose(p.absorbed, 1.0 - f, rtol=1e-12)


@pytest.mark.parametrize("theta", [0.0, 30.0, 60.0, 75.0, 85.0, 89.0])
def test_lossless_height_field_albedo_is_one(rough, theta):
    # F = 1 and no roulette below weight 1: every ray leaves with weight exactly 1 unless
    # a path is cut off, which must not happen; the albedo estimate is then exactly 1
    p = trace(rough, direction(theta, 17), 20000, seed=4)
    assert p.lost.sum() == 0.0
    assert np.all(p.weights == 1.0) and np.all(p.directions[:, 2] > 0)


def test_odd_sized_heightfield_traces(rng):
    # no pyramid levels (odd sizes): plain cell walk; lossless mirror keeps every ray
    hf = Heightfield(0.3 * rng.normal(size=(7, 9)), 1.0)
    assert hf.levels == 0
    p = trace(hf, direction(40, 20), 5000, seed=1)
    assert np.all(p.weights == 1.0) and np.all(p.directions[:, 2] > 0)


def test_roulette_is_unbiased():
    # diffuse facets of albedo 0.2: weights fall below the roulette threshold after two
    # bounces; reflected + absorbed must still be 1 in expectation (roulette noise only)
    s = GaussianSurface(1.0, 3.0, resolution=32, seed=1, material=Diffuse(0.2))
    p = trace(s, direction(45), 100000, seed=6)
    total = p.weights + p.absorbed
    assert np.max(p.bounces) > 3 and np.any(p.weights == 0) and p.lost.sum() == 0
    assert abs(total.mean() - 1.0) < K_SIGMA * total.std() / np.sqrt(total.size)


# -- validation against Beckmann + Smith (Westin Fig 6) ---------------------------------------

def test_single_bounce_fraction_is_separable_smith(big):
    # fraction of rays leaving after one reflection vs the single-scatter albedo of
    # Beckmann + separable Smith at the mesh's measured m (models docstring: 0.9996, 0.990,
    # 0.964, 0.920, 0.901, 0.936 at m = 0.3077). The he1991 form (0.999 ... 0.766, 0.583,
    # test_models.py::test_cook_torrance_he1991_single_scatter_albedo) is far off at 75-85
    # degrees. Binomial error <= 1.1e-3 at 2e5 rays; the real surface is less shadowed than
    # the separable form near grazing (heights and shadowing are correlated), hence the
    # one-sided allowances of 0.015 at 75 and 0.03 at 85 degrees (measured excess 0.010 and
    # 0.024).
    ct = CookTorrance(0.0, big.roughness)
    for theta, up in [(0.0, 0.006), (30.0, 0.006), (45.0, 0.008), (60.0, 0.008),
                      (75.0, 0.015), (85.0, 0.03)]:
        p = trace(big, direction(theta), 200000, seed=5)
        single = np.mean(p.bounces == 1)
        smith = float(ct.albedo(direction(theta), n_theta=256, n_phi=256))
        assert smith - 0.006 < single < smith + up, (theta, single, smith)


def _inplane(surface, theta_i, rays, seed, lo_deg, hi_deg, dphi_deg=10.0):
    """Energy per incident ray (all bounces, first bounce) into in-plane forward/backward bins
    of 10 degrees, and the Beckmann + separable Smith value by 16 x 16 Gauss-Legendre."""
    wi = direction(theta_i)
    p = trace(surface, wi, rays, seed=seed)
    th = np.arccos(np.clip(p.directions[:, 2], -1, 1))
    phi = np.arctan2(p.directions[:, 1], p.directions[:, 0])
    dphi = np.radians(dphi_deg)
    ct = CookTorrance(0.0, surface.roughness)
    x, w = np.polynomial.legendre.leggauss(16)
    rows = []
    for a in range(lo_deg, hi_deg, 10):  # signed theta_o: > 0 forward (specular side)
        lo, hi = np.radians(min(abs(a), abs(a + 10))), np.radians(max(abs(a), abs(a + 10)))
        ph0 = np.pi if a >= 0 else 0.0
        sel = (np.abs(np.angle(np.exp(1j * (phi - ph0)))) < dphi) & (th >= lo) & (th < hi)
        t = 0.5 * (hi - lo) * x + 0.5 * (hi + lo)
        ph = dphi * x + ph0
        tt, pp = np.meshgrid(t, ph, indexing="ij")
        wo = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1)
        wts = np.outer(0.5 * (hi - lo) * w, dphi * w) * np.cos(tt) * np.sin(tt)
        ref = float(np.sum(ct.eval(wi, wo) * wts))
        e_all = p.weights[sel].sum() / rays
        e_one = p.weights[sel & (p.bounces == 1)].sum() / rays
        rows.append((a + 5, e_all, e_one, ref, np.sqrt(np.sum(sel & (p.bounces == 1))) / rays))
    return rows


@pytest.mark.parametrize("theta_i, lo, hi", [(0, -60, 60), (30, -20, 80), (45, 0, 80),
                                             (60, 10, 80)])
def test_beckmann_smith_in_plane(big, theta_i, lo, hi):
    # Westin Fig 6 (large-roughness He limit = Beckmann D, separable Smith G, F = 1) at the
    # mesh's measured m. Single-bounce energy must agree within 4 % + 4 sigma wherever the
    # reference holds >= 5e-4 of the energy; 4 % covers the specimen's own slope-histogram
    # noise (~2 % per bin at 1024^2) and the bin quadrature. The multiply scattered excess is
    # reported separately: it is never negative and grows towards grazing forward.
    for centre, e_all, e_one, ref, sig in _inplane(big, theta_i, 300000, 8, lo, hi):
        if ref < 5e-4:
            continue
        assert abs(e_one / ref - 1.0) < 0.04 + 4 * sig / ref, (theta_i, centre, e_one / ref)
        assert e_all >= e_one


def test_multiple_scattering_excess_grows_towards_grazing(big):
    # at 60 degrees incidence the forward in-plane excess over single scattering is a few
    # percent at theta_o = 25 and well above 10 % at 65 (measured 1.5 % and 18 %)
    rows = {c: (e_all / ref, e_one / ref) for c, e_all, e_one, ref, _ in
            _inplane(big, 60, 300000, 9, 20, 70)}
    assert rows[25][0] - rows[25][1] < 0.05
    assert rows[65][0] - rows[65][1] > 0.10
