"""Peak-resolving pairs and error metrics: the weights integrate over H x H (closed forms),
sharp Cook-Torrance lobes are measured as a dense half-vector quadrature measures them while a
uniform sampler of the same size is far off, the reported standard errors are calibrated, and
bad input is refused.

Monte Carlo assertions use K_SIGMA = 5 standard errors (the replicate standard error has 15
degrees of freedom with the default 16 replicates: a Student t beyond 5 has probability ~2e-4
per assertion), and every seed is fixed, so the suite is deterministic."""

from __future__ import annotations

import numpy as np
import pytest

from project.models import CookTorrance, Lambert
from project.sampling import (
    PairSamples,
    brdf_errors,
    log_rms,
    peak_resolving_pairs,
    relative_l2,
)

K_SIGMA = 5.0
N = 16384


def replicate_mean_and_stderr(s: PairSamples, g: np.ndarray) -> tuple[float, float]:
    """Estimate of int g over H x H and its standard error from the replicate spread."""
    per = np.bincount(s.replicate, s.weights * g, minlength=s.replicates) * s.replicates
    return float(per.mean()), float(per.std(ddof=1) / np.sqrt(s.replicates))


# -- an independent dense reference --------------------------------------------------------------

def _gauss(a: float, b: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (b - a) * x + 0.5 * (a + b), 0.5 * (b - a) * w


#: theta_h panels, dense where the lobes of roughness 0.05-0.06 live
BREAKS = (0.0, 0.02, 0.06, 0.15, 0.35, 0.8, np.pi / 2)


def dense_q2(brdf, other=None, *, n_theta_i=48, n_seg=32, n_phi=128) -> float:
    """int_H int_H (q - q_other)^2 dw_i dw_o (q^2 without ``other``) for an isotropic BRDF.

    Gauss-Legendre in theta_i (weight 2 pi sin theta_i: the azimuth of w_i is irrelevant);
    for each w_i, w_o is written through its half vector h (theta_h, phi_h): w_o = 2 (w_i . h)
    h - w_i, dw_o = 4 cos theta_d dw_h (Walter et al. 2007, eq. 14, cos theta_d = w_i . h),
    with panels of Gauss-Legendre nodes in theta_h concentrated near 0 (``BREAKS``) and the
    midpoint rule in phi_h (periodic); pairs with w_o below the horizon contribute 0.
    """
    ti, wti = _gauss(0.0, np.pi / 2, n_theta_i)
    panels = [_gauss(a, b, n_seg) for a, b in zip(BREAKS[:-1], BREAKS[1:], strict=True)]
    th = np.concatenate([p[0] for p in panels])
    wth = np.concatenate([p[1] for p in panels])
    ph = (np.arange(n_phi) + 0.5) * 2.0 * np.pi / n_phi
    t, p = np.meshgrid(th, ph, indexing="ij")
    h = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    wh = (np.sin(t) * wth[:, None] * (2.0 * np.pi / n_phi)).reshape(-1)
    total = 0.0
    for theta, w in zip(ti, wti, strict=True):
        wi = np.array([np.sin(theta), 0.0, np.cos(theta)])
        d = h @ wi
        wo = 2.0 * d[:, None] * h - wi
        ok = (d > 0.0) & (wo[:, 2] > 0.0)
        wo = wo[ok] / np.linalg.norm(wo[ok], axis=1)[:, None]
        f = brdf.eval(wi, wo)
        if other is not None:
            f = f - other.eval(wi, wo)
        q = f * wi[2] * wo[:, 2]
        total += 2.0 * np.pi * np.sin(theta) * w * np.sum(wh[ok] * 4.0 * d[ok] * q * q)
    return total


SHARP = {"beckmann": CookTorrance(0.0, 0.05, "beckmann"), "ggx": CookTorrance(0.0, 0.05, "ggx")}


@pytest.fixture(scope="module")
def dense_norms() -> dict[str, float]:
    return {k: dense_q2(b) for k, b in SHARP.items()}


def test_dense_reference_is_converged():
    """The dense rule against itself refined (more nodes in every coordinate): relative
    change 1e-6 at most (measured: 7e-9 Beckmann, 2e-9 GGX), so it is a reference to far
    better than the 1-2 % asked of the sampler."""
    b = SHARP["beckmann"]
    coarse = dense_q2(b, n_theta_i=32, n_seg=24, n_phi=96)
    fine = dense_q2(b)
    assert abs(coarse / fine - 1.0) < 1e-6


# -- (1) the weights integrate over H x H ------------------------------------------------------

@pytest.mark.parametrize("fraction", [0.0, 0.5, 0.9])
def test_weights_integrate_closed_forms(fraction):
    """Closed forms over H x H: int 1 = (2 pi)^2, int z_i z_o = pi^2, int (z_i z_o)^2 =
    (2 pi / 3)^2 (int_H z^k dw = 2 pi / (k + 1)); within K_SIGMA replicate standard errors and
    within 1 % (the standard errors are ~0.1 % at n = 16384)."""
    s = peak_resolving_pairs(N, seed=3, mirror_fraction=fraction)
    zz = s.wi[:, 2] * s.wo[:, 2]
    for g, exact in [(np.ones(len(s)), (2 * np.pi) ** 2), (zz, np.pi ** 2),
                     (zz * zz, (2 * np.pi / 3) ** 2)]:
        est, se = replicate_mean_and_stderr(s, g)
        assert np.isclose(est, float(np.sum(s.weights * g)), rtol=1e-12)
        # the uniform sampler integrates constants exactly (equal weights): rounding only
        assert abs(est - exact) <= K_SIGMA * se + 1e-12 * exact
        assert abs(est / exact - 1.0) < 0.01


def test_pairs_are_unit_upper_and_weights_bounded():
    """Every pair is a unit vector pair above the horizon; draws below it were dropped and
    still count (len <= draws); each weight is at most (2 pi)^2 / (R n_0), the bound given by
    the uniform component alone (n_0 = the uniform draws of a replicate)."""
    s = peak_resolving_pairs(N, seed=1, mirror_fraction=0.5)
    for w in (s.wi, s.wo):
        np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, rtol=0, atol=1e-14)
        assert np.all(w[:, 2] >= 0.0)
    assert s.draws == N and 0.9 * N < len(s) <= N
    n0 = (N // s.replicates) // 2  # mirror_fraction 0.5 of 1024 draws per replicate
    assert np.all(s.weights > 0.0)
    assert s.weights.max() <= (2 * np.pi) ** 2 / (s.replicates * n0) * (1 + 1e-12)
    assert not s.wi.flags.writeable and not s.weights.flags.writeable
    assert "dropped" in s.description and f"{N} draws" in s.description


# -- (2) sharp lobes: against the dense reference, and the uniform sampler ----------------------

@pytest.mark.parametrize("name", list(SHARP))
def test_sharp_lobe_norm_matches_dense_reference(name, dense_norms):
    """||q||^2 of Cook-Torrance with roughness 0.05 (kd = 0, F = 1): the peak-resolving
    estimate agrees with the dense half-vector quadrature ``dense_q2`` within 1.5 % (measured
    at seeds 0-5: within 0.38 %, standard errors 0.2-0.4 %) and within K_SIGMA standard errors.
    A uniform sampler with the same n (mirror_fraction = 0) is off by much more: over six
    seeds its RMS deviation is > 10x that of the peak-resolving sampler (measured: 7.1 % vs
    0.18 % for Beckmann, ratio 39; 9.3 % vs 0.16 % for GGX, ratio 58)."""
    brdf, ref = SHARP[name], dense_norms[name]
    dev = {}
    for fraction in (0.5, 0.0):
        devs = []
        for seed in range(6):
            s = peak_resolving_pairs(N, seed=seed, mirror_fraction=fraction)
            q = brdf.eval(s.wi, s.wo) * s.wi[:, 2] * s.wo[:, 2]
            est, se = replicate_mean_and_stderr(s, q * q)
            if fraction > 0:
                assert abs(est / ref - 1.0) < 0.015
                assert abs(est - ref) < K_SIGMA * se
            devs.append(est / ref - 1.0)
        dev[fraction] = float(np.sqrt(np.mean(np.square(devs))))
    ratio = dev[0.0] / dev[0.5]
    print(f"{name}: RMS relative deviation from the dense reference over 6 seeds, "
          f"peak-resolving {dev[0.5]:.2e}, uniform {dev[0.0]:.2e}, ratio {ratio:.0f}")
    assert dev[0.5] < 0.005
    assert ratio > 10.0


# -- (3) the l2 error of a deliberately wrong lobe ---------------------------------------------

@pytest.mark.parametrize("name", list(SHARP))
def test_wrong_lobe_l2_matches_dense_reference(name, dense_norms):
    """Roughness 0.06 against 0.05: sqrt(int (q_06 - q_05)^2 / int q_05^2) from ``dense_q2``
    (0.2349 Beckmann, 0.2118 GGX) against ``brdf_errors``: within K_SIGMA reported standard
    errors and within 1 %. The log metric is checked against its definition."""
    ref_brdf = SHARP[name]
    wrong = CookTorrance(0.0, 0.06, name)
    exact = np.sqrt(dense_q2(wrong, ref_brdf) / dense_norms[name])
    s = peak_resolving_pairs(N, seed=11)
    e = brdf_errors(ref_brdf, wrong, s)
    assert set(e) == {"l2", "log", "l2_stderr"}
    assert 0.0 < e["l2_stderr"] < 0.01 * e["l2"]
    assert abs(e["l2"] - exact) < K_SIGMA * e["l2_stderr"]
    assert abs(e["l2"] / exact - 1.0) < 0.01
    f, g = ref_brdf.eval(s.wi, s.wo), wrong.eval(s.wi, s.wo)
    assert e["l2"] == pytest.approx(relative_l2(f, g, s), rel=1e-12)
    ci = s.wi[:, 2]
    d = np.log1p(f * ci) - np.log1p(g * ci)
    assert e["log"] == pytest.approx(np.sqrt(np.sum(s.weights * d * d) / s.weights.sum()),
                                     rel=1e-12)


def test_reported_stderr_is_calibrated():
    """The reported l2_stderr describes the real scatter: over 24 seeds the standard
    deviation of the l2 estimates is within a factor 2 of the mean reported standard error
    (measured ratio ~1; the bound allows for the ~15 % sampling error of a 24-seed standard
    deviation and for the 15-degree-of-freedom replicate estimates)."""
    a, b = CookTorrance(0.1, 0.05, "ggx"), CookTorrance(0.1, 0.06, "ggx")
    l2, se = [], []
    for seed in range(24):
        e = brdf_errors(a, b, peak_resolving_pairs(4096, seed=100 + seed))
        l2.append(e["l2"])
        se.append(e["l2_stderr"])
    ratio = float(np.std(l2, ddof=1) / np.mean(se))
    print(f"scatter / reported stderr = {ratio:.2f}")
    assert 0.5 < ratio < 2.0


# -- metrics ----------------------------------------------------------------------------------

def test_metrics_closed_forms_and_channels():
    """f_hat = (1 + e) f gives relative l2 = e exactly in every channel; log_rms of f_hat = f
    is 0 and negative f_hat counts as 0 (so log_rms(f, -f) = log_rms(f, 0))."""
    s = peak_resolving_pairs(2048, seed=2)
    f = Lambert([0.2, 0.5, 0.8]).eval(s.wi, s.wo)
    g = f * np.array([1.1, 0.8, 1.0])
    np.testing.assert_allclose(relative_l2(f, g, s, per_channel=True), [0.1, 0.2, 0.0],
                               rtol=1e-12, atol=1e-15)
    assert relative_l2(f, g, s) == pytest.approx(0.2, rel=1e-12)
    assert log_rms(f, f, s) == 0.0
    assert log_rms(f, -f, s) == log_rms(f, np.zeros_like(f), s) > 0.0
    assert log_rms(f, g, s, per_channel=True).shape == (3,)
    e = brdf_errors(Lambert([0.2, 0.5, 0.8]), Lambert(0.5), s)  # one channel broadcasts
    assert e["l2"] == pytest.approx(1.5, rel=1e-12) and e["l2_stderr"] < 1e-12


# -- (4) determinism ---------------------------------------------------------------------------

def test_deterministic_for_a_seed():
    """The same arguments give the same pairs bit for bit; another seed gives other pairs."""
    a = peak_resolving_pairs(1000, seed=7, widths=(0.05, 0.2))
    b = peak_resolving_pairs(1000, seed=7, widths=(0.05, 0.2))
    c = peak_resolving_pairs(1000, seed=8, widths=(0.05, 0.2))
    for name in ("wi", "wo", "weights", "replicate"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.description == b.description
    assert not np.array_equal(a.wo[:100], c.wo[:100])


# -- (5) bad input ----------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, error, match", [
    ({"n": 2.0}, TypeError, "n must be an integer"),
    ({"n": -1}, ValueError, "n must be >= 0"),
    ({"n": 50}, ValueError, r"n must be >= \d+ so that each of the 16 replicates"),
    ({"seed": -3}, ValueError, "seed must be >= 0"),
    ({"seed": 1.5}, TypeError, "seed must be an integer"),
    ({"mirror_fraction": 1.0}, ValueError, r"mirror_fraction must lie in \[0, 1\)"),
    ({"mirror_fraction": -0.1}, ValueError, r"mirror_fraction must lie in \[0, 1\)"),
    ({"mirror_fraction": "half"}, TypeError, "mirror_fraction must be a number"),
    ({"widths": ()}, ValueError, "widths must hold at least one"),
    ({"widths": (0.1, 0.0)}, ValueError, "widths must be finite, > 0"),
    ({"widths": (0.1, np.inf)}, ValueError, "widths must be finite, > 0"),
    ({"widths": 0.1}, TypeError, "widths must be a sequence of numbers"),
    ({"widths": ("a",)}, TypeError, "widths must be a sequence of numbers"),
    ({"replicates": 1}, ValueError, "replicates must be >= 2"),
])
def test_bad_sampler_arguments(kwargs, error, match):
    args = {"n": 4096, **kwargs}
    with pytest.raises(error, match=match):
        peak_resolving_pairs(args.pop("n"), **args)


def test_bad_metric_arguments():
    s = peak_resolving_pairs(256)
    f = np.full(len(s), 0.3)
    with pytest.raises(TypeError, match="samples must be a PairSamples"):
        relative_l2(f, f, {"wi": s.wi})
    with pytest.raises(ValueError, match="f_hat must have shape"):
        relative_l2(f, f[:-1], s)
    with pytest.raises(ValueError, match="f and f_hat must have the same shape"):
        relative_l2(f, np.stack([f, f], 1), s)
    with pytest.raises(ValueError, match="f must be finite"):
        relative_l2(np.where(np.arange(len(s)) == 3, np.nan, f), f, s)
    with pytest.raises(ValueError, match="f must not be 0 at every pair"):
        relative_l2(0 * f, f, s)
    with pytest.raises(ValueError, match="f must be >= 0 for the log metric"):
        log_rms(-f, f, s)
    with pytest.raises(TypeError, match="approx must be a BRDF"):
        brdf_errors(Lambert(0.3), "lambert", s)
    with pytest.raises(ValueError, match="same number of channels"):
        brdf_errors(Lambert([0.3, 0.4]), Lambert([0.3, 0.4, 0.5]), s)
