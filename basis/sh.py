"""Real spherical harmonics on the sphere and their parity restrictions to the hemisphere.

Convention: orthonormal on the sphere, no Condon-Shortley phase, m > 0 uses
cos(m phi), m < 0 uses sin(|m| phi); the same values as pyshtools with normalization='ortho',
csphase=1, kind='real'. Flat index of (l, m) in the full basis: l*l + l + m.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._base import Basis, triangular_offsets
from .jit import (
    LANES,
    lane_mul,
    lane_recur,
    lane_rotate,
    lane_scaled,
    lane_transpose,
    lane_unit,
    njit,
    run_parallel,
    writable,
)
from .quadrature import HemisphereRule, hemisphere_rule, sphere_rule
from .validation import choice

# Values are carried as mantissa * 2**exponent while they would underflow float64: sin(theta)^m
# reaches 1e-308 for sin(theta) = m/l near the turning point once l is above about 1900, while
# the harmonics it seeds are O(1) further along the recurrence (Holmes & Featherstone 2002).
_TINY = 2.0**-600
_HUGE = 2.0**600
_RESCALE = 600

_PARITY_CODE = {"all": 2, "odd": 1, "even": 0}


class _Harmonics(Basis):
    """Real spherical harmonics of one parity class (all, odd or even l + |m|), degrees 0..lmax.

    The indices, the scaled Legendre recurrence and its kernel, shared by
    :class:`SphericalHarmonics` and :class:`HemiHarmonics`.
    """

    max_order = 2800
    _parity = "all"
    _norm = 1.0

    def __init__(self, lmax: int) -> None:
        super().__init__(lmax, "lmax")
        self._degree, self._azimuthal = _sh_indices(self._order, self._parity)
        self._a, self._b, self._d = _legendre_tables(self._order)
        self._rows = _row_tables(self._order, self._a, self._b)
        self._off = triangular_offsets(self._order)  # start of column m in a, b
        self._smin = _seed_floor(self._order, self._norm)
        # column of each function in the full basis, where the kernel computes it
        self._cols = self._degree * self._degree + self._degree + self._azimuthal

    @property
    def lmax(self) -> int:
        """Highest degree (same as ``order``)."""
        return self._order

    def _eval_flat(self, dirs: NDArray[np.float64], out: NDArray[np.float64]) -> None:
        _eval_harmonics(writable(dirs), self._order, _PARITY_CODE[self._parity], self._norm,
                        self._a, self._b, self._d, self._off, self._rows, self._smin,
                        self._cols, out)


class SphericalHarmonics(_Harmonics):
    """Real orthonormal spherical harmonics on the whole sphere, degrees 0..lmax.

    Parameters
    ----------
    lmax : int
        Highest degree, inclusive, 0 <= lmax <= 2800 (the range over which the scaled
        recurrence has been checked against pyshtools; pyshtools documents the same limit).

    Notes
    -----
    Y_lm(theta, phi) = N_lm P_l^|m|(cos theta) * {1, sqrt(2) cos(m phi), sqrt(2) sin(|m| phi)},
    with N_lm the orthonormal (4 pi) normalisation and no (-1)^m phase. The associated Legendre
    functions are computed by the standard stable three-term recurrence in l for fixed m on
    normalised functions (never factorials), seeded by the sectoral P_mm = prod sqrt((2k+1)/2k)
    sin(theta). Seeds below 2**-600 are carried with a separate binary exponent, so degrees up to
    several thousand stay accurate near the poles. cos(m phi) and sin(m phi) come from repeated
    complex multiplication of (x + i y)/sqrt(x^2 + y^2), whose error grows only linearly in m.

    Examples
    --------
    >>> import numpy as np
    >>> sh = SphericalHarmonics(2)
    >>> sh.size
    9
    >>> y = sh.eval([0.0, 0.0, 1.0])
    >>> bool(np.isclose(y[sh.index(1, 0)], np.sqrt(3 / (4 * np.pi))))
    True
    """

    domain = "sphere"
    kind = "sh"

    def exact_rule(self) -> HemisphereRule:
        """Return a product rule exact for every product of two functions of this basis.

        The rule covers the basis' domain (here the whole sphere).
        """
        return sphere_rule(self._order + 1, 2 * self._order + 1)

    # -- grid transforms (pyshtools, ducc backend) ------------------------------------------
    def grid(self) -> NDArray[np.float64]:
        """Return the directions of the Gauss-Legendre grid of pyshtools, (lmax+1, 2 lmax+1, 3).

        Latitude rows at the zeros of P_{lmax+1}(cos theta) (north to south), longitudes
        2 pi j / (2 lmax + 1). Values sampled there are what :meth:`expand` takes.
        """
        import pyshtools

        zero, _ = pyshtools.expand.SHGLQ(self._order)
        phi = 2.0 * np.pi * np.arange(2 * self._order + 1) / (2 * self._order + 1)
        s = np.sqrt((1.0 - zero) * (1.0 + zero))
        return np.stack(np.broadcast_arrays(s[:, None] * np.cos(phi), s[:, None] * np.sin(phi),
                                            zero[:, None]), axis=-1)

    def expand(self, values: ArrayLike) -> NDArray[np.float64]:
        """Return the coefficients (flat order) of a function sampled on :meth:`grid`.

        Exact for band-limited functions of degree <= lmax (Gauss-Legendre quadrature);
        computed by pyshtools' ``SHExpandGLQ`` (ducc0 backend when installed).

        Parameters
        ----------
        values : (lmax+1, 2 lmax+1) array_like of float
        """
        import pyshtools

        v = np.asarray(values, dtype=np.float64)
        want = (self._order + 1, 2 * self._order + 1)
        if v.shape != want:
            raise ValueError(f"values must have the grid shape {want}, got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError("values must be finite")
        cilm = pyshtools.expand.SHExpandGLQ(np.ascontiguousarray(v), norm=4, csphase=1)
        return self.from_cilm(cilm)

    def synthesize(self, coeffs: ArrayLike) -> NDArray[np.float64]:
        """Evaluate the expansion with these flat coefficients on :meth:`grid`.

        Computed by pyshtools' ``MakeGridGLQ``.
        """
        import pyshtools

        return pyshtools.expand.MakeGridGLQ(self.to_cilm(coeffs), norm=4, csphase=1)

    # -- pyshtools interoperability ---------------------------------------------------------
    def to_cilm(self, coeffs: NDArray[np.float64]) -> NDArray[np.float64]:
        """Convert coefficients in flat order to the pyshtools array ``cilm[2, lmax+1, lmax+1]``.

        Valid for pyshtools with normalization='ortho', csphase=1 (the same functions).
        """
        c = np.asarray(coeffs, dtype=np.float64)
        if c.shape != (self.size,):
            raise ValueError(f"coeffs must have shape ({self.size},), got shape {c.shape}")
        cilm = np.zeros((2, self._order + 1, self._order + 1))
        l, m = self._degree, self._azimuthal
        cilm[0, l[m >= 0], m[m >= 0]] = c[m >= 0]
        cilm[1, l[m < 0], -m[m < 0]] = c[m < 0]
        return cilm

    def from_cilm(self, cilm: NDArray[np.float64]) -> NDArray[np.float64]:
        """Convert a pyshtools array ``cilm[2, L+1, L+1]`` to coefficients in flat order.

        Valid for pyshtools with normalization='ortho', csphase=1 (the same functions).
        """
        c = np.asarray(cilm, dtype=np.float64)
        if c.ndim != 3 or c.shape[0] != 2 or c.shape[1] != c.shape[2] or c.shape[1] <= self._order:
            raise ValueError(f"cilm must have shape (2, L+1, L+1) with L >= {self._order}, "
                             f"got shape {c.shape}")
        l, m = self._degree, self._azimuthal
        return np.where(m >= 0, c[0, l, np.abs(m)], c[1, l, np.abs(m)])


class HemiHarmonics(_Harmonics):
    """sqrt(2) Y_lm with l + |m| odd (or even): real harmonics orthonormal on the hemisphere.

    Parameters
    ----------
    lmax : int
        Highest degree, inclusive (0 <= lmax <= 2800).
    parity : {"odd", "even"}
        ``"odd"`` keeps l + |m| odd: the functions are odd under z -> -z and vanish on the
        horizon. This is Westin et al.'s (1992) odd completion: a hemisphere function f is
        extended to the sphere by f(-z) = -f(z), and only these harmonics survive; the basis
        size is lmax (lmax + 1) / 2. ``"even"`` keeps l + |m| even (size (lmax+1)(lmax+2)/2),
        the even completion.

    Notes
    -----
    Two harmonics of the same parity under z -> -z have an even product, so their hemisphere
    integral is half the sphere integral: sqrt(2) Y_lm is orthonormal on the upper hemisphere.
    Westin's full-sphere coefficients of the completed function are therefore twice the
    coefficients in this basis per direction argument (four times for a BRDF matrix).
    Evaluation is restricted to the upper hemisphere (z >= 0), like every hemisphere basis.

    Examples
    --------
    >>> HemiHarmonics(3).size, HemiHarmonics(3, parity="even").size
    (6, 10)
    """

    domain = "hemisphere"
    _norm = float(np.sqrt(2.0))

    def __init__(self, lmax: int, parity: str = "odd") -> None:
        self._parity = choice(parity, "parity", ("odd", "even"))
        super().__init__(lmax)

    @property
    def vanishes_on_horizon(self) -> bool:
        """True for the odd parity: sqrt(2) Y_lm with l + |m| odd is odd in z, so 0 at z = 0."""
        return self._parity == "odd"

    @property
    def kind(self) -> str:
        """``"harmonics"`` (odd parity) or ``"harmonics-even"``; see :func:`basis.make_basis`."""
        return "harmonics" if self._parity == "odd" else "harmonics-even"

    def _with_order(self, order: int) -> HemiHarmonics:
        return type(self)(order, self._parity)

    @property
    def parity(self) -> str:
        """``"odd"`` or ``"even"``."""
        return self._parity

    def exact_rule(self) -> HemisphereRule:
        """Return a product rule exact for every product of two functions of this basis.

        The rule covers the basis' domain, the upper hemisphere.
        """
        return hemisphere_rule(self._order + 1, 2 * self._order + 1)

    def _key(self) -> tuple:
        return (*super()._key(), self._parity)

    def __repr__(self) -> str:
        return f"HemiHarmonics({self._order}, parity={self._parity!r})"


def _sh_indices(lmax: int, parity: str) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Degree and signed order of each function, ordered by l, then m ascending."""
    l_all = np.repeat(np.arange(lmax + 1), 2 * np.arange(lmax + 1) + 1)
    m_all = np.concatenate([np.arange(-l, l + 1) for l in range(lmax + 1)]).astype(np.int64)
    if parity != "all":
        keep = (l_all + np.abs(m_all)) % 2 == (1 if parity == "odd" else 0)
        l_all, m_all = l_all[keep], m_all[keep]
    return l_all.astype(np.int64), m_all


def _legendre_tables(lmax: int) -> tuple[NDArray, NDArray, NDArray]:
    """Recurrence coefficients, stored by column m (see ``triangular_offsets``).

    P_lm = a_lm z P_{l-1,m} - b_lm P_{l-2,m}, with a_lm = sqrt((4l^2-1)/(l^2-m^2)) and
    b_lm = sqrt((2l+1)((l-1)^2-m^2) / ((2l-3)(l^2-m^2))); d_m = sqrt((2m+1)/(2m)) seeds
    P_mm = d_m sin(theta) P_{m-1,m-1}.
    """
    off = triangular_offsets(lmax)
    a = np.zeros(off[-1] + 1 if lmax >= 0 else 0)
    b = np.zeros_like(a)
    for m in range(lmax + 1):
        l = np.arange(m, lmax + 1, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            am = np.sqrt((4 * l * l - 1) / (l * l - m * m))
            bm = np.sqrt((2 * l + 1) * ((l - 1) ** 2 - m * m) / ((2 * l - 3) * (l * l - m * m)))
        am[0] = 0.0
        bm[0] = 0.0
        if lmax > m:
            am[1] = np.sqrt(2.0 * m + 3.0)
            bm[1] = 0.0
        a[off[m]:off[m] + lmax + 1 - m] = am
        b[off[m]:off[m] + lmax + 1 - m] = bm
    mm = np.arange(1, lmax + 1, dtype=np.float64)
    d = np.concatenate([[0.0], np.sqrt((2 * mm + 1) / (2 * mm))])
    return a, b, d


@njit
def _pos(l, m, parity):
    if parity == 2:
        return l * l + l + m
    if parity == 1:
        return (l * (l - 1)) // 2 + (m + l - 1) // 2
    return (l * (l + 1)) // 2 + (m + l) // 2


#: Fewest directions per part of run_parallel (scratch arrays are allocated once per part);
#: a multiple of LANES.
_TASK = 32 * LANES
#: Below this degree the bases take _sh_pairs (two directions at a time, rows written
#: straight to the output), from it _sh_lanes (measured on one core of an AMD EPYC, AVX2,
#: into a reused output: pairs 1.19x / 1.06x as fast at lmax = 10 / 12, lanes 1.04x / 1.16x
#: at 14 / 16, for the full basis; for one parity class, which the lanes pick from the full
#: basis, the pairs store only the class: 1.23x / 1.36x the lanes at 8 / 12).
_PAIR_LMAX = 13


def _row_tables(lmax: int, a: NDArray, b: NDArray) -> tuple[NDArray, NDArray]:
    """Re-order the recurrence coefficients by row l (entry (l, m) at l (l + 1) / 2 + m)."""
    l, m = np.tril_indices(lmax + 1)
    col = triangular_offsets(lmax)[m] + l - m
    return np.ascontiguousarray(a[col]), np.ascontiguousarray(b[col])


def _seed_floor(lmax: int, norm: float) -> float:
    """Smallest sin(theta) > 0 for which no sectoral seed P_mm, m <= lmax, falls below _TINY.

    P_mm >= norm / sqrt(4 pi) sin(theta)^m since every factor d_m exceeds 1, so above this
    floor the carried exponent is never needed and the fast kernels apply.
    """
    if lmax == 0:
        return 0.0
    p00 = norm / np.sqrt(4.0 * np.pi)
    return float((_TINY / p00) ** (1.0 / lmax)) * (1.0 + 1e-12)


def _eval_harmonics(dirs, lmax, parity, norm, a, b, d, off, rows, smin, cols, out):
    """Evaluate into ``out``; the lane kernel and its per-direction fallback give the same bits."""
    blocks = (dirs.shape[0] + LANES - 1) // LANES
    # each strategy its own kernel, so a program compiles only the ones its degrees use
    if lmax < _PAIR_LMAX:
        run_parallel(_sh_pairs, blocks, dirs, lmax, parity, norm, a, b, d, off, smin, out,
                     grain=_TASK // LANES)
    else:
        run_parallel(_sh_lanes, blocks, dirs, lmax, parity, norm, a, b, d, off, rows[0],
                     rows[1], smin, cols, out, grain=_TASK // LANES)


@njit(inline="always")
def _unit(dirs, i):
    # renormalised z, sin(theta) and the unit azimuth (cos phi, sin phi) of direction i
    x = dirs[i, 0]
    y = dirs[i, 1]
    z = dirs[i, 2]
    r = np.sqrt(x * x + y * y + z * z)
    x /= r
    y /= r
    z /= r
    s = np.sqrt(x * x + y * y)
    if s > 0.0:
        return z, s, x / s, y / s
    return z, s, 1.0, 0.0


@njit
def _sh_point(dirs, i, lmax, parity, norm, a, b, d, off, row):
    # The reference evaluation of one direction, with the carried exponent: every fast kernel
    # falls back to it where a sectoral seed would underflow.
    z, s, c1, s1 = _unit(dirs, i)
    sqrt2 = np.sqrt(2.0)
    cm = sqrt2  # sqrt(2) cos(m phi) and sqrt(2) sin(m phi): the m != 0 normalisation
    sm = 0.0
    pmm = norm / np.sqrt(4.0 * np.pi)
    emm = 0
    for m in range(lmax + 1):
        if m > 0:
            t = cm * c1 - sm * s1
            sm = sm * c1 + cm * s1
            cm = t
            pmm *= d[m] * s
            if pmm < _TINY and pmm != 0.0:
                pmm *= _HUGE
                emm -= _RESCALE
        if m == 0:
            fc = 1.0
            fs = 0.0
        else:
            fc = cm
            fs = sm
        if emm < 0:
            fc *= np.ldexp(1.0, emm)
            fs *= np.ldexp(1.0, emm)
        _store(row, m, m, pmm, fc, fs, parity)
        if m == lmax:
            continue
        base = off[m] - m
        p2 = pmm
        p1 = a[base + m + 1] * z * pmm
        _store(row, m + 1, m, p1, fc, fs, parity)
        e = emm
        for l in range(m + 2, lmax + 1):
            p = a[base + l] * z * p1 - b[base + l] * p2
            p2 = p1
            p1 = p
            if abs(p) > _HUGE:  # only in carried-exponent columns
                p1 *= _TINY
                p2 *= _TINY
                e += _RESCALE
                scale = np.ldexp(1.0, e) if e < 0 else 1.0
                fc = (cm if m else 1.0) * scale
                fs = (sm if m else 0.0) * scale
            _store(row, l, m, p1, fc, fs, parity)


@njit
def _sh_lanes(first, stop, dirs, lmax, parity, norm, a, b, d, off, ra, rb, smin, cols, out):
    # Blocks first .. stop - 1 of LANES directions (run_parallel): directions lo..hi-1, the
    # LANES of a block running the recurrence together, row l by row l, each step one
    # <LANES x double> operation (basis.jit): ra, rb are a, b by row
    # (_row_tables). Scratch is flat and lane-fastest (entry r of lane j at r * LANES + j);
    # buf holds the full basis in flat order for each lane. For the full basis every row's
    # finished columns go out in LANES x LANES transposed tiles while they are still in L1,
    # so the buffer is read once, from cache, and the output rows are written LANES values
    # at a time; one parity class (HemiHarmonics) is picked by cols after the block.
    # A block with a direction needing the carried exponent (0 < sin(theta) < smin), and a
    # last partial block, take _sh_point; the others give its bits (same operations in the
    # same order; an m = 0 value is stored as p * 1.0, as _sh_point stores it). out must be
    # C-contiguous: the tiles address it by flat index.
    lo = first * LANES
    hi = min(dirs.shape[0], stop * LANES)
    sqrt2 = np.sqrt(2.0)
    p00 = norm / np.sqrt(4.0 * np.pi)
    nl = lmax + 1
    kk = nl * nl
    size = out.shape[1]
    zz = np.empty(LANES)
    sn = np.empty(LANES)
    c1 = np.empty(LANES)
    s1 = np.empty(LANES)
    ones = np.ones(LANES)
    cc = np.empty(nl * LANES)
    ss = np.empty(nl * LANES)
    seed = np.empty(nl * LANES)
    pa = np.empty(nl * LANES)
    pb = np.empty(nl * LANES)
    buf = np.empty(kk * LANES)
    nfull = (hi - lo) // LANES
    for i in range(lo + nfull * LANES, hi):
        _sh_point(dirs, i, lmax, parity, norm, a, b, d, off, out[i])
    for blk in range(nfull):
        i0 = lo + blk * LANES
        if lane_unit(dirs, i0, zz, sn, c1, s1, smin):
            for j in range(LANES):
                _sh_point(dirs, i0 + j, lmax, parity, norm, a, b, d, off, out[i0 + j])
            continue
        for j in range(LANES):
            cc[j] = 1.0
            ss[j] = 0.0
            seed[j] = p00
            pa[j] = p00
            buf[j] = p00
            if lmax > 0:
                cc[LANES + j] = sqrt2 * c1[j] - 0.0 * s1[j]
                ss[LANES + j] = 0.0 * c1[j] + sqrt2 * s1[j]
                seed[LANES + j] = p00 * (d[1] * sn[j])
        for m in range(2, nl):
            lane_rotate(cc, ss, seed, m * LANES, c1, s1, d[m], sn)
        p1 = pa
        p2 = pb
        done = 0  # columns of the block already in out
        for l in range(1, nl):
            o = (l * (l + 1)) // 2
            k0 = l * l + l
            if l >= 2:
                lane_recur(p2, 0, zz, 0, p1, 0, p2, 0, ra[o], rb[o])
                lane_mul(buf, k0 * LANES, p2, 0, ones, 0)
                for m in range(1, l - 1):
                    r = m * LANES
                    lane_recur(p2, r, zz, 0, p1, r, p2, r, ra[o + m], rb[o + m])
                    lane_mul(buf, (k0 + m) * LANES, p2, r, cc, r)
                    lane_mul(buf, (k0 - m) * LANES, p2, r, ss, r)
            r = (l - 1) * LANES
            lane_scaled(p2, r, ra[o + l - 1], zz, 0, seed, r)
            if l == 1:
                lane_mul(buf, k0 * LANES, p2, r, ones, 0)
            else:
                lane_mul(buf, (k0 + l - 1) * LANES, p2, r, cc, r)
                lane_mul(buf, (k0 - l + 1) * LANES, p2, r, ss, r)
            r = l * LANES
            lane_mul(p2, r, seed, r, ones, 0)
            lane_mul(buf, (k0 + l) * LANES, seed, r, cc, r)
            lane_mul(buf, (k0 - l) * LANES, seed, r, ss, r)
            t = p1
            p1 = p2
            p2 = t
            if parity == 2:
                while done + LANES <= k0 + l + 1:
                    lane_transpose(out, i0 * size + done, size, buf, done * LANES)
                    done += LANES
        if parity == 2:
            for j in range(LANES):
                for k in range(done, kk):
                    out[i0 + j, k] = buf[k * LANES + j]
        else:
            for j in range(LANES):
                for k in range(size):
                    out[i0 + j, k] = buf[cols[k] * LANES + j]


@njit
def _sh_pairs(first, stop, dirs, lmax, parity, norm, a, b, d, off, smin, out):
    # Blocks first .. stop - 1 of LANES directions (run_parallel): directions lo..hi-1, two
    # per iteration, for lmax < _PAIR_LMAX: the
    # recurrence in l is a chain of dependent multiplications, and two independent chains
    # keep the FPU busy; each row (at most 1.4 KB) is written straight to out, for one
    # parity class (HemiHarmonics) only the functions of that class. The polar
    # coordinates of a block's directions come from lane_unit (its square roots and
    # quotients lane-wise). The loops over l index with unsigned integers, which spares
    # every load and store numba's wraparound of negative indices: that integer work, not
    # the arithmetic, was the loop's bottleneck (1.25x faster at lmax = 8 without it).
    # Same operations in the same order as _sh_point, so the same bits; a direction with
    # 0 < sin(theta) < smin needs the carried exponent and takes _sh_point.
    lo = first * LANES
    hi = min(dirs.shape[0], stop * LANES)
    sqrt2 = np.sqrt(2.0)
    p00 = norm / np.sqrt(4.0 * np.pi)
    zz = np.empty(LANES)
    sn = np.empty(LANES)
    cv = np.empty(LANES)
    sv = np.empty(LANES)
    two = np.uint64(2)
    for i in range(lo, hi, 2):
        j = min(i + 1, hi - 1)  # odd count: the last direction twice, the same values twice
        q = (i - lo) % LANES  # lanes q and q + j - i of the block
        if q == 0:
            if i + LANES <= hi:
                lane_unit(dirs, i, zz, sn, cv, sv, smin)
            else:
                for r in range(hi - i):
                    zz[r], sn[r], cv[r], sv[r] = _unit(dirs, i + r)
        qb = q + j - i
        z, s, c1, s1 = zz[q], sn[q], cv[q], sv[q]
        zb, sb, c1b, s1b = zz[qb], sn[qb], cv[qb], sv[qb]
        if (0.0 < s < smin) or (0.0 < sb < smin):  # a seed needs the carried exponent
            _sh_point(dirs, i, lmax, parity, norm, a, b, d, off, out[i])
            _sh_point(dirs, j, lmax, parity, norm, a, b, d, off, out[j])
            continue
        row = out[i]
        rowb = out[j]
        cm = sqrt2
        sm = 0.0
        pmm = p00
        cmb = sqrt2
        smb = 0.0
        pmmb = p00
        fc = 1.0
        fs = 0.0
        fcb = 1.0
        fsb = 0.0
        for m in range(lmax + 1):
            if m > 0:
                t = cm * c1 - sm * s1
                sm = sm * c1 + cm * s1
                cm = t
                pmm *= d[m] * s
                fc = cm
                fs = sm
                t = cmb * c1b - smb * s1b
                smb = smb * c1b + cmb * s1b
                cmb = t
                pmmb *= d[m] * sb
                fcb = cmb
                fsb = smb
            k = m * m + 2 * m  # position of (l, m) = (m, m); (l, -m) is 2m before
            if parity == 2:
                row[k] = pmm * fc
                rowb[k] = pmmb * fcb
                if m > 0:
                    row[k - 2 * m] = pmm * fs
                    rowb[k - 2 * m] = pmmb * fsb
            else:
                _store(row, m, m, pmm, fc, fs, parity)
                _store(rowb, m, m, pmmb, fcb, fsb, parity)
            if m == lmax:
                continue
            base = off[m] - m
            p2 = pmm
            p1 = a[base + m + 1] * z * pmm
            p2b = pmmb
            p1b = a[base + m + 1] * zb * pmmb
            k += 2 * m + 2
            if parity == 2:
                row[k] = p1 * fc
                rowb[k] = p1b * fcb
                if m > 0:
                    row[k - 2 * m] = p1 * fs
                    rowb[k - 2 * m] = p1b * fsb
            else:
                _store(row, m + 1, m, p1, fc, fs, parity)
                _store(rowb, m + 1, m, p1b, fcb, fsb, parity)
            ku = np.uint64(k)
            bu = np.uint64(base)
            m2 = np.uint64(2 * m)
            if parity != 2:
                # one class: every other degree, (l, m) at _pos(l, m, parity), (l, -m) m
                # places before (an unsigned index: no wraparound)
                um = np.uint64(m)
                up = np.uint64(parity)
                for l in range(np.uint64(m + 2), np.uint64(lmax + 1)):
                    al = a[bu + l]
                    bl = b[bu + l]
                    p = al * z * p1 - bl * p2
                    pb = al * zb * p1b - bl * p2b
                    p2 = p1
                    p1 = p
                    p2b = p1b
                    p1b = pb
                    if (l + um) % two == up:
                        kp = np.uint64(_pos(np.int64(l), m, parity))
                        row[kp] = p * fc
                        rowb[kp] = pb * fcb
                        if m > 0:
                            row[kp - um] = p * fs
                            rowb[kp - um] = pb * fsb
            elif m == 0:
                for l in range(two, np.uint64(lmax + 1)):
                    al = a[bu + l]
                    bl = b[bu + l]
                    p = al * z * p1 - bl * p2
                    pb = al * zb * p1b - bl * p2b
                    p2 = p1
                    p1 = p
                    p2b = p1b
                    p1b = pb
                    ku += two * l
                    row[ku] = p
                    rowb[ku] = pb
            else:
                for l in range(np.uint64(m + 2), np.uint64(lmax + 1)):
                    al = a[bu + l]
                    bl = b[bu + l]
                    p = al * z * p1 - bl * p2
                    pb = al * zb * p1b - bl * p2b
                    p2 = p1
                    p1 = p
                    p2b = p1b
                    p1b = pb
                    ku += two * l
                    row[ku] = p * fc
                    row[ku - m2] = p * fs
                    rowb[ku] = pb * fcb
                    rowb[ku - m2] = pb * fsb


@njit
def _store(row, l, m, p, fc, fs, parity):
    if parity == 2 or (l + m) % 2 == parity:
        if m == 0:
            row[_pos(l, 0, parity)] = p * fc
        else:
            row[_pos(l, m, parity)] = p * fc
            row[_pos(l, -m, parity)] = p * fs
