"""Choosing how much of a representation to keep: by error on the BRDF, or by what a scene uses.

- :func:`select_order`: the smallest order whose error against the BRDF meets a tolerance.
- :func:`for_scene`: the smallest truncation (and rank) whose *rendered radiance* for given
  lights and views stays within a tolerance of the full representation.

Radiance
--------
With the BRDF held as q(w_i, w_o) = b(w_i)^T M b(w_o), the radiance leaving towards w_o is

    L_o(w_o) = int_H f(w_i, w_o) L_i(w_i) cos(theta_i) dw_i = b(w_o)^T M l / c(w_o),

where the light enters only through its coefficients in the same basis,
l_j = int_H b_j(w) L_i(w) dw and c(w_o) = cos(theta_o) for quantity "f_cos" (the form of
Westin, Arvo & Torrance 1992, sec. 2.5), or l_j = int_H b_j L_i cos(theta) dw and c = 1 for
quantity "f".

The band-limit fact: if the light has no component above degree L in the basis (l_j = 0 for
degree(b_j) > L), the columns of M above L never meet it, so truncating the *incident* side
above L changes the radiance not at all. :class:`ScenePlan` reports the light's bandwidth
and the radiance error of incident-side truncation at each order, which drops to rounding
level at L. A symmetric truncation (needed to stay reciprocal) also cuts outgoing detail,
which point views do see, so the symmetric ``order`` is measured, not inferred.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

import basis
import project
from basis import CoefficientMatrix
from basis.evaluate import lift_to
from basis.validation import as_directions, nonneg_int

from .study import MAX_THETA, METRICS, NODES, errors, eval_ns, make_basis, reference_samples
from .truncate import lowrank, truncate, unique_coefficients

__all__ = ["Environment", "ScenePlan", "for_scene", "select_order"]


def select_order(brdf: Any, kind: str, tol: float, *, metric: str = "l2",
                 max_order: int = 20, quantity: str = "auto",
                 nodes: tuple[int, int] = NODES, max_theta: float = MAX_THETA,
                 **project_kwargs: Any) -> int:
    """Find the smallest order of basis ``kind`` whose ``metric`` error on ``brdf`` is <= ``tol``.

    Parameters
    ----------
    brdf : BRDF
    kind : str
        ``"zernike"``, ``"harmonics"`` (odd), ``"harmonics-even"`` or ``"sh"``
        (:data:`compress.study.KINDS`).
    tol : float
        Tolerance on the metric (relative for l2, rel_rms; 1/sr for max_abs; percent for
        smape; ...; see :mod:`compress.study`).
    metric : str
        One of :data:`compress.study.METRICS` except ``"albedo"`` for anisotropic BRDFs.
    max_order : int
        Largest order tried. The BRDF is projected once at this order and the lower orders
        are its truncations, which is exact: every basis is ordered by degree, so the L2
        projection at a lower order is a prefix of the higher one.
    quantity, nodes, max_theta, **project_kwargs
        As in :func:`compress.study`.

    Returns
    -------
    int

    Raises
    ------
    ValueError
        If no order up to ``max_order`` meets ``tol`` (the message gives the best reached).

    Examples
    --------
    Lambert is exact at order 1 in the odd hemisphere harmonics:

    >>> from project.models import Lambert
    >>> select_order(Lambert(0.5), "harmonics", 1e-10, max_order=4)
    1
    """
    if metric not in METRICS:
        raise ValueError(f"metric must be one of {', '.join(METRICS)}, got {metric!r}")
    if not (isinstance(tol, int | float) and tol > 0):
        raise ValueError(f"tol must be a positive number, got {tol!r}")
    max_order = nonneg_int(max_order, "max_order")
    top = project.project(brdf, make_basis(kind, max_order), quantity=quantity,
                          **project_kwargs)
    ts = reference_samples(brdf, nodes=nodes, max_theta=max_theta)
    lowest = 1 if kind == "harmonics" else 0
    best = (np.inf, -1)
    for order in range(lowest, max_order + 1):
        err = errors(truncate(top, order), ts)[metric]
        if err is None:
            raise ValueError(f"metric {metric!r} is not defined for this test set "
                             "(albedo needs an isotropic BRDF)")
        if err <= tol:
            return order
        best = min(best, (err, order))
    raise ValueError(f"no order <= {max_order} of kind {kind!r} meets {metric} <= {tol:.3g} "
                     f"for {brdf!r}: the best is {best[0]:.3g} at order {best[1]}; raise "
                     "max_order or the tolerance")


# -- lights ----------------------------------------------------------------------------------
class Environment:
    """The light of a scene, in one of three forms.

    Use the constructors: :meth:`directional` (weighted directions), :meth:`sh` (real
    spherical-harmonic coefficients of an environment, this package's convention) or
    :meth:`latlong` (an equirectangular image). Only light from the upper hemisphere reaches
    the surface.
    """

    def __init__(self, form: str, data: dict[str, Any]) -> None:
        self.form = form
        self._data = data

    @classmethod
    def directional(cls, dirs: ArrayLike, weights: ArrayLike | None = None) -> Environment:
        """Build distant lights from their directions and irradiances.

        ``dirs`` are (n, 3) unit vectors towards the lights, ``weights`` their irradiance
        ((n,) or (n, channels), measured normal to each beam; default 1):
        L_o(w_o) = sum_k weights_k f(d_k, w_o) cos(theta_k).
        """
        d = as_directions(dirs, "dirs").reshape(-1, 3)
        w = np.ones(d.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
        if w.shape[:1] != (d.shape[0],) or w.ndim > 2:
            raise ValueError(f"weights must have shape ({d.shape[0]},) or ({d.shape[0]}, "
                             f"channels), got shape {w.shape}")
        if not np.all(np.isfinite(w)):
            raise ValueError("weights must be finite")
        return cls("directional", dict(dirs=d, weights=w.reshape(d.shape[0], -1)))

    @classmethod
    def sh(cls, coeffs: ArrayLike) -> Environment:
        """Build an environment from its real spherical-harmonic coefficients.

        L_i(w) = sum_j c_j Y_j(w) in real spherical harmonics (``basis.SphericalHarmonics``
        order, flat index l*l + l + m); ``coeffs`` has shape ((lmax+1)^2,) or
        ((lmax+1)^2, channels).
        """
        c = np.asarray(coeffs, dtype=np.float64)
        n = c.shape[0] if c.ndim else 0
        lmax = int(round(np.sqrt(n))) - 1
        if c.ndim not in (1, 2) or n == 0 or (lmax + 1) ** 2 != n:
            raise ValueError(f"coeffs must have shape ((lmax+1)^2,) or ((lmax+1)^2, channels),"
                             f" got shape {c.shape}")
        return cls("sh", dict(coeffs=c.reshape(n, -1), lmax=lmax))

    @classmethod
    def latlong(cls, image: ArrayLike) -> Environment:
        """Build an environment from an equirectangular radiance image.

        The image is (H, W) or (H, W, channels): row i spans theta in [i, i+1] pi / H from
        the zenith, column j spans phi in [j, j+1] 2 pi / W from +x. Each upper-hemisphere
        pixel becomes a light at its centre with the pixel's exact solid angle (midpoint
        rule).
        """
        img = np.asarray(image, dtype=np.float64)
        if img.ndim not in (2, 3) or img.shape[0] < 2 or img.shape[1] < 1:
            raise ValueError(f"image must have shape (H, W) or (H, W, channels) with H >= 2, "
                             f"got shape {img.shape}")
        if not np.all(np.isfinite(img)):
            raise ValueError("image must be finite")
        h, w = img.shape[:2]
        edges = np.linspace(0.0, np.pi, h + 1)
        rows = np.flatnonzero(edges[1:] <= np.pi / 2 + 1e-15)
        theta = 0.5 * (edges[rows] + edges[rows + 1])
        phi = (np.arange(w) + 0.5) * 2.0 * np.pi / w
        solid = np.broadcast_to((np.cos(edges[rows]) - np.cos(edges[rows + 1]))[:, None]
                                * (2.0 * np.pi / w), (rows.size, w))
        st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
        d = np.stack([st * np.cos(phi), st * np.sin(phi), np.broadcast_to(ct, (rows.size, w))],
                     axis=-1).reshape(-1, 3)
        radiance = img[rows].reshape(rows.size * w, -1)
        # a pixel of radiance L and solid angle W gives irradiance L W normal to its beam
        out = cls.directional(d, radiance * solid.reshape(-1, 1))
        out.form = "latlong"
        return out

    def coefficients(self, b: basis.Basis, quantity: str) -> NDArray[np.float64]:
        """(size, channels) l_j = int_H b_j L_i dw ("f_cos") or with a cos weight ("f")."""
        if self.form in ("directional", "latlong"):
            d, w = self._data["dirs"], self._data["weights"]
            up = d[:, 2] > 0
            d, w = d[up], w[up]
            if quantity == "f":
                w = w * d[:, 2:3]
            return b.eval(d).T @ w
        lmax = self._data["lmax"]
        n = b.order + lmax + 16  # generous: the integrands are smooth on H
        rule = basis.hemisphere_rule(n, 2 * (b.order + lmax) + 2)
        radiance = basis.SphericalHarmonics(lmax).eval(rule.points) @ self._data["coeffs"]
        wt = rule.weights * (rule.points[:, 2] if quantity == "f" else 1.0)
        return b.eval(rule.points).T @ (wt[:, None] * radiance)

    def radiance(self, brdf: Any, views: ArrayLike, *,
                 resolution: int = 128) -> NDArray[np.float64]:
        """Radiance L_o(w_o) = int_H f(w_i, w_o) L_i(w_i) cos(theta_i) dw_i towards views.

        Works for any BRDF (not only coefficient matrices): directional and latlong lights
        are summed exactly, L_o = sum_k weights_k f(d_k, w_o) cos(theta_k); an SH
        environment is first sampled on an equirectangular grid of ``resolution`` rows
        (:meth:`latlong`, midpoint rule), which resolves lobes down to about
        180 / resolution degrees.

        Parameters
        ----------
        brdf : BRDF
            Any object with ``eval(wi, wo)``.
        views : (m, 3) array_like of float
            Unit vectors towards the viewer, local frame.
        resolution : int
            Rows of the latlong grid of an SH environment (columns: twice as many).

        Returns
        -------
        (m, channels) ndarray
            L_o in the units of the light's radiance (irradiance for directional lights)
            per steradian times sr, i.e. radiance.
        """
        v = as_directions(views, "views").reshape(-1, 3)
        if self.form == "sh":
            rows = nonneg_int(resolution, "resolution")
            if rows < 2:
                raise ValueError(f"resolution must be >= 2, got {rows}")
            theta = (np.arange(rows) + 0.5) * np.pi / rows
            phi = (np.arange(2 * rows) + 0.5) * np.pi / rows
            dirs = basis.from_angles(theta[:, None], phi[None, :])
            image = basis.SphericalHarmonics(self._data["lmax"]).eval(dirs) \
                @ self._data["coeffs"]
            return Environment.latlong(image).radiance(brdf, v)
        d, w = self._data["dirs"], self._data["weights"]
        up = d[:, 2] > 0
        d, w = d[up], w[up] * d[up, 2:3]
        out = None
        step = max(1, (1 << 20) // max(v.shape[0], 1))  # ~1M pairs per evaluation
        for s in range(0, d.shape[0], step):
            wi = np.broadcast_to(d[s:s + step, None, :], (min(step, d.shape[0] - s),
                                                           v.shape[0], 3))
            wo = np.broadcast_to(v[None, :, :], wi.shape)
            f = np.asarray(brdf.eval(wi, wo), dtype=np.float64)
            if f.ndim == 2:
                f = f[..., None]
            c = max(w.shape[1], f.shape[2])
            part = np.einsum("lvc,lc->vc", np.broadcast_to(f, (*f.shape[:2], c)),
                             np.broadcast_to(w[s:s + step], (wi.shape[0], c)))
            out = part if out is None else out + part
        if out is None:
            return np.zeros((v.shape[0], w.shape[1]))
        return out

    def __repr__(self) -> str:
        if self.form == "sh":
            return f"Environment.sh(lmax={self._data['lmax']})"
        return f"Environment.{self.form}({self._data['dirs'].shape[0]} directions)"


# -- scenes --------------------------------------------------------------------------------
@dataclass
class ScenePlan:
    """What a scene needs of a representation (result of :func:`for_scene`).

    Attributes
    ----------
    order : int
        Smallest symmetric truncation whose radiance error is <= tol.
    rank : int
        Smallest number of eigen-terms per channel (:func:`compress.lowrank`) at ``order``
        within tol (the number of all terms when the truncation is already minimal).
    error : float
        Radiance error of ``matrix`` (relative RMS over the views, max over channels).
    matrix : basis.CoefficientMatrix
        The reduced representation (low rank when that stores fewer numbers).
    light_bandwidth : int
        Highest degree of the basis at which the light's coefficients exceed 1e-12 of their
        largest (the cm's order if the light reaches it).
    incident_errors, order_errors : list of float
        Radiance error per order 0..cm.order with only the incident side truncated, and with
        symmetric truncation. ``incident_errors`` is at rounding level from
        ``light_bandwidth`` on (the band-limit fact).
    bytes_full, bytes, bytes_saved : int
        Stored float64 bytes (unique coefficients, or low-rank factors).
    eval_ns_full, eval_ns, eval_ns_saved : float
        Evaluation time per BRDF sample (fast evaluator, best of three).
    radiance_full, radiance : (views, channels) ndarray
        L_o at the views from the full representation and from ``matrix``.
    """

    order: int
    rank: int
    error: float
    matrix: CoefficientMatrix
    light_bandwidth: int
    incident_errors: list[float]
    order_errors: list[float]
    bytes_full: int
    bytes: int
    bytes_saved: int
    eval_ns_full: float
    eval_ns: float
    eval_ns_saved: float
    radiance_full: NDArray[np.float64]
    radiance: NDArray[np.float64]


def for_scene(cm: CoefficientMatrix, *, lights: Environment | ArrayLike,
              views: ArrayLike, tol: float, light_weights: ArrayLike | None = None,
              view_weights: ArrayLike | None = None, min_cos: float = 1e-3,
              time_eval: bool = True) -> ScenePlan:
    """Find the smallest truncation (and rank) of ``cm`` that a scene needs.

    Model no more than a scene needs: the smallest truncation (and rank) of ``cm`` whose
    rendered radiance stays within ``tol`` of the full representation's.

    Parameters
    ----------
    cm : basis.CoefficientMatrix
    lights : Environment or (n, 3) array_like
        An :class:`Environment`, or light directions (then ``light_weights`` are their
        irradiances, default 1).
    views : (m, 3) array_like
        View directions (upper hemisphere).
    tol : float
        Bound on the relative RMS radiance error over the views (weighted by
        ``view_weights``, default equal), max over channels.
    light_weights, view_weights : array_like, optional
    min_cos : float
        Views closer to the horizon are evaluated at this elevation (quantity "f_cos").
    time_eval : bool
        Measure evaluation times (NaN otherwise).

    Returns
    -------
    ScenePlan

    Examples
    --------
    A uniform sky has Zernike bandwidth 0 (the constant is K_0^0): the light sees nothing of
    the BRDF above order 0 on the incident side.

    >>> import numpy as np, basis
    >>> from project import project
    >>> from project.models import Phong
    >>> cm = project(Phong(0.3, 0.5, 8.0), basis.HemiZernike(8), quantity="f_cos")
    >>> sky = Environment.sh(np.array([1.0]))
    >>> views = basis.from_angles(np.radians([0.0, 30.0, 60.0]), 0.0)
    >>> plan = for_scene(cm, lights=sky, views=views, tol=1e-3, time_eval=False)
    >>> plan.light_bandwidth, plan.incident_errors[0] < 1e-13
    (0, True)
    """
    if not isinstance(cm, CoefficientMatrix):
        raise TypeError(f"cm must be a basis.CoefficientMatrix, got {type(cm).__name__}")
    if not (isinstance(tol, int | float) and tol > 0):
        raise ValueError(f"tol must be a positive number, got {tol!r}")
    if not isinstance(lights, Environment):
        lights = Environment.directional(lights, light_weights)
    elif light_weights is not None:
        raise ValueError("light_weights applies to lights given as directions, not to an "
                         "Environment")
    v = as_directions(views, "views").reshape(-1, 3)
    if v.shape[0] == 0:
        raise ValueError("views must hold at least one direction")
    if np.any(v[:, 2] < 0):
        raise ValueError(f"views must lie in the upper hemisphere, min z = {v[:, 2].min():.3g}")
    vw = np.ones(v.shape[0]) if view_weights is None else np.asarray(view_weights, float)
    if vw.shape != (v.shape[0],) or np.any(vw < 0) or not np.any(vw > 0):
        raise ValueError(f"view_weights must be ({v.shape[0]},) non-negative, not all zero, got "
                         f"shape {vw.shape}")
    b = cm.basis
    ell = lights.coefficients(b, cm.quantity)  # (size, lc)
    mat = cm.matrix.reshape(cm.channels, b.size, b.size)
    vz = np.maximum(v[:, 2], min_cos) if cm.quantity == "f_cos" else np.ones(v.shape[0])
    bv = b.eval(lift_to(v, min_cos) if cm.quantity == "f_cos" else v)  # (m, size)
    deg = b.degree

    def radiance(m: NDArray, s_in: int, s_out: int) -> NDArray:
        # (m, channels): b(v)[:s_out] M[:s_out, :s_in] l[:s_in] / c(v)
        x = np.einsum("cjk,kl->jcl", m[:, :s_out, :s_in], ell[:s_in])
        r = np.einsum("vj,jcl->vcl", bv[:, :s_out], x) / vz[:, None, None]
        return r.reshape(v.shape[0], -1)

    full = radiance(mat, b.size, b.size)
    den = np.sum(vw[:, None] * full**2, axis=0)

    def err(r: NDArray) -> float:
        num = np.sum(vw[:, None] * (r - full) ** 2, axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            e = np.where(den > 0, np.sqrt(num / np.where(den > 0, den, 1.0)), np.sqrt(num))
        return float(np.max(e))

    sizes = [int(np.sum(deg <= n)) for n in range(cm.order + 1)]
    incident = [err(radiance(mat, s, b.size)) for s in sizes]
    symmetric = [err(radiance(mat, s, s)) for s in sizes]
    mag = np.max(np.abs(ell), axis=1)
    big = np.flatnonzero(mag > 1e-12 * (mag.max() if mag.size and mag.max() > 0 else 1.0))
    bandwidth = int(deg[big].max()) if big.size else 0
    order = next(n for n, e in enumerate(symmetric) if e <= tol or n == cm.order)
    if b.size and sizes[order] == 0:  # odd harmonics at order 0 hold nothing
        order = 1
    reduced = truncate(cm, order)
    chosen, error = reduced, symmetric[order]
    chosen_radiance = radiance(mat, sizes[order], sizes[order])
    n_terms = sum(blk.shape[-1] for blk in reduced.stored)
    rank = n_terms
    for r in range(1, n_terms):
        lr = lowrank(reduced, r)
        sub = lr.matrix.reshape(cm.channels, sizes[order], sizes[order])
        rad = radiance(_pad(sub, b.size), b.size, b.size)
        e = err(rad)
        if e <= tol:
            rank = r
            if 8 * lr.info["lowrank"]["numbers"] < 8 * unique_coefficients(reduced):
                chosen, error, chosen_radiance = lr, e, rad
            break
    bytes_full = 8 * unique_coefficients(cm)
    nbytes = (8 * chosen.info["lowrank"]["numbers"] if "lowrank" in chosen.info
              and chosen is not reduced else 8 * unique_coefficients(chosen))
    if time_eval:
        t_full, t_red = eval_ns(cm), eval_ns(chosen)
    else:
        t_full = t_red = float("nan")
    return ScenePlan(order=order, rank=rank, error=error, matrix=chosen,
                     light_bandwidth=bandwidth, incident_errors=incident,
                     order_errors=symmetric, bytes_full=bytes_full, bytes=nbytes,
                     bytes_saved=bytes_full - nbytes, eval_ns_full=t_full, eval_ns=t_red,
                     eval_ns_saved=t_full - t_red, radiance_full=full,
                     radiance=chosen_radiance)


def _pad(sub: NDArray, size: int) -> NDArray:
    out = np.zeros((sub.shape[0], size, size))
    out[:, :sub.shape[1], :sub.shape[2]] = sub
    return out

