"""The packet walk: LANES rays stepped through the max pyramid at once, in vector registers.

The ray-by-ray walk (``_paths._intersect``) spends most of its time waiting: each step
branches on where the ray is (climb, descend, test a cell) and the CPU mispredicts a good
share of these branches, which costs more than the step's arithmetic. Here one step of
LANES independent rays is one branch-free sequence of vector operations (:mod:`basis.simd`):
every lane computes its grid step, its pyramid node, the decision and, for lanes at the
finest level, the exact test of the cell's two triangles (skipped when no lane is there);
a select keeps what each lane needs. :func:`walk_step` repeats such steps, its state in
registers, until some lane's cast ends (hit, escaped or lost); its caller
(``trace._walk_casts``) hands that lane its next cast. Two packets stepped in the same loop
(independent chains for the CPU to overlap) were slower on an AVX2 machine with sixteen
vector registers: their operands spilled to the stack.

LANES is the vector width of the CPU (:func:`basis.simd.host_lanes`: 8 doubles with
AVX-512, 4 with AVX2, 2 otherwise). Every lane runs the operations of ``_intersect`` in
the same order, so a ray meets the same facet at the same bits whatever the width and
whatever its neighbours in the packet do (tests compare the two tracers bit for bit).

State layout: a (NROWS, LANES) float64 array, one row per quantity below, one column per
lane. Cell and node indices are kept as doubles (whole numbers, exact below 2^53), so that
the lanes need no integer vector instructions (AVX2 has no double to int64 conversion); the
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

# rows of the state array: the ray (origin, direction), its per-cast constants (_cast_setup),
# the walk (t, level, steps, lane in use), and what a hit leaves for the caller
(OX, OY, OZ, DX, DY, DZ, IDX, IDY, TSL, DU, DV, IGD, T, P2, IP2, STEPS, ACT,
 TA, TB, FA, FB, A1, A2, EVENT, CAST) = range(25)
NROWS = 25  # CAST: the caller's own (which cast the lane walks); walk_step leaves it alone

#: values of row EVENT: the lane's cast met a facet, left the slab above, or was lost
HIT, ESCAPED, LOST = 1.0, 2.0, 3.0

#: entries of the constants array G of :func:`walk_step`
(G_SX, G_SY, G_ISX, G_ISY, G_NX, G_NY, G_INX, G_INY, G_CELLS, G_HMIN, G_HMAX, G_TOL, G_PTOP,
 G_MAXSTEPS) = range(14)
NCONST = 14


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


def _walk_codegen():
    def codegen(context, builder, signature, args):
        sty, hty, pty, gty = signature.args
        S, h, pyr, G = args
        v = Lanes(builder, LANES)
        sdata = context.make_array(sty)(context, builder, S).data
        hdata = context.make_array(hty)(context, builder, h).data
        pdata = context.make_array(pty)(context, builder, pyr).data
        gdata = context.make_array(gty)(context, builder, G).data

        def at(r):
            return builder.gep(sdata, [ir.Constant(ir.IntType(64), r * LANES)])

        def const(i):
            return v.splat(builder.load(builder.gep(gdata, [ir.Constant(ir.IntType(64), i)])))

        sx, sy, isx, isy, nx, ny, inx, iny, cells, hmin, hmax, tol, ptop, maxsteps = (
            const(i) for i in range(NCONST))
        ox, oy, oz, dx, dy, dz = (v.load(at(r)) for r in (OX, OY, OZ, DX, DY, DZ))
        idx, idy, tsl, du, dv, igd = (v.load(at(r)) for r in (IDX, IDY, TSL, DU, DV, IGD))
        live = v.load(at(ACT)) > 0.0
        hit_slot = cgutils.alloca_once(builder, ir.VectorType(ir.IntType(1), LANES))

        # the steps loop here, in registers, until a lane's cast ends: what changes from step
        # to step (t, the level, the step count) is carried by phi nodes
        vty = ir.VectorType(ir.DoubleType(), LANES)
        first = builder.block
        loop = builder.append_basic_block("walk.step")
        done = builder.append_basic_block("walk.end")
        start = [v.load(at(r)) for r in (T, P2, IP2, STEPS)]
        builder.branch(loop)
        builder.position_at_end(loop)
        phis = [builder.phi(vty) for _ in start]
        for phi, x in zip(phis, start, strict=True):
            phi.add_incoming(x.v, first)
        t, p2, ip2, steps = (Vec(v, phi) for phi in phis)

        # -- the step of _intersect: node under the ray at the current level ------------------
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
        # steps of four lanes); lanes elsewhere read cell (0, 0), which stays in cache --
        builder.store(ir.Constant(ir.VectorType(ir.IntType(1), LANES), None), hit_slot)
        with builder.if_then(v.any(leaf), likely=True):
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
            for piece in range(2):
                ta, tb = (t, ts) if piece == 0 else (ts, t1)
                gm = g0 + (0.5 * (ta + tb) - t) * gd
                upper = gm >= 0.0
                a1 = v.where(upper, h10 - h00, h11 - h01)
                a2 = v.where(upper, h11 - h10, h01 - h00)
                fa = oz + ta * dz - (h00 + a1 * (ua + (ta - t) * du) + a2 * (va + (ta - t) * dv))
                fb = oz + tb * dz - (h00 + a1 * (ua + (tb - t) * du) + a2 * (va + (tb - t) * dv))
                cross = (fa > 0.0) & (fb <= 0.0)
                found = (ta, tb, fa, fb, a1, a2)
                if piece == 0:
                    hit, kept = cross, found
                else:
                    cross = cross & (tb > ta) & ~hit
                    kept = tuple(v.where(cross, a, b) for a, b in zip(found, kept, strict=True))
                    hit = hit | cross
            for r, x in zip((TA, TB, FA, FB, A1, A2), kept, strict=True):
                v.store(at(r), x)
            builder.store((leaf & hit).m, hit_slot)
        hit = Mask(v, builder.load(hit_slot))

        # -- the walk's update: advance past a cleared node or a crossed cell, climb, descend --
        crossed = leaf & ~hit
        adv = (go & clear) | crossed
        climb = ((go & clear & up) | crossed) & (p2 < ptop)
        new = (v.where(adv, t1, t), p2 * v.where(climb, 2.0, v.where(desc, 0.5, 1.0)),
               ip2 * v.where(climb, 0.5, v.where(desc, 2.0, 1.0)), steps + v.where(live, 1.0, 0.0))
        ended = hit | esc | lost
        last = builder.block
        for phi, x in zip(phis, new, strict=True):
            phi.add_incoming(x.v, last)
        builder.cbranch(builder.or_(v.any(ended), builder.not_(v.any(live))), done, loop)

        builder.position_at_end(done)
        for r, x in zip((T, P2, IP2, STEPS), new, strict=True):
            v.store(at(r), x)
        v.store(at(EVENT), v.where(hit, HIT, v.where(esc, ESCAPED, v.where(lost, LOST, 0.0))))
        return v.bits(ended)

    return codegen


def _walk_signature(S, h, pyr, G):
    ok = (isinstance(S, types.Array) and S.dtype == types.float64 and S.ndim == 2
          and isinstance(h, types.Array) and h.dtype == types.float64 and h.ndim == 2
          and isinstance(pyr, types.Array) and pyr.dtype == types.float32
          and isinstance(G, types.Array) and G.dtype == types.float64)
    if not ok:
        raise TypeError("walk_step(S float64 2-d, h float64 2-d, pyr float32, G float64)")
    return types.int64(S, h, pyr, G)


@intrinsic
def walk_step(typingctx, S, h, pyr, G):
    """One step of the pyramid walk for every lane of the packet ``S``.

    S : (NROWS, LANES) C-contiguous float64 state (rows above); updated in place.
    h : (ny, nx) C-contiguous float64 heights; pyr: the float32 pyramid of
    ``Heightfield._max_pyramid`` (fewer than 2^31 nodes); G: the NCONST constants.
    Lanes with ACT = 0 do nothing. Returns the lanes whose cast ended in this step as bits
    (lane j: bit j); their row EVENT says how (HIT: rows TA..A2 hold the crossing piece for
    ``_paths._facet_hit``), the others hold 0.
    """
    return _walk_signature(S, h, pyr, G), _walk_codegen()
