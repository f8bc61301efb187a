"""Fast evaluation of coefficient matrices: q(w_i, w_o) = b(w_i)^T M b(w_o) without tables.

Isotropic matrices (one block B_m per azimuthal order m) use one fused numba kernel. Every
function of azimuthal order m separates as b(w) = s(w)^m g(w) p(x(w)) A(phi), so

    q(w_i, w_o) = g_i g_o sum_m Re[(a_i conj(a_o))^m] p_m(x_i)^T B_m p_m(x_o),

with a(w) = s e^{i phi} formed from (x + i y) without trigonometry, and p_m the polynomial
factors of the block's functions. Writing p_m = V_m T(x) in Chebyshev polynomials T_0..T_{k-1}
(of the same count k_m as the block has functions, so nothing is lost) turns each block into
C_m = V_m^T B_m V_m; then per pair the kernel needs the Chebyshev values of x_i and x_o once
(shared by every block), k_m^2 multiply-adds per block and channel, and one complex
multiplication per block. No basis table is materialised. A general (non-reciprocal) block
adds its antisymmetric part A_m = (C_m - C_m^T) / 2 on the antisymmetrised products
T_a(x_i) T_b(x_o) - T_b(x_i) T_a(x_o), a < b; symmetric blocks skip that sum.

==================  ================  =================  ======  ===========================
basis               a(w)              x(w)               g(w)    functions of order m
==================  ================  =================  ======  ===========================
HemiZernike         (x+iy)/sqrt(1+z)  1 - 2z (2rho^2-1)  1       n = m, m+2, ... <= order
HemiHarmonics odd   x + iy            2z^2 - 1           z       l = m+1, m+3, ...
HemiHarmonics even  x + iy            2z^2 - 1           1       l = m, m+2, ...
SphericalHarmonics  x + iy            z                  1       l = m, m+1, ...
==================  ================  =================  ======  ===========================

The change of basis V_m is found by least squares on Chebyshev nodes from the basis' own
radial factors (:meth:`basis.Basis.radial`); the kernel agrees with the direct product
b(w_i)^T M b(w_o) to about 1e-13 relative at order 16 (tests).

Dense (anisotropic) matrices are evaluated in chunks of pairs: the basis kernels give
b(w_i) and b(w_o), and one matrix product per chunk (BLAS) applies every channel at once.

Both paths treat grazing directions alike: for ``quantity="f_cos"`` directions with
cos(theta) < ``min_cos`` are lifted to that elevation at the same azimuth before dividing by
cos(theta_i) cos(theta_o) (see :meth:`basis.CoefficientMatrix.eval`); directions below the
horizon give 0.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._base import Basis
from .jit import pjit, prange, writable
from .validation import UNIT_ATOL, as_directions, broadcast_batch, check_bytes

__all__ = ["Evaluator"]

#: Kernel codes of the separable forms in the module docstring, by ``Basis.kind``.
_FORMS = {"zernike": 0, "harmonics": 1, "harmonics-even": 2, "sh": 3}
#: Pairs per task of the parallel loop (scratch arrays are allocated once per task).
_CHUNK = 128
#: The kernel's length test on |w|^2: |w|^2 within this of 1 implies | |w| - 1 | within
#: UNIT_ATOL, so it never accepts a vector that as_directions rejects.
_QUICK_ATOL = 2.0 * UNIT_ATOL * (1.0 - UNIT_ATOL)
#: Bytes of scratch per chunk of the dense path (basis tables and the product).
_DENSE_BYTES = 2**25


class Evaluator:
    """A compiled evaluator for one :class:`basis.CoefficientMatrix`.

    :meth:`basis.CoefficientMatrix.eval` builds one on first use and keeps it, so most users
    never construct it; it is public for loops that evaluate many small batches and want
    :meth:`eval_flat` (no validation, no allocation).

    Parameters
    ----------
    cm : basis.CoefficientMatrix
        Any matrix: isotropic ones use the fused block kernel, dense ones chunked products.
    min_cos : float
        As in :meth:`basis.CoefficientMatrix.eval`, in (0, 1).

    Notes
    -----
    Building the evaluator of an isotropic matrix costs a few small least-squares fits
    (microseconds to milliseconds); evaluation then runs at tens of millions of pairs per
    second on two cores at order 8 (``tests/benchmarks/bench_compress.py``).

    Examples
    --------
    >>> import numpy as np
    >>> from basis import CoefficientMatrix, HemiZernike
    >>> zb = HemiZernike(2)
    >>> M = np.zeros((zb.size, zb.size)); M[0, 0] = 1.0
    >>> cm = CoefficientMatrix(zb, M, quantity="f")
    >>> w = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    >>> bool(np.allclose(Evaluator(cm)(w, w[::-1]), 1 / (2 * np.pi), rtol=1e-13))
    True
    """

    def __init__(self, cm: Any, *, min_cos: float = 1e-3) -> None:
        # duck-typed on what a CoefficientMatrix exposes: basis.matrix builds on this module
        if not all(hasattr(cm, a) for a in ("stored", "basis", "quantity", "is_isotropic")):
            raise TypeError(f"cm must be a basis.CoefficientMatrix, got {type(cm).__name__}")
        if not 0.0 < min_cos < 1.0:
            raise ValueError(f"min_cos must lie in (0, 1), got {min_cos!r}")
        self.cm = cm
        self.min_cos = float(min_cos)
        self.fcos = cm.quantity == "f_cos"
        if cm.is_isotropic:
            self._coef, self._tri, self._coefa, self._tria = _chebyshev_blocks(
                cm.basis, cm.stored, general=not getattr(cm, "reciprocal", True))
        else:
            m = cm.stored[0]  # (channels, size, size)
            # one (size, channels * size) operand: b_i^T [M_0 | M_1 | ...] in one product
            self._dense = np.ascontiguousarray(m.transpose(1, 0, 2).reshape(m.shape[1], -1))

    @property
    def channels(self) -> int:
        """Number of channels of the matrix."""
        return self.cm.channels

    def __call__(self, wi: ArrayLike, wo: ArrayLike) -> NDArray[np.float64]:
        """Evaluate the BRDF, as :meth:`basis.CoefficientMatrix.eval` (same shapes, same zeros).

        Parameters
        ----------
        wi, wo : (..., 3) array_like of float
            Unit vectors; batch shapes broadcast.

        Returns
        -------
        (...) or (..., channels) ndarray of float64
        """
        if self.cm.is_isotropic and _plain_pairs(wi, wo):
            # Already (n, 3) C-contiguous float64: the kernel checks the lengths as it goes,
            # which saves the separate validation pass; only when its (slightly stricter)
            # test flags a vector does the full validation run, to raise its message.
            out = np.empty((wi.shape[0], self.channels))
            if self._iso(wi, wo, out, _QUICK_ATOL):
                as_directions(wi, "wi")
                as_directions(wo, "wo")
            return out[:, 0] if self.cm.is_scalar else out
        wi = as_directions(wi, "wi")
        wo = as_directions(wo, "wo")
        shape = broadcast_batch(wi, wo)
        a = np.ascontiguousarray(np.broadcast_to(wi, (*shape, 3)).reshape(-1, 3))
        b = np.ascontiguousarray(np.broadcast_to(wo, (*shape, 3)).reshape(-1, 3))
        check_bytes(8.0 * a.shape[0] * (6 + self.channels),
                    f"evaluating {self.cm!r} at {a.shape[0]} pairs")
        out = np.empty((a.shape[0], self.channels))
        self.eval_flat(a, b, out)
        out = out.reshape(*shape, self.channels)
        return out[..., 0] if self.cm.is_scalar else out

    def eval_flat(self, wi: NDArray[np.float64], wo: NDArray[np.float64],
                  out: NDArray[np.float64]) -> None:
        """Evaluate into ``out`` without validation, for hot loops.

        Parameters
        ----------
        wi, wo : (n, 3) C-contiguous float64 arrays
            Unit vectors (lengths within 1e-6 of one; they are renormalised).
        out : (n, channels) C-contiguous float64 array
            Overwritten with the BRDF values.
        """
        if self.cm.is_isotropic:
            self._iso(wi, wo, out, np.inf)
        else:
            self._dense_flat(wi, wo, out)

    def _iso(self, wi: NDArray, wo: NDArray, out: NDArray, atol: float) -> bool:
        """Run the fused kernel; True if some |w|^2 is further than ``atol`` from 1 (or NaN)."""
        flags = np.zeros((wi.shape[0] + _CHUNK - 1) // _CHUNK, dtype=np.uint8)
        _iso_kernel(writable(wi), writable(wo), self._coef, self._tri, self._coefa, self._tria,
                    _FORMS[self.cm.basis.kind], self.fcos, self.min_cos, atol, flags, out)
        return bool(flags.any())

    def _dense_flat(self, wi: NDArray, wo: NDArray, out: NDArray) -> None:
        b, nch = self.cm.basis, self.channels
        step = max(64, _DENSE_BYTES // (8 * b.size * (nch + 2)))
        lift = self.min_cos if self.fcos else 0.0
        bi = np.empty((step, b.size))
        bo = np.empty((step, b.size))
        for k in range(0, wi.shape[0], step):
            n = min(step, wi.shape[0] - k)
            di, do = lift_to(wi[k:k + n], lift), lift_to(wo[k:k + n], lift)
            b._eval_flat(np.ascontiguousarray(di), bi[:n])
            b._eval_flat(np.ascontiguousarray(do), bo[:n])
            t = (bi[:n] @ self._dense).reshape(n, nch, b.size)
            q = np.einsum("ncs,ns->nc", t, bo[:n])
            if self.fcos:
                q /= (di[:, 2] * do[:, 2])[:, None]
            q[(wi[k:k + n, 2] < 0) | (wo[k:k + n, 2] < 0)] = 0.0
            out[k:k + n] = q


def _plain_pairs(wi: object, wo: object) -> bool:
    """Tell whether two arrays are (n, 3), n > 0, C-contiguous float64: no conversion needed."""
    return (isinstance(wi, np.ndarray) and isinstance(wo, np.ndarray)
            and wi.dtype == np.float64 and wo.dtype == np.float64
            and wi.ndim == 2 and wi.shape == wo.shape and wi.shape[0] > 0 and wi.shape[1] == 3
            and wi.flags.c_contiguous and wo.flags.c_contiguous)


def lift_to(w: NDArray[np.float64], min_cos: float) -> NDArray[np.float64]:
    """Move directions with cos(theta) < ``min_cos`` up to that elevation, keeping the azimuth.

    Parameters
    ----------
    w : (..., 3) ndarray of float64
        Unit vectors (not validated).
    min_cos : float
        Lowest cos(theta) kept, in [0, 1); 0 lifts only directions below the horizon.

    Returns
    -------
    (..., 3) ndarray
        ``w`` itself when nothing is lifted, otherwise a copy. A direction straight down
        (z = -1) has no azimuth and goes to azimuth 0.
    """
    low = w[..., 2] < min_cos
    if not np.any(low):
        return w
    w = w.copy()
    v = w[low]
    s = np.hypot(v[:, 0], v[:, 1])
    s_new = math.sqrt(1.0 - min_cos * min_cos)
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(s > 0, s_new / s, 0.0)
    v[:, 0] *= f
    v[:, 1] *= f
    v[s == 0, 0] = s_new
    v[:, 2] = min_cos
    w[low] = v
    return w


def _factors(kind: str, z: NDArray, m: int) -> NDArray:
    """s^m g(z): the non-polynomial factor of the order-m functions on the azimuth phi = 0."""
    if kind == "zernike":
        return np.sqrt(1.0 - z) ** m  # |a| = sqrt((1 - z^2) / (1 + z))
    s = np.sqrt((1.0 - z) * (1.0 + z))
    return s**m * (z if kind == "harmonics" else 1.0)


def _chebyshev_blocks(b: Basis, blocks: tuple[NDArray, ...], *, general: bool = False
                      ) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Packed Chebyshev blocks and their lengths: symmetric parts, then antisymmetric parts.

    The symmetric part of C_m = V_m^T B_m V_m has its upper triangle packed column by column
    (entry (a, b), a <= b, at b (b + 1) / 2 + a), so the triangle of any leading k x k
    sub-block is a prefix of length k (k + 1) / 2: every block shares the products
    S_ab = T_a(x_i) T_b(x_o) + T_b(x_i) T_a(x_o) (a < b), S_aa = T_a(x_i) T_a(x_o).
    With ``general`` the antisymmetric part (C_m - C_m^T) / 2 follows, its strict upper
    triangle packed alike (entry (a, b), a < b, at b (b - 1) / 2 + a, prefix length
    k (k - 1) / 2), on the products D_ab = T_a(x_i) T_b(x_o) - T_b(x_i) T_a(x_o); otherwise
    those arrays are empty (length 0 per block). Shapes: (blocks, channels, K), (blocks,),
    (blocks, channels, K'), (blocks,).
    """
    kind = b.kind
    if kind not in _FORMS:
        raise NotImplementedError(f"no fused evaluator for {b!r}")
    cos_idx = b.azimuthal_blocks().cos
    sizes = np.array([i.size for i in cos_idx], dtype=np.int64)
    kmax = int(sizes.max()) if sizes.size else 0
    nch = blocks[0].shape[0]
    coef = np.zeros((len(blocks), nch, max(kmax * (kmax + 1) // 2, 1)))
    coefa = np.zeros((len(blocks), nch, max(kmax * (kmax - 1) // 2, 1) if general else 1))
    nodes = 2 * kmax + 8  # interior Chebyshev nodes in x; z from x (a monotone map)
    t = np.cos(np.pi * (np.arange(nodes) + 0.5) / nodes)
    if kind == "zernike":
        z = (1.0 - t) / 2.0
    elif kind == "sh":
        z = t
    else:
        z = np.sqrt((t + 1.0) / 2.0)
    table = b.radial(z)
    cheb = np.polynomial.chebyshev.chebvander(t, max(kmax - 1, 0))
    ib = np.repeat(np.arange(kmax), np.arange(1, kmax + 1))  # column b of the packed entries
    ia = np.concatenate([np.arange(k + 1) for k in range(kmax)]).astype(np.int64)
    jb = np.repeat(np.arange(kmax), np.arange(kmax))  # strict triangle: column b, row a < b
    ja = np.concatenate([np.arange(k) for k in range(kmax)]).astype(np.int64)
    for m, idx in enumerate(cos_idx):
        k = idx.size
        if k == 0:
            continue
        poly = table[:, idx] / _factors(kind, z, m)[:, None]  # (nodes, k) polynomial parts
        v, *_ = np.linalg.lstsq(cheb[:, :k], poly, rcond=None)  # (k cheb, k functions)
        n, na = k * (k + 1) // 2, k * (k - 1) // 2
        for c in range(nch):
            cm = v @ blocks[m][c] @ v.T
            sym = 0.5 * (cm + cm.T) if general else cm
            coef[m, c, :n] = sym[ia[:n], ib[:n]]
            if general:
                coefa[m, c, :na] = 0.5 * (cm - cm.T)[ja[:na], jb[:na]]
    tria = (sizes * (sizes - 1) // 2 if general else np.zeros_like(sizes)).astype(np.int64)
    return (np.ascontiguousarray(coef), (sizes * (sizes + 1) // 2).astype(np.int64),
            np.ascontiguousarray(coefa), tria)


@pjit
def _iso_kernel(wi, wo, coef, tri, coefa, tria, form, fcos, min_cos, atol, flags,
                out):  # pragma: no cover - compiled
    # wi, wo: (n, 3) unit vectors; coef: (nb, nc, K) packed Chebyshev blocks; tri: (nb,)
    # packed length per block; coefa: (nb, nc, K') packed antisymmetric parts, tria: (nb,)
    # their lengths (all 0 for symmetric blocks); form: 0 zernike, 1 odd, 2 even, 3 sh;
    # out: (n, nc).
    # flags (ntask,): set to 1 for a task holding a vector with | |w|^2 - 1 | > atol or NaN.
    # Pairs in tasks of _CHUNK lanes. Only phase 1 (the geometry of each pair) is scalar;
    # every later loop runs over the contiguous lanes of one quantity (Chebyshev values,
    # their products, the azimuthal powers, the block sums), so it vectorises.
    n = wi.shape[0]
    nb, nc, npk = coef.shape[0], coef.shape[1], coef.shape[2]
    kmax = int(round((math.sqrt(8 * npk + 1) - 1) / 2))
    npa = 0
    for m in range(nb):
        npa = max(npa, tria[m])
    ntask = (n + _CHUNK - 1) // _CHUNK
    lift = min_cos if fcos else 0.0
    s_lift = math.sqrt(1.0 - lift * lift)
    for task in prange(ntask):
        ti = np.empty((max(kmax, 2), _CHUNK))
        to = np.empty((max(kmax, 2), _CHUNK))
        sp = np.empty((npk, _CHUNK))
        sa = np.empty((max(npa, 1), _CHUNK))
        wm = np.empty((nb, _CHUNK))
        wr = np.empty(_CHUNK)
        wim = np.empty(_CHUNK)
        scale = np.empty(_CHUNK)
        acc = np.empty(_CHUNK)
        tot = np.empty(_CHUNK)
        p0 = task * _CHUNK
        lanes = min(n, p0 + _CHUNK) - p0
        bad = False
        for j in range(lanes):
            p = p0 + j
            qi = wi[p, 0] * wi[p, 0] + wi[p, 1] * wi[p, 1] + wi[p, 2] * wi[p, 2]
            qo = wo[p, 0] * wo[p, 0] + wo[p, 1] * wo[p, 1] + wo[p, 2] * wo[p, 2]
            bad |= not (abs(qi - 1.0) <= atol and abs(qo - 1.0) <= atol)
        flags[task] = bad
        # phase 1: per-pair geometry. Pairs below the horizon get harmless factors and
        # scale 0 (their value is set to 0 at the end).
        for j in range(lanes):
            p = p0 + j
            ix, iy, iz = wi[p, 0], wi[p, 1], wi[p, 2]
            ox, oy, oz = wo[p, 0], wo[p, 1], wo[p, 2]
            if iz < 0.0 or oz < 0.0:  # below the horizon: 0
                ti[1, j] = 0.0
                to[1, j] = 0.0
                wr[j] = 0.0
                wim[j] = 0.0
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
            if form == 0:
                xi, xo = 1.0 - 2.0 * iz, 1.0 - 2.0 * oz
                fi, fo = 1.0 / math.sqrt(1.0 + iz), 1.0 / math.sqrt(1.0 + oz)
            elif form == 3:
                xi, xo = iz, oz
                fi, fo = 1.0, 1.0
            else:
                xi, xo = 2.0 * iz * iz - 1.0, 2.0 * oz * oz - 1.0
                fi, fo = 1.0, 1.0
            ti[1, j] = xi
            to[1, j] = xo
            ar, ai = ix * fi, iy * fi
            br, bi = ox * fo, -oy * fo
            wr[j] = ar * br - ai * bi
            wim[j] = ar * bi + ai * br
            if form == 1:  # g = z: q = z_i z_o S
                scale[j] = 1.0 if fcos else iz * oz
            else:
                scale[j] = 1.0 / (iz * oz) if fcos else 1.0
        # Chebyshev values T_a(x) of both directions
        for j in range(lanes):
            ti[0, j] = 1.0
            to[0, j] = 1.0
        for a in range(2, kmax):
            for j in range(lanes):
                ti[a, j] = 2.0 * ti[1, j] * ti[a - 1, j] - ti[a - 2, j]
                to[a, j] = 2.0 * to[1, j] * to[a - 1, j] - to[a - 2, j]
        # symmetrised products S_ab, packed column by column (see _chebyshev_blocks)
        t = 0
        for b in range(kmax):
            for a in range(b):
                for j in range(lanes):
                    sp[t, j] = ti[a, j] * to[b, j] + ti[b, j] * to[a, j]
                t += 1
            for j in range(lanes):
                sp[t, j] = ti[b, j] * to[b, j]
            t += 1
        # antisymmetrised products D_ab (a < b), only for general blocks
        t = 0
        for b in range(kmax):
            if t >= npa:
                break
            for a in range(b):
                for j in range(lanes):
                    sa[t, j] = ti[a, j] * to[b, j] - ti[b, j] * to[a, j]
                t += 1
        # Re (a_i conj a_o)^m
        for j in range(lanes):
            wm[0, j] = 1.0
            acc[j] = 0.0  # Im of the running power
        for m in range(1, nb):
            for j in range(lanes):
                pr, pim = wm[m - 1, j], acc[j]
                wm[m, j] = pr * wr[j] - pim * wim[j]
                acc[j] = pr * wim[j] + pim * wr[j]
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
                for t in range(tria[m]):
                    cv = coefa[m, c, t]
                    for j in range(lanes):
                        acc[j] += cv * sa[t, j]
                for j in range(lanes):
                    tot[j] += wm[m, j] * acc[j]
            for j in range(lanes):
                out[p0 + j, c] = tot[j] * scale[j] if scale[j] != 0.0 else 0.0
