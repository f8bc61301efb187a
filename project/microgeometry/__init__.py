"""Westin-style Monte Carlo microgeometry simulator (Westin, Arvo & Torrance 1992).

Rays are traced through a periodic, triangulated height field whose facets are mirrors
(with Fresnel), ideal diffusers or any microscale BRDF; the exiting rays give a Monte Carlo
estimate of the coefficient matrix of f cos(theta_i) cos(theta_o) in any hemisphere basis.

- :class:`GaussianSurface`, :class:`Heightfield`: the specimens.
- :class:`Scene`, :func:`brushed_metal`, :class:`Mesh`, :class:`BVH`: periodic scenes of
  meshes, cylinders, tubes, spheres and height fields traced through one BVH
  (:class:`ScenePart`: the read-only description of one part, from :attr:`Scene.parts`).
- :class:`Mirror`, :class:`Diffuse`, :class:`MicroBRDF`, :class:`Dielectric`: facet
  materials (Dielectric: transparent closed solids with absorption inside).
- :func:`velvet`: transparent fibres with random tilt over an absorbing base.
- :func:`woven_cloth`: a plain weave of threads scattering with a simulated thread BRDF.
- :func:`trace`: paths for one incident direction (exit directions, weights, bounces).
- :func:`simulate`: the coefficient matrix with Q, standard errors and energy balance.

References
----------
Westin, S. H., Arvo, J. R. and Torrance, K. E. Predicting reflectance functions from
complex surfaces. Computer Graphics 26(2) (SIGGRAPH '92 Proceedings), 255-264, 1992.
Reprinted in the SIGGRAPH 2001 course notes "State of the Art in Modeling and Measuring of
Surface Reflection" (Shirley, Marschner, Stam, Ashikhmin).
"""

from .bvh import BVH, Mesh
from .cloth import woven_cloth
from .estimate import SimulationResult, merge, simulate
from .materials import Dielectric, Diffuse, Material, MicroBRDF, Mirror
from .scene import Scene, ScenePart, brushed_metal
from .surface import GaussianSurface, Heightfield
from .trace import Paths, trace
from .velvet import velvet

__all__ = [
    "BVH",
    "Dielectric",
    "Diffuse",
    "GaussianSurface",
    "Heightfield",
    "Material",
    "Mesh",
    "MicroBRDF",
    "Mirror",
    "Paths",
    "Scene",
    "ScenePart",
    "SimulationResult",
    "brushed_metal",
    "merge",
    "simulate",
    "trace",
    "velvet",
    "woven_cloth",
]
