"""_paths.py: the shared facet-event kernels, called directly -- the Fresnel kernel of either
side of an interface (total internal reflection included) and the dielectric event (Snell's
law, the choice by Fresnel probability) -- and the max-pyramid walk of height fields, against
a brute-force search over every triangle under the ray.

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


def _brute_first_hit(h, sx, sy, o, d):
    """(t, upward unit normal) of the first triangle of the periodic surface the ray meets,
    or (inf, None): every triangle of every cell the ray passes over inside the height slab,
    Moller-Trumbore, the cell split along u = v as the tracer's (00, 10, 11), (00, 11, 01)."""
    ny, nx = h.shape
    hmin, hmax = h.min(), h.max()
    ts = [0.0]
    if d[2] != 0:
        ts.append(((hmin if d[2] < 0 else hmax) - o[2]) / d[2])
    else:
        ts.append(4 * (nx * sx + ny * sy) / max(np.hypot(d[0], d[1]), 1e-300))
    ends = o[:2] + np.outer([max(ts[0], 0.0), ts[1]], d[:2])
    i0, i1 = np.floor(ends[:, 0].min() / sx) - 1, np.floor(ends[:, 0].max() / sx) + 1
    j0, j1 = np.floor(ends[:, 1].min() / sy) - 1, np.floor(ends[:, 1].max() / sy) + 1
    ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1))
    ii, jj = ii.ravel().astype(int), jj.ravel().astype(int)
    cx, cy = ii % nx, jj % ny
    cx1, cy1 = (cx + 1) % nx, (cy + 1) % ny
    p00 = np.stack([ii * sx, jj * sy, h[cy, cx]], -1)
    p10 = np.stack([(ii + 1) * sx, jj * sy, h[cy, cx1]], -1)
    p11 = np.stack([(ii + 1) * sx, (jj + 1) * sy, h[cy1, cx1]], -1)
    p01 = np.stack([ii * sx, (jj + 1) * sy, h[cy1, cx]], -1)
    best, normal = np.inf, None
    for a, b, c in [(p00, p10, p11), (p00, p11, p01)]:
        e1, e2 = b - a, c - a
        pv = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, pv)
        ok = np.abs(det) > 1e-300
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = o - a
        u = np.einsum("ij,ij->i", tv, pv) * inv
        q = np.cross(tv, e1)
        v = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-12)
        if hit.any():
            k = np.flatnonzero(hit)[np.argmin(t[hit])]
            if t[k] < best:
                n = np.cross(e1[k], e2[k])
                best, normal = t[k], n / np.linalg.norm(n) * np.sign(n[2])
    return best, normal


@pytest.mark.parametrize("shape", [(16, 16), (6, 10)])
def test_pyramid_walk_finds_the_first_triangle(shape, rng):
    # reference: brute force over every triangle under the ray (_brute_first_hit); rays from
    # above (down to 1 degree above the horizon) and rays leaving the surface upwards and
    # sideways, as after a bounce. The walk's start level, climbing rule and node masks
    # (power-of-two grid, and the modulo of a 6 x 10 one) must never skip the first hit.
    from project.microgeometry import Heightfield
    from project.microgeometry._paths import _ESCAPED, _HIT, _intersect

    hf = Heightfield(rng.normal(0.0, 0.6, shape), (0.7, 0.9))
    h, (sx, sy) = hf.heights, hf.spacing
    ny, nx = h.shape
    hmin, hmax = float(h.min()), float(h.max())
    hits = 0
    for k in range(400):
        if k % 2 == 0:  # from above, aimed at a uniform point of the period
            z = -np.sin(rng.uniform(np.radians(1.0), np.pi / 2))
            phi = rng.uniform(0, 2 * np.pi)
            d = np.array([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z])
            target = np.array([rng.uniform(0, nx * sx), rng.uniform(0, ny * sy), hmax])
            o = target - d * (1e-3 / -d[2])
        else:  # from just above a surface point, upwards (0.5 to 90 degrees)
            x, y = rng.uniform(0, nx * sx), rng.uniform(0, ny * sy)
            t0, _ = _brute_first_hit(h, sx, sy, np.array([x, y, hmax + 1.0]),
                                     np.array([0.0, 0.0, -1.0]))
            o = np.array([x, y, hmax + 1.0 - t0 + 1e-6])
            z = np.sin(rng.uniform(np.radians(0.5), np.pi / 2))
            phi = rng.uniform(0, 2 * np.pi)
            d = np.array([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z])
        t_ref, n_ref = _brute_first_hit(h, sx, sy, o, d)
        status, t, gx, gy, gz = _intersect(*o, *d, h, hf._pyramid, hf._offsets, hf._levels,
                                           sx, sy, hmin, hmax, 10**6)
        if np.isinf(t_ref):
            assert status == _ESCAPED, (k, o, d, t)
        else:
            hits += 1
            assert status == _HIT, (k, o, d, t_ref)
            # rounding of the two formulations of the same intersection
            assert t == pytest.approx(t_ref, rel=1e-9, abs=1e-9), (k, o, d)
            np.testing.assert_allclose([gx, gy, gz], n_ref, atol=1e-9)
    assert 250 < hits < 400  # both outcomes were exercised


@pytest.mark.parametrize("nx, ny", [(512, 512), (96, 40), (3, 700)])
def test_coherent_order_is_a_permutation_along_the_morton_curve(nx, ny):
    # reference: the targets drawn the way _launch draws them (first two uniforms of each
    # ray's stream) and their Morton keys computed here bit by bit; exact comparisons
    from project.microgeometry._paths import _TAG_RAY, ORDER_BINS, _coherent_order, _uniform

    seed, start, n = np.uint64(7), 1000, 5000
    order = _coherent_order(seed, np.uint64(start), n, nx, ny)
    assert np.array_equal(np.sort(order), np.arange(n))  # every ray traced exactly once
    bx, by = min(nx, ORDER_BINS), min(ny, ORDER_BINS)
    keys = []
    for r in range(n):
        s = _stream(seed, np.uint64(start + r), _TAG_RAY)
        u1, s = _uniform(np.uint64(s))  # numba hands uint64 back as a Python int
        u2, s = _uniform(np.uint64(s))
        ix, iy = min(int(u1 * bx), bx - 1), min(int(u2 * by), by - 1)
        keys.append(sum(((ix >> b) & 1) << (2 * b) | ((iy >> b) & 1) << (2 * b + 1)
                        for b in range(7)))
    keys = np.array(keys)
    assert np.all(np.diff(keys[order]) >= 0)
    # stable within a bin: rays of one bin keep their index order
    same = np.diff(keys[order]) == 0
    assert np.all(np.diff(order)[same] > 0)


def test_grid_step_gives_the_bits_of_the_integer_form():
    # reference: the step written with an integer index, i = floor(p / size) moved across a
    # boundary within tol * size, then ((i + 1) * size - o) / d (resp. i * size), evaluated
    # here in Python; the kernel keeps the index a float and forms both exits first, which
    # must change no bit. Points on, just off and within tol of the boundaries, both signs.
    from project.microgeometry._paths import _grid_step

    def reference(o, d, inv_d, p, size, inv_size, tol):
        i = int(np.floor(p * inv_size))
        if d > 0.0:
            if (i + 1) * size - p <= tol * size:
                i += 1
            return i, ((i + 1) * size - o) * inv_d
        if d < 0.0:
            if p - i * size <= tol * size:
                i -= 1
            return i, (i * size - o) * inv_d
        return i, np.inf

    rng = np.random.default_rng(4)
    size = 1.625
    cells = rng.integers(-3000, 3000, 400).astype(float) * size
    near = np.concatenate([cells, np.nextafter(cells, np.inf), np.nextafter(cells, -np.inf),
                           cells + 0.5e-9 * size, cells - 0.5e-9 * size,
                           cells + 2e-9 * size, cells - 2e-9 * size,
                           rng.uniform(-5000.0, 5000.0, 400)])
    for p in near:
        for d in (0.7, -0.3, 1e-12, -1.0, 0.0):
            o = p - 3.7 * d
            inv_d = 1.0 / d if d != 0.0 else 0.0
            for w in (size, 4.0 * size):
                args = (o, d, inv_d, p, w, 1.0 / w, 1e-9)
                i, t = _grid_step(*args)
                ri, rt = reference(*args)
                assert i == ri and (t == rt or (np.isinf(t) and np.isinf(rt))), (args, i, t)
                assert np.float64(t).tobytes() == np.float64(rt).tobytes(), args
