"""Facet materials of the microgeometry simulator (one material per surface).

Each material hands the tracer kernel a code and a small parameter vector; the scattering
itself happens inside the numba kernels (the facet events of ``_paths.py``) or, for
:class:`MicroBRDF`, in batches (``scatter.py``).
"""

from __future__ import annotations

import numpy as np

from ._checks import _number
from .scatter import FacetSampler

__all__ = ["Dielectric", "Diffuse", "Material", "MicroBRDF", "Mirror"]

MIRROR, DIFFUSE, MICRO, DIELECTRIC = 0, 1, 2, 3


class Material:
    """Base class of facet materials: ``code`` and ``params`` (ior, k, albedo) for the kernel."""

    code: int = -1

    def _params(self) -> np.ndarray:
        raise NotImplementedError


class Mirror(Material):
    """Ideal mirror facets, lossless (F = 1) or with the exact unpolarised Fresnel reflectance.

    Parameters
    ----------
    ior : float or None
        None: F = 1 (lossless, the default). Otherwise the real part n > 0 of the relative
        index; the reflectance is :func:`project.models.fresnel` of n + i k at the local angle
        of incidence on the facet.
    k : float
        Extinction coefficient >= 0 (conductors); needs ``ior``.

    Examples
    --------
    >>> Mirror(), Mirror(1.5)
    (Mirror(), Mirror(ior=1.5, k=0))
    """

    code = MIRROR

    def __init__(self, ior: float | None = None, k: float = 0.0) -> None:
        if ior is None:
            if k != 0:
                raise ValueError(f"k must be 0 when ior is None (F = 1), got {k!r}")
            self.ior, self.k = None, 0.0
        else:
            self.ior = _number(ior, "ior", strict=True)
            self.k = _number(k, "k", strict=False)

    def _params(self) -> np.ndarray:
        # ior = 0 tells the kernel "F = 1"
        return np.array([0.0 if self.ior is None else self.ior, self.k, 1.0])

    def __repr__(self) -> str:
        return "Mirror()" if self.ior is None else f"Mirror(ior={self.ior:g}, k={self.k:g})"


class Diffuse(Material):
    """Ideal diffuse (Lambertian) facets of albedo ``albedo`` in [0, 1], sampled by cosine.

    Examples
    --------
    >>> Diffuse(0.5)
    Diffuse(0.5)
    """

    code = DIFFUSE

    def __init__(self, albedo: float = 1.0) -> None:
        a = _number(albedo, "albedo", strict=False)
        if a > 1.0:
            raise ValueError(f"albedo must be <= 1, got {albedo!r}")
        self.albedo = a

    def _params(self) -> np.ndarray:
        return np.array([0.0, 0.0, self.albedo])

    def __repr__(self) -> str:
        return f"Diffuse({self.albedo:g})"


class MicroBRDF(Material):
    """Any BRDF (e.g. a :mod:`project.models` model) as the microscale BRDF of every facet.

    Parameters
    ----------
    brdf : BRDF
        One channel, evaluated in the facet's local frame: z is the facet normal and x the
        mean plane's x axis projected onto the facet (this orients anisotropic models), or
        on scene meshes given ``tangents`` (``Scene.add_mesh``) the triangle's tangent
        projected onto it (e.g. along a thread).
        Ideal mirror (``delta``) terms are supported (chosen against the smooth part by
        their albedos at each event).

    Raises
    ------
    TypeError
        If ``brdf`` lacks ``eval`` or ``channels``.
    ValueError
        If it has more than one channel, or returns negative or non-finite values on a
        test grid (8 incidences x 16 x 32 exit directions; values met while tracing are
        checked too).

    Notes
    -----
    Directional-diffuse scattering (Westin et al. 1992, sec. 4.4, eqs 23-24) with one
    importance-sampled ray per event instead of n uniformly spread rays, and Russian roulette
    instead of branching. The new direction is drawn from a mixture of the cosine density and,
    for CookTorrance (Beckmann, GGX), Phong and BlinnPhong, a sampler of the model's lobe, or
    the BRDF's own ``sample(wi, u)`` / ``pdf(wi, wo)`` when it has them (e.g.
    :class:`project.MatrixBRDF`, a simulated BRDF used again); the path weight is multiplied by
    f cos(theta_o) / pdf. The estimator is unbiased (the cosine part of the mixture keeps pdf >
    0 wherever f > 0; roulette is unbiased). Variance: pure cosine sampling (factor pi f) has a
    per-event variance of order the lobe's peak value, ~ 1 / m^2 for a microfacet lobe of
    roughness m, so sharp lobes without a sampler converge slowly; with the lobe sampler the
    factor stays near the lobe's albedo. See :mod:`project.microgeometry.scatter` and
    :mod:`project.microgeometry.wavefront` (the bounce-by-bounce tracer).

    Examples
    --------
    >>> from project.models import Lambert
    >>> MicroBRDF(Lambert(0.5))
    MicroBRDF(Lambert(albedo=0.5))
    """

    code = MICRO

    def __init__(self, brdf: object) -> None:
        if not (hasattr(brdf, "eval") and hasattr(brdf, "channels")):
            raise TypeError(f"brdf must be a BRDF (eval, channels, isotropic), got "
                            f"{type(brdf).__name__}")
        if int(brdf.channels) != 1:
            raise ValueError(f"brdf must have 1 channel, got {brdf.channels}")
        self.brdf = brdf
        self._sampler = FacetSampler(brdf)

    def _params(self) -> np.ndarray:
        return np.array([0.0, 0.0, 1.0])

    def __repr__(self) -> str:
        return f"MicroBRDF({self.brdf!r})"


class Dielectric(Material):
    """Smooth transparent dielectric facets: Fresnel reflection or refraction, absorbing inside.

    The facets are the boundary of a solid of refractive index ``ior`` (relative to the
    surrounding medium) in which light is attenuated by Beer-Lambert absorption. At every hit
    the ray reflects with the exact unpolarised Fresnel probability F of the local angle of
    incidence (total internal reflection, F = 1, beyond the critical angle when leaving) and
    refracts otherwise (Snell's law). The choice is random, so the interface changes only
    the direction, never the path weight; the weight falls by exp(-absorption * length) along
    every segment travelled inside.

    Parameters
    ----------
    ior : float
        Real refractive index n > 0 of the solid relative to the surrounding medium (about
        1.5 for glass, nylon, silk or polyester fibres in air; values below 1 describe a
        solid optically thinner than its surroundings, e.g. a bubble).
    absorption : float
        Absorption coefficient sigma >= 0 inside the solid, per unit length of the scene
        (the same length unit as the geometry): a path of length t inside keeps
        exp(-sigma t) of its energy.

    Notes
    -----
    Only closed solids have an inside: closed triangle meshes wound with
    (v1 - v0) x (v2 - v0) pointing outwards (a layer spanning the period needs only its top
    and bottom faces: the periodic tiling closes it), cylinders along x or y (closed by the
    tiling), spheres and capped tubes. Open surfaces (a :class:`Heightfield`) are refused;
    an open mesh or plane is not, but light entering it has no inside to leave by.

    Inside/outside bookkeeping (``scene.py``): the tracer keeps the absorption coefficient
    of the medium the ray is in. Refracting into a dielectric through its outer side sets
    it to that solid's ``absorption``; refracting out through an inner side sets it to 0
    (the surrounding medium is clear); reflections, and events at opaque (Mirror, Diffuse)
    facets, which send the ray back to the side it came from, leave it unchanged. Each
    crossing uses the crossed facet's own index relative to the surrounding medium, so in
    the overlap of two solids (intersecting fibres) the optics is approximate, but the
    energy balance stays exact: weight lost to absorption is counted as absorbed.

    Examples
    --------
    >>> Dielectric(1.5), Dielectric(1.33, absorption=0.2)
    (Dielectric(1.5), Dielectric(1.33, absorption=0.2))
    """

    code = DIELECTRIC

    def __init__(self, ior: float, absorption: float = 0.0) -> None:
        self.ior = _number(ior, "ior", strict=True)
        self.absorption = _number(absorption, "absorption", strict=False)

    def _params(self) -> np.ndarray:
        # the kernel's (ior, k, albedo) row; the k slot carries the absorption coefficient
        return np.array([self.ior, self.absorption, 1.0])

    def __repr__(self) -> str:
        if self.absorption == 0.0:
            return f"Dielectric({self.ior:g})"
        return f"Dielectric({self.ior:g}, absorption={self.absorption:g})"
