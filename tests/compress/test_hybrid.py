"""compress.hybrid: lobe + residual expansion. References: a BRDF that is its own lobe (the
residual vanishes), and a lobe plus a Lambertian (the residual is one coefficient)."""

from __future__ import annotations

import numpy as np
import pytest

import basis
from compress import Hybrid, hybrid
from compress.truncate import unique_coefficients
from project.models import CookTorrance, Lambert, Phong
from tests.conftest import random_directions


class _Sum:
    """Two BRDFs added: the reference for a lobe + Lambert decomposition."""

    isotropic = True
    reciprocal = True

    def __init__(self, a, b):
        self.a, self.b, self.channels = a, b, 1

    def eval(self, wi, wo):
        return self.a.eval(wi, wo) + self.b.eval(wi, wo)


def test_lobe_only_brdf_has_zero_residual(rng):
    lobe = CookTorrance(0.0, 0.2, distribution="ggx", ior=1.5)
    h = hybrid(lobe, 4, lobe=lobe)
    assert np.max(np.abs(h.residual.matrix)) == 0.0  # exact zeros: f - lobe is 0 everywhere
    wi, wo = random_directions(rng, 200, upper=True), random_directions(rng, 200, upper=True)
    np.testing.assert_array_equal(h.eval(wi, wo), lobe.eval(wi, wo))
    # stored bytes: the residual's unique coefficients (symmetric blocks once), not its memory
    assert h.nbytes == 8 * unique_coefficients(h.residual) < h.residual.nbytes
    assert h.info["lobe_bytes"] == 0
    assert h.info["l2"] == 0.0 and h.info["l2_stderr"] == 0.0


def test_lambert_residual_is_one_coefficient(rng):
    # f = lobe + a / pi; the residual a / pi = 2a K_0^0 K_0^0 in Zernike as quantity "f"
    lobe = Phong(0.0, 0.5, 30.0)
    h = hybrid(_Sum(lobe, Lambert(0.3)), 6, lobe=lobe, tol=1e-10, quantity="f")
    m = h.residual.matrix
    assert h.residual.quantity == "f"
    assert m[0, 0] == pytest.approx(0.6, rel=1e-12)
    assert np.max(np.abs(m - np.diag([0.6] + [0.0] * (m.shape[0] - 1)))) < 1e-12
    wi, wo = random_directions(rng, 300, upper=True), random_directions(rng, 300, upper=True)
    np.testing.assert_allclose(h.eval(wi, wo), lobe.eval(wi, wo) + 0.3 / np.pi, rtol=1e-11)
    assert h.info["l2"] < 1e-11  # peak-resolving estimate of an exact representation


@pytest.mark.filterwarnings("ignore:the expansion of")
def test_residual_never_worsens_the_lobe():
    """The default f_cos residual is the L2(q) projection of q - q_lobe: at every order the
    hybrid's l2 error is at most the lobe's (on the same pairs, up to quadrature error),
    and it falls with the order when the lobe misses a broad part (here the Lambert term
    of the BRDF, which the lobe lacks)."""
    from project.sampling import brdf_errors, peak_resolving_pairs

    lobe = CookTorrance(0.0, 0.3, distribution="ggx", ior=1.5)
    brdf = _Sum(CookTorrance(0.0, 0.25, distribution="ggx", ior=1.5), Lambert(0.3))
    pairs = peak_resolving_pairs(1 << 14, seed=5)
    alone = brdf_errors(brdf, lobe, pairs)["l2"]
    errs = [brdf_errors(brdf, hybrid(brdf, n, lobe=lobe, error_samples=0), pairs)["l2"]
            for n in (0, 2, 6)]
    assert errs[0] < alone and errs[2] < errs[1] < errs[0]


@pytest.mark.filterwarnings("ignore:the expansion of")  # the residual is a sharp difference
def test_errors_resolve_the_peak():
    # a sharp lobe as the BRDF, a wider one as the lobe: the residual at order 4 cannot
    # hold the difference, and the peak-resolving estimate says so with a standard error
    brdf = CookTorrance(0.1, 0.05, distribution="ggx", ior=1.5)
    h = hybrid(brdf, 4, lobe=CookTorrance(0.1, 0.08, distribution="ggx", ior=1.5),
               error_samples=1 << 14)
    assert 0.05 < h.info["l2"] < 1.0
    assert 0 < h.info["l2_stderr"] < 0.2 * h.info["l2"]


def test_channels_broadcast_between_parts():
    zb = basis.HemiZernike(2)
    m = np.zeros((3, zb.size, zb.size))
    m[:, 0, 0] = [0.2, 0.4, 0.6]
    h = Hybrid(Lambert(0.5), basis.CoefficientMatrix(zb, m, quantity="f"))
    v = h.eval([0, 0, 1.0], [0.6, 0, 0.8])
    np.testing.assert_allclose(v, (0.5 + np.array([0.1, 0.2, 0.3])) / np.pi, rtol=1e-14)
    assert h.channels == 3 and h.isotropic and "Hybrid(Lambert" in repr(h)


def test_errors():
    zb = basis.HemiZernike(2)
    cm = basis.CoefficientMatrix(zb, np.zeros((zb.size, zb.size)), quantity="f")
    with pytest.raises(TypeError, match="lobe must be a BRDF"):
        Hybrid(object(), cm)
    with pytest.raises(TypeError, match="residual must be a basis.CoefficientMatrix"):
        Hybrid(Lambert(0.5), np.eye(2))
    with pytest.raises(ValueError, match="channels must match"):
        Hybrid(Lambert([0.1, 0.2]), basis.CoefficientMatrix(zb, np.zeros((3, 6, 6)), "f"))
    with pytest.raises(ValueError, match="lobe_options apply only"):
        hybrid(Lambert(0.5), 2, lobe=Lambert(0.1), lobe_options={"restarts": 2})
    with pytest.raises(ValueError, match="kind must be one of"):
        hybrid(Lambert(0.5), 2, lobe=Lambert(0.1), kind="wavelets")


def test_measurements_hybrid_is_cross_validated():
    """A GGX lobe over a Lambertian term whose albedo rises towards grazing (which the
    lobe's family cannot hold): on noise-free samples the residual's expansion captures the
    rest, so the hybrid predicts held-out samples better than the lobe alone."""
    from basis import from_angles
    from project import Measurements, fit_model

    class _Grazing:
        isotropic, reciprocal, channels = True, True, 1

        def eval(self, wi, wo):
            return 0.1 * (2.0 - wi[..., 2] - wo[..., 2])

    truth = _Sum(CookTorrance(0.0, 0.3, distribution="ggx", ior=1.5), _Grazing())
    ti, to, po = np.meshgrid(np.radians(np.arange(5, 81, 5)), np.radians(np.arange(0, 81, 8)),
                             np.radians(np.arange(-165, 181, 15)), indexing="ij")
    wi, wo = from_angles(ti.ravel(), 0.0), from_angles(to.ravel(), po.ravel())
    meas = Measurements(wi, wo, truth.eval(wi, wo), isotropic=True)
    lobe = fit_model(meas, "lambert+ggx", restarts=1, folds=5)
    h = hybrid(meas, 4, lobe="lambert+ggx", lobe_options={"restarts": 1}, folds=5)
    assert isinstance(h, Hybrid) and h.info["folds"] == 5
    assert "5-fold CV on held-out samples" in h.info["validation"]
    assert h.info["l2"] < 0.5 * lobe.info["l2"]
    # the default lobe for samples is the microfacet one (factored needs a BRDF)
    assert hybrid(meas, 2, folds=0).lobe.family == "lambert+ggx"
    with pytest.raises(ValueError, match="folds must be 0"):
        hybrid(meas, 2, folds=1)
