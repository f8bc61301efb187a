"""A small standard scene: a sphere under a constant environment and a point light."""

from __future__ import annotations

import operator
from typing import Any

import mitsuba as mi
import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["MAX_SIZE", "relative_rmse", "sphere_scene", "to_numpy"]

#: Largest image side of :func:`sphere_scene`.
MAX_SIZE = 4096


def _positive_int(value: object, name: str, high: int | None = None) -> int:
    try:
        n = operator.index(value)  # rejects 2.0, "2", None
    except TypeError:
        raise TypeError(f"{name} must be an integer, got {value!r}") from None
    if n < 1 or (high is not None and n > high):
        bound = f"in [1, {high}]" if high is not None else ">= 1"
        raise ValueError(f"{name} must be {bound}, got {n}")
    return n


def sphere_scene(material: Any, *, size: int = 64, spp: int = 16, environment: float = 0.5,
                 point: float = 20.0, max_depth: int = 2) -> Any:
    """Build the Mitsuba scene of a unit sphere with ``material``, lit from around and above.

    A perspective camera 4 units away along +z (field of view 33 degrees: the sphere fills
    most of the frame), a constant environment of radiance ``environment`` and a point
    light of intensity ``point`` at (2.5, 3, 3). The sphere is alone, so ``max_depth=2``
    (one bounce) is exact: a convex object never sees itself.

    Parameters
    ----------
    material : mitsuba.BSDF or dict
        The sphere's BSDF (e.g. :func:`compress.mitsuba.bsdf` or a plugin dictionary).
    size : int
        Image side in pixels, 1 to :data:`MAX_SIZE`.
    spp : int
        Samples per pixel (``independent`` sampler), >= 1.
    environment, point : float
        Radiance of the environment and intensity of the point light (W/sr), >= 0.
    max_depth : int
        Path length of Mitsuba's ``path`` integrator.

    Returns
    -------
    mitsuba.Scene
    """
    size = _positive_int(size, "size", MAX_SIZE)
    spp = _positive_int(spp, "spp")
    for name, v in (("environment", environment), ("point", point)):
        if not (isinstance(v, int | float) and 0 <= v < float("inf")):
            raise ValueError(f"{name} must be a number >= 0, got {v!r}")
    T = mi.ScalarTransform4f
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(max_depth)},
        "sensor": {
            "type": "perspective", "fov": 33.0,
            "to_world": T().look_at(origin=[0.0, 0.0, 4.0], target=[0.0, 0.0, 0.0],
                                    up=[0.0, 1.0, 0.0]),
            "film": {"type": "hdrfilm", "width": size, "height": size,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "sphere": {"type": "sphere", "bsdf": material},
    }
    if environment > 0:
        scene["environment"] = {"type": "constant",
                                "radiance": {"type": "rgb", "value": float(environment)}}
    if point > 0:
        scene["light"] = {"type": "point", "position": [2.5, 3.0, 3.0],
                          "intensity": {"type": "rgb", "value": float(point)}}
    return mi.load_dict(scene)


def relative_rmse(image: ArrayLike, reference: ArrayLike) -> float:
    """Return sqrt(mean((image - reference)^2) / mean(reference^2)) over pixels and channels.

    Parameters
    ----------
    image, reference : array_like of float
        Images of the same shape (e.g. (height, width, 3) radiance).

    Returns
    -------
    float
        0 for identical images; ``inf`` when the reference is all zero and the image is not.
    """
    a = np.asarray(image, dtype=np.float64)
    b = np.asarray(reference, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"image and reference must have the same shape, got {a.shape} and "
                         f"{b.shape}")
    num = float(np.mean((a - b) ** 2))
    den = float(np.mean(b * b))
    if den == 0:
        return 0.0 if num == 0 else float("inf")
    return float(np.sqrt(num / den))


def to_numpy(image: Any) -> NDArray[np.float64]:
    """Return a Mitsuba image tensor as a (height, width, channels) float64 array."""
    return np.array(image, dtype=np.float64)
