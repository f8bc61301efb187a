"""compress.select on glossy goniometer tables and on car paints in MDL files.

Stand-ins from tests/project/gonio.py (no data files): glossy paints measured in the layout
of the Cornell tables, and car paints (metallic flakes under a clear coat, with sparkle)
written as ``.mbsdf`` files at the resolution of the MDL SDK's example, (45, 90) RGB,
2,187,055 bytes. References: the plain least-squares fit of tests/project/gonio.py for the
tables, the file's size for the car paints.
"""

from __future__ import annotations

import os

import h5py
import numpy as np
import pytest

import compress
import project
from project.measured import MBSDFBRDF, read_mbsdf, write_mbsdf
from tests.project import gonio


def _car_paint(tmp_path, k: int, resolution=(45, 90)):
    paint = gonio.car_paints()[k]
    path = tmp_path / f"{paint.name}.mbsdf"
    write_mbsdf(paint, path, resolution=resolution)
    noisy = gonio.sparkle(np.array(read_mbsdf(path).table), seed=k)
    write_mbsdf(MBSDFBRDF(noisy), path, resolution=resolution)
    return read_mbsdf(path)


@pytest.mark.parametrize("name", ["gloss-red", "satin-green"])
def test_meets_025_where_the_plain_fit_does(name):
    """select(meas, 0.25) meets 0.25 on a glossy table whose plain least-squares fit does,
    on the same 10 folds (gloss-red: 0.217 for both)."""
    paints = {p.name: (k, p) for k, p in enumerate(gonio.paints())}
    k, paint = paints[name]
    wi, wo = gonio.cornell_layout(0)
    meas = gonio.measure(paint, wi, wo, seed=100 + k, clip=k % 2 == 1)
    meas = meas.select_channels(list(range(0, 31, 3)))
    plain = project.crossval.cross_validate(meas, gonio.plain_fit)["l2"]
    assert plain <= 0.24, plain  # the premise: the plain fit meets 0.25 with room
    rep = compress.select(meas, 0.25)
    assert rep.info["selected"]["l2"] <= min(0.25, 1.05 * plain + 0.01)
    assert rep.info["bytes"] <= 8 * (2 * meas.channels + 2)  # a compact model, not a table


def test_grid_family_reproduces_an_mbsdf_file(tmp_path):
    src = _car_paint(tmp_path, 0, resolution=(12, 24))
    whole = project.fit_model(src, "grid", symmetric=False, error_n=4096)
    # the source's own grid at its own resolution: the same table, the same lookup
    assert whole.params["table"].shape == (12, 12, 24, 3)
    # (the lookup returns max(0, value): the noise floor's negative values read as 0)
    # (the interpolation weights at a centre round to 1 and 0 within a few ulp: observed
    # 4e-16 relative, and 1e-17 absolute beside a negative neighbour)
    np.testing.assert_allclose(whole.params["table"], np.maximum(src.table, 0.0), rtol=1e-13,
                               atol=1e-15)
    assert whole.info["l2"] < 1e-12 and whole.reciprocal is False
    assert whole.nparams == 12 * 12 * 24 * 3
    half = project.fit_model(src, "grid", error_n=4096)
    assert half.reciprocal is True and half.nparams == 12 * 13 // 2 * 24 * 3
    t = half.params["table"]
    np.testing.assert_array_equal(t, t.transpose(1, 0, 2, 3))
    # written at its resolution it reads back as itself (float32 rounding)
    out = write_mbsdf(half, tmp_path / "half.mbsdf", resolution=(12, 24))
    np.testing.assert_allclose(read_mbsdf(out).table, t, rtol=1e-6, atol=1e-15)
    # stored and loaded as any model
    compress.save(half, tmp_path / "half.h5")
    back = compress.load(tmp_path / "half.h5")
    assert back.family == "grid" and back.nparams == half.nparams
    # the file holds the reals nparams counts: a symmetric table as its upper triangle
    with h5py.File(tmp_path / "half.h5", "r") as f:
        assert f["params/table"].size == half.nparams
    np.testing.assert_array_equal(back.params["table"], t)


@pytest.mark.parametrize("params, error, match", [
    ({"table": np.ones((2, 2, 4, 3)), "x": 1.0}, ValueError, r"exactly \['table'\]"),
    ({"table": np.ones((2, 3, 4, 3))}, ValueError, "table"),
])
def test_grid_params_refused(params, error, match):
    with pytest.raises(error, match=match):
        project.FittedModel("grid", params)


def test_grid_options_refused():
    with pytest.raises(TypeError, match="symmetric must be True or False"):
        project.fit_model(project.models.Lambert(0.5), "grid", symmetric="yes",
                          resolution=(4, 8), error_n=1024)
    with pytest.raises(ValueError, match="resolution must be"):
        project.fit_model(project.models.Lambert(0.5), "grid", resolution=(0, 8))


def test_car_paint_answer_no_larger_than_its_file(tmp_path):
    """A coat narrower than the file's cells: the half/difference tables stop at ~0.16
    (module notes of project.fitting.grid); the file's own grid meets 10 % in a quarter of
    its bytes."""
    src = _car_paint(tmp_path, 1)
    size = os.path.getsize(src.path)
    rep = compress.select(src, 0.10, error_n=1 << 14, candidates=[
        {"form": "model", "family": "lambert+ggx", "restarts": 1},
        {"form": "model", "family": "tabulated", "bins": (48, 32, 32)},
        {"form": "model", "family": "grid", "symmetric": True},
        {"form": "model", "family": "grid", "symmetric": False}])
    assert rep.info["bytes"] <= size
    assert rep.family == "grid" and rep.info["selected"]["l2"] <= 0.10
    rows = {(r["label"], r["dtype"]): r for r in rep.info["candidates"]}
    tab = rows[("model: family=tabulated, bins=(48, 32, 32)", "float16")]
    assert tab["l2"] > 0.10  # what made select fail before the grid family


@pytest.mark.slow
def test_car_paint_default_candidates(tmp_path):
    """The default candidates on the blue-pearl stand-in (about 100 s on 2 loaded cores):
    before the grid family, NoCandidateError (best 0.153, a 32 kB Tucker tensor)."""
    src = _car_paint(tmp_path, 1)
    rep = compress.select(src, 0.10)
    assert rep.info["bytes"] <= os.path.getsize(src.path)
    assert rep.info["selected"]["l2"] <= 0.10
