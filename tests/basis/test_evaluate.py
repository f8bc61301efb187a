"""basis.evaluate (the compiled evaluator behind CoefficientMatrix.eval): against the direct
product b(w_i)^T M b(w_o) formed here from Basis.eval and the dense matrix, for every basis
kind, isotropic and dense storage, one and three channels, both quantities."""

from __future__ import annotations

import numpy as np
import pytest

import basis
from basis import CoefficientMatrix, Evaluator
from tests.conftest import random_directions

BASES = [basis.HemiZernike(16), basis.HemiHarmonics(16), basis.HemiHarmonics(9, parity="even"),
         basis.SphericalHarmonics(8), basis.HemiZernike(0)]


def _random(b, rng, channels, quantity, isotropic):
    shape = (b.size, b.size) if channels is None else (channels, b.size, b.size)
    x = rng.normal(size=shape)
    cm = CoefficientMatrix(b, x + np.swapaxes(x, -1, -2), quantity, isotropic=False)
    return cm.to_isotropic() if isotropic else cm


def _lift(w, c):
    # independent restatement of the grazing rule: same azimuth, cos(theta) raised to c
    w = w.copy()
    low = w[:, 2] < c
    s = np.hypot(w[low, 0], w[low, 1])
    w[low, 0] *= np.sqrt(1 - c * c) / s
    w[low, 1] *= np.sqrt(1 - c * c) / s
    w[low, 2] = c
    return w


def _direct(cm, wi, wo, min_cos):
    """b(w_i)^T M b(w_o) per channel, divided by cos cos for f_cos; 0 below the horizon."""
    c = min_cos if cm.quantity == "f_cos" else 0.0
    li, lo = _lift(wi, c), _lift(wo, c)
    m = cm.matrix.reshape(-1, cm.basis.size, cm.basis.size)
    q = np.einsum("ni,cij,nj->nc", cm.basis.eval(li), m, cm.basis.eval(lo))
    if cm.quantity == "f_cos":
        q /= (li[:, 2] * lo[:, 2])[:, None]
    q[(wi[:, 2] < 0) | (wo[:, 2] < 0)] = 0.0
    return q[:, 0] if cm.is_scalar else q


@pytest.mark.parametrize("b", BASES, ids=repr)
@pytest.mark.parametrize("quantity", ["f_cos", "f"])
@pytest.mark.parametrize("isotropic", [True, False])
@pytest.mark.parametrize("channels", [None, 3])
def test_matches_direct_product(b, quantity, isotropic, channels, rng):
    cm = _random(b, rng, channels, quantity, isotropic)
    assert cm.is_isotropic == isotropic
    wi = random_directions(rng, 3000, upper=True)
    wo = random_directions(rng, 3000, upper=True)
    wi[:5, 2] = 0.0  # on the horizon, and just above it
    wi[5:10, 2] = 1e-5
    wi[:10] /= np.linalg.norm(wi[:10], axis=1)[:, None]
    wo[:3] = [0.0, 0.0, 1.0]  # the pole, where the azimuth is undefined
    if b.domain == "sphere":
        wo[10:200, 2] *= -1  # below the horizon: 0
    got = cm.eval(wi, wo)
    ref = _direct(cm, wi, wo, 1e-3)
    # dense: the same products summed in another order, rounding only; isotropic: the
    # Chebyshev change of basis (least squares on 2k + 8 nodes) adds ~1e-12 relative at
    # order 16 (observed 1.3e-12); the bound leaves ~8x headroom
    tol = 1e-11 if isotropic else 1e-12
    assert np.max(np.abs(got - ref)) <= tol * np.max(np.abs(ref))
    assert got.shape == ((3000,) if channels is None else (3000, channels))
    assert np.all(got[(wi[:, 2] < 0) | (wo[:, 2] < 0)] == 0.0)


@pytest.mark.parametrize("isotropic", [True, False])
def test_below_horizon_is_zero_for_hemisphere_bases(isotropic, rng):
    cm = _random(basis.HemiZernike(4), rng, 2, "f_cos", isotropic)
    wi = random_directions(rng, 500)  # both hemispheres
    wo = random_directions(rng, 500)
    got = cm.eval(wi, wo)
    below = (wi[:, 2] < 0) | (wo[:, 2] < 0)
    assert below.sum() > 300 and np.all(got[below] == 0.0)
    assert np.all(got[~below] != 0.0)


def test_broadcasting_and_flat_path(rng):
    cm = _random(basis.HemiZernike(6), rng, 3, "f", True)
    wi = random_directions(rng, (4, 1), upper=True)
    wo = random_directions(rng, (1, 5), upper=True)
    got = cm.eval(wi, wo)
    assert got.shape == (4, 5, 3)
    ref = _direct(cm, np.broadcast_to(wi, (4, 5, 3)).reshape(-1, 3),
                  np.broadcast_to(wo, (4, 5, 3)).reshape(-1, 3), 1e-3)
    np.testing.assert_allclose(got.reshape(-1, 3), ref, rtol=0,
                               atol=1e-12 * np.max(np.abs(ref)))
    ev = cm.evaluator()
    a = np.ascontiguousarray(np.broadcast_to(wi, (4, 5, 3)).reshape(-1, 3))
    b = np.ascontiguousarray(np.broadcast_to(wo, (4, 5, 3)).reshape(-1, 3))
    out = np.empty((20, 3))
    ev.eval_flat(a, b, out)
    assert np.array_equal(out, got.reshape(-1, 3))
    assert cm.eval(np.empty((0, 3)), np.empty((0, 3))).shape == (0, 3)


def test_evaluator_is_built_once_per_min_cos(rng):
    cm = _random(basis.HemiZernike(4), rng, None, "f_cos", True)
    assert cm.evaluator() is cm.evaluator(min_cos=1e-3)
    assert cm.evaluator(min_cos=0.1) is not cm.evaluator()
    w = np.array([[0.6, 0.0, 0.8]])
    assert cm.eval(w, w).shape == (1,)


def test_dense_path_works_in_chunks(rng, monkeypatch):
    # small chunks: several passes through the chunk loop must give the same values
    cm = _random(basis.HemiHarmonics(6), rng, 3, "f_cos", False)
    wi = random_directions(rng, 1000, upper=True)
    wo = random_directions(rng, 1000, upper=True)
    whole = cm.eval(wi, wo)
    monkeypatch.setattr("basis.evaluate._DENSE_BYTES", 8 * 64 * 21 * 5)
    parts = CoefficientMatrix(cm.basis, cm.matrix, cm.quantity, isotropic=False).eval(wi, wo)
    np.testing.assert_allclose(parts, whole, rtol=1e-14, atol=1e-14 * np.max(np.abs(whole)))


def test_errors(rng):
    b = basis.HemiZernike(2)
    x = rng.normal(size=(b.size, b.size))
    cm = CoefficientMatrix(b, x + x.T, isotropic=False)
    with pytest.raises(TypeError, match="cm must be a basis.CoefficientMatrix"):
        Evaluator(np.eye(2))
    for bad in (0.0, 1.0, -0.5):
        with pytest.raises(ValueError, match=r"min_cos must lie in \(0, 1\)"):
            cm.eval([0, 0, 1.0], [0, 0, 1.0], min_cos=bad)
    with pytest.raises(ValueError, match="wi must be unit vectors"):
        cm.eval([0, 0, 2.0], [0, 0, 1.0])
    with pytest.raises(ValueError, match="broadcastable batch shapes"):
        cm.eval(random_directions(rng, 3), random_directions(rng, 4))


def test_plain_arrays_are_checked_inside_the_kernel(rng):
    # (n, 3) float64 C-contiguous pairs skip the separate validation pass: the kernel tests
    # |w|^2 and only a flagged vector runs as_directions, so the accepted set is unchanged
    b = basis.HemiZernike(4)
    x = rng.normal(size=(b.size, b.size))
    cm = CoefficientMatrix(b, x + x.T)
    wi = random_directions(rng, 300, upper=True)
    wo = random_directions(rng, 300, upper=True)
    ref = cm.eval(wi.tolist(), wo.tolist())  # the general path
    np.testing.assert_array_equal(cm.eval(wi, wo), ref)
    near = wi.copy()
    near[7] *= 1 + 0.99e-6  # inside UNIT_ATOL, outside the kernel's stricter test
    np.testing.assert_array_equal(cm.eval(near, wo), cm.eval(near.tolist(), wo.tolist()))
    for value, match in ((1 + 2e-6, "wo must be unit vectors"), (np.nan, "wo must be finite")):
        bad = wo.copy()
        bad[123] *= value
        with pytest.raises(ValueError, match=match):
            cm.eval(wi, bad)


@pytest.mark.parametrize("channels", [None, 2, 4, 7])
def test_partial_steps_and_channel_groups(channels, rng):
    # the kernel takes pairs LANES at a time (a last partial step runs on padded copies) and
    # channels three at a time (a last partial group repeats its last channel): every count
    # of pairs up to 17, channel counts that leave 1 and 2 over, grazing pairs lifted in some
    # lanes and not others. Reference and tolerance as in test_matches_direct_product.
    b = basis.HemiZernike(8)
    cm = _random(b, rng, channels, "f_cos", True)
    wi = random_directions(rng, 17, upper=True)
    wo = random_directions(rng, 17, upper=True)
    wi[[2, 9, 16], 2] = 1e-4  # under min_cos: lifted
    wi[[2, 9, 16]] /= np.linalg.norm(wi[[2, 9, 16]], axis=1)[:, None]
    wo[[3, 10]] = [0.0, 0.0, 1.0]
    for n in range(1, 18):
        got = cm.eval(wi[:n], wo[:n])
        ref = _direct(cm, wi[:n], wo[:n], 1e-3)
        assert np.max(np.abs(got - ref)) <= 1e-11 * np.max(np.abs(ref)), n


def _from_separable(form, wi, wo):
    """q or f rebuilt from Evaluator.separable() by the module notes' formula, in numpy."""
    kind = form["kind"]

    def geometry(w):
        x, y, z = w[:, 0], w[:, 1], w[:, 2]
        if kind == "zernike":
            r = 1.0 / np.sqrt(1.0 + z)
            return (x + 1j * y) * r, 1.0 - 2.0 * z, 1.0
        a = x + 1j * y
        if kind == "sh":
            return a, z, 1.0
        return a, 2.0 * z * z - 1.0, (z if kind == "harmonics" else 1.0)

    (ai, xi, gi), (ao, xo, go) = geometry(wi), geometry(wo)
    coef, tri, coefa, tria = form["coef"], form["tri"], form["coefa"], form["tria"]
    kmax = int(round((np.sqrt(8 * coef.shape[2] + 1) - 1) / 2))
    ti = np.polynomial.chebyshev.chebvander(xi, max(kmax - 1, 0))
    to = np.polynomial.chebyshev.chebvander(xo, max(kmax - 1, 0))
    sym = [(a, b) for b in range(kmax) for a in range(b + 1)]
    anti = [(a, b) for b in range(kmax) for a in range(b)]
    out = np.zeros((wi.shape[0], coef.shape[1]))
    for m in range(coef.shape[0]):
        phase = ((ai * np.conj(ao)) ** m).real
        for c in range(coef.shape[1]):
            s = sum(coef[m, c, q] * (ti[:, a] * to[:, b] + (ti[:, b] * to[:, a] if a != b
                                                            else 0.0))
                    for q, (a, b) in enumerate(sym[:tri[m]]))
            s = s + sum(coefa[m, c, q] * (ti[:, a] * to[:, b] - ti[:, b] * to[:, a])
                        for q, (a, b) in enumerate(anti[:tria[m]]))
            out[:, c] += phase * s
    scale = gi * go
    if form["fcos"]:
        scale = scale / (wi[:, 2] * wo[:, 2])
    return out * np.asarray(scale)[:, None]


@pytest.mark.parametrize("b", [basis.HemiZernike(4), basis.HemiHarmonics(4),
                               basis.HemiHarmonics(4, parity="even"),
                               basis.SphericalHarmonics(3)], ids=repr)
@pytest.mark.parametrize("reciprocal", [True, False])
def test_separable_form_reproduces_eval(b, reciprocal, rng):
    """Evaluator.separable() holds what the kernel sums: rebuilt in numpy, the same values.

    Directions above cos(theta) = 0.2 (no lifting); 1e-12 relative: both are sums of the
    same few hundred products in float64.
    """
    blocks = b.azimuthal_blocks()
    m = np.zeros((b.size, b.size))
    for cos, sin in zip(blocks.cos, blocks.sin, strict=True):
        block = rng.normal(size=(cos.size, cos.size))
        block = block if not reciprocal else block + block.T
        m[np.ix_(cos, cos)] = block
        if sin.size:  # the sin functions of order m > 0 pair with the cos ones
            m[np.ix_(sin, sin)] = block
    cm = CoefficientMatrix(b, m, quantity="f_cos", reciprocal=reciprocal)
    assert cm.is_isotropic
    form = cm.evaluator().separable()
    assert form["kind"] == b.kind and not form["coef"].flags.writeable
    wi, wo = (random_directions(rng, 300) for _ in range(2))
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]), np.abs(wo[:, 2])
    keep = (wi[:, 2] > 0.2) & (wo[:, 2] > 0.2)
    got = _from_separable(form, wi[keep], wo[keep])
    ref = np.asarray(cm.eval(wi[keep], wo[keep])).reshape(got.shape)
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    dense = CoefficientMatrix(b, m + 1e-3 * np.eye(b.size)[::-1], quantity="f",
                              reciprocal=False)
    assert not dense.is_isotropic and dense.evaluator().separable() is None
