"""Shared checks of the Monte Carlo microgeometry tests (imported as ``tests.project.mc``).

Statistical assertions compare in units of the batch-means standard error of
:class:`~project.microgeometry.SimulationResult` (k = ``K_SIGMA``); the rotation checks use
the exact action of the +90 degree turn about z on a hemisphere basis. ``fresnel_hecht`` is
the textbook Fresnel reference of the dielectric tests.
"""

from __future__ import annotations

import numpy as np

from project.microgeometry import Mirror

#: Monte Carlo tolerance in standard errors (a false alarm per entry ~ 6e-7 for Gaussian noise)
K_SIGMA = 5.0

#: n + i k of aluminium near 550 nm
ALUMINIUM = Mirror(0.96, 6.69)


def direction(theta_deg: float, phi_deg: float = 0.0) -> np.ndarray:
    """Unit vector at polar angle theta and azimuth phi (degrees)."""
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def rotation_action(basis):
    """A with b(R^-1 w) = A b(w) for R the +90 degree turn about z, by least squares on
    random directions; for 90 degrees cos(m (phi - pi/2)) and sin(...) are +-cos(m phi) or
    +-sin(m phi), so A is a signed permutation (checked)."""
    w = np.random.default_rng(5).normal(size=(400, 3))
    w[:, 2] = np.abs(w[:, 2])
    w /= np.linalg.norm(w, axis=1)[:, None]
    rinv = np.stack([w[:, 1], -w[:, 0], w[:, 2]], 1)
    at = np.linalg.lstsq(basis.eval(w), basis.eval(rinv), rcond=None)[0]
    a = np.round(at.T)
    np.testing.assert_allclose(at.T, a, rtol=0, atol=1e-10)
    return a


def rotated_z(res_a, res_b, a):
    """max |M_b - A^T M_a A| in units of the combined standard error (A signed permutation,
    so the standard errors map through |A|)."""
    ma = a.T @ res_a.matrix.matrix @ a
    sa = np.abs(a).T @ res_a.stderr @ np.abs(a)
    return float(np.max(np.abs(res_b.matrix.matrix - ma) / np.hypot(sa, res_b.stderr)))


def assert_anisotropic_and_turns(basis, rx, ry, rrot):
    """Brushed along x (rx), along y (ry) and the x scene turned by 90 degrees (rrot):
    turning the geometry turns the BRDF (M_y = A^T M_x A within k sigma), while the unturned
    matrices differ by far more than the noise and entries coupling different azimuthal
    orders (zero for isotropic BRDFs) are large."""
    a = rotation_action(basis)
    assert rotated_z(rx, ry, a) < K_SIGMA
    assert rotated_z(rx, rrot, a) < K_SIGMA
    assert np.max(np.abs(ry.matrix.matrix - rx.matrix.matrix)
                  / np.hypot(ry.stderr, rx.stderr)) > 10 * K_SIGMA
    m = np.abs(basis.azimuthal)
    off = m[:, None] != m[None, :]
    assert np.max(np.abs(rx.matrix.matrix[off]) / rx.stderr[off]) > 10 * K_SIGMA


def mean_z(x: np.ndarray, ref: float) -> float:
    """|mean(x) - ref| in standard errors of the mean (inf-safe for constant x)."""
    se = x.std() / np.sqrt(x.size)
    return abs(x.mean() - ref) / se if se > 0 else (0.0 if x.mean() == ref else np.inf)


def fresnel_hecht(cos_i: float, n: float) -> float:
    """Unpolarised reflectance of a real relative index n (either side), 1 beyond the
    critical angle: r_s = (cos_i - n cos_t) / (cos_i + n cos_t), r_p = (n cos_i - cos_t) /
    (n cos_i + cos_t), cos_t from Snell's law."""
    sin_t2 = (1.0 - cos_i * cos_i) / (n * n)
    if sin_t2 >= 1.0:
        return 1.0
    cos_t = np.sqrt(1.0 - sin_t2)
    rs = (cos_i - n * cos_t) / (cos_i + n * cos_t)
    rp = (n * cos_i - cos_t) / (n * cos_i + cos_t)
    return 0.5 * (rs * rs + rp * rp)
