"""compress.report: the self-contained HTML page, checked as text and in a real browser.

References: closed forms (a Lambertian lobe scaled by 1.1 has relative L2 error 0.1 in q,
in every band of angles, and image error 0.1; a matrix whose every value is negative is
negative on all of H x H), Parseval (the rounding error of a matrix stored as float16,
which :func:`compress.precision` computes exactly in coefficient space, against the page's
Monte Carlo estimate on peak-resolving pairs), Pillow (every figure decodes as a PNG) and
headless Chromium (the page loads without console errors, every image decodes, the text
holds the numbers recorded in the file, the screenshot is not blank).
"""

from __future__ import annotations

import base64
import io
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import compress
import project
from basis import CoefficientMatrix, HemiZernike
from compress.report import _band_errors, read_source, report
from project.measured import write_measurements, write_merl
from project.models import CookTorrance, Lambert

PAPER = Path(__file__).parents[1] / "data" / "paper_white_rgb.bsdf"
SURROGATE_TOOL = Path(__file__).parents[3] / "shared" / "tools" / "merl_surrogate.py"
SURROGATE_ZIP = Path(__file__).parents[3] / "shared" / "data" / "merl_nbrdf.zip"
CT = CookTorrance([0.3, 0.2, 0.1], 0.3, "ggx", ior=1.5)


def images(page: str) -> list[tuple[str, bytes]]:
    """(alt, PNG bytes) of every <img> of the page."""
    out = []
    for tag in re.findall(r"<img [^>]*>", page):
        src = re.search(r'src="data:image/png;base64,([^"]+)"', tag)
        alt = re.search(r'alt="([^"]*)"', tag)
        assert src is not None, f"an image that is not an inline PNG: {tag[:80]}"
        out.append(("" if alt is None else alt.group(1), base64.b64decode(src.group(1))))
    return out


@pytest.fixture(scope="module")
def selected(tmp_path_factory):
    """A select result (info with candidates, bytes and errors), saved and its path."""
    rep = compress.select(CT, 0.06, error_n=4096, candidates=[
        {"form": "model", "family": "lambert+ggx", "restarts": 1},
        {"form": "modal", "kind": "zernike", "order": 4}])
    path = tmp_path_factory.mktemp("report") / "ct.h5"
    compress.save(rep, path)
    return path


@pytest.fixture(scope="module")
def selected_page(selected):
    return report(selected, CT)


# -- reading ----------------------------------------------------------------------------------
def test_read_source_reads_every_kind(tmp_path, selected):
    assert read_source(selected).family == "lambert+ggx"
    merl = write_merl(tmp_path / "matte.binary", Lambert(0.5))
    assert type(read_source(merl)).__name__ == "MERLBRDF"
    assert type(read_source(PAPER)).__name__ == "RGLBRDF"
    meas = project.Measurements([[0.0, 0.0, 1.0]], [[0.6, 0.0, 0.8]], [[0.1, 0.2, 0.3]])
    back = read_source(write_measurements(tmp_path / "m.csv", meas))
    assert isinstance(back, project.Measurements) and len(back) == 1


def test_read_source_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_source(tmp_path / "missing.h5")
    with pytest.raises(IsADirectoryError, match="must be a file, got the directory"):
        read_source(tmp_path)
    junk = tmp_path / "junk.txt"
    junk.write_text("hello world\n")
    with pytest.raises(ValueError, match=r"is not a file of compress.save .* read as a "
                                         r"measurement table"):
        read_source(junk)
    fake = tmp_path / "fake.h5"
    fake.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 64)
    with pytest.raises(ValueError, match="damaged or truncated HDF5"):
        read_source(fake)


# -- the page as text -------------------------------------------------------------------------
def test_page_is_self_contained_and_every_figure_decodes(selected_page):
    page = selected_page
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")
    # nothing to fetch: no external URL in any src or href, no script at all
    assert not re.search(r'(src|href)="(https?:)?//', page)
    assert "<script" not in page and "@media print" in page
    for title in ("1. Summary", "2. Lobes", "3. Spheres",
                  "4. Where the error lives", "5. Resolution against error"):
        assert f"<h2>{title}</h2>" in page, title
    imgs = images(page)
    assert len(imgs) == 5  # lobes (2), spheres, error by band, chart
    for alt, png in imgs:
        assert len(alt) > 20  # a sentence, not a placeholder
        with Image.open(io.BytesIO(png)) as im:
            im.load()
            assert im.format == "PNG" and min(im.size) > 100


def test_page_holds_the_recorded_numbers(selected, selected_page):
    info = compress.load(selected).info
    assert f"{info['bytes']:,}" in selected_page
    sel = info["selected"]
    assert f"l2 {sel['l2']:.4g}" in selected_page  # the provenance row of the selection
    for row in info["candidates"]:
        if row["status"] == "measured":
            assert f"{row['l2']:.4g}" in selected_page  # the table of section 5
    # the file's header and the family
    assert "file schema_version" in selected_page and "lambert+ggx" in selected_page


def test_errors_against_a_reference_are_the_closed_forms():
    # f_hat = 1.1 f: relative L2 of q is 0.1 exactly, with zero spread over the replicates
    # (up to float64 rounding, ~1e-16); the pictures scale by 1.1 too, so the image error
    # is 0.1 (to rounding); printed to 4 digits
    page = report(Lambert([0.3, 0.4, 0.5]), Lambert([0.3 / 1.1, 0.4 / 1.1, 0.5 / 1.1]),
                  table=False)
    row = re.search(r"<td>l2 error against the reference</td><td>(\S+) \+- (\S+) ", page)
    assert row is not None and row.group(1) == "0.1" and float(row.group(2)) < 1e-12
    assert re.search(r"Image error .*<strong>0\.1</strong>", page)


def test_band_errors_closed_form(unit_vectors):
    # a uniform 10 % excess is 10 % in every band; the shares sum to 1 (float64 rounding)
    wi = unit_vectors(4000, upper=True)
    wo = unit_vectors(4000, upper=True)
    f = np.full((4000, 2), 0.3)
    share, rel = _band_errors(wi, wo, np.ones(4000), f, 1.1 * f,
                              np.radians([0, 30, 60, 90]))
    assert np.allclose(rel, 0.1, rtol=1e-12, atol=0)
    assert share.sum() == pytest.approx(1.0, rel=1e-12)


def test_storage_precision_rows_match_parseval():
    # quantity f_cos: the relative L2 change of q is the Frobenius change of the matrix
    # (Parseval), which compress.precision computes exactly; the page estimates it on
    # 2**15 peak-resolving pairs, whose Monte Carlo error on a smooth function is a few
    # per cent: 10 % tolerance
    cm = project.project(Lambert([0.2, 0.5, 0.7]), HemiZernike(4), quantity="f_cos")
    rng = np.random.default_rng(3)
    m = cm.matrix + 1e-3 * rng.standard_normal(cm.matrix.shape)
    cm = CoefficientMatrix(cm.basis, m, quantity="f_cos", symmetrize=True)
    page = report(cm, table=False)
    exact = compress.precision(cm, "float16").info["precision"]
    row = re.search(r"<td>float16</td><td>([0-9,]+)</td><td>([0-9.e+-]+)</td>", page)
    assert row is not None
    assert int(row.group(1).replace(",", "")) == exact["bytes"]
    assert float(row.group(2)) == pytest.approx(exact["error"], rel=0.1)


def test_negative_fraction_of_a_negative_expansion():
    # q = -(const) on all of H x H: negative everywhere, fraction 1 exactly
    b = HemiZernike(2)
    m = np.zeros((b.size, b.size))
    m[0, 0] = -1.0
    page = report(CoefficientMatrix(b, m, quantity="f_cos"), table=False)
    assert "negative in some channel: <strong>1</strong>" in page


def test_measurements_show_the_fit_and_its_residuals(tmp_path):
    rng = np.random.default_rng(1)
    ti = np.repeat(np.radians([0.0, 30.0, 60.0]), 80)
    wi = np.stack([np.sin(ti), np.zeros_like(ti), np.cos(ti)], axis=1)
    wo = rng.normal(size=(ti.size, 3))
    wo[:, 2] = np.abs(wo[:, 2])
    wo /= np.linalg.norm(wo, axis=1)[:, None]
    meas = project.Measurements(wi, wo, CT.eval(wi, wo), isotropic=True, name="ct")
    path = write_measurements(tmp_path / "ct.csv", meas)
    page = report(path, table=False)
    assert "<h2>6. Measurements</h2>" in page and "lambert+ggx" in page
    assert "240 x 3 channel(s)" in page


def test_written_atomically_and_bad_paths(tmp_path):
    out = tmp_path / "r.html"
    assert report(Lambert(0.5), path=out, table=False) == out
    assert out.read_text(encoding="utf-8").startswith("<!DOCTYPE html>")
    with pytest.raises(ValueError, match="directory .* does not exist"):
        report(Lambert(0.5), path=tmp_path / "no" / "r.html")
    junk = tmp_path / "junk.txt"
    junk.write_text("not a measurement\n")
    with pytest.raises(ValueError, match="is not a file of compress.save"):
        report(junk, path=tmp_path / "bad.html")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.txt", "r.html"]


def test_type_errors():
    with pytest.raises(TypeError, match="rep must be a coefficient matrix"):
        report(42)
    with pytest.raises(TypeError, match="reference must be a coefficient matrix"):
        report(Lambert(0.5), reference=[1, 2])


def test_benchmark_writes_one_report_per_material(tmp_path):
    from compress.benchmark import benchmark_merl

    folder = tmp_path / "in"
    folder.mkdir()
    write_merl(folder / "matte.binary", Lambert([0.2, 0.4, 0.6]))
    benchmark_merl(folder, tmp_path / "out", workers=1, tols=(0.05,), error_n=4096,
                   candidates=[{"form": "modal", "kind": "zernike", "order": 2}])
    page = (tmp_path / "out" / "materials" / "matte.html").read_text(encoding="utf-8")
    record = json.loads((tmp_path / "out" / "materials" / "matte.json").read_text())
    assert f"{record['row']['bytes_0.05']:,}" in page
    assert "compared with matte (measured BRDF (MERL table))" in page


# -- a MERL table (the shared surrogate tool) -------------------------------------------------
@pytest.fixture(scope="module")
def merl_file(tmp_path_factory):
    if not SURROGATE_TOOL.is_file() or not SURROGATE_ZIP.is_file():
        pytest.skip(f"MERL surrogate tool or data not found ({SURROGATE_TOOL}): ../shared "
                    "is absent")
    out = tmp_path_factory.mktemp("merl")
    proc = subprocess.run([sys.executable, str(SURROGATE_TOOL), "blue-acrylic", "-o", str(out)],
                          capture_output=True, text=True, timeout=600, check=False)
    if proc.returncode != 0:
        pytest.fail(f"merl_surrogate.py failed:\n{proc.stderr}")
    return out / "blue-acrylic.binary"


def test_merl_table_report(merl_file, tmp_path):
    out = report(merl_file, path=tmp_path / "blue.html")
    page = out.read_text(encoding="utf-8")
    assert "measured BRDF (MERL table)" in page
    assert f"{merl_file.stat().st_size:,} bytes on disk" in page
    assert "A small table computed for this page" in page
    assert len(images(page)) == 4  # lobes (2), spheres, chart: no reference, no expansion


# -- in a real browser (the fixture `browser` of tests/conftest.py) ---------------------------
def test_report_in_a_real_browser(browser, selected, tmp_path):
    out = report(selected, CT, tmp_path / "ct.html")
    for domain in ("Page", "Runtime", "Log"):
        browser.page(f"{domain}.enable")
    # a laptop screen
    browser.page("Emulation.setDeviceMetricsOverride", width=1366, height=768,
                 deviceScaleFactor=1, mobile=False)
    browser.page("Page.navigate", url=out.resolve().as_uri())
    browser.wait("Page.loadEventFired")

    def js(expr: str):
        return browser.page("Runtime.evaluate", expression=expr,
                            returnByValue=True)["result"]["value"]

    imgs = js("Array.from(document.images).map(i => [i.complete, i.naturalWidth, i.alt])")
    assert len(imgs) == 5  # lobes (2), spheres, error by band, chart
    assert all(done and width > 0 and alt for done, width, alt in imgs), imgs
    text = js("document.body.innerText")
    info = compress.load(selected).info
    assert f"{info['bytes']:,}" in text and f"{info['selected']['l2']:.4g}" in text
    assert js("document.documentElement.scrollWidth <= window.innerWidth")  # no sideways scroll
    shot = base64.b64decode(browser.page("Page.captureScreenshot", format="png")["data"])
    (tmp_path / "ct.png").write_bytes(shot)
    with Image.open(io.BytesIO(shot)) as im:
        pixels = np.asarray(im.convert("L"), dtype=float)
    # a blank page has variance 0; text and figures on white give hundreds (8-bit grey)
    assert pixels.shape == (768, 1366) and pixels.var() > 100.0
    pdf = base64.b64decode(browser.page("Page.printToPDF")["data"])  # the print style
    assert pdf.startswith(b"%PDF") and len(pdf) > 10_000
    assert browser.errors() == []


def test_tucker_file_report(tmp_path):
    """A saved Tucker tensor (float16) reads back and gets its page: its family, ranks and
    stored bytes, and its l2 against the source it was fitted to, as measured by the fit
    (independent pairs, to two digits: the page's pairs are others)."""
    from project.tucker import fit_tucker

    t = fit_tucker(CT, budget=400, grid=(64, 16, 32), phi_turn="full")
    m = project.FittedModel("tucker", t.params, info=dict(t.info))
    path = compress.save(m, tmp_path / "t.h5", dtype="float16")
    page = report(path, CT, table=False)
    assert "<td>family</td><td>FittedModel(&#x27;tucker&#x27;, knots=" in page
    assert f"<td>float16</td><td>{2 * m.nparams:,}</td>" in page  # the storage rows
    row = re.search(r"<td>l2 error against the reference</td><td>(\S+) \+- ", page)
    err = project.sampling.brdf_errors(CT, compress.load(path),
                                       project.sampling.peak_resolving_pairs(1 << 15, seed=3))
    assert row is not None and abs(float(row.group(1)) - err["l2"]) < 0.1 * err["l2"] + 2e-3


def test_spectral_table_is_shown_at_three_wavelengths(tmp_path):
    """A 31-wavelength table (a Cornell file's layout) is fitted and shown at the measured
    wavelengths nearest 450, 550 and 650 nm, and the page says so (a fit of all 31 channels,
    64 parameters and ten folds, took minutes on a 1,439-sample table; three take seconds)."""
    rng = np.random.default_rng(2)
    n = 300
    ti, to, po = rng.uniform(0, 1.3, n), rng.uniform(0, 1.3, n), rng.uniform(-3, 3, n)
    wi = np.stack([np.sin(ti), 0 * ti, np.cos(ti)], axis=1)
    wo = np.stack([np.sin(to) * np.cos(po), np.sin(to) * np.sin(po), np.cos(to)], axis=1)
    lam = np.linspace(400, 700, 31)
    model = CookTorrance(list(0.1 + 0.3 * np.exp(-((lam - 600) / 60) ** 2)), 0.2, "ggx")
    meas = project.Measurements(wi, wo, model.eval(wi, wo), wavelengths=lam, isotropic=True)
    path = write_measurements(tmp_path / "spectral.brdf", meas, format="cornell")
    page = report(path, table=False)
    assert "The file holds 31 channels; this page fits and shows 3 of them (450, 550, " \
           "650 nm)." in page
