"""Lane-wise arithmetic written as Python expressions that emit LLVM vector IR.

A kernel whose lanes follow different paths through branches (a ray walking a pyramid,
say) is not vectorised by LLVM's loop vectoriser, and numba runs no SLP vectoriser. An
intrinsic can still emit the vector operations itself; these classes let its code generator
read like the scalar code it replaces: ``Vec`` values combine with ``+ - * /`` and compare
into ``Mask`` values, which combine with ``& | ~`` and choose with :meth:`Lanes.where`.

Every operation is the IEEE operation of the scalar expression, lane by lane, in the order
written (no reassociation, and no fused multiply-add but where :meth:`Lanes.fma` asks for
one, as :func:`basis.jit.fma` does in scalar code): a kernel written this way gives the bits
of the scalar code with the same expression. Masks are LLVM ``<W x i1>`` vectors: ``k``
registers with AVX-512, full-width compare results with AVX2.

:func:`host_lanes` is the width to use: the doubles in one vector register of the CPU that
numba compiles for (numba caches kernels per CPU and features, so a cached kernel never
runs at a width chosen for another machine).

Public, as :mod:`basis.jit` is, so that the kernels of ``project`` (the packet walk of the
microgeometry tracer) and of extensions share it.
"""

from __future__ import annotations

import llvmlite.binding as llvm
from llvmlite import ir
from numba.core import cgutils, config

__all__ = ["Lanes", "Mask", "Vec", "host_lanes"]

_D = ir.DoubleType()
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)


def host_lanes() -> int:
    """Doubles per vector register of the compile target: 8 (avx512f), 4 (AVX) or 2.

    The target is the host, or ``NUMBA_CPU_NAME`` / ``NUMBA_CPU_FEATURES`` when set (then a
    CPU name alone, without features, counts as 2: nothing is known of its registers).
    """
    if config.CPU_FEATURES:
        features = config.CPU_FEATURES
    elif config.CPU_NAME:
        return 2
    else:
        features = llvm.get_host_cpu_features().flatten()
    have = {f[1:] for f in features.split(",") if f.startswith("+")}
    if "avx512f" in have:
        return 8
    if "avx" in have:
        return 4
    return 2


#: :meth:`Lanes.gather` as one gather instruction (the CPU has AVX-512), else a load per
#: lane; read when a kernel compiles
GATHER = host_lanes() >= 8


class Lanes:
    """Emit ``w``-lane double operations with ``builder``; makes constants and chooses."""

    def __init__(self, builder: ir.IRBuilder, w: int):
        self.b = builder
        self.w = w
        self.vty = ir.VectorType(_D, w)

    def const(self, x) -> Vec:
        """``x`` as a vector: a Vec unchanged, a number in every lane."""
        if isinstance(x, Vec):
            return x
        return Vec(self, ir.Constant(self.vty, [float(x)] * self.w))

    def splat(self, x: ir.Value) -> Vec:
        """Return the scalar double ``x`` (an IR value) in every lane."""
        b = self.b
        v = b.insert_element(ir.Constant(self.vty, ir.Undefined), x, ir.Constant(_I32, 0))
        return Vec(self, b.shuffle_vector(v, ir.Constant(self.vty, ir.Undefined),
                                          ir.Constant(ir.VectorType(_I32, self.w),
                                                      [0] * self.w)))

    def load(self, ptr: ir.Value) -> Vec:
        """Load ``w`` doubles from the double pointer ``ptr`` (8-byte aligned)."""
        return Vec(self, self.b.load(self.b.bitcast(ptr, self.vty.as_pointer()), align=8))

    def store(self, ptr: ir.Value, v: Vec) -> None:
        """Store ``w`` doubles at the double pointer ``ptr`` (8-byte aligned)."""
        self.b.store(v.v, self.b.bitcast(ptr, self.vty.as_pointer()), align=8)

    def gather(self, data: ir.Value, index: Vec) -> Vec:
        """Load ``data[index]`` lane by lane.

        ``data`` is a float or double pointer, ``index`` holds whole numbers below 2^31
        (converted to int32); float values are widened to double (exact).

        Where :data:`GATHER` holds (AVX-512) this is one ``llvm.masked.gather``
        (``vgatherdpd`` / ``vgatherdps``: the packet walk's loop 296 instructions instead of
        434 for Skylake-SP, 247 cycles per step instead of 328 in llvm-mca's model of it).
        Elsewhere it is one load per lane: LLVM turns the gather into such loads on CPUs whose
        gather instruction it judges slow (AMD Zen 1 and 2), and there the explicit loads
        measured 3 % faster. Both load the same values.
        """
        b = self.b
        w = self.w
        elem = data.type.pointee
        ii = b.fptosi(index.v, ir.VectorType(_I32, w))
        if not GATHER:
            out = ir.Constant(self.vty, ir.Undefined)
            for j in range(w):
                k = b.sext(b.extract_element(ii, ir.Constant(_I32, j)), _I64)
                x = b.load(b.gep(data, [k]))
                if x.type != _D:
                    x = b.fpext(x, _D)
                out = b.insert_element(out, x, ir.Constant(_I32, j))
            return Vec(self, out)
        # the lanes' addresses: a getelementptr with a vector of indices, whose result (a
        # vector of pointers) llvmlite's gep does not type
        ptrs = ir.instructions.GEPInstr(b.block, data, [ii], inbounds=True, name="",
                                        source_etype=elem)
        ptrs.type = ir.VectorType(data.type, w)
        b._insert(ptrs)
        vty = ir.VectorType(elem, w)
        fnty = ir.FunctionType(vty, [ptrs.type, _I32, ir.VectorType(ir.IntType(1), w), vty])
        suffix = "f64" if elem == _D else "f32"
        fn = cgutils.get_or_insert_function(b.module, fnty,
                                            f"llvm.masked.gather.v{w}{suffix}.v{w}p0")
        x = b.call(fn, [ptrs, ir.Constant(_I32, 8 if elem == _D else 4),
                        ir.Constant(ir.VectorType(ir.IntType(1), w), [1] * w),
                        ir.Constant(vty, ir.Undefined)])
        return Vec(self, x if elem == _D else b.fpext(x, self.vty))

    def call(self, name: str, *vals: Vec) -> Vec:
        """Call an LLVM vector intrinsic such as ``llvm.floor`` on doubles."""
        fnty = ir.FunctionType(self.vty, [self.vty] * len(vals))
        fn = cgutils.get_or_insert_function(self.b.module, fnty, f"{name}.v{self.w}f64")
        return Vec(self, self.b.call(fn, [v.v for v in vals]))

    def floor(self, x: Vec) -> Vec:
        """Return ``floor(x)`` lane-wise (exact)."""
        return self.call("llvm.floor", x)

    def fma(self, a, b, c) -> Vec:
        """Return ``a * b + c`` rounded once, lane-wise (:func:`basis.jit.fma`)."""
        return self.call("llvm.fma", self.const(a), self.const(b), self.const(c))

    def where(self, m: Mask, a, b) -> Vec:
        """Return ``a`` in the lanes where ``m`` holds, else ``b``."""
        return Vec(self, self.b.select(m.m, self.const(a).v, self.const(b).v))

    def min(self, a: Vec, b: Vec) -> Vec:
        """Return numba's ``min(a, b)`` of floats lane-wise: ``b if b < a else a``."""
        return self.where(b < a, b, a)

    def any(self, m: Mask) -> ir.Value:
        """Return an i1 that holds when ``m`` holds in some lane."""
        bits = self.b.bitcast(m.m, ir.IntType(self.w))
        return self.b.icmp_unsigned("!=", bits, ir.Constant(ir.IntType(self.w), 0))

    def bits(self, m: Mask) -> ir.Value:
        """Return the lanes of ``m`` as the low bits of an int64 (lane j: bit j)."""
        return self.b.zext(self.b.bitcast(m.m, ir.IntType(self.w)), _I64)


class Mask:
    """A lane-wise truth value; ``& | ~`` combine."""

    def __init__(self, lanes: Lanes, m: ir.Value):
        self.lanes, self.m = lanes, m

    def __and__(self, o: Mask) -> Mask:
        return Mask(self.lanes, self.lanes.b.and_(self.m, o.m))

    def __or__(self, o: Mask) -> Mask:
        return Mask(self.lanes, self.lanes.b.or_(self.m, o.m))

    def __invert__(self) -> Mask:
        return Mask(self.lanes, self.lanes.b.not_(self.m))


class Vec:
    """A vector of doubles; numbers on either side are taken into every lane.

    Comparisons are ordered (false when a lane holds NaN), as Python's on floats; ``eq``
    is ``==`` (kept a method so that Vec stays hashable).
    """

    def __init__(self, lanes: Lanes, v: ir.Value):
        self.lanes, self.v = lanes, v

    def _o(self, o) -> ir.Value:
        return self.lanes.const(o).v

    def _op(self, name: str, a: ir.Value, b: ir.Value) -> Vec:
        return Vec(self.lanes, getattr(self.lanes.b, name)(a, b))

    def __add__(self, o) -> Vec:
        return self._op("fadd", self.v, self._o(o))

    def __radd__(self, o) -> Vec:
        return self._op("fadd", self._o(o), self.v)

    def __sub__(self, o) -> Vec:
        return self._op("fsub", self.v, self._o(o))

    def __rsub__(self, o) -> Vec:
        return self._op("fsub", self._o(o), self.v)

    def __mul__(self, o) -> Vec:
        return self._op("fmul", self.v, self._o(o))

    def __rmul__(self, o) -> Vec:
        return self._op("fmul", self._o(o), self.v)

    def __truediv__(self, o) -> Vec:
        return self._op("fdiv", self.v, self._o(o))

    def __neg__(self) -> Vec:
        return Vec(self.lanes, self.lanes.b.fneg(self.v))

    def _cmp(self, op: str, o) -> Mask:
        return Mask(self.lanes, self.lanes.b.fcmp_ordered(op, self.v, self._o(o)))

    def __lt__(self, o) -> Mask:
        return self._cmp("<", o)

    def __le__(self, o) -> Mask:
        return self._cmp("<=", o)

    def __gt__(self, o) -> Mask:
        return self._cmp(">", o)

    def __ge__(self, o) -> Mask:
        return self._cmp(">=", o)

    def eq(self, o) -> Mask:
        """Return ``self == o`` lane-wise (false where a lane holds NaN)."""
        return self._cmp("==", o)

    def ne(self, o) -> Mask:
        """Return ``self != o`` lane-wise, as Python's on floats: true where a lane is NaN."""
        return Mask(self.lanes, self.lanes.b.fcmp_unordered("!=", self.v, self._o(o)))
