"""Saving and loading coefficient matrices: HDF5 (h5py) with a versioned schema.

Schema version 2
----------------
One file holds one :class:`basis.CoefficientMatrix`. Everything is in the root group ``/``.

Root attributes:

==================  =========================================================================
``format``          the string ``"scatmodes.coefficients"`` (foreign files lack it)
``schema_version``  integer, 2
``library``         ``"scatmodes <version>"`` that wrote the file (information only)
``basis_kind``      ``Basis.kind``, one of ``basis.KINDS``: ``"zernike"`` (HemiZernike),
                    ``"harmonics"`` (HemiHarmonics, odd), ``"harmonics-even"`` or ``"sh"``
                    (SphericalHarmonics)
``basis_order``     integer, inclusive order (lmax or n_max)
``quantity``        ``"f"`` or ``"f_cos"`` (what the matrix represents, see CoefficientMatrix)
``channels``        integer >= 1
``scalar``          bool: True if the matrix has no channel axis ((size, size))
``storage``         ``"isotropic"`` (one block per azimuthal order) or ``"dense"``
``dtype``           ``"float64"``, ``"float32"`` or ``"float16"``: precision of the stored
                    coefficients (loading always returns float64)
``info``            JSON text: ``CoefficientMatrix.info`` (provenance: source, parameters,
                    method, estimated errors, timings). Tagged objects keep their type:
                    ``{"__ndarray__": [...], "dtype": "...", "shape": [...]}`` for numpy
                    arrays, ``{"__tuple__": [...]}`` for tuples, ``{"__float__": "nan"}``
                    (or "inf", "-inf") for non-finite floats. Numpy scalars become Python
                    numbers.
==================  =========================================================================

Datasets (symmetric storage: only the upper triangle, row by row, i <= j, as
``numpy.triu_indices``):

- ``storage == "isotropic"``: group ``blocks`` with datasets ``m0``, ``m1``, ... one per
  azimuthal order m = 0..top, each of shape (channels, k_m (k_m + 1) / 2), k_m the number of
  basis functions with azimuthal order +m. Attribute ``sizes`` of the group: the k_m.
- ``storage == "dense"``: dataset ``matrix`` of shape (channels, size (size + 1) / 2).

Group ``provenance`` repeats, as plain attributes for ``h5dump`` readers, the scalar string
and number entries of ``info`` among ``source``, ``method``, ``truncation_error``,
``error_estimate``, ``rel_error`` and ``seconds``. Readers use ``info``.

Writing is atomic: the file is written under a temporary name in the same directory and
renamed over the target only when complete, so a crash never leaves a half-written file
under the real name. Reading refuses, with a message naming the problem: files that are not
HDF5 (or are truncated), HDF5 files without the ``format`` attribute (foreign), and schema
versions other than those listed in :data:`READABLE_VERSIONS`. Older versions stay readable:
each version has its own reader in ``_READERS``.

Schema version 1 (written by scatmodes 0.1.0 before the basis kinds had one vocabulary)
differs only in naming the hemisphere harmonics ``basis_kind = "hemi_sh"`` with a separate
``basis_parity`` attribute (``"odd"`` or ``"even"``; ``"all"`` for the other kinds).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

import basis
from basis import CoefficientMatrix
from project.io import atomic_path

__all__ = ["FORMAT", "READABLE_VERSIONS", "SCHEMA_VERSION", "load", "save"]

#: Value of the ``format`` attribute that marks a scatmodes coefficient file.
FORMAT = "scatmodes.coefficients"
#: Schema written by :func:`save`.
SCHEMA_VERSION = 2
#: Storage precisions accepted by :func:`save`.
DTYPES = ("float64", "float32", "float16")
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_PROVENANCE_KEYS = ("source", "method", "truncation_error", "error_estimate", "rel_error",
                    "seconds")


def save(cm: CoefficientMatrix, path: str | os.PathLike, *, dtype: str = "float64") -> Path:
    """Write a coefficient matrix to an HDF5 file (schema version 2, see the module notes).

    Parameters
    ----------
    cm : basis.CoefficientMatrix
    path : str or os.PathLike
        Target file; its directory must exist. An existing file is replaced atomically.
    dtype : {"float64", "float32", "float16"}
        Precision of the stored coefficients. float64 round-trips bit for bit; the others
        cost the rounding error reported by :func:`compress.precision`.

    Returns
    -------
    pathlib.Path
        ``path``.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from basis import HemiHarmonics, CoefficientMatrix
    >>> hb = HemiHarmonics(3)
    >>> M = np.zeros((hb.size, hb.size)); M[0, 0] = 1 / 3
    >>> cm = CoefficientMatrix(hb, M, info={"source": "Lambert(0.5)"})
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     back = load(save(cm, os.path.join(tmp, "lambert.h5")))
    >>> bool(np.array_equal(back.matrix, cm.matrix)), back.info["source"]
    (True, 'Lambert(0.5)')
    """
    if not isinstance(cm, CoefficientMatrix):
        raise TypeError(f"cm must be a basis.CoefficientMatrix, got {type(cm).__name__}")
    if not isinstance(dtype, str) or dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {', '.join(map(repr, DTYPES))}, got {dtype!r}")
    info_text = json.dumps(_encode(cm.info), allow_nan=False)
    scalar = cm.is_scalar
    arrays = _packed(cm)
    top = float(np.finfo(dtype).max)
    worst = max(float(np.max(np.abs(a), initial=0.0)) for a in arrays.values())
    if worst > top:
        raise ValueError(f"dtype {dtype!r} cannot hold coefficients up to {worst:.6g} "
                         f"(its largest finite value is {float(top):.6g}); use a wider dtype")
    target = Path(os.fspath(path))
    with atomic_path(target, suffix=".tmp") as tmp, h5py.File(tmp, "w") as f:
        a = f.attrs
        a["format"] = FORMAT
        a["schema_version"] = SCHEMA_VERSION
        a["library"] = f"scatmodes {_version()}"
        a["basis_kind"] = cm.basis.kind
        a["basis_order"] = cm.basis.order
        a["quantity"] = cm.quantity
        a["channels"] = cm.channels
        a["scalar"] = bool(scalar)
        a["storage"] = "isotropic" if cm.is_isotropic else "dense"
        a["dtype"] = dtype
        a["info"] = info_text
        if cm.is_isotropic:
            g = f.create_group("blocks")
            sizes = []
            for m in range(len(arrays)):
                data = arrays[f"m{m}"]
                g.create_dataset(f"m{m}", data=data.astype(dtype))
                sizes.append(_side(data.shape[1]))
            g.attrs["sizes"] = np.array(sizes, dtype=np.int64)
        else:
            f.create_dataset("matrix", data=arrays["matrix"].astype(dtype))
        p = f.create_group("provenance")
        for key in _PROVENANCE_KEYS:
            v = cm.info.get(key)
            if isinstance(v, str | int | float) and not isinstance(v, bool):
                p.attrs[key] = v
        f.flush()
    return target


def load(path: str | os.PathLike) -> CoefficientMatrix:
    """Read a coefficient matrix written by :func:`save`.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    basis.CoefficientMatrix
        float64 coefficients, the same storage (isotropic blocks or dense) and ``info`` as
        saved (numpy arrays and tuples restored).

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        Not an HDF5 file, a truncated or damaged one, a foreign HDF5 file (no ``format``
        attribute ``"scatmodes.coefficients"``), an unknown schema version, or content that
        contradicts the schema (missing datasets, wrong shapes).
    """
    p = Path(os.fspath(path))
    if not p.exists():
        raise FileNotFoundError(f"coefficient file {str(p)!r} does not exist")
    if p.is_dir():
        raise IsADirectoryError(f"path must be a file, got the directory {str(p)!r}")
    with open(p, "rb") as fh:
        head = fh.read(8)
    if head != _HDF5_SIGNATURE:
        raise ValueError(f"{str(p)!r} is not an HDF5 file (no HDF5 signature in its first "
                         "bytes); scatmodes coefficient files are written by compress.save")
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise ValueError(f"{str(p)!r} is a damaged or truncated HDF5 file and cannot be "
                         f"opened ({exc}); write it again") from None
    with f:
        fmt = _attr(f, "format", p, required=False)
        if fmt != FORMAT:
            raise ValueError(f"{str(p)!r} is an HDF5 file but not a scatmodes coefficient file "
                             f"(format attribute {fmt!r}, expected {FORMAT!r})")
        version = _attr(f, "schema_version", p)
        reader = _READERS.get(int(version)) if np.ndim(version) == 0 else None
        if reader is None:
            raise ValueError(f"{str(p)!r} has schema version {version!r}; this library "
                             f"(scatmodes {_version()}) reads schema versions "
                             f"{', '.join(map(str, READABLE_VERSIONS))}: upgrade scatmodes to "
                             "read it")
        try:
            return reader(f, p)
        except (KeyError, OSError) as exc:
            raise ValueError(f"{str(p)!r} is damaged: {exc}") from None


# -- schema versions 1 and 2 -------------------------------------------------------------------
def _read_v1(f: h5py.File, p: Path) -> CoefficientMatrix:
    kind = _attr(f, "basis_kind", p)
    if kind == "hemi_sh":
        parity = _attr(f, "basis_parity", p)
        kind = {"odd": "harmonics", "even": "harmonics-even"}.get(parity)
        if kind is None:
            raise ValueError(f"{str(p)!r} is damaged: basis_parity {parity!r} of hemisphere "
                             "harmonics is neither 'odd' nor 'even'")
    return _read_matrix(f, p, kind)


def _read_v2(f: h5py.File, p: Path) -> CoefficientMatrix:
    return _read_matrix(f, p, _attr(f, "basis_kind", p))


def _read_matrix(f: h5py.File, p: Path, kind: str) -> CoefficientMatrix:
    if kind not in basis.KINDS:
        raise ValueError(f"{str(p)!r} names an unknown basis kind {kind!r} (known: "
                         f"{', '.join(map(repr, basis.KINDS))})")
    order = int(_attr(f, "basis_order", p))
    b = basis.make_basis(kind, order)
    quantity = _attr(f, "quantity", p)
    channels = int(_attr(f, "channels", p))
    scalar = bool(_attr(f, "scalar", p))
    storage = _attr(f, "storage", p)
    info = _decode(json.loads(_attr(f, "info", p)))
    if storage == "isotropic":
        cos_idx = b.azimuthal_blocks().cos
        g = f["blocks"]
        blocks = []
        for m, idx in enumerate(cos_idx):
            data = np.asarray(g[f"m{m}"][()], dtype=np.float64)
            blocks.append(_unpack(data, idx.size, channels, f"blocks/m{m}", p))
        if f"m{len(cos_idx)}" in g:
            raise ValueError(f"{str(p)!r} is damaged: more blocks than {b!r} has azimuthal "
                             "orders")
        return CoefficientMatrix.from_blocks(b, [x[0] if scalar else x for x in blocks],
                                             quantity, info=info)
    if storage == "dense":
        data = np.asarray(f["matrix"][()], dtype=np.float64)
        m = _unpack(data, b.size, channels, "matrix", p)
        return CoefficientMatrix(b, m[0] if scalar else m, quantity, isotropic=False, info=info)
    raise ValueError(f"{str(p)!r} is damaged: storage attribute {storage!r} is neither "
                     "'isotropic' nor 'dense'")


_READERS = {1: _read_v1, 2: _read_v2}
#: Schema versions :func:`load` understands.
READABLE_VERSIONS = tuple(sorted(_READERS))


# -- helpers ----------------------------------------------------------------------------------
def _version() -> str:
    try:
        from importlib.metadata import version

        return version("scatmodes")
    except Exception:  # noqa: BLE001 - not installed: still write a file
        return "unknown"


def _attr(f: h5py.File, name: str, p: Path, *, required: bool = True) -> Any:
    if name not in f.attrs:
        if not required:
            return None
        raise ValueError(f"{str(p)!r} is damaged: the root attribute {name!r} is missing")
    v = f.attrs[name]
    if isinstance(v, bytes):
        v = v.decode()
    if isinstance(v, np.generic):
        v = v.item()
    return v


def _packed(cm: CoefficientMatrix) -> dict[str, NDArray[np.float64]]:
    """Upper triangles, (channels, k (k + 1) / 2), of each block or of the dense matrix."""
    if cm.is_isotropic:
        out = {}
        for m, blk in enumerate(cm.stored):
            iu = np.triu_indices(blk.shape[-1])
            out[f"m{m}"] = np.ascontiguousarray(blk[:, iu[0], iu[1]])
        return out
    dense = cm.stored[0]
    iu = np.triu_indices(dense.shape[-1])
    return {"matrix": np.ascontiguousarray(dense[:, iu[0], iu[1]])}


def _side(n_packed: int) -> int:
    return int(round((math.sqrt(8 * n_packed + 1) - 1) / 2))


def _unpack(data: NDArray, k: int, channels: int, name: str, p: Path) -> NDArray[np.float64]:
    want = (channels, k * (k + 1) // 2)
    if data.shape != want:
        raise ValueError(f"{str(p)!r} is damaged: dataset {name!r} has shape {data.shape}, "
                         f"the schema needs {want}")
    out = np.zeros((channels, k, k))
    iu = np.triu_indices(k)
    out[:, iu[0], iu[1]] = data
    out[:, iu[1], iu[0]] = data
    return out


def _encode(obj: Any) -> Any:
    """JSON-able form of an info dict (arrays, tuples, numpy scalars, non-finite floats)."""
    if isinstance(obj, dict):
        bad = [k for k in obj if not isinstance(k, str)]
        if bad:
            raise TypeError(f"info keys must be strings to be saved, got {bad[0]!r}")
        return {k: _encode(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in "biuf":
            raise TypeError(f"info arrays must be numeric to be saved, got dtype {obj.dtype}")
        return {"__ndarray__": [_encode(x) for x in obj.ravel().tolist()],
                "dtype": obj.dtype.str, "shape": list(obj.shape)}
    if isinstance(obj, tuple):
        return {"__tuple__": [_encode(x) for x in obj]}
    if isinstance(obj, list):
        return [_encode(x) for x in obj]
    if isinstance(obj, np.generic):
        return _encode(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return {"__float__": repr(obj)}
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    raise TypeError(f"info values must be numbers, strings, lists, tuples, dicts or numeric "
                    f"arrays to be saved, got {type(obj).__name__}")


def _decode(obj: Any) -> Any:
    if isinstance(obj, dict):
        if "__ndarray__" in obj:
            flat = [_decode(x) for x in obj["__ndarray__"]]
            return np.array(flat, dtype=np.dtype(obj["dtype"])).reshape(obj["shape"])
        if "__tuple__" in obj:
            return tuple(_decode(x) for x in obj["__tuple__"])
        if "__float__" in obj:
            return float(obj["__float__"])
        return {k: _decode(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_decode(x) for x in obj]
    return obj
