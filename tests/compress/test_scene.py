"""for_scene: radiance against closed forms and direct evaluation; the band-limit fact."""

from __future__ import annotations

import numpy as np
import pytest

import basis
from compress import Environment, for_scene, truncate
from project import project
from project.models import BlinnPhong, Lambert, Phong
from tests.conftest import random_directions

VIEWS = basis.from_angles(np.radians(np.linspace(0.0, 75.0, 16)),
                          np.radians(np.linspace(0.0, 300.0, 16)))


@pytest.fixture(scope="module")
def glossy():
    return project(BlinnPhong(0.3, 0.5, 20.0), basis.HemiZernike(10), quantity="f_cos")


def test_lambert_under_uniform_sky_closed_form():
    # L_o = (a / pi) int_H 1 cos dw = a for a constant sky of radiance 1
    cm = project(Lambert(0.4), basis.HemiHarmonics(5))
    plan = for_scene(cm, lights=Environment.sh(np.array([np.sqrt(4 * np.pi)])),  # L = 1
                     views=VIEWS, tol=1e-6, time_eval=False)
    # sky projected by a product rule exact to rounding for these polynomial integrands
    np.testing.assert_allclose(plan.radiance_full, 0.4, rtol=1e-12)
    assert plan.order == 1 and plan.rank == 1 and plan.error < 1e-12


def test_uniform_sky_has_zernike_bandwidth_zero(glossy):
    sky = Environment.sh(np.array([1.0]))
    plan = for_scene(glossy, lights=sky, views=VIEWS, tol=1e-3, time_eval=False)
    # the constant is K_0^0: the incident side needs nothing above order 0 (rounding only)
    assert plan.light_bandwidth == 0
    assert max(plan.incident_errors) < 1e-13
    # the symmetric truncation also cuts outgoing detail, which the views do see
    assert plan.order_errors[0] > 0.1 and plan.order_errors[-1] == 0.0
    assert plan.error <= 1e-3 and plan.order < glossy.order
    assert plan.bytes < plan.bytes_full and plan.bytes_saved == plan.bytes_full - plan.bytes


@pytest.mark.filterwarnings("ignore:the expansion of BlinnPhong")  # order 6 misses 16 %
def test_uniform_sky_has_zernike_bandwidth_two_for_f():
    # as quantity "f" the light enters with its cos: z = 1 - rho^2 holds R_2^0, so degree 2
    cm = project(BlinnPhong(0.3, 0.5, 20.0), basis.HemiZernike(6), quantity="f")
    plan = for_scene(cm, lights=Environment.sh(np.array([1.0])), views=VIEWS, tol=1e-3,
                     time_eval=False)
    assert plan.light_bandwidth == 2
    assert max(plan.incident_errors[2:]) < 1e-13 < plan.incident_errors[1]


@pytest.mark.parametrize("lmax", [2, 5])
def test_band_limit_fact_odd_harmonics(lmax, rng):
    # An SH light with only l + |m| odd terms is, on the upper hemisphere, a combination of
    # the odd hemisphere harmonics of degree <= lmax (int_H sqrt2 Y_j Y_lm = delta / sqrt2),
    # so incident-side truncation at lmax and above is exact.
    cm = project(Phong(0.2, 0.6, 10.0), basis.HemiHarmonics(9))
    sh = basis.SphericalHarmonics(lmax)
    coeffs = rng.normal(size=sh.size) * ((sh.degree + np.abs(sh.azimuthal)) % 2 == 1)
    coeffs[sh.index(1, 0)] += 3.0
    plan = for_scene(cm, lights=Environment.sh(coeffs), views=VIEWS, tol=1e-4,
                     time_eval=False)
    assert plan.light_bandwidth == lmax
    assert max(plan.incident_errors[lmax:]) < 1e-13  # rounding of the light projection
    assert plan.incident_errors[lmax - 1] > 1e-6


def test_directional_radiance_matches_direct_evaluation(glossy, rng):
    lights = random_directions(rng, 5, upper=True)
    power = rng.uniform(0.5, 2.0, 5)
    plan = for_scene(glossy, lights=lights, light_weights=power, views=VIEWS, tol=1e-2,
                     time_eval=False)

    def direct(cm):  # L_o(v) = sum_k w_k f(d_k, v) cos(theta_k), by CoefficientMatrix.eval
        f = cm.eval(lights[:, None, :], VIEWS[None, :, :])  # (5, views)
        return np.einsum("k,kv->v", power * lights[:, 2], f)

    # same bilinear form, different summation order: rounding ~1e-15 relative
    np.testing.assert_allclose(plan.radiance_full[:, 0], direct(glossy), rtol=1e-11)
    np.testing.assert_allclose(plan.radiance[:, 0], direct(plan.matrix), rtol=1e-11)
    ref = direct(glossy)
    err = np.sqrt(np.sum((direct(plan.matrix) - ref) ** 2) / np.sum(ref**2))
    assert err == pytest.approx(plan.error, rel=1e-9) and err <= 1e-2
    smaller = truncate(glossy, plan.order - 1)
    worse = np.sqrt(np.sum((direct(smaller) - ref) ** 2) / np.sum(ref**2))
    assert worse > 1e-2  # the order found is the smallest


def test_latlong_constant_image_is_uniform_sky():
    cm = project(Lambert(0.4), basis.HemiHarmonics(3))
    img = np.ones((64, 128, 3)) * np.array([1.0, 0.5, 2.0])
    plan = for_scene(cm, lights=Environment.latlong(img), views=VIEWS, tol=1e-6,
                     time_eval=False)
    # cos(theta) taken at each row's centre: relative error about h^2 / 8 = 3.0e-4 for
    # h = pi / 64 (observed 3.0e-4)
    want = np.broadcast_to(0.4 * np.array([1.0, 0.5, 2.0]), plan.radiance_full.shape)
    np.testing.assert_allclose(plan.radiance_full, want, rtol=4e-4)


def test_times_are_measured(glossy):
    plan = for_scene(glossy, lights=Environment.sh(np.array([1.0])), views=VIEWS, tol=1e-2)
    assert plan.eval_ns_full > 0 and plan.eval_ns > 0
    assert plan.eval_ns_saved == pytest.approx(plan.eval_ns_full - plan.eval_ns)


def test_for_scene_errors(glossy):
    sky = Environment.sh(np.array([1.0]))
    with pytest.raises(ValueError, match="tol must be a positive number"):
        for_scene(glossy, lights=sky, views=VIEWS, tol=0.0)
    with pytest.raises(ValueError, match="views must lie in the upper hemisphere"):
        for_scene(glossy, lights=sky, views=[[0.0, 0.6, -0.8]], tol=0.1)
    with pytest.raises(ValueError, match="light_weights applies to lights given as"):
        for_scene(glossy, lights=sky, views=VIEWS, tol=0.1, light_weights=[1.0])
    with pytest.raises(TypeError, match="cm must be a basis.CoefficientMatrix"):
        for_scene(np.eye(3), lights=sky, views=VIEWS, tol=0.1)
    with pytest.raises(ValueError, match=r"coeffs must have shape \(\(lmax\+1\)\^2,\)"):
        Environment.sh(np.ones(3))
    with pytest.raises(ValueError, match=r"image must have shape \(H, W\)"):
        Environment.latlong(np.ones(5))
    with pytest.raises(ValueError, match=r"weights must have shape \(2,\)"):
        Environment.directional([[0, 0, 1.0], [0, 1.0, 0]], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="view_weights must be"):
        for_scene(glossy, lights=sky, views=VIEWS, tol=0.1, view_weights=np.zeros(16))
