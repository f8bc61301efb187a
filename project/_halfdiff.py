"""Inlined numba helpers of the tables in half/difference angles (MERL and tabulated BRDFs).

Rusinkiewicz (1998) coordinates are formed from h = w_i + w_o and w_i - w_o: exchanging w_i
and w_o leaves h, theta_h and theta_d unchanged bit for bit and negates w_i - w_o exactly,
which turns phi_d into phi_d + pi; folded onto half a turn, a table is then exactly
reciprocal. Both helpers are inlined into the kernels that call them (the kernels' numba
caches are checked against their own files only: after editing this one, ``make
clean-cache``).
"""

from __future__ import annotations

import math

from basis.jit import njit


@njit(inline="always")
def half_difference(wi, wo, p, fold):  # pragma: no cover - compiled
    """Return theta_h, theta_d, phi_d, cos theta_i, cos theta_o of pair ``p``.

    phi_d = atan2(b, a) in (-pi, pi], or in [0, pi) when ``fold`` (reciprocity).
    """
    ni = math.sqrt(wi[p, 0] ** 2 + wi[p, 1] ** 2 + wi[p, 2] ** 2)
    no = math.sqrt(wo[p, 0] ** 2 + wo[p, 1] ** 2 + wo[p, 2] ** 2)
    ix, iy, iz = wi[p, 0] / ni, wi[p, 1] / ni, wi[p, 2] / ni
    ox, oy, oz = wo[p, 0] / no, wo[p, 1] / no, wo[p, 2] / no
    hx, hy, hz = ix + ox, iy + oy, iz + oz
    dx, dy, dz = ix - ox, iy - oy, iz - oz
    r = math.sqrt(hx * hx + hy * hy)
    hn = math.sqrt(r * r + hz * hz)
    if hn > 0.0:
        theta_h = math.atan2(r, hz)
        ct, st = hz / hn, r / hn
    else:  # wi = -wo on the horizon: no half vector, take h = z (as to_rusinkiewicz)
        theta_h = 0.0
        ct, st = 1.0, 0.0
    if r > 0.0:
        cp, sp = hx / r, hy / r
    else:  # h = z: phi_h = 0
        cp, sp = 1.0, 0.0
    theta_d = math.atan2(math.sqrt(dx * dx + dy * dy + dz * dz), hn)
    # (wi - wo)/2 in the frame t1 = (ct cp, ct sp, -st), t2 = (-sp, cp, 0) of h
    a = ct * (cp * dx + sp * dy) - st * dz + 0.0  # + 0.0 turns -0.0 into +0.0
    b = cp * dy - sp * dx + 0.0
    if fold and (b < 0.0 or (b == 0.0 and a < 0.0)):
        a = -a
        b = -b
    return theta_h, theta_d, math.atan2(b, a), iz, oz


@njit(inline="always")
def cell(x, n):  # pragma: no cover - compiled
    """Return the cell i0 (of nodes 0..n-1, clamped to the last) and the weight t of x."""
    i0 = min(int(x), n - 2)
    return i0, min(x - i0, 1.0)


@njit(inline="always")
def periodic_cell(x, m):  # pragma: no cover - compiled
    """Return the nodes k0, k1 of x on a periodic axis of m nodes and the weight of k1."""
    k0 = int(x)
    t = x - k0
    k0 = k0 % m
    return k0, (k0 + 1) % m, t


@njit(inline="always")
def cell_trilinear(t, i0, j0, k0, k1, tu, tv, tw, c):  # pragma: no cover - compiled
    """Return channel ``c`` of table ``t`` interpolated in cell (i0, j0, k0..k1)."""
    lo = ((1.0 - tv) * ((1.0 - tw) * t[i0, j0, k0, c] + tw * t[i0, j0, k1, c])
          + tv * ((1.0 - tw) * t[i0, j0 + 1, k0, c] + tw * t[i0, j0 + 1, k1, c]))
    hi = ((1.0 - tv) * ((1.0 - tw) * t[i0 + 1, j0, k0, c] + tw * t[i0 + 1, j0, k1, c])
          + tv * ((1.0 - tw) * t[i0 + 1, j0 + 1, k0, c] + tw * t[i0 + 1, j0 + 1, k1, c]))
    return (1.0 - tu) * lo + tu * hi


@njit(inline="always")
def half_difference_unit(ix, iy, iz, ox, oy, oz, fold):  # pragma: no cover - compiled
    """Return theta_h, theta_d, phi_d of a pair given as normalised components.

    The arithmetic of :func:`half_difference` after its normalisation, operation for
    operation, so a caller that normalises as it does (x / sqrt(x ** 2 + y ** 2 + z ** 2))
    gets the same bits; it lets a kernel normalise a direction shared by many pairs once.
    """
    hx, hy, hz = ix + ox, iy + oy, iz + oz
    dx, dy, dz = ix - ox, iy - oy, iz - oz
    r = math.sqrt(hx * hx + hy * hy)
    hn = math.sqrt(r * r + hz * hz)
    if hn > 0.0:
        theta_h = math.atan2(r, hz)
        ct, st = hz / hn, r / hn
    else:
        theta_h = 0.0
        ct, st = 1.0, 0.0
    if r > 0.0:
        cp, sp = hx / r, hy / r
    else:
        cp, sp = 1.0, 0.0
    theta_d = math.atan2(math.sqrt(dx * dx + dy * dy + dz * dz), hn)
    a = ct * (cp * dx + sp * dy) - st * dz + 0.0
    b = cp * dy - sp * dx + 0.0
    if fold and (b < 0.0 or (b == 0.0 and a < 0.0)):
        a = -a
        b = -b
    return theta_h, theta_d, math.atan2(b, a)
