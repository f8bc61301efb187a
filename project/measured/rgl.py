r"""Measured BRDFs of the RGL-EPFL material database: reading ``.bsdf`` tensor files.

The RGL material database (Dupuy & Jakob 2018) stores each measured material in a
"tensor_file" (version 1.0): a header, then named n-dimensional arrays. :func:`read_rgl`
returns an :class:`RGLBRDF`, a :class:`~project.brdf.BRDF` that evaluates the stored model
at any direction pair; :func:`read_tensor_file` and :func:`write_tensor_file` read and write
the container itself (any fields).

Notes
-----
**Container** (as read by the reference loader rgl-epfl/brdf-loader, ``powitacq*.inl``,
and by Mitsuba 3's ``TensorFile``). All numbers little-endian:

- 12 bytes ``b"tensor_file\0"``, 2 bytes version (major 1, minor 0), uint32 field count;
- per field: uint16 name length, the UTF-8 name, uint16 ndim, uint8 type code, uint64 byte
  offset of the data in the file, ndim uint64 sizes (C order, last axis contiguous);
- type codes 1-11: uint8, int8, uint16, int16, uint32, int32, uint64, int64, float16,
  float32, float64 (0 is "invalid"). The published files align every array to 8 bytes.

This reader checks what the reference loader does not: every field lies inside the file and
after the header, sizes are computed without overflow, names are unique UTF-8, and every
field the model uses has the expected type, shape and finite values.

**Alignment and overlap.** Neither loader checks either. The reference loader (``Tensor``
in ``powitacq*.inl``) ``fread``\ s each field from its offset into a buffer of its own, so
any offset works there and two fields may share bytes. Mitsuba 3's ``TensorFile``
memory-maps the file and points each field at ``data() + offset``; the ``measured`` plugin
then reads the arrays through ``float *`` casts, which C++ leaves undefined for an offset
that is not a multiple of 4 (it happens to work on x86, and traps on strict-alignment
processors). The format's writers (Mitsuba's ``tensor_io.write``, :func:`write_tensor_file`)
align every field to 8 bytes and give each its own bytes, and so do all published files.
This reader therefore refuses a field whose offset is not a multiple of its item size, and
fields whose bytes overlap (fields of 0 bytes overlap nothing): both come from a damaged
header, and reading on would give a BRDF made of some other field's numbers. A field whose
shape numpy cannot hold (more dimensions than numpy allows, sizes past its index range even
when another size is 0) is refused too.

**Fields of a material.** ``description`` (uint8 text), ``theta_i`` and ``phi_i`` (float32
incidence angles of the measured slices, radians), ``ndf`` and ``sigma`` (float32 2-D
tables of the microfacet distribution D and the projected area sigma(w_i) = int D(m)
max(0, m.w_i) dm), ``vndf`` (float32 (n_phi_i, n_theta_i, n_y, n_x), the visible normal
distribution used as a warp), ``luminance`` (float32 (n_phi_i, n_theta_i, m, m), for
importance sampling only), ``rgb`` (float32 (n_phi_i, n_theta_i, 3, m, m)) or ``spectra``
(float32 (n_phi_i, n_theta_i, n_lambda, m, m)) with ``wavelengths`` (float32 nm),
``jacobian`` (uint8 (1,), see below), and in the published files ``valid`` (a bit mask) and
``version``. All fields are kept in :attr:`RGLBRDF.fields`, unknown ones included.

**Warps.** An angle theta in [0, pi/2] maps to u = sqrt(2 theta / pi) and an azimuth phi in
[-pi, pi] to u = (phi + pi) / (2 pi). 2-D tables are indexed [y, x] with x the theta
coordinate and y the phi coordinate, nodes at u = k / (n - 1), and read by bilinear
interpolation in u. Tables that depend on the incidence (vndf, luminance, the slices) are
blended linearly between the slices of the two nearest ``theta_i`` nodes (and ``phi_i``
nodes when there are several), the weights clamped to [0, 1] (constant beyond the first and
last node).

**Evaluation** (Dupuy & Jakob 2018, Sec. 5; the loader's ``BRDF::eval``), for w_i and w_o
above the horizon: the half vector m = (w_i + w_o)/|w_i + w_o|; theta and phi of w_i and m
(theta as 2 asin(|w - z|/2), well conditioned near the normal); u_m = (u(theta_m),
u(phi_m - phi_i) for isotropic files or u(phi_m) otherwise, wrapped into [0, 1)). The VNDF
of the incidence, normalised to integrate to 1 over the unit square, is a
marginal-conditional 2-D distribution: u_m is mapped through its inverse warp, i.e. to
s = (C(u_m,x | u_m,y), M(u_m,y)) with M the marginal CDF along y and C the conditional CDF
along x, both of the bilinear interpolant (so piecewise quadratic). The slice (one per
channel) is read at s, clamped to >= 0, and, when ``jacobian`` is set, multiplied by
D(u_m) / (4 sigma(u_i)). The result is what the reference returns: f(w_i, w_o) cos(theta_o).

**Conventions, and where they differ from the reference.** Both here and in the reference,
w_i and w_o point away from the surface, z is the normal and phi = 0 is the x axis.
``theta_i``/``phi_i`` are the incidence of the measurement, the light's direction on the
gonio-photometer, which is our w_i (towards the light). The reference returns
f cos(theta_o); :meth:`RGLBRDF.eval` returns f in 1/sr, the reference's value divided by
cos(theta_o) = w_o.z. Since the reference's value tends to a non-zero constant at grazing
w_o, our f grows like 1/cos(theta_o) near the horizon; this reproduces the reference, it is
not an artefact of this reader. The reference tests w.z <= 0 in float32: a z that rounds to
0 in float32 (below 7e-46) counts as the horizon here too, and such pairs evaluate to 0,
which keeps f finite. Mitsuba 3's ``measured`` plugin calls the same formula with its own
``si.wi`` (towards the camera in a path tracer) in the incidence slot and returns
f cos of its ``wo`` (towards the light): a renderer therefore reads the table with the
roles of light and viewer exchanged, relying on reciprocity, which measured data obey only
approximately. This class follows the acquisition (w_i = light) and so sets
``reciprocal = False``.

**Disagreements between the sources** (paper, brdf-loader at commit c9ea6f9, Mitsuba 3):

- Negative slice values (out-of-gamut RGB conversions; ``vch_golden_yellow_rgb.bsdf`` has
  values down to -0.04): the loader clamps the RGB slice to >= 0 only when compiled with
  ``POWITACQ_CLIP_RGB`` (off by default) and never clamps spectra; Mitsuba 3 does not
  clamp. This reader always clamps (a BRDF must be >= 0), so it differs from both where
  the interpolated slice is negative, and nowhere else.
- ``jacobian``: Mitsuba 3 multiplies by D / (4 sigma) only when the flag is set; the
  loader reads the flag but always multiplies. This reader follows Mitsuba 3; the
  published files set the flag, so all agree on them.
- Anisotropic files covering only half or a quarter of the azimuths ("reduction" 2 or 4,
  2 pi divided by the span of ``phi_i``): the loader refuses them; Mitsuba 3 folds w_i
  into the stored range by negating x and y (reduction 2, a rotation by pi) or each of
  them separately (reduction 4, two mirror symmetries) and applies the same to w_o. This
  reader does what Mitsuba 3 does. Mitsuba 3 leaves that reduction factor uninitialised
  for isotropic files (harmless when it happens to be < 2).
- A file is isotropic when ``phi_i`` has at most 2 entries (both loaders; there is no
  separate flag in the published files).
- The ``valid`` field is read by neither loader; its meaning is not documented. It is a
  packed bit mask with one bit per slice sample; :attr:`RGLBRDF.valid` unpacks it with
  numpy's default bit order (most significant bit first), an assumption.
- Where the VNDF vanishes along a whole row (back-facing azimuths at grazing incidence:
  the published files' theta_i = pi/2 slices), the conditional warp is 0/0 and both loaders
  return NaN if a pair lands exactly there; this reader keeps the x coordinate instead. With
  float64 directions above the horizon the blend always includes a slice with a positive
  row, so this does not occur for the published files.
- The loader computes in float32 (CDFs accumulated in double, stored in float32); this
  reader in float64. Agreement with Mitsuba 3 is at float32 precision (see the tests).

**Speed.** One numba kernel, parallel over pairs: about 0.3 s per million pairs on 2 cores
for an RGB file, validation of the directions included (``tests/benchmarks/bench_rgl.py``).

References
----------
J. Dupuy, W. Jakob, "An adaptive parameterization for efficient material acquisition and
rendering", ACM TOG 37(6), 2018. Reference loader: github.com/rgl-epfl/brdf-loader (BSD-3).
Data: rgl.epfl.ch/materials (CC0).
"""

from __future__ import annotations

import math
import os
import struct
import types
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basis.jit import loopjit, njit, run_parallel, writable

from ..brdf import BRDF
from ..io import atomic_path
from ._files import as_path, input_file, output_file

__all__ = [
    "TENSOR_MAGIC",
    "RGLBRDF",
    "read_rgl",
    "read_tensor_file",
    "write_tensor_file",
]

#: First 12 bytes of a tensor file.
TENSOR_MAGIC = b"tensor_file\x00"
_VERSION = (1, 0)
_PREAMBLE = 12 + 2 + 4
#: Tensor-file type code -> numpy dtype (little-endian).
_DTYPES = {1: "u1", 2: "i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<u8", 8: "<i8",
           9: "<f2", 10: "<f4", 11: "<f8"}
_CODES = {np.dtype(v): k for k, v in _DTYPES.items()}
_ALIGN = 8
_F32_PI = float(np.float32(np.pi))
_F32_HALF_PI = float(np.float32(np.pi / 2))


# ----------------------------------------------------------------------------- container


def read_tensor_file(path: str | os.PathLike) -> dict[str, NDArray]:
    """Read every field of a tensor file (format 1.0).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    dict of str to ndarray
        Field name -> read-only array with the stored dtype (little-endian) and shape, in
        the order of the header.

    Raises
    ------
    FileNotFoundError, IsADirectoryError
        The path does not exist or is a directory.
    ValueError
        The file is not a tensor file (magic, version), is truncated, or a field header is
        damaged: unknown type code, a name that is not UTF-8 or repeats, data outside the
        file, an offset that is not a multiple of the item size, fields that overlap, a
        shape numpy cannot hold. The message names the file and the field. Also for a path
        that is not a regular file (a FIFO, a device).

    Examples
    --------
    >>> import os, tempfile
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     p = write_tensor_file(os.path.join(tmp, "t.bsdf"), {"x": np.arange(3.0)})
    ...     fields = read_tensor_file(p)
    >>> fields["x"].tolist(), fields["x"].dtype.str
    ([0.0, 1.0, 2.0], '<f8')
    """
    p = input_file(path, "tensor")
    data = p.read_bytes()
    where = f"tensor file {str(p)!r}"
    size = len(data)
    if size < _PREAMBLE:
        raise ValueError(f"{where} has {size} bytes, fewer than the {_PREAMBLE}-byte preamble "
                         "(magic, version, field count); the file is truncated or empty")
    if data[:12] != TENSOR_MAGIC:
        raise ValueError(f"{where} must start with {TENSOR_MAGIC!r}, got {data[:12]!r}; it is "
                         "not a tensor file")
    version = (data[12], data[13])
    if version != _VERSION:
        raise ValueError(f"{where} has format version {version[0]}.{version[1]}; only "
                         f"{_VERSION[0]}.{_VERSION[1]} is supported")
    (n_fields,) = struct.unpack_from("<I", data, 14)
    if n_fields * 13 > size - _PREAMBLE:  # a field header takes at least 13 bytes
        raise ValueError(f"{where} declares {n_fields} fields, more than its {size} bytes can "
                         "hold; the header is damaged or the file truncated")
    pos = _PREAMBLE
    specs: list[tuple[str, np.dtype, tuple[int, ...], int]] = []
    for k in range(n_fields):
        field = f"field #{k}"
        try:
            (name_len,) = struct.unpack_from("<H", data, pos)
            raw_name = data[pos + 2:pos + 2 + name_len]
            if len(raw_name) < name_len:
                raise struct.error
            pos += 2 + name_len
            try:
                name = raw_name.decode("utf-8")
            except UnicodeDecodeError:
                raise ValueError(f"{where}: the name of {field} is not UTF-8: "
                                 f"{raw_name[:40]!r}") from None
            field = f"field {name!r}"
            ndim, code, offset = struct.unpack_from("<HBQ", data, pos)
            pos += 11
            shape = struct.unpack_from(f"<{ndim}Q", data, pos)
            pos += 8 * ndim
        except struct.error:
            raise ValueError(f"{where}: the header of {field} (of {n_fields}) ends past the "
                             f"end of the file ({size} bytes); the file is truncated or "
                             "damaged") from None
        if code not in _DTYPES:
            raise ValueError(f"{where}: {field} has unknown type code {code}; known codes "
                             f"are 1-11 (uint8 ... float64)")
        if any(name == s[0] for s in specs):
            raise ValueError(f"{where}: {field} appears twice")
        specs.append((name, np.dtype(_DTYPES[code]), tuple(int(s) for s in shape), offset))
    fields: dict[str, NDArray] = {}
    spans: list[tuple[int, int, str]] = []  # (start, end, name) of the fields holding bytes
    for name, dtype, shape, offset in specs:
        nbytes = dtype.itemsize * math.prod(shape)  # Python ints: no overflow
        if offset < pos or offset + nbytes > size:
            raise ValueError(f"{where}: field {name!r} ({dtype}, shape {_shown(shape)}, "
                             f"{nbytes} bytes at offset {offset}) must lie between the end of "
                             f"the header ({pos}) and the end of the file ({size}); the file "
                             "is truncated or damaged")
        if offset % dtype.itemsize:
            raise ValueError(f"{where}: field {name!r} ({dtype}) must start at an offset that "
                             f"is a multiple of its item size {dtype.itemsize}, got offset "
                             f"{offset}; the header is damaged (see the module notes)")
        try:
            fields[name] = np.frombuffer(data, dtype, math.prod(shape), offset).reshape(shape)
        except (ValueError, OverflowError):  # too many dimensions, or sizes too large
            raise ValueError(f"{where}: field {name!r} has shape {_shown(shape)}, which "
                             f"numpy cannot hold (too many dimensions, or sizes whose product "
                             f"without the zeros passes 2**63); the header is damaged") \
                from None
        if nbytes:
            spans.append((offset, offset + nbytes, name))
    spans.sort()  # an overlap shows between neighbours in the order of the offsets
    for (_, end, first), (start, end2, second) in zip(spans, spans[1:], strict=False):
        if start < end:
            raise ValueError(f"{where}: fields {first!r} and {second!r} overlap (bytes "
                             f"{start} to {min(end, end2) - 1} belong to both); each field "
                             "must have bytes of its own: the header is damaged")
    return fields


def _shown(shape: tuple[int, ...]) -> str:
    """Return a shape for a message: in full up to 8 dimensions, else the first 4 and ndim."""
    if len(shape) <= 8:
        return str(shape)
    return f"({', '.join(map(str, shape[:4]))}, ... {len(shape)} dimensions)"


def write_tensor_file(path: str | os.PathLike, fields: Mapping[str, ArrayLike]) -> Path:
    r"""Write arrays as a tensor file (format 1.0), each aligned to 8 bytes.

    The file is written beside ``path`` and renamed over it when complete.

    Parameters
    ----------
    path : str or os.PathLike
        Target file; its directory must exist.
    fields : mapping of str to array_like
        Name -> array of an integer type (8-64 bits) or float16/32/64 (bool is not a tensor
        type: convert to uint8). Stored little-endian, C order, in the mapping's order.

    Returns
    -------
    pathlib.Path
        ``path``.

    Examples
    --------
    >>> import os, tempfile
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     p = write_tensor_file(os.path.join(tmp, "t.bsdf"),
    ...                           {"a": np.zeros((2, 3), np.float32)})
    ...     head = p.read_bytes()[:18]
    >>> head
    b'tensor_file\x00\x01\x00\x01\x00\x00\x00'
    """
    p = output_file(path)
    arrays: list[tuple[bytes, NDArray, int]] = []
    for name, value in fields.items():
        if not isinstance(name, str):
            raise TypeError(f"field names must be str, got {name!r}")
        a = np.asarray(value)
        code = _CODES.get(a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype)
        if code is None:
            raise ValueError(f"field {name!r} must have an integer or float16/32/64 dtype, "
                             f"got {a.dtype}")
        raw = name.encode("utf-8")
        if len(raw) > 0xFFFF or a.ndim > 0xFFFF:
            raise ValueError(f"field {name!r}: name or ndim too long for the format")
        arrays.append((raw, np.asarray(a, a.dtype.newbyteorder("<"), order="C"), code))
    header = bytearray(TENSOR_MAGIC + bytes(_VERSION) + struct.pack("<I", len(arrays)))
    header_size = len(header) + sum(2 + len(r) + 11 + 8 * a.ndim for r, a, _ in arrays)
    offset = -(-header_size // _ALIGN) * _ALIGN
    body = bytearray()
    for raw, a, code in arrays:
        header += struct.pack("<H", len(raw)) + raw
        header += struct.pack(f"<HBQ{a.ndim}Q", a.ndim, code, offset + len(body), *a.shape)
        body += a.tobytes()
        body += bytes(-len(body) % _ALIGN)
    header += bytes(offset - len(header))
    with atomic_path(p, suffix=".tmp") as tmp, open(tmp, "wb") as f:
        f.write(bytes(header))
        f.write(bytes(body))
    return p


# ----------------------------------------------------------------------------- the model


def _field(fields: Mapping[str, NDArray], key: str, where: str, dtype: str, ndim: int
           ) -> NDArray:
    """Return the field ``key`` if it has this dtype and ndim, else raise ValueError."""
    if key not in fields:
        raise ValueError(f"{where}: the required field {key!r} is missing (fields present: "
                         f"{', '.join(map(repr, fields)) or 'none'})")
    a = np.asarray(fields[key])
    if a.dtype != np.dtype(dtype):
        raise ValueError(f"{where}: field {key!r} must have dtype {np.dtype(dtype)}, got "
                         f"{a.dtype}")
    if a.ndim != ndim:
        raise ValueError(f"{where}: field {key!r} must have {ndim} dimension(s), got shape "
                         f"{a.shape}")
    return a


def _finite(a: NDArray, key: str, where: str) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        first = np.unravel_index(int(np.flatnonzero(bad)[0]), a.shape)
        raise ValueError(f"{where}: field {key!r} must be finite, {int(bad.sum())} of "
                         f"{a.size} values are NaN or inf (first at index "
                         f"{tuple(map(int, first))})")


def _shape(a: NDArray, key: str, where: str, expected: tuple, what: str) -> None:
    if a.shape != tuple(expected):
        raise ValueError(f"{where}: field {key!r} must have shape {tuple(expected)} ({what}), "
                         f"got {a.shape}")


def _nodes(a: NDArray, key: str, where: str, low: float, high: float) -> None:
    _finite(a, key, where)
    if a.size == 0:
        raise ValueError(f"{where}: field {key!r} must have at least 1 entry, got 0")
    if np.any(np.diff(a) <= 0):
        raise ValueError(f"{where}: field {key!r} must increase strictly, got "
                         f"{np.array2string(a, precision=4, threshold=12)}")
    if a[0] < low or a[-1] > high:
        raise ValueError(f"{where}: field {key!r} must lie in [{low:.7g}, {high:.7g}] "
                         f"(radians), got [{a[0]:.7g}, {a[-1]:.7g}]")


def _marginal_conditional(vndf: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Normalised VNDF slices and their CDFs: data, conditional (along x) and marginal.

    vndf: (S, ny, nx) float64. Each slice's bilinear interpolant is scaled to integrate to 1
    over [0, 1]^2 in node units; cond[s, y, x] = integral over nodes 0..x of row y
    (trapezoid: exact for the linear interpolant), marg[s, y] = integral of the row totals
    over rows 0..y. Returned as (S, ny, nx), (S, ny, nx), (S, ny), C-contiguous.
    """
    s, ny, nx = vndf.shape
    cond = np.zeros((s, ny, nx))
    cond[:, :, 1:] = np.cumsum(0.5 * (vndf[:, :, 1:] + vndf[:, :, :-1]), axis=2)
    rows = cond[:, :, -1]
    marg = np.zeros((s, ny))
    marg[:, 1:] = np.cumsum(0.5 * (rows[:, 1:] + rows[:, :-1]), axis=1)
    total = marg[:, -1:]
    return (np.ascontiguousarray(vndf / total[:, :, None]),
            np.ascontiguousarray(cond / total[:, :, None]), np.ascontiguousarray(marg / total))


def _read_only(a: NDArray) -> NDArray:
    a = np.array(a, copy=True)
    a.flags.writeable = False
    return a


class RGLBRDF(BRDF):
    """A BRDF measured by RGL-EPFL, evaluated as the reference loader does (module notes).

    ``reciprocal`` is False: the table is parameterised by the incidence w_i and measured
    data need not satisfy f(w_i, w_o) = f(w_o, w_i), so no symmetry is assumed.

    Parameters
    ----------
    fields : mapping of str to array_like
        The arrays of a tensor file, as :func:`read_tensor_file` returns them; required:
        ``description``, ``theta_i``, ``phi_i``, ``ndf``, ``sigma``, ``vndf``,
        ``luminance``, ``jacobian`` and either ``rgb`` or ``spectra`` with
        ``wavelengths`` (types and shapes in the module notes). Copied.
    name : str, optional
        Material name (``read_rgl`` uses the file name without ``.bsdf``).
    path : str or os.PathLike, optional
        File the fields came from; named in error messages.

    Attributes
    ----------
    channels : int
        3 for an RGB file, the number of wavelengths for a spectral one.
    channel_names : tuple of str
        ``("R", "G", "B")`` or e.g. ``("360 nm", "365 nm", ...)``.
    wavelengths : (channels,) ndarray of float or None
        Wavelengths in nm of a spectral file, None for RGB.
    isotropic : bool
        True when ``phi_i`` has at most 2 entries (the reference's rule).
    reciprocal : bool
        False (see above).
    jacobian : bool
        The file's flag: slices are multiplied by D / (4 sigma).
    reduction : int
        Azimuthal symmetry of an anisotropic file: 1 (full circle), 2 or 4; 1 if isotropic.
    description : str
    name : str or None
    path : pathlib.Path or None
    fields : mapping of str to ndarray
        Every field, read-only, unknown ones included.

    Raises
    ------
    ValueError
        A required field is missing, or has the wrong dtype or shape, or non-finite values,
        or values the model cannot use (message names the field and the file).

    Examples
    --------
    A flat table without the D / (4 sigma) factor (``jacobian`` 0): the reference returns the
    slice, 0.25, as f cos(theta_o), so f = 0.25 / cos(theta_o).

    >>> f32 = np.float32
    >>> fields = {
    ...     "description": np.frombuffer(b"flat", np.uint8), "jacobian": np.array([0], np.uint8),
    ...     "theta_i": np.array([0, np.pi / 2], f32), "phi_i": np.array([0], f32),
    ...     "ndf": np.ones((2, 2), f32), "sigma": np.ones((2, 2), f32),
    ...     "vndf": np.ones((1, 2, 2, 2), f32), "luminance": np.ones((1, 2, 2, 2), f32),
    ...     "rgb": np.full((1, 2, 3, 2, 2), 0.25, f32)}
    >>> brdf = RGLBRDF(fields, name="flat")
    >>> brdf.eval([0.0, 0.0, 1.0], [0.6, 0.0, 0.8]).tolist()
    [0.3125, 0.3125, 0.3125]
    >>> brdf
    RGLBRDF(name='flat', description='flat', channels=3, isotropic=True)
    """

    reciprocal = False
    _scalar = False

    def __init__(self, fields: Mapping[str, ArrayLike], *, name: str | None = None,
                 path: str | os.PathLike | None = None) -> None:
        self.path = None if path is None else as_path(path)
        self.name = None if name is None else str(name)
        where = "RGLBRDF fields" if self.path is None else f"RGL file {str(self.path)!r}"
        if not isinstance(fields, Mapping):
            raise TypeError(f"fields must be a mapping of names to arrays, got "
                            f"{type(fields).__name__}")
        fields = {str(k): np.asarray(v) for k, v in fields.items()}

        desc = _field(fields, "description", where, "u1", 1)
        self.description = bytes(desc).decode("utf-8", errors="replace").rstrip("\x00")
        jac = _field(fields, "jacobian", where, "u1", 1)
        _shape(jac, "jacobian", where, (1,), "one flag")
        if int(jac[0]) not in (0, 1):
            raise ValueError(f"{where}: field 'jacobian' must be 0 or 1, got {int(jac[0])}")
        self.jacobian = bool(jac[0])
        theta = _field(fields, "theta_i", where, "f4", 1)
        _nodes(theta, "theta_i", where, 0.0, _F32_HALF_PI)
        phi = _field(fields, "phi_i", where, "f4", 1)
        _nodes(phi, "phi_i", where, -_F32_PI, _F32_PI)
        n_phi, n_theta = phi.size, theta.size
        self.isotropic = n_phi <= 2
        self.reduction = 1
        if not self.isotropic:
            self.reduction = int(np.rint(2 * np.pi / (float(phi[-1]) - float(phi[0]))))
            if self.reduction not in (1, 2, 4):
                raise ValueError(f"{where}: field 'phi_i' must span 2 pi, pi or pi/2 "
                                 f"(symmetry reduction 1, 2 or 4), got a span of "
                                 f"{float(phi[-1] - phi[0]):.6g} rad")

        tables = {}
        for key in ("ndf", "sigma"):
            a = _field(fields, key, where, "f4", 2)
            if min(a.shape) < 2:
                raise ValueError(f"{where}: field {key!r} must have at least 2 x 2 nodes, got "
                                 f"shape {a.shape}")
            _finite(a, key, where)
            tables[key] = a
        if np.any(tables["ndf"] < 0):
            raise ValueError(f"{where}: field 'ndf' must be >= 0, min "
                             f"{tables['ndf'].min():.6g}")
        if np.any(tables["sigma"] <= 0):
            raise ValueError(f"{where}: field 'sigma' must be > 0 (it divides the BRDF), min "
                             f"{tables['sigma'].min():.6g}")
        vndf = _field(fields, "vndf", where, "f4", 4)
        if vndf.shape[:2] != (n_phi, n_theta) or min(vndf.shape[2:]) < 2:
            raise ValueError(f"{where}: field 'vndf' must have shape ({n_phi}, {n_theta}, "
                             f"n_y >= 2, n_x >= 2) (phi_i, theta_i, phi_m, theta_m), got "
                             f"{vndf.shape}")
        _finite(vndf, "vndf", where)
        if np.any(vndf < 0):
            raise ValueError(f"{where}: field 'vndf' must be >= 0, min {vndf.min():.6g}")
        total = (vndf[..., 1:] + vndf[..., :-1]).sum(axis=(-2, -1))
        if np.any(total <= 0):
            first = tuple(int(i) for i in np.argwhere(total <= 0)[0])
            raise ValueError(f"{where}: field 'vndf' must have a positive integral in every "
                             f"slice (the warp is normalised by it), slice {first} is zero")
        lum = _field(fields, "luminance", where, "f4", 4)
        if lum.shape[:2] != (n_phi, n_theta) or lum.shape[2] != lum.shape[3] \
                or lum.shape[2] < 2:
            raise ValueError(f"{where}: field 'luminance' must have shape ({n_phi}, "
                             f"{n_theta}, m, m) with m >= 2, got {lum.shape}")
        _finite(lum, "luminance", where)
        m = lum.shape[2]
        if "wavelengths" in fields:
            wl = _field(fields, "wavelengths", where, "f4", 1)
            _finite(wl, "wavelengths", where)
            if wl.size == 0 or np.any(wl <= 0) or np.any(np.diff(wl) <= 0):
                raise ValueError(f"{where}: field 'wavelengths' must be > 0 nm and increase "
                                 "strictly")
            key = "spectra"
            self.wavelengths: NDArray | None = _read_only(wl.astype(np.float64))
            self.channel_names = tuple(f"{w:g} nm" for w in wl.tolist())
        else:
            key = "rgb"
            self.wavelengths = None
            self.channel_names = ("R", "G", "B")
        nc = len(self.channel_names)
        slab = _field(fields, key, where, "f4", 5)
        _shape(slab, key, where, (n_phi, n_theta, nc, m, m),
               "phi_i, theta_i, channel, and the luminance's m x m")
        _finite(slab, key, where)
        self.channels = nc

        self._fields = types.MappingProxyType({k: _read_only(v) for k, v in fields.items()})
        s = n_phi * n_theta
        self._theta_nodes = theta.astype(np.float64)
        self._phi_nodes = phi.astype(np.float64)
        self._vdata, self._vcond, self._vmarg = _marginal_conditional(
            vndf.astype(np.float64).reshape(s, *vndf.shape[2:]))
        self._slices = np.ascontiguousarray(
            np.moveaxis(slab.astype(np.float64).reshape(s, nc, m, m), 1, 3))
        self._ndf = np.ascontiguousarray(tables["ndf"], dtype=np.float64)
        self._sigma = np.ascontiguousarray(tables["sigma"], dtype=np.float64)

    @property
    def fields(self) -> Mapping[str, NDArray]:
        """Every field of the file, read-only arrays with the stored dtypes."""
        return self._fields

    @property
    def theta_i(self) -> NDArray[np.float32]:
        """(n_theta_i,) incidence elevations of the measured slices, radians (float32)."""
        return self._fields["theta_i"]

    @property
    def phi_i(self) -> NDArray[np.float32]:
        """(n_phi_i,) incidence azimuths of the measured slices, radians (float32)."""
        return self._fields["phi_i"]

    @property
    def valid(self) -> NDArray[np.bool_] | None:
        """(n_phi_i, n_theta_i, m, m) the file's ``valid`` bits, or None without that field.

        The field is a packed bit mask, one bit per sample of the slices; neither reference
        loader reads it, and its meaning and bit order are undocumented: it is unpacked here
        most significant bit first (numpy's default). None also when the field does not
        have one bit per slice sample.
        """
        v = self._fields.get("valid")
        shape = self._slices.shape[:1] + self._slices.shape[1:3]
        n = math.prod(shape)
        if v is None or v.dtype != np.uint8 or v.ndim != 1 or v.size != -(-n // 8):
            return None
        bits = np.unpackbits(v, count=n).astype(bool).reshape(
            self.phi_i.size, self.theta_i.size, *shape[1:])
        bits.flags.writeable = False
        return bits

    def _eval(self, wi: NDArray[np.float64], wo: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.empty((wi.shape[0], self.channels))
        # one compiled specialisation: inputs from BRDF.eval may be read-only views
        # ~0.4 us a pair: parts of 256 pairs outweigh the hand-off to a thread
        run_parallel(_rgl_eval_kernel, wi.shape[0], writable(wi), writable(wo),
                     self._theta_nodes, self._phi_nodes, self._vdata, self._vcond, self._vmarg,
                     self._slices, self._ndf, self._sigma, self.isotropic, self.reduction,
                     self.jacobian, out, grain=256)
        return out

    def __repr__(self) -> str:
        return (f"RGLBRDF(name={self.name!r}, description={self.description!r}, "
                f"channels={self.channels}, isotropic={self.isotropic})")


@njit
def _interval(nodes, x):  # pragma: no cover - compiled
    # nodes: (n,) increasing. Returns (k, w): x sits between nodes[k] and nodes[k + 1] with
    # weight w of the upper node, clamped to [0, 1]; (0, 0.0) for a single node.
    n = nodes.shape[0]
    if n == 1:
        return 0, 0.0
    lo, hi = 0, n - 2  # largest k in [0, n - 2] with nodes[k] <= x (0 if none)
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if nodes[mid] <= x:
            lo = mid
        else:
            hi = mid - 1
    w = (x - nodes[lo]) / (nodes[lo + 1] - nodes[lo])
    return lo, min(max(w, 0.0), 1.0)


@njit
def _cell(u, n):  # pragma: no cover - compiled
    # u in [0, 1] (clamped) on n nodes: (cell k in [0, n - 2], fraction in [0, 1]).
    t = min(max(u, 0.0), 1.0) * (n - 1)
    k = min(int(t), n - 2)
    return k, t - k


@njit
def _bilinear(table, ux, uy):  # pragma: no cover - compiled
    # table: (ny, nx) read at (ux, uy) in [0, 1]^2, x along the last axis.
    jx, fx = _cell(ux, table.shape[1])
    jy, fy = _cell(uy, table.shape[0])
    return ((1.0 - fy) * ((1.0 - fx) * table[jy, jx] + fx * table[jy, jx + 1])
            + fy * ((1.0 - fx) * table[jy + 1, jx] + fx * table[jy + 1, jx + 1]))


@njit
def _elevation(x, y, z):  # pragma: no cover - compiled
    # theta of a unit vector as 2 asin(|w - z| / 2): accurate near the normal, unlike acos.
    return 2.0 * math.asin(min(0.5 * math.sqrt(x * x + y * y + (z - 1.0) ** 2), 1.0))


@loopjit
def _rgl_eval_kernel(first, stop, wi, wo, theta_nodes, phi_nodes, vdata, vcond, vmarg, slices,
                     ndf, sigma, isotropic, reduction, jacobian,
                     out):  # pragma: no cover - compiled
    # Pairs first .. stop - 1 (run_parallel). wi, wo: (n, 3) unit vectors, z >= 0;
    # theta_nodes (n_t,), phi_nodes (n_p,); vdata, vcond: (n_p * n_t, ny, nx) normalised VNDF
    # and conditional CDF, vmarg (n_p * n_t, ny); slices: (n_p * n_t, m, m, c); ndf, sigma:
    # 2-D; out: (n, c) = f in 1/sr.
    n_t = theta_nodes.shape[0]
    n_p = phi_nodes.shape[0]
    ny, nx = vdata.shape[1], vdata.shape[2]
    m = slices.shape[1]
    nc = slices.shape[3]
    # an unsigned index: no negative-index test on a[p] (basis.jit.loopjit)
    for p in range(np.uint64(first), np.uint64(stop)):
        ix, iy, iz = wi[p, 0], wi[p, 1], wi[p, 2]
        ox, oy, oz = wo[p, 0], wo[p, 1], wo[p, 2]
        if np.float32(iz) <= 0.0 or np.float32(oz) <= 0.0:  # the reference's float32 test
            for c in range(nc):
                out[p, c] = 0.0
            continue
        if reduction >= 2:  # fold w_i into the stored azimuths, w_o alike (Mitsuba 3)
            flip_y = math.copysign(1.0, iy) > 0.0
            flip_x = (math.copysign(1.0, ix) > 0.0) if reduction == 4 else flip_y
            if flip_x:
                ix, ox = -ix, -ox
            if flip_y:
                iy, oy = -iy, -oy
        hx, hy, hz = ix + ox, iy + oy, iz + oz
        hn = math.sqrt(hx * hx + hy * hy + hz * hz)
        hx, hy, hz = hx / hn, hy / hn, hz / hn
        theta_i = _elevation(ix, iy, iz)
        phi_i = math.atan2(iy, ix)
        theta_m = _elevation(hx, hy, hz)
        phi_m = math.atan2(hy, hx)
        ui_x = math.sqrt(theta_i * (2.0 / math.pi))
        ui_y = (phi_i + math.pi) / (2.0 * math.pi)
        um_x = math.sqrt(theta_m * (2.0 / math.pi))
        um_y = ((phi_m - phi_i if isotropic else phi_m) + math.pi) / (2.0 * math.pi)
        um_y -= math.floor(um_y)
        # the (up to) four slices around the incidence and their weights
        kt, wt = _interval(theta_nodes, theta_i)
        kp, wp = _interval(phi_nodes, phi_i)
        kt1, kp1 = min(kt + 1, n_t - 1), min(kp + 1, n_p - 1)
        s00, s01 = kp * n_t + kt, kp * n_t + kt1
        s10, s11 = kp1 * n_t + kt, kp1 * n_t + kt1
        w00, w01 = (1.0 - wp) * (1.0 - wt), (1.0 - wp) * wt
        w10, w11 = wp * (1.0 - wt), wp * wt
        # inverse VNDF warp of u_m: the conditional CDF in x, then the marginal in y
        jx, fx = _cell(um_x, nx)
        jy, fy = _cell(um_y, ny)
        v00 = v10 = v01 = v11 = q0 = q1 = r0 = r1 = m0 = 0.0
        for k in range(4):
            s = s00 if k == 0 else s01 if k == 1 else s10 if k == 2 else s11
            w = w00 if k == 0 else w01 if k == 1 else w10 if k == 2 else w11
            if w == 0.0:
                continue
            v00 += w * vdata[s, jy, jx]
            v10 += w * vdata[s, jy, jx + 1]
            v01 += w * vdata[s, jy + 1, jx]
            v11 += w * vdata[s, jy + 1, jx + 1]
            q0 += w * vcond[s, jy, jx]
            q1 += w * vcond[s, jy + 1, jx]
            r0 += w * vcond[s, jy, nx - 1]
            r1 += w * vcond[s, jy + 1, nx - 1]
            m0 += w * vmarg[s, jy]
        c0 = (1.0 - fy) * v00 + fy * v01
        c1 = (1.0 - fy) * v10 + fy * v11
        row = (1.0 - fy) * r0 + fy * r1
        if row > 0.0:
            sx = (fx * (c0 + 0.5 * fx * (c1 - c0)) + (1.0 - fy) * q0 + fy * q1) / row
        else:  # no visible normal along this row: the reference's 0/0; keep x (module notes)
            sx = um_x
        sy = fy * (r0 + 0.5 * fy * (r1 - r0)) + m0
        # the slices at the warped sample, clamped to >= 0
        kx, gx = _cell(sx, m)
        ky, gy = _cell(sy, m)
        scale = 1.0 / oz
        if jacobian:
            scale *= _bilinear(ndf, um_x, um_y) / (4.0 * _bilinear(sigma, ui_x, ui_y))
        for c in range(nc):
            v = 0.0
            for k in range(4):
                s = s00 if k == 0 else s01 if k == 1 else s10 if k == 2 else s11
                w = w00 if k == 0 else w01 if k == 1 else w10 if k == 2 else w11
                if w == 0.0:
                    continue
                v += w * ((1.0 - gy) * ((1.0 - gx) * slices[s, ky, kx, c]
                                        + gx * slices[s, ky, kx + 1, c])
                          + gy * ((1.0 - gx) * slices[s, ky + 1, kx, c]
                                  + gx * slices[s, ky + 1, kx + 1, c]))
            out[p, c] = max(v, 0.0) * scale


def read_rgl(path: str | os.PathLike) -> RGLBRDF:
    """Read a measured material of the RGL-EPFL database (``.bsdf``, RGB or spectral).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    RGLBRDF
        ``name`` is the file name without ``.bsdf``.

    Raises
    ------
    FileNotFoundError, IsADirectoryError
        The path does not exist or is a directory.
    ValueError
        Not a tensor file, truncated or damaged, or a field missing, of the wrong type or
        shape, or not finite; the message names the file and the field. Also for a path
        that is not a regular file (a FIFO, a device).

    Examples
    --------
    >>> import os, tempfile
    >>> f32 = np.float32
    >>> fields = {
    ...     "description": np.frombuffer(b"grey", np.uint8), "jacobian": np.array([1], np.uint8),
    ...     "theta_i": np.array([0, np.pi / 2], f32), "phi_i": np.array([0], f32),
    ...     "ndf": np.ones((2, 2), f32), "sigma": np.ones((2, 2), f32),
    ...     "vndf": np.ones((1, 2, 2, 2), f32), "luminance": np.ones((1, 2, 2, 2), f32),
    ...     "rgb": np.full((1, 2, 3, 2, 2), 0.5, f32)}
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     brdf = read_rgl(write_tensor_file(os.path.join(tmp, "grey.bsdf"), fields))
    >>> brdf.name, brdf.channel_names, brdf.jacobian
    ('grey', ('R', 'G', 'B'), True)
    >>> brdf.eval([0.0, 0.0, 1.0], [0.0, 0.0, 1.0]).tolist()   # 0.5 * 1 / (4 * 1) / cos 0
    [0.125, 0.125, 0.125]
    """
    p = input_file(path, "RGL")
    fields = read_tensor_file(p)
    name = p.name[:-len(".bsdf")] if p.name.endswith(".bsdf") else p.name
    return RGLBRDF(fields, name=name, path=p)
