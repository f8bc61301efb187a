"""The "lambert+ggx" and "lambert+beckmann" families: a Lambertian term and a microfacet lobe.

Fitted by :func:`project.fitting.fit_model`; the fit itself (residuals, restarts, standard
errors) is described in :mod:`project.fitting.model`.

The model
---------
``"lambert+ggx"``, ``"lambert+beckmann"`` (2 C + 2 reals for C channels)
    f = kd/pi + ks F(w_i . h) D(h) G(w_i, w_o) / (4 cos theta_i cos theta_o), with D and the
    separable Smith G of :class:`project.models.CookTorrance` (``shadowing="separable"``,
    F = 1: the library's own microfacet model, which a kernel here evaluates with the same
    formulas, equal to rounding, together with its derivative in log alpha) and
    Schlick's Fresnel F(u) = F0 + (1 - F0)(1 - u)^5 (Schlick 1994, eq. 15). Parameters:
    ``kd`` (C,) in [0, 1], ``ks`` (C,) in [0, 5], ``alpha`` (GGX alpha or Beckmann RMS
    slope m, one for all channels) in [5e-4, 1.5], ``f0`` (one for all channels, an
    achromatic Fresnel as of a dielectric; the colour of the highlight is in ``ks``) in
    [0.02, 1]. ks F0 is the specular reflectance at normal incidence, ks the one at
    grazing; ks <= 1 conserves energy, larger values are allowed because measured data
    sometimes need them. Holzschuch & Pacanowski 2015 bound F0 to [0.02, 1.2] in their
    fits of MERL data; here F0 <= 1 keeps Schlick's F a reflectance.

References
----------
- J. Holzschuch and R. Pacanowski, "A physically accurate reflectance model combining
  reflection and diffraction", Inria Research Report RR-8807, 2015.
- C. Schlick, "An inexpensive BRDF model for physically-based rendering", Computer Graphics
  Forum 13(3), 1994, pp. 233-246.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from basis.jit import njit

from ._geometry import _Geometry
from ._solver import _sqrt_diag

# the family is used through fit_model and FittedModel: nothing public here
__all__: list[str] = []

_SQRT_PI = math.sqrt(math.pi)
#: tan^2 theta_h on the horizon (h_z = 0), as project.models caps it
_TAN2_CAP = 1e100
#: Lower bound of alpha: a clear coat seen through a detector of 0.1 degree reads as
#: alpha ~ 0.002 (half-angle widths are half the view's), so the bound leaves room below
#: the sharpest measured paints.
ALPHA_MIN = 5e-4
#: Columns of the per-pair geometry of the kernels (:func:`_pair_geometry`).
_GEO = 7


class _Microfacet:
    """x = [kd (C), ks (C), log alpha, f0].

    The lobe is :class:`project.models.CookTorrance` (F = 1, separable Smith G), evaluated
    here by a kernel that also gives its derivative in log alpha in closed form; the
    residuals and Jacobian of a fit come from one pass over the pairs (:meth:`residuals`).
    """

    def __init__(self, distribution: str, channels: int) -> None:
        self.distribution = distribution
        self.beckmann = distribution == "beckmann"
        self.c = channels
        self.p = 2 * channels + 2
        self.k = 1  # linear parameters besides kd, per channel
        lo = np.r_[np.zeros(2 * channels), np.log(ALPHA_MIN), 0.02]
        hi = np.r_[np.ones(channels), np.full(channels, 5.0), np.log(1.5), 1.0]
        self.bounds = (lo, hi)

    def lobe(self, alpha: float, g: _Geometry, deriv: bool = False):
        """D G / (4 c_i c_o) of the library's Cook-Torrance (F = 1, separable Smith G).

        With ``deriv`` also its derivative in log alpha.
        """
        s = np.empty(g.n)
        ds = np.empty(g.n if deriv else 0)
        _lobe_kernel(_geometry(g), float(alpha), self.beckmann, s, ds)
        return (s, ds) if deriv else s

    def value(self, x: NDArray, g: _Geometry, jac: bool = False):
        c = self.c
        if not jac:
            f = np.empty((g.n, c))
            _value_kernel(_geometry(g), np.ascontiguousarray(x, dtype=np.float64), c,
                          self.beckmann, f)
            return f
        kd, ks, la, f0 = x[:c], x[c:2 * c], x[2 * c], x[2 * c + 1]
        s, ds = self.lobe(float(np.exp(la)), g, deriv=True)
        x5 = _geometry(g)[:, 6]
        fr = f0 + (1.0 - f0) * x5
        f = kd / np.pi + ks * (fr * s)[:, None]
        df = np.zeros((g.n, c, self.p))
        idx = np.arange(c)
        df[:, idx, idx] = 1.0 / np.pi
        df[:, idx, c + idx] = (fr * s)[:, None]
        df[:, :, 2 * c] = ks * (fr * ds)[:, None]
        df[:, :, 2 * c + 1] = ks * (s * (1.0 - x5))[:, None]
        return f, df

    def residuals(self, x: NDArray, g: _Geometry, scale: NDArray, target: NDArray,
                  log: bool) -> tuple[NDArray, NDArray]:
        """Residuals (n C,) and Jacobian (n C, p) of a metric in one pass over the pairs.

        l2: scale (q_model - target) with q = f c_i c_o; log: scale (log1p(f c_i) - target);
        ``scale`` and ``target`` are (n, C) (the rows of :func:`project.fitting._solver.
        _objective`).
        """
        c = self.c
        r = np.empty(g.n * c)
        jac = np.empty((g.n * c, self.p))
        _residual_kernel(_geometry(g), np.ascontiguousarray(x, dtype=np.float64), c,
                         self.beckmann, scale, target, log, r, jac)
        return r, jac

    def columns(self, xnl: NDArray, g: _Geometry) -> NDArray:
        """Functions multiplying the linear parameters (kd, ks) at fixed (log alpha, f0)."""
        s = self.lobe(float(np.exp(xnl[0])), g)
        fr = xnl[1] + (1.0 - xnl[1]) * _geometry(g)[:, 6]
        return np.stack([np.full(g.n, 1.0 / np.pi), fr * s], axis=1)

    #: kd and ks enter linearly, two per channel: fitted by variable projection in l2
    projected = True

    def search_grid(self) -> NDArray:
        """(m, 2) points (log alpha, F0) of the global search: alpha over its whole range."""
        la = np.linspace(self.bounds[0][2 * self.c], self.bounds[1][2 * self.c], 49)
        f0 = np.array([0.02, 0.04, 0.08, 0.15, 0.3, 0.6, 1.0])
        return np.stack(np.meshgrid(la, f0, indexing="ij"), axis=-1).reshape(-1, 2)

    def nonlinear_grid(self) -> list[NDArray]:
        return [np.array([np.log(a), 0.1]) for a in (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.4)]

    def nonlinear_random(self, rng: np.random.Generator) -> NDArray:
        return np.array([rng.uniform(np.log(0.005), np.log(0.8)), rng.uniform(0.02, 1.0)])

    def params(self, x: NDArray) -> dict[str, NDArray]:
        c = self.c
        return {"kd": x[:c].copy(), "ks": x[c:2 * c].copy(), "alpha": np.array(np.exp(x[2 * c])),
                "f0": np.array(x[2 * c + 1])}

    def natural_stderr(self, x: NDArray, cov: NDArray) -> dict[str, NDArray]:
        c = self.c
        se = _sqrt_diag(cov)
        return {"kd": se[:c].copy(), "ks": se[c:2 * c].copy(),
                "alpha": np.array(np.exp(x[2 * c]) * se[2 * c]), "f0": np.array(se[2 * c + 1])}

    def vector(self, params: dict[str, NDArray]) -> NDArray:
        return np.r_[params["kd"], params["ks"], np.log(params["alpha"]), params["f0"]]


# -- kernels ----------------------------------------------------------------------------------

def _geometry(g: _Geometry) -> NDArray:
    """Per-pair geometry of the kernels, (n, 7), computed once per pair set (kept on ``g``).

    Columns: c_i, c_o, sin theta_i, sin theta_o, h_z^2, h_x^2 + h_y^2 (unit h), (1 - c_d)^5.
    """
    geo = getattr(g, "_microfacet", None)
    if geo is None:
        geo = np.empty((g.n, _GEO))
        _pair_geometry_kernel(np.ascontiguousarray(g.wi, dtype=np.float64),
                              np.ascontiguousarray(g.wo, dtype=np.float64), geo)
        g._microfacet = geo
    return geo


@njit
def _pair_geometry_kernel(wi, wo, geo):  # pragma: no cover - compiled
    # wi, wo (n, 3) -> geo (n, 7); the steps of CookTorrance._eval: directions renormalised,
    # cosines clipped to [0, 1], h = (0, 0, 1) and c_d = 0 where w_i = -w_o
    for p in range(wi.shape[0]):
        ni = math.sqrt(wi[p, 0] * wi[p, 0] + wi[p, 1] * wi[p, 1] + wi[p, 2] * wi[p, 2])
        no = math.sqrt(wo[p, 0] * wo[p, 0] + wo[p, 1] * wo[p, 1] + wo[p, 2] * wo[p, 2])
        ix, iy, iz = wi[p, 0] / ni, wi[p, 1] / ni, wi[p, 2] / ni
        ox, oy, oz = wo[p, 0] / no, wo[p, 1] / no, wo[p, 2] / no
        ci = min(max(iz, 0.0), 1.0)
        co = min(max(oz, 0.0), 1.0)
        hx, hy, hz = ix + ox, iy + oy, iz + oz
        norm = math.sqrt(hx * hx + hy * hy + hz * hz)
        if norm > 0.0:
            hx, hy, hz = hx / norm, hy / norm, hz / norm
        else:
            hx, hy, hz = 0.0, 0.0, 1.0
        t = 1.0 - min(max(0.5 * norm, 0.0), 1.0)
        geo[p, 0] = ci
        geo[p, 1] = co
        geo[p, 2] = math.sqrt(max((1.0 - ci) * (1.0 + ci), 0.0))
        geo[p, 3] = math.sqrt(max((1.0 - co) * (1.0 + co), 0.0))
        geo[p, 4] = hz * hz
        geo[p, 5] = hx * hx + hy * hy
        geo[p, 6] = t * t * t * t * t


@njit(inline="always")
def _smith(c, rs, beckmann):  # pragma: no cover - compiled
    """Return c Lambda(c) and its derivative in log alpha, for rs = alpha sin theta.

    GGX: c Lambda = (sqrt(c^2 + rs^2) - c) / 2, written rs^2 / (2 (c + sqrt(c^2 + rs^2)))
    (no cancellation), derivative rs^2 / (2 sqrt(c^2 + rs^2)). Beckmann: with a = c / rs,
    c Lambda = (rs exp(-a^2) / sqrt(pi) - c erfc(a)) / 2 (:func:`project.models.
    smith_lambda` times c), derivative rs exp(-a^2) / (2 sqrt(pi)) (d Lambda / da =
    -exp(-a^2) / (2 sqrt(pi) a^2), da / dlog alpha = -a); both 0 at normal incidence (rs = 0).
    """
    if not beckmann:
        root = math.sqrt(c * c + rs * rs)
        return rs * rs / (2.0 * (c + root)), rs * rs / (2.0 * root)
    if rs <= 0.0:
        return 0.0, 0.0
    a = c / rs
    e = math.exp(-a * a)
    return max(0.5 * (rs * e / _SQRT_PI - c * math.erfc(a)), 0.0), rs * e / (2.0 * _SQRT_PI)


@njit(inline="always")
def _lobe_at(geo, p, r, a2, beckmann):  # pragma: no cover - compiled
    """Return D G / (4 c_i c_o) at pair p and its derivative in log alpha (r = alpha, a2 = r^2).

    D in log alpha: GGX d log D = 2 (h_xy^2 - a2 h_z^2) / (a2 h_z^2 + h_xy^2); Beckmann
    (tan^2 = y) 2 y / a2 - 2.
    """
    ci, co, hz2, hxy2 = geo[p, 0], geo[p, 1], geo[p, 4], geo[p, 5]
    if beckmann:
        y = hxy2 / hz2 if hz2 > 0.0 else _TAN2_CAP
        y = min(y, _TAN2_CAP)
        dist = (1.0 + y) ** 2 * math.exp(-y / a2) / (math.pi * a2)
        dlog = 2.0 * y / a2 - 2.0
    else:
        den = a2 * hz2 + hxy2
        dist = a2 / (math.pi * den * den)
        dlog = 2.0 * (hxy2 - a2 * hz2) / den
    li, dli = _smith(ci, r * geo[p, 2], beckmann)
    lo, dlo = _smith(co, r * geo[p, 3], beckmann)
    s = dist * (1.0 / ((ci + li) * (co + lo))) / 4.0
    if s == 0.0:
        return 0.0, 0.0
    return s, s * (dlog - dli / (ci + li) - dlo / (co + lo))


@njit
def _lobe_kernel(geo, alpha, beckmann, s, ds):  # pragma: no cover - compiled
    # geo (n, 7), alpha > 0 -> s (n,), and ds (n,) the derivative in log alpha if ds.size
    a2 = alpha * alpha
    deriv = ds.shape[0] > 0
    for p in range(geo.shape[0]):
        v, d = _lobe_at(geo, p, alpha, a2, beckmann)
        s[p] = v
        if deriv:
            ds[p] = d


@njit
def _value_kernel(geo, x, c, beckmann, f):  # pragma: no cover - compiled
    # geo (n, 7), x (2 c + 2,) = [kd, ks, log alpha, f0] -> f (n, c)
    alpha = math.exp(x[2 * c])
    a2 = alpha * alpha
    f0 = x[2 * c + 1]
    for p in range(geo.shape[0]):
        s, _ = _lobe_at(geo, p, alpha, a2, beckmann)
        frs = (f0 + (1.0 - f0) * geo[p, 6]) * s
        for ch in range(c):
            f[p, ch] = x[ch] / math.pi + x[c + ch] * frs


@njit
def _residual_kernel(geo, x, c, beckmann, scale, target, log, r, jac):  # pragma: no cover
    # geo (n, 7), x (2 c + 2,) = [kd, ks, log alpha, f0], scale and target (n, c) ->
    # r (n c,) and jac (n c, 2 c + 2), rows pair-major; the operations of the numpy
    # residuals of project.fitting._solver._objective, in one pass without temporaries
    alpha = math.exp(x[2 * c])
    a2 = alpha * alpha
    f0 = x[2 * c + 1]
    p_ = 2 * c + 2
    for p in range(geo.shape[0]):
        s, ds = _lobe_at(geo, p, alpha, a2, beckmann)
        x5 = geo[p, 6]
        fr = f0 + (1.0 - f0) * x5
        frs = fr * s
        ci = geo[p, 0]
        cc = ci * geo[p, 1]
        for ch in range(c):
            f = x[ch] / math.pi + x[c + ch] * frs
            row = p * c + ch
            if log:
                r[row] = scale[p, ch] * (math.log1p(f * ci) - target[p, ch])
                gr = scale[p, ch] * ci / (1.0 + f * ci)
            else:
                r[row] = scale[p, ch] * (f * cc - target[p, ch])
                gr = scale[p, ch] * cc
            for k in range(p_):
                jac[row, k] = 0.0
            jac[row, ch] = gr * (1.0 / math.pi)
            jac[row, c + ch] = gr * frs
            jac[row, 2 * c] = gr * (x[c + ch] * (fr * ds))
            jac[row, 2 * c + 1] = gr * (x[c + ch] * (s * (1.0 - x5)))
