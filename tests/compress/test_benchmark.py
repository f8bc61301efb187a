"""compress.benchmark and ``scatmodes benchmark merl``: the MERL benchmark on small tables.

References: MERL files written from analytic models (``project.measured.write_merl``), for
which the answers are known: a Lambertian table is one coefficient (exact at order 0) and
a Lambertian lobe fit, so its errors and image error vanish to the accuracy of the table.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from compress.benchmark import benchmark_merl, image_error
from compress.cli.commands import main
from project.measured import write_merl
from project.models import CookTorrance, Lambert

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
                            dashboard_address=None) as client:
        remote = benchmark_merl(folder, tmp_path / "dask", candidates=CANDS, error_n=4096,
                                client=client)

    def strip(rows):
        return [{k: v for k, v in r.items() if k != "select_seconds"} for r in rows]

    assert strip(remote) == strip(local)
    with pytest.raises(TypeError, match="dask.distributed.Client"):
        benchmark_merl(folder, tmp_path / "x", candidates=CANDS, client="tcp://nowhere:1")


def test_command_line_bad_scheduler(folder, tmp_path, capsys):
    pytest.importorskip("distributed")
    assert main(["benchmark", "merl", str(folder), "--out", str(tmp_path / "o"),
                 "--scheduler", "tcp://127.0.0.1:9"]) == 2
    assert "--scheduler 'tcp://127.0.0.1:9': cannot connect" in capsys.readouterr().err
