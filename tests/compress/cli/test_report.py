"""``scatmodes report``: the page written from files, and one-line errors without a file.

References: the file written is the page :func:`compress.report.report` returns for the same
input (both start with the doctype and hold the same sections); the error lines are those
of :func:`compress.report.read_source` (pinned by their wording).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import compress
from basis import CoefficientMatrix, HemiZernike
from compress.cli import main

PAPER = Path(__file__).parents[2] / "data" / "paper_white_rgb.bsdf"


def run(capsys, *argv):
    """main(argv) -> (status, stdout, stderr)."""
    try:
        status = main(list(argv))
    except SystemExit as stop:
        status = stop.code
    out, err = capsys.readouterr()
    return status, out, err


def one_line_error(capsys, *argv) -> str:
    status, out, err = run(capsys, *argv)
    assert status == 2, err
    assert out == "" and "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("scatmodes report: error: "), lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A matrix of a constant q (one coefficient) with errors recorded in its info."""
    b = HemiZernike(2)
    m = np.zeros((b.size, b.size))
    m[0, 0] = 0.5
    cm = CoefficientMatrix(b, m, quantity="f_cos",
                           info={"source": "Lambert(0.5)", "l2": 0.012345, "log": 0.00321})
    path = tmp_path_factory.mktemp("cli") / "lambert.h5"
    return compress.save(cm, path)


def test_report_writes_the_page(capsys, saved, tmp_path):
    out = tmp_path / "lambert.html"
    status, text, err = run(capsys, "report", str(saved), "-o", str(out), "--no-table")
    assert status == 0, err
    assert text.startswith(f"wrote {out} (") and err == ""
    page = out.read_text(encoding="utf-8")
    assert page.startswith("<!DOCTYPE html>")
    for section in ("1. Summary", "2. Lobes", "3. Spheres", "4. Where the error lives"):
        assert f"<h2>{section}</h2>" in page
    assert "5. Resolution against error" not in page  # --no-table, and none in the file
    # the numbers recorded in the file, as the page prints them (4 significant digits)
    assert "0.01235" in page and "0.00321" in page and "Lambert(0.5)" in page


def test_report_with_a_reference_file(capsys, saved, tmp_path):
    out = tmp_path / "vs-paper.html"
    status, _, err = run(capsys, "report", str(saved), "--reference", str(PAPER), "-o",
                         str(out), "--no-table", "--title", "matte against paper")
    assert status == 0, err
    page = out.read_text(encoding="utf-8")
    assert "<h1>matte against paper</h1>" in page
    assert "compared with paper_white_rgb.bsdf" in page
    assert "l2 error against the reference" in page
    assert "reciprocity floor of the reference" in page


def test_nonsense_input_is_one_line_and_no_file(capsys, tmp_path):
    junk = tmp_path / "junk.dat"
    junk.write_text("this is not a BRDF\n")
    out = tmp_path / "junk.html"
    line = one_line_error(capsys, "report", str(junk), "-o", str(out))
    assert "is not a file of compress.save" in line
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["junk.dat"]


def test_missing_input_and_unwritable_output(capsys, saved, tmp_path):
    line = one_line_error(capsys, "report", str(tmp_path / "none.h5"), "-o",
                          str(tmp_path / "r.html"))
    assert "does not exist" in line
    line = one_line_error(capsys, "report", str(saved), "-o",
                          str(tmp_path / "missing" / "r.html"))
    assert "directory" in line and "does not exist" in line
    line = one_line_error(capsys, "report", str(saved), "--reference",
                          str(tmp_path / "nothing.binary"), "-o", str(tmp_path / "r.html"))
    assert "nothing.binary" in line and "does not exist" in line


def test_library_and_command_agree(capsys, saved, tmp_path):
    # the command writes what the library returns (up to the seconds in the lead line)
    out = tmp_path / "a.html"
    assert run(capsys, "report", str(saved), "-o", str(out), "--no-table")[0] == 0
    page = compress.report(saved, table=False)

    def body(text):
        return text.split("</p>", 1)[1]  # after the lead paragraph with the time

    assert body(out.read_text(encoding="utf-8")) == body(page)


def test_help_lists_examples(capsys):
    status, out, _ = run(capsys, "report", "--help")
    assert status == 0
    assert "scatmodes report blue-acrylic.binary -o blue.html" in out and "--reference" in out


def test_model_input_is_refused_with_a_hint(capsys, tmp_path):
    # INPUT is a file; an analytic model goes through the library (compress.report)
    line = one_line_error(capsys, "report", "Lambert", "-o", str(tmp_path / "r.html"))
    assert "'Lambert' does not exist" in line
