"""The mathematics of scatmodes.

Spherical harmonics, hemisphere Zernike functions, Helmholtz surface scattering modes,
quadrature rules, the symmetric coefficient matrix and its evaluation.

``basis`` knows nothing of BRDF models, files or plots; ``project`` and ``compress`` build
on it, never the other way round.
"""

from ._base import AzimuthalBlocks, Basis
from .directions import from_angles, from_rusinkiewicz, to_angles, to_rusinkiewicz
from .evaluate import Evaluator
from .kinds import KINDS, make_basis
from .matrix import QUANTITIES, CoefficientMatrix
from .modes import HelmholtzModes
from .quadrature import HemisphereRule, hemisphere_rule, sphere_rule
from .sh import HemiHarmonics, SphericalHarmonics
from .zernike import HemiZernike, zernike_radial

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
