"""Monte Carlo microgeometry simulator: surfaces, tracer, estimator constants, validation
against closed forms and Beckmann + Smith, convergence, determinism, checkpoints, bad input.

Monte Carlo assertions use k = 5 standard errors (two-sided tail 6e-7 per assertion for
Gaussian errors) unless stated otherwise; all seeds are fixed, so the outcomes are exact
regressions that only the stated tolerances guard against changes in the algorithm.
"""

from __future__ import annotations

import warnings

import numba
import numpy as np
import pytest

from basis import HemiHarmonics, HemiZernike
from project import project
from project.brdf import BRDF
from project.microgeometry import (
    Diffuse,
    GaussianSurface,
    Heightfield,
    MicroBRDF,
    Mirror,
    merge,
    simulate,
    trace,
)
from project.microgeometry import estimate as est_mod
from project.models import BlinnPhong, CookTorrance, GlossyPaint, Lambert, Phong, fresnel

K_SIGMA = 5.0


def _dir(theta_deg: float, phi_deg: float = 0.0) -> np.ndarray:
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


@pytest.fixture(scope="module")
def rough() -> GaussianSurface:
    """Westin's specimen in units of sigma: sigma/tau = 10/65, m = 0.3077; 64 x 64 points."""
    return GaussianSurface(1.0, 6.5, resolution=64, seed=3)


@pytest.fixture(scope="module")
def big() -> GaussianSurface:
    """1024^2 points (period 256 tau): the specimen's own slope-histogram noise is ~2 %."""
    return GaussianSurface(1.0, 6.5, resolution=1024, seed=7)


# -- surfaces ---------------------------------------------------------------------------------

def test_gaussian_surface_statistics(big):
    h = big.heights
    assert h.shape == (1024, 1024) and big.triangles == 2 * 1024**2
    # rescaled exactly: mean 0 and RMS sigma up to rounding
    assert abs(h.mean()) < 1e-12 and abs(h.std() - 1.0) < 1e-12
    # autocorrelation exp(-r^2/tau^2): at r = tau (4 grid steps) it is 1/e; the sample
    # value of a 256-tau period deviates by ~1/sqrt(256^2 / pi) ~ 0.7 %, allow 3 %
    c = np.mean(h * np.roll(h, 4, axis=1))
    assert abs(c - np.exp(-1.0)) < 0.03
    # mesh slopes: m = 2 sigma/tau lowered by triangulation to sqrt(0.969) (digest 2.10),
    # 1.6 %; sampling adds < 1 %
    assert abs(big.roughness / (big.nominal_roughness * np.sqrt(0.969)) - 1.0) < 0.02


def test_gaussian_surface_seeded():
    a = GaussianSurface(1.0, 4.0, resolution=16, seed=5)
    assert np.array_equal(a.heights, GaussianSurface(1.0, 4.0, resolution=16, seed=5).heights)
    assert not np.array_equal(a.heights, GaussianSurface(1.0, 4.0, resolution=16, seed=6).heights)
    assert a.fingerprint() != GaussianSurface(1.0, 4.0, resolution=16, seed=6).fingerprint()


def test_pyramid_is_max_of_cells(rng):
    hf = Heightfield(rng.normal(size=(8, 16)), (0.5, 1.0))
    pyr, offs, levels = hf._pyramid, hf._offsets, hf._levels
    assert levels == 3  # 8 x 16 -> 4 x 8 -> 2 x 4 -> 1 x 2
    h = hf.heights
    cell = np.max([h, np.roll(h, -1, 0), np.roll(h, -1, 1), np.roll(h, (-1, -1), (0, 1))], 0)
    assert np.array_equal(pyr[:offs[1]].reshape(8, 16), cell)
    assert pyr[offs[3]:offs[4]].tolist() == [cell[:, :8].max(), cell[:, 8:].max()]


def test_odd_sized_heightfield_traces(rng):
    # no pyramid levels (odd sizes): plain cell walk; lossless mirror keeps every ray
    hf = Heightfield(0.3 * rng.normal(size=(7, 9)), 1.0)
    assert hf._levels == 0
    p = trace(hf, _dir(40, 20), 5000, seed=1)
    assert np.all(p.weights == 1.0) and np.all(p.directions[:, 2] > 0)


# -- tracer -----------------------------------------------------------------------------------

@pytest.mark.parametrize("theta", [0.0, 30.0, 89.0])
def test_flat_mirror(theta):
    p = trace(Heightfield(np.zeros((8, 8)), 1.0), _dir(theta, 30), 100, seed=2)
    mirror = _dir(theta, 210)
    # one reflection on an exactly flat facet: rounding only
    np.testing.assert_allclose(p.directions, np.broadcast_to(mirror, (100, 3)), rtol=0,
                               atol=1e-14)
    assert np.all(p.bounces == 1) and np.all(p.weights == 1.0)


@pytest.mark.parametrize("ior, k", [(1.5, 0.0), (0.18, 3.42)])
def test_flat_fresnel_mirror(ior, k):
    wi = _dir(60)
    p = trace(Heightfield(np.zeros((4, 4)), 1.0, material=Mirror(ior, k)), wi, 50, seed=2)
    f = float(fresnel(wi[2], ior, k))
    # F > roulette threshold, so every ray keeps weight F exactly (up to rounding of cos)
    np.testing.assert_allclose(p.weights, f, rtol=1e-13)
    np.testing.assert_allclose(p.absorbed, 1.0 - f, rtol=1e-12)


@pytest.mark.parametrize("theta", [0.0, 30.0, 60.0, 75.0, 85.0, 89.0])
def test_lossless_height_field_albedo_is_one(rough, theta):
    # F = 1 and no roulette below weight 1: every ray leaves with weight exactly 1 unless
    # a path is cut off, which must not happen; the albedo estimate is then exactly 1
    p = trace(rough, _dir(theta, 17), 20000, seed=4)
    assert p.lost.sum() == 0.0
    assert np.all(p.weights == 1.0) and np.all(p.directions[:, 2] > 0)


def test_single_bounce_fraction_is_separable_smith(big):
    # fraction of rays leaving after one reflection vs the single-scatter albedo of
    # Beckmann + separable Smith at the mesh's measured m (models docstring: 0.9996, 0.990,
    # 0.964, 0.920, 0.901, 0.936 at m = 0.3077). The he1991 form (0.999 ... 0.766, 0.583:
    # digest 5.4 item 2) is far off at 75-85 degrees. Binomial error <= 1.1e-3 at 2e5 rays;
    # the real surface is less shadowed than the separable form near grazing (heights and
    # shadowing are correlated), hence the one-sided allowances of 0.015 at 75 and 0.03 at
    # 85 degrees (measured excess 0.010 and 0.024).
    ct = CookTorrance(0.0, big.roughness)
    for theta, up in [(0.0, 0.006), (30.0, 0.006), (45.0, 0.008), (60.0, 0.008),
                      (75.0, 0.015), (85.0, 0.03)]:
        p = trace(big, _dir(theta), 200000, seed=5)
        single = np.mean(p.bounces == 1)
        smith = float(ct.albedo(_dir(theta), n_theta=256, n_phi=256))
        assert smith - 0.006 < single < smith + up, (theta, single, smith)


def test_roulette_is_unbiased():
    # diffuse facets of albedo 0.2: weights fall below the roulette threshold after two
    # bounces; reflected + absorbed must still be 1 in expectation (roulette noise only)
    s = GaussianSurface(1.0, 3.0, resolution=32, seed=1, material=Diffuse(0.2))
    p = trace(s, _dir(45), 100000, seed=6)
    total = p.weights + p.absorbed
    assert np.max(p.bounces) > 3 and np.any(p.weights == 0) and p.lost.sum() == 0
    assert abs(total.mean() - 1.0) < K_SIGMA * total.std() / np.sqrt(total.size)


# -- estimator constants ----------------------------------------------------------------------

@pytest.mark.parametrize("incident", ["cosine", "uniform"])
@pytest.mark.parametrize("basis", [HemiHarmonics(3), HemiZernike(4)], ids=repr)
def test_flat_diffuse_plane_is_lambert(incident, basis):
    plane = Heightfield(np.zeros((4, 4)), 1.0, material=Diffuse(0.6))
    res = simulate(plane, basis, rays=160000, seed=1, incident=incident, chunk=1000)
    ref = project(Lambert(0.6), basis).matrix
    err = np.abs(res.matrix.matrix - ref)
    assert np.all(err <= K_SIGMA * res.stderr + 1e-12), np.max(err / res.stderr)
    assert res.energy == pytest.approx({"reflected": 0.6, "absorbed": 0.4, "escaped": 0.0},
                                       abs=1e-12)


def test_flat_mirror_matches_closed_form_projection():
    basis = HemiZernike(6)
    res = simulate(Heightfield(np.zeros((4, 4)), 1.0), basis, rays=160000, seed=2, chunk=1000)
    with warnings.catch_warnings():  # the closed form converges to 2.6e-12, not 1e-14
        warnings.filterwarnings("ignore", "the mirror term", RuntimeWarning)
        ref = project(GlossyPaint(0.0, 1.0), basis, nodes=(64, 128)).matrix
    err = np.abs(res.matrix.matrix - ref)
    assert np.all(err <= K_SIGMA * res.stderr + 1e-12), np.max(err / res.stderr)


def test_lossless_matrix_albedo_is_one(rough):
    # albedo(wi) cos(theta_i) = z is a degree-2 Zernike polynomial, so the matrix albedo is
    # exact up to Monte Carlo error; error bound from the entry standard errors (treated as
    # independent) divided by cos(theta_i)
    basis = HemiZernike(6)
    res = simulate(rough, basis, rays=200000, seed=3, chunk=500)
    g = basis.moments("none")
    for theta in [0.0, 30.0, 45.0, 60.0, 75.0]:
        wi = _dir(theta, 40)
        b = basis.eval(wi)
        se = np.sqrt(np.sum((b[:, None] * res.stderr * g[None, :]) ** 2)) / wi[2]
        a = float(res.matrix.albedo(wi))
        assert abs(a - 1.0) < K_SIGMA * se + 1e-12, (theta, a, se)
    assert res.energy["reflected"] == 1.0


# -- validation against Beckmann + Smith (Westin Fig 6) ---------------------------------------

def _inplane(surface, theta_i, rays, seed, lo_deg, hi_deg, dphi_deg=10.0):
    """Energy per incident ray (all bounces, first bounce) into in-plane forward/backward bins
    of 10 degrees, and the Beckmann + separable Smith value by 16 x 16 Gauss-Legendre."""
    wi = _dir(theta_i)
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


# -- convergence, determinism, merging --------------------------------------------------------

def test_q_falls_like_inverse_sqrt_rays(rough):
    basis = HemiZernike(4)
    n = np.array([4000, 16000, 64000, 256000])
    q = [simulate(rough, basis, rays=int(k), seed=11).asymmetry for k in n]
    slope = np.polyfit(np.log(n), np.log(q), 1)[0]
    # one realisation per N: the fitted slope scatters by ~0.05 around -1/2
    assert -0.62 < slope < -0.38, (slope, q)


def test_deterministic_across_threads_and_chunks(rough):
    basis = HemiZernike(4)
    a = simulate(rough, basis, rays=20000, seed=5, chunk=300)
    b = simulate(rough, basis, rays=20000, seed=5, chunk=300)
    assert np.array_equal(a.raw, b.raw)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        c = simulate(rough, basis, rays=20000, seed=5, chunk=300)
    finally:
        numba.set_num_threads(old)
    assert np.array_equal(a.raw, c.raw)  # per-ray streams, fixed summation order
    d = simulate(rough, basis, rays=20000, seed=5, chunk=700)
    np.testing.assert_allclose(d.raw, a.raw, rtol=0, atol=1e-12)  # summation order only
    e = simulate(rough, basis, rays=20000, seed=6, chunk=300)
    assert not np.array_equal(a.raw, e.raw)


def test_merge_is_additive(rough):
    basis = HemiHarmonics(3)
    a = simulate(rough, basis, rays=8000, seed=1, chunk=250)
    b = simulate(rough, basis, rays=24000, seed=2, chunk=250)
    m = merge(a, b)
    assert m.rays == 32000
    np.testing.assert_allclose(m.raw, (8000 * a.raw + 24000 * b.raw) / 32000, rtol=1e-13,
                               atol=1e-15)
    assert a.merge(b).rays == 32000
    with pytest.raises(ValueError, match="different seeds, seed 1 repeats"):
        merge(a, a)
    with pytest.raises(ValueError, match="must share the basis"):
        merge(a, simulate(rough, HemiZernike(2), rays=1000, seed=3))


# -- checkpoints ------------------------------------------------------------------------------

def test_checkpoint_resume_equals_uninterrupted(rough, tmp_path):
    basis = HemiZernike(4)
    path = tmp_path / "run.h5"
    full = simulate(rough, basis, rays=24000, seed=7, chunk=250)
    half = simulate(rough, basis, rays=12000, seed=7, chunk=250, checkpoint=path)
    assert path.is_file() and half.rays == 12000
    rest = simulate(rough, basis, rays=24000, seed=7, chunk=250, resume=path, checkpoint=path)
    assert rest.rays == 24000
    np.testing.assert_allclose(rest.raw, full.raw, rtol=0, atol=1e-13)
    np.testing.assert_allclose(rest.stderr, full.stderr, rtol=1e-10)


def test_interrupted_run_loses_at_most_one_interval(rough, tmp_path, monkeypatch):
    basis = HemiZernike(2)
    path = tmp_path / "run.h5"
    real = est_mod._chunk
    calls = []

    def flaky(*args):
        if len(calls) == 5:
            raise KeyboardInterrupt
        calls.append(1)
        real(*args)

    monkeypatch.setattr(est_mod, "_chunk", flaky)
    with pytest.raises(KeyboardInterrupt):
        # interval 1e-9 s: a checkpoint after every chunk
        simulate(rough, basis, rays=8000, seed=1, chunk=100, checkpoint=path,
                 checkpoint_interval=1e-9)
    monkeypatch.setattr(est_mod, "_chunk", real)
    done = simulate(rough, basis, rays=800 * 5 // 8 * 8, seed=1, chunk=100, resume=path)
    assert done.rays == 5 * 100 * 8  # the five finished chunks survived
    assert not (tmp_path / "run.h5.tmp").exists()


@pytest.mark.parametrize("change, match", [
    ({"seed": 8}, "different seed"),
    ({"basis": HemiZernike(3)}, "different basis"),
    ({"surface": GaussianSurface(1.0, 6.5, resolution=64, seed=4)}, "different surface"),
    ({"incident": "uniform"}, "different incident"),
])
def test_incompatible_resume(rough, tmp_path, change, match):
    path = tmp_path / "run.h5"
    args = {"surface": rough, "basis": HemiZernike(2), "seed": 7}
    simulate(**args, rays=1000, checkpoint=path)
    args.update(change)
    with pytest.raises(ValueError, match=match):
        simulate(**args, rays=2000, resume=path)


def test_unwritable_checkpoint_is_refused_before_tracing(rough, tmp_path, monkeypatch):
    monkeypatch.setattr(est_mod, "_chunk", lambda *a: pytest.fail("traced before checking"))
    with pytest.raises(ValueError, match="checkpoint must be a writable file path"):
        simulate(rough, HemiZernike(2), rays=1000, checkpoint=tmp_path / "no" / "run.h5")
    with pytest.raises(ValueError, match="checkpoint must be a writable file path"):
        simulate(rough, HemiZernike(2), rays=1000, checkpoint=tmp_path)
    with pytest.raises(FileNotFoundError, match="resume must name an existing checkpoint"):
        simulate(rough, HemiZernike(2), rays=1000, resume=tmp_path / "missing.h5")


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


def test_bad_materials():
    with pytest.raises(TypeError, match="material must be a Material"):
        Heightfield(np.zeros((2, 2)), 1.0, material="mirror")
    with pytest.raises(ValueError, match=r"albedo must be <= 1, got 1.5"):
        Diffuse(1.5)
    with pytest.raises(ValueError, match=r"ior must be finite and > 0, got 0"):
        Mirror(0)
    with pytest.raises(ValueError, match=r"k must be 0 when ior is None"):
        Mirror(k=1.0)


@pytest.mark.parametrize("kwargs, exc, match", [
    ({"rays": 0}, ValueError, r"rays must be > 0, got 0"),
    ({"rays": -5}, ValueError, r"rays must be > 0, got -5"),
    ({"rays": 1e4}, TypeError, r"rays must be an integer, got 10000.0"),
    ({"rays": 10, "seed": -1}, ValueError, r"seed must be in \[0, 2\*\*64\), got -1"),
    ({"rays": 10, "incident": "sun"}, ValueError, r"incident must be 'cosine' or 'uniform'"),
    ({"rays": 10, "targets": 0}, ValueError, r"targets must be > 0, got 0"),
    ({"rays": 10, "checkpoint_interval": 0}, ValueError, r"checkpoint_interval must be > 0"),
])
def test_bad_simulate_arguments(rough, kwargs, exc, match):
    with pytest.raises(exc, match=match):
        simulate(rough, HemiZernike(2), **kwargs)


def test_bad_simulate_objects(rough):
    with pytest.raises(TypeError, match="surface must be a Heightfield"):
        simulate(np.zeros((4, 4)), HemiZernike(2), rays=10)
    with pytest.raises(TypeError, match="basis must be a basis object"):
        simulate(rough, "zernike", rays=10)
    with pytest.raises(ValueError, match="wi must be one unit vector with z > 0"):
        trace(rough, [0.6, 0.0, -0.8], 10)
    with pytest.raises(ValueError, match=r"rays must be > 0, got 0"):
        trace(rough, [0.0, 0.0, 1.0], 0)


# -- MicroBRDF facets (wavefront tracer) -------------------------------------------------------

def _flat(material) -> Heightfield:
    return Heightfield(np.zeros((4, 4)), 1.0, material=material)


def _projected(brdf, basis) -> np.ndarray:
    with warnings.catch_warnings():  # sharp lobes in a low order: the truncation warning
        warnings.filterwarnings("ignore", "the expansion of", RuntimeWarning)
        warnings.filterwarnings("ignore", "the mirror term", RuntimeWarning)
        return project(brdf, basis).matrix


def test_flat_micro_lambert_equals_diffuse_and_lambert():
    basis = HemiHarmonics(3)
    micro = simulate(_flat(MicroBRDF(Lambert(0.6))), basis, rays=160000, seed=1, chunk=1000)
    diff = simulate(_flat(Diffuse(0.6)), basis, rays=160000, seed=1, chunk=1000)
    ref = project(Lambert(0.6), basis).matrix
    err = np.abs(micro.matrix.matrix - ref)
    assert np.all(err <= K_SIGMA * micro.stderr + 1e-12), np.max(err / micro.stderr)
    # same streams, different tangent frames: statistically equal (independent-error bound)
    err = np.abs(micro.matrix.matrix - diff.matrix.matrix)
    assert np.all(err <= K_SIGMA * np.hypot(micro.stderr, diff.stderr) + 1e-12)
    # one event of factor exactly 0.6 > roulette threshold: the energy balance is exact
    assert micro.energy == pytest.approx({"reflected": 0.6, "absorbed": 0.4, "escaped": 0.0},
                                         abs=1e-12)


@pytest.mark.parametrize("brdf", [
    CookTorrance(0.0, 0.2, ior=1.5),          # Beckmann lobe sampler, dielectric Fresnel
    CookTorrance(0.1, 0.3, "ggx"),            # GGX sampler + Lambert
    Phong(0.2, 0.6, 30),                      # lobe about the mirror direction
    BlinnPhong(0.3, 0.5, 40),                 # half-vector lobe
    GlossyPaint(0.5, 0.3),                    # Lambert + ideal mirror (delta branch)
], ids=repr)
def test_flat_micro_glossy_reproduces_projection(brdf):
    # The key independent reference: one facet event on a flat plane is the microscale BRDF
    # itself, so the simulated matrix must equal the quadrature projection within
    # K_SIGMA = 5 batch-means standard errors per entry (largest observed deviation over the
    # 5 x 28 x 28 entries: 3.6 sigma).
    basis = HemiZernike(6)
    res = simulate(_flat(MicroBRDF(brdf)), basis, rays=160000, seed=2, chunk=1000)
    ref = _projected(brdf, basis)
    err = np.abs(res.matrix.matrix - ref)
    assert np.all(err <= K_SIGMA * res.stderr + 1e-12), np.max(err / res.stderr)


@pytest.mark.parametrize("theta", [0.0, 60.0, 85.0])
def test_flat_micro_albedo_is_model_albedo(theta):
    brdf = CookTorrance(0.0, 0.2)  # F = 1: albedo 0.99 ... 0.87, single scattering
    p = trace(_flat(MicroBRDF(brdf)), _dir(theta, 30), 40000, seed=3)
    a = float(brdf.albedo(_dir(theta, 30), n_theta=256, n_phi=512))
    se = p.weights.std() / np.sqrt(p.weights.size)
    assert abs(p.weights.mean() - a) < K_SIGMA * se, (p.weights.mean(), a, se)
    assert np.all(p.bounces == 1) and p.lost.sum() == 0


def test_rough_micro_conserves_energy(rough):
    # energy bound: every event keeps at most the microscale albedo in expectation, so the
    # height field reflects no more than the model's largest albedo (+ K_SIGMA sigma)
    brdf = CookTorrance(0.0, 0.2)
    top = float(np.max(brdf.albedo(np.array([_dir(t) for t in range(0, 90, 5)]),
                                   n_theta=128, n_phi=256)))
    surf = GaussianSurface(1.0, 6.5, resolution=64, seed=3, material=MicroBRDF(brdf))
    for theta in [0.0, 45.0, 80.0]:
        p = trace(surf, _dir(theta, 17), 20000, seed=4)
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


class _Negative(BRDF):
    def _eval(self, wi, wo):
        return np.full((wi.shape[0], 1), -0.1)


class _NegativeSomewhere(BRDF):
    """Non-negative on the construction grid (azimuth 0 incidence), negative elsewhere."""

    def _eval(self, wi, wo):
        return np.where(wi[:, 1:2] > 0.5, -1.0, 0.3)


def test_bad_micro_brdf():
    with pytest.raises(TypeError, match="brdf must be a BRDF .* got str"):
        MicroBRDF("lambert")
    with pytest.raises(ValueError, match="brdf must have 1 channel, got 3"):
        MicroBRDF(Lambert([0.1, 0.2, 0.3]))
    with pytest.raises(ValueError, match="brdf must be non-negative, got values down to -0.1"):
        MicroBRDF(_Negative())
    surf = GaussianSurface(1.0, 2.0, resolution=16, seed=1,
                           material=MicroBRDF(_NegativeSomewhere()))
    with pytest.raises(ValueError, match="brdf must be finite and non-negative, got -1.0"):
        trace(surf, _dir(80, 90), 2000, seed=1)
