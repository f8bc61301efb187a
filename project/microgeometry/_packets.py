"""The packet walk: LANES rays stepped through the max pyramid at once, in vector registers.

The ray-by-ray walk (``_paths._intersect``) spends most of its time waiting: each step
branches on where the ray is (climb, descend, test a cell) and the CPU mispredicts a good
share of these branches, which costs more than the step's arithmetic. Here one step of
LANES independent rays is one branch-free sequence of vector operations (:mod:`basis.simd`):
every lane computes its grid step, its pyramid node, the decision and, for lanes at the
finest level, the exact test of the cell's two triangles (skipped when no lane is there);
a select keeps what each lane needs. :func:`walk_casts` walks a whole queue of casts (ray
segments, each to its first facet or out of the slab) this way: when some lanes' casts end
(hit, escaped or lost) it writes their results and gives those lanes the next casts of the
queue, without leaving the loop, so the lanes' state stays in registers throughout (the
tracer 1.06-1.10x faster on an AMD Zen 1 than when the loop returned to numba code for
each ended cast, which stored the state, refilled it lane by lane and loaded it back). Two
packets stepped in the same loop (independent chains for the CPU to overlap) were slower
on an AVX2 machine with sixteen vector registers: their operands spilled to the stack.

LANES is the vector width of the CPU (:func:`basis.simd.host_lanes`: 8 doubles with
AVX-512, 4 with AVX2, 2 otherwise). Every lane runs the operations of ``_intersect`` in
the same order, so a ray meets the same facet at the same bits whatever the width and
whatever its neighbours in the packet do (tests compare the two tracers bit for bit).

Cell and node indices are kept as doubles (whole numbers, exact below 2^53), so that the
lanes need no integer vector instructions (AVX2 has no double to int64 conversion); the
pyramid level is kept as p2 = 2^level and its inverse (doubling and halving are exact, so
node sizes sx p2 and counts nx / p2 are the bits of the scalar walk's running products).
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from basis.simd import Lanes, Mask, Vec, host_lanes

#: rays per packet: the doubles in one vector register of the CPU
LANES = host_lanes()

#: rows of the queue of casts (one column per cast): the origin (3 rows) and direction (3),
#: the per-cast constants of ``_paths._cast_setup`` (1/dx, 1/dy, t_slab, du, dv, 1/(du - dv)),
#: and a row of the caller's own (the path the cast continues), which the walk leaves alone
Q_ORIGIN, Q_DIR, Q_INV, Q_TSLAB, Q_DU, Q_PATH = 0, 3, 6, 8, 9, 12
QROWS = 13
#: rows of the results (one column per cast): the event, and the crossing piece of a hit
#: (``_paths._facet_hit``'s ta, tb, fa, fb, a1, a2)
R_EVENT, R_PIECE = 0, 1
RROWS = 7

#: values of row R_EVENT: the cast met a facet, left the slab above, or was lost
HIT, ESCAPED, LOST = 1.0, 2.0, 3.0

#: entries of the constants array G of :func:`walk_casts`
(G_SX, G_SY, G_ISX, G_ISY, G_NX, G_NY, G_INX, G_INY, G_CELLS, G_HMIN, G_HMAX, G_TOL, G_PTOP,
 G_MAXSTEPS) = range(14)
NCONST = 14

# the lanes' state: the queue's first rows (the cast), then the walk's own
_RAY = Q_PATH  # rows 0 .. 11 of the queue
_T, _P2, _IP2, _STEPS, _LIVE, _CAST = range(_RAY, _RAY + 6)
_STATE = _RAY + 6
#: a lane's walk state at the start of a cast (the live flag is 1.0)
_START = ((_T, 0.0), (_P2, 1.0), (_IP2, 1.0), (_STEPS, 0.0), (_LIVE, 1.0))


def _axis(v: Lanes, o, d, inv_d, t, w, iw):
    # _paths._grid_step lane-wise: the index (a double) and exit distance along one axis,
    # the three cases (d > 0, d < 0, d = 0) chosen by select instead of branches
    p = o + t * d
    f = v.floor(p * iw)
    pos = d > 0.0
    e = v.where(pos, f + 1.0, f) * w
    stay = (e - o) * inv_d
    enter = (v.where(pos, f + 2.0, f - 1.0) * w - o) * inv_d
    take = v.where(pos, e - p, p - e) <= w * 1e-9  # 1e-9: _intersect's tol for the step
    fi = v.where(take, v.where(pos, f + 1.0, f - 1.0), f)
    flat = d.eq(0.0)
    return v.where(flat, f, fi), v.where(flat, float("inf"), v.where(take, enter, stay))


def _wrap(v: Lanes, f, n, inv_n):
    # f modulo n (whole numbers; Python's modulo, in [0, n)) without a division: the
    # quotient from the product by inv_n ~ 1 / n may be one off (when n is not a power of
    # two), which the two selects correct; every operation is exact on whole numbers
    r = f - v.floor(f * inv_n) * n
    r = v.where(r < 0.0, r + n, r)
    return v.where(r >= n, r - n, r)


def _step(v: Lanes, k, st, hdata, pdata, piece, hit_slot):
    # One step of _intersect for every lane: returns (t, p2, ip2, steps) after it, the
    # lanes whose cast ended in it and how. A step with a lane at the finest level stores
    # every lane's crossing piece in the slots ``piece``: the walk reads them right after
    # the step, and only for the lanes that hit in it
    b = v.b
    sx, sy, isx, isy, nx, ny, inx, iny, cells, hmin, hmax, tol, ptop, maxsteps = k
    ox, oy, oz, dx, dy, dz, idx, idy, tsl, du, dv, igd, t, p2, ip2, steps = st[:_LIVE]
    live = st[_LIVE] > 0.0

    # -- the node under the ray at the current level --------------------------------------
    z = oz + t * dz
    fx, tx = _axis(v, ox, dx, idx, t, sx * p2, isx * ip2)
    fy, ty = _axis(v, oy, dy, idy, t, sy * p2, isy * ip2)
    txy = v.min(tx, ty)
    t1 = v.min(txy, tsl)
    wl = nx * ip2
    hl = ny * ip2
    cx = _wrap(v, fx, wl, inx * p2)
    cy = _wrap(v, fy, hl, iny * p2)
    # offset of the level in the flat pyramid: the levels below hold cells (1 + 1/4 +
    # ... + 4^(1 - level)) nodes, a whole number that this computes exactly
    q = ip2 * ip2
    off = ((cells - cells * q) * 4.0) / 3.0
    zn = v.gather(pdata, off + cy * wl + cx)
    clear = v.min(z, oz + t1 * dz) > zn
    px = fx - 2.0 * v.floor(fx * 0.5)
    py = fy - 2.0 * v.floor(fy * 0.5)
    up = (tsl <= txy) | ((tx <= ty) & px.eq(v.where(dx > 0.0, 1.0, 0.0))) | (
        (ty <= tx) & py.eq(v.where(dy > 0.0, 1.0, 0.0)))
    cap = steps >= maxsteps
    esc = live & ~cap & (dz >= 0.0) & (z > hmax)
    lost = live & (cap | ((dz < 0.0) & (z < hmin - tol)))
    go = live & ~esc & ~lost
    deep = p2 > 1.0
    desc = go & ~clear & deep
    leaf = go & ~clear & ~deep

    # -- _cell at the finest level, skipped when no lane is there (about a third of the
    # steps of four lanes); lanes elsewhere read cell (0, 0), which stays in cache --------
    b.store(ir.Constant(ir.VectorType(ir.IntType(1), LANES), None), hit_slot)
    with b.if_then(v.any(leaf), likely=True):
        cxl = v.where(leaf, cx, 0.0)
        cyl = v.where(leaf, cy, 0.0)
        i1 = v.where(cxl + 1.0 < nx, cxl + 1.0, 0.0)
        j1 = v.where(cyl + 1.0 < ny, cyl + 1.0, 0.0)
        h00 = v.gather(hdata, cyl * nx + cxl)
        h10 = v.gather(hdata, cyl * nx + i1)
        h01 = v.gather(hdata, j1 * nx + cxl)
        h11 = v.gather(hdata, j1 * nx + i1)
        ua = (ox + t * dx - fx * sx) * isx
        va = (oy + t * dy - fy * sy) * isy
        g0 = ua - va
        gd = du - dv
        tc = t - g0 * igd
        ts = v.where(gd.ne(0.0) & (t < tc) & (tc < t1), tc, t1)
        hit = None
        for half in range(2):
            ta, tb = (t, ts) if half == 0 else (ts, t1)
            gm = g0 + (0.5 * (ta + tb) - t) * gd
            upper = gm >= 0.0
            a1 = v.where(upper, h10 - h00, h11 - h01)
            a2 = v.where(upper, h11 - h10, h01 - h00)
            fa = oz + ta * dz - (h00 + a1 * (ua + (ta - t) * du) + a2 * (va + (ta - t) * dv))
            fb = oz + tb * dz - (h00 + a1 * (ua + (tb - t) * du) + a2 * (va + (tb - t) * dv))
            cross = (fa > 0.0) & (fb <= 0.0)
            found = (ta, tb, fa, fb, a1, a2)
            if half == 0:
                hit, kept = cross, found
            else:
                cross = cross & (tb > ta) & ~hit
                kept = tuple(v.where(cross, a, c) for a, c in zip(found, kept, strict=True))
                hit = hit | cross
        hit = leaf & hit
        for slot, x in zip(piece, kept, strict=True):
            b.store(x.v, slot)
        b.store(hit.m, hit_slot)
    hit = Mask(v, b.load(hit_slot))

    # -- the walk's update: advance past a cleared node or a crossed cell, climb, descend --
    crossed = leaf & ~hit
    adv = (go & clear) | crossed
    climb = ((go & clear & up) | crossed) & (p2 < ptop)
    new = (v.where(adv, t1, t), p2 * v.where(climb, 2.0, v.where(desc, 0.5, 1.0)),
           ip2 * v.where(climb, 0.5, v.where(desc, 2.0, 1.0)), steps + v.where(live, 1.0, 0.0))
    event = v.where(hit, HIT, v.where(esc, ESCAPED, v.where(lost, LOST, 0.0)))
    return new, hit | esc | lost, event


def _walk_codegen(context, builder, signature, args):
    cty, rty, _, hty, pty, gty = signature.args
    C, R, ncast, h, pyr, G = args
    b = builder
    v = Lanes(b, LANES)
    d, i32, i64 = ir.DoubleType(), ir.IntType(32), ir.IntType(64)
    bits_ty = ir.IntType(LANES)
    vty = ir.VectorType(d, LANES)
    carr = context.make_array(cty)(context, b, C)
    rarr = context.make_array(rty)(context, b, R)
    cstride = b.extract_value(carr.shape, 1)
    rstride = b.extract_value(rarr.shape, 1)
    hdata = context.make_array(hty)(context, b, h).data
    pdata = context.make_array(pty)(context, b, pyr).data
    gdata = context.make_array(gty)(context, b, G).data
    k = tuple(v.splat(b.load(b.gep(gdata, [ir.Constant(i64, i)]))) for i in range(NCONST))

    def entry(data, stride, row, col):  # &array[row, col] of a C-contiguous 2-d array
        return b.gep(data, [b.add(b.mul(ir.Constant(i64, row), stride), col)])

    # the lanes' state, the crossing pieces and the queue's next cast in stack slots, which
    # LLVM promotes to registers (phi nodes): written as loads and stores of slots, the
    # lanes' control flow needs no phi bookkeeping here
    zero = ir.Constant(vty, [0.0] * LANES)
    state = [cgutils.alloca_once_value(b, zero) for _ in range(_STATE)]
    piece = [cgutils.alloca_once_value(b, zero) for _ in range(RROWS - R_PIECE)]
    hit_slot = cgutils.alloca_once(b, ir.VectorType(ir.IntType(1), LANES))
    event = cgutils.alloca_once_value(b, zero)
    ended = cgutils.alloca_once_value(b, ir.Constant(bits_ty, (1 << LANES) - 1))  # all idle
    nxt = cgutils.alloca_once_value(b, ir.Constant(i64, 0))
    step = b.append_basic_block("walk.step")
    turn = b.append_basic_block("walk.turn")
    done = b.append_basic_block("walk.end")
    b.branch(turn)

    # -- steps until some lane's cast ends --------------------------------------------------
    b.position_at_end(step)
    new, end, ev = _step(v, k, [Vec(v, b.load(s)) for s in state], hdata, pdata, piece,
                         hit_slot)
    for slot, x in zip(state[_T:_LIVE], new, strict=True):
        b.store(x.v, slot)
    b.store(ev.v, event)
    b.store(b.bitcast(end.m, bits_ty), ended)
    b.cbranch(v.any(end), turn, step)

    # -- each lane whose cast ended (at the start: every lane) writes its results and takes
    # the next cast of the queue; with none left it idles -----------------------------------
    b.position_at_end(turn)
    bits = b.load(ended)
    results = [b.load(event)] + [b.load(s) for s in piece]

    def put(row, lane, x):  # lane ``lane`` of state row ``row`` = the double x
        b.store(b.insert_element(b.load(state[row]), x, lane), state[row])

    for j in range(LANES):
        lane = ir.Constant(i32, j)
        with b.if_then(b.trunc(b.lshr(bits, ir.Constant(bits_ty, j)), ir.IntType(1))):
            was = b.fcmp_ordered(">", b.extract_element(b.load(state[_LIVE]), lane),
                                 ir.Constant(d, 0.0))
            with b.if_then(was):
                c = b.fptosi(b.extract_element(b.load(state[_CAST]), lane), i64)
                for row, x in enumerate(results):
                    b.store(b.extract_element(x, lane), entry(rarr.data, rstride, row, c))
            n = b.load(nxt)
            with b.if_else(b.icmp_signed("<", n, ncast)) as (more, idle):
                with more:
                    for row in range(_RAY):
                        put(row, lane, b.load(entry(carr.data, cstride, row, n)))
                    for row, x in _START:
                        put(row, lane, ir.Constant(d, x))
                    put(_CAST, lane, b.sitofp(n, d))
                    b.store(b.add(n, ir.Constant(i64, 1)), nxt)
                with idle:
                    put(_LIVE, lane, ir.Constant(d, 0.0))
    b.cbranch(v.any(Vec(v, b.load(state[_LIVE])) > 0.0), step, done)
    b.position_at_end(done)
    return context.get_dummy_value()


@intrinsic
def walk_casts(typingctx, C, R, ncast, h, pyr, G):
    """Walk casts 0 .. ncast - 1 of the queue ``C`` to their ends; ``R[:, c]``: how cast c ended.

    C : (QROWS, >= ncast) C-contiguous float64 queue (rows above); R: (RROWS, >= ncast)
    C-contiguous float64 results; h : (ny, nx) C-contiguous float64 heights; pyr: the
    float32 pyramid of ``Heightfield._max_pyramid`` (fewer than 2^31 nodes); G: the NCONST
    constants. Row R_EVENT of a cast says how it ended (HIT: rows R_PIECE.. hold the
    crossing piece for ``_paths._facet_hit``); casts are taken in order, LANES at a time.
    """
    def array(t, dtype, ndim):
        return (isinstance(t, types.Array) and t.dtype == dtype and t.ndim == ndim
                and t.layout == "C")

    if not (array(C, types.float64, 2) and array(R, types.float64, 2)
            and isinstance(ncast, types.Integer) and array(h, types.float64, 2)
            and array(pyr, types.float32, 1) and array(G, types.float64, 1)):
        raise TypeError("walk_casts(C float64 2-d C, R float64 2-d C, ncast int, "
                        "h float64 2-d C, pyr float32 1-d C, G float64 1-d C)")
    return types.void(C, R, types.int64, h, pyr, G), _walk_codegen
