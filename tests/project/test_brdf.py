"""project.brdf: the BRDF contract (validation, broadcasting, horizon, channel shapes), the
ideal mirror term and the parameter helpers, on small BRDFs whose values are known exactly."""

from __future__ import annotations

import numpy as np
import pytest

from project.brdf import BRDF, MirrorDelta, as_color, broadcast_channels
from tests.conftest import random_directions


class _Const(BRDF):
    """f = c / pi: the Lambertian of albedo c, per channel."""

    def __init__(self, c, scalar=True):
        self.c = np.atleast_1d(np.asarray(c, dtype=float))
        self.channels = self.c.size
        self._scalar = scalar

    def _eval(self, wi, wo):
        assert wi.flags.c_contiguous and wo.flags.c_contiguous
        assert np.all(wi[:, 2] >= 0) and np.all(wo[:, 2] >= 0)  # the contract of _eval
        return np.broadcast_to(self.c / np.pi, (wi.shape[0], self.channels))


def test_shapes_broadcast_and_horizon(rng):
    f = _Const(0.5)
    wi = random_directions(rng, (4, 1))
    wo = random_directions(rng, (1, 6))
    v = f.eval(wi, wo)
    assert v.shape == (4, 6)
    below = (wi[..., 2] < 0) | (wo[..., 2] < 0)
    assert np.all(v[below] == 0.0) and np.all(v[~below] == 0.5 / np.pi)
    rgb = _Const([0.1, 0.2, 0.3])
    assert rgb.eval(wi, wo).shape == (4, 6, 3)
    one = _Const([0.5], scalar=False)  # one channel given as a sequence keeps its axis
    assert one.eval(wi[0, 0], wo[0, 0]).shape == (1,)


def test_all_below_horizon_never_calls_eval():
    v = _Const(0.5).eval([0, 0, -1.0], [0.6, 0, 0.8])
    assert v.shape == () and v == 0.0


def test_albedo_of_lambert_with_mirror_term():
    # Lambert albedo c (exact for the product rule: the integrand is cos theta_o) plus R
    f = _Const([0.25, 0.5])
    f.delta = (MirrorDelta([0.1, 0.2]),)
    a = f.albedo([[0, 0, 1.0], [0.6, 0, 0.8], [0, 0.6, -0.8]], n_theta=4, n_phi=4)
    np.testing.assert_allclose(a[:2], [[0.35, 0.7], [0.35, 0.7]], rtol=1e-14)
    assert np.all(a[2] == 0.0)


def test_mirror_delta():
    d = MirrorDelta(0.3)
    assert d.is_constant and d.channels == 1
    np.testing.assert_array_equal(d.reflectance([1.0, 0.5]), [[0.3], [0.3]])
    fresnel = MirrorDelta(lambda c: np.stack([c, c * c], axis=-1), channels=2)
    assert not fresnel.is_constant and fresnel.constant is None
    np.testing.assert_array_equal(fresnel.reflectance([0.5]), [[0.5, 0.25]])
    with pytest.raises(ValueError, match="channels must be given"):
        MirrorDelta(lambda c: c)
    with pytest.raises(ValueError, match=r"reflectance must be <= 1"):
        MirrorDelta(1.5)


def test_as_color_and_broadcast_channels():
    np.testing.assert_array_equal(as_color(0.5, "kd"), [0.5])
    np.testing.assert_array_equal(as_color([0.1, 0.2], "kd"), [0.1, 0.2])
    cases = [
        (TypeError, "kd must be a number or a sequence", dict(value="red")),
        (ValueError, "kd must be a number or a 1-D sequence", dict(value=[[0.1]])),
        (ValueError, "kd must be finite", dict(value=np.nan)),
        (ValueError, "kd must be >= 0", dict(value=-0.1)),
        (ValueError, "kd must be > 0", dict(value=0.0, open_low=True)),
        (ValueError, "kd must be <= 1", dict(value=2.0, high=1.0)),
    ]
    for exc, match, kw in cases:
        with pytest.raises(exc, match=match):
            as_color(name="kd", **kw)
    assert broadcast_channels(a=np.ones(1), b=np.ones(3)) == 3
    assert broadcast_channels(a=np.ones(1)) == 1
    with pytest.raises(ValueError, match="per-channel parameters must have the same length"):
        broadcast_channels(a=np.ones(2), b=np.ones(3))


def test_bad_directions():
    with pytest.raises(ValueError, match="wo must be unit vectors"):
        _Const(0.5).eval([0, 0, 1.0], [0, 0, 3.0])
    with pytest.raises(ValueError, match="broadcastable batch shapes"):
        _Const(0.5).eval(np.eye(3), np.eye(3)[:2])
