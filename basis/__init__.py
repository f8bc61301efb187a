"""The mathematics: spherical harmonics, hemisphere Zernike functions, Helmholtz surface
scattering modes, quadrature rules and the symmetric coefficient matrix."""

from .quadrature import HemisphereRule, hemisphere_rule, sphere_rule
from .sh import HemiHarmonics, SphericalHarmonics
from .zernike import HemiZernike, zernike_radial

__all__ = [
    "HemiHarmonics",
    "HemiZernike",
    "HemisphereRule",
    "SphericalHarmonics",
    "hemisphere_rule",
    "sphere_rule",
    "zernike_radial",
]
