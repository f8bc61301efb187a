"""The numba decorators every kernel of scatmodes uses, so all are compiled and cached alike.

Public so that ``project`` and ``compress`` (and extensions) share one configuration.

Caching and editing the source: numba checks a cached kernel against the file that defines
it, not against the files of the kernels it calls (and inlines). After editing a module whose
kernels others call (``project/microgeometry/_paths.py`` under every tracer, for instance),
remove the caches (``make clean-cache``), or the callers keep running the old code. Installed
packages are not affected: installing a version rewrites every file.
"""

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from functools import partial

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from .simd import host_lanes

#: lane count forced for tests (see LANES below); kernels are not cached then
_FORCED_LANES = os.environ.get("SCATMODES_LANES", "")

#: Every kernel: compiled once, cached on disk next to the module, and run without the GIL
#: so that :func:`run_parallel` can run several at once.
njit = partial(numba.njit, cache=not _FORCED_LANES, fastmath=False, nogil=True)

#: A loop kernel that :func:`run_parallel` runs over a task range: :data:`njit` with numpy's
#: error model, under which x / 0 gives inf or nan (integers: 0) instead of raising
#: ZeroDivisionError, so that no division waits for a test of its divisor. Numba compiles
#: the bodies of its parallel loops the same way, and gives them an unsigned loop index, which
#: spares every ``a[p]`` numba's test for a negative index: loops that index many arrays
#: iterate ``range(np.uint64(first), np.uint64(stop))`` (measured 30 % faster on one).
loopjit = partial(numba.njit, cache=not _FORCED_LANES, fastmath=False, nogil=True,
                  error_model="numpy")


def run_parallel(kernel, tasks: int, *args, grain: int = 1) -> None:
    """Run ``kernel(first, stop, *args)`` over the task range ``0 .. tasks - 1`` on threads.

    The range is cut into at most four parts per thread, which the calling thread and
    ``numba.get_num_threads() - 1`` pool threads take in turn until none is left (a thread
    that loses its core on a shared machine then holds up at most one part). ``kernel`` is
    an :data:`njit` function that handles tasks ``first .. stop - 1`` and writes nothing
    that another task writes, so the result does not depend on the number of threads.
    Parts hold at least ``grain`` tasks: with fewer than ``2 * grain`` tasks, one thread, or
    from inside a part, the kernel runs once in the calling thread.

    Why not numba's ``parallel=True``: its parfor passes made compilation 2.4 times as
    long (26 s instead of 11 s for the kernels of ``scatmodes demo``, measured on one core
    with an empty cache), and a first run after installing pays that in full. The kernels
    release the GIL (``nogil``), so plain threads run them at full speed; the thread count
    still follows ``numba.set_num_threads`` and ``NUMBA_NUM_THREADS``.
    """
    threads = min(numba.get_num_threads(), tasks // max(grain, 1))
    if threads <= 1 or getattr(_LOCAL, "inside", False):
        kernel(0, tasks, *args)
        return
    parts = min(tasks // max(grain, 1), 4 * threads)
    edges = [tasks * k // parts for k in range(parts + 1)]
    todo = iter(range(parts))
    lock = threading.Lock()

    def work() -> None:
        outer = getattr(_LOCAL, "inside", False)
        _LOCAL.inside = True
        try:
            while True:
                with lock:
                    k = next(todo, None)
                if k is None:
                    return
                kernel(edges[k], edges[k + 1], *args)
        except BaseException:  # an error or an interrupt: the others take no new part
            with lock:
                for _ in todo:
                    pass
            raise
        finally:
            _LOCAL.inside = outer

    pool = _pool()
    futures = [pool.submit(work) for _ in range(threads - 1)]
    try:
        work()
    finally:
        for f in futures:
            f.result()


_LOCAL = threading.local()
_POOL: list = []  # the pool, created at first use
_POOL_LOCK = [threading.Lock()]


def _pool() -> ThreadPoolExecutor:
    with _POOL_LOCK[0]:
        if not _POOL:
            _POOL.append(ThreadPoolExecutor(max(1, numba.config.NUMBA_NUM_THREADS - 1),
                                            thread_name_prefix="scatmodes-kernel"))
        return _POOL[0]


def _forget_pool() -> None:
    # a forked child has none of the parent's threads, and the lock may have been held
    _POOL.clear()
    _POOL_LOCK[0] = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def writable(a: np.ndarray) -> np.ndarray:
    """Return ``a``, or a copy if it is read-only, before it goes to a kernel.

    numba compiles (and caches) a separate specialisation of a kernel for read-only arrays,
    which rule points, broadcast views and frozen inputs are; copying an (n, 3) input is far
    cheaper than a second compilation on a cold start, and keeps one cache entry per kernel.
    """
    return a if a.flags.writeable else a.copy()


# -- vector width -------------------------------------------------------------------------------
# What LLVM emits for the host decides the width: numba compiles for the host CPU and its
# features (or NUMBA_CPU_NAME / NUMBA_CPU_FEATURES), and caches a kernel per CPU and features.
# The <LANES x double> operations below are two zmm registers on a CPU with avx512f and two
# ymm on AVX2. (LLVM splits 512-bit vectors into 256-bit halves only in a function whose
# "min-legal-vector-width" attribute is below 512, as clang marks functions without 512-bit
# intrinsics; numba sets no such attribute, and tests/basis/test_jit.py checks for zmm in
# the lane kernels compiled for Skylake-SP.) LLVM's loop vectoriser is another matter: on
# Intel's AVX-512 server cores (Skylake-SP to Sapphire Rapids) its tuning "prefer-256-bit"
# keeps loops at four doubles, for the lower clock that 512-bit instructions cost there.


@intrinsic
def wide_loops(typingctx):
    """Let LLVM vectorise the calling kernel's loops at the full width of the CPU.

    Marks the function ``"prefer-vector-width"="512"``: on an AVX-512 CPU whose tuning
    prefers 256-bit vectors (Intel Skylake-SP to Sapphire Rapids), its loops then run eight
    doubles per instruction instead of four; elsewhere (AVX2, or AVX-512 CPUs that prefer
    512 bits already) the code is the same. For loops whose iterations are independent (no
    reduction across them), so that the width cannot change a bit of the result.
    """
    def codegen(context, builder, signature, args):
        attrs = builder.function.attributes
        name = '"prefer-vector-width"="512"'
        try:
            attrs._known = attrs._known | {name}  # llvmlite lists only its own attribute names
            attrs.add(name)
        except (AttributeError, TypeError, ValueError):
            pass  # an llvmlite that refuses it: the loops keep LLVM's default width
        return context.get_dummy_value()

    return types.void(), codegen


@intrinsic
def fma(typingctx, a, b, c):
    """Return ``a * b + c`` rounded once (IEEE 754 fusedMultiplyAdd), in a kernel.

    Explicit, because LLVM never fuses ``a * b + c`` on its own under ``fastmath=False``.
    The result is the same on every CPU: one FMA instruction where the CPU has one (x86-64
    since Intel Haswell and AMD Piledriver, every AArch64 CPU), else the C library's
    ``fma``, which is exact too but slow. LLVM's loop vectoriser vectorises it. Integer and
    float32 operands are converted to float64 first, as numba's arithmetic converts them.

    Why in the accumulation kernels: a product added to a running sum costs two
    floating-point operations, or one. On Intel's AVX-512 cores, multiplications and
    additions share the same two ports, so a chain of them runs at half the rate of a chain
    of FMAs (LLVM's machine-code analyser, llvm-mca, for Skylake-SP: 16 cycles against 8
    per iteration of the outer-product loop of the Monte Carlo estimator); on AMD Zen 1
    (AVX2, the instructions in fewer slots and fewer registers) that loop was measured
    1.2-1.4x faster. The products are rounded once instead of twice: the sums differ from
    ``a * b + c`` in the last bits, and are at least as accurate.
    """
    f64 = types.float64
    if not all(isinstance(t, (types.Float, types.Integer)) for t in (a, b, c)):
        return None  # numba reports no matching signature

    def codegen(context, builder, signature, args):
        d = ir.DoubleType()
        x = [context.cast(builder, v, t, f64) for v, t in zip(args, signature.args,
                                                              strict=True)]
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(d, [d, d, d]),
                                            "llvm.fma.f64")
        return builder.call(fn, x)

    return f64(a, b, c), codegen


# -- lane vector operations ---------------------------------------------------------------------
# numba runs LLVM's loop vectoriser but not its SLP vectoriser, and the loop vectoriser gives
# up on short loops over scratch arrays it cannot prove disjoint; these intrinsics emit the
# <LANES x double> operations directly (L below stands for LANES). Each works on flat
# float64 indices into C-contiguous arrays (any number of dimensions), with no bounds checks:
# the callers own the index ranges.
# Every product and difference is a separate IEEE operation in the order written (no fused
# multiply-add), so the values are the bits of the scalar code with the same expression.

#: Lanes of the vector operations below, chosen for the compile target: two of its vector
#: registers of doubles (:func:`basis.simd.host_lanes`). That is two zmm registers on a CPU
#: with avx512f (16 lanes), two ymm on AVX2 (8), two xmm without AVX (4). Four lanes (one
#: ymm) on an AVX2 machine (AMD EPYC) were 4-14 % slower than eight for the harmonics
#: (L = 16, 32), the Zernike functions (order 16) and a coefficient matrix (order 8), and
#: level (within the spread) for Zernike order 8, in CPU time of one thread: each
#: operation's two independent halves hide the latency of the chains of dependent steps
#: (the block evaluator's sums, for one, are chains of FMAs, four cycles each on Intel's
#: AVX-512 cores: with one zmm per value its three channels kept the two FMA ports half
#: idle, llvm-mca's model of Skylake-SP finds, with two they are busy). The lane count
#: never changes a result: the lanes are independent directions, each computed by the
#: same operations in the same order (tests compare this machine's count with 4 and with
#: 8 or 16, bit for bit).
#: ``SCATMODES_LANES`` (2, 4, 8 or 16) overrides the choice, for those tests; kernels are
#: then not cached, since numba's cache does not know the lane count.
if _FORCED_LANES and _FORCED_LANES not in ("2", "4", "8", "16"):
    raise ValueError(f"SCATMODES_LANES must be 2, 4, 8 or 16, got {_FORCED_LANES!r}")
LANES = int(_FORCED_LANES) if _FORCED_LANES else min(16, 2 * host_lanes())

_V8 = ir.VectorType(ir.DoubleType(), LANES)


def _ptr(context, builder, aty, a, i):
    data = context.make_array(aty)(context, builder, a).data
    return builder.bitcast(builder.gep(data, [i]), _V8.as_pointer())


def _load(context, builder, aty, a, i):
    return builder.load(_ptr(context, builder, aty, a, i), align=8)


def _store(context, builder, aty, a, i, v):
    builder.store(v, _ptr(context, builder, aty, a, i), align=8)


def _splat(builder, x):
    v = builder.insert_element(ir.Constant(_V8, ir.Undefined), x, ir.Constant(ir.IntType(32), 0))
    return builder.shuffle_vector(v, ir.Constant(_V8, ir.Undefined),
                                  ir.Constant(ir.VectorType(ir.IntType(32), LANES), [0] * LANES))


def _shuffle(builder, u, v, mask):
    return builder.shuffle_vector(u, v, ir.Constant(ir.VectorType(ir.IntType(32), LANES), mask))


@intrinsic
def lane_recur(typingctx, dst, di, x, xi, p1, i1, p2, i2, a, b):
    """dst[di:di+L] = (a * x[xi:xi+L]) * p1[i1:i1+L] - b * p2[i2:i2+L]."""
    sig = types.void(dst, di, x, xi, p1, i1, p2, i2, a, b)

    def codegen(context, builder, signature, args):
        t = signature.args
        d, idi, xx, ixi, q1, ii1, q2, ii2, aa, bb = args
        aa = context.cast(builder, aa, t[8], types.float64)
        bb = context.cast(builder, bb, t[9], types.float64)
        v = builder.fmul(builder.fmul(_splat(builder, aa), _load(context, builder, t[2], xx, ixi)),
                         _load(context, builder, t[4], q1, ii1))
        v = builder.fsub(v, builder.fmul(_splat(builder, bb),
                                         _load(context, builder, t[6], q2, ii2)))
        _store(context, builder, t[0], d, idi, v)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def lane_scaled(typingctx, dst, di, a, x, xi, y, yi):
    """dst[di:di+L] = (a * x[xi:xi+L]) * y[yi:yi+L]."""
    sig = types.void(dst, di, a, x, xi, y, yi)

    def codegen(context, builder, signature, args):
        t = signature.args
        d, idi, aa, xx, ixi, yy, iyi = args
        aa = context.cast(builder, aa, t[2], types.float64)
        v = builder.fmul(builder.fmul(_splat(builder, aa), _load(context, builder, t[3], xx, ixi)),
                         _load(context, builder, t[5], yy, iyi))
        _store(context, builder, t[0], d, idi, v)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def lane_mul(typingctx, dst, di, x, xi, y, yi):
    """dst[di:di+L] = x[xi:xi+L] * y[yi:yi+L]."""
    sig = types.void(dst, di, x, xi, y, yi)

    def codegen(context, builder, signature, args):
        t = signature.args
        d, idi, xx, ixi, yy, iyi = args
        v = builder.fmul(_load(context, builder, t[2], xx, ixi),
                         _load(context, builder, t[4], yy, iyi))
        _store(context, builder, t[0], d, idi, v)
        return context.get_dummy_value()

    return sig, codegen


def _transpose_store(context, builder, aty, d, idi, st, rows):
    # rows[r] holds entry r of lanes 0..LANES-1: store lane j's LANES entries at d[idi + j * st:]
    # in log2(LANES) rounds of shuffles; the round of step s pairs rows r and r + s (r & s = 0)
    # and interleaves blocks of s entries, after which row j holds lane j
    ity = idi.type
    cur = list(rows)
    s = 1
    while s < LANES:
        lo = [i if i & s == 0 else LANES + i - s for i in range(LANES)]
        hi = [i + s if i & s == 0 else LANES + i for i in range(LANES)]
        nxt = list(cur)
        for r in range(LANES):
            if r & s == 0:
                nxt[r] = _shuffle(builder, cur[r], cur[r + s], lo)
                nxt[r + s] = _shuffle(builder, cur[r], cur[r + s], hi)
        cur = nxt
        s *= 2
    for lane, v in enumerate(cur):
        off = builder.add(idi, builder.mul(st, ir.Constant(ity, lane)))
        _store(context, builder, aty, d, off, v)


@intrinsic
def lane_copy(typingctx, dst, di, src, si):
    """dst[di:di+L] = src[si:si+L]."""
    sig = types.void(dst, di, src, si)

    def codegen(context, builder, signature, args):
        t = signature.args
        d, idi, s, isi = args
        _store(context, builder, t[0], d, idi, _load(context, builder, t[2], s, isi))
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def lane_transpose(typingctx, dst, di, stride, src, si):
    """dst[di + j * stride + r] = src[si + L r + j] for r, j < L: an L x L block transposed.

    Moves L values of each of L lanes (stored lane-fastest) to L output rows
    ``stride`` apart, through registers.
    """
    sig = types.void(dst, di, stride, src, si)

    def codegen(context, builder, signature, args):
        t = signature.args
        d, idi, st, s, isi = args
        rows = [_load(context, builder, t[3], s,
                      builder.add(isi, ir.Constant(isi.type, LANES * r)))
                for r in range(LANES)]
        _transpose_store(context, builder, t[0], d, idi, st, rows)
        return context.get_dummy_value()

    return sig, codegen


def _fcall(builder, name, *vals):
    fnty = ir.FunctionType(_V8, [_V8] * len(vals))
    fn = cgutils.get_or_insert_function(builder.module, fnty, f"{name}.v{LANES}f64")
    return builder.call(fn, list(vals))


def _unit_lanes(context, builder, aty, dd, ii0):
    """Load directions ii0 .. ii0 + L - 1 of an (n, 3) array as x, y, z lanes, divided by |w|."""
    data = context.make_array(aty)(context, builder, dd).data
    ity = ii0.type
    base = builder.mul(ii0, ir.Constant(ity, 3))
    undef = ir.Constant(_V8, ir.Undefined)
    comp = []
    for c in range(3):
        v = undef
        for j in range(LANES):
            p = builder.gep(data, [builder.add(base, ir.Constant(ity, 3 * j + c))])
            v = builder.insert_element(v, builder.load(p), ir.Constant(ir.IntType(32), j))
        comp.append(v)
    x, y, z = comp
    r = _fcall(builder, "llvm.sqrt", builder.fadd(builder.fadd(builder.fmul(x, x),
                                                               builder.fmul(y, y)),
                                                  builder.fmul(z, z)))
    return builder.fdiv(x, r), builder.fdiv(y, r), builder.fdiv(z, r)


@intrinsic
def lane_unit(typingctx, dirs, i0, zz, sn, c1, s1, smin):
    """Renormalise directions i0..i0+L-1 of ``dirs`` (n, 3) and store their polar coordinates.

    Stores, lane by lane, z, sin(theta) and the unit azimuth (cos phi, sin phi) (1, 0 at the
    poles) into the first L entries of zz, sn, c1, s1: the operations of the scalar
    routine, lane-wise (each square root and quotient correctly rounded, so the same bits).
    Returns True when some lane has 0 < sin(theta) < smin.
    """
    sig = types.boolean(dirs, i0, zz, sn, c1, s1, smin)

    def codegen(context, builder, signature, args):
        t = signature.args
        dd, ii0, z_, s_, c_, si_, sm = args
        x, y, z = _unit_lanes(context, builder, t[0], dd, ii0)
        s = _fcall(builder, "llvm.sqrt", builder.fadd(builder.fmul(x, x), builder.fmul(y, y)))
        zero = ir.Constant(_V8, [0.0] * LANES)
        pos = builder.fcmp_ordered(">", s, zero)
        cv = builder.select(pos, builder.fdiv(x, s), ir.Constant(_V8, [1.0] * LANES))
        sv = builder.select(pos, builder.fdiv(y, s), zero)
        sm = context.cast(builder, sm, t[6], types.float64)
        low = builder.and_(pos, builder.fcmp_ordered("<", s, _splat(builder, sm)))
        zi = ir.Constant(ii0.type, 0)
        for arr, aty, v in ((z_, t[2], z), (s_, t[3], s), (c_, t[4], cv), (si_, t[5], sv)):
            _store(context, builder, aty, arr, zi, v)
        bits = builder.bitcast(low, ir.IntType(LANES))
        return builder.icmp_unsigned("!=", bits, ir.Constant(ir.IntType(LANES), 0))

    return sig, codegen


@intrinsic
def lane_rotate(typingctx, cc, ss, seed, r, c1, s1, dm, sn):
    """One step of the azimuthal and sectoral recurrences, lane-wise, from row r - L to row r.

    cc[r:r+L] = cc' c1 - ss' s1, ss[r:r+L] = ss' c1 + cc' s1, seed[r:r+L] = seed' (dm sn),
    where ' marks the entries r - L .. r - 1 and c1, s1, sn their first L entries.
    """
    sig = types.void(cc, ss, seed, r, c1, s1, dm, sn)

    def codegen(context, builder, signature, args):
        t = signature.args
        ca, sa, sd, rr, c1a, s1a, dmv, sna = args
        zi = ir.Constant(rr.type, 0)
        rp = builder.sub(rr, ir.Constant(rr.type, LANES))
        cm = _load(context, builder, t[0], ca, rp)
        sm = _load(context, builder, t[1], sa, rp)
        cv = _load(context, builder, t[4], c1a, zi)
        sv = _load(context, builder, t[5], s1a, zi)
        _store(context, builder, t[0], ca, rr,
               builder.fsub(builder.fmul(cm, cv), builder.fmul(sm, sv)))
        _store(context, builder, t[1], sa, rr,
               builder.fadd(builder.fmul(sm, cv), builder.fmul(cm, sv)))
        dmv = context.cast(builder, dmv, t[6], types.float64)
        f = builder.fmul(_splat(builder, dmv), _load(context, builder, t[7], sna, zi))
        _store(context, builder, t[2], sd, rr,
               builder.fmul(_load(context, builder, t[2], sd, rp), f))
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def lane_affine(typingctx, dst, di, a, x, xi, b, y, yi):
    """dst[di:di+L] = (a * x[xi:xi+L] - b) * y[yi:yi+L]."""
    sig = types.void(dst, di, a, x, xi, b, y, yi)

    def codegen(context, builder, signature, args):
        t = signature.args
        d, idi, aa, xx, ixi, bb, yy, iyi = args
        aa = context.cast(builder, aa, t[2], types.float64)
        bb = context.cast(builder, bb, t[5], types.float64)
        v = builder.fsub(builder.fmul(_splat(builder, aa), _load(context, builder, t[3], xx, ixi)),
                         _splat(builder, bb))
        _store(context, builder, t[0], d, idi,
               builder.fmul(v, _load(context, builder, t[6], yy, iyi)))
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def lane_jacobi(typingctx, dst, di, a, x, xi, b, p1, i1, c, p2, i2):
    """dst[di:di+L] = (a * x[xi:xi+L] - b) * p1[i1:i1+L] - c * p2[i2:i2+L].

    The three-term recurrence of the Jacobi polynomials in the form the Zernike radial
    functions use; ``dst`` may be ``p2`` (each lane is read before it is written).
    """
    sig = types.void(dst, di, a, x, xi, b, p1, i1, c, p2, i2)

    def codegen(context, builder, signature, args):
        t = signature.args
        d, idi, aa, xx, ixi, bb, q1, ii1, cc, q2, ii2 = args
        aa = context.cast(builder, aa, t[2], types.float64)
        bb = context.cast(builder, bb, t[5], types.float64)
        cc = context.cast(builder, cc, t[8], types.float64)
        v = builder.fsub(builder.fmul(_splat(builder, aa), _load(context, builder, t[3], xx, ixi)),
                         _splat(builder, bb))
        v = builder.fmul(v, _load(context, builder, t[6], q1, ii1))
        v = builder.fsub(v, builder.fmul(_splat(builder, cc),
                                         _load(context, builder, t[9], q2, ii2)))
        _store(context, builder, t[0], d, idi, v)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def lane_disk(typingctx, dirs, i0, rho2, rho, c1, s1):
    """Map directions i0..i0+L-1 of ``dirs`` (n, 3) to Lambert's azimuthal equal-area disk.

    After renormalising each direction (as :func:`lane_unit`), stores lane by lane
    rho^2 = (x^2 + y^2) / (1 + z) (1 - z where z <= -1/2), rho = sqrt(rho^2) and the unit
    azimuth (cos phi, sin phi) (1, 0 at the poles) into the first L entries of rho2, rho,
    c1, s1: the operations of the scalar routine, lane-wise, so the same bits.
    """
    sig = types.void(dirs, i0, rho2, rho, c1, s1)

    def codegen(context, builder, signature, args):
        t = signature.args
        dd, ii0, r2_, rh_, c_, si_ = args
        x, y, z = _unit_lanes(context, builder, t[0], dd, ii0)
        s2 = builder.fadd(builder.fmul(x, x), builder.fmul(y, y))
        s = _fcall(builder, "llvm.sqrt", s2)
        zero = ir.Constant(_V8, [0.0] * LANES)
        one = ir.Constant(_V8, [1.0] * LANES)
        pos = builder.fcmp_ordered(">", s, zero)
        cv = builder.select(pos, builder.fdiv(x, s), one)
        sv = builder.select(pos, builder.fdiv(y, s), zero)
        far = builder.fcmp_ordered(">", z, ir.Constant(_V8, [-0.5] * LANES))
        q = builder.select(far, builder.fdiv(s2, builder.fadd(one, z)), builder.fsub(one, z))
        zi = ir.Constant(ii0.type, 0)
        for arr, aty, v in ((r2_, t[2], q), (rh_, t[3], _fcall(builder, "llvm.sqrt", q)),
                            (c_, t[4], cv), (si_, t[5], sv)):
            _store(context, builder, aty, arr, zi, v)
        return context.get_dummy_value()

    return sig, codegen


def _elem(context, builder, aty, a, i):
    data = context.make_array(aty)(context, builder, a).data
    return builder.load(builder.gep(data, [i]))


@intrinsic
def lane_tile(typingctx, dst, di, stride, x, ix, y, iy, f, k):
    """L products (f[q] * x[ix[q]:ix[q]+L]) * y[iy[q]:iy[q]+L], q = k..k+L-1, transposed.

    Lane j of product k + r goes to dst[di + j * stride + r]: L output rows ``stride``
    apart get L values each, as :func:`lane_transpose` stores them, with no trip through
    memory between the products and the transpose. ix, iy: int64 arrays; f: float64.
    """
    sig = types.void(dst, di, stride, x, ix, y, iy, f, k)

    def codegen(context, builder, signature, args):
        t = signature.args
        d, idi, st, xa, ixa, ya, iya, fa, kk = args
        kk = context.cast(builder, kk, t[8], types.intp)
        rows = []
        for r in range(LANES):
            q = builder.add(kk, ir.Constant(kk.type, r))
            fr = _splat(builder, _elem(context, builder, t[7], fa, q))
            xi, yi = (context.cast(builder, _elem(context, builder, ty, ia, q), ty.dtype,
                                   types.intp) for ty, ia in ((t[4], ixa), (t[6], iya)))
            rows.append(builder.fmul(builder.fmul(fr, _load(context, builder, t[3], xa, xi)),
                                     _load(context, builder, t[5], ya, yi)))
        _transpose_store(context, builder, t[0], d, idi, st, rows)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def lane_turn(typingctx, a, c, cp, s, sp, c1, s1):
    """One step of the azimuthal recurrence, lane-wise, within one array.

    a[c:c+L] = a[cp:cp+L] c1 - a[sp:sp+L] s1 and a[s:s+L] = a[sp:sp+L] c1 + a[cp:cp+L] s1,
    with c1, s1 their first L entries: (cos, sin) of the next multiple of the azimuth,
    the operations of :func:`lane_rotate`.
    """
    sig = types.void(a, c, cp, s, sp, c1, s1)

    def codegen(context, builder, signature, args):
        t = signature.args
        aa, ic, icp, is_, isp, c1a, s1a = args
        zi = ir.Constant(ic.type, 0)
        cm = _load(context, builder, t[0], aa, icp)
        sm = _load(context, builder, t[0], aa, isp)
        cv = _load(context, builder, t[5], c1a, zi)
        sv = _load(context, builder, t[6], s1a, zi)
        _store(context, builder, t[0], aa, ic,
               builder.fsub(builder.fmul(cm, cv), builder.fmul(sm, sv)))
        _store(context, builder, t[0], aa, is_,
               builder.fadd(builder.fmul(sm, cv), builder.fmul(cm, sv)))
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def lane_muladd(typingctx, dst, di, x, xi, y, yi, u, ui, v, vi, sign):
    """dst[di:di+L] = x[xi:xi+L] * y[yi:yi+L] + sign * (u[ui:ui+L] * v[vi:vi+L]).

    ``sign`` is 1.0 or -1.0: the second product is added or subtracted (negation is exact,
    so these are the bits of x y + u v and x y - u v).
    """
    sig = types.void(dst, di, x, xi, y, yi, u, ui, v, vi, sign)

    def codegen(context, builder, signature, args):
        t = signature.args
        d, idi, xa, ixa, ya, iya, ua, iua, va, iva, sg = args
        sg = context.cast(builder, sg, t[10], types.float64)
        p = builder.fmul(_load(context, builder, t[2], xa, ixa),
                         _load(context, builder, t[4], ya, iya))
        q = builder.fmul(_load(context, builder, t[6], ua, iua),
                         _load(context, builder, t[8], va, iva))
        _store(context, builder, t[0], d, idi,
               builder.fadd(p, builder.fmul(_splat(builder, sg), q)))
        return context.get_dummy_value()

    return sig, codegen
