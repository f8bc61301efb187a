"""Tests of project.tucker: the Tucker tensor of piecewise-linear curves, its fit and storage.

References: the trilinear table of project.tabulated (an independent kernel: a Tucker tensor
of full ranks with a knot at every node is that table), numpy's interp and einsum with
basis.to_rusinkiewicz (the kernel's angles and contraction), and the weighted norm on the
fine grid computed directly (the fit's Pythagorean error bookkeeping).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import compress
from basis import to_rusinkiewicz
from project import FittedModel, fit_model
from project.factored import reuse_samples
from project.models import CookTorrance, Lambert
from project.sampling import brdf_errors, peak_resolving_pairs
from project.tabulated import tabulate
from project.tucker import TuckerBRDF, _Prepared, fit_tucker, tucker_reals

SHARP = CookTorrance([0.3, 0.2, 0.1], 0.1, "ggx", ior=1.5)


def _pairs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n pairs uniform over H x H (z >= 1e-3), both orders of a pair as separate draws."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(2):
        z = rng.uniform(1e-3, 1.0, n)
        phi = rng.uniform(0.0, 2.0 * math.pi, n)
        s = np.sqrt(1.0 - z * z)
        out.append(np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1))
    return out[0], out[1]


def _random_tucker(seed: int, phi_turn: str = "full", channels: int = 3) -> TuckerBRDF:
    rng = np.random.default_rng(seed)
    knots = [np.sort(np.concatenate([[0.0, 1.0], rng.uniform(0.05, 0.95, 5)])),
             np.sort(np.concatenate([[0.0, 1.0], rng.uniform(0.05, 0.95, 3)])),
             np.sort(rng.uniform(0.0, 1.0, 6))]
    knots = [k.astype(np.float16).astype(np.float64) for k in knots]
    ranks = (3, 2, 4)
    factors = [rng.uniform(0.1, 1.0, (k.size, r)) for k, r in zip(knots, ranks, strict=True)]
    core = rng.uniform(0.0, 1.0, (*ranks, 2))
    color = rng.uniform(0.2, 1.0, (channels, 2))
    return TuckerBRDF(knots, factors, core, color, phi_turn=phi_turn)


def _reference(t: TuckerBRDF, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """f of a TuckerBRDF by numpy: to_rusinkiewicz, np.interp per factor column, einsum."""
    p = t.params
    th, _, td, pd = to_rusinkiewicz(wi, wo)
    period = 2.0 * math.pi * float(p["phi_turn"])
    s = (np.sqrt(np.clip(th / (math.pi / 2), 0, 1)),
         1 - (1 - np.clip(td / (math.pi / 2), 0, 1)) ** (1 / float(p["warp_d"])),
         np.mod(pd, period) / period)
    rows = []
    for name, x in zip(("h", "d", "phi"), s, strict=True):
        k, f = p[f"{name}_knots"], p[f"{name}_factor"]
        if name == "phi":  # periodic: extend one knot either side
            k = np.concatenate([k[-1:] - 1, k, k[:1] + 1])
            f = np.concatenate([f[-1:], f, f[:1]])
        rows.append(np.stack([np.interp(x, k, f[:, a]) for a in range(f.shape[1])], axis=-1))
    q = np.einsum("abke,na,nb,nk,ce->nc", p["core"], *rows, p["color"])
    cc = wi[:, 2] * wo[:, 2]
    return np.maximum(q, 0) / cc[:, None]


@pytest.mark.parametrize("turn", ["full", "half"])
def test_kernel_matches_numpy_reference(turn):
    """The numba kernel against np.interp + einsum on basis.to_rusinkiewicz, to 1e-12."""
    t = _random_tucker(1, turn)
    wi, wo = _pairs(20000, 2)
    got, want = t.eval(wi, wo), _reference(t, wi, wo)
    if turn == "half":  # the reference does not fold phi_d: compare where it lies in [0, pi)
        _, _, _, pd = to_rusinkiewicz(wi, wo)
        keep = (pd >= 0) & (pd < math.pi - 1e-9)
        got, want = got[keep], want[keep]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_half_turn_is_reciprocal_bit_for_bit_and_full_turn_is_not():
    wi, wo = _pairs(5000, 3)
    half = _random_tucker(4, "half")
    assert half.reciprocal and np.array_equal(half.eval(wi, wo), half.eval(wo, wi))
    full = _random_tucker(4, "full")
    assert not full.reciprocal and not np.allclose(full.eval(wi, wo), full.eval(wo, wi))


def test_horizon_and_below_are_zero():
    t = _random_tucker(5)
    up = np.array([[0.6, 0.0, 0.8]])
    flat = np.array([[1.0, 0.0, 0.0]])
    down = np.array([[0.0, 0.6, -0.8]])
    assert np.all(t.eval(flat, up) == 0) and np.all(t.eval(up, down) == 0)
    assert np.all(t.eval(up, up) > 0)


@pytest.mark.parametrize("turn", ["full", "half"])
def test_full_ranks_and_knots_are_the_trilinear_table(turn):
    """With a knot at every node and full ranks the fit interpolates the fine grid: it is
    project.tabulated's table (another kernel) up to rounding. Node coordinates i/8, i/4
    and k/8 are exact in float16, so the knots sit on the nodes."""
    grid = (9, 5, 16)
    m = 16 if turn == "full" else 8
    fit = fit_tucker(SHARP, ranks=(9, 5, m), knots=(9, 5, m), grid=grid, phi_turn=turn)
    tab = tabulate(SHARP, grid, phi_turn=turn)
    wi, wo = _pairs(20000, 6)
    a, b = fit.eval(wi, wo), tab.eval(wi, wo)
    assert fit.info["fit_l2"] < 1e-6  # the square root of rounding in 1 - |kept|^2
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * np.abs(b).max())


def test_fit_error_is_the_weighted_error_on_the_grid():
    """fit_l2 (projection + truncation, by Pythagoras) against the weighted norm of the
    difference on the fine grid, computed directly from the model's values at the nodes."""
    grid = (33, 17, 32)
    with reuse_samples():
        t = fit_tucker(SHARP, budget=500, grid=grid, phi_turn="full")
        prep = _Prepared(SHARP, grid, "grazing", "full")
    sh, sd, sp = prep.s
    # model q at the nodes (the nodes are where tabulate sampled; filled ones included)
    p = t.params
    rows = [np.stack([np.interp(x, p[f"{n}_knots"], p[f"{n}_factor"][:, a])
                      for a in range(p[f"{n}_factor"].shape[1])], axis=-1)
            for n, x in (("h", sh), ("d", sd))]
    k = np.concatenate([p["phi_knots"][-1:] - 1, p["phi_knots"], p["phi_knots"][:1] + 1])
    f = np.concatenate([p["phi_factor"][-1:], p["phi_factor"], p["phi_factor"][:1]])
    rows.append(np.stack([np.interp(sp, k, f[:, a]) for a in range(f.shape[1])], axis=-1))
    q = np.einsum("abke,ia,jb,lk,ce->ijlc", p["core"], *rows, p["color"])
    w = prep.w[0][:, None, None] * prep.w[1][None, :, None] * prep.w[2][None, None, :]
    ref = prep.t * prep.norms
    err = np.sqrt((w[..., None] * (q - ref) ** 2).sum((0, 1, 2))
                  / (w[..., None] * ref ** 2).sum((0, 1, 2)))
    np.testing.assert_allclose(t.info["fit_l2_channels"], err, rtol=1e-6)


def test_budget_is_kept_and_error_falls_with_it():
    """Within each budget; on a sharp GGX (alpha 0.1) the independent l2 error falls with
    the budget, and the fine-grid error predicts it (both resolve the peak)."""
    pairs = peak_resolving_pairs(1 << 15, seed=11)
    errs = []
    with reuse_samples():
        for budget in (200, 800, 3200):
            t = fit_tucker(SHARP, budget=budget, grid=(128, 32, 32))
            assert t.nparams <= budget and t.reciprocal  # CookTorrance is reciprocal
            e = brdf_errors(SHARP, t, pairs)
            errs.append(e["l2"])
            assert abs(e["l2"] - t.info["fit_l2"]) < 0.3 * t.info["fit_l2"] + 0.005
    assert errs[0] > errs[1] > errs[2] and errs[2] < 0.02


def test_fit_model_family_and_storage_round_trip(tmp_path):
    """fit_model(..., "tucker") gives a FittedModel whose params rebuild it; compress.save /
    load keep it (float16: rounded once, then bit for bit)."""
    m = fit_model(SHARP, "tucker", budget=600, grid=(64, 16, 32), error_n=4096)
    assert m.family == "tucker" and m.nparams <= 600 and m.info["l2"] < 0.1
    again = FittedModel("tucker", m.params)
    wi, wo = _pairs(2000, 8)
    assert np.array_equal(again.eval(wi, wo), m.eval(wi, wo))
    path = compress.save(m, tmp_path / "t.h5", dtype="float16")
    back = compress.load(path)
    assert back.family == "tucker" and back.nparams == m.nparams
    # knots are float16 values: rounding moves none of them
    for name in ("h", "d", "phi"):
        assert np.array_equal(back.params[f"{name}_knots"], m.params[f"{name}_knots"])
    rel = np.abs(back.eval(wi, wo) - m.eval(wi, wo)).max() / np.abs(m.eval(wi, wo)).max()
    assert rel < 5e-3
    again = compress.load(compress.save(back, tmp_path / "u.h5", dtype="float16"))
    assert np.array_equal(again.eval(wi, wo), back.eval(wi, wo))


def test_reals_count():
    t = _random_tucker(9)
    assert t.nparams == tucker_reals(t.knot_counts, t.ranks, t.color_rank, 3) == \
        7 * 4 + 5 * 3 + 6 * 5 + 24 * 2 + 3 * 2
    assert t.nbytes == 8 * t.nparams


def test_one_channel_and_a_large_budget_reaches_the_grid():
    """A one-channel BRDF gives scalar values; with a budget near the grid's own size the
    fit is as accurate as the grid's table (project.tabulated), its floor."""
    lam = Lambert(0.5)
    grid = (64, 16, 16)
    t = fit_tucker(lam, budget=3000, grid=grid)
    wi, wo = _pairs(1000, 10)
    assert t.eval(wi, wo).shape == (1000,)
    pairs = peak_resolving_pairs(1 << 14, seed=1)
    table = brdf_errors(lam, tabulate(lam, grid), pairs)["l2"]
    assert brdf_errors(lam, t, pairs)["l2"] < 1.02 * table


@pytest.mark.parametrize("kwargs, match", [
    ({"knots": [[0.0, 0.5, 0.4], [0.0, 1.0], [0.0, 0.2, 0.4, 0.6]]}, "strictly increasing"),
    ({"knots": [[0.0, 1.0], [0.0, 1.0], [0.0, 0.5]]}, "at least 4"),
    ({"knots": [[0.0, 1.0], [0.0, 1.0], [0.0, 0.2, 0.4, 1.0]]}, r"\[0, 1\)"),
    ({"core": np.ones((2, 1, 1, 1))}, "h factor must have shape"),
    ({"color": np.ones((3, 2))}, "color must have shape"),
    ({"core": np.full((1, 1, 1, 1), np.nan)}, "finite"),
    ({"phi_turn": "third"}, "phi_turn"),
])
def test_bad_construction(kwargs, match):
    args = {"knots": [[0.0, 1.0], [0.0, 1.0], [0.0, 0.25, 0.5, 0.75]],
            "factors": [np.ones((2, 1)), np.ones((2, 1)), np.ones((4, 1))],
            "core": np.ones((1, 1, 1, 1)), "color": np.ones((3, 1))}
    args.update(kwargs)
    extra = {k: args.pop(k) for k in ("phi_turn",) if k in args}
    with pytest.raises(ValueError, match=match):
        TuckerBRDF(args["knots"], args["factors"], args["core"], args["color"], **extra)


def test_bad_fits():
    with pytest.raises(ValueError, match="no Tucker structure fits in 19 reals .* takes 20"):
        fit_tucker(SHARP, budget=19, grid=(16, 8, 8))
    with pytest.raises(ValueError, match="ranks and knots together"):
        fit_tucker(SHARP, ranks=(2, 2, 2), grid=(16, 8, 8))
    with pytest.raises(ValueError, match="at most the grid's"):
        fit_tucker(SHARP, ranks=(2, 2, 2), knots=(40, 4, 4), grid=(16, 8, 8))
    with pytest.raises(ValueError, match="grid must be"):
        fit_tucker(SHARP, budget=100, grid=(16, 8, 7))
    with pytest.raises(TypeError, match="must be a BRDF"):
        fit_tucker(np.ones(3), budget=100)
    with pytest.raises(ValueError, match="params of family 'tucker' must be exactly"):
        FittedModel("tucker", {"core": np.ones((1, 1, 1, 1))})


def test_zero_channel_is_refused():
    with pytest.raises(ValueError, match="0 everywhere on the grid in channel 1"):
        fit_tucker(Lambert([0.5, 0.0]), budget=300, grid=(16, 8, 8))
