"""Shared kernels of the microgeometry path tracers: random streams, facet events, traversal.

The height-field tracer (``trace.py``), the BVH walk (``bvh.py``), the bounce-by-bounce
tracer of MicroBRDF facets (``wavefront.py``) and the scene tracer (``scene.py``) are built
from these pieces, so that a ray draws the same random numbers, starts at the same point and
meets the same facet event in every tracer. This module sits below all of them in the
subpackage: of its siblings it imports only the material codes.

Random numbers: every ray has its own counter-based stream (SplitMix64 of seed, stream tag
and the global ray index), so results do not depend on the number of threads or on how the
rays are split into chunks.

Height-field traversal (``_intersect``): the max-height mip pyramid of
:class:`~project.microgeometry.Heightfield` is walked per ray (a stack-free quadtree walk, as
in "maximum mipmap" height-field ray casting): at level L the ray segment inside the current
node is skipped if it stays above the node's max height (then the walk climbs one level),
otherwise it descends; at level 0 the two triangles of the cell are intersected exactly (the
surface is piecewise linear along the segment). Coordinates are unwrapped (periodic tiling)
and node indices are taken modulo the grid. ``_packets.py`` runs the same walk for several
rays at once in vector registers, with the same bits.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from basis.jit import njit

from .materials import MIRROR

_GOLD = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_TAG_RAY = 1
_TAG_INCIDENT = 2

#: status codes of _intersect (and bvh._periodic_hit)
_HIT, _ESCAPED, _LOST = 0, 1, 2

#: default caps: facet interactions per path, traversal steps per segment
MAX_BOUNCES = 10_000
MAX_STEPS = 1_000_000

#: Russian roulette starts below this path weight (survivors continue with this weight)
ROULETTE = 0.05


def _alloc(n: int) -> tuple:
    """Allocate the outputs of n paths: directions (n, 3), weights, bounces, absorbed, lost (n,)."""
    return (np.empty((n, 3)), np.empty(n), np.empty(n, np.int64), np.empty(n), np.empty(n))


def incident_directions(count: int, seed: np.uint64, start: int, cosine: bool) -> NDArray:
    """Draw (count, 3) incident directions: cosine (pdf z / pi) or uniform (pdf 1 / (2 pi))."""
    out = np.empty((count, 3))
    _incident_kernel(seed, np.uint64(start), cosine, out)
    return out


# -- random numbers -------------------------------------------------------------------------

@njit
def _mix64(z):
    # SplitMix64 finaliser (Steele, Lea & Flood 2014): a bijection of uint64 with good avalanche
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


@njit
def _stream(seed, index, tag):
    # initial state of the stream (seed, tag, index); index is a uint64
    return _mix64(_mix64(seed ^ (np.uint64(tag) * _GOLD)) + index)


@njit
def _uniform(s):
    # one double in [0, 1) from the top 53 bits; returns (value, new state)
    s = s + _GOLD
    return float(_mix64(s) >> np.uint64(11)) * (1.0 / 9007199254740992.0), s


@njit
def _incident_kernel(seed, start, cosine, out):
    # out (B, 3) unit vectors with z in (0, 1]; serial: a few thousand per call at most
    for i in range(out.shape[0]):
        s = _stream(seed, start + np.uint64(i), _TAG_INCIDENT)
        u1, s = _uniform(s)
        u2, s = _uniform(s)
        z = np.sqrt(1.0 - u1) if cosine else 1.0 - u1
        r = np.sqrt(max(0.0, (1.0 - z) * (1.0 + z)))
        phi = 2.0 * np.pi * u2
        out[i, 0] = r * np.cos(phi)
        out[i, 1] = r * np.sin(phi)
        out[i, 2] = z


# -- facet optics -----------------------------------------------------------------------------

@njit
def _fresnel1(u, n, k):
    # exact unpolarised Fresnel of index n + i k at cos = u (as project.models._fresnel);
    # n = 0 flags "F = 1"
    if n == 0.0:
        return 1.0
    s2 = (1.0 - u) * (1.0 + u)
    t = n * n - k * k - s2
    nk2 = (n * k) ** 2
    r = np.sqrt(t * t + 4.0 * nk2)
    big = 0.5 * (r + t) if t >= 0.0 else 0.5 * (r - t)  # the cancellation-free one
    small = nk2 / big if big > 0.0 else 0.0
    a2 = big if t >= 0.0 else small
    b2 = small if t >= 0.0 else big
    a = np.sqrt(a2)
    den_s = (a + u) ** 2 + b2
    rs = ((a - u) ** 2 + b2) / den_s if den_s > 0.0 else 0.0
    au = a * u
    bu2 = b2 * u * u
    den_p = (au + s2) ** 2 + bu2
    rp = rs * ((au - s2) ** 2 + bu2) / den_p if den_p > 0.0 else rs
    return min(1.0, max(0.0, 0.5 * (rs + rp)))


@njit
def _cosine_sample(nx, ny, nz, u1, u2):
    # cosine-distributed unit vector about the unit normal n; orthonormal frame of
    # Duff et al. 2017 (branch-free, no singularity except the sign switch)
    sign = 1.0 if nz >= 0.0 else -1.0
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    r = np.sqrt(u1)
    phi = 2.0 * np.pi * u2
    x = r * np.cos(phi)
    y = r * np.sin(phi)
    z = np.sqrt(max(0.0, 1.0 - u1))
    dx = x * (1.0 + sign * nx * nx * a) + y * b + z * nx
    dy = x * (sign * b) + y * (sign + ny * ny * a) + z * ny
    dz = x * (-sign * nx) + y * (-ny) + z * nz
    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
    return dx * inv, dy * inv, dz * inv


# -- traversal --------------------------------------------------------------------------------

@njit(inline="always")
def _cell(ix, iy, cx, cy, t0, t1, ox, oy, oz, dx, dy, dz, h, sx, sy, isx, isy, du, dv, igd):
    # First crossing of the ray from above the two triangles of cell (cx, cy) (unwrapped
    # position ix, iy) on [t0, t1]. The surface along the segment is piecewise linear with
    # one kink where it crosses the diagonal u = v, so the signed height f = z_ray - z_surf
    # is exact at the piece ends and linear in between. isx, isy = 1 / sx, 1 / sy and the
    # ray's du, dv = dx / sx, dy / sy and igd = 1 / (du - dv) are the caller's (_cast_setup):
    # the packet walk of _packets.py computes these lines for several rays at once, where a
    # division costs several times a product, and gives the same bits.
    # Inlined into the walk: as a call it spilled and reloaded some twenty registers.
    ny, nx = h.shape
    i1 = cx + 1 if cx + 1 < nx else 0
    j1 = cy + 1 if cy + 1 < ny else 0
    h00 = h[cy, cx]
    h10 = h[cy, i1]
    h01 = h[j1, cx]
    h11 = h[j1, i1]
    ua = (ox + t0 * dx - ix * sx) * isx
    va = (oy + t0 * dy - iy * sy) * isy
    g0 = ua - va
    gd = du - dv
    ts = t1
    if gd != 0.0:
        tc = t0 - g0 * igd
        if t0 < tc < t1:
            ts = tc
    ta = t0
    for piece in range(2):
        tb = ts if piece == 0 else t1
        if piece == 1 and tb <= ta:
            break
        gm = g0 + (0.5 * (ta + tb) - t0) * gd
        if gm >= 0.0:  # triangle A (00, 10, 11)
            a1 = h10 - h00
            a2 = h11 - h10
        else:  # triangle B (00, 11, 01)
            a1 = h11 - h01
            a2 = h01 - h00
        fa = oz + ta * dz - (h00 + a1 * (ua + (ta - t0) * du) + a2 * (va + (ta - t0) * dv))
        fb = oz + tb * dz - (h00 + a1 * (ua + (tb - t0) * du) + a2 * (va + (tb - t0) * dv))
        if fa > 0.0 and fb <= 0.0:
            th, gx, gy, gz = _facet_hit(ta, tb, fa, fb, a1, a2, sx, sy)
            return True, th, gx, gy, gz
        ta = tb
    return False, 0.0, 0.0, 0.0, 1.0


@njit(inline="always")
def _facet_hit(ta, tb, fa, fb, a1, a2, sx, sy):
    """Return the crossing t and the unit facet normal of a piece where f changes sign.

    f = z_ray - z_surf is linear on [ta, tb] from fa > 0 to fb <= 0; the facet's heights
    rise by a1 per cell along x and a2 along y.
    """
    th = ta + (tb - ta) * fa / (fa - fb)
    gx = -a1 / sx
    gy = -a2 / sy
    inv = 1.0 / np.sqrt(gx * gx + gy * gy + 1.0)
    return th, gx * inv, gy * inv, inv


@njit(inline="always")
def _cast_setup(dx, dy, dz, oz, sx, sy, hmin, hmax, tol):
    """Return the per-cast constants of the walk.

    They are 1 / dx, 1 / dy (0 for 0), the distance t_slab at which the ray leaves the slab
    [hmin, hmax], and du, dv, 1 / (du - dv) of the cell test: the same bits in _intersect
    and in the packet walk of _packets.py.
    """
    inv_dx = 1.0 / dx if dx != 0.0 else 0.0
    inv_dy = 1.0 / dy if dy != 0.0 else 0.0
    # never step past the slab [hmin, hmax] (vertical rays have tx = ty = inf)
    if dz < 0.0:
        t_slab = (hmin - 2.0 * tol - oz) / dz
    elif dz > 0.0:
        t_slab = (hmax + tol - oz) / dz
    else:
        t_slab = np.inf
    du = dx / sx
    dv = dy / sy
    igd = 1.0 / (du - dv) if du != dv else 0.0  # used only when du != dv
    return inv_dx, inv_dy, t_slab, du, dv, igd


@njit(inline="always")
def _grid_step(o, d, inv_d, p, size, inv_size, tol):
    """Step along one axis of a grid of cells of width ``size``.

    Returns the cell index of the ray (origin o, direction d, ``inv_d`` = 1 / d) at its
    position p, and the distance t at which it leaves that cell. On a cell boundary (within
    tol * size) the cell it is entering is taken, else the walk would make zero-length steps.
    Multiplications by the precomputed inverses replace the divisions of a naive step: a
    step is a few tens of instructions, and two divisions per axis were a third of them.

    The index stays a float (f, an integer exactly) until the end, and the exit distances
    of both candidate cells (with and without the boundary rule) are formed before the rule
    picks one: the walk is a chain of dependent steps, and this takes two int-to-float
    conversions and a multiply-subtract-multiply off it (the tracer 1.15-1.27x faster). The
    values are the bits of ``i = floor(p * inv_size)``, then ``((i + 1) * size - o) * inv_d``: f + 1
    is float(i + 1) exactly.
    """
    f = np.floor(p * inv_size)
    i = int(f)
    if d > 0.0:
        e = (f + 1.0) * size
        stay = (e - o) * inv_d
        enter = ((f + 2.0) * size - o) * inv_d
        if e - p <= tol * size:
            return i + 1, enter
        return i, stay
    if d < 0.0:
        e = f * size
        stay = (e - o) * inv_d
        enter = ((f - 1.0) * size - o) * inv_d
        if p - e <= tol * size:
            return i - 1, enter
        return i, stay
    return i, np.inf


@njit
def _intersect(ox, oy, oz, dx, dy, dz, h, pyr, offs, top, sx, sy, hmin, hmax, max_steps):
    # Walk the max pyramid from t = 0; returns (status, t, normal x, y, z). The walk starts
    # at level 0, in the cell under the origin: any start level finds the same first hit
    # (the walk skips only nodes the ray clears and descends into every other one), but the
    # nodes of the upper levels hold heights close to the maximum, so a walk started at the
    # top descends through nearly all of them before any progress. Measured on a 512 x 512
    # Gaussian field (m = 0.3, cosine incidence): 7.7 steps per incident ray instead of
    # 15.4, and 6 instead of 15 for a ray leaving a facet.
    ny, nx = h.shape
    tol = 1e-9 * (hmax - hmin + sx + sy)
    inv_dx, inv_dy, t_slab, du, dv, igd = _cast_setup(dx, dy, dz, oz, sx, sy, hmin, hmax, tol)
    isx = 1.0 / sx
    isy = 1.0 / sy
    # node widths are powers of two times the top level's: a mask replaces the modulo (an
    # integer division) when the grid is a power of two, the usual case
    pow2 = (nx & (nx - 1)) == 0 and (ny & (ny - 1)) == 0
    # the level's node size, its inverse, node counts and offset, kept up to date as the
    # level changes (doubling and halving are exact)
    lev = 0
    wx = sx
    wy = sy
    iwx = 1.0 / sx
    iwy = 1.0 / sy
    wl = nx
    hl = ny
    off = offs[0]
    t = 0.0
    for _ in range(max_steps):
        z = oz + t * dz
        if dz >= 0.0 and z > hmax:
            return _ESCAPED, t, 0.0, 0.0, 0.0
        if dz < 0.0 and z < hmin - tol:
            return _LOST, t, 0.0, 0.0, 0.0  # passed through the surface (rounding)
        ix, tx = _grid_step(ox, dx, inv_dx, ox + t * dx, wx, iwx, 1e-9)
        iy, ty = _grid_step(oy, dy, inv_dy, oy + t * dy, wy, iwy, 1e-9)
        t1 = min(tx, ty, t_slab)
        if pow2:
            cx = ix & (wl - 1)  # two's complement: also right for negative ix
            cy = iy & (hl - 1)
        else:
            cx = ix % wl
            cy = iy % hl
        zn = pyr[off + cy * wl + cx]
        if min(z, oz + t1 * dz) > zn:
            # the ray clears the node: climb only if its exit leaves the parent node too,
            # else the parent (holding the next node, a sibling) would be examined only to
            # be descended into again (11 % fewer steps, the same walk otherwise)
            up = t_slab <= min(tx, ty)
            if tx <= ty and ((ix & 1) == 1 if dx > 0.0 else (ix & 1) == 0):
                up = True
            if ty <= tx and ((iy & 1) == 1 if dy > 0.0 else (iy & 1) == 0):
                up = True
        elif lev > 0:
            lev -= 1
            wx *= 0.5
            wy *= 0.5
            iwx *= 2.0
            iwy *= 2.0
            wl <<= 1
            hl <<= 1
            off = offs[lev]
            continue
        else:
            hit, th, gx, gy, gz = _cell(ix, iy, cx, cy, t, t1, ox, oy, oz, dx, dy, dz, h, sx,
                                        sy, isx, isy, du, dv, igd)
            if hit:
                return _HIT, th, gx, gy, gz
            up = True  # a cell the ray crossed without a hit
        t = t1
        if up and lev < top:
            lev += 1
            wx *= 2.0
            wy *= 2.0
            iwx *= 0.5
            iwy *= 0.5
            wl >>= 1
            hl >>= 1
            off = offs[lev]
    return _LOST, t, 0.0, 0.0, 0.0


# -- path steps -------------------------------------------------------------------------------

@njit(inline="always")
def _launch(dirs, b, zs, lx, ly, s):
    """Start a ray of incidence dirs[b] above the surface.

    The origin lies above the highest point, at z = zs, on the line through a uniform point
    of the mean plane's period (lx x ly); the ray travels towards the surface.
    """
    u1, s = _uniform(s)
    u2, s = _uniform(s)
    k = zs / dirs[b, 2]
    ox = u1 * lx + k * dirs[b, 0]
    oy = u2 * ly + k * dirs[b, 1]
    ox -= np.floor(ox / lx) * lx
    oy -= np.floor(oy / ly) * ly
    return ox, oy, zs, -dirs[b, 0], -dirs[b, 1], -dirs[b, 2], s


@njit(inline="always")
def _scatter(code, ior, kext, alb, dx, dy, dz, gx, gy, gz, front, w, absorbed, rr, s):
    """Apply one opaque facet event to a ray.

    The ray travels along d and hit a facet of normal g (facing the ray; ``front`` says
    whether the ray arrived on the primitive's outer side): mirror reflection weighted by
    Fresnel, or a cosine-distributed diffuse bounce weighted by the albedo, then Russian
    roulette (survive with probability w / rr at weight rr).
    Returns the new direction, weight (0 when the ray dies), absorbed energy and stream.
    """
    ci = -(dx * gx + dy * gy + dz * gz)
    if code == MIRROR:
        f = _fresnel1(min(1.0, max(0.0, ci)), ior, kext)
        dx += 2.0 * ci * gx
        dy += 2.0 * ci * gy
        dz += 2.0 * ci * gz
        inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
        dx *= inv
        dy *= inv
        dz *= inv
    else:
        f = alb
        u1, s = _uniform(s)
        u2, s = _uniform(s)
        dx, dy, dz = _cosine_sample(gx, gy, gz, u1, u2)
    absorbed += w * (1.0 - f)
    w, s = _roulette(w * f, rr, s)
    return dx, dy, dz, w, absorbed, s


@njit(inline="always")
def _roulette(w, rr, s):
    """Play Russian roulette with the weight w.

    A weight below rr survives with probability w / rr at weight rr (unbiased: the expected
    weight is w), else becomes 0. One draw, only when w < rr.
    """
    if w < rr:
        u1, s = _uniform(s)
        w = rr if u1 * rr < w else 0.0
    return w, s


@njit(inline="always")
def _dielectric(ior, dx, dy, dz, gx, gy, gz, front, w, rr, s):
    """Reflect or refract a ray at a smooth dielectric facet (one event).

    The facet has relative index ``ior``; the ray travels along d and hit it with normal g
    facing the ray; ``front``: the ray arrives from outside (it would enter, relative index
    n) or from inside (it would leave, 1 / n).

    Reflects with the exact unpolarised Fresnel probability F (_fresnel1 with k = 0: it
    handles relative indices below 1 and gives F = 1 beyond the critical angle), else
    refracts by Snell's law. Choosing by probability F instead of splitting the weight
    keeps the weight unchanged (unbiased: the expected contribution of each branch is F,
    resp. 1 - F, times the weight), so only absorption along segments (_attenuate) and
    roulette change it. One uniform draw for the choice, then _roulette.
    Returns (new direction, weight, stream, refracted).
    """
    ci = min(1.0, max(0.0, -(dx * gx + dy * gy + dz * gz)))
    eta = ior if front else 1.0 / ior  # n2 / n1 across the facet
    f = _fresnel1(ci, eta, 0.0)
    u, s = _uniform(s)
    refracted = u >= f  # never under total internal reflection (F = 1 > u)
    if refracted:
        # t = d / eta + (ci / eta - ct) g: the tangential part shrinks by 1 / eta and the
        # normal part, -ct along g, points through the facet
        r = 1.0 / eta
        ct = np.sqrt(max(0.0, 1.0 - r * r * (1.0 - ci) * (1.0 + ci)))
        a = r * ci - ct
        dx = r * dx + a * gx
        dy = r * dy + a * gy
        dz = r * dz + a * gz
    else:
        dx += 2.0 * ci * gx
        dy += 2.0 * ci * gy
        dz += 2.0 * ci * gz
    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
    w, s = _roulette(w, rr, s)
    return dx * inv, dy * inv, dz * inv, w, s, refracted


@njit(inline="always")
def _attenuate(sigma, t, w, absorbed):
    """Apply the Beer-Lambert loss over a segment of length t in a medium of absorption sigma.

    The weight keeps exp(-sigma t), the rest is added to ``absorbed`` (the two sum to the
    old weight up to rounding). Returns (w, absorbed).
    """
    if sigma > 0.0:
        loss = -w * np.expm1(-sigma * t)
        absorbed += loss
        w -= loss
    return w, absorbed


@njit(inline="always")
def _next_origin(px, py, pz, side, gx, gy, gz, lx, ly):
    """Return the origin of the next segment.

    It is the hit point moved by ``side`` along the facet normal g (positive: the side the
    normal faces) and wrapped into the period [0, lx) x [0, ly).
    """
    ox = px + side * gx
    oy = py + side * gy
    ox -= np.floor(ox / lx) * lx
    oy -= np.floor(oy / ly) * ly
    return ox, oy, pz + side * gz


@njit(inline="always")
def _store_path(r, w, dx, dy, dz, bounces, absorbed, lost, out_dir, out_w, out_b, out_abs,
                out_lost):
    """Write ray r's exit (direction, or +z for a dead ray), weight and bookkeeping."""
    if w > 0.0:
        out_dir[r, 0] = dx
        out_dir[r, 1] = dy
        out_dir[r, 2] = dz
    else:
        out_dir[r, 0] = 0.0
        out_dir[r, 1] = 0.0
        out_dir[r, 2] = 1.0
    out_w[r] = w
    out_b[r] = bounces
    out_abs[r] = absorbed
    out_lost[r] = lost


# -- ray order --------------------------------------------------------------------------------

#: bins per side of the period (at most) in which :func:`_coherent_order` sorts the rays
ORDER_BINS = 128


@njit
def _coherent_order(seed, start, n, nx, ny):
    """Return the ray indices 0 .. n - 1 sorted along a Morton curve by where they aim.

    Ray r (stream start + r) crosses the mean plane at the uniform point of the period that
    :func:`_launch` draws first; that is where its walk and, for most rays, its whole path
    stay. Tracing in this order, neighbouring rays read the same pyramid nodes and heights
    from cache instead of memory (a counting sort over at most ORDER_BINS^2 bins of the
    period, Morton order of the bins). The order changes no ray's path, only which runs when.
    """
    bx = min(nx, ORDER_BINS)
    by = min(ny, ORDER_BINS)
    nkeys = ORDER_BINS * ORDER_BINS
    key = np.empty(n, np.int64)
    first = np.zeros(nkeys + 1, np.int64)
    for r in range(n):
        s = _stream(seed, start + np.uint64(r), _TAG_RAY)
        u1, s = _uniform(s)
        u2, s = _uniform(s)
        ix = min(int(u1 * bx), bx - 1)
        iy = min(int(u2 * by), by - 1)
        k = 0
        for bit in range(7):  # ORDER_BINS = 2^7
            k |= ((ix >> bit) & 1) << (2 * bit)
            k |= ((iy >> bit) & 1) << (2 * bit + 1)
        key[r] = k
        first[k + 1] += 1
    for k in range(nkeys):
        first[k + 1] += first[k]
    order = np.empty(n, np.int64)
    for r in range(n):
        k = key[r]
        order[first[k]] = r
        first[k] += 1
    return order
