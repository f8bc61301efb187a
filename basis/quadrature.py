"""Product quadrature rules on the sphere and the upper hemisphere.

Gauss-Legendre in z = cos(theta) times the uniform (trapezoidal) rule in azimuth. With
``n_theta`` nodes in z and ``n_phi`` in phi, a rule integrates exactly every function
p(z) t(phi) with p a polynomial of degree <= 2 n_theta - 1 and t a trigonometric polynomial
of degree <= n_phi - 1. In particular it is exact for every polynomial in (x, y, z) of total
degree <= min(2 n_theta - 1, n_phi - 1): the terms x^a y^b z^c with a + b odd integrate to
zero in phi, the others are polynomials in z. The degree is stored with the rule.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import roots_legendre

from .validation import nonneg_int

__all__ = ["HemisphereRule", "hemisphere_rule", "sphere_rule"]


@dataclass(frozen=True)
class HemisphereRule:
    """Nodes and weights of a product rule.

    Attributes
    ----------
    points : (n_theta * n_phi, 3) ndarray of float64
        Unit vectors, ordered theta-major (all azimuths of the first z node first).
    weights : (n_theta * n_phi,) ndarray of float64
        Solid-angle weights (steradians); they sum to 2 pi (hemisphere) or 4 pi (sphere).
    z : (n_theta,) ndarray, phi : (n_phi,) ndarray
        The one-dimensional nodes, for separable (FFT) use.
    degree_z, degree_phi : int
        Exactness: polynomials in z up to ``degree_z`` times trigonometric polynomials in phi
        up to ``degree_phi``.
    domain : str
        ``"hemisphere"`` or ``"sphere"``.
    """

    points: NDArray[np.float64]
    weights: NDArray[np.float64]
    z: NDArray[np.float64]
    phi: NDArray[np.float64]
    degree_z: int
    degree_phi: int
    domain: str

    @property
    def shape(self) -> tuple[int, int]:
        """(n_theta, n_phi)."""
        return (self.z.size, self.phi.size)

    def integrate(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        """Integrate values given at ``points`` (leading axis) over the domain."""
        return np.tensordot(self.weights, np.asarray(values, dtype=np.float64), axes=(0, 0))


def _product_rule(n_theta: int, n_phi: int, lo: float, domain: str) -> HemisphereRule:
    n_theta = nonneg_int(n_theta, "n_theta")
    n_phi = nonneg_int(n_phi, "n_phi")
    if n_theta < 1 or n_phi < 1:
        raise ValueError(f"n_theta and n_phi must be >= 1, got {n_theta} and {n_phi}")
    t, wt = roots_legendre(n_theta)
    half = (1.0 - lo) / 2.0
    z = lo + half * (t + 1.0)
    wz = half * wt
    phi = 2.0 * np.pi * np.arange(n_phi) / n_phi
    s = np.sqrt(np.maximum(0.0, (1.0 - z) * (1.0 + z)))
    pts = np.empty((n_theta, n_phi, 3))
    pts[..., 0] = s[:, None] * np.cos(phi)
    pts[..., 1] = s[:, None] * np.sin(phi)
    pts[..., 2] = z[:, None]
    w = np.repeat(wz * (2.0 * np.pi / n_phi), n_phi)
    return HemisphereRule(pts.reshape(-1, 3), w, z, phi, 2 * n_theta - 1, n_phi - 1, domain)


def hemisphere_rule(n_theta: int, n_phi: int) -> HemisphereRule:
    """Build the Gauss-Legendre (z in [0, 1]) x uniform azimuth rule on the upper hemisphere.

    Parameters
    ----------
    n_theta, n_phi : int
        Number of nodes in z = cos(theta) and in phi, both >= 1.

    Returns
    -------
    HemisphereRule
        Exact for p(z) t(phi), deg p <= 2 n_theta - 1 and deg t <= n_phi - 1.

    Examples
    --------
    >>> rule = hemisphere_rule(2, 3)
    >>> round(float(rule.weights.sum()), 12)  # 2 pi
    6.28318530718
    >>> round(float(rule.integrate(rule.points[:, 2] ** 3)), 12)  # int_H cos^3 = pi / 2
    1.570796326795
    """
    return _product_rule(n_theta, n_phi, 0.0, "hemisphere")


def sphere_rule(n_theta: int, n_phi: int) -> HemisphereRule:
    """Build the Gauss-Legendre (z in [-1, 1]) x uniform azimuth rule on the whole sphere.

    Exact for p(z) t(phi), deg p <= 2 n_theta - 1 and deg t <= n_phi - 1 (the Gauss-Legendre
    grid of pyshtools' ``SHExpandGLQ`` is the same construction).
    """
    return _product_rule(n_theta, n_phi, -1.0, "sphere")
