"""Numbers of the report: errors, values, stored reals, rounding, bands and truncations.

The image error of lit spheres, BRDF values as (n, channels), the reals a compact form
stores and its rounding to a storage type, the relative L2 error of
q = f cos theta_i cos theta_o, errors and negative fractions by (theta_i, theta_o) band,
truncations of a matrix, and the samples near the plane of incidence.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

import project
from basis import CoefficientMatrix

from ..hybrid import Hybrid
from ..render import render_sphere
from ..truncate import precision, truncate, unique_coefficients
from ._settings import _VIEW, LIGHTS, SPHERE_SIZE


def image_error(brdf: Any, approx: Any, *, size: int = SPHERE_SIZE) -> float:
    """Relative RMS difference of lit-sphere pictures, ``approx`` against ``brdf``.

    Parameters
    ----------
    brdf, approx : BRDF
        Objects with ``eval(wi, wo)`` (``approx`` may also be a coefficient matrix).
    size : int
        Image side in pixels (:func:`compress.render_sphere`).

    Returns
    -------
    float
        sqrt(sum (I_approx - I)^2 / sum I^2) over the pixels on the sphere, the channels
        and the three lights of :data:`LIGHTS` (view along z), each light of unit
        irradiance.

    Examples
    --------
    >>> from project.models import Lambert
    >>> round(image_error(Lambert(0.5), Lambert(0.55), size=32), 12)
    0.1
    """
    refs = [render_sphere(brdf, light, size=size, view=_VIEW) for light in LIGHTS]
    imgs = [render_sphere(approx, light, size=size, view=_VIEW) for light in LIGHTS]
    return _image_error(refs, imgs)


def _image_error(refs: Sequence[NDArray], imgs: Sequence[NDArray]) -> float:
    num = den = 0.0
    for ref, img in zip(refs, imgs, strict=True):
        if img.ndim < ref.ndim:
            img = img[..., None]
        on = np.isfinite(ref)
        num += float(np.sum((np.broadcast_to(img, ref.shape)[on] - ref[on]) ** 2))
        den += float(np.sum(ref[on] ** 2))
    return math.sqrt(num / den) if den > 0 else math.nan


def _values(brdf: Any, wi: NDArray, wo: NDArray) -> NDArray[np.float64]:
    """BRDF values as (n, channels) float64."""
    v = np.asarray(brdf.eval(wi, wo), dtype=np.float64)
    return v.reshape(v.shape[0], -1) if v.ndim != 2 else v


def _reals(obj: Any) -> int | None:
    """Count the stored reals of a compact representation (None: a table, an analytic BRDF)."""
    if isinstance(obj, CoefficientMatrix):
        return unique_coefficients(obj)
    if isinstance(obj, Hybrid):
        lobe = _reals(obj.lobe)
        return None if lobe is None else lobe + unique_coefficients(obj.residual)
    if hasattr(obj, "family") and hasattr(obj, "params"):
        n = getattr(obj, "nparams", None)
        return int(n) if isinstance(n, int | np.integer) else \
            int(sum(np.size(v) for v in obj.params.values()))
    return None


def _rounded(obj: Any, dtype: str) -> tuple[Any, int]:
    """Round a representation to a storage type (held as float64); return it and its reals."""
    if isinstance(obj, CoefficientMatrix):
        return precision(obj, dtype), unique_coefficients(obj)
    if isinstance(obj, Hybrid):
        lobe, n = _rounded(obj.lobe, dtype)
        res = precision(obj.residual, dtype)
        return Hybrid(lobe, res, dict(obj.info)), n + unique_coefficients(obj.residual)
    top = float(np.finfo(dtype).max)
    params = {}
    for k, v in obj.params.items():
        if np.max(np.abs(v), initial=0.0) > top:
            raise ValueError(f"parameter {k!r} exceeds the largest {dtype}")
        params[k] = np.asarray(v).astype(dtype).astype(np.float64)
    model = project.FittedModel(obj.family, params, info=dict(obj.info or {}))
    return model, _reals(model)


def _rel_l2(f: NDArray, g: NDArray, pairs: Any) -> float:
    cc = (pairs.wi[:, 2] * pairs.wo[:, 2])[:, None] ** 2
    w = pairs.weights[:, None]
    den = np.sum(w * cc * f * f, axis=0)
    num = np.sum(w * cc * (g - f) ** 2, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.sqrt(num / den)
    return float(np.nanmax(rel)) if np.any(np.isfinite(rel)) else math.nan


def _band_errors(wi: NDArray, wo: NDArray, w: NDArray, f: NDArray, fh: NDArray,
                 edges: NDArray) -> tuple[NDArray, NDArray]:
    """Share of the squared error of q and relative error by (theta_i, theta_o) band."""
    nb = len(edges) - 1
    cc = (wi[:, 2] * wo[:, 2])[:, None]
    err2 = np.sum(w[:, None] * ((fh - f) * cc) ** 2, axis=1)
    ref2 = np.sum(w[:, None] * (f * cc) ** 2, axis=1)
    bi, bo = _band_index(wi, edges), _band_index(wo, edges)
    e = np.zeros((nb, nb))
    r = np.zeros((nb, nb))
    np.add.at(e, (bi, bo), err2)
    np.add.at(r, (bi, bo), ref2)
    total = e.sum()
    share = e / total if total > 0 else np.zeros_like(e)
    rel = np.full_like(e, np.nan)
    np.divide(e, r, out=rel, where=r > 0)
    return share, np.sqrt(rel)


def _band_index(d: NDArray, edges: NDArray) -> NDArray:
    """Return the band of theta of each direction of ``d`` (n, 3), edges in radians."""
    nb = len(edges) - 1
    return np.clip(np.searchsorted(edges, np.arccos(np.clip(d[:, 2], -1, 1))) - 1, 0, nb - 1)


def _negative_fractions(expansion: Any, wi: NDArray, wo: NDArray, w: NDArray,
                        edges: NDArray) -> tuple[float, NDArray]:
    """Weighted fraction of the pairs where ``expansion`` is negative in some channel.

    Returns the fraction over all pairs and, by (theta_i, theta_o) band, the fraction
    within each band (0 where a band holds no pair).
    """
    neg = np.any(_values(expansion, wi, wo) < 0.0, axis=1)
    frac = float(np.sum(w[neg]) / np.sum(w))
    nb = len(edges) - 1
    bi, bo = _band_index(wi, edges), _band_index(wo, edges)
    tot = np.zeros((nb, nb))
    bad = np.zeros((nb, nb))
    np.add.at(tot, (bi, bo), w)
    np.add.at(bad, (bi, bo), w * neg)
    return frac, np.divide(bad, tot, out=np.zeros_like(bad), where=tot > 0)


def _truncations(cm: CoefficientMatrix, pairs: Any) -> list[dict[str, Any]]:
    f = _values(cm, pairs.wi, pairs.wo)
    rows = []
    orders = sorted({int(o) for o in np.linspace(0, cm.order, min(cm.order + 1, 7))})
    for o in orders:
        t = cm if o == cm.order else truncate(cm, o)
        err = _rel_l2(f, _values(t, pairs.wi, pairs.wo), pairs)
        rows.append({"label": f"truncated to order {o}", "family": cm.basis.kind,
                     "dtype": "float64", "bytes": 8 * unique_coefficients(t), "l2": err,
                     "log": math.nan, "status": "measured"})
    return rows


def _in_plane(meas: Any, ti: float, tol_deg: float = 3.0) -> tuple[NDArray, NDArray]:
    """Return the samples near the plane of incidence at ``ti``: signed theta_o, f cos theta_o."""
    wi, wo = meas.wi, meas.wo
    near_i = np.abs(np.arccos(np.clip(wi[:, 2], -1, 1)) - ti) < math.radians(tol_deg)
    # the plane of incidence: wo's azimuth equals wi's (back) or wi's + pi (mirror side)
    phi_i = np.arctan2(wi[:, 1], wi[:, 0])
    phi_o = np.arctan2(wo[:, 1], wo[:, 0])
    d = np.angle(np.exp(1j * (phi_o - phi_i)))
    sin_o = np.hypot(wo[:, 0], wo[:, 1])
    tol = math.radians(tol_deg)
    back = np.abs(d) * sin_o < tol
    front = (math.pi - np.abs(d)) * sin_o < tol
    keep = near_i & (back | front)
    theta_o = np.arccos(np.clip(wo[keep, 2], -1, 1))
    signed = np.where(front[keep], theta_o, -theta_o)
    if ti == 0.0:
        signed = np.where(wo[keep, 0] <= 0, theta_o, -theta_o)
    return signed, np.asarray(meas.values)[keep].mean(axis=1) * np.cos(theta_o)
