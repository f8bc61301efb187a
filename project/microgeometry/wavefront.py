"""Bounce-by-bounce ("wavefront") tracing for facets with a microscale BRDF.

A :class:`~project.microgeometry.MicroBRDF` is a Python object evaluated in numpy, so it
cannot be called from inside the numba path loops of ``trace.py`` and ``scene.py``. Instead
all live rays are advanced one facet interaction at a time:

1. numba (a step kernel, on threads over rays): intersect every live ray with the specimen,
   record escapes, cut-offs and hits, and move the origins of hit rays to the hit point
   (offset along the facet normal, wrapped into the period). The height field is walked
   with the max pyramid (``_step_kernel``, as ``trace._trace_kernel``), a
   :class:`~project.microgeometry.Scene` with its periodic BVH (``_scene_step_kernel``, as
   ``scene._scene_kernel``), which also records the material of the hit primitive;
2. hits on :class:`Mirror` and :class:`Diffuse` facets (scene parts): numba
   (``_facet_kernel``), the path tracers' own facet event ``_paths._scatter`` with its
   Fresnel, cosine sampling and Russian roulette;
3. hits on MicroBRDF facets, one batch per distinct MicroBRDF (a loop over materials, not
   rays): numpy (:class:`~project.microgeometry.scatter.FacetSampler`): express w_i in each
   facet's frame, draw the new direction and evaluate the BRDF in one batched
   ``brdf.eval`` call; multiply the weights by f cos / pdf; then numba
   (``_roulette_kernel``): Russian roulette below weight ``ROULETTE``, as in the path
   tracers (survive with probability w / rr at weight rr: unbiased).

Only the step kernel differs between height fields and scenes; the bounce loop
(:func:`_bounces`) is shared. There is no Python loop over rays, only over bounces (until no
ray is left) and materials. Every ray draws its uniforms from its own counter-based stream
(seed, global ray index), a fixed number per event, so the result does not depend on threads
or chunking.

Facet frames: x is the world x axis projected onto the facet (``scatter.facet_frame``), so
anisotropic microscale BRDFs keep their x axis along the mean plane's x; on facets whose
normal is (anti)parallel to x (walls of meshes, sides of cylinders along y) that projection
vanishes and the world y axis projected onto the facet is used instead. Scene meshes may
give every triangle its own tangent (``Scene.add_mesh(tangents=...)``, e.g. along a
thread): then x is that tangent projected onto the facet, with the same fallback where the
projection vanishes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from basis.jit import loopjit, njit, run_parallel

from ._paths import (
    _ESCAPED,
    _HIT,
    _LOST,
    _TAG_RAY,
    ROULETTE,
    _intersect,
    _launch,
    _next_origin,
    _scatter,
    _stream,
    _uniform,
)
from .bvh import BVH, _periodic_hit
from .materials import DIFFUSE, MICRO, MIRROR, Material
from .scatter import FacetSampler, facet_frame
from .surface import Heightfield

__all__ = ["run_scene_wavefront", "run_wavefront"]

#: |g_x| above this: the facet faces along x and its frame's x is the projected world y
_SIDE = 1.0 - 1e-12


def run_wavefront(surface: Heightfield, dirs: NDArray, per: int, seed: np.uint64, start: int,
                  out: tuple, max_bounces: int, max_steps: int) -> None:
    """Fill ``out`` (directions, weights, bounces, absorbed, lost) like ``trace._run``."""
    h = surface.heights
    sx, sy = surface.spacing
    hmin, hmax = float(h.min()), float(h.max())

    def step(act, o, d, w, nb, lost, status, g, mid, front, prim):
        # one material (mid = 0), every facet seen from above (front = True): untouched
        run_parallel(_step_kernel, act.shape[0], act, o, d, w, nb, lost, h, surface._pyramid,
                     surface._offsets, surface._levels, sx, sy, hmin, hmax, max_bounces,
                     max_steps, status, g, grain=_GRAIN)

    _bounces(step, [surface.material], hmax + 1e-6 * (hmax - hmin + sx), h.shape[1] * sx,
             h.shape[0] * sy, dirs, per, seed, start, out)


def run_scene_wavefront(bvh: BVH, period: NDArray, materials: Sequence[Material], slot: NDArray,
                        dirs: NDArray, per: int, seed: np.uint64, start: int, out: tuple,
                        max_bounces: int, max_steps: int, *,
                        tangents: NDArray | None = None) -> None:
    """Fill ``out`` like ``scene._scene_kernel`` for a scene with MicroBRDF parts.

    ``bvh`` is the scene's periodic :class:`~project.microgeometry.BVH`, ``materials`` the
    distinct materials of its parts (Mirror, Diffuse or MicroBRDF) and ``slot`` (P,) int64
    the index into ``materials`` of every stored primitive (``bvh.pdata`` row).
    ``tangents`` (P, 3) unit vectors, optional: the x axis of the MicroBRDF facet frame of
    every stored primitive before projection onto the facet (None: the world x axis).
    """
    lx, ly = float(period[0]), float(period[1])
    zmin, zmax = float(bvh.lo[0, 2]), float(bvh.hi[0, 2])
    slot = np.ascontiguousarray(slot, dtype=np.int64)

    def step(act, o, d, w, nb, lost, status, g, mid, front, prim):
        run_parallel(_scene_step_kernel, act.shape[0], act, o, d, w, nb, lost, lx, ly, zmin,
                     zmax, bvh.lo, bvh.hi, bvh.link, bvh.ptype, bvh.pdata, slot, max_bounces,
                     max_steps, status, g, mid, front, prim, grain=_GRAIN)

    # the start height of scene._scene_kernel
    _bounces(step, materials, zmax + 1e-6 * (zmax - zmin + lx), lx, ly, dirs, per, seed,
             start, out, tangents)


def _bounces(step: Callable, materials: Sequence[Material], zs: float, lx: float, ly: float,
             dirs: NDArray, per: int, seed: np.uint64, start: int, out: tuple,
             tangents: NDArray | None = None) -> None:
    """Run the bounce loop shared by height fields and scenes (see the module docstring).

    ``step(act, o, d, w, nb, lost, status, g, mid, front, prim)`` advances the live rays
    ``act`` to their next facet: it writes ``status`` (hit, escaped, lost) per row of
    ``act``, and for hits the facet normal ``g`` (facing the ray), the material index
    ``mid`` into ``materials``, ``front`` (the ray arrived on the primitive's outer side)
    and, for scenes, the stored primitive ``prim`` (indexing ``tangents``, (P, 3) or None:
    world x); it moves hit origins and cuts off rays (weight to ``lost``) as the path
    tracers do.
    """
    n = dirs.shape[0] * per
    o = np.empty((n, 3))
    d = np.empty((n, 3))
    s = np.empty(n, np.uint64)
    _start_kernel(np.ascontiguousarray(dirs), per, seed, np.uint64(start), zs, lx, ly, o, d, s)
    w = np.ones(n)
    nb = np.zeros(n, np.int64)
    absorbed = np.zeros(n)
    lost = np.zeros(n)
    status = np.empty(n, np.int64)
    g = np.empty((n, 3))
    mid = np.zeros(n, np.int64)
    front = np.ones(n, np.bool_)
    prim = np.zeros(n, np.int64)
    table = np.array([[float(m.code), *m._params()] for m in materials])  # (K, 4) for numba
    micro = [j for j, m in enumerate(materials) if m.code == MICRO]
    plain = np.array([m.code in (MIRROR, DIFFUSE) for m in materials])
    other = [m for j, m in enumerate(materials) if not plain[j] and j not in micro]
    if other:
        raise NotImplementedError(f"the bounce-by-bounce tracer of MicroBRDF facets handles "
                                  f"Mirror, Diffuse and MicroBRDF facets, got {other[0]!r}")
    act = np.arange(n, dtype=np.int64)
    while act.size:
        step(act, o, d, w, nb, lost, status, g, mid, front, prim)
        hit = act[status[act] == _HIT]
        if hit.size == 0:
            break
        if plain.any():
            rows = hit[plain[mid[hit]]]
            if rows.size:
                run_parallel(_facet_kernel, rows.shape[0], rows, d, g, front, mid, table, w,
                             absorbed, s, ROULETTE, grain=_FACET_GRAIN)
        for j in micro:
            rows = hit if len(materials) == 1 else hit[mid[hit] == j]
            if rows.size:
                tan = None if tangents is None else tangents[prim[rows]]
                _micro_event(materials[j]._sampler, rows, d, g, w, absorbed, s, tan)
        act = hit[w[hit] > 0.0]
    dead = ~(w > 0.0)
    d[dead] = (0.0, 0.0, 1.0)
    out[0][:] = d
    out[1][:] = w
    out[2][:] = nb
    out[3][:] = absorbed
    out[4][:] = lost


def _micro_event(sampler: FacetSampler, rows: NDArray, d: NDArray, g: NDArray, w: NDArray,
                 absorbed: NDArray, s: NDArray, tangents: NDArray | None = None) -> None:
    """Apply one MicroBRDF event to the rays ``rows`` (directions, weights, streams updated).

    ``tangents`` (len(rows), 3): unit x axes of the facet frames before projection, or None
    (world x).
    """
    gh = g[rows]
    t, b = _frame(gh) if tangents is None else _tangent_frame(gh, tangents)
    wi = -d[rows]
    # g faces the ray, so w_i . g >= 0 up to rounding
    wl = np.stack([np.sum(wi * t, 1), np.sum(wi * b, 1), np.maximum(np.sum(wi * gh, 1), 0.0)],
                  axis=-1)
    wl /= np.linalg.norm(wl, axis=1)[:, None]
    u = np.empty((rows.size, sampler.uniforms))
    _draw_kernel(rows, s, u)
    wo, factor = sampler.scatter(wl, u)
    dn = wo[:, 0:1] * t + wo[:, 1:2] * b + wo[:, 2:3] * gh
    d[rows] = dn / np.linalg.norm(dn, axis=1)[:, None]
    absorbed[rows] += w[rows] * (1.0 - factor)
    w[rows] *= factor
    _roulette_kernel(rows, w, s, ROULETTE)


def _frame(g: NDArray) -> tuple[NDArray, NDArray]:
    """Return (t, b) of ``scatter.facet_frame``, also on facets that face along x.

    The projected world y is t where the projected x vanishes (|g_x| > _SIDE); (t, b, g)
    right-handed, shapes (n, 3).
    """
    side = np.abs(g[:, 0]) > _SIDE
    if not side.any():
        return facet_frame(g)
    t = np.empty_like(g)
    b = np.empty_like(g)
    t[~side], b[~side] = facet_frame(g[~side])
    gs = g[side]
    ts = -gs[:, 1:2] * gs
    ts[:, 1] += 1.0
    ts /= np.linalg.norm(ts, axis=1)[:, None]
    t[side] = ts
    b[side] = np.cross(gs, ts)
    return t, b


def _tangent_frame(g: NDArray, a: NDArray) -> tuple[NDArray, NDArray]:
    """Return (t, b) with t the unit tangents ``a`` projected onto the facets of normals ``g``.

    Falls back to :func:`_frame` where that projection vanishes (|a . g| > _SIDE); (t, b, g)
    right-handed, shapes (n, 3). For a = world x this is :func:`_frame` exactly (the same
    operations in the same order).
    """
    ag = np.sum(a * g, 1)
    side = np.abs(ag) > _SIDE
    t = a - ag[:, None] * g
    t /= np.where(side, 1.0, np.linalg.norm(t, axis=1))[:, None]
    b = np.cross(g, t)
    if side.any():
        t[side], b[side] = _frame(g[side])
    return t, b


@njit
def _start_kernel(dirs, per, seed, start, zs, lx, ly, o, d, s):
    # dirs (B, 3) incident directions; o, d (B * per, 3) out: first origins and directions of
    # _paths._launch (the start of the path tracers); s (B * per,) out: stream states after it
    # serial: a few microseconds per thousand rays, less than a parallel launch costs
    for r in range(dirs.shape[0] * per):
        ox, oy, oz, dx, dy, dz, st = _launch(dirs, r // per, zs, lx, ly,
                                             _stream(seed, start + np.uint64(r), _TAG_RAY))
        o[r, 0] = ox
        o[r, 1] = oy
        o[r, 2] = oz
        d[r, 0] = dx
        d[r, 1] = dy
        d[r, 2] = dz
        s[r] = st


@njit(inline="always")
def _record(r, code, t, gx, gy, gz, eps, lx, ly, o, d, w, nb, lost, max_bounces, status, g):
    """Book-keep the traversal outcome ``code`` of ray r (as the path tracers do).

    Returns True for a hit, whose origin then moves to the hit point + eps g, wrapped.
    """
    if code == _ESCAPED:
        status[r] = _ESCAPED
        return False
    if code == _LOST or nb[r] >= max_bounces:
        status[r] = _LOST
        lost[r] = w[r]
        w[r] = 0.0
        return False
    status[r] = _HIT
    nb[r] += 1
    o[r, 0], o[r, 1], o[r, 2] = _next_origin(o[r, 0] + t * d[r, 0], o[r, 1] + t * d[r, 1],
                                             o[r, 2] + t * d[r, 2], eps, gx, gy, gz, lx, ly)
    g[r, 0] = gx
    g[r, 1] = gy
    g[r, 2] = gz
    return True


#: live rays per part of run_parallel in the step kernels: a step costs about a microsecond
_GRAIN = 64
#: rays per part in _facet_kernel: a facet event costs a tenth of a step
_FACET_GRAIN = 1024


@loopjit
def _step_kernel(first, stop, act, o, d, w, nb, lost, h, pyr, offs, top, sx, sy, hmin, hmax,
                 max_bounces, max_steps, status, g):
    # Rows act[first] .. act[stop - 1] (run_parallel).
    # act (A,) rows of live rays; o, d (n, 3) origins and unit directions; w, lost (n,)
    # weights; nb (n,) bounces; status (n,) out per row in act; g (n, 3) out: facet normal
    # of each hit. Hit rays get nb += 1 and their origin moved to the (offset) hit point;
    # cut-off rays (lost, or at the bounce cap) move their weight to lost.
    ny, nx = h.shape
    lx = nx * sx
    ly = ny * sy
    eps = 1e-7 * min(sx, sy)
    for a in range(first, stop):
        r = act[a]
        code, t, gx, gy, gz = _intersect(o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1], d[r, 2],
                                         h, pyr, offs, top, sx, sy, hmin, hmax, max_steps)
        _record(r, code, t, gx, gy, gz, eps, lx, ly, o, d, w, nb, lost, max_bounces, status, g)


@loopjit
def _scene_step_kernel(first, stop, act, o, d, w, nb, lost, lx, ly, zmin, zmax, lo, hi, link,
                       ptype, pdata, slot, max_bounces, max_steps, status, g, mid, front, prim):
    # As _step_kernel with the periodic BVH walk (bvh._periodic_hit); slot (P,) material
    # index of each stored primitive; mid (n,) out: material index of each hit, front (n,)
    # out: the ray arrived on the primitive's outer side, prim (n,) out: stored primitive.
    eps = 1e-7 * min(lx, ly)  # the offset of scene._scene_kernel
    for a in range(first, stop):
        r = act[a]
        code, t, gx, gy, gz, k, fr = _periodic_hit(o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1],
                                                   d[r, 2], lx, ly, zmin, zmax, max_steps, lo,
                                                   hi, link, ptype, pdata)
        if _record(r, code, t, gx, gy, gz, eps, lx, ly, o, d, w, nb, lost, max_bounces,
                   status, g):
            mid[r] = slot[k]
            front[r] = fr
            prim[r] = k


@loopjit
def _facet_kernel(first, stop, rows, d, g, front, mid, table, w, absorbed, s, rr):
    # rows[first] .. rows[stop - 1] (run_parallel) of rows (A,): hits on Mirror / Diffuse
    # facets; table (K, 4) (code, ior, k, albedo) per material; d, g (n, 3); front, mid, w,
    # absorbed, s (n,): the path tracers' facet event (its draws and roulette) in place
    for a in range(first, stop):
        r = rows[a]
        m = table[mid[r]]
        dx, dy, dz, wr, ab, st = _scatter(int(m[0]), m[1], m[2], m[3], d[r, 0], d[r, 1],
                                          d[r, 2], g[r, 0], g[r, 1], g[r, 2], front[r], w[r],
                                          absorbed[r], rr, s[r])
        d[r, 0] = dx
        d[r, 1] = dy
        d[r, 2] = dz
        w[r] = wr
        absorbed[r] = ab
        s[r] = st


@njit
def _draw_kernel(rows, s, u):
    # rows (A,); s (n,) stream states (advanced); u (A, k) out: k uniforms per row (serial)
    for a in range(rows.shape[0]):
        st = s[rows[a]]
        for j in range(u.shape[1]):
            x, st = _uniform(st)
            u[a, j] = x
        s[rows[a]] = st


@njit
def _roulette_kernel(rows, w, s, rr):
    # rows (A,); w (n,) weights; s (n,) states: below rr survive with probability w / rr at
    # weight rr (one uniform drawn only then, as in _trace_kernel)
    for a in range(rows.shape[0]):
        r = rows[a]
        if w[r] < rr and w[r] > 0.0:
            x, st = _uniform(s[r])
            s[r] = st
            w[r] = rr if x * rr < w[r] else 0.0
