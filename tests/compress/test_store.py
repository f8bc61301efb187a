"""compress.save / compress.load: bit-exact round trips, precision, clear refusals."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

import basis
from basis import CoefficientMatrix
from compress import load, save
from compress.store import FORMAT, SCHEMA_VERSION


def _iso(b: basis.Basis, rng: np.random.Generator, channels: int | None = 3,
         quantity: str = "f_cos") -> CoefficientMatrix:
    cos_idx = b.azimuthal_blocks().cos
    blocks = []
    for idx in cos_idx:
        shape = (idx.size, idx.size) if channels is None else (channels, idx.size, idx.size)
        x = rng.normal(size=shape)
        blocks.append(x + np.swapaxes(x, -1, -2))
    return CoefficientMatrix.from_blocks(b, blocks, quantity)


INFO = {"source": "Phong(kd=0.3)", "method": "quadrature", "nodes": (64, 130),
        "error_estimate": 1.25e-15, "converged": True, "truncation_error": None,
        "standard_error": np.arange(6.0).reshape(2, 3) / 7, "count": np.int64(7),
        "nested": {"list": [1, 2.5, "x"], "nan": float("nan")}}


@pytest.mark.parametrize("b, channels", [
    (basis.HemiZernike(6), 3), (basis.HemiHarmonics(5), None),
    (basis.HemiHarmonics(4, parity="even"), 1), (basis.SphericalHarmonics(3), 3)])
def test_round_trip_isotropic_bit_exact(tmp_path, rng, b, channels):
    cm = _iso(b, rng, channels)
    cm.info.update(INFO)
    back = load(save(cm, tmp_path / "c.h5"))
    assert back.basis == b and back.quantity == cm.quantity and back.is_isotropic
    assert back.matrix.shape == cm.matrix.shape
    for x, y in zip(back.blocks, cm.blocks, strict=True):
        assert np.array_equal(x, y)  # bit exact: float64 written, symmetric blocks
    assert back.info.keys() == cm.info.keys()
    assert back.info["nodes"] == (64, 130) and isinstance(back.info["nodes"], tuple)
    assert np.array_equal(back.info["standard_error"], INFO["standard_error"])
    assert back.info["standard_error"].dtype == np.float64
    assert back.info["count"] == 7 and back.info["truncation_error"] is None
    assert back.info["nested"]["list"] == [1, 2.5, "x"]
    assert np.isnan(back.info["nested"]["nan"])


def test_round_trip_dense(tmp_path, rng):
    b = basis.HemiZernike(3)
    x = rng.normal(size=(2, b.size, b.size))
    cm = CoefficientMatrix(b, x + x.swapaxes(1, 2), "f", isotropic=False)
    back = load(save(cm, tmp_path / "d.h5"))
    assert not back.is_isotropic and back.quantity == "f"
    assert np.array_equal(back.matrix, cm.matrix)


def test_schema_layout(tmp_path, rng):
    cm = _iso(basis.HemiZernike(4), rng, 3)
    cm.info.update(source="test", seconds=0.5)
    save(cm, tmp_path / "s.h5")
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert f.attrs["format"] == FORMAT and f.attrs["schema_version"] == SCHEMA_VERSION
        assert f.attrs["basis_kind"] == "zernike" and f.attrs["basis_order"] == 4
        assert f.attrs["storage"] == "isotropic" and f.attrs["channels"] == 3
        # blocks, not dense; upper triangles only: k_m = 3, 2, 2, 1, 1
        assert list(f["blocks"].attrs["sizes"]) == [3, 2, 2, 1, 1]
        assert f["blocks/m0"].shape == (3, 6) and f["blocks/m4"].shape == (3, 1)
        assert "matrix" not in f
        assert f["provenance"].attrs["source"] == "test"
        assert json.loads(f.attrs["info"])["seconds"] == 0.5


@pytest.mark.parametrize("dtype, rel", [("float32", 2.0**-24), ("float16", 2.0**-11)])
def test_reduced_precision(tmp_path, rng, dtype, rel):
    cm = _iso(basis.HemiZernike(4), rng, 3)
    back = load(save(cm, tmp_path / "p.h5", dtype=dtype))
    # round to nearest: relative error of each entry <= unit roundoff of the dtype
    # (float16 normal range: every entry here is > 6e-5 in magnitude or exactly 0)
    a, b = back.matrix, cm.matrix
    assert np.all(np.abs(a - b) <= rel * np.abs(b) + 1e-7 * (dtype == "float16"))
    assert not np.array_equal(a, b)


def test_atomic_write_leaves_no_partial_file(tmp_path, rng, monkeypatch):
    cm = _iso(basis.HemiZernike(2), rng, 1)
    target = tmp_path / "a.h5"
    save(cm, target)
    before = target.read_bytes()

    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(h5py.Group, "create_group", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        save(_iso(basis.HemiZernike(2), rng, 1), target)
    assert target.read_bytes() == before  # the old file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5"]  # no temporary left


def test_truncated_file(tmp_path, rng):
    path = save(_iso(basis.HemiZernike(6), rng, 3), tmp_path / "t.h5")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="damaged or truncated HDF5 file"):
        load(path)


def test_not_hdf5(tmp_path):
    p = tmp_path / "x.h5"
    p.write_bytes(b"hello world, not hdf5")
    with pytest.raises(ValueError, match="is not an HDF5 file"):
        load(p)


def test_foreign_hdf5(tmp_path):
    p = tmp_path / "foreign.h5"
    with h5py.File(p, "w") as f:
        f["data"] = np.arange(3)
    with pytest.raises(ValueError, match="not a scatmodes coefficient file"):
        load(p)


@pytest.mark.parametrize("version", [3, 0])
def test_unknown_version(tmp_path, rng, version):
    p = save(_iso(basis.HemiZernike(2), rng, 1), tmp_path / "v.h5")
    with h5py.File(p, "r+") as f:
        f.attrs["schema_version"] = version
    with pytest.raises(ValueError, match=rf"schema version {version}; .* reads schema "
                                         r"versions 1, 2"):
        load(p)


@pytest.mark.parametrize("b", [basis.HemiHarmonics(4), basis.HemiHarmonics(3, parity="even"),
                               basis.HemiZernike(3), basis.SphericalHarmonics(2)])
def test_schema_1_files_still_load(tmp_path, rng, b):
    # schema 1 named the hemisphere harmonics "hemi_sh" with a separate basis_parity; rewrite
    # a fresh file into that form, as scatmodes 0.1.0 wrote it
    cm = _iso(b, rng, 3)
    p = save(cm, tmp_path / "old.h5")
    with h5py.File(p, "r+") as f:
        f.attrs["schema_version"] = 1
        f.attrs["basis_parity"] = getattr(b, "parity", "all")
        if isinstance(b, basis.HemiHarmonics):
            f.attrs["basis_kind"] = "hemi_sh"
    back = load(p)
    assert back.basis == b
    assert np.array_equal(back.matrix, cm.matrix)
    with h5py.File(p, "r+") as f:
        f.attrs["basis_parity"] = "sideways"
    if isinstance(b, basis.HemiHarmonics):
        with pytest.raises(ValueError, match="basis_parity 'sideways' .* neither 'odd'"):
            load(p)


def test_unknown_basis_kind(tmp_path, rng):
    p = save(_iso(basis.HemiZernike(2), rng, 1), tmp_path / "k.h5")
    with h5py.File(p, "r+") as f:
        f.attrs["basis_kind"] = "wavelets"
    with pytest.raises(ValueError, match="unknown basis kind 'wavelets' .* 'harmonics-even'"):
        load(p)


def test_damaged_content(tmp_path, rng):
    p = save(_iso(basis.HemiZernike(3), rng, 1), tmp_path / "m.h5")
    with h5py.File(p, "r+") as f:
        del f["blocks/m2"]
    with pytest.raises(ValueError, match="is damaged"):
        load(p)


def test_missing_file_and_bad_args(tmp_path, rng):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load(tmp_path / "none.h5")
    with pytest.raises(TypeError, match="cm must be a basis.CoefficientMatrix"):
        save(np.eye(2), tmp_path / "x.h5")
    cm = _iso(basis.HemiZernike(2), rng, 1)
    with pytest.raises(ValueError, match="dtype must be one of"):
        save(cm, tmp_path / "x.h5", dtype="int8")
    big = CoefficientMatrix(basis.HemiZernike(0), [[1e6]])
    with pytest.raises(ValueError, match="cannot hold coefficients up to 1e"):
        save(big, tmp_path / "x.h5", dtype="float16")
    cm.info["bad"] = object()
    with pytest.raises(TypeError, match="info values must be"):
        save(cm, tmp_path / "x.h5")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        save(_iso(basis.HemiZernike(2), rng, 1), tmp_path / "nodir" / "x.h5")
