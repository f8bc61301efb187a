"""Pictures of a BRDF: a unit sphere under one directional light, seen orthographically.

:func:`render_sphere` shades every pixel of the sphere's disc with the radiance
L = E f(w_i, w_o) max(cos theta_i, 0) of the BRDF in the pixel's own tangent frame, so an
isotropic and an anisotropic representation of the same material, or a material and its
90-degree turn, can be looked at side by side. :func:`tonemap` turns such an image into
display values (exposure, clipping, the sRGB transfer curve).

World frame: with the default ``view = (0, 0, 1)`` image x points right, y up and z towards
the viewer. The tangent frame at a point with normal n is (t, b, n) with t the world
direction ``tangent`` projected onto the tangent plane and normalised and b = n x t, so the
local frame of :mod:`basis` (z the normal, x the tangent of azimuth 0) is right-handed. A
tangent field on the sphere must vanish somewhere (hairy ball theorem): this one is
undefined at the two points n = +-tangent; see :func:`render_sphere` for what is done there.
"""

from __future__ import annotations

import operator
import warnings

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basis import CoefficientMatrix
from basis.validation import as_directions, check_bytes

__all__ = ["render_sphere", "tonemap"]

#: Largest image side accepted (16.8 million pixels); larger pictures would only be slow.
MAX_SIZE = 4096
#: Lit pixels evaluated per call of the BRDF (bounds the memory of a dense matrix's basis
#: tables: 2^16 pixels x 2 directions x 153 functions (HemiZernike(16)) x 8 bytes = 160 MB).
_CHUNK = 1 << 16
#: Below this length of the projected tangent (tangent of unit length) the frame is taken
#: from a fallback axis: the projection T - (T.n) n loses relative accuracy ~ 1e-16 / |t|, so
#: above it the frame's direction is good to ~1e-8.
_POLE = 1e-8


#: float64 numbers per pixel alive at the peak of :func:`render_sphere`, besides 3 per channel
#: (the BRDF values, the radiance and the image): the normal, the tangent frame, both
#: directions in it, the disc coordinates and the masks.
_PIXEL_FLOATS = 24


def render_sphere(brdf: object, light: ArrayLike, *, size: int = 256,
                  view: ArrayLike = (0.0, 0.0, 1.0), tangent: ArrayLike = (1.0, 0.0, 0.0),
                  intensity: ArrayLike = 1.0, min_cos: float = 1e-3) -> NDArray[np.float64]:
    """Render the radiance image of a unit sphere lit by a directional light, seen orthographically.

    Parameters
    ----------
    brdf : basis.CoefficientMatrix or BRDF
        A coefficient matrix (isotropic ones are evaluated by the compiled
        :class:`~compress.evaluate.FastEvaluator`, dense ones by
        :meth:`~basis.CoefficientMatrix.eval`), or any object with ``eval(wi, wo)`` such as
        the models of :mod:`project.models`. Ideal mirror (``delta``) terms are not drawn
        (under a directional light they light one point of zero area); a warning says so.
    light : (3,) array_like of float
        Unit vector towards the light, world frame. Any direction: a light behind the
        sphere lights a crescent or nothing.
    size : int
        Image side in pixels, 1 <= size <= 4096. Pixel (i, j) (row i from the top, column j
        from the left) sees the point u = -1 + (2 j + 1) / size, v = 1 - (2 i + 1) / size of
        the image plane, i.e. pixel centres on a regular grid covering [-1, 1]^2.
    view : (3,) array_like of float
        Unit vector towards the viewer (the camera looks along -view). The image axes are
        right = normalise(e_y x view), up = view x right (e_y = (0, 1, 0)); for a view along
        +-e_y, right = e_x. With the default (0, 0, 1): right = e_x, up = e_y.
    tangent : (3,) array_like of float
        World direction whose projection onto each tangent plane is the local x axis (the
        azimuth 0 of the BRDF; for a brushed metal simulated with grooves along x, the
        brushing direction). Any non-zero finite vector; it is normalised.
    intensity : float or (channels,) array_like of float
        Irradiance E >= 0 of the light on a surface facing it; the image is in units of
        E per steradian.
    min_cos : float
        Passed to the evaluation of a coefficient matrix (see
        :meth:`basis.CoefficientMatrix.eval`); ignored for other BRDFs.

    Returns
    -------
    (size, size) ndarray, or (size, size, channels) for a BRDF whose ``eval`` returns a
    channel axis
        Radiance L = E f(w_i, w_o) max(cos theta_i, 0) (float64), with w_i, w_o the light and
        view directions in the pixel's tangent frame. NaN outside the disc u^2 + v^2 < 1
        (pixels whose centre misses the sphere), 0 where the light is below the local
        horizon. Row 0 is the top of the image (as ``matplotlib.pyplot.imshow`` draws it).

    Notes
    -----
    At a pixel inside the disc the normal is n = u right + v up + sqrt(1 - u^2 - v^2) view,
    the frame is t = (T - (T.n) n) / |T - (T.n) n| for T = tangent / |tangent|, b = n x t,
    and w = (w.t, w.b, w.n) in local coordinates. The frame is undefined where n = +-T, the
    two poles of the tangent field (one of them is visible unless T lies in the image
    plane, where both sit on the rim, which pixel centres never reach); a pixel centre
    lands on a pole only by coincidence, e.g. the centre pixel of an odd-sized image when
    T = view. Where |T - (T.n) n| < 1e-8 the frame is built from the world axis least
    aligned with T instead: an anisotropic BRDF's value there is that of one particular
    approach to the pole, and an isotropic BRDF's image does not depend on the frame at all.

    Turning the whole scene (light and tangent) by 90 degrees about the view turns the image
    exactly (``np.rot90``). A BRDF turned by 90 degrees on the surface, f(R^-1 w_i, R^-1 w_o),
    is the original seen in the frame (b, -t); that is the frame of the turned tangent
    (``tangent`` e_y instead of e_x) only on the image's central row and column, because the
    projections of two fixed world directions are not perpendicular elsewhere
    (t_x . t_y is proportional to -n_x n_y).

    Examples
    --------
    >>> import numpy as np
    >>> from project.models import Lambert
    >>> img = render_sphere(Lambert(0.5), [0, 0, 1.0], size=5)
    >>> img.shape, bool(np.isnan(img[0, 0]))            # corner pixel: outside the disc
    ((5, 5), True)
    >>> round(float(img[2, 2]) * np.pi, 12)  # centre: n = l, so L = f = a / pi
    0.5
    """
    evaluate = _evaluator(brdf, min_cos)
    light = _unit(light, "light")
    view = _unit(view, "view")
    tan = _nonzero(tangent, "tangent")
    size = _size(size)
    e = _intensity(intensity)
    ch = getattr(brdf, "channels", 1)
    ch = ch if isinstance(ch, int) and ch > 0 else 1
    check_bytes(8.0 * size * size * (_PIXEL_FLOATS + 3 * ch),
                f"rendering {brdf!r} on a {size} x {size} image")

    right, up = _camera(view)
    c = -1.0 + (2.0 * np.arange(size) + 1.0) / size
    u = c[None, :]
    v = -c[:, None]  # row 0 at the top: v = 1 - (2 i + 1) / size
    r2 = u * u + v * v
    inside = r2 < 1.0
    uu, vv = np.broadcast_to(u, r2.shape)[inside], np.broadcast_to(v, r2.shape)[inside]
    n = (uu[:, None] * right + vv[:, None] * up
         + np.sqrt(1.0 - r2[inside])[:, None] * view)                    # (p, 3) normals
    n /= np.linalg.norm(n, axis=1)[:, None]
    t, b = _frame(n, tan)
    cos_i = n @ light
    lit = cos_i > 0.0
    wi = np.stack([t[lit] @ light, b[lit] @ light, cos_i[lit]], axis=1)
    wo = np.stack([t[lit] @ view, b[lit] @ view, n[lit] @ view], axis=1)
    # the three projections of a unit vector on an orthonormal frame: unit to rounding
    wi /= np.linalg.norm(wi, axis=1)[:, None]
    wo /= np.linalg.norm(wo, axis=1)[:, None]
    f = _chunked(evaluate, wi, wo)
    if f.ndim == 1:
        if np.ndim(e) and np.size(e) != 1:
            raise ValueError(f"intensity must be a scalar for a one-channel BRDF, got "
                             f"{np.size(e)} values")
        chan: tuple[int, ...] = ()
    else:
        if np.size(e) not in (1, f.shape[1]):
            raise ValueError(f"intensity must be a scalar or hold one value per channel "
                             f"({f.shape[1]}), got {np.size(e)} values")
        chan = (f.shape[1],)
    rad = f * (cos_i[lit] if f.ndim == 1 else cos_i[lit][:, None])
    rad = rad * (np.reshape(e, -1)[0] if np.size(e) == 1 else e)
    disc = np.zeros((n.shape[0], *chan))
    disc[lit] = rad
    img = np.full((size, size, *chan), np.nan)
    img[inside] = disc
    return img


def tonemap(image: ArrayLike, exposure: float = 1.0, *,
            background: float | None = None) -> NDArray[np.float64]:
    """Map a radiance image to display values: exposure, clipping to [0, 1], sRGB encoding.

    Parameters
    ----------
    image : array_like of float
        Linear radiance, any shape (e.g. from :func:`render_sphere`); NaN marks background.
    exposure : float
        Factor > 0 applied before clipping (a radiance of 1 / exposure maps to white). Use
        one exposure for pictures that are to be compared.
    background : float, optional
        Value in [0, 1] put where ``image`` is NaN; None keeps NaN (drawn transparent by
        ``imshow`` with a colormap).

    Returns
    -------
    ndarray of float64, same shape, values in [0, 1] (or NaN)
        The sRGB transfer function (IEC 61966-2-1) of clip(exposure * image, 0, 1):
        12.92 x below 0.0031308, 1.055 x^(1/2.4) - 0.055 above.

    Examples
    --------
    >>> tonemap([0.0, 0.5, 2.0, np.nan], background=0.0).round(4).tolist()
    [0.0, 0.7354, 1.0, 0.0]
    """
    try:
        img = np.array(image, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"image must be an array of floats, got {type(image).__name__}") from None
    x = float(exposure)
    if not (np.isfinite(x) and x > 0):
        raise ValueError(f"exposure must be finite and > 0, got {exposure!r}")
    if background is not None and not 0.0 <= float(background) <= 1.0:
        raise ValueError(f"background must lie in [0, 1] or be None, got {background!r}")
    if np.any(np.isinf(img)):
        raise ValueError("image must not hold inf (NaN marks background)")
    nan = np.isnan(img)
    lin = np.clip(np.where(nan, 0.0, img) * x, 0.0, 1.0)
    out = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1.0 / 2.4) - 0.055)
    out[nan] = np.nan if background is None else float(background)
    return out


# -- helpers --------------------------------------------------------------------------------

def _evaluator(brdf: object, min_cos: float):
    """Return a function (wi (n, 3), wo (n, 3)) -> (n,) or (n, channels) for ``brdf``."""
    if isinstance(brdf, CoefficientMatrix):
        if not 0.0 < min_cos < 1.0:
            raise ValueError(f"min_cos must lie in (0, 1), got {min_cos!r}")
        return brdf.evaluator(min_cos=min_cos)
    if not callable(getattr(brdf, "eval", None)):
        raise TypeError(f"brdf must be a basis.CoefficientMatrix or a BRDF with eval(wi, wo) "
                        f"(e.g. project.models.Lambert(0.5)), got {type(brdf).__name__}")
    if getattr(brdf, "delta", ()):
        warnings.warn(f"the ideal mirror (delta) terms of {brdf!r} are not rendered: under a "
                      "directional light they light a single point", UserWarning, stacklevel=3)
    return brdf.eval


def _chunked(evaluate, wi: NDArray, wo: NDArray) -> NDArray[np.float64]:
    if wi.shape[0] <= _CHUNK:
        return np.asarray(evaluate(wi, wo), dtype=np.float64)
    parts = [np.asarray(evaluate(wi[k:k + _CHUNK], wo[k:k + _CHUNK]), dtype=np.float64)
             for k in range(0, wi.shape[0], _CHUNK)]
    return np.concatenate(parts)


def _unit(w: ArrayLike, name: str) -> NDArray[np.float64]:
    d = as_directions(w, name)
    if d.shape != (3,):
        raise ValueError(f"{name} must be one direction of shape (3,), got shape {d.shape}")
    return d / np.linalg.norm(d)


def _nonzero(w: ArrayLike, name: str) -> NDArray[np.float64]:
    try:
        d = np.array(w, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a vector of 3 floats, got {type(w).__name__}") from None
    if d.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got shape {d.shape}")
    if not np.all(np.isfinite(d)):
        raise ValueError(f"{name} must be finite, got {d.tolist()}")
    norm = float(np.linalg.norm(d))
    if norm == 0.0:
        raise ValueError(f"{name} must be a non-zero vector, got {d.tolist()}")
    return d / norm


def _size(size: object) -> int:
    if isinstance(size, bool):
        raise TypeError(f"size must be an integer, got {size!r}")
    try:
        s = operator.index(size)
    except TypeError:
        raise TypeError(f"size must be an integer, got {size!r}") from None
    if not 1 <= s <= MAX_SIZE:
        raise ValueError(f"size must lie in 1 .. {MAX_SIZE}, got {s}")
    return s


def _intensity(intensity: ArrayLike) -> NDArray[np.float64]:
    try:
        e = np.array(intensity, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"intensity must be a number or one number per channel, got "
                        f"{intensity!r}") from None
    if e.ndim > 1 or e.size == 0:
        raise ValueError(f"intensity must be a number or a 1-D sequence (one per channel), "
                         f"got shape {e.shape}")
    if not np.all(np.isfinite(e)) or np.any(e < 0):
        raise ValueError(f"intensity must be finite and >= 0, got {intensity!r}")
    return e


def _camera(view: NDArray) -> tuple[NDArray, NDArray]:
    """Image axes (right, up) for a camera looking along -view (see render_sphere)."""
    right = np.cross([0.0, 1.0, 0.0], view)
    norm = np.linalg.norm(right)
    right = np.array([1.0, 0.0, 0.0]) if norm < 1e-12 else right / norm
    return right, np.cross(view, right)


def _frame(n: NDArray, tan: NDArray) -> tuple[NDArray, NDArray]:
    """(t, b) of the tangent frame at unit normals n (p, 3) for the unit world tangent."""
    t = tan - (n @ tan)[:, None] * n
    norm = np.linalg.norm(t, axis=1)
    pole = norm < _POLE
    if np.any(pole):
        axis = np.zeros(3)
        axis[np.argmin(np.abs(tan))] = 1.0  # |axis . tan| <= 1/sqrt(3): far from n = +-tan
        np_ = n[pole]
        t[pole] = axis - (np_ @ axis)[:, None] * np_
        norm[pole] = np.linalg.norm(t[pole], axis=1)
    t /= norm[:, None]
    return t, np.cross(n, t)
