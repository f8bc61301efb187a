"""Fast evaluation of isotropic coefficient matrices: one fused numba kernel per call.

For an isotropic matrix held as blocks B_m (one per azimuthal order m), every basis function
with azimuthal order m separates as b(w) = s(w)^m g(w) p(x(w)) A(phi), so

    q(w_i, w_o) = g_i g_o sum_m Re[(a_i conj(a_o))^m] p_m(x_i)^T B_m p_m(x_o),

with a(w) = s e^{i phi} formed from (x + i y) without trigonometry, and p_m the polynomial
factors of the block's functions. Writing p_m = V_m T(x) in Chebyshev polynomials T_0..T_{k-1}
(of the same count k_m as the block has functions, so nothing is lost) turns each block into
C_m = V_m^T B_m V_m; then per pair the kernel needs the Chebyshev values of x_i and x_o once
(shared by every block), k_m^2 multiply-adds per block and channel, and one complex
multiplication per block. No basis table is materialised.

==================  ================  =================  ======  ===========================
basis               a(w)              x(w)               g(w)    functions of order m
==================  ================  =================  ======  ===========================
HemiZernike         (x+iy)/sqrt(1+z)  1 - 2z (2rho^2-1)  1       n = m, m+2, ... <= order
HemiHarmonics odd   x + iy            2z^2 - 1           z       l = m+1, m+3, ...
HemiHarmonics even  x + iy            2z^2 - 1           1       l = m, m+2, ...
SphericalHarmonics  x + iy            z                  1       l = m, m+1, ...
==================  ================  =================  ======  ===========================

The change of basis V_m is found by least squares on Chebyshev nodes from the basis' own
values (``project.radial_table``); the kernel agrees with ``CoefficientMatrix.eval`` to
about 1e-13 relative at order 16 (tests). Grazing directions are handled exactly as in
``CoefficientMatrix.eval`` (lifted to ``min_cos`` for ``quantity="f_cos"``).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

import basis
from basis import CoefficientMatrix
from basis.jit import pjit, prange
from basis.validation import as_directions, broadcast_batch
from project import radial_table

__all__ = ["FastEvaluator", "evaluate"]

_KINDS = {"zernike": 0, "odd": 1, "even": 2, "sh": 3}
#: Pairs per task of the parallel loop (scratch arrays are allocated once per task).
_CHUNK = 128


class FastEvaluator:
    """A compiled evaluator for one isotropic :class:`basis.CoefficientMatrix`.

    Parameters
    ----------
    cm : basis.CoefficientMatrix
        Must be isotropic (block form); any basis of this package.
    min_cos : float
        As in :meth:`basis.CoefficientMatrix.eval`.

    Notes
    -----
    Building the evaluator costs a few small least-squares fits (microseconds to
    milliseconds); evaluation then runs at tens of millions of pairs per second on two cores
    at order 8 (``tests/benchmarks/bench_compress.py``).

    Examples
    --------
    >>> import numpy as np
    >>> from basis import HemiZernike, CoefficientMatrix
    >>> zb = HemiZernike(2)
    >>> M = np.zeros((zb.size, zb.size)); M[0, 0] = 1.0
    >>> cm = CoefficientMatrix(zb, M, quantity="f")
    >>> w = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    >>> bool(np.allclose(FastEvaluator(cm)(w, w[::-1]), cm.eval(w, w[::-1]), rtol=1e-13))
    True
    """

    def __init__(self, cm: CoefficientMatrix, *, min_cos: float = 1e-3) -> None:
        if not isinstance(cm, CoefficientMatrix):
            raise TypeError(f"cm must be a basis.CoefficientMatrix, got {type(cm).__name__}")
        if not cm.is_isotropic:
            raise ValueError("cm must be isotropic (block form) for the fast evaluator; use "
                             "cm.eval for dense matrices or cm.to_isotropic()")
        if not 0.0 < min_cos < 1.0:
            raise ValueError(f"min_cos must lie in (0, 1), got {min_cos!r}")
        self.cm = cm
        self.min_cos = float(min_cos)
        self.kind = _kind(cm.basis)
        self.coef, self.tri = _chebyshev_blocks(cm)
        self.fcos = cm.quantity == "f_cos"

    @property
    def channels(self) -> int:
        return self.cm.channels

    def __call__(self, wi: ArrayLike, wo: ArrayLike) -> NDArray[np.float64]:
        """BRDF values, as :meth:`basis.CoefficientMatrix.eval` (same shapes, same zeros)."""
        wi = as_directions(wi, "wi")
        wo = as_directions(wo, "wo")
        shape = broadcast_batch(wi, wo)
        a = np.ascontiguousarray(np.broadcast_to(wi, (*shape, 3)).reshape(-1, 3))
        b = np.ascontiguousarray(np.broadcast_to(wo, (*shape, 3)).reshape(-1, 3))
        out = np.empty((a.shape[0], self.coef.shape[1]))
        self.eval_flat(a, b, out)
        out = out.reshape(*shape, out.shape[-1])
        return out[..., 0] if self.cm._scalar else out

    def eval_flat(self, wi: NDArray[np.float64], wo: NDArray[np.float64],
                  out: NDArray[np.float64]) -> None:
        """No-validation path: (n, 3) C-contiguous float64 unit vectors, out (n, channels)."""
        _iso_kernel(wi, wo, self.coef, self.tri, _KINDS[self.kind], self.fcos,
                    self.min_cos, out)


def evaluate(cm: CoefficientMatrix, wi: ArrayLike, wo: ArrayLike, *,
             min_cos: float = 1e-3) -> NDArray[np.float64]:
    """BRDF values of ``cm``: the fast kernel when isotropic, ``cm.eval`` otherwise.

    Parameters
    ----------
    cm : basis.CoefficientMatrix
    wi, wo : (..., 3) array_like of float
    min_cos : float

    Returns
    -------
    (...) or (..., channels) ndarray, as :meth:`basis.CoefficientMatrix.eval`.
    """
    if isinstance(cm, CoefficientMatrix) and cm.is_isotropic:
        return FastEvaluator(cm, min_cos=min_cos)(wi, wo)
    if not isinstance(cm, CoefficientMatrix):
        raise TypeError(f"cm must be a basis.CoefficientMatrix, got {type(cm).__name__}")
    return cm.eval(wi, wo, min_cos=min_cos)


def _kind(b: basis.Basis) -> str:
    if isinstance(b, basis.HemiZernike):
        return "zernike"
    if isinstance(b, basis.HemiHarmonics):
        return b.parity
    if isinstance(b, basis.SphericalHarmonics):
        return "sh"
    raise NotImplementedError(f"no fast evaluator for {b!r}; supported: HemiZernike, "
                              "HemiHarmonics, SphericalHarmonics")


def _factors(kind: str, z: NDArray, m: int) -> tuple[NDArray, NDArray]:
    """(x(z), s^m g) on the azimuth where the cos functions equal their radial factor."""
    if kind == "zernike":
        return 1.0 - 2.0 * z, np.sqrt(1.0 - z) ** m
    s = np.sqrt((1.0 - z) * (1.0 + z))
    if kind == "sh":
        return z, s**m
    g = z if kind == "odd" else 1.0
    return 2.0 * z * z - 1.0, s**m * g


def _chebyshev_blocks(cm: CoefficientMatrix) -> tuple[NDArray, NDArray]:
    """Packed Chebyshev blocks (blocks, channels, K) and the packed length of each block.

    C_m = V_m^T B_m V_m is symmetric; its upper triangle is packed column by column
    (entry (a, b), a <= b, at b (b + 1) / 2 + a), so the triangle of any leading k x k
    sub-block is a prefix of length k (k + 1) / 2: every block shares the products
    S_ab = T_a(x_i) T_b(x_o) + T_b(x_i) T_a(x_o) (a < b), S_aa = T_a(x_i) T_a(x_o).
    """
    from basis.matrix import _azimuthal_groups

    kind = _kind(cm.basis)
    cos_idx, _ = _azimuthal_groups(cm.basis)
    blocks = cm._blocks
    sizes = np.array([i.size for i in cos_idx], dtype=np.int64)
    kmax = int(sizes.max()) if sizes.size else 0
    nch = blocks[0].shape[0]
    packed_len = kmax * (kmax + 1) // 2
    coef = np.zeros((len(blocks), nch, max(packed_len, 1)))
    nodes = 2 * kmax + 8  # Chebyshev nodes in x, interior; z from x (monotone map)
    t = np.cos(np.pi * (np.arange(nodes) + 0.5) / nodes)
    if kind == "zernike":
        z = (1.0 - t) / 2.0
    elif kind == "sh":
        z = t
    else:
        z = np.sqrt((t + 1.0) / 2.0)
    table = radial_table(cm.basis, z)
    cheb = np.polynomial.chebyshev.chebvander(t, max(kmax - 1, 0))
    bb, aa = np.triu_indices(kmax)[::-1]  # not used for ordering; see below
    del aa, bb
    cols = [(a, b) for b in range(kmax) for a in range(b + 1)]
    ia = np.array([c[0] for c in cols], dtype=np.int64)
    ib = np.array([c[1] for c in cols], dtype=np.int64)
    for m, idx in enumerate(cos_idx):
        k = idx.size
        if k == 0:
            continue
        _, fac = _factors(kind, z, m)
        poly = table[:, idx] / fac[:, None]  # (nodes, k) polynomial parts
        v, *_ = np.linalg.lstsq(cheb[:, :k], poly, rcond=None)  # (k cheb, k functions)
        n = k * (k + 1) // 2
        for c in range(nch):
            cm_ = v @ blocks[m][c] @ v.T
            coef[m, c, :n] = cm_[ia[:n], ib[:n]]
    return np.ascontiguousarray(coef), (sizes * (sizes + 1) // 2).astype(np.int64)


@pjit
def _iso_kernel(wi, wo, coef, tri, kind, fcos, min_cos, out):  # pragma: no cover - compiled
    # wi, wo: (n, 3) unit vectors; coef: (nb, nc, K) packed Chebyshev blocks; tri: (nb,)
    # packed length per block; kind: 0 zernike, 1 odd, 2 even, 3 sh; out: (n, nc).
    # Pairs in tasks of _CHUNK: the per-pair factors are stored lane by lane (sp: (K, chunk),
    # wm: (nb, chunk)) so the multiply-adds of phase 2 run over contiguous lanes (SIMD).
    n = wi.shape[0]
    nb, nc, npk = coef.shape[0], coef.shape[1], coef.shape[2]
    kmax = int(round((math.sqrt(8 * npk + 1) - 1) / 2))
    ntask = (n + _CHUNK - 1) // _CHUNK
    lift = min_cos if fcos else 0.0
    s_lift = math.sqrt(1.0 - lift * lift)
    for task in prange(ntask):
        ti = np.empty(kmax + 1)
        to = np.empty(kmax + 1)
        sp = np.empty((npk, _CHUNK))
        wm = np.empty((nb, _CHUNK))
        scale = np.empty(_CHUNK)
        acc = np.empty(_CHUNK)
        tot = np.empty(_CHUNK)
        p0 = task * _CHUNK
        lanes = min(n, p0 + _CHUNK) - p0
        # phase 1: per-pair factors
        for j in range(lanes):
            p = p0 + j
            ix, iy, iz = wi[p, 0], wi[p, 1], wi[p, 2]
            ox, oy, oz = wo[p, 0], wo[p, 1], wo[p, 2]
            if iz < 0.0 or oz < 0.0:  # below the horizon: 0
                for t in range(npk):
                    sp[t, j] = 0.0
                for m in range(nb):
                    wm[m, j] = 0.0
                scale[j] = 0.0
                continue
            r = 1.0 / math.sqrt(ix * ix + iy * iy + iz * iz)
            ix, iy, iz = ix * r, iy * r, iz * r
            r = 1.0 / math.sqrt(ox * ox + oy * oy + oz * oz)
            ox, oy, oz = ox * r, oy * r, oz * r
            if iz < lift:
                h = math.sqrt(ix * ix + iy * iy)
                if h > 0.0:
                    ix, iy = ix * s_lift / h, iy * s_lift / h
                else:
                    ix, iy = s_lift, 0.0
                iz = lift
            if oz < lift:
                h = math.sqrt(ox * ox + oy * oy)
                if h > 0.0:
                    ox, oy = ox * s_lift / h, oy * s_lift / h
                else:
                    ox, oy = s_lift, 0.0
                oz = lift
            # Chebyshev variable x and azimuthal factor a = s e^{i phi}
            if kind == 0:
                xi, xo = 1.0 - 2.0 * iz, 1.0 - 2.0 * oz
                fi, fo = 1.0 / math.sqrt(1.0 + iz), 1.0 / math.sqrt(1.0 + oz)
            elif kind == 3:
                xi, xo = iz, oz
                fi, fo = 1.0, 1.0
            else:
                xi, xo = 2.0 * iz * iz - 1.0, 2.0 * oz * oz - 1.0
                fi, fo = 1.0, 1.0
            ti[0] = 1.0
            to[0] = 1.0
            ti[1] = xi
            to[1] = xo
            for a in range(2, kmax):
                ti[a] = 2.0 * xi * ti[a - 1] - ti[a - 2]
                to[a] = 2.0 * xo * to[a - 1] - to[a - 2]
            t = 0
            for b in range(kmax):
                for a in range(b):
                    sp[t, j] = ti[a] * to[b] + ti[b] * to[a]
                    t += 1
                sp[t, j] = ti[b] * to[b]
                t += 1
            ar, ai = ix * fi, iy * fi
            br, bi = ox * fo, -oy * fo
            wr = ar * br - ai * bi
            wim = ar * bi + ai * br
            pr, pim = 1.0, 0.0  # Re (a_i conj a_o)^m
            for m in range(nb):
                wm[m, j] = pr
                pr, pim = pr * wr - pim * wim, pr * wim + pim * wr
            if kind == 1:  # g = z: q = z_i z_o S
                scale[j] = 1.0 if fcos else iz * oz
            else:
                scale[j] = 1.0 / (iz * oz) if fcos else 1.0
        # phase 2: sum_m wm_m sum_t C_m,t sp_t, lane-parallel
        for c in range(nc):
            for j in range(lanes):
                tot[j] = 0.0
            for m in range(nb):
                for j in range(lanes):
                    acc[j] = 0.0
                nt = tri[m]
                t = 0
                while t + 4 <= nt:  # four rows per pass: fewer loads and stores of acc
                    c0, c1 = coef[m, c, t], coef[m, c, t + 1]
                    c2, c3 = coef[m, c, t + 2], coef[m, c, t + 3]
                    for j in range(lanes):
                        acc[j] += ((c0 * sp[t, j] + c1 * sp[t + 1, j])
                                   + (c2 * sp[t + 2, j] + c3 * sp[t + 3, j]))
                    t += 4
                while t < nt:
                    cv = coef[m, c, t]
                    for j in range(lanes):
                        acc[j] += cv * sp[t, j]
                    t += 1
                for j in range(lanes):
                    tot[j] += wm[m, j] * acc[j]
            for j in range(lanes):
                out[p0 + j, c] = tot[j] * scale[j]
