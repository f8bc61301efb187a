"""What every basis shares: the uniform shape (size, order, degree, azimuthal, eval)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .validation import as_directions, check_bytes, nonneg_int


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
        """Flat position of the function with this degree and signed azimuthal order."""
        hit = np.flatnonzero((self._degree == degree) & (self._azimuthal == azimuthal))
        if hit.size == 0:
            raise ValueError(f"{type(self).__name__}({self._order}) has no function with "
                             f"degree {degree} and azimuthal order {azimuthal}")
        return int(hit[0])

    def truncate(self, order: int) -> Basis:
        """The same kind of basis at a lower order (its functions are a prefix of this one's)."""
        order = nonneg_int(order, "order", maximum=self._order,
                           why=f" (the order of {self!r})")
        return self._with_order(order)

    def _with_order(self, order: int) -> Basis:
        return type(self)(order)

    def eval(self, dirs: ArrayLike) -> NDArray[np.float64]:
        """Evaluate every basis function at the given directions.

        Parameters
        ----------
        dirs : (..., 3) array_like of float
            Unit vectors in the local frame (z is the surface normal). Hemisphere bases require
            z >= 0. Lengths within 1e-6 of one are accepted and renormalised.

        Returns
        -------
        (..., size) ndarray of float64
        """
        d = as_directions(dirs, "dirs", upper=self.domain == "hemisphere")
        batch = d.shape[:-1]
        flat = d.reshape(-1, 3)
        check_bytes(8.0 * flat.shape[0] * self.size,
                    f"evaluating {self!r} at {flat.shape[0]} directions")
        out = np.empty((flat.shape[0], self.size))
        if flat.shape[0]:
            self._eval_flat(flat, out)
        return out.reshape(*batch, self.size)

    def _eval_flat(self, dirs: NDArray[np.float64], out: NDArray[np.float64]) -> None:
        raise NotImplementedError

    def moments(self, weight: str = "cos") -> NDArray[np.float64]:
        """Integrals of each function over the upper hemisphere.

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
    """Start of column m in a table holding, for each m = 0..order, the entries l = m..order."""
    lengths = order + 1 - np.arange(order + 1)
    return np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
