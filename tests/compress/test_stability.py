"""The stability atlas (compress.stability): each item's qualitative facts, pinned with margins
taken from the measured values (noted at each assert), at small sizes."""

from __future__ import annotations

import numpy as np
import pytest

from compress import stability as st

pytest.importorskip("mpmath")


@pytest.fixture(scope="module")
def radial():
    return st.radial_accuracy(zernike_orders=(20, 60, 200), sh_degrees=(20, 60, 200, 2000))


def test_radial_factorial_fails_recurrence_holds(radial):
    f = radial.facts
    # measured: the factorial sum keeps 0.0 digits at n = 60 (interior / rim): > 6 digits lost
    assert f["zernike/factorial/min_digits@60"] < 16 - 6
    assert f["zernike/power/min_digits@60"] < 16 - 6
    # measured 12.95 digits at n = 200 (worst region); 12 is the claim
    assert f["zernike/recurrence/min_digits@200"] >= 12.0
    # measured 13.6 (l = 60), 13.2 (l = 200), 11.0 (l = 2000); bound ~ l^2 eps conditioning
    assert f["sh/recurrence/min_digits@200"] >= 12.0
    assert f["sh/recurrence/min_digits@2000"] >= 10.0
    assert f["sh/factorial/min_digits@60"] < 4.0  # measured 0.0
    # the factorial form overflows (NaN -> 0 digits) past 170!
    assert f["zernike/factorial/min_digits@200"] == 0.0


def test_radial_naive_sums_fine_near_pole(radial):
    # near the pole the terms are small and do not cancel: measured >= 15.8 digits at n = 200
    d = radial.column("digits", family="zernike", method="power", region="pole", m="low")
    assert np.nanmin(d) > 14.0


def test_radial_table_and_chart(radial, tmp_path):
    md = radial.to_markdown()
    assert "| family | method | order |" in md
    assert radial.plot(tmp_path / "r.png").stat().st_size > 1000


def test_naive_baselines_agree_at_low_order():
    from basis import zernike_radial
    # R_4^0(0.5) = 6/16 - 6/4 + 1 = -0.125 exactly; all three forms agree to rounding
    for fn in (st.zernike_factorial, st.zernike_power):
        assert abs(fn(4, 0, 0.5) + 0.125) < 1e-15
    assert abs(float(zernike_radial(4, 0, 0.5)) + 0.125) < 1e-15
    # Y_10 = sqrt(3 / (4 pi)) z
    z, s = 0.6, 0.8
    for fn in (st.sh_factorial, st.sh_power):
        assert abs(fn(1, 0, z, s) - np.sqrt(3 / (4 * np.pi)) * z) < 1e-15


def test_hemisphere_conditioning():
    a = st.hemisphere_conditioning((2, 8))
    f = a.facts
    # measured 1.03e11 (exact rule) and ~2e11 (random pairs) at degree 8: the 1e10
    assert f["sh/cond_pairs_rule@8"] > 1e10
    assert f["sh/cond_pairs_random@8"] > 1e10
    # one direction only: measured 3.2e5, far from 1e10 (the squaring comes from the pairs)
    assert 1e4 < f["sh/cond_direction@8"] < 1e7
    for kind in ("zernike", "harmonics", "harmonics-even"):
        # orthonormal on an exact rule: 1 up to rounding
        assert f[f"{kind}/max_cond_pairs_rule"] < 1 + 1e-8
        # unweighted random pairs (4 per unknown): measured 6-34, never above ~100
        assert f[f"{kind}/max_cond_pairs_random"] < 200
    # the SVD solve is stable, so the SH fit on the hemisphere is not worse, but its
    # coefficients cancel: measured norm ratio ~1e8 against ~1
    sh = a.column("coef_norm", kind="sh", order=8)[0]
    zb = a.column("coef_norm", kind="zernike", order=8)[0]
    assert sh > 1e5 * zb


def test_sparse_fits_regularisation():
    a = st.sparse_fits((8,), ratios=(66 / 55, 16.0), noise=(0.01,), trials=3)
    brick, dense = a.rows
    assert brick["samples"] == 66 and brick["unknowns"] == 55
    # measured gain ~6 at the brick case, ~1.01 with 16 samples per unknown
    assert brick["gain"] > 2.0
    assert dense["gain"] < 1.2
    assert brick["cond"] > 10 * dense["cond"]  # measured ~1e3 against ~4.7
    # the perturbation bound holds (measured error / bound <= 0.28)
    assert all(r["bound_ratio"] <= 1.0 for r in a.rows)
    # the "auto" curve, project.fit(regularization="auto") against the same quadrature
    # projection: at the brick case it regularised in every trial (auto_plain 0) and cut the
    # error 12x (0.876 -> 0.073), below even the oracle of the identity penalty (0.119): the
    # degree penalty is the better prior; 2x is the margin on the gain
    assert brick["auto_plain"] == 0.0 and brick["gain_auto"] > 6.0
    assert brick["error_auto"] < brick["error_regularized"]
    # with 16 samples per unknown it kept the plain fit in every trial: the same error
    assert dense["auto_plain"] == 1.0
    assert dense["error_auto"] == pytest.approx(dense["error"], rel=1e-9)
    assert a.facts["gain_auto@8/66/0.01"] == brick["gain_auto"]
    assert [p.y for p in a.panels][:3] == ["error", "error_regularized", "error_auto"]


def test_sharp_lobes(tmp_path):
    a = st.sharp_lobes((0.5, 0.2), (4,), quantities=("f_cos",), filters=("hann",),
                       pairs=4096)
    f = a.facts
    # truncation error grows as the lobe sharpens: measured 0.143 -> 0.68
    assert f["truncation@0.2/4/f_cos/none"] > 2 * f["truncation@0.5/4/f_cos/none"]
    # a fixed rule's quadrature error grows too: measured 1.4e-3 -> ~0.1
    assert f["quad_fixed@0.2/4/f_cos/none"] > 10 * f["quad_fixed@0.5/4/f_cos/none"]
    # Hann lowers the negative fraction at order 4: measured 0.18 -> 0.03, 0.41 -> 0.13
    for r0 in (0.5, 0.2):
        assert f[f"negative@{r0:g}/4/f_cos/hann"] < 0.7 * f[f"negative@{r0:g}/4/f_cos/none"]
    # dividing out the cosines amplifies the error near grazing: measured 0.3 below 60 deg,
    # 15-140 above 85 deg
    assert f["grazing/amplification_above_85"] > 10 * f["grazing/amplification_below_60"]
    amp = a.column("amplification", table="grazing")
    assert np.all(np.diff(amp) > 0)
    assert a.plot(tmp_path / "s.png").exists()


def test_monte_carlo():
    a = st.monte_carlo((2000, 8000, 32000), seeds=6, resolution=64, coarsen=(1, 4),
                       resolution_rays=64000)
    f = a.facts
    # 1/sqrt(N): measured slopes -0.50 (error) and -0.50 (Q); with 6 seeds the spread of the
    # error estimate is ~30 %, i.e. +-0.15 on the slope over a factor 16
    assert -0.7 < f["slope_error"] < -0.3
    assert -0.7 < f["slope_q"] < -0.3
    # relative noise grows with degree: measured 19x from degree 1 to 6
    assert f["relative_ratio_top_to_1"] > 5
    # spacing = tau (coarsen 4) lowers the slopes (m 0.50 -> 0.40) and biases M by 5.7 x the
    # MC error of the difference; 3 is the margin
    assert f["roughness@4"] < 0.9 * f["roughness@1"]
    assert f["resolution_z@4"] > 3.0


def test_write_all_rejects_missing_dir(tmp_path):
    with pytest.raises(FileNotFoundError, match="out_dir must be an existing directory"):
        st.write_all(tmp_path / "nope", small=True)


def test_markdown_and_select():
    a = st.Atlas("t", [dict(a=1, b=0.5), dict(a=2, b=None)])
    assert a.select(a=2) == [dict(a=2, b=None)]
    assert "| 2 | n/a |" in a.to_markdown()
    with pytest.raises(ValueError, match="table must be 'main'"):
        a.select("other")


def test_fit_stability():
    """Item 6 on a one-channel glossy Cook-Torrance, 4 restarts on 512 pairs: the costs per
    case are those fit_model reports (recomputed here for lambert+ggx), ordered, and the
    fractions follow from them. Measured: lambert+ggx and rr8807 reach one minimum from all
    4 starts (relative spread < 1e-9), so at_best = 1 is asserted for them."""
    from project import fit_model

    cases = (("lafortune", 1), ("lambert+ggx", None), ("dsbrdf", 1), ("rr8807", None))
    a = st.fit_stability(cases, restarts=4, n=512, error_n=1024, channels=1)
    assert [r["case"] for r in a.rows] == ["lafortune/1", "lambert+ggx", "dsbrdf/1", "rr8807"]
    assert [r["nparams"] for r in a.rows] == [4, 4, 12, 7]
    for r in a.rows:
        assert r["cost_min"] <= r["cost_median"] <= r["cost_max"]
        assert 0.25 <= r["at_best"] <= r["near_best"] <= 1.0
        assert len(a.select("restarts", case=r["case"])) == 4
    fit = fit_model(st._glossy_target(1), "lambert+ggx", n=512, error_n=1024, restarts=4)
    got = np.sort(a.column("cost", "restarts", case="lambert+ggx"))
    np.testing.assert_allclose(got, np.sort(fit.info["cost"]), rtol=1e-12)
    assert a.facts["at_best@lambert+ggx"] == 1.0 and a.facts["at_best@rr8807"] == 1.0
    assert a.facts["spread@rr8807"] < 1e-6
    assert "restarts at the best" in a.to_markdown()


def test_write_all_on_a_dask_cluster(tmp_path):
    """The six measurements as tasks (an in-process cluster): the same tables as when
    they are computed here (hemisphere_conditioning is deterministic)."""
    distributed = pytest.importorskip("distributed")
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=1,
                            dashboard_address=None) as client:
        written = st.write_all(tmp_path, small=True, client=client)
    assert sorted(written) == sorted(["radial_accuracy", "hemisphere_conditioning",
                                      "sparse_fits", "sharp_lobes", "monte_carlo",
                                      "fit_stability"])
    md, png = written["hemisphere_conditioning"]
    assert md.read_text() == st.hemisphere_conditioning((2, 4, 6)).to_markdown()
    assert png.stat().st_size > 0
    with pytest.raises(TypeError, match="dask.distributed.Client"):
        st.write_all(tmp_path, small=True, client=object())
