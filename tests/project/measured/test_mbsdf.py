"""NVIDIA MDL measured BSDF files (``.mbsdf``): layout, lookup, conventions, damaged files.

References are independent of ``project.measured.mbsdf``:

- files are assembled byte by byte here (``mbsdf_bytes``) from the layout of the MDL SDK's
  loader (``import_measurement_from_reader`` and ``export_to_file`` in
  ``src/io/scene/bsdf_measurement/bsdf_measurement.cpp``, github.com/NVIDIA/MDL-SDK);
- ``sdk_lookup`` re-derives the CUDA texture lookup of ``df_bsdf_measurement_evaluate``
  (``examples/mdl_sdk/shared/texture_support_cuda.h``: normalised coordinates
  (delta_phi / pi, 2 theta_out / pi, 2 theta_in / pi), linear filtering, clamp addressing)
  with scipy's ``RegularGridInterpolator`` on the texel centres, padded with the edge values
  at 0 and 1 (what clamp-to-edge filtering gives between the outer centre and the end);
- the MDL example material ``example_modules.mbsdf`` (CC0, from the SDK's examples), read
  with ``np.fromfile`` at the SDK's byte offsets, when ``../shared/data/mbsdf`` is present;
- analytic models of ``project.models`` for write-then-read round trips.
"""

from __future__ import annotations

import os
import struct
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from project.measured import MBSDFBRDF, read_mbsdf, texel_centres, write_mbsdf
from project.models import CookTorrance, Lambert

ROOT = Path(__file__).resolve().parents[3]
EXAMPLE = ROOT.parent / "shared" / "data" / "mbsdf" / "example_modules.mbsdf"
MAGIC = b"NVIDIA ARC MBSDF V1\n"


def example_file() -> Path:
    """The MDL SDK's example material (skip when ../shared is absent)."""
    if not EXAMPLE.is_file():
        pytest.skip(f"{EXAMPLE} not present (the example lives in ../shared/data/mbsdf)")
    return EXAMPLE


def mbsdf_bytes(reflection: np.ndarray | None = None, transmission: np.ndarray | None = None,
                *, metadata: tuple[bytes, ...] = (), marker: bytes = b"MBSDF_DATA_REFLECTION=\n"
                ) -> bytes:
    """A file assembled by hand: tables (n, n, m, c) written as the SDK's export_to_file."""
    def part(t: np.ndarray) -> bytes:
        n, _, m, c = t.shape
        return struct.pack("<3I", 1 if c == 3 else 0, n, m) + t.astype("<f4").tobytes()
    out = MAGIC + b"".join(line + b"\n" for line in metadata)
    if reflection is not None:
        out += marker + part(reflection)
    if transmission is not None:
        out += b"MBSDF_DATA_TRANSMISSION=\n" + part(transmission)
    return out


def sdk_lookup(table: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """(n, c) CUDA texture lookup (texel centres, linear, clamp) of (n_in, n_out, n_phi, c)."""
    n_theta, _, n_phi, c = table.shape
    def axis(n: int) -> np.ndarray:  # texel centres in normalised coordinates, plus the ends
        return np.concatenate([[0.0], (np.arange(n) + 0.5) / n, [1.0]])
    padded = np.pad(table, ((1, 1), (1, 1), (1, 1), (0, 0)), mode="edge")
    interp = RegularGridInterpolator((axis(n_theta), axis(n_theta), axis(n_phi)), padded)
    theta_in = np.arccos(np.clip(wi[:, 2], -1, 1))
    theta_out = np.arccos(np.clip(wo[:, 2], -1, 1))
    dphi = np.abs(np.arctan2(wo[:, 1], wo[:, 0]) - np.arctan2(wi[:, 1], wi[:, 0]))
    dphi = np.where(dphi > np.pi, 2 * np.pi - dphi, dphi)   # bsdf_compute_uvw's fold
    uvw = np.stack([2 * theta_in / np.pi, 2 * theta_out / np.pi, dphi / np.pi], axis=-1)
    return interp(np.clip(uvw, 0.0, 1.0)).reshape(-1, c)


def upper(rng: np.random.Generator, n: int) -> np.ndarray:
    """n uniform directions of the upper hemisphere."""
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def centre_pairs(n_theta: int, n_phi: int, phi_in: float = 0.0) -> tuple[np.ndarray, ...]:
    """Directions at every texel centre: (wi, wo), shape (n_theta, n_theta, n_phi, 3)."""
    theta, dphi = texel_centres((n_theta, n_phi))
    ti, to, dp = np.meshgrid(theta, theta, dphi, indexing="ij")
    wi = np.stack([np.sin(ti) * np.cos(phi_in), np.sin(ti) * np.sin(phi_in), np.cos(ti)], -1)
    po = phi_in + dp
    wo = np.stack([np.sin(to) * np.cos(po), np.sin(to) * np.sin(po), np.cos(to)], -1)
    return wi, wo


# ---- the example material --------------------------------------------------------------

def test_example_layout_and_texel_centres():
    path = example_file()
    brdf = read_mbsdf(path)
    # SDK layout: magic (20 bytes), marker (23), type/n_theta/n_phi (12), then float32
    raw = np.fromfile(path, dtype="<f4", offset=55).reshape(45, 45, 90, 3)
    assert struct.unpack("<3I", path.read_bytes()[43:55]) == (1, 45, 90)
    assert brdf.channels == 3 and brdf.resolution == (45, 90) and brdf.transmission is None
    assert brdf.isotropic and not brdf.reciprocal
    assert np.array_equal(brdf.table, raw.astype(np.float64))   # float32 -> float64 is exact
    assert brdf.path == path and brdf.name == "example_modules"
    assert brdf.negative_count == int((raw < 0).sum()) > 0
    assert brdf.info["negative_count"] == brdf.negative_count
    wi, wo = centre_pairs(45, 90, phi_in=0.7)
    got = brdf.eval(wi, wo)
    # at a centre the filter weight of the neighbour is ~1e-14 (angles from vectors), so
    # the value is the stored one to a few ulps of the largest neighbour difference
    np.testing.assert_allclose(got, np.maximum(raw, 0.0), rtol=1e-12, atol=1e-12)


def test_example_between_centres_matches_sdk_lookup():
    brdf = read_mbsdf(example_file())
    rng = np.random.default_rng(20261205)
    wi, wo = upper(rng, 4000), upper(rng, 4000)
    # grazing and normal edges, where clamping and the fold of delta_phi matter
    wi[:50, :] = [0.0, 0.0, 1.0]
    wo[50:100, 2] = 0.0
    wo[50:100] /= np.linalg.norm(wo[50:100], axis=1, keepdims=True)
    ref = np.maximum(sdk_lookup(brdf.table, wi, wo), 0.0)
    # both interpolate float64 values with float64 weights: agreement to rounding (values
    # are <= ~10, so 1e-12 absolute is ~1000 ulps)
    np.testing.assert_allclose(brdf.eval(wi, wo), ref, rtol=0, atol=1e-12)


def test_example_read_time():
    path = example_file()
    read_mbsdf(path)
    t0 = time.perf_counter()
    read_mbsdf(path)
    elapsed = time.perf_counter() - t0
    assert elapsed < 1.0, f"reading the 2.2 MB example took {elapsed:.3f} s"


# ---- conventions --------------------------------------------------------------------

def test_theta_in_is_the_light_direction():
    # f depends on theta_in only: cell i_in holds i_in + 1
    n = 6
    table = np.broadcast_to((np.arange(n) + 1.0)[:, None, None, None], (n, n, 4, 1)).copy()
    brdf = MBSDFBRDF(table)
    theta, _ = texel_centres((n, 4))
    wi = np.array([np.sin(theta[2]), 0.0, np.cos(theta[2])])    # light at cell 2
    wo = np.array([0.0, np.sin(theta[5]), np.cos(theta[5])])    # viewer at cell 5
    assert brdf.eval(wi, wo)[0] == pytest.approx(3.0, abs=1e-12)
    assert brdf.eval(wo, wi)[0] == pytest.approx(6.0, abs=1e-12)


def test_swap_transposes_and_symmetrize_averages():
    rng = np.random.default_rng(3)
    table = rng.uniform(0.0, 1.0, (5, 5, 7, 3))
    wi, wo = upper(rng, 300), upper(rng, 300)
    raw = MBSDFBRDF(table)
    transposed = MBSDFBRDF(table.transpose(1, 0, 2, 3))
    np.testing.assert_allclose(raw.eval(wo, wi), transposed.eval(wi, wo), rtol=0, atol=1e-14)
    sym = MBSDFBRDF(table, symmetrize=True)
    assert sym.reciprocal and not raw.reciprocal
    np.testing.assert_allclose(sym.eval(wi, wo), sym.eval(wo, wi), rtol=0, atol=1e-14)
    np.testing.assert_allclose(sym.eval(wi, wo), 0.5 * (raw.eval(wi, wo) + raw.eval(wo, wi)),
                               rtol=0, atol=1e-14)   # interpolation is linear in the table


def test_isotropic_and_fold_of_delta_phi():
    rng = np.random.default_rng(4)
    brdf = MBSDFBRDF(rng.uniform(0.0, 1.0, (4, 4, 9, 1)))
    wi, wo = upper(rng, 200), upper(rng, 200)
    a = rng.uniform(0, 2 * np.pi)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    mirror = np.array([1.0, -1.0, 1.0])   # delta_phi -> -delta_phi
    base = brdf.eval(wi, wo)
    np.testing.assert_allclose(brdf.eval(wi @ rot.T, wo @ rot.T), base, rtol=0, atol=1e-13)
    np.testing.assert_allclose(brdf.eval(wi * mirror, wo * mirror), base, rtol=0, atol=1e-13)


def test_negative_values_clamped_and_counted():
    table = np.full((2, 2, 2, 1), -0.01)
    table[0, 0, 0, 0] = 1.0
    brdf = MBSDFBRDF(table)
    assert brdf.negative_count == 7 and brdf.info["min_value"] == -0.01
    rng = np.random.default_rng(5)
    assert (brdf.eval(upper(rng, 500), upper(rng, 500)) >= 0.0).all()
    theta, _ = texel_centres((2, 2))
    w = np.array([np.sin(theta[1]), 0.0, np.cos(theta[1])])
    assert brdf.eval(w, w)[0] == 0.0


def test_below_horizon_is_zero():
    brdf = MBSDFBRDF(np.ones((3, 3, 3, 1)))
    assert brdf.eval([0.0, 0.0, 1.0], [0.6, 0.0, -0.8])[0] == 0.0


# ---- writing --------------------------------------------------------------------------

@pytest.mark.parametrize("resolution", [(45, 90), (7, 3), (1, 1)])
def test_write_read_cook_torrance(tmp_path, resolution):
    rep = CookTorrance(kd=[0.2, 0.3, 0.4], roughness=0.3)
    path = write_mbsdf(rep, tmp_path / "ct.mbsdf", resolution=resolution)
    n_theta, n_phi = resolution
    assert path.stat().st_size == 20 + 23 + 12 + 4 * 3 * n_theta**2 * n_phi
    back = read_mbsdf(path)
    assert back.resolution == resolution and back.channels == 3
    wi, wo = centre_pairs(n_theta, n_phi, phi_in=-1.1)
    want = rep.eval(wi, wo)
    # stored as float32: half an ulp of float32 (2**-24 relative), plus the ~1e-14 weight of
    # a neighbour cell at a centre computed from vectors
    np.testing.assert_allclose(back.eval(wi, wo), want, rtol=2.0**-24 + 1e-12, atol=1e-12)


def test_write_coefficient_matrix(tmp_path):
    # any representation: a one-channel coefficient matrix (eval returns shape (n,))
    from basis import HemiZernike
    from project import project

    cm = project(Lambert(0.4), HemiZernike(2))
    back = read_mbsdf(write_mbsdf(cm, tmp_path / "cm.mbsdf", resolution=(5, 6)))
    assert back.channels == 1
    wi, wo = centre_pairs(5, 6, phi_in=0.3)
    np.testing.assert_allclose(back.eval(wi, wo)[..., 0], cm.eval(wi, wo),
                               rtol=2.0**-24 + 1e-12, atol=1e-12)


def test_write_scalar_and_bytes(tmp_path):
    path = write_mbsdf(Lambert(0.5), tmp_path / "l.mbsdf", resolution=(2, 3))
    data = path.read_bytes()
    assert data[:43] == MAGIC + b"MBSDF_DATA_REFLECTION=\n"
    assert struct.unpack("<3I", data[43:55]) == (0, 2, 3)
    assert np.array_equal(np.frombuffer(data[55:], "<f4"), np.full(12, np.float32(0.5 / np.pi)))


def test_write_is_atomic_and_checks(tmp_path):
    target = tmp_path / "x.mbsdf"
    target.write_bytes(b"old")

    class Bad:
        channels = 1

        def eval(self, wi, wo):
            return np.full(np.broadcast_shapes(wi.shape, wo.shape)[:-1], np.nan)

    with pytest.raises(ValueError, match="finite"):
        write_mbsdf(Bad(), target, resolution=(2, 2))
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == ["x.mbsdf"]
    with pytest.raises(TypeError, match="eval"):
        write_mbsdf(object(), target)
    with pytest.raises(ValueError, match="resolution must be two integers in"):
        write_mbsdf(Lambert(0.5), target, resolution=(0, 4))
    with pytest.raises(TypeError, match="resolution must be two integers"):
        write_mbsdf(Lambert(0.5), target, resolution=(2.0, 4))


def test_transmission_kept(tmp_path):
    r = np.full((2, 2, 3, 1), 0.25)
    t = np.full((3, 3, 2, 3), 0.5)
    path = tmp_path / "rt.mbsdf"
    path.write_bytes(mbsdf_bytes(r, t, metadata=(b"some metadata",), marker=b"MBSDF_DATA=\n"))
    brdf = read_mbsdf(path)
    assert brdf.metadata == ("some metadata",)
    assert brdf.transmission.shape == (3, 3, 2, 3) and brdf.info["transmission"] == (3, 2)
    assert brdf.eval([0, 0, 1.0], [0, 0, 1.0])[0] == 0.25


# ---- damaged files --------------------------------------------------------------------

def _raises_fast(path: Path, match: str) -> None:
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=match) as err:
        read_mbsdf(path)
    assert str(path) in str(err.value)
    assert time.perf_counter() - t0 < 1.0


@pytest.mark.parametrize("data, match", [
    (b"", "must start with the line"),
    (b"NVIDIA ARC MBSDF V2\nMBSDF_DATA=\n", "must start with the line"),
    (MAGIC, "no data marker line"),
    (MAGIC + b"meta\n", "no data marker line"),
    (MAGIC + b"MBSDF_DATA=\n" + struct.pack("<I", 1), "ends inside the header"),
    (MAGIC + b"MBSDF_DATA=\n" + struct.pack("<3I", 2, 1, 1) + bytes(4), "must be 0"),
    (MAGIC + b"MBSDF_DATA=\n" + struct.pack("<3I", 0, 0, 5), r"must be >= 1"),
    (MAGIC + b"MBSDF_DATA=\n" + struct.pack("<3I", 0, 3, 0), r"must be >= 1"),
    # 2**31 texels promised, 4 bytes present
    (MAGIC + b"MBSDF_DATA=\n" + struct.pack("<3I", 0, 2**15, 2) + bytes(4), "needs"),
    (MAGIC + b"MBSDF_DATA=\n" + struct.pack("<3I", 1, 2**32 - 1, 2**32 - 1) + bytes(4), "needs"),
    (mbsdf_bytes(transmission=np.ones((1, 1, 1, 1))), "only a transmission part"),
    (mbsdf_bytes(np.ones((1, 1, 1, 1))) + b"junk", "must end after its reflection part"),
    (mbsdf_bytes(np.ones((1, 1, 1, 1)), np.ones((1, 1, 1, 1))) + b"x", "bytes after"),
])
def test_damaged(tmp_path, data, match):
    path = tmp_path / "bad.mbsdf"
    path.write_bytes(data)
    _raises_fast(path, match)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_not_finite(tmp_path, value):
    table = np.ones((2, 2, 3, 3))
    table[1, 0, 2, 1] = value
    path = tmp_path / "nan.mbsdf"
    path.write_bytes(mbsdf_bytes(table))
    _raises_fast(path, r"finite values, 1 are NaN or inf \(first at theta_in 1, theta_out 0, "
                       r"delta_phi 2, channel 1\)")


def test_truncated_everywhere(tmp_path):
    data = mbsdf_bytes(np.ones((3, 3, 4, 3)), np.ones((2, 2, 2, 1)))
    path = tmp_path / "cut.mbsdf"
    whole = len(mbsdf_bytes(np.ones((3, 3, 4, 3))))   # a complete reflection-only file
    for n in range(len(data)):
        if n == whole:
            continue
        path.write_bytes(data[:n])
        _raises_fast(path, "MBSDF file")


def test_fuzz_flipped_header_bytes(tmp_path):
    # every byte before the values flipped by a random non-zero mask, 4 rounds: each file is
    # rejected with a ValueError (a one-byte change cannot make another valid header), fast
    rng = np.random.default_rng(2026)
    data = bytearray(mbsdf_bytes(np.full((3, 3, 4, 3), 0.1), metadata=(b"m",)))
    path = tmp_path / "flip.mbsdf"
    for _ in range(4):
        for pos in range(len(MAGIC) + 2 + 23 + 12):
            bad = bytearray(data)
            bad[pos] ^= int(rng.integers(1, 256))
            path.write_bytes(bytes(bad))
            if pos == len(MAGIC):   # the metadata text "m": any other byte is metadata too
                assert read_mbsdf(path).resolution == (3, 4)
                continue
            _raises_fast(path, "MBSDF file")


def test_fuzz_example_header(tmp_path):
    data = bytearray(example_file().read_bytes())
    path = tmp_path / "flip.mbsdf"
    rng = np.random.default_rng(7)
    for pos in range(55):
        bad = bytearray(data)
        bad[pos] ^= int(rng.integers(1, 256))
        path.write_bytes(bytes(bad))
        _raises_fast(path, "MBSDF file")


def test_not_regular_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_mbsdf(tmp_path / "missing.mbsdf")
    with pytest.raises(IsADirectoryError, match="directory"):
        read_mbsdf(tmp_path)
    fifo = tmp_path / "pipe.mbsdf"
    os.mkfifo(fifo)
    _raises_fast(fifo, "regular file")


def test_table_checks():
    with pytest.raises(ValueError, match="shape"):
        MBSDFBRDF(np.ones((2, 3, 4, 1)))
    with pytest.raises(ValueError, match="finite"):
        MBSDFBRDF(np.full((1, 1, 1, 3), np.nan))


def test_example_symmetrized_as_the_sdk_renderers():
    # prepare_mbsdfs_part (examples/mdl_sdk/shared/example_cuda_shared.h) averages the table
    # with its transpose in (theta_in, theta_out) before building the texture
    path = example_file()
    raw = np.fromfile(path, dtype="<f4", offset=55).reshape(45, 45, 90, 3).astype(np.float64)
    sym = read_mbsdf(path, symmetrize=True)
    assert sym.reciprocal and sym.info["symmetrized"]
    assert np.array_equal(sym.table, raw)   # the stored values are kept as read
    wi, wo = centre_pairs(45, 90, phi_in=2.0)
    want = np.maximum(0.5 * (raw + raw.transpose(1, 0, 2, 3)), 0.0)
    np.testing.assert_allclose(sym.eval(wi, wo), want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sym.eval(wo, wi), want, rtol=1e-12, atol=1e-12)
