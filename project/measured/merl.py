"""Measured BRDFs: reading, writing and evaluating MERL ``.binary`` tables.

The MERL BRDF database (Matusik et al. 2003) stores each isotropic material as RGB values on a
90 x 90 x 180 grid of Rusinkiewicz half/difference angles (theta_h, theta_d, phi_d).
:func:`read_merl` returns a :class:`MERLBRDF`, a :class:`~project.brdf.BRDF` that evaluates
the table at any direction pair; :func:`write_merl` writes a table, or samples any BRDF, in
the same format.

Notes
-----
**File layout.** Checked against the MERL reference reader ``BRDFRead.cpp`` as copied in
public code (e.g. ``BRDFMeasuredMERL.cpp`` of Disney's BRDF Explorer, wdas/brdf) and against
surrogate MERL files, written in the reference reader's layout from the neural fits of the
100 MERL materials by Sztrajman et al. ("Neural BRDF representation and importance
sampling", Computer Graphics Forum 2021); they agree on every point below (the surrogate
files themselves are checked in ``tests/project/test_measured.py``):

- header: three little-endian int32, the dimensions (n_theta_h, n_theta_d, n_phi_d) =
  (90, 90, 180); the reference reader only checks their product (1,458,000), this reader
  requires exactly (90, 90, 180) because the layout below depends on the order;
- body: 3 x 1,458,000 little-endian float64, channel-major (all red, then green, then blue);
  file size 12 + 8 * 4,374,000 = 34,992,012 bytes;
- flat index within a channel block: ``phi_d_i + 180 * (theta_d_i + 90 * theta_h_i)``, i.e.
  ``raw.reshape(3, 90, 90, 180)`` is indexed ``[channel, theta_h, theta_d, phi_d]``;
- theta_h is non-linear: continuous index u = 90 sqrt(theta_h / (pi/2)) (the reference reader
  writes ``sqrt(theta_h / (pi/2) * 90 * 90)``, the same number); node i sits at
  theta_h = (i/90)^2 pi/2, so the grid is dense near the specular direction;
- theta_d is linear, node j at j * (pi/2)/90 (1 degree steps over [0, pi/2));
- phi_d is linear, node k at k * pi/180 over [0, pi): reciprocity (swapping w_i and w_o maps
  phi_d to phi_d + pi) folds the full circle onto half of it;
- stored value = BRDF / scale with scale = (1/1500, 1.15/1500, 1.66/1500) for (R, G, B), so
  BRDF (1/sr) = stored * scale;
- negative stored values mark invalid cells: the real files use -1 in all three channels
  (reported in the GitHub issue ryushinn/meta-sampling#1); the surrogate writes -1 exactly
  where the incident or outgoing direction of the node lies at or below the horizon (z <= 0),
  23.8 % of the cells, in all channels, and clamps its other values to >= 0. This reader
  treats any negative value as invalid, per channel.
- node directions: w_i is d rotated by theta_h about y (phi_h = 0) and w_o its mirror about
  h, which is :func:`basis.from_rusinkiewicz` (checked in ``tests/basis``).

**Where each node sits in its cell.** Node i is the *lower* edge of cell i in every
coordinate, not its centre: the surrogate samples (theta_h, theta_d, phi_d) =
((i/90)^2 pi/2, j deg, k deg), and the MERL reference lookup takes the cell
``int(u)``, the cell whose lower node is below the point. :func:`write_merl` samples BRDFs at
the same nodes, and :class:`MERLBRDF` places the stored values there, so writing and reading
are inverse to each other at the nodes. (Sampling at cell centres, ((i + 1/2)/90)^2 pi/2 and
so on, would shift every value by half a cell against all other readers.) Two node families
lie exactly on the horizon in exact arithmetic (theta_h index 30 with theta_d 80 deg, and 60
with 50 deg, at phi_d = 0); :func:`write_merl` evaluates nodes within 1e-12 of the horizon on
it, which marks the same cells invalid as the surrogate does.

**Interpolation.** ``"trilinear"`` (the default) interpolates linearly in the index
coordinates (u, v, w) = (90 sqrt(2 theta_h/pi), theta_d / 1 deg, phi_d / 1 deg): it is
continuous, so quadrature projections of the table converge smoothly as the rule is refined,
and it reproduces the stored values at the nodes. ``"nearest"`` returns the value of the
nearest node in those coordinates (rounding, at most half a cell off; the reference reader's
``int(u)`` is up to a whole cell off, and at the nodes themselves it can fall one cell low by
rounding). phi_d is periodic with period pi (node 179 neighbours node 0). Beyond the last
node in theta_h (u > 89, theta_h > 87.0 deg) and theta_d (theta_d > 89 deg), where the table
has no nodes, the value of the last node is used (constant extrapolation). Two angles are
undefined at the edges of the domain: at theta_h = 0 (h = z) phi_h is taken as 0, so phi_d
is measured from x; at theta_d = 0 (w_i = w_o) phi_d is taken as 0. A physical isotropic
table does not depend on phi_d there; a table that does is read at those conventions.

**Evaluation** is one numba kernel, parallel over pairs: Rusinkiewicz coordinates are formed
from h = w_i + w_o and w_i - w_o (so f(w_i, w_o) == f(w_o, w_i) bit for bit), then the
lookup; about 0.12 s per million pairs on 2 cores, plus about 0.1 s of validation in
:meth:`BRDF.eval`.

**Invalid cells.** ``MERLBRDF.table`` keeps them as NaN (``valid`` is the mask,
``valid_fraction`` its mean). For evaluation each channel's NaN cells are filled with the
value of the nearest valid node of that channel (Euclidean distance in index space, not
wrapping in phi_d; ``scipy.ndimage.distance_transform_edt``). Nearly all invalid cells are
below the horizon and are reached only by the interpolation stencil of pairs just above it,
so those pairs get values continued from the valid side instead of being pulled towards 0
(or -1/1500) as they would be if the markers were used as values. A pair of directions both
above the horizon always evaluates to a finite value >= 0; pairs with a direction below the
horizon evaluate to 0 (the BRDF contract).

**Rounding of the scale.** A value t is stored as fl(t / scale) and read back as
fl(stored * scale). This returns t bit for bit whenever t is itself such a product (every
table read from a file); about 10-15 % of arbitrary doubles are not a product of a double
with fl(1/1500) and come back within 1 ulp.

References
----------
W. Matusik, H. Pfister, M. Brand, L. McMillan, "A data-driven reflectance model", ACM TOG
22(3), 2003. S. Rusinkiewicz, "A new change of variables for efficient BRDF representation",
Eurographics Rendering Workshop, 1998.
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from basis.directions import from_rusinkiewicz
from basis.jit import loopjit, njit, run_parallel
from basis.validation import choice

from .._halfdiff import (
    cell,
    cell_trilinear,
    half_difference,
    half_difference_unit,
    periodic_cell,
)
from ..brdf import BRDF
from ..io import atomic_path
from ._files import as_path, input_file, output_file

__all__ = [
    "MERL_BYTES",
    "MERL_SCALE",
    "MERL_SHAPE",
    "MERLBRDF",
    "merl_grid",
    "read_merl",
    "write_merl",
]

N_THETA_H, N_THETA_D, N_PHI_D = 90, 90, 180
#: Shape of a MERL table: (channel, theta_h, theta_d, phi_d).
MERL_SHAPE = (3, N_THETA_H, N_THETA_D, N_PHI_D)
#: Per-channel factors from stored numbers to BRDF values in 1/sr (R, G, B).
MERL_SCALE = np.array([1.0 / 1500, 1.15 / 1500, 1.66 / 1500])
MERL_SCALE.flags.writeable = False
_HEADER_BYTES = 12
#: Size of a MERL file: the header and 3 * 90 * 90 * 180 float64 values.
MERL_BYTES = _HEADER_BYTES + 8 * int(np.prod(MERL_SHAPE))
INTERPOLATIONS = ("trilinear", "nearest")
#: Node directions within this distance of the horizon are evaluated on it by write_merl.
HORIZON_ATOL = 1e-12


def merl_grid() -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Return the angles of the MERL nodes: (theta_h (90,), theta_d (90,), phi_d (180,)), radians.

    theta_h_i = (i/90)^2 pi/2, theta_d_j = j pi/180, phi_d_k = k pi/180: the lower edge of
    each cell, where the stored values belong (see the module notes).

    Examples
    --------
    >>> th, td, pd = merl_grid()
    >>> th.shape, td.shape, pd.shape
    ((90,), (90,), (180,))
    >>> bool(th[1] == (1 / 90) ** 2 * np.pi / 2), round(float(np.degrees(td[89])), 12)
    (True, 89.0)
    """
    theta_h = (np.arange(N_THETA_H) / N_THETA_H) ** 2 * (np.pi / 2)
    theta_d = np.arange(N_THETA_D) * (np.pi / 2) / N_THETA_D
    phi_d = np.arange(N_PHI_D) * np.pi / N_PHI_D
    return theta_h, theta_d, phi_d


def _first_index(mask: NDArray[np.bool_]) -> str:
    """'channel c, theta_h i, theta_d j, phi_d k' of the first True entry of a table mask."""
    c, i, j, k = np.unravel_index(int(np.flatnonzero(mask)[0]), MERL_SHAPE)
    return f"channel {c}, theta_h index {i}, theta_d index {j}, phi_d index {k}"


def _check_table(table: ArrayLike, name: str) -> NDArray[np.float64]:
    """Return a (3, 90, 90, 180) float64 copy of BRDF values; NaN marks missing cells."""
    try:
        t = np.array(table, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be an array of floats with shape {MERL_SHAPE}, got "
                        f"{type(table).__name__}") from None
    if t.shape != MERL_SHAPE:
        raise ValueError(f"{name} must have shape {MERL_SHAPE} (channel, theta_h, theta_d, "
                         f"phi_d), got shape {t.shape}")
    if np.isinf(t).any():
        bad = np.isinf(t)
        raise ValueError(f"{name} must be finite (NaN marks missing cells): {int(bad.sum())} "
                         f"values are inf, first at {_first_index(bad)}")
    with np.errstate(invalid="ignore"):
        neg = t < 0
    if neg.any():
        raise ValueError(f"{name} must be >= 0 (NaN marks missing cells): {int(neg.sum())} "
                         f"values are negative, min {np.nanmin(t):.6g} at {_first_index(neg)}")
    return t


class MERLBRDF(BRDF):
    """An isotropic RGB BRDF tabulated on the MERL grid.

    Parameters
    ----------
    table : (3, 90, 90, 180) array_like of float
        BRDF values in 1/sr (after the MERL channel scales), indexed
        [channel, theta_h, theta_d, phi_d] at the nodes of :func:`merl_grid`. NaN marks
        invalid (missing) cells; values must otherwise be finite and >= 0. The table is
        copied.
    interpolation : {"trilinear", "nearest"}
        How :meth:`eval` reads between nodes (module notes). Trilinear, the default, is
        continuous, which is what quadrature projections need; nearest is a step function.
    name : str, optional
        Material name, e.g. ``"gold-metallic-paint"``.
    path : str or os.PathLike, optional
        File the table came from.

    Attributes
    ----------
    channels : int
        3 (R, G, B).
    isotropic, reciprocal : bool
        True: the table depends on (theta_h, theta_d, phi_d) only, phi_d folded mod pi.
    table : (3, 90, 90, 180) ndarray, read-only
    valid : (3, 90, 90, 180) bool ndarray, read-only
        False for invalid cells (NaN in ``table``).
    valid_fraction : float
        Mean of ``valid``.

    Examples
    --------
    >>> t = np.full(MERL_SHAPE, 0.25)
    >>> t[2] = 0.5
    >>> brdf = MERLBRDF(t, name="flat")
    >>> brdf.eval([0.0, 0.0, 1.0], [0.6, 0.0, 0.8]).tolist()
    [0.25, 0.25, 0.5]
    >>> brdf.eval([0.0, 0.0, 1.0], [0.6, 0.0, -0.8]).tolist()   # below the horizon
    [0.0, 0.0, 0.0]
    """

    channels = 3
    isotropic = True
    reciprocal = True
    _scalar = False

    def __init__(self, table: ArrayLike, *, interpolation: str = "trilinear",
                 name: str | None = None, path: str | os.PathLike | None = None) -> None:
        self._interpolation = choice(interpolation, "interpolation", INTERPOLATIONS)
        t = _check_table(table, "table")
        valid = ~np.isnan(t)
        if not valid.any(axis=(1, 2, 3)).all():
            c = int(np.flatnonzero(~valid.any(axis=(1, 2, 3)))[0])
            raise ValueError(f"table must have at least one valid (non-NaN) value per channel, "
                             f"channel {c} has none")
        t.flags.writeable = False
        valid.flags.writeable = False
        self._table = t
        self._valid = valid
        self._lut = _filled_lookup_table(t, valid)
        self.name = None if name is None else str(name)
        self.path = None if path is None else as_path(path)

    @property
    def table(self) -> NDArray[np.float64]:
        """(3, 90, 90, 180) read-only BRDF values in 1/sr, NaN at invalid cells."""
        return self._table.view()  # a view of a read-only array cannot be made writeable

    @property
    def lookup_table(self) -> NDArray[np.float64]:
        """(90, 90, 180, 3) read-only table that ``eval`` interpolates: invalid cells filled.

        Each invalid cell holds the value of the nearest valid cell of its channel; for other
        evaluators of the same lookup (e.g. a renderer's kernels).
        """
        view = self._lut.view()
        view.flags.writeable = False
        return view

    @property
    def valid(self) -> NDArray[np.bool_]:
        """(3, 90, 90, 180) read-only mask, False at invalid cells."""
        return self._valid.view()

    @property
    def valid_fraction(self) -> float:
        """Fraction of the 3 * 1,458,000 values that are valid."""
        return float(self._valid.mean())

    @property
    def interpolation(self) -> str:
        """``"trilinear"`` or ``"nearest"``."""
        return self._interpolation

    def with_interpolation(self, interpolation: str) -> MERLBRDF:
        """Return the same table (shared, not copied) evaluated with another interpolation."""
        choice(interpolation, "interpolation", INTERPOLATIONS)
        other = object.__new__(MERLBRDF)
        other.__dict__.update(self.__dict__)
        other._interpolation = interpolation
        return other

    def _eval(self, wi: NDArray[np.float64], wo: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.empty((wi.shape[0], self.channels))
        # ~0.5 us a pair: parts of 128 pairs outweigh the hand-off to a thread
        run_parallel(_merl_lookup_kernel, wi.shape[0], wi, wo, self._lut,
                     self._interpolation == "trilinear", out, grain=128)
        return out

    def _isotropic_sums(self, sti, zi, sto, zo, cd, sd, scale, cosr, raw, sums, sq) -> bool:
        """Azimuthal sums of the table on an isotropic product rule, read and summed at once.

        For :func:`project.project`: pair p is w_i = (sti_p, 0, zi_p) and, at azimuth j,
        w_o = (sto_p cd_j, -sto_p sd_j, zo_p); with v = f scale_p it writes
        sums[p, c, m] = sum_j cosr[j, m] v and sq[p, c] = sum_j raw_j v^2. The values are
        those of :meth:`eval`, bit for bit. Returns False (nothing done) for a subclass that
        evaluates otherwise.
        """
        if type(self)._eval is not MERLBRDF._eval:
            return False
        # a pair reads the table at every azimuth (~0.3 us each): ~0.1 ms per part
        run_parallel(_merl_isotropic_kernel, sti.size, sti, zi, sto, zo, cd, sd, self._lut,
                     self._interpolation == "trilinear", scale, cosr, raw, sums, sq,
                     grain=max(1, 256 // max(cd.size, 1)))
        return True

    def __repr__(self) -> str:
        return (f"MERLBRDF(name={self.name!r}, interpolation={self._interpolation!r}, "
                f"valid_fraction={self.valid_fraction:.4f})")


def _filled_lookup_table(table: NDArray[np.float64],
                         valid: NDArray[np.bool_]) -> NDArray[np.float64]:
    """(90, 90, 180, 3) C-contiguous copy of ``table``, invalid cells = nearest valid node."""
    lut = np.empty((N_THETA_H, N_THETA_D, N_PHI_D, 3))
    nearest: dict[bytes, NDArray] = {}  # channels usually share one mask: one transform
    for c in range(3):
        if valid[c].all():
            lut[..., c] = table[c]
            continue
        key = np.packbits(valid[c]).tobytes()
        if key not in nearest:
            nearest[key] = ndimage.distance_transform_edt(
                ~valid[c], return_distances=False, return_indices=True)
        lut[..., c] = table[c][tuple(nearest[key])]
    return lut


@njit(inline="always")
def _merl_value(lut, theta_h, theta_d, phi_d, trilinear, out):  # pragma: no cover - compiled
    # out (c,): the table at folded Rusinkiewicz angles (module notes: Interpolation)
    nc = lut.shape[3]
    nh, nd, npd = lut.shape[0], lut.shape[1], lut.shape[2]
    u = math.sqrt(theta_h / (0.5 * math.pi)) * nh
    v = theta_d / (0.5 * math.pi) * nd
    w = phi_d / math.pi * npd
    if trilinear:
        i0, tu = cell(u, nh)
        j0, tv = cell(v, nd)
        k0, k1, tw = periodic_cell(w, npd)
        for c in range(nc):
            out[c] = cell_trilinear(lut, i0, j0, k0, k1, tu, tv, tw, c)
    else:
        i = min(int(u + 0.5), nh - 1)
        j = min(int(v + 0.5), nd - 1)
        k = int(w + 0.5) % npd
        for c in range(nc):
            out[c] = lut[i, j, k, c]


@loopjit
def _merl_lookup_kernel(first, stop, wi, wo, lut, trilinear, out):  # pragma: no cover - compiled
    # Pairs first .. stop - 1 (run_parallel). wi, wo: (n, 3) unit vectors with z >= 0;
    # lut: (90, 90, 180, c) filled table; out: (n, c). Rusinkiewicz coordinates from
    # h = wi + wo and d = wi - wo, both symmetric (d antisymmetric) under wi <-> wo, so the
    # folded phi_d and the result are exactly reciprocal.
    # an unsigned index: no negative-index test on a[p] (basis.jit.loopjit)
    for p in range(np.uint64(first), np.uint64(stop)):
        theta_h, theta_d, phi_d, _, _ = half_difference(wi, wo, p, True)
        _merl_value(lut, theta_h, theta_d, phi_d, trilinear, out[p])


@loopjit
def _merl_isotropic_kernel(first, stop, sti, zi, sto, zo, cd, sd, lut, trilinear, scale, cosr,
                           raw, sums, sq):  # pragma: no cover - compiled
    # Pairs first .. stop - 1 (run_parallel). The table at the pairs w_i = (sti_p, 0, zi_p),
    # w_o = (sto_p cd_j, -sto_p sd_j, zo_p) of an isotropic product rule, summed over the
    # azimuths j as they are read, so no direction or value array is formed:
    # sums[p, c, m] = sum_j cosr[j, m] v, sq[p, c] = sum_j raw_j v^2 with v = f_c scale_p.
    # Directions, normalisation and Rusinkiewicz angles are those of _merl_lookup_kernel
    # (half_difference) operation for operation, w_i normalised once per pair: the values are
    # the bits of eval at those directions.
    nj, nm, nc = cd.size, cosr.shape[1], lut.shape[3]
    # an unsigned index: no negative-index test on a[p] (basis.jit.loopjit)
    for p in range(np.uint64(first), np.uint64(stop)):
        acc = np.zeros((nc, nm))
        s2 = np.zeros(nc)
        val = np.empty(nc)
        a0, a2 = sti[p], zi[p]
        ni = math.sqrt(a0 ** 2 + 0.0 ** 2 + a2 ** 2)
        ix, iy, iz = a0 / ni, 0.0 / ni, a2 / ni
        # read once: numba cannot tell that the stores to acc, s2, val miss these arrays
        sp, so, zp = scale[p], sto[p], zo[p]
        for j in range(nj):
            b0 = so * cd[j]
            b1 = -so * sd[j]
            b2 = zp
            no = math.sqrt(b0 ** 2 + b1 ** 2 + b2 ** 2)
            theta_h, theta_d, phi_d = half_difference_unit(ix, iy, iz, b0 / no, b1 / no,
                                                           b2 / no, True)
            _merl_value(lut, theta_h, theta_d, phi_d, trilinear, val)
            rj = raw[j]
            for c in range(nc):
                v = val[c] * sp
                s2[c] += rj * v * v
                for m in range(nm):
                    acc[c, m] += cosr[j, m] * v
        for c in range(nc):
            for m in range(nm):
                sums[p, c, m] = acc[c, m]
            sq[p, c] = s2[c]


def read_merl(path: str | os.PathLike, *, interpolation: str = "trilinear") -> MERLBRDF:
    """Read a MERL ``.binary`` file.

    Parameters
    ----------
    path : str or os.PathLike
    interpolation : {"trilinear", "nearest"}
        Passed to :class:`MERLBRDF`. Trilinear (default) is continuous, which quadrature
        projections need; nearest reproduces the stored values as steps.

    Returns
    -------
    MERLBRDF
        ``name`` is the file name without ``.binary``; negative stored values (the MERL
        marker -1) become NaN in ``table``.

    Raises
    ------
    FileNotFoundError, IsADirectoryError
        The path does not exist or is a directory.
    ValueError
        The file is shorter or longer than its header promises, the header is not
        (90, 90, 180), or a value is NaN or inf; or the path is not a regular file (a
        FIFO, a device).

    Examples
    --------
    >>> import os, tempfile
    >>> table = np.full(MERL_SHAPE, 0.3)
    >>> table[:, :, 85:] = np.nan                     # theta_d >= 85 deg not measured
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     brdf = read_merl(write_merl(os.path.join(tmp, "demo.binary"), table))
    >>> brdf
    MERLBRDF(name='demo', interpolation='trilinear', valid_fraction=0.9444)
    >>> brdf.eval([0.0, 0.0, 1.0], [0.0, 0.0, 1.0]).round(12).tolist()
    [0.3, 0.3, 0.3]
    """
    choice(interpolation, "interpolation", INTERPOLATIONS)
    p = input_file(path, "MERL", "a MERL .binary file")
    with open(p, "rb") as f:
        head = f.read(_HEADER_BYTES)
        size = os.fstat(f.fileno()).st_size
        if len(head) < _HEADER_BYTES:
            raise ValueError(f"MERL file {str(p)!r} has {size} bytes, fewer than the "
                             f"{_HEADER_BYTES}-byte header; the file is truncated or empty, "
                             "download or write it again")
        dims = tuple(int(x) for x in np.frombuffer(head, "<i4"))
        if dims != MERL_SHAPE[1:]:
            swapped = tuple(int(x) for x in np.frombuffer(head, ">i4"))
            hint = (" (the file is big-endian; MERL files are little-endian)"
                    if swapped == MERL_SHAPE[1:] else
                    " (same number of values in another order, which this reader does not "
                    "support)" if np.prod(dims, dtype=np.int64) == np.prod(MERL_SHAPE[1:])
                    else "; it is not a MERL .binary file")
            raise ValueError(f"MERL header must hold the dimensions {MERL_SHAPE[1:]}, got "
                             f"{dims} in {str(p)!r}{hint}")
        if size != MERL_BYTES:
            what, gap = ("shorter", "missing") if size < MERL_BYTES else ("longer", "extra")
            raise ValueError(f"MERL file {str(p)!r} has {size} bytes, {what} than the "
                             f"{MERL_BYTES} its header {MERL_SHAPE[1:]} promises "
                             f"({abs(size - MERL_BYTES)} bytes {gap}); the file is truncated "
                             "or damaged, download or write it again")
        raw = np.frombuffer(f.read(), dtype="<f8").reshape(MERL_SHAPE)
    bad = ~np.isfinite(raw)
    if bad.any():
        raise ValueError(f"MERL file {str(p)!r} must hold finite values: {int(bad.sum())} are "
                         f"NaN or inf, first at {_first_index(bad)}; the file is damaged")
    missing = raw < 0
    empty = np.flatnonzero(missing.all(axis=(1, 2, 3)))
    if empty.size:
        c = int(empty[0])
        raise ValueError(f"MERL file {str(p)!r} holds no valid value in channel {c} "
                         f"({('red', 'green', 'blue')[c]}): all {raw[c].size} are negative (the "
                         "mark of a missing cell); the file is damaged or holds no measurement "
                         "of that channel")
    table = raw * MERL_SCALE[:, None, None, None]
    table[missing] = np.nan
    name = p.name[:-len(".binary")] if p.name.endswith(".binary") else p.name
    return MERLBRDF(table, interpolation=interpolation, name=name, path=p)


def write_merl(path: str | os.PathLike, source: object) -> Path:
    """Write a MERL ``.binary`` file from a table or by sampling a BRDF.

    The file is written to a temporary file in the same directory and renamed over ``path``
    when complete, so ``path`` never holds a partial file (an existing file is replaced only
    on success).

    Parameters
    ----------
    path : str or os.PathLike
        Target file; its directory must exist.
    source : MERLBRDF, BRDF-like object, or (3, 90, 90, 180) array_like of float
        A table of BRDF values in 1/sr (NaN = invalid, written as -1); a :class:`MERLBRDF`
        (its ``table``); or any object with ``eval(wi, wo)`` returning (...), (..., 1) or
        (..., 3) values, sampled at the nodes of :func:`merl_grid` (the lower edge of each
        cell, where :class:`MERLBRDF` reads them back) with phi_h = 0. Nodes with a
        direction more than 1e-12 below the horizon are written as invalid (-1); those within
        1e-12 of it are evaluated on it. One-channel values are written to all three
        channels; delta terms are dropped (with a warning).

    Returns
    -------
    pathlib.Path
        ``path``.

    Examples
    --------
    >>> import os, tempfile
    >>> t = np.full(MERL_SHAPE, 1 / np.pi)
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     written = write_merl(os.path.join(tmp, "gray.binary"), t)
    ...     back = read_merl(written)
    ...     size = os.path.getsize(written)
    >>> size, back.name, bool(np.array_equal(back.table, t))
    (34992012, 'gray', True)
    """
    p = output_file(path)
    if isinstance(source, MERLBRDF):
        table = source.table
    elif callable(getattr(source, "eval", None)):
        table = _sample(source)
    else:
        table = _check_table(source, "source")
    missing = np.isnan(table)
    with np.errstate(invalid="ignore", over="ignore"):
        raw = table / MERL_SCALE[:, None, None, None]
    raw[missing] = -1.0
    if not np.isfinite(raw).all():
        big = ~np.isfinite(raw)
        raise ValueError(f"source values must be below {np.finfo(float).max / 1500:.3g} to be "
                         f"stored with the MERL scales, got {np.nanmax(table):.6g} at "
                         f"{_first_index(big)}")
    header = np.array(MERL_SHAPE[1:], dtype="<i4").tobytes()
    _write_atomic(p, (header, raw.astype("<f8", copy=False).tobytes()))
    return p


def _sample(brdf: object) -> NDArray[np.float64]:
    """(3, 90, 90, 180) values of ``brdf`` at the MERL nodes; NaN below the horizon."""
    if getattr(brdf, "isotropic", True) is False:
        warnings.warn(f"{brdf!r} is anisotropic; a MERL table holds isotropic BRDFs, so it is "
                      "sampled at phi_h = 0 only", stacklevel=3)
    if getattr(brdf, "delta", ()):
        warnings.warn(f"{brdf!r} has ideal mirror (delta) terms, which a MERL table cannot "
                      "hold; they are left out", stacklevel=3)
    theta_h, theta_d, phi_d = merl_grid()
    table = np.full(MERL_SHAPE, np.nan)
    rows = 10  # theta_h rows per batch: 162,000 pairs, bounds the memory of brdf.eval
    for start in range(0, N_THETA_H, rows):
        th = theta_h[start:start + rows, None, None]
        wi, wo = from_rusinkiewicz(th, 0.0, theta_d[None, :, None], phi_d[None, None, :])
        wi, wo = wi.reshape(-1, 3), wo.reshape(-1, 3)
        ok = (wi[:, 2] >= -HORIZON_ATOL) & (wo[:, 2] >= -HORIZON_ATOL)
        for w in (wi, wo):  # nodes exactly on the horizon, rounded below it: put them on it
            near = ok & (w[:, 2] < 0.0)
            w[near, 2] = 0.0
            w[near] /= np.linalg.norm(w[near], axis=1, keepdims=True)
        f = np.asarray(brdf.eval(wi[ok], wo[ok]), dtype=np.float64)  # type: ignore[attr-defined]
        m = int(ok.sum())
        if f.shape in ((m,), (m, 1)):
            f = np.repeat(f.reshape(m, 1), 3, axis=1)
        elif f.shape != (m, 3):
            raise ValueError(f"source.eval must return shape (n,), (n, 1) or (n, 3) for n "
                             f"direction pairs, got {f.shape} for n = {m}")
        if not np.all(np.isfinite(f)) or np.any(f < 0):
            raise ValueError("source.eval must return finite values >= 0 above the horizon, "
                             f"got min {np.nanmin(f):.6g}, max {np.nanmax(f):.6g} "
                             f"(theta_h rows {start}-{start + th.shape[0] - 1})")
        block = np.full((wi.shape[0], 3), np.nan)
        block[ok] = f
        table[:, start:start + th.shape[0]] = block.T.reshape(3, th.shape[0], N_THETA_D,
                                                              N_PHI_D)
    return table


def _write_atomic(path: Path, chunks: tuple[bytes, ...]) -> None:
    """Write ``chunks`` to a temporary file beside ``path``, then rename it over ``path``."""
    with atomic_path(path, suffix=".tmp") as tmp, open(tmp, "wb") as f:
        for chunk in chunks:
            f.write(chunk)
