"""Where BRDFs come from and how they become coefficients.

- :mod:`project.models`: analytic BRDFs (Lambert, Phong, Ward, Cook-Torrance, ...).
- :mod:`project.measured`: MERL files.
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

__all__ = [
    "BRDF",
    "FittedModel",
    "MatrixBRDF",
    "Measurements",
    "default_quantity",
    "MirrorDelta",
    "PairSamples",
    "Reciprocity",
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
    "tail_fraction",
    "tessellate_hemisphere",
    "truncation_error",
]
