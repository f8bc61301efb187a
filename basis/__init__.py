"""The mathematics of scatmodes.

Spherical harmonics, hemisphere Zernike functions, Helmholtz surface scattering modes,
quadrature rules, the symmetric coefficient matrix and its evaluation.

``basis`` knows nothing of BRDF models, files or plots; ``project`` and ``compress`` build
on it, never the other way round.

The public names are imported on first use (PEP 562): ``import basis`` costs almost
nothing, and numba, NumPy and SciPy load when a basis is first built, so that the
``scatmodes`` command answers ``--version`` and ``--help`` at once.
"""

from __future__ import annotations

import importlib
import importlib.util
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # what static tools see; at run time __getattr__ imports these on first use
    from ._base import AzimuthalBlocks, Basis
    from .directions import from_angles, from_rusinkiewicz, to_angles, to_rusinkiewicz
    from .evaluate import Evaluator
    from .kinds import KINDS, make_basis
    from .matrix import QUANTITIES, CoefficientMatrix
    from .modes import HelmholtzModes
    from .quadrature import HemisphereRule, hemisphere_rule, sphere_rule
    from .sh import HemiHarmonics, SphericalHarmonics
    from .zernike import HemiZernike, zernike_radial

    __version__: str

#: public name -> the submodule that defines it
_EXPORTS = {
    "AzimuthalBlocks": "_base", "Basis": "_base",
    "from_angles": "directions", "from_rusinkiewicz": "directions", "to_angles": "directions",
    "to_rusinkiewicz": "directions",
    "Evaluator": "evaluate",
    "KINDS": "kinds", "make_basis": "kinds",
    "QUANTITIES": "matrix", "CoefficientMatrix": "matrix",
    "HelmholtzModes": "modes",
    "HemisphereRule": "quadrature", "hemisphere_rule": "quadrature", "sphere_rule": "quadrature",
    "HemiHarmonics": "sh", "SphericalHarmonics": "sh",
    "HemiZernike": "zernike", "zernike_radial": "zernike",
}

__all__ = [
    "KINDS",
    "QUANTITIES",
    "AzimuthalBlocks",
    "Basis",
    "CoefficientMatrix",
    "Evaluator",
    "HelmholtzModes",
    "HemiHarmonics",
    "HemiZernike",
    "HemisphereRule",
    "SphericalHarmonics",
    "from_angles",
    "from_rusinkiewicz",
    "hemisphere_rule",
    "make_basis",
    "sphere_rule",
    "to_angles",
    "to_rusinkiewicz",
    "zernike_radial",
]


def _version() -> str:
    # importlib.metadata costs ~0.1 s to import: only --version and callers who ask pay it
    from importlib.metadata import PackageNotFoundError, version

    try:  # the distribution "scatmodes" holds basis, project and compress: one version for all
        return version("scatmodes")
    except PackageNotFoundError:  # pragma: no cover - imported from a source tree, not installed
        return "unknown"


def __getattr__(name: str) -> Any:
    """Import a public name, ``__version__`` or a submodule on first use (PEP 562)."""
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    elif name == "__version__":
        value = _version()
    elif not name.startswith("__") and importlib.util.find_spec(f"{__name__}.{name}"):
        return importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # later look-ups are plain attribute reads
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__, "__version__"})
