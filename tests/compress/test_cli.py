"""The scatmodes command line: demo on embedded defaults, info, one-line errors."""

import subprocess
import sys

from compress.cli import main


def test_demo_writes_table_and_picture(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--orders", "2,4", "--points", "200"]) == 0
    out = capsys.readouterr().out
    assert "| HemiZernike(4) | 4 | 15 |" in out
    assert "HelmholtzModes(8, isotropic=True) | 8 | 55 |" in out
    png = tmp_path / "modes.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob(".modes.png*"))  # no temporary file left behind


def test_info(capsys):
    assert main(["info"]) == 0
    assert "HemiZernike: order <= 1000" in capsys.readouterr().out


def test_bad_input_is_one_line_without_traceback(tmp_path):
    r = subprocess.run([sys.executable, "-m", "compress.cli", "demo", "--out", str(tmp_path),
                        "--orders", "-3"], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip() == ("scatmodes demo: error: --orders must be comma-separated "
                                "integers >= 0, got '-3'")
    assert "Traceback" not in r.stderr


def test_help_for_every_command():
    for cmd in ([], ["demo"], ["info"]):
        r = subprocess.run([sys.executable, "-m", "compress.cli", *cmd, "--help"],
                           capture_output=True, text=True)
        assert r.returncode == 0 and "usage: scatmodes" in r.stdout
