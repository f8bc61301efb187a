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
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic
from numpy.typing import ArrayLike, NDArray

from ._base import Basis
from .jit import (
    _V8,
    LANES,
    _elem,
    _fcall,
    _load,
    _splat,
    _store,
    lane_copy,
    lane_mul,
    lane_muladd,
    lane_recur,
    loopjit,
    run_parallel,
    writable,
)
from .validation import UNIT_ATOL, as_directions, broadcast_batch, check_bytes

__all__ = ["Evaluator"]

#: Kernel codes of the separable forms in the module docstring, by ``Basis.kind``.
_FORMS = {"zernike": 0, "harmonics": 1, "harmonics-even": 2, "sh": 3}
#: Pairs per task of the parallel loop (scratch arrays are allocated once per task).
_CHUNK = 1024
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

    def separable(self) -> dict[str, Any] | None:
        """Return the separable form the fused kernel evaluates, or None for a dense matrix.

        For other evaluators of the same form (e.g. a renderer's kernels): ``kind`` (the
        basis' kind: ``"zernike"``, ``"harmonics"``, ``"harmonics-even"`` or ``"sh"``, whose
        a(w), x(w), g(w) are in the module notes), ``coef`` (blocks, channels, K) and ``tri``
        (blocks,), the packed symmetric parts and their lengths, ``coefa`` and ``tria`` the
        antisymmetric parts (lengths 0 for a reciprocal matrix), as
        :func:`_chebyshev_blocks` packs them; ``fcos`` (q = f cos cos) and ``min_cos``.
        The arrays are read-only views.
        """
        if not self.cm.is_isotropic:
            return None
        out = {"kind": self.cm.basis.kind, "coef": self._coef, "tri": self._tri,
               "coefa": self._coefa, "tria": self._tria, "fcos": self.fcos,
               "min_cos": self.min_cos}
        for k in ("coef", "tri", "coefa", "tria"):
            out[k] = out[k].view()
            out[k].flags.writeable = False
        return out

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
        run_parallel(_iso_kernel, flags.size, writable(wi), writable(wo), self._coef,
                     self._tri, self._coefa, self._tria, _FORMS[self.cm.basis.kind], self.fcos,
                     self.min_cos, atol, flags, out)
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


# -- the fused kernel: LANES pairs per step ---------------------------------------------------
# numba's loop vectoriser gives up on the lane loops of this kernel (many scratch arrays it
# cannot prove disjoint), so the per-pair geometry and the block sums are emitted here as
# explicit <LANES x double> operations (the powers of a_i conj(a_o) inside the block sums, in
# registers), and the Chebyshev values and their products use the lane operations of
# basis.jit.


def _geometry_codegen(context, builder, signature, args):
    t = signature.args
    wi, wo, p, form, fcos, lift, s_lift, atol, tt, to1, wr_, wim_, scale_ = args
    f64 = types.float64
    lift, s_lift, atol = (context.cast(builder, v, ty, f64)
                          for v, ty in ((lift, t[5]), (s_lift, t[6]), (atol, t[7])))
    form = context.cast(builder, form, t[3], types.int64)
    fcos = context.cast(builder, fcos, t[4], types.boolean)
    i32 = ir.IntType(32)
    zero = ir.Constant(_V8, [0.0] * LANES)
    one = ir.Constant(_V8, [1.0] * LANES)

    def mask(idx):
        return ir.Constant(ir.VectorType(i32, LANES), idx)

    def direction(aty, a):
        # (x, y, z) of directions p..p+LANES-1: three loads of LANES, de-interleaved (entry
        # 3 j + c of the three is component c of lane j: two shuffles, the first from the
        # first two loads, the second adding what lies in the third)
        base = builder.mul(p, ir.Constant(p.type, 3))
        v = [_load(context, builder, aty, a,
                   builder.add(base, ir.Constant(p.type, LANES * k))) for k in range(3)]
        out = []
        for c in range(3):
            idx = [3 * j + c for j in range(LANES)]
            u = builder.shuffle_vector(v[0], v[1], mask([i if i < 2 * LANES else 0
                                                         for i in idx]))
            out.append(builder.shuffle_vector(u, v[2], mask(
                [j if i < 2 * LANES else i - LANES for j, i in enumerate(idx)])))
        return tuple(out)

    def fabs(v):
        return _fcall(builder, "llvm.fabs", v)

    def sqrt(v):
        return _fcall(builder, "llvm.sqrt", v)

    def unit(aty, a):
        x, y, z = direction(aty, a)
        q = builder.fadd(builder.fadd(builder.fmul(x, x), builder.fmul(y, y)),
                         builder.fmul(z, z))
        ok = builder.fcmp_ordered("<=", fabs(builder.fsub(q, one)), _splat(builder, atol))
        below = builder.fcmp_ordered("<", z, zero)
        r = builder.fdiv(one, sqrt(q))
        x, y, z = builder.fmul(x, r), builder.fmul(y, r), builder.fmul(z, r)
        # directions under cos(theta) = lift go up to it, same azimuth (rare: a branch)
        low = builder.fcmp_ordered("<", z, _splat(builder, lift))
        slot = [cgutils.alloca_once_value(builder, v) for v in (x, y, z)]
        anylow = builder.icmp_unsigned("!=", builder.bitcast(low, ir.IntType(LANES)),
                                       ir.Constant(ir.IntType(LANES), 0))
        with builder.if_then(anylow, likely=False):
            h = sqrt(builder.fadd(builder.fmul(x, x), builder.fmul(y, y)))
            hp = builder.fcmp_ordered(">", h, zero)
            sl = _splat(builder, s_lift)
            lx = builder.select(hp, builder.fdiv(builder.fmul(x, sl), h), sl)
            ly = builder.select(hp, builder.fdiv(builder.fmul(y, sl), h), zero)
            builder.store(builder.select(low, lx, x), slot[0])
            builder.store(builder.select(low, ly, y), slot[1])
            builder.store(builder.select(low, _splat(builder, lift), z), slot[2])
        x, y, z = (builder.load(v) for v in slot)
        return x, y, z, ok, below

    ix, iy, iz, oki, bi_ = unit(t[0], wi)
    ox, oy, oz, oko, bo_ = unit(t[1], wo)
    below = builder.or_(bi_, bo_)
    ok = builder.and_(oki, oko)
    bad = builder.icmp_unsigned("!=", builder.bitcast(ok, ir.IntType(LANES)),
                                ir.Constant(ir.IntType(LANES), 2**LANES - 1))
    is0 = builder.icmp_signed("==", form, ir.Constant(ir.IntType(64), 0))
    is3 = builder.icmp_signed("==", form, ir.Constant(ir.IntType(64), 3))
    two = ir.Constant(_V8, [2.0] * LANES)
    # zernike: a = (x + i y) / sqrt(1 + z), so a_i conj(a_o) carries the one factor
    # g = 1 / sqrt((1 + z_i)(1 + z_o)); the other forms have g = 1
    gs = cgutils.alloca_once_value(builder, one)
    with builder.if_then(is0):
        builder.store(builder.fdiv(one, sqrt(builder.fmul(builder.fadd(one, iz),
                                                          builder.fadd(one, oz)))), gs)
    g = builder.load(gs)

    def cheb(z):
        return builder.select(is0, builder.fsub(one, builder.fmul(two, z)),
                              builder.select(is3, z, builder.fsub(builder.fmul(
                                  builder.fmul(two, z), z), one)))

    xi, xo = cheb(iz), cheb(oz)
    wr = builder.fmul(builder.fadd(builder.fmul(ix, ox), builder.fmul(iy, oy)), g)
    wim = builder.fmul(builder.fsub(builder.fmul(iy, ox), builder.fmul(ix, oy)), g)
    is1 = builder.icmp_signed("==", form, ir.Constant(ir.IntType(64), 1))
    zz = builder.fmul(iz, oz)
    scale = builder.select(is1, builder.select(fcos, one, zz),
                           builder.select(fcos, builder.fdiv(one, zz), one))
    zi = ir.Constant(p.type, 0)
    l8 = ir.Constant(p.type, LANES)
    for arr, aty, idx, v in ((tt, t[8], l8, xi), (tt, t[8], builder.add(to1, zi), xo),
                             (wr_, t[10], zi, wr), (wim_, t[11], zi, wim),
                             (scale_, t[12], zi, scale)):
        _store(context, builder, aty, arr, idx, builder.select(below, zero, v))
    return bad


@intrinsic
def _lane_geometry(typingctx, wi, wo, p, form, fcos, lift, s_lift, atol, tt, to1, wr, wim,
                   scale):
    # Pairs p..p+L-1 of wi, wo (n, 3), L = LANES: renormalised, lifted to cos(theta) >= lift,
    # then the Chebyshev variables x_i, x_o (to tt[L:2L] and tt[to1:to1+L]), Re and Im of
    # a_i conj(a_o) (wr, wim) and the factor of q (scale) of the form (module docstring);
    # all 0 where a direction is below the horizon. True when some |w|^2 is further than
    # atol from 1 or NaN.
    sig = types.boolean(wi, wo, p, form, fcos, lift, s_lift, atol, tt, to1, wr, wim, scale)
    return sig, _geometry_codegen


@intrinsic
def _lane_blocks(typingctx, res, coef, tri, coefa, tria, sp, sa, wr, wim, ca, cb, cc):
    # For channels ca, cb, cc of coef (nb, nc, K) and coefa (nb, nc, K'), both C-contiguous:
    # res[L g:L g+L] = sum_m Re(w^m) (sum_t coef[m, c_g, t] sp[L t:L t+L]
    #                                   + sum_t coefa[m, c_g, t] sa[L t:L t+L]), L = LANES,
    # t below tri[m] and tria[m], w = wr + i wim lane-wise. Three channels at once share each
    # load of sp, sa; the powers of w stay in registers (a chain through memory would wait
    # on each store). The sums' multiply-adds are fused (basis.jit.fma): one rounding each,
    # and on Intel's AVX-512 cores half the instructions on the two ports that both share.
    sig = types.void(res, coef, tri, coefa, tria, sp, sa, wr, wim, ca, cb, cc)

    def codegen(context, builder, signature, args):
        t = signature.args
        r_, cf, tr, cfa, tra, sp_, sa_, wr_, wim_, *chan = args
        intp = context.get_value_type(types.intp)
        chan = [context.cast(builder, c, ty, types.intp)
                for c, ty in zip(chan, t[9:], strict=True)]
        zero = ir.Constant(_V8, [0.0] * LANES)
        zi = ir.Constant(intp, 0)
        wrv = _load(context, builder, t[7], wr_, zi)
        wiv = _load(context, builder, t[8], wim_, zi)
        tot = [cgutils.alloca_once_value(builder, zero) for _ in chan]
        pw = [cgutils.alloca_once_value(builder, v)
              for v in (ir.Constant(_V8, [1.0] * LANES), zero)]

        def dims(aty, a):
            arr = context.make_array(aty)(context, builder, a)
            return arr.data, cgutils.unpack_tuple(builder, arr.shape, 3)

        (cdata, (nb, nc, kk)), (adata, (_, _, ka)) = dims(t[1], cf), dims(t[3], cfa)
        lanes = ir.Constant(intp, LANES)
        with cgutils.for_range(builder, nb) as loop:
            m = loop.index
            acc = [cgutils.alloca_once_value(builder, zero) for _ in chan]
            for data, k, ta, ia, sta, isa in ((cdata, kk, t[2], tr, t[5], sp_),
                                              (adata, ka, t[4], tra, t[6], sa_)):
                count = context.cast(builder, _elem(context, builder, ta, ia, m),
                                     ta.dtype, types.intp)
                rows = [builder.mul(builder.add(builder.mul(m, nc), c), k) for c in chan]
                with cgutils.for_range(builder, count) as inner:
                    q = inner.index
                    v = _load(context, builder, sta, isa, builder.mul(q, lanes))
                    for a, row in zip(acc, rows, strict=True):
                        c = builder.load(builder.gep(data, [builder.add(row, q)]))
                        builder.store(_fcall(builder, "llvm.fma", _splat(builder, c), v,
                                             builder.load(a)), a)
            pr, pim = (builder.load(v) for v in pw)
            for s_, a in zip(tot, acc, strict=True):
                builder.store(_fcall(builder, "llvm.fma", pr, builder.load(a),
                                     builder.load(s_)), s_)
            builder.store(builder.fsub(builder.fmul(pr, wrv), builder.fmul(pim, wiv)), pw[0])
            builder.store(builder.fadd(builder.fmul(pr, wiv), builder.fmul(pim, wrv)), pw[1])
        for g, s_ in enumerate(tot):
            _store(context, builder, t[0], r_, ir.Constant(intp, LANES * g), builder.load(s_))
        return context.get_dummy_value()

    return sig, codegen


@loopjit
def _iso_kernel(first, stop, wi, wo, coef, tri, coefa, tria, form, fcos, min_cos, atol, flags,
                out):  # pragma: no cover - compiled
    # Tasks first .. stop - 1 (run_parallel) of _CHUNK pairs; wi, wo: (n, 3) unit vectors;
    # coef: (nb, nc, K) packed Chebyshev blocks; tri: (nb,) packed length per block; coefa:
    # (nb, nc, K') packed antisymmetric parts, tria: (nb,) their lengths (all 0 for
    # symmetric blocks); form: 0 zernike, 1 odd, 2 even, 3 sh; out: (n, nc).
    # flags (ntask,): set to 1 for a task holding a vector with | |w|^2 - 1 | > atol or NaN.
    # Each task runs in steps of LANES pairs; a last partial step runs on
    # copies padded with the pole (whose values are dropped). Scratch is lane-fastest:
    # entry r of lane j at r * LANES + j. tt holds T_a(x_i) at rows a < kk, T_a(x_o) at
    # rows kk + a; sp, sa the products S_ab, D_ab in the packed order of _chebyshev_blocks.
    n = wi.shape[0]
    nb, nc, npk = coef.shape[0], coef.shape[1], coef.shape[2]
    kmax = int(round((math.sqrt(8 * npk + 1) - 1) / 2))
    kk = max(kmax, 2)
    npa = 0
    for m in range(nb):
        npa = max(npa, tria[m])
    lift = min_cos if fcos else 0.0
    s_lift = math.sqrt(1.0 - lift * lift)
    for task in range(first, stop):
        tt = np.empty(2 * kk * LANES)
        sp = np.empty(npk * LANES)
        sa = np.empty(max(npa, 1) * LANES)
        ones = np.ones(LANES)
        wr = np.empty(LANES)
        wim = np.empty(LANES)
        scale = np.empty(LANES)
        res = np.empty(3 * LANES)
        pad_i = np.zeros((LANES, 3))
        pad_o = np.zeros((LANES, 3))
        bad = False
        p0 = task * _CHUNK
        for p in range(p0, min(n, p0 + _CHUNK), LANES):
            lanes = min(LANES, n - p)
            if lanes == LANES:
                bad |= _lane_geometry(wi, wo, p, form, fcos, lift, s_lift, atol, tt,
                                      (kk + 1) * LANES, wr, wim, scale)
            else:
                for j in range(LANES):
                    for c in range(3):
                        pad_i[j, c] = wi[p + j, c] if j < lanes else (1.0 if c == 2 else 0.0)
                        pad_o[j, c] = wo[p + j, c] if j < lanes else (1.0 if c == 2 else 0.0)
                bad |= _lane_geometry(pad_i, pad_o, 0, form, fcos, lift, s_lift, atol, tt,
                                      (kk + 1) * LANES, wr, wim, scale)
            # Chebyshev values T_a(x) of both directions (vector stores: a vector load of
            # scalar stores would wait for them to reach the cache)
            lane_copy(tt, 0, ones, 0)
            lane_copy(tt, kk * LANES, ones, 0)
            for a in range(2, kmax):
                for h in (0, kk * LANES):
                    lane_recur(tt, h + a * LANES, tt, h + LANES, tt, h + (a - 1) * LANES,
                               tt, h + (a - 2) * LANES, 2.0, 1.0)
            # symmetrised products S_ab, packed column by column (see _chebyshev_blocks),
            # and the antisymmetrised D_ab (a < b) of general blocks
            q = 0
            qa = 0
            for b in range(kmax):
                for a in range(b):
                    lane_muladd(sp, q * LANES, tt, a * LANES, tt, (kk + b) * LANES,
                                tt, b * LANES, tt, (kk + a) * LANES, 1.0)
                    q += 1
                    if qa < npa:
                        lane_muladd(sa, qa * LANES, tt, a * LANES, tt, (kk + b) * LANES,
                                    tt, b * LANES, tt, (kk + a) * LANES, -1.0)
                        qa += 1
                lane_mul(sp, q * LANES, tt, b * LANES, tt, (kk + b) * LANES)
                q += 1
            # sum_m Re (a_i conj a_o)^m sum_t C_m,t S_t, three channels at a time
            for c in range(0, nc, 3):
                _lane_blocks(res, coef, tri, coefa, tria, sp, sa, wr, wim, c,
                             min(c + 1, nc - 1), min(c + 2, nc - 1))
                for g in range(min(3, nc - c)):
                    for j in range(lanes):
                        v = res[g * LANES + j]
                        out[p + j, c + g] = v * scale[j] if scale[j] != 0.0 else 0.0
        flags[task] = bad
