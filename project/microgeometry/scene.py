"""Periodic scenes of meshes, cylinders and height fields, traced through one BVH.

A :class:`Scene` is one period box [0, Lx) x [0, Ly) of a surface tiled in x and y, built
from parts -- triangle meshes (:class:`~project.microgeometry.bvh.Mesh`), height fields
(triangulated as by the height-field tracer), base planes and cylinders lying along x or y --
each with its own facet material (:class:`Mirror` or :class:`Diffuse`). It is accepted by
:func:`~project.microgeometry.simulate` in place of a :class:`Heightfield`; the path loop is
the one of ``trace.py`` (same random streams, same start points, same Fresnel and roulette)
with the max-pyramid walk replaced by the periodic BVH walk of ``bvh.py``.

:func:`brushed_metal` builds the brushed-metal specimen: parallel cylinders on a base plane.
"""

from __future__ import annotations

import hashlib

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basis._jit import pjit, prange

from .bvh import _HIT, _LOST, BVH, CYLINDER, TRIANGLE, Mesh, _periodic_hit
from .materials import MICRO, Material, Mirror
from .surface import Heightfield
from .trace import _TAG_RAY, ROULETTE, _launch, _scatter, _store_path, _stream

__all__ = ["Scene", "brushed_metal"]


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
        self._bvh: BVH | None = None

    # -- building -----------------------------------------------------------------------------

    def add_mesh(self, mesh: Mesh, *, material: Material | None = None) -> Scene:
        """Add the triangles of ``mesh`` (coordinates in the scene's frame); returns self."""
        if not isinstance(mesh, Mesh):
            raise TypeError(f"mesh must be a Mesh, got {type(mesh).__name__}")
        return self._add("triangles", mesh.triangles().reshape(-1, 9), material)

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

    def _add(self, kind: str, rows: NDArray, material: Material | None) -> Scene:
        if material is None:
            material = Mirror()
        if not isinstance(material, Material):
            raise TypeError(f"material must be a Material (Mirror, Diffuse), got "
                            f"{type(material).__name__}")
        if material.code == MICRO:
            raise NotImplementedError("material must be Mirror or Diffuse in a Scene; "
                                      "MicroBRDF facets are supported on Heightfield only")
        self._parts.append((kind, np.array(rows, dtype=np.float64), material))
        self._bvh = None
        return self

    # -- views --------------------------------------------------------------------------------

    def rotated(self) -> Scene:
        """The scene turned by +90 degrees about z: (x, y) -> (Ly - y, x), period (Ly, Lx)."""
        lx, ly = self.period
        out = Scene((ly, lx))
        for kind, rows, mat in self._parts:
            r = rows.copy()
            if kind == "triangles":
                r[:, 0::3] = ly - rows[:, 1::3]
                r[:, 1::3] = rows[:, 0::3]
            else:
                a = rows[:, 0]
                r[:, 0] = 1 - a
                # along x (position in y) -> along y at x = Ly - y; along y -> along x at y = x
                r[:, 1] = np.where(a == 0, ly - rows[:, 1], rows[:, 1])
                r[:, 4] = 0.0
                r[:, 5] = np.where(a == 0, ly, lx)
            out._parts.append((kind, r, mat))
        return out

    @property
    def triangles(self) -> int:
        """Triangles per period (before periodic copies)."""
        return sum(r.shape[0] for k, r, _ in self._parts if k == "triangles")

    @property
    def cylinders(self) -> int:
        """Cylinders per period."""
        return sum(r.shape[0] for k, r, _ in self._parts if k == "cylinder")

    @property
    def bvh(self) -> BVH:
        """The periodic hierarchy (built on first use)."""
        if self._bvh is None:
            if not self._parts:
                raise ValueError("the scene must hold at least one part (add_mesh, "
                                 "add_heightfield, add_plane, add_cylinder), got none")
            pt, pd, _ = self._packed()
            self._bvh = BVH(pt, pd, period=self.period)
        return self._bvh

    def _packed(self) -> tuple[NDArray, NDArray, NDArray]:
        pt, pd, mats = [], [], []
        for kind, rows, mat in self._parts:
            pt.append(np.full(rows.shape[0], TRIANGLE if kind == "triangles" else CYLINDER))
            pd.append(rows)
            p = mat._params()
            mats.append(np.tile([float(mat.code), *p], (rows.shape[0], 1)))
        return np.concatenate(pt), np.concatenate(pd), np.concatenate(mats)

    def fingerprint(self) -> str:
        """SHA-256 of the period, the parts and their materials (checkpoint identity)."""
        d = hashlib.sha256()
        d.update(self.period.tobytes())
        for kind, rows, mat in self._parts:
            d.update(kind.encode())
            d.update(np.ascontiguousarray(rows).tobytes())
            d.update(repr(mat).encode())
        return d.hexdigest()

    def __repr__(self) -> str:
        return (f"Scene(period={self.period.tolist()}, triangles={self.triangles}, "
                f"cylinders={self.cylinders})")

    # -- tracing (called by estimate._chunk through trace-compatible arguments) ---------------

    def _run(self, dirs: NDArray, per: int, seed: np.uint64, start: int, out: tuple,
             max_bounces: int, max_steps: int) -> None:
        bvh = self.bvh
        _, _, mats = self._packed()
        mats = np.ascontiguousarray(mats[bvh.source])  # per stored primitive
        lx, ly = self.period
        _scene_kernel(np.ascontiguousarray(dirs), per, seed, np.uint64(start), lx, ly,
                      float(bvh.lo[0, 2]), float(bvh.hi[0, 2]), bvh.lo, bvh.hi, bvh.link,
                      bvh.ptype, bvh.pdata, mats, ROULETTE, max_bounces, max_steps, *out)


def brushed_metal(radius: float, spacing: float, *, height: float = 0.0,
                  material: Material | None = None, direction: str = "x") -> Scene:
    """Brushed metal: parallel cylinders of ``radius`` every ``spacing`` on a base plane.

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
        550 nm is ``Mirror(0.96, 6.69)``.
    direction : {"x", "y"}
        Direction of the cylinder axes (the brushing direction).

    Returns
    -------
    Scene

    Examples
    --------
    >>> brushed_metal(0.5, 1.0)
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
    scene = Scene((s, s)).add_plane(0.0, material=material)
    return scene.add_cylinder(direction, 0.5 * s, h, r, material=material)


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


@pjit
def _scene_kernel(dirs, per, seed, start, lx, ly, zmin, zmax, lo, hi, link, ptype, pdata, mats,
                  rr, max_bounces, max_steps, out_dir, out_w, out_b, out_abs, out_lost):
    # As trace._trace_kernel with the periodic BVH walk; mats (P, 4) per stored primitive:
    # (material code, ior, k, albedo). dirs (B, 3); outputs (B * per, 3), (B * per,) x 4.
    eps = 1e-7 * min(lx, ly)
    zs = zmax + 1e-6 * (zmax - zmin + lx)
    for r in prange(dirs.shape[0] * per):
        ox, oy, oz, dx, dy, dz, s = _launch(dirs, r // per, zs, lx, ly,
                                            _stream(seed, start + np.uint64(r), _TAG_RAY))
        w = 1.0
        absorbed = 0.0
        lost = 0.0
        bounces = 0
        while True:
            status, t, gx, gy, gz, prim, front = _periodic_hit(
                ox, oy, oz, dx, dy, dz, lx, ly, zmin, zmax, max_steps, lo, hi, link, ptype, pdata)
            if status == _LOST or (status == _HIT and bounces >= max_bounces):
                lost = w
                w = 0.0
                break
            if status != _HIT:
                break
            bounces += 1
            px = ox + t * dx
            py = oy + t * dy
            pz = oz + t * dz
            m = mats[prim]
            dx, dy, dz, w, absorbed, s = _scatter(int(m[0]), m[1], m[2], m[3], dx, dy, dz, gx,
                                                  gy, gz, front, w, absorbed, rr, s)
            if w == 0.0:
                break
            ox = px + eps * gx
            oy = py + eps * gy
            oz = pz + eps * gz
            ox -= np.floor(ox / lx) * lx
            oy -= np.floor(oy / ly) * ly
        _store_path(r, w, dx, dy, dz, bounces, absorbed, lost, out_dir, out_w, out_b,
                    out_abs, out_lost)
