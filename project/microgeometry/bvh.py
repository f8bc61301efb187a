"""A numba bounding volume hierarchy over triangles and analytic cylinders, periodic in x, y.

Primitives are stored in two flat arrays: ``ptype`` (P,) int64 (``TRIANGLE`` or
``CYLINDER``) and ``pdata`` (P, 9) float64:

- triangle: the corners v0, v1, v2 (9 numbers);
- cylinder: (axis, p, cz, r, lo, hi, 0, 0, 0) -- an open tube of radius r whose axis is
  parallel to x (axis = 0; the axis is the line y = p, z = cz) or to y (axis = 1; x = p,
  z = cz), cut to lo <= x <= hi (resp. y). Intersected exactly (a quadratic per ray).

The hierarchy is built in numpy by median splits of the primitive centroids along the
longest axis (leaves of at most ``LEAF`` primitives) and stored as flat node arrays:
``lo``, ``hi`` (N, 3) boxes and ``link`` (N, 2) int64 -- a leaf holds (first primitive,
count > 0), an inner node (right child, 0) with its left child at the next index (depth-first
order). Traversal is iterative with a fixed stack of 64 entries (median splits keep the
depth at about log2(P / LEAF) + 1).

Periodic tiling: for a period box [0, Lx) x [0, Ly) every primitive whose box pokes out of it
is also inserted shifted by whole periods, so the copies cover every part of the surface
that lies inside the box. :func:`_periodic_hit` then walks the ray from period cell to
period cell (unwrapped coordinates, as the height-field tracer does) and asks the hierarchy
for the first hit inside each cell.
"""

from __future__ import annotations

import os

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basis._jit import njit, pjit, prange

__all__ = ["BVH", "Mesh"]

TRIANGLE, CYLINDER = 0, 1

#: at most this many primitives per leaf
LEAF = 4

#: status codes of _periodic_hit (the same values as trace._intersect)
_HIT, _ESCAPED, _LOST = 0, 1, 2

_STACK = 64


class Mesh:
    """A triangle mesh: vertex positions and triangle (or polygon) faces.

    Parameters
    ----------
    vertices : (V, 3) array_like of float
        Vertex positions, all finite.
    faces : (F, 3) array_like of int
        Zero-based vertex indices of each triangle. Every triangle must have a non-zero
        area (relative to its longest edge squared, > 1e-12).

    Attributes
    ----------
    vertices : (V, 3) ndarray
    faces : (F, 3) ndarray of int64

    Examples
    --------
    >>> m = Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    >>> m.triangles().shape
    (1, 3, 3)
    """

    def __init__(self, vertices: ArrayLike, faces: ArrayLike) -> None:
        try:
            v = np.array(vertices, dtype=np.float64)
        except (TypeError, ValueError):
            raise TypeError(f"vertices must be a (V, 3) array of floats, got "
                            f"{type(vertices).__name__}") from None
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"vertices must have shape (V, 3), got shape {v.shape}")
        bad = np.flatnonzero(~np.all(np.isfinite(v), axis=1))
        if bad.size:
            raise ValueError(f"vertices must be finite: {bad.size} of {v.shape[0]} are NaN or "
                             f"inf (first: vertex {bad[0]})")
        f = np.asarray(faces)
        if f.size == 0:
            raise ValueError(f"faces must hold at least one triangle, got shape {f.shape}")
        if not np.issubdtype(f.dtype, np.integer):
            raise TypeError(f"faces must be integer vertex indices, got dtype {f.dtype}")
        if f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"faces must have shape (F, 3), got shape {f.shape}")
        f = f.astype(np.int64)
        out = np.flatnonzero(np.any((f < 0) | (f >= v.shape[0]), axis=1))
        if out.size:
            raise ValueError(f"faces must index vertices 0 .. {v.shape[0] - 1}: {out.size} "
                             f"faces do not (first: face {out[0]} = {f[out[0]].tolist()})")
        tri = v[f]
        e1 = tri[:, 1] - tri[:, 0]
        e2 = tri[:, 2] - tri[:, 0]
        e3 = tri[:, 2] - tri[:, 1]
        area2 = np.linalg.norm(np.cross(e1, e2), axis=1)
        longest = np.max(np.stack([np.sum(e * e, axis=1) for e in (e1, e2, e3)]), axis=0)
        degen = np.flatnonzero(~(area2 > 1e-12 * longest) | (longest == 0))
        if degen.size:
            raise ValueError(f"faces must be non-degenerate triangles: {degen.size} of "
                             f"{f.shape[0]} have zero area (first: face {degen[0]} = "
                             f"{f[degen[0]].tolist()})")
        v.setflags(write=False)
        f.setflags(write=False)
        self.vertices = v
        self.faces = f

    @classmethod
    def from_obj(cls, path: str | os.PathLike) -> Mesh:
        """Read the ``v`` and ``f`` lines of a Wavefront OBJ file.

        Face entries may be ``i``, ``i/t``, ``i//n`` or ``i/t/n`` (only i is used; negative
        i counts back from the last vertex read so far); polygons with more than three
        corners are split into a fan around their first corner. Other lines (``vt``, ``vn``,
        ``o``, ``g``, ``usemtl``, comments, ...) are ignored.
        """
        verts: list[list[float]] = []
        faces: list[list[int]] = []
        with open(path, encoding="utf-8") as fh:
            for lineno, line in enumerate(fh, 1):
                parts = line.split()
                if not parts:
                    continue
                if parts[0] == "v":
                    try:
                        verts.append([float(x) for x in parts[1:4]])
                    except ValueError:
                        raise ValueError(f"{path}:{lineno}: v line must hold three numbers, "
                                         f"got {line.strip()!r}") from None
                    if len(verts[-1]) != 3:
                        raise ValueError(f"{path}:{lineno}: v line must hold three numbers, "
                                         f"got {line.strip()!r}")
                elif parts[0] == "f":
                    try:
                        idx = [int(p.split("/")[0]) for p in parts[1:]]
                    except ValueError:
                        raise ValueError(f"{path}:{lineno}: f line must hold vertex indices, "
                                         f"got {line.strip()!r}") from None
                    if len(idx) < 3:
                        raise ValueError(f"{path}:{lineno}: f line must have >= 3 corners, "
                                         f"got {line.strip()!r}")
                    if any(i == 0 for i in idx):
                        raise ValueError(f"{path}:{lineno}: OBJ vertex indices start at 1, "
                                         f"got {line.strip()!r}")
                    idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
                    faces.extend([idx[0], idx[j], idx[j + 1]] for j in range(1, len(idx) - 1))
        if not faces:
            raise ValueError(f"{path} must contain at least one f line, found none")
        return cls(np.array(verts, dtype=np.float64).reshape(-1, 3),
                   np.array(faces, dtype=np.int64))

    def triangles(self) -> NDArray[np.float64]:
        """(F, 3, 3) corner positions of every triangle."""
        return self.vertices[self.faces]

    def __repr__(self) -> str:
        return f"Mesh(vertices={self.vertices.shape[0]}, faces={self.faces.shape[0]})"


class BVH:
    """A bounding volume hierarchy over packed primitives (see the module docstring).

    Parameters
    ----------
    ptype : (P,) array_like of int
        ``TRIANGLE`` (0) or ``CYLINDER`` (1) per primitive.
    pdata : (P, 9) array_like of float
        Primitive parameters.
    period : (2,) array_like of float, optional
        (Lx, Ly) of a periodic tiling; primitives poking out of [0, Lx) x [0, Ly) are copied.

    Attributes
    ----------
    source : (P',) ndarray of int64
        For each stored primitive (after copies and reordering), its input index.
    """

    def __init__(self, ptype: ArrayLike, pdata: ArrayLike, *,
                 period: ArrayLike | None = None) -> None:
        pt = np.ascontiguousarray(ptype, dtype=np.int64).reshape(-1)
        pd = np.ascontiguousarray(pdata, dtype=np.float64).reshape(-1, 9)
        if pt.size == 0:
            raise ValueError("the scene must hold at least one primitive, got none")
        if pd.shape[0] != pt.size:
            raise ValueError(f"pdata must have one row per primitive ({pt.size}), got "
                             f"{pd.shape[0]}")
        lo, hi = _prim_bounds(pt, pd)
        src = np.arange(pt.size, dtype=np.int64)
        if period is not None:
            per = np.asarray(period, dtype=np.float64)
            pt, pd, lo, hi, src = _tile(pt, pd, lo, hi, src, per)
            self.period = per
        else:
            self.period = None
        order, nlo, nhi, link = _build(lo, hi)
        self.ptype = np.ascontiguousarray(pt[order])
        self.pdata = np.ascontiguousarray(pd[order])
        self.source = src[order]
        self.lo, self.hi, self.link = nlo, nhi, link

    @property
    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(lo, hi) corners of the box around all stored primitives."""
        return self.lo[0].copy(), self.hi[0].copy()

    def intersect(self, origins: ArrayLike, directions: ArrayLike, *,
                  tmax: float = np.inf) -> tuple[NDArray, NDArray, NDArray]:
        """First hits of rays with the stored primitives (no periodic walk).

        Parameters
        ----------
        origins, directions : (n, 3) array_like of float
            Ray origins and (unit) directions.
        tmax : float
            Hits beyond this distance are ignored.

        Returns
        -------
        t : (n,) ndarray -- hit distance (inf on a miss)
        prim : (n,) ndarray of int64 -- input primitive index (``source``; -1 on a miss)
        normal : (n, 3) ndarray -- unit normal facing the incoming ray (0 on a miss)
        """
        o = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
        n = o.shape[0]
        t = np.empty(n)
        prim = np.empty(n, np.int64)
        nrm = np.empty((n, 3))
        _intersect_kernel(o, d, float(tmax), self.lo, self.hi, self.link, self.ptype,
                          self.pdata, t, prim, nrm)
        hit = prim >= 0
        prim[hit] = self.source[prim[hit]]
        return t, prim, nrm

    def intersect_periodic(self, origins: ArrayLike, directions: ArrayLike, *,
                           max_steps: int = 100_000) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """First hits in the periodic tiling (needs ``period``); origins may lie anywhere.

        Returns
        -------
        status : (n,) int64 -- 0 hit, 1 escaped upwards, 2 lost (fell through or step cap)
        t, prim, normal : as :meth:`intersect` (prim is the input index of the primitive
        whose periodic copy was hit)
        """
        if self.period is None:
            raise ValueError("intersect_periodic needs a BVH built with a period")
        o = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
        n = o.shape[0]
        st = np.empty(n, np.int64)
        t = np.empty(n)
        prim = np.empty(n, np.int64)
        nrm = np.empty((n, 3))
        lx, ly = self.period
        _periodic_kernel(o, d, lx, ly, self.lo[0, 2], self.hi[0, 2], max_steps, self.lo,
                         self.hi, self.link, self.ptype, self.pdata, st, t, prim, nrm)
        hit = prim >= 0
        prim[hit] = self.source[prim[hit]]
        return st, t, prim, nrm

    def __repr__(self) -> str:
        return f"BVH(primitives={self.ptype.size}, nodes={self.link.shape[0]})"


# -- building ---------------------------------------------------------------------------------

def _prim_bounds(pt: NDArray, pd: NDArray) -> tuple[NDArray, NDArray]:
    lo = np.empty((pt.size, 3))
    hi = np.empty((pt.size, 3))
    tri = pt == TRIANGLE
    v = pd[tri].reshape(-1, 3, 3)
    lo[tri] = v.min(axis=1)
    hi[tri] = v.max(axis=1)
    cyl = pt == CYLINDER
    c = pd[cyl]
    ax = c[:, 0].astype(np.int64)
    r = c[:, 3]
    along = np.stack([c[:, 4], c[:, 5]], axis=1)  # lo, hi along the axis
    across = np.stack([c[:, 1] - r, c[:, 1] + r], axis=1)
    x = np.where(ax[:, None] == 0, along, across)
    y = np.where(ax[:, None] == 0, across, along)
    lo[cyl] = np.stack([x[:, 0], y[:, 0], c[:, 2] - r], axis=1)
    hi[cyl] = np.stack([x[:, 1], y[:, 1], c[:, 2] + r], axis=1)
    return lo, hi


def _shift(pt: NDArray, pd: NDArray, sx: float, sy: float) -> NDArray:
    out = pd.copy()
    tri = pt == TRIANGLE
    out[tri, 0::3] += sx
    out[tri, 1::3] += sy
    cyl = pt == CYLINDER
    ax = out[cyl, 0]
    # across-axis position p moves by the shift across; the cut [lo, hi] by the shift along
    out[cyl, 1] += np.where(ax == 0, sy, sx)
    out[cyl, 4] += np.where(ax == 0, sx, sy)
    out[cyl, 5] += np.where(ax == 0, sx, sy)
    return out


def _tile(pt, pd, lo, hi, src, per):
    # copies shifted by -(kx Lx, ky Ly) for every period cell (kx, ky) the box touches
    lx, ly = per
    kx0 = np.floor(lo[:, 0] / lx).astype(np.int64)
    kx1 = np.ceil(hi[:, 0] / lx).astype(np.int64) - 1
    ky0 = np.floor(lo[:, 1] / ly).astype(np.int64)
    ky1 = np.ceil(hi[:, 1] / ly).astype(np.int64) - 1
    kx1 = np.maximum(kx1, kx0)
    ky1 = np.maximum(ky1, ky0)
    parts = []
    for kx in range(int(kx0.min()), int(kx1.max()) + 1):
        for ky in range(int(ky0.min()), int(ky1.max()) + 1):
            sel = (kx0 <= kx) & (kx <= kx1) & (ky0 <= ky) & (ky <= ky1)
            if not sel.any():
                continue
            d = _shift(pt[sel], pd[sel], -kx * lx, -ky * ly)
            sh = np.array([-kx * lx, -ky * ly, 0.0])
            parts.append((pt[sel], d, lo[sel] + sh, hi[sel] + sh, src[sel]))
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(5))


def _build(plo: NDArray, phi: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Median-split hierarchy: (primitive order, node lo, node hi, node link)."""
    n = plo.shape[0]
    cent = 0.5 * (plo + phi)
    order = np.arange(n, dtype=np.int64)
    nlo: list[NDArray] = []
    nhi: list[NDArray] = []
    link: list[list[int]] = []
    todo = [(0, n, -1)]  # (start, end, parent whose right link to set); left child first
    while todo:
        start, end, parent = todo.pop()
        idx = len(link)
        if parent >= 0:
            link[parent][0] = idx
        sub = order[start:end]
        nlo.append(plo[sub].min(axis=0))
        nhi.append(phi[sub].max(axis=0))
        if end - start <= LEAF:
            link.append([start, end - start])
            continue
        link.append([-1, 0])
        c = cent[sub]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        mid = (end - start) // 2
        order[start:end] = sub[np.argpartition(c[:, axis], mid)]
        # the right half waits on the stack; the left half is built next (index idx + 1)
        todo.append((start + mid, end, idx))
        todo.append((start, start + mid, -1))
    return (order, np.array(nlo), np.array(nhi), np.array(link, dtype=np.int64))


# -- kernels ----------------------------------------------------------------------------------

@njit
def _hit_triangle(p, ox, oy, oz, dx, dy, dz, tmin, tmax):
    # Moeller-Trumbore; p (9,) corners; returns t in (tmin, tmax) or inf
    e1x = p[3] - p[0]
    e1y = p[4] - p[1]
    e1z = p[5] - p[2]
    e2x = p[6] - p[0]
    e2y = p[7] - p[1]
    e2z = p[8] - p[2]
    qx = dy * e2z - dz * e2y
    qy = dz * e2x - dx * e2z
    qz = dx * e2y - dy * e2x
    det = e1x * qx + e1y * qy + e1z * qz
    if det == 0.0:
        return np.inf
    inv = 1.0 / det
    sx = ox - p[0]
    sy = oy - p[1]
    sz = oz - p[2]
    u = (sx * qx + sy * qy + sz * qz) * inv
    if u < 0.0 or u > 1.0:
        return np.inf
    rx = sy * e1z - sz * e1y
    ry = sz * e1x - sx * e1z
    rz = sx * e1y - sy * e1x
    v = (dx * rx + dy * ry + dz * rz) * inv
    if v < 0.0 or u + v > 1.0:
        return np.inf
    t = (e2x * rx + e2y * ry + e2z * rz) * inv
    if tmin < t < tmax:
        return t
    return np.inf


@njit
def _hit_cylinder(p, ox, oy, oz, dx, dy, dz, tmin, tmax):
    # open tube p = (axis, pos, cz, r, lo, hi): nearest root in (tmin, tmax) whose point lies
    # in [lo, hi] along the axis; the quadratic in the cross-section plane, solved stably
    if p[0] == 0.0:
        a0, ad, u0, ud = oy - p[1], dy, ox, dx
    else:
        a0, ad, u0, ud = ox - p[1], dx, oy, dy
    b0 = oz - p[2]
    a = ad * ad + dz * dz
    if a == 0.0:
        return np.inf
    hb = a0 * ad + b0 * dz
    c = a0 * a0 + b0 * b0 - p[3] * p[3]
    disc = hb * hb - a * c
    if disc < 0.0:
        return np.inf
    sq = np.sqrt(disc)
    q = -(hb + sq) if hb >= 0.0 else -(hb - sq)
    if q == 0.0:
        return np.inf
    r1 = q / a
    r2 = c / q
    t1 = min(r1, r2)
    t2 = max(r1, r2)
    for t in (t1, t2):
        if tmin < t < tmax:
            u = u0 + t * ud
            if p[4] <= u <= p[5]:
                return t
    return np.inf


@njit
def _normal(ptype, p, px, py, pz, dx, dy, dz):
    # unit normal of the primitive at the point, turned to face the incoming direction, and
    # front: True when the ray arrives on the outer side (triangles: the side the winding
    # (v1 - v0) x (v2 - v0) points to; cylinders: outside the tube)
    if ptype == TRIANGLE:
        e1x = p[3] - p[0]
        e1y = p[4] - p[1]
        e1z = p[5] - p[2]
        e2x = p[6] - p[0]
        e2y = p[7] - p[1]
        e2z = p[8] - p[2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
    else:
        if p[0] == 0.0:
            nx = 0.0
            ny = py - p[1]
        else:
            nx = px - p[1]
            ny = 0.0
        nz = pz - p[2]
    inv = 1.0 / np.sqrt(nx * nx + ny * ny + nz * nz)
    front = nx * dx + ny * dy + nz * dz <= 0.0
    if not front:
        inv = -inv
    return nx * inv, ny * inv, nz * inv, front


@njit
def _closest(ox, oy, oz, dx, dy, dz, tmin, tmax, lo, hi, link, ptype, pdata):
    # First hit in (tmin, tmax): returns (stored primitive index or -1, t). Iterative
    # traversal with a fixed stack; the nearer child is visited first.
    idx = np.ones(3)
    idx[0] = 1.0 / dx if dx != 0.0 else np.inf
    idx[1] = 1.0 / dy if dy != 0.0 else np.inf
    idx[2] = 1.0 / dz if dz != 0.0 else np.inf
    stack = np.empty(_STACK, np.int64)
    sp = 0
    stack[sp] = 0
    sp += 1
    best = -1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        if not _box(node, ox, oy, oz, idx, tmin, tmax, lo, hi):
            continue
        start = link[node, 0]
        count = link[node, 1]
        if count > 0:
            for k in range(start, start + count):
                if ptype[k] == TRIANGLE:
                    t = _hit_triangle(pdata[k], ox, oy, oz, dx, dy, dz, tmin, tmax)
                else:
                    t = _hit_cylinder(pdata[k], ox, oy, oz, dx, dy, dz, tmin, tmax)
                if t < tmax:
                    tmax = t
                    best = k
        else:
            left = node + 1
            right = start
            # push the farther child first (by the entry distance along the split axis)
            cl = lo[left, 0] + hi[left, 0] - lo[right, 0] - hi[right, 0]
            cy = lo[left, 1] + hi[left, 1] - lo[right, 1] - hi[right, 1]
            cz = lo[left, 2] + hi[left, 2] - lo[right, 2] - hi[right, 2]
            if cl * dx + cy * dy + cz * dz > 0.0:
                stack[sp] = left
                stack[sp + 1] = right
            else:
                stack[sp] = right
                stack[sp + 1] = left
            sp += 2
    return best, tmax


@njit
def _box(node, ox, oy, oz, idx, tmin, tmax, lo, hi):
    # slab test of the ray against node's box on (tmin, tmax)
    t0 = tmin
    t1 = tmax
    o = (ox, oy, oz)
    for a in range(3):
        if idx[a] == np.inf:
            if o[a] < lo[node, a] or o[a] > hi[node, a]:
                return False
            continue
        ta = (lo[node, a] - o[a]) * idx[a]
        tb = (hi[node, a] - o[a]) * idx[a]
        if ta > tb:
            ta, tb = tb, ta
        t0 = max(t0, ta)
        t1 = min(t1, tb * (1.0 + 4e-16))
        if t0 > t1:
            return False
    return True


@pjit
def _intersect_kernel(o, d, tmax, lo, hi, link, ptype, pdata, t, prim, nrm):
    # o, d (n, 3) rays; t (n,), prim (n,), nrm (n, 3) out
    for r in prange(o.shape[0]):
        k, th = _closest(o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1], d[r, 2], 0.0, tmax, lo,
                         hi, link, ptype, pdata)
        prim[r] = k
        if k >= 0:
            t[r] = th
            nx, ny, nz, _ = _normal(ptype[k], pdata[k], o[r, 0] + th * d[r, 0],
                                 o[r, 1] + th * d[r, 1], o[r, 2] + th * d[r, 2], d[r, 0],
                                 d[r, 1], d[r, 2])
            nrm[r, 0] = nx
            nrm[r, 1] = ny
            nrm[r, 2] = nz
        else:
            t[r] = np.inf
            nrm[r, 0] = 0.0
            nrm[r, 1] = 0.0
            nrm[r, 2] = 0.0


@njit
def _periodic_hit(ox, oy, oz, dx, dy, dz, lx, ly, zmin, zmax, max_steps, lo, hi, link, ptype,
                  pdata):
    # Walk the period cells along the ray from t = 0 (unwrapped coordinates); in each cell
    # ask the hierarchy (origin moved back into [0, Lx) x [0, Ly)) for the first hit inside
    # the cell. Returns (status, t, normal x, y, z, stored primitive or -1, front) with the
    # normal facing the ray and front as in _normal (True when nothing was hit).
    tol = 1e-9 * (zmax - zmin + lx + ly)
    t = 0.0
    for _ in range(max_steps):
        z = oz + t * dz
        if dz >= 0.0 and z > zmax:
            return _ESCAPED, t, 0.0, 0.0, 0.0, -1, True
        if dz < 0.0 and z < zmin - tol:
            return _LOST, t, 0.0, 0.0, 0.0, -1, True
        px = ox + t * dx
        py = oy + t * dy
        ix = int(np.floor(px / lx))
        iy = int(np.floor(py / ly))
        # on a cell boundary, take the cell the ray is entering
        if dx > 0.0:
            if (ix + 1) * lx - px <= 1e-12 * lx:
                ix += 1
            tx = ((ix + 1) * lx - ox) / dx
        elif dx < 0.0:
            if px - ix * lx <= 1e-12 * lx:
                ix -= 1
            tx = (ix * lx - ox) / dx
        else:
            tx = np.inf
        if dy > 0.0:
            if (iy + 1) * ly - py <= 1e-12 * ly:
                iy += 1
            ty = ((iy + 1) * ly - oy) / dy
        elif dy < 0.0:
            if py - iy * ly <= 1e-12 * ly:
                iy -= 1
            ty = (iy * ly - oy) / dy
        else:
            ty = np.inf
        t1 = min(tx, ty)
        if dz < 0.0:
            t1 = min(t1, (zmin - 2.0 * tol - oz) / dz)
        elif dz > 0.0:
            t1 = min(t1, (zmax + tol - oz) / dz)
        lox = ox - ix * lx
        loy = oy - iy * ly
        k, th = _closest(lox, loy, oz, dx, dy, dz, max(t - tol, tol), t1 + tol, lo, hi, link,
                         ptype, pdata)
        if k >= 0:
            nx, ny, nz, front = _normal(ptype[k], pdata[k], lox + th * dx, loy + th * dy,
                                        oz + th * dz, dx, dy, dz)
            return _HIT, th, nx, ny, nz, k, front
        t = max(t1, t)
    return _LOST, t, 0.0, 0.0, 0.0, -1, True


@pjit
def _periodic_kernel(o, d, lx, ly, zmin, zmax, max_steps, lo, hi, link, ptype, pdata, st, t,
                     prim, nrm):
    # o, d (n, 3) rays; st, t, prim (n,), nrm (n, 3) out
    for r in prange(o.shape[0]):
        s, th, nx, ny, nz, k, _ = _periodic_hit(o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1],
                                             d[r, 2], lx, ly, zmin, zmax, max_steps, lo, hi,
                                             link, ptype, pdata)
        st[r] = s
        t[r] = th if s == _HIT else np.inf
        prim[r] = k
        nrm[r, 0] = nx
        nrm[r, 1] = ny
        nrm[r, 2] = nz
