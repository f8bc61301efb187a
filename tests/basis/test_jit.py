"""The eight-lane vector intrinsics of basis.jit against numpy's scalar IEEE arithmetic."""

import numba
import numpy as np

from basis.jit import (
    LANES,
    lane_mul,
    lane_recur,
    lane_rotate,
    lane_scaled,
    lane_transpose,
    lane_unit,
)


@numba.njit(cache=False)
def _run(out, x, p1, p2, cc, ss, seed, c1, s1, sn, tile, src, dirs, unit):
    lane_recur(out, 0, x, 0, p1, LANES, p2, 0, 1.5, 0.25)
    lane_scaled(out, LANES, 1.5, x, 0, p1, LANES)
    lane_mul(out, 2 * LANES, x, 0, p1, LANES)
    lane_rotate(cc, ss, seed, LANES, c1, s1, 0.75, sn)
    lane_transpose(tile, 3, 11, src, LANES)
    return lane_unit(dirs, 1, unit[0], unit[1], unit[2], unit[3], 1e-3)


def test_lane_operations_give_the_scalar_bits(rng):
    # Reference: the same expressions in numpy, evaluated element by element in the same
    # order (no fused multiply-add on either side), so equality is bitwise, no tolerance.
    x, p1, p2 = rng.random(LANES), rng.random(2 * LANES), rng.random(LANES)
    cc, ss, seed = rng.random(2 * LANES), rng.random(2 * LANES), rng.random(2 * LANES)
    c1, sn = rng.random(LANES), rng.random(LANES)
    src = rng.random(10 * LANES)
    dirs = rng.normal(size=(2 + LANES, 3))
    dirs[3] = [0.0, 0.0, 1.0]  # the pole: azimuth (1, 0)
    dirs[4] = [1e-9, 0.0, 1.0]  # 0 < sin(theta) < 1e-3: flagged
    out, tile, unit = np.zeros(3 * LANES), np.zeros((8, 11)), np.zeros((4, LANES))
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
            assert flat[3 + 11 * j + r] == src[LANES + LANES * r + j]
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
