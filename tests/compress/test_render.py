"""render_sphere and tonemap: closed forms, per-pixel recomputation, frame symmetries, errors."""

from __future__ import annotations

import numpy as np
import pytest

import basis
import compress.render as render_mod
from basis import CoefficientMatrix
from compress import render_sphere, tonemap
from project import project
from project.models import CookTorrance, GlossyPaint, Lambert, Ward


def _unit(*v):
    v = np.array(v, dtype=float)
    return v / np.linalg.norm(v)


def _pixel_normals(size):
    """(u, v, inside, n) from the documented pixel centres, default view (0, 0, 1)."""
    c = -1.0 + (2.0 * np.arange(size) + 1.0) / size
    u, v = np.meshgrid(c, -c)  # u along columns, v = 1 - (2 i + 1) / size along rows
    r2 = u * u + v * v
    inside = r2 < 1.0
    n = np.stack([u, v, np.sqrt(np.maximum(1.0 - r2, 0.0))], axis=-1)
    return u, v, inside, n


class _Turned:
    """The BRDF f'(wi, wo) = f(R^-1 wi, R^-1 wo), R the +90 degree turn about the normal."""

    def __init__(self, f):
        self.f, self.channels, self.isotropic = f, 1, False

    def eval(self, wi, wo):
        return self.f.eval(_turn_back(wi), _turn_back(wo))


def _turn_back(w):
    """R^-1 w: (x, y, z) -> (y, -x, z)."""
    w = np.asarray(w)
    return np.stack([w[..., 1], -w[..., 0], w[..., 2]], axis=-1)


def _random_dense(rng, order=4):
    """A general (anisotropic, not mirror-symmetric) symmetric matrix, quantity "f"."""
    b = basis.HemiZernike(order)
    x = rng.normal(size=(b.size, b.size))
    return CoefficientMatrix(b, x + x.T, "f", isotropic=False)


# -- against closed forms and independent recomputation ------------------------------------

@pytest.mark.parametrize("storage", ["isotropic", "dense"])
def test_lambert_matrix_renders_cosine_law(storage):
    a = 0.6
    cm = project(Lambert(a), basis.HemiZernike(4))
    # Lambert's f cos cos = (a/pi) z_i z_o is a degree-2 Zernike polynomial, so the projection
    # is exact up to its quadrature error (observed rel_error 3e-15)
    assert cm.info["rel_error"] < 1e-13
    if storage == "dense":  # same numbers through CoefficientMatrix.eval instead of the kernel
        cm = CoefficientMatrix(cm.basis, cm.matrix, cm.quantity, isotropic=False)
    light = _unit(0.3, -0.5, 0.8)
    img = render_sphere(cm, light, size=33)
    _, _, inside, n = _pixel_normals(33)
    assert np.array_equal(np.isnan(img), ~inside)
    ref = a / np.pi * np.maximum(n[inside] @ light, 0.0)
    # the fast evaluator adds ~1e-13 relative (compress/evaluate.py); observed max 2e-16
    # absolute on values up to 0.19
    np.testing.assert_allclose(img[inside], ref, rtol=0, atol=1e-13)
    assert np.sum(img[inside] == 0.0) > 0  # part of the disc faces away from the light


def test_model_pixels_match_independent_frames():
    # anisotropic Ward, oblique view and tangent: recompute chosen pixels from the documented
    # conventions with differently formed vectors (cross products instead of projections)
    f = Ward(0.1, 0.5, 0.12, 0.35, variant="bounded")
    size = 41
    light, view, tangent = _unit(-0.4, 0.7, 0.6), _unit(0.2, 0.3, 0.9), np.array([2.0, 1.0, 0.5])
    img = render_sphere(f, light, size=size, view=view, tangent=tangent, intensity=2.5)
    right = np.cross([0, 1, 0], view)
    right /= np.linalg.norm(right)
    up = np.cross(view, right)
    T = tangent / np.linalg.norm(tangent)
    checked = 0
    for i, j in [(20, 20), (5, 20), (20, 3), (33, 30), (10, 28), (36, 12), (0, 0), (2, 38)]:
        u, v = -1 + (2 * j + 1) / size, 1 - (2 * i + 1) / size
        if u * u + v * v >= 1:
            assert np.isnan(img[i, j])
            continue
        n = u * right + v * up + np.sqrt(1 - u * u - v * v) * view
        t = np.cross(np.cross(n, T), n)  # = T - (T.n) n
        t /= np.linalg.norm(t)
        b = np.cross(n, t)
        frame = np.stack([t, b, n])
        want = 2.5 * float(f.eval(frame @ light, frame @ view)) * max(float(n @ light), 0.0)
        # same formula, different rounding: observed relative differences ~1e-15
        np.testing.assert_allclose(img[i, j], want, rtol=1e-12, atol=1e-300)
        checked += want > 0
    assert checked >= 3  # the checks include lit pixels, not only zeros


def test_multichannel_intensity():
    f = Lambert([0.2, 0.5, 0.8])
    light = _unit(0.1, 0.2, 1.0)
    img = render_sphere(f, light, size=17, intensity=[1.0, 2.0, 0.5])
    _, _, inside, n = _pixel_normals(17)
    assert img.shape == (17, 17, 3)
    ref = np.maximum(n[inside] @ light, 0)[:, None] * np.array([0.2, 1.0, 0.4]) / np.pi
    np.testing.assert_allclose(img[inside], ref, rtol=1e-14, atol=1e-16)  # rounding only
    assert np.all(np.isnan(img[~inside]))


def test_light_behind_and_at_the_side():
    f = Lambert(0.5)
    back = render_sphere(f, [0, 0, -1.0], size=16)
    _, _, inside, n = _pixel_normals(16)
    assert np.all(back[inside] == 0.0) and np.all(np.isnan(back[~inside]))
    side = render_sphere(f, [1.0, 0, 0], size=16)  # terminator along the central column
    lit = n[..., 0] > 0
    assert np.all(side[inside & lit] > 0) and np.all(side[inside & ~lit] == 0)


# -- the tangent frame ---------------------------------------------------------------------

def test_swapped_ward_equals_turned_tangent_on_the_axes():
    # Ward(ax, ay) in the frame of tangent e_y is Ward(ay, ax) in the frame of e_x wherever the
    # two frames are 90 degrees apart: (t_y, b_y) = (b_x, -t_x) on the central row and column
    # (Ward is even in h_x and h_y, so the sign of b does not matter). Elsewhere the projected
    # e_x and e_y are not perpendicular and the images differ.
    size = 31
    light = _unit(-0.5, 0.3, 0.7)
    a = render_sphere(Ward(0.1, 0.5, 0.08, 0.3), light, size=size, tangent=(0, 1, 0))
    b = render_sphere(Ward(0.1, 0.5, 0.3, 0.08), light, size=size, tangent=(1, 0, 0))
    c = size // 2  # odd size: row c is v = 0, column c is u = 0
    np.testing.assert_allclose(a[c], b[c], rtol=1e-12, atol=1e-300)  # observed ~1e-15
    np.testing.assert_allclose(a[:, c], b[:, c], rtol=1e-12, atol=1e-300)
    off = ~np.isnan(a)
    off[c], off[:, c] = False, False
    assert np.max(np.abs(a[off] - b[off])) > 1e-2 * np.nanmax(a)


def test_general_matrix_turned_equals_tangent_turned_on_the_axes(rng):
    # a general matrix (neither isotropic nor mirror-symmetric) exposes the sign convention of
    # b = n x t: f turned by +90 degrees in the frame of e_x = f in the frame of e_y on the axes
    cm = _random_dense(rng)
    size, light = 31, _unit(0.4, 0.45, 0.8)
    a = render_sphere(_Turned(cm), light, size=size, tangent=(1, 0, 0))
    b = render_sphere(cm, light, size=size, tangent=(0, 1, 0))
    c = size // 2
    scale = np.nanmax(np.abs(b))
    np.testing.assert_allclose(a[c], b[c], rtol=0, atol=1e-12 * scale)  # observed 3e-16 scale
    np.testing.assert_allclose(a[:, c], b[:, c], rtol=0, atol=1e-12 * scale)
    # the check can fail: with a left-handed b = t x n the two sides would differ by a turn of
    # 180 degrees, and this matrix (odd azimuthal orders) is not invariant under it
    flipped = render_sphere(_Turned(_Turned(_Turned(cm))), light, size=size, tangent=(1, 0, 0))
    assert np.max(np.abs(flipped[c] - b[c])[~np.isnan(b[c])]) > 1e-3 * scale


@pytest.mark.parametrize("which", ["ward", "matrix"])
def test_turning_the_whole_scene_turns_the_image(which, rng):
    # R = +90 degrees about the view axis z maps tangent e_x -> e_y, the light l -> R l and the
    # image point (u, v) -> (-v, u): img_B = np.rot90(img_A) exactly (pixel centres map onto
    # pixel centres), for any BRDF.
    f = Ward(0.1, 0.5, 0.08, 0.3) if which == "ward" else _random_dense(rng)
    l = _unit(-0.5, 0.3, 0.7)
    rl = np.array([-l[1], l[0], l[2]])
    a = render_sphere(f, l, size=24, tangent=(1, 0, 0))
    b = render_sphere(f, rl, size=24, tangent=(0, 1, 0))
    scale = np.nanmax(np.abs(a))
    np.testing.assert_allclose(b, np.rot90(a), rtol=0, atol=1e-12 * scale)  # rounding only


@pytest.mark.parametrize("which", ["model", "isotropic matrix"])
def test_isotropic_image_does_not_depend_on_the_tangent(which, rng):
    # a random isotropic matrix: any function of (z_i, z_o, cos(phi_i - phi_o)) will do
    f = CookTorrance(0.2, 0.3) if which == "model" else _random_dense(rng).to_isotropic()
    light = _unit(0.5, -0.2, 0.6)
    ref = render_sphere(f, light, size=25, tangent=(1, 0, 0))
    scale = np.nanmax(np.abs(ref))
    # (0, 0, 1) puts a pole of the tangent field at the centre pixel (size odd): fallback frame
    for tangent in [(0, 1, 0), (1, 2, 3), (0, 0, 1), (-1, 0, 0)]:
        img = render_sphere(f, light, size=25, tangent=tangent)
        # the BRDF sees only cos(phi_i - phi_o) of the local directions: rounding, ~1e-15
        np.testing.assert_allclose(img, ref, rtol=0, atol=1e-12 * scale)


def test_pole_uses_the_fallback_axis():
    # tangent along the view: the centre pixel (n = tangent) gets t = e_x (the world axis
    # least aligned with the tangent), b = e_y; a Ward lobe there is that of frame (x, y, z)
    f = Ward(0.0, 1.0, 0.05, 0.4)
    light = _unit(0.3, 0.2, 0.9)
    img = render_sphere(f, light, size=9, tangent=(0, 0, 1))
    want = float(f.eval(light, [0, 0, 1.0])) * light[2]
    np.testing.assert_allclose(img[4, 4], want, rtol=1e-13)
    assert np.isfinite(img[~np.isnan(img)]).all()


def test_chunked_evaluation_is_the_same(monkeypatch, rng):
    dense = _random_dense(rng)
    light = _unit(0.2, 0.1, 1.0)
    for cm in (dense, dense.to_isotropic()):
        whole = render_sphere(cm, light, size=20)
        with monkeypatch.context() as m:
            m.setattr(render_mod, "_CHUNK", 7)  # 7 does not divide the 200-odd lit pixels
            # the same values; BLAS may block matrix products of other lengths differently
            # (observed 1.3e-15 on values ~0.3 for the dense matrix)
            np.testing.assert_allclose(render_sphere(cm, light, size=20), whole, rtol=0,
                                       atol=1e-13 * np.nanmax(np.abs(whole)))


# -- tonemap ---------------------------------------------------------------------------------

def test_tonemap_srgb_curve():
    x = np.array([0.0, 0.0031308, 0.01, 0.5, 1.0, 3.0, -1.0, np.nan])
    got = tonemap(x, 1.0)
    lin = np.clip(x[:-1], 0, 1)
    # IEC 61966-2-1; the two branches meet at 0.0031308 to ~1e-8 (the standard's rounding)
    want = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    np.testing.assert_allclose(got[:-1], want, rtol=0, atol=1e-15)
    assert got[4] == pytest.approx(1.0, abs=1e-15) and got[5] == got[4] and got[6] == 0.0
    assert np.isnan(got[-1])
    assert tonemap(x, 2.0, background=0.25)[-1] == 0.25
    np.testing.assert_allclose(tonemap([0.25], 2.0), tonemap([0.5]), rtol=0, atol=0)


# -- bad input -------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, err, match", [
    ({"brdf": "Lambert"}, TypeError, r"brdf must be a basis.CoefficientMatrix or a BRDF"),
    ({"light": [0, 0, 2.0]}, ValueError, r"light must be unit vectors"),
    ({"light": [[0, 0, 1.0]] * 2}, ValueError, r"light must be one direction of shape \(3,\)"),
    ({"light": [np.nan, 0, 1.0]}, ValueError, r"light must be finite"),
    ({"view": [0, 0, 0.0]}, ValueError, r"view must be unit vectors.*zero-length"),
    ({"tangent": [0, 0, 0]}, ValueError, r"tangent must be a non-zero vector"),
    ({"tangent": [1, 0]}, ValueError, r"tangent must have shape \(3,\), got shape \(2,\)"),
    ({"tangent": [1, np.inf, 0]}, ValueError, r"tangent must be finite"),
    ({"size": 0}, ValueError, r"size must lie in 1 .. 4096, got 0"),
    ({"size": 5000}, ValueError, r"size must lie in 1 .. 4096, got 5000"),
    ({"size": 8.0}, TypeError, r"size must be an integer, got 8.0"),
    ({"size": True}, TypeError, r"size must be an integer, got True"),
    ({"intensity": -1.0}, ValueError, r"intensity must be finite and >= 0"),
    ({"intensity": [[1.0]]}, ValueError, r"intensity must be a number or a 1-D sequence"),
    ({"intensity": [1.0, 2.0]}, ValueError, r"intensity must be a scalar for a one-channel"),
])
def test_bad_input(kwargs, err, match):
    args = {"brdf": Lambert(0.5), "light": [0, 0, 1.0], **kwargs}
    brdf, light = args.pop("brdf"), args.pop("light")
    with pytest.raises(err, match=match):
        render_sphere(brdf, light, **{"size": 8, **args})


def test_bad_input_channels_and_min_cos():
    with pytest.raises(ValueError, match=r"one value per channel \(3\), got 2 values"):
        render_sphere(Lambert([0.1, 0.2, 0.3]), [0, 0, 1.0], size=4, intensity=[1.0, 2.0])
    cm = project(Lambert(0.5), basis.HemiZernike(2))
    with pytest.raises(ValueError, match=r"min_cos must lie in \(0, 1\), got 0"):
        render_sphere(cm, [0, 0, 1.0], size=4, min_cos=0)


def test_delta_terms_are_announced():
    with pytest.warns(UserWarning, match=r"delta\) terms of GlossyPaint.* are not rendered"):
        img = render_sphere(GlossyPaint(0.5, 0.1), [0, 0, 1.0], size=5)
    assert img[2, 2] == pytest.approx(0.5 / np.pi, rel=1e-14)  # the Lambert part only


@pytest.mark.parametrize("kwargs, err, match", [
    ({"exposure": 0.0}, ValueError, r"exposure must be finite and > 0, got 0.0"),
    ({"background": 2.0}, ValueError, r"background must lie in \[0, 1\]"),
    ({"image": [np.inf]}, ValueError, r"image must not hold inf"),
    ({"image": ["a"]}, TypeError, r"image must be an array of floats"),
])
def test_tonemap_bad_input(kwargs, err, match):
    image = kwargs.pop("image", [0.5])
    with pytest.raises(err, match=match):
        tonemap(image, **kwargs)
