"""The "lafortune" family: a Lambertian term and generalised cosine lobes (Lafortune et al. 1997).

Fitted by :func:`project.fitting.fit_model`; the fit itself (residuals, restarts, standard
errors) is described in :mod:`project.fitting.model`.

The model
---------
``"lafortune"`` (C + L (C + 2) reals for L lobes)
    f = kd/pi + sum_j rho_j (n_j + 2)/(2 pi) max(0, Cx_j (u_x v_x + u_y v_y) + u_z v_z)^n_j,
    the isotropic generalised cosine lobes of Lafortune et al. 1997 (eq. 4 with
    C_x = C_y and C_z = 1) with the albedo taken out of the C's: scaling C multiplies a
    lobe by |C|^n, the same as rho, so the scale is fixed by C_z = 1, and the classical
    Phong lobe about the mirror (Cx = -1) has albedo rho at normal incidence. Each lobe is
    fitted in t = n log(-Cx) (Cx = -exp(t / n)) and log n: t measures how much the lobe
    grows from normal to grazing incidence ((u_z v_z + Cx (...))^n <= e^|t|), which keeps
    the fit away from the overflowing lobes of unbounded C that make such fits fail.
    Parameters: ``kd`` (C,) in [0, 1], ``rho`` (L, C) in [0, 5], ``cx`` (L,) < 0 with
    |t| <= 20, ``cz`` (L,) = 1, ``n`` (L,) in [1, 1e5]. Forward lobes only (Cx < 0:
    specular, or off-specular for Cx < -1, Minnaert-like for Cx -> 0); retro-reflective
    lobes (Cx > 0) are not in this family. Lafortune's own per-channel C's are
    (rho_jc (n_j + 2)/(2 pi))^(1/n_j) (Cx_j, Cx_j, 1).

Stability of multi-lobe Lafortune fits
--------------------------------------
Ngan et al. 2005 found multi-lobe Lafortune fits to measured data unstable (as Holzschuch &
Pacanowski 2015 recall). Measured here on the MERL-format surrogate of blue-acrylic (the
Sztrajman et al. 2021 neural fit written on the MERL grid) with ``metric="l2"``, n = 16384,
seed 0 and 8 restarts, final cost 0.5 sum_c relative l2_c^2 on the fitting pairs
(min / median / max over the restarts), and the l2 error of the best restart on the
independent pairs:

- 1 lobe: 0.5725 / 0.5725 / 0.5725, all 8 restarts at the same minimum (to 1e-9);
  l2 = 0.643 +- 0.005;
- 2 lobes: 0.4189 / 0.4680 / 0.4680, only 2 of 8 restarts reach the best minimum, the other
  6 stop in a local minimum 12 % higher; l2 = 0.557 +- 0.005;
- 3 lobes: 0.3591 / 0.3591 / 0.3591, all 8 at the same minimum; l2 = 0.498 +- 0.004.

(lambert+ggx reaches l2 = 0.599 +- 0.004 on the same target with 8 reals.) The fitted lobes
are very sharp (n ~ 5e3 to 9e4) and nearly mirror-centred (Cx within 0.2 % of -1). The same
protocol on the gold-metallic-paint surrogate: 1 lobe 0.1136 for all 8 (l2 = 0.3787 +-
0.0007); 2 lobes 0.0898 / 0.0916 / 0.0934, 4 of 8 at the best, 4 in a minimum 4 % higher
(l2 = 0.3102 +- 0.0010); 3 lobes 0.0678 for all 8 (l2 = 0.2887 +- 0.0010). On both targets
the two-lobe fit is the unstable one, while one and three lobes reached a single minimum
from every start: the instability depends on the target and the lobe count, so use 8 or
more restarts for two or more lobes and compare ``info["cost"]`` across them. Lobes
parametrised by (t, log n) (above) never overflow; an earlier parametrisation by the angle
of (Cx, Cz) on the circle Cx^2 + Cz^2 = 2, in which a lobe off the mirror grows like up to
2^(n/2), sent 2 of 8 one-lobe restarts on blue-acrylic to costs of 1e17 and 1e212.

References
----------
- J. Holzschuch and R. Pacanowski, "A physically accurate reflectance model combining
  reflection and diffraction", Inria Research Report RR-8807, 2015.
- E. P. F. Lafortune, S.-C. Foo, K. E. Torrance and D. P. Greenberg, "Non-linear
  approximation of reflectance functions", SIGGRAPH 97, pp. 117-126.
- A. Ngan, F. Durand and W. Matusik, "Experimental analysis of BRDF models", Eurographics
  Symposium on Rendering 2005.
- A. Sztrajman, G. Rainer, T. Ritschel and T. Weyrich, "Neural BRDF representation and
  importance sampling", Computer Graphics Forum 40(6), 2021.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ._geometry import _Geometry
from ._solver import _quad, _sqrt_diag

# the family is used through fit_model and FittedModel: nothing public here
__all__: list[str] = []

_LOG_CAP = 690.0  # cap on log of a lobe value (e^690 ~ 1e299): keeps every value finite
#: Bounds of the Lafortune exponent n and of t = n log|Cx / Cz|: (V + Cx U)^n <= e^|t|.
_N_MAX, _T_MAX = 1e5, 20.0


class _Lafortune:
    """x = [kd (C), rho (L x C, lobe-major), (t, log n) per lobe]; Cx = -exp(t / n), Cz = 1."""

    def __init__(self, lobes: int, channels: int) -> None:
        self.lobes = lobes
        self.c = channels
        self.k = lobes
        self.p = channels + lobes * (channels + 2)
        nl_lo = np.tile([-_T_MAX, 0.0], lobes)
        nl_hi = np.tile([_T_MAX, np.log(_N_MAX)], lobes)
        lo = np.r_[np.zeros(channels * (lobes + 1)), nl_lo]
        hi = np.r_[np.ones(channels), np.full(channels * lobes, 5.0), nl_hi]
        self.bounds = (lo, hi)

    def _lobes(self, xnl: NDArray, g: _Geometry, jac: bool = False):
        """Per lobe: N B^n, and with ``jac`` also its derivatives in t and log n."""
        out = []
        for j in range(self.lobes):
            t, n = xnl[2 * j], float(np.exp(xnl[2 * j + 1]))
            c = -np.exp(t / n)
            norm = (n + 2.0) / (2.0 * np.pi)
            b = g.v + c * g.u
            pos = b > 0.0
            logb = np.log(np.where(pos, b, 1.0))
            bn = np.where(pos, np.exp(np.minimum(n * logb, _LOG_CAP)), 0.0)
            val = norm * bn
            if not jac:
                out.append(val)
                continue
            bn1 = np.where(pos, bn / np.where(pos, b, 1.0), 0.0)  # B^(n - 1)
            d_t = norm * bn1 * g.u * c  # dc/dt = c / n
            d_ln = n * (bn / (2.0 * np.pi) + val * logb) - t * d_t  # dc/dlog n = -c t / n
            out.append((val, d_t, d_ln))
        return out

    def value(self, x: NDArray, g: _Geometry, jac: bool = False):
        c, nl = self.c, self.lobes
        kd = x[:c]
        rho = x[c:c + nl * c].reshape(nl, c)
        xnl = x[c + nl * c:]
        f = np.broadcast_to(kd / np.pi, (g.n, c)).copy()
        lobes = self._lobes(xnl, g, jac)
        for j in range(nl):
            val = lobes[j][0] if jac else lobes[j]
            f += rho[j] * val[:, None]
        if not jac:
            return f
        df = np.zeros((g.n, c, self.p))
        idx = np.arange(c)
        df[:, idx, idx] = 1.0 / np.pi
        base = c + nl * c
        for j, (val, d_t, d_ln) in enumerate(lobes):
            df[:, idx, c + j * c + idx] = val[:, None]
            df[:, :, base + 2 * j] = rho[j] * d_t[:, None]
            df[:, :, base + 2 * j + 1] = rho[j] * d_ln[:, None]
        return f, df

    def columns(self, xnl: NDArray, g: _Geometry) -> NDArray:
        return np.stack([np.full(g.n, 1.0 / np.pi), *self._lobes(xnl, g)], axis=1)

    @property
    def projected(self) -> bool:
        """One lobe: kd and rho, two linear parameters per channel (variable projection)."""
        return self.lobes == 1

    #: the basins of the global search are those of the exponent (log n)
    profile_axis = 1

    def search_grid(self) -> NDArray:
        """(m, 2) points (t, log n) of the global search of one lobe: n over its range."""
        ln = np.linspace(np.log(1.5), np.log(_N_MAX), 40)
        t = np.array([-2.0, -1.0, -0.3, 0.0, 0.3, 1.0, 2.0, 4.0])
        return np.stack(np.meshgrid(t, ln, indexing="ij"), axis=-1).reshape(-1, 2)

    def nonlinear_grid(self) -> list[NDArray]:
        if self.lobes == 1:
            exps = [[e] for e in (3.0, 10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0)]
        else:  # geometric spreads of exponents, all lobes about the mirror (t = 0)
            exps = [list(np.geomspace(lo, hi, self.lobes)) for lo, hi in
                    ((3.0, 300.0), (10.0, 1000.0), (3.0, 3000.0), (30.0, 10000.0))]
        return [np.ravel([[0.0, np.log(e)] for e in es]) for es in exps]

    def nonlinear_random(self, rng: np.random.Generator) -> NDArray:
        t = rng.uniform(-2.0, 4.0, self.lobes)
        ln = rng.uniform(np.log(1.5), np.log(3000.0), self.lobes)
        return np.ravel(np.stack([t, ln], axis=1))

    def params(self, x: NDArray) -> dict[str, NDArray]:
        c, nl = self.c, self.lobes
        xnl = x[c + nl * c:].reshape(nl, 2)
        n = np.exp(xnl[:, 1])
        return {"kd": x[:c].copy(), "rho": x[c:c + nl * c].reshape(nl, c).copy(),
                "cx": -np.exp(xnl[:, 0] / n), "cz": np.ones(nl), "n": n}

    def natural_stderr(self, x: NDArray, cov: NDArray) -> dict[str, NDArray]:
        c, nl = self.c, self.lobes
        base = c + nl * c
        se = _sqrt_diag(cov)
        xnl = x[base:].reshape(nl, 2)
        n = np.exp(xnl[:, 1])
        cx = -np.exp(xnl[:, 0] / n)
        se_cx = np.empty(nl)
        for j in range(nl):  # cx = -exp(t / n) depends on both: use their covariance
            grad = np.array([cx[j] / n[j], -cx[j] * xnl[j, 0] / n[j]])
            block = cov[base + 2 * j:base + 2 * j + 2, base + 2 * j:base + 2 * j + 2]
            se_cx[j] = _quad(grad, block)
        return {"kd": se[:c].copy(), "rho": se[c:base].reshape(nl, c).copy(), "cx": se_cx,
                "cz": np.zeros(nl), "n": n * se[base + 1::2]}

    def vector(self, params: dict[str, NDArray]) -> NDArray:
        n = params["n"]
        t = n * np.log(-params["cx"])
        return np.r_[params["kd"], params["rho"].ravel(),
                     np.ravel(np.stack([t, np.log(n)], axis=1))]
