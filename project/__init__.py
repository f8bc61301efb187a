"""Where BRDFs come from and how they become coefficients.

- :mod:`project.models`: analytic BRDFs (Lambert, Phong, Ward, Cook-Torrance, ...).
- :mod:`project.measured`: measured BRDFs (MERL, RGL-EPFL ``.bsdf``) and goniometer tables.
- :class:`project.Measurements`: scattered samples; every fit to them is cross-validated
  (:mod:`project.crossval`).
- :func:`project.reciprocity`: how far a BRDF or a sample set is from f(w_i, w_o) =
  f(w_o, w_i), and the floor below which no reciprocal representation can go.
- :func:`project.project`: quadrature (or Monte Carlo, or least-squares) projection.
- :func:`project.fit`: least squares for scattered measurements.
- :func:`project.fit_model`: compact parametric models (microfacet, Lafortune lobes) fitted
  to any BRDF, with errors measured on peak-resolving pairs (:mod:`project.sampling`).
- :class:`project.MatrixBRDF`: a coefficient matrix evaluated and sampled as a BRDF (recursion).

Imports flow one way: ``compress`` -> ``project`` -> ``basis``.
"""

from basis import __version__  # noqa: F401 - one version for the distribution

from . import measured, models
from .brdf import BRDF, MirrorDelta
from .fitting import FittedModel, fit_model
from .lstsq import bin_samples, fit, read_table, tessellate_hemisphere
from .matrix_brdf import MatrixBRDF
from .measurements import Measurements
from .quadrature import default_quantity, project, radial_table, tail_fraction, truncation_error
from .reciprocity import Reciprocity, reciprocity
from .sampling import PairSamples, brdf_errors, peak_resolving_pairs
from .tabulated import TabulatedBRDF, tabulate

__all__ = [
    "BRDF",
    "FittedModel",
    "MatrixBRDF",
    "Measurements",
    "default_quantity",
    "MirrorDelta",
    "PairSamples",
    "Reciprocity",
    "TabulatedBRDF",
    "bin_samples",
    "brdf_errors",
    "fit",
    "fit_model",
    "measured",
    "models",
    "peak_resolving_pairs",
    "project",
    "radial_table",
    "reciprocity",
    "read_table",
    "tabulate",
    "tail_fraction",
    "tessellate_hemisphere",
    "truncation_error",
]
