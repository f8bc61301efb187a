"""MERL tables: the file layout, the grid and its lookups, invalid cells, damaged files.

References are independent of ``project.measured``: files are assembled byte by byte with
numpy, node directions are built as the surrogate tool builds them (rotate d by theta_h about
y, mirror about h), and index coordinates come from ``basis.to_rusinkiewicz`` and the MERL
formulas written out here.
"""

from __future__ import annotations

import os
import re

import numpy as np
import pytest

from basis import from_rusinkiewicz, to_rusinkiewicz
from project.brdf import BRDF, MirrorDelta
from project.measured import (
    MERL_BYTES,
    MERL_SCALE,
    MERL_SHAPE,
    MERLBRDF,
    merl_grid,
    read_merl,
    write_merl,
)

SCALE = np.array([1.0 / 1500, 1.15 / 1500, 1.66 / 1500])  # MERL reference reader's constants
N = 90 * 90 * 180


def merl_bytes(raw: np.ndarray, dims: tuple[int, int, int] = (90, 90, 180),
               header: str = "<i4") -> bytes:
    """A MERL file assembled by hand: int32 dims, then channel-major little-endian float64."""
    return np.array(dims, header).tobytes() + np.asarray(raw, "<f8").tobytes()


def node_directions() -> tuple[np.ndarray, np.ndarray]:
    """(wi, wo), each (90, 90, 180, 3), at the MERL nodes, built as merl_surrogate.py does."""
    th = ((np.arange(90) / 90) ** 2 * np.pi / 2)[:, None, None]
    td = (np.arange(90) * np.pi / 180)[None, :, None]
    pd = (np.arange(180) * np.pi / 180)[None, None, :]
    th, td, pd = np.broadcast_arrays(th, td, pd)
    d = np.stack([np.sin(td) * np.cos(pd), np.sin(td) * np.sin(pd), np.cos(td)], -1)
    h = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], -1)
    c, s = np.cos(th), np.sin(th)
    wi = np.stack([c * d[..., 0] + s * d[..., 2], d[..., 1], -s * d[..., 0] + c * d[..., 2]], -1)
    wo = 2 * np.sum(wi * h, -1, keepdims=True) * h - wi
    return wi, wo


def merl_coordinates(wi: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, ...]:
    """Continuous MERL indices (u, v, w) from the formulas of the format description."""
    theta_h, _, theta_d, phi_d = to_rusinkiewicz(wi, wo)
    u = np.sqrt(theta_h / (np.pi / 2)) * 90
    v = theta_d / (np.pi / 2) * 90
    w = np.mod(phi_d, np.pi) / np.pi * 180
    return u, v, w


def random_pairs(rng: np.random.Generator, n: int,
                 low: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Pairs with both directions above the horizon, from random Rusinkiewicz angles with
    theta_h, theta_d >= ``low`` (phi_d is ill-conditioned near theta_h = 0 and theta_d = 0)."""
    wi, wo = from_rusinkiewicz(rng.uniform(low, np.pi / 2, 3 * n),
                               rng.uniform(0, 2 * np.pi, 3 * n),
                               rng.uniform(low, np.pi / 2, 3 * n),
                               rng.uniform(0, 2 * np.pi, 3 * n))
    up = (wi[:, 2] > 1e-6) & (wo[:, 2] > 1e-6)
    return wi[up][:n], wo[up][:n]


def index_tolerance(theta_h: np.ndarray, theta_d: np.ndarray) -> tuple[np.ndarray, ...]:
    """Rounding bounds (in cells) of the lookup coordinates (u, v, w) at these angles.

    v is well conditioned (a few ulps of 89); u = 90 sqrt(2 theta_h / pi) has derivative
    90 / (pi sqrt(2 theta_h / pi)); phi_h, hence phi_d, is undefined at theta_h = 0 and phi_d
    at theta_d = 0, so phi_d carries eps (1/sin theta_h + 1/sin theta_d) rad. Both the
    reference and the lookup round, independently. Observed over 600,000 random pairs: u
    within 77 and w within 401 times these bounds; allowed 200 and 1000. Exactly at
    theta_h = 0 or theta_d = 0 (nodes built with h = z or wi = wo exactly) the singular
    terms do not arise and are dropped.
    """
    eps = np.finfo(float).eps
    sh, sd = np.sin(theta_h), np.sin(theta_d)
    inv_h = np.divide(1.0, sh, out=np.zeros_like(sh), where=theta_h > 0)
    inv_d = np.divide(1.0, sd, out=np.zeros_like(sd), where=theta_d > 0)
    root = np.sqrt(2 * theta_h / np.pi)
    tol_u = 200 * eps * 90 / np.pi * np.divide(1.0, root, out=np.zeros_like(root),
                                                where=root > 0)
    tol_v = np.full_like(theta_h, 1000 * eps)
    tol_w = 1000 * eps * 180 / np.pi * (inv_h + inv_d)
    return tol_u, tol_v, tol_w


@pytest.fixture(scope="module")
def index_brdf() -> MERLBRDF:
    """Channels hold the theta_h, theta_d and phi_d indices: lookups return coordinates."""
    i, j, k = np.meshgrid(np.arange(90.0), np.arange(90.0), np.arange(180.0), indexing="ij")
    return MERLBRDF(np.stack([i, j, k]), name="index")


@pytest.fixture(scope="module")
def random_brdf() -> MERLBRDF:
    """Independent uniform values: the harshest table for interpolation (module-scoped, so it
    has its own fixed seed rather than the per-test ``rng``)."""
    return MERLBRDF(np.random.default_rng(7).uniform(0.0, 1.0, MERL_SHAPE), name="random")


class Smooth(BRDF):
    """f = (1 + z_i z_o + 0.3 wi.wo) * (1, 2, 3): isotropic, reciprocal, smooth."""

    channels = 3
    _scalar = False

    def _eval(self, wi, wo):
        g = 1.0 + wi[:, 2] * wo[:, 2] + 0.3 * np.sum(wi * wo, axis=1)
        return g[:, None] * np.array([1.0, 2.0, 3.0])


# ---------------------------------------------------------------------------------- format


def test_format_constants():
    th, td, pd = merl_grid()
    # the grid formulas are the definition: exact equality
    np.testing.assert_array_equal(th, (np.arange(90) / 90) ** 2 * (np.pi / 2))
    np.testing.assert_array_equal(td, np.arange(90) * (np.pi / 2) / 90)
    np.testing.assert_array_equal(pd, np.arange(180) * np.pi / 180)
    np.testing.assert_array_equal(MERL_SCALE, SCALE)
    assert MERL_SHAPE == (3, 90, 90, 180)
    assert MERL_BYTES == 34_992_012


def test_reads_hand_made_file(tmp_path, rng):
    raw = rng.uniform(0, 3000, (3, N))
    raw[:, 5] = -1.0
    raw[2, 7] = -0.5  # any negative value is invalid, per channel
    path = tmp_path / "hand.binary"
    path.write_bytes(merl_bytes(raw))
    brdf = read_merl(path)
    expect = (raw * SCALE[:, None]).reshape(MERL_SHAPE)
    expect[(raw < 0).reshape(MERL_SHAPE)] = np.nan
    # raw * scale is one multiplication, as in the reference reader: bit for bit
    np.testing.assert_array_equal(brdf.table, expect)
    assert (brdf.name, brdf.path, brdf.channels, brdf.isotropic, brdf.reciprocal) == (
        "hand", path, 3, True, True)
    assert brdf.valid.sum() == 3 * N - 4  # cell 5 in three channels, cell 7 in blue
    assert brdf.valid_fraction == pytest.approx(1 - 4 / (3 * N), rel=1e-15)  # a mean of bools
    with pytest.raises(ValueError, match="read-only"):
        brdf.table[0, 0, 0, 0] = 1.0
    with pytest.raises(ValueError, match="cannot set WRITEABLE flag"):
        brdf.table.flags.writeable = True


def test_round_trip_exact_for_stored_values(tmp_path, rng):
    # values that a MERL file can hold (raw * scale), over 40 binades, with invalid cells
    raw = rng.uniform(1, 2, MERL_SHAPE) * 2.0 ** rng.integers(-20, 20, MERL_SHAPE)
    table = raw * SCALE[:, None, None, None]
    table[:, 3, 80:] = np.nan
    path = write_merl(tmp_path / "rt.binary", table)
    assert os.path.getsize(path) == MERL_BYTES
    data = np.fromfile(path, "<f8", offset=12).reshape(MERL_SHAPE)
    np.testing.assert_array_equal(np.fromfile(path, "<i4", count=3), [90, 90, 180])
    np.testing.assert_array_equal(data[:, 3, 80:], -1.0)  # NaN is written as the -1 marker
    back = read_merl(path)
    # fl(fl(t / s) * s) == t when t = fl(r * s): bit for bit, NaN where written invalid
    np.testing.assert_array_equal(back.table, table)
    # writing what was read reproduces the file byte for byte
    again = write_merl(tmp_path / "again.binary", back)
    assert again.read_bytes() == path.read_bytes()


def test_round_trip_arbitrary_values_within_one_ulp(tmp_path, rng):
    table = rng.uniform(0, 10, MERL_SHAPE)
    back = read_merl(write_merl(tmp_path / "rt.binary", table))
    # about 10-15 % of doubles are not fl(r * fl(1/1500)) for any r: they come back 1 ulp off
    np.testing.assert_array_max_ulp(back.table, table, maxulp=1)


# ------------------------------------------------------------------------------- the grid


def test_lookup_coordinates(index_brdf, rng):
    wi, wo = random_pairs(rng, 20000)
    u, v, w = merl_coordinates(wi, wo)
    theta_h, _, theta_d, _ = to_rusinkiewicz(wi, wo)
    got = index_brdf.eval(wi, wo)
    # table = index, so trilinear returns the coordinate itself, clamped at the last node;
    # phi_d wraps: between node 179 and node 0 (at 180) the value falls from 179 to 0
    wrap = np.where(w > 179, 179 * (180 - w), w)
    tol_u, tol_v, tol_w = index_tolerance(theta_h, theta_d)  # rounding, see there
    assert np.all(np.abs(got[:, 0] - np.minimum(u, 89)) <= tol_u)
    assert np.all(np.abs(got[:, 1] - np.minimum(v, 89)) <= tol_v)
    assert np.all(np.abs(got[:, 2] - wrap) <= tol_w)
    assert (u > 89).any() and (w > 179).any() and (v > 89).any()  # the edges were visited
    near = index_brdf.with_interpolation("nearest").eval(wi, wo)
    # nearest node: exact integers (ties have probability ~1e-11 here)
    np.testing.assert_array_equal(near[:, 0], np.minimum(np.round(u), 89))
    np.testing.assert_array_equal(near[:, 1], np.minimum(np.round(v), 89))
    np.testing.assert_array_equal(near[:, 2], np.round(w) % 180)


def test_theta_h_index_is_nonlinear(index_brdf):
    # theta_h = 45 deg sits at u = 90 sqrt(1/2) = 63.64, not at the linear 45
    wi, wo = from_rusinkiewicz(np.pi / 4, 0.3, 0.1, 0.2)
    # one coordinate conversion: a few ulps of 63.6 (see test_lookup_coordinates)
    assert index_brdf.eval(wi, wo)[0] == pytest.approx(90 * np.sqrt(0.5), abs=1e-12)
    # node i is at (i/90)^2 pi/2: node 30 is theta_h = 10 deg
    wi, wo = from_rusinkiewicz(np.radians(10.0), 0.0, 0.1, 0.2)
    assert index_brdf.with_interpolation("nearest").eval(wi, wo)[0] == 30.0


def test_reciprocity_and_phi_d_period(random_brdf, rng):
    wi, wo = random_pairs(rng, 5000, low=0.05)
    for brdf in (random_brdf, random_brdf.with_interpolation("nearest")):
        # h and |wi - wo| are symmetric and wi - wo antisymmetric in floating point, so the
        # folded coordinates, and the values, are bitwise equal
        np.testing.assert_array_equal(brdf.eval(wi, wo), brdf.eval(wo, wi))
    th, ph, td, pd = to_rusinkiewicz(wi, wo)
    a = random_brdf.eval(*from_rusinkiewicz(th, ph, td, pd))
    b = random_brdf.eval(*from_rusinkiewicz(th, ph, td, pd + np.pi))
    # phi_d and phi_d + pi give wi and wo swapped up to rounding; with theta_h, theta_d >=
    # 0.05 the coordinates move by < 2 * 1000 eps (2/0.05) 180/pi = 1.0e-9 cells (see
    # index_tolerance), and values of a table in [0, 1] by no more; 2e-9 leaves a factor 2
    np.testing.assert_allclose(a, b, rtol=0, atol=2e-9)


def test_isotropic(random_brdf, rng):
    wi, wo = random_pairs(rng, 5000, low=0.05)
    alpha = 1.234
    rot = np.array([[np.cos(alpha), -np.sin(alpha), 0], [np.sin(alpha), np.cos(alpha), 0],
                    [0, 0, 1]])
    # rotating both directions about the normal changes phi_h only; rounding as in
    # test_reciprocity_and_phi_d_period
    np.testing.assert_allclose(random_brdf.eval(wi @ rot.T, wo @ rot.T),
                               random_brdf.eval(wi, wo), rtol=0, atol=2e-9)


def test_nearest_and_trilinear_agree_at_nodes(random_brdf, rng):
    wi, wo = node_directions()
    valid = (wi[..., 2] > 1e-9) & (wo[..., 2] > 1e-9)
    valid[:, 0] = False  # theta_d = 0: wi = wo, phi_d (the node's k) cannot be recovered
    cells = rng.choice(np.flatnonzero(valid), 20000, replace=False)
    i, j, k = np.unravel_index(cells, valid.shape)
    expect = random_brdf.table[:, i, j, k].T
    wi, wo = wi.reshape(-1, 3)[cells], wo.reshape(-1, 3)[cells]
    # nearest: the node's own value, bit for bit (rounding moves u, v, w by << 0.5)
    np.testing.assert_array_equal(random_brdf.with_interpolation("nearest").eval(wi, wo), expect)
    # trilinear: the node value up to the rounding of the coordinates (index_tolerance)
    # times the neighbour differences, <= 1 in this table
    th, _, td = merl_grid()
    tol = sum(index_tolerance(th[i], td[j]))[:, None]
    assert np.all(np.abs(random_brdf.eval(wi, wo) - expect) <= tol)


def test_below_horizon_and_shapes(random_brdf, rng):
    up = np.array([0.0, 0.6, 0.8])
    down = np.array([0.0, 0.6, -0.8])
    assert random_brdf.eval(up, down).tolist() == [0.0, 0.0, 0.0]  # the BRDF contract
    assert random_brdf.eval(down, up).tolist() == [0.0, 0.0, 0.0]
    # on the horizon (z = 0 is above it), even wi = -wo with no half vector: finite, >= 0
    graze = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    f = random_brdf.eval(graze[0], graze)
    assert np.all(np.isfinite(f)) and np.all(f >= 0)
    wi = rng.normal(size=(4, 5, 3))
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    assert random_brdf.eval(wi, up).shape == (4, 5, 3)
    assert random_brdf.eval(np.empty((0, 3)), up).shape == (0, 3)


# --------------------------------------------------------------------------- invalid cells


def test_invalid_cells_take_nearest_valid_value(rng):
    # theta_d index as the value, invalid from theta_d index 60 on, plus a hole at node
    # (40, 20, 100) of the green channel only
    j = np.broadcast_to(np.arange(90.0)[None, None, :, None], MERL_SHAPE).copy()
    j[:, :, 60:] = np.nan
    j[1, 40, 20, 100] = np.nan
    brdf = MERLBRDF(j)
    assert brdf.valid_fraction == pytest.approx((3 * 90 * 60 * 180 - 1) / (3 * N), rel=1e-15)
    assert not brdf.valid[1, 40, 20, 100] and brdf.valid[0, 40, 20, 100]
    wi, wo = from_rusinkiewicz(0.2, 0.5, np.radians([75.0, 59.5, 30.0]), 1.0)
    # beyond the valid region: the last valid node (59), not 0 and not a marker; values are
    # exact small integers, or one trilinear step from them (rounding ~1e-13)
    np.testing.assert_allclose(brdf.eval(wi, wo)[:, 0], [59.0, 59.0, 30.0], rtol=0, atol=1e-12)
    # the hole is filled from a neighbour node: for this table every neighbour holds 20 or
    # (along theta_d) 19 / 21; the nearest is at distance 1, so the value is one of those
    th = (40 / 90) ** 2 * np.pi / 2
    wi, wo = from_rusinkiewicz(th, 0.0, np.radians(20.0), np.radians(100.0))
    got = brdf.with_interpolation("nearest").eval(wi, wo)
    assert got[0] == 20.0 and got[1] in (19.0, 20.0, 21.0)
    assert np.isnan(brdf.table[1, 40, 20, 100])  # the table keeps the cell marked


def test_surrogate_nodes_and_mask(merl_surrogate, rng):
    path = merl_surrogate("gold-metallic-paint")
    raw = np.fromfile(path, "<f8", offset=12).reshape(MERL_SHAPE)
    brdf = read_merl(path, interpolation="nearest")
    assert brdf.name == "gold-metallic-paint"
    invalid = raw < 0
    assert np.all(raw[invalid] == -1.0)  # the surrogate marks invalid cells with -1 only
    # -1 exactly where a node direction is at or below the horizon, in all channels
    wi, wo = node_directions()
    np.testing.assert_array_equal(invalid[0], (wi[..., 2] <= 0) | (wo[..., 2] <= 0))
    np.testing.assert_array_equal(brdf.valid, ~invalid)
    assert brdf.valid_fraction == pytest.approx(1 - invalid.mean(), rel=1e-15)
    # values at the nodes: raw * scale, bit for bit
    cells = rng.choice(np.flatnonzero(~invalid[0]), 20000, replace=False)
    i, j, k = np.unravel_index(cells, invalid.shape[1:])
    got = brdf.eval(wi.reshape(-1, 3)[cells], wo.reshape(-1, 3)[cells])
    np.testing.assert_array_equal(got, (raw[:, i, j, k] * SCALE[:, None]).T)


@pytest.mark.parametrize("name, albedo", [
    ("white-diffuse-bball", (0.342, 0.296, 0.195)),
    ("gold-metallic-paint", (0.215, 0.154, 0.056)),
])
def test_surrogate_albedo(merl_surrogate, name, albedo):
    brdf = read_merl(merl_surrogate(name))
    got = brdf.albedo([0.0, 0.0, 1.0], n_theta=128, n_phi=256)
    # reference: shared/reference/landscape.md C2, the same networks integrated off the
    # grid, 3 digits. Tabulation + interpolation of the specular peak costs 2 % for gold
    # (observed 0.211 / 0.215) and 0.5 % for the diffuse ball; a wrong channel scale
    # (15-66 %) or theta_h mapping would not pass
    np.testing.assert_allclose(got, albedo, rtol=0.03)


def test_write_marks_the_horizon_like_the_surrogate(tmp_path, merl_surrogate):
    raw = np.fromfile(merl_surrogate("gold-metallic-paint"), "<f8", offset=12)
    written = np.fromfile(write_merl(tmp_path / "smooth.binary", Smooth()), "<f8", offset=12)
    # same invalid cells: sampling puts -1 where the surrogate does (the two nodes exactly on
    # the horizon happen to round above it in both)
    np.testing.assert_array_equal(written < 0, raw < 0)


# ------------------------------------------------------------------------------- writing


def test_write_samples_brdf_at_nodes(tmp_path):
    path = write_merl(tmp_path / "smooth.binary", Smooth())
    raw = np.fromfile(path, "<f8", offset=12).reshape(MERL_SHAPE)
    wi, wo = node_directions()
    ok = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    expect = Smooth().eval(wi[ok], wo[ok]).T
    # f has |grad| <= 2 * 3; node directions agree with from_rusinkiewicz to ~1e-15; stored
    # values carry one division and one multiplication by the scale: rtol 1e-14 is ~45 ulp
    np.testing.assert_allclose(raw[:, ok] * SCALE[:, None], expect, rtol=1e-14, atol=0)
    assert np.all(raw[:, ~ok] == -1.0)


class Gray(BRDF):
    channels = 1

    def _eval(self, wi, wo):
        return np.full((wi.shape[0], 1), 0.5)


class Bad(BRDF):
    channels = 2
    _scalar = False

    def _eval(self, wi, wo):
        return np.ones((wi.shape[0], 2))


class Negative(BRDF):
    def _eval(self, wi, wo):
        return np.full((wi.shape[0], 1), -1.0)


class Anisotropic(Gray):
    isotropic = False


class WithMirror(Gray):
    delta = (MirrorDelta(0.5),)


def test_write_gray_source(tmp_path):
    back = read_merl(write_merl(tmp_path / "gray.binary", Gray()))
    # 0.5 / s * s: within 1 ulp of 0.5 (see test_round_trip_arbitrary_values_within_one_ulp)
    values = back.table[back.valid]
    np.testing.assert_array_max_ulp(values, np.full_like(values, 0.5), maxulp=1)


@pytest.mark.parametrize("source, match", [
    (Anisotropic(), "anisotropic; a MERL table holds isotropic BRDFs"),
    (WithMirror(), "delta\\) terms, which a MERL table cannot hold"),
])
def test_write_warns(tmp_path, source, match):
    with pytest.warns(UserWarning, match=match):
        write_merl(tmp_path / "w.binary", source)


@pytest.mark.parametrize("source, error, match", [
    (np.ones((3, 90, 90, 179)), ValueError, r"source must have shape \(3, 90, 90, 180\)"),
    ("table", TypeError, "source must be an array of floats"),
    (np.full(MERL_SHAPE, -1.0), ValueError, "source must be >= 0 \\(NaN marks missing"),
    (np.full(MERL_SHAPE, np.inf), ValueError, "source must be finite"),
    (np.full(MERL_SHAPE, 1e306), ValueError, "source values must be below"),
    (Bad(), ValueError, r"must return shape \(n,\), \(n, 1\) or \(n, 3\)"),
    (Negative(), ValueError, "must return finite values >= 0"),
])
def test_write_bad_source(tmp_path, source, error, match):
    with pytest.raises(error, match=match):
        write_merl(tmp_path / "x.binary", source)
    assert list(tmp_path.iterdir()) == []  # nothing written, no temporary file left


def test_write_bad_path(tmp_path):
    table = np.zeros(MERL_SHAPE)
    with pytest.raises(IsADirectoryError, match="path must be a file name, got the directory"):
        write_merl(tmp_path, table)
    with pytest.raises(FileNotFoundError, match="does not exist; create it first"):
        write_merl(tmp_path / "no" / "x.binary", table)
    with pytest.raises(TypeError, match="path must be a str or os.PathLike, got int"):
        write_merl(3, table)


def test_write_failure_keeps_old_file(tmp_path, monkeypatch):
    target = tmp_path / "m.binary"
    target.write_bytes(b"old")

    def disk_full(fd):
        raise OSError("No space left on device (simulated)")

    monkeypatch.setattr(os, "fsync", disk_full)  # fails after the data went to the temp file
    with pytest.raises(OSError, match="simulated"):
        write_merl(target, np.zeros(MERL_SHAPE))
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["m.binary"]


def test_write_failure_in_source(tmp_path):
    class Failing(Gray):
        calls = 0

        def _eval(self, wi, wo):
            Failing.calls += 1
            if Failing.calls == 3:
                raise RuntimeError("model broke halfway")
            return super()._eval(wi, wo)

    with pytest.raises(RuntimeError, match="model broke halfway"):
        write_merl(tmp_path / "m.binary", Failing())
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------- damaged files


@pytest.fixture(scope="module")
def good_raw() -> np.ndarray:
    return np.ones((3, N))


def _nan_at(raw: np.ndarray, value: float) -> np.ndarray:
    raw = raw.copy().reshape(MERL_SHAPE)
    raw[1, 2, 3, 4] = value
    return raw


@pytest.mark.parametrize("make, match", [
    (lambda r: merl_bytes(r)[:-8], "34992004 bytes, shorter than the 34992012 its header"),
    (lambda r: merl_bytes(r) + bytes(8), "34992020 bytes, longer than the 34992012"),
    (lambda r: b"", "0 bytes, fewer than the 12-byte header"),
    (lambda r: merl_bytes(r)[:5], "5 bytes, fewer than the 12-byte header"),
    (lambda r: merl_bytes(r, (90, 90, 360)),
     r"dimensions \(90, 90, 180\), got \(90, 90, 360\).*not a MERL"),
    (lambda r: merl_bytes(r, (180, 90, 90)), r"got \(180, 90, 90\).*in another order"),
    (lambda r: merl_bytes(r, header=">i4"), "the file is big-endian"),
    (lambda r: merl_bytes(_nan_at(r, np.nan)),
     "1 are NaN or inf, first at channel 1, theta_h index 2, theta_d index 3, phi_d index 4"),
    (lambda r: merl_bytes(_nan_at(r, -np.inf)), "must hold finite values: 1 are NaN or inf"),
], ids=["truncated", "extra", "empty", "short-header", "wrong-dims", "reordered", "big-endian",
        "nan", "inf"])
def test_damaged_file(tmp_path, good_raw, make, match):
    path = tmp_path / "damaged.binary"
    path.write_bytes(make(good_raw))
    with pytest.raises(ValueError, match=match):
        read_merl(path)


def _channel_missing(raw: np.ndarray) -> np.ndarray:
    raw = raw.copy().reshape(MERL_SHAPE)
    raw[1] = -1.0  # every cell of the green channel marked missing
    return raw


def test_file_with_an_empty_channel(tmp_path, good_raw, capsys):
    # the API and the command line name the file and the channel (the table check alone
    # said "channel 1 has none")
    from compress.cli import main

    path = tmp_path / "green-gone.binary"
    path.write_bytes(merl_bytes(_channel_missing(good_raw)))
    match = (r"MERL file '.*green-gone\.binary' holds no valid value in channel 1 \(green\): "
             r"all 1458000 are negative \(the mark of a missing cell\)")
    with pytest.raises(ValueError, match=match):
        read_merl(path)
    assert main(["project", "--merl", str(path), "--basis", "zernike", "--order", "2",
                 "-o", str(tmp_path / "out.h5")]) != 0
    assert re.search(match, capsys.readouterr().err)


def test_bad_paths(tmp_path):
    with pytest.raises(FileNotFoundError, match="MERL file .*missing.binary' does not exist"):
        read_merl(tmp_path / "missing.binary")
    with pytest.raises(IsADirectoryError, match="must be a MERL .binary file, got the directory"):
        read_merl(tmp_path)
    with pytest.raises(TypeError, match="path must be a str or os.PathLike, got NoneType"):
        read_merl(None)


def test_fifo_refused(on_fifo):
    # opening a FIFO blocks until a writer appears: refused before it is opened
    with pytest.raises(ValueError, match=r"MERL file '.*pipe.binary' must be a regular file, "
                                         r"got a FIFO \(named pipe\)"):
        on_fifo(read_merl, "pipe.binary")


@pytest.mark.parametrize("table, kwargs, match", [
    (np.zeros((3, 90, 90)), {}, r"table must have shape \(3, 90, 90, 180\)"),
    (np.full(MERL_SHAPE, -0.5), {}, "table must be >= 0 .* min -0.5"),
    (np.zeros(MERL_SHAPE), {"interpolation": "cubic"},
     "interpolation must be one of 'trilinear', 'nearest', got 'cubic'"),
])
def test_bad_table(table, kwargs, match):
    with pytest.raises(ValueError, match=match):
        MERLBRDF(table, **kwargs)


def test_channel_without_valid_values():
    t = np.zeros(MERL_SHAPE)
    t[2] = np.nan
    with pytest.raises(ValueError, match="at least one valid .* channel 2 has none"):
        MERLBRDF(t)


def test_read_bad_interpolation(tmp_path):
    with pytest.raises(ValueError, match="interpolation must be one of"):
        read_merl(tmp_path / "x.binary", interpolation="linear")


@pytest.mark.parametrize("interpolation", ["trilinear", "nearest"])
def test_isotropic_sums_are_eval_bit_for_bit(random_brdf, rng, interpolation):
    # Reference: eval at the directions of the isotropic product rule, summed over the
    # azimuths in the same order by project.quadrature's kernel. The fused kernel must give
    # the same bits (same normalisation, angles and interpolation; same summation order).
    from project.quadrature import _azimuth_raw, _azimuth_sums, _iso_directions

    brdf = random_brdf.with_interpolation(interpolation)
    zi, zo = rng.uniform(0.0, 1.0, 57), rng.uniform(0.0, 1.0, 57)
    zi[:3], zo[:3] = [1.0, 0.3, 0.0], [1.0, 0.3, 0.5]  # the pole, w_i = w_o, the horizon
    sti, sto = np.sqrt((1.0 - zi) * (1.0 + zi)), np.sqrt((1.0 - zo) * (1.0 + zo))
    dphi, raw = _azimuth_raw(40, 6)
    cd, sd = np.cos(dphi), np.sin(dphi)
    cosr = raw[:, None] * np.cos(np.outer(dphi, np.arange(9)))
    scale = zi * zo
    sums, sq = np.empty((57, 3, 9)), np.empty((57, 3))
    assert brdf._isotropic_sums(sti, zi, sto, zo, cd, sd, scale, cosr, raw, sums, sq)
    wi, wo = _iso_directions(sti, zi, sto, zo, cd, sd)
    q = brdf.eval(wi, wo).reshape(57, dphi.size, 3)
    ref_sums, ref_sq = np.empty_like(sums), np.empty_like(sq)
    _azimuth_sums(q, scale, cosr, raw, ref_sums, ref_sq)
    np.testing.assert_array_equal(sums, ref_sums)
    np.testing.assert_array_equal(sq, ref_sq)


def test_isotropic_sums_defer_to_a_subclass_eval(random_brdf):
    class Scaled(MERLBRDF):
        def _eval(self, wi, wo):
            return 2.0 * super()._eval(wi, wo)

    brdf = Scaled(random_brdf.table)
    z = np.array([0.5])
    out = np.zeros((1, 3, 2))
    # the fused kernel would skip the override: it must decline, and write nothing
    assert not brdf._isotropic_sums(z, z, z, z, z, z, z, np.ones((1, 2)), z, out, out[:, :, 0])
    assert not out.any()
