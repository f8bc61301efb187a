"""Paths of rays through a specimen: :func:`trace`, :class:`Paths`, the height-field loop.

The numba path loop of height fields is ``_trace_kernel``.

``_trace_kernel`` follows every ray from its start above the surface through the max-pyramid
walk to the next facet, the facet event (Fresnel mirror or cosine-diffuse bounce, then
Russian roulette) and the next origin, until it escapes, dies or is cut off. These pieces,
and the per-ray random streams, are the shared kernels of ``_paths.py``; a
:class:`~project.microgeometry.Scene` is traced by its own loop (``scene.py``) and
:class:`~project.microgeometry.MicroBRDF` facets bounce by bounce (``wavefront.py``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba.cpython.unsafe.numbers import trailing_zeros
from numpy.typing import ArrayLike, NDArray

from basis.jit import loopjit, njit, run_parallel
from basis.validation import as_directions

from . import _packets as pk
from ._checks import _positive_int, _seed
from ._packets import walk_step
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
        traced bounce by bounce (``wavefront.py``), the others path by path in numba.
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
#: rays launched at a time by _trace_packets (_launch_block)
_BLOCK = 512


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


@njit
def _begin_cast(S, k, ox, oy, oz, dx, dy, dz, G):
    """Start lane k of the packet S on the cast from o along d (the set-up of _intersect)."""
    inv_dx, inv_dy, t_slab, du, dv, igd = _cast_setup(dx, dy, dz, oz, G[pk.G_SX], G[pk.G_SY],
                                                      G[pk.G_HMIN], G[pk.G_HMAX], G[pk.G_TOL])
    S[pk.OX, k] = ox
    S[pk.OY, k] = oy
    S[pk.OZ, k] = oz
    S[pk.DX, k] = dx
    S[pk.DY, k] = dy
    S[pk.DZ, k] = dz
    S[pk.IDX, k] = inv_dx
    S[pk.IDY, k] = inv_dy
    S[pk.TSL, k] = t_slab
    S[pk.DU, k] = du
    S[pk.DV, k] = dv
    S[pk.IGD, k] = igd
    S[pk.T, k] = 0.0
    S[pk.P2, k] = 1.0
    S[pk.IP2, k] = 1.0
    S[pk.STEPS, k] = 0.0
    S[pk.ACT, k] = 1.0


@njit
def _launch_block(first, stop, order, dirs, per, seed, start, zs, lx, ly, buf, sbuf):
    """Launch rays order[first] .. order[stop - 1] into buf (origin, direction) and sbuf.

    One pass whose iterations are independent: the reads of dirs (by incidence, in the
    coherent order of the rays: scattered in memory) overlap, instead of stalling the
    walk one at a time.
    """
    for i in range(first, stop):
        r = order[i]
        j = i - first
        buf[j, 0], buf[j, 1], buf[j, 2], buf[j, 3], buf[j, 4], buf[j, 5], sbuf[j] = _launch(
            dirs, r // per, zs, lx, ly, _stream(seed, start + np.uint64(r), _TAG_RAY))


@loopjit
def _trace_packets(first, stop, order, dirs, per, seed, start, h, pyr, G, code, params,
                   rr, max_bounces, out_dir, out_w, out_b, out_abs, out_lost):
    # _trace_kernel with the walks of LANES paths interleaved in one packet (_packets.py):
    # each walk_step advances every lane by one step of its own walk; the lanes whose cast
    # ended meet their facet event here, one by one, and start their next cast or path.
    # Every ray's path, and so every output, has the bits of _trace_kernel.
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
    S = np.zeros((pk.NROWS, pk.LANES))
    ray = np.zeros(pk.LANES, np.int64)
    w = np.zeros(pk.LANES)
    absorbed = np.zeros(pk.LANES)
    bounces = np.zeros(pk.LANES, np.int64)
    strm = np.zeros(pk.LANES, np.uint64)
    buf = np.empty((_BLOCK, 6))
    sbuf = np.empty(_BLOCK, np.uint64)
    nxt = first
    block = first - _BLOCK  # rays block .. block + _BLOCK - 1 are launched in buf
    live = 0
    for k in range(pk.LANES):
        S[pk.ACT, k] = 0.0
    while True:
        # fill the idle lanes with new paths
        for k in range(pk.LANES):
            if S[pk.ACT, k] == 0.0 and nxt < stop:
                if nxt == block + _BLOCK:
                    block = nxt
                    _launch_block(block, min(stop, block + _BLOCK), order, dirs, per, seed,
                                  start, zs, lx, ly, buf, sbuf)
                j = nxt - block
                ray[k] = order[nxt]
                strm[k] = sbuf[j]
                w[k] = 1.0
                absorbed[k] = 0.0
                bounces[k] = 0
                _begin_cast(S, k, buf[j, 0], buf[j, 1], buf[j, 2], buf[j, 3], buf[j, 4],
                            buf[j, 5], G)
                nxt += 1
                live += 1
        if live == 0:
            break
        m = walk_step(S, h, pyr, G)
        while m != 0:
            k = trailing_zeros(m)
            m &= m - 1
            event = S[pk.EVENT, k]
            dx = S[pk.DX, k]
            dy = S[pk.DY, k]
            dz = S[pk.DZ, k]
            lost = 0.0
            if event == pk.HIT and bounces[k] < max_bounces:
                bounces[k] += 1
                th, gx, gy, gz = _facet_hit(S[pk.TA, k], S[pk.TB, k], S[pk.FA, k],
                                            S[pk.FB, k], S[pk.A1, k], S[pk.A2, k], sx, sy)
                px = S[pk.OX, k] + th * dx
                py = S[pk.OY, k] + th * dy
                pz = S[pk.OZ, k] + th * dz
                dx, dy, dz, w[k], absorbed[k], strm[k] = _scatter(
                    code, ior, kext, alb, dx, dy, dz, gx, gy, gz, True, w[k], absorbed[k], rr,
                    strm[k])
                if w[k] != 0.0:
                    ox, oy, oz = _next_origin(px, py, pz, eps, gx, gy, gz, lx, ly)
                    _begin_cast(S, k, ox, oy, oz, dx, dy, dz, G)
                    continue
            elif event != pk.ESCAPED:  # lost, or a hit beyond the bounce cap
                lost = w[k]
                w[k] = 0.0
            _store_path(ray[k], w[k], dx, dy, dz, bounces[k], absorbed[k], lost, out_dir, out_w,
                        out_b, out_abs, out_lost)
            S[pk.ACT, k] = 0.0
            live -= 1
