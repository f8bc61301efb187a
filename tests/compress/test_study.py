"""study, the metrics, the table, the chart and select_order."""

from __future__ import annotations

import numpy as np
import pytest

import basis
from compress import errors, pareto_front, reference_samples, select_order, study
from compress.study import COLUMNS, METRICS, make_basis
from project import project
from project.models import Lambert, Phong, Ward

NODES = (24, 48)  # small test set: every test here runs in well under a second


@pytest.fixture(scope="module")
def phong_study():
    # f_cos in both kinds: the l2 metric (of q) is then the Parseval truncation error
    return study(Phong(0.2, 0.4, 6.0), ["zernike", "harmonics"], [2, 4, 8], nodes=NODES,
                 quantity="f_cos")


def test_rows_and_columns(phong_study):
    st = phong_study
    assert len(st.rows) == 6 and all(set(r) == set(COLUMNS) for r in st.rows)
    r = st.rows[2]  # zernike order 8: blocks k_m = 5,4,4,3,3,2,2,1,1 -> 55 unique numbers
    assert (r["kind"], r["order"], r["coefficients"], r["bytes"]) == ("zernike", 8, 55, 440)
    assert st.rows[5]["coefficients"] == 40  # odd harmonics order 8: 4,4,3,3,2,2,1,1
    assert all(r["reciprocity"] < 1e-13 for r in st.rows)  # symmetric matrices
    assert all(r["eval_ns"] > 0 for r in st.rows)


def test_l2_equals_parseval_truncation_error(phong_study):
    # Two independent routes to the same number: the project() Parseval estimate
    # (||q||^2 - ||M||_F^2 on the projection rule) and the direct quadrature of
    # (q_hat - q)^2 on the 24 x 24 x 48 test set. Observed agreement 2e-4 relative; the
    # test set's own quadrature error on this smooth lobe is the limit.
    for r in phong_study.rows:
        assert r["l2"] == pytest.approx(r["truncation_error"], rel=2e-3)
    l2 = phong_study.column("l2")
    assert np.all(np.diff(l2[:3]) < 0) and np.all(np.diff(l2[3:]) < 0)  # nested projections


def test_lambert_metrics_vanish():
    ts = reference_samples(Lambert(0.5), nodes=NODES)
    cm = project(Lambert(0.5), basis.HemiHarmonics(3))
    e = errors(cm, ts)
    # exact representation: rounding only (values ~0.16, relative ~1e-15)
    for m in ("l2", "rel_rms", "log_rms", "smape", "negative", "reciprocity"):
        assert e[m] < 1e-12 and e.get(m + "_all", 0.0) < 1e-12, m
    assert e["max_abs"] < 1e-14 and e["albedo"] < 1e-14
    assert e["max_abs_all"] < 1e-14 and e["albedo_all"] < 1e-14


def test_albedo_error_against_closed_form():
    # Order-1 odd harmonics keep only b_10 of Phong's f cos cos; the represented albedo is
    # then independent of the lobe. Compare with the albedo computed by the BRDF class.
    brdf = Lambert(0.25)
    ts = reference_samples(brdf, nodes=NODES)
    cm = project(Lambert(0.5), basis.HemiHarmonics(1))  # albedo 0.5 instead of 0.25
    e = errors(cm, ts)
    assert e["albedo"] == pytest.approx(0.25, rel=1e-12)  # Gauss rule exact for z
    assert e["smape"] == pytest.approx(100 * 0.25 / 0.75, rel=1e-12)  # |a-b|/(a+b), percent
    assert e["max_abs"] == pytest.approx(0.25 / np.pi, rel=1e-12)
    assert e["rel_rms"] == pytest.approx(1.0, rel=1e-12)  # f_hat = 2 f everywhere


def test_anisotropic_uses_sobol():
    brdf = Ward(0.3, 0.2, 0.3, 0.5)
    ts = reference_samples(brdf, nodes=(8, 16))
    assert ts.grid is None and ts.wi.shape == (1024, 3)
    assert ts.weights.sum() == pytest.approx((2 * np.pi) ** 2, rel=1e-14)


def test_markdown_and_plot(phong_study, tmp_path):
    md = phong_study.to_markdown()
    assert md.splitlines()[2].startswith("| kind | order | quantity | coefficients | bytes |")
    assert "| zernike | 8 | f_cos | 55 | 440 |" in md
    png = phong_study.plot(tmp_path / "s.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.png"]
    with pytest.raises(ValueError, match="metric must be one of"):
        phong_study.plot(tmp_path / "x.png", metric="psnr")


def test_pareto_front():
    cost = np.array([1.0, 2.0, 3.0, 4.0, 2.0])
    err = np.array([0.5, 0.3, 0.4, 0.1, 0.6])
    assert pareto_front(cost, err).tolist() == [True, True, False, True, False]
    with pytest.raises(ValueError, match="cost and error must be 1-D of one length"):
        pareto_front([1.0], [1.0, 2.0])


def test_study_warns_into_table():
    st = study(Phong(0.0, 1.0, 60.0), "zernike", [2], nodes=NODES, time_eval=False)
    assert st.rows[0]["warnings"] == 1 and "misses" in st.messages[0]
    assert "1 projection warning(s)" in st.to_markdown()


def test_study_errors():
    with pytest.raises(ValueError, match="kind must be one of 'zernike'"):
        study(Lambert(0.5), "wavelets", [2])
    with pytest.raises(ValueError, match="orders must hold at least one order"):
        study(Lambert(0.5), "zernike", [])
    with pytest.raises(ValueError, match="order must be >= 1 for kind='harmonics'"):
        make_basis("harmonics", 0)
    with pytest.raises(ValueError, match=r"max_theta must lie in \(0, pi/2\]"):
        reference_samples(Lambert(0.5), max_theta=2.0)


def test_select_order():
    brdf = Phong(0.2, 0.4, 6.0)
    # study records the projection warnings (orders 0-2 miss > 10 %) in the table
    st = study(brdf, "zernike", list(range(0, 9)), nodes=NODES, time_eval=False)
    assert [r["warnings"] for r in st.rows][:3] == [1, 1, 1]
    l2 = st.column("l2")
    tol = 0.05
    want = int(np.flatnonzero(l2 <= tol)[0])  # the study, order by order, independently
    assert select_order(brdf, "zernike", tol, max_order=8, nodes=NODES) == want
    assert select_order(Lambert(0.3), "harmonics", 1e-12, max_order=3, nodes=NODES) == 1
    # Lambert's f is the constant K_0^0 (order 0); its f cos cos needs z_i z_o (order 2)
    assert select_order(Lambert(0.3), "zernike", 1e-12, max_order=3, nodes=NODES) == 0
    assert select_order(Lambert(0.3), "zernike", 1e-12, max_order=3, nodes=NODES,
                        quantity="f_cos") == 2
    with pytest.raises(ValueError, match="no order <= 2 of kind 'zernike' meets l2"), \
            pytest.warns(RuntimeWarning, match="misses 43.1 %"):
        select_order(brdf, "zernike", 1e-6, max_order=2, nodes=NODES)
    with pytest.raises(ValueError, match="metric must be one of"):
        select_order(brdf, "zernike", 0.1, metric="psnr")
    with pytest.raises(ValueError, match="tol must be a positive number"):
        select_order(brdf, "zernike", -1.0)


def test_metric_names():
    assert METRICS == ("l2", "max_abs", "rel_rms", "log_rms", "smape", "negative", "albedo",
                       "reciprocity", "max_abs_all", "rel_rms_all", "log_rms_all", "smape_all",
                       "albedo_all", "reciprocity_all")


def test_whole_hemisphere_metrics_see_the_grazing_band():
    # Phong in HemiZernike(8) as f_cos: inside D the division by cos cos is harmless, on all of
    # H x H it amplifies the truncation error (the failure the _all columns exist to show)
    brdf = Phong(0.3, 0.4, 20)
    ts = reference_samples(brdf, nodes=NODES)
    with pytest.warns(RuntimeWarning, match="misses"):
        cm = project(brdf, basis.HemiZernike(8), quantity="f_cos")
    e = errors(cm, ts)
    assert e["max_abs_all"] > 10 * e["max_abs"]
    assert e["rel_rms_all"] > e["rel_rms"]
    assert e["albedo_all"] >= e["albedo"]


def test_study_of_measurements_is_cross_validated():
    """Lambertian samples on random pairs: every order predicts held-out samples exactly
    (the constant is in every Zernike span), so l2 vanishes; a sample set with a value
    that no smooth fit predicts (one outlier) shows up in the held-out error of every
    order, while the fit's own residual would hide it at high order."""
    from project import Measurements
    from tests.conftest import random_directions

    rng = np.random.default_rng(3)
    wi, wo = random_directions(rng, 600, upper=True), random_directions(rng, 600, upper=True)
    meas = Measurements(wi, wo, np.full(600, 0.25), isotropic=True)
    st = study(meas, "zernike", [2, 4], time_eval=False)
    assert [r["order"] for r in st.rows] == [2, 4]
    assert all(set(r) == set(COLUMNS) for r in st.rows)
    assert all(r["l2"] < 1e-10 and r["albedo"] is None for r in st.rows)
    assert "10-fold cross-validation on 600 held-out samples" in st.sampling
    values = np.full(600, 0.25)
    values[7] = 25.0  # at normal incidence and exitance, where q = f
    wi[7] = wo[7] = [0.0, 0.0, 1.0]
    st = study(Measurements(wi, wo, values, isotropic=True), "zernike", [2], time_eval=False)
    # q_7 = 25 against q <= 0.25 elsewhere: it holds over 97 % of sum q^2, and held out,
    # no fit to the other samples predicts it
    assert st.rows[0]["l2"] > 0.95
