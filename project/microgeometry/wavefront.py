"""Bounce-by-bounce ("wavefront") tracing for facets with a microscale BRDF.

A :class:`~project.microgeometry.MicroBRDF` is a Python object evaluated in numpy, so it
cannot be called from inside the numba path loop of ``trace.py``. Instead all live rays are
advanced one facet interaction at a time:

1. numba (``_step_kernel``, parallel over rays): intersect every live ray with the height
   field (the same max-pyramid traversal as the path tracer), record escapes, cut-offs and
   hits, and move the origins of hit rays to the hit point (offset along the facet normal);
2. numpy (:class:`~project.microgeometry.scatter.FacetSampler`): for all hits of this bounce
   at once, express w_i in each facet's frame, draw the new direction and evaluate the BRDF
   in one batched ``brdf.eval`` call; multiply the weights by f cos / pdf;
3. numba (``_roulette_kernel``): Russian roulette below weight ``ROULETTE``, as in the
   path tracer (survive with probability w / rr at weight rr: unbiased).

There is no Python loop over rays, only over bounces (until no ray is left). Every ray
draws its uniforms from its own counter-based stream (seed, global ray index), a fixed
number per event, so the result does not depend on threads or chunking.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from basis._jit import njit, pjit, prange

from .scatter import FacetSampler, facet_frame
from .surface import Heightfield
from .trace import _ESCAPED, _HIT, _LOST, _TAG_RAY, ROULETTE, _intersect, _stream, _uniform

__all__ = ["run_wavefront"]


def run_wavefront(surface: Heightfield, dirs: NDArray, per: int, seed: np.uint64, start: int,
                  out: tuple, max_bounces: int, max_steps: int) -> None:
    """Fill ``out`` (directions, weights, bounces, absorbed, lost) like ``trace._run``."""
    sampler: FacetSampler = surface.material._sampler
    h = surface.heights
    sx, sy = surface.spacing
    hmin, hmax = float(h.min()), float(h.max())
    n = dirs.shape[0] * per
    o = np.empty((n, 3))
    d = np.empty((n, 3))
    s = np.empty(n, np.uint64)
    _start_kernel(np.ascontiguousarray(dirs), per, seed, np.uint64(start), h.shape[1] * sx,
                  h.shape[0] * sy, hmax + 1e-6 * (hmax - hmin + sx), o, d, s)
    w = np.ones(n)
    nb = np.zeros(n, np.int64)
    absorbed = np.zeros(n)
    lost = np.zeros(n)
    status = np.empty(n, np.int64)
    g = np.empty((n, 3))
    act = np.arange(n, dtype=np.int64)
    k = sampler.uniforms
    while act.size:
        _step_kernel(act, o, d, w, nb, lost, h, surface._pyramid, surface._offsets,
                     surface._levels, sx, sy, hmin, hmax, max_bounces, max_steps, status, g)
        hit = act[status[act] == _HIT]
        if hit.size == 0:
            break
        gh = g[hit]
        t, b = facet_frame(gh)
        wi = -d[hit]
        wl = np.stack([np.sum(wi * t, 1), np.sum(wi * b, 1), np.maximum(np.sum(wi * gh, 1),
                                                                          0.0)], axis=-1)
        wl /= np.linalg.norm(wl, axis=1)[:, None]
        u = np.empty((hit.size, k))
        _draw_kernel(hit, s, u)
        wo, factor = sampler.scatter(wl, u)
        d[hit] = wo[:, 0:1] * t + wo[:, 1:2] * b + wo[:, 2:3] * gh
        d[hit] /= np.linalg.norm(d[hit], axis=1)[:, None]
        absorbed[hit] += w[hit] * (1.0 - factor)
        w[hit] *= factor
        _roulette_kernel(hit, w, s, ROULETTE)
        act = hit[w[hit] > 0.0]
    dead = ~(w > 0.0)
    d[dead] = (0.0, 0.0, 1.0)
    out[0][:] = d
    out[1][:] = w
    out[2][:] = nb
    out[3][:] = absorbed
    out[4][:] = lost


@njit
def _start_kernel(dirs, per, seed, start, lx, ly, zs, o, d, s):
    # dirs (B, 3) incident directions; o, d (B * per, 3) out: first origins (above the
    # highest point, aimed at a uniform mean-plane point, as _trace_kernel) and directions;
    # s (B * per,) out: stream states after the two uniforms used here
    # serial: a few microseconds per thousand rays, less than a parallel launch costs
    for r in range(dirs.shape[0] * per):
        st = _stream(seed, start + np.uint64(r), _TAG_RAY)
        b = r // per
        u1, st = _uniform(st)
        u2, st = _uniform(st)
        k = zs / dirs[b, 2]
        ox = u1 * lx + k * dirs[b, 0]
        oy = u2 * ly + k * dirs[b, 1]
        o[r, 0] = ox - np.floor(ox / lx) * lx
        o[r, 1] = oy - np.floor(oy / ly) * ly
        o[r, 2] = zs
        d[r, 0] = -dirs[b, 0]
        d[r, 1] = -dirs[b, 1]
        d[r, 2] = -dirs[b, 2]
        s[r] = st


@pjit
def _step_kernel(act, o, d, w, nb, lost, h, pyr, offs, top, sx, sy, hmin, hmax, max_bounces,
                 max_steps, status, g):
    # act (A,) rows of live rays; o, d (n, 3) origins and unit directions; w, lost (n,)
    # weights; nb (n,) bounces; status (n,) out per row in act; g (n, 3) out: facet normal
    # of each hit. Hit rays get nb += 1 and their origin moved to the (offset) hit point;
    # cut-off rays (lost, or at the bounce cap) move their weight to lost.
    ny, nx = h.shape
    lx = nx * sx
    ly = ny * sy
    eps = 1e-7 * min(sx, sy)
    for a in prange(act.shape[0]):
        r = act[a]
        code, t, gx, gy, gz = _intersect(o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1], d[r, 2],
                                         h, pyr, offs, top, sx, sy, hmin, hmax, max_steps)
        if code == _ESCAPED:
            status[r] = _ESCAPED
            continue
        if code == _LOST or nb[r] >= max_bounces:
            status[r] = _LOST
            lost[r] = w[r]
            w[r] = 0.0
            continue
        status[r] = _HIT
        nb[r] += 1
        px = o[r, 0] + t * d[r, 0] + eps * gx
        py = o[r, 1] + t * d[r, 1] + eps * gy
        o[r, 0] = px - np.floor(px / lx) * lx
        o[r, 1] = py - np.floor(py / ly) * ly
        o[r, 2] = o[r, 2] + t * d[r, 2] + eps * gz
        g[r, 0] = gx
        g[r, 1] = gy
        g[r, 2] = gz


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
