"""truncate, smooth, lowrank, precision and the fast evaluator, against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

import basis
from basis import CoefficientMatrix
from compress import (
    lowrank,
    precision,
    ringing,
    smooth,
    smoothing_factors,
    truncate,
    unique_coefficients,
)
from project import project
from project.models import Lambert, Phong
from tests.conftest import random_directions

EPS = np.finfo(float).eps


def _random_iso(b, rng, channels=3, quantity="f_cos"):
    blocks = []
    for idx in b.azimuthal_blocks().cos:
        x = rng.normal(size=(channels, idx.size, idx.size))
        blocks.append(x + x.swapaxes(1, 2))
    return CoefficientMatrix.from_blocks(b, blocks, quantity)


# -- truncate ----------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["zernike", "harmonics"])
def test_lambert_survives_every_truncation(kind, rng):
    b = basis.HemiZernike(8) if kind == "zernike" else basis.HemiHarmonics(8)
    cm = project(Lambert(0.6), b)
    wi, wo = random_directions(rng, 500, upper=True), random_directions(rng, 500, upper=True)
    lowest = 0 if kind == "zernike" else 1
    for order in range(lowest, 9):
        t = truncate(cm, order)
        # Lambert is f cos cos = (a/pi) z_i z_o: degree <= 1 in the odd harmonics; in Zernike
        # z = 1 - rho^2 has degree 2, so order 0 and 1 keep only the constant part
        if kind == "harmonics" or order >= 2:
            assert t.info["truncation_change"] < 1e-12  # quadrature rounding of zeros
            # compare q = f cos cos: the coefficients that should vanish carry ~1e-17 of
            # quadrature rounding, which f = q / (cos cos) would amplify near grazing
            cc = wi[:, 2] * wo[:, 2]
            np.testing.assert_allclose(t.eval(wi, wo) * cc, 0.6 / np.pi * cc, rtol=0,
                                       atol=1e-14)
        assert t.info["truncated_from"] == 8 and t.order == order


def test_truncation_change_is_parseval(rng):
    cm = _random_iso(basis.HemiZernike(6), rng, 1)
    t = truncate(cm, 3)
    m, mt = cm.matrix[0], t.matrix[0]
    keep = mt.shape[0]
    dropped = np.sum(m**2) - np.sum(m[:keep, :keep] ** 2)
    # both sides are sums of ~800 squares: relative rounding ~1e-15
    assert abs(t.info["truncation_change"] - np.sqrt(dropped / np.sum(m**2))) < 1e-13


def test_truncate_errors(rng):
    cm = _random_iso(basis.HemiZernike(3), rng)
    with pytest.raises(ValueError, match=r"order must be <= 3 \(the order of"):
        truncate(cm, 4)
    with pytest.raises(TypeError, match="order must be an integer, got 2.0"):
        truncate(cm, 2.0)
    with pytest.raises(TypeError, match="cm must be a basis.CoefficientMatrix"):
        truncate(np.eye(3), 1)


# -- smoothing ---------------------------------------------------------------------------
def test_smoothing_factors_closed_forms():
    n = 7
    d = np.arange(n + 1)
    # Lanczos sigma at d = (N+1)/2 is sin(pi/2)/(pi/2) = 2/pi; Hann there is 1/2
    assert smoothing_factors("lanczos", n)[4] == pytest.approx(2 / np.pi, rel=1e-15)
    assert smoothing_factors("hann", n)[4] == pytest.approx(0.5, rel=1e-15)
    np.testing.assert_allclose(smoothing_factors("hann", n), np.cos(np.pi * d / 16) ** 2,
                               rtol=1e-15)  # (1 + cos 2x)/2 = cos^2 x
    g = smoothing_factors("half-gaussian", 8, start=3, width=2.0)
    assert np.all(g[:4] == 1.0)
    assert g[5] == pytest.approx(np.exp(-0.5), rel=1e-15)  # one width above start
    # defaults: start = order // 2 = 4, width = (8 - 4)/2 = 2 -> exp(-2) at the last degree
    assert smoothing_factors("half-gaussian", 8)[8] == pytest.approx(np.exp(-2), rel=1e-15)


def test_smooth_is_separable_and_reciprocal(rng):
    b = basis.HemiHarmonics(6)
    cm = _random_iso(b, rng, 1)
    s = smooth(cm, "lanczos")
    w = smoothing_factors("lanczos", 6)[b.degree]
    np.testing.assert_allclose(s.matrix, cm.matrix * np.outer(w, w), rtol=1e-15, atol=0)
    wi, wo = random_directions(rng, 200, upper=True), random_directions(rng, 200, upper=True)
    # symmetric matrix: exact reciprocity up to the rounding of the two bilinear sums
    np.testing.assert_allclose(s.eval(wi, wo), s.eval(wo, wi), rtol=1e-12, atol=1e-12)
    rep = s.info["smoothing"]
    assert rep["kind"] == "lanczos" and rep["start"] is None
    assert set(rep["before"]) == {"negative_fraction", "min_value", "overshoot", "pairs"}


def test_smoothing_reduces_ringing():
    brdf = Phong(0.0, 1.0, 60.0)  # sharp lobe: order 6 rings
    with pytest.warns(RuntimeWarning, match="misses"):
        cm = project(brdf, basis.HemiZernike(6))
    s = smooth(cm, "hann", brdf=brdf)
    before, after = s.info["smoothing"]["before"], s.info["smoothing"]["after"]
    assert before["negative_fraction"] > 0.05  # observed 0.28
    assert after["negative_fraction"] < before["negative_fraction"]
    assert after["min_value"] > before["min_value"]
    assert before["overshoot"] is not None and after["overshoot"] <= before["overshoot"]


def test_ringing_of_lambert_is_zero():
    r = ringing(project(Lambert(0.5), basis.HemiHarmonics(3)), Lambert(0.5))
    # exact representation: overshoot is rounding (1e-15 relative), no negative values
    assert r.negative_fraction == 0.0 and r.overshoot < 1e-12 and r.pairs == 1 << 15


def test_smooth_errors(rng):
    cm = _random_iso(basis.HemiZernike(2), rng)
    with pytest.raises(ValueError, match="kind must be one of 'half-gaussian'"):
        smooth(cm, "box")
    with pytest.raises(ValueError, match="start and width apply to kind='half-gaussian'"):
        smooth(cm, "hann", width=2.0)
    with pytest.raises(ValueError, match="width must be a positive number"):
        smoothing_factors("half-gaussian", 4, width=0.0)


# -- low rank ----------------------------------------------------------------------------
def test_lowrank_rank_one_exact(rng):
    b = basis.HemiZernike(5)
    u = rng.normal(size=b.size)
    u[b.azimuthal != 2] = 0.0  # one azimuthal order: one block term (cos and sin copies)
    cm = CoefficientMatrix(b, np.outer(u, u) + np.outer(u * (b.azimuthal == 2), u)[::-1, ::-1]
                           * 0, isotropic=False)
    iso = cm.to_isotropic()
    r = lowrank(iso, 1)
    np.testing.assert_allclose(r.matrix, iso.matrix, rtol=0, atol=1e-13 * np.max(u**2))
    assert r.info["lowrank"]["error"] < 1e-14


def test_lowrank_eckart_young(rng):
    b = basis.HemiZernike(4)
    x = rng.normal(size=(b.size, b.size))
    cm = CoefficientMatrix(b, x + x.T, isotropic=False)
    lam = np.linalg.eigvalsh(cm.matrix)
    lam = lam[np.argsort(-np.abs(lam))]
    for rank in (1, 5, 14):
        r = lowrank(cm, rank)
        want = np.sqrt(np.sum(lam[rank:] ** 2) / np.sum(lam**2))
        # Frobenius error of the best rank-r symmetric approximation; rounding ~1e-15
        assert r.info["lowrank"]["error"] == pytest.approx(want, abs=1e-13)
        assert np.linalg.matrix_rank(r.matrix, tol=1e-10) == rank
        assert r.info["lowrank"]["numbers"] == rank * (1 + b.size)
    with pytest.raises(ValueError, match="rank must be <= 15"):
        lowrank(cm, 16)
    with pytest.raises(ValueError, match="rank must be >= 1"):
        lowrank(cm, 0)


# -- precision ---------------------------------------------------------------------------
@pytest.mark.parametrize("dtype, u", [("float64", 0.0), ("float32", 2.0**-24),
                                      ("float16", 2.0**-11)])
def test_precision_error_bounded_by_unit_roundoff(rng, dtype, u):
    cm = _random_iso(basis.HemiZernike(6), rng)
    p = precision(cm, dtype)
    info = p.info["precision"]
    # round to nearest: every entry moves by <= u |x|, so the relative L2 change is <= u
    assert info["error"] <= u and (info["error"] > u / 10 or u == 0.0)
    assert info["bytes"] == unique_coefficients(cm) * np.dtype(dtype).itemsize
    with pytest.raises(ValueError, match="dtype must be one of"):
        precision(cm, "float8")


def test_precision_overflow():
    cm = CoefficientMatrix(basis.HemiZernike(0), [[1e5]])
    with pytest.raises(ValueError, match="cannot hold coefficients up to 100000"):
        precision(cm, "float16")


# -- general (non-reciprocal) matrices --------------------------------------------------------
def _general(rng, dense=False, channels=2):
    from basis import HemiZernike

    b = HemiZernike(6)
    blocks = [rng.normal(size=(channels, i.size, i.size)) for i in b.azimuthal_blocks().cos]
    cm = CoefficientMatrix.from_blocks(b, blocks, "f", reciprocal=False)
    if dense:
        cm = CoefficientMatrix(b, rng.normal(size=(channels, b.size, b.size)), "f",
                               isotropic=False, reciprocal=False)
    return cm


@pytest.mark.parametrize("dense", [False, True])
def test_general_truncate_smooth_precision(rng, dense):
    cm = _general(rng, dense)
    m = cm.matrix
    t = truncate(cm, 4)
    k = t.basis.size
    assert not t.reciprocal
    np.testing.assert_array_equal(t.matrix, m[:, :k, :k])
    # dropped part by Parseval, computed densely: rounding ~1e-15
    want = np.max(np.sqrt(1 - np.sum(m[:, :k, :k] ** 2, axis=(1, 2))
                          / np.sum(m**2, axis=(1, 2))))
    assert t.info["truncation_change"] == pytest.approx(want, rel=1e-12)
    s = smooth(cm, "hann")
    w = smoothing_factors("hann", cm.order)[cm.basis.degree]
    assert not s.reciprocal
    np.testing.assert_allclose(s.matrix, m * w[:, None] * w[None, :], rtol=0, atol=1e-15 * 8)
    p = precision(cm, "float32")
    assert not p.reciprocal
    np.testing.assert_array_equal(p.matrix, m.astype(np.float32).astype(np.float64))
    # a general block of side k holds k^2 numbers
    sides = [x.shape[-1] for x in cm.stored]
    assert unique_coefficients(cm) == 2 * sum(n * n for n in sides)
    assert p.info["precision"]["bytes"] == 4 * unique_coefficients(cm)
    assert unique_coefficients(cm.symmetric_part()) == 2 * sum(n * (n + 1) // 2 for n in sides)


def test_general_lowrank_dense_is_the_truncated_svd(rng):
    # Eckart-Young: the best rank-r approximation is the truncated SVD (numpy reference)
    cm = _general(rng, dense=True, channels=1)
    m = cm.matrix[0]
    u, s, vt = np.linalg.svd(m)
    for r in (1, 5, 20):
        lr = lowrank(cm, r)
        ref = (u[:, :r] * s[:r]) @ vt[:r]
        assert not lr.reciprocal
        np.testing.assert_allclose(lr.matrix[0], ref, rtol=0, atol=1e-12 * s[0])
        info = lr.info["lowrank"]
        assert info["error"] == pytest.approx(np.sqrt(np.sum(s[r:] ** 2) / np.sum(s**2)),
                                              rel=1e-10)
        np.testing.assert_allclose(info["singular_values"][0], s[:r], rtol=1e-12)
        assert info["numbers"] == r * (1 + 2 * cm.basis.size)


def test_general_lowrank_isotropic_competes_across_blocks(rng):
    # reference: every block's singular values, a block m > 0 weighted twice (cos and sin
    # copies), the r largest kept; error = sqrt(dropped weighted s^2 / total)
    cm = _general(rng, channels=1)
    blocks = [b[0] for b in cm.stored]
    terms = sorted(((1 if m == 0 else 2) * x * x, m) for m, b in enumerate(blocks)
                   for x in np.linalg.svd(b, compute_uv=False))[::-1]
    total = sum(t for t, _ in terms)
    for r in (1, 4, 9):
        lr = lowrank(cm, r)
        dropped = sum(t for t, _ in terms[r:])
        assert lr.is_isotropic and not lr.reciprocal
        assert lr.info["lowrank"]["error"] == pytest.approx(np.sqrt(dropped / total), rel=1e-10)
        # the kept terms of each block are its truncated SVD
        for m, b in enumerate(blocks):
            n = sum(1 for _, mm in terms[:r] if mm == m)
            u, s, vt = np.linalg.svd(b)
            np.testing.assert_allclose(lr.blocks[m][0], (u[:, :n] * s[:n]) @ vt[:n], rtol=0,
                                       atol=1e-12 * s[0])
