"""The "dsbrdf" family: the directional-statistics BRDF of Nishino & Lombardi (2010).

Fitted by :func:`project.fitting.fit_model`; the fit itself (residuals, restarts, standard
errors, and why this family stops on a looser ``ftol``) is described in
:mod:`project.fitting.model`.

The model
---------
``"dsbrdf"`` (2 x K x 6 x C reals: 108 for K = 3 lobes on RGB)
    f_c = sum_k (exp[kappa_kc(theta_d) cos^gamma_kc(theta_d) theta_h] - 1), the isotropic
    directional-statistics BRDF of Nishino & Lombardi (DU-CS-10-06, 2010; eq. 6, the
    unnormalised mixture of hemispherical exponential power distributions, eq. 4, as it is
    fitted to measured data) in the half/difference angles of Rusinkiewicz 1998: each lobe
    is a hemi-EPD in theta_h whose scale kappa and shape gamma are functions of theta_d. The
    paper fits them on 18 theta_d slices and then writes each (kappa, gamma) curve as a
    quadratic B-spline with five uniform knots, "one third" of the 18 samples; that compact
    form is the model here: the knots 0, pi/8, pi/4, 3 pi/8, pi/2, clamped, give 6
    coefficients per curve (:data:`DS_KNOTS`), fitted directly (no slices, so no
    interpolation between them is needed). Non-negative coefficients give non-negative
    curves (the B-splines are a partition of unity), so f >= 0; kappa = 0 is a zero lobe,
    gamma = 0 a constant (Lambertian) one. The lobes are per channel, as in the paper, and
    no parameter is shared between channels, so each channel is fitted alone. The number
    of lobes is the ``lobes`` option (default 3, "K is typically 3"; the paper picks K per
    material by Williams' test, 2 to 5 for its examples; not done here). Not modelled: the
    delta term at theta_h = 0 that the paper adds after fitting, the mask of the sphere's
    perimeter and the exclusion of theta_h < 1 deg (the paper's data cleaning). Parameters:
    ``kappa``, ``gamma`` (K, 6, C), the spline coefficients per lobe and channel (natural
    units: kappa is the log of 1 + the peak value in 1/sr, gamma an exponent), lobes sorted
    per channel by decreasing mean kappa (the paper's order). Fitted in log scale with
    bounds kappa in [1e-6, 25], gamma in [1e-3, 1e6]. Reciprocal by construction (theta_h
    and theta_d are symmetric in w_i, w_o).

Printed formulas that fail a check
----------------------------------
Each was derived again and verified numerically (tests/project/test_fitting.py):

- DSBRDF, energy: the paper states energy is conserved if sum_k 1/C_k <= 1, 1/C the
  integral of a lobe over the (theta_h, phi_d) hemisphere. The albedo int f cos theta_o
  dw_o carries the Jacobian dw_o = 4 cos theta_d dw_h of the half vector: for a sharp lobe
  it is 4 cos^2 theta_i / C (measured 3.99 / C at normal incidence for gamma = 2000), so a
  mixture meeting the paper's bound can reflect up to 4 times the incident energy.
  Use :meth:`BRDF.albedo` instead.
- DSBRDF, slices and splines: theta_d = m pi/36, m = 0..18, is 19 slices (the paper says
  18), and "6th-order B-splines" are quadratic (order 3) with 6 coefficients, which is
  what a third of 18 samples means.

References
----------
- K. Nishino and S. Lombardi, technical report DU-CS-10-06, Drexel University, 2010, the
  directional statistics BRDF (also "Directional statistics-based reflectance model for
  isotropic bidirectional reflectance distribution functions", JOSA A 28(1), 2011).
- S. Rusinkiewicz, "A new change of variables for efficient BRDF representation",
  Eurographics Workshop on Rendering 1998.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import BSpline

from ._geometry import _Geometry
from ._solver import _sqrt_diag

__all__ = ["DS_COEFFS", "DS_KNOTS"]

#: Knots of the quadratic B-splines of kappa(theta_d) and gamma(theta_d): five uniform knots
#: on [0, pi/2], clamped, so 6 coefficients per curve.
DS_KNOTS = np.r_[0.0, 0.0, np.linspace(0.0, np.pi / 2, 5), np.pi / 2, np.pi / 2]
DS_COEFFS = len(DS_KNOTS) - 3
#: Bounds of the DSBRDF spline coefficients (kappa, gamma).
_KAPPA = (1e-6, 25.0)
_GAMMA = (1e-3, 1e6)


def _ds_design(cd: NDArray) -> NDArray:
    """(n, 6) quadratic B-spline basis of theta_d = arccos(c_d) on :data:`DS_KNOTS`."""
    td = np.clip(np.arccos(np.clip(cd, 0.0, 1.0)), 0.0, np.pi / 2)
    return BSpline.design_matrix(td, DS_KNOTS, 2).toarray()


class _DSBRDF:
    """x = per channel [log kappa (K x 6), log gamma (K x 6)], channel-major.

    f_c = sum_k expm1(kappa_kc(theta_d) cos(theta_h)^gamma_kc(theta_d)), kappa and gamma
    quadratic B-splines of theta_d. Channels share no parameter: fitted one at a time.
    """

    separable = True
    # the cost valley is flat along lobes that fade out (kappa -> 0 over part of theta_d):
    # stop on a 1e-6 relative cost decrease (see the notes of project.fitting.model), in
    # the log-scale units
    x_scale, ftol = 1.0, 1e-6

    def __init__(self, lobes: int, channels: int) -> None:
        self.lobes = lobes
        self.c = channels
        self.per = 2 * lobes * DS_COEFFS  # reals per channel
        self.p = channels * self.per
        one = np.r_[np.full(lobes * DS_COEFFS, np.log(_KAPPA[0])),
                    np.full(lobes * DS_COEFFS, np.log(_GAMMA[0]))]
        top = np.r_[np.full(lobes * DS_COEFFS, np.log(_KAPPA[1])),
                    np.full(lobes * DS_COEFFS, np.log(_GAMMA[1]))]
        self.bounds = (np.tile(one, channels), np.tile(top, channels))

    def channel_model(self) -> _DSBRDF:
        return _DSBRDF(self.lobes, 1)

    @staticmethod
    def _basis(g: _Geometry) -> NDArray:
        if not hasattr(g, "_ds_b"):
            g._ds_b = _ds_design(g.cd)
            g._ds_logt = np.log(np.where(g.ch > 0.0, g.ch, 1.0))  # 0 where cos theta_h = 0
            g._ds_zero = g.ch <= 0.0
        return g._ds_b

    def _lobes(self, xc: NDArray, g: _Geometry, jac: bool = False):
        """Per lobe of one channel: value, and with ``jac`` d/dlog kappa_j and d/dlog gamma_j."""
        b = self._basis(g)
        nk = self.lobes * DS_COEFFS
        lk = np.exp(xc[:nk]).reshape(self.lobes, DS_COEFFS)
        lg = np.exp(xc[nk:]).reshape(self.lobes, DS_COEFFS)
        out = []
        for j in range(self.lobes):
            kap, gam = b @ lk[j], b @ lg[j]
            tg = np.where(g._ds_zero, 0.0, np.exp(gam * g._ds_logt))  # cos^gamma theta_h
            val = np.expm1(kap * tg)
            if not jac:
                out.append(val)
                continue
            e = val + 1.0
            d_k = b * (lk[j] * (tg * e)[:, None])
            d_g = b * (lg[j] * (kap * tg * g._ds_logt * e)[:, None])
            out.append((val, d_k, d_g))
        return out

    def value(self, x: NDArray, g: _Geometry, jac: bool = False):
        f = np.zeros((g.n, self.c))
        df = np.zeros((g.n, self.c, self.p)) if jac else None
        nk = self.lobes * DS_COEFFS
        for ch in range(self.c):
            xc = x[ch * self.per:(ch + 1) * self.per]
            for j, lobe in enumerate(self._lobes(xc, g, jac)):
                if not jac:
                    f[:, ch] += lobe
                    continue
                val, d_k, d_g = lobe
                f[:, ch] += val
                o = ch * self.per + j * DS_COEFFS
                df[:, ch, o:o + DS_COEFFS] = d_k
                df[:, ch, o + nk:o + nk + DS_COEFFS] = d_g
        return (f, df) if jac else f

    def start(self, g: _Geometry, f: NDArray, row: NDArray, k: int,
              rng: np.random.Generator) -> NDArray:
        """Return a start of constant (kappa, gamma) curves.

        Restart 0 as Nishino & Lombardi initialise (the best single lobe on a grid, then
        kappa and gamma halved for each further lobe), the others at random.
        """
        x = []
        logt = np.log(np.where(g.ch > 0.0, g.ch, 1.0))
        for ch in range(self.c):
            if k == 0:
                best = None
                kap = np.geomspace(1e-3, 12.0, 16)
                for gam in np.geomspace(1e-2, 1e5, 22):
                    tg = np.where(g.ch > 0.0, np.exp(gam * logt), 0.0)
                    vals = np.expm1(kap[:, None] * tg[None, :])
                    cost = np.sum(((vals - f[:, ch]) * row[:, ch]) ** 2, axis=1)
                    i = int(np.argmin(cost))
                    if best is None or cost[i] < best[0]:
                        best = (cost[i], kap[i], gam)
                _, k0, g0 = best
                kaps = k0 / 2.0 ** np.arange(self.lobes)
                gams = g0 / 2.0 ** np.arange(self.lobes)
            else:
                kaps = np.exp(rng.uniform(np.log(1e-2), np.log(10.0), self.lobes))
                gams = np.exp(rng.uniform(np.log(0.03), np.log(3e4), self.lobes))
            x.append(np.r_[np.repeat(np.log(kaps), DS_COEFFS), np.repeat(np.log(gams),
                                                                         DS_COEFFS)])
        lo, hi = self.bounds
        span = hi - lo
        return np.clip(np.concatenate(x), lo + 1e-6 * span, hi - 1e-6 * span)

    def _order(self, x: NDArray) -> list[NDArray]:
        """Per channel, the lobes sorted by decreasing mean kappa (as the paper sorts them)."""
        nk = self.lobes * DS_COEFFS
        return [np.argsort(-x[ch * self.per:ch * self.per + nk].reshape(
            self.lobes, DS_COEFFS).mean(axis=1), kind="stable") for ch in range(self.c)]

    def _split(self, v: NDArray, x: NDArray) -> tuple[NDArray, NDArray]:
        nk = self.lobes * DS_COEFFS
        kap = np.empty((self.lobes, DS_COEFFS, self.c))
        gam = np.empty_like(kap)
        for ch, order in enumerate(self._order(x)):
            vc = v[ch * self.per:(ch + 1) * self.per]
            kap[:, :, ch] = vc[:nk].reshape(self.lobes, DS_COEFFS)[order]
            gam[:, :, ch] = vc[nk:].reshape(self.lobes, DS_COEFFS)[order]
        return kap, gam

    def params(self, x: NDArray) -> dict[str, NDArray]:
        kap, gam = self._split(np.exp(x), x)
        return {"kappa": kap, "gamma": gam}

    def natural_stderr(self, x: NDArray, cov: NDArray) -> dict[str, NDArray]:
        kap, gam = self._split(np.exp(x) * _sqrt_diag(cov), x)
        return {"kappa": kap, "gamma": gam}

    def vector(self, params: dict[str, NDArray]) -> NDArray:
        with np.errstate(divide="ignore"):  # a coefficient 0 is exp(-inf): a zero lobe
            lk, lg = np.log(params["kappa"]), np.log(params["gamma"])
        return np.concatenate([np.r_[lk[:, :, ch].ravel(), lg[:, :, ch].ravel()]
                               for ch in range(self.c)])
