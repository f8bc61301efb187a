"""What every basis shares.

The uniform shape (size, order, degree, azimuthal, eval), the azimuthal block layout and the
radial factors.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .validation import as_directions, check_bytes, nonneg_int


class AzimuthalBlocks(NamedTuple):
    """Positions of a basis' functions grouped by azimuthal order m = 0..order.

    ``cos[m]`` holds the flat positions of the functions with azimuthal order +m (for m = 0,
    the zonal ones) and ``sin[m]`` those with -m (empty for m = 0), each ordered by degree.
    Every basis of this package pairs them: ``cos[m][j]`` and ``sin[m][j]`` share their
    degree and radial factor, so ``len(cos[m]) == len(sin[m])`` for m > 0. An isotropic
    coefficient matrix is block diagonal in this layout, with one block per m.
    """

    cos: tuple[NDArray[np.int64], ...]
    sin: tuple[NDArray[np.int64], ...]

    @property
    def sizes(self) -> NDArray[np.int64]:
        """(order + 1,) number of functions per azimuthal order (cos side)."""
        return np.array([c.size for c in self.cos], dtype=np.int64)


class Basis:
    """Common interface of the spherical and hemispherical bases.

    Subclasses set ``_order``, ``_degree``, ``_azimuthal`` in ``__init__`` and implement
    ``_eval_flat(dirs, out)`` (a numba kernel call) and ``exact_rule()``.

    Functions are ordered by degree (``degree`` is non-decreasing), so the first functions of a
    basis of order N are exactly the basis of any lower order: truncation is a prefix.
    """

    #: "sphere" or "hemisphere": the domain on which the functions are orthonormal.
    domain: str = "sphere"
    #: Short name used in storage and messages.
    kind: str = ""
    #: Largest order accepted by the constructor (documented per class).
    max_order: int = 0
    #: True when every function vanishes on the horizon (z = 0), as Westin's odd hemisphere
    #: harmonics do; then f = q / (cos theta_i cos theta_o) of a ``"f_cos"`` matrix has a
    #: finite limit at grazing angles and is the natural representation.
    vanishes_on_horizon: bool = False

    def __init__(self, order: object, name: str = "order") -> None:
        self._order = nonneg_int(order, name, maximum=self.max_order,
                                 why=f" for {type(self).__name__}")

    # -- the uniform shape ------------------------------------------------------------------
    @property
    def order(self) -> int:
        """Highest degree in the basis (inclusive)."""
        return self._order

    @property
    def size(self) -> int:
        """Number of functions."""
        return int(self._degree.size)

    @property
    def degree(self) -> NDArray[np.int64]:
        """(size,) int array: the degree (l for harmonics, n for Zernike) of each function."""
        return self._degree.copy()

    @property
    def azimuthal(self) -> NDArray[np.int64]:
        """(size,) signed int array: m > 0 for cos(m phi), m < 0 for sin(|m| phi), 0 zonal."""
        return self._azimuthal.copy()

    def index(self, degree: int, azimuthal: int) -> int:
        """Return the flat position of the function with this degree and signed azimuthal order."""
        hit = np.flatnonzero((self._degree == degree) & (self._azimuthal == azimuthal))
        if hit.size == 0:
            raise ValueError(f"{type(self).__name__}({self._order}) has no function with "
                             f"degree {degree} and azimuthal order {azimuthal}")
        return int(hit[0])

    def truncate(self, order: int) -> Basis:
        """Return the same kind of basis at a lower order.

        Its functions are a prefix of this one's.
        """
        order = nonneg_int(order, "order", maximum=self._order,
                           why=f" (the order of {self!r})")
        return self._with_order(order)

    def _with_order(self, order: int) -> Basis:
        return type(self)(order)

    def azimuthal_blocks(self) -> AzimuthalBlocks:
        """Return the azimuthal block layout: positions of the cos(m phi) and sin(m phi) functions.

        Returns
        -------
        AzimuthalBlocks
            ``cos[m]``, ``sin[m]`` for m = 0..max |azimuthal| (read-only int64 arrays).

        Examples
        --------
        >>> from basis import HemiZernike
        >>> blocks = HemiZernike(2).azimuthal_blocks()
        >>> [c.tolist() for c in blocks.cos], [s.tolist() for s in blocks.sin]
        ([[0, 4], [2], [5]], [[], [1], [3]])
        """
        cached = self.__dict__.get("_blocks_cache")
        if cached is None:
            az = self._azimuthal
            top = int(np.max(np.abs(az))) if az.size else -1
            cos = tuple(np.flatnonzero(az == m) for m in range(top + 1))
            sin = tuple(np.flatnonzero(az == -m) if m else np.empty(0, np.int64)
                        for m in range(top + 1))
            for a in (*cos, *sin):
                a.flags.writeable = False
            cached = self.__dict__["_blocks_cache"] = AzimuthalBlocks(cos, sin)
        return cached

    def radial(self, z: ArrayLike) -> NDArray[np.float64]:
        """Evaluate the radial factors P_k(z) of every function.

        Each function factors as b_k(theta, phi) = P_k(cos theta) A_k(phi).

        Parameters
        ----------
        z : (n,) array_like of float
            cos(theta), in [0, 1] for hemisphere bases and [-1, 1] for the sphere.

        Returns
        -------
        (n, size) ndarray of float64
            The value at the azimuth where A_k = 1: A_k is 1 for zonal functions,
            cos(m phi) for azimuthal order m > 0 and sin(|m| phi) for m < 0 (with the
            sqrt(2) or other normalisation inside P_k). A sin function has the radial factor
            of the cos function of the same degree and |m| (see :meth:`azimuthal_blocks`),
            so one evaluation at phi = 0 gives them all.

        Examples
        --------
        >>> import numpy as np
        >>> from basis import HemiZernike
        >>> zb = HemiZernike(3)
        >>> w = np.array([0.6 * np.cos(0.4), 0.6 * np.sin(0.4), 0.8])
        >>> ang = np.where(zb.azimuthal > 0, np.cos(zb.azimuthal * 0.4),
        ...                np.where(zb.azimuthal < 0, np.sin(-zb.azimuthal * 0.4), 1.0))
        >>> bool(np.allclose(zb.radial([0.8])[0] * ang, zb.eval(w), atol=1e-14))
        True
        """
        try:
            zz = np.asarray(z, dtype=np.float64)
        except (TypeError, ValueError):
            raise TypeError(f"z must be an array of floats, got {type(z).__name__}") from None
        if zz.ndim != 1:
            raise ValueError(f"z must be one-dimensional, got shape {zz.shape}")
        lo = 0.0 if self.domain == "hemisphere" else -1.0
        if not np.all(np.isfinite(zz)) or np.any((zz < lo) | (zz > 1.0)):
            raise ValueError(f"z must lie in [{lo:g}, 1] for {self!r}")
        s = np.sqrt((1.0 - zz) * (1.0 + zz))
        out = self.eval(np.stack([s, np.zeros_like(zz), zz], axis=-1))
        blocks = self.azimuthal_blocks()
        for c, si in zip(blocks.cos[1:], blocks.sin[1:], strict=True):
            out[:, si] = out[:, c]
        return out

    def eval(self, dirs: ArrayLike, *,
             out: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """Evaluate every basis function at the given directions.

        Parameters
        ----------
        dirs : (..., 3) array_like of float
            Unit vectors in the local frame (z is the surface normal). Hemisphere bases require
            z >= 0. Lengths within 1e-6 of one are accepted and renormalised.
        out : (..., size) ndarray of float64, optional
            C-contiguous array to write the values to (and return), e.g. a buffer reused
            across batches of the same size; every element is overwritten.

        Returns
        -------
        (..., size) ndarray of float64
            ``out`` when given.
        """
        d = as_directions(dirs, "dirs", upper=self.domain == "hemisphere")
        batch = d.shape[:-1]
        flat = d.reshape(-1, 3)
        if out is None:
            check_bytes(8.0 * flat.shape[0] * self.size,
                        f"evaluating {self!r} at {flat.shape[0]} directions")
            res = np.empty((flat.shape[0], self.size))
        else:
            if not isinstance(out, np.ndarray) or out.dtype != np.float64 or \
                    out.shape != (*batch, self.size) or not out.flags.c_contiguous or \
                    not out.flags.writeable:
                got = f"{out.dtype} array of shape {out.shape}" \
                    if isinstance(out, np.ndarray) else type(out).__name__
                raise ValueError(f"out must be a writable C-contiguous float64 array of shape "
                                 f"{(*batch, self.size)}, got {got}")
            res = out.reshape(flat.shape[0], self.size)
        if flat.shape[0]:
            self._eval_flat(flat, res)
        return res.reshape(*batch, self.size) if out is None else out

    def _eval_flat(self, dirs: NDArray[np.float64], out: NDArray[np.float64]) -> None:
        raise NotImplementedError

    def moments(self, weight: str = "cos") -> NDArray[np.float64]:
        """Integrate each function over the upper hemisphere.

        Parameters
        ----------
        weight : {"cos", "none"}
            ``"cos"``: int_H b_k(w) cos(theta) dw; ``"none"``: int_H b_k(w) dw.

        Returns
        -------
        (size,) ndarray of float64
            Computed with a rule that is exact for these integrands (the zonal functions are
            polynomials in cos(theta) or, for full-sphere harmonics restricted to the
            hemisphere, still polynomials in z; all others vanish by azimuthal symmetry).
        """
        from .quadrature import hemisphere_rule

        if weight not in ("cos", "none"):
            raise ValueError(f"weight must be 'cos' or 'none', got {weight!r}")
        # degree <= order + 1 in z, and azimuthal degree <= order: exact with these sizes
        rule = hemisphere_rule(self._order // 2 + 2, self._order + 1)
        w = rule.weights * (rule.points[:, 2] if weight == "cos" else 1.0)
        out = w @ self.eval(rule.points)
        out[self._azimuthal != 0] = 0.0  # exact zeros, not rounding noise
        return out

    # -- identity -----------------------------------------------------------------------
    def _key(self) -> tuple:
        return (type(self).__name__, self._order)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Basis) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self._order})"


def triangular_offsets(order: int) -> NDArray[np.int64]:
    """Return the start of column m in a table of the entries l = m..order for m = 0..order."""
    lengths = order + 1 - np.arange(order + 1)
    return np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
