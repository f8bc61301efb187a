"""Koenderink's hemisphere functions: Zernike polynomials carried to the hemisphere.

The upper hemisphere is mapped onto the unit disk by Lambert's equal-area map
rho = sqrt(2) sin(theta / 2), i.e. rho^2 = 1 - cos(theta), phi unchanged. Since
rho d rho d phi = d omega / 2, functions orthogonal on the disk stay orthogonal on the
hemisphere, and the disk norm int_D |V_n^l|^2 dA = pi / (n + 1) becomes 2 pi / (n + 1).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._base import Basis
from .jit import (
    LANES,
    lane_affine,
    lane_disk,
    lane_jacobi,
    lane_mul,
    lane_rotate,
    lane_tile,
    lane_turn,
    njit,
    run_parallel,
    writable,
)
from .quadrature import HemisphereRule, hemisphere_rule
from .validation import nonneg_int

_INV_SQRT2 = float(1.0 / np.sqrt(2.0))
#: Below this order the recurrences run two directions at a time (_zernike_pairs), from it
#: LANES (_zernike_lanes). Measured on one core into fresh output arrays: the pairs 1.05x as
#: fast as the lanes at order 6, the lanes 1.1x at order 8 and 1.4-1.9x from 12 to 32.
_PAIR_ORDER = 8


class HemiZernike(Basis):
    """Koenderink's K_n^l in real form: orthonormal functions on the upper hemisphere, n <= order.

    Parameters
    ----------
    order : int
        Highest radial degree n, inclusive (0 <= order <= 1000). The basis has
        (order + 1)(order + 2) / 2 functions.

    Notes
    -----
    With rho = sqrt(2) sin(theta/2) and R_n^l the Zernike radial polynomial (R_n^l(1) = 1),

        K_n^0 = sqrt((n + 1) / (2 pi)) R_n^0(rho),
        K_n^l = sqrt((n + 1) / pi) R_n^|l|(rho) cos(l phi)        (l > 0),
        K_n^l = sqrt((n + 1) / pi) R_n^|l|(rho) sin(|l| phi)      (l < 0),

    for n - |l| even, ordered by n and then by signed l ascending. ``degree`` holds n and
    ``azimuthal`` the signed l.

    Where this disagrees with Koenderink, van Doorn & Stavridi (1996, sec. 2):
    the printed normalisation sqrt((2n + 1)/2) is wrong; the disk norm pi/(n+1) and the
    Jacobian d omega = 2 dA give sqrt((n + 1)/(2 pi)) for the complex functions R e^{il phi},
    and the real functions above (checked by exact quadrature in the tests). The explicit
    order-2 modes printed in sec. 3.3 are discussed in :class:`basis.HelmholtzModes`.

    The radial functions are computed with the three-term recurrence of the Jacobi
    polynomials, R_n^l(rho) = rho^l P_k^(0,l)(2 rho^2 - 1), k = (n - l)/2, run on R itself (so
    every intermediate value is bounded by 1) and seeded by R_l^l = rho^l. The textbook
    factorial sum loses all accuracy by n ~ 40 in float64; the recurrence agrees with mpmath to
    about 1e-13 at n = 300 (tests). rho^2 is computed as (x^2 + y^2)/(1 + z), which keeps full
    relative accuracy near the pole, and cos(l phi), sin(l phi) by complex multiplication.

    Examples
    --------
    >>> import numpy as np
    >>> zb = HemiZernike(2)
    >>> zb.size, zb.degree.tolist(), zb.azimuthal.tolist()
    (6, [0, 1, 1, 2, 2, 2], [0, -1, 1, -2, 0, 2])
    >>> bool(np.isclose(zb.eval([0.0, 0.0, 1.0])[0], 1 / np.sqrt(2 * np.pi)))
    True
    """

    domain = "hemisphere"
    kind = "zernike"
    max_order = 1000

    def __init__(self, order: int) -> None:
        super().__init__(order)
        n = np.repeat(np.arange(self._order + 1), np.arange(self._order + 1) + 1)
        l = np.concatenate([np.arange(-k, k + 1, 2) for k in range(self._order + 1)])
        self._degree = n.astype(np.int64)
        self._azimuthal = l.astype(np.int64)
        self._coef = _radial_tables(self._order)
        self._start = np.array([_col(self._order, l) for l in range(self._order + 1)],
                               dtype=np.int64)
        self._norm = np.sqrt((np.arange(self._order + 1) + 1.0) / np.pi)

    def _eval_flat(self, dirs: NDArray[np.float64], out: NDArray[np.float64]) -> None:
        if not out.flags.c_contiguous:  # the kernel writes whole tiles by flat index
            res = np.empty(out.shape)
            self._eval_flat(dirs, res)
            out[...] = res
            return
        # each strategy its own kernel, so a program compiles only the ones its orders use
        run_parallel(_zernike_pairs if self._order < _PAIR_ORDER else _zernike_lanes,
                     (dirs.shape[0] + LANES - 1) // LANES, writable(dirs), self._order,
                     self._coef, self._start, self._norm, out, grain=_TASK // LANES)

    def exact_rule(self) -> HemisphereRule:
        """Return a product rule exact for every product of two functions of this basis.

        Exact for every product K_a K_b: a polynomial of degree <= order in rho^2 = 1 - z
        when |l_a| = |l_b|, and of azimuthal degree <= 2 order otherwise.
        """
        return hemisphere_rule(self._order // 2 + 1, 2 * self._order + 1)


def zernike_radial(n: int, l: int, rho: ArrayLike) -> NDArray[np.float64]:
    """Evaluate the Zernike radial polynomial R_n^l(rho) on the unit disk by a stable recurrence.

    Parameters
    ----------
    n, l : int
        Radial degree and |azimuthal order|, n >= l >= 0, n - l even.
    rho : array_like of float
        Radii in [0, 1].

    Returns
    -------
    ndarray of float64, the shape of ``rho``.

    Examples
    --------
    >>> float(zernike_radial(4, 0, 0.5))  # 6 rho^4 - 6 rho^2 + 1
    -0.125
    """
    n = nonneg_int(n, "n", maximum=HemiZernike.max_order)
    l = nonneg_int(l, "l", maximum=n, why=" (n)")
    if (n - l) % 2:
        raise ValueError(f"n - l must be even, got n = {n}, l = {l}")
    r = np.asarray(rho, dtype=np.float64)
    if not np.all(np.isfinite(r)) or np.any((r < 0) | (r > 1)):
        raise ValueError("rho must lie in [0, 1]")
    flat = np.ascontiguousarray(r.reshape(-1))
    out = np.empty_like(flat)
    _radial_kernel(flat, n, l, out)
    return out.reshape(r.shape)


def _radial_tables(order: int) -> NDArray[np.float64]:
    """Jacobi recurrence coefficients (A, B, C) for every (l, k), k >= 1, by column l.

    R_{k+1} = (A x - B) R_k - C R_{k-1} with x = 2 rho^2 - 1 and, for beta = l,
    D = 2 (k + 1)(k + beta + 1)(2k + beta), A = (2k+beta+1)(2k+beta+2)(2k+beta) / D,
    B = (2k + beta + 1) beta^2 / D, C = 2 k (k + beta)(2k + beta + 2) / D.
    Column l holds entries for k = 0..(order - l)//2 (k = 0 unused) at offset ``_col(l)``.
    """
    out = np.zeros((_col(order, order + 1), 3))
    for l in range(order + 1):
        k = np.arange((order - l) // 2 + 1, dtype=np.float64)
        b = float(l)
        with np.errstate(divide="ignore", invalid="ignore"):
            d = 2 * (k + 1) * (k + b + 1) * (2 * k + b)
            out[_col(order, l):_col(order, l) + k.size, 0] = (
                (2 * k + b + 1) * (2 * k + b + 2) * (2 * k + b) / d)
            out[_col(order, l):_col(order, l) + k.size, 1] = (2 * k + b + 1) * b * b / d
            out[_col(order, l):_col(order, l) + k.size, 2] = 2 * k * (k + b) * (2 * k + b + 2) / d
        out[_col(order, l)] = 0.0  # k = 0 is seeded in closed form
    return out


def _col(order: int, l: int) -> int:
    """Start of column l in the coefficient table: sum over j < l of ((order - j)//2 + 1)."""
    j = np.arange(l)
    return int(np.sum((order - j) // 2 + 1))


@njit
def _radial_kernel(rho, n, l, out):
    # rho (p,) in [0, 1]; out (p,)
    b = float(l)
    for i in range(rho.size):
        r2 = rho[i] * rho[i]
        x = 2.0 * r2 - 1.0
        rl = rho[i] ** l if l > 0 else 1.0
        r_prev = 0.0
        r = rl
        for k in range(1, (n - l) // 2 + 1):
            if k == 1:
                rn = ((b + 2.0) * r2 - (b + 1.0)) * rl
            else:
                kk = k - 1.0
                d = 2.0 * (kk + 1.0) * (kk + b + 1.0) * (2.0 * kk + b)
                rn = (((2 * kk + b + 1) * (2 * kk + b + 2) * (2 * kk + b) / d) * x
                      - (2 * kk + b + 1) * b * b / d) * r \
                    - (2 * kk * (kk + b) * (2 * kk + b + 2) / d) * r_prev
            r_prev = r
            r = rn
        out[i] = r


@njit(inline="always")
def _disk(dirs, i):
    # rho^2, rho and the unit azimuth (cos phi, sin phi) of direction i, renormalised
    x = dirs[i, 0]
    y = dirs[i, 1]
    z = dirs[i, 2]
    r = np.sqrt(x * x + y * y + z * z)
    x /= r
    y /= r
    z /= r
    s2 = x * x + y * y
    s = np.sqrt(s2)
    if s > 0.0:
        c1 = x / s
        s1 = y / s
    else:
        c1 = 1.0
        s1 = 0.0
    rho2 = s2 / (1.0 + z) if z > -0.5 else 1.0 - z
    return rho2, np.sqrt(rho2), c1, s1


#: Fewest directions per part of run_parallel (scratch arrays are allocated and the column
#: tables filled once per part); a multiple of LANES.
_TASK = 128 * LANES

# _zernike_lanes keeps R in _RBUF buffers, row n in buffer (n // 2) % _RBUF, so that rows
# n - 2 _RBUF + 1 .. n are all held once row n is known (rows 2j and 2j + 1 share buffer
# j % _RBUF at entries of opposite parity, and a row overwrites only entries of its own
# parity: those of the row 2 _RBUF before it). A tile of LANES consecutive columns that
# row n completes reaches back LANES - 1 columns: at most four rows for eight lanes (rows
# 0..3 hold ten columns), six for sixteen (rows 0..5 hold 21)
_RBUF = 2 if LANES <= 8 else 3
if LANES > 16:
    raise RuntimeError(f"the Zernike lane kernel supports at most 16 lanes, got {LANES}")


@njit
def _zernike_point(dirs, i, order, coef, norm, row):
    # The reference evaluation of one direction, l by l along each radial recurrence;
    # _zernike_lanes gives its bits. row (size,), position of (n, l) = n(n+1)/2 + (l + n)/2.
    rho2, rho, c1, s1 = _disk(dirs, i)
    xx = 2.0 * rho2 - 1.0
    rll = 1.0
    cl = 1.0
    sl = 0.0
    col = 0
    for l in range(order + 1):
        if l > 0:
            rll *= rho
            t = cl * c1 - sl * s1
            sl = sl * c1 + cl * s1
            cl = t
        fl = float(l)
        nk = (order - l) // 2 + 1
        fc = _INV_SQRT2 if l == 0 else cl  # zonal: one function per n
        # k = 0: R_l^l = rho^l; positions of (n, +l) and (n, -l) move by 2n + 4 per k
        n = l
        kc = (l * (l + 1)) // 2 + l
        ks = kc - l
        v = rll * norm[n]
        row[kc] = v * fc
        if l > 0:
            row[ks] = v * sl
        r_prev = 0.0
        rr = rll
        for k in range(1, nk):
            if k == 1:  # closed form
                rn = ((fl + 2.0) * rho2 - (fl + 1.0)) * rll
            else:
                a = coef[col + k - 1, 0]
                b = coef[col + k - 1, 1]
                c = coef[col + k - 1, 2]
                rn = (a * xx - b) * rr - c * r_prev
            r_prev = rr
            rr = rn
            kc += 2 * n + 4
            ks += 2 * n + 4
            n += 2
            v = rr * norm[n]
            row[kc] = v * fc
            if l > 0:
                row[ks] = v * sl
        col += nk


@njit
def _zernike_lanes(first, stop, dirs, order, coef, start, norm, out):
    # Blocks first .. stop - 1 of LANES directions (run_parallel): directions lo..hi-1 in
    # blocks of LANES that run the radial recurrences together, row n
    # by row n (the output order), each step one <LANES x double> operation (basis.jit).
    # Scratch is lane-fastest (entry r of lane j at r * LANES + j):
    #   ang: the angular factor of (n, l) at entry order + l for every signed l: sin(|l| phi)
    #        below order, 1/sqrt(2) at order, cos(l phi) above;
    #   seed: rho^l at entry l;
    #   rr: _RBUF buffers, R_n^l at entry l of buffer (n // 2) % _RBUF; R_{n-2} and R_{n-4}
    #       in the buffers before it (cyclically). With two, R_{n-4}^l is in the one written,
    #       which the step overwrites in place (buffers chosen by offset: swapping arrays in a
    #       loop would cost numba an atomic reference count each time).
    # Columns leave LANES at a time as soon as their R are known: lane_tile forms
    # (norm R) * angle for LANES consecutive columns and stores them transposed, LANES values
    # into each of LANES output rows. Where column k finds its R, angle and norm (ix[k],
    # iy[k], f[k]) is the same for every block. A tile spans at most 2 _RBUF rows
    # (n - 2 _RBUF + 1..n), whose R are all still in rr (so does the last tile, shifted to
    # end at the last column). A last partial block takes _zernike_point; the blocks give
    # its bits (same operations in the same order). out must be C-contiguous: the tiles
    # address it by flat index.
    lo = first * LANES
    hi = min(dirs.shape[0], stop * LANES)
    nl = order + 1
    size = out.shape[1]
    flat = out.reshape(out.size)
    z0 = order * LANES
    rho2 = np.empty(LANES)
    rho = np.empty(LANES)
    xx = np.empty(LANES)
    c1 = np.empty(LANES)
    s1 = np.empty(LANES)
    ones = np.ones(LANES)
    # two more entries of ang hold 1 and 0, the start of the recurrence; these and the
    # zonal entry are the same for every block, as is seed[0] = rho^0
    e1 = (2 * order + 1) * LANES
    ang = np.empty(e1 + 2 * LANES)
    seed = np.empty(nl * LANES)
    for j in range(LANES):
        ang[z0 + j] = _INV_SQRT2
        ang[e1 + j] = 1.0
        ang[e1 + LANES + j] = 0.0
        seed[j] = 1.0
    rr = np.empty(_RBUF * nl * LANES)
    ix = np.empty(size, dtype=np.int64)
    iy = np.empty(size, dtype=np.int64)
    f = np.empty(size)
    k = 0
    for n in range(nl):
        for l in range(-n, n + 1, 2):
            ix[k] = ((n // 2) % _RBUF) * nl * LANES + abs(l) * LANES
            iy[k] = z0 + l * LANES
            f[k] = norm[n]
            k += 1
    nfull = (hi - lo) // LANES
    for i in range(lo + nfull * LANES, hi):
        _zernike_point(dirs, i, order, coef, norm, out[i])
    for blk in range(nfull):
        i0 = lo + blk * LANES
        lane_disk(dirs, i0, rho2, rho, c1, s1)
        # only vector stores feed vector loads: a vector load of scalar stores waits for them
        # to reach the cache
        lane_affine(xx, 0, 2.0, rho2, 0, 1.0, ones, 0)  # 2 rho^2 - 1
        for l in range(1, nl):
            lane_mul(seed, l * LANES, seed, (l - 1) * LANES, rho, 0)
            r = l * LANES
            if l == 1:  # from cos 0 = 1, sin 0 = 0
                lane_turn(ang, z0 + r, e1, z0 - r, e1 + LANES, c1, s1)
            else:
                lane_turn(ang, z0 + r, z0 + r - LANES, z0 - r, z0 - r + LANES, c1, s1)
        done = 0  # columns of the block already in out
        for n in range(nl):
            # offsets of R_n, R_{n-2} and R_{n-4} in rr
            cur = ((n // 2) % _RBUF) * nl * LANES
            prv = ((n // 2 + _RBUF - 1) % _RBUF) * nl * LANES
            old = ((n // 2 + _RBUF - 2) % _RBUF) * nl * LANES
            r = n * LANES
            lane_mul(rr, cur + r, seed, r, ones, 0)  # k = 0: R_n^n = rho^n
            if n >= 2:  # k = 1, closed form
                r = (n - 2) * LANES
                lane_affine(rr, cur + r, n + 0.0, rho2, 0, n - 1.0, seed, r)
            for k in range(2, n // 2 + 1):
                l = n - 2 * k
                t = start[l] + k - 1
                r = l * LANES
                lane_jacobi(rr, cur + r, coef[t, 0], xx, 0, coef[t, 1], rr, prv + r,
                            coef[t, 2], rr, old + r)
            while done + LANES <= (n + 1) * (n + 2) // 2:  # row n ends there
                lane_tile(flat, i0 * size + done, size, rr, ix, ang, iy, f, done)
                done += LANES
        if done < size and size >= LANES:
            # the last columns as a tile overlapping the one before (same values written
            # twice) rather than scalar stores into lines the tiles have written
            lane_tile(flat, i0 * size + size - LANES, size, rr, ix, ang, iy, f, size - LANES)
        else:
            for j in range(LANES):
                for q in range(done, size):
                    out[i0 + j, q] = (f[q] * rr[ix[q] + j]) * ang[iy[q] + j]


@njit
def _zernike_pairs(first, stop, dirs, order, coef, start, norm, out):
    # Blocks first .. stop - 1 of LANES directions (run_parallel): directions lo..hi-1 for
    # low orders, where a block of LANES has too little work to
    # hide the latency of its lane operations: the geometry, cos(l phi), sin(l phi) and
    # rho^l run lane-wise (lane_disk, lane_rotate), then the radial recurrences of two
    # directions at a time in scalar code, l by l, each value written straight to its row
    # (two independent chains of dependent multiplications keep the FPU busy). Same
    # operations as _zernike_point, so the same bits; a last partial block takes it.
    lo = first * LANES
    hi = min(dirs.shape[0], stop * LANES)
    nl = order + 1
    rho2 = np.empty(LANES)
    rho = np.empty(LANES)
    c1 = np.empty(LANES)
    s1 = np.empty(LANES)
    cc = np.empty(nl * LANES)
    ss = np.empty(nl * LANES)
    seed = np.empty(nl * LANES)
    for j in range(LANES):  # l = 0, the same for every block
        cc[j] = 1.0
        ss[j] = 0.0
        seed[j] = 1.0
    nfull = (hi - lo) // LANES
    for i in range(lo + nfull * LANES, hi):
        _zernike_point(dirs, i, order, coef, norm, out[i])
    for blk in range(nfull):
        i0 = lo + blk * LANES
        lane_disk(dirs, i0, rho2, rho, c1, s1)
        for l in range(1, nl):
            lane_rotate(cc, ss, seed, l * LANES, c1, s1, 1.0, rho)
        for j in range(0, LANES, 2):
            row = out[i0 + j]
            rowb = out[i0 + j + 1]
            r2 = rho2[j]
            r2b = rho2[j + 1]
            xx = 2.0 * r2 - 1.0
            xxb = 2.0 * r2b - 1.0
            for l in range(nl):
                e = l * LANES + j
                rll = seed[e]
                rllb = seed[e + 1]
                if l == 0:  # zonal: one function per n
                    fc = _INV_SQRT2
                    fcb = _INV_SQRT2
                else:
                    fc = cc[e]
                    fcb = cc[e + 1]
                sl = ss[e]
                slb = ss[e + 1]
                fl = float(l)
                # k = 0: R_l^l = rho^l; positions of (n, +l) and (n, -l) move by 2n + 4 per k
                n = l
                kc = (l * (l + 1)) // 2 + l
                ks = kc - l
                v = rll * norm[n]
                vb = rllb * norm[n]
                row[kc] = v * fc
                rowb[kc] = vb * fcb
                if l > 0:
                    row[ks] = v * sl
                    rowb[ks] = vb * slb
                r_prev = 0.0
                r_prevb = 0.0
                rr = rll
                rrb = rllb
                col = start[l]
                for k in range(1, (order - l) // 2 + 1):
                    if k == 1:  # closed form
                        rn = ((fl + 2.0) * r2 - (fl + 1.0)) * rll
                        rnb = ((fl + 2.0) * r2b - (fl + 1.0)) * rllb
                    else:
                        a = coef[col + k - 1, 0]
                        b = coef[col + k - 1, 1]
                        c = coef[col + k - 1, 2]
                        rn = (a * xx - b) * rr - c * r_prev
                        rnb = (a * xxb - b) * rrb - c * r_prevb
                    r_prev = rr
                    rr = rn
                    r_prevb = rrb
                    rrb = rnb
                    kc += 2 * n + 4
                    ks += 2 * n + 4
                    n += 2
                    v = rr * norm[n]
                    vb = rrb * norm[n]
                    row[kc] = v * fc
                    rowb[kc] = vb * fcb
                    if l > 0:
                        row[ks] = v * sl
                        rowb[ks] = vb * slb
