"""Making a coefficient matrix smaller: truncation, smoothing, low rank, storage precision.

Every operation returns a new :class:`basis.CoefficientMatrix` of the same form (a symmetric
matrix stays symmetric, so the result is still exactly reciprocal; a general one,
``reciprocal=False``, stays general) and records what it did, and what it cost, in ``info``:

- :func:`truncate`: keep the basis functions of degree <= order (a prefix of every basis).
- :func:`smooth`: multiply entry (j, k) by w(d_j) w(d_k), d the degree, with w a
  half-Gaussian (Westin, Arvo & Torrance 1992, sec. 2.5, after Cabral et al. 1987), the Lanczos
  sigma factors or a Hann window. The separable product keeps M symmetric. Reports the
  fraction of negative BRDF values and the Gibbs overshoot before and after.
- :func:`lowrank`: the symmetric eigen-decomposition of each block (isotropic) or of the
  dense matrix, per channel, keeping the ``rank`` terms of largest |eigenvalue|; for a
  general matrix the singular value decomposition instead (Eckart-Young holds for both).
- :func:`precision`: coefficients rounded to float32 or float16, with the error that costs.

Errors of coefficient changes are exact L2 errors of the represented quantity q (Parseval:
the basis is orthonormal on H x H): ||q - q'|| = ||M - M'||_F, per channel; for the isotropic
storage the Frobenius norm counts each block m > 0 twice (its cos-cos and sin-sin copies).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from basis import CoefficientMatrix
from basis.validation import choice, nonneg_int

from .evaluate import evaluate

__all__ = ["SMOOTHING", "Ringing", "lowrank", "precision", "ringing", "smooth",
           "smoothing_factors", "truncate", "unique_coefficients"]

#: Window kinds accepted by :func:`smooth`.
SMOOTHING = ("half-gaussian", "lanczos", "hann")
#: Storage precisions accepted by :func:`precision`.
PRECISIONS = ("float64", "float32", "float16")
#: Direction pairs (seeded, uniform in solid angle on H x H) used by :func:`ringing`.
RINGING_PAIRS = 1 << 15


def _check_cm(cm: object) -> CoefficientMatrix:
    if not isinstance(cm, CoefficientMatrix):
        raise TypeError(f"cm must be a basis.CoefficientMatrix, got {type(cm).__name__}")
    return cm


def _with(cm: CoefficientMatrix, stored: list[NDArray] | NDArray, info: dict) -> CoefficientMatrix:
    """Return a matrix like ``cm`` with new (channels-first) blocks or dense matrix and info."""
    scalar = cm.is_scalar
    if cm.is_isotropic:
        return CoefficientMatrix.from_blocks(cm.basis, [b[0] if scalar else b for b in stored],
                                             cm.quantity, info=info, reciprocal=cm.reciprocal)
    return CoefficientMatrix(cm.basis, stored[0] if scalar else stored, cm.quantity,
                             isotropic=False, info=info, reciprocal=cm.reciprocal)


def _stored(cm: CoefficientMatrix) -> list[NDArray] | NDArray:
    stored = [b.copy() for b in cm.stored]
    return stored if cm.is_isotropic else stored[0]


def _frobenius2(cm_stored: list[NDArray] | NDArray) -> NDArray[np.float64]:
    """||M||_F^2 per channel of the full matrix (blocks m > 0 count twice)."""
    if isinstance(cm_stored, list):
        return sum((1.0 if m == 0 else 2.0) * np.sum(b * b, axis=(1, 2))
                   for m, b in enumerate(cm_stored))
    return np.sum(cm_stored * cm_stored, axis=(1, 2))


def _rel_change(a: list[NDArray] | NDArray, b: list[NDArray] | NDArray) -> float:
    """Return the max over channels of ||A - B||_F / ||A||_F (the relative L2 change of q)."""
    if isinstance(a, list):
        diff = [x - y for x, y in zip(a, b, strict=True)]
    else:
        diff = a - b
    num, den = _frobenius2(diff), _frobenius2(a)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.where(den > 0, np.sqrt(num / np.where(den > 0, den, 1.0)), np.sqrt(num))
    return float(np.max(rel))


# -- truncation ---------------------------------------------------------------------------------
def truncate(cm: CoefficientMatrix, order: int) -> CoefficientMatrix:
    """Restrict the matrix to the basis functions of degree <= ``order``.

    Parameters
    ----------
    cm : basis.CoefficientMatrix
    order : int
        0 <= order <= cm.order (inclusive).

    Returns
    -------
    basis.CoefficientMatrix
        In ``cm.basis.truncate(order)``; ``info`` gains ``truncated_from`` (the original
        order) and ``truncation_change``: the relative L2 norm of the dropped coefficients,
        max over channels (by Parseval, the relative L2 change of q).

    Examples
    --------
    Lambert is one coefficient on the degree-1 harmonic, so it survives every truncation
    down to order 1:

    >>> import numpy as np
    >>> from basis import HemiHarmonics, CoefficientMatrix
    >>> hb = HemiHarmonics(6)
    >>> M = np.zeros((hb.size, hb.size)); M[0, 0] = 1 / 3
    >>> t = truncate(CoefficientMatrix(hb, M), 1)
    >>> t.basis, t.matrix.tolist(), t.info["truncation_change"]
    (HemiHarmonics(1, parity='odd'), [[0.3333333333333333]], 0.0)
    """
    cm = _check_cm(cm)
    order = nonneg_int(order, "order", maximum=cm.order, why=f" (the order of {cm!r})")
    out = cm.truncate(order)
    full = _stored(cm)
    kept = _stored(out)
    if isinstance(full, list):
        padded = []
        for m, b in enumerate(full):
            p = np.zeros_like(b)
            if m < len(kept):
                k = kept[m].shape[-1]
                p[:, :k, :k] = kept[m]
            padded.append(p)
    else:
        padded = np.zeros_like(full)
        k = kept.shape[-1]
        padded[:, :k, :k] = kept
    out.info = dict(cm.info, truncated_from=cm.order,
                    truncation_change=_rel_change(full, padded))
    return out


# -- smoothing ----------------------------------------------------------------------------------
def smoothing_factors(kind: str, order: int, *, start: int | None = None,
                      width: float | None = None) -> NDArray[np.float64]:
    """Return the attenuation w(d) for degrees d = 0..order.

    Parameters
    ----------
    kind : {"half-gaussian", "lanczos", "hann"}
        ``"half-gaussian"``: w = 1 for d <= start, exp(-(d - start)^2 / (2 width^2)) above
        (Westin et al. 1992, sec. 2.5; the paper gives no values, these defaults are ours).
        ``"lanczos"``: the Lanczos sigma factors w = sinc(d / (order + 1)) =
        sin(pi d / (order + 1)) / (pi d / (order + 1)). ``"hann"``: w = (1 + cos(pi d /
        (order + 1))) / 2. The last two vanish at d = order + 1, the first degree dropped.
    order : int
    start : int, optional
        Half-Gaussian only: l_filter, the last degree left untouched (default order // 2).
    width : float, optional
        Half-Gaussian only: standard deviation in degrees (default (order - start) / 2, so
        the last degree is attenuated by exp(-2) = 0.135; at least 0.5).

    Returns
    -------
    (order + 1,) ndarray

    Examples
    --------
    >>> smoothing_factors("hann", 3).round(6).tolist()
    [1.0, 0.853553, 0.5, 0.146447]
    >>> smoothing_factors("half-gaussian", 4, start=2, width=1.0).round(6).tolist()
    [1.0, 1.0, 1.0, 0.606531, 0.135335]
    """
    kind = choice(kind, "kind", SMOOTHING)
    order = nonneg_int(order, "order")
    d = np.arange(order + 1, dtype=np.float64)
    if kind != "half-gaussian":
        if start is not None or width is not None:
            raise ValueError(f"start and width apply to kind='half-gaussian' only, got "
                             f"kind={kind!r} with start={start!r}, width={width!r}")
        x = d / (order + 1)
        return np.sinc(x) if kind == "lanczos" else 0.5 * (1.0 + np.cos(np.pi * x))
    start = order // 2 if start is None else nonneg_int(start, "start")
    if width is None:
        width = max(0.5, (order - start) / 2.0)
    if not (isinstance(width, int | float) and np.isfinite(width) and width > 0):
        raise ValueError(f"width must be a positive number of degrees, got {width!r}")
    excess = np.maximum(d - start, 0.0)
    return np.exp(-0.5 * (excess / float(width)) ** 2)


def smooth(cm: CoefficientMatrix, kind: str = "half-gaussian", *, start: int | None = None,
           width: float | None = None, brdf: Any = None) -> CoefficientMatrix:
    """Attenuate high degrees to reduce Gibbs ringing, symmetrically (reciprocity is kept).

    The same factors apply to rows (w_i) and columns (w_o), so a symmetric matrix stays
    symmetric and a general one general.

    Parameters
    ----------
    cm : basis.CoefficientMatrix
    kind, start, width
        See :func:`smoothing_factors`; the factors are those of ``cm.order``.
    brdf : BRDF, optional
        The function ``cm`` approximates; when given, the overshoot is measured against it.

    Returns
    -------
    basis.CoefficientMatrix
        Entry (j, k) multiplied by w(d_j) w(d_k). ``info["smoothing"]`` holds ``kind``,
        ``start``, ``width`` (None unless half-Gaussian), ``factors``, ``change`` (relative
        L2 change of q), and ``before`` / ``after``: :class:`Ringing` reports as dicts.

    Notes
    -----
    Smoothing (the half-Gaussian is that of Westin, Arvo & Torrance 1992, sec. 2.5) changes
    the directional albedo slightly, since it also attenuates zonal coefficients that
    contribute to it, and does not guarantee non-negativity: check ``after``.
    """
    cm = _check_cm(cm)
    w = smoothing_factors(kind, cm.order, start=start, width=width)
    deg = cm.basis.degree
    full = _stored(cm)
    if isinstance(full, list):
        cos_idx = cm.basis.azimuthal_blocks().cos
        new = []
        for b, idx in zip(full, cos_idx, strict=True):
            f = w[deg[idx]]
            new.append(b * f[None, :, None] * f[None, None, :])
    else:
        f = w[deg]
        new = full * f[None, :, None] * f[None, None, :]
    report = dict(kind=kind, start=None, width=None, factors=w,
                  change=_rel_change(full, new))
    if kind == "half-gaussian":
        report["start"] = cm.order // 2 if start is None else int(start)
        report["width"] = float(max(0.5, (cm.order - report["start"]) / 2.0)
                                if width is None else width)
    out = _with(cm, new, dict(cm.info))
    report["before"] = asdict(ringing(cm, brdf))
    report["after"] = asdict(ringing(out, brdf))
    out.info["smoothing"] = report
    return out


@dataclass(frozen=True)
class Ringing:
    """Ringing of a representation on a fixed set of direction pairs.

    Attributes
    ----------
    negative_fraction : float
        Fraction of the pairs where the represented BRDF is < 0.
    min_value : float
        Smallest represented BRDF value (1/sr).
    overshoot : float or None
        (max f_hat - max f) / max f: how far the representation exceeds the largest value of
        the BRDF (0 when it does not); None without a reference BRDF.
    pairs : int
        Number of direction pairs.
    """

    negative_fraction: float
    min_value: float
    overshoot: float | None
    pairs: int


def ringing(cm: CoefficientMatrix, brdf: Any = None, *, pairs: int = RINGING_PAIRS,
            seed: int = 0) -> Ringing:
    """Measure the negative values and Gibbs overshoot of ``cm`` on seeded random pairs.

    Parameters
    ----------
    cm : basis.CoefficientMatrix
    brdf : BRDF, optional
        Reference for the overshoot.
    pairs : int
        Direction pairs, uniform in solid angle on H x H, with theta < 80 degrees for both
        directions (the grazing band is left out: quantity "f_cos" divides by the cosines
        there).
    seed : int

    Returns
    -------
    Ringing
    """
    cm = _check_cm(cm)
    pairs = nonneg_int(pairs, "pairs")
    wi, wo = _random_pairs(pairs, seed, max_theta=np.radians(80.0))
    v = np.asarray(evaluate(cm, wi, wo)).reshape(pairs, -1)
    neg = float(np.mean(v < 0)) if v.size else 0.0
    low = float(v.min()) if v.size else 0.0
    over = None
    if brdf is not None:
        ref = np.asarray(brdf.eval(wi, wo), dtype=np.float64).reshape(pairs, -1)
        top = np.max(ref, axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            o = np.where(top > 0, (np.max(v, axis=0) - top) / np.where(top > 0, top, 1.0), 0.0)
        over = float(max(0.0, np.max(o)))
    return Ringing(negative_fraction=neg, min_value=low, overshoot=over, pairs=pairs)


def _random_pairs(n: int, seed: int, *, max_theta: float = np.pi / 2
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Draw n pairs uniform in solid angle on the cap theta <= max_theta (each direction)."""
    rng = np.random.default_rng(seed)
    zmin = np.cos(max_theta)
    out = []
    for _ in range(2):
        z = rng.uniform(zmin, 1.0, n)
        phi = rng.uniform(0.0, 2.0 * np.pi, n)
        s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
        out.append(np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1))
    return out[0], out[1]


# -- low rank -----------------------------------------------------------------------------------
def lowrank(cm: CoefficientMatrix, rank: int) -> CoefficientMatrix:
    """Return the best approximation of the same form with ``rank`` separable terms per channel.

    Parameters
    ----------
    cm : basis.CoefficientMatrix
    rank : int
        Number of terms kept per channel, >= 1. Symmetric (reciprocal) matrices: eigen-terms
        lambda u u^T; general ones (``cm.reciprocal`` False): singular terms s u v^T (the
        truncated SVD). Isotropic matrices: the terms of all blocks compete, and a term of
        block m > 0 stands for its cos and sin copies (two dense terms sharing one value and
        its stored vectors). Dense matrices: the terms of the full matrix.

    Returns
    -------
    basis.CoefficientMatrix
        Sum of the kept terms lambda u u^T (or s u v^T), chosen by the L2 error each
        removes (multiplicity x lambda^2, largest first; ties by block order), which is
        optimal for a budget of stored terms.
        ``info["lowrank"]`` holds ``rank``, ``error`` (relative L2 change of q, exact by
        Parseval and Eckart-Young: sqrt of the dropped sum of (multiplicity) lambda^2 over
        the total), ``numbers`` (stored reals, all channels: per symmetric term one
        eigenvalue and its vector, 1 + k; per general term one singular value and two
        vectors, 1 + 2 k) and ``eigenvalues`` ((channels, rank) kept, ordered), or for a
        general matrix ``singular_values``.

    Examples
    --------
    A rank-1 matrix is reproduced exactly by one term:

    >>> import numpy as np
    >>> from basis import HemiZernike, CoefficientMatrix
    >>> zb = HemiZernike(4)
    >>> u = np.zeros(zb.size); u[zb.azimuthal == 0] = [1.0, -2.0, 0.5]
    >>> cm = CoefficientMatrix(zb, np.outer(u, u))
    >>> r = lowrank(cm, 1)
    >>> err = r.info["lowrank"]["error"]
    >>> bool(np.allclose(r.matrix, cm.matrix, rtol=0, atol=1e-14)), err < 1e-15
    (True, True)
    """
    cm = _check_cm(cm)
    rank = nonneg_int(rank, "rank")
    if rank < 1:
        raise ValueError(f"rank must be >= 1, got {rank}")
    full = _stored(cm)
    blocks = full if isinstance(full, list) else [full]
    mult = [1.0 if (m == 0 or not cm.is_isotropic) else 2.0 for m in range(len(blocks))]
    nch = blocks[0].shape[0]
    new = [np.zeros_like(b) for b in blocks]
    kept_vals = np.zeros((nch, rank))
    numbers = 0
    total_terms = sum(b.shape[-1] for b in blocks)
    if rank > total_terms:
        raise ValueError(f"rank must be <= {total_terms} (the number of eigen-terms of "
                         f"{cm!r}), got {rank}")
    sym = cm.reciprocal
    for c in range(nch):
        terms = []  # (multiplicity lambda^2, block, index)
        decomp = []
        for m, b in enumerate(blocks):
            k = b.shape[-1]
            if sym:
                lam, vec = np.linalg.eigh(b[c]) if k else (np.empty(0), np.empty((0, 0)))
                left = right = vec
            else:
                left, lam, rt = (np.linalg.svd(b[c]) if k
                                 else (np.empty((0, 0)), np.empty(0), np.empty((0, 0))))
                right = rt.T
            decomp.append((lam, left, right))
            terms.extend((mult[m] * float(x) ** 2, m, i) for i, x in enumerate(lam))
        terms.sort(key=lambda t: (-t[0], t[1], t[2]))
        for r, (_, m, i) in enumerate(terms[:rank]):
            lam, left, right = decomp[m]
            u, v = left[:, i], right[:, i]
            new[m][c] += lam[i] * np.outer(u, v)
            kept_vals[c, r] = lam[i]
            numbers += 1 + u.size * (1 if sym else 2)
    if sym:  # make each block exactly symmetric (outer products are symmetric up to rounding)
        new = [0.5 * (b + b.swapaxes(-1, -2)) for b in new]
    stored_new: list[NDArray] | NDArray = new if isinstance(full, list) else new[0]
    info = dict(cm.info)
    info["lowrank"] = dict(rank=rank, error=_rel_change(full, stored_new), numbers=numbers,
                           **{"eigenvalues" if sym else "singular_values": kept_vals})
    return _with(cm, stored_new, info)


# -- storage precision --------------------------------------------------------------------------
def precision(cm: CoefficientMatrix, dtype: str) -> CoefficientMatrix:
    """Round the coefficients of the matrix to a storage precision (held as float64).

    Parameters
    ----------
    cm : basis.CoefficientMatrix
    dtype : {"float64", "float32", "float16"}

    Returns
    -------
    basis.CoefficientMatrix
        ``info["precision"]``: ``dtype``, ``bytes`` (the unique coefficients, symmetric or
        general storage (:func:`unique_coefficients`), at that precision: what
        ``compress.save(..., dtype=...)`` writes),
        ``error`` (relative L2 change of q, exact by Parseval) and ``max_abs`` (largest
        coefficient change).

    Raises
    ------
    ValueError
        If a coefficient exceeds the largest finite value of ``dtype``.

    Examples
    --------
    >>> import numpy as np
    >>> from basis import HemiZernike, CoefficientMatrix
    >>> zb = HemiZernike(2)
    >>> cm = CoefficientMatrix(zb, np.eye(zb.size) / 3)
    >>> p = precision(cm, "float16")
    >>> p.info["precision"]["bytes"], f'{p.info["precision"]["error"]:.2e}'
    (10, '2.44e-04')
    """
    cm = _check_cm(cm)
    dtype = choice(dtype, "dtype", PRECISIONS)
    full = _stored(cm)
    blocks = full if isinstance(full, list) else [full]
    top = float(np.finfo(dtype).max)
    worst = max(float(np.max(np.abs(b), initial=0.0)) for b in blocks)
    if worst > top:
        raise ValueError(f"dtype {dtype!r} cannot hold coefficients up to {worst:.6g} (its "
                         f"largest finite value is {top:.6g})")
    new = [b.astype(dtype).astype(np.float64) for b in blocks]
    stored_new: list[NDArray] | NDArray = new if isinstance(full, list) else new[0]
    info = dict(cm.info)
    info["precision"] = dict(
        dtype=dtype, bytes=unique_coefficients(cm) * np.dtype(dtype).itemsize,
        error=_rel_change(full, stored_new),
        max_abs=max(float(np.max(np.abs(a - b), initial=0.0)) for a, b in zip(blocks, new,
                                                                               strict=True)))
    return _with(cm, stored_new, info)


def unique_coefficients(cm: CoefficientMatrix) -> int:
    """Count the real numbers stored with symmetric (and, if isotropic, block) storage.

    All channels are counted. A symmetric block (or dense matrix) of side k holds
    k (k + 1) / 2 numbers, a general one (``cm.reciprocal`` False) k^2.

    Examples
    --------
    >>> import numpy as np
    >>> from basis import HemiZernike, CoefficientMatrix
    >>> zb = HemiZernike(2)
    >>> M = np.arange(36.0).reshape(6, 6)
    >>> unique_coefficients(CoefficientMatrix(zb, M, reciprocal=False, isotropic=False))
    36
    >>> unique_coefficients(CoefficientMatrix(zb, M, symmetrize=True, isotropic=False))
    21
    """
    cm = _check_cm(cm)
    blocks = cm.stored
    if not cm.reciprocal:
        return int(sum(b.shape[0] * b.shape[-1] ** 2 for b in blocks))
    return int(sum(b.shape[0] * b.shape[-1] * (b.shape[-1] + 1) // 2 for b in blocks))
