"""The "grid" family: a BRDF tabulated on the grid of an NVIDIA MDL measured BSDF.

``"grid"`` (a (n_theta, n_theta, n_phi, C) table of f, C = 1 or 3)
    f at the cell centres of (theta_in, theta_out, delta_phi) -- the layout of an ``.mbsdf``
    file's reflection part, :func:`project.measured.texel_centres` -- interpolated as the
    MDL SDK does (:class:`project.measured.MBSDFBRDF`). "Fitting" is sampling:
    ``fit_model(brdf, "grid", resolution=(n_theta, n_phi), symmetric=True)`` evaluates the
    BRDF at the cell centres; ``symmetric`` stores the reciprocal part (the table averaged
    with its transpose in theta_in <-> theta_out), whose reals are counted once:
    n_theta (n_theta + 1) / 2 n_phi C instead of n_theta^2 n_phi C. The default
    resolution is the BRDF's own ``resolution`` when it has one (a file read by
    :func:`project.measured.read_mbsdf`), else (45, 90), the MDL SDK's example.

Why a family of its own: an MBSDF file's lobe is what its grid makes of it. A clear coat
(GGX alpha 0.01-0.03) is narrower than the 2-degree cells of a (45, 90) file, so the file
holds, about each mirror direction, a tent of linear interpolation whose height depends on
where the cell centres fall; tables in the half/difference angles of Rusinkiewicz (1998)
cannot follow it at any resolution (0.16-0.18 l2 error on a car-paint stand-in from 147 kB
to 1.2 MB), while the file's own grid holds it exactly. Its reciprocal part at float16 is
a quarter of the file (559 kB for a (45, 90) RGB file of 2.2 MB); writing it with
:func:`project.measured.write_mbsdf` at the same resolution gives back its table.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from ..measured.mbsdf import MBSDFBRDF, texel_centres

__all__: list[str] = []

#: Options of ``fit_model(brdf, "grid")``.
GRID_OPTIONS = ("resolution", "symmetric")
#: The resolution of a grid when the BRDF has none of its own.
DEFAULT_RESOLUTION = (45, 90)


def grid_resolution(brdf: object, resolution: object = None) -> tuple[int, int]:
    """Return ``resolution``, else the BRDF's own (n_theta, n_phi), else the default."""
    if resolution is None:
        resolution = getattr(brdf, "resolution", None)
    if resolution is None:
        return DEFAULT_RESOLUTION
    try:
        n_theta, n_phi = (int(x) for x in resolution)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise TypeError(f"resolution must be two integers (n_theta, n_phi), got "
                        f"{resolution!r}") from None
    if not (1 <= n_theta <= 1024 and 1 <= n_phi <= 4096):
        raise ValueError(f"resolution must be (n_theta, n_phi) with 1 <= n_theta <= 1024 and "
                         f"1 <= n_phi <= 4096, got {(n_theta, n_phi)}")
    return n_theta, n_phi


def grid_reals(resolution: tuple[int, int], channels: int, symmetric: bool) -> int:
    """Reals a grid stores: n_theta (n_theta + 1) / 2 or n_theta^2, times n_phi C."""
    n, m = resolution
    return (n * (n + 1) // 2 if symmetric else n * n) * m * channels


def sample_grid(brdf: object, resolution: tuple[int, int], symmetric: bool) -> NDArray:
    """Return the (n, n, m, C) table of ``brdf.eval`` at the cell centres."""
    n, m = resolution
    theta, dphi = texel_centres((n, m))
    st, ct = np.sin(theta), np.cos(theta)
    wo = np.stack(np.broadcast_arrays(st[:, None] * np.cos(dphi), st[:, None] * np.sin(dphi),
                                      ct[:, None]), axis=-1).reshape(-1, 3)
    rows = []
    for i in range(n):  # one theta_in at a time bounds the memory of eval
        wi = np.broadcast_to(np.array([st[i], 0.0, ct[i]]), wo.shape)
        f = np.asarray(brdf.eval(wi, wo), dtype=np.float64)  # type: ignore[attr-defined]
        rows.append(f.reshape(n, m, -1))
    table = np.stack(rows)
    if not np.all(np.isfinite(table)):
        raise ValueError("brdf must be finite at the cell centres of the grid")
    if symmetric:
        table = 0.5 * (table + table.transpose(1, 0, 2, 3))
    return table


def grid_model(table: object) -> tuple[MBSDFBRDF, bool]:
    """Return the lookup of a grid's table and whether the table is symmetric (reciprocal).

    ``table`` is the whole (n, n, m, C) table, or the packed (n (n + 1) / 2, m, C) upper
    triangle of a symmetric one (:func:`pack_symmetric`, the form a file stores).
    """
    t = np.asarray(table, dtype=np.float64)
    if t.ndim == 3:
        t = unpack_symmetric(t)
    brdf = MBSDFBRDF(t)  # checks the shape (n, n, m, 1 or 3) and finiteness
    t = brdf.table
    return brdf, bool(np.array_equal(t, t.transpose(1, 0, 2, 3)))


def pack_symmetric(table: NDArray) -> NDArray:
    """Return the (n (n + 1) / 2, m, C) entries theta_in <= theta_out of a symmetric table.

    These are the reals a symmetric grid stores (:func:`grid_reals`); the transpose
    holds the rest.
    """
    i, j = np.triu_indices(table.shape[0])
    return table[i, j]


def unpack_symmetric(packed: NDArray) -> NDArray:
    """Return the symmetric (n, n, m, C) table of its packed upper triangle."""
    k = packed.shape[0]
    n = int(round((math.sqrt(8 * k + 1) - 1) / 2))
    if k == 0 or n * (n + 1) // 2 != k:
        raise ValueError(f"a packed grid table must have n (n + 1) / 2 rows (a triangular "
                         f"number), got shape {packed.shape}")
    i, j = np.triu_indices(n)
    table = np.empty((n, n, *packed.shape[1:]))
    table[i, j] = packed
    table[j, i] = packed
    return table
