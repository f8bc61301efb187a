"""The "rr8807" family: reflection and diffraction of Holzschuch & Pacanowski (RR-8807, 2015).

Fitted by :func:`project.fitting.fit_model`; the fit itself (residuals, restarts, standard
errors) is described in :mod:`project.fitting.model`.

The model
---------
``"rr8807"`` (4 C + 3 reals: the report's 15 for RGB)
    f = kd/pi + G(w_i, w_o) [ks D(theta_h) F(theta_d) / (4 cos theta_i cos theta_o)
    + kw / lambda^4 S(f) / E(a, lambda)], the reflection and diffraction model of Holzschuch
    & Pacanowski (Inria RR-8807, 2015, eq. 24): D(theta) = beta exp(-(tan^2 theta /
    sigma^2)^p) / cos^4 theta with beta = p / (pi sigma^2 Gamma(1/p)) (eqs. 18, 19, 26),
    the separable Smith G = G1(theta_i) G1(theta_o), G1 = 1 / (1 + Lambda) of that slope
    distribution (eqs. 6, 7, 20, 21; Lambda depends on (sigma tan theta, p) only and is
    computed by a one-dimensional quadrature per p and splined, to ~1e-7), Schlick's
    F(theta_d) = F0 + (1 - F0)(1 - cos theta_d)^5 on the reflection lobe only (eq. 27), and
    the diffraction lobe S(f) = (1 + f^2 / a^2)^-2 of the spatial frequency f = 2 sin
    theta_h cos theta_d / lambda (eqs. 11, 25), divided by its largest albedo E (corrected
    below) and multiplied by G as in the report (section 5.3). lambda (um) is per channel:
    the report's 0.645, 0.526, 0.444 for three channels, 0.526 for one, else the
    ``wavelength`` option; it is stored in ``params["wavelength"]`` (fixed, not fitted, not
    counted in ``nparams``). Parameters and bounds: ``kd`` (C,) in [0, 1], ``ks`` (C,) in
    [0, 5] (as for lambert+ggx), ``kw`` (C,) in [0, 1] (the report's k_T = kd + ks + kw < 1
    is not imposed; kw / lambda^4 is the diffraction lobe's albedo at normal incidence
    without G, 5.8 kw at 0.645 um to 25.7 kw at 0.444 um), ``f0`` (C,) in [0.02, 1.2] (the
    report's bounds: F may exceed 1), ``sigma`` in [1e-4, 1.5], ``p`` in [0.15, 5] (the
    report's upper bound; below 0.15 the slope distribution has so much mass at grazing
    slopes that the quadrature of Lambda and the check of D's normalisation fail at 1e-6),
    ``a`` (1/um) in [0.01, 50]; sigma, p and a are fitted in log scale. The report's
    two-step fit and its samples restricted to theta < 1.4 rad are not reproduced: the fit
    is the one-step fit of every family here, with several starts (the report finds its
    one-step fit reaches the best optimum from ~30 % of random starts; see the stability
    atlas, :func:`compress.stability.fit_stability`).

Printed formulas that fail a check
----------------------------------
Each was derived again and verified numerically (tests/project/test_fitting.py):

- RR-8807, E(a, lambda): the text reads pi (1 + 1/(a^2 lambda^2)). The cosine-weighted
  albedo of S at normal incidence, where it is largest, is
  2 pi int_0^1 s ds / (1 + s^2 / (a lambda)^2)^2 = pi / (1 + 1/(a^2 lambda^2)) (f = sin
  theta_o / lambda there), so that is the E used: 0.80499, 0.58561, 0.44089 for a = 0.91 at
  the three wavelengths, and the lobe kw = lambda^4 has albedo 1 (checked with G ~ 1).
- RR-8807, eq. 20: P2(r) = p / (pi Gamma(1/p)) int_0^inf exp(-(r^2 + q^2)^p) dq is half
  the marginal slope density (the integral runs over the whole line), so eq. 21 built on it
  halves Lambda. At p = 1 (Beckmann) the full-line form gives the closed-form Smith Lambda,
  and only it satisfies the projected-area identity int G1 <o, m> D dm = cos theta_o;
  the halved one misses it by > 1 % at theta_o = 1.4 rad.
- RR-8807, eq. 23 (importance sampling, not used here): the exponent p/2 should be
  1/(2p), tan^2 theta_h = sigma^2 y^(1/p) with y ~ Gamma(1/p, 1).

References
----------
- E. Heitz, "Understanding the masking-shadowing function in microfacet-based BRDFs",
  Journal of Computer Graphics Techniques 3(2), 2014.
- J. Holzschuch and R. Pacanowski, "A physically accurate reflectance model combining
  reflection and diffraction", Inria Research Report RR-8807, 2015.
- C. Schlick, "An inexpensive BRDF model for physically-based rendering", Computer Graphics
  Forum 13(3), 1994, pp. 233-246.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline
from scipy.special import digamma, gammaln

from ._geometry import _Geometry
from ._solver import _sqrt_diag

__all__ = ["RGB_WAVELENGTHS"]

#: Bounds of the rr8807 (sigma, p, a).
_SIGMA, _P, _A = (1e-4, 1.5), (0.15, 5.0), (1e-2, 50.0)
#: Wavelengths (um) of the red, green and blue channels in Holzschuch & Pacanowski 2015.
RGB_WAVELENGTHS = (0.645, 0.526, 0.444)

_EPD_NODES, _EPD_TABLE, _EPD_M_LO, _EPD_TAIL = 128, 384, 1e-4, 40.0


def _epd_lambda_direct(m: NDArray, p: float, nodes: int = _EPD_NODES,
                       dp: bool = False) -> NDArray:
    """Smith Lambda of the slope distribution P22(x) ~ exp(-(x / sigma^2)^p), m = cot / sigma.

    Lambda(m) = p / (pi Gamma(1/p)) J(m) / m with J(m) = int_{s > m} (s - m) g(s) ds and
    g(s) = int_R exp(-(s^2 + t^2)^p) dt; in polar coordinates r = m cosh v this is
    J = 2 m^3 int_0^inf exp(-r^(2p)) cosh v sinh v (sinh v - arctan sinh v) dv, smooth and
    fast-decaying: the trapezoidal rule to r^(2p) = m^(2p) + 40 (128 nodes: 1e-13
    relative). With ``dp``, also dlog Lambda / dlog p at fixed m.
    """
    m = np.asarray(m, dtype=np.float64)
    rmax = (m ** (2.0 * p) + 40.0) ** (0.5 / p)  # relative truncation e^-40
    vmax = np.arccosh(rmax / m)
    v = vmax[:, None] * np.linspace(0.0, 1.0, nodes)[None, :]
    ch, sh = np.cosh(v), np.sinh(v)
    # sinh v - arctan(sinh v) by its series where the difference cancels
    s2 = sh * sh
    diff = np.where(sh < 1e-2, sh * s2 * (1.0 / 3.0 - s2 / 5.0 + s2 * s2 / 7.0),
                    sh - np.arctan(sh))
    r2p = (m[:, None] * ch) ** (2.0 * p)
    y = np.exp(-r2p) * ch * sh * diff

    def trap(z: NDArray) -> NDArray:
        return vmax / (nodes - 1) * (z.sum(axis=1) - 0.5 * (z[:, 0] + z[:, -1]))

    j = 2.0 * m ** 3 * trap(y)
    lam = float(np.exp(np.log(p) - np.log(np.pi) - gammaln(1.0 / p))) * j / m
    if not dp:
        return lam
    # d/dp exp(-r^(2p)) = -exp(-r^(2p)) r^(2p) log r^2; the limit moves by O(e^-40)
    jp = -2.0 * m ** 3 * trap(y * r2p * np.log(m[:, None] * ch) * 2.0)
    return lam, 1.0 + digamma(1.0 / p) / p + p * jp / j


@lru_cache(maxsize=32)
def _epd_table(p: float):
    """Tabulate Lambda(m, p) at one p: cubic splines in xi = 2p log m + m^(2p).

    The splines are of log psi, psi = m Lambda(m), and of dlog psi / dlog p, on
    [1e-4, m_hi]; below, the asymptote A(p) - m / 2. log psi is smooth and falls like
    -m^(2p), and xi is close to log m^(2p) for small m and to m^(2p) for large m: splined in
    xi, Lambda keeps ~1e-7 relative accuracy over the 17 orders of magnitude it spans
    (measured against the Beckmann closed form at p = 1).
    """
    m_hi = _EPD_TAIL ** (0.5 / p)  # Lambda < e^-40 beyond
    xi = np.linspace(_epd_xi(_EPD_M_LO, p), _epd_xi(m_hi, p), _EPD_TABLE)
    ell = np.linspace(np.log(_EPD_M_LO), np.log(m_hi), 4096)
    lm = np.interp(xi, _epd_xi(np.exp(ell), p), ell)
    for _ in range(3):  # Newton on xi(m) = xi, dxi / dlog m = 2p (1 + m^(2p))
        mm = np.exp(lm)
        lm -= (_epd_xi(mm, p) - xi) / (2.0 * p * (1.0 + mm ** (2.0 * p)))
    m = np.exp(lm)
    lam, dlp = _epd_lambda_direct(m, p, dp=True)
    x = _epd_xi(m, p)
    # m Lambda -> A(p) - m / 2 as m -> 0, A = Gamma(3 / (2p)) / (pi Gamma(1/p))
    a = float(np.exp(gammaln(1.5 / p) - gammaln(1.0 / p)) / np.pi)
    da = float(digamma(1.0 / p) / p - 1.5 * digamma(1.5 / p) / p)  # dlog A / dlog p
    return CubicSpline(x, np.log(m * lam)), CubicSpline(x, dlp), a, da, float(m_hi)


def _epd_xi(m: NDArray | float, p: float) -> NDArray:
    return 2.0 * p * np.log(m) + m ** (2.0 * p)


def _epd_lambda(m: NDArray, p: float, deriv: bool = False):
    """Return Lambda(m, p) for m = 1 / (sigma tan theta) >= 0 (inf at the normal).

    With ``deriv``, also dLambda / dlog m and dLambda / dlog p.
    """
    spline, dspline, a, da, m_hi = _epd_table(float(p))
    m = np.asarray(m, dtype=np.float64)
    lo, hi = m < _EPD_M_LO, m > m_hi
    mid = ~(lo | hi)
    psi = np.zeros_like(m)
    mm = m[mid]
    xi = _epd_xi(mm, p)
    psi[mid] = np.exp(spline(xi))
    psi[lo] = a - 0.5 * m[lo]
    safe = np.where(m > 0.0, m, 1.0)
    lam = np.where(m > 0.0, psi / safe, np.inf)
    if not deriv:
        return lam
    dpsi = np.zeros_like(m)  # dpsi / dlog m
    dpsi[mid] = psi[mid] * spline(xi, 1) * 2.0 * p * (1.0 + mm ** (2.0 * p))
    dpsi[lo] = -0.5 * m[lo]
    dlp = np.zeros_like(m)  # dpsi / dlog p
    dlp[mid] = psi[mid] * dspline(xi)
    dlp[lo] = a * da
    return (lam, np.where(m > 0.0, (dpsi - psi) / safe, -np.inf),
            np.where(m > 0.0, dlp / safe, np.inf))


class _RR8807:
    """x = [kd (C), ks (C), kw (C), f0 (C), log sigma, log p, log a]."""

    separable = False

    def __init__(self, channels: int, wavelength: NDArray) -> None:
        self.c = channels
        self.lam = np.asarray(wavelength, dtype=np.float64).reshape(channels)
        self.p = 4 * channels + 3
        self.k = 2
        c = channels
        lo = np.r_[np.zeros(3 * c), np.full(c, 0.02), np.log([_SIGMA[0], _P[0], _A[0]])]
        hi = np.r_[np.ones(c), np.full(c, 5.0), np.ones(c), np.full(c, 1.2),
                   np.log([_SIGMA[1], _P[1], _A[1]])]
        self.bounds = (lo, hi)
        self.nl_bounds = (np.r_[0.02, lo[-3:]], np.r_[1.2, hi[-3:]])

    def _terms(self, sigma: float, p: float, a: float, g: _Geometry, jac: bool = False):
        """G D / (4 c_i c_o), G S / (lambda^4 E) per channel, and log-derivatives."""
        ci, co = g.ci, g.co
        up = (ci > 0.0) & (co > 0.0) & (g.ch > 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            mi = np.where(up, ci / (sigma * g.si), 0.0)
            mo = np.where(up, co / (sigma * g.so), 0.0)
            res = [_epd_lambda(mi, p, jac), _epd_lambda(mo, p, jac)]
            lam_i, lam_o = (r[0] for r in res) if jac else res
            g1i, g1o = 1.0 / (1.0 + lam_i), 1.0 / (1.0 + lam_o)
            gg = np.where(up, g1i * g1o, 0.0)
            # D = beta exp(-(tan^2 theta_h / sigma^2)^p) / cos^4 theta_h, Eq. 26
            x = np.where(up, g.sh2 / np.where(up, g.ch, 1.0) ** 2, 0.0) / sigma ** 2
            y = x ** p
            logb = np.log(p) - np.log(np.pi) - 2.0 * np.log(sigma) - gammaln(1.0 / p)
            d = np.where(up, np.exp(logb - y) / np.where(up, g.ch, 1.0) ** 4, 0.0)
            spec = np.where(up, gg * d / (4.0 * np.where(up, ci * co, 1.0)), 0.0)
        # diffraction: f = 2 sin theta_h cos theta_d / lambda (Eq. 11), S = (1 + f^2/a^2)^-2
        z = (2.0 * np.sqrt(g.sh2) * g.cd)[:, None] ** 2 / (self.lam * a) ** 2
        inv_e = (1.0 + 1.0 / (a * self.lam) ** 2) / np.pi  # 1 / E_{a,lambda}, corrected
        diff = gg[:, None] * inv_e / (1.0 + z) ** 2 / self.lam ** 4
        if not jac:
            return spec, diff
        (_, dli, dpi), (_, dlo, dpo) = res
        # d log G / d log sigma: m = 1 / (sigma tan theta), d log m / d log sigma = -1
        with np.errstate(invalid="ignore"):
            dg_s = np.where(up, g1i * dli + g1o * dlo, 0.0)
            dg_p = np.where(up, -(g1i * dpi + g1o * dpo), 0.0)
            dd_s = -2.0 + 2.0 * p * y
            dd_p = 1.0 + digamma(1.0 / p) / p - np.where(y > 0.0, p * y * np.log(
                np.where(y > 0.0, x, 1.0)), 0.0)
        dspec_s = np.where(spec > 0.0, spec * (dd_s + dg_s), 0.0)
        dspec_p = np.where(spec > 0.0, spec * (dd_p + dg_p), 0.0)
        ddiff_s = diff * dg_s[:, None]
        ddiff_p = diff * dg_p[:, None]
        ddiff_a = diff * (4.0 * z / (1.0 + z) - 2.0 / (1.0 + (a * self.lam) ** 2))
        return spec, diff, (dspec_s, dspec_p, ddiff_s, ddiff_p, ddiff_a)

    def value(self, x: NDArray, g: _Geometry, jac: bool = False):
        c = self.c
        kd, ks, kw, f0 = x[:c], x[c:2 * c], x[2 * c:3 * c], x[3 * c:4 * c]
        sigma, p, a = np.exp(x[4 * c:])
        x5 = ((1.0 - g.cd) ** 5)[:, None]
        fr = f0 + (1.0 - f0) * x5
        out = self._terms(sigma, p, a, g, jac)
        spec, diff = out[0], out[1]
        f = kd / np.pi + ks * fr * spec[:, None] + kw * diff
        if not jac:
            return f
        dspec_s, dspec_p, ddiff_s, ddiff_p, ddiff_a = out[2]
        df = np.zeros((g.n, c, self.p))
        idx = np.arange(c)
        df[:, idx, idx] = 1.0 / np.pi
        df[:, idx, c + idx] = fr * spec[:, None]
        df[:, idx, 2 * c + idx] = diff
        df[:, idx, 3 * c + idx] = ks * (1.0 - x5) * spec[:, None]
        df[:, :, 4 * c] = ks * fr * dspec_s[:, None] + kw * ddiff_s
        df[:, :, 4 * c + 1] = ks * fr * dspec_p[:, None] + kw * ddiff_p
        df[:, :, 4 * c + 2] = kw * ddiff_a
        return f, df

    def columns(self, xnl: NDArray, g: _Geometry) -> NDArray:
        """(n, C, 3) functions multiplying (kd, ks, kw) at fixed (f0, log sigma, log p, log a)."""
        spec, diff = self._terms(*np.exp(xnl[1:]), g)
        fr = xnl[0] + (1.0 - xnl[0]) * (1.0 - g.cd) ** 5
        return np.stack([np.full((g.n, self.c), 1.0 / np.pi),
                         np.broadcast_to((fr * spec)[:, None], (g.n, self.c)), diff], axis=2)

    def assemble(self, lin: NDArray, xnl: NDArray) -> NDArray:
        return np.r_[lin[:, 0], lin[:, 1], lin[:, 2], np.full(self.c, xnl[0]), xnl[1:]]

    def nonlinear_grid(self) -> list[NDArray]:
        return [np.r_[0.05, np.log([s, p, a])] for s in (0.005, 0.01, 0.03, 0.1, 0.3)
                for p in (0.5, 1.0) for a in (0.3, 3.0)]

    def nonlinear_random(self, rng: np.random.Generator) -> NDArray:
        return np.r_[rng.uniform(0.02, 1.0), rng.uniform(np.log(0.003), np.log(0.8)),
                     rng.uniform(np.log(0.3), np.log(2.0)), rng.uniform(np.log(0.1),
                                                                         np.log(10.0))]

    def params(self, x: NDArray) -> dict[str, NDArray]:
        c = self.c
        sigma, p, a = np.exp(x[4 * c:])
        return {"kd": x[:c].copy(), "ks": x[c:2 * c].copy(), "kw": x[2 * c:3 * c].copy(),
                "f0": x[3 * c:4 * c].copy(), "sigma": np.array(sigma), "p": np.array(p),
                "a": np.array(a), "wavelength": self.lam.copy()}

    def natural_stderr(self, x: NDArray, cov: NDArray) -> dict[str, NDArray]:
        c = self.c
        se = _sqrt_diag(cov)
        nat = np.exp(x[4 * c:]) * se[4 * c:]
        return {"kd": se[:c].copy(), "ks": se[c:2 * c].copy(), "kw": se[2 * c:3 * c].copy(),
                "f0": se[3 * c:4 * c].copy(), "sigma": np.array(nat[0]),
                "p": np.array(nat[1]), "a": np.array(nat[2]), "wavelength": np.zeros(c)}

    def vector(self, params: dict[str, NDArray]) -> NDArray:
        return np.r_[params["kd"], params["ks"], params["kw"], params["f0"],
                     np.log([float(params["sigma"]), float(params["p"]), float(params["a"])])]


def _wavelengths(wavelength: object, channels: int) -> NDArray:
    """Return the wavelengths (um) of rr8807's channels: given, or the report's for 3 or 1."""
    if wavelength is None:
        if channels == 3:
            return np.array(RGB_WAVELENGTHS)
        if channels == 1:
            return np.array(RGB_WAVELENGTHS[1:2])
        raise ValueError(f"family 'rr8807' needs the option wavelength (um, one per channel) "
                         f"for {channels} channels (defaults exist for 3, RGB, and 1)")
    try:
        lam = np.array(wavelength, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise TypeError(f"wavelength must be numbers (um), got {wavelength!r}") from None
    if lam.size != channels or not np.all(np.isfinite(lam)) or np.any(lam <= 0.0):
        raise ValueError(f"wavelength must hold {channels} finite values > 0 (um, one per "
                         f"channel), got {wavelength!r}")
    return lam
