"""basis._base (what every basis shares): the azimuthal block layout and the radial factors,
checked against the functions' own values at chosen azimuths."""

from __future__ import annotations

import numpy as np
import pytest

import basis

ALL = [basis.HemiZernike(7), basis.HemiHarmonics(7), basis.HemiHarmonics(6, parity="even"),
       basis.SphericalHarmonics(6)]


@pytest.mark.parametrize("b", ALL, ids=repr)
def test_azimuthal_blocks_partition_and_pair(b):
    blocks = b.azimuthal_blocks()
    both = np.concatenate([*blocks.cos, *blocks.sin])
    assert sorted(both.tolist()) == list(range(b.size))  # every function exactly once
    deg, az = b.degree, b.azimuthal
    for m, (c, s) in enumerate(zip(blocks.cos, blocks.sin, strict=True)):
        assert np.all(az[c] == m) and np.all(az[s] == -m)
        assert np.all(np.diff(deg[c]) > 0)  # ordered by degree
        if m:
            assert np.array_equal(deg[c], deg[s])  # cos and sin partners share the degree
        else:
            assert s.size == 0
    assert np.array_equal(blocks.sizes, [c.size for c in blocks.cos])
    assert b.azimuthal_blocks() is blocks  # computed once
    with pytest.raises(ValueError):
        blocks.cos[0][0] = 5  # read-only


@pytest.mark.parametrize("b", ALL, ids=repr)
def test_radial_separates_the_basis(b, rng):
    # b_k(theta, phi) = P_k(cos theta) A_k(phi) at random azimuths
    lo = 0.0 if b.domain == "hemisphere" else -1.0
    z = rng.uniform(lo, 1.0, 300)
    z[:2] = [lo, 1.0]
    phi = rng.uniform(0, 2 * np.pi, 300)
    s = np.sqrt((1 - z) * (1 + z))
    d = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1)
    az = b.azimuthal
    ang = np.where(az > 0, np.cos(az * phi[:, None]),
                   np.where(az < 0, np.sin(-az * phi[:, None]), 1.0))
    # O(1) to O(sqrt(order)) values: rounding only
    np.testing.assert_allclose(b.radial(z) * ang, b.eval(d), rtol=0, atol=1e-12)


def test_radial_errors():
    zb = basis.HemiZernike(3)
    with pytest.raises(ValueError, match=r"z must lie in \[0, 1\] for HemiZernike\(3\)"):
        zb.radial([-0.1])
    with pytest.raises(ValueError, match="z must be one-dimensional"):
        zb.radial([[0.5]])
    with pytest.raises(ValueError, match=r"z must lie in \[-1, 1\]"):
        basis.SphericalHarmonics(2).radial([np.nan])
    with pytest.raises(TypeError, match="z must be an array of floats"):
        zb.radial(["a"])
    assert basis.SphericalHarmonics(2).radial([-1.0]).shape == (1, 9)


@pytest.mark.parametrize("b", [basis.HemiZernike(5), basis.HemiHarmonics(4),
                               basis.SphericalHarmonics(6)], ids=repr)
def test_eval_into_out(b, rng):
    # reference: eval without out; every element of out must be overwritten (NaN before)
    d = rng.standard_normal((6, 5, 3))
    d[..., 2] = np.abs(d[..., 2])
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    out = np.full((6, 5, b.size), np.nan)
    got = b.eval(d, out=out)
    assert got is out
    np.testing.assert_array_equal(out, b.eval(d))


def test_eval_out_errors():
    b = basis.HemiZernike(3)
    d = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    ro = np.empty((2, b.size))
    ro.flags.writeable = False
    for bad in [np.empty((2, b.size + 1)), np.empty((2, b.size), np.float32),
                np.empty((b.size, 2)).T, ro, [[0.0] * b.size] * 2]:
        with pytest.raises(ValueError, match="out must be a writable C-contiguous float64"):
            b.eval(d, out=bad)
