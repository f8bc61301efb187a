"""surface.py: Gaussian random surfaces (statistics, seeding), the max pyramid of a height
field, and bad input (including the refusal of Dielectric facets on an open height field).
"""

from __future__ import annotations

import numpy as np
import pytest

from project.microgeometry import Dielectric, GaussianSurface, Heightfield

# -- Gaussian surfaces ------------------------------------------------------------------------

def test_gaussian_surface_statistics(big):
    h = big.heights
    assert h.shape == (1024, 1024) and big.triangles == 2 * 1024**2
    # rescaled exactly: mean 0 and RMS sigma up to rounding
    assert abs(h.mean()) < 1e-12 and abs(h.std() - 1.0) < 1e-12
    # autocorrelation exp(-r^2/tau^2): at r = tau (4 grid steps) it is 1/e; the sample
    # value of a 256-tau period deviates by ~1/sqrt(256^2 / pi) ~ 0.7 %, allow 3 %
    c = np.mean(h * np.roll(h, 4, axis=1))
    assert abs(c - np.exp(-1.0)) < 0.03
    # mesh slopes: m = 2 sigma/tau lowered by triangulation: a facet's slope is a difference
    # over one grid step d, whose per-axis variance is 2 sigma^2 (1 - exp(-d^2/tau^2)) / d^2
    # against 2 sigma^2 / tau^2 for the continuum, a factor 16 (1 - exp(-1/16)) = 0.969 at
    # d = tau/4, so m is sqrt(0.969), 1.6 % low; sampling adds < 1 %
    assert abs(big.roughness / (big.nominal_roughness * np.sqrt(0.969)) - 1.0) < 0.02


def test_gaussian_surface_seeded():
    a = GaussianSurface(1.0, 4.0, resolution=16, seed=5)
    assert np.array_equal(a.heights, GaussianSurface(1.0, 4.0, resolution=16, seed=5).heights)
    assert not np.array_equal(a.heights, GaussianSurface(1.0, 4.0, resolution=16, seed=6).heights)
    assert a.fingerprint() != GaussianSurface(1.0, 4.0, resolution=16, seed=6).fingerprint()


# -- the max pyramid --------------------------------------------------------------------------

def test_pyramid_is_max_of_cells(rng):
    hf = Heightfield(rng.normal(size=(8, 16)), (0.5, 1.0))
    assert hf.levels == 3  # 8 x 16 -> 4 x 8 -> 2 x 4 -> 1 x 2
    # kernel layout: the flat pyramid and its level offsets are what the tracer walks
    pyr, offs = hf._pyramid, hf._offsets
    h = hf.heights
    cell = np.max([h, np.roll(h, -1, 0), np.roll(h, -1, 1), np.roll(h, (-1, -1), (0, 1))], 0)
    # stored in float32, rounded up: each node is the smallest float32 >= its true max
    assert pyr.dtype == np.float32

    def smallest_float32_above(stored, exact):
        below = np.nextafter(stored, np.float32(-np.inf)).astype(np.float64)
        return np.all(stored.astype(np.float64) >= exact) and np.all(below < exact)

    assert smallest_float32_above(pyr[:offs[1]].reshape(8, 16), cell)
    assert smallest_float32_above(pyr[offs[3]:offs[4]],
                                  np.array([cell[:, :8].max(), cell[:, 8:].max()]))


def test_levels_is_a_read_only_count():
    assert Heightfield(np.zeros((8, 16)), 1.0).levels == 3
    assert Heightfield(np.zeros((4, 4)), 1.0).levels == 2  # 4 x 4 -> 2 x 2 -> 1 x 1
    assert Heightfield(np.zeros((6, 4)), 1.0).levels == 1  # 6 x 4 -> 3 x 2, then odd
    hf = Heightfield(np.zeros((5, 4)), 1.0)
    assert hf.levels == 0
    with pytest.raises(AttributeError):
        hf.levels = 2  # type: ignore[misc]


# -- bad input --------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, exc, match", [
    ({"sigma": 0.0, "tau": 1.0}, ValueError, r"sigma must be finite and > 0, got 0.0"),
    ({"sigma": -1.0, "tau": 1.0}, ValueError, r"sigma must be finite and > 0, got -1.0"),
    ({"sigma": 1.0, "tau": 0.0}, ValueError, r"tau must be finite and > 0, got 0.0"),
    ({"sigma": 1.0, "tau": float("nan")}, ValueError, r"tau must be finite and > 0"),
    ({"sigma": "a", "tau": 1.0}, TypeError, r"sigma must be a number, got 'a'"),
    ({"sigma": 1.0, "tau": 1.0, "resolution": 2}, ValueError, r"resolution must be >= 4"),
    ({"sigma": 1.0, "tau": 1.0, "resolution": 8.0}, TypeError, r"resolution must be an int"),
])
def test_bad_gaussian_surface(kwargs, exc, match):
    with pytest.raises(exc, match=match):
        GaussianSurface(**kwargs)


def test_huge_gaussian_surface_is_refused_before_allocating():
    # 12000^2 points at 72 bytes each: 9.7 GiB, over the 8 GiB of basis.validation.MAX_BYTES
    # (before, numpy tried to allocate them)
    with pytest.raises(MemoryError, match=r"GaussianSurface\(resolution=12000\) \(12000 x "
                                          r"12000 points\) would need 9\.66 GiB"):
        GaussianSurface(1.0, 1.0, resolution=12000)


def test_gaussian_surface_memory_estimate_is_the_measured_peak():
    import tracemalloc

    from project.microgeometry import surface

    tracemalloc.start()
    try:
        GaussianSurface(1.0, 3.0, resolution=256)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak <= surface._BYTES_PER_POINT * 256**2 * 1.05


@pytest.mark.parametrize("heights, spacing, match", [
    (np.zeros((0, 0)), 1.0, r"non-empty 2-D array, got shape \(0, 0\)"),
    (np.zeros(5), 1.0, r"non-empty 2-D array, got shape \(5,\)"),
    (np.zeros((1, 5)), 1.0, r"at least 2 x 2 points, got shape \(1, 5\)"),
    (np.array([[0.0, np.nan], [0.0, 0.0]]), 1.0, r"finite: 1 of 4 values are NaN or inf"),
    (np.zeros((2, 2)), 0.0, r"spacing must be finite and > 0, got 0.0"),
    (np.zeros((2, 2)), (1.0, -1.0), r"spacing must be finite and > 0"),
])
def test_bad_heightfield(heights, spacing, match):
    with pytest.raises(ValueError, match=match):
        Heightfield(heights, spacing)


def test_dielectric_refused_on_heightfield():
    with pytest.raises(ValueError, match=r"opaque \(Mirror, Diffuse, MicroBRDF\) on a "
                                         r"Heightfield, which is an open surface"):
        Heightfield(np.zeros((4, 4)), 1.0, material=Dielectric(1.5))
