"""The "lambert+ggx" and "lambert+beckmann" families: a Lambertian term and a microfacet lobe.

Fitted by :func:`project.fitting.fit_model`; the fit itself (residuals, restarts, standard
errors) is described in :mod:`project.fitting.model`.

The model
---------
``"lambert+ggx"``, ``"lambert+beckmann"`` (2 C + 2 reals for C channels)
    f = kd/pi + ks F(w_i . h) D(h) G(w_i, w_o) / (4 cos theta_i cos theta_o), with D and the
    separable Smith G of :class:`project.models.CookTorrance` (``shadowing="separable"``,
    F = 1, evaluated by that class, so the lobe is the library's own microfacet model) and
    Schlick's Fresnel F(u) = F0 + (1 - F0)(1 - u)^5 (Schlick 1994, eq. 15). Parameters:
    ``kd`` (C,) in [0, 1], ``ks`` (C,) in [0, 5], ``alpha`` (GGX alpha or Beckmann RMS
    slope m, one for all channels) in [1e-3, 1.5], ``f0`` (one for all channels, an
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

import numpy as np
from numpy.typing import NDArray

from ..models import CookTorrance
from ._geometry import _Geometry
from ._solver import _sqrt_diag

# the family is used through fit_model and FittedModel: nothing public here
__all__: list[str] = []


class _Microfacet:
    """x = [kd (C), ks (C), log alpha, f0]."""

    def __init__(self, distribution: str, channels: int) -> None:
        self.distribution = distribution
        self.c = channels
        self.p = 2 * channels + 2
        self.k = 1  # linear parameters besides kd, per channel
        lo = np.r_[np.zeros(2 * channels), np.log(1e-3), 0.02]
        hi = np.r_[np.ones(channels), np.full(channels, 5.0), np.log(1.5), 1.0]
        self.bounds = (lo, hi)

    def lobe(self, alpha: float, g: _Geometry) -> NDArray:
        """D G / (4 c_i c_o) of the library's Cook-Torrance (F = 1, separable Smith G)."""
        return CookTorrance(0.0, alpha, self.distribution).eval(g.wi, g.wo)

    def value(self, x: NDArray, g: _Geometry, jac: bool = False):
        c = self.c
        kd, ks, la, f0 = x[:c], x[c:2 * c], x[2 * c], x[2 * c + 1]
        s = self.lobe(float(np.exp(la)), g)
        x5 = (1.0 - g.cd) ** 5
        fr = f0 + (1.0 - f0) * x5
        f = kd / np.pi + ks * (fr * s)[:, None]
        if not jac:
            return f
        h = 1e-5  # central difference in log alpha: relative error ~1e-10
        ds = (self.lobe(float(np.exp(la + h)), g) - self.lobe(float(np.exp(la - h)), g)) / (2 * h)
        df = np.zeros((g.n, c, self.p))
        idx = np.arange(c)
        df[:, idx, idx] = 1.0 / np.pi
        df[:, idx, c + idx] = (fr * s)[:, None]
        df[:, :, 2 * c] = ks * (fr * ds)[:, None]
        df[:, :, 2 * c + 1] = ks * (s * (1.0 - x5))[:, None]
        return f, df

    def columns(self, xnl: NDArray, g: _Geometry) -> NDArray:
        """Functions multiplying the linear parameters (kd, ks) at fixed (log alpha, f0)."""
        s = self.lobe(float(np.exp(xnl[0])), g)
        fr = xnl[1] + (1.0 - xnl[1]) * (1.0 - g.cd) ** 5
        return np.stack([np.full(g.n, 1.0 / np.pi), fr * s], axis=1)

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
