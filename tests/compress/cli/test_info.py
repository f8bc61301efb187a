"""``scatmodes info FILE``: descriptions of saved matrices, models, hybrids and simulation
checkpoints (text and JSON), and one-line errors for missing, foreign and damaged files."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys

import h5py
import numpy as np
import pytest

import basis
from basis import CoefficientMatrix
from compress import Hybrid, save
from compress.cli import main
from compress.store import file_kind, load
from project import FittedModel


def run(capsys, *argv):
    """main(argv) -> (status, stdout, stderr)."""
    try:
        status = main(list(argv))
    except SystemExit as stop:
        status = stop.code
    out, err = capsys.readouterr()
    return status, out, err


def described(capsys, path):
    """The --json description of ``path`` (asserts success)."""
    status, out, err = run(capsys, "info", str(path), "--json")
    assert status == 0, err
    return json.loads(out)


def one_line_error(capsys, *argv):
    status, out, err = run(capsys, *argv)
    assert status == 2, err
    assert out == "" and "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("scatmodes info: error: "), lines[0]
    return lines[0]


def rows(out):
    """``key  value`` lines of the text form as a dict (indentation and padding dropped)."""
    out_rows = {}
    for line in out.splitlines()[1:]:
        key, _, value = line.strip().partition("  ")
        out_rows.setdefault(key, value.strip())
    return out_rows


def _matrix(rng, order=3, channels=3, quantity="f_cos"):
    b = basis.HemiZernike(order)
    blocks = []
    for idx in b.azimuthal_blocks().cos:
        x = rng.normal(size=(channels, idx.size, idx.size))
        blocks.append(x + x.swapaxes(1, 2))
    return CoefficientMatrix.from_blocks(b, blocks, quantity,
                                         info={"source": "Phong(kd=0.3)", "truncation_error":
                                               0.0125, "stderr": np.arange(3.0),
                                               "bad": float("nan")})


def _ggx():
    return FittedModel("lambert+ggx", {"kd": [0.5, 0.4, 0.3], "ks": [1, 1, 1], "alpha": 0.2,
                                       "f0": 1.0}, info={"l2": 0.031, "converged": True})


def test_matrix_text_and_json(tmp_path, rng, capsys):
    path = save(_matrix(rng), tmp_path / "phong.h5")
    status, out, err = run(capsys, "info", str(path))
    assert status == 0, err
    with h5py.File(path, "r") as f:
        library = f.attrs["library"].decode()
    assert out.splitlines()[0] == (f"{path}: scatmodes coefficients (schema 6, written by "
                                   f"{library}), {os.path.getsize(path):,} bytes on disk, "
                                   "192 bytes of float64 numbers")
    r = rows(out)
    assert r["basis"] == "HemiZernike(3) (kind zernike, order 3, 10 functions)"
    assert r["quantity"] == "f_cos" and r["channels"] == "3" and r["isotropic"] == "yes"
    # 3 channels x (2 x 2 + 2 x 2 + 1 + 1) block entries held in memory
    assert r["coefficients"] == "24 unique (192 bytes as float64; 240 bytes in memory)"
    assert r["info.source"] == "Phong(kd=0.3)" and r["info.stderr"] == "[0, 1, 2]"
    assert r["info.truncation_error"] == "0.0125" and r["info.bad"] == "nan"

    d = described(capsys, path)
    # k_m = 2, 2, 1, 1: 3 + 3 + 1 + 1 upper-triangle entries per channel, 8 bytes each
    assert d["stored_bytes"] == 3 * 8 * 8 and d["bytes_on_disk"] == os.path.getsize(path)
    assert d["kind"] == "representation" and d["content"] == "coefficients"
    assert (d["basis_kind"], d["order"], d["size"], d["channels"]) == ("zernike", 3, 10, 3)
    assert d["isotropic"] and not d["scalar"] and d["dtype"] == "float64"
    assert d["unique_coefficients"] == 24 and d["nbytes"] == 240
    assert d["info"] == {"source": "Phong(kd=0.3)", "truncation_error": 0.0125,
                         "stderr": [0.0, 1.0, 2.0], "bad": "nan"}


def test_reduced_precision_and_dense(tmp_path, rng, capsys):
    cm = _matrix(rng, channels=1)
    dense = CoefficientMatrix(cm.basis, cm.matrix, cm.quantity, isotropic=False)
    d = described(capsys, save(dense, tmp_path / "d.h5", dtype="float32"))
    assert d["dtype"] == "float32" and not d["isotropic"]
    assert d["stored_bytes"] == 4 * 10 * 11 // 2  # the upper triangle of the dense 10 x 10
    status, out, _ = run(capsys, "info", str(tmp_path / "d.h5"))
    assert "bytes of float32 numbers" in out and rows(out)["isotropic"] == "no (dense)"


def test_model(tmp_path, capsys):
    path = save(_ggx(), tmp_path / "m.h5")
    d = described(capsys, path)
    assert d["content"] == "model" and d["family"] == "lambert+ggx"
    assert d["nparams"] == 8 and d["channels"] == 3 and d["nbytes"] == 64
    assert d["params"] == {"kd": [3], "ks": [3], "alpha": [], "f0": []}
    assert d["info"] == {"l2": 0.031, "converged": True} and d["stored_bytes"] == 64
    _, out, _ = run(capsys, "info", str(path))
    r = rows(out)
    assert r["family"] == "lambert+ggx" and r["parameters"] == "8 reals, 64 bytes as float64"
    assert r["shapes"] == "kd (3,), ks (3,), alpha (), f0 ()"


def test_hybrid(tmp_path, rng, capsys):
    h = Hybrid(_ggx(), _matrix(rng, order=2, quantity="f"), {"l2": 0.02, "source": "x"})
    d = described(capsys, save(h, tmp_path / "h.h5"))
    assert d["content"] == "hybrid" and d["info"] == {"l2": 0.02, "source": "x"}
    assert d["lobe"]["family"] == "lambert+ggx" and d["lobe"]["nparams"] == 8
    assert d["residual"]["basis"] == "HemiZernike(2)" and d["residual"]["quantity"] == "f"
    assert d["nbytes"] == h.nbytes
    _, out, _ = run(capsys, "info", str(tmp_path / "h.h5"))
    lines = out.splitlines()
    assert "scatmodes hybrid (schema 6" in lines[0]
    assert lines.index("lobe:") < lines.index("residual:")
    r = rows(out)
    assert r["family"] == "lambert+ggx" and r["basis"].startswith("HemiZernike(2)")


def test_schema_2_file(tmp_path, rng, capsys):
    cm = _matrix(rng, channels=1)
    path = save(cm, tmp_path / "old.h5")
    with h5py.File(path, "r+") as f:  # relabelled: what a schema 2 reader accepts
        f.attrs["schema_version"] = 2
        del f.attrs["content"]
    d = described(capsys, path)
    assert d["schema_version"] == 2 and d["content"] == "coefficients"


def test_checkpoint(tmp_path, capsys):
    from project.microgeometry import GaussianSurface, simulate

    ckpt = tmp_path / "run.ckpt"
    simulate(GaussianSurface(1.0, 6.5, resolution=16, seed=0), basis.HemiZernike(2),
             rays=800, seed=3, checkpoint=ckpt)
    d = described(capsys, ckpt)
    assert d["kind"] == "checkpoint" and d["rays"] == 800 and d["directions_done"] == 100
    assert d["basis"] == "HemiZernike(2)" and d["matrix_size"] == 6 and d["seeds"] == [3]
    assert d["energy"]["reflected"] == pytest.approx(800.0)  # lossless mirror facets
    assert d["surface"].startswith("GaussianSurface(sigma=1, tau=6.5")
    _, out, _ = run(capsys, "info", str(ckpt))
    assert rows(out)["rays traced"].startswith("800 in 1 chunk(s), ")
    with h5py.File(ckpt, "r+") as f:
        del f["rays"]
    line = one_line_error(capsys, "info", str(ckpt))
    assert f"{str(ckpt)!r} is a damaged simulation checkpoint: dataset 'rays' is missing" in line


def test_errors(tmp_path, rng, capsys):
    missing = tmp_path / "none.h5"
    assert one_line_error(capsys, "info", str(missing)).endswith(
        f"file {str(missing)!r} does not exist")
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    assert f"{str(text)!r} is not an HDF5 file" in one_line_error(capsys, "info", str(text))
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["x"] = np.arange(3)
    assert "is an HDF5 file but not a scatmodes file" in one_line_error(capsys, "info",
                                                                        str(foreign))
    path = save(_matrix(rng), tmp_path / "m.h5")
    with h5py.File(path, "r") as f:
        at = f["blocks/m0"].id.get_chunk_info(0).byte_offset
    data = bytearray(path.read_bytes())
    data[at] ^= 1
    path.write_bytes(bytes(data))
    line = one_line_error(capsys, "info", str(path))
    assert f"{str(path)!r} is damaged: /blocks/m0 cannot be read (its Fletcher-32" in line
    assert "directory" in one_line_error(capsys, "info", str(tmp_path))
    assert "--json describes a FILE" in one_line_error(capsys, "info", "--json")


def test_console_exit_status(tmp_path):
    r = subprocess.run([sys.executable, "-m", "compress.cli", "info", str(tmp_path / "x.h5")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip() == (f"scatmodes info: error: file {str(tmp_path / 'x.h5')!r} does "
                                "not exist")


@pytest.mark.parametrize("name", ["pipe.txt", "pipe.bsdf", "pipe.binary", "pipe.h5"])
def test_fifo(on_fifo, capsys, name):
    # compress.store.file_kind opened the file to read its first bytes: blocked forever
    line = on_fifo(lambda p: one_line_error(capsys, "info", str(p)), name)
    assert f"{name}' must be a regular file, got a FIFO (named pipe)" in line


@pytest.mark.parametrize("reader", [file_kind, load])
def test_fifo_refused_by_the_store(on_fifo, reader):
    with pytest.raises(ValueError, match=r"file '.*pipe.h5' must be a regular file, got a "
                                         r"FIFO \(named pipe\)"):
        on_fifo(reader, "pipe.h5")


# ------------------------------------------------------------------------ measurement files
CORNELL = """# Cornell University, Program of Computer Graphics
# Test Lacquer

# num wls
3

# wls
450 550
650

# theta i, phi i, theta s, phi_s, spectral sample values

0.174533 0.000000 0.573513 0.000000 0.1 0.2 0.3
0.174533 0.000000 0.427512 -0.261799 0.4 0.5 0.6
1.396263 0.000000 0.000000 0.000000 2.5 0.0 -0.01
"""


def test_cornell_measurements(tmp_path, capsys):
    path = tmp_path / "lacquer.brdf"
    path.write_text(CORNELL)
    d = described(capsys, path)
    assert d["kind"] == "measurements" and d["samples"] == 3 and d["channels"] == 3
    assert d["wavelengths_nm"] == [450.0, 650.0] and d["isotropic"] is True
    assert d["info"]["format"] == "cornell" and d["incidence_directions"] == 2
    assert d["theta_i_deg"] == [10.000004, 79.999977]  # 0.174533 rad, 1.396263 rad
    assert d["negative_values"] == 1 and d["value_range"][0] == [0.1, 2.5]
    status, out, err = run(capsys, "info", str(path))
    assert status == 0, err
    assert out.splitlines()[0] == f"{path}: BRDF measurements, {path.stat().st_size:,} bytes " \
                                  "on disk"
    r = rows(out)
    assert r["description"] == "Cornell University, Program of Computer Graphics / Test Lacquer"
    assert r["samples"] == "3" and r["channels"] == "3 (450-650 nm)"
    assert r["isotropic"] == "yes (as stated)" and r["phi_i constant"] == "yes"
    assert r["negative values"] == "1 (11.1 %)"
    assert r["incidence directions"] == "2; theta_i [10, 80] deg"


def test_csv_measurements(tmp_path, capsys):
    path = tmp_path / "gonio.csv"
    path.write_text("theta_i,phi_i,theta_o,phi_o,R,G,B\n0.5,0,1.2,3,1,2,3\n1.2,3,0.5,0,1,2,3\n")
    d = described(capsys, path)
    assert d["kind"] == "measurements" and d["channel_names"] == ["R", "G", "B"]
    assert d["isotropic"] is None and d["reciprocal_pairs"] == 2
    assert d["info"]["angles"] == "radians"
    assert d["info"]["angles_from"].startswith("detected: every theta <= pi/2")
    status, out, _ = run(capsys, "info", str(path))
    r = rows(out)
    assert r["isotropic"] == "not stated" and r["channels"] == "3 ([R, G, B])"
    assert r["angles"].startswith("radians (detected: every theta <= pi/2")


def test_damaged_measurements(tmp_path, capsys):
    path = tmp_path / "cut.brdf"
    path.write_text(CORNELL[:-12])
    line = one_line_error(capsys, "info", str(path))
    assert f"{str(path)!r} is not an HDF5 file" in line
    assert "line 15: the wavelength count 3 (line 5) does not fit the body" in line


@pytest.mark.parametrize("text, match", [
    ("inf 0 45 0 0.5\n", "line 1, column 1: cell must be finite, got 'inf'"),
    ("1e999\n", "line 1: a row must have 5 columns"),
    ("30 0 45 0 1_5\n", "line 1, column 5: cell must be a number, got '1_5' (ASCII digits "
                        "only, no '_' between them)"),
    ("30 0 45 0 \u0661\n", "line 1, column 5: cell must be a number, got '\u0661' (ASCII "
                             "digits only"),
], ids=["inf", "1e999-alone", "underscore", "arabic-indic"])
def test_measurement_numbers(tmp_path, capsys, text, match):
    # inf once raised OverflowError in format detection: a traceback and status 1
    path = tmp_path / "t.txt"
    path.write_text(text, encoding="utf-8")
    line = one_line_error(capsys, "info", str(path))
    assert f"{str(path)!r}" in line and match in line


def test_measurements_with_a_byte_order_mark(tmp_path, capsys):
    path = tmp_path / "t.txt"
    path.write_bytes(b"\xef\xbb\xbf30 0 45 180 0.5\n30 0 60 0 0.25\n")
    d = described(capsys, path)
    assert d["info"]["format"] == "table" and d["samples"] == 2


def test_rgl_file(tmp_path, capsys):
    rgl = pytest.importorskip("project.measured.rgl")
    f32 = np.float32
    fields = {
        "description": np.frombuffer(b"grey", np.uint8), "jacobian": np.array([1], np.uint8),
        "theta_i": np.array([0, np.pi / 2], f32), "phi_i": np.array([0], f32),
        "ndf": np.ones((2, 2), f32), "sigma": np.ones((2, 2), f32),
        "vndf": np.ones((1, 2, 2, 2), f32), "luminance": np.ones((1, 2, 2, 2), f32),
        "rgb": np.full((1, 2, 3, 2, 2), 0.5, f32)}
    path = rgl.write_tensor_file(tmp_path / "grey.bsdf", fields)
    d = described(capsys, path)
    assert d["kind"] == "rgl" and d["name"] == "grey" and d["description"] == "grey"
    assert d["channels"] == 3 and d["isotropic"] is True and d["jacobian"] is True
    assert d["theta_i_nodes"] == 2 and d["phi_i_nodes"] == 1 and d["wavelengths_nm"] is None
    status, out, _ = run(capsys, "info", str(path))
    assert "RGL-EPFL measured BRDF" in out.splitlines()[0]
    assert rows(out)["incidence nodes"] == "2 theta_i x 1 phi_i"


def _container(fields, size):
    """Tensor-file bytes whose headers say anything: fields of (name, code, offset, shape)."""
    head = b"tensor_file\0" + bytes([1, 0]) + struct.pack("<I", len(fields))
    for name, code, offset, shape in fields:
        head += struct.pack("<H", len(name)) + name.encode()
        head += struct.pack(f"<HBQ{len(shape)}Q", len(shape), code, offset, *shape)
    return head + bytes(size - len(head))


@pytest.mark.parametrize("fields, size, match", [
    ([("a", 10, 1024, (2**40, 2**40, 0))], 1028, "field 'a' has shape (1099511627776, "
                                                 "1099511627776, 0), which numpy cannot hold"),
    ([("a", 1, 1024, (1,) * 65)], 1028, "which numpy cannot hold"),
    ([("a", 10, 64, (2,)), ("b", 10, 68, (2,))], 80, "fields 'a' and 'b' overlap"),
    ([("a", 10, 66, (2,))], 80, "must start at an offset that is a multiple of its item size "
                                "4, got offset 66"),
], ids=["huge", "65-dims", "overlap", "misaligned"])
def test_damaged_rgl_header(tmp_path, capsys, fields, size, match):
    path = tmp_path / "bad.bsdf"
    path.write_bytes(_container(fields, size))
    line = one_line_error(capsys, "info", str(path))
    assert f"tensor file {str(path)!r}: " in line and match in line


# ------------------------------------------------------------------------------ reciprocity
PAPER = os.path.join(os.path.dirname(__file__), "..", "..", "data", "paper_white_rgb.bsdf")


def test_rgl_reciprocity(capsys):
    from compress.cli.info import RECIPROCITY_PAIRS
    from project import reciprocity
    from project.measured import read_rgl

    d = described(capsys, PAPER)
    r = d["reciprocity"]
    # the same seeded pairs as project.reciprocity with n = RECIPROCITY_PAIRS: equal numbers
    ref = reciprocity(read_rgl(PAPER), n=RECIPROCITY_PAIRS)
    assert r["residual"] == ref.residual and r["residual_stderr"] == ref.residual_stderr
    assert r["floor"] == r["residual"] / 2 and r["matched"] == ref.matched
    # white paper: residual 0.045 (module notes of project.reciprocity), about 1 % stderr
    assert 0.03 < r["residual"] < 0.06 and 0 < r["residual_stderr"] < 0.05 * r["residual"]
    assert r["tol_deg"] is None and "source" not in r and len(r["bands"]) == 4
    assert [c["name"] for c in r["channels"]] == ["R", "G", "B"]
    status, out, _ = run(capsys, "info", PAPER)
    text = rows(out)
    assert text["reciprocity"].startswith(f"residual ||q - q^T|| / ||q|| = {r['residual']:.4g}"
                                          f" +- {r['residual_stderr']:.2g}, floor ")
    assert text["reciprocity"].endswith(f"(worst channel; {r['matched']:,} pairs, both orders)")
    assert text["antisymmetric energy"].startswith("0-30 deg ")
    assert text["floor below"].startswith("30 deg ") and "90 deg " in text["floor below"]


def test_measurement_reciprocity(tmp_path, capsys):
    path = tmp_path / "twins.csv"
    # a pair and its reciprocal with R values 1 and 2, equal G and B; cos products equal
    path.write_text("theta_i,phi_i,theta_o,phi_o,R,G,B\n0.5,0,1.2,3,1,2,3\n1.2,3,0.5,0,2,2,3\n")
    r = described(capsys, path)["reciprocity"]
    # R: sqrt(((1 - 2)^2 + (2 - 1)^2) / (1^2 + 2^2)) = sqrt(2 / 5); G and B: 0
    assert r["residual"] == pytest.approx(np.sqrt(0.4), rel=1e-12)
    assert r["residual_stderr"] is None  # one group of twins: no spread to estimate it from
    assert r["matched"] == 2 and r["tol_deg"] == 0.01 and r["note"] == ""
    assert [c["residual"] for c in r["channels"][1:]] == [0.0, 0.0]
    _, out, _ = run(capsys, "info", str(path))
    assert rows(out)["reciprocity"] == ("residual ||q - q^T|| / ||q|| = 0.6325, floor 0.3162 "
                                        "(worst channel; 2 samples with a reciprocal twin "
                                        "within 0.01 deg)")


def test_measurements_without_reciprocal_pairs(tmp_path, capsys):
    path = tmp_path / "lacquer.brdf"
    path.write_text(CORNELL)  # theta_i 10 and 80 degrees, theta_o 33 and 25 and 0: no twins
    r = described(capsys, path)["reciprocity"]
    assert r["residual"] is None and r["floor"] is None and r["matched"] == 0
    assert r["note"].startswith("no sample has a reciprocal twin within 0.01 deg per "
                                "direction, up to rotation and mirroring about the normal")
    _, out, _ = run(capsys, "info", str(path))
    assert rows(out)["reciprocity"].startswith("unknown: no sample has a reciprocal twin")


def test_measurement_reciprocity_not_estimated(tmp_path, capsys):
    path = tmp_path / "dark.csv"
    path.write_text("theta_i,phi_i,theta_o,phi_o,v\n0.5,0,1.2,3,0\n1.2,3,0.5,0,0\n")
    r = described(capsys, path)["reciprocity"]
    assert r == {"error": "measurements must not be 0 (or of weight 0) at every matched sample "
                          "of channel 'v': the relative residual is undefined"}
    status, out, _ = run(capsys, "info", str(path))
    assert status == 0 and rows(out)["reciprocity"].startswith("not estimated: measurements")


def test_mbsdf_file(tmp_path, capsys):
    from project.measured import write_mbsdf
    from project.models import CookTorrance

    path = write_mbsdf(CookTorrance(kd=[0.2, 0.3, 0.4], roughness=0.4), tmp_path / "ct.mbsdf",
                       resolution=(8, 16))
    d = described(capsys, path)
    assert d["kind"] == "mbsdf" and d["name"] == "ct" and d["channels"] == 3
    assert d["resolution"] == [8, 16] and d["negative_count"] == 0
    assert d["transmission"] is None and d["metadata"] == []
    assert d["bytes_on_disk"] == 20 + 23 + 12 + 4 * 3 * 8 * 8 * 16
    assert d["reciprocity"]["residual"] < 0.05   # a reciprocal model, sampled on a grid
    status, out, _ = run(capsys, "info", str(path))
    assert status == 0
    assert out.startswith(f"{path}: NVIDIA MDL measured BSDF (.mbsdf)")
    r = rows(out)
    assert r["grid"] == "8 theta_in x 8 theta_out x 16 delta_phi"
    assert r["channels"] == "3 (RGB)" and r["transmission"] == "none"


def test_damaged_mbsdf(tmp_path, capsys):
    path = tmp_path / "cut.mbsdf"
    path.write_bytes(b"NVIDIA ARC MBSDF V1\nMBSDF_DATA=\n" + bytes(6))
    line = one_line_error(capsys, "info", str(path))
    assert f"MBSDF file {str(path)!r} ends inside the header of its reflection part" in line
