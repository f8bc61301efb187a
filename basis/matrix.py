"""The coefficient matrix that holds a BRDF in a basis.

q(w_i, w_o) = b(w_i)^T M b(w_o). By default M is symmetric, so every representation is
reciprocal whatever its truncation or noise (Westin, Arvo & Torrance 1992, eqs 8-10); with
``reciprocal=False`` M is any real matrix, for measured data that are not reciprocal.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._base import Basis
from .evaluate import Evaluator, lift_to
from .modes import HelmholtzModes
from .validation import as_directions, as_float, check_bytes, choice
from .zernike import HemiZernike

__all__ = ["CoefficientMatrix", "QUANTITIES"]

#: What a matrix represents: the BRDF itself, or f cos(theta_i) cos(theta_o) (the choice of
#: Westin, Arvo & Torrance 1992, sec. 2.5).
QUANTITIES = ("f", "f_cos")

_R2 = float(np.sqrt(2.0))


class CoefficientMatrix:
    """A BRDF held as a matrix of coefficients in a (hemi)spherical basis.

    Parameters
    ----------
    basis : basis.Basis
        The basis of both directions (``HemiZernike``, ``HemiHarmonics`` or
        ``SphericalHarmonics``).
    matrix : (size, size) or (channels, size, size) array_like of float
        Coefficients, rows for w_i and columns for w_o. With ``reciprocal=True`` they must
        be symmetric in the last two axes (relative tolerance ``rtol``) unless
        ``symmetrize`` is set.
    quantity : {"f", "f_cos"}
        ``"f"``: q = f; ``"f_cos"``: q = f cos(theta_i) cos(theta_o).
    symmetrize : bool
        Replace ``matrix`` by (M + M^T) / 2 (use for Monte Carlo or fitted estimates);
        only with ``reciprocal=True``.
    reciprocal : bool
        True (default): M is symmetric, f(w_i, w_o) = f(w_o, w_i). False: M is a general
        real matrix (a non-reciprocal BRDF, e.g. a measurement); nothing is checked or
        symmetrised. Stored in :attr:`reciprocal`.
    isotropic : bool or None
        Storage. None: store in isotropic block form if the matrix is isotropic to ``rtol``,
        densely otherwise. True: require isotropy (raises if the anisotropic part exceeds
        ``rtol``; use :meth:`to_isotropic` to project instead). False: always dense.
    rtol : float
        Tolerance for the symmetry and isotropy checks, relative to max |M|.
    info : dict, optional
        Provenance (source, parameters, method, estimated errors); kept with the matrix and
        written by ``compress.save``.

    Notes
    -----
    Isotropic storage. Every basis function of azimuthal order m > 0 is R(theta) cos(m phi)
    or R(theta) sin(m phi), the two with the same radial factors (ordered alike by degree).
    An isotropic BRDF depends on the azimuths through dphi = phi_i - phi_o only; expand
    q = sum_m [a_m(theta_i, theta_o) cos(m dphi) + c_m(theta_i, theta_o) sin(m dphi)].
    Isotropic materials are also mirror symmetric about the plane of incidence
    (q(dphi) = q(-dphi)), so c_m = 0, and

        cos(m dphi) = cos(m phi_i) cos(m phi_o) + sin(m phi_i) sin(m phi_o)

    makes the cos-cos block equal to the sin-sin block, B_m (rows the radial factors of
    w_i, columns those of w_o), with no cos-sin coupling: M is block diagonal by m with
    blocks B_0, B_1, B_1, B_2, B_2, ... . This needs no reciprocity: B_m is symmetric
    exactly when q(theta_i, theta_o, dphi) = q(theta_o, theta_i, dphi), i.e. when the BRDF
    is reciprocal. So one block per azimuthal order m = 0..order is stored (``blocks[m]``,
    rows and columns ordered by degree): symmetric when ``reciprocal`` (k_m (k_m + 1) / 2
    numbers), general otherwise (k_m^2 numbers). An isotropic BRDF that is not mirror
    symmetric has c_m != 0, which sin(m dphi) = sin(m phi_i) cos(m phi_o) -
    cos(m phi_i) sin(m phi_o) turns into cos-sin blocks C_m and sin-cos blocks -C_m; the
    isotropic storage cannot hold them, and :meth:`to_isotropic` drops them (the orthogonal
    projection onto mirror-symmetric isotropic BRDFs). ``nbytes`` reports the bytes held
    (k_m^2 float64 per block and channel in both cases).

    Examples
    --------
    Lambert with albedo a in Westin's form (Westin, Arvo & Torrance 1992, sec. 2.5) is one
    coefficient: f cos cos =
    (a/pi) z_i z_o = (2a/3) b_10(w_i) b_10(w_o) for the hemisphere harmonic
    b_10 = sqrt(2) Y_10 = sqrt(3/(2 pi)) z.

    >>> import numpy as np
    >>> from basis import HemiHarmonics
    >>> hb = HemiHarmonics(3)
    >>> M = np.zeros((hb.size, hb.size)); k = hb.index(1, 0); M[k, k] = 2 * 0.5 / 3
    >>> cm = CoefficientMatrix(hb, M, quantity="f_cos")
    >>> f = cm.eval([0, 0, 1.0], [0.6, 0, 0.8])
    >>> cm.is_isotropic, round(float(f), 12), round(float(cm.albedo([0.6, 0, 0.8])), 12)
    (True, 0.159154943092, 0.5)
    """

    def __init__(
        self,
        basis: Basis,
        matrix: ArrayLike,
        quantity: str = "f_cos",
        *,
        symmetrize: bool = False,
        isotropic: bool | None = None,
        rtol: float = 1e-10,
        info: dict[str, Any] | None = None,
        reciprocal: bool = True,
    ) -> None:
        if not isinstance(basis, Basis):
            raise TypeError(f"basis must be a basis object (e.g. basis.HemiZernike(8)), got "
                            f"{type(basis).__name__}")
        self.basis = basis
        self.quantity = choice(quantity, "quantity", QUANTITIES)
        self.info: dict[str, Any] = dict(info or {})
        self.reciprocal = _flag(reciprocal, "reciprocal")
        if symmetrize and not self.reciprocal:
            raise ValueError("symmetrize must be False with reciprocal=False (a general matrix "
                             "is kept as given); use .symmetric_part() for (M + M^T)/2")
        m = _as_matrix(matrix, basis.size)
        self._scalar = m.ndim == 2
        m = m.reshape(-1, basis.size, basis.size)
        scale = float(np.max(np.abs(m))) if m.size else 0.0
        asym = (float(np.max(np.abs(m - m.swapaxes(-1, -2)))) if m.size and self.reciprocal
                else 0.0)
        if symmetrize:
            m = 0.5 * (m + m.swapaxes(-1, -2))
        elif asym > rtol * scale:
            raise ValueError(f"matrix must be symmetric (reciprocity): max |M - M^T| = "
                             f"{asym:.3g} exceeds rtol * max |M| = {rtol * scale:.3g}; pass "
                             "symmetrize=True to use (M + M^T)/2, or reciprocal=False to keep "
                             "the general matrix")
        self._evaluators: dict[float, Evaluator] = {}
        self._blocks: list[NDArray[np.float64]] | None = None
        self._dense: NDArray[np.float64] | None = m
        if isotropic is None or isotropic:
            blocks = _isotropic_blocks(basis, m)
            resid = float(np.max(np.abs(m - _assemble(basis, blocks)))) if m.size else 0.0
            if resid <= rtol * scale:
                self._blocks, self._dense = blocks, None
            elif isotropic:
                raise ValueError(f"matrix is not isotropic: its anisotropic part reaches "
                                 f"{resid:.3g} (> rtol * max |M| = {rtol * scale:.3g}); use "
                                 "CoefficientMatrix(...).to_isotropic() to project it")

    # -- alternative constructors -----------------------------------------------------------
    @classmethod
    def from_blocks(
        cls,
        basis: Basis,
        blocks: list[ArrayLike],
        quantity: str = "f_cos",
        *,
        info: dict[str, Any] | None = None,
        reciprocal: bool = True,
    ) -> CoefficientMatrix:
        """Build an isotropic matrix from its blocks, one per azimuthal order m = 0..basis.order.

        ``blocks[m]`` has shape (k_m, k_m) or (channels, k_m, k_m), k_m the number of basis
        functions with azimuthal order +m; rows (w_i) and columns (w_o) ordered by degree.
        With ``reciprocal=True`` each block is symmetrised; with False it is kept as given
        (see the class Notes for the block structure).
        """
        reciprocal = _flag(reciprocal, "reciprocal")
        if not isinstance(basis, Basis):
            raise TypeError(f"basis must be a basis object, got {type(basis).__name__}")
        cos_idx = basis.azimuthal_blocks().cos
        if len(blocks) != len(cos_idx):
            raise ValueError(f"blocks must hold one block per azimuthal order 0..{len(cos_idx) - 1}"
                             f", got {len(blocks)}")
        arrs = [as_float(b, f"blocks[{m}]") for m, b in enumerate(blocks)]
        scalar = arrs[0].ndim == 2
        out = []
        for m, (b, idx) in enumerate(zip(arrs, cos_idx, strict=True)):
            want = (idx.size, idx.size) if scalar else (arrs[0].shape[0], idx.size, idx.size)
            if b.shape != want:
                raise ValueError(f"blocks[{m}] must have shape {want}, got {b.shape}")
            if not np.all(np.isfinite(b)):
                raise ValueError(f"blocks[{m}] must be finite")
            b = b.reshape(-1, idx.size, idx.size)
            out.append(0.5 * (b + b.swapaxes(-1, -2)) if reciprocal else b.copy())
        self = cls.__new__(cls)
        self.basis, self.quantity = basis, choice(quantity, "quantity", QUANTITIES)
        self.reciprocal = reciprocal
        self.info = dict(info or {})
        self._scalar, self._blocks, self._dense = scalar, out, None
        self._evaluators = {}
        return self

    @classmethod
    def from_modes(
        cls,
        modes: ArrayLike,
        order: int,
        quantity: str = "f_cos",
        *,
        isotropic: bool = True,
        info: dict[str, Any] | None = None,
    ) -> CoefficientMatrix:
        """Inverse of :meth:`to_modes`: coefficients of ``HelmholtzModes(order, isotropic)``.

        Parameters
        ----------
        modes : (size,) or (channels, size) array_like of float
        order : int
        isotropic : bool
            Which mode set ``modes`` refers to.
        """
        hm = HelmholtzModes(order, isotropic=isotropic)
        a = as_float(modes, "modes")
        if a.shape[-1:] != (hm.size,) or a.ndim > 2:
            raise ValueError(f"modes must have shape ({hm.size},) or (channels, {hm.size}) for "
                             f"{hm!r}, got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError("modes must be finite")
        scalar = a.ndim == 1
        a = a.reshape(-1, hm.size)
        zb = hm.hemisphere
        p, q = hm.pairs.T
        if isotropic:
            n, m, l = hm.indices.T
            factor = _iso_mode_factor(n, m, l)
            blocks = [np.zeros((a.shape[0], (zb.order - j) // 2 + 1, (zb.order - j) // 2 + 1))
                      for j in range(zb.order + 1)]
            for k in range(hm.size):
                i, j = (n[k] - l[k]) // 2, (m[k] - l[k]) // 2
                blocks[l[k]][:, i, j] = blocks[l[k]][:, j, i] = a[:, k] / factor[k]
            return cls.from_blocks(zb, [b[0] if scalar else b for b in blocks], quantity,
                                   info=info)
        mat = np.zeros((a.shape[0], zb.size, zb.size))
        vals = a / np.where(p == q, 1.0, _R2)
        mat[:, p, q] = vals
        mat[:, q, p] = vals
        return cls(zb, mat[0] if scalar else mat, quantity, info=info)

    # -- what it holds ------------------------------------------------------------------
    @property
    def channels(self) -> int:
        """Number of colour channels (1 for a scalar matrix)."""
        src = self._dense if self._dense is not None else self._blocks[0]
        return int(src.shape[0])

    @property
    def is_isotropic(self) -> bool:
        """True when held in isotropic block form (a function of |phi_i - phi_o|)."""
        return self._blocks is not None

    @property
    def is_scalar(self) -> bool:
        """True when the matrix has no channel axis (built from a (size, size) array)."""
        return self._scalar

    @property
    def stored(self) -> tuple[NDArray[np.float64], ...]:
        """Read-only views of the coefficients as held, always with a leading channel axis.

        Isotropic: one (channels, k_m, k_m) block per azimuthal order m = 0..order, rows and
        columns in the order of ``basis.azimuthal_blocks().cos[m]``. Dense: a single
        (channels, size, size) array. Their bytes add up to :attr:`nbytes`; nothing is
        copied (use :attr:`blocks` or :attr:`matrix` for copies).
        """
        views = []
        for a in (self._blocks if self._blocks is not None else [self._dense]):
            v = a.view()
            v.flags.writeable = False
            views.append(v)
        return tuple(views)

    @property
    def blocks(self) -> list[NDArray[np.float64]]:
        """Isotropic blocks, one per azimuthal order (copies); raises if not isotropic."""
        if self._blocks is None:
            raise ValueError("this matrix is not held in isotropic form; see to_isotropic()")
        return [b[0].copy() if self._scalar else b.copy() for b in self._blocks]

    @property
    def matrix(self) -> NDArray[np.float64]:
        """Dense (size, size) or (channels, size, size) matrix (assembled if isotropic)."""
        m = self._full()
        return m[0].copy() if self._scalar else m.copy()

    @property
    def nbytes(self) -> int:
        """Bytes of memory the coefficients hold (full blocks when isotropic, float64).

        Not the size of a file: a file stores each symmetric block's unique entries once,
        ``compress.unique_coefficients(cm)`` numbers at the storage precision (1,320 bytes
        at float64 for an isotropic RGB HemiZernike(8) matrix, which holds 2,040 bytes here).
        """
        if self._blocks is not None:
            return int(sum(b.nbytes for b in self._blocks))
        return int(self._dense.nbytes)

    @property
    def order(self) -> int:
        """Order of the basis."""
        return self.basis.order

    def _full(self) -> NDArray[np.float64]:
        if self._dense is not None:
            return self._dense
        check_bytes(8.0 * self.channels * self.basis.size**2, f"assembling {self!r}")
        return _assemble(self.basis, self._blocks)

    # -- evaluation ---------------------------------------------------------------------
    def eval(self, wi: ArrayLike, wo: ArrayLike, *, min_cos: float = 1e-3) -> NDArray:
        """BRDF values f(w_i, w_o).

        Parameters
        ----------
        wi, wo : (..., 3) array_like of float
            Unit vectors (towards the light and towards the viewer); batch shapes broadcast.
        min_cos : float
            Only for ``quantity="f_cos"``, where f = q / (cos theta_i cos theta_o): directions
            closer to the horizon than cos(theta) = ``min_cos`` are evaluated as if at that
            elevation (same azimuth), which bounds the division. For the odd hemisphere
            harmonics q vanishes on the horizon and this gives the limit value to O(min_cos);
            for other bases it caps the grazing amplification at 1/min_cos per direction.

        Returns
        -------
        (...) ndarray, or (..., channels) for a multi-channel matrix
            Zero where either direction is below the horizon (z < 0).

        Notes
        -----
        Runs compiled kernels (:class:`basis.evaluate.Evaluator`, built on first use for each
        ``min_cos`` and kept): isotropic matrices by a fused block kernel that never forms
        the basis tables, dense ones by chunked matrix products.
        """
        return self.evaluator(min_cos=min_cos)(wi, wo)

    def evaluator(self, *, min_cos: float = 1e-3) -> Evaluator:
        """Return the compiled evaluator of this matrix (built once per ``min_cos``, then kept).

        Parameters
        ----------
        min_cos : float
            As in :meth:`eval`.

        Returns
        -------
        basis.evaluate.Evaluator
            Callable as ``ev(wi, wo)``; ``ev.eval_flat(wi, wo, out)`` skips validation.
        """
        key = float(min_cos) if isinstance(min_cos, int | float) else min_cos
        ev = self._evaluators.get(key)
        if ev is None:
            ev = self._evaluators[key] = Evaluator(self, min_cos=min_cos)
        return ev

    def albedo(self, wi: ArrayLike, *, min_cos: float = 1e-3) -> NDArray:
        """Directional albedo a(w_i) = int_H f(w_i, w_o) cos(theta_o) d w_o of the representation.

        Parameters
        ----------
        wi : (..., 3) array_like of float
            Incident directions; below the horizon the albedo is 0.
        min_cos : float
            As in :meth:`eval` (``f_cos`` divides by cos theta_i).

        Returns
        -------
        (...) or (..., channels) ndarray

        Notes
        -----
        Exact for the truncated representation: a = b(w_i)^T M h with
        h_k = int_H b_k cos(theta) dw (``quantity="f"``), or a = b(w_i)^T M g / cos(theta_i)
        with g_k = int_H b_k dw (``"f_cos"``); see ``Basis.moments``. The integral runs over
        the second argument w_o, so M acts on the moments from the right; for a
        non-reciprocal matrix the albedo of light arriving from w_o, int_H f(w_i, w_o)
        cos(theta_i) dw_i, is that of :meth:`transpose` (b(w_o)^T M^T h).
        """
        wi = as_directions(wi, "wi")
        below = wi[..., 2] < 0
        lift = min_cos if self.quantity == "f_cos" else 0.0
        if self.quantity == "f_cos" and not 0.0 < min_cos < 1.0:
            raise ValueError(f"min_cos must lie in (0, 1), got {min_cos!r}")
        wl = lift_to(wi, lift)
        h = self.basis.moments("cos" if self.quantity == "f" else "none")
        v = self._full() @ h  # (channels, size)
        a = self.basis.eval(wl) @ v.T  # (..., channels)
        if self.quantity == "f_cos":
            a /= wl[..., 2][..., None]
        a[below] = 0.0
        return a[..., 0] if self._scalar else a

    # -- derived matrices ---------------------------------------------------------------
    def truncate(self, order: int) -> CoefficientMatrix:
        """Return the same BRDF in the basis truncated to ``order`` (a prefix of the functions)."""
        nb = self.basis.truncate(order)
        if self._blocks is not None:
            cos_idx = nb.azimuthal_blocks().cos
            blocks = [b[:, :idx.size, :idx.size]
                      for b, idx in zip(self._blocks, cos_idx, strict=False)]  # fewer orders
            return CoefficientMatrix.from_blocks(
                nb, [b[0] if self._scalar else b for b in blocks], self.quantity,
                info=self.info, reciprocal=self.reciprocal)
        m = self._dense[:, :nb.size, :nb.size]
        return CoefficientMatrix(nb, m[0] if self._scalar else m, self.quantity,
                                 isotropic=False, info=self.info, reciprocal=self.reciprocal)

    def to_isotropic(self) -> CoefficientMatrix:
        """Project orthogonally onto isotropic BRDFs (the average over rotations of the surface).

        The cos-cos and sin-sin blocks are averaged, every other coupling is dropped; for a
        non-reciprocal matrix that includes the cos-sin blocks of a BRDF that is not mirror
        symmetric about the plane of incidence (class Notes). ``reciprocal`` is kept.
        """
        if self._blocks is not None:
            return self
        blocks = _isotropic_blocks(self.basis, self._dense)
        return CoefficientMatrix.from_blocks(
            self.basis, [b[0] if self._scalar else b for b in blocks], self.quantity,
            info=self.info, reciprocal=self.reciprocal)

    def rotated(self, angle: float) -> CoefficientMatrix:
        """Return the same BRDF turned by ``angle`` about the normal.

        f'(w_i, w_o) = f(R^-1 w_i, R^-1 w_o), with R the rotation by ``angle`` (radians,
        counter-clockwise seen from +z).

        Parameters
        ----------
        angle : float
            Rotation angle in radians (any real number).

        Returns
        -------
        CoefficientMatrix
            ``self`` when isotropic (an isotropic BRDF is invariant); otherwise a dense matrix
            A^T M A in the same basis, quantity and channels.

        Notes
        -----
        Exact for any angle: every basis pairs cos(m phi) and sin(m phi) functions with the
        same radial factor (ordered alike by degree), and at R^-1 w the azimuth is
        phi - angle, so cos(m (phi - a)) = cos(m a) cos(m phi) + sin(m a) sin(m phi) and
        sin(m (phi - a)) = cos(m a) sin(m phi) - sin(m a) cos(m phi): b(R^-1 w) = A b(w) with
        A block diagonal (2 x 2 rotations by m a). Then f' = b(w_i)^T A^T M A b(w_o).
        A is orthogonal, so the rotation keeps symmetry (and ``reciprocal``) and the Frobenius
        norm.

        Examples
        --------
        >>> import numpy as np
        >>> from basis import HemiZernike
        >>> zb = HemiZernike(2)
        >>> M = np.zeros((6, 6)); M[0, 0] = 1.0; M[0, 5] = M[5, 0] = 0.3  # cos(2 phi) term
        >>> cm = CoefficientMatrix(zb, M, quantity="f")
        >>> r = cm.rotated(np.pi / 2).matrix  # cos(2 (phi - pi/2)) = -cos(2 phi)
        >>> float(r[0, 5]), float(r[0, 0])
        (-0.3, 1.0)
        """
        try:
            a = float(angle)
        except (TypeError, ValueError):
            raise TypeError(f"angle must be a number (radians), got {angle!r}") from None
        if not np.isfinite(a):
            raise ValueError(f"angle must be finite, got {angle!r}")
        if self._blocks is not None:
            return self
        rot = _rotation_action(self.basis, a)
        m = rot.T @ self._dense @ rot
        return CoefficientMatrix(self.basis, m[0] if self._scalar else m, self.quantity,
                                 symmetrize=self.reciprocal, isotropic=False, info=self.info,
                                 reciprocal=self.reciprocal)

    def transpose(self) -> CoefficientMatrix:
        """Return the matrix of the transposed BRDF f'(w_i, w_o) = f(w_o, w_i): M^T.

        ``self`` when reciprocal (M^T = M); otherwise a matrix of the same storage, basis,
        quantity and channels with every block (or the dense matrix) transposed.

        Examples
        --------
        >>> import numpy as np
        >>> from basis import HemiZernike
        >>> zb = HemiZernike(2)
        >>> M = np.zeros((6, 6)); M[0, 3] = 0.2
        >>> cm = CoefficientMatrix(zb, M, quantity="f", reciprocal=False)
        >>> float(cm.transpose().matrix[3, 0])
        0.2
        """
        if self.reciprocal:
            return self
        return self._like([a.swapaxes(-1, -2) for a in self.stored], reciprocal=False)

    def symmetric_part(self) -> CoefficientMatrix:
        """Return (M + M^T) / 2, the reciprocal part of the BRDF, as a reciprocal matrix.

        By orthonormality it is the closest reciprocal representation in L2, and
        ||q - q_sym|| = ||(M - M^T) / 2||_F (:meth:`antisymmetric_part`). ``self`` when
        already reciprocal.
        """
        if self.reciprocal:
            return self
        return self._like([0.5 * (a + a.swapaxes(-1, -2)) for a in self.stored],
                          reciprocal=True)

    def antisymmetric_part(self) -> CoefficientMatrix:
        """Return (M - M^T) / 2, the non-reciprocal part, as a general (reciprocal=False) matrix.

        Zero for a reciprocal matrix.
        """
        return self._like([0.5 * (a - a.swapaxes(-1, -2)) for a in self.stored],
                          reciprocal=False)

    def _like(self, stored: list[NDArray], *, reciprocal: bool) -> CoefficientMatrix:
        """Return a matrix with this one's basis, storage, quantity and info, holding ``stored``."""
        arrs = [a[0] if self._scalar else a for a in stored]
        if self._blocks is not None:
            return CoefficientMatrix.from_blocks(self.basis, arrs, self.quantity,
                                                 info=self.info, reciprocal=reciprocal)
        return CoefficientMatrix(self.basis, arrs[0], self.quantity, isotropic=False,
                                 info=self.info, symmetrize=reciprocal,
                                 reciprocal=reciprocal)

    def to_modes(self, isotropic: bool | None = None) -> NDArray[np.float64]:
        """Coefficients in the Helmholtz surface scattering modes (HemiZernike basis only).

        The modes are the symmetrised products of hemisphere Zernike functions of
        Koenderink, van Doorn & Stavridi (ECCV 1996); see :class:`basis.HelmholtzModes`.

        Parameters
        ----------
        isotropic : bool or None
            Mode set: ``HelmholtzModes(order, isotropic=True)`` (requires an isotropic matrix)
            or the general reciprocal set. None picks the isotropic set when the matrix is
            isotropic.

        Returns
        -------
        (size,) or (channels, size) ndarray
            In ``HelmholtzModes`` order; the sum of squares equals that of the matrix entries
            (both bases are orthonormal).
        """
        if not isinstance(self.basis, HemiZernike):
            raise ValueError(f"to_modes needs a HemiZernike basis, this matrix is in "
                             f"{self.basis!r}")
        if not self.reciprocal:
            raise ValueError("to_modes needs a reciprocal matrix: the Helmholtz modes are "
                             "symmetric products and cannot hold a non-reciprocal one; use "
                             ".symmetric_part().to_modes() for its reciprocal part")
        iso = self.is_isotropic if isotropic is None else bool(isotropic)
        hm = HelmholtzModes(self.order, isotropic=iso)
        if iso:
            if self._blocks is None:
                raise ValueError("matrix is not isotropic; use to_isotropic() first or "
                                 "to_modes(isotropic=False)")
            n, m, l = hm.indices.T
            vals = np.stack([self._blocks[lk][:, (nk - lk) // 2, (mk - lk) // 2]
                             for nk, mk, lk in zip(n, m, l, strict=True)], axis=-1)
            out = vals * _iso_mode_factor(n, m, l)
        else:
            p, q = hm.pairs.T
            out = self._full()[:, p, q] * np.where(p == q, 1.0, _R2)
        return out[0] if self._scalar else out

    def __repr__(self) -> str:
        ch = "" if self._scalar else f", channels={self.channels}"
        form = "isotropic" if self.is_isotropic else "dense"
        rec = "" if self.reciprocal else ", reciprocal=False"
        return (f"CoefficientMatrix({self.basis!r}, quantity={self.quantity!r}{ch}, {form}"
                f"{rec})")


def _flag(value: object, name: str) -> bool:
    if not isinstance(value, bool | np.bool_):
        raise TypeError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def _as_matrix(matrix: ArrayLike, size: int) -> NDArray[np.float64]:
    try:
        m = np.array(as_float(matrix, "matrix"), dtype=np.float64)
    except TypeError as exc:
        if "must be real" in str(exc):  # complex values: as_float's message
            raise
        raise TypeError(f"matrix must be an array of floats, got {type(matrix).__name__}") from None
    except ValueError:
        raise TypeError(f"matrix must be an array of floats, got {type(matrix).__name__}") from None
    if m.ndim not in (2, 3) or m.shape[-2:] != (size, size):
        raise ValueError(f"matrix must have shape ({size}, {size}) or (channels, {size}, {size}) "
                         f"for this basis, got shape {m.shape}")
    if m.ndim == 3 and m.shape[0] < 1:
        raise ValueError("matrix must have at least one channel")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"matrix must be finite: {int(np.sum(~np.isfinite(m)))} entries are "
                         "NaN or inf")
    return m


def _isotropic_blocks(basis: Basis, m: NDArray) -> list[NDArray]:
    cos_idx, sin_idx = basis.azimuthal_blocks()
    blocks = []
    for k, (c, s) in enumerate(zip(cos_idx, sin_idx, strict=True)):
        b = m[:, c[:, None], c]
        if k:
            b = 0.5 * (b + m[:, s[:, None], s])
        blocks.append(b)
    return blocks


def _assemble(basis: Basis, blocks: list[NDArray]) -> NDArray:
    cos_idx, sin_idx = basis.azimuthal_blocks()
    out = np.zeros((blocks[0].shape[0], basis.size, basis.size))
    for k, (c, s) in enumerate(zip(cos_idx, sin_idx, strict=True)):
        out[:, c[:, None], c] = blocks[k]
        if k:
            out[:, s[:, None], s] = blocks[k]
    return out


def _rotation_action(basis: Basis, angle: float) -> NDArray[np.float64]:
    """(size, size) A with b(R^-1 w) = A b(w), R the turn by ``angle`` about z."""
    cos_idx, sin_idx = basis.azimuthal_blocks()
    a = np.eye(basis.size)
    for m in range(1, len(cos_idx)):
        c, s = cos_idx[m], sin_idx[m]
        ca, sa = np.cos(m * angle), np.sin(m * angle)
        a[c, c] = ca
        a[s, s] = ca
        a[c, s] = sa
        a[s, c] = -sa
    return a


def _iso_mode_factor(n: NDArray, m: NDArray, l: NDArray) -> NDArray[np.float64]:
    """Mode coefficient / block entry: 1, sqrt(2), sqrt(2), 2 (see HelmholtzModes Notes)."""
    return np.where(n == m, np.where(l == 0, 1.0, _R2), np.where(l == 0, _R2, 2.0))
