"""Least-squares fits of scattered BRDF measurements, and a tessellation of the hemisphere.

A measurement is a triple (w_i, w_o, f). The fit finds the coefficient matrix M of
q(w_i, w_o) = b(w_i)^T M b(w_o) (q = f, or q = f cos(theta_i) cos(theta_o)) that best matches
the measurements in the least-squares sense. Reciprocity (M = M^T) and, optionally,
isotropy are built into the unknowns, so a fit is reciprocal whatever the noise; measured
data that are not reciprocal (see :func:`project.reciprocity`) can be fitted with
``reciprocal=False``, whose unknowns are every entry of a general M (about twice as many).

Koenderink, van Doorn & Stavridi (ECCV 1996, sec. 6) fit measured brick on a tessellation of
the hemisphere into 40 triangles (a once-subdivided icosahedron) with a pseudoinverse;
:func:`tessellate_hemisphere` and :func:`bin_samples` give that face-by-face data matrix and
:func:`fit` the pseudoinverse (an SVD, with the condition number it reveals).

Data that cannot support the order (a gonioreflectometer's few incidence angles) make the
pseudoinverse useless between the measured directions, so :func:`fit` regularises by
default: a Tikhonov penalty on high degrees, its weight chosen by cross-validation on
held-out direction pairs, and the plain fit kept whenever regularising does not predict them
clearly better (see its Notes for the measurements behind each choice).
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from os import PathLike
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray
from threadpoolctl import threadpool_limits

from basis import QUANTITIES, Basis, CoefficientMatrix, from_angles
from basis.validation import as_directions, check_bytes, choice, nonneg_int

from ._reading import number, regular_file
from .measurements import FOLDS as _FOLDS
from .measurements import Measurements, pair_groups

__all__ = [
    "COND_WARN",
    "PENALTIES",
    "REGULARIZATION_METHODS",
    "ZERO_MARGIN",
    "BinnedSamples",
    "Tessellation",
    "bin_samples",
    "design_matrix",
    "fit",
    "read_table",
    "tessellate_hemisphere",
    "to_unknowns",
    "Unknowns",
    "unknowns",
]

#: Condition number above which :func:`fit` warns (without regularization): the solution's
#: relative error can reach condition * 1.1e-16 > 1e-4 from rounding alone, and any noise in
#: the data is amplified by the same factor.
COND_WARN = 1e12

#: Copies of the (samples, unknowns) design matrix alive at the peak of a fit: the matrix, the
#: left singular vectors and the SVD's workspace. Used for the MAX_BYTES check.
_DESIGN_COPIES = 3


# -- the unknowns ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Unknowns:
    """Which entries of the matrix M each unknown of a fit stands for.

    Built by :func:`unknowns`; the order and scaling are described in :func:`design_matrix`.
    All arrays have one entry per unknown.

    Attributes
    ----------
    rows, cols : (count,) int arrays
        Flat basis positions of the (cos, or only) functions of the two factors.
    sin_rows, sin_cols : (count,) int arrays
        Their sin partners in an isotropic block (``basis.size`` when there is none).
    block : (count,) int array
        Azimuthal order m of the block (isotropic), or -1 (general).
    brow, bcol : (count,) int arrays
        Position inside block m (isotropic), or ``rows``, ``cols`` (general).
    mult : (count,) float array
        Number of entries of the dense M that share the unknown (1, 2 or 4).
    sizes : tuple of int
        Block sizes k_m (isotropic); empty for the general layout.
    reciprocal : bool
        True: M is symmetric and an unknown with ``rows != cols`` also stands for the
        transposed entry. False: M is general and every unknown is one entry (or, isotropic,
        one entry of a block B_m, shared by its cos-cos and sin-sin copies).
    """

    rows: NDArray[np.int64]  # cos (or only) function of the first factor, per unknown
    cols: NDArray[np.int64]  # ... of the second; rows[u] <= cols[u] in block order (reciprocal)
    sin_rows: NDArray[np.int64]  # sin partners (index ``size``, a zero column, when none)
    sin_cols: NDArray[np.int64]
    block: NDArray[np.int64]  # azimuthal order m (isotropic) or -1 (general)
    brow: NDArray[np.int64]  # position inside block m (isotropic)
    bcol: NDArray[np.int64]
    mult: NDArray[np.float64]  # entries of the dense M that share this unknown
    sizes: tuple[int, ...]  # block sizes k_m (isotropic)
    reciprocal: bool = True

    @property
    def count(self) -> int:
        """Number of unknowns."""
        return int(self.rows.size)


def unknowns(basis: Basis, isotropic: bool = True, *, reciprocal: bool = True) -> Unknowns:
    """Return the unknowns of a fit in ``basis``: the free entries of an (isotropic) M.

    Parameters
    ----------
    basis : basis.Basis
    isotropic : bool
        One block per azimuthal order (True) or every entry of M (False).
    reciprocal : bool
        M symmetric (True: entries j <= k) or general (False: every entry).

    Returns
    -------
    Unknowns

    Examples
    --------
    >>> from basis import HemiZernike
    >>> unknowns(HemiZernike(8)).count, unknowns(HemiZernike(8), isotropic=False).count
    (55, 1035)
    >>> unknowns(HemiZernike(8), reciprocal=False).count
    85
    """
    _check_basis(basis, hemisphere=False)
    return _layout(basis, _flag(isotropic, "isotropic"), _flag(reciprocal, "reciprocal"))


def _count(basis: Basis, isotropic: bool, reciprocal: bool = True) -> int:
    """Return the unknowns of :func:`_layout`, counted from the block sizes (no allocation)."""
    def entries(k: int) -> int:
        return k * (k + 1) // 2 if reciprocal else k * k

    if not isotropic:
        return entries(basis.size)
    return sum(entries(c.size) for c in basis.azimuthal_blocks().cos)


#: Bytes per unknown of :func:`_layout`: seven int64 index arrays and the float multiplicity,
#: plus numpy's temporaries while building them (the upper-triangle indices and the
#: concatenated blocks).
_LAYOUT_BYTES = 8 * 8 * 2


def _entries(k: int, reciprocal: bool) -> tuple[NDArray, NDArray]:
    """Return the (row, column) of every unknown entry of a k x k matrix, row by row."""
    if reciprocal:
        return np.triu_indices(k)
    return np.divmod(np.arange(k * k), k)


def _layout(basis: Basis, isotropic: bool, reciprocal: bool = True) -> Unknowns:
    size = basis.size
    count = _count(basis, isotropic, reciprocal)
    # before any index array: HemiZernike(200), isotropic=False has 206 million unknowns
    check_bytes(_LAYOUT_BYTES * count,
                f"the index arrays of {count} unknowns "
                f"({'isotropic' if isotropic else 'general'} {basis!r})")
    if not isotropic:
        r, c = _entries(size, reciprocal)
        none = np.full(r.size, size, dtype=np.int64)
        mult = np.where(r == c, 1.0, 2.0) if reciprocal else np.ones(r.size)
        return Unknowns(r.astype(np.int64), c.astype(np.int64), none, none,
                        np.full(r.size, -1, dtype=np.int64), r.astype(np.int64),
                        c.astype(np.int64), mult, (), reciprocal)
    parts: list[tuple[NDArray, ...]] = []
    sizes = []
    blocks = basis.azimuthal_blocks()
    for m, (cos_idx, sin_idx) in enumerate(zip(*blocks, strict=True)):
        if m == 0:
            sin_idx = np.full(cos_idx.size, size)
        sizes.append(cos_idx.size)
        j, k = _entries(cos_idx.size, reciprocal)
        mult = (np.where(j == k, 1.0, 2.0) if reciprocal else 1.0) * (1.0 if m == 0 else 2.0)
        mult = np.broadcast_to(mult, j.shape)
        parts.append((cos_idx[j], cos_idx[k], sin_idx[j], sin_idx[k], np.full(j.size, m),
                      j, k, mult))
    cat = [np.concatenate([p[i] for p in parts]) if parts else np.empty(0) for i in range(8)]
    ints = [np.asarray(a, dtype=np.int64) for a in cat[:7]]
    return Unknowns(*ints, np.asarray(cat[7], dtype=np.float64), tuple(sizes), reciprocal)


def design_matrix(wi: ArrayLike, wo: ArrayLike, basis: Basis, *,
                  isotropic: bool = True, reciprocal: bool = True) -> NDArray[np.float64]:
    """Build the linear map from the fit's unknowns to q at each measured pair of directions.

    Parameters
    ----------
    wi, wo : (n, 3) array_like of float
        Unit vectors in the upper hemisphere.
    basis : basis.Basis
        Any basis. On the hemisphere the full-sphere harmonics give linearly dependent
        columns (their even and odd halves span the same functions there), which is why
        :func:`fit` refuses them; the matrix itself is still well defined.
    isotropic : bool
        Unknowns of an isotropic (True) or general (False) matrix.
    reciprocal : bool
        Unknowns of a symmetric (True) or general, non-reciprocal (False) matrix.

    Returns
    -------
    (n, unknowns) ndarray of float64
        Column u is q(w_i, w_o) for the matrix with ``to_unknowns`` equal to the unit vector u.

    Notes
    -----
    The unknowns are the free entries of the symmetric matrix M, in orthonormal scaling:

    * ``isotropic=False``: one unknown per entry M_jk, j <= k (``np.triu_indices(size)``
      order). The column is b_j(w_i) b_k(w_o) for j = k and
      (b_j(w_i) b_k(w_o) + b_k(w_i) b_j(w_o)) / sqrt(2) for j < k.
    * ``isotropic=True``: blocks B_m for m = 0..max |azimuthal| as in
      ``CoefficientMatrix.from_blocks`` (rows and columns the functions with azimuthal order
      +m, by degree), one unknown per upper-triangle entry (j, k), j <= k, in row-major order,
      block after block. With c and s the cos (+m) and sin (-m) functions, the column is
      [b_cj(w_i) b_ck(w_o) + b_sj(w_i) b_sk(w_o)] (+ the transposed term when j < k; no sin
      terms when m = 0), divided by sqrt(mult), mult the number of entries of M sharing the
      unknown: 1 (j = k, m = 0), 2 (j < k or m > 0, not both), 4 (j < k and m > 0).
    * ``reciprocal=False``: every entry (j, k) instead of j <= k, row-major, with no
      transposed term: the column is b_j(w_i) b_k(w_o) (``isotropic=False``) or
      [b_cj(w_i) b_ck(w_o) + b_sj(w_i) b_sk(w_o)] / sqrt(mult), mult 1 (m = 0) or 2.

    Each unknown is sqrt(mult) times the matrix entry, so the squared norm of the unknowns is
    the squared Frobenius norm of M, which for an orthonormal basis is the L2 norm of q over
    H x H. The columns are the orthonormal reciprocal products of the basis: for
    ``HemiZernike`` they are exactly the ``basis.HelmholtzModes`` (isotropic or general), so
    weighting the rows by an exact product quadrature gives a design matrix with orthonormal
    columns (condition number 1).

    Examples
    --------
    >>> from basis import HemiZernike
    >>> design_matrix([[0, 0, 1.0]], [[0.6, 0, 0.8]], HemiZernike(8)).shape
    (1, 55)
    """
    wi, wo, _ = _check_pairs(wi, wo)
    lay = unknowns(basis, isotropic, reciprocal=reciprocal)
    check_bytes(8.0 * wi.shape[0] * lay.count * 2,
                f"the design matrix of {wi.shape[0]} samples and {lay.count} unknowns")
    return _design(basis.eval(wi), basis.eval(wo), lay)


def _design(bi: NDArray, bo: NDArray, lay: Unknowns) -> NDArray[np.float64]:
    # bi, bo (n, size) basis values; returns (n, unknowns). A zero column is appended so that
    # index ``size`` stands for "no sin partner"; no loop over samples or unknowns.
    n = bi.shape[0]
    bi = np.concatenate([bi, np.zeros((n, 1))], axis=1)
    bo = np.concatenate([bo, np.zeros((n, 1))], axis=1)
    a = bi[:, lay.rows] * bo[:, lay.cols]
    # the transposed entry shares the unknown only in a symmetric matrix
    off = (lay.rows != lay.cols) & lay.reciprocal
    a[:, off] += bi[:, lay.cols[off]] * bo[:, lay.rows[off]]
    sin = lay.sin_rows < bi.shape[1] - 1
    if np.any(sin):
        s = sin & off
        a[:, sin] += bi[:, lay.sin_rows[sin]] * bo[:, lay.sin_cols[sin]]
        a[:, s] += bi[:, lay.sin_cols[s]] * bo[:, lay.sin_rows[s]]
    a *= 1.0 / np.sqrt(lay.mult)
    return a


def to_unknowns(cm: CoefficientMatrix, *, isotropic: bool = True,
                reciprocal: bool | None = None) -> NDArray[np.float64]:
    """Return the fit's unknowns for a coefficient matrix.

    ``design_matrix(...) @ to_unknowns(cm)`` is q at the sampled pairs.

    Parameters
    ----------
    cm : basis.CoefficientMatrix
    isotropic : bool
        Layout as in :func:`design_matrix`; True needs an isotropic ``cm``.
    reciprocal : bool, optional
        Layout as in :func:`design_matrix`; default ``cm.reciprocal``. True needs a
        reciprocal ``cm``.

    Returns
    -------
    (unknowns,) or (unknowns, channels) ndarray of float64
        sqrt(mult) times the matrix entries (see :func:`design_matrix`); its squared norm is
        the squared Frobenius norm of ``cm.matrix``.
    """
    if not isinstance(cm, CoefficientMatrix):
        raise TypeError(f"cm must be a CoefficientMatrix, got {type(cm).__name__}")
    rec = cm.reciprocal if reciprocal is None else _flag(reciprocal, "reciprocal")
    if rec and not cm.reciprocal:
        raise ValueError("cm is not reciprocal: use reciprocal=False, or the reciprocal part "
                         "cm.symmetric_part()")
    lay = _layout(cm.basis, _flag(isotropic, "isotropic"), rec)
    scale = np.sqrt(lay.mult)
    scalar = cm.matrix.ndim == 2 if not cm.is_isotropic else cm.blocks[0].ndim == 2
    if isotropic:
        if not cm.is_isotropic:
            raise ValueError("cm must be isotropic for isotropic=True; use cm.to_isotropic() "
                             "or isotropic=False")
        blocks = [b.reshape(-1, *b.shape[-2:]) for b in cm.blocks]
        cells = zip(lay.block, lay.brow, lay.bcol, strict=True)
        vals = np.stack([blocks[m][:, j, k] for m, j, k in cells], axis=-1) if lay.count \
            else np.zeros((len(blocks[0]), 0))
    else:
        mat = cm.matrix.reshape(-1, cm.basis.size, cm.basis.size)
        vals = mat[:, lay.rows, lay.cols]
    out = (vals * scale).T
    return out[:, 0].copy() if scalar else out


def _unpack(z: NDArray, basis: Basis, lay: Unknowns, isotropic: bool, scalar: bool,
            quantity: str, info: dict[str, Any]) -> CoefficientMatrix:
    # z (unknowns, channels) -> CoefficientMatrix
    x = z / np.sqrt(lay.mult)[:, None]
    ch = z.shape[1]
    if isotropic:
        blocks = [np.zeros((ch, k, k)) for k in lay.sizes]
        for m in range(len(lay.sizes)):
            sel = lay.block == m
            j, kk = lay.brow[sel], lay.bcol[sel]
            if lay.reciprocal:
                blocks[m][:, kk, j] = x[sel].T
            blocks[m][:, j, kk] = x[sel].T
        return CoefficientMatrix.from_blocks(basis, [b[0] if scalar else b for b in blocks],
                                             quantity, info=info, reciprocal=lay.reciprocal)
    mat = np.zeros((ch, basis.size, basis.size))
    if lay.reciprocal:
        mat[:, lay.cols, lay.rows] = x.T
    mat[:, lay.rows, lay.cols] = x.T
    return CoefficientMatrix(basis, mat[0] if scalar else mat, quantity, isotropic=False,
                             info=info, reciprocal=lay.reciprocal)


# -- the fit -----------------------------------------------------------------------------------
def fit(
    wi: ArrayLike | Measurements,
    wo: ArrayLike | Basis | None = None,
    values: ArrayLike | None = None,
    basis: Basis | None = None,
    *,
    quantity: str = "f",
    isotropic: bool = True,
    weights: ArrayLike | None = None,
    regularization: float | str = "auto",
    penalty: str | None = None,
    reciprocal: bool = True,
) -> CoefficientMatrix:
    """Fit a coefficient matrix to scattered BRDF measurements by least squares.

    Called as ``fit(wi, wo, values, basis, ...)`` or ``fit(measurements, basis, ...)``.

    Parameters
    ----------
    wi, wo : (n, 3) array_like of float
        Unit vectors in the upper hemisphere (towards the light, towards the viewer).
        Or ``wi`` a :class:`project.Measurements` and ``wo`` the basis: its directions,
        values (all channels) and weights are fitted.
    values : (n,) or (n, channels) array_like of float
        Measured BRDF values f, in 1/sr. All channels are fitted in one solve.
    basis : basis.Basis
        A hemisphere basis: ``HemiZernike`` or ``HemiHarmonics``. ``SphericalHarmonics`` is
        refused: restricted to the hemisphere, its even and odd halves each span the same
        functions, so its products are nearly dependent and the fit is ill-posed.
    quantity : {"f", "f_cos"}
        What the matrix represents and the fit matches: f itself, or
        f cos(theta_i) cos(theta_o) (the target is then ``values * cos_i * cos_o``).
    isotropic : bool
        Fit only the isotropic blocks (one symmetric block per azimuthal order); otherwise
        every entry of the symmetric matrix.
    weights : (n,) array_like of float, optional
        Per-sample weights w >= 0 (e.g. inverse variances, or bin counts); samples of weight 0
        are dropped.
    regularization : {"auto", "gcv", "leave-incidence-out"} or float
        ``"auto"`` (default): Tikhonov regularisation with the degree penalty, its weight
        chosen by 10-fold cross-validation on held-out direction pairs (see Notes); the
        plain least-squares fit is kept unless regularisation predicts the held-out pairs
        clearly better. ``"gcv"`` and ``"leave-incidence-out"`` choose the weight by
        generalised cross-validation or with one fold per incidence direction instead (both
        measured against ``"auto"`` in the Notes). A number lambda >= 0 is the weight itself
        (0: the plain least-squares fit). It is absolute: it scales with the weights and the
        number of samples (as W^(1/2) A does squared), not with the values;
        lambda / s_max^2, s_max the largest singular value of W^(1/2) A (of its standard form
        for the degree penalty), is the scale-free ratio. The automatic choices report their
        lambda on the same scale.
    penalty : {"identity", "degree"}, optional
        The regularisation term: lambda ||z||^2 (``"identity"``: the squared L2 norm of q
        over H x H) or lambda sum_u d_u z_u^2 (``"degree"``, see Notes). Default:
        ``"degree"`` for the automatic choices, ``"identity"`` for a number (its meaning
        before ``"auto"`` existed). ``fit(..., regularization=cm.info["regularization"],
        penalty=cm.info["penalty"])`` reproduces an automatic fit ``cm``.
    reciprocal : bool
        True (default): a symmetric matrix, reciprocal by construction. False: a general
        matrix (``CoefficientMatrix(..., reciprocal=False)``) for data that are measurably
        not reciprocal (:func:`project.reciprocity`): about twice the unknowns, and held-out
        pairs no longer inform the fit at their reciprocal incidences, so it needs more
        samples.

    Returns
    -------
    basis.CoefficientMatrix
        Isotropic block form if ``isotropic``, dense otherwise; ``info`` holds:

        * ``method`` ("lstsq"), ``unknowns``, ``samples`` (those of weight > 0),
          ``isotropic``, ``reciprocal``, ``quantity``, ``basis``;
        * ``condition_number`` (alias ``cond``): largest / smallest singular value of the
          weighted design matrix W^(1/2) A, inf if rank-deficient; ``rank``;
        * ``regularization``: the weight lambda used (chosen or given); ``penalty``;
          ``regularization_method``: how it was chosen ("given", or a description of the
          cross-validation); ``cond_regularized``: the condition number of the stacked
          matrix [W^(1/2) A; sqrt(lambda) L] whose least-squares solution is the fit (L = I
          or diag(sqrt(d_u))), equal to ``cond`` for lambda = 0;
        * ``effective_parameters``: the trace of the influence matrix (the rank for lambda = 0);
        * ``validation_error``: the estimated relative RMS error of predicting held-out
          measurements, sqrt(sum w (prediction - y)^2 / sum w y^2) over all channels, at the
          chosen weight (None when the weight was given); 1 is the error of predicting 0;
        * ``lambert_validation_error``: the same error, on the same folds, of the best
          Lambertian fit (one constant f per channel), the simplest compact model (None
          when the weight was given);
        * ``validation_l2`` and ``lambert_validation_l2``: the held-out errors of the fit
          and of the Lambertian fit in the metric of every fit to samples
          (:mod:`project.crossval`): the relative L2 error of q = f cos(theta_i)
          cos(theta_o), the worst channel (None without folds: GCV, or a given weight);
        * ``residual_rms`` (list, one per channel): sqrt(sum w r^2 / sum w) of the residual r
          in the fitted quantity.

    Raises
    ------
    ValueError
        Bad shapes, non-finite values, negative weights, directions below the horizon, an
        unknown regularization method or penalty, a negative or non-finite regularization,
        no samples of weight > 0, or fewer samples than unknowns with
        ``regularization=0``.
    TypeError
        A regularization that is neither a string nor a real number.
    MemoryError
        If the design matrix and its SVDs would exceed ``basis.validation.MAX_BYTES``.

    Warns
    -----
    RuntimeWarning
        When the fit is unregularised (lambda = 0, given or chosen) and the design matrix is
        rank-deficient (the minimum-norm solution is returned) or its condition number
        exceeds :data:`COND_WARN` = 1e12. When a cross-validated error (``validation_l2``
        or ``validation_error``) is >= 1 (the fit
        predicts held-out samples no better than zero) or above that of a Lambertian fit
        (by more than :data:`ZERO_MARGIN` and :data:`LAMBERT_MARGIN`):
        an expansion cannot follow a narrow measured highlight between a gonioreflectometer's
        few incidence angles (five glossy paints of the Cornell gonioreflectometer data,
        1,439 samples each: held-out errors of 0.85-1.4 at every order from 4 to 16); the
        message names what predicts better.

    Notes
    -----
    Minimises ||W^(1/2) (A z - y)||^2 + lambda z^T P z with A = :func:`design_matrix`, y the
    target and P = I (identity penalty) or P = diag(d_u) (degree penalty). With P = D the
    problem is brought to standard form by x = D^(1/2) z, and one SVD of
    W^(1/2) A D^(-1/2) = U S V^T gives every weight: z = D^(-1/2) V diag(s / (s^2 + lambda))
    U^T W^(1/2) y. For lambda = 0 singular values below s_max * max(samples, unknowns) * eps
    are treated as zero (the pseudoinverse, as in Koenderink et al. 1996; numpy's
    ``matrix_rank`` tolerance). The unknowns z are the matrix entries scaled by the square
    root of the number of entries of M that share them, so ||z|| is the Frobenius norm of the
    whole (dense) M, that is the L2 norm of q over H x H, independent of the storage: the
    penalty does not favour the off-diagonal or the m > 0 entries, which the raw entry vector
    would count once though they appear two or four times in M. The same scaling makes the
    condition number 1 for data on an exact quadrature rule (orthonormal columns).

    *The degree penalty.* The unknown u multiplies b_j(w_i) b_k(w_o) (and its reciprocal and
    azimuthal partners, all of the same degrees), and d_u = (1 + e_j + e_k)^2 with
    e = l (l + 1) for the harmonics (the eigenvalue of the Laplace-Beltrami operator) and
    e = n (n + 2) for HemiZernike (the eigenvalue of the differential operator whose
    eigenfunctions the Zernike polynomials are on the disk; Zernike 1934). For
    eigenfunctions, sum_u d_u z_u^2 = ||(1 + Delta_i + Delta_o) q||^2: a squared second-order
    Sobolev norm on H x H, the analogue of the m = 2 smoothing splines on the sphere (Wahba
    1981). It penalises high degrees (order 12: d up to 337^2), and the 1 keeps D invertible
    so that lambda -> 0 is the least-squares fit. Measured on the test problem below (held-out
    error at the chosen weight, orders 12 / 16 / 20): 0.50 / 0.58 / 0.58 %, against
    0.58 / 2.4 / 12.6 % with the identity penalty and 0.50 / 0.71 / 0.68 % with the first-order
    form 1 + e_j + e_k (1.8 / 2.0 % against 2.5 / 3.4 % at orders 16 / 20 for the sharp lobe).

    *Choosing the weight.* The candidates are 0 and lambda = t s_max^2, t = 10^-14 ... 10^0
    in steps of 10^0.25 (s_max of the standard-form matrix). ``"auto"`` splits the samples
    into 10 folds at random (seeded, so the fit is deterministic) with repeated measurements
    of one direction pair, or of its reciprocal (for an isotropic fit: of any pair with the
    same theta_i, theta_o, phi_i - phi_o up to sign) kept in one fold, fits the other nine
    folds by one SVD each and scores the predictions of the held-out fold for every weight
    at once (Stone 1974). ``"leave-incidence-out"`` makes one fold per incidence direction
    (theta_i for an isotropic fit) when there are 3 to 24 of them, random groups of
    incidences otherwise, 10-fold on pairs below 3. ``"gcv"`` minimises the generalised
    cross-validation function n RSS / (n - trace H)^2 (Golub, Heath & Wahba 1979) from the
    one SVD of all data. The plain fit (weight 0) is a candidate only if the design and
    every training fold have full column rank (otherwise the least-squares solution is not
    determined by the data, and nothing validates the minimum-norm choice); it is kept
    unless the best weight lowers the cross-validated error by more than
    :data:`ZERO_MARGIN` (5 %) *and* the mean over folds of log(fold error at 0 / fold error
    at the best weight) exceeds twice its standard error (GCV has no folds: the margin
    alone). The log makes the paired test see the gain of an ill-conditioned fit, whose fold
    errors spread over orders of magnitude: at the brick case of Koenderink et al. (66
    random pairs, 55 unknowns, condition ~1e3) a paired t on the raw differences was
    1.0-2.2 (below 2 in 7 of 8 data sets) while the error fell 10x to 70x; on the log scale
    it was 3.9-8.8. Measured on well-posed fits (8 samples per unknown, orders 4-8, noise
    0-5 %, 27 data sets) the gain reached 30 % in single cases, carried by one or two folds
    (t at most 1.6), and t reached 2.3 only for gains below 0.01 %: the test keeps the
    first kind plain, the margin the second. Cost: 11 SVDs (one per fold, one of all data)
    instead of 1; 2.5 s against 0.3-0.7 s at order 20 with 1800 samples (one thread).

    *Why 10-fold on pairs.* Test problem: Oren-Nayar (albedo 0.6, sigma 0.35) plus a
    Phong lobe (ks 0.25, n 4), 300 uniform outgoing directions at each of the incidences
    0, 15, ..., 75 degrees (1800 samples), 0.5 % noise; truth: 2000 random pairs whose
    incidence lies between the measured ones. The plain fit's held-out error is 0.71 % at
    order 8, 1.9 % at 12 (rank 137 of 140), 200 % at 16 and 9e5 % at 20. With ``"auto"``
    it is 0.50-0.58 % at orders 12-20 (0.71-0.72 % at orders 8-10, kept plain), and the
    validation estimate 0.62-0.93 % (the noise included). Leave-incidence-out chooses about
    as well (0.54-0.62 %) but estimates 3.9-4.4 % at orders 10-20 (18 % at order 8): its
    folds ask a harder question (a held-out incidence leaves a gap twice as wide, and
    holding out 75 degrees is an extrapolation towards grazing). GCV does as well here
    (0.45-0.59 %), but without noise and with a sharper lobe (Phong ks 0.4, n 20) it picks
    lambda ~ 5e-13 at orders 16 and 20, where the design is rank-deficient, and returns
    168 % and 57 % errors against 1.8 % and 2.0 % for ``"auto"``: it scores predictions at
    the measured pairs, which a rank-deficient design interpolates. Reciprocity is why
    random pairs still probe unmeasured incidences: a held-out pair (w_i, w_o) is, by
    q(w_i, w_o) = q(w_o, w_i), a measurement at the incidence w_o. The pair folds can be
    optimistic without noise: 0.67 % estimated against 2.0 % at order 20 for the sharp lobe.

    Koenderink et al. (1996, sec. 6) fit 40 x 40 face-centre data of brick at order 8
    isotropic (55 unknowns, the ``HelmholtzModes(8)`` count) with a pseudoinverse; see
    :func:`tessellate_hemisphere` and :func:`bin_samples`.

    Examples
    --------
    Lambert with albedo 0.5 is recovered exactly from 40 random pairs (the default keeps
    the plain fit, weight 0, for this well-posed problem):

    >>> import numpy as np
    >>> from basis import HemiZernike
    >>> rng = np.random.default_rng(1)
    >>> w = rng.normal(size=(80, 3)); w[:, 2] = abs(w[:, 2])
    >>> w /= np.linalg.norm(w, axis=1, keepdims=True)
    >>> cm = fit(w[:40], w[40:], np.full(40, 0.5 / np.pi), HemiZernike(2))
    >>> round(float(cm.albedo([0, 0, 1.0])), 12), cm.info["unknowns"], cm.info["rank"]
    (0.5, 5, 5)
    >>> cm.info["regularization"], cm.info["regularization_method"]
    (0.0, '10-fold CV on direction pairs')
    """
    if isinstance(wi, Measurements):
        if values is not None or (basis is not None and wo is not None):
            raise TypeError("fit(measurements, basis, ...) takes the values from the "
                            "measurements: pass no values")
        if weights is not None:
            raise TypeError("fit(measurements, ...) takes the weights from the measurements; "
                            "build them with Measurements(..., weights=...)")
        meas, basis = wi, (wo if basis is None else basis)
        wi, wo, values, weights = meas.wi, meas.wo, meas.values, meas.weights
    elif wo is None or values is None or basis is None:
        raise TypeError("fit needs (wi, wo, values, basis) or (measurements, basis)")
    wi, wo, n = _check_pairs(wi, wo)
    _check_basis(basis)
    quantity = choice(quantity, "quantity", QUANTITIES)
    isotropic = _flag(isotropic, "isotropic")
    reciprocal = _flag(reciprocal, "reciprocal")
    y, scalar = _check_values(values, n)
    w = _check_weights(weights, n)
    how, lam = _check_regularization(regularization)
    pen = _check_penalty(penalty, how)

    keep = w > 0
    wi, wo, y, w = wi[keep], wo[keep], y[keep], w[keep]
    samples = int(wi.shape[0])
    # closed form: the index arrays come after the check
    unknowns = _count(basis, isotropic, reciprocal)
    kind = ("isotropic" if isotropic else "general") + ("" if reciprocal else " non-reciprocal")
    if samples == 0 or (samples < unknowns and how == "given" and lam == 0.0):
        raise ValueError(
            f"fit is underdetermined: {samples} samples (of weight > 0) for {unknowns} "
            f"unknowns ({kind} {basis!r}); lower the order, use isotropic=True, add samples, "
            "or pass regularization='auto' or > 0")
    check_bytes(_fit_bytes(samples, unknowns, basis.size, how, pen),
                f"fitting {unknowns} unknowns to {samples} samples (design matrix, its SVDs "
                "and square matrices of the unknowns)")
    lay = _layout(basis, isotropic, reciprocal)
    if quantity == "f_cos":
        y = y * (wi[:, 2] * wo[:, 2])[:, None]
    sw = np.sqrt(w)
    a = _design(basis.eval(wi), basis.eval(wo), lay)
    a *= sw[:, None]
    yw = y * sw[:, None]
    scale = 1.0 / np.sqrt(_degree_penalty(basis, lay)) if pen == "degree" else None

    validation = lambert = validation_q = lambert_q = None
    method_text = "given"
    if how != "given" and samples and unknowns:
        folds, method_text = _folds(wi, wo, isotropic, how)
        # the weighted residual of the fitted quantity times qw is that of q = f cos cos
        cc = wi[:, 2] * wo[:, 2]
        qw = np.ones(samples) if quantity == "f_cos" else cc
        sel = _select(a, yw, scale, folds, how, qw)
        lam, validation, validation_q = sel.weight, sel.error, sel.error_q
        std = sel.svd
        lambert, lambert_q = _lambert_error(sw * (cc if quantity == "f_cos" else 1.0), yw,
                                            folds, qw)
    elif lam > 0.0 and pen == "degree" and samples and unknowns:
        std = _Svd.of(a * scale, yw)
    else:
        std = None
    if lam == 0.0 or std is None:
        z, s, rank = _solve(a, yw, lam)
        eff = float(np.sum(s * s / (s * s + lam))) if lam > 0 else float(rank)
    else:
        z = std.vt.T @ (std.filter(lam)[:, None] * std.uty)
        if scale is not None:
            z *= scale[:, None]
        eff = float(np.sum(std.s ** 2 / (std.s ** 2 + lam)))
        s = std.s if pen == "identity" else scipy.linalg.svdvals(a, check_finite=False)
        rank = int(np.sum(s > _rank_tol(s, a.shape))) if s.size else 0
    cond = float(s[0] / s[-1]) if rank == unknowns and unknowns and s[-1] > 0 else float("inf")
    if unknowns == 0:
        cond = 1.0
    cond_reg = cond if lam == 0.0 else _cond_regularized(s, std, scale, lam, unknowns)
    resid = a @ z - yw
    rms = np.sqrt(np.sum(resid * resid, axis=0) / np.sum(w)) if samples else np.zeros(y.shape[1])
    if lam == 0.0 and rank < unknowns:
        warnings.warn(f"fit is rank-deficient: rank {rank} of {unknowns} unknowns ({kind} "
                      f"{basis!r}, {samples} samples), condition number inf; the minimum-norm "
                      "solution is returned: sample more pairs of directions, lower the "
                      "order or pass regularization='auto' or > 0", RuntimeWarning,
                      stacklevel=2)
    elif lam == 0.0 and cond > COND_WARN:
        warnings.warn(f"fit is badly conditioned: condition number {cond:.3g} > {COND_WARN:.0e} "
                      f"({unknowns} unknowns, {samples} samples); rounding alone may cost "
                      f"{cond * np.finfo(float).eps:.1e} relative error: lower the order or "
                      "pass regularization='auto' or > 0", RuntimeWarning, stacklevel=2)
    # judged in the fitted quantity and, where there are folds, in the l2 error of q (worst
    # channel), the metric of every fit to samples (project.crossval): either one warns
    flagged = [(j, b, m) for j, b, m in ((validation_q, lambert_q, "l2 of q"),
                                         (validation, lambert, "relative RMS"))
               if j is not None and (j >= 1.0 or j > max((1.0 + ZERO_MARGIN) * b,
                                                          b + LAMBERT_MARGIN))]
    judged, baseline, metric = flagged[0] if flagged else (None, None, None)
    if judged is not None:
        than = ("no better than zero" if judged >= 1.0 else
                f"worse than a Lambertian fit ({baseline:.3g})")
        warnings.warn(f"fit predicts held-out samples {than}: cross-validated error "
                      f"{judged:.3g} ({metric}; {kind} {basis!r}, {samples} samples, "
                      f"{method_text}). An expansion cannot follow these data between the "
                      "measured directions (a narrow highlight?); fit a compact model, "
                      "project.fit_model(measurements, 'lambert+ggx'), or let "
                      "compress.select(measurements, tol) compare models and expansions",
                      RuntimeWarning, stacklevel=2)
    info = {
        "method": "lstsq",
        "condition_number": cond,
        "cond": cond,
        "cond_regularized": cond_reg,
        "rank": int(rank),
        "unknowns": int(unknowns),
        "samples": samples,
        "residual_rms": [float(r) for r in rms],
        "regularization": float(lam),
        "penalty": pen,
        "regularization_method": method_text,
        "effective_parameters": eff,
        "validation_error": validation,
        "lambert_validation_error": lambert,
        "validation_l2": validation_q,
        "lambert_validation_l2": lambert_q,
        "isotropic": isotropic,
        "reciprocal": reciprocal,
        "quantity": quantity,
        "basis": repr(basis),
    }
    return _unpack(z, basis, lay, isotropic, scalar, quantity, info)


def _fit_bytes(samples: int, unknowns: int, size: int, how: str, pen: str) -> float:
    """Return the peak bytes of :func:`fit`, for the MAX_BYTES check before it allocates.

    The design matrix and its copies (``_DESIGN_COPIES`` or ``_AUTO_COPIES``), the basis
    values at both directions of every sample, the right singular vectors of each SVD (full
    data and one training fold: rank x unknowns each), and for the degree penalty the
    (unknowns, unknowns) matrices of the regularised condition number (the penalty's
    diagonal, the stacked system and its copy inside svdvals). With fewer samples than
    unknowns (allowed when regularised) the square matrices dominate.
    """
    rank = min(samples, unknowns)
    copies = _DESIGN_COPIES if how == "given" and pen == "identity" else _AUTO_COPIES
    square = (3 * unknowns + 2 * rank) * unknowns if pen == "degree" else 0
    return (8.0 * (copies * samples * unknowns + 2 * samples * (size + 1) + 2 * rank * unknowns
                   + square) + _LAYOUT_BYTES * unknowns)


#: Designs with at most this many unknowns are factored on one BLAS thread: a tall, narrow
#: matrix gains nothing from a second thread, and loses up to 40x when another process holds
#: a core (SVD of 1439 x 55, the order-8 isotropic Zernike fit of a gonioreflectometer
#: table: 20 s for the ten folds on two threads of a loaded machine, 0.6 s on one).
NARROW = 512


def _svd(a: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    with threadpool_limits(1 if a.shape[1] <= NARROW else None, user_api="blas"):
        try:
            return scipy.linalg.svd(a, full_matrices=False, check_finite=False,
                                    lapack_driver="gesdd")
        except np.linalg.LinAlgError:  # gesdd may not converge; gesvd is slower but robust
            return scipy.linalg.svd(a, full_matrices=False, check_finite=False,
                                    lapack_driver="gesvd")


def _rank_tol(s: NDArray, shape: tuple[int, int]) -> float:
    return float(s[0]) * max(shape) * np.finfo(np.float64).eps if s.size else 0.0


def _solve(a: NDArray, y: NDArray, lam: float) -> tuple[NDArray, NDArray, int]:
    """Tikhonov / pseudoinverse solution of a z = y by SVD; a (n, u), y (n, c).

    Returns z (u, c), the singular values (min(n, u),) in decreasing order, and the rank.
    """
    n, u = a.shape
    if n == 0 or u == 0:
        return np.zeros((u, y.shape[1])), np.zeros(min(n, u)), 0
    left, s, vt = _svd(a)
    rank = int(np.sum(s > _rank_tol(s, a.shape)))
    if lam > 0.0:
        filt = s / (s * s + lam)
    else:
        filt = np.zeros_like(s)
        filt[:rank] = 1.0 / s[:rank]
    z = vt.T @ (filt[:, None] * (left.T @ y))
    return z, s, rank


# -- choosing the weight -----------------------------------------------------------------------
#: Ways to choose the Tikhonov weight: see :func:`fit`.
REGULARIZATION_METHODS = ("auto", "gcv", "leave-incidence-out")
#: Penalties: see :func:`fit`.
PENALTIES = ("identity", "degree")
#: Relative gain in cross-validated error that a weight > 0 must bring over the plain fit
#: (besides twice its standard error across folds) to be chosen; see :func:`fit`.
ZERO_MARGIN = 0.05
#: Absolute margin (besides :data:`ZERO_MARGIN`) by which :func:`fit`'s cross-validated
#: error must exceed a Lambertian fit's for the warning: differences below 0.1 % of the data
#: are noise of the folds, not a failure.
LAMBERT_MARGIN = 1e-3
#: Candidate weights of the automatic choices, relative to s_max^2 of the standard form.
_REL_WEIGHTS = 10.0 ** np.arange(-14.0, 0.125, 0.25)
_MAX_INCIDENCE_FOLDS = 24
#: Copies of the design alive in an automatic or degree-penalised fit: the matrix, its
#: standard form and its left singular vectors, one training fold and its left singular
#: vectors.
_AUTO_COPIES = 5


@dataclass(frozen=True)
class _Svd:
    """SVD of a weighted (standard-form) design and the projected target."""

    u: NDArray
    s: NDArray
    vt: NDArray
    uty: NDArray
    rank: int

    @classmethod
    def of(cls, a: NDArray, y: NDArray) -> _Svd:
        u, s, vt = _svd(a)
        return cls(u, s, vt, u.T @ y, int(np.sum(s > _rank_tol(s, a.shape))))

    def filter(self, lam: float) -> NDArray:
        """Return the Tikhonov filter s / (s^2 + lam) (the pseudoinverse for lam = 0)."""
        if lam > 0.0:
            return self.s / (self.s * self.s + lam)
        f = np.zeros_like(self.s)
        f[:self.rank] = 1.0 / self.s[:self.rank]
        return f


@dataclass(frozen=True)
class _Selection:
    weight: float
    error: float
    svd: _Svd
    weights: NDArray  # the candidates
    errors: NDArray  # their validation errors (relative RMS)
    fold_sse: NDArray | None  # (folds, candidates) squared errors
    error_q: float | None = None  # held-out l2 error of q at the chosen weight, worst channel


def _degree_penalty(basis: Basis, lay: Unknowns) -> NDArray[np.float64]:
    """Return d_u = (1 + e_j + e_k)^2: e = n (n + 2) (Zernike) or l (l + 1) (harmonics)."""
    deg = basis.degree.astype(np.float64)
    e = deg * (deg + 2.0) if basis.kind == "zernike" else deg * (deg + 1.0)
    return (1.0 + e[lay.rows] + e[lay.cols]) ** 2


def _folds(wi: NDArray, wo: NDArray, isotropic: bool, how: str) -> tuple[NDArray, str]:
    """Return the fold of each sample and a description of the split."""
    n = wi.shape[0]
    if how == "gcv":
        return np.zeros(n, dtype=np.int64), "GCV"
    if how == "leave-incidence-out":
        inc = pair_groups(wi, wo, isotropic, "incidence")
        count = int(inc.max()) + 1 if n else 0
        if 3 <= count <= _MAX_INCIDENCE_FOLDS:
            return inc, f"leave-one-incidence-out CV ({count} incidences)"
        if count > _MAX_INCIDENCE_FOLDS:
            return _group_folds(inc, count), f"{_FOLDS}-fold CV on incidences ({count})"
    pair = pair_groups(wi, wo, isotropic, "pairs")
    count = int(pair.max()) + 1 if n else 0
    if count < 2:
        return np.zeros(n, dtype=np.int64), "GCV (one distinct direction pair: no folds)"
    return _group_folds(pair, count), f"{min(_FOLDS, count)}-fold CV on direction pairs"


def _group_folds(group: NDArray, count: int) -> NDArray[np.int64]:
    k = min(_FOLDS, count)
    order = np.random.default_rng(0).permutation(count)
    fold_of = np.empty(count, dtype=np.int64)
    fold_of[order] = np.arange(count) % max(k, 1)
    return fold_of[group]


def _select(a: NDArray, y: NDArray, scale: NDArray | None, folds: NDArray,
            how: str, qw: NDArray | None = None) -> _Selection:
    """Choose the Tikhonov weight among 0 and t s_max^2 by the validation of ``how``.

    ``qw`` (n,) turns a weighted residual of the fitted quantity into one of q: the
    held-out l2 error of q at the chosen weight is then reported too (with folds only).
    """
    ap = a if scale is None else a * scale
    full = _Svd.of(ap, y)
    n, u = ap.shape
    lams = np.concatenate([[0.0], _REL_WEIGHTS * full.s[0] ** 2]) if full.s.size and \
        full.s[0] > 0 else np.zeros(1)
    total = float(np.sum(y * y))
    zero_ok = full.rank == u
    if how == "gcv" or int(folds.max()) < 1:
        rss = np.empty(lams.size)
        trace = np.empty(lams.size)
        perp = max(total - float(np.sum(full.uty ** 2)), 0.0)
        for k, lam in enumerate(lams):
            h = full.filter(lam) * full.s
            rss[k] = float(np.sum(((1.0 - h)[:, None] * full.uty) ** 2)) + perp
            trace[k] = float(np.sum(h))
        with np.errstate(divide="ignore", invalid="ignore"):
            gcv = np.where(n - trace > 0.5, n * rss / np.maximum(n - trace, 0.5) ** 2, np.inf)
            err = np.sqrt(gcv * n / total) if total > 0 else np.zeros(lams.size)
        if not zero_ok:
            err[0] = np.inf
        best = int(np.argmin(err[1:])) + 1 if lams.size > 1 else 0
        pick = 0 if zero_ok and not err[best] < (1.0 - ZERO_MARGIN) * err[0] else best
        return _Selection(float(lams[pick]), float(err[pick]), full, lams, err, None)
    nf = int(folds.max()) + 1
    sse = np.zeros((nf, lams.size))
    sse_q = np.zeros((lams.size, y.shape[1]))
    for f in range(nf):
        test = folds == f
        part = _Svd.of(ap[~test], y[~test])
        if part.rank < u:
            zero_ok = False
        filt = np.stack([part.filter(lam) for lam in lams])  # (L, r)
        proj = ap[test] @ part.vt.T  # (m, r)
        pred = np.einsum("mr,lr,rc->lmc", proj, filt, part.uty, optimize=True)
        sse[f] = np.sum((pred - y[test][None]) ** 2, axis=(1, 2))
        if qw is not None:
            sse_q += np.sum(((pred - y[test][None]) * qw[test][None, :, None]) ** 2, axis=1)
    err = np.sqrt(sse.sum(axis=0) / total) if total > 0 else np.zeros(lams.size)
    best = int(np.argmin(err[1:])) + 1 if lams.size > 1 else 0
    pick = best
    if zero_ok:
        # paired gain per fold on a log scale: the plain fit's fold errors are heavy-tailed
        # exactly when it is ill-conditioned, which would hide a gain from a test on the raw
        # differences
        floor = 1e-30 * total + np.finfo(np.float64).tiny
        gain = np.log((sse[:, 0] + floor) / (sse[:, best] + floor))
        se = float(np.std(gain, ddof=1) / np.sqrt(nf)) if nf > 1 else 0.0
        clear = bool(err[best] < (1.0 - ZERO_MARGIN) * err[0]) and \
            float(np.mean(gain)) > 2.0 * se
        pick = best if clear else 0
    else:
        err[0] = np.inf
    error_q = None
    if qw is not None:
        total_q = np.sum((y * qw[:, None]) ** 2, axis=0)
        error_q = float(np.max(np.sqrt(np.divide(sse_q[pick], total_q, out=np.zeros_like(
            total_q), where=total_q > 0))))
    return _Selection(float(lams[pick]), float(err[pick]), full, lams, err, sse, error_q)


def _lambert_error(x: NDArray, y: NDArray, folds: NDArray,
                   qw: NDArray) -> tuple[float, float | None]:
    """Cross-validated errors of the best one-constant-per-channel fit y ~ c x (weighted).

    ``x`` (n,) is the weighted column of a Lambertian BRDF in the fitted quantity, ``y``
    (n, C) the weighted targets; scored as :func:`_select` scores its candidates, and
    (with folds) in the l2 error of q, worst channel, ``qw`` as in :func:`_select`.
    """
    total = float(np.sum(y * y))
    if total <= 0.0:
        return 0.0, 0.0
    if int(folds.max()) < 1:  # no folds (GCV): the residual of the one fit, leave-one-out
        xx = float(x @ x)
        c = (x @ y) / xx if xx > 0 else np.zeros(y.shape[1])
        h = x * x / xx if xx > 0 else np.zeros_like(x)
        r = (y - np.outer(x, c)) / np.maximum(1.0 - h, 1e-12)[:, None]
        return float(np.sqrt(np.sum(r * r) / total)), None
    sse = 0.0
    sse_q = np.zeros(y.shape[1])
    for f in range(int(folds.max()) + 1):
        test = folds == f
        xx = float(x[~test] @ x[~test])
        c = (x[~test] @ y[~test]) / xx if xx > 0 else np.zeros(y.shape[1])
        r = np.outer(x[test], c) - y[test]
        sse += float(np.sum(r * r))
        sse_q += np.sum((r * qw[test, None]) ** 2, axis=0)
    total_q = np.sum((y * qw[:, None]) ** 2, axis=0)
    err_q = np.sqrt(np.divide(sse_q, total_q, out=np.zeros_like(total_q), where=total_q > 0))
    return float(np.sqrt(sse / total)), float(np.max(err_q))


def _cond_regularized(s: NDArray, std: _Svd | None, scale: NDArray | None, lam: float,
                      unknowns: int) -> float:
    """Condition number of [W^(1/2) A; sqrt(lam) L] (L = I, or diag(1 / scale))."""
    if scale is None or std is None:
        smin = float(s[-1]) if s.size == unknowns else 0.0
        return float(np.sqrt((s[0] ** 2 + lam) / (smin ** 2 + lam)))
    root = 1.0 / scale
    stacked = np.vstack([(std.s[:, None] * std.vt) * root[None, :], np.sqrt(lam) * np.diag(root)])
    sv = scipy.linalg.svdvals(stacked, check_finite=False)
    return float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")


# -- validation --------------------------------------------------------------------------------
def _check_basis(basis: object, *, hemisphere: bool = True) -> None:
    if not isinstance(basis, Basis):
        raise TypeError(f"basis must be a basis object (e.g. basis.HemiZernike(8)), got "
                        f"{type(basis).__name__}")
    if hemisphere and basis.domain != "hemisphere":
        raise ValueError(f"basis must be a hemisphere basis (HemiZernike or HemiHarmonics), got "
                         f"{basis!r}: on the hemisphere the full-sphere harmonics are redundant "
                         "(their even and odd halves span the same functions), so a fit in "
                         "them is ill-posed; use basis.HemiHarmonics(lmax) instead")


def _flag(value: object, name: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def _check_pairs(wi: ArrayLike, wo: ArrayLike) -> tuple[NDArray, NDArray, int]:
    wi = as_directions(wi, "wi", upper=True)
    wo = as_directions(wo, "wo", upper=True)
    if wi.ndim != 2:
        raise ValueError(f"wi must have shape (n, 3), got shape {wi.shape}")
    if wo.shape != wi.shape:
        raise ValueError(f"wo must have the shape of wi {wi.shape}, got shape {wo.shape}")
    return wi, wo, int(wi.shape[0])


def _check_values(values: ArrayLike, n: int) -> tuple[NDArray, bool]:
    try:
        v = np.array(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"values must be an array of floats, got {type(values).__name__}") \
            from None
    if v.ndim not in (1, 2) or v.shape[0] != n or (v.ndim == 2 and v.shape[1] < 1):
        raise ValueError(f"values must have shape ({n},) or ({n}, channels) to match wi, got "
                         f"shape {v.shape}")
    bad = ~np.isfinite(v)
    if bad.any():
        raise ValueError(f"values must be finite: {int(bad.sum())} entries are NaN or inf "
                         f"(first at sample {np.argwhere(bad)[0][0]})")
    return (v[:, None], True) if v.ndim == 1 else (v, False)


def _check_weights(weights: ArrayLike | None, n: int) -> NDArray[np.float64]:
    if weights is None:
        return np.ones(n)
    w = np.array(weights, dtype=np.float64)
    if w.shape != (n,):
        raise ValueError(f"weights must have shape ({n},) to match wi, got shape {w.shape}")
    if not np.all(np.isfinite(w)):
        raise ValueError("weights must be finite")
    if np.any(w < 0):
        raise ValueError(f"weights must be >= 0, got min {w.min():.6g}")
    if n and not np.any(w > 0):
        raise ValueError("weights must not all be zero")
    return w


def _check_regularization(value: object) -> tuple[str, float]:
    """Return ("given", lambda) for a number, (method, 0.0) for a method name."""
    if isinstance(value, str):
        if value not in REGULARIZATION_METHODS:
            names = ", ".join(repr(m) for m in REGULARIZATION_METHODS)
            raise ValueError(f"regularization must be one of {names} or a number >= 0, got "
                             f"{value!r}")
        return value, 0.0
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer,
                                                                      np.floating)):
        raise TypeError(f"regularization must be a number or one of "
                        f"{', '.join(repr(m) for m in REGULARIZATION_METHODS)}, got {value!r}")
    lam = float(value)
    if not np.isfinite(lam) or lam < 0:
        raise ValueError(f"regularization must be finite and >= 0, got {value!r}")
    return "given", lam


def _check_penalty(value: object, how: str) -> str:
    if value is None:
        return "identity" if how == "given" else "degree"
    return choice(value, "penalty", PENALTIES)


# -- the tessellation of Koenderink et al. 1996 ------------------------------------------------
@dataclass(frozen=True, eq=False)
class Tessellation:
    """Spherical triangles covering the upper hemisphere.

    Attributes
    ----------
    vertices : (v, 3) ndarray of float
        Unit vectors.
    faces : (f, 3) ndarray of int
        Vertex indices, counter-clockwise seen from outside the sphere.
    centroids : (f, 3) ndarray of float
        Mean of each face's vertices, normalised to a unit vector.
    solid_angles : (f,) ndarray of float
        Exact spherical-triangle areas (steradians); they sum to 2 pi.
    """

    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]
    centroids: NDArray[np.float64]
    solid_angles: NDArray[np.float64]

    @property
    def size(self) -> int:
        """Number of faces."""
        return int(self.faces.shape[0])

    def locate(self, dirs: ArrayLike) -> NDArray[np.int64]:
        """Return the index of the face containing each direction.

        Parameters
        ----------
        dirs : (..., 3) array_like of float
            Unit vectors with z >= 0.

        Returns
        -------
        (...) ndarray of int
            The face whose three edge planes the direction is farthest inside (a direction
            on an edge shared by two faces goes to either, as rounding decides).
        """
        d = as_directions(dirs, "dirs", upper=True)
        flat = d.reshape(-1, 3)
        check_bytes(8.0 * flat.shape[0] * self.size * 2, f"locating {flat.shape[0]} directions")
        v = self.vertices[self.faces]  # (f, 3 corners, 3)
        normals = np.cross(v, np.roll(v, -1, axis=1))  # edge planes, (f, 3, 3), inward
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        inside = flat @ normals[:, 0].T  # (n, f): signed distance inside the closest edge
        for e in (1, 2):
            np.minimum(inside, flat @ normals[:, e].T, out=inside)
        return np.argmax(inside, axis=-1).reshape(d.shape[:-1])


def tessellate_hemisphere(subdivisions: int = 1) -> Tessellation:
    """Triangulate the upper hemisphere into 40 near-equal-area faces (Koenderink et al. 1996).

    Parameters
    ----------
    subdivisions : int
        Times each icosahedron face is split into four (edge midpoints pushed onto the
        sphere), >= 1: 40 * 4^(subdivisions - 1) faces. 1 is the tessellation of Koenderink,
        van Doorn & Stavridi (1996, sec. 6).

    Returns
    -------
    Tessellation

    Notes
    -----
    The icosahedron is oriented with a vertex at the pole z = 1 and its upper ring of five
    vertices at z = 1/sqrt(5), azimuths 0, 72, ..., 288 degrees (the lower ring at
    z = -1/sqrt(5), azimuths 36 + 72 k). The equator then crosses the ten faces of the middle
    band, but each crossing edge runs from one ring to the other, symmetric about z = 0, so
    its midpoint lies exactly on the equator, and one subdivision splits every band face along
    the equator: 5 cap faces x 4 + 5 band faces x 3 + 5 band faces x 1 = 40 faces in z >= 0,
    none straddling it (further subdivisions keep the equator, since the midpoint of two
    equator points is on the equator). Other orientations leave faces straddling the equator
    (checked: with a face centred at the pole 34 faces lie above, 34 below and 12 straddle;
    with an edge centred there, 36, 36 and 8).

    The faces are not of identical area, although Koenderink et al. (1996, sec. 6) say they are:
    the 30 corner faces subtend 0.14949 sr and the 10 central faces 0.17985 sr (spread max/min =
    1.2031), against 2 pi / 40 = 0.15708 sr. Areas are exact (Van Oosterom & Strackee 1983:
    tan(Omega/2) = |a.(b x c)| / (1 + a.b + b.c + c.a)); their sum is 2 pi to rounding.

    Koenderink et al. count 820 reciprocal data values (40 * 41 / 2) and 66 with isotropy.
    For this orientation the face-pair classes under isotropy (equal theta_i, theta_o and
    |phi_i - phi_o| up to exchange, i.e. the orbits of the tessellation's own symmetry group
    C5v) number 96; we could not reproduce 66. Both exceed the 55 unknowns of an isotropic
    order 8 fit (``HelmholtzModes(8).size``), so that fit is overdetermined either way.

    Examples
    --------
    >>> t = tessellate_hemisphere()
    >>> t.size, round(float(t.solid_angles.sum() / np.pi), 12)
    (40, 2.0)
    """
    k = nonneg_int(subdivisions, "subdivisions", maximum=5)
    if k < 1:
        raise ValueError(f"subdivisions must be >= 1 (0 leaves faces straddling the equator), "
                         f"got {k}")
    ring = 2 * np.pi * np.arange(5) / 5
    r, h = 2 / np.sqrt(5), 1 / np.sqrt(5)
    verts = np.vstack([
        [[0.0, 0.0, 1.0]],
        np.stack([r * np.cos(ring), r * np.sin(ring), np.full(5, h)], axis=1),
        np.stack([r * np.cos(ring + np.pi / 5), r * np.sin(ring + np.pi / 5), np.full(5, -h)],
                 axis=1),
        [[0.0, 0.0, -1.0]],
    ])
    faces = []
    for i in range(5):
        a, b, c, d = 1 + i, 1 + (i + 1) % 5, 6 + i, 6 + (i + 1) % 5
        faces += [(0, a, b), (a, c, b), (b, c, d), (c, 11, d)]
    f = np.array(faces, dtype=np.int64)
    for _ in range(k):
        verts, f = _subdivide(verts, f)
    z = verts[f][..., 2]
    f = f[np.all(z > -1e-12, axis=1)]
    used, f = np.unique(f, return_inverse=True)
    f = f.reshape(-1, 3)
    verts = verts[used]
    verts[np.abs(verts[:, 2]) < 1e-12, 2] = 0.0  # equator vertices exactly on it
    verts /= np.linalg.norm(verts, axis=1, keepdims=True)
    a, b, c = verts[f[:, 0]], verts[f[:, 1]], verts[f[:, 2]]
    num = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = 1 + np.einsum("ij,ij->i", a, b) + np.einsum("ij,ij->i", b, c) \
        + np.einsum("ij,ij->i", c, a)
    areas = 2 * np.arctan2(np.abs(num), den)
    cen = a + b + c
    cen /= np.linalg.norm(cen, axis=1, keepdims=True)
    return Tessellation(verts, f, cen, areas)


def _subdivide(verts: NDArray, faces: NDArray) -> tuple[NDArray, NDArray]:
    """Split each triangle into four at its edge midpoints (projected onto the sphere)."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]),
                    axis=1)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    mids = verts[uniq[:, 0]] + verts[uniq[:, 1]]
    mids /= np.linalg.norm(mids, axis=1, keepdims=True)
    nf = faces.shape[0]
    ab, bc, ca = (len(verts) + inv.reshape(-1)[j * nf:(j + 1) * nf] for j in range(3))
    a, b, c = faces.T
    new = np.concatenate([np.stack(t, axis=1) for t in
                          ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return np.vstack([verts, mids]), new


# -- binning -----------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class BinnedSamples:
    """Measurements binned face by face: the data matrix of Koenderink et al. (1996, sec. 6).

    Attributes
    ----------
    mean : (faces, faces) or (faces, faces, channels) ndarray of float
        Mean value of the samples with w_i in face i and w_o in face o; NaN where empty.
    counts : (faces, faces) ndarray of int
        Number of samples per cell.
    tessellation : Tessellation
    """

    mean: NDArray[np.float64]
    counts: NDArray[np.int64]
    tessellation: Tessellation

    def samples(self) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Return (wi, wo, values, weights) of the occupied cells at the face centroids.

        Pass them to :func:`fit` (``fit(wi, wo, values, basis, weights=weights)``): the
        weights are the counts, so the fit treats every original sample as if it had been
        measured at its face centroid.
        """
        i, o = np.nonzero(self.counts)
        c = self.tessellation.centroids
        return c[i], c[o], self.mean[i, o], self.counts[i, o].astype(np.float64)


def bin_samples(wi: ArrayLike, wo: ArrayLike, values: ArrayLike,
                tessellation: Tessellation | None = None) -> BinnedSamples:
    """Average measurements over the faces of a tessellation (a 40 x 40 matrix by default).

    This is the 40 x 40 data matrix of Koenderink, van Doorn & Stavridi (1996, sec. 6).

    Parameters
    ----------
    wi, wo : (n, 3) array_like of float
        Unit vectors in the upper hemisphere.
    values : (n,) or (n, channels) array_like of float
    tessellation : Tessellation, optional
        Default :func:`tessellate_hemisphere` ().

    Returns
    -------
    BinnedSamples

    Examples
    --------
    >>> t = tessellate_hemisphere()
    >>> b = bin_samples(t.centroids[:2], t.centroids[2:4], [1.0, 3.0], t)
    >>> b.mean.shape, int(b.counts.sum()), float(b.mean[0, 2])
    ((40, 40), 2, 1.0)
    """
    wi, wo, n = _check_pairs(wi, wo)
    y, scalar = _check_values(values, n)
    t = tessellate_hemisphere() if tessellation is None else tessellation
    if not isinstance(t, Tessellation):
        raise TypeError(f"tessellation must be a Tessellation, got {type(t).__name__}")
    f = t.size
    cell = t.locate(wi) * f + t.locate(wo)
    counts = np.bincount(cell, minlength=f * f)
    sums = np.stack([np.bincount(cell, weights=y[:, c], minlength=f * f)
                     for c in range(y.shape[1])], axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts[:, None] > 0, sums / counts[:, None], np.nan)
    mean = mean.reshape(f, f, -1)
    return BinnedSamples(mean[..., 0] if scalar else mean, counts.reshape(f, f), t)


# -- plain tables ------------------------------------------------------------------------------
def read_table(path: str | PathLike) -> tuple[NDArray, NDArray, NDArray]:
    """Read tabular BRDF measurements from a text file.

    Parameters
    ----------
    path : str or path-like
        Text with one measurement per line: theta_i, phi_i, theta_o, phi_o in DEGREES, then
        one value column or three (RGB), in 1/sr. Cells are separated by commas or by
        whitespace (not both in one line); '#' starts a comment; blank lines are skipped.
        theta must lie in [0, 90]; phi is any finite angle. Numbers are written in ASCII
        digits (no ``_`` separators); UTF-8, with or without a byte-order mark.

    Returns
    -------
    wi, wo : (n, 3) ndarray of float
        Unit vectors (z the surface normal).
    values : (n,) or (n, 3) ndarray of float

    Raises
    ------
    ValueError
        Naming the line, for a wrong number of columns, a cell that is not a number, a
        non-finite cell, or theta outside [0, 90]; or if the file holds no data, or is not
        a regular file (a FIFO, a device).
    """
    rows: list[list[float]] = []
    ncol = None
    regular_file(path, "table file")  # a FIFO would block open()
    with open(path, encoding="utf-8-sig") as fh:  # a byte-order mark is not a cell
        for lineno, raw in enumerate(fh, start=1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            cells = [c.strip() for c in line.split(",")] if "," in line else re.split(r"\s+",
                                                                                   line)
            if ncol is None:
                if len(cells) not in (5, 7):
                    raise ValueError(f"line {lineno}: a row must have 5 columns (theta_i, phi_i, "
                                     "theta_o, phi_o in degrees, value) or 7 (... R, G, B), got "
                                     f"{len(cells)}")
                ncol = len(cells)
            elif len(cells) != ncol:
                raise ValueError(f"line {lineno}: every row must have {ncol} columns like the "
                                 f"first, got {len(cells)}")
            row = []
            for j, cell in enumerate(cells):
                try:
                    x = number(cell)  # float() would also read "1_5" and non-ASCII digits
                except ValueError as exc:
                    raise ValueError(f"line {lineno}, column {j + 1}: cell {exc} (comment out "
                                     "header lines with '#')") from None
                if not np.isfinite(x):
                    raise ValueError(f"line {lineno}, column {j + 1}: cell must be finite, got "
                                     f"{cell!r}")
                row.append(x)
            for j in (0, 2):
                if not 0.0 <= row[j] <= 90.0:
                    name = "theta_i" if j == 0 else "theta_o"
                    raise ValueError(f"line {lineno}: {name} must lie in [0, 90] degrees, got "
                                     f"{row[j]:g}")
            rows.append(row)
    if not rows:
        raise ValueError(f"{path}: the file must hold at least one data row, got none")
    a = np.array(rows)
    rad = np.radians(a[:, :4])
    wi = from_angles(rad[:, 0], rad[:, 1])
    wo = from_angles(rad[:, 2], rad[:, 3])
    values = a[:, 4] if a.shape[1] == 5 else a[:, 4:]
    return wi, wo, values
