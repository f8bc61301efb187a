"""Woven cloth: a plain weave of threads whose surface scatters with a simulated thread BRDF.

Recursion (Westin, Arvo & Torrance 1992, sec. 5.4, where the thread BRDF came from a
simulation of the parallel cylinders of their sec. 5.2): the coefficient matrix of one
simulation -- e.g. parallel fibres, the inside of a thread -- becomes the microscale BRDF of
the next, the surface of the threads of a cloth, through :class:`project.MatrixBRDF`
(evaluation and importance sampling of a matrix) and
:class:`~project.microgeometry.MicroBRDF`.

Geometry (one period of 2 s x 2 s, s the thread spacing): two threads along x, at
y = (j + 1/2) s, and two along y, at x = (i + 1/2) s (i, j = 0, 1), each a swept tube of
radius r around a smooth centreline

    along x:  z = (-1)^j h sin(pi x / s),        along y:  z = -(-1)^i h sin(pi y / s),

so at the crossing (x_i, y_j) the thread along x is at height (-1)^(i+j) h and the one
along y at the opposite height: every thread passes alternately over and under the threads
it crosses, and neighbouring threads are in opposite phase (a plain weave). The phase
(sin rather than cos) puts the crests at the crossings. Every triangle carries its thread's
direction (the centreline tangent) as the x axis of its facet frame, so the thread BRDF
runs along the thread everywhere, on the sloping flanks and for both families. The weave,
with those tangents, is invariant under the 90-degree turn (x, y) -> (2 s - y, x) of
``Scene.rotated``, which maps each family of threads onto the other.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..matrix_brdf import MatrixBRDF
from .bvh import Mesh
from .materials import Diffuse, Material, MicroBRDF
from .scene import Scene

__all__ = ["woven_cloth"]


def woven_cloth(
    thread: object,
    *,
    spacing: float = 1.0,
    radius: float = 0.3,
    crimp: float | None = None,
    segments: int = 32,
    sides: int = 12,
    base: Material | None = None,
    base_height: float | None = None,
    negative: str = "raise",
    tol: float = 1e-2,
) -> Scene:
    """Build a plain-weave cloth whose threads scatter with ``thread``, on a base plane.

    Parameters
    ----------
    thread : CoefficientMatrix or SimulationResult
        The thread's own BRDF (one channel), e.g. the result of :func:`simulate` on a
        specimen of parallel fibres along x. Its x axis is taken along the thread.
    spacing : float
        Distance s > 0 between neighbouring parallel threads; the period is 2 s x 2 s.
    radius : float
        Thread radius r, 0 < r < s / 2 (parallel neighbours must not overlap).
    crimp : float, optional
        Amplitude h >= 0 of the over/under undulation of the centrelines (default r: the
        threads touch at the crossings; h < r makes them interpenetrate there, which the
        tracer handles as the union of the solids). The tube must not fold over itself
        where the centreline bends most, at the crests (radius of curvature
        s^2 / (pi^2 h)): h r < s^2 / pi^2. Touching threads (h >= r) thus need r < s / pi.
    segments : int
        Rings per thread and period (a multiple of 4, >= 8: the crossings fall on rings).
    sides : int
        Vertices per ring (a multiple of 4, >= 4: the tops and bottoms are vertices).
    base : Material, optional
        Material of the base plane under the weave (default ``Diffuse(0.05)``, dark).
    base_height : float, optional
        Height of the base plane (default -(h + r): it touches the lowest points of the
        threads).
    negative : {"raise", "clamp"}
        Passed to :class:`project.MatrixBRDF`: a thread matrix with negative lobes beyond
        ``tol`` raises unless ``negative="clamp"`` (then see ``MatrixBRDF.clamp_bias``).
    tol : float
        Relative tolerance of negative values, passed to :class:`project.MatrixBRDF`.

    Returns
    -------
    Scene
        Parts in this order: the threads along x, the threads along y (one mesh each, one
        shared material ``MicroBRDF(MatrixBRDF(thread))``, with per-triangle tangents) and
        the base plane.

    Notes
    -----
    Facet frames: every thread triangle's tangent (``Scene.add_mesh(tangents=...)``) is
    the centreline tangent of its thread at the middle of its ring segment, so a MicroBRDF
    facet's x axis is that direction projected onto the facet: along the thread for both
    families, also on the sloping flanks, where the projected world x axis would tilt away
    from the thread by up to atan(pi h / s). Both families therefore use the same
    material.

    ``Scene.rotated`` turns the tangents with the geometry, so it is a true rotation of the
    cloth, for anisotropic threads too; and the square weave is invariant under the
    90-degree turn (the weave maps onto itself with each thread's BRDF along it), which
    the simulated matrix shows.

    Tubes: each thread is a swept tube whose rings lie in the planes normal to the
    centreline; the last ring of a period is the first one shifted by 2 s, so the surface
    is closed under the periodic tiling, with triangles wound so that (v1 - v0) x (v2 - v0)
    points out of the tube.

    Examples
    --------
    >>> from basis import HemiHarmonics
    >>> from project import project
    >>> from project.models import Lambert
    >>> woven_cloth(project(Lambert(0.8), HemiHarmonics(3)), segments=8, sides=4)
    Scene(period=[2.0, 2.0], triangles=258, cylinders=0)
    """
    s = _finite(spacing, "spacing")
    r = _finite(radius, "radius")
    if not s > 0:
        raise ValueError(f"spacing must be > 0, got {spacing!r}")
    if not 0 < r < 0.5 * s:
        raise ValueError(f"radius must be > 0 and < spacing / 2 = {0.5 * s:g} (neighbouring "
                         f"parallel threads must not overlap), got {radius!r}")
    h = r if crimp is None else _finite(crimp, "crimp")
    if h < 0:
        raise ValueError(f"crimp must be >= 0, got {crimp!r}")
    if h * r * np.pi**2 >= s * s:
        raise ValueError(f"crimp * radius must be < spacing^2 / pi^2 = {s * s / np.pi**2:.4g} "
                         f"(else the tube folds over itself at the crests, where the "
                         f"centreline's radius of curvature s^2 / (pi^2 crimp) is smallest), "
                         f"got crimp = {h:g}, radius = {r:g}; lower the crimp or the radius")
    segments = _count(segments, "segments", 8)
    sides = _count(sides, "sides", 4)
    if base is None:
        base = Diffuse(0.05)
    zb = -(h + r) if base_height is None else _finite(base_height, "base_height")
    mat = MicroBRDF(MatrixBRDF(thread, negative=negative, tol=tol))
    along_x = [_tube("x", (j + 0.5) * s, (-1.0) ** j * h, s, r, segments, sides)
               for j in range(2)]
    along_y = [_tube("y", (i + 0.5) * s, -((-1.0) ** i) * h, s, r, segments, sides)
               for i in range(2)]
    scene = Scene((2.0 * s, 2.0 * s))
    for family in (along_x, along_y):
        mesh, tangents = _join(family)
        scene.add_mesh(mesh, material=mat, tangents=tangents)
    return scene.add_plane(zb, material=base)


def _tube(axis: str, position: float, amplitude: float, s: float, r: float, segments: int,
          sides: int) -> tuple[NDArray, NDArray, NDArray]:
    """Build one thread over one period as a swept tube.

    Returns vertices ((segments + 1) * sides, 3), faces (2 segments sides, 3) and face
    tangents (2 segments sides, 3) (the centreline's unit tangent at the middle of each
    face's ring segment).
    """
    u = 2.0 * s * np.arange(segments + 1) / segments
    z = amplitude * np.sin(np.pi * u / s)
    c = _along(axis, u, position, z)
    t = _along(axis, np.ones_like(u), 0.0, amplitude * np.pi / s * np.cos(np.pi * u / s))
    t /= np.linalg.norm(t, axis=1)[:, None]
    um = u[:-1] + s / segments  # the middle of each ring segment
    tm = _along(axis, np.ones_like(um), 0.0, amplitude * np.pi / s * np.cos(np.pi * um / s))
    tm /= np.linalg.norm(tm, axis=1)[:, None]
    n1 = np.cross([0.0, 0.0, 1.0], t)  # horizontal, normal to the thread
    n1 /= np.linalg.norm(n1, axis=1)[:, None]
    n2 = np.cross(t, n1)  # (t, n1, n2) right-handed; n2 points up
    a = 2.0 * np.pi * np.arange(sides) / sides
    v = c[:, None] + r * (np.cos(a)[None, :, None] * n1[:, None] + np.sin(a)[None, :, None]
                          * n2[:, None])
    shift = np.zeros(3)
    shift[0 if axis == "x" else 1] = 2.0 * s
    v[-1] = v[0] + shift  # the periodic copy of the first ring, exactly
    k, l = np.meshgrid(np.arange(segments), np.arange(sides), indexing="ij")
    v00 = k * sides + l
    v01 = k * sides + (l + 1) % sides
    v10 = v00 + sides
    v11 = v01 + sides
    # (v00, v11, v10) and (v00, v01, v11): outward for increasing ring angle about t
    f = np.concatenate([np.stack([v00, v11, v10], -1).reshape(-1, 3),
                        np.stack([v00, v01, v11], -1).reshape(-1, 3)])
    # faces run segment-major in each half: face k sides + l lies in segment k
    return v.reshape(-1, 3), f, np.tile(np.repeat(tm, sides, axis=0), (2, 1))


def _along(axis: str, along: NDArray, across: float, z: NDArray) -> NDArray:
    """Return (n, 3) points or vectors from their components along a thread.

    The components are ``along`` the thread axis, ``across`` it (horizontal) and ``z``.
    """
    a = np.broadcast_to(along, z.shape)
    b = np.full_like(z, across)
    return np.stack([a, b, z] if axis == "x" else [b, a, z], -1)


def _join(parts: list[tuple[NDArray, NDArray, NDArray]]) -> tuple[Mesh, NDArray]:
    verts, faces, tangents, off = [], [], [], 0
    for v, f, t in parts:
        verts.append(v)
        faces.append(f + off)
        tangents.append(t)
        off += v.shape[0]
    return Mesh(np.concatenate(verts), np.concatenate(faces)), np.concatenate(tangents)


def _finite(value: object, name: str) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return v


def _count(value: object, name: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {value!r}")
    if value < low or value % 4:
        raise ValueError(f"{name} must be a multiple of 4 and >= {low}, got {value}")
    return int(value)
