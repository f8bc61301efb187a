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

The public names are imported on first use (PEP 562), so ``import project`` loads neither
numba nor SciPy until a name is used.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import types
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # what static tools see; at run time __getattr__ imports these on first use
    from basis import __version__ as __version__

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
    from .tucker import TuckerBRDF, fit_tucker

#: public name -> the submodule that defines it (None: the name is that submodule)
_EXPORTS: dict[str, str | None] = {
    "measured": None, "models": None,
    "BRDF": "brdf", "MirrorDelta": "brdf",
    "FittedModel": "fitting", "fit_model": "fitting",
    "bin_samples": "lstsq", "fit": "lstsq", "read_table": "lstsq",
    "tessellate_hemisphere": "lstsq",
    "MatrixBRDF": "matrix_brdf",
    "Measurements": "measurements",
    "default_quantity": "quadrature", "project": "quadrature", "radial_table": "quadrature",
    "tail_fraction": "quadrature", "truncation_error": "quadrature",
    "Reciprocity": "reciprocity", "reciprocity": "reciprocity",
    "PairSamples": "sampling", "brdf_errors": "sampling", "peak_resolving_pairs": "sampling",
    "TabulatedBRDF": "tabulated", "tabulate": "tabulated",
    "TuckerBRDF": "tucker", "fit_tucker": "tucker",
}

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
    "TuckerBRDF",
    "bin_samples",
    "brdf_errors",
    "fit",
    "fit_model",
    "fit_tucker",
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


def __getattr__(name: str) -> Any:
    """Import a public name, ``__version__`` or a submodule on first use (PEP 562)."""
    if name in _EXPORTS:
        module = importlib.import_module(f"{__name__}.{_EXPORTS[name] or name}")
        value = module if _EXPORTS[name] is None else getattr(module, name)
    elif name == "__version__":  # one version for the distribution
        from basis import __version__ as value
    elif not name.startswith("__") and importlib.util.find_spec(f"{__name__}.{name}"):
        return importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # later look-ups are plain attribute reads
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__, "__version__"})


class _Package(types.ModuleType):
    """The package's module type: a submodule import does not hide a function of its name."""

    def __setattr__(self, name: str, value: Any) -> None:
        # importing project.reciprocity (the module) binds it on the package; the public
        # name is the function reciprocity, which __getattr__ fetches from that module
        if _EXPORTS.get(name) and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
