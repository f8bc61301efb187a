"""wavefront.py: bounce-by-bounce tracing of MicroBRDF facets, on height fields and on Scenes
(through the periodic BVH) -- energy balance and the lossless limit, agreement with the path
tracers where both apply (Mirror and Diffuse facets: bit-identical paths), the height field
against the same triangles in a Scene, mixed materials, determinism across threads and
chunks, and the facet frames (projected x axis, its fallback, per-triangle tangents).

Monte Carlo assertions use k = 5 standard errors (K_SIGMA of tests/project/mc.py); seeds
are fixed.
"""

from __future__ import annotations

import warnings

import numba
import numpy as np
import pytest

from basis import HemiHarmonics, HemiZernike
from project import project
from project.microgeometry import Diffuse, GaussianSurface, MicroBRDF, Scene, simulate, trace
from project.microgeometry._paths import _alloc  # the runners' output arrays (private layout)
from project.microgeometry.bvh import Mesh
from project.microgeometry.scatter import facet_frame
from project.microgeometry.trace import MAX_BOUNCES, MAX_STEPS

# _frame and _tangent_frame (private): the MicroBRDF facet frames, checked directly
from project.microgeometry.wavefront import (
    _frame,
    _tangent_frame,
    run_scene_wavefront,
    run_wavefront,
)
from project.models import CookTorrance, GlossyPaint, Lambert
from tests.project.mc import ALUMINIUM, K_SIGMA, direction, mean_z

#: slightly rough aluminium: Beckmann RMS slope 0.2, n + i k = 0.96 + 6.69 i (550 nm)
ROUGH_AL = CookTorrance(0.0, 0.2, ior=0.96, k=6.69)


# -- height fields ----------------------------------------------------------------------------

def test_rough_micro_conserves_energy(rough):
    # energy bound: every event keeps at most the microscale albedo in expectation, so the
    # height field reflects no more than the model's largest albedo (+ K_SIGMA sigma)
    brdf = CookTorrance(0.0, 0.2)
    top = float(np.max(brdf.albedo(np.array([direction(t) for t in range(0, 90, 5)]),
                                   n_theta=128, n_phi=256)))
    surf = GaussianSurface(1.0, 6.5, resolution=64, seed=3, material=MicroBRDF(brdf))
    for theta in [0.0, 45.0, 80.0]:
        p = trace(surf, direction(theta, 17), 20000, seed=4)
        se = p.weights.std() / np.sqrt(p.weights.size)
        assert p.weights.mean() <= top + K_SIGMA * se, (theta, p.weights.mean(), top)
        assert np.all(p.directions[p.weights > 0, 2] > 0) and p.lost.sum() == 0
        assert abs(np.mean(p.weights + p.absorbed) - 1.0) < K_SIGMA * np.std(
            p.weights + p.absorbed) / np.sqrt(p.weights.size)
        assert np.max(p.bounces) > 1


def test_micro_deterministic(rough):
    basis = HemiZernike(4)
    surf = GaussianSurface(1.0, 6.5, resolution=64, seed=3,
                           material=MicroBRDF(CookTorrance(0.2, 0.3, ior=1.5)))
    a = simulate(surf, basis, rays=8000, seed=5, chunk=300)
    b = simulate(surf, basis, rays=8000, seed=5, chunk=300)
    assert np.array_equal(a.raw, b.raw)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        c = simulate(surf, basis, rays=8000, seed=5, chunk=300)
    finally:
        numba.set_num_threads(old)
    assert np.array_equal(a.raw, c.raw)
    d = simulate(surf, basis, rays=8000, seed=5, chunk=700)
    np.testing.assert_allclose(d.raw, a.raw, rtol=0, atol=1e-12)  # summation order only
    assert not np.array_equal(a.raw, simulate(surf, basis, rays=8000, seed=6, chunk=300).raw)


def _heightfield_wavefront_paths(surface, wi: np.ndarray, rays: int, seed: int) -> tuple:
    """The height field traced by run_wavefront whatever its material (trace() sends only
    MicroBRDF height fields there)."""
    out = _alloc(rays)
    w = wi[None] / np.linalg.norm(wi)  # as trace() normalises it
    run_wavefront(surface, w, rays, np.uint64(seed), 0, out, MAX_BOUNCES, MAX_STEPS)
    return out


@pytest.mark.parametrize("material", [ALUMINIUM, Diffuse(0.3)], ids=repr)
def test_height_field_wavefront_with_plain_facets_is_the_path_tracer(material):
    # the bounce loop with Mirror / Diffuse facets: the path tracer's launch, max-pyramid
    # walk, facet event (_scatter, roulette) and next origin with the same streams, one
    # bounce at a time, so a rough height field traced both ways gives bit-identical paths
    # (Fresnel losses of aluminium; a grey diffuse surface: cosine draws and roulette)
    s = GaussianSurface(1.0, 6.5, resolution=32, seed=3, material=material)
    wi = direction(50, 20)
    p = trace(s, wi, 5000, seed=7)
    out = _heightfield_wavefront_paths(s, wi, 5000, 7)
    for got, ref in zip(out, p, strict=True):
        np.testing.assert_array_equal(got, ref)
    assert np.max(p.bounces) >= 3 and p.lost.sum() == 0.0
    assert np.any(p.weights == 0) == (material.code == Diffuse.code)  # roulette killed some


# -- scenes -----------------------------------------------------------------------------------

@pytest.mark.parametrize("theta", [0.0, 50.0, 85.0])
def test_lossless_micro_lambert_scene_albedo_is_one(theta):
    # Lambert(1) facets, sampled by cosine: factor pi f cos / pdf = 1 up to rounding at every
    # event, so every ray leaves with weight 1 (a few ulps per bounce: 1e-12 bounds 17
    # bounces by far) and nothing is lost; raised cylinders trap rays beneath them
    mat = MicroBRDF(Lambert(1.0))
    s = (Scene(1.0).add_plane(0.0, material=mat)
         .add_cylinder("y", 0.5, 0.1, 0.3, material=mat))
    p = trace(s, direction(theta, 20), 5000, seed=1)
    assert p.lost.sum() == 0.0 and np.all(p.directions[:, 2] > 0)
    np.testing.assert_allclose(p.weights, 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(p.weights + p.absorbed + p.lost, 1.0, rtol=0, atol=1e-12)
    assert np.max(p.bounces) >= 5


@pytest.mark.parametrize("brdf, basis", [
    (CookTorrance(0.0, 0.3, ior=0.96, k=6.69), HemiZernike(4)),  # conductor Fresnel
    (GlossyPaint(0.5, 0.3), HemiHarmonics(4)),                     # delta branch
], ids=repr)
def test_flat_micro_scene_plane_reproduces_projection(brdf, basis):
    # one event on a flat plane is the microscale BRDF itself: the simulated matrix equals
    # the quadrature projection within K_SIGMA batch-means standard errors per entry
    # (observed max 3.1 and 3.4 sigma)
    s = Scene((1.0, 2.0)).add_plane(0.3, material=MicroBRDF(brdf))
    res = simulate(s, basis, rays=80000, seed=2, chunk=1000)
    with warnings.catch_warnings():  # low orders: the projection's truncation warnings
        warnings.simplefilter("ignore", RuntimeWarning)
        ref = project(brdf, basis, quantity="f_cos").matrix  # what simulate estimates
    err = np.abs(res.matrix.matrix - ref)
    assert np.all(err <= K_SIGMA * res.stderr + 1e-12), np.max(err / res.stderr)


def test_heightfield_in_scene_traces_like_the_height_field_wavefront():
    # same triangles, same streams and start lines: the BVH walk reproduces the max-pyramid
    # walk up to rounding (observed 1e-15 on all 3 x 4000 rays); a rare ray may diverge at
    # a rounding-level tie (grazing hit, roulette threshold), so allow 1 in 1000
    g = GaussianSurface(1.0, 6.5, resolution=32, seed=3, material=MicroBRDF(ROUGH_AL))
    s = Scene(g.period).add_heightfield(g)
    for theta in (0.0, 60.0, 85.0):
        a = trace(g, direction(theta, 30), 4000, seed=1)
        b = trace(s, direction(theta, 30), 4000, seed=1)
        same = (a.bounces == b.bounces) & (np.abs(a.weights - b.weights) < 1e-12)
        assert same.mean() >= 0.999
        np.testing.assert_allclose(b.directions[same], a.directions[same], rtol=0, atol=1e-12)
        assert np.max(a.bounces) >= 2


def _wavefront_paths(scene: Scene, wi: np.ndarray, rays: int, seed: int) -> tuple:
    """The scene traced by run_scene_wavefront even without MicroBRDF parts (one material
    slot per part, as Scene._run builds them)."""
    out = _alloc(rays)
    bvh = scene.bvh
    mats = [p.material for p in scene.parts]
    slot = np.concatenate([np.full(p.rows.shape[0], j) for j, p in enumerate(scene.parts)])
    w = wi[None] / np.linalg.norm(wi)  # as trace() normalises it
    run_scene_wavefront(bvh, scene.period, mats, slot[bvh.source], w, rays, np.uint64(seed), 0,
                        out, MAX_BOUNCES, MAX_STEPS)
    return out


def test_wavefront_mirror_and_diffuse_facets_are_the_path_tracers():
    # Mirror / Diffuse hits in the wavefront go through _paths._scatter with the path
    # tracer's streams and draws: a scene without MicroBRDF parts traced both ways gives
    # bit-identical paths (Fresnel aluminium cylinders, a grey diffuse plane: roulette too)
    s = (Scene(1.0).add_plane(0.0, material=Diffuse(0.3))
         .add_cylinder("x", 0.5, 0.1, 0.35, material=ALUMINIUM))
    wi = direction(40, 30)
    p = trace(s, wi, 5000, seed=7)
    out = _wavefront_paths(s, wi, 5000, 7)
    for got, ref in zip(out, p, strict=True):
        np.testing.assert_array_equal(got, ref)
    assert np.max(p.bounces) >= 3 and np.any(p.weights == 0)


def test_mixed_micro_cylinders_and_diffuse_plane():
    # MicroBRDF(Lambert(a)) and Diffuse(a) scatter with the same law, so MicroBRDF cylinders
    # + Diffuse plane must reproduce the all-Diffuse scene (path tracer) in distribution:
    # reflected and absorbed fractions within K_SIGMA (different streams after the first
    # MicroBRDF event: independent errors), and energy closes per ray up to roulette
    def scene(cyl):
        return (Scene(1.0).add_plane(0.0, material=Diffuse(0.5))
                .add_cylinder("y", 0.5, 0.1, 0.3, material=cyl))

    wi = direction(50, 10)
    m = trace(scene(MicroBRDF(Lambert(0.8))), wi, 20000, seed=3)
    d = trace(scene(Diffuse(0.8)), wi, 20000, seed=4)
    assert m.lost.sum() == 0.0
    tot = m.weights + m.absorbed
    assert mean_z(tot, 1.0) < K_SIGMA  # roulette is unbiased
    for x, y in ((m.weights, d.weights), (m.absorbed, d.absorbed)):
        se = np.hypot(x.std(), y.std()) / np.sqrt(x.size)
        assert abs(x.mean() - y.mean()) < K_SIGMA * se, (x.mean(), y.mean(), se)
    # a real mix of materials: ~40 % absorbed (observed 0.41), several bounces
    assert 0.3 < m.absorbed.mean() < 0.5 and np.mean(m.bounces) > 1.3


def test_micro_scene_deterministic_across_threads():
    # per-ray streams and no cross-ray reductions: bit-identical for 1 and 2 threads
    s = (Scene(1.0).add_plane(0.0, material=Diffuse(0.5))
         .add_cylinder("x", 0.5, 0.1, 0.35, material=MicroBRDF(ROUGH_AL)))
    a = trace(s, direction(60, 30), 4000, seed=5)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        b = trace(s, direction(60, 30), 4000, seed=5)
    finally:
        numba.set_num_threads(old)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a.weights, trace(s, direction(60, 30), 4000, seed=6).weights)


# -- facet frames -----------------------------------------------------------------------------

def test_micro_facets_facing_along_x():
    # vertical walls with normals exactly +-x (a square ridge of a mesh): the frame's
    # projected x axis vanishes there and the projected y takes over; lossless Lambert
    # facets must still return every ray with weight 1 (1e-12: rounding per bounce) and
    # finite directions. The walls are hit at oblique incidence from the side.
    v = [[0.25, 0, 0], [0.25, 1, 0], [0.25, 1, 0.3], [0.25, 0, 0.3],
         [0.75, 0, 0], [0.75, 1, 0], [0.75, 1, 0.3], [0.75, 0, 0.3]]
    f = [[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6], [3, 2, 6], [3, 6, 7]]
    mat = MicroBRDF(Lambert(1.0))
    s = Scene(1.0).add_plane(0.0, material=mat).add_mesh(Mesh(v, f), material=mat)
    p = trace(s, direction(70, 0), 4000, seed=2)
    assert np.all(np.isfinite(p.directions)) and p.lost.sum() == 0.0
    np.testing.assert_allclose(p.weights, 1.0, rtol=0, atol=1e-12)
    g = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.6, 0.0, 0.8]])
    t, b = _frame(g)
    np.testing.assert_allclose(np.stack([t, b, g], 1) @ np.stack([t, b, g], 1).transpose(
        0, 2, 1), np.broadcast_to(np.eye(3), (3, 3, 3)), rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.sum(np.cross(t, b) * g, 1), 1.0, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(t[2], facet_frame(g[2:])[0][0])  # the usual frame elsewhere


def test_tangent_frame_projects_the_tangent():
    # t = the tangent projected onto the facet: orthonormal right-handed (t, b, g); for the
    # world x axis it is _frame bit for bit (same operations), including the fallback on
    # facets facing along x; a tangent along the normal falls back to _frame. Tolerance
    # 1e-14: the projection's rounding grows as eps / |a - (a.g) g|, and the smallest
    # projection of these random tangents is 0.049 (observed error 4.7e-15)
    g = np.random.default_rng(1).normal(size=(200, 3))
    g[:3] = [[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.6, 0.8]]
    g /= np.linalg.norm(g, axis=1)[:, None]
    x = np.tile([1.0, 0.0, 0.0], (g.shape[0], 1))
    for got, ref in zip(_tangent_frame(g, x), _frame(g), strict=True):
        np.testing.assert_array_equal(got, ref)
    a = np.random.default_rng(2).normal(size=g.shape)
    a /= np.linalg.norm(a, axis=1)[:, None]
    a[2] = g[2]  # along the normal: no projection
    t, b = _tangent_frame(g, a)
    frames = np.stack([t, b, g], 1)
    np.testing.assert_allclose(frames @ frames.transpose(0, 2, 1),
                               np.broadcast_to(np.eye(3), frames.shape), rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.sum(np.cross(t, b) * g, 1), 1.0, rtol=0, atol=1e-14)
    # t lies in the plane of a and g, on a's side: t = (a - (a.g) g) / |...|
    proj = a - np.sum(a * g, 1)[:, None] * g
    keep = np.arange(g.shape[0]) != 2
    np.testing.assert_allclose(t[keep], proj[keep] / np.linalg.norm(proj[keep], axis=1)[:, None],
                               rtol=0, atol=1e-14)
    np.testing.assert_array_equal(t[2], _frame(g[2:3])[0][0])
