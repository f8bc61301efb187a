"""Factored half/difference-angle BRDFs (project.factored): the quadrature rule and its
Jacobian, exact recovery of a model in the family, convergence on a Cook-Torrance lobe, the
BRDF contract of the fitted model, input validation, and a fit of a MERL surrogate.

References: the change of variables d w_i d w_o = 4 cos(theta_d) d w_h d w_d is that of
Rusinkiewicz ("A new change of variables for efficient BRDF representation", EGWR 1998),
with d w_o = 4 (w_o . h) d w_h from Torrance & Sparrow (1967) and Walter et al. (EGSR
2007); the hemisphere integrals int_H z dw = pi and int_H z^2 dw = 2 pi / 3 are elementary.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from basis import from_angles, to_rusinkiewicz
from project.brdf import BRDF, MirrorDelta
from project.factored import FactoredLobe, fit_factored, rusinkiewicz_rule
from project.measured import read_merl
from project.models import CookTorrance, Lambert, Ward

RNG = np.random.default_rng(20240607)


def _cos(th, td, phi):
    a = np.cos(th)[:, None, None] * np.cos(td)[None, :, None]
    b = np.sin(th)[:, None, None] * np.sin(td)[None, :, None] * np.cos(phi)
    return a - b, a + b


def _pairs(n, rng=RNG):
    """n random pairs of directions in the upper hemisphere."""
    def one():
        v = rng.normal(size=(n, 3))
        v[:, 2] = np.abs(v[:, 2])
        return v / np.linalg.norm(v, axis=1, keepdims=True)
    return one(), one()


# -- (1) the rule: weights and Jacobian -------------------------------------------------------

@pytest.mark.parametrize("bins,warp,warp_d", [
    ((90, 32), "sqrt", "linear"), ((16, 8), "linear", "grazing"), ((48, 16), "cbrt", "linear"),
    ((32, 24), "cbrt", "grazing")])
def test_rule_integrates_known_functions_over_h_x_h(bins, warp, warp_d):
    """int 1 = (2 pi)^2, int z_i z_o = pi^2, int (z_i z_o)^2 = (2 pi / 3)^2 and
    int z_i z_o (w_i . w_o) = (2 pi / 3)^2 (w_i . w_o = cos 2 theta_d): the Jacobian
    4 cos(theta_d) sin(theta_h) sin(theta_d) of Rusinkiewicz (1998)."""
    th, td, phi, w = rusinkiewicz_rule(bins, warp, warp_d=warp_d)
    zi, zo = _cos(th, td, phi)
    assert np.all(zi > 0) and np.all(zo > 0) and np.all(w > 0)
    # measured relative errors over the four rules: 1: 8e-6 to 4e-5 (1 jumps to 0 at the
    # horizon, a kink of the phi_d interval in (theta_h, theta_d)); z_i z_o: 4e-8 to 3e-7;
    # (z_i z_o)^2: 2e-10 to 6e-9; z_i z_o cos 2 theta_d: 6e-8 to 2e-7
    assert w.sum() == pytest.approx((2 * np.pi) ** 2, rel=1e-4)
    assert (w * zi * zo).sum() == pytest.approx(np.pi ** 2, rel=1e-6)
    assert (w * (zi * zo) ** 2).sum() == pytest.approx((2 * np.pi / 3) ** 2, rel=3e-8)
    cos2d = np.cos(2 * td)[None, :, None]
    assert (w * zi * zo * cos2d).sum() == pytest.approx((2 * np.pi / 3) ** 2, rel=1e-6)


def test_rule_converges_and_nodes_map_to_the_angles():
    """Refining the rule reduces the error of int z_i z_o; from_rusinkiewicz of the nodes
    gives back their angles (to_rusinkiewicz), with both directions above the horizon."""
    errs = [abs((w * np.prod(_cos(th, td, phi), axis=0)).sum() / np.pi ** 2 - 1)
            for th, td, phi, w in (rusinkiewicz_rule((16, 8), "sqrt", s)
                                   for s in ((48, 24, 4), (96, 48, 8), (384, 192, 32)))]
    assert errs[2] < errs[0] and errs[2] < 1e-8
    th, td, phi, _ = rusinkiewicz_rule((8, 4), "sqrt", (24, 12, 5))
    from basis import from_rusinkiewicz
    T = np.broadcast_to(th[:, None, None], phi.shape)
    D = np.broadcast_to(td[None, :, None], phi.shape)
    wi, wo = from_rusinkiewicz(T, 0.0, D, phi)
    assert wi[..., 2].min() > 0 and wo[..., 2].min() > 0
    th2, _, td2, pd2 = to_rusinkiewicz(wi, wo)
    np.testing.assert_allclose(th2, T, atol=1e-12)
    np.testing.assert_allclose(td2, D, atol=1e-12)
    np.testing.assert_allclose(np.mod(pd2, 2 * np.pi), phi, atol=1e-9)


# -- (2) exact recovery ------------------------------------------------------------------------

def _member(n_h=16, n_d=8, n_phi=None, channels=3):
    """kd/pi + A(theta_h) B(theta_d) [C(phi_d)] with piecewise-linear A, B, C on the nodes."""
    th = np.pi / 2 * (np.arange(n_h) / (n_h - 1)) ** 2
    A = 30.0 * np.exp(-(th / 0.08) ** 2) + 0.05
    B = 1.0 + np.linspace(0.0, 1.0, n_d) ** 4
    if channels == 3:
        B = B[:, None] * np.array([1.0, 0.8, 0.6])
        kd = [0.2, 0.3, 0.5]
    else:
        kd = 0.25
    C = None if n_phi is None else (1.0 + 0.4 * np.sin(np.arange(n_phi) * 2.1))[None, :]
    return FactoredLobe(kd, A[None], B[None], phi_table=C)


def _tensor(lobe):
    """(n_h, n_d, channels) sum_k w_k A_k B_k at the nodes."""
    w = np.ones((lobe.rank, 1)) if lobe.weights is None else lobe.weights
    return np.einsum("kac,kbc,kc->abc", lobe.h_table, lobe.d_table, w)


def test_exact_recovery_rank_one():
    """A BRDF of the family on the same nodes is recovered to rounding at rank 1."""
    true = _member()
    fit = fit_factored(true, rank=1, bins=(16, 8))
    assert fit.info["error"] < 1e-10
    assert fit.info["converged"]
    np.testing.assert_allclose(fit.kd, true.kd, rtol=1e-7)  # measured 2e-9
    np.testing.assert_allclose(_tensor(fit), _tensor(true), rtol=1e-8, atol=1e-10)
    wi, wo = _pairs(2000)
    np.testing.assert_allclose(fit.eval(wi, wo), true.eval(wi, wo), rtol=1e-9)


def test_exact_recovery_with_phi_factor():
    """The same with a phi_d table: the error is limited by the stopping rule of the phi_d
    stage (its squared error is formed as S - 2 cross + quad), measured 5e-9."""
    true = _member(n_phi=5, channels=1)
    fit = fit_factored(true, rank=1, bins=(16, 8, 5))
    assert fit.info["error"] < 1e-7
    np.testing.assert_allclose(fit.phi_table / fit.phi_table.mean(),
                               true.phi_table / true.phi_table.mean(), rtol=1e-6)
    wi, wo = _pairs(2000)
    np.testing.assert_allclose(fit.eval(wi, wo), true.eval(wi, wo), rtol=1e-6)


def test_floor_reports_the_phi_dependence():
    """A member with a phi_d factor fitted without one: the error cannot go below the
    reported floor (the best phi_d-independent function), and is close to it at rank 1."""
    true = _member(n_phi=5, channels=1)
    fit = fit_factored(true, rank=1, bins=(16, 8))
    assert 0.01 < fit.info["floor"] <= fit.info["error"] < 1.05 * fit.info["floor"]


# -- (3) a Cook-Torrance lobe ------------------------------------------------------------------

#: Measured relative L2 errors of q on the default rule for CookTorrance(0.1, 0.1, "ggx",
#: ior=1.5), bins (32, 24) with warp_d="grazing", ranks 1, 2, 3: without a phi_d factor
#: (floor 0.0296) and with 8 phi_d nodes. The phi_d factor is what removes the floor: the
#: Smith shadowing G(w_i) G(w_o) / (cos theta_i cos theta_o) depends on phi_d.
CT_ERRORS = {False: (0.0351, 0.0343, 0.0334), True: (0.0314, 0.0149, 0.0149)}


@pytest.mark.parametrize("phi", [False, True])
def test_cook_torrance_error_falls_with_rank(phi):
    """GGX (Walter et al. 2007) alpha 0.1, the Fresnel factor of glass (ior 1.5), kd 0.1: the
    error falls with the rank, and without a phi_d factor it stays above the floor."""
    ct = CookTorrance(0.1, 0.1, "ggx", ior=1.5)
    bins = (32, 24, 8) if phi else (32, 24)
    errs = []
    for rank in (1, 2, 3):
        fit = fit_factored(ct, rank=rank, bins=bins)  # warp_d="grazing", the default
        errs.append(fit.info["error"])
        assert fit.info["converged"]
        if not phi:
            assert fit.info["error"] >= fit.info["floor"] > 0.029
    assert errs[0] > errs[1] >= errs[2] * (1 - 1e-9)
    np.testing.assert_allclose(errs, CT_ERRORS[phi], rtol=0.03)
    # the grazing warp of theta_d pays on this lobe: linear nodes do worse at rank 1
    if not phi:
        lin = fit_factored(ct, rank=1, bins=bins, warp_d="linear")
        assert lin.info["error"] > 1.2 * errs[0]  # measured 0.0466 against 0.0351


# -- (4) the BRDF contract ---------------------------------------------------------------------

@pytest.fixture(scope="module")
def rgb_fit():
    ct = CookTorrance([0.1, 0.2, 0.3], 0.15, "ggx", ior=[1.4, 1.5, 1.6])
    return fit_factored(ct, rank=2, bins=(32, 12, 6))


def test_contract_shapes_horizon_reciprocity(rgb_fit):
    f = rgb_fit
    assert f.channels == 3 and f.isotropic and f.reciprocal
    assert f.eval([0, 0, 1.0], [0, 0, 1.0]).shape == (3,)
    wi, wo = _pairs(500)
    v = f.eval(wi, wo)
    assert v.shape == (500, 3) and np.all(np.isfinite(v)) and np.all(v >= 0)
    assert f.eval(wi.reshape(5, 100, 3), wo[:100]).shape == (5, 100, 3)
    # reciprocity bit for bit: the angles come from wi + wo and wi - wo
    assert np.array_equal(f.eval(wi, wo), f.eval(wo, wi))
    # below the horizon: zero
    below = wo * np.array([1, 1, -1.0])
    assert np.all(f.eval(wi, below) == 0) and np.all(f.eval(below, wi) == 0)
    # isotropy: a common rotation about the normal changes nothing (phi_h is not used;
    # phi_d is measured in the frame of h, except at h = z exactly)
    a = 0.7
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    np.testing.assert_allclose(f.eval(wi @ rot.T, wo @ rot.T), v, rtol=1e-9, atol=1e-12)
    assert repr(f) == ("FactoredLobe(rank=2, bins=(32, 12, 6), warp='cbrt', warp_d='grazing', "
                       "channels=3, nbytes=872)")


def test_contract_tables_and_sizes(rgb_fit):
    f = rgb_fit
    # the default colour: shared tables, one RGB weight per term
    assert f.rank == 2 and f.bins == (32, 12, 6)
    assert f.h_table.shape == (2, 32, 1) and f.d_table.shape == (2, 12, 1)
    assert f.phi_table.shape == (2, 6) and f.weights.shape == (2, 3)
    assert f.nparams == 3 + 2 * 32 + 2 * 12 + 2 * 6 + 2 * 3 and f.nbytes == 8 * f.nparams
    for t in (f.h_table, f.d_table, f.phi_table, f.weights):
        assert not t.flags.writeable
        with pytest.raises(ValueError):
            t[0, 0] = 1.0
    assert f.kd.shape == (3,) and np.all(f.kd >= 0)
    assert f.theta_h_nodes[0] == 0 and f.theta_h_nodes[-1] == pytest.approx(np.pi / 2)
    assert f.theta_h_nodes[1] == pytest.approx(np.pi / 2 / 31 ** 3)  # the cbrt warp
    # the grazing warp of theta_d: (pi/2) (1 - (1 - j/11)^2), dense towards pi/2
    np.testing.assert_allclose(f.theta_d_nodes,
                               np.pi / 2 * (1 - (1 - np.linspace(0, 1, 12)) ** 2))
    for key in ("error", "error_channels", "floor", "iterations", "converged", "seconds"):
        assert key in f.info
    # continuity: a table is linear between its nodes
    wi = from_angles(0.3, 0.0)
    wo = from_angles(np.linspace(0.2, 0.4, 201), np.pi)
    assert np.abs(np.diff(f.eval(wi, wo), axis=0)).max() < 0.05 * f.eval(wi, wo).max()


def test_scalar_source_gives_scalar_model():
    fit = fit_factored(CookTorrance(0.2, 0.3, "ggx"), rank=1, bins=(16, 8))
    assert fit.channels == 1 and fit.eval([0, 0, 1.0], [0, 0, 1.0]).shape == ()
    fit = fit_factored(Lambert([0.5]), rank=1, bins=(4, 4))
    wi, wo = _pairs(50)
    # a constant is in the family (kd and a constant term are interchangeable: kd is not
    # unique, only the sum is)
    assert fit.eval(wi, wo).shape == (50, 1) and fit.info["error"] < 1e-12
    np.testing.assert_allclose(fit.eval(wi, wo), 0.5 / np.pi, rtol=1e-12)


@pytest.mark.parametrize("color,shapes", [
    ("theta_h", ((2, 16, 3), (2, 8, 1), None)), ("both", ((2, 16, 3), (2, 8, 3), None)),
    ("theta_d", ((2, 16, 1), (2, 8, 3), None))])
def test_color_modes(color, shapes):
    ct = CookTorrance([0.1, 0.2, 0.3], 0.2, "ggx", ior=[1.3, 1.5, 1.7])
    f = fit_factored(ct, rank=2, bins=(16, 8), color=color)
    assert f.h_table.shape == shapes[0] and f.d_table.shape == shapes[1]
    assert (f.weights is None) == (shapes[2] is None)
    if shapes[2]:
        assert f.weights.shape == shapes[2]
    assert f.info["error"] < 0.1 and f.eval([0, 0, 1.0], [0.6, 0, 0.8]).shape == (3,)


def test_non_reciprocal_source_fits_its_reciprocal_part():
    """f(wi, wo) = g(wi) (not reciprocal): the fit sees (f + f^T)/2, and the antisymmetric
    part's energy counts in the error and the floor."""

    class Tilted(BRDF):
        channels, isotropic, reciprocal = 1, True, False

        def _eval(self, wi, wo):
            return (0.1 + 0.2 * wi[:, 2:3]) / np.pi

    f = fit_factored(Tilted(), rank=2, bins=(16, 8))
    assert 0 < f.info["floor"] <= f.info["error"]
    wi, wo = _pairs(100)
    assert np.array_equal(f.eval(wi, wo), f.eval(wo, wi))


# -- (5) bad input -----------------------------------------------------------------------------

class _Bad(BRDF):
    channels = 1

    def __init__(self, value):
        self.value = value

    def _eval(self, wi, wo):
        out = np.full((wi.shape[0], 1), 0.1)
        out[wi[:, 2] < 0.5] = self.value
        return out


@pytest.mark.parametrize("value,word", [(-1.0, "-1.0"), (np.nan, "nan"), (np.inf, "inf")])
def test_bad_values_raise(value, word):
    with pytest.raises(ValueError, match=f"finite values >= 0.*{word}.*theta_h"):
        fit_factored(_Bad(value), rank=1, bins=(8, 4))


@pytest.mark.parametrize("kwargs,err,match", [
    ({"rank": 0}, ValueError, "rank"), ({"rank": 1.5}, TypeError, "rank"),
    ({"bins": (1, 8)}, ValueError, "bins"), ({"bins": (8, 8, 1)}, ValueError, "bins"),
    ({"bins": (8,)}, ValueError, "bins"), ({"bins": 8}, TypeError, "bins"),
    ({"warp": "log"}, ValueError, "warp"), ({"color": "red"}, ValueError, "color"),
    ({"metric": "l1"}, ValueError, "metric"), ({"samples": (10, 10)}, ValueError, "samples"),
    ({"samples": (10, 10, 0)}, ValueError, "samples"), ({"max_iter": 0}, ValueError,
                                                        "max_iter"),
    ({"tol": -1.0}, ValueError, "tol")])
def test_bad_arguments_raise(kwargs, err, match):
    with pytest.raises(err, match=match):
        fit_factored(Lambert(0.5), **{"bins": (8, 4), **kwargs})


def test_bad_sources():
    with pytest.raises(TypeError, match="eval"):
        fit_factored(object())
    with pytest.raises(ValueError, match="isotropic"):
        fit_factored(Ward(0.2, 0.3, 0.1, 0.3), bins=(8, 4))
    with pytest.raises(ValueError, match="vanish"):
        fit_factored(Lambert(0.0), bins=(8, 4))


def test_delta_terms_warn_and_are_left_out():
    class Glossy(Lambert):
        delta = (MirrorDelta(0.04),)

    with pytest.warns(UserWarning, match="delta"):
        f = fit_factored(Glossy(0.5), rank=1, bins=(4, 4))
    assert f.eval([0, 0, 1.0], [0.6, 0, 0.8]) == pytest.approx(0.5 / np.pi, rel=1e-12)


def test_no_convergence_warns_with_the_error():
    ct = CookTorrance(0.1, 0.1, "ggx", ior=1.5)
    with pytest.warns(RuntimeWarning, match=r"did not converge in max_iter = 2 .*error 0\.\d"):
        f = fit_factored(ct, rank=2, bins=(16, 8), max_iter=2)
    assert not f.info["converged"] and f.info["iterations"] == 2


def test_bad_tables_raise():
    with pytest.raises(ValueError, match="h_table"):
        FactoredLobe(0.1, [[-1.0, 1.0]], [[1.0, 1.0]])
    with pytest.raises(ValueError, match="same rank"):
        FactoredLobe(0.1, [[1.0, 1.0]], [[1.0, 1.0], [1.0, 1.0]])
    with pytest.raises(ValueError, match="channels"):
        FactoredLobe([0.1, 0.2], np.ones((1, 4, 3)), np.ones((1, 4)))
    with pytest.raises(ValueError, match="phi_table"):
        FactoredLobe(0.1, np.ones((1, 4)), np.ones((1, 4)), phi_table=np.ones((2, 4)))


# -- a MERL surrogate --------------------------------------------------------------------------

#: Measured with the defaults (rank 4, bins (32, 24, 8), 2168 bytes) on the blue-acrylic
#: surrogate (the Sztrajman et al. 2021 network fit of the MERL material of Matusik et al.
#: 2003): 0.0703 (0.0698 with warp_d="linear", which moves by < 0.001 on rules of 51k to
#: 1.6M points). The fit is a local minimum of a non-convex problem; the bound leaves room
#: for other roundings.
BLUE_ACRYLIC_ERROR = 0.075


def test_merl_surrogate_blue_acrylic(merl_surrogate):
    brdf = read_merl(merl_surrogate("blue-acrylic"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit = fit_factored(brdf)
    assert fit.info["skipped"] < 1e-4
    assert fit.info["error"] < BLUE_ACRYLIC_ERROR
    # no phi_d-independent model gets below 0.1136 here: the phi_d factor is what pays
    assert fit.info["floor"] > 0.11
    assert fit.nbytes == 2168 and fit.channels == 3
    print("blue-acrylic", fit, fit.info["error"], fit.info["seconds"])
