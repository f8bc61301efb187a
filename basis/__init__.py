"""The mathematics: spherical harmonics, hemisphere Zernike functions, Helmholtz surface
scattering modes, quadrature rules and the symmetric coefficient matrix.

``basis`` knows nothing of BRDF models, files or plots.
"""

from ._base import Basis
from .directions import from_angles, from_rusinkiewicz, to_angles, to_rusinkiewicz
from .matrix import QUANTITIES, CoefficientMatrix
from .modes import HelmholtzModes
from .quadrature import HemisphereRule, hemisphere_rule, sphere_rule
from .sh import HemiHarmonics, SphericalHarmonics
from .zernike import HemiZernike, zernike_radial

__all__ = [
    "QUANTITIES",
    "Basis",
    "CoefficientMatrix",
    "HelmholtzModes",
    "HemiHarmonics",
    "HemiZernike",
    "HemisphereRule",
    "SphericalHarmonics",
    "from_angles",
    "from_rusinkiewicz",
    "hemisphere_rule",
    "sphere_rule",
    "to_angles",
    "to_rusinkiewicz",
    "zernike_radial",
]
