"""Fits of parametric BRDF families to any BRDF: :func:`fit_model` returns a :class:`FittedModel`.

A :class:`FittedModel` is a :class:`~project.brdf.BRDF` (``eval``, ``channels``,
``isotropic``, ``albedo``) with its ``family``, fitted ``params``, ``nparams``, ``nbytes``
and an ``info`` dict that says how good the fit is: the errors of :mod:`project.sampling` on
pairs independent of the fitting pairs, with the Monte Carlo standard error, the cost of every
restart, convergence and parameter standard errors.

Families
--------
One module per family holds its model: the formula, the parameters and their bounds, its
references and, for the families taken from papers, the printed formulas that failed a check
(derived again and verified numerically in tests/project/test_fitting.py):

=========================================  =================================  ==============
family                                     module                             reals
=========================================  =================================  ==============
``"lambert+ggx"``, ``"lambert+beckmann"``  :mod:`project.fitting.microfacet`  2 C + 2
``"lafortune"``                            :mod:`project.fitting.lafortune`   C + L (C + 2)
``"factored"``                             :mod:`project.fitting.model`       271 (defaults)
``"dsbrdf"``                               :mod:`project.fitting.dsbrdf`      12 K C
``"rr8807"``                               :mod:`project.fitting.rr8807`      4 C + 3
``"tabulated"``                            :mod:`project.tabulated`           n_h n_d m C
``"tucker"``                               :mod:`project.tucker`              <= ``budget``
``"grid"``                                 :mod:`project.fitting.grid`        n (n+1)/2 m C
=========================================  =================================  ==============

C is the number of channels, L and K the number of lobes. The lobe of "factored" is
:class:`project.factored.FactoredLobe`; :mod:`project.fitting.model` describes how
:func:`fit_model` adapts it, and how the parametric families are fitted (the residuals of
each metric, the restarts, the parameter standard errors). The solver is in
``project/fitting/_solver.py``, the pair geometry the families share in
``project/fitting/_geometry.py``.

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

(reals in brackets; lambert+ggx as measured by compress.select; log RMS errors 0.015 / 0.029 /
0.014 for rr8807 and 0.011 / 0.010 / 0.019 for dsbrdf.) rr8807 gains most where the
highlight has long tails: its fits reach sigma ~2e-4 and p at or near the lower bound (0.24
on blue-acrylic, 0.15 on the other two), with F0 at its bound 1.2 in two channels of the
paint. The per-slice hemi-EPD lobes follow the theta_d dependence of these peaks far better
than one microfacet lobe: dsbrdf with 108 reals (864 bytes) is below the tabulated
separable lobe (project.factored: 0.18 / 0.21 / 0.13 at ~1.5 kB). Fits took 45-75 s (rr8807)
and 135-280 s (dsbrdf) on a shared, loaded machine (one BLAS thread). Across the 4
restarts rr8807 reached one minimum on all three (costs equal to 1e-5), dsbrdf did not:
blue-acrylic 0.03294 / 0.03336 / 0.03336 / 0.03489, alum-bronze 0.03401 / 0.03402 / 0.03668
/ 0.03707, gold-metallic-paint3 0.00908 (3) / 0.00915; use more restarts for dsbrdf. On
the nickel surrogate rr8807 gives sigma = 0.024, p = 0.47, a = 1.30 um^-1 (l2 0.229), near
the report's fit of the measured nickel (sigma 0.027, p 0.51, a 0.91) in sigma and p,
although the objective (cos^2 theta_i weighted, theta < 1.4 rad, two-step) differs.

References
----------
- G. H. Golub and V. Pereyra, "The differentiation of pseudo-inverses and nonlinear least
  squares problems whose variables separate", SIAM J. Numer. Anal. 10(2), 1973, pp. 413-432.
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

# __all__ names what `import *` brings; the other public names of the single module this
# package replaced stay importable from here (project.fitting.FACTORED_OPTIONS, ...)
from .dsbrdf import DS_COEFFS, DS_KNOTS  # noqa: F401
from .model import (  # noqa: F401
    DEFAULTS,
    FACTORED_OPTIONS,
    FAMILIES,
    GRID_OPTIONS,
    METRICS,
    SAMPLE_DEFAULTS,
    TABULATED_OPTIONS,
    TUCKER_OPTIONS,
    FittedModel,
    fit_model,
)
from .rr8807 import RGB_WAVELENGTHS  # noqa: F401

__all__ = ["FAMILIES", "FittedModel", "fit_model"]
