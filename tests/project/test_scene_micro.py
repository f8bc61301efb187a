"""MicroBRDF facets on Scenes (bounce-by-bounce tracing through the periodic BVH): lossless
albedo, the flat-plane projection reference, agreement with the height-field wavefront and
with the path tracer, mixed materials, rough brushed aluminium (energy, anisotropy, rotation,
blur), determinism across threads, bad input.

Monte Carlo assertions use k = 5 standard errors (K_SIGMA of tests/project/mc.py); seeds are fixed.
"""

from __future__ import annotations

import warnings

import numba
import numpy as np
import pytest

from basis import HemiHarmonics, HemiZernike
from project import project
from project.microgeometry import (
    Dielectric,
    Diffuse,
    GaussianSurface,
    MicroBRDF,
    Scene,
    brushed_metal,
    simulate,
    trace,
)
from project.microgeometry.bvh import Mesh
from project.microgeometry.scatter import facet_frame
from project.microgeometry.trace import MAX_BOUNCES, MAX_STEPS, _alloc, _seed
from project.microgeometry.wavefront import _frame, _tangent_frame, run_scene_wavefront
from project.models import CookTorrance, GlossyPaint, Lambert, Ward
from tests.project.mc import (
    ALUMINIUM,
    K_SIGMA,
    assert_anisotropic_and_turns,
    direction,
    rotated_z,
    rotation_action,
)

#: slightly rough aluminium: Beckmann RMS slope 0.2, n + i k = 0.96 + 6.69 i (550 nm)
ROUGH_AL = CookTorrance(0.0, 0.2, ior=0.96, k=6.69)


def _mean_z(x: np.ndarray, ref: float) -> float:
    """|mean(x) - ref| in standard errors of the mean (inf-safe for constant x)."""
    se = x.std() / np.sqrt(x.size)
    return abs(x.mean() - ref) / se if se > 0 else (0.0 if x.mean() == ref else np.inf)


# -- energy and the independent references ----------------------------------------------------

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
        ref = project(brdf, basis).matrix
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


# -- per-triangle tangents (the x axis of the facet frame) --------------------------------------

#: the unit square at height 0.3 as a mesh (two triangles)
_SQUARE = Mesh([[0, 0, 0.3], [1, 0, 0.3], [1, 1, 0.3], [0, 1, 0.3]], [[0, 1, 2], [0, 2, 3]])


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


def test_tangents_orient_the_microscale_brdf():
    # a flat square whose facet x axis is the world y axis scatters with the Ward BRDF's
    # axes swapped: its matrix is the projection of Ward(alpha_y, alpha_x) within K_SIGMA
    # standard errors per entry, and the +90 degree turn A^T M A of the default plane's
    # matrix (independent seeds: K_SIGMA of the combined error); the two planes differ by
    # far more (observed max z 3.8 / 2.9 / 31)
    ward, swapped = Ward(0.0, 0.9, 0.2, 0.4), Ward(0.0, 0.9, 0.4, 0.2)
    b = HemiHarmonics(4)
    kw = {"rays": 40000, "chunk": 1000}
    along_y = simulate(Scene(1.0).add_mesh(_SQUARE, material=MicroBRDF(ward),
                                           tangents=[0.0, 2.0, 0.0]), b, seed=4, **kw)
    default = simulate(Scene(1.0).add_mesh(_SQUARE, material=MicroBRDF(ward)), b, seed=5, **kw)
    with warnings.catch_warnings():  # low order: the projection's truncation warnings
        warnings.simplefilter("ignore", RuntimeWarning)
        ref = project(swapped, b).matrix
    err = np.abs(along_y.matrix.matrix - ref)
    assert np.all(err <= K_SIGMA * along_y.stderr + 1e-12), np.max(err / along_y.stderr)
    a = rotation_action(b)
    assert rotated_z(default, along_y, a) < K_SIGMA
    z = np.abs(along_y.matrix.matrix - default.matrix.matrix) / np.hypot(along_y.stderr,
                                                                         default.stderr)
    assert z.max() > 2 * K_SIGMA


def test_tangents_along_x_change_nothing():
    # explicit world-x tangents on one part of a mixed scene: bit-identical paths
    ward = MicroBRDF(Ward(0.0, 0.9, 0.2, 0.5))

    def scene(**kw):
        return (Scene(1.0).add_mesh(_SQUARE, material=ward, **kw)
                .add_cylinder("y", 0.5, 0.3, 0.2, material=ward))

    a = trace(scene(), direction(50, 30), 3000, seed=3)
    b = trace(scene(tangents=[[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]]), direction(50, 30), 3000,
              seed=3)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)


def test_tangents_turn_with_the_scene_and_enter_the_fingerprint():
    s = Scene((1.0, 2.0)).add_plane(0.0).add_mesh(_SQUARE, tangents=[[1, 0, 0], [0.6, 0.8, 0]])
    r = s.rotated()
    assert r._tangents[0] is None
    np.testing.assert_allclose(r._tangents[1], [[0, 1, 0], [-0.8, 0.6, 0]], rtol=0, atol=1e-16)
    plain = Scene((1.0, 2.0)).add_plane(0.0).add_mesh(_SQUARE)
    assert plain._tangents == [None, None]
    assert s.fingerprint() != plain.fingerprint()
    # scenes without tangents keep their fingerprint: that of the parts alone
    assert plain.fingerprint() == Scene((1.0, 2.0)).add_plane(0.0).add_mesh(_SQUARE).fingerprint()


def test_bad_tangents():
    s = Scene(1.0)
    with pytest.raises(ValueError, match=r"tangents must have shape \(3,\) or \(2, 3\) \(one per "
                                         r"triangle\), got shape \(3, 3\)"):
        s.add_mesh(_SQUARE, tangents=np.eye(3))
    with pytest.raises(ValueError, match=r"tangents must be finite and non-zero: 1 of 2 are not "
                                         r"\(first: triangle 1, \[0.0, 0.0, 0.0\]\)"):
        s.add_mesh(_SQUARE, tangents=[[1, 0, 0], [0, 0, 0]])
    with pytest.raises(ValueError, match=r"tangents must be finite and non-zero: 2 of 2"):
        s.add_mesh(_SQUARE, tangents=[np.nan, 0, 1])
    with pytest.raises(TypeError, match=r"tangents must be a direction \(3,\) or 2 directions"):
        s.add_mesh(_SQUARE, tangents="along")
    assert s.triangles == 0  # nothing added by a refused call


def _wavefront_paths(scene: Scene, wi: np.ndarray, rays: int, seed: int) -> tuple:
    """The scene traced by run_scene_wavefront even without MicroBRDF parts (one material
    slot per part, as Scene._run builds them)."""
    out = _alloc(rays)
    bvh = scene.bvh
    mats = [m for _, _, m in scene._parts]
    slot = np.concatenate([np.full(r.shape[0], j) for j, (_, r, _) in enumerate(scene._parts)])
    w = wi[None] / np.linalg.norm(wi)  # as trace() normalises it
    run_scene_wavefront(bvh, scene.period, mats, slot[bvh.source], w, rays, _seed(seed), 0, out,
                        MAX_BOUNCES, MAX_STEPS)
    return out


def test_wavefront_mirror_and_diffuse_facets_are_the_path_tracers():
    # Mirror / Diffuse hits in the wavefront go through trace._scatter with the path
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
    assert _mean_z(tot, 1.0) < K_SIGMA  # roulette is unbiased
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


# -- rough brushed aluminium ------------------------------------------------------------------

@pytest.mark.parametrize("theta", [0.0, 60.0, 85.0])
def test_rough_brushed_aluminium_energy_closes(theta):
    # every facet event splits the weight into kept + absorbed; roulette is unbiased
    s = brushed_metal(0.4, 1.0, material=ALUMINIUM, roughness=0.2)
    p = trace(s, direction(theta, 20), 10000, seed=4)
    tot = p.weights + p.absorbed + p.lost
    assert p.lost.sum() == 0.0 and _mean_z(tot, 1.0) < K_SIGMA
    # aluminium reflects 0.92 at normal incidence; multiple bounces and the Smith loss of the
    # rough facets take more (observed 0.83 ... 0.87)
    assert 0.75 < p.weights.mean() < 0.92
    assert np.all(p.directions[p.weights > 0, 2] > 0)


@pytest.fixture(scope="module")
def rough_brushed():
    """HemiHarmonics(4) matrices of brushed aluminium: smooth (Mirror) along x, rough
    (m = 0.2) along x, along y, and the rough x scene turned by 90 degrees."""
    b = HemiHarmonics(4)
    kw = {"rays": 100000, "chunk": 2500}
    rough = brushed_metal(0.4, 1.0, material=ALUMINIUM, roughness=0.2)
    return (b, simulate(brushed_metal(0.4, 1.0, material=ALUMINIUM), b, seed=1, **kw),
            simulate(rough, b, seed=1, **kw),
            simulate(brushed_metal(0.4, 1.0, material=ALUMINIUM, roughness=0.2, direction="y"),
                     b, seed=2, **kw),
            simulate(rough.rotated(), b, seed=3, **kw))


def test_rough_brushed_aluminium_is_anisotropic_and_rotates(rough_brushed):
    b, _, rx, ry, rrot = rough_brushed
    assert_anisotropic_and_turns(b, rx, ry, rrot)


def test_roughening_blurs_brushed_aluminium(rough_brushed):
    # the share of |M|^2 in the degree >= 3 block (sharp features) falls from 0.40 (smooth)
    # to 0.22 (m = 0.2); seed-to-seed scatter at 1e5 rays is 0.003, so the 0.1 margin is
    # > 30 sigma
    b, smooth, rough, _, _ = rough_brushed
    hi = b.degree >= 3

    def high_share(res):
        mm = res.matrix.matrix
        return float(np.sum(mm[np.ix_(hi, hi)] ** 2) / np.sum(mm**2))

    assert high_share(smooth) > high_share(rough) + 0.1, (high_share(smooth), high_share(rough))
    # the retro-reflection peak at normal incidence q(z, z) drops (observed 0.61 -> 0.49,
    # 9 sigma with the bound sigma <= |b|^T stderr |b|, which ignores cancellations)
    bz = b.eval(np.array([0.0, 0.0, 1.0]))
    peak = [bz @ r.matrix.matrix @ bz for r in (smooth, rough)]
    se = [np.abs(bz) @ r.stderr @ np.abs(bz) for r in (smooth, rough)]
    assert peak[0] - peak[1] > K_SIGMA * np.hypot(*se), (peak, se)
    # the Smith single-scattering loss of the rough facets absorbs a little more: reflected
    # 0.877 -> 0.856 (standard error of each ~3e-4)
    assert 0.0 < smooth.energy["reflected"] - rough.energy["reflected"] < 0.05


# -- bad input --------------------------------------------------------------------------------

def test_micro_scene_bad_input():
    micro = MicroBRDF(Lambert(0.5))
    with pytest.raises(NotImplementedError, match=r"must not mix MicroBRDF and Dielectric"):
        Scene(1.0).add_plane(0.0, material=micro).add_cylinder(
            "x", 0.5, 0.2, 0.1, material=Dielectric(1.5))
    with pytest.raises(NotImplementedError, match=r"must not mix MicroBRDF and Dielectric"):
        Scene(1.0).add_cylinder("x", 0.5, 0.2, 0.1, material=Dielectric(1.5)).add_plane(
            0.0, material=micro)
    with pytest.raises(ValueError, match=r"roughness must be a finite number > 0 \(or None\), "
                                         r"got 0.0"):
        brushed_metal(0.4, 1.0, roughness=0.0)
    with pytest.raises(ValueError, match=r"roughness must be a finite number > 0"):
        brushed_metal(0.4, 1.0, roughness="rough")
    with pytest.raises(TypeError, match=r"material must be a Mirror .* when roughness is given, "
                                        r"got Diffuse\(0.5\)"):
        brushed_metal(0.4, 1.0, material=Diffuse(0.5), roughness=0.1)
