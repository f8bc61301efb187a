"""basis.simd: lane-wise expressions emit the IEEE operations of the scalar code.

The reference is the same expression compiled by numba as scalar code (Python semantics of
comparisons, numba's min), evaluated lane by lane: results must be equal bit for bit,
including NaN, infinities and signed zeros in the inputs.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest
from numba import types
from numba.core import config
from numba.extending import intrinsic

from basis import simd
from basis.jit import fma
from basis.simd import Lanes, host_lanes

W = 4


def _expr(v, x, y):
    # every operation of Vec and Lanes once
    m = (x < y) | ((x >= 2.0) & ~(y > 0.5)) | x.ne(x)
    a = v.where(m, v.floor(x) * 2.0 - y / 3.0, v.min(x, y))
    b = v.where(x.eq(y) | (x <= -1.0), 1.0 - x, -y + 0.25)
    return v.fma(a + b, y, x), m  # (a + b) * y + x, rounded once


@intrinsic
def _lanes_expr(typingctx, x, y, out):
    def codegen(context, builder, signature, args):
        v = Lanes(builder, W)
        ptr = [context.make_array(t)(context, builder, a).data
               for t, a in zip(signature.args, args, strict=True)]
        r, m = _expr(v, v.load(ptr[0]), v.load(ptr[1]))
        v.store(ptr[2], r)
        return v.bits(m)

    return types.int64(x, y, out), codegen


@numba.njit(cache=False)
def _vector_kernel(x, y, out):
    return _lanes_expr(x, y, out)


@numba.njit(cache=False, error_model="numpy")
def _scalar_kernel(x, y, out):
    bits = 0
    for j in range(x.shape[0]):
        a, b = x[j], y[j]
        m = (a < b) or (a >= 2.0 and not (b > 0.5)) or (a != a)
        p = np.floor(a) * 2.0 - b / 3.0 if m else min(a, b)
        q = 1.0 - a if (a == b or a <= -1.0) else -b + 0.25
        out[j] = fma(p + q, b, a)
        bits |= int(m) << j
    return bits


_SPECIAL = [0.0, -0.0, 1.0, -1.0, 2.5, 0.5, np.inf, -np.inf, np.nan, 1e-300, -3.7, 2.0]


def test_lane_expressions_match_scalar_code_bit_for_bit():
    rng = np.random.default_rng(0)
    vals = np.concatenate([_SPECIAL, rng.normal(0, 3, 40)])
    x = np.array(np.meshgrid(vals, vals)).reshape(2, -1)
    n = x.shape[1] - x.shape[1] % W
    for i in range(0, n, W):
        a, b = x[0, i:i + W].copy(), x[1, i:i + W].copy()
        got, want = np.empty(W), np.empty(W)
        assert _vector_kernel(a, b, got) == _scalar_kernel(a, b, want)
        assert np.array_equal(got.view(np.int64), want.view(np.int64)), (a, b, got, want)


@pytest.mark.parametrize("features, name, lanes", [
    ("+avx512f,+avx2,+avx", "", 8),
    ("+avx2,+avx,-avx512f", "", 4),
    ("+sse4.2,-avx", "", 2),
    ("", "generic", 2),  # a CPU name alone: nothing known of its registers
])
def test_host_lanes_follows_the_compile_target(monkeypatch, features, name, lanes):
    monkeypatch.setattr(config, "CPU_FEATURES", features)
    monkeypatch.setattr(config, "CPU_NAME", name)
    assert host_lanes() == lanes


def test_host_lanes_of_this_machine_matches_its_features():
    if config.CPU_FEATURES or config.CPU_NAME:
        pytest.skip("NUMBA_CPU_NAME / NUMBA_CPU_FEATURES set: not the host")
    flags = set(simd.llvm.get_host_cpu_features().flatten().split(","))
    assert host_lanes() == (8 if "+avx512f" in flags else 4 if "+avx" in flags else 2)



def _gather_kernel():
    # a fresh kernel each call: GATHER is read when it compiles
    @intrinsic
    def lanes_gather(typingctx, data, index, out):
        def codegen(context, builder, signature, args):
            v = Lanes(builder, W)
            d, i, o = (context.make_array(t)(context, builder, a).data
                       for t, a in zip(signature.args, args, strict=True))
            v.store(o, v.gather(d, v.load(i)))
            return context.get_dummy_value()

        return types.void(data, index, out), codegen

    @numba.njit(cache=False)
    def kernel(data, index, out):
        lanes_gather(data, index, out)

    return kernel


@pytest.mark.parametrize("gather", [False, True])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_gather_loads_each_lanes_entry(monkeypatch, gather, dtype):
    # both ways of gathering (one gather instruction, the AVX-512 default, or a load per
    # lane) against numpy's indexing; floats are widened exactly, repeated and far-apart
    # indices included
    monkeypatch.setattr(simd, "GATHER", gather)
    data = (np.arange(5000, dtype=np.float64) * 1.1 - 7.3).astype(dtype)
    kernel = _gather_kernel()
    for index in ([0, 4999, 3, 3], [17, 2, 4096, 1]):
        idx = np.array(index, dtype=np.float64)
        out = np.empty(W)
        kernel(data, idx, out)
        assert np.array_equal(out, data[idx.astype(np.int64)].astype(np.float64))
    ir = next(iter(kernel.inspect_llvm().values()))
    assert ("llvm.masked.gather" in ir) == gather
