"""Helmholtz surface scattering modes: reciprocal product functions on H x H.

Koenderink, van Doorn & Stavridi (1996) expand a BRDF in products K_a(w_i) K_b(w_o) of the
hemisphere functions of :class:`basis.HemiZernike` and keep only the symmetrised products,
which makes every expansion reciprocal; for isotropic surfaces they keep the combinations
that depend on the azimuths only through cos(l (phi_i - phi_o)).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .validation import as_directions, broadcast_batch, check_bytes, nonneg_int
from .zernike import HemiZernike

_R2 = float(np.sqrt(2.0))


class HelmholtzModes:
    """Orthonormal reciprocal modes on H x H built from hemisphere Zernike functions.

    Parameters
    ----------
    order : int
        Highest radial degree n of the hemisphere functions, inclusive (0 <= order <= 60 when
        ``isotropic``, <= 24 otherwise; beyond that a single evaluation row alone runs to
        hundreds of thousands of modes: use :class:`basis.CoefficientMatrix` instead).
    isotropic : bool
        True: modes that depend on the azimuths only through cos(l (phi_i - phi_o)) (surfaces
        whose BRDF depends on |phi_i - phi_o|). False: the general reciprocal set.

    Attributes
    ----------
    size : int
        Number of modes: 5, 14, 55, 285 for orders 2, 4, 8, 16 when isotropic, and
        S (S + 1) / 2 with S = (order+1)(order+2)/2 for the general set.
    indices : (size, 3) int array when isotropic, (size, 4) otherwise
        Isotropic: (n, m, l) with n >= m >= l >= 0, n - l and m - l even (n, m radial degrees
        of the two factors, l the azimuthal order), ordered lexicographically. General:
        (n_a, l_a, n_b, l_b) of the two hemisphere functions a <= b (signed l as in
        ``HemiZernike.azimuthal``), ordered by b then a. Both orders make the modes of a lower
        order a prefix.

    Notes
    -----
    With k_n^l(theta) = sqrt((n + 1)/(2 pi)) R_n^l(sqrt(2) sin(theta/2)), the isotropic mode is

        S_nm^l = c [k_n^l(theta_i) k_m^l(theta_o) + k_m^l(theta_i) k_n^l(theta_o)] cos(l dphi),

    dphi = phi_i - phi_o, with c = 1/2 when n = m and l = 0, 1/sqrt(2) when n = m or l = 0 (but
    not both), and 1 otherwise; this makes the modes orthonormal with respect to
    d omega_i d omega_o, which the tests verify by exact quadrature. The general modes are
    K_a(w_i) K_a(w_o) and (K_a(w_i) K_b(w_o) + K_b(w_i) K_a(w_o)) / sqrt(2).

    Where this disagrees with Koenderink, van Doorn & Stavridi (1996, sec. 3.2-3.3): the
    paper's S_nm^l omits c, so its modes are orthogonal but have norms 2, sqrt(2), sqrt(2), 1
    in the four cases above (``paper_norms`` returns them); its printed
    S_20^0 = sqrt(3)/pi (cos theta_1 + cos theta_2 - 1) has the opposite sign to
    R_2^0 = 2 rho^2 - 1 = 1 - 2 cos theta (the correct unnormalised mode is
    sqrt(3)/pi (1 - cos theta_1 - cos theta_2)), and its printed
    S_22^0 = (3/pi)(1 + cos theta_1)(1 + cos theta_2) is not a mode at all: the correct one is
    (3/pi)(1 - 2 cos theta_1)(1 - 2 cos theta_2). S_00^0 = 1/pi, S_11^1 and S_22^2 as printed
    agree with the unnormalised form. The paper also prints the hemisphere normalisation as
    sqrt((2n + 1)/2); it is sqrt((n + 1)/(2 pi)) (see :class:`basis.HemiZernike`).

    Examples
    --------
    >>> [HelmholtzModes(k).size for k in (2, 4, 8, 16)]
    [5, 14, 55, 285]
    >>> HelmholtzModes(2).indices.tolist()
    [[0, 0, 0], [1, 1, 1], [2, 0, 0], [2, 2, 0], [2, 2, 2]]
    """

    max_order_isotropic = 60
    max_order_general = 24

    def __init__(self, order: int, isotropic: bool = True) -> None:
        if not isinstance(isotropic, (bool, np.bool_)):
            raise TypeError(f"isotropic must be True or False, got {isotropic!r}")
        self.isotropic = bool(isotropic)
        limit = self.max_order_isotropic if self.isotropic else self.max_order_general
        self._order = nonneg_int(order, "order", maximum=limit,
                                 why=f" for {'isotropic' if self.isotropic else 'general'} "
                                     "HelmholtzModes")
        self.hemisphere = HemiZernike(self._order)
        if self.isotropic:
            self._build_isotropic()
        else:
            self._build_general()

    def _build_isotropic(self) -> None:
        rows = [(n, m, l) for n in range(self._order + 1) for m in range(n + 1)
                for l in range(m + 1) if (n - l) % 2 == 0 and (m - l) % 2 == 0]
        self._indices = np.array(rows, dtype=np.int64).reshape(-1, 3)
        n, m, l = self._indices.T
        pos = _zernike_position
        self._p1, self._q1 = pos(n, l), pos(m, l)
        self._p2, self._q2 = pos(n, -l), pos(m, -l)
        self._w1 = np.where(n == m, 0.5, 1.0 / _R2)
        self._w1 = np.where(l == 0, self._w1, np.where(n == m, 0.5 / _R2, 0.5))
        self._w2 = np.where(l == 0, 0.0, self._w1)

    def _build_general(self) -> None:
        s = self.hemisphere.size
        a, b = np.triu_indices(s)  # a <= b; reordered by b then a below
        order = np.lexsort((a, b))
        a, b = a[order], b[order]
        deg, az = self.hemisphere.degree, self.hemisphere.azimuthal
        self._indices = np.stack([deg[a], az[a], deg[b], az[b]], axis=1)
        self._p1, self._q1 = a, b
        self._p2, self._q2 = a, b
        self._w1 = np.where(a == b, 0.5, 1.0 / _R2)
        self._w2 = np.zeros_like(self._w1)
        self._pairs = np.stack([a, b], axis=1)

    @property
    def order(self) -> int:
        """Highest radial degree, inclusive."""
        return self._order

    @property
    def size(self) -> int:
        """Number of modes."""
        return int(self._indices.shape[0])

    @property
    def indices(self) -> NDArray[np.int64]:
        """(size, 3) array of (n, m, l) when isotropic; (size, 4) of (n_a, l_a, n_b, l_b)."""
        return self._indices.copy()

    @property
    def pairs(self) -> NDArray[np.int64]:
        """(size, 2) positions (a, b), a <= b, in ``hemisphere`` of the two factors."""
        if self.isotropic:
            return np.stack([self._q1, self._p1], axis=1)
        return self._pairs.copy()

    @property
    def paper_norms(self) -> NDArray[np.float64]:
        """L2 norms of the unnormalised S_nm^l of Koenderink et al. 1996 (isotropic modes only)."""
        if not self.isotropic:
            raise ValueError("paper_norms is defined for the isotropic modes only")
        n, m, l = self._indices.T
        return np.where(n == m, np.where(l == 0, 2.0, _R2), np.where(l == 0, _R2, 1.0))

    def eval(self, wi: ArrayLike, wo: ArrayLike) -> NDArray[np.float64]:
        """Evaluate every mode at pairs of directions.

        Parameters
        ----------
        wi, wo : (..., 3) array_like of float
            Unit vectors in the upper hemisphere; their batch shapes must broadcast.

        Returns
        -------
        (..., size) ndarray of float64
            Symmetric under exchanging ``wi`` and ``wo``.
        """
        wi = as_directions(wi, "wi", upper=True)
        wo = as_directions(wo, "wo", upper=True)
        shape = broadcast_batch(wi, wo)
        check_bytes(8.0 * 3 * int(np.prod(shape)) * self.size,
                    f"evaluating {self!r} at {int(np.prod(shape))} direction pairs")
        ki = self.hemisphere.eval(wi)
        ko = self.hemisphere.eval(wo)
        out = ki[..., self._p1] * ko[..., self._q1] + ki[..., self._q1] * ko[..., self._p1]
        out *= self._w1
        if self.isotropic:
            out += self._w2 * (ki[..., self._p2] * ko[..., self._q2]
                               + ki[..., self._q2] * ko[..., self._p2])
        return out

    def __repr__(self) -> str:
        return f"HelmholtzModes({self._order}, isotropic={self.isotropic})"

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, HelmholtzModes) and other._order == self._order
                and other.isotropic == self.isotropic)

    def __hash__(self) -> int:
        return hash(("HelmholtzModes", self._order, self.isotropic))


def _zernike_position(n: NDArray, l: NDArray) -> NDArray[np.int64]:
    """Flat index of K_n^l (signed l) in HemiZernike: n(n+1)/2 + (n + l)/2."""
    return (n * (n + 1) // 2 + (n + l) // 2).astype(np.int64)
