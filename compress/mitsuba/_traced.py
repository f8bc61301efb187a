"""The representations in Dr.Jit operations: what the plugin traces into Mitsuba's kernels.

:func:`traced_eval` turns a representation into a function of two Mitsuba direction arrays
written only with Dr.Jit operations (arithmetic, ``dr.select``, ``dr.gather`` from arrays
made once at load time). Mitsuba traces such a function symbolically into the kernel of
its path tracer, like its own C++ plugins: no numpy, no wavefront, no copy to the host.
Numbers that are the same for every pair (a coefficient matrix, a Tucker core, a microfacet
model's parameters) enter the kernel as literal constants; tables enter as device arrays
read with ``dr.gather``. The arithmetic is Mitsuba's precision (float32 in the ``*_rgb``
variants); the numpy evaluation of each representation is the reference the tests compare
with.

The forms (each the formula of the representation's own ``eval``, operation for operation
where it matters):

- :class:`basis.CoefficientMatrix`, isotropic, any basis, reciprocal or not: the separable
  Chebyshev form of :mod:`basis.evaluate` (per azimuthal order m a small block on the
  Chebyshev values of both directions, times Re[(a_i conj a_o)^m]); anisotropic (dense)
  ones: every basis function from its radial factor in Chebyshev form, then b_i^T M b_o;
- fitted models: "lambert+ggx", "lambert+beckmann", "lafortune", "dsbrdf", "rr8807"
  (its Smith G1, a spline of a quadrature, tabulated from the model at load time),
  "factored", "tucker", "tabulated";
- :class:`compress.Hybrid`: its lobe plus its residual matrix, when both have a form here.

- the analytic models ``Lambert``, ``Minnaert``, ``Phong``, ``BlinnPhong``, ``OrenNayar``
  (qualitative form) and ``CookTorrance`` (separable Smith G, F = 1 or the exact Fresnel
  reflectance) of :mod:`project.models`;
- MERL tables (:func:`project.measured.read_merl`), trilinear or nearest, read from a
  device copy of their filled lookup table (17.5 MB in float32).

Anything else (RGL and other measured data read by :mod:`project.measured`, the other
analytic models, any object with ``eval``) returns ``None``: the plugin then evaluates
it with numpy in Dr.Jit's evaluated mode (:func:`compress.mitsuba.render`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from basis import CoefficientMatrix
from project.measured.mbsdf import MBSDFBRDF

from ._traced_matrix import Traced, matrix_form

__all__ = ["FORMS", "traced_eval"]

#: What :func:`traced_eval` covers: "matrix" (isotropic coefficient matrices) and the fitted
#: families; a hybrid is covered when its lobe and residual are.
FORMS = ("matrix", "lambert+ggx", "lambert+beckmann", "lafortune", "dsbrdf", "rr8807",
         "factored", "tucker", "tabulated", "hybrid")
_HALF_PI = 0.5 * math.pi
_INV_PI = 1.0 / math.pi
_SQRT_PI = math.sqrt(math.pi)


def traced_eval(rep: Any) -> Traced | None:
    """Return the Dr.Jit form of a representation's ``eval``, or None when it has none.

    Parameters
    ----------
    rep : BRDF
        A coefficient matrix, fitted model, factored lobe, Tucker or tabulated model, or
        hybrid.

    Returns
    -------
    callable or None
        ``f(wi, wo)`` with ``mi.Vector3f`` unit directions (w_i towards the light, w_o
        towards the viewer, both above the horizon) returning a list of ``mi.Float``, one
        per channel: the BRDF values (1/sr), not clamped. Must be called with a JIT
        variant set (the one the arrays were made for).
    """
    if isinstance(rep, CoefficientMatrix):
        return matrix_form(rep)
    if hasattr(rep, "lobe") and hasattr(rep, "residual"):
        lobe, res = traced_eval(rep.lobe), traced_eval(rep.residual)
        if lobe is None or res is None:
            return None
        return _sum(lobe, res)
    model = _analytic(rep)
    if model is not None:
        return model
    if hasattr(rep, "lookup_table") and hasattr(rep, "interpolation"):
        return _merl(rep)
    if isinstance(rep, MBSDFBRDF):
        return _mbsdf(rep.table)
    family = getattr(rep, "family", None)
    params = getattr(rep, "params", None)
    if not isinstance(family, str) or params is None:
        return None
    make = _FAMILIES.get(family)
    return None if make is None else make(params)


def _sum(a: Traced, b: Traced) -> Traced:
    def f(wi: Any, wo: Any) -> list:
        x, y = a(wi, wo), b(wi, wo)
        if len(x) < len(y):
            x = x * len(y)
        elif len(y) < len(x):
            y = y * len(x)
        return [u + v for u, v in zip(x, y, strict=True)]
    return f


def _floats(a: Any) -> list[float]:
    return [float(v) for v in np.asarray(a, dtype=np.float64).reshape(-1)]


def _device(a: Any) -> Any:
    """Return a device array (float32 in the rgb variants) to read with ``dr.gather``."""
    return mi.Float(np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1)))


def _gather(table: Any, index: Any) -> Any:
    return dr.gather(mi.Float, table, index)


# -- MERL tables ----------------------------------------------------------------------------

def _merl(rep: Any) -> Traced:
    """Return the lookup of a MERL table (project.measured.MERLBRDF), trilinear or nearest."""
    t = np.asarray(rep.lookup_table, dtype=np.float64)
    nh, nd, npd, nch = t.shape
    data = _device(t)
    trilinear = rep.interpolation == "trilinear"

    def f(wi: Any, wo: Any) -> list:
        theta_h, theta_d, phi_d = _half_difference(wi, wo, True)
        u = dr.sqrt(theta_h * (1.0 / _HALF_PI)) * nh
        v = theta_d * (nd / _HALF_PI)
        w = phi_d * (npd / math.pi)
        if not trilinear:
            i = mi.UInt32(dr.minimum(dr.floor(u + 0.5), nh - 1.0))
            j = mi.UInt32(dr.minimum(dr.floor(v + 0.5), nd - 1.0))
            k = mi.UInt32(dr.floor(w + 0.5)) % npd
            base = ((i * nd + j) * npd + k) * nch
            return [_gather(data, base + c) for c in range(nch)]
        i0f = dr.minimum(dr.floor(u), nh - 2.0)
        tu = dr.minimum(u - i0f, 1.0)
        j0f = dr.minimum(dr.floor(v), nd - 2.0)
        tv = dr.minimum(v - j0f, 1.0)
        k0f = dr.floor(w)
        tw = w - k0f
        i0, j0 = mi.UInt32(i0f), mi.UInt32(j0f)
        k0 = mi.UInt32(k0f) % npd
        k1 = dr.select(k0 + 1 >= npd, 0, k0 + 1)
        return _trilinear(data, (i0 * nd + j0) * (npd * nch), nd, npd, nch, k0, k1,
                          (tu, tv, tw))
    return f


def _trilinear(data: Any, base: Any, nd: int, m: int, nch: int, k0: Any, k1: Any,
               t: tuple[Any, Any, Any]) -> list:
    """Interpolate a (n, nd, m, nch) device table in its cell at ``base`` (row i0, j0).

    ``k0``, ``k1`` are the two columns of the last axis (periodic neighbours), ``t`` the
    fractions along the three axes; returns one value per channel.
    """
    tu, tv, tw = t
    out = []
    for c in range(nch):
        def at(di: int, dj: int, k: Any, c: int = c) -> Any:
            return _gather(data, base + ((di * nd + dj) * m * nch + c) + k * nch)
        lo = dr.lerp(dr.lerp(at(0, 0, k0), at(0, 0, k1), tw),
                     dr.lerp(at(0, 1, k0), at(0, 1, k1), tw), tv)
        hi = dr.lerp(dr.lerp(at(1, 0, k0), at(1, 0, k1), tw),
                     dr.lerp(at(1, 1, k0), at(1, 1, k1), tw), tv)
        out.append(dr.lerp(lo, hi, tu))
    return out


# -- NVIDIA MDL measured BSDF grids ---------------------------------------------------------

def _mbsdf(table: Any) -> Traced:
    """Return the lookup of an MDL grid (project.measured.MBSDFBRDF, family "grid").

    The MDL SDK's filtering, as ``project.measured.mbsdf`` evaluates it: linear between texel
    centres over (delta_phi / pi, 2 theta_out / pi, 2 theta_in / pi), clamped at the edges;
    negative values (measurement noise) evaluate to 0.
    """
    t = np.asarray(table, dtype=np.float64)
    nt, nphi, nch = t.shape[0], t.shape[2], t.shape[3]
    data = _device(t)

    def cell(x: Any, n: int) -> tuple[Any, Any, Any]:
        fx = dr.floor(x)
        i0 = mi.UInt32(dr.minimum(dr.maximum(fx, 0.0), n - 1.0))
        i1 = mi.UInt32(dr.minimum(dr.maximum(fx + 1.0, 0.0), n - 1.0))
        return i0, i1, x - fx

    def f(wi: Any, wo: Any) -> list:
        theta_in = dr.atan2(dr.sqrt(wi.x * wi.x + wi.y * wi.y), wi.z)
        theta_out = dr.atan2(dr.sqrt(wo.x * wo.x + wo.y * wo.y), wo.z)
        dphi = dr.abs(dr.atan2(wo.y, wo.x) - dr.atan2(wi.y, wi.x))
        dphi = dr.select(dphi > math.pi, 2.0 * math.pi - dphi, dphi)
        k0, k1, tx = cell(dr.minimum(dphi * (1.0 / math.pi), 1.0) * nphi - 0.5, nphi)
        j0, j1, ty = cell(dr.minimum(theta_out * (1.0 / _HALF_PI), 1.0) * nt - 0.5, nt)
        i0, i1, tz = cell(dr.minimum(theta_in * (1.0 / _HALF_PI), 1.0) * nt - 0.5, nt)
        out = []
        for c in range(nch):
            def at(i: Any, j: Any, k: Any, c: int = c) -> Any:
                return _gather(data, ((i * nt + j) * nphi + k) * nch + c)
            lo = dr.lerp(dr.lerp(at(i0, j0, k0), at(i0, j0, k1), tx),
                         dr.lerp(at(i0, j1, k0), at(i0, j1, k1), tx), ty)
            hi = dr.lerp(dr.lerp(at(i1, j0, k0), at(i1, j0, k1), tx),
                         dr.lerp(at(i1, j1, k0), at(i1, j1, k1), tx), ty)
            out.append(dr.maximum(dr.lerp(lo, hi, tz), 0.0))
        return out
    return f


# -- analytic models of project.models ---------------------------------------------------

def _analytic(rep: Any) -> Traced | None:
    """Return the form of an analytic model of project.models, or None.

    Lambert, Minnaert, Phong, Blinn-Phong, Oren-Nayar (qualitative) and CookTorrance with the
    separable Smith G (F = 1 or exact Fresnel).
    """
    from project import models
    if not isinstance(rep, models.Lambert | models.Minnaert | models.Phong |
                      models.BlinnPhong | models.OrenNayar | models.CookTorrance):
        return None
    nch = rep.channels
    p = {k: _floats(np.broadcast_to(v, (nch,))) for k, v in rep.arrays.items()}
    if isinstance(rep, models.Lambert):
        return lambda wi, wo: [mi.Float(a * _INV_PI) for a in p["albedo"]]
    if isinstance(rep, models.Minnaert):
        def minnaert(wi: Any, wo: Any) -> list:
            x = dr.clip(wi.z, 0.0, 1.0) * dr.clip(wo.z, 0.0, 1.0)
            return [mi.Float(a * (k + 1.0) / (2.0 * math.pi)) if k == 1.0 else
                    a * (k + 1.0) / (2.0 * math.pi)
                    * dr.select(x > 0.0, dr.power(dr.maximum(x, 1e-30), k - 1.0), 0.0)
                    for a, k in zip(p["albedo"], p["k"], strict=True)]
        return minnaert
    if isinstance(rep, models.Phong | models.BlinnPhong):
        blinn = isinstance(rep, models.BlinnPhong)

        def phong(wi: Any, wo: Any) -> list:
            if blinn:
                h = wi + wo
                norm = dr.norm(h)
                base = dr.clip(dr.select(norm > 0.0, h.z / dr.select(norm > 0.0, norm, 1.0),
                                         1.0), 0.0, 1.0)
            else:
                base = wi.z * wo.z - wi.x * wo.x - wi.y * wo.y
            out = []
            for kd, ks, n in zip(p["kd"], p["ks"], p["n"], strict=True):
                scale = (n + 1.0) / (8.0 * math.pi) if blinn else (n + 2.0) / (2.0 * math.pi)
                lobe = dr.select(base > 0.0, dr.power(dr.maximum(base, 1e-30), n),
                                 1.0 if (blinn and n == 0.0) else 0.0)
                out.append(kd * _INV_PI + ks * scale * lobe)
            return out
        return phong
    if isinstance(rep, models.OrenNayar):
        if rep.form != "qualitative":
            return None

        def oren_nayar(wi: Any, wo: Any) -> list:
            dot = wi.x * wo.x + wi.y * wo.y
            cmax = dr.maximum(dr.clip(wi.z, 0.0, 1.0), dr.clip(wo.z, 0.0, 1.0))
            t = dr.select(cmax > 1e-300, dr.maximum(dot, 0.0) / dr.select(cmax > 0.0, cmax,
                                                                          1.0), 0.0)
            out = []
            for rho, sigma in zip(p["albedo"], p["sigma"], strict=True):
                s2 = sigma * sigma
                a = 1.0 - 0.5 * s2 / (s2 + 0.33)
                b = 0.45 * s2 / (s2 + 0.09)
                out.append(rho * _INV_PI * (a + b * t))
            return out
        return oren_nayar
    if rep.shadowing != "separable":
        return None
    kd, rough = p["kd"], p["roughness"]
    lobes = {r: _microfacet_lobe(r, rep.distribution == "beckmann") for r in set(rough)}
    ior, ext = p.get("ior"), p.get("k")

    def f(wi: Any, wo: Any) -> list:
        spec = {r: lobe(wi, wo)[0] for r, lobe in lobes.items()}
        cd = dr.clip(0.5 * dr.norm(wi + wo), 0.0, 1.0)
        out = []
        for c in range(nch):
            s = spec[rough[c]]
            if ior is not None:
                s = s * _fresnel(cd, ior[c], ext[c])
            out.append(kd[c] * _INV_PI + s)
        return out
    return f


def _fresnel(u: Any, n: float, k: float) -> Any:
    """Unpolarised Fresnel reflectance of n + i k at cos = u (project.models.fresnel)."""
    s2 = (1.0 - u) * (1.0 + u)
    t = n * n - k * k - s2
    nk2 = (n * k) ** 2
    r = dr.sqrt(t * t + 4.0 * nk2)
    pos = t >= 0.0
    big = dr.select(pos, r + t, r - t) * 0.5
    small = dr.select(big > 0.0, nk2 / dr.select(big > 0.0, big, 1.0), 0.0)
    a2 = dr.select(pos, big, small)
    b2 = dr.select(pos, small, big)
    a = dr.sqrt(a2)
    den_s = dr.square(a + u) + b2
    rs = dr.select(den_s > 0.0, (dr.square(a - u) + b2) / dr.select(den_s > 0.0, den_s, 1.0),
                   0.0)
    au = a * u
    bu2 = b2 * u * u
    den_p = dr.square(au + s2) + bu2
    rp = rs * dr.select(den_p > 0.0, (dr.square(au - s2) + bu2)
                        / dr.select(den_p > 0.0, den_p, 1.0), 1.0)
    return dr.clip(0.5 * (rs + rp), 0.0, 1.0)


# -- half/difference angles --------------------------------------------------------------

def _half_difference(wi: Any, wo: Any, fold: bool) -> tuple[Any, Any, Any]:
    """theta_h, theta_d, phi_d (atan2: (-pi, pi], or [0, pi] with ``fold``) of unit pairs.

    The arithmetic of ``project._halfdiff.half_difference`` (from h = w_i + w_o and
    w_i - w_o, so exchanging w_i and w_o keeps theta_h, theta_d and adds pi to phi_d).
    """
    hx, hy, hz = wi.x + wo.x, wi.y + wo.y, wi.z + wo.z
    dx, dy, dz = wi.x - wo.x, wi.y - wo.y, wi.z - wo.z
    r = dr.sqrt(dr.fma(hx, hx, hy * hy))
    hn = dr.sqrt(dr.fma(r, r, hz * hz))
    pos = hn > 0.0
    inv = dr.rcp(dr.select(pos, hn, 1.0))
    theta_h = dr.select(pos, dr.atan2(r, hz), 0.0)
    ct = dr.select(pos, hz * inv, 1.0)
    st = dr.select(pos, r * inv, 0.0)
    rp = r > 0.0
    invr = dr.rcp(dr.select(rp, r, 1.0))
    cp = dr.select(rp, hx * invr, 1.0)
    sp = dr.select(rp, hy * invr, 0.0)
    theta_d = dr.atan2(dr.sqrt(dx * dx + dy * dy + dz * dz), hn)
    a = ct * (cp * dx + sp * dy) - st * dz
    b = cp * dy - sp * dx
    if fold:
        flip = (b < 0.0) | ((b == 0.0) & (a < 0.0))
        a = dr.select(flip, -a, a)
        b = dr.select(flip, -b, b)
    return theta_h, theta_d, dr.atan2(b, a)


def _power_root(x: Any, p: float) -> Any:
    """X ** (1 / p) for the warp exponents 1, 2, 3 (x >= 0)."""
    if p == 1.0:
        return x
    if p == 2.0:
        return dr.sqrt(x)
    if p == 3.0:
        return dr.cbrt(x)
    return dr.power(x, 1.0 / p)


def _unwarp(theta: Any, p: float, top: bool) -> Any:
    x = dr.clip(theta * (1.0 / _HALF_PI), 0.0, 1.0)
    return 1.0 - _power_root(1.0 - x, p) if top else _power_root(x, p)


# -- fitted microfacet models -------------------------------------------------------------

def _microfacet(beckmann: bool) -> Callable[[dict], Traced]:
    def make(params: dict) -> Traced:
        kd = _floats(params["kd"])
        ks = _floats(params["ks"])
        alpha = float(params["alpha"])
        f0 = float(params["f0"])
        lobe = _microfacet_lobe(alpha, beckmann)

        def f(wi: Any, wo: Any) -> list:
            s, x5 = lobe(wi, wo)
            frs = (f0 + (1.0 - f0) * x5) * s
            return [dr.fma(k, frs, d * _INV_PI) for d, k in zip(kd, ks, strict=True)]
        return f
    return make


def _smith(c: Any, rs: Any, beckmann: bool) -> Any:
    """C Lambda(c) of Smith's masking for rs = alpha sin theta (project.fitting.microfacet)."""
    if not beckmann:
        return rs * rs / (2.0 * (c + dr.sqrt(dr.fma(c, c, rs * rs))))
    pos = rs > 0.0
    a = c / dr.select(pos, rs, 1.0)
    e = dr.exp(-a * a)
    v = dr.maximum(0.5 * (rs * e * (1.0 / _SQRT_PI) - c * (1.0 - dr.erf(a))), 0.0)
    return dr.select(pos, v, 0.0)


def _microfacet_lobe(alpha: float, beckmann: bool) -> Callable[[Any, Any], tuple[Any, Any]]:
    """D G / (4 c_i c_o) (separable Smith G, F = 1) and (1 - c_d)^5 of unit pairs."""
    a2 = alpha * alpha

    def lobe(wi: Any, wo: Any) -> tuple[Any, Any]:
        ci = dr.clip(wi.z, 0.0, 1.0)
        co = dr.clip(wo.z, 0.0, 1.0)
        h = wi + wo
        norm = dr.norm(h)
        pos = norm > 0.0
        h = dr.select(pos, h * dr.rcp(dr.select(pos, norm, 1.0)), mi.Vector3f(0.0, 0.0, 1.0))
        t = 1.0 - dr.clip(0.5 * norm, 0.0, 1.0)
        t2 = t * t
        x5 = t2 * t2 * t
        hz2 = h.z * h.z
        hxy2 = dr.fma(h.x, h.x, h.y * h.y)
        if beckmann:
            y = dr.select(hz2 > 0.0, hxy2 / dr.select(hz2 > 0.0, hz2, 1.0), 1e30)
            y = dr.minimum(y, 1e30)
            e = y * (1.0 / a2)
            dist = dr.select(e < 80.0, dr.square(1.0 + dr.minimum(y, 1e15))
                             * dr.exp(-e) * (1.0 / (math.pi * a2)), 0.0)
        else:
            den = dr.fma(a2, hz2, hxy2)
            dist = a2 * (1.0 / math.pi) / (den * den)
        si = dr.sqrt(dr.maximum((1.0 - ci) * (1.0 + ci), 0.0))
        so = dr.sqrt(dr.maximum((1.0 - co) * (1.0 + co), 0.0))
        li = _smith(ci, alpha * si, beckmann)
        lo = _smith(co, alpha * so, beckmann)
        return dist / ((ci + li) * (co + lo)) * 0.25, x5
    return lobe


# -- Lafortune ---------------------------------------------------------------------------------

def _lafortune(params: dict) -> Traced:
    kd = _floats(params["kd"])
    rho = np.asarray(params["rho"], dtype=np.float64)
    cx = _floats(params["cx"])
    cz = _floats(params["cz"])
    n = _floats(params["n"])

    def f(wi: Any, wo: Any) -> list:
        u = wi.x * wo.x + wi.y * wo.y
        v = wi.z * wo.z
        out = [mi.Float(d * _INV_PI) for d in kd]
        for j in range(len(n)):
            b = cz[j] * v + cx[j] * u
            val = dr.select(b > 0.0, dr.power(dr.maximum(b, 1e-30), n[j]), 0.0) \
                * ((n[j] + 2.0) / (2.0 * math.pi))
            out = [dr.fma(float(rho[j, c]), val, out[c]) for c in range(len(kd))]
        return out
    return f


# -- the directional-statistics BRDF ---------------------------------------------------------

def _bspline_basis(x: Any, knots: list[float], degree: int) -> list[Any]:
    """B-spline basis functions (Cox-de Boor) at x on literal knots, the last span closed."""
    n = len(knots) - 1
    last = max(i for i in range(n) if knots[i] < knots[i + 1])
    b = []
    for i in range(n):
        if knots[i] < knots[i + 1]:
            inside = (x >= knots[i]) & ((x < knots[i + 1]) if i < last else (x <= knots[i + 1]))
            b.append(dr.select(inside, 1.0, 0.0))
        else:
            b.append(mi.Float(0.0))
    for k in range(1, degree + 1):
        nxt = []
        for i in range(n - k):
            v = mi.Float(0.0)
            d1 = knots[i + k] - knots[i]
            d2 = knots[i + k + 1] - knots[i + 1]
            if d1 > 0.0:
                v = (x - knots[i]) * (1.0 / d1) * b[i]
            if d2 > 0.0:
                v = v + (knots[i + k + 1] - x) * (1.0 / d2) * b[i + 1]
            nxt.append(v)
        b = nxt
    return b


def _dsbrdf(params: dict) -> Traced:
    from project.fitting.dsbrdf import DS_KNOTS
    kappa = np.asarray(params["kappa"], dtype=np.float64)  # (K, 6, C)
    gamma = np.asarray(params["gamma"], dtype=np.float64)
    knots = [float(v) for v in DS_KNOTS]
    lobes, ncoef, nch = kappa.shape

    def f(wi: Any, wo: Any) -> list:
        h = wi + wo
        norm = dr.norm(h)
        ch = dr.clip(h.z * dr.rcp(dr.select(norm > 0.0, norm, 1.0)), 0.0, 1.0)
        ch = dr.select(norm > 0.0, ch, 0.0)
        # theta_d = arccos(c_d) by atan2 (arccos loses half the digits near c_d = 1)
        td = dr.clip(dr.atan2(dr.norm(wi - wo), norm), 0.0, _HALF_PI)
        basis_ = _bspline_basis(td, knots, 2)
        logt = dr.log(dr.select(ch > 0.0, ch, 1.0))
        out = []
        for c in range(nch):
            acc = mi.Float(0.0)
            for j in range(lobes):
                kap = sum(basis_[i] * float(kappa[j, i, c]) for i in range(ncoef))
                gam = sum(basis_[i] * float(gamma[j, i, c]) for i in range(ncoef))
                tg = dr.select(ch > 0.0, dr.exp(gam * logt), 0.0)
                acc = acc + (dr.exp(kap * tg) - 1.0)
            out.append(acc)
        return out
    return f


# -- reflection and diffraction (Holzschuch & Pacanowski) -------------------------------------

#: Nodes of the Smith G1 table of an "rr8807" model (theta = (pi/2) (1 - (1 - s)^2), s
#: uniform: the "grazing" spacing of the factored tables). Linear interpolation keeps f
#: within 1e-5 relative of the model's spline (20,000 random pairs, sigma 0.01-0.3, p 0.5-2)
#: except within 0.01 degree of the horizon at p = 0.5 (5e-4).
_G1_NODES = 4096


def _rr8807(params: dict) -> Traced:
    from project import FittedModel
    kd, ks, kw, f0 = (_floats(params[k]) for k in ("kd", "ks", "kw", "f0"))
    lam = _floats(params["wavelength"])
    sigma, p, a = (float(params[k]) for k in ("sigma", "p", "a"))
    # G1(theta) of the model's slope distribution (its Lambda is a spline of a quadrature):
    # read off the model itself, whose diffraction term at theta_h = 0 (w_o the mirror
    # image of w_i) is G1(theta)^2 / (E lambda^4) for kd = ks = 0, kw = 1
    s = np.arange(_G1_NODES) / (_G1_NODES - 1)
    theta = _HALF_PI * (1.0 - (1.0 - s) ** 2)  # dense at grazing, where G1 falls to 0
    w = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=1)
    mirror = w * np.array([-1.0, -1.0, 1.0])
    probe = FittedModel("rr8807", {"kd": [0.0], "ks": [0.0], "kw": [1.0], "f0": [0.5],
                                   "sigma": sigma, "p": p, "a": a, "wavelength": [lam[0]]})
    inv_e0 = (1.0 + 1.0 / (a * lam[0]) ** 2) / math.pi
    q = np.asarray(probe.eval(w, mirror), dtype=np.float64).reshape(-1) * lam[0] ** 4 / inv_e0
    g1 = _device(np.sqrt(np.clip(q, 0.0, None)))
    logb = math.log(p) - math.log(math.pi) - 2.0 * math.log(sigma) - math.lgamma(1.0 / p)
    inv_e = [(1.0 + 1.0 / (a * v) ** 2) / math.pi for v in lam]

    def smith(c: Any) -> Any:
        x = _unwarp(dr.safe_acos(c), 2.0, True) * (_G1_NODES - 1)
        i0f = dr.clip(dr.floor(x), 0.0, _G1_NODES - 2.0)
        t = dr.clip(x - i0f, 0.0, 1.0)
        i0 = mi.UInt32(i0f)
        return dr.lerp(_gather(g1, i0), _gather(g1, i0 + 1), t)

    def f(wi: Any, wo: Any) -> list:
        ci = dr.clip(wi.z, 0.0, 1.0)
        co = dr.clip(wo.z, 0.0, 1.0)
        h = wi + wo
        hn2 = dr.squared_norm(h)
        hn2 = dr.select(hn2 > 0.0, hn2, 1.0)
        ch = dr.clip(h.z * dr.rsqrt(hn2), 0.0, 1.0)
        sh2 = dr.clip(dr.fma(h.x, h.x, h.y * h.y) / hn2, 0.0, 1.0)
        cd = dr.clip(0.5 * dr.norm(wi + wo), 0.0, 1.0)
        up = (ci > 0.0) & (co > 0.0) & (ch > 0.0)
        gg = dr.select(up, smith(ci) * smith(co), 0.0)
        chs = dr.select(up, ch, 1.0)
        x = sh2 / (chs * chs) * (1.0 / (sigma * sigma))
        y = dr.power(x, p)
        d = dr.exp(logb - y) / dr.square(chs * chs)
        spec = dr.select(up, gg * d / (4.0 * dr.select(up, ci * co, 1.0)), 0.0)
        t = 1.0 - cd
        x5 = dr.square(dr.square(t)) * t
        zs = dr.square(2.0 * dr.sqrt(sh2) * cd)
        out = []
        for c in range(len(kd)):
            z = zs * (1.0 / (lam[c] * a) ** 2)
            diff = gg * (inv_e[c] / lam[c] ** 4) / dr.square(1.0 + z)
            fr = f0[c] + (1.0 - f0[c]) * x5
            out.append(kd[c] * _INV_PI + ks[c] * fr * spec + kw[c] * diff)
        return out
    return f


# -- the factored lobe ------------------------------------------------------------------------

class _Table1D:
    """Piecewise-linear tables (rank, nodes, channels) on equally spaced coordinates."""

    def __init__(self, table: Any) -> None:
        t = np.asarray(table, dtype=np.float64)
        if t.ndim == 2:
            t = t[:, :, None]
        self.rank, self.nodes, self.channels = t.shape
        self.data = _device(t)

    def at(self, s: Any) -> list[list[Any]]:
        """Values [k][c] at coordinates s in node units."""
        n = self.nodes
        i0f = dr.clip(dr.floor(s), 0.0, n - 2.0)
        t = dr.clip(s - i0f, 0.0, 1.0)
        i0 = mi.UInt32(i0f)
        out = []
        for k in range(self.rank):
            row = []
            for c in range(self.channels):
                base = i0 * self.channels + (k * n * self.channels + c)
                a = _gather(self.data, base)
                b = _gather(self.data, base + self.channels)
                row.append(dr.fma(t, b - a, a))
            out.append(row)
        return out


def _factored(params: dict) -> Traced:
    kd = _floats(params["kd"])
    a_t = _Table1D(params["h_table"])
    b_t = _Table1D(params["d_table"])
    p = float(params["warp"])
    pd = float(params["warp_d"])
    phi = params.get("phi_table")
    full = "phi_turn" in params and float(params["phi_turn"]) == 1.0
    period = 2.0 * math.pi if full else math.pi
    c_t = None if phi is None else np.asarray(phi, dtype=np.float64)
    c_dev = None if c_t is None else _device(c_t)
    w = params.get("weights")
    w = None if w is None else np.asarray(w, dtype=np.float64).reshape(a_t.rank, -1)
    nch = max(len(kd), a_t.channels, b_t.channels, 1 if w is None else w.shape[1])
    rank = a_t.rank

    def f(wi: Any, wo: Any) -> list:
        theta_h, theta_d, phi_d = _half_difference(wi, wo, not full)
        theta_h = dr.minimum(theta_h, _HALF_PI)
        theta_d = dr.minimum(theta_d, _HALF_PI)
        av = a_t.at(_unwarp(theta_h, p, False) * (a_t.nodes - 1))
        bv = b_t.at(_unwarp(theta_d, pd, True) * (b_t.nodes - 1))
        cv = None
        if c_t is not None:
            m = c_t.shape[1]
            phi_d = dr.select(phi_d < 0.0, phi_d + 2.0 * math.pi, phi_d)
            phi_d = dr.select(phi_d >= period, phi_d - period, phi_d)
            x = phi_d * (m / period)
            fl = dr.floor(x)
            u = dr.clip(x - fl, 0.0, 1.0)
            e0 = mi.UInt32(dr.clip(fl, 0.0, m - 1.0))
            e1 = dr.select(e0 + 1 >= m, 0, e0 + 1)
            cv = []
            for k in range(rank):
                c0 = _gather(c_dev, e0 + k * m)
                c1 = _gather(c_dev, e1 + k * m)
                cv.append(dr.fma(u, c1 - c0, c0))
        out = []
        for c in range(nch):
            acc = mi.Float(kd[c if len(kd) > 1 else 0] * _INV_PI)
            for k in range(rank):
                term = av[k][c if a_t.channels > 1 else 0] * bv[k][c if b_t.channels > 1 else 0]
                if cv is not None:
                    term = term * cv[k]
                if w is not None:
                    term = term * float(w[k, c if w.shape[1] > 1 else 0])
                acc = acc + term
            out.append(acc)
        return out
    return f


# -- the Tucker tensor ------------------------------------------------------------------------

class _Curve:
    """Factor rows (knots, rank) interpolated linearly between increasing knots."""

    def __init__(self, knots: Any, factor: Any, periodic: bool) -> None:
        self.k = [float(v) for v in np.asarray(knots, dtype=np.float64)]
        f = np.asarray(factor, dtype=np.float64)
        self.rank = f.shape[1]
        self.periodic = periodic
        self.knots = _device(self.k)
        self.data = _device(f)

    def at(self, s: Any) -> list[Any]:
        k, m, r = self.k, len(self.k), self.rank
        if not self.periodic:
            j = mi.UInt32(0)
            for v in k[1:m - 1]:  # the interval: interior knots <= s
                j = dr.select(s >= v, j + 1, j)
            k0 = _gather(self.knots, j)
            k1 = _gather(self.knots, j + 1)
            t = dr.clip((s - k0) / (k1 - k0), 0.0, 1.0)
            j0, j1 = j, j + 1
        else:
            cnt = mi.UInt32(0)
            for v in k:
                cnt = dr.select(s >= v, cnt + 1, cnt)
            wrap = (cnt == 0) | (cnt == m)
            j0 = dr.select(wrap, m - 1, cnt - 1)
            j1 = dr.select(wrap, 0, cnt)
            k0 = _gather(self.knots, j0)
            k1 = dr.select(wrap, k[0] + 1.0, _gather(self.knots, j1))
            ss = dr.select(wrap & (s < k[m - 1]), s + 1.0, s)
            t = (ss - k0) / (k1 - k0)
        out = []
        for a in range(r):
            f0 = _gather(self.data, j0 * r + a)
            f1 = _gather(self.data, j1 * r + a)
            out.append(dr.fma(t, f1 - f0, f0))
        return out


def _tucker(params: dict) -> Traced:
    h = _Curve(params["h_knots"], params["h_factor"], False)
    d = _Curve(params["d_knots"], params["d_factor"], False)
    ph = _Curve(params["phi_knots"], params["phi_factor"], True)
    core = np.asarray(params["core"], dtype=np.float64)
    color = np.asarray(params["color"], dtype=np.float64)
    pd = float(params["warp_d"])
    full = float(params["phi_turn"]) == 1.0
    period = 2.0 * math.pi if full else math.pi
    rh, rd, rp, rc = core.shape
    # the colour folded into the core: (r_h, r_d, r_phi, channels)
    g = np.einsum("abke,ce->abkc", core, color)
    nch = color.shape[0]

    def f(wi: Any, wo: Any) -> list:
        theta_h, theta_d, phi_d = _half_difference(wi, wo, not full)
        phi_d = dr.select(phi_d < 0.0, phi_d + 2.0 * math.pi, phi_d)
        hv = h.at(dr.sqrt(dr.minimum(theta_h * (1.0 / _HALF_PI), 1.0)))
        x = dr.minimum(theta_d * (1.0 / _HALF_PI), 1.0)
        dv = d.at(1.0 - _power_root(1.0 - x, pd))
        s = dr.minimum(phi_d * (1.0 / period), 1.0)
        pv = ph.at(dr.select(s >= 1.0, s - 1.0, s))
        cc = dr.maximum(wi.z, 0.0) * dr.maximum(wo.z, 0.0)
        acc = [[mi.Float(0.0) for _ in range(nch)] for _ in range(rp)]
        for a in range(rh):
            for b in range(rd):
                hd = hv[a] * dv[b]
                for k in range(rp):
                    for c in range(nch):
                        v = float(g[a, b, k, c])
                        if v != 0.0:
                            acc[k][c] = dr.fma(hd, v, acc[k][c])
        scale = dr.select(cc > 0.0, dr.rcp(dr.select(cc > 0.0, cc, 1.0)), 0.0)
        out = []
        for c in range(nch):
            v = acc[0][c] * pv[0]
            for k in range(1, rp):
                v = dr.fma(acc[k][c], pv[k], v)
            out.append(dr.maximum(v, 0.0) * scale)
        return out
    return f


# -- the trilinear table ----------------------------------------------------------------------

def _tabulated(params: dict) -> Traced:
    t = np.asarray(params["table"], dtype=np.float64)
    nh, nd, m, nch = t.shape
    data = _device(t)
    pd = float(params["warp_d"])
    full = float(params["phi_turn"]) == 1.0
    period = 2.0 * math.pi if full else math.pi
    divide = float(params["cosines"]) == 1.0

    def cell(x: Any, n: int) -> tuple[Any, Any]:
        i0f = dr.minimum(dr.floor(x), n - 2.0)
        return mi.UInt32(i0f), dr.minimum(x - i0f, 1.0)

    def f(wi: Any, wo: Any) -> list:
        theta_h, theta_d, phi_d = _half_difference(wi, wo, not full)
        phi_d = dr.select(phi_d < 0.0, phi_d + 2.0 * math.pi, phi_d)
        u = dr.sqrt(dr.minimum(theta_h * (1.0 / _HALF_PI), 1.0)) * (nh - 1)
        x = dr.minimum(theta_d * (1.0 / _HALF_PI), 1.0)
        v = (1.0 - _power_root(1.0 - x, pd)) * (nd - 1)
        w = phi_d * (m / period)
        i0, tu = cell(u, nh)
        j0, tv = cell(v, nd)
        k0f = dr.floor(w)
        tw = w - k0f
        k0 = mi.UInt32(k0f) % m
        k1 = dr.select(k0 + 1 >= m, 0, k0 + 1)
        values = _trilinear(data, (i0 * nd + j0) * (m * nch), nd, m, nch, k0, k1,
                            (tu, tv, tw))
        if not divide:
            return values
        cc = dr.maximum(wi.z, 0.0) * dr.maximum(wo.z, 0.0)
        scale = dr.select(cc > 0.0, dr.rcp(dr.select(cc > 0.0, cc, 1.0)), 0.0)
        return [v * scale for v in values]
    return f


_FAMILIES: dict[str, Callable[[dict], Traced]] = {
    "lambert+ggx": _microfacet(False),
    "lambert+beckmann": _microfacet(True),
    "lafortune": _lafortune,
    "dsbrdf": _dsbrdf,
    "rr8807": _rr8807,
    "factored": _factored,
    "tucker": _tucker,
    "tabulated": _tabulated,
    "grid": lambda params: _mbsdf(params["table"]),
}
