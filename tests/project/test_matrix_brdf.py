"""MatrixBRDF: a coefficient matrix evaluated and importance-sampled as a BRDF, and the
recursion (the simulated matrix of a surface whose facets scatter with a matrix).

References: the matrix's own evaluation and exact albedo, exact quadrature of the
piecewise-constant pdf (cell-aligned midpoint rule), chi-square and Kolmogorov-Smirnov tests
of the samples against the pdf, and the quadrature projection of the microscale BRDF.
Monte Carlo assertions use k = 5 standard errors (K_SIGMA), seeds are fixed.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy import stats

from basis import (
    CoefficientMatrix,
    HemiHarmonics,
    HemiZernike,
    SphericalHarmonics,
    hemisphere_rule,
)
from project import MatrixBRDF, project
from project.microgeometry import Heightfield, MicroBRDF, brushed_metal, simulate, trace
from project.microgeometry.scatter import FacetSampler
from project.models import Lambert, Phong, Ward
from tests.project.mc import K_SIGMA, rotation_action


def _dir(theta_deg: float, phi_deg: float = 0.0) -> np.ndarray:
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def _projected(brdf, basis, **kw) -> CoefficientMatrix:
    with warnings.catch_warnings():  # sharp lobes in a low order: the truncation warning
        warnings.filterwarnings("ignore", "the expansion of", RuntimeWarning)
        return project(brdf, basis, **kw)


@pytest.fixture(scope="module")
def peaked() -> CoefficientMatrix:
    """A glossy lobe truncated at order 8 (odd harmonics, f cos cos): negative lobes near
    the horizon, albedo <= 1.05 (no warning)."""
    return _projected(Phong(0.1, 0.8, 30), HemiHarmonics(8))


@pytest.fixture(scope="module")
def anisotropic() -> CoefficientMatrix:
    """Ward with alpha_x = 0.2, alpha_y = 0.6 in HemiHarmonics(4): a general (dense) matrix
    (one fixed quadrature rule: accuracy of the projection does not matter here)."""
    return _projected(Ward(0.3, 0.5, 0.2, 0.6), HemiHarmonics(4), nodes=(16, 32))


def _cell_rule(wi, n_z, n_ph, sub=1):
    """Midpoints of the (n_z sub) x (n_ph sub) grid in (z_o, azimuth relative to wi):
    exact for a density that is constant on the n_z x n_ph cells. Returns (points, weight)."""
    z = (np.arange(n_z * sub) + 0.5) / (n_z * sub)
    phi = np.arctan2(wi[1], wi[0]) + 2 * np.pi * (np.arange(n_ph * sub) + 0.5) / (n_ph * sub)
    s = np.sqrt(1 - z * z)
    w = np.stack([s[:, None] * np.cos(phi), s[:, None] * np.sin(phi),
                  np.broadcast_to(z[:, None], (z.size, phi.size))], -1)
    return w.reshape(-1, 3), 2 * np.pi / w[..., 0].size


# -- evaluation ---------------------------------------------------------------------------------

def test_eval_is_the_matrix_where_non_negative(rng):
    cm = _projected(Phong(0.3, 0.5, 2), HemiHarmonics(4))
    brdf = MatrixBRDF(cm)
    assert brdf.min_value > 0 and brdf.clamp_bias == 0.0 and brdf.isotropic
    wi, wo = rng.normal(size=(2, 50, 3))
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]), np.abs(wo[:, 2])
    wi /= np.linalg.norm(wi, axis=1)[:, None]
    wo /= np.linalg.norm(wo, axis=1)[:, None]
    np.testing.assert_array_equal(brdf.eval(wi, wo), cm.eval(wi, wo))
    assert brdf.eval(_dir(30), -_dir(30)) == 0.0  # below the horizon
    # the tabulated albedo (midpoint rule on 64 x 128 exit points) against the exact one
    # of the matrix: the smooth integrand leaves ~1e-4
    np.testing.assert_allclose(brdf.albedo_table[:, 0],
                               cm.albedo(np.array([_dir(t) for t in np.linspace(0, 90, 16)])),
                               rtol=0, atol=1e-3)


def test_clamped_eval_and_clamp_bias(peaked):
    with pytest.raises(ValueError, match=r"matrix must be non-negative as a BRDF: it reaches "
                                         r"f = -1\.5\d+ \(below -tol \* max f = -0\.12\d+\) at "
                                         r"theta_i = 90\.0 deg.*negative='clamp'.*"
                                         r"compress\.smooth"):
        MatrixBRDF(peaked)
    brdf = MatrixBRDF(peaked, negative="clamp")
    assert brdf.min_value < -1.5 and brdf.clamp_bias > 0.5
    wi = np.array([_dir(t, 20) for t in np.linspace(0, 90, 16)])
    wo = np.array([_dir(t, p) for t in (10, 50, 88) for p in (0, 170)])
    f = peaked.eval(wi[:, None], wo)
    # the same sums in another batch order: rounding of values up to ~10
    np.testing.assert_allclose(brdf.eval(wi[:, None], wo), np.maximum(f, 0.0), rtol=0,
                               atol=1e-13)
    # the clamp adds exactly int max(-f, 0) cos: clamped albedo (Gauss-Legendre product rule
    # on the BRDF) minus the matrix's exact albedo, against the table (midpoint rule on
    # 64 x 128 points). Both integrate a kinked function: observed 1.1e-3 of 0.58, from the
    # table (unchanged when the product rule is refined to 256 x 512). The table's incident
    # nodes are these 16 theta_i; azimuth 20 deg changes nothing (isotropic)
    rule = hemisphere_rule(64, 128)
    added = brdf.eval(wi[:, None], rule.points) @ (rule.weights * rule.points[:, 2]) \
        - peaked.albedo(wi)
    np.testing.assert_allclose(added, brdf.clamp_table[:, 0], rtol=0, atol=3e-3)
    assert brdf.clamp_bias == brdf.clamp_table.max()


def test_channels_and_simulation_result(rng):
    cm = _projected(Lambert([0.2, 0.5, 0.8]), HemiHarmonics(3))
    brdf = MatrixBRDF(cm)
    assert brdf.channels == 3
    assert brdf.eval(_dir(10), _dir(40, 90)).shape == (3,)
    np.testing.assert_allclose(brdf.albedo_table, np.broadcast_to([0.2, 0.5, 0.8], (16, 3)),
                               rtol=1e-12)

    class Result:  # what a SimulationResult offers
        matrix = _projected(Lambert(0.5), HemiHarmonics(3))

    assert MatrixBRDF(Result()).eval(_dir(0), _dir(60)) == pytest.approx(0.5 / np.pi, 1e-12)


def test_full_sphere_basis_is_accepted():
    # full-sphere harmonics are evaluated on the upper hemisphere only (f = 0 below it, by
    # the BRDF contract); their truncation rings at the horizon like any other, so a
    # projection of Lambert at order 4 has small negative lobes (within tol) and is usable
    cm = _projected(Lambert(0.5), SphericalHarmonics(4), quantity="f")
    brdf = MatrixBRDF(cm, tol=0.2)
    wi, wo = _dir(20), np.array([_dir(70, 40), _dir(89.5, 100)])
    np.testing.assert_array_equal(brdf.eval(wi, wo), np.maximum(cm.eval(wi, wo), 0.0))
    assert brdf.eval(wi, -wo[0]) == 0.0


def test_grazing_amplification_of_f_cos_warns():
    # HemiZernike functions do not vanish on the horizon: the truncated q / (cos cos) of a
    # glossy lobe reaches albedos far above 1 at grazing incidence
    cm = _projected(Phong(0.3, 0.5, 2), HemiZernike(4), quantity="f_cos")
    with pytest.warns(RuntimeWarning, match=r"reflects more than it receives: directional "
                                            r"albedo up to \d+\.?\d* at theta_i = 90\.0 deg"):
        MatrixBRDF(cm, negative="clamp")
    # the same lobe as quantity "f" is fine
    brdf = MatrixBRDF(_projected(Phong(0.3, 0.5, 2), HemiZernike(4), quantity="f"))
    assert brdf.albedo_table.max() < 1


def test_rotated_agrees_with_the_least_squares_quarter_turn(anisotropic):
    # CoefficientMatrix.rotated(pi/2) against A^T M A with the signed permutation A that
    # test_scene.py finds by least squares (entries ~0.4; cos(m pi/2) is 0 only to 6e-17)
    a = rotation_action(anisotropic.basis)
    np.testing.assert_allclose(anisotropic.rotated(np.pi / 2).matrix,
                               a.T @ anisotropic.matrix @ a, rtol=0, atol=1e-15)


def test_rotated_matrix_turns_the_brdf(anisotropic):
    a = 0.8
    b0 = MatrixBRDF(anisotropic, negative="clamp")
    b1 = MatrixBRDF(anisotropic.rotated(a), negative="clamp")
    assert not b0.isotropic
    c, s = np.cos(a), np.sin(a)
    rinv = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])  # R^-1 w = rinv @ w
    wi = np.array([_dir(t, p) for t, p in ((10, 0), (45, 70), (80, 200))])
    wo = np.array([_dir(t, p) for t, p in ((30, 10), (60, 150), (5, 300))])
    np.testing.assert_allclose(b1.eval(wi[:, None], wo), b0.eval((wi @ rinv.T)[:, None],
                                                                wo @ rinv.T),
                               rtol=0, atol=1e-13)


# -- sampling -----------------------------------------------------------------------------------

@pytest.mark.parametrize("which", ["peaked", "anisotropic"])
@pytest.mark.parametrize("theta, phi", [(0.0, 0.0), (37.3, 21.0), (71.0, 200.0), (90.0, 95.0)])
def test_pdf_integrates_to_one(which, theta, phi, request):
    brdf = MatrixBRDF(request.getfixturevalue(which), negative="clamp")
    wi = _dir(theta, phi)
    # the pdf is constant on cells of (z_o, relative azimuth): the midpoint rule on them is
    # exact; sums of 2048 terms leave ~1e-15
    pts, dw = _cell_rule(wi, 32, 64)
    p = brdf.pdf(np.broadcast_to(wi, pts.shape), pts)
    assert abs(p.sum() * dw - 1.0) < 1e-12
    assert p.min() > 0.0  # the defensive floor: positive on the whole hemisphere
    assert brdf.pdf(wi[None], -_dir(40)[None])[0] == 0.0


@pytest.mark.parametrize("which, theta, phi", [("peaked", 37.3, 21.0),
                                               ("anisotropic", 52.0, 111.0)])
def test_samples_follow_the_pdf(which, theta, phi, request):
    brdf = MatrixBRDF(request.getfixturevalue(which), negative="clamp")
    wi = _dir(theta, phi)
    n = 200_000
    u = np.random.default_rng(11).random((n, 2))
    wo = brdf.sample(np.broadcast_to(wi, (n, 3)), u)
    np.testing.assert_allclose(np.linalg.norm(wo, axis=1), 1.0, rtol=0, atol=1e-14)
    assert wo[:, 2].min() > 0
    # chi-square on 8 x 16 bins of 4 x 4 cells each (relative azimuth), expected counts by
    # the exact cell rule; seeded, so the p-value is a fixed number (observed > 0.05)
    pts, dw = _cell_rule(wi, 32, 64)
    p = brdf.pdf(np.broadcast_to(wi, pts.shape), pts).reshape(8, 4, 16, 4).sum(axis=(1, 3))
    expected = n * p.reshape(-1) * dw
    rel = (np.arctan2(wo[:, 1], wo[:, 0]) - np.radians(phi)) % (2 * np.pi)
    zb = np.minimum((wo[:, 2] * 8).astype(int), 7)
    pb = np.minimum((rel / (2 * np.pi) * 16).astype(int), 15)
    counts = np.bincount(zb * 16 + pb, minlength=128)
    keep = expected > 5
    assert keep.sum() > 40
    chi2 = np.sum((counts[keep] - expected[keep]) ** 2 / expected[keep])
    assert stats.chi2.sf(chi2, keep.sum() - 1) > 1e-3, chi2
    # uniform inside the cells: the fractional cell coordinates, Kolmogorov-Smirnov
    for frac in (wo[:, 2] * 32 % 1.0, rel / (2 * np.pi) * 64 % 1.0):
        assert stats.kstest(frac, "uniform").pvalue > 1e-3


def test_sampler_reduces_variance(peaked):
    # per-sample variance of the estimator f cos / pdf of the albedo, importance sampling
    # against cosine sampling (factor pi f): observed ratios 36 ... 117
    brdf = MatrixBRDF(peaked, negative="clamp")
    rng = np.random.default_rng(3)
    n = 50_000
    for theta in (0.0, 30.0, 60.0):
        wi = np.broadcast_to(_dir(theta, 40), (n, 3))
        u = rng.random((n, 2))
        wo = brdf.sample(wi, u)
        est = brdf.eval(wi, wo) * wo[:, 2] / brdf.pdf(wi, wo)
        r = np.sqrt(u[:, 0])
        wc = np.stack([r * np.cos(2 * np.pi * u[:, 1]), r * np.sin(2 * np.pi * u[:, 1]),
                       np.sqrt(1 - u[:, 0])], 1)
        cos_est = np.pi * brdf.eval(wi, wc)
        # both estimate the same albedo (within the combined standard error)
        se = np.hypot(est.std(), cos_est.std()) / np.sqrt(n)
        assert abs(est.mean() - cos_est.mean()) < K_SIGMA * se
        assert cos_est.var() > 20 * est.var(), (theta, cos_est.var() / est.var())


def test_facet_sampler_uses_the_brdf_sampler(peaked):
    s = FacetSampler(MatrixBRDF(peaked, negative="clamp"))
    assert s.lobe == "brdf" and s.lobe_fraction == 0.9 and s.uniforms == 3
    # the mixture estimate of the albedo is unbiased: the clamped BRDF's albedo by quadrature
    wi = _dir(50, 10)
    n = 100_000
    u = np.random.default_rng(4).random((n, 3))
    _, factor = s.scatter(np.broadcast_to(wi, (n, 3)).copy(), u)
    a = float(s.brdf.albedo(wi, n_theta=256, n_phi=256))
    assert abs(factor.mean() - a) < K_SIGMA * factor.std() / np.sqrt(n)


# -- recursion ----------------------------------------------------------------------------------

def _flat(material) -> Heightfield:
    return Heightfield(np.zeros((4, 4)), 1.0, material=material)


@pytest.mark.parametrize("brdf, basis", [(Lambert(0.7), HemiHarmonics(3)),
                                         (Phong(0.3, 0.5, 2), HemiHarmonics(4))], ids=repr)
def test_recursion_reproduces_the_matrix(brdf, basis):
    # one facet event on a flat plane is the microscale BRDF itself, so simulating a plane
    # whose facets scatter with M (non-negative, in the simulation's basis) must give M back
    # within K_SIGMA batch-means standard errors per entry (observed max 2.5 sigma)
    cm = _projected(brdf, basis)
    res = simulate(_flat(MicroBRDF(MatrixBRDF(cm))), basis, rays=80000, seed=1, chunk=1000)
    err = np.abs(res.matrix.matrix - cm.matrix)
    assert np.all(err <= K_SIGMA * res.stderr + 1e-12), np.max(err / res.stderr)


def test_recursion_of_a_clamped_lossless_thread():
    # a lossless specimen (mirror cylinders: albedo exactly 1) simulated at order 4, used as
    # the facet BRDF of a flat plane: every ray's energy is accounted for, and the plane
    # reflects what the clamped representation reflects -- between the unclamped matrix's
    # hemispherical albedo g^T M g / pi (exact) and that plus the clamp bias
    b = HemiHarmonics(4)
    thread = simulate(brushed_metal(0.4, 1.0), b, rays=100000, seed=1, chunk=2500)
    assert thread.energy["reflected"] == 1.0
    with pytest.warns(RuntimeWarning, match="reflects more than it receives"):
        brdf = MatrixBRDF(thread, negative="clamp")
    res = simulate(_flat(MicroBRDF(brdf)), b, rays=80000, seed=2, chunk=1000)
    e = res.energy
    assert e["escaped"] == 0.0
    # per ray, reflected + absorbed = 1 except for Russian roulette, which is unbiased
    for theta in (0.0, 60.0, 89.0):
        p = trace(_flat(MicroBRDF(brdf)), _dir(theta, 30), 20000, seed=4)
        tot = p.weights + p.absorbed + p.lost
        assert abs(tot.mean() - 1.0) <= K_SIGMA * tot.std() / np.sqrt(tot.size) + 1e-14
    g = b.moments("none")
    unclamped = float(g @ thread.matrix.matrix @ g / np.pi)
    # cosine-weighted mean of the clamped albedo over incidences (it depends on phi_i: the
    # thread is anisotropic), product rules in and out; ~1e-3 from the kinks of the clamp
    ri, ro = hemisphere_rule(10, 12), hemisphere_rule(48, 96)
    f = brdf.eval(ri.points[:, None], ro.points)
    clamped = float((ri.weights * ri.points[:, 2] / np.pi) @ f @ (ro.weights * ro.points[:, 2]))
    assert unclamped - 0.01 < clamped <= unclamped + brdf.clamp_bias
    # reflected energy per ray: its standard error from the batch means of M is not at
    # hand, so bound it by the per-ray spread (factor <= f cos / pdf <= ~10): 0.03 / sqrt(N)
    assert abs(e["reflected"] - clamped) < K_SIGMA * 3.0 / np.sqrt(res.rays)


# -- bad input ----------------------------------------------------------------------------------

def test_bad_input(peaked):
    with pytest.raises(TypeError, match=r"matrix must be a basis\.CoefficientMatrix .* got "
                                        r"ndarray"):
        MatrixBRDF(np.eye(3))
    with pytest.raises(ValueError, match=r"negative must be one of 'raise', 'clamp', got "
                                         r"'ignore'"):
        MatrixBRDF(peaked, negative="ignore")
    with pytest.raises(ValueError, match=r"tol must lie in \[0, 1\), got 1\.5"):
        MatrixBRDF(peaked, tol=1.5)
    with pytest.raises(ValueError, match=r"min_cos must lie in \(0, 1\), got 0\.0"):
        MatrixBRDF(peaked, min_cos=0.0)
    with pytest.raises(ValueError, match=r"incident must be at least \(2, 1\), got \(1, 4\)"):
        MatrixBRDF(peaked, incident=(1, 4))
    with pytest.raises(TypeError, match=r"cells must be a pair of integers, got 8"):
        MatrixBRDF(peaked, cells=8)
    zb = HemiZernike(2)
    aniso = CoefficientMatrix(zb, np.eye(6) + np.eye(6)[::-1], quantity="f")
    with pytest.raises(ValueError, match=r"cells\[1\] must be a multiple of incident\[1\] = 16"
                                         r" for an anisotropic matrix, got 40"):
        MatrixBRDF(aniso, negative="clamp", cells=(32, 40))
    # non-finite matrices never get this far; values that overflow do
    with pytest.raises(ValueError, match=r"matrix must be finite"):
        CoefficientMatrix(zb, np.full((6, 6), np.nan))
    with pytest.raises(ValueError, match=r"matrix must evaluate to finite values"):
        # q ~ 1e304 divided by min_cos^2 = 1e-6 at the horizon overflows
        MatrixBRDF(CoefficientMatrix(zb, np.full((6, 6), 1e303)))
    brdf = MatrixBRDF(peaked, negative="clamp")
    with pytest.raises(ValueError, match=r"u must have shape \(2, 2\), got shape \(2, 3\)"):
        brdf.sample(np.array([_dir(0), _dir(30)]), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"wi must lie in the upper hemisphere"):
        brdf.pdf(-_dir(30)[None], _dir(30)[None])
    with pytest.raises(ValueError, match=r"wo must have the shape of wi \(1, 3\), got "
                                         r"\(2, 3\)"):
        brdf.pdf(_dir(30)[None], np.array([_dir(0), _dir(10)]))
