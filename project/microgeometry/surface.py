"""Periodic height fields for the microgeometry simulator: user maps and Gaussian surfaces.

A height field h[j, i] on a regular grid (x = i dx, y = j dy) is tiled periodically with
period (nx dx, ny dy) and triangulated: cell (i, j) is split along its (0, 0)-(1, 1)
diagonal into triangle A (corners 00, 10, 11; u >= v) and triangle B (00, 11, 01; v >= u),
u, v the local coordinates in [0, 1]. Periodic tiling removes the edge and target-area
problems of a finite patch: Westin, Arvo & Torrance (1992) aim their rays at a target region
that must lie well inside the modelled geometry (sec. 4.5), and for their Gaussian surface
(sec. 5.1) used a 3.13 mm patch in the centre of an 8 x 8 mm model, i.e. a margin of
(8 - 3.13) / 2 = 2.4 mm on each side. The traversal structure is a max-height mip pyramid
over the cells.
"""

from __future__ import annotations

import hashlib

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basis.validation import check_bytes

from .materials import DIELECTRIC, Material, Mirror

__all__ = ["GaussianSurface", "Heightfield"]

#: Peak bytes per grid point of GaussianSurface: white noise, wavenumbers and filter (float64),
#: the complex spectrum, its filtered copy and the inverse transform (complex128); measured
#: with tracemalloc at 72.0 for resolution 1024
_BYTES_PER_POINT = 72.0


class Heightfield:
    """A user height map, tiled periodically and triangulated (two triangles per cell).

    Parameters
    ----------
    heights : (ny, nx) array_like of float
        Heights in length units, at x = i * dx, y = j * dy; ny, nx >= 2, all finite. The map
        is treated as one period of a periodic surface: cell (nx - 1, j) joins column nx - 1
        to column 0. A map that is not periodic gets a step at the seam (make it periodic, or
        accept the seam as part of the specimen).
    spacing : float or (2,) array_like of float
        Grid spacing (dx, dy) > 0, same length units as ``heights``.
    material : Material, optional
        Facet material of every triangle (default: lossless :class:`Mirror`).

    Attributes
    ----------
    heights : (ny, nx) ndarray
        A read-only float64 copy.
    period : (2,) ndarray
        (nx dx, ny dy).
    triangles : int
        2 nx ny.
    levels : int
        Levels of the max-height mip pyramid above the cells.

    Examples
    --------
    >>> import numpy as np
    >>> hf = Heightfield(np.zeros((4, 4)), 0.5)
    >>> hf.triangles, hf.period.tolist(), hf.roughness
    (32, [2.0, 2.0], 0.0)
    """

    def __init__(self, heights: ArrayLike, spacing: ArrayLike, *,
                 material: Material | None = None) -> None:
        try:
            h = np.array(heights, dtype=np.float64)
        except (TypeError, ValueError):
            raise TypeError(f"heights must be a 2-D array of floats, got "
                            f"{type(heights).__name__}") from None
        if h.ndim != 2 or h.size == 0:
            raise ValueError(f"heights must be a non-empty 2-D array, got shape {h.shape}")
        if min(h.shape) < 2:
            raise ValueError(f"heights must have at least 2 x 2 points, got shape {h.shape}")
        bad = int(np.sum(~np.isfinite(h)))
        if bad:
            raise ValueError(f"heights must be finite: {bad} of {h.size} values are NaN or inf")
        try:
            sp = np.broadcast_to(np.asarray(spacing, dtype=np.float64), (2,)).copy()
        except (TypeError, ValueError):
            raise ValueError(f"spacing must be a number or a pair (dx, dy), got "
                             f"{spacing!r}") from None
        if not np.all(np.isfinite(sp)) or np.any(sp <= 0):
            raise ValueError(f"spacing must be finite and > 0, got {spacing!r}")
        if material is None:
            material = Mirror()
        if not isinstance(material, Material):
            raise TypeError(f"material must be a Material (Mirror, Diffuse, MicroBRDF), got "
                            f"{type(material).__name__}")
        if material.code == DIELECTRIC:
            # an open surface has no inside for the refracted light to travel in
            raise ValueError(f"material must be opaque (Mirror, Diffuse, MicroBRDF) on a "
                             f"Heightfield, which is an open surface with no inside; put a "
                             f"Dielectric on closed parts of a Scene (closed meshes, spheres, "
                             f"capped tubes, cylinders), got {material!r}")
        h.setflags(write=False)
        self.heights = h
        self.spacing = sp
        self.material = material
        self._pyramid, self._offsets, self._levels = _max_pyramid(h)

    @property
    def shape(self) -> tuple[int, int]:
        """(ny, nx) grid points per period."""
        return self.heights.shape

    @property
    def period(self) -> NDArray[np.float64]:
        """(2,) period (nx dx, ny dy) of the tiling, in length units."""
        return np.array([self.shape[1] * self.spacing[0], self.shape[0] * self.spacing[1]])

    @property
    def triangles(self) -> int:
        """Number of triangles per period, 2 nx ny."""
        return 2 * self.heights.size

    @property
    def levels(self) -> int:
        """Number of levels of the max-height mip pyramid above the cells (read-only).

        The tracer skips empty space with a pyramid whose level 0 holds, per cell, the
        highest of its four corners and whose level L + 1 the max over 2 x 2 nodes of level
        L, built while both dimensions stay even: 0 for a grid with an odd side (a plain
        cell walk), log2(n) for an n x n grid with n a power of two.

        Examples
        --------
        >>> Heightfield(np.zeros((8, 16)), 1.0).levels, Heightfield(np.zeros((6, 7)), 1.0).levels
        (3, 0)
        """
        return self._levels

    def slopes(self) -> NDArray[np.float64]:
        """Return the (2 ny nx, 2) facet slopes (dh/dx, dh/dy) of every triangle.

        The rows hold triangle A then B of each cell.

        All triangles have the same projected area, so plain averages over these rows are
        averages over the mean plane.
        """
        h = self.heights
        dx, dy = self.spacing
        h10 = np.roll(h, -1, axis=1)
        h01 = np.roll(h, -1, axis=0)
        h11 = np.roll(h01, -1, axis=1)
        a = np.stack([(h10 - h) / dx, (h11 - h10) / dy], axis=-1)
        b = np.stack([(h11 - h01) / dx, (h01 - h) / dy], axis=-1)
        return np.concatenate([a.reshape(-1, 2), b.reshape(-1, 2)])

    @property
    def roughness(self) -> float:
        """Measured Beckmann RMS slope m = sqrt(<(dh/dx)^2 + (dh/dy)^2>) of the mesh.

        For a Beckmann distribution m^2 = <tan^2 theta_h>; compare the simulation against
        this measured value, since triangulation lowers the slope variance: a facet's slope
        is a difference quotient over one grid step dx, whose variance for the Gaussian
        autocorrelation sigma^2 exp(-r^2 / tau^2) is that of the continuous surface times
        (1 - exp(-dx^2 / tau^2)) / (dx^2 / tau^2).
        """
        s = self.slopes()
        return float(np.sqrt(np.mean(np.sum(s * s, axis=1))))

    def fingerprint(self) -> str:
        """Return the SHA-256 of heights, spacing and material (the specimen's checkpoint id)."""
        d = hashlib.sha256()
        d.update(np.ascontiguousarray(self.heights).tobytes())
        d.update(str(self.heights.shape).encode())
        d.update(self.spacing.tobytes())
        d.update(repr(self.material).encode())
        return d.hexdigest()

    def __repr__(self) -> str:
        return (f"Heightfield(shape={self.shape}, spacing={self.spacing.tolist()}, "
                f"material={self.material!r})")


class GaussianSurface(Heightfield):
    """A periodic Gaussian random height field made by FFT filtering of white noise.

    Parameters
    ----------
    sigma : float
        RMS height > 0 (the sample standard deviation is set to exactly ``sigma``).
    tau : float
        Correlation length > 0: the autocorrelation is sigma^2 exp(-r^2 / tau^2) (He et al.
        1991, eq 48), so the Beckmann RMS slope is m = 2 sigma / tau.
    resolution : int
        Grid points per side (the period holds resolution^2 points and 2 resolution^2
        triangles). Default 128.
    spacing : float, optional
        Grid spacing dx. Default tau / 4: triangulation then lowers the per-axis slope
        variance by the factor (1 - exp(-dx^2 / tau^2)) / (dx^2 / tau^2)
        = (1 - exp(-1/16)) * 16 = 0.969 (computed from the autocorrelation, see
        :attr:`roughness`), i.e. m is 1.5 % low; :attr:`roughness` reports the measured m.
    seed : int
        Seed of the white noise (numpy ``default_rng``).
    material : Material, optional
        Facet material (default lossless :class:`Mirror`).

    Notes
    -----
    White noise w on the grid is filtered in Fourier space by exp(-|k|^2 tau^2 / 8), which
    gives the power spectrum exp(-|k|^2 tau^2 / 4), i.e. the autocorrelation
    exp(-r^2 / tau^2); the result is shifted to zero mean and scaled to RMS ``sigma``. With
    the defaults the period is 32 tau, an area of 1024 tau^2: about 330 correlation areas
    pi tau^2 (the integral of exp(-r^2 / tau^2) over the plane).

    References
    ----------
    He, X. D., Torrance, K. E., Sillion, F. X. and Greenberg, D. P. A comprehensive physical
    model for light reflection. Computer Graphics 25(4) (SIGGRAPH '91), 175-186, 1991.

    Examples
    --------
    >>> s = GaussianSurface(1.0, 6.5, resolution=64, seed=1)
    >>> s.shape, round(float(s.heights.std()), 12), s.triangles
    ((64, 64), 1.0, 8192)
    """

    def __init__(self, sigma: float, tau: float, *, resolution: int = 128,
                 spacing: float | None = None, seed: int = 0,
                 material: Material | None = None) -> None:
        sigma = _positive(sigma, "sigma")
        tau = _positive(tau, "tau")
        if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)):
            raise TypeError(f"resolution must be an integer, got {resolution!r}")
        if resolution < 4:
            raise ValueError(f"resolution must be >= 4, got {resolution}")
        sp = tau / 4.0 if spacing is None else _positive(spacing, "spacing")
        n = int(resolution)
        check_bytes(_BYTES_PER_POINT * n * n, f"GaussianSurface(resolution={n}) "
                                              f"({n} x {n} points)")
        rng = np.random.default_rng(seed)
        white = rng.standard_normal((n, n))
        k = 2.0 * np.pi * np.fft.fftfreq(n, d=sp)
        k2 = k[:, None] ** 2 + k[None, :] ** 2
        h = np.fft.ifft2(np.fft.fft2(white) * np.exp(-k2 * tau * tau / 8.0)).real
        h -= h.mean()
        h *= sigma / h.std()
        super().__init__(h, sp, material=material)
        self.sigma, self.tau, self.seed = sigma, tau, seed

    @property
    def nominal_roughness(self) -> float:
        """Beckmann m = 2 sigma / tau of the continuous surface."""
        return 2.0 * self.sigma / self.tau

    def __repr__(self) -> str:
        return (f"GaussianSurface(sigma={self.sigma:g}, tau={self.tau:g}, "
                f"resolution={self.shape[0]}, spacing={self.spacing[0]:g}, seed={self.seed}, "
                f"material={self.material!r})")


def _positive(value: object, name: str) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be finite and > 0, got {value!r}")
    return v


def _max_pyramid(h: NDArray[np.float64]) -> tuple[NDArray, NDArray, int]:
    """Build the max-height mip pyramid of the cells, flattened level after level.

    Level 0 holds, per cell (i, j), the max of its four corners (periodic); level L + 1 the
    max over 2 x 2 nodes of level L, while both dimensions stay even. Returns the flat
    values, the offset of each level (plus the end) and the number of levels above 0.

    The values are float32, each the smallest float32 at or above its float64 maximum: a
    node may only look higher than it is, which makes the walk descend a little more often
    but never skip a facet (the facets themselves are intersected in float64), so the paths
    are the same bits; half the bytes keep more of the pyramid in cache (the tracer runs
    1.2-1.3x faster on a 512 x 512 field).
    """
    cell = np.maximum(np.maximum(h, np.roll(h, -1, 0)),
                      np.maximum(np.roll(h, -1, 1), np.roll(np.roll(h, -1, 0), -1, 1)))
    c = cell.astype(np.float32)
    low = c < cell  # compared in float64
    c[low] = np.nextafter(c[low], np.float32(np.inf))
    del cell, low
    # rounding up is monotone, so the max of rounded-up values is the rounded-up max
    levels = [c]
    while c.shape[0] % 2 == 0 and c.shape[1] % 2 == 0 and min(c.shape) > 1:
        c = np.maximum(np.maximum(c[0::2, 0::2], c[1::2, 0::2]),
                       np.maximum(c[0::2, 1::2], c[1::2, 1::2]))
        levels.append(c)
    offsets = np.cumsum([0] + [lv.size for lv in levels]).astype(np.int64)
    flat = np.concatenate([lv.reshape(-1) for lv in levels])
    return flat, offsets, len(levels) - 1
