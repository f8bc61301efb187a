"""Measured BRDFs: NVIDIA MDL measured BSDF files (``.mbsdf``, "NVIDIA ARC MBSDF V1").

:func:`read_mbsdf` returns an :class:`MBSDFBRDF`, a :class:`~project.brdf.BRDF` that evaluates
the reflection part of a file at any pair of directions as the MDL SDK does;
:func:`write_mbsdf` samples any representation on the grid of the format and writes a file
that MDL renderers (and :func:`read_mbsdf`) read.

Notes
-----
**File layout.** As read and written by the MDL SDK's loader
(``src/io/scene/bsdf_measurement/bsdf_measurement.cpp``, ``import_measurement_from_reader``
and ``export_to_file``, NVIDIA MDL SDK, github.com/NVIDIA/MDL-SDK):

- a text line, the magic ``NVIDIA ARC MBSDF V1`` followed by a newline;
- any number of metadata lines (free text, each ending in a newline), up to a marker line:
  ``MBSDF_DATA=`` or ``MBSDF_DATA_REFLECTION=`` (a reflection part follows) or
  ``MBSDF_DATA_TRANSMISSION=`` (a transmission part follows); a reflection part may be
  followed by a ``MBSDF_DATA_TRANSMISSION=`` line and a transmission part;
- each part: three little-endian uint32, the type (0 scalar, 1 RGB), n_theta and n_phi (both
  >= 1), then n_theta * n_theta * n_phi * c little-endian float32 values (c = 1 or 3), the
  BSDF f in 1/sr, at flat index ``c * ((i_in * n_theta + i_out) * n_phi + k) + channel``:
  ``values.reshape(n_theta, n_theta, n_phi, c)`` is indexed
  ``[theta_in, theta_out, delta_phi, channel]``;
- the file ends after the last part.

The grid is uniform: theta_in and theta_out in [0, pi/2] in n_theta steps, the azimuth
difference delta_phi = |phi_out - phi_in| folded into [0, pi] (the data are isotropic and
symmetric under delta_phi -> -delta_phi) in n_phi steps, each azimuth atan2(y, x) (so 0 for
the normal itself, as in the SDK); the value of cell k belongs to its
centre, (k + 1/2) (pi/2) / n_theta and (k + 1/2) pi / n_phi (:func:`texel_centres`).

**Which direction is which.** theta_in is the polar angle of the incident direction, the one
towards the light: in the SDK's BSDF library (``src/mdl/jit/libbsdf/libbsdf.cpp``,
``measured_bsdf`` evaluate) the incoming polar angles come from ``k2``, the light direction,
and the looked-up value is multiplied by the cosine of that direction. Here that is ``wi``
(both ``wi`` and ``wo`` point away from the surface); ``wo``, towards the viewer, is
theta_out. The reflection part holds pairs of the upper hemisphere (both z >= 0), which is
what :meth:`MBSDFBRDF.eval` covers; a transmission part is read and kept in
:attr:`MBSDFBRDF.transmission` but not evaluated.

**Interpolation.** As the SDK's CUDA reference, ``df_bsdf_measurement_evaluate`` in
``examples/mdl_sdk/shared/texture_support_cuda.h``: the table is a 3-D texture with
normalised coordinates (u, v, w) = (delta_phi / pi, 2 theta_out / pi, 2 theta_in / pi),
linear filtering and clamp-to-edge addressing. Along an axis of n cells, x = u n - 1/2, the
value is the linear interpolation between cells floor(x) and floor(x) + 1 (each index clamped
to [0, n - 1]) with weight x - floor(x): the stored values sit at the cell centres, and
between the outer centres and the ends of the axis the value is constant. The trilinear
weights are computed in float64 here; CUDA hardware rounds them to 8 fractional bits, so the
GPU differs from this by up to 1/512 of the difference between neighbouring cells.

The SDK's renderers average each table with its transpose in (theta_in, theta_out) before the
lookup (``prepare_mbsdfs_part`` in ``examples/mdl_sdk/shared/example_cuda_shared.h``, and the
native runtime), which makes the BSDF reciprocal. :func:`read_mbsdf` keeps the file's values
by default (``reciprocal`` False: measurements need not be reciprocal, and a written file
reads back as written); ``symmetrize=True`` applies the SDK's average (then ``reciprocal`` is
True).

**Negative values.** Measured files hold small negative values (noise). They are kept in
:attr:`MBSDFBRDF.table` and counted in ``negative_count`` (and ``info``); :meth:`eval`
interpolates the stored values as above and returns max(0, value), so it is the SDK's value
wherever that is >= 0 and 0 elsewhere.

**Validation.** Only regular files are read (checked with ``os.stat`` before opening, so a
FIFO cannot block). The magic, the markers, the type, the resolutions and the number of
bytes each part promises are checked against the file size before anything is allocated, and
every value must be finite: a damaged file raises ValueError naming the file and the fault.

References
----------
NVIDIA, "MDL SDK", github.com/NVIDIA/MDL-SDK: the loader ``src/io/scene/bsdf_measurement/``,
the CUDA texture lookup ``examples/mdl_sdk/shared/texture_support_cuda.h``
(``df_bsdf_measurement_evaluate``). NVIDIA, "NVIDIA Material Definition Language 1.x
Language Specification", section on measured BSDFs (``bsdf_measurement``,
``df::measured_bsdf``).
"""

from __future__ import annotations

import math
import operator
import os
import stat
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from basis.jit import loopjit, run_parallel
from basis.validation import check_bytes

from ..brdf import BRDF
from ..io import atomic_path
from ._files import as_path, output_file

__all__ = ["MBSDFBRDF", "MBSDF_MAGIC", "read_mbsdf", "texel_centres", "write_mbsdf"]

#: First line of every file (with its newline).
MBSDF_MAGIC = b"NVIDIA ARC MBSDF V1\n"
_REFLECTION = (b"MBSDF_DATA=\n", b"MBSDF_DATA_REFLECTION=\n")
_TRANSMISSION = b"MBSDF_DATA_TRANSMISSION=\n"
_PART_HEAD = 12  # type, n_theta, n_phi: three uint32
#: Metadata read before a marker line, at most (the SDK reads lines into a 1024-byte buffer).
MAX_METADATA_BYTES = 1 << 20


def texel_centres(resolution: tuple[int, int]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Return the angles of the cell centres of an MBSDF grid, where its values belong.

    Parameters
    ----------
    resolution : (int, int)
        (n_theta, n_phi).

    Returns
    -------
    theta : (n_theta,) ndarray of float
        (k + 1/2) (pi/2) / n_theta, radians, for theta_in and theta_out alike.
    delta_phi : (n_phi,) ndarray of float
        (k + 1/2) pi / n_phi, radians.

    Examples
    --------
    >>> theta, dphi = texel_centres((2, 4))
    >>> np.degrees(theta).tolist(), np.degrees(dphi).tolist()
    ([22.5, 67.5], [22.5, 67.5, 112.5, 157.5])
    """
    n_theta, n_phi = _resolution(resolution)
    return ((np.arange(n_theta) + 0.5) * (0.5 * np.pi / n_theta),
            (np.arange(n_phi) + 0.5) * (np.pi / n_phi))


def _resolution(resolution: object) -> tuple[int, int]:
    """(n_theta, n_phi) as two positive ints; TypeError/ValueError otherwise."""
    try:
        n_theta, n_phi = (operator.index(r) for r in resolution)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise TypeError(f"resolution must be two integers (n_theta, n_phi), got "
                        f"{resolution!r}") from None
    if n_theta < 1 or n_phi < 1 or n_theta >= 2**32 or n_phi >= 2**32:
        raise ValueError(f"resolution must be two integers in [1, 2**32), got "
                         f"{(n_theta, n_phi)}")
    return n_theta, n_phi


class MBSDFBRDF(BRDF):
    """The reflection part of an NVIDIA MDL measured BSDF, evaluated as the MDL SDK does.

    Parameters
    ----------
    table : (n_theta, n_theta, n_phi, channels) array_like of float
        f in 1/sr at the cell centres (:func:`texel_centres`), indexed
        [theta_in, theta_out, delta_phi, channel], channels 1 or 3; finite (small negative
        values, measurement noise, are allowed and counted). Copied as float64.
    transmission : (m_theta, m_theta, m_phi, c) array_like of float, optional
        The transmission part, kept (read-only) but not evaluated.
    symmetrize : bool
        Average the table with its transpose in (theta_in, theta_out) before the lookup, as
        the MDL SDK's renderers do (module notes); then ``reciprocal`` is True.
    metadata : sequence of str, optional
        The file's metadata lines (without newlines).
    name : str, optional
    path : str or os.PathLike, optional
        File the table came from (``compress.select`` bounds its results by its size).

    Attributes
    ----------
    channels : int
        1 (scalar file) or 3 (RGB).
    isotropic : bool
        True: the format depends on delta_phi only.
    reciprocal : bool
        False unless ``symmetrize``.
    table : (n_theta, n_theta, n_phi, channels) ndarray, read-only
        The values as stored (float32 values as float64), before any symmetrization.
    resolution : (int, int)
        (n_theta, n_phi).
    negative_count : int
        Stored values < 0 in ``table`` (evaluation returns max(0, value)).
    info : dict
        ``format``, ``resolution``, ``channels``, ``negative_count``, ``min_value``,
        ``symmetrized``, ``transmission`` (its resolution or None).

    Examples
    --------
    >>> t = np.full((2, 2, 4, 1), 1 / np.pi)
    >>> brdf = MBSDFBRDF(t)
    >>> brdf.channels, brdf.resolution, round(float(brdf.eval([0, 0, 1.0], [0.6, 0, 0.8])[0]), 6)
    (1, (2, 4), 0.31831)
    """

    isotropic = True
    reciprocal = False
    _scalar = False

    def __init__(self, table: object, *, transmission: object = None, symmetrize: bool = False,
                 metadata: tuple[str, ...] | list[str] = (), name: str | None = None,
                 path: str | os.PathLike | None = None) -> None:
        t = _check_table(table, "table")
        t.flags.writeable = False
        self._table = t
        self.channels = t.shape[3]
        self.symmetrized = bool(symmetrize)
        self.reciprocal = self.symmetrized
        lut = 0.5 * (t + t.transpose(1, 0, 2, 3)) if self.symmetrized else t
        self._lut = np.ascontiguousarray(lut)
        if transmission is not None:
            transmission = _check_table(transmission, "transmission")
            transmission.flags.writeable = False
        self._transmission = transmission
        self.metadata = tuple(str(m) for m in metadata)
        self.name = None if name is None else str(name)
        self.path = None if path is None else as_path(path)
        self.negative_count = int(np.count_nonzero(t < 0))

    @property
    def table(self) -> NDArray[np.float64]:
        """(n_theta, n_theta, n_phi, channels) read-only f in 1/sr, as stored."""
        return self._table.view()

    @property
    def transmission(self) -> NDArray[np.float64] | None:
        """The transmission part (read-only, same layout as ``table``), or None."""
        return None if self._transmission is None else self._transmission.view()

    @property
    def resolution(self) -> tuple[int, int]:
        """(n_theta, n_phi) of the reflection part."""
        return int(self._table.shape[0]), int(self._table.shape[2])

    @property
    def info(self) -> dict:
        """What the file held: resolution, channels, negative values, parts."""
        tr = self._transmission
        return {
            "format": "mbsdf",
            "resolution": self.resolution,
            "channels": self.channels,
            "negative_count": self.negative_count,
            "min_value": float(self._table.min()),
            "symmetrized": self.symmetrized,
            "transmission": None if tr is None else (int(tr.shape[0]), int(tr.shape[2])),
        }

    def _eval(self, wi: NDArray[np.float64], wo: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.empty((wi.shape[0], self.channels))
        # ~0.2 us a pair: parts of 256 pairs outweigh the hand-off to a thread
        run_parallel(_mbsdf_lookup_kernel, wi.shape[0], wi, wo, self._lut, out, grain=256)
        return out

    def __repr__(self) -> str:
        n_theta, n_phi = self.resolution
        return (f"MBSDFBRDF(name={self.name!r}, resolution=({n_theta}, {n_phi}), "
                f"channels={self.channels}, negative_count={self.negative_count})")


def _check_table(table: object, name: str) -> NDArray[np.float64]:
    """Return a float64 copy of a finite (n, n, m, 1 or 3) table."""
    try:
        t = np.array(table, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be an array of floats of shape (n_theta, n_theta, n_phi, "
                        f"channels), got {type(table).__name__}") from None
    if t.ndim != 4 or t.shape[0] != t.shape[1] or t.shape[3] not in (1, 3) or t.size == 0:
        raise ValueError(f"{name} must have shape (n_theta, n_theta, n_phi, channels) with "
                         f"n_theta, n_phi >= 1 and channels 1 or 3, got shape {t.shape}")
    if not np.isfinite(t).all():
        raise ValueError(f"{name} must be finite: {int((~np.isfinite(t)).sum())} values are "
                         "NaN or inf")
    return t


@loopjit
def _mbsdf_lookup_kernel(first, stop, wi, wo, lut, out):  # pragma: no cover - compiled
    # Pairs first .. stop - 1 (run_parallel). wi, wo: (n, 3) unit vectors with z >= 0;
    # lut: (n_theta, n_theta, n_phi, c) indexed [theta_in, theta_out, delta_phi, channel];
    # out: (n, c). Texel-centre linear filtering with clamped edges (module notes).
    nt, nphi, nc = lut.shape[0], lut.shape[2], lut.shape[3]
    half_pi = 0.5 * math.pi
    # an unsigned index: no negative-index test on a[p] (basis.jit.loopjit)
    for p in range(np.uint64(first), np.uint64(stop)):
        ix, iy, iz = wi[p, 0], wi[p, 1], wi[p, 2]
        ox, oy, oz = wo[p, 0], wo[p, 1], wo[p, 2]
        theta_in = math.atan2(math.sqrt(ix * ix + iy * iy), iz)
        theta_out = math.atan2(math.sqrt(ox * ox + oy * oy), oz)
        # |phi_out - phi_in| folded into [0, pi] (bsdf_compute_uvw); the normal's azimuth is
        # atan2(0, 0) = 0, as in the SDK
        dphi = abs(math.atan2(oy, ox) - math.atan2(iy, ix))
        if dphi > math.pi:
            dphi = 2.0 * math.pi - dphi
        x = min(dphi / math.pi, 1.0) * nphi - 0.5
        y = min(theta_out / half_pi, 1.0) * nt - 0.5
        z = min(theta_in / half_pi, 1.0) * nt - 0.5
        fx, fy, fz = math.floor(x), math.floor(y), math.floor(z)
        tx, ty, tz = x - fx, y - fy, z - fz
        k0 = min(max(int(fx), 0), nphi - 1)
        k1 = min(max(int(fx) + 1, 0), nphi - 1)
        j0 = min(max(int(fy), 0), nt - 1)
        j1 = min(max(int(fy) + 1, 0), nt - 1)
        i0 = min(max(int(fz), 0), nt - 1)
        i1 = min(max(int(fz) + 1, 0), nt - 1)
        for c in range(nc):
            a = ((1.0 - tx) * lut[i0, j0, k0, c] + tx * lut[i0, j0, k1, c]) * (1.0 - ty) \
                + ((1.0 - tx) * lut[i0, j1, k0, c] + tx * lut[i0, j1, k1, c]) * ty
            b = ((1.0 - tx) * lut[i1, j0, k0, c] + tx * lut[i1, j0, k1, c]) * (1.0 - ty) \
                + ((1.0 - tx) * lut[i1, j1, k0, c] + tx * lut[i1, j1, k1, c]) * ty
            v = a * (1.0 - tz) + b * tz
            out[p, c] = v if v > 0.0 else 0.0


def read_mbsdf(path: str | os.PathLike, *, symmetrize: bool = False) -> MBSDFBRDF:
    """Read an NVIDIA MDL measured BSDF file (``.mbsdf``, "NVIDIA ARC MBSDF V1").

    Parameters
    ----------
    path : str or os.PathLike
        A regular file.
    symmetrize : bool
        Average the reflection table with its transpose in (theta_in, theta_out), as the MDL
        SDK's renderers do before the lookup (module notes). Default False: the values as
        stored.

    Returns
    -------
    MBSDFBRDF
        Its reflection part, ``name`` the file name without ``.mbsdf``; the transmission part,
        if any, in ``transmission``; negative values counted in ``negative_count``.

    Raises
    ------
    FileNotFoundError, IsADirectoryError
        The path does not exist or is a directory.
    ValueError
        Not a regular file, not an MBSDF file (magic), no reflection part, a damaged part
        (type, resolution, fewer or more bytes than promised) or a value NaN or inf; the
        message names the file and the fault.

    Examples
    --------
    >>> import os, tempfile
    >>> from project.models import Lambert
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     brdf = read_mbsdf(write_mbsdf(Lambert(0.5), os.path.join(tmp, "grey.mbsdf"),
    ...                                   resolution=(4, 8)))
    >>> brdf
    MBSDFBRDF(name='grey', resolution=(4, 8), channels=1, negative_count=0)
    >>> round(float(brdf.eval([0, 0, 1.0], [0.6, 0, 0.8])[0]), 7)   # 0.5 / pi, in float32
    0.1591549
    """
    p = as_path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise FileNotFoundError(f"MBSDF file {str(p)!r} does not exist") from None
    if stat.S_ISDIR(st.st_mode):
        raise IsADirectoryError(f"path must be an MBSDF file, got the directory {str(p)!r}")
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"MBSDF file {str(p)!r} must be a regular file (not a pipe, socket "
                         "or device); copy it to a file first")
    with open(p, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        parts, metadata = _read_parts(f, size, str(p))
    reflection = parts.get("reflection")
    if reflection is None:
        what = "only a transmission part" if parts else "no data part"
        raise ValueError(f"MBSDF file {str(p)!r} holds {what}; read_mbsdf evaluates the "
                         "reflection part (marker MBSDF_DATA_REFLECTION= or MBSDF_DATA=)")
    name = p.name[:-len(".mbsdf")] if p.name.lower().endswith(".mbsdf") else p.name
    return MBSDFBRDF(reflection, transmission=parts.get("transmission"), symmetrize=symmetrize,
                     metadata=metadata, name=name, path=p)


def _read_parts(f, size: int, where: str) -> tuple[dict[str, NDArray], list[str]]:
    """Return the parts ({"reflection": table, "transmission": table}) and metadata."""
    head = f.readline(len(MBSDF_MAGIC))
    if head != MBSDF_MAGIC:
        raise ValueError(f"MBSDF file {where!r} must start with the line "
                         f"{MBSDF_MAGIC.decode().strip()!r}, got {head[:40]!r}; it is not an "
                         "NVIDIA MDL measured BSDF (or its header is damaged)")
    metadata: list[str] = []
    read = len(head)
    while True:  # metadata lines up to the first marker
        line = f.readline(MAX_METADATA_BYTES)
        if not line:
            raise ValueError(f"MBSDF file {where!r} has no data marker line (MBSDF_DATA=, "
                             "MBSDF_DATA_REFLECTION= or MBSDF_DATA_TRANSMISSION=) after its "
                             f"{len(metadata)} metadata lines; the file is truncated or damaged")
        read += len(line)
        if line in _REFLECTION or line == _TRANSMISSION:
            break
        if read > MAX_METADATA_BYTES:
            raise ValueError(f"MBSDF file {where!r} has more than {MAX_METADATA_BYTES} bytes of "
                             "metadata before its data marker line; the file is damaged or "
                             "not an MBSDF file")
        metadata.append(line.rstrip(b"\r\n").decode("utf-8", errors="replace"))
    parts: dict[str, NDArray] = {}
    marker = line
    if marker in _REFLECTION:
        parts["reflection"], read = _read_part(f, size, read, where, "reflection")
        marker = f.readline(len(_TRANSMISSION))
        read += len(marker)
        if marker and marker != _TRANSMISSION:
            raise ValueError(f"MBSDF file {where!r} must end after its reflection part or "
                             f"continue with the line 'MBSDF_DATA_TRANSMISSION=', got "
                             f"{marker[:30]!r} at byte {read - len(marker)}; the file is "
                             "damaged")
    if marker == _TRANSMISSION:
        parts["transmission"], read = _read_part(f, size, read, where, "transmission")
    if read != size:
        raise ValueError(f"MBSDF file {where!r} has {size - read} bytes after its last part "
                         f"(which ends at byte {read}); the file is damaged")
    return parts, metadata


def _read_part(f, size: int, start: int, where: str, part: str) -> tuple[NDArray, int]:
    """Return the part at byte ``start``: (table (n, n, m, c) float64, the byte after it)."""
    head = f.read(_PART_HEAD)
    if len(head) < _PART_HEAD:
        raise ValueError(f"MBSDF file {where!r} ends inside the header of its {part} part "
                         f"(byte {start + len(head)} of {start + _PART_HEAD}); the file is "
                         "truncated")
    kind, n_theta, n_phi = (int(x) for x in np.frombuffer(head, "<u4"))
    if kind not in (0, 1):
        raise ValueError(f"MBSDF file {where!r}: the type of its {part} part must be 0 "
                         f"(scalar) or 1 (RGB), got {kind}; the file is damaged")
    if n_theta == 0 or n_phi == 0:
        raise ValueError(f"MBSDF file {where!r}: the resolution of its {part} part must be "
                         f">= 1, got n_theta = {n_theta}, n_phi = {n_phi}; the file is damaged")
    channels = 3 if kind == 1 else 1
    count = n_theta * n_theta * n_phi * channels  # Python ints: no overflow
    nbytes = 4 * count
    start += _PART_HEAD
    if start + nbytes > size:
        raise ValueError(f"MBSDF file {where!r}: its {part} part ({n_theta} x {n_theta} x "
                         f"{n_phi} x {channels} float32 values, {nbytes} bytes) needs "
                         f"{start + nbytes - size} bytes more than the file has ({size}); the "
                         "file is truncated or its header damaged")
    check_bytes(8.0 * count, f"reading the {part} part of {where!r}")
    raw = np.frombuffer(f.read(nbytes), dtype="<f4")
    if raw.size != count:  # the file shrank while being read
        raise ValueError(f"MBSDF file {where!r} ends inside its {part} part; it is truncated")
    bad = ~np.isfinite(raw)
    if bad.any():
        i, j, k, c = np.unravel_index(int(np.flatnonzero(bad)[0]),
                                      (n_theta, n_theta, n_phi, channels))
        raise ValueError(f"MBSDF file {where!r}: its {part} part must hold finite values, "
                         f"{int(bad.sum())} are NaN or inf (first at theta_in {i}, theta_out "
                         f"{j}, delta_phi {k}, channel {c}); the file is damaged")
    table = raw.astype(np.float64).reshape(n_theta, n_theta, n_phi, channels)
    return table, start + nbytes


def write_mbsdf(rep: object, path: str | os.PathLike,
                resolution: tuple[int, int] = (45, 90)) -> Path:
    """Write a representation as an NVIDIA MDL measured BSDF file (reflection part).

    ``rep`` is sampled at the cell centres of the grid (:func:`texel_centres`), where the
    MDL SDK's lookup (and :func:`read_mbsdf`) returns the stored values: reading the file back
    gives ``rep.eval`` there, rounded to float32. The file is written to a temporary file
    beside ``path`` and renamed over it when complete.

    Parameters
    ----------
    rep : object with ``eval(wi, wo)`` and ``channels`` 1 or 3
        Any BRDF or representation (f in 1/sr; ``wi`` towards the light, which the file calls
        theta_in). Sampled with phi_in = 0 and phi_out = delta_phi; delta (mirror) terms are
        left out with a warning.
    path : str or os.PathLike
        Target file; its directory must exist.
    resolution : (int, int)
        (n_theta, n_phi): cells in theta_in and theta_out over [0, pi/2], and in delta_phi over
        [0, pi]. The default (45, 90) is 2-degree cells; the file has
        20 + 23 + 12 + 4 n_theta^2 n_phi channels bytes.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    TypeError
        ``rep`` has no ``eval`` method, or ``resolution`` is not two integers.
    ValueError
        A bad resolution, a channel count other than 1 or 3, or values that are not finite
        or exceed float32.

    Examples
    --------
    >>> import os, tempfile
    >>> from project.models import Lambert
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     out = write_mbsdf(Lambert(0.5), os.path.join(tmp, "grey.mbsdf"), resolution=(4, 8))
    ...     size = os.path.getsize(out)
    >>> size   # 20 + 23 + 12 + 4 * 4 * 4 * 8
    567
    """
    if not callable(getattr(rep, "eval", None)):
        raise TypeError(f"rep must have an eval(wi, wo) method, got {type(rep).__name__}")
    n_theta, n_phi = _resolution(resolution)
    p = output_file(path)
    table = _sample(rep, n_theta, n_phi)
    channels = table.shape[3]
    with np.errstate(over="ignore"):
        raw = table.astype("<f4")
    if not np.isfinite(raw).all():
        raise ValueError(f"rep.eval must return values within float32 range (|f| < 3.4e38) "
                         f"to be stored, got max {np.abs(table).max():.6g}")
    head = np.array([1 if channels == 3 else 0, n_theta, n_phi], dtype="<u4").tobytes()
    with atomic_path(p, suffix=".tmp") as tmp, open(tmp, "wb") as f:
        f.write(MBSDF_MAGIC)
        f.write(_REFLECTION[1])
        f.write(head)
        f.write(raw.tobytes())
    return p


def _sample(rep: object, n_theta: int, n_phi: int) -> NDArray[np.float64]:
    """Return the (n_theta, n_theta, n_phi, c) values of ``rep`` at the cell centres."""
    channels = int(getattr(rep, "channels", 1))
    if channels not in (1, 3):
        raise ValueError(f"rep.channels must be 1 or 3 (an MBSDF file is scalar or RGB), got "
                         f"{channels}")
    check_bytes(8.0 * n_theta * n_theta * n_phi * (channels + 7),
                f"sampling {n_theta} x {n_theta} x {n_phi} MBSDF cells")
    if getattr(rep, "isotropic", True) is False:
        warnings.warn(f"{rep!r} is anisotropic; an MBSDF file holds isotropic BSDFs, so it is "
                      "sampled at phi_in = 0 only", stacklevel=3)
    if getattr(rep, "delta", ()):
        warnings.warn(f"{rep!r} has ideal mirror (delta) terms, which an MBSDF file cannot "
                      "hold; they are left out", stacklevel=3)
    theta, dphi = texel_centres((n_theta, n_phi))
    st, ct = np.sin(theta), np.cos(theta)
    wo = np.stack(np.broadcast_arrays(st[:, None] * np.cos(dphi), st[:, None] * np.sin(dphi),
                                      ct[:, None]), axis=-1).reshape(-1, 3)
    m = wo.shape[0]
    table = np.empty((n_theta, n_theta, n_phi, channels))
    for i in range(n_theta):  # one theta_in at a time bounds the memory of rep.eval
        wi = np.broadcast_to(np.array([st[i], 0.0, ct[i]]), wo.shape)
        f = np.asarray(rep.eval(wi, wo), dtype=np.float64)  # type: ignore[attr-defined]
        if f.shape in ((m,), (m, 1)) and channels == 1:
            f = f.reshape(m, 1)
        elif f.shape != (m, channels):
            raise ValueError(f"rep.eval must return shape (n,) or (n, {channels}) for n = {m} "
                             f"direction pairs (rep.channels = {channels}), got {f.shape}")
        if not np.isfinite(f).all():
            raise ValueError(f"rep.eval must return finite values, got "
                             f"{int((~np.isfinite(f)).sum())} NaN or inf at theta_in "
                             f"{np.degrees(theta[i]):.4g} deg")
        table[i] = f.reshape(n_theta, n_phi, channels)
    return table
