"""fit_model and FittedModel: parameter recovery from each family's own noise-free data, the
fitted models equal the library's own models where they coincide, the BRDF contract, the
reported errors and parameter standard errors recomputed independently, warnings on
non-convergence, bad input, and one fit of a MERL-format surrogate (skipped when ../shared is
absent)."""

from __future__ import annotations

import numpy as np
import pytest

from project.brdf import BRDF
from project.fitting import FAMILIES, FittedModel, fit_model
from project.models import CookTorrance, GlossyPaint, Lafortune, Lambert
from project.sampling import brdf_errors, peak_resolving_pairs

SQRT2 = np.sqrt(2.0)
#: small problems keep the file fast; the sampler still resolves lobes of these widths
FAST = {"n": 2048, "restarts": 2, "error_n": 4096}


def lafortune_params(kd, rho, t, n):
    """Parameters of the "lafortune" family from t = n log(-Cx) per lobe (Cz = 1)."""
    t, n = np.atleast_1d(t), np.atleast_1d(n)
    return {"kd": kd, "rho": rho, "cx": -np.exp(t / n), "cz": np.ones(n.size), "n": n}


TRUTH = {
    "lambert+ggx": {"kd": [0.3, 0.2, 0.1], "ks": [0.8, 0.9, 1.0], "alpha": 0.08, "f0": 0.3},
    "lambert+beckmann": {"kd": [0.1, 0.25, 0.4], "ks": [0.5, 0.5, 0.6], "alpha": 0.15,
                         "f0": 0.1},
    # an off-specular lobe (Cx = -exp(1.5 / 40) = -1.038: it grows towards grazing)
    "lafortune": lafortune_params([0.2, 0.3, 0.4], [[0.5, 0.4, 0.3]], 1.5, 40.0),
}


# -- the fitted models are the library's models -------------------------------------------------

@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
def test_microfacet_family_is_cook_torrance(dist):
    """With ks = 1 and f0 = 1 (F = 1) the family is project.models.CookTorrance (separable
    Smith G, ior=None): the lobe is the library's own, evaluated by that class. Agreement to
    1e-12 relative: alpha is stored as log(alpha), and exp(log(alpha)) is within 1 ulp of
    alpha, which the Beckmann exp(-tan^2 / m^2) amplifies by 2 tan^2 / m^2 (< 1400 where
    the value has not underflowed): 1400 x 2.2e-16 = 3e-13 (measured 2.3e-13)."""
    s = peak_resolving_pairs(1024, seed=4)
    m = FittedModel(f"lambert+{dist}", {"kd": [0.5, 0.2, 0.0], "ks": [1.0, 1.0, 1.0],
                                        "alpha": 0.12, "f0": 1.0})
    ref = CookTorrance([0.5, 0.2, 0.0], 0.12, dist)
    np.testing.assert_allclose(m.eval(s.wi, s.wo), ref.eval(s.wi, s.wo), rtol=1e-12, atol=0)


def test_lafortune_family_is_lafortune_model():
    """The "lafortune" family equals project.models.Lafortune (Lafortune et al. 1997, eq. 4)
    with per-channel C = (rho (n + 2)/(2 pi))^(1/n) (Cx, Cx, 1): the normalisation taken out
    of the C's is put back. Agreement to 1e-11 relative: the exponent n and t = n log(-Cx)
    are stored, and the 1/n power then the n-th power lose a few ulp times n."""
    p = lafortune_params([0.1, 0.2, 0.3], [[0.5, 0.4, 0.3], [0.05, 0.1, 0.2]],
                         [0.0, 2.0], [60.0, 3.0])
    m = FittedModel("lafortune", p)
    lobes = []
    for j in range(2):
        scale = (np.asarray(p["rho"][j]) * (p["n"][j] + 2) / (2 * np.pi)) ** (1 / p["n"][j])
        cx = p["cx"][j] * scale
        lobes.append((cx, cx, scale, p["n"][j]))
    ref = Lafortune(p["kd"], lobes)
    s = peak_resolving_pairs(1024, seed=5)
    np.testing.assert_allclose(m.eval(s.wi, s.wo), ref.eval(s.wi, s.wo), rtol=1e-11, atol=0)


# -- recovery ---------------------------------------------------------------------------------

@pytest.mark.parametrize("family", list(TRUTH))
def test_recovers_parameters_from_own_model(family):
    """Noise-free data from the family's own model with known parameters: the truth is the
    global minimum (cost 0), and near a zero-residual minimum Gauss-Newton converges
    quadratically, so the fit stops within rounding of it. Measured relative parameter errors
    <= 1e-9; asserted 1e-6. The l2 error on the independent pairs is ~1e-12 (asserted
    < 1e-6), and its standard error is as small."""
    truth = FittedModel(family, TRUTH[family])
    fit = fit_model(truth, family, **FAST)
    assert fit.family == family and fit.info["converged"]
    for name, value in truth.params.items():
        np.testing.assert_allclose(fit.params[name], value, rtol=1e-6, atol=1e-9,
                                   err_msg=name)
    assert fit.info["l2"] < 1e-6 and fit.info["l2_stderr"] < 1e-6
    assert fit.info["log"] < 1e-6


def test_recovers_with_log_metric():
    """metric="log" reaches the same (exact) minimum from the same starts."""
    truth = FittedModel("lambert+ggx", TRUTH["lambert+ggx"])
    fit = fit_model(truth, "lambert+ggx", metric="log", **FAST)
    assert fit.info["metric"] == "log" and fit.info["fit_log"] < 1e-8
    np.testing.assert_allclose(fit.params["alpha"], 0.08, rtol=1e-6)
    np.testing.assert_allclose(fit.params["ks"], [0.8, 0.9, 1.0], rtol=1e-6)



def _microfacet_residuals(dist, x, wi, wo, f, w, metric):
    """The residuals of project.fitting.model's notes, from project.models.CookTorrance and
    Schlick's Fresnel, x = [kd (3), ks (3), log alpha, f0]."""
    kd, ks, alpha, f0 = x[:3], x[3:6], np.exp(x[6]), x[7]
    ci, co = wi[:, 2:3], wo[:, 2:3]
    cd = 0.5 * np.linalg.norm(wi + wo, axis=1)[:, None]
    lobe = CookTorrance(0.0, alpha, dist).eval(wi, wo)[:, None]
    fm = kd / np.pi + ks * lobe * (f0 + (1.0 - f0) * (1.0 - cd) ** 5)
    if metric == "l2":
        q = f * ci * co
        norm = np.sqrt(np.sum(w[:, None] * q * q, axis=0))
        return (np.sqrt(w)[:, None] * (fm * ci * co - q) / norm).ravel()
    return (np.sqrt(w / w.sum())[:, None] * (np.log1p(fm * ci) - np.log1p(f * ci))).ravel()


@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
@pytest.mark.parametrize("metric", ["l2", "log"])
def test_microfacet_residuals_and_jacobian(dist, metric):
    """The one-pass residuals and closed-form Jacobian (in log alpha) of the microfacet
    families against the residuals written out from project.models.CookTorrance
    (rtol 1e-11: the same formulas in another order, amplified by the Beckmann
    exp(-tan^2 / m^2) as in test_microfacet_family_is_cook_torrance) and against central
    differences of those residuals (step 1e-5 in every parameter: truncation ~1e-10 times
    the third derivative, rounding ~1e-16 / 1e-5 = 1e-11 of the residual scale; asserted
    1e-6 of each column's largest entry)."""
    from project.fitting._geometry import _Geometry
    from project.fitting._solver import _objective
    from project.fitting.microfacet import _Microfacet

    s = peak_resolving_pairs(2048, seed=6)
    f = CookTorrance([0.3, 0.2, 0.1], 0.2, "beckmann", ior=1.5).eval(s.wi, s.wo)
    res, jac, _ = _objective(_Microfacet(dist, 3), _Geometry(s.wi, s.wo), f, s.weights,
                             metric)
    x = np.array([0.2, 0.3, 0.1, 0.5, 0.7, 0.9, np.log(0.15), 0.3])
    ref = _microfacet_residuals(dist, x, s.wi, s.wo, f, s.weights, metric)
    np.testing.assert_allclose(res(x), ref, rtol=1e-11, atol=1e-14 * np.abs(ref).max())
    j = jac(x)
    assert j.shape == (ref.size, x.size)
    h = 1e-5
    for k in range(x.size):
        e = np.zeros(x.size)
        e[k] = h
        fd = (_microfacet_residuals(dist, x + e, s.wi, s.wo, f, s.weights, metric)
              - _microfacet_residuals(dist, x - e, s.wi, s.wo, f, s.weights, metric)) / (2 * h)
        np.testing.assert_allclose(j[:, k], fd, rtol=0, atol=1e-6 * np.abs(fd).max(),
                                   err_msg=f"column {k}")
    # the Jacobian asked for at another point than the last residuals is computed there
    x2 = x + 0.01
    np.testing.assert_allclose(jac(x2)[:, 6], (res(x2 + 1e-5 * np.eye(8)[6])
                                               - res(x2 - 1e-5 * np.eye(8)[6])) / 2e-5,
                               rtol=0, atol=1e-6 * np.abs(jac(x2)[:, 6]).max())


# -- the BRDF contract and the report ----------------------------------------------------------

@pytest.fixture(scope="module")
def misfit():
    """A Beckmann Cook-Torrance (roughness 0.1, kd per channel) fitted by lambert+ggx: the
    family cannot match it, so residuals, errors and standard errors are all non-zero."""
    target = CookTorrance([0.4, 0.3, 0.2], 0.1, "beckmann")
    return target, fit_model(target, "lambert+ggx", **FAST)


def test_fitted_model_obeys_the_brdf_contract(misfit):
    _, fit = misfit
    assert isinstance(fit, BRDF) and fit.channels == 3 and fit.isotropic
    assert fit.nparams == 8 and fit.nbytes == 64
    wi = np.array([[0.6, 0.0, 0.8], [0.0, 0.0, 1.0]])
    assert fit.eval(wi[0], wi[1]).shape == (3,)
    assert fit.eval(wi[:, None, :], wi[None, :, :]).shape == (2, 2, 3)
    below = np.array([0.6, 0.0, -0.8])
    np.testing.assert_array_equal(fit.eval(below, wi[1]), 0.0)
    np.testing.assert_array_equal(fit.eval(wi[0], below), 0.0)
    s = peak_resolving_pairs(512, seed=9)
    f = fit.eval(s.wi, s.wo)
    assert np.all(np.isfinite(f)) and np.all(f >= 0)
    np.testing.assert_allclose(fit.eval(s.wo, s.wi), f, rtol=1e-12)  # reciprocal
    assert fit.albedo(wi[1], n_theta=64, n_phi=64).shape == (3,)
    with pytest.raises(ValueError):
        fit.params["kd"][0] = 1.0  # read-only


def test_info_errors_are_on_independent_pairs(misfit):
    """info["l2"], ["log"], ["l2_stderr"] equal brdf_errors on
    peak_resolving_pairs(error_n, seed=seed + 1), recomputed here, not on the fitting pairs."""
    target, fit = misfit
    e = brdf_errors(target, fit, peak_resolving_pairs(FAST["error_n"], seed=1))
    for key in ("l2", "log", "l2_stderr"):
        assert fit.info[key] == pytest.approx(e[key], rel=1e-12)
    assert 0 < fit.info["l2_stderr"] < 0.1 * fit.info["l2"]
    info = fit.info
    assert len(info["cost"]) == info["restarts"] == 2 and len(info["status"]) == 2
    assert info["cost"][info["best_restart"]] == min(info["cost"])
    assert info["iterations"] >= 1 and info["seconds"] > 0
    assert set(info["param_stderr"]) == set(fit.params)


def test_param_stderr_matches_the_formula(misfit):
    """param_stderr recomputed independently: the l2 residuals sqrt(w) (q_fit - q) / ||q_c||
    on the fitting pairs (seed 0), differentiated numerically in the natural parameters
    (forward differences, upwards because kd sits at its bound 0; step 1e-7 relative), then
    sqrt(diag((J^T J)^-1) sum r^2 / (m - p)). Agreement to 1e-3 relative (forward-difference
    error ~1e-7 relative; the log scale of alpha in the fit is a linear change of variables
    at the optimum)."""
    target, fit = misfit
    s = peak_resolving_pairs(FAST["n"], seed=0)
    cc = (s.wi[:, 2] * s.wo[:, 2])[:, None]
    q = target.eval(s.wi, s.wo) * cc
    scale = np.sqrt(s.weights)[:, None] / np.sqrt(np.sum(s.weights[:, None] * q * q, 0))
    names = [("kd", i) for i in range(3)] + [("ks", i) for i in range(3)] + \
        [("alpha", None), ("f0", None)]

    def residual(params):
        return (scale * (FittedModel("lambert+ggx", params).eval(s.wi, s.wo) * cc - q)).ravel()

    base = {k: np.array(v, dtype=float) for k, v in fit.params.items()}
    r = residual(base)
    jac = []
    for name, i in names:
        p = {k: v.copy() for k, v in base.items()}
        h = 1e-7 * max(abs(float(p[name][i] if i is not None else p[name])), 1e-3)
        if i is None:
            p[name] = p[name] + h
        else:
            p[name][i] += h
        jac.append((residual(p) - r) / h)
    jac = np.array(jac).T
    s2 = r @ r / (r.size - len(names))
    expect = np.sqrt(np.diag(np.linalg.inv(jac.T @ jac)) * s2)
    got = np.concatenate([np.ravel(fit.info["param_stderr"][k]) for k in
                          ("kd", "ks", "alpha", "f0")])
    np.testing.assert_allclose(got, expect, rtol=1e-3)


# -- warnings and errors -----------------------------------------------------------------------

def test_warns_when_not_converged():
    target = CookTorrance([0.4, 0.3, 0.2], 0.1, "beckmann")
    with pytest.warns(RuntimeWarning, match=r"did not converge: every one of the 2 restarts "
                      r"stopped at max_nfev=2; best l2 error reached on the fitting pairs "
                      r"\d\.\d+"):
        fit = fit_model(target, "lafortune", max_nfev=2, **FAST)
    assert fit.info["converged"] is False and fit.info["status"] == [0, 0]


def test_warns_on_delta_terms():
    with pytest.warns(UserWarning, match="delta"):
        fit_model(GlossyPaint(0.5, 0.3), "lambert+ggx", **FAST)


class _Values(BRDF):
    """A BRDF returning fixed values (to feed bad data to fit_model)."""

    channels = 3
    _scalar = False

    def __init__(self, value):
        self.value = value

    def _eval(self, wi, wo):
        out = np.full((wi.shape[0], 3), 0.1)
        out[0] = self.value
        return out


@pytest.mark.parametrize("call, error, match", [
    (lambda: fit_model(Lambert(0.5), "phong"), ValueError,
     "family must be one of 'lambert\\+ggx', .*'factored'.*, got 'phong'"),
    (lambda: fit_model(Lambert(0.5), "lambert+ggx", metric="l1"), ValueError,
     "metric must be one of 'l2', 'log'"),
    (lambda: fit_model(Lambert(0.5), "lambert+ggx", restart=3), TypeError,
     "unknown option\\(s\\) 'restart'; the options are 'n', 'seed', 'restarts'"),
    (lambda: fit_model(Lambert(0.5), "lambert+ggx", lobes=2), ValueError,
     "option 'lobes' applies to families 'lafortune' and 'dsbrdf' only"),
    (lambda: fit_model(Lambert(0.5), "lafortune", lobes=0), ValueError, "lobes must be >= 1"),
    (lambda: fit_model(Lambert(0.5), "lafortune", lobes=9), ValueError, "lobes must be <= 8"),
    (lambda: fit_model(Lambert(0.5), "lambert+ggx", restarts=0), ValueError,
     "restarts must be >= 1"),
    (lambda: fit_model(Lambert(0.5), "lambert+ggx", restarts=2.0), TypeError,
     "restarts must be an integer"),
    (lambda: fit_model(Lambert(0.5), "lambert+ggx", max_nfev=0), ValueError,
     "max_nfev must be >= 1 or None"),
    (lambda: fit_model(Lambert(0.5), "lambert+ggx", seed=3, error_seed=3), ValueError,
     "error_seed must differ from seed"),
    (lambda: fit_model(Lambert(0.5), "lambert+ggx", n=10), ValueError, "n must be >= "),
    (lambda: fit_model(Lambert(0.5), "lambert+ggx", widths=(0.0,)), ValueError,
     "widths must be finite, > 0"),
    (lambda: fit_model("lambert", "lambert+ggx"), TypeError,
     "brdf must be a BRDF \\(an object with eval\\(wi, wo\\)\\) or project.Measurements, got str"),
    (lambda: fit_model(_Values(np.nan), "lambert+ggx", **FAST), ValueError,
     "brdf must be finite at the fitting pairs: 3 values are NaN or inf"),
    (lambda: fit_model(_Values(-1.0), "lambert+ggx", **FAST), ValueError,
     "brdf must be >= 0 at the fitting pairs: 3 values are negative, min -1"),
    (lambda: fit_model(Lambert([0.5, 0.0]), "lambert+ggx", **FAST), ValueError,
     "brdf must not be 0 at every fitting pair \\(channel 1\\)"),
])
def test_bad_input(call, error, match):
    with pytest.raises(error, match=match):
        call()


@pytest.mark.parametrize("family, params, error, match", [
    ("ggx", {}, ValueError, "family must be one of"),
    ("lambert+ggx", [1, 2], TypeError, "params must be a dict"),
    ("lambert+ggx", {"kd": 0.5, "ks": 0.5, "alpha": 0.1}, ValueError,
     "params of family 'lambert\\+ggx' must be exactly \\['alpha', 'f0', 'kd', 'ks'\\]"),
    ("lambert+ggx", {"kd": [0.5, 0.5], "ks": [0.5], "alpha": 0.1, "f0": 0.5}, ValueError,
     "params\\['ks'\\] must have shape \\(2,\\)"),
    ("lambert+ggx", {"kd": 0.5, "ks": -0.5, "alpha": 0.1, "f0": 0.5}, ValueError,
     "params\\['ks'\\] must be finite and >= 0"),
    ("lambert+ggx", {"kd": 0.5, "ks": 0.5, "alpha": 0.0, "f0": 0.5}, ValueError,
     "alpha must be > 0"),
    ("lambert+ggx", {"kd": 0.5, "ks": 0.5, "alpha": "rough", "f0": 0.5}, TypeError,
     "params\\['alpha'\\] must be numbers"),
    ("lafortune", {"kd": [0.1], "rho": [[0.5]], "cx": [-1.0], "cz": [1.1], "n": [10.0]},
     ValueError, "cz must be 1 \\(the scale of C is in rho\\) and cx < 0"),
    ("lafortune", {"kd": [0.1], "rho": [[0.5]], "cx": [0.5], "cz": [1.0], "n": [10.0]},
     ValueError, "cz must be 1 \\(the scale of C is in rho\\) and cx < 0"),
])
def test_bad_params(family, params, error, match):
    with pytest.raises(error, match=match):
        FittedModel(family, params)


def test_families_listed():
    assert FAMILIES == ("lambert+ggx", "lambert+beckmann", "lafortune", "factored", "dsbrdf",
                        "rr8807", "tabulated", "tucker", "grid")


# -- the factored family ------------------------------------------------------------------------

def test_factored_family_recovers_a_member():
    """fit_model(..., "factored") on a FactoredLobe with the same nodes: the table is
    recovered to rounding (as fit_factored itself, tests/project/test_factored.py), and
    the errors of info, measured on independent peak-resolving pairs, are ~0."""
    from project.factored import FactoredLobe

    rng = np.random.default_rng(3)
    true = FactoredLobe([0.2, 0.3, 0.1], 0.1 + rng.random((1, 16, 1)) * [[[1.0]]] * 5,
                        0.5 + rng.random((1, 8, 3)))
    fit = fit_model(true, "factored", rank=1, bins=(16, 8), color="theta_d",
                    error_n=4096)
    assert isinstance(fit, FittedModel) and fit.family == "factored"
    assert fit.info["converged"] and fit.info["fit_l2"] < 1e-9
    assert fit.info["l2"] < 1e-8 and fit.info["log"] < 1e-8
    assert fit.nparams == 3 + 16 + 8 * 3 and fit.nbytes == 8 * fit.nparams
    wi = np.array([[0.3, 0.1, 0.9], [0.8, 0.0, 0.2]])
    wo = np.array([[-0.2, 0.3, 0.9], [0.1, 0.6, 0.5]])
    wi, wo = (w / np.linalg.norm(w, axis=1, keepdims=True) for w in (wi, wo))
    np.testing.assert_allclose(fit.eval(wi, wo), true.eval(wi, wo), rtol=1e-8)


def test_factored_params_rebuild_the_model():
    """FittedModel("factored", params) from a fit's params evaluates bit for bit alike,
    params carry the warps, and the family refuses what it does not know."""
    from project.models import CookTorrance

    fit = fit_model(CookTorrance(0.1, 0.3, "ggx", ior=1.5), "factored", rank=1,
                    bins=(12, 8, 4), error_n=1024)
    assert set(fit.params) == {"kd", "h_table", "d_table", "phi_table", "warp", "warp_d"}
    again = FittedModel("factored", fit.params)
    v = np.random.default_rng(0).normal(size=(2, 500, 3)) + [0.0, 0.0, 1.5]
    wi, wo = v / np.linalg.norm(v, axis=-1, keepdims=True)
    np.testing.assert_array_equal(again.eval(wi, wo), fit.eval(wi, wo))
    assert again.eval(wi, wo).shape == (500,)
    assert "rank=1, bins=(12, 8, 4)" in repr(fit)
    with pytest.raises(ValueError, match="exponent of one of the warps"):
        FittedModel("factored", {**fit.params, "warp": 2.5})
    with pytest.raises(ValueError, match="must hold"):
        FittedModel("factored", {"kd": [0.1], "h_table": [[1.0, 2.0]]})
    with pytest.raises(ValueError, match="l2 metric only"):
        fit_model(CookTorrance(0.1, 0.3, "ggx"), "factored", metric="log")
    with pytest.raises(TypeError, match="its options are"):
        fit_model(CookTorrance(0.1, 0.3, "ggx"), "factored", lobes=2)


# -- a MERL-format surrogate -------------------------------------------------------------------

def test_blue_acrylic_lambert_ggx(merl_surrogate):
    """lambert+ggx on the MERL-format surrogate of blue-acrylic (the Sztrajman et al. 2021
    neural fit written on the MERL grid): a one-lobe fit cannot follow this sharp, bright
    highlight and the Lambert floor together. Measured (default n = 16384, seeds 0/1): l2 =
    0.599 with standard error 0.004 (largest in the blue channel), alpha = 0.008, log RMS
    0.018; 4 restarts all reach the same cost. Asserted: the error is reported with a
    standard error below 0.02 and lies in [0.55, 0.62] (0.599 +- ~5 standard errors)."""
    from project.measured import read_merl

    brdf = read_merl(merl_surrogate("blue-acrylic"))
    fit = fit_model(brdf, "lambert+ggx", restarts=1)
    info = fit.info
    print(f"blue-acrylic lambert+ggx: l2 {info['l2']:.4f} +- {info['l2_stderr']:.4f}, "
          f"log {info['log']:.4f}, {fit}, {info['seconds']:.1f} s")
    assert info["converged"]
    assert 0.0 < info["l2_stderr"] < 0.02
    assert 0.55 < info["l2"] < 0.62


# -- dsbrdf (Nishino & Lombardi) and rr8807 (Holzschuch & Pacanowski 2015) ---------------------

def dsbrdf_params(lobes):
    """kappa and gamma (lobes, 6, 3) from per-lobe (kappa at theta_d = 0 and pi/2, gamma at
    theta_d = 0 and pi/2), linear in the spline coefficients, and a colour per channel."""
    kappa = np.empty((len(lobes), 6, 3))
    gamma = np.empty_like(kappa)
    for j, (k0, k1, g0, g1) in enumerate(lobes):
        kappa[j] = np.linspace(k0, k1, 6)[:, None] * [[1.0, 0.8, 0.6]]
        gamma[j] = np.linspace(g0, g1, 6)[:, None] * [[1.0, 1.1, 1.2]]
    return {"kappa": kappa, "gamma": gamma}


RR8807_TRUTH = {"kd": [0.1, 0.2, 0.3], "ks": [0.8, 0.6, 0.5], "kw": [0.02, 0.03, 0.01],
                "f0": [0.1, 0.2, 0.5], "sigma": 0.05, "p": 0.6, "a": 0.9}
DSBRDF_TRUTH = dsbrdf_params([(3.0, 2.0, 200.0, 100.0), (0.4, 0.3, 0.8, 0.5)])
NEW_TRUTH = {"dsbrdf": DSBRDF_TRUTH, "rr8807": RR8807_TRUTH}


@pytest.mark.parametrize("family", ["dsbrdf", "rr8807"])
@pytest.mark.parametrize("metric", ["l2", "log"])
def test_new_families_recover_parameters(family, metric):
    """Noise-free data from the family itself (as test_recovers_parameters_from_own_model).
    rr8807: every parameter recovered to 1e-6 relative (measured <= 3e-12 in l2). dsbrdf
    (two lobes, fitted channel by channel): the zero-residual minimum is reached (l2 ~1e-6
    measured), but the last spline coefficient of the broad lobe only acts for theta_d near
    pi/2 on a lobe ~0.3 high, so the fit stops (ftol) with it known to a few 1e-3: asserted
    2e-2 relative, and the whole model to l2 < 1e-4."""
    truth = FittedModel(family, NEW_TRUTH[family])
    opts = {"lobes": 2} if family == "dsbrdf" else {}
    fit = fit_model(truth, family, metric=metric, **FAST, **opts)
    assert fit.family == family and fit.info["converged"]
    tol = 1e-6 if family == "rr8807" else 2e-2
    for name, value in truth.params.items():
        np.testing.assert_allclose(fit.params[name], value, rtol=tol, atol=1e-9, err_msg=name)
    assert fit.info["l2"] < (1e-6 if family == "rr8807" else 1e-4)
    assert set(fit.info["param_stderr"]) == set(fit.params)
    again = FittedModel(family, {k: np.array(v) for k, v in fit.params.items()})
    s = peak_resolving_pairs(256, seed=7)
    np.testing.assert_array_equal(again.eval(s.wi, s.wo), fit.eval(s.wi, s.wo))


@pytest.mark.parametrize("family", ["dsbrdf", "rr8807"])
def test_new_families_obey_the_contract(family):
    """Reciprocity to rounding (both depend on i, o only through symmetric quantities:
    theta_h, theta_d and, for rr8807, the separable G), shapes, zero below the horizon,
    finite and >= 0 everywhere above it, grazing included."""
    m = FittedModel(family, NEW_TRUTH[family])
    assert m.channels == 3 and m.isotropic
    s = peak_resolving_pairs(2048, seed=11)
    f = m.eval(s.wi, s.wo)
    assert f.shape == (len(s), 3) and np.all(np.isfinite(f)) and np.all(f >= 0.0)
    np.testing.assert_allclose(m.eval(s.wo, s.wi), f, rtol=1e-12, atol=0)
    horizon = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    up = np.array([0.3, 0.0, np.sqrt(0.91)])
    g = m.eval(horizon, up)
    assert np.all(np.isfinite(g)) and np.all(g >= 0.0)
    np.testing.assert_array_equal(m.eval(np.array([0.6, 0.0, -0.8]), up), 0.0)
    np.testing.assert_array_equal(m.eval(up, np.array([0.0, 0.6, -0.8])), 0.0)
    assert m.eval(up[None, None], s.wo[:6].reshape(2, 3, 3)).shape == (2, 3, 3)


def test_dsbrdf_is_the_sum_of_hemi_epd_lobes():
    """Nishino & Lombardi eq. 6 with constant curves: each lobe is exp(kappa cos^gamma
    theta_h) - 1, independent of theta_d and phi_d; the B-spline of a constant is that
    constant (partition of unity), so constant coefficients give constant curves."""
    m = FittedModel("dsbrdf", {"kappa": np.full((2, 6, 1), [[[2.0]], [[0.3]]]),
                               "gamma": np.full((2, 6, 1), [[[50.0]], [[1.0]]])})
    s = peak_resolving_pairs(512, seed=2)
    h = s.wi + s.wo
    ct = h[:, 2] / np.linalg.norm(h, axis=1)
    expect = np.expm1(2.0 * ct ** 50) + np.expm1(0.3 * ct)
    np.testing.assert_allclose(m.eval(s.wi, s.wo), expect, rtol=1e-12)
    assert m.nparams == 2 * 2 * 6 and m.nbytes == 8 * 24
    # the paper's count: 108 reals for three lobes on RGB (2 x 3 x 3 x 18 / 3)
    assert FittedModel("dsbrdf", dsbrdf_params([(1, 1, 1, 1)] * 3)).nparams == 108


def _epd_reference_lambda(m, p):
    """Smith Lambda of P22 ~ exp(-(x / sigma^2)^p) by adaptive quadrature in the marginal
    slope form (Heitz 2014): Lambda = int_m^inf (s - m) P2(s) ds / m with P2 the full-line
    marginal, P2(s) = p / (pi Gamma(1/p)) int_R exp(-(s^2 + t^2)^p) dt."""
    from scipy.integrate import quad
    from scipy.special import gamma

    def p2(s):
        return 2 * quad(lambda t: np.exp(-(s * s + t * t) ** p), 0, np.inf)[0]

    val = quad(lambda s: (s - m) * p2(s), m, np.inf, limit=200)[0]
    return p / (np.pi * gamma(1 / p)) * val / m


def test_rr8807_shadowing_is_smith_for_its_distribution():
    """The Lambda of rr8807 (one-dimensional quadrature, splined in log m): (1) at p = 1 the
    distribution is Beckmann with m = sigma, and Lambda equals the closed form
    (erfc form of Walter et al. 2007) to 1e-7; (2) for p = 0.51 (the report's nickel) it
    equals an independent double adaptive quadrature of the marginal form to 1e-6; (3) the
    projected-area identity int G1(o, m) <o, m> D(m) dm = cos theta_o (Heitz 2014, eq. 9)
    holds to 1e-4 at three angles. Holzschuch & Pacanowski's eq. 20 integrates the marginal
    over q in [0, inf) only, which halves Lambda: with it the identity fails by >1e-2 (checked
    here too), so the implementation integrates over the whole line."""
    from scipy.special import erfc, gammaln

    from project.fitting.rr8807 import _epd_lambda

    m = np.array([0.05, 0.3, 1.0, 2.0, 3.5])
    beck = 0.5 * (np.exp(-m * m) / (m * np.sqrt(np.pi)) - erfc(m))
    np.testing.assert_allclose(_epd_lambda(m, 1.0), beck, rtol=1e-7)
    for mm in (0.1, 1.0, 4.0):
        assert _epd_lambda(np.array([mm]), 0.51)[0] == pytest.approx(
            _epd_reference_lambda(mm, 0.51), rel=1e-6)
    sigma, p = 0.3, 0.51
    th = np.linspace(0, np.pi / 2, 4001)[1:-1]  # facet normals (theta, phi) midpoint grid
    ph = (np.arange(512) + 0.5) * 2 * np.pi / 512
    tt, pp = np.meshgrid(th, ph, indexing="ij")
    x = np.tan(tt) ** 2
    d = np.exp(np.log(p) - np.log(np.pi) - 2 * np.log(sigma) - gammaln(1 / p)
               - (x / sigma ** 2) ** p) / np.cos(tt) ** 4
    da = np.sin(tt) * (th[1] - th[0]) * (2 * np.pi / 512)
    assert np.sum(d * np.cos(tt) * da) == pytest.approx(1.0, abs=1e-4)  # eq. 19
    for theta_o in (0.3, 1.0, 1.4):
        mo = 1.0 / (sigma * np.tan(theta_o))
        dot = np.maximum(0.0, np.sin(theta_o) * np.sin(tt) * np.cos(pp)
                         + np.cos(theta_o) * np.cos(tt))
        proj = np.sum(dot * d * da)
        lam = _epd_lambda(np.array([mo]), p)[0]
        assert proj / (1 + lam) == pytest.approx(np.cos(theta_o), rel=1e-4)
        if theta_o > 1.0:
            assert abs(proj / (1 + lam / 2) / np.cos(theta_o) - 1) > 1e-2


def test_rr8807_diffraction_energy():
    """E_{a, lambda} is the cosine-weighted albedo of S_z at normal incidence,
    pi / (1 + 1 / (a^2 lambda^2)) (the report prints pi (1 + 1 / (a^2 lambda^2)), the fraction
    bar lost): for a = 0.91 it is 0.80499, 0.58561, 0.44089 at 0.645, 0.526, 0.444 um
    (integrated here independently), and the model's diffraction term with kw = lambda^4
    (kd = ks = 0) has albedo 1 at normal incidence. sigma = 1e-4 makes G = 1 but within
    1e-4 rad of the horizon; measured albedo 1 - 2e-6 (the quadrature of albedo())."""
    lam = np.array([0.645, 0.526, 0.444])
    t = np.linspace(0, np.pi / 2, 200001)
    s_z = 1 / (1 + (np.sin(t)[:, None] / lam) ** 2 / 0.91 ** 2) ** 2  # f = sin(theta_o)/lam
    e = 2 * np.pi * np.trapezoid(s_z * (np.cos(t) * np.sin(t))[:, None], t, axis=0)
    np.testing.assert_allclose(e, [0.80499, 0.58561, 0.44089], atol=1e-5)
    np.testing.assert_allclose(e, np.pi / (1 + 1 / (0.91 * lam) ** 2), rtol=1e-8)
    m = FittedModel("rr8807", {"kd": [0, 0, 0], "ks": [0, 0, 0], "kw": lam ** 4,
                               "f0": [0.5] * 3, "sigma": 1e-4, "p": 1.0, "a": 0.91})
    np.testing.assert_allclose(m.albedo([0.0, 0.0, 1.0], n_theta=512, n_phi=64), 1.0,
                               atol=1e-4)
    # S alone (kw = lambda^4 E) at 0.526 um away from normal incidence: 0.5319, 0.3677,
    # 0.2867 at 30, 60, 80 deg (G and F excluded), computed independently by adaptive
    # quadrature over the exit hemisphere (scipy dblquad, 1e-9), four decimals
    e_g = np.pi / (1 + 1 / (0.91 * 0.526) ** 2)
    green = FittedModel("rr8807", {"kd": [0], "ks": [0], "kw": [0.526 ** 4 * e_g],
                                   "f0": [0.5], "sigma": 1e-4, "p": 1.0, "a": 0.91})
    for deg, expect in ((30, 0.5319), (60, 0.3677), (80, 0.2867)):
        t_i = np.radians(deg)
        a = green.albedo([np.sin(t_i), 0.0, np.cos(t_i)], n_theta=512, n_phi=256)
        assert float(a) == pytest.approx(expect, abs=2e-4)


def test_rr8807_wavelengths():
    """Three channels take the report's RGB wavelengths, one channel its green; others need
    the option, which other families refuse."""
    rgb = FittedModel("rr8807", RR8807_TRUTH)
    np.testing.assert_array_equal(rgb.params["wavelength"], [0.645, 0.526, 0.444])
    assert rgb.nparams == 15 and rgb.nbytes == 120  # the report's 15 parameters
    one = FittedModel("rr8807", {k: (v[1] if isinstance(v, list) else v)
                                 for k, v in RR8807_TRUTH.items()})
    assert one.params["wavelength"].tolist() == [0.526] and one.nparams == 7
    two = {k: (v[:2] if isinstance(v, list) else v) for k, v in RR8807_TRUTH.items()}
    with pytest.raises(ValueError, match="needs the option wavelength"):
        FittedModel("rr8807", two)
    m2 = FittedModel("rr8807", {**two, "wavelength": [0.6, 0.5]})
    fit = fit_model(m2, "rr8807", wavelength=[0.6, 0.5], n=1024, restarts=1, error_n=1024)
    np.testing.assert_allclose(fit.params["sigma"], 0.05, rtol=1e-6)
    with pytest.raises(ValueError, match="'wavelength' applies to family 'rr8807' only"):
        fit_model(Lambert(0.5), "lambert+ggx", wavelength=[0.5])
    with pytest.raises(ValueError, match="wavelength must hold 3 finite values > 0"):
        fit_model(rgb, "rr8807", wavelength=[0.5, -0.5, 0.4], **FAST)


@pytest.mark.parametrize("family, params, error, match", [
    ("dsbrdf", {"kappa": np.ones((2, 5, 3)), "gamma": np.ones((2, 5, 3))}, ValueError,
     "params\\['kappa'\\] must have shape \\(lobes, 6, channels\\)"),
    ("dsbrdf", {"kappa": np.ones((2, 6, 3)), "gamma": np.ones((2, 6, 1))}, ValueError,
     "params\\['gamma'\\] must have shape \\(2, 6, 3\\)"),
    ("dsbrdf", {"kappa": -np.ones((1, 6, 1)), "gamma": np.ones((1, 6, 1))}, ValueError,
     "params\\['kappa'\\] must be finite and >= 0"),
    ("dsbrdf", {"kappa": np.ones((1, 6, 1))}, ValueError,
     "must be exactly \\['gamma', 'kappa'\\]"),
    ("rr8807", {**RR8807_TRUTH, "p": 7.0}, ValueError, "p in \\[0.15, 5.0\\]"),
    ("rr8807", {**RR8807_TRUTH, "sigma": 0.0}, ValueError, "sigma and a must be > 0"),
    ("rr8807", {**RR8807_TRUTH, "kw": [0.1, -0.1, 0.0]}, ValueError,
     "params\\['kw'\\] must be finite and >= 0"),
    ("rr8807", {**RR8807_TRUTH, "wavelength": [0.5, 0.5]}, ValueError,
     "wavelength must hold 3 finite values"),
    ("rr8807", {k: v for k, v in RR8807_TRUTH.items() if k != "a"}, ValueError,
     "must be exactly"),
])
def test_new_families_bad_params(family, params, error, match):
    with pytest.raises(error, match=match):
        FittedModel(family, params)


def test_lobes_option_for_dsbrdf():
    """lobes applies to dsbrdf (default 3, the paper's typical K) as to lafortune."""
    truth = FittedModel("dsbrdf", dsbrdf_params([(2.0, 2.0, 30.0, 30.0)]))
    fit = fit_model(truth, "dsbrdf", lobes=1, n=1024, restarts=1, error_n=1024)
    assert fit.params["kappa"].shape == (1, 6, 3) and fit.info["l2"] < 1e-6
    with pytest.raises(ValueError, match="lobes must be <= 8"):
        fit_model(truth, "dsbrdf", lobes=9)


def test_dsbrdf_energy_bound_of_the_paper_is_not_the_albedo():
    """Nishino & Lombardi state that sum_k 1/C_k <= 1 conserves energy, 1/C_k =
    2 pi int_0^1 (exp(kappa t^gamma) - 1) dt the integral of a lobe over the (theta_h,
    phi_d) hemisphere (their normalisation after eq. 4; at (1, 1) the closed form
    1 / (2 pi (e - 2)) gives C = 0.2215772929). The albedo carries the half-vector Jacobian
    dw_o = 4 cos theta_d dw_h: a sharp lobe reflects 4 cos^2 theta_i / C (measured 3.993
    at normal incidence and 3.076 at 0.5 rad for gamma = 2000), so the bound is not one on
    the albedo; a broad lobe (kappa = gamma = 1) stays near 1 / C (1.04 at normal
    incidence)."""
    from scipy.integrate import quad

    def inv_c(kappa, gamma):
        return 2 * np.pi * quad(lambda t: np.expm1(kappa * t ** gamma), 0, 1,
                                points=[1 - 10 / gamma] if gamma > 10 else None,
                                limit=200)[0]

    assert 1 / inv_c(1.0, 1.0) == pytest.approx(0.2215772929, rel=1e-9)
    sharp = FittedModel("dsbrdf", {"kappa": np.full((1, 6, 1), 2.0),
                                   "gamma": np.full((1, 6, 1), 2000.0)})
    for theta, ratio in ((0.0, 4.0), (0.5, 4 * np.cos(0.5) ** 2)):
        a = sharp.albedo([np.sin(theta), 0.0, np.cos(theta)], n_theta=1024, n_phi=1024)
        assert float(a) / inv_c(2.0, 2000.0) == pytest.approx(ratio, rel=0.01)


def test_rr8807_nickel_near_the_report(merl_surrogate):
    """rr8807 on the MERL-format surrogate of nickel against Holzschuch & Pacanowski's fit
    of the measured nickel (RR-8807, fig. 12a: sigma = 0.027, p = 0.51, a = 0.91 um^-1).
    Measured here (4 restarts, all at one minimum): sigma 0.0242, p 0.466, a 1.30, l2
    0.229. The data (a neural fit of the measurement) and the objective (relative l2 of
    f cos cos on all angles, not their cos^2 theta_i weighted MSE below 1.4 rad, two-step)
    differ, so asserted: sigma and p within 25 % of the report's, a within a factor 2."""
    from project.measured import read_merl

    fit = fit_model(read_merl(merl_surrogate("nickel")), "rr8807", restarts=1)
    p = fit.params
    print(f"nickel rr8807: {fit}, l2 {fit.info['l2']:.4f}, {fit.info['seconds']:.1f} s")
    assert fit.info["converged"]
    assert float(p["sigma"]) == pytest.approx(0.027, rel=0.25)
    assert float(p["p"]) == pytest.approx(0.51, rel=0.25)
    assert 0.91 / 2 < float(p["a"]) < 0.91 * 2


def test_rr8807_sampling_exponent():
    """RR-8807 eq. 23 samples theta_h = arctan(sigma Q^-1(1/p, u)^e) with e = p/2 as
    printed; y = Q^-1(1/p, u) ~ Gamma(1/p), so P(tan^2 theta_h <= X) = P(1/p, (X /
    sigma^2)^(1/(2e))). The distribution of the model (D cos theta_h, integrated here on a
    grid) has P(1/p, (X / sigma^2)^p): e = 1/(2p). Values for sigma = 0.1, p = 0.51 at X =
    0.002, 0.01, 0.03, 0.1: 0.0779, 0.2752, 0.5346, 0.8402 (P(1/p, (X / sigma^2)^p), the
    regularised lower incomplete gamma, to four decimals); the printed exponent gives 0.998
    at X = 0.03."""
    from scipy.special import gammainc, gammaln

    sigma, p = 0.1, 0.51
    t = np.linspace(0.0, np.arctan(np.sqrt(0.1)), 400001)
    x = np.tan(t) ** 2
    d = np.exp(np.log(p) - np.log(np.pi) - 2 * np.log(sigma) - gammaln(1 / p)
               - (x / sigma ** 2) ** p) / np.cos(t) ** 4
    dens = 2 * np.pi * d * np.cos(t) * np.sin(t)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(t))])
    xs = np.array([0.002, 0.01, 0.03, 0.1])
    got = np.interp(xs, x, cdf)
    np.testing.assert_allclose(got, [0.0779, 0.2752, 0.5346, 0.8402], atol=1e-4)
    np.testing.assert_allclose(got, gammainc(1 / p, (xs / sigma ** 2) ** p), atol=1e-6)
    printed = gammainc(1 / p, (0.03 / sigma ** 2) ** (1 / p))
    assert printed == pytest.approx(0.998, abs=1e-3)


# -- fits to measured samples (project.Measurements) ---------------------------------------------

def gonio_pairs():
    """A gonioreflectometer layout: 8 incidences theta_i = 10..80 deg at phi_i = 0, and theta_o
    in {5, 10, 15, 20, 30, ..., 80} deg (the specular theta_o of every incidence among them)
    with phi_o = 0, 20, ..., 340 deg: 8 x 10 x 18 = 1440 pairs."""
    from basis import from_angles

    ti = np.radians(np.arange(10.0, 81.0, 10.0))
    to = np.radians(np.r_[5.0, 10.0, 15.0, np.arange(20.0, 81.0, 10.0)])
    po = np.radians(np.arange(0.0, 360.0, 20.0))
    t, o, p = np.meshgrid(ti, to, po, indexing="ij")
    return from_angles(t.ravel(), 0.0), from_angles(o.ravel(), p.ravel())


GONIO_TRUTH = {"kd": [0.5, 0.3, 0.1], "ks": [0.6, 0.7, 0.8], "alpha": 0.2, "f0": 0.04}


def test_samples_noise_free_recovers_parameters():
    """Lambert + GGX evaluated at 1440 gonioreflectometer pairs is fitted back: the data are in
    the family, so the optimum is the truth and the fit stops on scipy's tolerances (ftol,
    xtol 1e-8): parameters within 1e-6 relative (measured 1e-10), and the cross-validated l2
    error is that of exact predictions, < 1e-6 (measured 4e-10)."""
    from project import Measurements

    wi, wo = gonio_pairs()
    truth = FittedModel("lambert+ggx", GONIO_TRUTH)
    fit = fit_model(Measurements(wi, wo, truth.eval(wi, wo)), "lambert+ggx", restarts=1)
    for k, v in GONIO_TRUTH.items():
        np.testing.assert_allclose(fit.params[k], v, rtol=1e-6, atol=0, err_msg=k)
    assert fit.info["l2"] < 1e-6 and fit.info["folds"] == 10 and len(fit.info["fold_l2"]) == 10
    assert fit.info["converged"] and fit.info["samples"]["count"] == 1440
    assert fit.info["validation"] == "10-fold CV on held-out samples, grouped by direction pair"


def test_samples_with_noise_within_standard_errors():
    """1 % multiplicative Gaussian noise on one channel, weighted by the inverse variance of q
    (w = 1 / q^2): the weighted residuals are then i.i.d., so info["param_stderr"] is a real
    standard error and every parameter lies within 4 of them of the truth (seeded; over 30
    seeds the RMS z-score was 0.9-1.2 per parameter, the largest |z| 3.3). The
    cross-validated l2 error of q is the noise level, the RMS of 1440 draws of 1 % noise:
    0.010 within 8 %, 4 of its relative standard deviations 1 / sqrt(2 n) = 1.9 % (the
    out-of-fold bias, ~p / (2 n) = 0.1 %, is smaller; measured 0.0097, l2_stderr 1.5e-4)."""
    from project import Measurements

    wi, wo = gonio_pairs()
    truth_params = {"kd": [0.3], "ks": [0.7], "alpha": 0.2, "f0": 0.04}
    f = FittedModel("lambert+ggx", truth_params).eval(wi, wo)
    q = f * wi[:, 2] * wo[:, 2]
    noisy = f * (1.0 + 0.01 * np.random.default_rng(5).standard_normal(f.shape))
    fit = fit_model(Measurements(wi, wo, noisy, weights=1.0 / q ** 2), "lambert+ggx",
                    restarts=1)
    se = fit.info["param_stderr"]
    for k, v in truth_params.items():
        z = (fit.params[k] - np.asarray(v)) / se[k]
        assert np.all(np.abs(z) < 4.0), (k, z)
    assert fit.info["l2"] == pytest.approx(0.01, rel=0.08)
    assert 0.0 < fit.info["l2_stderr"] < 0.1 * fit.info["l2"]


def test_samples_weight_zero_does_not_move_the_fit():
    """A corrupted sample (f = 100) of weight 0 leaves the fit as without it (the residual
    rows of weight 0 are 0): parameters equal to 1e-9 relative. With weight 1 it moves them."""
    from project import Measurements

    wi, wo = gonio_pairs()
    sub = slice(0, 1440, 3)
    wi, wo = wi[sub], wo[sub]
    f = FittedModel("lambert+ggx", {"kd": [0.3], "ks": [0.7], "alpha": 0.2, "f0": 0.04}
                    ).eval(wi, wo)
    f = f * (1.0 + 0.01 * np.random.default_rng(2).standard_normal(f.shape))
    bad = f.copy()
    bad[7] = 100.0
    opts = {"restarts": 1, "folds": 0}
    clean = fit_model(Measurements(np.delete(wi, 7, 0), np.delete(wo, 7, 0), np.delete(f, 7)),
                      "lambert+ggx", **opts)
    w = np.ones(len(wi))
    w[7] = 0.0
    zero = fit_model(Measurements(wi, wo, bad, weights=w), "lambert+ggx", **opts)
    moved = fit_model(Measurements(wi, wo, bad), "lambert+ggx", **opts)
    for k in ("kd", "ks", "alpha", "f0"):
        np.testing.assert_allclose(zero.params[k], clean.params[k], rtol=1e-9, atol=0,
                                   err_msg=k)
    assert abs(moved.params["kd"][0] - clean.params["kd"][0]) > 0.01


def test_samples_folds_zero_and_options():
    from project import Measurements

    wi, wo = gonio_pairs()
    m = Measurements(wi[::4], wo[::4], FittedModel("lambert+ggx", GONIO_TRUTH).eval(wi[::4],
                                                                                    wo[::4]))
    fit = fit_model(m, "lambert+ggx", restarts=1, folds=0)
    assert all(fit.info[k] is None for k in ("l2", "l2_stderr", "log", "log_stderr"))
    assert "fold_l2" not in fit.info and fit.info["fit_l2"] < 1e-6
    with pytest.raises(ValueError, match=r"folds must be 0 \(no cross-validation\) or >= 2, "
                                         r"got 1"):
        fit_model(m, "lambert+ggx", folds=1)
    with pytest.raises(ValueError, match=r"family 'factored' tabulates a BRDF on a dense rule "
                                         r".*scattered samples do not cover its tables"):
        fit_model(m, "factored")
    for opt in ("n", "error_n"):
        with pytest.raises(TypeError, match=rf"unknown option\(s\) '{opt}' for measurements "
                                            r"\(the samples are the measurements: n, error_n, "
                                            r"error_seed and widths choose pairs of a BRDF\); "
                                            r"the options are 'seed', 'restarts'"):
            fit_model(m, "lambert+ggx", **{opt: 100})
    with pytest.raises(TypeError, match=r"unknown option\(s\) 'bogus' for measurements; the "
                                        r"options are"):
        fit_model(m, "lambert+ggx", bogus=1)


def test_samples_warns_when_the_family_cannot_follow():
    """Values that are pure noise around 0 (q has no signal; 720 of the pairs, 3 folds): a
    family with f >= 0 predicts held-out zero-mean noise no better than 0, so the
    cross-validated l2 error is >= 1 (1.0003 to 1.2 over 18 seeded variants; 1.20 here) and
    fit_model warns."""
    from project import Measurements

    wi, wo = gonio_pairs()
    m = Measurements(wi[::2], wo[::2], 0.01 * np.random.default_rng(2).standard_normal(720))
    with pytest.warns(RuntimeWarning, match=r"fit_model\('lambert\+ggx'\) predicts the held-out "
                                            r"samples of Measurements\(.*\) no better than "
                                            r"zero: cross-validated l2 error 1\.2 >= 1\. The "
                                            r"family cannot follow these data"):
        fit = fit_model(m, "lambert+ggx", restarts=1, folds=3)
    assert fit.info["l2"] >= 1.0 and fit.info["folds"] == 3


def test_samples_rr8807_takes_the_wavelengths_of_the_measurements():
    """Spectral measurements (nm) give rr8807 its per-channel lambda in um; the wavelength
    option still overrides them. A few evaluations suffice to check where lambda comes from
    (the fit does not converge: warned)."""
    from project import Measurements

    wi, wo = gonio_pairs()
    wi, wo = wi[::8], wo[::8]
    f = FittedModel("lambert+ggx", {"kd": [0.3, 0.2], "ks": [0.7, 0.7], "alpha": 0.2,
                                    "f0": 0.04}).eval(wi, wo)
    m = Measurements(wi, wo, f, wavelengths=[480.0, 620.0])
    opts = {"restarts": 1, "folds": 0, "max_nfev": 2}
    with pytest.warns(RuntimeWarning, match=r"did not converge"):
        fit = fit_model(m, "rr8807", **opts)
    np.testing.assert_array_equal(fit.params["wavelength"], [0.48, 0.62])
    with pytest.warns(RuntimeWarning, match=r"did not converge"):
        fit = fit_model(m, "rr8807", wavelength=[0.5, 0.6], **opts)
    np.testing.assert_array_equal(fit.params["wavelength"], [0.5, 0.6])
    # without wavelengths, 2 channels have no default
    with pytest.raises(ValueError, match=r"family 'rr8807' needs the option wavelength"):
        fit_model(Measurements(wi, wo, f), "rr8807", **opts)
