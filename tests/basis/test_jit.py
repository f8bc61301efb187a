"""basis.jit: the lane vector intrinsics against numpy's scalar IEEE arithmetic, fma
against exact rational arithmetic, and run_parallel's split of a task range."""

import numba
import numpy as np
import pytest

from basis.jit import (
    LANES,
    fma,
    lane_affine,
    lane_copy,
    lane_disk,
    lane_jacobi,
    lane_mul,
    lane_muladd,
    lane_recur,
    lane_rotate,
    lane_scaled,
    lane_tile,
    lane_transpose,
    lane_turn,
    lane_unit,
)

#: Row stride of the transposed tiles in the tests: rows longer than a tile, offset 3.
_STRIDE = LANES + 3


@numba.njit(cache=False)
def _run(out, x, p1, p2, cc, ss, seed, c1, s1, sn, tile, src, dirs, unit):
    lane_recur(out, 0, x, 0, p1, LANES, p2, 0, 1.5, 0.25)
    lane_scaled(out, LANES, 1.5, x, 0, p1, LANES)
    lane_mul(out, 2 * LANES, x, 0, p1, LANES)
    lane_rotate(cc, ss, seed, LANES, c1, s1, 0.75, sn)
    lane_transpose(tile, 3, _STRIDE, src, LANES)
    return lane_unit(dirs, 1, unit[0], unit[1], unit[2], unit[3], 1e-3)


def test_lane_operations_give_the_scalar_bits(rng):
    # Reference: the same expressions in numpy, evaluated element by element in the same
    # order (no fused multiply-add on either side), so equality is bitwise, no tolerance.
    x, p1, p2 = rng.random(LANES), rng.random(2 * LANES), rng.random(LANES)
    cc, ss, seed = rng.random(2 * LANES), rng.random(2 * LANES), rng.random(2 * LANES)
    c1, sn = rng.random(LANES), rng.random(LANES)
    src = rng.random((LANES + 2) * LANES)
    dirs = rng.normal(size=(2 + LANES, 3))
    dirs[3] = [0.0, 0.0, 1.0]  # the pole: azimuth (1, 0)
    dirs[4] = [1e-9, 0.0, 1.0]  # 0 < sin(theta) < 1e-3: flagged
    out, tile, unit = np.zeros(3 * LANES), np.zeros((LANES, _STRIDE)), np.zeros((4, LANES))
    cc0, ss0, seed0 = cc.copy(), ss.copy(), seed.copy()
    flagged = _run(out, x, p1, p2, cc, ss, seed, c1, c1[::-1].copy(), sn, tile, src, dirs, unit)
    s1 = c1[::-1]
    np.testing.assert_array_equal(out[:LANES], (1.5 * x) * p1[LANES:] - 0.25 * p2)
    np.testing.assert_array_equal(out[LANES:2 * LANES], (1.5 * x) * p1[LANES:])
    np.testing.assert_array_equal(out[2 * LANES:], x * p1[LANES:])
    np.testing.assert_array_equal(cc[LANES:], cc0[:LANES] * c1 - ss0[:LANES] * s1)
    np.testing.assert_array_equal(ss[LANES:], ss0[:LANES] * c1 + cc0[:LANES] * s1)
    np.testing.assert_array_equal(seed[LANES:], seed0[:LANES] * (0.75 * sn))
    flat = tile.reshape(-1)
    for r in range(LANES):
        for j in range(LANES):
            assert flat[3 + _STRIDE * j + r] == src[LANES + LANES * r + j]
    d = dirs[1:1 + LANES]
    r = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
    xx, yy, zz = d[:, 0] / r, d[:, 1] / r, d[:, 2] / r
    s = np.sqrt(xx * xx + yy * yy)
    with np.errstate(invalid="ignore", divide="ignore"):
        np.testing.assert_array_equal(unit[0], zz)
        np.testing.assert_array_equal(unit[1], s)
        np.testing.assert_array_equal(unit[2], np.where(s > 0, xx / s, 1.0))
        np.testing.assert_array_equal(unit[3], np.where(s > 0, yy / s, 0.0))
    assert flagged
    assert not _run(out, x, p1, p2, cc, ss, seed, c1, c1, sn, tile, src,
                    np.tile([0.6, 0.0, 0.8], (2 + LANES, 1)), unit)


@numba.njit(cache=False)
def _run_more(out, x, p1, p2, ang, c1, s1, tile, ix, iy, f, dirs, disk):
    lane_affine(out, 0, 1.5, x, 0, 0.25, p1, LANES)
    lane_jacobi(out, LANES, 1.5, x, 0, 0.25, p1, LANES, 0.75, p2, 0)
    lane_muladd(out, 2 * LANES, x, 0, p1, LANES, p2, 0, p1, 0, 1.0)
    lane_muladd(out, 3 * LANES, x, 0, p1, LANES, p2, 0, p1, 0, -1.0)
    lane_copy(out, 4 * LANES, p2, 0)
    lane_turn(ang, 2 * LANES, 0, 3 * LANES, LANES, c1, s1)
    lane_tile(tile, 3, _STRIDE, p1, ix, ang, iy, f, 1)
    lane_disk(dirs, 1, disk[0], disk[1], disk[2], disk[3])


def test_more_lane_operations_give_the_scalar_bits(rng):
    # Reference as above: numpy's element-wise IEEE operations in the same order, bitwise.
    x, p1, p2 = rng.random(LANES), rng.random(2 * LANES), rng.random(LANES)
    ang, c1, s1 = rng.random(4 * LANES), rng.random(LANES), rng.random(LANES)
    ix = rng.integers(0, LANES + 1, size=LANES + 1)
    iy = rng.integers(0, 3 * LANES + 1, size=LANES + 1)
    f = rng.random(LANES + 1)
    dirs = rng.normal(size=(2 + LANES, 3))
    dirs[1] = [0.0, 0.0, 1.0]  # the pole: azimuth (1, 0), rho = 0
    dirs[2] = [0.3, -0.4, -0.7]  # z <= -1/2: rho^2 = 1 - z
    dirs[3] *= 1 + 1e-7  # not quite unit: renormalised
    out, tile, disk = np.zeros(5 * LANES), np.zeros((LANES, _STRIDE)), np.zeros((4, LANES))
    ang0 = ang.copy()
    _run_more(out, x, p1, p2, ang, c1, s1, tile, ix, iy, f, dirs, disk)
    q = p1[LANES:]
    np.testing.assert_array_equal(out[:LANES], (1.5 * x - 0.25) * q)
    np.testing.assert_array_equal(out[LANES:2 * LANES], (1.5 * x - 0.25) * q - 0.75 * p2)
    np.testing.assert_array_equal(out[2 * LANES:3 * LANES], x * q + p2 * p1[:LANES])
    np.testing.assert_array_equal(out[3 * LANES:4 * LANES], x * q - p2 * p1[:LANES])
    np.testing.assert_array_equal(out[4 * LANES:], p2)
    cp, sp = ang0[:LANES], ang0[LANES:2 * LANES]
    np.testing.assert_array_equal(ang[2 * LANES:3 * LANES], cp * c1 - sp * s1)
    np.testing.assert_array_equal(ang[3 * LANES:], sp * c1 + cp * s1)
    flat = tile.reshape(-1)
    for r in range(LANES):
        k = 1 + r
        v = (f[k] * p1[ix[k]:ix[k] + LANES]) * ang[iy[k]:iy[k] + LANES]
        for j in range(LANES):
            assert flat[3 + _STRIDE * j + r] == v[j]
    d = dirs[1:1 + LANES]
    r = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
    xx, yy, zz = d[:, 0] / r, d[:, 1] / r, d[:, 2] / r
    s2 = xx * xx + yy * yy
    s = np.sqrt(s2)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho2 = np.where(zz > -0.5, s2 / (1.0 + zz), 1.0 - zz)
        np.testing.assert_array_equal(disk[0], rho2)
        np.testing.assert_array_equal(disk[1], np.sqrt(rho2))
        np.testing.assert_array_equal(disk[2], np.where(s > 0, xx / s, 1.0))
        np.testing.assert_array_equal(disk[3], np.where(s > 0, yy / s, 0.0))


# -- run_parallel -------------------------------------------------------------------------------
@numba.njit(cache=False, nogil=True)
def _mark(first, stop, hits):
    for t in range(first, stop):
        hits[t] += 1


def _ranges(tasks, threads, grain=1):
    """The calls run_parallel makes (first, stop) with ``threads`` numba threads."""
    import threading

    from basis.jit import run_parallel

    calls, lock = [], threading.Lock()

    def kernel(first, stop):
        with lock:
            calls.append((first, stop, threading.get_ident()))

    old = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        run_parallel(kernel, tasks, grain=grain)
    finally:
        numba.set_num_threads(old)
    return calls


# -- fma: one rounding, against exact rational arithmetic -----------------------------------

@numba.njit(cache=False)
def _fma_loop(a, b, c, out):
    # a loop LLVM vectorises (the kernels' use), with a float32 operand widened exactly
    for i in range(a.shape[0]):
        out[i] = fma(a[i], b[i], c[i])
    return fma(np.float32(0.5), a[0], 1)


def test_fma_rounds_the_exact_product_sum_once(rng):
    # Reference: a * b + c in exact rationals (fractions), rounded once by int / int true
    # division, which CPython rounds correctly. The first rows are cases where rounding the
    # product first gives another result: (1 + 2^-30)(1 - 2^-30) - 1 = -2^-60 exactly (0
    # unfused), a product's low half that decides the sum's last bit, and cancellation of
    # large terms; then random magnitudes over 60 binades, each sign, c cancelling a * b to
    # about 8 digits.
    from fractions import Fraction

    e = 2.0**-30
    a = [1 + e, 1 + 2.0**-52, 3.0, 1e300, 0.1]
    b = [1 - e, 1 + 2.0**-52, 1 / 3, 1e8, 10.0]
    c = [-1.0, -1.0, -1.0, -1e308, -1.0]
    n = 2000
    a = np.concatenate([a, rng.normal(size=n) * 2.0 ** rng.integers(-30, 30, n)])
    b = np.concatenate([b, rng.normal(size=n) * 2.0 ** rng.integers(-30, 30, n)])
    c = np.concatenate([c, -a[5:] * b[5:] * (1 + rng.normal(size=n) * 1e-8)])
    out = np.empty_like(a)
    assert _fma_loop(a, b, c, out) == 0.5 * a[0] + 1  # float32 and int operands: exact here
    for x, y, z, got in zip(a, b, c, out, strict=True):
        exact = Fraction(x) * Fraction(y) + Fraction(z)
        want = exact.numerator / exact.denominator if exact else 0.0
        assert got == want, (x, y, z, got, want)
    assert out[0] == -(2.0**-60) and a[0] * b[0] + c[0] == 0.0  # unfused would differ
    assert np.sum(out != a * b + c) > 100  # the random rows differ in the last bits often


def test_run_parallel_covers_every_task_once():
    from basis.jit import run_parallel

    for tasks in (1, 2, 7, 100, 1001):
        hits = np.zeros(tasks, np.int64)
        run_parallel(_mark, tasks, hits)
        assert (hits == 1).all()
        spans = sorted((a, b) for a, b, _ in _ranges(tasks, 2))
        assert spans[0][0] == 0 and spans[-1][1] == tasks
        assert all(b0 == a1 for (_, b0), (a1, _) in zip(spans, spans[1:], strict=False))
        assert all(a < b for a, b in spans)


def test_run_parallel_grain_and_one_thread_run_in_the_caller():
    import threading

    me = threading.get_ident()
    assert _ranges(1000, 1) == [(0, 1000, me)]  # one thread: one call, here
    assert _ranges(15, 2, grain=8) == [(0, 15, me)]  # fewer than 2 * grain tasks
    calls = _ranges(1000, 2, grain=100)
    if numba.config.NUMBA_NUM_THREADS >= 2:
        assert 2 <= len(calls) <= 8 and all(b - a >= 100 for a, b, _ in calls)


def test_run_parallel_nested_call_runs_inline_and_errors_propagate():
    from basis.jit import run_parallel

    inner = []

    def outer(first, stop):
        run_parallel(lambda a, b: inner.append((a, b)), 50)  # inside a part: no new parts

    run_parallel(outer, 4)
    assert sorted(inner) == [(0, 50)] * len(inner) and len(inner) >= 1

    def bad(first, stop):
        if first > 0:
            raise ValueError("from a pool thread")

    if numba.config.NUMBA_NUM_THREADS >= 2:
        with pytest.raises(ValueError, match="pool thread"):
            run_parallel(bad, 100)


# -- what LLVM emits for a wide-vector CPU ------------------------------------------------------
# Compiled (never run) in a child process whose numba targets the named CPU; prints the count
# of packed-double instructions on zmm and on ymm registers for a kernel of lane operations
# and for a loop kernel marked with wide_loops, then of its packed fused multiply-adds.
_CROSS = r"""
import re
import numba
from basis.jit import fma, lane_recur, lane_transpose, wide_loops

@numba.njit(cache=False)
def lanes(dst, x, p1, p2, tile):
    for i in range(0, x.size, 8):
        lane_recur(dst, i, x, i, p1, i, p2, i, 1.5, 0.25)
    lane_transpose(tile, 0, 8, dst, 0)

@numba.njit(cache=False)
def loops(m, a, s):
    wide_loops()
    for j in range(m.shape[0]):
        for k in range(m.shape[1]):
            m[j, k] = fma(a[j], s[k], m[j, k])

f1, f2 = numba.float64[::1], numba.float64[:, ::1]
for k, sig in ((lanes, (f1, f1, f1, f1, f1)), (loops, (f2, f1, f1))):
    k.compile(sig)
    asm = k.inspect_asm(sig)
    print(*(len(re.findall(r"\tv\w+pd\t[^\n]*%" + r, asm)) for r in ("zmm", "ymm")))
print(*(len(re.findall(r"\tvfmadd\w+pd\t[^\n]*%" + r, asm)) for r in ("zmm", "ymm")))
"""


#: the features of the CPUs compiled for (the lane count follows them: basis.simd.host_lanes)
_FEATURES = {"skylake-avx512": "+avx512f,+avx512dq,+avx512vl,+avx512bw,+avx2,+avx,+fma,+sse4.2",
             "haswell": "+avx2,+avx,+fma,+sse4.2"}


def _cross_compile(cpu: str, tmp_path) -> list[tuple[int, int]]:
    import os
    import platform
    import subprocess
    import sys

    if platform.machine().lower() not in ("x86_64", "amd64"):
        pytest.skip("numba compiles for the host's architecture: x86-64 needs an x86-64 host")
    env = dict(os.environ, NUMBA_CPU_NAME=cpu, NUMBA_CPU_FEATURES=_FEATURES[cpu],
               NUMBA_CACHE_DIR=str(tmp_path))
    r = subprocess.run([sys.executable, "-c", _CROSS], env=env, capture_output=True,
                       text=True, timeout=300)
    if r.returncode and "No available targets" in r.stderr:
        pytest.skip("this LLVM build has no x86 target")
    assert r.returncode == 0, r.stderr[-2000:]
    return [tuple(int(v) for v in line.split()) for line in r.stdout.split("\n") if line]


def test_lane_operations_use_zmm_registers_on_avx512(tmp_path):
    # Skylake-SP: LLVM's tuning prefers 256-bit vectors there, yet explicit <8 x double>
    # stays whole (numba marks no "min-legal-vector-width"; split, it would be ymm pairs and
    # no zmm), and wide_loops lifts the loop vectoriser to 512 bits. Without it that loop
    # ran on ymm registers only (0 zmm, 15 ymm with LLVM 22).
    (lane_zmm, lane_ymm), (loop_zmm, loop_ymm), (fma_zmm, _) = _cross_compile(
        "skylake-avx512", tmp_path)
    assert lane_zmm > 0 and lane_ymm < lane_zmm, (lane_zmm, lane_ymm)
    assert loop_zmm > 0, (loop_zmm, loop_ymm)
    assert fma_zmm > 0  # basis.jit.fma: one instruction, vectorised


def test_lane_operations_use_ymm_pairs_on_avx2(tmp_path):
    (lane_zmm, lane_ymm), (loop_zmm, loop_ymm), (fma_zmm, fma_ymm) = _cross_compile(
        "haswell", tmp_path)
    assert lane_zmm == 0 and lane_ymm > 0, (lane_zmm, lane_ymm)
    assert loop_zmm == 0 and loop_ymm > 0, (loop_zmm, loop_ymm)
    assert fma_zmm == 0 and fma_ymm > 0, (fma_zmm, fma_ymm)


# -- other lane counts: the same bits --------------------------------------------------------
# the evaluations compared: run in a child with another lane count and in this process alike.
# Zernike order 5 (the pair kernel, geometry in lanes), 8 (the smallest for the lane kernel:
# at sixteen lanes its first tile spans rows 0..5, held only with three buffers of R) and 21;
# harmonics below and above the pair kernel's degree, the hemispherical harmonics (one
# parity picked from a block)
_EVALS = r"""
import numpy as np
import basis
rng = np.random.default_rng(7)
d = rng.normal(size=(1003, 3))
d[:, 2] = np.abs(d[:, 2])
d /= np.linalg.norm(d, axis=1, keepdims=True)
m = basis.CoefficientMatrix(basis.HemiZernike(8), rng.normal(size=(3, 45, 45)),
                            reciprocal=False)
iso = m.to_isotropic()  # the block evaluator (evaluate.py)
out = [basis.SphericalHarmonics(8).eval(d), basis.SphericalHarmonics(16).eval(d),
       basis.HemiHarmonics(12).eval(d), basis.HemiZernike(5).eval(d),
       basis.HemiZernike(8).eval(d), basis.HemiZernike(21).eval(d),
       m.eval(d[:500], d[500:1000]), iso.eval(d[:500], d[500:1000])]
"""
_CHILD = _EVALS + r"""
import sys
from basis.jit import LANES
np.savez(sys.argv[1], lanes=LANES, *out)
"""

#: SSE only (two doubles per register: four lanes; an SSE program runs on any x86-64 CPU,
#: and the block evaluator's fused multiply-adds are the C library's fma there, with no FMA
#: instruction), and another count forced: sixteen (what an AVX-512 CPU takes, two zmm
#: registers per value; on AVX2 each value is four ymm), or eight where this process has
#: sixteen already
_OTHER = 8 if LANES == 16 else 16
_BUILDS = {"sse": ({"NUMBA_CPU_NAME": "x86-64",
                    "NUMBA_CPU_FEATURES": "+sse2,+sse3,+ssse3,+sse4.1,+sse4.2,+popcnt,+cx16"}, 4),
           "forced": ({"SCATMODES_LANES": str(_OTHER)}, _OTHER)}


@pytest.mark.parametrize("build", list(_BUILDS))
def test_lane_count_keeps_the_bits(build, tmp_path):
    # the harmonics, Zernike functions and a coefficient matrix (dense and block
    # evaluators) give the bits of this process's kernels, whatever either lane count
    import os
    import platform
    import subprocess
    import sys

    if platform.machine().lower() not in ("x86_64", "amd64"):
        pytest.skip("the child builds run on x86-64 only")
    extra, lanes = _BUILDS[build]
    env = {k: v for k, v in os.environ.items() if k != "SCATMODES_LANES"}
    env.update(extra, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    path = tmp_path / "child.npz"
    r = subprocess.run([sys.executable, "-c", _CHILD, str(path)], env=env, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    got = np.load(path)
    assert int(got["lanes"]) == lanes
    want = {}
    exec(_EVALS, want)  # noqa: S102 - the same evaluations, with this process's lanes
    for i, w in enumerate(want["out"]):
        assert np.array_equal(got[f"arr_{i}"], w), i


def test_forced_lane_count_is_checked():
    import os
    import subprocess
    import sys

    env = dict(os.environ, SCATMODES_LANES="12")
    r = subprocess.run([sys.executable, "-c", "import basis.jit"], env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode != 0 and "SCATMODES_LANES must be 2, 4, 8 or 16" in r.stderr
