"""The scatmodes command line: every command on small inputs, --help everywhere, and one-line
errors (status 2, no traceback) for each class of user error."""

import os
import re
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from compress import load
from compress.cli import main
from project.measured import write_mbsdf, write_merl
from project.models import Lambert

PHONG = ["Phong", "--param", "kd=0.3", "--param", "ks=0.4", "--param", "n=20"]


def run(capsys, *argv):
    """main(argv) -> (status, stdout, stderr); --help and argparse errors exit via SystemExit."""
    try:
        status = main(list(argv))
    except SystemExit as stop:
        status = stop.code
    out, err = capsys.readouterr()
    return status, out, err


def one_line_error(capsys, *argv):
    """The single stderr line of a failing command (asserts status 2 and no traceback)."""
    status, _, err = run(capsys, *argv)
    assert status == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"scatmodes {argv[0]}: error: "), lines[0]
    return lines[0]


# -- demo and info ---------------------------------------------------------------------------
def test_demo_writes_tables_and_charts(tmp_path, capsys):
    status, out, _ = run(capsys, "demo", "--out", str(tmp_path), "--orders", "2,4", "--points",
                         "200", "--study-orders", "2,4", "--rays", "2000", "--resolution", "16")
    assert status == 0
    assert "| HemiZernike(4) | 4 | 15 |" in out
    assert "HelmholtzModes(8, isotropic=True) | 8 | 55 |" in out
    # resolution-vs-error table: one row per model, kind and order; resolution = 180 / order
    assert "| phong | zernike | 4 | 45.0 | 14 |" in out
    assert "| cooktorrance | harmonics | 2 | 90.0 | 2 |" in out
    assert "asymmetry Q =" in out and "reflected 1.0000" in out  # lossless mirror facets
    for name in ("modes", "study-phong", "study-cooktorrance", "simulated"):
        png = tmp_path / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    assert "| kind | order |" in (tmp_path / "study.md").read_text()
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_demo_without_simulation(tmp_path, capsys):
    status, out, _ = run(capsys, "demo", "--out", str(tmp_path), "--orders", "2", "--points",
                         "100", "--study-orders", "2", "--rays", "0")
    assert status == 0 and "Monte Carlo" not in out
    assert not (tmp_path / "simulated.png").exists()


def test_info(capsys):
    status, out, _ = run(capsys, "info")
    assert status == 0
    assert "HemiZernike: order <= 1000" in out
    assert "CookTorrance" in out and "harmonics-even" in out


# -- project and convert ---------------------------------------------------------------------
def test_project_lambert_is_one_coefficient(tmp_path, capsys):
    path = tmp_path / "lambert.h5"
    status, out, err = run(capsys, "project", "lambert", "--param", "albedo=0.5", "--basis",
                           "harmonics", "--order", "1", "-o", str(path))
    assert status == 0, err
    assert out.startswith(f"wrote {path}: Lambert(albedo=0.5) in HemiHarmonics(1")
    assert "error estimate" in out and "truncation error" in out
    cm = load(path)
    k = cm.basis.index(1, 0)
    # Westin's form: 2a/3 on b_10, exact up to the quadrature's rounding (see project doctest)
    np.testing.assert_allclose(cm.matrix[k, k], 1 / 3, rtol=0, atol=1e-12)


def test_project_per_channel_parameters_and_words(tmp_path, capsys):
    path = tmp_path / "ct.h5"
    status, _, err = run(capsys, "project", "CookTorrance", "--param", "kd=0.2,0.3,0.4",
                         "--param", "roughness=0.5", "--param", "distribution=ggx",
                         "--order", "4", "-o", str(path))
    assert status == 0, err
    cm = load(path)
    assert cm.channels == 3 and "ggx" in cm.info["source"]


def test_project_reports_warnings_in_one_line(tmp_path, capsys):
    status, _, err = run(capsys, "project", *PHONG, "--order", "2", "-o",
                         str(tmp_path / "p.h5"))
    assert status == 0
    lines = err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("scatmodes project: warning: the expansion of Phong")


@pytest.fixture(scope="module")
def merl_file(tmp_path_factory):
    """A MERL-format file sampled from Lambert(0.5) (34,992,012 bytes, in a temp dir)."""
    return write_merl(tmp_path_factory.mktemp("merl") / "white.binary", Lambert(0.5))


def test_convert_merl(tmp_path, capsys, merl_file):
    path = tmp_path / "white.h5"
    status, out, err = run(capsys, "convert", str(merl_file), "--order", "2", "-o", str(path))
    assert status == 0, err
    assert "MERLBRDF(name='white'" in out
    cm = load(path)
    # a constant table interpolates to the constant: albedo 0.5 to the quadrature tolerance
    # 1e-3 (relative to max |M|) of convert's default
    np.testing.assert_allclose(cm.albedo([0.0, 0.0, 1.0]), 0.5, rtol=0, atol=2e-3)


def test_project_merl_same_as_convert(tmp_path, capsys, merl_file):
    status, out, _ = run(capsys, "project", "--merl", str(merl_file), "--order", "2", "-o",
                         str(tmp_path / "w.h5"))
    assert status == 0 and "MERLBRDF(name='white'" in out


# -- fit -------------------------------------------------------------------------------------
def test_fit_recovers_lambert(tmp_path, capsys, rng):
    table = tmp_path / "lambert.txt"
    n = 60
    deg = np.column_stack([rng.uniform(0, 89, n), rng.uniform(0, 360, n),
                           rng.uniform(0, 89, n), rng.uniform(0, 360, n),
                           np.full(n, 0.5 / np.pi)])
    np.savetxt(table, deg, header="theta_i phi_i theta_o phi_o f")
    path = tmp_path / "fit.h5"
    status, out, err = run(capsys, "fit", str(table), "--order", "2", "-o", str(path))
    assert status == 0, err
    assert "60 samples" in out and "rank 5 of 5 unknowns" in out and "condition number" in out
    # exact data in the span of the basis: only rounding remains (%.18e text keeps ~1e-16)
    np.testing.assert_allclose(load(path).albedo([0.0, 0.0, 1.0]), 0.5, rtol=0, atol=1e-12)
    # the default validates the weight: this well-posed fit keeps the plain one
    assert ("regularization weight 0 (degree penalty, chosen by 10-fold CV on direction "
            "pairs), 5.0 effective parameters") in out
    assert re.search(r"validation error [0-9.e-]+ % \(relative RMS at held-out pairs\)", out)
    assert load(path).info["regularization_method"] == "10-fold CV on direction pairs"


def test_fit_no_reciprocal_recovers_a_general_matrix(tmp_path, capsys, rng):
    # independent reference: a known non-symmetric matrix, evaluated by CoefficientMatrix.eval
    from basis import CoefficientMatrix, HemiZernike, from_angles

    zb = HemiZernike(2)
    sizes = [c.size for c in zb.azimuthal_blocks().cos]
    blocks = [np.abs(rng.normal(size=(k, k))) + (2.0 if m == 0 else 0.0)
              for m, k in enumerate(sizes)]
    truth = CoefficientMatrix.from_blocks(zb, blocks, "f", reciprocal=False)
    n = 200
    deg = np.column_stack([rng.uniform(0, 85, n), rng.uniform(0, 360, n),
                           rng.uniform(0, 85, n), rng.uniform(0, 360, n)])
    wi, wo = from_angles(*np.radians(deg[:, :2]).T), from_angles(*np.radians(deg[:, 2:]).T)
    table = tmp_path / "general.txt"
    np.savetxt(table, np.column_stack([deg, truth.eval(wi, wo)]), fmt="%.18e")
    path = tmp_path / "fit.h5"
    status, out, err = run(capsys, "fit", str(table), "--order", "2", "--no-reciprocal",
                           "-o", str(path))
    assert status == 0, err
    got = load(path)
    assert not got.reciprocal and "rank 6 of 6 unknowns" in out  # blocks of sizes 2, 1, 1
    # exact data in the span: rounding of the %.18e text and of the solve
    np.testing.assert_allclose(got.matrix[0], truth.matrix, rtol=0, atol=1e-10)
    # with --model the option is refused like the other modal options
    status, _, err = run(capsys, "fit", str(table), "--model", "lambert+ggx", "--no-reciprocal",
                         "-o", str(path))
    assert status == 2 and "reciprocal" in err and "modal fit" in err


def test_fit_regularises_a_rank_deficient_table(tmp_path, capsys, rng):
    # every incidence at the pole: only the m = 0 functions of w_i are seen (rank 3 of 14 at
    # order 4), so the plain fit warns and the default regularises without a warning
    table = tmp_path / "pole.txt"
    n = 100
    deg = np.column_stack([np.zeros(n), np.zeros(n), rng.uniform(0, 89, n),
                           rng.uniform(0, 360, n), np.full(n, 0.5 / np.pi)])
    np.savetxt(table, deg)
    status, out, err = run(capsys, "fit", str(table), "--order", "4", "-o",
                           str(tmp_path / "a.h5"))
    assert status == 0 and "warning" not in err, err
    weight = float(re.search(r"regularization weight ([0-9.e+-]+) \(degree penalty", out)[1])
    assert weight > 0
    status, out, err = run(capsys, "fit", str(table), "--order", "4", "--regularization", "0",
                           "-o", str(tmp_path / "p.h5"))
    assert status == 0 and "rank-deficient" in err
    assert "regularization weight 0 (identity penalty, given)" in out
    assert "validation error not computed (weight given)" in out
    # the chosen weight and penalty given back reproduce the automatic fit
    status, out, err = run(capsys, "fit", str(table), "--order", "4", "--regularization",
                           repr(weight), "--penalty", "degree", "-o", str(tmp_path / "r.h5"))
    assert status == 0, err
    np.testing.assert_allclose(load(tmp_path / "r.h5").matrix, load(tmp_path / "a.h5").matrix,
                               rtol=1e-6, atol=1e-9)  # the weight printed to 3 digits


@pytest.mark.parametrize("argv, match", [
    (["--regularization", "-1"], "argument --regularization: must be one of auto, gcv, "
                                 "leave-incidence-out or a number >= 0, got '-1'"),
    (["--regularization", "often"], "argument --regularization: must be one of auto"),
    (["--regularization", "inf"], "got 'inf'"),
    (["--penalty", "smooth"], "argument --penalty: invalid choice: 'smooth'"),
])
def test_fit_bad_regularization(tmp_path, capsys, argv, match):
    from compress.cli import commands
    from project.lstsq import REGULARIZATION_METHODS

    assert commands._FIT_METHODS == REGULARIZATION_METHODS
    table = tmp_path / "t.txt"
    table.write_text("10 0 20 0 0.1\n")
    line = one_line_error(capsys, "fit", str(table), *argv, "-o", str(tmp_path / "x.h5"))
    assert match in line


# -- simulate --------------------------------------------------------------------------------
def test_simulate_with_checkpoint_and_resume(tmp_path, capsys):
    common = ["simulate", "--sigma", "1", "--tau", "6.5", "--resolution", "16", "--order",
              "4", "--seed", "3", "--checkpoint", str(tmp_path / "run.ckpt")]
    status, out, err = run(capsys, *common, "--rays", "2000", "-o", str(tmp_path / "a.h5"))
    assert status == 0, err
    assert "Q = " in out and "rays/s" in out and "reflected 1.0000" in out
    status, out, err = run(capsys, *common, "--rays", "4000", "--resume",
                           str(tmp_path / "run.ckpt"), "-o", str(tmp_path / "b.h5"))
    assert status == 0, err
    assert "traced 4000 rays" in out
    assert load(tmp_path / "b.h5").info["rays"] == 4000


def test_simulate_diffuse_with_progress_bar(tmp_path, capsys):
    status, out, err = run(capsys, "simulate", "--sigma", "1", "--tau", "3", "--material",
                           "diffuse", "--albedo", "0.5", "--resolution", "16", "--order", "2",
                           "--rays", "2000", "--progress", "-o", str(tmp_path / "d.h5"))
    assert status == 0, err
    assert "simulate" in err  # the tqdm bar
    total = float(re.search(r"\(sum ([0-9.]+)\)", out).group(1))
    # reflected + absorbed + escaped = 1 up to Russian-roulette noise (observed 0.9999)
    assert abs(total - 1.0) < 5e-3


def test_project_lafortune_lobes(tmp_path, capsys):
    status, out, err = run(capsys, "project", "Lafortune", "--param", "kd=0.2", "--param",
                           "lobes=-0.8,-0.8,0.8,20;0.1,0.1,0.2,2", "--order", "6", "-o",
                           str(tmp_path / "l.h5"))
    assert status == 0, err
    assert "Lafortune(" in out


# -- study -----------------------------------------------------------------------------------
def test_study_writes_markdown_and_chart(tmp_path, capsys):
    status, out, err = run(capsys, "study", *PHONG, "--kinds", "zernike,harmonics",
                           "--orders", "2,4", "--out", str(tmp_path / "st"))
    assert status == 0, err
    assert out.startswith("Study of Phong(kd=0.3, ks=0.4, n=20)")
    assert "| zernike | 4 | f | 14 |" in out and "| harmonics | 2 | f_cos | 2 |" in out
    assert (tmp_path / "st" / "study.md").read_text().startswith("Study of Phong")
    assert (tmp_path / "st" / "study.png").read_bytes()[:4] == b"\x89PNG"


# -- help ------------------------------------------------------------------------------------
@pytest.mark.parametrize("cmd", ["demo", "project", "convert", "fit", "simulate", "study",
                                 "info", "export"])
def test_help_for_every_command(cmd, capsys):
    status, out, _ = run(capsys, cmd, "--help")
    assert status == 0 and out.startswith(f"usage: scatmodes {cmd}")
    assert "example" in out


def test_help_and_errors_through_the_console_module(tmp_path):
    r = subprocess.run([sys.executable, "-m", "compress.cli", "--help"], capture_output=True,
                       text=True)
    assert r.returncode == 0 and "usage: scatmodes" in r.stdout
    r = subprocess.run([sys.executable, "-m", "compress.cli", "demo", "--out", str(tmp_path),
                        "--orders", "-3"], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip() == ("scatmodes demo: error: --orders must be comma-separated "
                                "integers >= 0, got '-3'")


# -- one-line errors, by class ---------------------------------------------------------------
def test_bad_model_name(tmp_path, capsys):
    line = one_line_error(capsys, "project", "Glossy", "-o", str(tmp_path / "x.h5"))
    assert "MODEL must be one of AshikhminShirley, BlinnPhong," in line and "got 'Glossy'" in line


@pytest.mark.parametrize("params, match", [
    (["albedo"], "--param must be KEY=VALUE, got 'albedo'"),
    (["colour=1"], "--param 'colour' is not a parameter of Lambert, which takes albedo"),
    ([], "Lambert needs --param for albedo (e.g. --param albedo=0.5)"),
    (["albedo=-0.5"], "albedo"),  # the model's own ValueError
    (["albedo=1,x"], "--param albedo must be a number"),
])
def test_bad_parameter(tmp_path, capsys, params, match):
    argv = ["project", "Lambert"] + [a for p in params for a in ("--param", p)]
    line = one_line_error(capsys, *argv, "-o", str(tmp_path / "x.h5"))
    assert match in line


def test_model_and_merl_are_exclusive(tmp_path, capsys, merl_file):
    line = one_line_error(capsys, "project", "Lambert", "--merl", str(merl_file), "-o",
                          str(tmp_path / "x.h5"))
    assert "either MODEL or --merl" in line
    line = one_line_error(capsys, "study", "--out", str(tmp_path))
    assert "give a MODEL" in line


@pytest.mark.parametrize("argv, match", [
    (["project", "--merl", "{tmp}/none.binary"], "--merl file '{tmp}/none.binary' does not exist"),
    (["convert", "{tmp}/none.binary"], "--merl file '{tmp}/none.binary' does not exist"),
    (["fit", "{tmp}/none.txt"], "TABLE file '{tmp}/none.txt' does not exist"),
    (["fit", "{tmp}"], "TABLE must be a file, got the directory '{tmp}'"),
    (["simulate", "--sigma", "1", "--tau", "2", "--resume", "{tmp}/none.ckpt"],
     "--resume file '{tmp}/none.ckpt' does not exist"),
])
def test_missing_file(tmp_path, capsys, argv, match):
    argv = [a.format(tmp=tmp_path) for a in argv]
    line = one_line_error(capsys, *argv, "-o", str(tmp_path / "x.h5"))
    assert match.format(tmp=tmp_path) in line


def test_damaged_files(tmp_path, capsys):
    bad = tmp_path / "bad.binary"
    bad.write_bytes(b"\x00" * 100)
    line = one_line_error(capsys, "convert", str(bad), "-o", str(tmp_path / "x.h5"))
    assert "MERL header must hold the dimensions (90, 90, 180)" in line
    table = tmp_path / "t.txt"
    table.write_text("10 0 20 0 0.1\n10 0 95 0 0.1\n")
    line = one_line_error(capsys, "fit", str(table), "-o", str(tmp_path / "x.h5"))
    assert "line 2: theta_o must lie in [0, 90] degrees, got 95" in line


@pytest.mark.parametrize("command", ["fit", "convert"])
@pytest.mark.parametrize("text, match", [
    ("inf 0 45 0 0.5\n", "line 1, column 1: cell must be finite, got 'inf'"),
    ("1e999 0 45 0 0.5\n", "line 1, column 1: cell must be finite, got '1e999'"),
    ("30 0 45 0 1_5\n", "line 1, column 5: cell must be a number, got '1_5' (ASCII digits "
                        "only, no '_' between them)"),
], ids=["inf", "1e999", "underscore"])
def test_measurement_numbers(tmp_path, capsys, command, text, match):
    table = tmp_path / "t.txt"
    table.write_text(text)
    line = one_line_error(capsys, command, str(table), "-o", str(tmp_path / "x.h5"))
    assert str(table) in line and match in line


@pytest.mark.parametrize("offsets, match", [((64, 68), "fields 'a' and 'b' overlap"),
                                            ((66, 76), "multiple of its item size 4")])
def test_convert_damaged_rgl_header(tmp_path, capsys, offsets, match):
    head = b"tensor_file\0" + bytes([1, 0]) + struct.pack("<I", 2)
    for name, offset in zip("ab", offsets, strict=True):
        head += struct.pack("<H", 1) + name.encode() + struct.pack("<HBQQ", 1, 10, offset, 2)
    bad = tmp_path / "bad.bsdf"
    bad.write_bytes(head + bytes(88 - len(head)))
    line = one_line_error(capsys, "convert", str(bad), "-o", str(tmp_path / "x.h5"))
    assert f"tensor file {str(bad)!r}: " in line and match in line


@pytest.mark.parametrize("command, name", [("fit", "pipe.txt"), ("convert", "pipe.txt"),
                                           ("convert", "pipe.bsdf"),
                                           ("convert", "pipe.binary")])
def test_fifo(tmp_path, capsys, on_fifo, command, name):
    # the command opened the file to tell its kind: blocked forever
    line = on_fifo(lambda p: one_line_error(capsys, command, str(p), "-o",
                                            str(tmp_path / "x.h5")), name)
    assert f"{name}' must be a regular file, got a FIFO, a device or a socket" in line


@pytest.mark.parametrize("out, match", [
    ("{tmp}/missing/x.h5", "cannot write -o '{tmp}/missing/x.h5': directory '{tmp}/missing' "
                           "does not exist"),
    ("{tmp}", "-o must name a file, got the directory '{tmp}'"),
])
def test_unwritable_output(tmp_path, capsys, out, match):
    out = out.format(tmp=tmp_path)
    line = one_line_error(capsys, "project", "Lambert", "--param", "albedo=0.5", "-o", out)
    assert match.format(tmp=tmp_path) in line


def test_unwritable_output_folder(tmp_path, capsys):
    afile = tmp_path / "a-file"
    afile.write_text("")
    line = one_line_error(capsys, "study", "Lambert", "--param", "albedo=0.5", "--out",
                          str(afile))
    assert f"--out must be a directory, got the file '{afile}'" in line
    line = one_line_error(capsys, "demo", "--out", str(afile / "sub"))
    assert "cannot create --out directory" in line


@pytest.mark.parametrize("argv, match", [
    (["--order", "-1"], "argument --order: must be an integer >= 0, got '-1'"),
    (["--order", "two"], "argument --order: must be an integer >= 0, got 'two'"),
    (["--basis", "harmonics", "--order", "0"], "order must be >= 1 for kind='harmonics'"),
    (["--order", "5000"], "order"),  # the basis' own limit
    (["--basis", "legendre"], "argument --basis: invalid choice: 'legendre'"),
])
def test_bad_order_or_basis(tmp_path, capsys, argv, match):
    line = one_line_error(capsys, "project", "Lambert", "--param", "albedo=0.5", *argv, "-o",
                          str(tmp_path / "x.h5"))
    assert match in line


@pytest.mark.parametrize("argv, match", [
    (["study", "Lambert", "--param", "albedo=0.5", "--orders", "2,x"],
     "--orders must be comma-separated integers >= 0, got '2,x'"),
    (["study", "Lambert", "--param", "albedo=0.5", "--kinds", "zernike,legendre"],
     "--kinds must be comma-separated basis kinds"),
    (["study", "Lambert", "--param", "albedo=0.5", "--metric", "psnr"],
     "--metric must be one of l2,"),
    (["simulate", "--sigma", "0", "--tau", "1", "-o", "x.h5"],
     "argument --sigma: must be a positive number, got '0'"),
    (["simulate", "--sigma", "1", "--tau", "1", "--rays", "-5", "-o", "x.h5"],
     "argument --rays: must be a positive integer"),
    (["simulate", "--sigma", "1", "--tau", "1", "--albedo", "0.5", "-o", "x.h5"],
     "--albedo applies to --material diffuse"),
    (["simulate", "--sigma", "1", "--tau", "1"], "the following arguments are required: -o"),
    (["fit", "t.txt", "--basis", "sh", "-o", "x.h5"], "argument --basis: invalid choice: 'sh'"),
])
def test_bad_values(tmp_path, capsys, monkeypatch, argv, match):
    monkeypatch.chdir(tmp_path)
    line = one_line_error(capsys, *argv)
    assert match in line


def test_version(capsys):
    import basis

    status, out, _ = run(capsys, "--version")
    assert status == 0 and out.strip() == f"scatmodes {basis.__version__}"


def test_no_command(capsys):
    status, _, err = run(capsys)
    assert status == 2
    assert err.strip().splitlines() == [
        "scatmodes: error: the following arguments are required: COMMAND (see 'scatmodes "
        "--help')"]


def test_every_model_example_builds():
    from compress.cli import MODEL_EXAMPLES, model_classes, parse_model

    assert set(MODEL_EXAMPLES) == set(model_classes())
    for name, example in MODEL_EXAMPLES.items():
        brdf = parse_model(name, [p.strip("'") for p in example.split()])
        assert type(brdf).__name__ == name


def test_study_stability_writes_the_atlas(tmp_path, capsys, monkeypatch):
    import compress.stability as stability

    calls = []

    def fake_write_all(out, small=False, client=None):  # the atlas: test_stability
        assert client is None  # neither --workers nor --scheduler
        calls.append((out, small))
        return {"radial_accuracy": (out / "radial_accuracy.md", out / "radial_accuracy.png")}

    monkeypatch.setattr(stability, "write_all", fake_write_all)
    assert main(["study", "--stability", "--small", "--out", str(tmp_path)]) == 0
    assert calls == [(tmp_path, True)]
    assert "radial_accuracy.md and" in capsys.readouterr().out


def test_study_stability_refuses_a_model(tmp_path, capsys):
    assert main(["study", "Lambert", "--stability", "--out", str(tmp_path)]) == 2
    assert "--stability takes no MODEL" in capsys.readouterr().err


# -- suffixes, quantities, checkpoints and signals -------------------------------------------
SIM = ["simulate", "--sigma", "1", "--tau", "6.5", "--resolution", "16", "--order", "2"]


@pytest.mark.parametrize("argv", [
    [*SIM, "-o", "{tmp}/x.txt"],
    [*SIM, "-o", "{tmp}/x"],
    ["fit", "{tmp}/t.txt", "-o", "{tmp}/x.csv"],
    ["project", "Lambert", "--order", "2", "-o", "{tmp}/x.npz"],
    ["convert", "{tmp}/t.txt", "--order", "2", "-o", "{tmp}/x.json"],
], ids=["simulate-txt", "simulate-none", "fit-csv", "project-npz", "convert-json"])
def test_output_suffix_must_be_hdf5(tmp_path, capsys, argv):
    (tmp_path / "t.txt").write_text("10 0 20 0 0.1\n")
    argv = [a.format(tmp=tmp_path) for a in argv]
    line = one_line_error(capsys, *argv)
    assert "must end in .h5, .hdf5, .hdf, .he5: the command writes HDF5" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.txt"]


def test_hdf5_suffixes_are_accepted(tmp_path, capsys):
    status, _, err = run(capsys, *SIM, "--rays", "400", "-o", str(tmp_path / "x.HDF5"))
    assert status == 0, err
    assert load(tmp_path / "x.HDF5").quantity == "f_cos"


def test_simulate_quantity_f_is_refused_with_the_reason(tmp_path, capsys):
    line = one_line_error(capsys, *SIM, "--quantity", "f", "-o", str(tmp_path / "x.h5"))
    assert "argument --quantity: simulate supports only f_cos, got 'f': Westin's estimator" in line
    status, _, err = run(capsys, *SIM, "--quantity", "f_cos", "--rays", "400", "-o",
                         str(tmp_path / "x.h5"))
    assert status == 0, err


def test_checkpoint_interval(tmp_path, capsys, monkeypatch):
    import project.microgeometry as mg

    line = one_line_error(capsys, *SIM, "--checkpoint-interval", "5", "-o",
                          str(tmp_path / "x.h5"))
    assert "--checkpoint-interval applies with --checkpoint PATH" in line
    line = one_line_error(capsys, *SIM, "--checkpoint-interval", "0", "-o",
                          str(tmp_path / "x.h5"))
    assert "argument --checkpoint-interval: must be a positive number, got '0'" in line
    seen, real = [], mg.simulate

    def spy(*args, **kw):
        seen.append(kw["checkpoint_interval"])
        return real(*args, **kw)

    monkeypatch.setattr(mg, "simulate", spy)
    for extra, want in [([], 60.0), (["--checkpoint-interval", "2.5"], 2.5)]:
        status, _, err = run(capsys, *SIM, "--rays", "400", "--checkpoint",
                             str(tmp_path / "run.ckpt"), *extra, "-o", str(tmp_path / "x.h5"))
        assert status == 0, err
        assert seen[-1] == want


def test_fit_of_a_binary_file_names_it(tmp_path, capsys):
    table = tmp_path / "scan.bin"
    table.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    line = one_line_error(capsys, "fit", str(table), "-o", str(tmp_path / "x.h5"))
    assert f"TABLE '{table}' is not a text table: it holds the byte 0x89" in line
    table.write_text("10 0 20 0 0.1\n10 0 95 0 0.1\n")
    line = one_line_error(capsys, "fit", str(table), "-o", str(tmp_path / "x.h5"))
    assert f"TABLE '{table}': line 2: theta_o must lie in [0, 90] degrees, got 95" in line


def test_study_small_without_stability_is_refused_and_leaves_no_folder(tmp_path, capsys):
    out = tmp_path / "D"
    line = one_line_error(capsys, "study", "--small", "--out", str(out))
    assert "--small applies to --stability" in line
    assert not out.exists()
    line = one_line_error(capsys, "study", "--out", str(out))  # no MODEL
    assert "give a MODEL" in line and not out.exists()
    line = one_line_error(capsys, "study", "Glossy", "--out", str(out))
    assert "MODEL must be one of" in line and not out.exists()


def test_study_failure_removes_the_folder_it_created(tmp_path, capsys, monkeypatch):
    import compress

    def boom(*args, **kw):
        raise ValueError("projection failed")

    monkeypatch.setattr(compress, "study", boom)
    out = tmp_path / "D"
    line = one_line_error(capsys, "study", "Lambert", "--param", "albedo=0.5", "--out", str(out))
    assert "projection failed" in line and not out.exists()
    out.mkdir()  # a folder the user made stays
    one_line_error(capsys, "study", "Lambert", "--param", "albedo=0.5", "--out", str(out))
    assert out.is_dir()


def test_simulate_checkpoint_in_use_and_damaged(tmp_path, capsys):
    from project.microgeometry import estimate

    ckpt = tmp_path / "run.ckpt"
    with estimate._locked(ckpt):  # private: the lock a running simulate holds
        line = one_line_error(capsys, *SIM, "--checkpoint", str(ckpt), "-o",
                              str(tmp_path / "x.h5"))
    assert f"checkpoint '{ckpt}' is in use by another run (process " in line
    ckpt.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))
    line = one_line_error(capsys, *SIM, "--resume", str(ckpt), "-o", str(tmp_path / "x.h5"))
    assert f"resume file '{ckpt}' is not a readable HDF5 checkpoint" in line


_CLI_RUN = """
import sys
from pathlib import Path
from compress.cli import main
from project.microgeometry import estimate
real, count = estimate._chunk, []
def chunk(*args):
    real(*args)
    count.append(1)
    if len(count) == 3:
        Path(sys.argv[1]).write_text("3 chunks")
estimate._chunk = chunk
sys.exit(main(sys.argv[2:]))
"""


def _default_sigint() -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.parametrize("sig, code, word", [(15, 143, "terminated (SIGTERM)"),
                                             (2, 130, "interrupted")], ids=["TERM", "INT"])
def test_simulate_signal_saves_a_final_checkpoint(tmp_path, sig, code, word):
    import signal
    import time
    from pathlib import Path

    ckpt, flag = tmp_path / "run.ckpt", tmp_path / "flag"
    argv = [*SIM, "--rays", "1e9", "--checkpoint", str(ckpt), "--checkpoint-interval", "3600",
            "-o", str(tmp_path / "x.h5")]
    root = Path(__file__).resolve().parents[3]
    # a shell that starts the suite in the background hands its children SIGINT ignored;
    # the child restores the default, as a program started in a terminal has it
    with subprocess.Popen([sys.executable, "-c", _CLI_RUN, str(flag), *argv], cwd=root,
                          preexec_fn=_default_sigint,
                          stderr=subprocess.PIPE, text=True) as proc:
        try:
            deadline = time.time() + 120
            while not flag.exists() and proc.poll() is None and time.time() < deadline:
                time.sleep(0.05)
            assert flag.exists(), proc.stderr.read() if proc.poll() is not None else "timeout"
            proc.send_signal(signal.Signals(sig))
            assert proc.wait(60) == code
            err = proc.stderr.read()
        finally:
            if proc.poll() is None:
                proc.kill()
    assert err.strip() == (f"scatmodes simulate: {word}; the rays traced so far are saved in "
                           f"'{ckpt}': continue with --resume {ckpt} --checkpoint {ckpt}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flag", "run.ckpt"]
    import h5py

    with h5py.File(ckpt, "r") as f:
        # the flag is written inside the third chunk of 4096 directions x 8 rays
        assert f["rays"][()] >= 2 * 32768 and f["rays"][()] % 32768 == 0


def test_study_dask_options(tmp_path, capsys):
    """--workers/--scheduler are for the stability atlas; a bad scheduler is one line."""
    line = one_line_error(capsys, "study", "Lambert", "--workers", "2", "--out",
                          str(tmp_path / "s"))
    assert "--workers and --scheduler apply to --stability" in line
    pytest.importorskip("distributed")
    line = one_line_error(capsys, "study", "--stability", "--small", "--scheduler",
                          "tcp://127.0.0.1:9", "--out", str(tmp_path / "t"))
    assert "cannot connect" in line


# -- measurement files: fit and convert --------------------------------------------------------
BSDF = Path(__file__).resolve().parents[2] / "data" / "paper_white_rgb.bsdf"
#: Lambert + GGX (Schlick Fresnel) of the synthetic measurements, at 450, 550 and 650 nm.
GGX = {"kd": [0.5, 0.4, 0.3], "ks": [0.6, 0.6, 0.6], "alpha": 0.3, "f0": 0.5}


@pytest.fixture
def ggx_samples(rng):
    """300 exact samples of FittedModel("lambert+ggx", GGX) at random pairs, theta < 78 deg."""
    from basis import from_angles
    from project import FittedModel, Measurements

    n = 300
    wi = from_angles(np.arccos(rng.uniform(0.2, 1.0, n)), rng.uniform(0, 2 * np.pi, n))
    wo = from_angles(np.arccos(rng.uniform(0.2, 1.0, n)), rng.uniform(0, 2 * np.pi, n))
    values = FittedModel("lambert+ggx", GGX).eval(wi, wo)
    return Measurements(wi, wo, values, wavelengths=[450.0, 550.0, 650.0], isotropic=True,
                        name="ggx")


def write(tmp_path, meas, fmt, name="ggx"):
    """Write ``meas`` as csv (.csv), table (.txt, no wavelengths) or cornell (.brdf)."""
    from project import Measurements
    from project.measured import write_measurements

    suffix = {"csv": ".csv", "table": ".txt", "cornell": ".brdf"}[fmt]
    if fmt == "table":
        meas = Measurements(meas.wi, meas.wo, meas.values, isotropic=meas.isotropic)
    return write_measurements(tmp_path / f"{name}{suffix}", meas, fmt)


def test_fit_options_match_the_library():
    from compress.cli import commands
    from project.fitting import FAMILIES
    from project.measured import MERL_SHAPE
    from project.measured.tables import ANGLE_UNITS, MEASUREMENT_FORMATS

    # the tabulated families need a BRDF that can be evaluated anywhere, not samples
    assert commands._FIT_FAMILIES == tuple(f for f in FAMILIES
                                           if f not in ("factored", "tabulated", "tucker", "grid"))
    assert commands._FIT_FORMATS == MEASUREMENT_FORMATS
    assert commands._FIT_ANGLES == ANGLE_UNITS
    assert commands._MERL_HEADER == np.array(MERL_SHAPE[1:], dtype="<i4").tobytes()


@pytest.mark.parametrize("fmt", ["csv", "table", "cornell"])
def test_fit_reads_each_format(tmp_path, capsys, ggx_samples, fmt):
    from basis import HemiZernike
    from project import fit

    path = write(tmp_path, ggx_samples, fmt)
    status, out, err = run(capsys, "fit", str(path), "--order", "3", "-o",
                           str(tmp_path / "f.h5"))
    assert status == 0, err
    assert f"({fmt} format, by " in out and "300 samples" in out
    assert re.search(r"validation error [0-9.e-]+ % \(relative RMS at held-out pairs\), "
                     r"[0-9.e-]+ % for a Lambertian fit", out)
    cm = load(tmp_path / "f.h5")
    assert cm.channels == 3 and cm.info["source"] == f"fit to {path.name}"
    # the library on the same samples: values round-trip exactly, the directions to a few
    # ulp (rebuilt from the written angles); the condition number is ~5
    ref = fit(ggx_samples, HemiZernike(3))
    np.testing.assert_allclose(cm.matrix, ref.matrix, rtol=0, atol=1e-12)


def test_fit_wavelengths_and_channels(tmp_path, capsys, ggx_samples):
    from basis import HemiZernike
    from project import fit

    path = write(tmp_path, ggx_samples, "cornell")
    status, out, err = run(capsys, "fit", str(path), "--wavelengths", "500,600", "--order",
                           "2", "--regularization", "0", "-o", str(tmp_path / "w.h5"))
    assert status == 0, err
    cm = load(tmp_path / "w.h5")
    assert cm.channels == 2
    # linear interpolation halfway between measured channels, then the same plain fit
    ref = fit(ggx_samples.at_wavelengths([500.0, 600.0]), HemiZernike(2), regularization=0)
    np.testing.assert_allclose(cm.matrix, ref.matrix, rtol=0, atol=1e-12)
    status, _, err = run(capsys, "fit", str(path), "--channels", "650 nm", "--order", "2",
                         "--regularization", "0", "-o", str(tmp_path / "c.h5"))
    assert status == 0, err
    one = load(tmp_path / "c.h5")
    full = fit(ggx_samples, HemiZernike(2), regularization=0)  # channels solved apart
    assert one.channels == 1
    np.testing.assert_allclose(np.squeeze(one.matrix), full.matrix[2], rtol=0, atol=1e-12)


def test_fit_model_recovers_lambert_ggx(tmp_path, capsys, ggx_samples):
    from project import FittedModel

    path = write(tmp_path, ggx_samples, "csv")
    out_h5 = tmp_path / "m.h5"
    status, out, err = run(capsys, "fit", str(path), "--wavelengths", "450,550,650",
                           "--model", "lambert+ggx", "--restarts", "1", "--folds", "3", "-o",
                           str(out_h5))
    assert status == 0 and err == "", err
    assert "FittedModel('lambert+ggx'" in out and "8 parameters (64 bytes stored as float64)" in out
    got = re.search(r"cross-validated l2 error ([0-9.e+-]+) \+- ([0-9.e+-]+) \(3-fold CV", out)
    assert got, out
    model = load(out_h5)
    assert isinstance(model, FittedModel) and model.family == "lambert+ggx"
    assert float(got[1]) == pytest.approx(model.info["l2"], rel=1e-2)  # printed to 3 digits
    assert float(got[2]) == pytest.approx(model.info["l2_stderr"], rel=1e-2)
    # exact samples of the family: the fit reaches l2 ~1e-9 and the parameters to ~1e-7
    # (observed); 1e-5 leaves room for the optimizer's stopping tolerance
    for name, value in GGX.items():
        np.testing.assert_allclose(model.params[name], value, rtol=1e-5, atol=0,
                                   err_msg=name)
    assert model.info["l2"] < 1e-6


def test_fit_warnings_reach_stderr(tmp_path, capsys, rng):
    from basis import from_angles
    from project import Measurements

    n = 200  # pure noise: nothing predicts held-out samples better than zero
    wi = from_angles(np.arccos(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n))
    wo = from_angles(np.arccos(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n))
    path = write(tmp_path, Measurements(wi, wo, rng.normal(0.0, 1.0, n)), "csv", "noise")
    status, _, err = run(capsys, "fit", str(path), "--order", "2", "-o", str(tmp_path / "a.h5"))
    assert status == 0
    assert "scatmodes fit: warning: fit predicts held-out samples no better than zero" in err
    # values < 0 everywhere: a model >= 0 is at best as far from them as zero is (l2 >= 1)
    path = write(tmp_path, Measurements(wi, wo, -0.1 - np.abs(rng.normal(0.0, 1.0, n))), "csv",
                 "negative")
    status, _, err = run(capsys, "fit", str(path), "--model", "lambert+ggx", "--restarts", "1",
                         "--folds", "3", "-o", str(tmp_path / "b.h5"))
    assert status == 0
    assert "scatmodes fit: warning: fit_model('lambert+ggx') predicts the held-out" in err


def test_convert_rgl(tmp_path, capsys):
    from basis import from_angles
    from project.measured import read_rgl

    status, out, err = run(capsys, "convert", str(BSDF), "--order", "2", "-o",
                           str(tmp_path / "paper.h5"))
    assert status == 0 and err == "", err
    assert out.startswith(f"wrote {tmp_path / 'paper.h5'}: RGLBRDF(name='paper_white_rgb'")
    assert "quantity f_cos" in out  # auto: f grows like 1 / cos(theta_o) at grazing angles
    cm = load(tmp_path / "paper.h5")
    assert cm.quantity == "f_cos" and cm.channels == 3
    # albedo at normal incidence against a product Gauss rule over w_o (64 x 128 nodes; 256 x
    # 512 agrees to 6e-6): the order-2 expansion is 0.8 % off (observed 0.0083)
    x, w = np.polynomial.legendre.leggauss(64)
    mu, phi = 0.5 * (x + 1.0), (np.arange(128) + 0.5) * np.pi / 64
    wo = from_angles(np.arccos(np.repeat(mu, 128)), np.tile(phi, 64))
    wi = np.broadcast_to([0.0, 0.0, 1.0], wo.shape)
    f = read_rgl(BSDF).eval(wi, wo)
    albedo = (f * (np.repeat(0.5 * w * mu, 128) * np.pi / 64)[:, None]).sum(axis=0)
    np.testing.assert_allclose(cm.albedo([0.0, 0.0, 1.0]), albedo, rtol=0, atol=0.015)


def test_convert_mbsdf(tmp_path, capsys):
    # a constant table: the MDL SDK's lookup returns 0.3 / pi everywhere, albedo 0.3
    path = write_mbsdf(Lambert(0.3), tmp_path / "grey.mbsdf", resolution=(6, 12))
    status, out, err = run(capsys, "convert", str(path), "--order", "2", "-o",
                           str(tmp_path / "grey.h5"))
    assert status == 0 and err == "", err
    assert out.startswith(f"wrote {tmp_path / 'grey.h5'}: MBSDFBRDF(name='grey'")
    cm = load(tmp_path / "grey.h5")
    assert cm.quantity == "f_cos" and cm.channels == 1
    # f cos cos of a Lambert BRDF is in every hemisphere basis of order >= 1; the projection's
    # quadrature tolerance is 1e-3 (--tol default)
    np.testing.assert_allclose(cm.albedo([0.0, 0.0, 1.0]), 0.3, rtol=0, atol=1e-3)


def test_mbsdf_fifo_does_not_block(tmp_path, capsys):
    fifo = tmp_path / "pipe.mbsdf"
    os.mkfifo(fifo)
    line = one_line_error(capsys, "convert", str(fifo), "-o", str(tmp_path / "x.h5"))
    assert "must be a regular file" in line


def test_convert_measurements_is_the_fit(tmp_path, capsys, ggx_samples):
    path = write(tmp_path, ggx_samples, "cornell")
    status, out, err = run(capsys, "convert", str(path), "--order", "2", "-o",
                           str(tmp_path / "c.h5"))
    assert status == 0, err
    assert "measurements: fitted by least squares as 'scatmodes fit' does" in out
    status, _, err = run(capsys, "fit", str(path), "--order", "2", "-o", str(tmp_path / "f.h5"))
    assert status == 0, err
    c, f = load(tmp_path / "c.h5"), load(tmp_path / "f.h5")
    assert c.quantity == "f"  # convert's auto is fit's default
    np.testing.assert_array_equal(c.matrix, f.matrix)


@pytest.mark.parametrize("argv, match", [
    (["fit", "{tmp}/foreign.csv"], "TABLE '{tmp}/foreign.csv': line 1: the header must name "
                                   "the angle columns theta_i, phi_i, theta_o, phi_o"),
    (["fit", "{bsdf}"], "TABLE '{bsdf}' is an RGL-EPFL .bsdf file, a BRDF that can be "
                        "evaluated anywhere rather than scattered measurements: project it "
                        "with 'scatmodes convert {bsdf} -o OUT.h5'"),
    (["fit", "{tmp}/m.binary"], "TABLE '{tmp}/m.binary' is a MERL .binary file"),
    (["fit", "{tmp}/saved.h5"], "TABLE '{tmp}/saved.h5' is an HDF5 file, not measurements"),
    (["fit", "{tmp}/ggx.csv", "--format", "xml"],
     "argument --format: invalid choice: 'xml' (choose from 'auto', 'table', 'csv', "
     "'cornell')"),
    (["fit", "{tmp}/ggx.csv", "--format", "table"],
     "TABLE '{tmp}/ggx.csv': line 4, column 1: cell must be a number"),
    (["fit", "{tmp}/ggx.brdf", "--angles", "degrees"],
     "the Cornell format holds angles in radians, got angles='degrees'"),
    (["fit", "{tmp}/ggx.csv", "--angles", "grads"], "argument --angles: invalid choice"),
    (["fit", "{tmp}/ggx.csv", "--wavelengths", "400,500"],
     "--wavelengths must lie within the measured range [450, 650] nm of TABLE "
     "'{tmp}/ggx.csv' (no extrapolation), got 400"),
    (["fit", "{tmp}/ggx.csv", "--wavelengths", "550,700"], "got 700"),
    (["fit", "{tmp}/ggx.csv", "--wavelengths", "550,500"],
     "argument --wavelengths: must be comma-separated wavelengths in nm, > 0 and increasing"),
    (["fit", "{tmp}/ggx.txt", "--wavelengths", "500"],
     "--wavelengths needs spectral data: TABLE '{tmp}/ggx.txt' holds the channels R, G, B "
     "without wavelengths"),
    (["fit", "{tmp}/ggx.csv", "--channels", "X"],
     "--channels: channels must be indices or names among ['450 nm', '550 nm', '650 nm'], "
     "got 'X'"),
    (["fit", "{tmp}/ggx.csv", "--channels", "0,"], "argument --channels: must be "
                                                   "comma-separated channel names or indices"),
    (["fit", "{tmp}/ggx.csv", "--model", "factored"],
     "argument --model: 'factored' cannot be fitted to measurements: it tabulates a BRDF on "
     "a dense rule"),
    (["fit", "{tmp}/ggx.csv", "--model", "phong"],
     "argument --model: must be one of lambert+ggx, lambert+beckmann, lafortune, dsbrdf, "
     "rr8807, got 'phong'"),
    (["fit", "{tmp}/ggx.csv", "--restarts", "2", "--folds", "3"],
     "--restarts, --folds apply to --model FAMILY"),
    (["fit", "{tmp}/ggx.csv", "--model", "lambert+ggx", "--order", "4"],
     "--order applies to the modal fit (a coefficient matrix), not to --model lambert+ggx"),
    (["fit", "{tmp}/ggx.csv", "--model", "lambert+ggx", "--lobes", "2"],
     "--lobes applies to --model lafortune and dsbrdf, not to lambert+ggx"),
    (["convert", "{tmp}/none.bsdf"], "RGL file '{tmp}/none.bsdf' does not exist"),
    (["convert", "{tmp}/none.csv"], "measurement file '{tmp}/none.csv' does not exist"),
    (["convert", "{tmp}/bad.bsdf"], "RGL file '{tmp}/bad.bsdf': the required field"),
    (["convert", "{tmp}/scan.png"], "FILE '{tmp}/scan.png' is neither a MERL .binary, an RGL "
                                    ".bsdf, an MDL .mbsdf nor a measurement text file: it holds "
                                    "the byte 0x89"),
    (["convert", "{tmp}/bad.mbsdf"], "MBSDF file '{tmp}/bad.mbsdf' must start with the line "
                                     "'NVIDIA ARC MBSDF V1'"),
    (["convert", "{tmp}/none.mbsdf"], "MBSDF file '{tmp}/none.mbsdf' does not exist"),
    (["fit", "{tmp}/bad.mbsdf"], "TABLE '{tmp}/bad.mbsdf' is an NVIDIA MDL .mbsdf file, a BRDF "
                                 "that can be evaluated anywhere"),
    (["convert", "{tmp}/foreign.csv"], "FILE '{tmp}/foreign.csv': line 1: the header must "
                                       "name the angle columns"),
    (["convert", "{tmp}/saved.h5"], "FILE '{tmp}/saved.h5' is an HDF5 file, not a BRDF or "
                                    "measurements to convert"),
    (["convert", "{tmp}/ggx.csv", "--tol", "1e-4"],
     "--tol and --method apply to projecting a MERL, RGL or MBSDF file"),
])
def test_measurement_file_errors(tmp_path, capsys, ggx_samples, argv, match):
    for fmt in ("csv", "table", "cornell"):
        write(tmp_path, ggx_samples, fmt)
    (tmp_path / "foreign.csv").write_text("a,b\n1,2\n")
    (tmp_path / "m.binary").write_bytes(b"\x00" * 12)
    (tmp_path / "saved.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(64))
    (tmp_path / "bad.bsdf").write_bytes(b"tensor_file\x00\x01\x00" + bytes(4))
    (tmp_path / "scan.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    (tmp_path / "bad.mbsdf").write_bytes(b"NVIDIA ARC MBSDF V2\n")
    argv = [a.format(tmp=tmp_path, bsdf=BSDF) for a in argv]
    line = one_line_error(capsys, *argv, "-o", str(tmp_path / "x.h5"))
    assert match.format(tmp=tmp_path, bsdf=BSDF) in line
    assert not (tmp_path / "x.h5").exists()


# -- export ------------------------------------------------------------------------------------

def test_export_mbsdf_reads_back_at_texel_centres(tmp_path, capsys):
    """scatmodes export writes what project.measured.write_mbsdf writes: read back, the
    file returns the saved model's values at the texel centres (float32 rounding)."""
    from compress import save
    from project import FittedModel
    from project.measured import read_mbsdf
    from project.measured.mbsdf import texel_centres

    model = FittedModel("lambert+ggx", {"kd": [0.3, 0.2, 0.1], "ks": [0.5, 0.5, 0.5],
                                        "alpha": 0.3, "f0": 0.04})
    src = save(model, tmp_path / "m.h5")
    out = tmp_path / "m.mbsdf"
    status, text, err = run(capsys, "export", str(src), "--format", "mbsdf", "--resolution",
                            "6,8", "-o", str(out))
    assert status == 0, err
    assert f"wrote {out}" in text and "mbsdf 6 x 6 x 8, 3 channels" in text
    back = read_mbsdf(out)
    assert back.resolution == (6, 8)
    from basis import from_angles

    theta, dphi = texel_centres((6, 8))
    ti, to, dp = np.meshgrid(theta, theta, dphi, indexing="ij")
    wi, wo = from_angles(ti.ravel(), 0.0), from_angles(to.ravel(), dp.ravel())
    np.testing.assert_allclose(back.eval(wi, wo), model.eval(wi, wo), rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("args, match", [
    (["--resolution", "4"], "--resolution must be two integers"),
    (["--resolution", "a,b"], "--resolution must be two integers"),
    (["--resolution", "0,8"], "resolution"),
])
def test_export_bad_arguments(tmp_path, capsys, args, match):
    from compress import save
    from project import FittedModel

    src = save(FittedModel("lambert+ggx", {"kd": [0.3], "ks": [0.5], "alpha": 0.3,
                                           "f0": 0.04}), tmp_path / "m.h5")
    line = one_line_error(capsys, "export", str(src), "--format", "mbsdf", *args, "-o",
                          str(tmp_path / "x.mbsdf"))
    assert re.search(match, line)
    assert not (tmp_path / "x.mbsdf").exists()
