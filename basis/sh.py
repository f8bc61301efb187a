"""Real spherical harmonics on the sphere and their parity restrictions to the hemisphere.

Convention: orthonormal on the sphere, no Condon-Shortley phase, m > 0 uses
cos(m phi), m < 0 uses sin(|m| phi); the same values as pyshtools with normalization='ortho',
csphase=1, kind='real'. Flat index of (l, m) in the full basis: l*l + l + m.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._base import Basis, triangular_offsets
from .jit import njit, pjit, prange
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

    @property
    def lmax(self) -> int:
        """Highest degree (same as ``order``)."""
        return self._order

    def _eval_flat(self, dirs: NDArray[np.float64], out: NDArray[np.float64]) -> None:
        _sh_kernel(dirs, self._order, _PARITY_CODE[self._parity], self._norm,
                   self._a, self._b, self._d, triangular_offsets(self._order), out)


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


@pjit
def _sh_kernel(dirs, lmax, parity, norm, a, b, d, off, out):
    # dirs (n, 3) float64 ~unit vectors; a, b (T,) recurrence tables by column m, d (lmax+1,)
    # sectoral factors, off (lmax+1,) column starts; out (n, size) with size fixed by parity.
    n = dirs.shape[0]
    sqrt2 = np.sqrt(2.0)
    for i in prange(n):
        x = dirs[i, 0]
        y = dirs[i, 1]
        z = dirs[i, 2]
        r = np.sqrt(x * x + y * y + z * z)
        x /= r
        y /= r
        z /= r
        s = np.sqrt(x * x + y * y)
        if s > 0.0:
            c1 = x / s
            s1 = y / s
        else:
            c1 = 1.0
            s1 = 0.0
        row = out[i]
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


@njit(inline="always")
def _store(row, l, m, p, fc, fs, parity):
    if parity == 2 or (l + m) % 2 == parity:
        if m == 0:
            row[_pos(l, 0, parity)] = p * fc
        else:
            row[_pos(l, m, parity)] = p * fc
            row[_pos(l, -m, parity)] = p * fs
