"""Angle and Rusinkiewicz conversions: round trips, known cases, and the MERL convention."""

import numpy as np
import pytest

from basis import from_angles, from_rusinkiewicz, to_angles, to_rusinkiewicz


def test_angles_round_trip(rng):
    theta = rng.uniform(0, np.pi, 100)
    phi = rng.uniform(-np.pi, np.pi, 100)
    t, p = to_angles(from_angles(theta, phi))
    # arctan2 round trip: a few ulps of angles up to pi
    np.testing.assert_allclose(t, theta, rtol=0, atol=4e-15)
    np.testing.assert_allclose(p, phi, rtol=0, atol=4e-15)


def test_angles_accurate_near_pole():
    # arccos(z) would lose half the digits here; arctan2(s, z) keeps them
    t, _ = to_angles(from_angles(1e-9, 0.0))
    assert t == pytest.approx(1e-9, rel=1e-15)


def test_rusinkiewicz_round_trip(rng):
    wi = from_angles(rng.uniform(0, np.pi / 2, 200), rng.uniform(-np.pi, np.pi, 200))
    wo = from_angles(rng.uniform(0, np.pi / 2, 200), rng.uniform(-np.pi, np.pi, 200))
    wi2, wo2 = from_rusinkiewicz(*to_rusinkiewicz(wi, wo))
    # composed rotations of unit vectors: a few ulps
    np.testing.assert_allclose(wi2, wi, rtol=0, atol=1e-14)
    np.testing.assert_allclose(wo2, wo, rtol=0, atol=1e-14)


def test_rusinkiewicz_known_cases():
    # theta_d = 0: both directions equal the half vector
    wi, wo = from_rusinkiewicz(0.4, 1.0, 0.0, 0.0)
    np.testing.assert_allclose(wi, from_angles(0.4, 1.0), atol=1e-15)
    np.testing.assert_allclose(wo, wi, atol=1e-15)
    # theta_h = 0: a mirror pair about the normal, both at polar angle theta_d
    wi, wo = from_rusinkiewicz(0.0, 0.0, 0.6, 0.3)
    np.testing.assert_allclose(wo, wi * [-1, -1, 1], atol=1e-15)
    assert to_angles(wi)[0] == pytest.approx(0.6, abs=1e-15)


def test_matches_merl_surrogate_convention():
    """The surrogate writer (shared/tools/merl_surrogate.py) builds wi by rotating d by theta_h
    about y (phi_h = 0) and wo as the mirror of wi about h; re-derived here independently."""
    th, td, pd = 0.5, 0.7, 1.9
    h = np.array([np.sin(th), 0, np.cos(th)])
    d = from_angles(td, pd)
    c, s = np.cos(th), np.sin(th)
    wi_ref = np.array([c * d[0] + s * d[2], d[1], -s * d[0] + c * d[2]])
    wo_ref = 2 * (wi_ref @ h) * h - wi_ref
    wi, wo = from_rusinkiewicz(th, 0.0, td, pd)
    np.testing.assert_allclose(wi, wi_ref, atol=1e-15)
    np.testing.assert_allclose(wo, wo_ref, atol=1e-15)


def test_bad_input():
    with pytest.raises(ValueError, match="theta must be finite"):
        from_angles(np.nan, 0.0)
    with pytest.raises(ValueError, match="broadcastable shapes"):
        from_angles(np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match=r"wi must have shape \(\.\.\., 3\)"):
        to_rusinkiewicz(np.zeros(2), np.zeros(3))
