"""Fits of parametric BRDF families to any BRDF: :func:`fit_model` returns a :class:`FittedModel`.

A :class:`FittedModel` is a :class:`~project.brdf.BRDF` (``eval``, ``channels``,
``isotropic``, ``albedo``) with its ``family``, fitted ``params``, ``nparams``, ``nbytes``
and an ``info`` dict that says how good the fit is: the errors of :mod:`project.sampling` on
pairs independent of the fitting pairs, with the Monte Carlo standard error, the cost of every
restart, convergence and parameter standard errors.

Families
--------
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

``"factored"`` (kd, tables and colour weights: 271 reals, 2168 bytes, at the defaults)
    f = kd/pi + sum_k w_k A_k(theta_h) B_k(theta_d) C_k(phi_d), the non-parametric factored
    lobe of :class:`project.factored.FactoredLobe` (non-negative piecewise-linear tables in
    the half/difference angles of Rusinkiewicz 1998), fitted by
    :func:`project.factored.fit_factored` (non-negative alternating least squares on a
    quadrature rule in those angles; ``metric="l2"`` only). The options are those of
    ``fit_factored`` (``rank``, ``bins``, ``warp``, ``warp_d``, ``color``, ...) and the
    error pairs below. Parameters: ``kd`` (C,), ``h_table`` (rank, n_h, 1 or C),
    ``d_table`` (rank, n_d, 1 or C), optionally ``phi_table`` (rank, n_phi) and
    ``weights`` (rank, C), and the node spacings ``warp`` and ``warp_d`` (the exponents of
    :data:`project.factored.WARPS` and :data:`~project.factored.D_WARPS`; not counted in
    ``nparams``). ``phi_turn="full"`` (default ``"half"``, also for a BRDF whose
    ``reciprocal`` is False) fits phi_d tables over the whole turn, which hold the
    antisymmetric part of non-reciprocal data; such a model has ``reciprocal`` False and
    its params hold ``phi_turn`` = 1.0 (params without it are half-turn lobes).
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
- DSBRDF, energy: the paper states energy is conserved if sum_k 1/C_k <= 1, 1/C the
  integral of a lobe over the (theta_h, phi_d) hemisphere. The albedo int f cos theta_o
  dw_o carries the Jacobian dw_o = 4 cos theta_d dw_h of the half vector: for a sharp lobe
  it is 4 cos^2 theta_i / C (measured 3.99 / C at normal incidence for gamma = 2000), so a
  mixture meeting the paper's bound can reflect up to 4 times the incident energy.
  Use :meth:`BRDF.albedo` instead.
- DSBRDF, slices and splines: theta_d = m pi/36, m = 0..18, is 19 slices (the paper says
  18), and "6th-order B-splines" are quadratic (order 3) with 6 coefficients, which is
  what a third of 18 samples means.

Fitting
-------
The parametric families are fitted as follows (for ``"factored"`` see its module). The
fitting pairs are ``peak_resolving_pairs(n, seed=seed)``; the BRDF is evaluated there once.
Residuals, one per pair and channel:

- ``metric="l2"``: sqrt(w) (q_model - q) / ||q_c||, q = f cos theta_i cos theta_o, w the
  pair weights and ||q_c||^2 = sum w q_c^2 per channel, so the cost 0.5 sum r^2 is half the
  sum over channels of the squared relative l2 errors of :func:`project.sampling.relative_l2`
  (each channel counts equally, whatever its brightness);
- ``metric="log"``: sqrt(w / sum w) (log(1 + f_model cos theta_i) - log(1 + f cos theta_i)),
  the log metric of :func:`project.sampling.log_rms`.

They are minimised by ``scipy.optimize.least_squares`` (trust-region reflective, bounds,
analytic Jacobians (for "lambert+ggx" and "lambert+beckmann" a central difference in log
alpha; for "rr8807" the derivative of Lambda in p comes from the derivative of its
quadrature, splined alike), roughness and exponents in log scale) from ``restarts`` starting points:
restart 0 picks the nonlinear parameters (roughness, or lobe direction and exponent) on a
small grid, the others draw them at random from ``SeedSequence([seed, restart])``; for each
start the parameters that enter linearly (kd, ks, rho) are solved by non-negative least
squares. For "rr8807" the nonlinear start is (F0, sigma, p, a) with one F0 for all channels. For
"dsbrdf", whose channels are fitted one at a time, restart 0 is the paper's initialisation
(the best single lobe, constant in theta_d, on a grid of (kappa, gamma), then kappa and
gamma halved for each further lobe) and the others draw constant curves at random; its
least squares stop when a step lowers the cost by less than 1e-6 relative (``ftol``,
instead of scipy's 1e-8), because the cost is flat along lobes that fade out over part of
theta_d: on a glossy Cook-Torrance the final costs then lie within 3e-4 of the 1e-7 ones
with 3 to 10 times fewer evaluations. The best restart is kept; if it stopped on
``max_nfev`` instead of a tolerance, a
RuntimeWarning reports the best error reached. ``info`` reports the errors on
``peak_resolving_pairs(error_n, seed=error_seed)``, a second, independent set (default
``error_seed = seed + 1``: another scrambling), so they are not biased by the fit. Both sets
use the lobe ``widths`` option; the default (0.02, 0.08, 0.3) resolves lobes down to alpha
~0.02 well and sharper ones without bias but with more variance: on the blue-acrylic
surrogate (alpha = 0.008) the standard error of the lambert+ggx l2 error is 0.0035 with the
default and 0.0007 with ``widths=(0.005, 0.02, 0.08, 0.3)`` (65536 pairs, both l2 = 0.600).

``info["param_stderr"]`` is the usual linearised standard error
sqrt(diag((J^T J)^-1) s^2), s^2 = sum r^2 / (m - p), at the optimum (in the natural units of
each parameter, through the derivative of the log scale). The residuals are the misfit of a
model, not independent noise, so read it as the local sensitivity of the fit (how far a
parameter moves before the cost rises by one residual variance), not as a confidence
interval. A parameter with no effect on the residuals (a zero column of J, or a direction
J does not see) gets ``inf``; a nearly undetermined one (``alpha`` and ``f0`` when ``ks`` is
~0) gets a large value, unless the residuals are themselves ~0 (data the family reproduces
exactly), when every parameter looks well determined. A parameter at a bound is linearised
as if it were free.

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

The new families on MERL-format surrogates
------------------------------------------
l2 error (+- its standard error, on the independent pairs) with the defaults (``metric=
"l2"``, n = 16384, seed 0, 4 restarts, error_n = 65536), on the MERL-format surrogates of
the Sztrajman et al. 2021 neural fits (not the measurements themselves):

====================  =================  ==============  ==============
material              lambert+ggx (8)    rr8807 (15)     dsbrdf K=3 (108)
====================  =================  ==============  ==============
blue-acrylic          0.600              0.571 +- 0.005  0.170 +- 0.006
alum-bronze           0.55               0.352 +- 0.002  0.180 +- 0.002
gold-metallic-paint3  0.21               0.142 +- 0.003  0.093 +- 0.001
====================  =================  ==============  ==============

(reals in brackets; lambert+ggx as measured for issue 11; log RMS errors 0.015 / 0.029 /
0.014 for rr8807 and 0.011 / 0.010 / 0.019 for dsbrdf.) rr8807 gains most where the
highlight has long tails: its fits reach sigma ~2e-4 and p at or near the lower bound (0.24
on blue-acrylic, 0.15 on the other two), with F0 at its bound 1.2 in two channels of the
paint. The per-slice hemi-EPD lobes follow the theta_d dependence of these peaks far better
than one microfacet lobe: dsbrdf with 108 reals (864 bytes) is below the tabulated
separable lobe of issue 11 (0.18 / 0.21 / 0.13 at ~1.5 kB). Fits took 45-75 s (rr8807)
and 135-280 s (dsbrdf) on a shared, loaded machine (one BLAS thread). Across the 4
restarts rr8807 reached one minimum on all three (costs equal to 1e-5), dsbrdf did not:
blue-acrylic 0.03294 / 0.03336 / 0.03336 / 0.03489, alum-bronze 0.03401 / 0.03402 / 0.03668
/ 0.03707, gold-metallic-paint3 0.00908 (3) / 0.00915; use more restarts for dsbrdf. On
the nickel surrogate rr8807 gives sigma = 0.024, p = 0.47, a = 1.30 um^-1 (l2 0.229), near
the report's fit of the measured nickel (sigma 0.027, p 0.51, a 0.91) in sigma and p,
although the objective (cos^2 theta_i weighted, theta < 1.4 rad, two-step) differs.

References
----------
- E. Heitz, "Understanding the masking-shadowing function in microfacet-based BRDFs",
  Journal of Computer Graphics Techniques 3(2), 2014.
- J. Holzschuch and R. Pacanowski, "A physically accurate reflectance model combining
  reflection and diffraction", Inria Research Report RR-8807, 2015.
- E. P. F. Lafortune, S.-C. Foo, K. E. Torrance and D. P. Greenberg, "Non-linear
  approximation of reflectance functions", SIGGRAPH 97, pp. 117-126.
- A. Ngan, F. Durand and W. Matusik, "Experimental analysis of BRDF models", Eurographics
  Symposium on Rendering 2005.
- K. Nishino and S. Lombardi, technical report DU-CS-10-06, Drexel University, 2010, the
  directional statistics BRDF (also "Directional statistics-based reflectance model for
  isotropic bidirectional reflectance distribution functions", JOSA A 28(1), 2011).
- S. Rusinkiewicz, "A new change of variables for efficient BRDF representation",
  Eurographics Workshop on Rendering 1998.
- C. Schlick, "An inexpensive BRDF model for physically-based rendering", Computer Graphics
  Forum 13(3), 1994, pp. 233-246.
- A. Sztrajman, G. Rainer, T. Ritschel and T. Weyrich, "Neural BRDF representation and
  importance sampling", Computer Graphics Forum 40(6), 2021.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Mapping
from functools import lru_cache
from types import SimpleNamespace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import BSpline, CubicSpline
from scipy.optimize import least_squares, nnls
from scipy.special import digamma, gammaln
from threadpoolctl import threadpool_limits

from basis.validation import nonneg_int

from .brdf import BRDF
from .crossval import fold_report, out_of_fold
from .factored import D_WARPS, PHI_TURNS, WARPS, FactoredLobe, fit_factored
from .measurements import Measurements
from .models import CookTorrance
from .sampling import DEFAULT_WIDTHS, brdf_errors, peak_resolving_pairs

__all__ = ["FAMILIES", "FittedModel", "fit_model"]

#: The parametric families :func:`fit_model` knows.
FAMILIES = ("lambert+ggx", "lambert+beckmann", "lafortune", "factored", "dsbrdf", "rr8807")
METRICS = ("l2", "log")
#: Options of :func:`fit_model` and their defaults (``lobes`` is for "lafortune", default 1,
#: and "dsbrdf", default 3; ``wavelength`` for "rr8807").
DEFAULTS = {"n": 2 ** 14, "seed": 0, "restarts": 4, "lobes": None, "max_nfev": None,
            "error_n": 2 ** 16, "error_seed": None, "widths": DEFAULT_WIDTHS,
            "wavelength": None}
_LOBES = {"lafortune": 1, "dsbrdf": 3}
#: Options of :func:`fit_model` for measurements (``folds``: of the cross-validation, 0 to
#: skip it).
SAMPLE_DEFAULTS = {"seed": 0, "restarts": 4, "lobes": None, "max_nfev": None,
                   "wavelength": None, "folds": 10}
#: Options of :func:`fit_model` for family "factored": those of
#: :func:`project.factored.fit_factored`, and the error pairs.
FACTORED_OPTIONS = ("rank", "bins", "warp", "warp_d", "color", "samples", "diffuse", "seed",
                    "max_iter", "tol", "accelerate", "phi_turn")
_ERROR_OPTIONS = ("error_n", "error_seed", "widths")
_LOG_CAP = 690.0  # cap on log of a lobe value (e^690 ~ 1e299): keeps every value finite
#: Bounds of the Lafortune exponent n and of t = n log|Cx / Cz|: (V + Cx U)^n <= e^|t|.
_N_MAX, _T_MAX = 1e5, 20.0
_SQRT2 = float(np.sqrt(2.0))


class _Geometry:
    """Flat pair geometry: cosines, c_d = w_i . h and the products of Lafortune's form."""

    def __init__(self, wi: NDArray, wo: NDArray) -> None:
        # as given (within 1e-6 of unit length): CookTorrance renormalises them itself
        self.wi, self.wo = np.ascontiguousarray(wi), np.ascontiguousarray(wo)
        wi = wi / np.linalg.norm(wi, axis=1)[:, None]
        wo = wo / np.linalg.norm(wo, axis=1)[:, None]
        self.ci = np.clip(wi[:, 2], 0.0, 1.0)
        self.co = np.clip(wo[:, 2], 0.0, 1.0)
        self.cd = np.clip(0.5 * np.linalg.norm(wi + wo, axis=1), 0.0, 1.0)
        self.u = wi[:, 0] * wo[:, 0] + wi[:, 1] * wo[:, 1]
        self.v = wi[:, 2] * wo[:, 2]
        self.n = wi.shape[0]
        # half vector: cos and sin^2 of theta_h; sines of theta_i, theta_o (rr8807, dsbrdf)
        h = wi + wo
        hn2 = np.sum(h * h, axis=1)
        hn2 = np.where(hn2 > 0.0, hn2, 1.0)
        self.ch = np.clip(h[:, 2] / np.sqrt(hn2), 0.0, 1.0)
        self.sh2 = np.clip((h[:, 0] ** 2 + h[:, 1] ** 2) / hn2, 0.0, 1.0)
        self.si = np.hypot(wi[:, 0], wi[:, 1])
        self.so = np.hypot(wo[:, 0], wo[:, 1])


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


# -- DSBRDF (seed 001) --------------------------------------------------------------------------

#: Knots of the quadratic B-splines of kappa(theta_d) and gamma(theta_d): five uniform knots
#: on [0, pi/2], clamped, so 6 coefficients per curve.
DS_KNOTS = np.r_[0.0, 0.0, np.linspace(0.0, np.pi / 2, 5), np.pi / 2, np.pi / 2]
DS_COEFFS = len(DS_KNOTS) - 3
#: Bounds of the DSBRDF spline coefficients (kappa, gamma) and of the rr8807 (sigma, p, a).
_KAPPA = (1e-6, 25.0)
_GAMMA = (1e-3, 1e6)
_SIGMA, _P, _A = (1e-4, 1.5), (0.15, 5.0), (1e-2, 50.0)
#: Wavelengths (um) of the red, green and blue channels in Holzschuch & Pacanowski 2015.
RGB_WAVELENGTHS = (0.645, 0.526, 0.444)


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
    # stop on a 1e-6 relative cost decrease (see the module notes), in the log-scale units
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


# -- Holzschuch & Pacanowski RR-8807 (seed 004) ---------------------------------------------------

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


def _check_family(family: object) -> str:
    if not isinstance(family, str) or family not in FAMILIES:
        raise ValueError(f"family must be one of {', '.join(map(repr, FAMILIES))}, got "
                         f"{family!r}")
    return family


def _family(family: object, channels: int, lobes: int = 1,
            wavelength: NDArray | None = None):
    _check_family(family)
    if family == "lafortune":
        return _Lafortune(lobes, channels)
    if family == "dsbrdf":
        return _DSBRDF(lobes, channels)
    if family == "rr8807":
        return _RR8807(channels, _wavelengths(wavelength, channels))
    return _Microfacet(family.split("+")[1], channels)


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


# -- the fitted model -------------------------------------------------------------------------

class FittedModel(BRDF):
    """A parametric BRDF fitted by :func:`fit_model` (or built from known parameters).

    Parameters
    ----------
    family : {"lambert+ggx", "lambert+beckmann", "lafortune", "factored", "dsbrdf", "rr8807"}
    params : dict of str to array_like of float
        The family's parameters (module notes): ``kd``, ``ks`` (C,), ``alpha``, ``f0``
        (scalars) for the microfacet families; ``kd`` (C,), ``rho`` (L, C), ``cx`` (< 0),
        ``cz`` (= 1), ``n`` (L,) for "lafortune"; the tables of
        :attr:`project.factored.FactoredLobe.params` for "factored"; ``kappa``, ``gamma``
        (K, 6, C) for "dsbrdf"; ``kd``, ``ks``, ``kw``, ``f0`` (C,), ``sigma``, ``p``,
        ``a`` (scalars) and optionally ``wavelength`` (C,) for "rr8807". C, the number of
        channels, is the length of ``kd`` (the last axis of ``kappa``).
    info : dict, optional
        What :func:`fit_model` measured (empty for a model built by hand).

    Attributes
    ----------
    family : str
    params : dict of str to ndarray
        Copies of the parameters (read-only arrays).
    nparams : int
        Number of real parameters (2 C + 2; C + L (C + 2); 12 K C; 4 C + 3).
    nbytes : int
        8 * nparams (float64 storage).
    info : dict
        ``"l2"``, ``"log"``, ``"l2_stderr"`` (on pairs independent of the fit),
        ``"iterations"``, ``"restarts"``, ``"cost"`` (per restart), ``"converged"``,
        ``"param_stderr"``, ``"seconds"``, and more (see :func:`fit_model`).

    Examples
    --------
    >>> m = FittedModel("lambert+ggx", {"kd": [0.5, 0.4, 0.3], "ks": [1.0, 1.0, 1.0],
    ...                                 "alpha": 0.2, "f0": 1.0})
    >>> m.nparams, m.nbytes, m.channels
    (8, 64, 3)
    >>> from project.models import CookTorrance
    >>> w = np.array([0.6, 0.0, 0.8])
    >>> bool(np.allclose(m.eval(w, w), CookTorrance([0.5, 0.4, 0.3], 0.2, "ggx").eval(w, w)))
    True
    """

    isotropic = True
    reciprocal = True

    def __init__(self, family: str, params: Mapping[str, ArrayLike], *,
                 info: dict | None = None) -> None:
        if not isinstance(params, Mapping):
            raise TypeError(f"params must be a dict of parameter arrays, got "
                            f"{type(params).__name__}")
        if _check_family(family) == "factored":
            self._init_factored(params, info)
            return
        if family == "dsbrdf":
            kappa = _param(params, "kappa", 3, low=0.0)
            if kappa.ndim != 3 or kappa.shape[1] != DS_COEFFS or 0 in kappa.shape:
                raise ValueError(f"params['kappa'] must have shape (lobes, {DS_COEFFS}, "
                                 f"channels), got {kappa.shape}")
            c = kappa.shape[2]
            model = _DSBRDF(kappa.shape[0], c)
            shapes = {"kappa": kappa.shape, "gamma": kappa.shape}
        else:
            c = _param(params, "kd", 1).size
        if family == "rr8807":
            model = _RR8807(c, _wavelengths(params.get("wavelength"), c))
            shapes = {"kd": (c,), "ks": (c,), "kw": (c,), "f0": (c,), "sigma": (), "p": (),
                      "a": (), "wavelength": (c,)}
        elif family == "lafortune":
            n = _param(params, "n", 1, low=0.0)
            model = _Lafortune(n.size, c)
            shapes = {"kd": (c,), "rho": (n.size, c), "cx": (n.size,), "cz": (n.size,),
                      "n": (n.size,)}
        elif family != "dsbrdf":
            model = _Microfacet(family.split("+")[1], c)
            shapes = {"kd": (c,), "ks": (c,), "alpha": (), "f0": ()}
        if family == "rr8807" and "wavelength" not in params:  # optional: the default
            params = {**params, "wavelength": model.lam}
        if set(params) != set(shapes):
            raise ValueError(f"params of family {family!r} must be exactly "
                             f"{sorted(shapes)}, got {sorted(params)}")
        lows = {"kd": 0.0, "ks": 0.0, "rho": 0.0, "n": 0.0, "f0": 0.0, "kw": 0.0,
                "gamma": 0.0, "kappa": 0.0}
        p = {}
        for name, shape in shapes.items():
            v = _param(params, name, len(shape), low=lows.get(name))
            if v.shape != shape:
                raise ValueError(f"params[{name!r}] must have shape {shape} (channels "
                                 f"{c} from {'kappa' if family == 'dsbrdf' else 'kd'}), "
                                 f"got {v.shape}")
            v.flags.writeable = False
            p[name] = v
        if "alpha" in p and not (p["alpha"] > 0.0 and p["f0"] <= 1.0):
            raise ValueError(f"alpha must be > 0 and f0 <= 1, got {float(p['alpha'])}, "
                             f"{float(p['f0'])}")
        if "cx" in p and not (np.all(p["cz"] == 1.0) and np.all(p["cx"] < 0.0)):
            raise ValueError(f"cz must be 1 (the scale of C is in rho) and cx < 0 (forward "
                             f"lobes) for every lobe, got cx={p['cx']}, cz={p['cz']}")
        if "sigma" in p and not (p["sigma"] > 0.0 and _P[0] <= p["p"] <= _P[1]
                                 and p["a"] > 0.0):
            raise ValueError(f"sigma and a must be > 0 and p in [{_P[0]}, {_P[1]}] (where the "
                             f"shadowing is tabulated), got sigma={float(p['sigma'])}, "
                             f"p={float(p['p'])}, a={float(p['a'])}")
        self.family = family
        self.params = p
        self.channels = c
        self._scalar = c == 1
        self._model = model
        self._x = model.vector(p)
        self.nparams = int(model.p)
        self.nbytes = 8 * self.nparams
        self.info = {} if info is None else dict(info)

    def _init_factored(self, params: Mapping[str, ArrayLike], info: dict | None) -> None:
        required = {"kd", "h_table", "d_table", "warp", "warp_d"}
        allowed = required | {"phi_table", "weights", "phi_turn"}
        if not required <= set(params) <= allowed:
            raise ValueError(f"params of family 'factored' must hold {sorted(required)} and "
                             f"optionally 'phi_table', 'weights' and 'phi_turn', got "
                             f"{sorted(params)}")
        warps = {}
        for name, table in (("warp", WARPS), ("warp_d", D_WARPS)):
            v = _param(params, name, 0)
            names = [k for k, p in table.items() if v.ndim == 0 and p == float(v)]
            if not names:
                raise ValueError(f"params[{name!r}] must be the exponent of one of the warps "
                                 f"{table}, got {v}")
            warps[name] = names[0]
        if "phi_turn" in params:  # absent: a half-turn lobe (the only kind before 'full')
            v = _param(params, "phi_turn", 0)
            names = [k for k, p in PHI_TURNS.items() if v.ndim == 0 and p == float(v)]
            if not names:
                raise ValueError(f"params['phi_turn'] must be the fraction of the turn of one "
                                 f"of {PHI_TURNS}, got {v}")
            warps["phi_turn"] = names[0]
        # FactoredLobe checks shapes, signs and channels of the tables
        self._model = FactoredLobe(
            _param(params, "kd", 1, low=0.0), params["h_table"], params["d_table"],
            phi_table=params.get("phi_table"), weights=params.get("weights"), **warps)
        self.family = "factored"
        self.reciprocal = self._model.reciprocal
        self.params = self._model.params
        self.channels = self._model.channels
        self._scalar = self.channels == 1
        self.nparams = self._model.nparams
        self.nbytes = self._model.nbytes
        self.info = {} if info is None else dict(info)

    def _eval(self, wi: NDArray, wo: NDArray) -> NDArray:
        if self.family == "factored":
            return self._model._eval(wi, wo)
        return self._model.value(self._x, _Geometry(wi, wo))

    def __repr__(self) -> str:
        if self.family == "factored":
            m = self._model
            turn = "" if m.phi_turn == "half" else f", phi_turn={m.phi_turn!r}"
            return (f"FittedModel('factored', rank={m.rank}, bins={m.bins}, warp={m.warp!r}, "
                    f"warp_d={m.warp_d!r}{turn}, channels={self.channels}, "
                    f"nbytes={self.nbytes})")

        def fmt(v: NDArray) -> str:
            return np.array2string(np.asarray(v), precision=4, separator=", ")
        args = ", ".join(f"{k}={fmt(v)}" for k, v in self.params.items())
        return f"FittedModel({self.family!r}, {args})"


def _param(params: Mapping, name: str, ndim: int, *, low: float | None = None) -> NDArray:
    if name not in params:
        raise ValueError(f"params must hold {name!r}, got the keys {sorted(params)}")
    try:
        v = np.array(params[name], dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"params[{name!r}] must be numbers, got {params[name]!r}") from None
    if ndim >= 1 and v.ndim == 0:
        v = v.reshape(1)
    if not np.all(np.isfinite(v)) or (low is not None and np.any(v < low)):
        raise ValueError(f"params[{name!r}] must be finite"
                         + ("" if low is None else f" and >= {low}") + f", got {v}")
    return v


# -- fitting ----------------------------------------------------------------------------------

def fit_model(brdf: object, family: str, *, metric: str = "l2", **options) -> FittedModel:
    """Fit a parametric family to a BRDF by weighted non-linear least squares.

    Parameters
    ----------
    brdf : BRDF
        Any object with ``eval(wi, wo)`` returning finite values >= 0 (an analytic model,
        :func:`project.measured.read_merl`, a coefficient matrix...). Delta terms are not
        fitted (warned).
    family : {"lambert+ggx", "lambert+beckmann", "lafortune", "factored", "dsbrdf", "rr8807"}
        See the module notes for each family's parameters and bounds.
    metric : {"l2", "log"}
        What the fit minimises: the relative l2 error of q = f cos theta_i cos theta_o, or
        the RMS of log(1 + f cos theta_i) (module notes).
    **options
        ``n`` (fitting pairs, default 16384), ``seed`` (default 0), ``restarts`` (starting
        points, default 4; use 8 or more for multi-lobe Lafortune), ``lobes`` (lobes of
        "lafortune", default 1, or of "dsbrdf", default 3), ``wavelength`` ("rr8807": um
        per channel, default the report's RGB for 3 channels), ``max_nfev`` (function
        evaluations per restart, default scipy's 100 x the number of parameters, per
        channel for "dsbrdf"), ``error_n`` (pairs of the error estimate,
        default 65536), ``error_seed`` (default ``seed + 1``, must differ from ``seed``) and
        ``widths`` (the lobe widths of :func:`project.sampling.peak_resolving_pairs` for both
        pair sets; add a narrower one for very sharp highlights, module notes).

    Returns
    -------
    FittedModel
        ``info`` holds ``"l2"``, ``"log"``, ``"l2_stderr"`` (:func:`project.sampling.
        brdf_errors` on the independent error pairs), ``"fit_l2"`` or ``"fit_log"`` (the
        minimised error on the fitting pairs, largest channel), ``"iterations"`` (Jacobian
        evaluations of the best restart), ``"nfev"`` (per restart), ``"restarts"``,
        ``"cost"`` (final 0.5 sum r^2 per restart), ``"status"`` (scipy's, per restart),
        ``"best_restart"``, ``"converged"``, ``"param_stderr"`` (dict like ``params``),
        ``"metric"``, ``"samples"`` (descriptions of both pair sets) and ``"seconds"``.
        For "factored": the errors, ``"fit_l2"`` (on the fitting rule) and the report of
        :func:`project.factored.fit_factored` (``"iterations"``, ``"converged"``,
        ``"floor"``, ``"history"``, ...).

    Raises
    ------
    TypeError
        ``brdf`` has no ``eval``, an option is unknown or of the wrong type.
    ValueError
        Unknown family (the known ones are listed) or metric, an option out of range, or
        the BRDF returns non-finite or negative values, or only zeros, at the fitting pairs.

    Warns
    -----
    RuntimeWarning
        The best restart stopped at ``max_nfev`` without meeting a tolerance; the message
        gives the best error reached.

    Examples
    --------
    >>> from project.models import CookTorrance
    >>> fit = fit_model(CookTorrance([0.3, 0.2, 0.1], 0.15, "ggx"), "lambert+ggx",
    ...                 n=2048, restarts=1, error_n=2048)
    >>> round(float(fit.params["alpha"]), 3), fit.nparams
    (0.15, 8)
    >>> bool(fit.info["l2"] < 1e-3) and fit.info["converged"]
    True
    """
    start = time.perf_counter()
    if not isinstance(metric, str) or metric not in METRICS:
        raise ValueError(f"metric must be one of {', '.join(map(repr, METRICS))}, got "
                         f"{metric!r}")
    if isinstance(brdf, Measurements):
        return _fit_samples(brdf, _check_family(family), metric, options, start)
    if _check_family(family) == "factored":
        return _fit_factored(brdf, metric, options, start)
    opts = _options(family, options)
    if not callable(getattr(brdf, "eval", None)):
        raise TypeError(f"brdf must be a BRDF (an object with eval(wi, wo)) or "
                        f"project.Measurements, got {type(brdf).__name__}")
    if getattr(brdf, "delta", ()):
        warnings.warn(f"{brdf!r} has delta (ideal mirror) terms; fit_model fits only its "
                      "eval() part", UserWarning, stacklevel=2)
    samples = peak_resolving_pairs(opts["n"], seed=opts["seed"], widths=opts["widths"])
    f = _target(brdf, samples)
    model = _family(family, f.shape[1], opts["lobes"], opts["wavelength"])
    fitted, report = _fit_parametric(family, model, _Geometry(samples.wi, samples.wo), f,
                                     samples.weights, metric, opts)
    err = brdf_errors(brdf, fitted, peak_resolving_pairs(
        opts["error_n"], seed=opts["error_seed"], widths=opts["widths"]))
    fitted.info = {
        **err, **report,
        "samples": {"fit": samples.description,
                    "error": f"error_n={opts['error_n']}, error_seed={opts['error_seed']}"},
        "seconds": time.perf_counter() - start,
    }
    return fitted


def _fit_parametric(family: str, model, geom: _Geometry, f: NDArray, w: NDArray, metric: str,
                    opts: dict, stacklevel: int = 3) -> tuple[FittedModel, dict]:
    """Fit ``model`` to values ``f`` (n, C) at ``geom`` with weights ``w``.

    Every restart is run and the best kept. Returns the model and the report of the fit
    (what ``info`` holds); warns at ``stacklevel`` (0: not) when the fit did not converge.
    """
    c = f.shape[1]
    lo, hi = model.bounds
    runs = []
    # the solver factors tall, narrow Jacobians (samples x ~10 parameters) at every step:
    # a second BLAS thread only adds synchronisation, and when another process holds a core
    # it costs 40x (SVD of 4317 x 15: 4 ms on one thread, 175 ms on two, 2 cores loaded)
    with threadpool_limits(1, user_api="blas"):
        for k in range(opts["restarts"]):
            rng = np.random.default_rng(np.random.SeedSequence([opts["seed"], k]))
            runs.append(_solve(model, geom, f, w, metric, k, rng, opts["max_nfev"]))
    costs = [float(r.cost) for r in runs]
    best = int(np.argmin(costs))
    run = runs[best]
    r2 = (run.fun.reshape(geom.n, c) ** 2).sum(axis=0)
    fit_err = float(np.sqrt(r2.max()))  # per-channel relative l2 (or log RMS) on the fit pairs
    converged = bool(run.status > 0)
    if not converged and stacklevel:
        why = (f"every one of the {opts['restarts']} restarts stopped" if
               all(r.status == 0 for r in runs) else "the best restart stopped")
        warnings.warn(f"fit_model({family!r}, metric={metric!r}) did not converge: {why} at "
                      f"max_nfev={opts['max_nfev']}; best {metric} error reached on the "
                      f"fitting pairs {fit_err:.4g} (raise max_nfev or restarts)",
                      RuntimeWarning, stacklevel=stacklevel)
    x = np.clip(run.x, lo, hi)
    with threadpool_limits(1, user_api="blas"):
        cov = _covariance(run.jac, run.fun, model.p)
    report = {
        f"fit_{metric}": fit_err,
        "iterations": int(run.njev or 0),
        "nfev": [int(r.nfev) for r in runs],
        "restarts": opts["restarts"],
        "cost": costs,
        "status": [int(r.status) for r in runs],
        "best_restart": best,
        "converged": converged,
        "param_stderr": model.natural_stderr(x, cov),
        "metric": metric,
    }
    return FittedModel(family, model.params(x)), report


def _fit_samples(meas: Measurements, family: str, metric: str, options: dict,
                 start: float) -> FittedModel:
    """fit_model(measurements, family): a weighted fit to the samples, cross-validated."""
    if family == "factored":
        raise ValueError(
            "family 'factored' tabulates a BRDF on a dense rule in the half/difference angles "
            "and needs a BRDF that can be evaluated anywhere; scattered samples do not cover "
            f"its tables. Fit a parametric family to {meas!r} ('lambert+ggx', "
            "'lambert+beckmann', 'lafortune', 'dsbrdf', 'rr8807'), or compare them with "
            "compress.select(measurements, tol)")
    unknown = sorted(set(options) - set(SAMPLE_DEFAULTS))
    if unknown:
        hint = (" (the samples are the measurements: n, error_n, error_seed and widths "
                "choose pairs of a BRDF)" if set(unknown) & set(DEFAULTS) else "")
        raise TypeError(f"fit_model() got unknown option(s) {', '.join(map(repr, unknown))} "
                        f"for measurements{hint}; the options are "
                        f"{', '.join(map(repr, SAMPLE_DEFAULTS))}")
    opts = _options(family, {k: v for k, v in options.items() if k != "folds"})
    k = nonneg_int(options.get("folds", SAMPLE_DEFAULTS["folds"]), "folds")
    if k == 1:
        raise ValueError("folds must be 0 (no cross-validation) or >= 2, got 1")
    wavelength = opts["wavelength"]
    if family == "rr8807" and wavelength is None and meas.wavelengths is not None:
        wavelength = meas.wavelengths / 1000.0  # nm -> um
    model = _family(family, meas.channels, opts["lobes"], wavelength)
    fit_values = meas.values
    if metric == "log" and np.any(fit_values * meas.wi[:, 2:3] <= -1.0):
        raise ValueError("the log metric needs f cos(theta_i) > -1 at every sample; "
                         f"{meas!r} has values below that")

    def fit_on(m: Measurements, stacklevel: int = 0) -> tuple[FittedModel, dict]:
        return _fit_parametric(family, model, _Geometry(m.wi, m.wo), m.values, m.weights,
                               metric, opts, stacklevel=stacklevel)

    fitted, report = fit_on(meas, stacklevel=4)
    info: dict = {"l2": None, "l2_stderr": None, "log": None, "log_stderr": None}
    if k:
        folds = meas.folds(k, seed=opts["seed"], by="pairs")
        if np.unique(folds).size >= 2:
            (pred,) = out_of_fold(meas, lambda m: fit_on(m)[0], folds)
            info = fold_report(meas, pred, folds, "pairs", start)
            info.pop("seconds")
    fitted.info = {**info, **report, "samples": {"fit": repr(meas), "count": len(meas)},
                   "seconds": time.perf_counter() - start}
    if info["l2"] is not None and info["l2"] >= 1.0:
        warnings.warn(f"fit_model({family!r}) predicts the held-out samples of {meas!r} no "
                      f"better than zero: cross-validated l2 error {info['l2']:.3g} >= 1. "
                      "The family cannot follow these data; compare the families (and "
                      "expansions) with compress.select(measurements, tol)", RuntimeWarning,
                      stacklevel=3)
    return fitted


def _fit_factored(brdf: object, metric: str, options: dict, start: float) -> FittedModel:
    """fit_model(brdf, "factored"): fit_factored, then the errors on independent pairs."""
    if metric != "l2":
        raise ValueError(f"family 'factored' is fitted in the l2 metric only, got metric="
                         f"{metric!r}")
    unknown = sorted(set(options) - set(FACTORED_OPTIONS) - set(_ERROR_OPTIONS))
    if unknown:
        raise TypeError(f"fit_model() got unknown option(s) {', '.join(map(repr, unknown))} "
                        f"for family 'factored'; its options are "
                        f"{', '.join(map(repr, FACTORED_OPTIONS + _ERROR_OPTIONS))}")
    seed = nonneg_int(options.get("seed", 0), "seed")
    error_n = nonneg_int(options.get("error_n", DEFAULTS["error_n"]), "error_n")
    error_seed = options.get("error_seed")
    error_seed = seed + 1 if error_seed is None else nonneg_int(error_seed, "error_seed")
    widths = options.get("widths", DEFAULTS["widths"])
    lobe = fit_factored(brdf, **{k: v for k, v in options.items() if k in FACTORED_OPTIONS})
    fitted = FittedModel("factored", lobe.params)
    err = brdf_errors(brdf, fitted, peak_resolving_pairs(error_n, seed=error_seed,
                                                         widths=widths))
    fitted.info = {**lobe.info, **err, "fit_l2": lobe.info["error"], "metric": metric,
                   "rank": lobe.rank, "bins": lobe.bins, "warp": lobe.warp,
                   "warp_d": lobe.warp_d, "phi_turn": lobe.phi_turn, "restarts": 1,
                   "samples": {"fit": "project.factored.rusinkiewicz_rule",
                               "error": f"error_n={error_n}, error_seed={error_seed}"},
                   "seconds": time.perf_counter() - start}
    return fitted


def _options(family: str, options: dict) -> dict:
    unknown = sorted(set(options) - set(DEFAULTS))
    if unknown:
        raise TypeError(f"fit_model() got unknown option(s) {', '.join(map(repr, unknown))}; "
                        f"the options are {', '.join(map(repr, DEFAULTS))}")
    if "lobes" in options and family not in _LOBES:
        raise ValueError(f"option 'lobes' applies to families 'lafortune' and 'dsbrdf' only, "
                         f"got family {family!r}")
    if "wavelength" in options and family != "rr8807":
        raise ValueError(f"option 'wavelength' applies to family 'rr8807' only, got family "
                         f"{family!r}")
    o = {**DEFAULTS, **options}
    if o["lobes"] is None:
        o["lobes"] = _LOBES.get(family, 1)
    o["n"] = nonneg_int(o["n"], "n")
    o["seed"] = nonneg_int(o["seed"], "seed")
    o["restarts"] = nonneg_int(o["restarts"], "restarts", maximum=1000)
    o["lobes"] = nonneg_int(o["lobes"], "lobes", maximum=8)
    o["error_n"] = nonneg_int(o["error_n"], "error_n")
    if o["restarts"] < 1:
        raise ValueError(f"restarts must be >= 1, got {o['restarts']}")
    if o["lobes"] < 1:
        raise ValueError(f"lobes must be >= 1, got {o['lobes']}")
    if o["max_nfev"] is not None:
        o["max_nfev"] = nonneg_int(o["max_nfev"], "max_nfev")
        if o["max_nfev"] < 1:
            raise ValueError(f"max_nfev must be >= 1 or None, got {o['max_nfev']}")
    o["error_seed"] = o["seed"] + 1 if o["error_seed"] is None else \
        nonneg_int(o["error_seed"], "error_seed")
    if o["error_seed"] == o["seed"]:
        raise ValueError(f"error_seed must differ from seed (the errors are measured on pairs "
                         f"independent of the fit), got {o['error_seed']} for both")
    return o


def _target(brdf: object, samples) -> NDArray[np.float64]:
    """Evaluate the BRDF at the fitting pairs as (n, C), checked finite, >= 0, not all 0."""
    f = np.asarray(brdf.eval(samples.wi, samples.wo), dtype=np.float64)
    if f.ndim not in (1, 2) or f.shape[0] != len(samples):
        raise ValueError(f"brdf.eval(wi, wo) must return shape (n,) or (n, channels) for n = "
                         f"{len(samples)} pairs, got {f.shape}")
    f = f.reshape(len(samples), -1)
    bad = ~np.isfinite(f)
    if bad.any():
        i = int(np.argwhere(bad)[0, 0])
        raise ValueError(f"brdf must be finite at the fitting pairs: {int(bad.sum())} values "
                         f"are NaN or inf (first at wi={samples.wi[i]}, wo={samples.wo[i]})")
    if np.any(f < 0.0):
        i = int(np.argwhere(f < 0.0)[0, 0])
        raise ValueError(f"brdf must be >= 0 at the fitting pairs: {int(np.sum(f < 0))} "
                         f"values are negative, min {f.min():.6g} (first at wi="
                         f"{samples.wi[i]}, wo={samples.wo[i]})")
    if np.any(np.all(f == 0.0, axis=0)):
        raise ValueError("brdf must not be 0 at every fitting pair (channel "
                         f"{int(np.flatnonzero(np.all(f == 0.0, axis=0))[0])})")
    return f


def _solve(model, g: _Geometry, f: NDArray, w: NDArray, metric: str, k: int,
           rng: np.random.Generator, max_nfev: int | None):
    """One restart: least_squares from start k, channel by channel for a separable family.

    A separable family (no parameter shared between channels) has a cost that is a sum of
    per-channel costs; solving each channel alone reaches the same optimum with a Jacobian C
    times narrower (the solves cost ~C^2 less). The result is put together as if one solve:
    x, fun and a block Jacobian in the joint layout, the summed cost and evaluations, and the
    worst status.
    """
    if not getattr(model, "separable", False):
        res_fn, jac_fn, row = _objective(model, g, f, w, metric)
        x0 = _start(model, g, f, row, k, rng)
        return least_squares(res_fn, x0, jac=jac_fn, bounds=model.bounds, method="trf",
                             x_scale="jac", max_nfev=max_nfev)
    sub = model.channel_model()
    c, per = f.shape[1], sub.p
    runs = []
    for ch in range(c):
        res_fn, jac_fn, row = _objective(sub, g, f[:, ch:ch + 1], w, metric)
        x0 = sub.start(g, f[:, ch:ch + 1], row, k, rng)
        runs.append(least_squares(res_fn, x0, jac=jac_fn, bounds=sub.bounds, method="trf",
                                  x_scale=sub.x_scale, ftol=sub.ftol, max_nfev=max_nfev))
    jac = np.zeros((g.n, c, model.p))
    for ch, r in enumerate(runs):
        jac[:, ch, ch * per:(ch + 1) * per] = r.jac
    statuses = [int(r.status) for r in runs]
    return SimpleNamespace(
        x=np.concatenate([r.x for r in runs]), cost=float(sum(r.cost for r in runs)),
        fun=np.stack([r.fun for r in runs], axis=1).ravel(), jac=jac.reshape(g.n * c, -1),
        status=min(statuses) if min(statuses) <= 0 else max(statuses),
        nfev=int(sum(r.nfev for r in runs)), njev=int(sum(r.njev or 0 for r in runs)))


def _objective(model, g: _Geometry, f: NDArray, w: NDArray, metric: str):
    """Residual and Jacobian functions of the metric, and the row weights for NNLS starts."""
    n, c = f.shape
    cc = g.ci * g.co
    if metric == "l2":
        q = f * cc[:, None]
        scale = np.sqrt(w)[:, None] / np.sqrt(np.sum(w[:, None] * q * q, axis=0))

        def res(x: NDArray) -> NDArray:
            return (scale * (model.value(x, g) * cc[:, None] - q)).ravel()

        def jac(x: NDArray) -> NDArray:
            _, df = model.value(x, g, jac=True)
            return ((scale * cc[:, None])[:, :, None] * df).reshape(n * c, -1)

        return res, jac, scale * cc[:, None]
    ci = g.ci[:, None]
    target = np.log1p(f * ci)
    scale = np.sqrt(w / np.sum(w))[:, None]

    def res_log(x: NDArray) -> NDArray:
        return (scale * (np.log1p(model.value(x, g) * ci) - target)).ravel()

    def jac_log(x: NDArray) -> NDArray:
        fm, df = model.value(x, g, jac=True)
        return ((scale * ci / (1.0 + fm * ci))[:, :, None] * df).reshape(n * c, -1)

    # starts: the l2 rows (the log metric is not linear in kd, ks)
    l2 = np.sqrt(w)[:, None] / np.sqrt(np.sum(w[:, None] * (f * cc[:, None]) ** 2, axis=0))
    return res_log, jac_log, l2 * cc[:, None]


def _start(model, g: _Geometry, f: NDArray, row: NDArray, k: int,
           rng: np.random.Generator) -> NDArray:
    """Return the starting point of restart k.

    The nonlinear part comes from a grid (k = 0) or at random, the linear part (kd and ks or
    rho) from non-negative least squares per channel.
    """
    lo, hi = model.bounds
    # the trailing nonlinear reals (2 per lobe), or the family's own start vector
    nl_lo, nl_hi = getattr(model, "nl_bounds", (lo[-2 * model.k:], hi[-2 * model.k:]))
    candidates = model.nonlinear_grid() if k == 0 else [model.nonlinear_random(rng)]
    best = None
    for xnl in candidates:
        xnl = np.clip(xnl, nl_lo, nl_hi)
        cols = model.columns(xnl, g)  # (n, m) shared, or (n, C, m) per channel
        lin = np.empty((f.shape[1], cols.shape[-1]))
        cost = 0.0
        for ch in range(f.shape[1]):
            a = (cols if cols.ndim == 2 else cols[:, ch]) * row[:, ch:ch + 1]
            lin[ch], rnorm = nnls(a, f[:, ch] * row[:, ch], maxiter=50 * a.shape[1])
            cost += rnorm ** 2
        if best is None or cost < best[0]:
            best = (cost, xnl, lin)
    _, xnl, lin = best
    x = model.assemble(lin, xnl) if hasattr(model, "assemble") else \
        np.r_[lin[:, 0], lin[:, 1:].T.ravel(), xnl]
    # strictly inside the bounds (the trust-region reflective method needs it)
    span = hi - lo
    return np.clip(x, lo + 1e-6 * span, hi - 1e-6 * span)


def _covariance(jac: NDArray, fun: NDArray, p: int) -> NDArray:
    """(J^T J)^-1 s^2 with s^2 = sum r^2 / (m - p); inf where the data do not determine."""
    m = fun.size
    s2 = float(fun @ fun) / max(m - p, 1)
    norms = np.linalg.norm(jac, axis=0)
    cov = np.full((p, p), np.inf)
    ok = norms > 0.0
    if not ok.any():
        return cov
    # columns scaled to unit norm, so that the rank test does not depend on units
    _, sv, vt = np.linalg.svd(jac[:, ok] / norms[ok], full_matrices=False)
    good = sv > 1e-10 * sv[0]
    inner = (vt[good].T / sv[good] ** 2) @ vt[good] * s2 / np.outer(norms[ok], norms[ok])
    weak = np.any(np.abs(vt[~good]) > 1e-3, axis=0) if (~good).any() else \
        np.zeros(int(ok.sum()), bool)
    inner[weak, :] = np.inf
    inner[:, weak] = np.inf
    cov[np.ix_(ok, ok)] = inner
    return cov


def _sqrt_diag(cov: NDArray) -> NDArray:
    return np.sqrt(np.diag(cov))


def _quad(grad: NDArray, cov: NDArray) -> float:
    """sqrt(grad^T cov grad) (inf if an involved variance is inf)."""
    idx = grad != 0.0
    sub = cov[np.ix_(idx, idx)]
    if np.any(np.isinf(sub)):
        return float(np.inf)
    return float(np.sqrt(max(grad[idx] @ sub @ grad[idx], 0.0)))
