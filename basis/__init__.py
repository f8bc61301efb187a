"""The mathematics of scatmodes.

Spherical harmonics, hemisphere Zernike functions, Helmholtz surface scattering modes,
quadrature rules, the symmetric coefficient matrix and its evaluation.

``basis`` knows nothing of BRDF models, files or plots; ``project`` and ``compress`` build
on it, never the other way round.
"""

from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _distribution_version

from ._base import AzimuthalBlocks, Basis
from .directions import from_angles, from_rusinkiewicz, to_angles, to_rusinkiewicz
from .evaluate import Evaluator
from .kinds import KINDS, make_basis
from .matrix import QUANTITIES, CoefficientMatrix
from .modes import HelmholtzModes
from .quadrature import HemisphereRule, hemisphere_rule, sphere_rule
from .sh import HemiHarmonics, SphericalHarmonics
from .zernike import HemiZernike, zernike_radial

try:  # the distribution "scatmodes" holds basis, project and compress: one version for all
    __version__ = _distribution_version("scatmodes")
except PackageNotFoundError:  # pragma: no cover - imported from a source tree, not installed
    __version__ = "unknown"

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
