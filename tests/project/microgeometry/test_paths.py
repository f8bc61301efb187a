"""_paths.py: the shared facet-event kernels, called directly -- the Fresnel kernel of either
side of an interface (total internal reflection included) and the dielectric event (Snell's
law, the choice by Fresnel probability).

References: Fresnel's equations written with the explicit refraction cosine (Hecht, Optics,
eqs 4.42-4.43; a different formulation from the kernel's, which uses the complex-index form)
and Snell's law. Monte Carlo assertions use k = 5 standard errors with fixed seeds.
"""

from __future__ import annotations

import numpy as np
import pytest

# kernel tests: the facet events and the random streams are private to the subpackage
from project.microgeometry._paths import ROULETTE, _dielectric, _fresnel1, _stream
from tests.project.mc import K_SIGMA, direction, fresnel_hecht


@pytest.mark.parametrize("n", [1.5, 1 / 1.5, 0.4, 2.7])
def test_fresnel_kernel_for_both_sides_and_total_reflection(n):
    u = np.linspace(0.0, 1.0, 1001)
    got = np.array([_fresnel1(x, n, 0.0) for x in u])
    ref = np.array([fresnel_hecht(x, n) for x in u])
    # two algebraically equal forms: observed agreement 8e-15
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-13)
    if n < 1:  # total internal reflection beyond the critical angle, exactly
        assert np.all(got[u < np.sqrt(1 - n * n) - 1e-12] == 1.0)
    # the Stokes relation used by the slab reference: F(theta_t, 1 / n) = F(theta, n); near
    # grazing theta, theta_t nears the critical angle where dF/d cos diverges and the
    # rounding of cos theta_t is amplified (1e-7 at u = 1e-3), so u >= 0.05
    ok = ((1 - u * u) / (n * n) < 1) & (u >= 0.05)
    ct = np.sqrt(1 - (1 - u[ok] ** 2) / (n * n))
    back = np.array([_fresnel1(x, 1 / n, 0.0) for x in ct])
    np.testing.assert_allclose(back, got[ok], rtol=0, atol=1e-13)


@pytest.mark.parametrize("front", [True, False])
def test_event_obeys_snell_and_chooses_by_fresnel(front):
    # a facet of normal g (facing the ray) hit at 35 degrees from outside (n = 1.5) or from
    # inside (1 / 1.5, below the critical angle 41.8 degrees): reflected rays are mirrored,
    # refracted ones obey Snell's law in the plane of incidence, the weight never changes,
    # and the fraction reflected is F (binomial: sigma = sqrt(F (1 - F) / N))
    g = np.array([0.3, -0.2, 0.9])
    g /= np.linalg.norm(g)
    e = np.cross(g, [1.0, 0.0, 0.0])
    e /= np.linalg.norm(e)
    ti = np.radians(35.0)
    d = -np.cos(ti) * g + np.sin(ti) * e
    eta = 1.5 if front else 1 / 1.5
    n = 4000
    streams = [np.uint64(_stream(np.uint64(9), np.uint64(i), 1)) for i in range(n)]
    out = np.array([_dielectric(1.5, *d, *g, front, 1.0, ROULETTE, s) for s in streams])
    new, w, refr = out[:, :3], out[:, 3], out[:, 5].astype(bool)
    assert np.all(w == 1.0)
    np.testing.assert_allclose(np.linalg.norm(new, axis=1), 1.0, rtol=0, atol=1e-15)
    mirror = d + 2 * np.cos(ti) * g
    np.testing.assert_allclose(new[~refr], np.broadcast_to(mirror, ((~refr).sum(), 3)),
                               rtol=0, atol=1e-15)
    tt = np.arcsin(np.sin(ti) / eta)
    snell = -np.cos(tt) * g + np.sin(tt) * e
    np.testing.assert_allclose(new[refr], np.broadcast_to(snell, (refr.sum(), 3)),
                               rtol=0, atol=1e-15)
    f = fresnel_hecht(np.cos(ti), eta)
    assert abs((~refr).mean() - f) < K_SIGMA * np.sqrt(f * (1 - f) / n)


def test_event_total_internal_reflection():
    # leaving n = 1.5 at 60 degrees (> critical 41.8): always mirrored, weight kept
    g = np.array([0.0, 0.0, 1.0])
    d = -direction(60.0)
    for i in range(50):
        dx, dy, dz, w, _, refr = _dielectric(1.5, *d, *g, False, 1.0, ROULETTE,
                                             np.uint64(_stream(np.uint64(3), np.uint64(i), 1)))
        assert not refr and w == 1.0
        np.testing.assert_allclose([dx, dy, dz], direction(60.0, 180.0), rtol=0, atol=1e-15)
