"""Paths of rays through a specimen: :func:`trace`, :class:`Paths`, the height-field loops.

Height fields are traced by ``_trace_packets``: it follows every ray from its start above
the surface through the max-pyramid walk to the next facet, the facet event (Fresnel mirror
or cosine-diffuse bounce, then Russian roulette) and the next origin, until it escapes, dies
or is cut off, walking as many rays at once as the CPU's vector registers hold doubles
(``_packets.py``). ``_trace_kernel`` does the same one ray at a time, with the same bits:
the reference of the tests, and the tracer of pyramids too large for the packets' int32
indices. The pieces of both, and the per-ray random streams, are the shared kernels of
``_paths.py``; a :class:`~project.microgeometry.Scene` is traced by its own loop
(``scene.py``) and :class:`~project.microgeometry.MicroBRDF` facets bounce by bounce
(``wavefront.py``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basis.jit import loopjit, njit, run_parallel
from basis.validation import as_directions

from . import _packets as pk
from ._checks import _positive_int, _seed
from ._packets import walk_casts
from ._paths import (
    _ESCAPED,
    _LOST,
    _TAG_RAY,
    MAX_BOUNCES,
    MAX_STEPS,
    ROULETTE,
    _alloc,
    _cast_setup,
    _coherent_order,
    _facet_hit,
    _intersect,
    _launch,
    _next_origin,
    _scatter,
    _store_path,
    _stream,
)
from ._paths import incident_directions as incident_directions  # its old home: still importable
from .materials import MICRO
from .scene import Scene
from .surface import Heightfield
from .wavefront import run_wavefront

__all__ = ["Paths", "trace"]


class Paths(NamedTuple):
    """Per-ray outcome of :func:`trace` (n rays).

    Attributes
    ----------
    directions : (n, 3) ndarray
        Exit directions (z > 0); (0, 0, 1) for rays with zero weight.
    weights : (n,) ndarray
        Exit energy (1 per incident ray; 0 when absorbed or killed by roulette).
    bounces : (n,) ndarray of int64
        Facet interactions before leaving.
    absorbed : (n,) ndarray
        Energy absorbed by facets along the path.
    lost : (n,) ndarray
        Energy of paths cut off unresolved (bounce or step cap; normally 0).
    """

    directions: NDArray[np.float64]
    weights: NDArray[np.float64]
    bounces: NDArray[np.int64]
    absorbed: NDArray[np.float64]
    lost: NDArray[np.float64]


def trace(surface: Heightfield, wi: ArrayLike, rays: int, *, seed: int = 0,
          start: int = 0) -> Paths:
    """Trace ``rays`` rays arriving from one direction onto uniformly spread target points.

    Parameters
    ----------
    surface : Heightfield or Scene
        Specimen (its ``material`` scatters at every facet). :class:`MicroBRDF` facets are
        traced bounce by bounce (``wavefront.py``), the others path by path in numba
        (height fields several rays at a time, in the CPU's vector registers).
    wi : (3,) array_like of float
        Unit vector towards the light, z > 0.
    rays : int
        Number of rays (> 0). The points where they cross the mean plane are uniform over
        one period, i.e. the incident flux per unit mean-plane area is constant.
    seed : int
        Seed (>= 0) of the per-ray random streams.
    start : int
        Global index of the first ray (disjoint ranges give independent rays).

    Returns
    -------
    Paths

    Examples
    --------
    >>> import numpy as np
    >>> from project.microgeometry import Heightfield
    >>> p = trace(Heightfield(np.zeros((4, 4)), 1.0), [0.6, 0.0, 0.8], 3)
    >>> (p.directions[0] + 0.0).round(12).tolist(), p.weights.tolist()
    ([-0.6, 0.0, 0.8], [1.0, 1.0, 1.0])
    """
    if not isinstance(surface, (Heightfield, Scene)):
        raise TypeError(f"surface must be a Heightfield or a Scene, got "
                        f"{type(surface).__name__}")
    w = as_directions(wi, "wi").reshape(-1, 3)
    if w.shape[0] != 1 or not w[0, 2] > 0:
        raise ValueError(f"wi must be one unit vector with z > 0, got {np.asarray(wi)!r}")
    rays = _positive_int(rays, "rays")
    out = _alloc(rays)
    if isinstance(surface, Scene):
        surface._run(w / np.linalg.norm(w), rays, _seed(seed), start, out, MAX_BOUNCES,
                     MAX_STEPS)
    else:
        _run(surface, w / np.linalg.norm(w), rays, _seed(seed), start, out)
    return Paths(*out)


def _run(surface: Heightfield, dirs: NDArray, per: int, seed: np.uint64, start: int,
         out: tuple, max_bounces: int = MAX_BOUNCES, max_steps: int = MAX_STEPS,
         packets: bool = True) -> None:
    """Trace ``per`` rays for each incident direction in ``dirs`` (B, 3).

    The rays of direction b are rows b * per ... (b + 1) * per - 1 of the outputs, with
    global ray index start + row. ``packets``: walk the pyramid with several rays per vector
    instruction (``_trace_packets``), else ray by ray (``_trace_kernel``); the same bits.
    """
    if surface.material.code == MICRO:
        run_wavefront(surface, dirs, per, seed, start, out, max_bounces, max_steps)
        return
    h = surface.heights
    sx, sy = surface.spacing
    start64 = np.uint64(start)
    # contiguous parts of this order trace rays aiming at neighbouring points
    order = _coherent_order(seed, start64, dirs.shape[0] * per, h.shape[1], h.shape[0])
    hmin, hmax = float(h.min()), float(h.max())
    if not packets or surface._pyramid.size >= 2**31:  # int32 node indices in the packets
        run_parallel(_trace_kernel, order.shape[0], order, np.ascontiguousarray(dirs), per,
                     seed, start64, h, surface._pyramid, surface._offsets, surface._levels, sx,
                     sy, hmin, hmax, surface.material.code, surface.material._params(),
                     ROULETTE, max_bounces, max_steps, *out, grain=_GRAIN)
        return
    ny, nx = h.shape
    g = np.empty(pk.NCONST)
    g[[pk.G_SX, pk.G_SY, pk.G_NX, pk.G_NY]] = sx, sy, nx, ny
    g[[pk.G_ISX, pk.G_ISY, pk.G_INX, pk.G_INY]] = 1.0 / sx, 1.0 / sy, 1.0 / nx, 1.0 / ny
    g[pk.G_CELLS] = nx * ny
    g[[pk.G_HMIN, pk.G_HMAX]] = hmin, hmax
    g[pk.G_TOL] = 1e-9 * (hmax - hmin + sx + sy)  # as _intersect
    g[pk.G_PTOP] = 2.0 ** surface._levels
    g[pk.G_MAXSTEPS] = max_steps
    run_parallel(_trace_packets, order.shape[0], order, np.ascontiguousarray(dirs), per, seed,
                 start64, np.ascontiguousarray(h), surface._pyramid, g,
                 surface.material.code, surface.material._params(), ROULETTE, max_bounces,
                 *out, grain=_GRAIN)


#: rays per part of run_parallel: a ray costs about a microsecond (more on steep surfaces)
_GRAIN = 128
#: paths traced together by _trace_packets: their casts are walked, then their facet events
#: met, in rounds (a few kB of state per block, which stays in the L1 and L2 caches)
_BLOCK = 256


@loopjit
def _trace_kernel(first, stop, order, dirs, per, seed, start, h, pyr, offs, top, sx, sy, hmin,
                  hmax, code, params, rr, max_bounces, max_steps, out_dir, out_w, out_b,
                  out_abs, out_lost):
    # Rays order[first] .. order[stop - 1] (run_parallel; order: _coherent_order of all rays).
    # dirs (B, 3) incident unit vectors (towards the light, z > 0); per rays each;
    # h (ny, nx) heights; pyr/offs the flat max pyramid; params (ior, k, albedo);
    # outputs (B * per, 3), (B * per,) x 4. Ray r uses stream (seed, start + r).
    ny, nx = h.shape
    lx = nx * sx
    ly = ny * sy
    eps = 1e-7 * min(sx, sy)  # offset of a new origin along the facet normal
    zs = hmax + 1e-6 * (hmax - hmin + sx)
    ior = params[0]
    kext = params[1]
    alb = params[2]
    for i in range(first, stop):
        r = order[i]
        ox, oy, oz, dx, dy, dz, s = _launch(dirs, r // per, zs, lx, ly,
                                            _stream(seed, start + np.uint64(r), _TAG_RAY))
        w = 1.0
        absorbed = 0.0
        lost = 0.0
        bounces = 0
        while True:
            status, t, gx, gy, gz = _intersect(ox, oy, oz, dx, dy, dz, h, pyr, offs, top, sx,
                                               sy, hmin, hmax, max_steps)
            if status == _ESCAPED:
                break
            if status == _LOST or bounces >= max_bounces:
                lost = w
                w = 0.0
                break
            bounces += 1
            px = ox + t * dx
            py = oy + t * dy
            pz = oz + t * dz
            dx, dy, dz, w, absorbed, s = _scatter(code, ior, kext, alb, dx, dy, dz, gx, gy, gz,
                                                  True, w, absorbed, rr, s)
            if w == 0.0:
                break
            ox, oy, oz = _next_origin(px, py, pz, eps, gx, gy, gz, lx, ly)
        _store_path(r, w, dx, dy, dz, bounces, absorbed, lost, out_dir, out_w, out_b,
                    out_abs, out_lost)


# -- the packet tracer ------------------------------------------------------------------------
# _trace_packets traces the paths of a block of rays in rounds. A round walks every queued
# cast (a ray segment from its origin to its first facet, or out of the slab) in packets of
# LANES lanes (_packets.walk_casts); then one loop meets every cast's facet event (_trace_packets):
# Fresnel or diffuse scattering and roulette for a hit, whose path goes on with a new cast
# queued for the next round, or the path's end. The events of a round are independent, so
# their chains of divisions and square roots overlap instead of stalling the walk one by one.
# Each path meets the same operations, in the same order, as in _trace_kernel: the same bits.

@njit(inline="always")
def _queue_cast(C, c, ox, oy, oz, dx, dy, dz, path, G):
    """Queue the cast from o along d of path ``path`` as cast c, with its per-cast set-up."""
    inv_dx, inv_dy, t_slab, du, dv, igd = _cast_setup(dx, dy, dz, oz, G[pk.G_SX], G[pk.G_SY],
                                                      G[pk.G_HMIN], G[pk.G_HMAX], G[pk.G_TOL])
    C[pk.Q_ORIGIN, c] = ox
    C[pk.Q_ORIGIN + 1, c] = oy
    C[pk.Q_ORIGIN + 2, c] = oz
    C[pk.Q_DIR, c] = dx
    C[pk.Q_DIR + 1, c] = dy
    C[pk.Q_DIR + 2, c] = dz
    C[pk.Q_INV, c] = inv_dx
    C[pk.Q_INV + 1, c] = inv_dy
    C[pk.Q_TSLAB, c] = t_slab
    C[pk.Q_DU, c] = du
    C[pk.Q_DU + 1, c] = dv
    C[pk.Q_DU + 2, c] = igd
    C[pk.Q_PATH, c] = path


@loopjit
def _trace_packets(first, stop, order, dirs, per, seed, start, h, pyr, G, code, params,
                   rr, max_bounces, out_dir, out_w, out_b, out_abs, out_lost):
    # Rays order[first] .. order[stop - 1], as _trace_kernel, in blocks of _BLOCK paths.
    ny, nx = h.shape
    sx = G[pk.G_SX]
    sy = G[pk.G_SY]
    hmin = G[pk.G_HMIN]
    hmax = G[pk.G_HMAX]
    lx = nx * sx
    ly = ny * sy
    eps = 1e-7 * min(sx, sy)
    zs = hmax + 1e-6 * (hmax - hmin + sx)
    ior = params[0]
    kext = params[1]
    alb = params[2]
    C = np.empty((pk.QROWS, _BLOCK))
    R = np.empty((pk.RROWS, _BLOCK))
    w = np.empty(_BLOCK)
    absorbed = np.empty(_BLOCK)
    bounces = np.empty(_BLOCK, np.int64)
    strm = np.empty(_BLOCK, np.uint64)
    for b0 in range(first, stop, _BLOCK):
        n = min(_BLOCK, stop - b0)
        for j in range(n):
            r = order[b0 + j]
            ox, oy, oz, dx, dy, dz, strm[j] = _launch(
                dirs, r // per, zs, lx, ly, _stream(seed, start + np.uint64(r), _TAG_RAY))
            w[j] = 1.0
            absorbed[j] = 0.0
            bounces[j] = 0
            _queue_cast(C, j, ox, oy, oz, dx, dy, dz, j, G)
        ncast = n
        while ncast > 0:
            walk_casts(C, R, ncast, h, pyr, G)
            queued = 0  # the next round's casts overwrite this round's, never ahead of them
            for c in range(ncast):
                j = int(C[pk.Q_PATH, c])
                dx = C[pk.Q_DIR, c]
                dy = C[pk.Q_DIR + 1, c]
                dz = C[pk.Q_DIR + 2, c]
                lost = 0.0
                if R[pk.R_EVENT, c] == pk.HIT and bounces[j] < max_bounces:
                    bounces[j] += 1
                    th, gx, gy, gz = _facet_hit(R[1, c], R[2, c], R[3, c], R[4, c], R[5, c],
                                                R[6, c], sx, sy)
                    px = C[pk.Q_ORIGIN, c] + th * dx
                    py = C[pk.Q_ORIGIN + 1, c] + th * dy
                    pz = C[pk.Q_ORIGIN + 2, c] + th * dz
                    dx, dy, dz, w[j], absorbed[j], strm[j] = _scatter(
                        code, ior, kext, alb, dx, dy, dz, gx, gy, gz, True, w[j], absorbed[j],
                        rr, strm[j])
                    if w[j] != 0.0:
                        ox, oy, oz = _next_origin(px, py, pz, eps, gx, gy, gz, lx, ly)
                        _queue_cast(C, queued, ox, oy, oz, dx, dy, dz, j, G)
                        queued += 1
                        continue
                elif R[pk.R_EVENT, c] != pk.ESCAPED:  # lost, or a hit beyond the bounce cap
                    lost = w[j]
                    w[j] = 0.0
                _store_path(order[b0 + j], w[j], dx, dy, dz, bounces[j], absorbed[j], lost,
                            out_dir, out_w, out_b, out_abs, out_lost)
            ncast = queued
