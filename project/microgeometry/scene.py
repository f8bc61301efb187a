"""Periodic scenes of meshes, cylinders and height fields, traced through one BVH.

A :class:`Scene` is one period box [0, Lx) x [0, Ly) of a surface tiled in x and y, built from
parts -- triangle meshes (:class:`~project.microgeometry.bvh.Mesh`), height fields
(triangulated as by the height-field tracer), base planes, cylinders lying along x or y,
spheres and finite (optionally capped) tubes in any direction -- each with its own facet
material (:class:`Mirror`, :class:`Diffuse`, :class:`Dielectric` or :class:`MicroBRDF`). It is
accepted by :func:`~project.microgeometry.simulate` in place of a :class:`Heightfield`; the
path loop is the one of ``trace.py`` (same random streams, same start points, same Fresnel and
roulette) with the max-pyramid walk replaced by the periodic BVH walk of ``bvh.py``. Scenes
with MicroBRDF parts are traced bounce by bounce through the same BVH (``wavefront.py``; Mirror
and Diffuse parts may be mixed in, Dielectric ones not).

:func:`brushed_metal` builds the brushed-metal specimen: parallel cylinders on a base plane.
"""

from __future__ import annotations

import hashlib
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basis.jit import loopjit, run_parallel

from ._paths import (
    _HIT,
    _LOST,
    _TAG_RAY,
    ROULETTE,
    _attenuate,
    _dielectric,
    _launch,
    _next_origin,
    _scatter,
    _store_path,
    _stream,
)
from .bvh import BVH, CYLINDER, SPHERE, TRIANGLE, TUBE, Mesh, _periodic_hit
from .materials import DIELECTRIC, MICRO, Material, MicroBRDF, Mirror
from .surface import Heightfield
from .wavefront import run_scene_wavefront

__all__ = ["Scene", "ScenePart", "brushed_metal"]

#: primitive type (bvh.py) of each kind of part
_PTYPE = {"triangles": TRIANGLE, "cylinder": CYLINDER, "sphere": SPHERE, "tube": TUBE}


class ScenePart(NamedTuple):
    """Read-only description of one part of a :class:`Scene` (see :attr:`Scene.parts`).

    One part is what one ``add_*`` call added: n primitives of one kind and one material.

    Attributes
    ----------
    kind : {"triangles", "cylinder", "sphere", "tube"}
        The kind of the primitives. Meshes, height fields and planes are ``"triangles"``.
    rows : (n, 9) ndarray of float64
        One row per primitive, read-only (``rows.flags.writeable`` is False), in the layout
        of :mod:`project.microgeometry.bvh`:

        - ``"triangles"``: the corners (x0, y0, z0, x1, y1, z1, x2, y2, z2); the outer
          side is the one the winding normal (v1 - v0) x (v2 - v0) points to;
        - ``"cylinder"``: (axis, p, cz, r, lo, hi, 0, 0, 0), axis 0 along x (the line
          y = p, z = cz) or 1 along y (x = p, z = cz), radius r, cut to lo <= x (or y)
          <= hi, one period long;
        - ``"sphere"``: (cx, cy, cz, r, 0, 0, 0, 0, 0);
        - ``"tube"``: (x0, y0, z0, x1, y1, z1, r, caps, 0), caps 1 (closed by discs) or 0.
    material : Material
        The facet material of every primitive of the part: the object that was passed in
        (not a copy), so parts added with one material object share it.
    tangents : (n, 3) ndarray of float64 or None
        Unit x axes of the facet frames of a :class:`MicroBRDF` material, one per triangle
        (read-only), as given to :meth:`Scene.add_mesh` (normalised, turned by
        :meth:`Scene.rotated`); None where none were given (the frame's x axis is the
        world x axis projected onto the facet).

    Examples
    --------
    >>> part = Scene(1.0).add_sphere([0.5, 0.5, 0.2], 0.1).parts[0]
    >>> part.kind, part.rows.shape, part.rows[0, :4].tolist(), part.material, part.tangents
    ('sphere', (1, 9), [0.5, 0.5, 0.2, 0.1], Mirror(), None)
    """

    kind: str
    rows: NDArray[np.float64]
    material: Material
    tangents: NDArray[np.float64] | None


class Scene:
    """One period of a periodic surface made of meshes, height fields and cylinders.

    Parameters
    ----------
    period : (2,) array_like of float
        (Lx, Ly) > 0: the scene repeats with these periods in x and y. Parts may poke out
        of the box [0, Lx) x [0, Ly); the tiling wraps them.

    Examples
    --------
    >>> s = Scene((1.0, 1.0)).add_plane(0.0).add_cylinder("x", 0.5, 0.0, 0.3)
    >>> s
    Scene(period=[1.0, 1.0], triangles=2, cylinders=1)
    """

    def __init__(self, period: ArrayLike) -> None:
        try:
            p = np.broadcast_to(np.asarray(period, dtype=np.float64), (2,)).copy()
        except (TypeError, ValueError):
            raise ValueError(f"period must be a number or a pair (Lx, Ly), got "
                             f"{period!r}") from None
        if not np.all(np.isfinite(p)) or np.any(p <= 0):
            raise ValueError(f"period must be finite and > 0, got {period!r}")
        self.period = p
        self._parts: list[tuple[str, NDArray, Material]] = []
        # per part: (n, 3) unit x axes of the MicroBRDF facet frames, or None (world x)
        self._tangents: list[NDArray | None] = []
        self._bvh: BVH | None = None

    # -- building -----------------------------------------------------------------------------

    def add_mesh(self, mesh: Mesh, *, material: Material | None = None,
                 tangents: ArrayLike | None = None) -> Scene:
        """Add the triangles of ``mesh`` (coordinates in the scene's frame); returns self.

        Parameters
        ----------
        mesh : Mesh
            The triangles.
        material : Material, optional
            Of the triangles (default lossless :class:`Mirror`).
        tangents : (F, 3) or (3,) array_like of float, optional
            Direction of the x axis of the facet frame of a :class:`MicroBRDF` material,
            per triangle (F = ``mesh.faces.shape[0]``) or one for all (finite, non-zero;
            length irrelevant): on a hit the frame's x axis is this direction projected
            onto the triangle, which orients anisotropic microscale BRDFs (e.g. along a
            thread). None (default): the world x axis, as for every other part. Turned
            with the scene by :meth:`rotated`; ignored by the other materials.

        Examples
        --------
        A unit square whose microscale BRDF's x axis is the world y axis:

        >>> m = Mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
        >>> Scene(1.0).add_mesh(m, tangents=[0.0, 1.0, 0.0])
        Scene(period=[1.0, 1.0], triangles=2, cylinders=0)
        """
        if not isinstance(mesh, Mesh):
            raise TypeError(f"mesh must be a Mesh, got {type(mesh).__name__}")
        rows = mesh.triangles().reshape(-1, 9)
        tan = None if tangents is None else _frozen(_tangents(tangents, rows.shape[0]))
        self._add("triangles", rows, material)
        self._tangents[-1] = tan
        return self

    def add_heightfield(self, surface: Heightfield) -> Scene:
        """Add a height field (its period must equal the scene's), with its own material."""
        if not isinstance(surface, Heightfield):
            raise TypeError(f"surface must be a Heightfield, got {type(surface).__name__}")
        if not np.allclose(surface.period, self.period, rtol=1e-12, atol=0):
            raise ValueError(f"surface period must equal the scene period "
                             f"{self.period.tolist()}, got {surface.period.tolist()}")
        return self._add("triangles", _heightfield_triangles(surface), surface.material)

    def add_plane(self, z: float = 0.0, *, material: Material | None = None) -> Scene:
        """Add the horizontal plane at height ``z`` (two triangles per period)."""
        z = float(z)
        if not np.isfinite(z):
            raise ValueError(f"z must be finite, got {z!r}")
        lx, ly = self.period
        tri = np.array([[0, 0, z, lx, 0, z, lx, ly, z], [0, 0, z, lx, ly, z, 0, ly, z]], float)
        return self._add("triangles", tri, material)

    def add_cylinder(self, axis: str, position: float, height: float, radius: float, *,
                     material: Material | None = None) -> Scene:
        """Add a cylinder lying along ``axis`` ("x" or "y"), infinite along it.

        Its axis is the line y = position, z = height (axis "x") or x = position,
        z = height (axis "y"); ``radius`` > 0.
        """
        if axis not in ("x", "y"):
            raise NotImplementedError(f"axis must be 'x' or 'y' (cylinders parallel to the "
                                      f"mean plane, along a period), got {axis!r}")
        vals = [float(position), float(height), float(radius)]
        if not np.all(np.isfinite(vals)) or not vals[2] > 0:
            raise ValueError(f"position, height must be finite and radius finite and > 0, got "
                             f"{position!r}, {height!r}, {radius!r}")
        a = 0 if axis == "x" else 1
        along = self.period[a]
        row = np.array([[a, vals[0], vals[1], vals[2], 0.0, along, 0.0, 0.0, 0.0]])
        return self._add("cylinder", row, material)

    def add_sphere(self, center: ArrayLike, radius: ArrayLike, *,
                   material: Material | None = None) -> Scene:
        """Add one sphere, or n spheres of one material; returns self.

        Parameters
        ----------
        center : (3,) or (n, 3) array_like of float
            Centres (finite; anywhere: the tiling wraps spheres poking out of the period).
        radius : float or (n,) array_like of float
            Radii, finite and > 0.
        material : Material, optional
            Of the sphere surfaces (default lossless :class:`Mirror`). The outer side (the
            ``front`` of a hit) is the outside; a ray inside meets the wall from behind.

        Examples
        --------
        >>> Scene(1.0).add_plane(0.0).add_sphere([[0.5, 0.5, 0.2], [0.0, 0.0, 0.1]], 0.2)
        Scene(period=[1.0, 1.0], triangles=2, cylinders=0, spheres=2)
        """
        c = _points(center, "center")
        r = _radii(radius, c.shape[0])
        rows = np.zeros((c.shape[0], 9))
        rows[:, 0:3] = c
        rows[:, 3] = r
        return self._add("sphere", rows, material)

    def add_tube(self, start: ArrayLike, end: ArrayLike, radius: ArrayLike, *,
                 caps: bool = True, material: Material | None = None) -> Scene:
        """Add one finite cylinder (fibre) around the segment start -> end, or n of them.

        Parameters
        ----------
        start, end : (3,) or (n, 3) array_like of float
            End points of the axes (finite, distinct); in any direction, anywhere (the
            tiling wraps tubes poking out of the period).
        radius : float or (n,) array_like of float
            Radii, finite and > 0.
        caps : bool
            True (default): closed by flat discs at both ends, a solid whose inside is well
            defined (transparent fibres); False: an open tube.
        material : Material, optional
            Of the tube surfaces (default lossless :class:`Mirror`). The outer side (the
            ``front`` of a hit) is away from the axis on the side wall and away from the
            tube on the caps.

        Examples
        --------
        A fibre standing on a plane, tilted by 10 degrees:

        >>> top = [0.5 + 0.4 * np.sin(0.1745), 0.5, 0.4 * np.cos(0.1745)]
        >>> s = Scene(1.0).add_plane(0.0).add_tube([0.5, 0.5, 0.0], top, 0.01)
        >>> s.tubes, s
        (1, Scene(period=[1.0, 1.0], triangles=2, cylinders=0, tubes=1))
        """
        p0 = _points(start, "start")
        p1 = _points(end, "end")
        if p0.shape != p1.shape:
            if p0.shape[0] == 1 or p1.shape[0] == 1:
                p0, p1 = np.broadcast_arrays(p0, p1)
            else:
                raise ValueError(f"start and end must hold the same number of points, got "
                                 f"{p0.shape[0]} and {p1.shape[0]}")
        length = np.linalg.norm(p1 - p0, axis=1)
        scale = np.maximum(np.abs(p0).max(axis=1), np.abs(p1).max(axis=1))
        short = np.flatnonzero(~(length > 1e-12 * scale))
        if short.size:
            k = short[0]
            raise ValueError(f"start and end must be distinct points: {short.size} of "
                             f"{length.size} tubes have (near) zero length (first: tube {k}, "
                             f"start {p0[k].tolist()}, end {p1[k].tolist()})")
        if not isinstance(caps, (bool, np.bool_)):
            raise TypeError(f"caps must be True or False, got {caps!r}")
        rows = np.zeros((p0.shape[0], 9))
        rows[:, 0:3] = p0
        rows[:, 3:6] = p1
        rows[:, 6] = _radii(radius, p0.shape[0])
        rows[:, 7] = 1.0 if caps else 0.0
        return self._add("tube", rows, material)

    def _add(self, kind: str, rows: NDArray, material: Material | None) -> Scene:
        if material is None:
            material = Mirror()
        if not isinstance(material, Material):
            raise TypeError(f"material must be a Material (Mirror, Diffuse, MicroBRDF, "
                            f"Dielectric), got {type(material).__name__}")
        codes = {m.code for _, _, m in self._parts} | {material.code}
        if MICRO in codes and DIELECTRIC in codes:
            # the bounce-by-bounce tracer of MicroBRDF facets keeps no inside-absorption state
            raise NotImplementedError("a Scene must not mix MicroBRDF and Dielectric parts "
                                      "(MicroBRDF scenes are traced bounce by bounce, which "
                                      "supports Mirror, Diffuse and MicroBRDF parts); use "
                                      "Mirror or Diffuse parts next to Dielectric ones")
        self._parts.append((kind, _frozen(np.array(rows, dtype=np.float64)), material))
        self._tangents.append(None)
        self._bvh = None
        return self

    # -- views --------------------------------------------------------------------------------

    def rotated(self) -> Scene:
        """Return the scene turned by +90 degrees about z: (x, y) -> (Ly - y, x).

        The period becomes (Ly, Lx).

        Facet-frame tangents (``add_mesh``) turn with it, (x, y) -> (-y, x); parts without
        them keep the world x axis as their frame's x, so anisotropic MicroBRDF facets turn
        with the scene only where tangents were given (or the BRDF is isotropic).
        """
        lx, ly = self.period
        out = Scene((ly, lx))
        for tan in self._tangents:
            out._tangents.append(None if tan is None else
                                 _frozen(np.stack([-tan[:, 1], tan[:, 0], tan[:, 2]], 1)))
        for kind, rows, mat in self._parts:
            r = rows.copy()
            if kind == "triangles":
                r[:, 0::3] = ly - rows[:, 1::3]
                r[:, 1::3] = rows[:, 0::3]
            elif kind in ("sphere", "tube"):
                # the centre (sphere) or both end points (tube): columns (0, 1) and (3, 4)
                for c in ((0,) if kind == "sphere" else (0, 3)):
                    r[:, c] = ly - rows[:, c + 1]
                    r[:, c + 1] = rows[:, c]
            else:
                a = rows[:, 0]
                r[:, 0] = 1 - a
                # along x (position in y) -> along y at x = Ly - y; along y -> along x at y = x
                r[:, 1] = np.where(a == 0, ly - rows[:, 1], rows[:, 1])
                r[:, 4] = 0.0
                r[:, 5] = np.where(a == 0, ly, lx)
            out._parts.append((kind, _frozen(r), mat))
        return out

    @property
    def parts(self) -> tuple[ScenePart, ...]:
        """The parts of the scene, in the order they were added (read-only).

        Returns
        -------
        tuple of ScenePart
            One :class:`ScenePart` (kind, rows, material, tangents) per ``add_*`` call;
            ``rows`` is (n, 9) and ``tangents`` (n, 3) or None for the n primitives of
            the part. The arrays are read-only views of the scene's storage (assigning
            into them raises ValueError) and the tuple cannot be changed either: build a
            new Scene to change the geometry.

        Examples
        --------
        >>> s = Scene(2.0).add_plane(0.5).add_cylinder("y", 1.0, 0.5, 0.25)
        >>> [(p.kind, p.rows.shape) for p in s.parts]
        [('triangles', (2, 9)), ('cylinder', (1, 9))]
        >>> s.parts[1].rows[0, :6].tolist()  # along y (axis 1) at x = 1, z = 0.5, r = 0.25
        [1.0, 1.0, 0.5, 0.25, 0.0, 2.0]
        """
        return tuple(ScenePart(kind, rows.view(), mat, None if tan is None else tan.view())
                     for (kind, rows, mat), tan in zip(self._parts, self._tangents, strict=True))

    def _count(self, kind: str) -> int:
        return sum(r.shape[0] for k, r, _ in self._parts if k == kind)

    @property
    def triangles(self) -> int:
        """Triangles per period (before periodic copies)."""
        return self._count("triangles")

    @property
    def cylinders(self) -> int:
        """Cylinders per period."""
        return self._count("cylinder")

    @property
    def spheres(self) -> int:
        """Spheres per period."""
        return self._count("sphere")

    @property
    def tubes(self) -> int:
        """Finite cylinders (:meth:`add_tube`) per period."""
        return self._count("tube")

    @property
    def bvh(self) -> BVH:
        """The periodic hierarchy (built on first use)."""
        if self._bvh is None:
            if not self._parts:
                raise ValueError("the scene must hold at least one part (add_mesh, "
                                 "add_heightfield, add_plane, add_cylinder, add_sphere, "
                                 "add_tube), got none")
            pt, pd, _ = self._packed()
            self._bvh = BVH(pt, pd, period=self.period)
        return self._bvh

    def _packed(self) -> tuple[NDArray, NDArray, NDArray]:
        pt, pd, mats = [], [], []
        for kind, rows, mat in self._parts:
            pt.append(np.full(rows.shape[0], _PTYPE[kind], np.int64))
            pd.append(rows)
            p = mat._params()
            mats.append(np.tile([float(mat.code), *p], (rows.shape[0], 1)))
        return np.concatenate(pt), np.concatenate(pd), np.concatenate(mats)

    def fingerprint(self) -> str:
        """Return the SHA-256 of the period, the parts and their materials (checkpoint identity)."""
        d = hashlib.sha256()
        d.update(self.period.tobytes())
        for (kind, rows, mat), tan in zip(self._parts, self._tangents, strict=True):
            d.update(kind.encode())
            d.update(np.ascontiguousarray(rows).tobytes())
            d.update(repr(mat).encode())
            if tan is not None:  # scenes without tangents keep their fingerprints
                d.update(b"tangents")
                d.update(np.ascontiguousarray(tan).tobytes())
        return d.hexdigest()

    def __repr__(self) -> str:
        # spheres and tubes are listed only when present (the form of older scenes stays)
        extra = "".join(f", {name}={count}" for name, count in
                        (("spheres", self.spheres), ("tubes", self.tubes)) if count)
        return (f"Scene(period={self.period.tolist()}, triangles={self.triangles}, "
                f"cylinders={self.cylinders}{extra})")

    # -- tracing (called by estimate._chunk through trace-compatible arguments) ---------------

    def _run(self, dirs: NDArray, per: int, seed: np.uint64, start: int, out: tuple,
             max_bounces: int, max_steps: int) -> None:
        bvh = self.bvh
        if any(m.code == MICRO for _, _, m in self._parts):
            # MicroBRDF facets are numpy objects: bounce by bounce (wavefront.py), with one
            # slot per distinct material object
            materials: list[Material] = []
            slot = []
            for _, rows, mat in self._parts:
                j = next((i for i, m in enumerate(materials) if m is mat), len(materials))
                if j == len(materials):
                    materials.append(mat)
                slot.append(np.full(rows.shape[0], j, np.int64))
            tangents = None
            if any(t is not None for t in self._tangents):
                tangents = np.concatenate([
                    np.tile([1.0, 0.0, 0.0], (rows.shape[0], 1)) if t is None else t
                    for (_, rows, _), t in zip(self._parts, self._tangents, strict=True)])
                tangents = np.ascontiguousarray(tangents[bvh.source])
            run_scene_wavefront(bvh, self.period, materials, np.concatenate(slot)[bvh.source],
                                dirs, per, seed, start, out, max_bounces, max_steps,
                                tangents=tangents)
            return
        _, _, mats = self._packed()
        mats = np.ascontiguousarray(mats[bvh.source])  # per stored primitive
        lx, ly = self.period
        run_parallel(_scene_kernel, dirs.shape[0] * per, np.ascontiguousarray(dirs), per, seed,
                     np.uint64(start), lx, ly, float(bvh.lo[0, 2]), float(bvh.hi[0, 2]), bvh.lo,
                     bvh.hi, bvh.link, bvh.ptype, bvh.pdata, mats, ROULETTE, max_bounces,
                     max_steps, *out, grain=_GRAIN)


def brushed_metal(radius: float, spacing: float, *, height: float = 0.0,
                  material: Material | None = None, direction: str = "x",
                  roughness: float | None = None) -> Scene:
    """Build brushed metal: parallel cylinders of ``radius`` every ``spacing`` on a base plane.

    Parameters
    ----------
    radius : float
        Cylinder radius > 0.
    spacing : float
        Distance between neighbouring cylinder axes (> 0; the period across the grooves; the
        period along them is the same number). Overlapping cylinders (spacing < 2 radius)
        form a scalloped ridge profile.
    height : float
        Height of the axes above the base plane z = 0 (0: half cylinders; negative: shallower
        ridges). Must be > -radius, else the cylinders would be buried.
    material : Material, optional
        Of the cylinders and the plane (default lossless :class:`Mirror`); aluminium near
        550 nm is ``Mirror(0.96, 6.69)``. Any other microscale BRDF: pass
        ``MicroBRDF(brdf)``.
    direction : {"x", "y"}
        Direction of the cylinder axes (the brushing direction).
    roughness : float, optional
        None (default): smooth facets of ``material``. A number m > 0: slightly rough
        metal -- the facets of the cylinders and the plane become
        ``MicroBRDF(CookTorrance(0, m, ior=n, k=k))``, a Beckmann microfacet BRDF of RMS
        slope m (separable Smith shadowing) with the conductor Fresnel of the
        ``Mirror(n, k)`` given as ``material`` (F = 1 for the default lossless Mirror).
        Traced bounce by bounce (:mod:`project.microgeometry.wavefront`), several times
        slower than smooth facets.

    Returns
    -------
    Scene

    Raises
    ------
    TypeError
        If ``roughness`` is given with a ``material`` that is not a :class:`Mirror`.

    Examples
    --------
    >>> brushed_metal(0.5, 1.0)
    Scene(period=[1.0, 1.0], triangles=2, cylinders=1)

    Slightly rough aluminium (n + i k = 0.96 + 6.69 i near 550 nm):

    >>> brushed_metal(0.4, 1.0, material=Mirror(0.96, 6.69), roughness=0.15)
    Scene(period=[1.0, 1.0], triangles=2, cylinders=1)
    """
    r = float(radius)
    s = float(spacing)
    if not (np.isfinite(r) and r > 0):
        raise ValueError(f"radius must be finite and > 0, got {radius!r}")
    if not (np.isfinite(s) and s > 0):
        raise ValueError(f"spacing must be finite and > 0, got {spacing!r}")
    h = float(height)
    if not (np.isfinite(h) and h > -r):
        raise ValueError(f"height must be finite and > -radius = {-r:g}, got {height!r}")
    if direction not in ("x", "y"):
        raise ValueError(f"direction must be 'x' or 'y', got {direction!r}")
    if roughness is not None:
        material = _rough_metal(material, roughness)
    scene = Scene((s, s)).add_plane(0.0, material=material)
    return scene.add_cylinder(direction, 0.5 * s, h, r, material=material)


def _rough_metal(material: Material | None, roughness: object) -> Material:
    """Return MicroBRDF(CookTorrance(0, roughness)) with the Fresnel of the Mirror ``material``."""
    from project.models import CookTorrance

    ok = isinstance(roughness, (int, float, np.number)) and not isinstance(roughness, bool)
    m = float(roughness) if ok else np.nan
    if not (np.isfinite(m) and m > 0):
        raise ValueError(f"roughness must be a finite number > 0 (or None), got {roughness!r}")
    mirror = Mirror() if material is None else material
    if not isinstance(mirror, Mirror):
        raise TypeError(f"material must be a Mirror (its n + i k gives the Fresnel term) when "
                        f"roughness is given, got {material!r}; pass material=MicroBRDF(...) "
                        f"and roughness=None for other microscale BRDFs")
    if mirror.ior is None:
        return MicroBRDF(CookTorrance(0.0, m))
    return MicroBRDF(CookTorrance(0.0, m, ior=mirror.ior, k=mirror.k))


def _frozen(a: NDArray) -> NDArray:
    # the array itself, made read-only: stored parts are never written after they are built,
    # so Scene.parts can hand out views that cannot be made writeable again
    a.flags.writeable = False
    return a


def _points(value: ArrayLike, name: str) -> NDArray[np.float64]:
    # (n, 3) finite points from a point (3,) or points (n, 3), n >= 1
    try:
        p = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a point (3,) or points (n, 3) of floats, got "
                        f"{value!r}") from None
    if p.ndim == 1:
        p = p[None]
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
        raise ValueError(f"{name} must be a point (3,) or points (n, 3) with n >= 1, got "
                         f"shape {np.shape(value)}")
    bad = np.flatnonzero(~np.all(np.isfinite(p), axis=1))
    if bad.size:
        raise ValueError(f"{name} must be finite: {bad.size} of {p.shape[0]} points are NaN "
                         f"or inf (first: {p[bad[0]].tolist()})")
    return p


def _tangents(value: ArrayLike, n: int) -> NDArray[np.float64]:
    # (n, 3) unit vectors from one direction (3,) or one per triangle (n, 3)
    try:
        t = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"tangents must be a direction (3,) or {n} directions (n, 3) of "
                        f"floats, got {value!r}") from None
    if t.shape not in ((3,), (n, 3)):
        raise ValueError(f"tangents must have shape (3,) or ({n}, 3) (one per triangle), got "
                         f"shape {t.shape}")
    t = np.broadcast_to(t.reshape(-1, 3), (n, 3))
    norm = np.linalg.norm(t, axis=1)
    bad = np.flatnonzero(~(np.isfinite(norm) & (norm > 0)))
    if bad.size:
        raise ValueError(f"tangents must be finite and non-zero: {bad.size} of {n} are not "
                         f"(first: triangle {bad[0]}, {t[bad[0]].tolist()})")
    return t / norm[:, None]


def _radii(value: ArrayLike, n: int) -> NDArray[np.float64]:
    # (n,) finite radii > 0 from a number or n numbers
    try:
        r = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"radius must be a number or {n} numbers, got {value!r}") from None
    if r.ndim > 1 or (r.ndim == 1 and r.size not in (1, n)):
        raise ValueError(f"radius must be a number or {n} numbers (one per primitive), got "
                         f"shape {r.shape}")
    r = np.broadcast_to(r.reshape(-1), (n,))
    bad = np.flatnonzero(~(np.isfinite(r) & (r > 0)))
    if bad.size:
        raise ValueError(f"radius must be finite and > 0, got {float(r[bad[0]])!r} (primitive "
                         f"{bad[0]})")
    return r.copy()


def _heightfield_triangles(surface: Heightfield) -> NDArray[np.float64]:
    # (2 ny nx, 9) triangles A (00, 10, 11) then B (00, 11, 01) of every cell, as surface.py
    h = surface.heights
    ny, nx = h.shape
    dx, dy = surface.spacing
    x = np.arange(nx) * dx
    y = np.arange(ny) * dy
    xx, yy = np.meshgrid(x, y)
    p00 = np.stack([xx, yy, h], -1)
    p10 = np.stack([xx + dx, yy, np.roll(h, -1, 1)], -1)
    p01 = np.stack([xx, yy + dy, np.roll(h, -1, 0)], -1)
    p11 = np.stack([xx + dx, yy + dy, np.roll(np.roll(h, -1, 0), -1, 1)], -1)
    a = np.concatenate([p00, p10, p11], -1).reshape(-1, 9)
    b = np.concatenate([p00, p11, p01], -1).reshape(-1, 9)
    return np.concatenate([a, b])


#: rays per part of run_parallel: a path through the BVH costs microseconds
_GRAIN = 64


@loopjit
def _scene_kernel(first, stop, dirs, per, seed, start, lx, ly, zmin, zmax, lo, hi, link, ptype,
                  pdata, mats, rr, max_bounces, max_steps, out_dir, out_w, out_b, out_abs,
                  out_lost):
    # Rays first .. stop - 1 (run_parallel).
    # As trace._trace_kernel with the periodic BVH walk; mats (P, 4) per stored primitive:
    # (material code, ior, k, albedo), k = absorption coefficient for DIELECTRIC.
    # dirs (B, 3); outputs (B * per, 3), (B * per,) x 4.
    eps = 1e-7 * min(lx, ly)
    zs = zmax + 1e-6 * (zmax - zmin + lx)
    for r in range(first, stop):
        ox, oy, oz, dx, dy, dz, s = _launch(dirs, r // per, zs, lx, ly,
                                            _stream(seed, start + np.uint64(r), _TAG_RAY))
        w = 1.0
        absorbed = 0.0
        lost = 0.0
        bounces = 0
        # absorption coefficient of the medium the ray travels in: set on refracting into a
        # dielectric's outer side, 0 on refracting out of an inner side; reflections and
        # opaque facets send the ray back to where it came from and keep it (Dielectric)
        sigma = 0.0
        while True:
            status, t, gx, gy, gz, prim, front = _periodic_hit(
                ox, oy, oz, dx, dy, dz, lx, ly, zmin, zmax, max_steps, lo, hi, link, ptype, pdata)
            if status == _LOST or (status == _HIT and bounces >= max_bounces):
                lost = w
                w = 0.0
                break
            w, absorbed = _attenuate(sigma, t, w, absorbed)
            if status != _HIT:
                break
            bounces += 1
            px = ox + t * dx
            py = oy + t * dy
            pz = oz + t * dz
            m = mats[prim]
            side = eps  # the new origin goes to the side the ray leaves on
            if int(m[0]) == DIELECTRIC:
                dx, dy, dz, w, s, through = _dielectric(m[1], dx, dy, dz, gx, gy, gz, front, w,
                                                        rr, s)
                if through:
                    side = -eps
                    sigma = m[2] if front else 0.0
            else:
                dx, dy, dz, w, absorbed, s = _scatter(int(m[0]), m[1], m[2], m[3], dx, dy, dz,
                                                      gx, gy, gz, front, w, absorbed, rr, s)
            if w == 0.0:
                break
            ox, oy, oz = _next_origin(px, py, pz, side, gx, gy, gz, lx, ly)
        _store_path(r, w, dx, dy, dz, bounces, absorbed, lost, out_dir, out_w, out_b,
                    out_abs, out_lost)
