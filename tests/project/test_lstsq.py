"""project.fit (module project.lstsq): least-squares fits of scattered samples (design matrix
against the Helmholtz modes, recovery of known coefficients, weights, regularization,
conditioning against numpy's SVD), the automatic regularisation on gonioreflectometer-like
data (a few incidences, dense outgoing directions) against a known BRDF, the seed's brick
scenario on the 40-face tessellation, binning and table reading."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import project.lstsq as fitmod
from basis import (
    CoefficientMatrix,
    HelmholtzModes,
    HemiHarmonics,
    HemiZernike,
    SphericalHarmonics,
    from_angles,
)
from project.lstsq import (
    REGULARIZATION_METHODS,
    bin_samples,
    design_matrix,
    fit,
    read_table,
    tessellate_hemisphere,
    to_unknowns,
)
from project.models import OrenNayar, Phong

EPS = np.finfo(np.float64).eps


def _random_matrix(rng, basis, *, isotropic, channels=None):
    """A random symmetric CoefficientMatrix (projected onto the isotropic ones if asked)."""
    shape = (basis.size, basis.size) if channels is None else (channels, basis.size, basis.size)
    a = rng.normal(size=shape)
    cm = CoefficientMatrix(basis, a + np.swapaxes(a, -1, -2), "f", isotropic=False)
    return cm.to_isotropic() if isotropic else cm


def _with_quantity(cm, quantity):
    m = cm.blocks if cm.is_isotropic else None
    if m is not None:
        return CoefficientMatrix.from_blocks(cm.basis, m, quantity)
    return CoefficientMatrix(cm.basis, cm.matrix, quantity, isotropic=False)


def _face_centre_pairs():
    """The seed's 40 x 40 data layout: every (face_i, face_o) pair of face centroids."""
    t = tessellate_hemisphere()
    i, o = np.meshgrid(np.arange(t.size), np.arange(t.size), indexing="ij")
    return t, t.centroids[i.ravel()], t.centroids[o.ravel()]


def brick_like(wi, wo, albedo=0.45, lobes=1.5, sharpness=2.0):
    """A smooth isotropic reciprocal BRDF in the spirit of the seed's brick: Lambertian near
    the normal, with back- and forward-scatter lobes that grow towards grazing angles."""
    zi, zo = wi[..., 2], wo[..., 2]
    back = np.einsum("...j,...j->...", wi, wo)
    forward = zi * zo - wi[..., 0] * wo[..., 0] - wi[..., 1] * wo[..., 1]
    grazing = (1 - zi) * (1 - zo)
    return albedo / np.pi * (1 + lobes * grazing * (np.exp(sharpness * (back - 1))
                                                    + np.exp(sharpness * (forward - 1))))


# -- the design matrix -------------------------------------------------------------------------
@pytest.mark.parametrize("isotropic", [True, False])
def test_design_columns_are_helmholtz_modes(isotropic, unit_vectors):
    # independent reference: basis.HelmholtzModes builds the same orthonormal reciprocal
    # products its own way (indices (n, m, l) or pairs (a, b))
    zb = HemiZernike(4)
    wi, wo = unit_vectors(200, upper=True), unit_vectors(200, upper=True)
    got = design_matrix(wi, wo, zb, isotropic=isotropic)
    hm = HelmholtzModes(4, isotropic=isotropic)
    lay = fitmod.unknowns(zb, isotropic)
    if isotropic:
        cells = zip(lay.block, lay.brow, lay.bcol, strict=True)
        where = {(b, j, k): u for u, (b, j, k) in enumerate(cells)}
        perm = [where[(az, (m - az) // 2, (n - az) // 2)] for n, m, az in hm.indices]
    else:
        where = {(j, k): u for u, (j, k) in enumerate(zip(lay.rows, lay.cols, strict=True))}
        perm = [where[(a, b)] for a, b in hm.pairs]
    assert sorted(perm) == list(range(hm.size))
    # values are O(1) products of two or four O(1) factors: rounding only
    np.testing.assert_allclose(got[:, perm], hm.eval(wi, wo), rtol=0, atol=1e-13)


@pytest.mark.parametrize("basis", [HemiZernike(4), HemiHarmonics(5)])
# a constant is not in the span of the odd completion (HemiHarmonics), whose fit of f = 1
# is then rightly reported worse than a Lambertian one; the condition number is the point
@pytest.mark.filterwarnings("ignore:fit predicts held-out samples worse than a Lambertian")
def test_exact_quadrature_gives_condition_one(basis):
    # the columns are orthonormal on H x H; the product of two exact rules integrates every
    # product of two columns exactly, so the weighted design has orthonormal columns
    rule = basis.exact_rule()
    p = rule.points.shape[0]
    i, o = np.meshgrid(np.arange(p), np.arange(p), indexing="ij")
    wi, wo = rule.points[i.ravel()], rule.points[o.ravel()]
    w = rule.weights[i.ravel()] * rule.weights[o.ravel()]
    cm = fit(wi, wo, np.ones(p * p), basis, weights=w, isotropic=False)
    # rounding in the Gauss-Legendre nodes and in Gram sums of ~1e3 terms
    assert cm.info["condition_number"] == pytest.approx(1.0, abs=1e-12)


def test_to_unknowns_norm_is_frobenius(rng, unit_vectors):
    zb = HemiZernike(3)
    for iso in (True, False):
        cm = _random_matrix(rng, zb, isotropic=iso)
        z = to_unknowns(cm, isotropic=iso)
        # the scaling by sqrt(mult) makes the unknowns an isometry of M: rounding only
        assert np.linalg.norm(z) == pytest.approx(np.linalg.norm(cm.matrix), rel=1e-14)
        wi, wo = unit_vectors(50, upper=True), unit_vectors(50, upper=True)
        np.testing.assert_allclose(design_matrix(wi, wo, zb, isotropic=iso) @ z,
                                   cm.eval(wi, wo), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="cm must be isotropic"):
        to_unknowns(_random_matrix(rng, zb, isotropic=False), isotropic=True)
    with pytest.raises(TypeError, match="cm must be a CoefficientMatrix"):
        to_unknowns(np.eye(3))


# -- recovery of known coefficients ------------------------------------------------------------
@pytest.mark.parametrize("basis", [HemiZernike(4), HemiHarmonics(5)])
@pytest.mark.parametrize("isotropic", [True, False])
@pytest.mark.parametrize("quantity", ["f", "f_cos"])
def test_recovers_known_coefficients(basis, isotropic, quantity, rng, unit_vectors):
    truth = _with_quantity(_random_matrix(rng, basis, isotropic=isotropic, channels=3),
                           quantity)
    wi, wo = unit_vectors(700, upper=True), unit_vectors(700, upper=True)
    # stay clear of the horizon so that eval(f_cos) needs no min_cos lift (f = q / cos cos)
    ok = (wi[:, 2] > 0.01) & (wo[:, 2] > 0.01)
    wi, wo = wi[ok], wo[ok]
    values = truth.eval(wi, wo)
    cm = fit(wi, wo, values, basis, quantity=quantity, isotropic=isotropic)
    assert cm.is_isotropic == isotropic and cm.channels == 3 and cm.quantity == quantity
    info = cm.info
    assert info["unknowns"] == (HelmholtzModes(4).size if isotropic else 120)
    assert info["rank"] == info["unknowns"] and info["samples"] == wi.shape[0]
    cond, scale = info["condition_number"], np.max(np.abs(truth.matrix))
    # noise-free data carry rounding ~ eps relative; least squares turns it into at most
    # ~cond * eps relative error in the unknowns; 100x covers the sums of ~10^2 terms
    # (observed: 1e-15 .. 3e-15 relative to max |M|, with cond 1.3 .. 8)
    np.testing.assert_allclose(cm.matrix, truth.matrix, rtol=0, atol=100 * cond * EPS * scale)
    # the residual of an exact representation is rounding of q: sums of ~10^2 terms
    q = values * (wi[:, 2] * wo[:, 2])[:, None] if quantity == "f_cos" else values
    assert max(info["residual_rms"]) < 100 * EPS * np.max(np.abs(q))


# -- non-reciprocal fits ------------------------------------------------------------------------
def _random_general(rng, basis, *, isotropic, channels=3):
    """A random non-symmetric CoefficientMatrix (isotropic: independent blocks B_m)."""
    if isotropic:
        sizes = [c.size for c in basis.azimuthal_blocks().cos]
        blocks = [rng.normal(size=(channels, k, k)) for k in sizes]
        return CoefficientMatrix.from_blocks(basis, blocks, "f", reciprocal=False)
    return CoefficientMatrix(basis, rng.normal(size=(channels, basis.size, basis.size)), "f",
                             isotropic=False, reciprocal=False)


@pytest.mark.parametrize("basis", [HemiZernike(4), HemiHarmonics(5)])
@pytest.mark.parametrize("isotropic", [True, False])
def test_recovers_non_reciprocal_coefficients(basis, isotropic, rng, unit_vectors):
    # independent reference: a known general matrix, evaluated by CoefficientMatrix.eval
    truth = _random_general(rng, basis, isotropic=isotropic)
    assert np.max(np.abs(truth.matrix - truth.matrix.swapaxes(-1, -2))) > 0.1
    wi, wo = unit_vectors(900, upper=True), unit_vectors(900, upper=True)
    values = truth.eval(wi, wo)
    cm = fit(wi, wo, values, basis, isotropic=isotropic, reciprocal=False)
    assert not cm.reciprocal and cm.is_isotropic == isotropic and cm.info["reciprocal"] is False
    blocks = [c.size for c in basis.azimuthal_blocks().cos]
    assert cm.info["unknowns"] == (sum(k * k for k in blocks) if isotropic else basis.size ** 2)
    assert cm.info["rank"] == cm.info["unknowns"]
    cond, scale = cm.info["condition_number"], np.max(np.abs(truth.matrix))
    # noise-free: rounding amplified by at most cond, as for the reciprocal recovery above
    np.testing.assert_allclose(cm.matrix, truth.matrix, rtol=0, atol=100 * cond * EPS * scale)
    # a reciprocal fit of the same data cannot follow them: its held-out error stays at the
    # antisymmetric part's share, far above the non-reciprocal fit's rounding
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sym = fit(wi, wo, values, basis, isotropic=isotropic)
    assert sym.reciprocal and sym.info["validation_l2"] > 0.1 > 1e3 * cm.info["validation_l2"]


def test_non_reciprocal_layout_round_trip(rng, unit_vectors):
    # to_unknowns and design_matrix agree with eval in the general layout, and the scaling
    # keeps ||z|| the Frobenius norm of the dense M (rounding only)
    zb = HemiZernike(3)
    wi, wo = unit_vectors(40, upper=True), unit_vectors(40, upper=True)
    for iso in (True, False):
        cm = _random_general(rng, zb, isotropic=iso, channels=1)
        z = to_unknowns(cm, isotropic=iso)
        assert np.linalg.norm(z) == pytest.approx(np.linalg.norm(cm.matrix), rel=1e-14)
        a = design_matrix(wi, wo, zb, isotropic=iso, reciprocal=False)
        np.testing.assert_allclose(a @ z[:, 0], cm.eval(wi, wo)[:, 0], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="cm is not reciprocal"):
        to_unknowns(_random_general(rng, zb, isotropic=False), isotropic=False, reciprocal=True)
    with pytest.raises(TypeError, match="reciprocal"):
        fit(wi, wo, np.ones(40), zb, reciprocal="no")
    # a reciprocal matrix in the general layout is the same function
    sym = _random_matrix(rng, zb, isotropic=False)
    a = design_matrix(wi, wo, zb, isotropic=False, reciprocal=False)
    np.testing.assert_allclose(a @ to_unknowns(sym, isotropic=False, reciprocal=False),
                               sym.eval(wi, wo), rtol=0, atol=1e-12)


def test_scalar_values_give_scalar_matrix(rng, unit_vectors):
    zb = HemiZernike(2)
    truth = _random_matrix(rng, zb, isotropic=True)
    wi, wo = unit_vectors(60, upper=True), unit_vectors(60, upper=True)
    cm = fit(wi, wo, truth.eval(wi, wo), zb)
    assert cm.matrix.shape == (zb.size, zb.size) and len(cm.info["residual_rms"]) == 1
    # cond ~ 1.3 here: rounding only
    np.testing.assert_allclose(cm.matrix, truth.matrix, rtol=0, atol=1e-13)


# -- weights, regularization, conditioning -----------------------------------------------------
def _noisy_problem(rng, unit_vectors, n=400, basis=None):
    basis = basis or HemiHarmonics(5)
    truth = _random_matrix(rng, basis, isotropic=True, channels=2)
    wi, wo = unit_vectors(n, upper=True), unit_vectors(n, upper=True)
    values = truth.eval(wi, wo) + 0.1 * rng.normal(size=(n, 2))
    return basis, wi, wo, values


def test_info_against_numpy_svd(rng, unit_vectors):
    basis, wi, wo, values = _noisy_problem(rng, unit_vectors)
    w = rng.uniform(0.2, 3.0, size=wi.shape[0])
    cm = fit(wi, wo, values, basis, weights=w, quantity="f_cos")
    # independent reference: numpy's SVD and lstsq of the same weighted system
    a = np.sqrt(w)[:, None] * design_matrix(wi, wo, basis)
    y = np.sqrt(w)[:, None] * values * (wi[:, 2] * wo[:, 2])[:, None]
    s = np.linalg.svd(a, compute_uv=False)
    z, *_ = np.linalg.lstsq(a, y, rcond=None)
    info = cm.info
    assert info["method"] == "lstsq" and info["regularization"] == 0.0
    assert info["rank"] == np.linalg.matrix_rank(a) == a.shape[1] == info["unknowns"]
    assert info["samples"] == 400
    # two LAPACK SVDs of the same matrix agree to a few eps relative in each singular value
    assert info["condition_number"] == pytest.approx(s[0] / s[-1], rel=1e-12)
    rms = np.sqrt(np.sum((a @ z - y) ** 2, axis=0) / np.sum(w))
    # the residual of a well-conditioned (cond ~1.3) solve is stable to rounding
    np.testing.assert_allclose(info["residual_rms"], rms, rtol=1e-10)
    np.testing.assert_allclose(to_unknowns(cm), z, rtol=0, atol=1e-12)


def test_zero_weights_equal_dropping(rng, unit_vectors):
    basis, wi, wo, values = _noisy_problem(rng, unit_vectors)
    w = rng.uniform(0.5, 2.0, size=wi.shape[0])
    w[::3] = 0.0
    keep = w > 0
    a = fit(wi, wo, values, basis, weights=w)
    b = fit(wi[keep], wo[keep], values[keep], basis, weights=w[keep])
    # the same rows reach the same SVD: identical up to rounding
    np.testing.assert_allclose(a.matrix, b.matrix, rtol=0, atol=1e-13)
    assert a.info["samples"] == b.info["samples"] == int(keep.sum())


def test_regularization_shrinks_and_matches_normal_equations(rng, unit_vectors):
    basis, wi, wo, values = _noisy_problem(rng, unit_vectors)
    lams = [0.0, 1e-4, 1e-2, 1.0, 1e2]
    norms = []
    a = design_matrix(wi, wo, basis)
    for lam in lams:
        cm = fit(wi, wo, values, basis, regularization=lam)
        assert cm.info["regularization"] == lam
        z = to_unknowns(cm)
        norms.append(np.linalg.norm(cm.matrix))
        # the unknowns' norm is the Frobenius norm of the dense M (documented penalty)
        assert np.linalg.norm(z) == pytest.approx(norms[-1], rel=1e-13)
        # independent reference: the augmented system [A; sqrt(lam) I] z = [y; 0] by lstsq
        aug = np.vstack([a, np.sqrt(lam) * np.eye(a.shape[1])])
        rhs = np.vstack([values, np.zeros((a.shape[1], values.shape[1]))])
        ref, *_ = np.linalg.lstsq(aug, rhs, rcond=None)
        # both solves are backward stable with cond(aug) < 2: rounding only
        np.testing.assert_allclose(z, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
        # a number keeps its meaning (identity penalty) and is not validated
        info = cm.info
        assert info["penalty"] == "identity" and info["regularization_method"] == "given"
        assert info["validation_error"] is None
        # references: the trace of the influence matrix A (A^T A + lam I)^-1 A^T, and numpy's
        # condition number of the augmented matrix (both well conditioned: rounding only)
        hat = a @ np.linalg.solve(a.T @ a + lam * np.eye(a.shape[1]), a.T)
        assert info["effective_parameters"] == pytest.approx(np.trace(hat), rel=1e-10)
        assert info["cond_regularized"] == pytest.approx(np.linalg.cond(aug), rel=1e-10)
        assert info["cond"] == info["condition_number"]
    # ||z(lam)|| decreases strictly with lam (sum of (s u.y / (s^2 + lam))^2 terms)
    assert all(n1 > n2 for n1, n2 in zip(norms[:-1], norms[1:], strict=True)), norms


def test_underdetermined_raises_with_numbers(unit_vectors, recwarn):
    zb = HemiZernike(8)
    wi, wo = unit_vectors(30, upper=True), unit_vectors(30, upper=True)
    with pytest.raises(ValueError, match=r"underdetermined: 30 samples .* for 55 unknowns "
                                         r"\(isotropic HemiZernike\(8\)\); lower the order"):
        fit(wi, wo, np.ones(30), zb, regularization=0)
    with pytest.raises(ValueError, match=r"30 samples .* for 1035 unknowns \(general"):
        fit(wi, wo, np.ones(30), zb, isotropic=False, regularization=0.0)
    # with regularization the minimum-norm Tikhonov solution is returned, without a warning
    cm = fit(wi, wo, np.ones(30), zb, regularization=1e-3)
    assert cm.info["rank"] == 30 and cm.info["condition_number"] == np.inf
    # the default regularises too: the plain fit is no candidate (not determined by the data)
    cm = fit(wi, wo, np.ones(30), zb)
    assert cm.info["rank"] == 30 and cm.info["regularization"] > 0
    assert cm.info["effective_parameters"] < 30
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]


def test_rank_deficient_warns(unit_vectors):
    # every incident direction at the pole: only the m = 0 functions of w_i survive
    zb = HemiZernike(4)
    wo = unit_vectors(100, upper=True)
    wi = np.tile([0.0, 0.0, 1.0], (100, 1))
    rank = np.linalg.matrix_rank(design_matrix(wi, wo, zb))
    assert rank < 14
    with pytest.warns(RuntimeWarning, match=rf"rank-deficient: rank {rank} of 14 unknowns"):
        cm = fit(wi, wo, np.ones(100), zb, regularization=0)
    assert cm.info["rank"] == rank and cm.info["condition_number"] == np.inf
    fit(wi, wo, np.ones(100), zb, regularization=1e-6)  # regularized: no warning
    cm = fit(wi, wo, np.ones(100), zb)  # the default regularises: no warning either
    assert cm.info["regularization"] > 0 and cm.info["rank"] == rank
    assert np.isfinite(cm.info["cond_regularized"])


def test_badly_conditioned_warns(monkeypatch, unit_vectors):
    zb = HemiZernike(2)
    wi, wo = unit_vectors(50, upper=True), unit_vectors(50, upper=True)
    monkeypatch.setattr(fitmod, "COND_WARN", 1.0)  # every real fit exceeds condition 1
    with pytest.warns(RuntimeWarning, match=r"badly conditioned: condition number \d"):
        fit(wi, wo, np.ones(50), zb, regularization=0)


# -- automatic regularisation: gonioreflectometer-like data -------------------------------------
#: Incidence angles (degrees) of the synthetic gonioreflectometer data: sparse in theta_i.
INCIDENCES = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0)


class _Smooth:
    """The known BRDF: Oren-Nayar (rough diffuse) plus a broad Phong lobe (n = 4), or with
    ``sharp`` a narrower one (n = 20)."""

    def __init__(self, sharp=False):
        self.parts = ((OrenNayar(0.5, 0.35), Phong(0.0, 0.4, 20)) if sharp
                      else (OrenNayar(0.6, 0.35), Phong(0.0, 0.25, 4)))

    def eval(self, wi, wo):
        return sum(np.asarray(p.eval(wi, wo)).reshape(-1) for p in self.parts)


def _hemisphere(rng, n):
    return from_angles(np.arccos(rng.uniform(0.0, 1.0, n)), rng.uniform(0.0, 2 * np.pi, n))


def _gonio(brdf, noise, per=300, seed=0):
    """300 uniform outgoing directions at each incidence (1800 samples, like the issue's data)
    with relative Gaussian noise, and 2000 held-out pairs: random outgoing directions, random
    incidences in [0, 75] degrees at least 1 degree from the measured ones."""
    rng = np.random.default_rng(seed)
    wi = np.concatenate([from_angles(np.full(per, np.radians(t)), np.zeros(per))
                         for t in INCIDENCES])
    wo = _hemisphere(rng, wi.shape[0])
    values = brdf.eval(wi, wo) * (1 + noise * rng.standard_normal(wi.shape[0]))
    test = np.random.default_rng(seed + 1)
    theta = test.uniform(0.0, 75.0, 8000)
    theta = theta[np.min(np.abs(theta[:, None] - np.array(INCIDENCES)), axis=1) > 1.0][:2000]
    ti = from_angles(np.radians(theta), test.uniform(0.0, 2 * np.pi, theta.size))
    to = _hemisphere(test, theta.size)
    return wi, wo, values, ti, to, brdf.eval(ti, to)


def _held_out(cm, ti, to, truth):
    """Relative RMS error against the known BRDF at the held-out pairs."""
    got = np.asarray(cm.eval(ti, to)).reshape(-1)
    return float(np.linalg.norm(got - truth) / np.linalg.norm(truth))


#: Orders of the sweep: 10 is the highest the six incidences support (order 12 is
#: rank-deficient, 137 of 140), 20 is twice that.
SWEEP = (4, 8, 10, 12, 16, 20)


@pytest.fixture(scope="module")
def sweep():
    """Plain and default fits of the 0.5 % noisy data at every order of SWEEP."""
    wi, wo, values, ti, to, truth = _gonio(_Smooth(), noise=0.005)
    out = {}
    for order in SWEEP:
        zb = HemiZernike(order)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            plain = fit(wi, wo, values, zb, regularization=0)
        auto = fit(wi, wo, values, zb)
        out[order] = dict(plain=plain, auto=auto, warned=[str(w.message) for w in caught],
                          plain_error=_held_out(plain, ti, to, truth),
                          auto_error=_held_out(auto, ti, to, truth))
    out["data"] = (wi, wo, values)
    return out


def test_auto_degrades_gracefully_with_order(sweep):
    """Reference: the known BRDF (Oren-Nayar + Phong n = 4) at 2000 held-out pairs.

    Measured (held-out relative RMS error, default fit): order 4: 5.8 %, 8: 0.71 %, 10:
    0.72 %, 12: 0.50 %, 16: 0.58 %, 20: 0.58 %. Orders 4 (and 6) are limited by truncation,
    which no regularisation can lift; from the best order up to twice the supported order
    the error stays within 1.16x of the best (the issue asks for 1.5x).
    """
    err = {o: sweep[o]["auto_error"] for o in SWEEP}
    best_order = min(err, key=err.get)
    best = err[best_order]
    assert best < 0.01  # measured 0.50 % at order 12: the fit resolves the BRDF
    for order in SWEEP:
        if order >= best_order:
            assert err[order] <= 1.5 * best, (order, err)
    # every order from 8 on stays within 1.5x too (measured at most 1.44x: orders 8-10,
    # kept plain); order 4 is the truncation floor (measured 12x the best)
    assert max(err[o] for o in SWEEP if o >= 8) <= 1.5 * best
    assert err[4] > 5 * best
    # well-posed orders keep the plain fit, rank-deficient ones are regularised
    for order in (4, 8):
        assert sweep[order]["auto"].info["regularization"] == 0.0
        assert sweep[order]["auto_error"] == pytest.approx(sweep[order]["plain_error"],
                                                           rel=1e-9)
    for order in (12, 16, 20):
        info = sweep[order]["auto"].info
        assert info["rank"] < info["unknowns"] and info["regularization"] > 0
        assert info["regularization_method"] == "10-fold CV on direction pairs"
        assert info["penalty"] == "degree"
        # the influence matrix keeps fewer parameters than the data determine; the
        # regularised problem is well conditioned (measured 65-89)
        assert 0 < info["effective_parameters"] < info["rank"]
        assert info["cond"] == np.inf and info["cond_regularized"] < 1e3


def test_plain_fit_blows_up_at_high_order(sweep):
    """Negative control. Reference: the known BRDF at the held-out pairs.

    Measured: the plain (minimum-norm) fit's held-out error is 1.9 % at order 12, 200 % at
    16 and 9e5 % at 20, with a rank-deficiency warning; the default fit's 0.50-0.58 %.
    """
    for order in (16, 20):
        s = sweep[order]
        assert s["plain_error"] > 1.0  # more than 100 % error
        assert s["plain_error"] > 100 * s["auto_error"]
        assert any("rank-deficient" in m for m in s["warned"])
    assert sweep[20]["plain_error"] > 1e3  # measured 9135


def test_validation_estimate_predicts_held_out_error(sweep):
    """Reference: the held-out error against the known BRDF.

    Measured ratios validation_error / held-out error: 0.99 (order 4), 1.30, 1.12, 1.54,
    1.12, 1.08 (order 20). The estimate scores noisy held-out samples, so it includes the
    0.5 % noise.
    """
    for order in SWEEP:
        ratio = sweep[order]["auto"].info["validation_error"] / sweep[order]["auto_error"]
        assert 0.5 <= ratio <= 2.0, (order, ratio)


def test_auto_weight_is_the_degree_penalised_least_squares(sweep):
    """The chosen weight solves min ||A z - y||^2 + lam sum d_u z_u^2; reference: numpy's
    lstsq of the augmented system [A; sqrt(lam) D^(1/2)] z = [y; 0], with D built here from
    the degrees (d_u = (1 + n_j (n_j + 2) + n_k (n_k + 2))^2)."""
    wi, wo, values = sweep["data"]
    cm = sweep[12]["auto"]
    zb = cm.basis
    lam = cm.info["regularization"]
    lay = fitmod.unknowns(zb)
    e = zb.degree * (zb.degree + 2.0)
    d = (1.0 + e[lay.rows] + e[lay.cols]) ** 2
    a = design_matrix(wi, wo, zb)
    aug = np.vstack([a, np.sqrt(lam) * np.diag(np.sqrt(d))])
    ref, *_ = np.linalg.lstsq(aug, np.concatenate([values, np.zeros(d.size)]), rcond=None)
    # cond(aug) is cond_regularized (measured 89): a few hundred eps relative
    np.testing.assert_allclose(to_unknowns(cm), ref, rtol=0,
                               atol=1e-11 * np.abs(ref).max())
    assert cm.info["cond_regularized"] == pytest.approx(np.linalg.cond(aug), rel=1e-8)
    hat = a @ np.linalg.solve(a.T @ a + lam * np.diag(d), a.T)
    assert cm.info["effective_parameters"] == pytest.approx(np.trace(hat), rel=1e-8)
    # the info reproduces the fit with a number and the penalty
    again = fit(wi, wo, values, zb, regularization=lam, penalty=cm.info["penalty"])
    np.testing.assert_allclose(again.matrix, cm.matrix, rtol=0, atol=1e-12)
    assert again.info["regularization_method"] == "given"


def test_well_posed_fit_is_the_plain_fit(rng, unit_vectors):
    """Reference: fit(..., regularization=0). Dense random pairs (8 per unknown), order 4,
    1 % noise, two channels: the default keeps weight 0 and returns the same matrix."""
    zb = HemiZernike(4)
    n = 8 * fitmod.unknowns(zb).count
    wi, wo = unit_vectors(n, upper=True), unit_vectors(n, upper=True)
    f = _Smooth().eval(wi, wo)
    values = np.stack([f, 2 * f], axis=1) * (1 + 0.01 * rng.standard_normal((n, 2)))
    plain = fit(wi, wo, values, zb, regularization=0)
    auto = fit(wi, wo, values, zb)
    # the same code path once weight 0 is chosen: rounding only (in fact identical)
    np.testing.assert_allclose(auto.matrix, plain.matrix, rtol=0, atol=1e-14)
    info = auto.info
    assert info["regularization"] == 0.0 and info["effective_parameters"] == 14.0
    assert info["cond_regularized"] == info["cond"] == plain.info["cond"]
    assert 0 < info["validation_error"] < 0.5


def test_validation_methods_compared():
    """Why "auto" is 10-fold CV on pairs. Reference: the known BRDF at held-out pairs.

    Without noise and with a sharp lobe (Phong n = 20), at order 16 (rank 259 of 285):
    measured held-out error 168 % for GCV (it picks lambda ~ 5e-13: a rank-deficient design
    interpolates the measured pairs, which is all GCV scores), 1.8 % for "auto" and for
    leave-incidence-out, whose estimate (22.6 %) is 12x too pessimistic: holding out an
    incidence asks for a gap twice as wide, or an extrapolation to 75 degrees.
    """
    wi, wo, values, ti, to, truth = _gonio(_Smooth(sharp=True), noise=0.0)
    zb = HemiZernike(16)
    fits = {m: fit(wi, wo, values, zb, regularization=m) for m in REGULARIZATION_METHODS}
    err = {m: _held_out(cm, ti, to, truth) for m, cm in fits.items()}
    assert err["auto"] < 0.03 and err["leave-incidence-out"] < 0.03
    assert err["gcv"] > 10 * err["auto"]
    assert fits["gcv"].info["regularization_method"] == "GCV"
    loio = fits["leave-incidence-out"].info
    assert loio["regularization_method"] == "leave-one-incidence-out CV (6 incidences)"
    assert loio["validation_error"] > 4 * err["leave-incidence-out"]
    ratio = fits["auto"].info["validation_error"] / err["auto"]
    assert 0.5 <= ratio <= 2.0  # measured 0.72


def test_folds_keep_repeats_and_reciprocal_pairs_together(unit_vectors):
    wi, wo = unit_vectors(40, upper=True), unit_vectors(40, upper=True)
    # repeats of pair 0 and the reciprocal of pair 1: each lands in the fold of its twin
    wi2 = np.concatenate([wi, wi[:1], wo[1:2]])
    wo2 = np.concatenate([wo, wo[:1], wi[1:2]])
    for iso in (True, False):
        folds, text = fitmod._folds(wi2, wo2, iso, "auto")
        assert text == "10-fold CV on direction pairs"
        assert folds[40] == folds[0] and folds[41] == folds[1]
        assert sorted(set(folds.tolist())) == list(range(10))
    # isotropic: a rotation about the normal is the same pair
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    folds, _ = fitmod._folds(np.concatenate([wi, wi[:1] @ turn.T]),
                             np.concatenate([wo, wo[:1] @ turn.T]), True, "auto")
    assert folds[40] == folds[0]
    # fewer than 3 incidences: leave-incidence-out falls back to folds on pairs
    two = np.where(np.arange(40)[:, None] < 20, [[0.0, 0.0, 1.0]], [[0.6, 0.0, 0.8]])
    assert fitmod._folds(two, wo, True, "leave-incidence-out")[1].endswith("direction pairs")
    # one distinct pair: nothing to hold out, GCV instead
    one = np.tile([[0.0, 0.0, 1.0]], (5, 1))
    assert fitmod._folds(one, one, True, "auto")[1].startswith("GCV")


# -- the seed's brick scenario -----------------------------------------------------------------
def test_brick_scenario_order_8():
    """Koenderink et al. fit brick at order 8 (isotropic) from the 40 x 40 face data.

    Unknowns: 55 (the seed's "55 independent functions", = HelmholtzModes(8).size); the
    seed's 66 counts data values, not unknowns (we find 96 distinct isotropic face-pair
    classes on this tessellation; see tessellate_hemisphere). Measured here: condition number
    82.2 of the face-centre design, relative residual 6e-5 for the brick-like BRDF.
    """
    t, wi, wo = _face_centre_pairs()
    zb = HemiZernike(8)
    values = brick_like(wi, wo)
    cm = fit(wi, wo, values, zb)
    info = cm.info
    assert info["unknowns"] == 55 == HelmholtzModes(8).size and info["samples"] == 1600
    assert info["rank"] == 55
    s = np.linalg.svd(design_matrix(wi, wo, zb), compute_uv=False)
    assert info["condition_number"] == pytest.approx(s[0] / s[-1], rel=1e-12)
    # observed 82.2: well posed, so noise of the measurement is amplified at most ~100x
    assert 10 < info["condition_number"] < 200
    # a smooth BRDF is nearly order 8: observed rms 8.5e-6 against mean f 0.15
    assert info["residual_rms"][0] < 1e-4 * np.mean(values)
    # an exactly representable isotropic order-8 matrix is recovered from the same samples:
    # error <= cond * eps * scale, with 100x for the sums (observed 2e-13 for scale ~ 6)
    truth = _random_matrix(np.random.default_rng(8), zb, isotropic=True)
    back = fit(wi, wo, truth.eval(wi, wo), zb)
    scale = np.max(np.abs(truth.matrix))
    np.testing.assert_allclose(back.matrix, truth.matrix, rtol=0,
                               atol=100 * info["condition_number"] * EPS * scale)


def test_brick_sampling_limits():
    # what the 40-face sampling can resolve. Reciprocity: the design is symmetric in
    # w_i <-> w_o, so the 1600 face pairs hold only 40 * 41 / 2 = 820 distinct rows (the
    # seed's count), fewer than the 1035 unknowns of a general order-8 fit
    t, wi, wo = _face_centre_pairs()
    zb = HemiZernike(8)
    np.testing.assert_array_equal(design_matrix(wi, wo, zb, isotropic=False),
                                  design_matrix(wo, wi, zb, isotropic=False))
    i, o = np.triu_indices(t.size)
    with pytest.raises(ValueError, match=r"820 samples .* for 1035 unknowns \(general"):
        fit(t.centroids[i], t.centroids[o], np.ones(i.size), zb, isotropic=False,
            regularization=0)
    # isotropy: isotropic order 12 (140 unknowns) is capped by the 96 distinct isotropic
    # face-pair classes (equal theta_i, theta_o, |phi_i - phi_o| up to exchange)
    with pytest.warns(RuntimeWarning, match="rank-deficient: rank 96 of 140 unknowns"):
        fit(wi, wo, brick_like(wi, wo), HemiZernike(12), regularization=0)


def test_fit_from_binned_samples(rng):
    # scattered samples binned onto the faces, fitted at the centroids with the counts as
    # weights, equal the fit of every sample moved to its face centroid
    t = tessellate_hemisphere()
    n = 5000
    wi = from_angles(np.arccos(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n))
    wo = from_angles(np.arccos(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n))
    values = np.stack([brick_like(wi, wo), 2 * brick_like(wi, wo)], axis=-1)
    binned = bin_samples(wi, wo, values, t)
    bi, bo, bv, bw = binned.samples()
    # for a given weight (here 0); the automatic choice may differ, since only the unbinned
    # samples show the validation the scatter inside a bin
    cm = fit(bi, bo, bv, HemiZernike(8), weights=bw, regularization=0)
    moved = fit(t.centroids[t.locate(wi)], t.centroids[t.locate(wo)], values, HemiZernike(8),
                regularization=0)
    # same normal equations summed in a different order; cond ~ 1e2: rounding only
    np.testing.assert_allclose(cm.matrix, moved.matrix, rtol=0, atol=1e-11)
    assert cm.info["samples"] == int(np.count_nonzero(binned.counts))


# -- tessellation -------------------------------------------------------------------------------
def _girard_areas(t):
    """Spherical excess from the corner angles (independent of Van Oosterom-Strackee)."""
    v = t.vertices[t.faces]
    angles = []
    for k in range(3):
        p, q, r = v[:, k], v[:, (k + 1) % 3], v[:, (k + 2) % 3]
        tq = q - p * np.sum(p * q, axis=1, keepdims=True)
        tr = r - p * np.sum(p * r, axis=1, keepdims=True)
        cosang = np.sum(tq * tr, axis=1) / np.linalg.norm(tq, axis=1) / np.linalg.norm(tr, axis=1)
        angles.append(np.arccos(cosang))
    return sum(angles) - np.pi


def test_tessellation_has_40_faces_of_near_equal_area():
    t = tessellate_hemisphere()
    assert t.size == 40 and t.faces.shape == (40, 3) and t.centroids.shape == (40, 3)
    # 40 arctan2 terms of O(0.15) each: a few eps of 2 pi
    assert t.solid_angles.sum() == pytest.approx(2 * np.pi, abs=1e-13)
    # Girard's excess loses digits in arccos near 60 degrees: 1e-12 is its rounding level
    np.testing.assert_allclose(t.solid_angles, _girard_areas(t), rtol=0, atol=1e-12)
    # 30 corner faces and 10 central faces; the spread documented in the docstring
    assert np.unique(np.round(t.solid_angles, 10)).size == 2
    assert t.solid_angles.max() / t.solid_angles.min() == pytest.approx(1.20313, abs=1e-5)
    assert np.all(t.centroids[:, 2] > 0)
    np.testing.assert_allclose(np.linalg.norm(t.centroids, axis=1), 1.0, rtol=0, atol=1e-15)
    # every face counter-clockwise from outside, and no face below the equator
    v = t.vertices[t.faces]
    assert np.all(np.einsum("fj,fj->f", np.cross(v[:, 0], v[:, 1]), v[:, 2]) > 0)
    assert np.all(t.vertices[:, 2] >= 0)
    # the equator: 10 vertices (midpoints of the icosahedron's ring-to-ring edges), 10 edges
    on = t.vertices[t.faces][..., 2] == 0
    assert np.sum(t.vertices[:, 2] == 0) == 10 and np.sum(on.sum(axis=1) == 2) == 10
    np.testing.assert_array_equal(t.locate(t.centroids), np.arange(40))


def test_tessellation_covers_the_hemisphere(rng):
    # uniform directions fall in each face in proportion to its solid angle
    t = tessellate_hemisphere()
    n = 100_000
    d = from_angles(np.arccos(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n))
    face = t.locate(d)
    frac = np.bincount(face, minlength=40) / n
    p = t.solid_angles / (2 * np.pi)
    # binomial: 5 sigma per face (40 faces: false-alarm rate ~ 2e-5 for a fresh seed)
    np.testing.assert_array_less(np.abs(frac - p), 5 * np.sqrt(p * (1 - p) / n))
    # each direction lies inside its face's three edge planes (rounding only)
    v = t.vertices[t.faces[face]]
    for k in range(3):
        side = np.einsum("nj,nj->n", np.cross(v[:, k], v[:, (k + 1) % 3]), d)
        assert side.min() > -1e-15


def test_tessellation_refinement_and_errors():
    for k, faces in ((2, 160), (3, 640)):
        t = tessellate_hemisphere(k)
        assert t.size == faces
        assert t.solid_angles.sum() == pytest.approx(2 * np.pi, abs=1e-12)  # rounding
    with pytest.raises(ValueError, match="subdivisions must be >= 1"):
        tessellate_hemisphere(0)
    with pytest.raises(TypeError, match="subdivisions must be an integer"):
        tessellate_hemisphere(1.0)


# -- binning ------------------------------------------------------------------------------------
def test_bin_samples_against_loop(rng, unit_vectors):
    t = tessellate_hemisphere()
    n = 3000
    wi, wo = unit_vectors(n, upper=True), unit_vectors(n, upper=True)
    values = rng.uniform(0, 1, size=(n, 3))
    b = bin_samples(wi, wo, values)
    fi, fo = t.locate(wi), t.locate(wo)
    sums, counts = np.zeros((40, 40, 3)), np.zeros((40, 40), dtype=int)
    for k in range(n):  # the obvious reference
        sums[fi[k], fo[k]] += values[k]
        counts[fi[k], fo[k]] += 1
    np.testing.assert_array_equal(b.counts, counts)
    full = counts > 0
    np.testing.assert_allclose(b.mean[full], sums[full] / counts[full][:, None], rtol=1e-14)
    assert np.all(np.isnan(b.mean[~full]))
    assert b.counts.sum() == n
    with pytest.raises(TypeError, match="tessellation must be a Tessellation"):
        bin_samples(wi, wo, values[:, 0], tessellation="icosahedron")


# -- input errors -------------------------------------------------------------------------------
def test_fit_input_errors(unit_vectors, monkeypatch):
    zb = HemiZernike(2)
    wi, wo = unit_vectors(20, upper=True), unit_vectors(20, upper=True)
    v = np.ones(20)
    bad_v = v.copy()
    bad_v[3] = np.nan
    below = wo.copy()
    below[5, 2] = -below[5, 2] - 0.1
    below[5] /= np.linalg.norm(below[5])
    cases = [
        (ValueError, r"values must be finite: 1 entries are NaN or inf \(first at sample 3\)",
         dict(values=bad_v)),
        (ValueError, r"values must have shape \(20,\) or \(20, channels\)",
         dict(values=np.ones(19))),
        (ValueError, r"wo must have the shape of wi \(20, 3\), got shape \(19, 3\)",
         dict(wo=wo[:19])),
        (ValueError, r"wo must lie in the upper hemisphere", dict(wo=below)),
        (ValueError, r"weights must be >= 0, got min -1", dict(weights=-np.ones(20))),
        (ValueError, r"weights must have shape \(20,\)", dict(weights=np.ones(3))),
        (ValueError, r"weights must not all be zero", dict(weights=np.zeros(20))),
        (ValueError, r"weights must be finite", dict(weights=np.full(20, np.inf))),
        (ValueError, r"regularization must be finite and >= 0, got -1.0",
         dict(regularization=-1.0)),
        (ValueError, r"regularization must be finite and >= 0, got inf",
         dict(regularization=np.inf)),
        (ValueError, r"regularization must be finite and >= 0, got nan",
         dict(regularization=float("nan"))),
        (ValueError, r"regularization must be one of 'auto', 'gcv', 'leave-incidence-out' or "
                     r"a number >= 0, got 'a lot'", dict(regularization="a lot")),
        (ValueError, r"regularization must be one of .* got 'Auto'", dict(regularization="Auto")),
        (TypeError, r"regularization must be a number or one of 'auto'",
         dict(regularization=True)),
        (TypeError, r"regularization must be a number or one of 'auto'",
         dict(regularization=[0.1])),
        (ValueError, r"penalty must be one of 'identity', 'degree', got 'smooth'",
         dict(penalty="smooth")),
        (ValueError, r"quantity must be one of 'f', 'f_cos'", dict(quantity="g")),
        (TypeError, r"isotropic must be True or False", dict(isotropic="yes")),
        (ValueError, r"basis must be a hemisphere basis .* SphericalHarmonics\(2\)",
         dict(basis=SphericalHarmonics(2))),
        (TypeError, r"basis must be a basis object", dict(basis="zernike")),
        (ValueError, r"wi must have shape \(n, 3\), got shape \(3,\)",
         dict(wi=[0, 0, 1.0], wo=[0, 0, 1.0])),
    ]
    for exc, match, kw in cases:
        args = dict(wi=wi, wo=wo, values=v, basis=zb) | kw
        with pytest.raises(exc, match=match):
            fit(args.pop("wi"), args.pop("wo"), args.pop("values"), args.pop("basis"), **args)
    monkeypatch.setattr("basis.validation.MAX_BYTES", 1000)
    with pytest.raises(MemoryError, match=r"fitting 5 unknowns to 20 samples"):
        fit(wi, wo, v, zb)


def test_fit_memory_check_counts_the_square_matrices(monkeypatch):
    # few samples, many unknowns, degree penalty: the (unknowns, unknowns) matrices of the
    # regularised condition number dominate the design; before, only the design was counted
    rng = np.random.default_rng(3)
    w = rng.normal(size=(400, 3))
    w[:, 2] = np.abs(w[:, 2])
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    with pytest.raises(MemoryError, match=r"fitting 45526 unknowns to 200 samples .* would "
                                          r"need 47 GiB"):
        fit(w[:200], w[200:], np.full(200, 0.1), HemiZernike(100), regularization="auto")
    # the same at a small order, with the limit between the design alone and the whole
    zb = HemiZernike(8)
    u = fitmod.unknowns(zb).count
    design = 8.0 * fitmod._AUTO_COPIES * 20 * u
    monkeypatch.setattr("basis.validation.MAX_BYTES", design * 1.5)
    assert fitmod._fit_bytes(20, u, zb.size, "auto", "degree") > design * 1.5
    with pytest.raises(MemoryError, match=rf"fitting {u} unknowns to 20 samples"):
        fit(w[:20], w[200:220], np.full(20, 0.1), zb, regularization="auto")


# -- tables -------------------------------------------------------------------------------------
def test_read_table_round_trip(tmp_path, rng):
    n = 12
    ang = np.column_stack([rng.uniform(0, 90, n), rng.uniform(-180, 360, n),
                           rng.uniform(0, 90, n), rng.uniform(0, 360, n)])
    ang[0, 0], ang[1, 2] = 90.0, 0.0  # the horizon and the pole are in range
    rgb = rng.uniform(0, 2, size=(n, 3))
    lines = ["# theta_i phi_i theta_o phi_o r g b (degrees, 1/sr)", ""]
    for k in range(n):
        cells = [repr(float(x)) for x in (*ang[k], *rgb[k])]
        lines.append(", ".join(cells) if k % 2 else "  ".join(cells) + "  # a remark")
    path = tmp_path / "rgb.txt"
    path.write_text("\n".join(lines) + "\n")
    wi, wo, values = read_table(path)
    rad = np.radians(ang)
    # repr() round-trips floats exactly; the degree conversion is the only rounding
    np.testing.assert_allclose(wi, from_angles(rad[:, 0], rad[:, 1]), rtol=0, atol=1e-15)
    np.testing.assert_allclose(wo, from_angles(rad[:, 2], rad[:, 3]), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(values, rgb)
    one = tmp_path / "one.csv"
    one.write_text("0,0,45,180,0.25\n30,10,60,20,0.5\n")
    wi, wo, values = read_table(one)
    assert values.shape == (2,) and values.tolist() == [0.25, 0.5]
    np.testing.assert_allclose(wo[0], [-np.sqrt(0.5), 0.0, np.sqrt(0.5)], rtol=0, atol=1e-15)


@pytest.mark.parametrize("text, match", [
    ("0 0 0 0 1 2\n", r"line 1: a row must have 5 columns .* or 7 .* got 6"),
    ("0 0 0 0 1\n0 0 0 0 1 2 3\n", r"line 2: every row must have 5 columns like the first, got 7"),
    ("theta_i phi_i theta_o phi_o f\n", r"line 1, column 1: cell must be a number, got "
                                         r"'theta_i' \(comment out header lines"),
    ("# header\n0,0,0,,1\n", r"line 2, column 4: cell must be a number, got ''"),
    ("0 0 0 0 nan\n", r"line 1, column 5: cell must be finite, got 'nan'"),
    ("95 0 0 0 1\n", r"line 1: theta_i must lie in \[0, 90\] degrees, got 95"),
    ("0 0 -1 0 1\n", r"line 1: theta_o must lie in \[0, 90\] degrees, got -1"),
    ("# nothing\n\n", r"must hold at least one data row"),
])
def test_read_table_errors(tmp_path, text, match):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        read_table(path)


# -- fit(measurements, basis) ---------------------------------------------------------------------

def gonio_pairs():
    """A gonioreflectometer layout: 8 incidences theta_i = 10..80 deg at phi_i = 0, and theta_o
    in {5, 10, 20, ..., 70, 75, 80} deg (the specular theta_o of every incidence among them)
    with phi_o = 0, 20, ..., 340 deg: 8 x 10 x 18 = 1440 pairs."""
    ti = np.radians(np.arange(10.0, 81.0, 10.0))
    to = np.radians(np.r_[5.0, np.arange(10.0, 71.0, 10.0), 75.0, 80.0])
    po = np.radians(np.arange(0.0, 360.0, 20.0))
    t, o, p = np.meshgrid(ti, to, po, indexing="ij")
    return from_angles(t.ravel(), 0.0), from_angles(o.ravel(), p.ravel())


def lambert_ggx(wi, wo, kd, ks, alpha):
    from project import FittedModel

    return FittedModel("lambert+ggx", {"kd": kd, "ks": ks, "alpha": alpha, "f0": 0.04}
                       ).eval(wi, wo)


def test_fit_measurements_equals_arrays(rng):
    """fit(measurements, basis) is fit(wi, wo, values, basis, weights=...) on the same
    arrays: identical coefficients and info."""
    from project import Measurements

    wi, wo = gonio_pairs()
    wi, wo = wi[::3], wo[::3]
    f = lambert_ggx(wi, wo, [0.5, 0.3], [0.4, 0.4], 0.3)
    w = rng.uniform(0.5, 2.0, len(wi))
    w[::7] = 0.0
    m = Measurements(wi, wo, f, weights=w)
    for kwargs in ({}, {"regularization": 1e-3, "quantity": "f_cos"}):
        a = fit(m, HemiZernike(4), **kwargs)
        b = fit(m.wi, m.wo, m.values, HemiZernike(4), weights=m.weights, **kwargs)
        c = fit(m, basis=HemiZernike(4), **kwargs)
        np.testing.assert_array_equal(a.blocks[0], b.blocks[0])
        np.testing.assert_array_equal(a.matrix, b.matrix)
        np.testing.assert_array_equal(c.matrix, b.matrix)
        assert a.info == b.info


@pytest.mark.parametrize("call, match", [
    (lambda m: fit(m, HemiZernike(4), np.ones(len(m))), r"fit\(measurements, basis, \.\.\.\) "
     r"takes the values from the measurements: pass no values"),
    (lambda m: fit(m, HemiZernike(4), None, HemiZernike(4)), r"takes the values from the "
     r"measurements"),
    (lambda m: fit(m, HemiZernike(4), weights=np.ones(len(m))), r"fit\(measurements, \.\.\.\) "
     r"takes the weights from the measurements; build them with Measurements\(\.\.\., "
     r"weights=\.\.\.\)"),
    (lambda m: fit(m), r"basis must be a basis object \(e\.g\. basis\.HemiZernike\(8\)\), got "
     r"NoneType"),
    (lambda m: fit(m.wi, m.wo), r"fit needs \(wi, wo, values, basis\) or \(measurements, "
     r"basis\)"),
    (lambda m: fit(m.wi, m.wo, m.values), r"fit needs \(wi, wo, values, basis\)"),
])
def test_fit_measurements_type_errors(call, match):
    from project import Measurements

    wi, wo = gonio_pairs()
    m = Measurements(wi[::20], wo[::20], np.ones(72))
    with pytest.raises(TypeError, match=match):
        call(m)


def test_fit_warns_on_a_narrow_lobe_between_few_incidences():
    """A sharp GGX lobe (alpha 0.05) measured at 8 incidences with the specular direction of
    each: an order-8 expansion cannot follow it between the measured directions, and its
    cross-validated error is >= 1 (measured in f 1.023, in q, the metric of the warning,
    1.29; a Lambertian fit scores 0.9995 in f): warned, with what to fit instead."""
    from project import Measurements

    wi, wo = gonio_pairs()
    m = Measurements(wi, wo, lambert_ggx(wi, wo, [0.3], [0.8], 0.05))
    with pytest.warns(RuntimeWarning, match=r"fit predicts held-out samples no better than "
                                            r"zero: cross-validated error 1\.29 \(l2 of q; "
                                            r"isotropic HemiZernike\(8\), 1440 samples, "
                                            r"10-fold CV on "
                                            r"direction pairs\)\. An expansion cannot follow "
                                            r"these data .*project\.fit_model\(measurements, "
                                            r"'lambert\+ggx'\)"):
        cm = fit(m, HemiZernike(8))
    assert cm.info["validation_error"] >= 1.0 and cm.info["validation_l2"] >= 1.0
    assert cm.info["lambert_validation_error"] < 1.0


def test_fit_does_not_warn_on_a_smooth_brdf():
    """Lambert + a broad lobe (alpha 0.3) on the same layout: the expansion predicts held-out
    samples better than a Lambertian fit (measured 0.31 against 0.65 at order 8), no warning
    (the test configuration turns warnings into errors)."""
    from project import Measurements

    wi, wo = gonio_pairs()
    m = Measurements(wi, wo, lambert_ggx(wi, wo, [0.5], [0.8], 0.3))
    cm = fit(m, HemiZernike(8))
    v, lam = cm.info["validation_error"], cm.info["lambert_validation_error"]
    assert v < lam < 1.0
    assert cm.info["validation_l2"] < cm.info["lambert_validation_l2"]


def test_lambert_validation_error_by_hand(rng):
    """info["lambert_validation_error"]: each fold's constant is the weighted least-squares
    c = sum w x y / sum w x^2 (x = 1, or cos cos for f_cos) on the other folds, scored like
    the validation error. Recomputed on the folds of fit's split to 1e-12."""
    from project import Measurements

    wi, wo = gonio_pairs()
    wi, wo = wi[::4], wo[::4]
    f = lambert_ggx(wi, wo, [0.5, 0.2], [0.6, 0.6], 0.25)
    w = rng.uniform(0.5, 2.0, len(wi))
    m = Measurements(wi, wo, f, weights=w)
    folds = fitmod._folds(m.wi, m.wo, True, "auto")[0]
    for quantity in ("f", "f_cos"):
        x = np.ones(len(m)) if quantity == "f" else m.wi[:, 2] * m.wo[:, 2]
        y = f * x[:, None]
        sse = 0.0
        for k in range(folds.max() + 1):
            t = folds == k
            c = np.sum((w * x)[~t, None] * y[~t], axis=0) / np.sum(w[~t] * x[~t] ** 2)
            sse += np.sum(w[t, None] * (np.outer(x[t], c) - y[t]) ** 2)
        want = np.sqrt(sse / np.sum(w[:, None] * y * y))
        cm = fit(m, HemiZernike(4), quantity=quantity)
        assert cm.info["lambert_validation_error"] == pytest.approx(want, rel=1e-12)
    assert fit(m, HemiZernike(4), regularization=0.0).info["lambert_validation_error"] is None
