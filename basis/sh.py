"""Real spherical harmonics on the sphere and their parity restrictions to the hemisphere.

Convention: orthonormal on the sphere, no Condon-Shortley phase, m > 0 uses
cos(m phi), m < 0 uses sin(|m| phi); the same values as pyshtools with normalization='ortho',
csphase=1, kind='real'. Flat index of (l, m) in the full basis: l*l + l + m.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._base import Basis, triangular_offsets
from .jit import njit, pjit, prange, writable
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
        self._smin = _seed_floor(self._order, self._norm)
        # column of each function in the full basis, where the kernel computes it
        self._cols = self._degree * self._degree + self._degree + self._azimuthal

    @property
    def lmax(self) -> int:
        """Highest degree (same as ``order``)."""
        return self._order

    def _eval_flat(self, dirs: NDArray[np.float64], out: NDArray[np.float64]) -> None:
        _eval_harmonics(writable(dirs), self._order, _PARITY_CODE[self._parity], self._norm,
                        self._a, self._b, self._d, self._rows, self._smin, self._cols, out)


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


@njit(inline="always")
def _pos(l, m, parity):
    if parity == 2:
        return l * l + l + m
    if parity == 1:
        return (l * (l - 1)) // 2 + (m + l - 1) // 2
    return (l * (l + 1)) // 2 + (m + l) // 2


#: Points per block of the lane kernel: the recurrence runs over a block's points at once.
_LANES = 8
#: Directions per parallel task (scratch arrays are allocated once per task); even, and a
#: multiple of _LANES.
_TASK = 32 * _LANES
#: Below this degree the full basis takes _sh_pairs (two directions at a time, rows written
#: straight to the output), from it _sh_lanes (measured on two cores: pairs faster at
#: lmax = 8, lanes faster at 12 and above).
_PAIR_LMAX = 12


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


def _eval_harmonics(dirs, lmax, parity, norm, a, b, d, rows, smin, cols, out):
    """Evaluate into ``out``; the lane kernel and its per-direction fallback give the same bits."""
    off = triangular_offsets(lmax)
    _sh_eval_kernel(dirs, lmax, parity, norm, a, b, d, off, rows[0], rows[1], smin, cols, out)


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
def _sh_lanes(dirs, lo, hi, lmax, parity, norm, a, b, d, off, ra, rb, smin, cols, out):
    # Directions lo..hi-1 in blocks of _LANES that run the recurrence together, row l by row
    # l: the innermost loops go over the lanes with a fixed trip count, and the chains of
    # different lanes overlap. ra, rb: a, b by row (_row_tables). Every index is unsigned or
    # a loop counter from 0: numba wraps negative signed indices around, and that test on
    # every access costs more than the arithmetic. Scratch is allocated here, so that its
    # shapes are known to the compiler.
    # A block's values go to buf, the full basis in flat order for each lane (the parity
    # classes of HemiHarmonics are picked by cols when copied out).
    # A block with a direction needing the carried exponent (0 < sin(theta) < smin), and a
    # last partial block, take _sh_point; the others give its bits (same operations in the
    # same order; an m = 0 value is stored as p where _sh_point stores p * 1.0).
    u0 = np.uint64(0)
    u1 = np.uint64(1)
    u2 = np.uint64(2)
    ul = np.uint64(lmax)
    sqrt2 = np.sqrt(2.0)
    p00 = norm / np.sqrt(4.0 * np.pi)
    zz = np.empty(_LANES)
    sn = np.empty(_LANES)
    c1 = np.empty(_LANES)
    s1 = np.empty(_LANES)
    cc = np.empty((lmax + 1, _LANES))
    ss = np.empty((lmax + 1, _LANES))
    seed = np.empty((lmax + 1, _LANES))
    pa = np.empty((lmax + 1, _LANES))
    pb = np.empty((lmax + 1, _LANES))
    buf = np.empty((_LANES, (lmax + 1) * (lmax + 1)))
    nfull = (hi - lo) // _LANES
    for i in range(lo + nfull * _LANES, hi):
        _sh_point(dirs, i, lmax, parity, norm, a, b, d, off, out[i])
    for blk in range(nfull):
        i0 = lo + blk * _LANES
        slow = False
        for j in range(_LANES):
            z, s, cj, sj = _unit(dirs, i0 + j)
            slow |= 0.0 < s < smin
            zz[j] = z
            sn[j] = s
            c1[j] = cj
            s1[j] = sj
        if slow:
            for j in range(_LANES):
                _sh_point(dirs, i0 + j, lmax, parity, norm, a, b, d, off, out[i0 + j])
            continue
        for j in range(_LANES):
            cc[0, j] = 1.0
            ss[0, j] = 0.0
            seed[0, j] = p00
            pa[0, j] = p00
            buf[j, 0] = p00
            if lmax > 0:
                cc[1, j] = sqrt2 * c1[j] - 0.0 * s1[j]
                ss[1, j] = 0.0 * c1[j] + sqrt2 * s1[j]
                seed[1, j] = p00 * (d[1] * sn[j])
        for m in range(u2, ul + u1):
            dm = d[m]
            for j in range(_LANES):
                cm = cc[m - u1, j]
                sm = ss[m - u1, j]
                cc[m, j] = cm * c1[j] - sm * s1[j]
                ss[m, j] = sm * c1[j] + cm * s1[j]
                seed[m, j] = seed[m - u1, j] * (dm * sn[j])
        p1 = pa
        p2 = pb
        for l in range(u1, ul + u1):
            o = (l * (l + u1)) // u2
            k0 = l * l + l
            if l >= u2:
                am = ra[o]
                bm = rb[o]
                for j in range(_LANES):
                    v = am * zz[j] * p1[u0, j] - bm * p2[u0, j]
                    p2[u0, j] = v
                    buf[j, k0] = v
                for m in range(u1, l - u1):
                    am = ra[o + m]
                    bm = rb[o + m]
                    for j in range(_LANES):
                        v = am * zz[j] * p1[m, j] - bm * p2[m, j]
                        p2[m, j] = v
                        buf[j, k0 + m] = v * cc[m, j]
                        buf[j, k0 - m] = v * ss[m, j]
            am = ra[o + l - u1]
            for j in range(_LANES):
                v = am * zz[j] * seed[l - u1, j]
                p2[l - u1, j] = v
                if l == u1:
                    buf[j, k0] = v
                else:
                    buf[j, k0 + l - u1] = v * cc[l - u1, j]
                    buf[j, k0 - l + u1] = v * ss[l - u1, j]
            for j in range(_LANES):
                v = seed[l, j]
                p2[l, j] = v
                buf[j, k0 + l] = v * cc[l, j]
                buf[j, k0 - l] = v * ss[l, j]
            t = p1
            p1 = p2
            p2 = t
        # rows i0..i0+_LANES-1 of out are contiguous: one sequential copy, where writing the
        # values in the order computed would scatter them over _LANES rows. One parity class
        # (HemiHarmonics) takes its columns of the full basis.
        if parity == 2:
            for j in range(_LANES):
                for k in range(out.shape[1]):
                    out[i0 + j, k] = buf[j, k]
        else:
            for j in range(_LANES):
                for k in range(out.shape[1]):
                    out[i0 + j, k] = buf[j, cols[k]]


@njit
def _sh_pairs(dirs, lo, hi, lmax, parity, norm, a, b, d, off, smin, out):
    # Directions lo..hi-1, two per iteration, for parity 2 and lmax < _PAIR_LMAX: the
    # recurrence in l is a chain of dependent multiplications, and two independent chains
    # keep the FPU busy; each row (under 1.2 KB) is written straight to out.
    # Same operations in the same order as _sh_point, so the same bits; a direction with
    # 0 < sin(theta) < smin needs the carried exponent and takes _sh_point.
    sqrt2 = np.sqrt(2.0)
    p00 = norm / np.sqrt(4.0 * np.pi)
    for i in range(lo, hi, 2):
        j = min(i + 1, hi - 1)  # odd count: the last direction twice, the same values twice
        z, s, c1, s1 = _unit(dirs, i)
        zb, sb, c1b, s1b = _unit(dirs, j)
        if parity != 2 or (0.0 < s < smin) or (0.0 < sb < smin):
            # one parity class (HemiHarmonics), or a seed that needs the carried exponent
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
            row[k] = pmm * fc
            rowb[k] = pmmb * fcb
            if m > 0:
                row[k - 2 * m] = pmm * fs
                rowb[k - 2 * m] = pmmb * fsb
            if m == lmax:
                continue
            base = off[m] - m
            p2 = pmm
            p1 = a[base + m + 1] * z * pmm
            p2b = pmmb
            p1b = a[base + m + 1] * zb * pmmb
            k += 2 * m + 2
            row[k] = p1 * fc
            rowb[k] = p1b * fcb
            if m > 0:
                row[k - 2 * m] = p1 * fs
                rowb[k - 2 * m] = p1b * fsb
            if m == 0:
                for l in range(2, lmax + 1):
                    al = a[base + l]
                    bl = b[base + l]
                    p = al * z * p1 - bl * p2
                    pb = al * zb * p1b - bl * p2b
                    p2 = p1
                    p1 = p
                    p2b = p1b
                    p1b = pb
                    k += 2 * l
                    row[k] = p
                    rowb[k] = pb
            else:
                for l in range(m + 2, lmax + 1):
                    al = a[base + l]
                    bl = b[base + l]
                    p = al * z * p1 - bl * p2
                    pb = al * zb * p1b - bl * p2b
                    p2 = p1
                    p1 = p
                    p2b = p1b
                    p1b = pb
                    k += 2 * l
                    row[k] = p * fc
                    row[k - 2 * m] = p * fs
                    rowb[k] = pb * fcb
                    rowb[k - 2 * m] = pb * fsb


@pjit
def _sh_eval_kernel(dirs, lmax, parity, norm, a, b, d, off, ra, rb, smin, cols, out):
    # dirs (n, 3) float64 ~unit vectors; a, b (T,) recurrence tables by column m, ra, rb the
    # same by row l, d (lmax+1,) sectoral factors, off (lmax+1,) column starts; out (n, size)
    # with size fixed by parity; cols (size,) the column of each function in the full basis.
    # One parallel kernel for both strategies, so a cold start compiles it once whatever the
    # degrees used.
    n = dirs.shape[0]
    pairs = parity == 2 and lmax < _PAIR_LMAX
    for task in prange((n + _TASK - 1) // _TASK):
        lo = task * _TASK
        hi = min(n, lo + _TASK)
        if pairs:
            _sh_pairs(dirs, lo, hi, lmax, parity, norm, a, b, d, off, smin, out)
        else:
            _sh_lanes(dirs, lo, hi, lmax, parity, norm, a, b, d, off, ra, rb, smin, cols, out)


@njit(inline="always")
def _store(row, l, m, p, fc, fs, parity):
    if parity == 2 or (l + m) % 2 == parity:
        if m == 0:
            row[_pos(l, 0, parity)] = p * fc
        else:
            row[_pos(l, m, parity)] = p * fc
            row[_pos(l, -m, parity)] = p * fs
