"""``scatmodes render``: Mitsuba renders of a saved representation, with and without a reference.

References: the written EXR files read back by Mitsuba's own ``Bitmap`` (the printed relative
RMSE must be the one of the written images), and one-line errors for bad inputs.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 (extra [mitsuba]) is not installed")

import basis  # noqa: E402
import compress  # noqa: E402
from basis import CoefficientMatrix  # noqa: E402
from compress.cli import main  # noqa: E402
from project import FittedModel  # noqa: E402

RGL = Path(__file__).resolve().parents[2] / "data" / "paper_white_rgb.bsdf"
ROOT = Path(__file__).resolve().parents[3]


def run(capsys, *argv):
    try:
        status = main([str(a) for a in argv])
    except SystemExit as stop:
        status = stop.code
    out, err = capsys.readouterr()
    return status, out, err


def one_line_error(capsys, *argv):
    status, out, err = run(capsys, *argv)
    assert status == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("scatmodes render: error: "), lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def ggx(tmp_path_factory):
    m = FittedModel("lambert+ggx", {"kd": [0.4, 0.3, 0.2], "ks": [0.5] * 3, "alpha": 0.3,
                                    "f0": 0.5})
    return compress.save(m, tmp_path_factory.mktemp("render") / "ggx.h5")


def _exr(path):
    return np.array(mi.Bitmap(str(path)), dtype=np.float64)


def test_render_writes_png_and_exr(ggx, tmp_path, capsys):
    out = tmp_path / "img.png"
    status, stdout, err = run(capsys, "render", ggx, "-o", out, "--size", 16, "--spp", 4)
    assert status == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["img.exr", "img.png"]  # no temps
    img = _exr(tmp_path / "img.exr")
    assert img.shape == (16, 16, 3) and np.all(np.isfinite(img)) and img.max() > 0
    png = np.array(mi.Bitmap(str(out)))
    assert png.shape[:2] == (16, 16) and png.dtype == np.uint8
    assert f"wrote {out}" in stdout


def test_reference_rgl_prints_the_rmse_of_the_written_images(ggx, tmp_path, capsys):
    out = tmp_path / "cmp.png"
    status, stdout, err = run(capsys, "render", ggx, "--reference", RGL, "-o", out,
                              "--size", 12, "--spp", 4)
    assert status == 0, err
    names = {p.name for p in tmp_path.iterdir()}
    assert {"cmp.png", "cmp.exr", "cmp-reference.png", "cmp-reference.exr",
            "cmp-difference.png", "cmp-difference.exr"} == names
    got = float(re.search(r"relative RMSE against paper_white_rgb.bsdf: ([0-9.e+-]+)",
                          stdout).group(1))
    a, r = _exr(tmp_path / "cmp.exr"), _exr(tmp_path / "cmp-reference.exr")
    ref = np.sqrt(np.mean((a - r) ** 2) / np.mean(r ** 2))
    # printed with 4 significant digits; EXR stores float32 (relative rounding 6e-8)
    assert got == pytest.approx(ref, rel=1e-3)
    np.testing.assert_allclose(_exr(tmp_path / "cmp-difference.exr"), np.abs(a - r),
                               rtol=1e-6, atol=1e-7)


def test_reference_merl(tmp_path, capsys):
    """A constant MERL file, read by project.measured.read_merl, rendered through the plugin."""
    merl = tmp_path / "const.binary"
    with open(merl, "wb") as fh:
        np.array([90, 90, 180], dtype="<i4").tofile(fh)
        np.full(3 * 90 * 90 * 180, 0.1, dtype="<f8").tofile(fh)
    zb = basis.HemiZernike(0)
    lam = compress.save(CoefficientMatrix(zb, [[0.3]], quantity="f"), tmp_path / "lam.h5")
    status, stdout, err = run(capsys, "render", lam, "--reference", merl, "-o",
                              tmp_path / "m.png", "--size", 8, "--spp", 2)
    assert status == 0, err
    assert "relative RMSE against const.binary" in stdout


def test_scalar_variant(ggx, tmp_path, capsys):
    status, stdout, err = run(capsys, "render", ggx, "-o", tmp_path / "s.png", "--size", 4,
                              "--spp", 1, "--variant", "scalar_rgb")
    assert status == 0, err
    assert _exr(tmp_path / "s.exr").shape == (4, 4, 3)


def test_bad_inputs(ggx, tmp_path, capsys):
    assert "-o must name a .png file" in one_line_error(
        capsys, "render", ggx, "-o", tmp_path / "x.jpg")
    assert "missing.h5" in one_line_error(
        capsys, "render", tmp_path / "missing.h5", "-o", tmp_path / "x.png")
    assert "No such directory" in one_line_error(
        capsys, "render", ggx, "-o", tmp_path / "nowhere" / "x.png")
    assert "--reference must be an RGL-EPFL .bsdf or a MERL .binary" in one_line_error(
        capsys, "render", ggx, "--reference", ggx, "-o", tmp_path / "x.png")
    assert "--size must be <= 4096" in one_line_error(
        capsys, "render", ggx, "-o", tmp_path / "x.png", "--size", 5000)
    assert "must be a positive integer" in one_line_error(
        capsys, "render", ggx, "-o", tmp_path / "x.png", "--spp", 0)
    assert list(tmp_path.iterdir()) == []  # nothing written on errors


def test_variant_without_gpu(ggx, tmp_path, capsys):
    """--variant cuda_ad_rgb where Mitsuba finds no CUDA device: a one-line error."""
    import drjit as dr
    import mitsuba as mi
    try:
        mi.set_variant("cuda_ad_rgb")
        dr.eval(mi.Float(1.0) + 1.0)
        pytest.skip("a CUDA device is present: nothing to refuse")
    except Exception:  # noqa: BLE001 - the case under test
        pass
    finally:
        mi.set_variant("scalar_rgb")
    assert "--variant cuda_ad_rgb needs an NVIDIA GPU" in one_line_error(
        capsys, "render", ggx, "-o", tmp_path / "x.png", "--variant", "cuda_ad_rgb")
    assert list(tmp_path.iterdir()) == []


def test_without_mitsuba(tmp_path):
    code = ("import sys; sys.modules['mitsuba'] = None\n"
            "from compress.cli import main\n"
            f"sys.exit(main(['render', {str(tmp_path / 'a.h5')!r}, '-o', "
            f"{str(tmp_path / 'a.png')!r}]))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=ROOT)
    assert proc.returncode == 2
    assert proc.stderr.strip() == ("scatmodes render: error: compress.mitsuba needs Mitsuba 3: "
                                   "pip install 'scatmodes[mitsuba]'")
