"""Conversions between direction vectors, spherical angles and Rusinkiewicz coordinates.

Directions are float64 unit vectors of shape (..., 3) in the local frame of the surface: z is
the surface normal, x the tangent that azimuth 0 points along. Both directions of a pair
point away from the surface. Angles are in radians.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .validation import as_directions

__all__ = ["from_angles", "from_rusinkiewicz", "to_angles", "to_rusinkiewicz"]


def _angles(*arrays: ArrayLike, names: tuple[str, ...]) -> list[NDArray[np.float64]]:
    out = []
    for a, name in zip(arrays, names, strict=True):
        v = np.asarray(a, dtype=np.float64)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be finite (radians)")
        out.append(v)
    try:
        return list(np.broadcast_arrays(*out))
    except ValueError:
        raise ValueError(f"{', '.join(names)} must have broadcastable shapes, got "
                         f"{[o.shape for o in out]}") from None


def from_angles(theta: ArrayLike, phi: ArrayLike) -> NDArray[np.float64]:
    """Return unit vectors from polar angle ``theta`` (from z) and azimuth ``phi`` (from x).

    Both angles are in radians.

    Returns
    -------
    (..., 3) ndarray of float64, the broadcast shape of the inputs plus 3.

    Examples
    --------
    >>> from_angles(0.0, 0.0).tolist()
    [0.0, 0.0, 1.0]
    """
    t, p = _angles(theta, phi, names=("theta", "phi"))
    s = np.sin(t)
    return np.stack([s * np.cos(p), s * np.sin(p), np.cos(t)], axis=-1)


def to_angles(dirs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Return the angles (theta, phi) of unit vectors; theta in [0, pi], phi in (-pi, pi].

    theta is computed with arctan2 of (|(x, y)|, z), which stays accurate near the poles.
    """
    d = as_directions(dirs)
    return np.arctan2(np.hypot(d[..., 0], d[..., 1]), d[..., 2]), np.arctan2(d[..., 1], d[..., 0])


def to_rusinkiewicz(wi: ArrayLike, wo: ArrayLike) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Return the half/difference angles (theta_h, phi_h, theta_d, phi_d) of direction pairs.

    h = (wi + wo)/|wi + wo|, d = R_y(-theta_h) R_z(-phi_h) wi (Rusinkiewicz 1998), so that
    ``from_rusinkiewicz`` inverts it. For wi = -wo (no half vector) theta_h is set to 0.
    """
    wi = as_directions(wi, "wi")
    wo = as_directions(wo, "wo")
    h = wi + wo
    n = np.linalg.norm(h, axis=-1, keepdims=True)
    h = np.where(n > 0, h / np.where(n > 0, n, 1.0), np.array([0.0, 0.0, 1.0]))
    th, ph = to_angles(h)
    c, s = np.cos(ph), np.sin(ph)
    # rotate wi by -phi_h about z, then by -theta_h about y
    x = c * wi[..., 0] + s * wi[..., 1]
    y = -s * wi[..., 0] + c * wi[..., 1]
    z = wi[..., 2]
    ct, st = np.cos(th), np.sin(th)
    d = np.stack([ct * x - st * z, y, st * x + ct * z], axis=-1)
    td, pd = to_angles(d / np.linalg.norm(d, axis=-1, keepdims=True))
    return th, ph, td, pd


def from_rusinkiewicz(
    theta_h: ArrayLike, phi_h: ArrayLike, theta_d: ArrayLike, phi_d: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Return the directions (wi, wo) from Rusinkiewicz half/difference angles (radians).

    Examples
    --------
    >>> import numpy as np
    >>> wi, wo = from_rusinkiewicz(0.0, 0.0, np.pi / 4, 0.0)
    >>> np.round(wi, 12).tolist(), np.round(wo, 12).tolist()
    ([0.707106781187, 0.0, 0.707106781187], [-0.707106781187, 0.0, 0.707106781187])
    """
    th, ph, td, pd = _angles(theta_h, phi_h, theta_d, phi_d,
                             names=("theta_h", "phi_h", "theta_d", "phi_d"))
    h = from_angles(th, ph)
    d = from_angles(td, pd)
    ct, st = np.cos(th), np.sin(th)
    x = ct * d[..., 0] + st * d[..., 2]
    z = -st * d[..., 0] + ct * d[..., 2]
    c, s = np.cos(ph), np.sin(ph)
    wi = np.stack([c * x - s * d[..., 1], s * x + c * d[..., 1], z], axis=-1)
    wo = 2.0 * np.sum(wi * h, axis=-1, keepdims=True) * h - wi
    return wi, wo
