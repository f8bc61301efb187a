"""A numba bounding volume hierarchy over triangles and analytic primitives, periodic in x, y.

Primitives are stored in two flat arrays: ``ptype`` (P,) int64 and ``pdata`` (P, 9) float64:

- ``TRIANGLE`` (0): the corners v0, v1, v2 (9 numbers); outer side: the one the winding
  normal (v1 - v0) x (v2 - v0) points to;
- ``CYLINDER`` (1): (axis, p, cz, r, lo, hi, 0, 0, 0) -- an open tube of radius r whose axis
  is parallel to x (axis = 0; the axis is the line y = p, z = cz) or to y (axis = 1; x = p,
  z = cz), cut to lo <= x <= hi (resp. y);
- ``SPHERE`` (2): (cx, cy, cz, r, 0, 0, 0, 0, 0);
- ``TUBE`` (3): (x0, y0, z0, x1, y1, z1, r, caps, 0) -- a finite cylinder of radius r around
  the segment p0 -> p1 in any direction; caps = 1 closes it with flat discs at both ends (a
  closed solid), caps = 0 leaves it open.

Analytic primitives are intersected exactly (a quadratic per ray, solved in the stable form
q = -(b + sign(b) sqrt(disc)), t = q / a, c / q, with the discriminant written as a r^2 -
|w x d|^2 so that it does not cancel for distant origins; caps as ray-plane + disc tests).
Their outer side is the outside of the solid (cylinders and open tubes: away from the axis),
so a ray starting inside a sphere or a capped tube finds the far wall from behind
(``front`` False in :func:`_normal`), as refraction inside fibres needs.

The hierarchy is built in numba, top-down, by binned surface-area-heuristic splits
(``build="sah"``, the default: 16 bins over the centroid extent on each axis, cost
``_COST_NODE`` per node visit against ``_COST_PRIM`` per primitive test) or by median splits
of the centroids along their longest extent (``build="median"``). A node becomes a leaf when
it holds at most ``LEAF`` primitives, or at most ``MAX_LEAF`` and no split beats testing them
all. Nodes are stored as flat arrays: ``lo``, ``hi`` (N, 3) boxes and ``link`` (N, 2) int64 --
a leaf holds (first primitive, count > 0), an inner node (right child, 0) with its left child
at the next index (depth-first order). Traversal is iterative: at an inner node both child
boxes are tested, the nearer one is visited next and the farther one waits with its entry
distance on a fixed stack of ``_STACK`` = 64 entries (at most one per level: enough for
leaves down to depth 63). The build keeps every leaf there: a node switches from SAH to
median splits (which halve the count) as soon as the depth left would not suffice for them,
and the depth is checked after the build.

Periodic tiling: for a period box [0, Lx) x [0, Ly) every primitive whose box pokes out of it
is also inserted shifted by whole periods, so the copies cover every part of the surface
that lies inside the box. :func:`_periodic_hit` then walks the ray from period cell to
period cell (unwrapped coordinates, as the height-field tracer does) and asks the hierarchy
for the first hit inside each cell.
"""

from __future__ import annotations

import codecs
import math
import os
import re

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basis.jit import loopjit, njit, run_parallel

from .._reading import NUMBER, regular_file
from ._paths import _ESCAPED, _HIT, _LOST, _grid_step

__all__ = ["BVH", "Mesh"]

TRIANGLE, CYLINDER, SPHERE, TUBE = 0, 1, 2, 3

#: a node with at most this many primitives is always a leaf
LEAF = 4

#: the SAH build keeps at most this many primitives in a leaf (when no split pays off)
MAX_LEAF = 16

#: traversal stack entries; a tree with leaves down to depth D needs at most D of them
_STACK = 64

#: SAH: number of centroid bins per axis, cost of visiting a node (its two child boxes)
#: relative to one primitive test
_BINS = 16
_COST_NODE = 1.0
_COST_PRIM = 1.0

_BUILDS = ("sah", "median")

#: an OBJ vertex index: optional sign and ASCII digits (int() would also take "1_0", "\u0661")
_OBJ_INDEX = re.compile(r"[+-]?[0-9]+")
#: a v or f keyword glued to its first number ("v1.0"): a damaged record, not a new keyword
_OBJ_GLUED = re.compile(r"[vf][-+.0-9]")
#: a number as C's strtod reads it in an OBJ file: ASCII digits only (Python's float would
#: also take "1_0" and other scripts' digits); inf and nan are read, then refused as such.
#: The measurement tables read numbers with the same pattern.
_OBJ_NUMBER = NUMBER
#: the keywords of the OBJ format (Wavefront, Appendix B1); they are case-sensitive, so a
#: line starting with one of them in other letter case is damage, not an unknown keyword
_OBJ_KEYWORDS = frozenset(
    "v vt vn vp cstype deg bmat step p l f curv curv2 surf parm trim hole scrv sp end con g s "
    "mg o bevel c_interp d_interp lod usemtl mtllib shadow_obj trace_obj ctech stech maplib "
    "usemap call csh".split())
_OBJ_FOLDED = {k.lower(): k for k in _OBJ_KEYWORDS}


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
        r"""Read the ``v`` and ``f`` lines of a Wavefront OBJ file.

        Face entries may be ``i``, ``i/t``, ``i//n`` or ``i/t/n`` (only i is used; negative
        i counts back from the last vertex read so far); polygons with more than three
        corners are split into a fan around their first corner. ``v`` lines take their first
        three numbers (a fourth weight or trailing colours are ignored), written as C's
        ``strtod`` reads them (ASCII digits, no ``_``). Every other line (``vt``, ``vn``,
        ``o``, ``g``, ``usemtl``, unknown keywords, ...) is ignored by its first token,
        except a known keyword in other letter case (``V``, ``Usemtl``: OBJ keywords are
        case-sensitive, and skipping a ``V`` line would shift every later vertex), as are
        comments from ``#`` to the end of a line; a line ending in
        ``\`` continues on the next one (Wavefront, "Object Files (.obj)", Appendix B1 of
        the Advanced Visualizer manual). A UTF-8 byte-order mark is skipped and bytes that
        are not UTF-8 are tolerated outside ``v`` and ``f`` lines (comments and names often
        hold Latin-1).

        Raises
        ------
        ValueError
            Naming the file and line: a ``v`` line without three finite numbers, an ``f``
            line with fewer than three corners or an index that is not an integer, is 0 or
            refers to a vertex the file does not define, a keyword glued to its number
            (``v1.0 2 3``) or in the wrong letter case (``V 1 2 3``), a file cut off in
            the middle of a record, no ``f`` line at all,
            or degenerate triangles; or a path that is not a regular file (a FIFO, a
            device).
        OSError
            If the file cannot be read.
        """
        name = os.fspath(path)
        regular_file(path, "OBJ file")  # a FIFO would block open()
        with open(path, "rb") as fh:
            data = fh.read()
        if data.startswith(codecs.BOM_UTF8):
            data = data[len(codecs.BOM_UTF8):]
        # bytes.splitlines splits at \n, \r\n and \r only (str.splitlines would also split at
        # form feeds and Unicode separators inside names)
        lines = data.splitlines()
        cut = bool(data) and not data.endswith((b"\n", b"\r"))

        def fail(lineno: int, what: str, line: str) -> ValueError:
            hint = ""
            if cut and lineno == len(lines):
                hint = " (the file ends inside this line without a newline: is it truncated?)"
            return ValueError(f"{name}:{lineno}: {what}, got {line.strip()!r}{hint}")

        verts: list[tuple[float, float, float]] = []
        faces: list[list[int]] = []
        face_lines: list[int] = []
        k = 0
        while k < len(lines):
            lineno = k + 1
            raw = lines[k]
            k += 1
            while raw.rstrip().endswith(b"\\") and k < len(lines):
                raw = raw.rstrip()[:-1] + b" " + lines[k]
                k += 1
            # '#' is one byte in UTF-8 and Latin-1 alike: cut the comment before decoding
            raw = raw.split(b"#", 1)[0]
            line = raw.decode("utf-8", errors="replace")
            parts = line.split()
            if not parts:
                continue
            key = parts[0]
            if key == "v":
                xyz = tuple(float(x) for x in parts[1:4] if _OBJ_NUMBER.fullmatch(x))
                if len(xyz) != 3:
                    raise fail(lineno, "v line must hold three numbers", line)
                if not all(map(math.isfinite, xyz)):
                    raise fail(lineno, "v line must hold finite numbers", line)
                verts.append(xyz)  # type: ignore[arg-type]
            elif key == "f":
                corners = [p.split("/")[0] for p in parts[1:]]
                if not all(_OBJ_INDEX.fullmatch(c) for c in corners):
                    raise fail(lineno, "f line must hold vertex indices", line)
                idx = [int(c) for c in corners]
                if len(idx) < 3:
                    raise fail(lineno, "f line must have >= 3 corners", line)
                if any(i == 0 for i in idx):
                    raise fail(lineno, "OBJ vertex indices start at 1", line)
                if any(len(verts) + i < 0 for i in idx if i < 0):
                    raise fail(lineno, f"f line counts back past the first vertex (only "
                                       f"{len(verts)} read so far)", line)
                idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
                for j in range(1, len(idx) - 1):
                    faces.append([idx[0], idx[j], idx[j + 1]])
                    face_lines.append(lineno)
            elif _OBJ_GLUED.match(key):
                raise fail(lineno, f"keyword {key[0]!r} must be followed by a space", line)
            elif key not in _OBJ_KEYWORDS and key.lower() in _OBJ_FOLDED:
                raise fail(lineno, f"keyword {key!r} differs from the OBJ keyword "
                                   f"{_OBJ_FOLDED[key.lower()]!r} only in case (keywords are "
                                   "case-sensitive)", line)
        if not faces:
            raise ValueError(f"{name} must contain at least one f line, found none")
        # positive indices may refer forward, so they are checked once every v line is read
        # (a 20-digit index is refused here, before numpy would overflow on it)
        nv = len(verts)
        for f, lineno in zip(faces, face_lines, strict=True):
            if max(f) >= nv:
                raise ValueError(f"{name}:{lineno}: f line refers to vertex {max(f) + 1}, but "
                                 f"the file defines only {nv} vertices (is it truncated?)")
        try:
            return cls(np.array(verts, dtype=np.float64).reshape(-1, 3),
                       np.array(faces, dtype=np.int64))
        except ValueError as err:
            match = re.search(r"first: face (\d+)", str(err))
            where = f":{face_lines[int(match.group(1))]}" if match else ""
            raise ValueError(f"{name}{where}: {err}") from None

    def triangles(self) -> NDArray[np.float64]:
        """Return the (F, 3, 3) corner positions of every triangle."""
        return self.vertices[self.faces]

    def __repr__(self) -> str:
        return f"Mesh(vertices={self.vertices.shape[0]}, faces={self.faces.shape[0]})"


class BVH:
    """A bounding volume hierarchy over packed primitives (see the module docstring).

    Parameters
    ----------
    ptype : (P,) array_like of int
        ``TRIANGLE`` (0), ``CYLINDER`` (1), ``SPHERE`` (2) or ``TUBE`` (3) per primitive.
    pdata : (P, 9) array_like of float
        Primitive parameters (see the module docstring).
    period : (2,) array_like of float, optional
        (Lx, Ly) of a periodic tiling; primitives poking out of [0, Lx) x [0, Ly) are copied.
    build : {"sah", "median"}
        Split rule of the hierarchy: binned surface area heuristic or centroid median. Both
        give the same first hits; SAH traces faster on uneven scenes.

    Attributes
    ----------
    source : (P',) ndarray of int64
        For each stored primitive (after copies and reordering), its input index.
    depth : int
        Depth of the deepest leaf (root 0); at most ``_STACK - 1``.

    Examples
    --------
    >>> bvh = BVH([SPHERE], [[0, 0, 0, 1, 0, 0, 0, 0, 0]])
    >>> t, prim, normal = bvh.intersect([[0, 0, 5]], [[0, 0, -1]])
    >>> float(t[0]), int(prim[0]), normal[0].tolist()
    (4.0, 0, [0.0, 0.0, 1.0])
    """

    def __init__(self, ptype: ArrayLike, pdata: ArrayLike, *,
                 period: ArrayLike | None = None, build: str = "sah") -> None:
        pt = np.ascontiguousarray(ptype, dtype=np.int64).reshape(-1)
        pd = np.ascontiguousarray(pdata, dtype=np.float64).reshape(-1, 9)
        if pt.size == 0:
            raise ValueError("the scene must hold at least one primitive, got none")
        if pd.shape[0] != pt.size:
            raise ValueError(f"pdata must have one row per primitive ({pt.size}), got "
                             f"{pd.shape[0]}")
        bad = np.flatnonzero((pt < TRIANGLE) | (pt > TUBE))
        if bad.size:
            raise ValueError(f"ptype must be TRIANGLE (0), CYLINDER (1), SPHERE (2) or TUBE "
                             f"(3), got {pt[bad[0]]} at index {bad[0]}")
        if build not in _BUILDS:
            raise ValueError(f"build must be one of {_BUILDS}, got {build!r}")
        lo, hi = _prim_bounds(pt, pd)
        src = np.arange(pt.size, dtype=np.int64)
        if period is not None:
            per = np.asarray(period, dtype=np.float64)
            pt, pd, lo, hi, src = _tile(pt, pd, lo, hi, src, per)
            self.period = per
        else:
            self.period = None
        order, nlo, nhi, link, depth = _build(lo, hi, build)
        if depth > _STACK - 1:  # _build guarantees this; traversal could overflow otherwise
            raise RuntimeError(f"BVH depth {depth} exceeds the {_STACK - 1} levels the "
                               f"traversal stack of {_STACK} entries allows")
        self.ptype = np.ascontiguousarray(pt[order])
        self.pdata = np.ascontiguousarray(pd[order])
        self.source = src[order]
        self.lo, self.hi, self.link = nlo, nhi, link
        self.depth = depth

    @property
    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(lo, hi) corners of the box around all stored primitives."""
        return self.lo[0].copy(), self.hi[0].copy()

    def intersect(self, origins: ArrayLike, directions: ArrayLike, *,
                  tmax: float = np.inf) -> tuple[NDArray, NDArray, NDArray]:
        """Find the first hits of rays with the stored primitives (no periodic walk).

        Parameters
        ----------
        origins, directions : (n, 3) array_like of float
            Ray origins and (unit) directions.
        tmax : float
            Hits beyond this distance are ignored.

        Returns
        -------
        t : (n,) ndarray
            Hit distance (inf on a miss).
        prim : (n,) ndarray of int64
            Input primitive index (``source``; -1 on a miss).
        normal : (n, 3) ndarray
            Unit normal facing the incoming ray (0 on a miss).
        """
        o = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
        n = o.shape[0]
        t = np.empty(n)
        prim = np.empty(n, np.int64)
        nrm = np.empty((n, 3))
        run_parallel(_intersect_kernel, n, o, d, float(tmax), self.lo, self.hi, self.link,
                     self.ptype, self.pdata, t, prim, nrm, grain=_GRAIN)
        hit = prim >= 0
        prim[hit] = self.source[prim[hit]]
        return t, prim, nrm

    def intersect_periodic(self, origins: ArrayLike, directions: ArrayLike, *,
                           max_steps: int = 100_000) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Find the first hits in the periodic tiling (needs ``period``).

        Parameters
        ----------
        origins, directions : (n, 3) array_like of float
            Ray origins (anywhere) and (unit) directions.
        max_steps : int
            Cap on the period cells walked per ray.

        Returns
        -------
        status : (n,) ndarray of int64
            0 hit, 1 escaped upwards, 2 lost (fell through or step cap).
        t, prim, normal : ndarray
            As :meth:`intersect` (prim is the input index of the primitive whose periodic
            copy was hit).
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
        run_parallel(_periodic_kernel, n, o, d, lx, ly, self.lo[0, 2], self.hi[0, 2], max_steps,
                     self.lo, self.hi, self.link, self.ptype, self.pdata, st, t, prim, nrm,
                     grain=_GRAIN)
        hit = prim >= 0
        prim[hit] = self.source[prim[hit]]
        return st, t, prim, nrm

    def __repr__(self) -> str:
        return f"BVH(primitives={self.ptype.size}, nodes={self.link.shape[0]})"


# -- building ---------------------------------------------------------------------------------

def _prim_bounds(pt: NDArray, pd: NDArray) -> tuple[NDArray, NDArray]:
    # exact axis-aligned boxes (P, 3) of every primitive
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
    sph = pt == SPHERE
    s = pd[sph]
    lo[sph] = s[:, 0:3] - s[:, 3:4]
    hi[sph] = s[:, 0:3] + s[:, 3:4]
    tub = pt == TUBE
    b = pd[tub]
    a = b[:, 3:6] - b[:, 0:3]
    a /= np.linalg.norm(a, axis=1)[:, None]
    # the end discs (radius r, normal a) reach r sqrt(1 - a_k^2) beyond the ends along axis k
    ext = b[:, 6:7] * np.sqrt(np.maximum(0.0, 1.0 - a * a))
    lo[tub] = np.minimum(b[:, 0:3], b[:, 3:6]) - ext
    hi[tub] = np.maximum(b[:, 0:3], b[:, 3:6]) + ext
    return lo, hi


def _shift(pt: NDArray, pd: NDArray, sx: float, sy: float) -> NDArray:
    # the primitives moved by (sx, sy, 0)
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
    sph = pt == SPHERE
    out[sph, 0] += sx
    out[sph, 1] += sy
    tub = pt == TUBE
    out[tub, 0] += sx
    out[tub, 1] += sy
    out[tub, 3] += sx
    out[tub, 4] += sy
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


def _build(plo: NDArray, phi: NDArray, build: str = "sah", max_depth: int = _STACK - 1
           ) -> tuple[NDArray, NDArray, NDArray, NDArray, int]:
    """Build the hierarchy over boxes (P, 3).

    Returns (primitive order, node lo, node hi, node link, depth). Every leaf lies at depth
    <= ``max_depth`` (given P <= LEAF 2^max_depth).
    """
    n = plo.shape[0]
    plo = np.ascontiguousarray(plo, dtype=np.float64)
    phi = np.ascontiguousarray(phi, dtype=np.float64)
    order = np.arange(n, dtype=np.int64)
    nlo = np.empty((2 * n - 1, 3))
    nhi = np.empty((2 * n - 1, 3))
    link = np.empty((2 * n - 1, 2), np.int64)
    nodes, depth = _build_kernel(plo, phi, build == "sah", max_depth, _COST_NODE, _COST_PRIM,
                                 MAX_LEAF, order, nlo, nhi, link)
    return order, nlo[:nodes].copy(), nhi[:nodes].copy(), link[:nodes].copy(), depth


@njit
def _median_levels(n):
    # depth a subtree of n primitives needs when every split halves it (larger half ceil)
    levels = 0
    while n > LEAF:
        n = (n + 1) // 2
        levels += 1
    return levels


@njit
def _area(lx, ly, lz, hx, hy, hz):
    # half the surface area of a box (the SAH only uses ratios)
    ex = hx - lx
    ey = hy - ly
    ez = hz - lz
    return ex * ey + ey * ez + ez * ex


@njit
def _build_kernel(plo, phi, sah, max_depth, cost_node, cost_prim, max_leaf, order, nlo, nhi,
                  link):
    # Top-down build with an explicit stack of pending right children. plo, phi (P, 3)
    # primitive boxes; order (P,) permuted in place; nlo, nhi (2P - 1, 3), link (2P - 1, 2)
    # filled depth-first. Returns (node count, depth of the deepest leaf).
    n = plo.shape[0]
    cent = 0.5 * (plo + phi)
    # pending nodes: at most one right sibling per depth plus the node being split
    st_start = np.empty(max_depth + 2, np.int64)
    st_end = np.empty(max_depth + 2, np.int64)
    st_parent = np.empty(max_depth + 2, np.int64)
    st_depth = np.empty(max_depth + 2, np.int64)
    st_start[0] = 0
    st_end[0] = n
    st_parent[0] = -1
    st_depth[0] = 0
    sp = 1
    nodes = 0
    deepest = 0
    bin_n = np.empty((3, _BINS), np.int64)
    bin_lo = np.empty((3, _BINS, 3))
    bin_hi = np.empty((3, _BINS, 3))
    right_area = np.empty(_BINS)
    right_n = np.empty(_BINS, np.int64)
    clo = np.empty(3)  # centroid bounds of the node
    chi = np.empty(3)
    while sp > 0:
        sp -= 1
        start = st_start[sp]
        end = st_end[sp]
        parent = st_parent[sp]
        depth = st_depth[sp]
        node = nodes
        nodes += 1
        if parent >= 0:
            link[parent, 0] = node
        cnt = end - start
        for a in range(3):
            nlo[node, a] = np.inf
            nhi[node, a] = -np.inf
            clo[a] = np.inf
            chi[a] = -np.inf
        for i in range(start, end):
            k = order[i]
            for a in range(3):
                nlo[node, a] = min(nlo[node, a], plo[k, a])
                nhi[node, a] = max(nhi[node, a], phi[k, a])
                clo[a] = min(clo[a], cent[k, a])
                chi[a] = max(chi[a], cent[k, a])
        if cnt <= LEAF:
            link[node, 0] = start
            link[node, 1] = cnt
            deepest = max(deepest, depth)
            continue
        need = _median_levels(cnt)
        # SAH only while a median chain below either child would still fit: children have
        # at most cnt - 1 primitives, so need(child) <= need(cnt)
        best_axis = -1
        best_bin = 0
        best_cost = np.inf
        if sah and depth + 1 + need <= max_depth:
            parea = _area(nlo[node, 0], nlo[node, 1], nlo[node, 2], nhi[node, 0],
                          nhi[node, 1], nhi[node, 2])
            for a in range(3):
                ext = chi[a] - clo[a]
                if not ext > 0.0:
                    continue
                for b in range(_BINS):
                    bin_n[a, b] = 0
                    for c in range(3):
                        bin_lo[a, b, c] = np.inf
                        bin_hi[a, b, c] = -np.inf
                scale = _BINS / ext
                for i in range(start, end):
                    k = order[i]
                    b = min(int((cent[k, a] - clo[a]) * scale), _BINS - 1)
                    bin_n[a, b] += 1
                    for c in range(3):
                        bin_lo[a, b, c] = min(bin_lo[a, b, c], plo[k, c])
                        bin_hi[a, b, c] = max(bin_hi[a, b, c], phi[k, c])
                # sweep from the right: area and count of bins b .. _BINS - 1
                rx0 = ry0 = rz0 = np.inf
                rx1 = ry1 = rz1 = -np.inf
                m = 0
                for b in range(_BINS - 1, 0, -1):
                    if bin_n[a, b] > 0:
                        rx0 = min(rx0, bin_lo[a, b, 0])
                        ry0 = min(ry0, bin_lo[a, b, 1])
                        rz0 = min(rz0, bin_lo[a, b, 2])
                        rx1 = max(rx1, bin_hi[a, b, 0])
                        ry1 = max(ry1, bin_hi[a, b, 1])
                        rz1 = max(rz1, bin_hi[a, b, 2])
                        m += bin_n[a, b]
                    right_n[b] = m
                    right_area[b] = _area(rx0, ry0, rz0, rx1, ry1, rz1) if m > 0 else 0.0
                lx0 = ly0 = lz0 = np.inf
                lx1 = ly1 = lz1 = -np.inf
                m = 0
                for b in range(_BINS - 1):  # split between bins b and b + 1
                    if bin_n[a, b] > 0:
                        lx0 = min(lx0, bin_lo[a, b, 0])
                        ly0 = min(ly0, bin_lo[a, b, 1])
                        lz0 = min(lz0, bin_lo[a, b, 2])
                        lx1 = max(lx1, bin_hi[a, b, 0])
                        ly1 = max(ly1, bin_hi[a, b, 1])
                        lz1 = max(lz1, bin_hi[a, b, 2])
                        m += bin_n[a, b]
                    if m == 0 or right_n[b + 1] == 0:
                        continue
                    larea = _area(lx0, ly0, lz0, lx1, ly1, lz1)
                    cost = cost_node + cost_prim * (larea * m + right_area[b + 1]
                                                    * right_n[b + 1]) / parea \
                        if parea > 0.0 else cost_node + cost_prim * max(m, right_n[b + 1])
                    if cost < best_cost:
                        best_cost = cost
                        best_axis = a
                        best_bin = b
            if best_axis >= 0 and cnt <= max_leaf and best_cost >= cost_prim * cnt:
                link[node, 0] = start  # no split pays for the extra node visit
                link[node, 1] = cnt
                deepest = max(deepest, depth)
                continue
        if best_axis >= 0:
            # partition: centroids in bins <= best_bin to the left
            a = best_axis
            scale = _BINS / (chi[a] - clo[a])
            i = start
            j = end - 1
            while i <= j:
                if min(int((cent[order[i], a] - clo[a]) * scale), _BINS - 1) <= best_bin:
                    i += 1
                else:
                    order[i], order[j] = order[j], order[i]
                    j -= 1
            mid = i
        else:
            # median of the centroids along their longest extent (if they all coincide, any
            # halving will do: the stable sort keeps the input order)
            a = 0
            for c in range(1, 3):
                if chi[c] - clo[c] > chi[a] - clo[a]:
                    a = c
            sub = order[start:end].copy()
            perm = np.argsort(cent[sub, a], kind="mergesort")
            for i in range(cnt):
                order[start + i] = sub[perm[i]]
            mid = start + cnt // 2
        link[node, 0] = -1
        link[node, 1] = 0
        # the right part waits on the stack; the left one is built next (index node + 1)
        st_start[sp] = mid
        st_end[sp] = end
        st_parent[sp] = node
        st_depth[sp] = depth + 1
        st_start[sp + 1] = start
        st_end[sp + 1] = mid
        st_parent[sp + 1] = -1
        st_depth[sp + 1] = depth + 1
        sp += 2
    return nodes, deepest


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


@njit(inline="always")
def _roots(a, hb, c, disc):
    # the two roots (t1 <= t2) of a t^2 + 2 hb t + c = 0 given disc = hb^2 - a c >= 0, in
    # the stable form (no cancellation between -hb and sqrt(disc))
    sq = np.sqrt(disc)
    q = -(hb + sq) if hb >= 0.0 else -(hb - sq)
    if q == 0.0:  # hb = disc = 0: a double root at 0
        return 0.0, 0.0
    r1 = q / a
    r2 = c / q
    return min(r1, r2), max(r1, r2)


@njit
def _hit_sphere(p, ox, oy, oz, dx, dy, dz, tmin, tmax):
    # sphere p = (cx, cy, cz, r): nearest root in (tmin, tmax) or inf
    wx = ox - p[0]
    wy = oy - p[1]
    wz = oz - p[2]
    r = p[3]
    a = dx * dx + dy * dy + dz * dz
    # hb^2 - a c = a r^2 - |w x d|^2 (Lagrange): no cancellation for distant origins
    cx = wy * dz - wz * dy
    cy = wz * dx - wx * dz
    cz = wx * dy - wy * dx
    disc = a * r * r - (cx * cx + cy * cy + cz * cz)
    if disc < 0.0:
        return np.inf
    t1, t2 = _roots(a, wx * dx + wy * dy + wz * dz, wx * wx + wy * wy + wz * wz - r * r, disc)
    if tmin < t1 < tmax:
        return t1
    if tmin < t2 < tmax:
        return t2
    return np.inf


@njit
def _hit_tube(p, ox, oy, oz, dx, dy, dz, tmin, tmax):
    # finite cylinder p = (p0, p1, r, caps): nearest hit in (tmin, tmax) of the side (a root
    # whose axial coordinate s lies in [0, L]) or, when capped, of the end discs; else inf
    ux = p[3] - p[0]
    uy = p[4] - p[1]
    uz = p[5] - p[2]
    length = np.sqrt(ux * ux + uy * uy + uz * uz)
    ux /= length
    uy /= length
    uz /= length
    r = p[6]
    wx = ox - p[0]
    wy = oy - p[1]
    wz = oz - p[2]
    # the distance from the axis of o + t d is |u x w + t u x d|
    cwx = uy * wz - uz * wy
    cwy = uz * wx - ux * wz
    cwz = ux * wy - uy * wx
    cdx = uy * dz - uz * dy
    cdy = uz * dx - ux * dz
    cdz = ux * dy - uy * dx
    su = wx * ux + wy * uy + wz * uz
    du = dx * ux + dy * uy + dz * uz
    best = tmax
    a = cdx * cdx + cdy * cdy + cdz * cdz
    c = cwx * cwx + cwy * cwy + cwz * cwz - r * r
    if a > 0.0:
        # hb^2 - a c = a r^2 - ((u x w) . d)^2 (Lagrange, |u| = 1)
        trip = cwx * dx + cwy * dy + cwz * dz
        disc = a * r * r - trip * trip
        if disc < 0.0:  # misses the infinite cylinder, hence also the caps inside it
            return np.inf
        t1, t2 = _roots(a, cwx * cdx + cwy * cdy + cwz * cdz, c, disc)
        if tmin < t1 < best and 0.0 <= su + t1 * du <= length:
            best = t1
        elif tmin < t2 < best and 0.0 <= su + t2 * du <= length:
            best = t2
    elif c > 0.0:  # parallel to the axis, outside the cylinder
        return np.inf
    if p[7] != 0.0 and du != 0.0:
        for s in (0.0, length):
            t = (s - su) / du
            if tmin < t < best:
                qx = cwx + t * cdx
                qy = cwy + t * cdy
                qz = cwz + t * cdz
                if qx * qx + qy * qy + qz * qz <= r * r:
                    best = t
    return best if best < tmax else np.inf


@njit
def _normal(ptype, p, px, py, pz, dx, dy, dz):
    # unit normal of the primitive at the point, turned to face the incoming direction, and
    # front: True when the ray arrives on the outer side (triangles: the side the winding
    # (v1 - v0) x (v2 - v0) points to; cylinders, spheres, tubes: outside the solid)
    if ptype == SPHERE:
        nx = px - p[0]
        ny = py - p[1]
        nz = pz - p[2]
    elif ptype == TUBE:
        ux = p[3] - p[0]
        uy = p[4] - p[1]
        uz = p[5] - p[2]
        length = np.sqrt(ux * ux + uy * uy + uz * uz)
        ux /= length
        uy /= length
        uz /= length
        vx = px - p[0]
        vy = py - p[1]
        vz = pz - p[2]
        s = vx * ux + vy * uy + vz * uz
        nx = vx - s * ux
        ny = vy - s * uy
        nz = vz - s * uz
        # the cap when the point is nearer its plane than the side surface (on the rim
        # either normal is as good)
        if p[7] != 0.0 and min(abs(s), abs(length - s)) < abs(
                np.sqrt(nx * nx + ny * ny + nz * nz) - p[6]):
            sign = -1.0 if s < 0.5 * length else 1.0
            nx = sign * ux
            ny = sign * uy
            nz = sign * uz
    elif ptype == TRIANGLE:
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
    # traversal: at an inner node both child boxes are tested, the nearer hit child is
    # visited next and the farther one waits on the stack with its entry distance (skipped
    # when a closer hit has been found by then). At most one child per level waits, so the
    # stack holds at most depth <= _STACK - 1 entries.
    ix = 1.0 / dx if dx != 0.0 else np.inf
    iy = 1.0 / dy if dy != 0.0 else np.inf
    iz = 1.0 / dz if dz != 0.0 else np.inf
    if _box(0, ox, oy, oz, ix, iy, iz, tmin, tmax, lo, hi) == np.inf:
        return -1, tmax
    if link[0, 1] > 0:  # a single leaf (small scenes): no stack needed
        return _leaf(link[0, 0], link[0, 1], -1, ox, oy, oz, dx, dy, dz, tmin, tmax, ptype,
                     pdata)
    stack = np.empty(_STACK, np.int64)
    entry = np.empty(_STACK)
    sp = 0
    best = -1
    node = 0
    while True:
        count = link[node, 1]
        if count == 0:
            left = node + 1
            right = link[node, 0]
            tl = _box(left, ox, oy, oz, ix, iy, iz, tmin, tmax, lo, hi)
            tr = _box(right, ox, oy, oz, ix, iy, iz, tmin, tmax, lo, hi)
            if tl < np.inf and tr < np.inf:
                if tl <= tr:
                    node = left
                    stack[sp] = right
                    entry[sp] = tr
                else:
                    node = right
                    stack[sp] = left
                    entry[sp] = tl
                sp += 1
                continue
            if tl < np.inf:
                node = left
                continue
            if tr < np.inf:
                node = right
                continue
        else:
            best, tmax = _leaf(link[node, 0], count, best, ox, oy, oz, dx, dy, dz, tmin, tmax,
                               ptype, pdata)
        # next waiting node that may still hold a closer hit
        node = -1
        while sp > 0:
            sp -= 1
            if entry[sp] <= tmax:
                node = stack[sp]
                break
        if node < 0:
            return best, tmax


@njit(inline="always")
def _leaf(start, count, best, ox, oy, oz, dx, dy, dz, tmin, tmax, ptype, pdata):
    # the primitives start .. start + count - 1 of a leaf: (closest so far or best, its t)
    for k in range(start, start + count):
        pk = ptype[k]
        if pk == TRIANGLE:
            t = _hit_triangle(pdata[k], ox, oy, oz, dx, dy, dz, tmin, tmax)
        elif pk == CYLINDER:
            t = _hit_cylinder(pdata[k], ox, oy, oz, dx, dy, dz, tmin, tmax)
        elif pk == SPHERE:
            t = _hit_sphere(pdata[k], ox, oy, oz, dx, dy, dz, tmin, tmax)
        else:
            t = _hit_tube(pdata[k], ox, oy, oz, dx, dy, dz, tmin, tmax)
        if t < tmax:
            tmax = t
            best = k
    return best, tmax


@njit(inline="always")
def _slab(lo, hi, o, inv, t0, t1):
    # one axis of the slab test: the interval (t0, t1) clipped to the slab lo <= o + t d <= hi
    # (inv = 1 / d, inf for d = 0: then the origin must lie in the slab); empty when t0 > t1
    if inv == np.inf:
        if o < lo or o > hi:
            return np.inf, -np.inf
        return t0, t1
    ta = (lo - o) * inv
    tb = (hi - o) * inv
    # the widening by 4 ulp keeps boxes of zero thickness (flat planes) hit
    return max(t0, min(ta, tb)), min(t1, max(ta, tb) * (1.0 + 4e-16))


@njit(inline="always")
def _box(node, ox, oy, oz, ix, iy, iz, tmin, tmax, lo, hi):
    # slab test of the ray against node's box on (tmin, tmax): the entry distance (finite),
    # or inf when the ray misses the box there (ix, iy, iz: inverse direction, inf for 0)
    t0, t1 = _slab(lo[node, 0], hi[node, 0], ox, ix, tmin, tmax)
    t0, t1 = _slab(lo[node, 1], hi[node, 1], oy, iy, t0, t1)
    t0, t1 = _slab(lo[node, 2], hi[node, 2], oz, iz, t0, t1)
    return t0 if t0 <= t1 else np.inf


#: rays per part of run_parallel in the query kernels: a query costs about a microsecond
_GRAIN = 64


@loopjit
def _intersect_kernel(first, stop, o, d, tmax, lo, hi, link, ptype, pdata, t, prim, nrm):
    # rays first .. stop - 1 (run_parallel) of o, d (n, 3); t (n,), prim (n,), nrm (n, 3) out
    for r in range(first, stop):
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
    inv_dx = 1.0 / dx if dx != 0.0 else 0.0
    inv_dy = 1.0 / dy if dy != 0.0 else 0.0
    t = 0.0
    for _ in range(max_steps):
        z = oz + t * dz
        if dz >= 0.0 and z > zmax:
            return _ESCAPED, t, 0.0, 0.0, 0.0, -1, True
        if dz < 0.0 and z < zmin - tol:
            return _LOST, t, 0.0, 0.0, 0.0, -1, True
        ix, tx = _grid_step(ox, dx, inv_dx, ox + t * dx, lx, 1.0 / lx, 1e-12)
        iy, ty = _grid_step(oy, dy, inv_dy, oy + t * dy, ly, 1.0 / ly, 1e-12)
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


@loopjit
def _periodic_kernel(first, stop, o, d, lx, ly, zmin, zmax, max_steps, lo, hi, link, ptype, pdata,
                     st, t, prim, nrm):
    # rays first .. stop - 1 (run_parallel) of o, d (n, 3); st, t, prim (n,), nrm (n, 3) out
    for r in range(first, stop):
        s, th, nx, ny, nz, k, _ = _periodic_hit(o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1],
                                             d[r, 2], lx, ly, zmin, zmax, max_steps, lo, hi,
                                             link, ptype, pdata)
        st[r] = s
        t[r] = th if s == _HIT else np.inf
        prim[r] = k
        nrm[r, 0] = nx
        nrm[r, 1] = ny
        nrm[r, 2] = nz
