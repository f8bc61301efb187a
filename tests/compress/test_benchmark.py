"""compress.benchmark and ``scatmodes benchmark``: the benchmark on small folders.

References: MERL files written from analytic models (``project.measured.write_merl``), for
which the answers are known: a Lambertian table is one coefficient (exact at order 0) and
a Lambertian lobe fit, so its errors and image error vanish to the accuracy of the table;
its table is reciprocal by construction (a residual of exactly 0). The RGL-EPFL white paper
(tests/data/paper_white_rgb.bsdf) is not reciprocal: its residual is 0.0446 on 2**16 pairs
(:mod:`project.reciprocity`), and select's own measurement is the benchmark's.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import project
from compress.benchmark import _chart, benchmark_files, benchmark_merl, image_error
from compress.cli.commands import main
from project.measured import read_rgl, write_merl
from project.models import CookTorrance, Lambert

PAPER = Path(__file__).parents[1] / "data" / "paper_white_rgb.bsdf"
#: Small candidates for the RGL file: a reciprocal lobe and expansion, and a full-turn
#: (non-reciprocal) factored lobe, so that either decision of select has something to build.
RGL_CANDS = [{"form": "model", "family": "lambert+ggx", "restarts": 1, "n": 4096},
             {"form": "model", "family": "factored", "rank": 1, "bins": (16, 8, 8),
              "phi_turn": "full"},
             {"form": "modal", "kind": "zernike", "order": 2}]

CANDS = [{"form": "modal", "kind": "zernike", "order": 2},
         {"form": "model", "family": "lambert+ggx", "restarts": 1, "n": 4096}]


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    d = tmp_path_factory.mktemp("merl")
    write_merl(d / "matte.binary", Lambert([0.2, 0.4, 0.6]))
    write_merl(d / "glossy.binary", CookTorrance([0.1, 0.1, 0.1], 0.2, "ggx"))
    return d


def test_image_error_closed_forms():
    lam = Lambert([0.2, 0.4, 0.6])
    assert image_error(lam, lam, size=32) == 0.0
    assert image_error(lam, Lambert([0.22, 0.44, 0.66]), size=32) == pytest.approx(0.1)


def test_tables_chart_and_resume(folder, tmp_path):
    out = tmp_path / "bench"
    rows = benchmark_merl(folder, out, workers=2, candidates=CANDS, error_n=4096)
    by = {r["material"]: r for r in rows}
    assert set(by) == {"matte", "glossy"}
    matte = by["matte"]
    # the MERL table of a Lambertian BRDF: exact in either candidate, so the smaller wins
    assert matte["meets_0.05"] and matte["l2_0.05"] < 1e-3
    assert matte["bytes_0.05"] == min(matte["bytes_0.05"], matte["bytes_0.1"])
    assert matte["image_0.05"] < 1e-3
    assert by["glossy"]["bytes_0.1"] <= by["glossy"]["bytes_0.05"]
    for name in ("materials.csv", "candidates.csv", "pareto.png", "summary.json"):
        assert (out / name).stat().st_size > 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["materials"] == 2 and summary["0.05"]["meet"] >= 1
    # resume: finished materials are read back, not recomputed
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "materials").iterdir()}
    again = benchmark_merl(folder, out, workers=1, candidates=CANDS, error_n=4096)
    assert again == rows
    assert stamps == {p.name: p.stat().st_mtime_ns for p in (out / "materials").iterdir()}
    assert not list(out.glob(".*tmp*"))  # no temporary file left behind


def test_a_failing_material_does_not_stop_the_others(folder, tmp_path):
    """A damaged file is reported by name after the tables of the others are written."""
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    (mixed / "matte.binary").symlink_to(folder / "matte.binary")
    (mixed / "broken.binary").write_bytes(b"not a MERL table")
    out = tmp_path / "out"
    with pytest.raises(RuntimeError, match="1 of 2 materials failed .* broken: ValueError"):
        benchmark_merl(mixed, out, workers=1, candidates=CANDS[:1], error_n=4096)
    assert [r["material"] for r in _csv(out / "materials.csv")] == ["matte"]
    with pytest.raises(RuntimeError, match="all 1 materials failed"):
        benchmark_merl(mixed, out, workers=1, materials=["broken"], candidates=CANDS[:1])


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    """A folder of one RGL file, one MERL file and a file of neither kind (ignored)."""
    d = tmp_path_factory.mktemp("measured")
    shutil.copy(PAPER, d / PAPER.name)
    write_merl(d / "matte.binary", Lambert([0.2, 0.4, 0.6]))
    (d / "README.md").write_text("not a material")
    return d


@pytest.fixture(scope="module")
def mixed_run(measured, tmp_path_factory):
    out = tmp_path_factory.mktemp("mixed") / "bench"
    return out, benchmark_files(measured, out, tols=(0.05, 0.001), workers=2,
                                candidates=RGL_CANDS, error_n=4096)


def test_rgl_and_merl_in_one_folder(mixed_run):
    out, rows = mixed_run
    by = {r["material"]: r for r in rows}
    assert set(by) == {"matte", "paper_white_rgb"}
    paper, matte = by["paper_white_rgb"], by["matte"]
    assert (paper["format"], matte["format"]) == ("rgl", "merl")
    # the MERL table is symmetric in w_i, w_o by its layout: exactly 0
    assert matte["reciprocity_residual"] == 0.0 and matte["reciprocity_floor"] == 0.0
    assert matte["forms_0.05"] == matte["forms_0.001"] == "reciprocal"
    # read off the table of 0.001: the same forms compete at 0.05 (floor 0)
    assert matte["seconds_0.05"] == 0.0 and matte["seconds_0.001"] > 0
    # the paper: 0.0446 on 2**16 pairs; here 4096 pairs (select's); both are 2 floors
    assert 0.03 < paper["reciprocity_residual"] < 0.06
    assert paper["reciprocity_floor"] == pytest.approx(paper["reciprocity_residual"] / 2,
                                                       rel=1e-12)
    for r in rows:
        assert r["select_seconds"] > 0
        assert np.isfinite(r["image_0.001"])
        # the smallest error reached; what a tolerance no candidate meets reports
        assert r["best_l2"] <= min(r["l2_0.05"], r["l2_0.001"])
        assert r["meets_0.001"] or r["best_l2"] == r["l2_0.001"]
    # 0.05: the paper meets it with a reciprocal lobe (floor 0.022 + 2 se <= 0.05 / 2); the
    # run at 0.001 left the reciprocal forms out, so select ran again
    assert paper["meets_0.05"] and paper["reciprocal_0.05"] is True
    assert paper["forms_0.05"] == "reciprocal" and paper["family_0.05"] == "lambert+ggx"
    assert paper["select_seconds"] == pytest.approx(
        paper["seconds_0.05"] + paper["seconds_0.001"], abs=0.011)  # each rounded to 0.01
    # 0.001 is below the floor: only the full-turn lobe competes and none meets it
    assert not paper["meets_0.001"] and paper["forms_0.001"] == "non-reciprocal"
    assert paper["reciprocal_0.001"] is False and paper["family_0.001"] == "factored"
    assert paper["best_l2"] > paper["reciprocity_floor"]  # a lower bound, see the docs
    # select raised for the paper: the floor is measured again on select's pairs
    again = project.reciprocity(read_rgl(PAPER), n=4096, seed=2027)
    assert paper["reciprocity_floor"] == pytest.approx(again.floor, rel=1e-12)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["formats"] == {"merl": 1, "rgl": 1, "mbsdf": 0}
    assert summary["median_reciprocity_floor"] == pytest.approx(
        paper["reciprocity_floor"] / 2, rel=1e-12)
    assert summary["median_select_seconds"] > 0 and summary["median_image_error"] >= 0
    assert summary["0.001"]["fail_best"]["paper_white_rgb"] == {
        "l2": paper["l2_0.001"], "floor": paper["reciprocity_floor"]}
    cands = _csv(out / "candidates.csv")
    full = [c for c in cands if c["material"] == "paper_white_rgb"
            and c["status"] == "measured" and c["reciprocal"] == "False"]
    assert full and {c["family"] for c in full} == {"factored"}
    table = [{**c, "material": c["material"], "reciprocal": c["reciprocal"] == "True",
              "bytes": int(c["bytes"]), "l2": float(c["l2"]) if c["l2"] else None}
             for c in cands]
    labels = _chart(table, out / "again.png")
    assert "factored, non-reciprocal" in labels and "lambert+ggx" in labels
    assert (out / "pareto.png").stat().st_size > 0


def test_mixed_resume(mixed_run, measured):
    out, rows = mixed_run
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "materials").iterdir()}
    again = benchmark_files(measured, out, tols=(0.05, 0.001), workers=1,
                            candidates=RGL_CANDS, error_n=4096)
    assert again == rows
    assert stamps == {p.name: p.stat().st_mtime_ns for p in (out / "materials").iterdir()}
    # a MERL-only run of the same folder reads back the MERL material alone
    merl = benchmark_merl(measured, out / "merl-only", tols=(0.05,), workers=1,
                          candidates=RGL_CANDS[:1], error_n=4096)
    assert [r["material"] for r in merl] == ["matte"]


def test_foreign_and_clashing_files(measured, tmp_path):
    d = tmp_path / "in"
    d.mkdir()
    shutil.copy(measured / "matte.binary", d / "matte.binary")
    (d / "junk.bsdf").write_bytes(b"not a tensor file")
    out = tmp_path / "out"
    with pytest.raises(RuntimeError, match=r"1 of 2 materials failed .* junk: ValueError: "
                                           r"tensor file .* truncated"):
        benchmark_files(d, out, workers=1, candidates=RGL_CANDS[:1], error_n=4096)
    assert [r["material"] for r in _csv(out / "materials.csv")] == ["matte"]
    (d / "matte.bsdf").write_bytes(b"")
    with pytest.raises(ValueError, match="two files of the material 'matte'.*matte.binary "
                                         "and matte.bsdf"):
        benchmark_files(d, out, candidates=RGL_CANDS[:1])


def test_bad_arguments_files(measured, tmp_path):
    with pytest.raises(FileNotFoundError, match=r"no \.binary, \.bsdf or \.mbsdf files"):
        benchmark_files(tmp_path, tmp_path / "o")
    with pytest.raises(FileNotFoundError, match=r"no \.bsdf files"):
        benchmark_files(tmp_path, tmp_path / "o", formats=("rgl",))
    with pytest.raises(FileNotFoundError,
                       match="no velvet.binary, velvet.bsdf or velvet.mbsdf"):
        benchmark_files(measured, tmp_path / "o", materials=["velvet"])
    with pytest.raises(NotADirectoryError, match=r"no folder of measured \(MERL \.binary, "
                                                 r"RGL \.bsdf and MDL \.mbsdf\) files"):
        benchmark_files(tmp_path / "nowhere", tmp_path / "o")
    with pytest.raises(ValueError, match=r"formats must name some of \('merl', 'rgl', "
                                         r"'mbsdf'\), "
                                         "got 'tiff'"):
        benchmark_files(measured, tmp_path / "o", formats="tiff")
    with pytest.raises(ValueError, match="formats must name some of"):
        benchmark_files(measured, tmp_path / "o", formats=())


def test_command_line_rgl(measured, tmp_path, capsys):
    """Default candidates on the paper at 0.05: the lambert+ggx lobe (0.044) at float16 is
    the smallest, so nothing larger is built (this stays fast)."""
    out = tmp_path / "cli"
    assert main(["benchmark", "rgl", str(measured), "--out", str(out), "--tols", "0.05",
                 "--workers", "1", "--error-pairs", "4096", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert '"materials": 1' in printed and '"rgl": 1' in printed
    rec = json.loads((out / "materials" / "paper_white_rgb.json").read_text())
    assert rec["row"]["family_0.05"] == "lambert+ggx" and rec["row"]["format"] == "rgl"
    assert rec["reciprocity"]["forms"] == {"0.05": ["reciprocal"]}
    assert "<= tol / 2" in rec["reciprocity"]["why"]["0.05"]
    # no target: both kinds, the finished paper read back
    assert main(["benchmark", str(measured), "--out", str(out), "--tols", "0.05",
                 "--workers", "1", "--error-pairs", "4096", "--no-progress"]) == 0
    assert '"materials": 2' in capsys.readouterr().out
    assert main(["benchmark", "rgl", str(tmp_path / "none"), "--out", str(out)]) == 2
    assert "no folder of RGL files" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["benchmark", str(empty), "--out", str(out)]) == 2
    assert "no .binary, .bsdf or .mbsdf files" in capsys.readouterr().err


def _csv(path):
    import csv

    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_bad_arguments(folder, tmp_path):
    with pytest.raises(NotADirectoryError, match="no folder"):
        benchmark_merl(tmp_path / "nowhere", tmp_path / "o")
    with pytest.raises(FileNotFoundError, match="no velvet.binary"):
        benchmark_merl(folder, tmp_path / "o", materials=["velvet"])
    with pytest.raises(ValueError, match="tols must be positive"):
        benchmark_merl(folder, tmp_path / "o", tols=(0.0,))
    with pytest.raises(FileNotFoundError, match="no .binary files"):
        benchmark_merl(tmp_path, tmp_path / "o")


def test_command_line(folder, tmp_path, capsys):
    """The default candidates on the Lambertian table: lambert+ggx at float16 is exact to
    rounding and the smallest, so nothing larger is built (this stays fast)."""
    out = tmp_path / "cli"
    assert main(["benchmark", "merl", str(folder), "--out", str(out), "--materials",
                 "matte", "--workers", "1", "--error-pairs", "4096", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert '"materials": 1' in printed and "materials.csv" in printed
    rec = json.loads((out / "materials" / "matte.json").read_text())
    assert rec["row"]["family_0.05"] == "lambert+ggx" and rec["row"]["dtype_0.05"] == "float16"
    skipped = [c for c in rec["candidates"] if c["status"].startswith("skipped")]
    assert len(skipped) >= 10
    assert main(["benchmark", "merl", str(tmp_path / "none"), "--out", str(out)]) == 2
    assert "no folder of MERL files" in capsys.readouterr().err
    assert np.isfinite(rec["row"]["image_0.05"])


def test_dask_client_gives_the_local_result(folder, tmp_path):
    """One task per material on a Dask cluster: the same tables as the local run (select
    is deterministic: seeded fits and error pairs), timings aside."""
    distributed = pytest.importorskip("distributed")
    local = benchmark_merl(folder, tmp_path / "local", workers=1, candidates=CANDS,
                           error_n=4096)
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=1,
                            dashboard_address=None,  # HTTP on a free port, not 8787
                            scheduler_kwargs={"dashboard_address": ":0"}) as client:
        remote = benchmark_merl(folder, tmp_path / "dask", candidates=CANDS, error_n=4096,
                                client=client)

    def strip(rows):
        return [{k: v for k, v in r.items() if "seconds" not in k} for r in rows]

    assert strip(remote) == strip(local)
    with pytest.raises(TypeError, match="dask.distributed.Client"):
        benchmark_merl(folder, tmp_path / "x", candidates=CANDS, client="tcp://nowhere:1")


def test_command_line_bad_scheduler(folder, tmp_path, capsys):
    pytest.importorskip("distributed")
    assert main(["benchmark", "merl", str(folder), "--out", str(tmp_path / "o"),
                 "--scheduler", "tcp://127.0.0.1:9"]) == 2
    assert "--scheduler 'tcp://127.0.0.1:9': cannot connect" in capsys.readouterr().err


def test_mbsdf_folder(tmp_path):
    """An MDL .mbsdf file of a Lambertian BRDF: constant at every texel centre, so the
    SDK's lookup is that constant everywhere and the order-2 expansion is exact."""
    from project.measured import write_mbsdf

    d = tmp_path / "mdl"
    d.mkdir()
    write_mbsdf(Lambert([0.2, 0.4, 0.6]), d / "matte.mbsdf", resolution=(6, 12))
    rows = benchmark_files(d, tmp_path / "o", formats=("mbsdf",), tols=(0.05,), workers=1,
                           candidates=CANDS, error_n=4096)
    (row,) = rows
    assert row["material"] == "matte" and row["format"] == "mbsdf"
    # float32 storage of 0.6 / pi: relative rounding 3e-8
    assert row["meets_0.05"] and row["l2_0.05"] < 1e-3
