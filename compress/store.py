"""Saving and loading representations: HDF5 (h5py) with a versioned schema.

:func:`save` writes, and :func:`load` reads back, one of

- a :class:`basis.CoefficientMatrix`;
- a :class:`project.FittedModel` (or any model with ``family`` and ``params``, such as
  :class:`project.factored.FactoredLobe`; it is read back as a :class:`project.FittedModel`);
- a :class:`compress.Hybrid` whose lobe is such a model.

Schema version 6
----------------
Root attributes of every file:

==================  =========================================================================
``format``          the string ``"scatmodes.coefficients"`` (foreign files lack it)
``schema_version``  integer, 6
``library``         ``"scatmodes <version>"`` that wrote the file (information only)
``content``         ``"coefficients"``, ``"model"`` or ``"hybrid"``
``dtype``           ``"float64"``, ``"float32"`` or ``"float16"``: precision of the stored
                    numbers (loading always returns float64)
==================  =========================================================================

A *matrix group* (the root for ``content = "coefficients"``, the group ``residual`` of a
hybrid) holds one coefficient matrix:

==================  =========================================================================
``basis_kind``      ``Basis.kind``, one of ``basis.KINDS``: ``"zernike"`` (HemiZernike),
                    ``"harmonics"`` (HemiHarmonics, odd), ``"harmonics-even"`` or ``"sh"``
                    (SphericalHarmonics)
``basis_order``     integer, inclusive order (lmax or n_max)
``quantity``        ``"f"`` or ``"f_cos"`` (what the matrix represents, see CoefficientMatrix)
``channels``        integer >= 1
``scalar``          bool: True if the matrix has no channel axis ((size, size)); then
                    ``channels`` is 1
``storage``         ``"isotropic"`` (one block per azimuthal order) or ``"dense"``
``reciprocal``      bool: True for a symmetric matrix, False for a general one
                    (``CoefficientMatrix.reciprocal``)
``dtype``           as above
``info``            JSON text: ``CoefficientMatrix.info`` (provenance: source, parameters,
                    method, estimated errors, timings), see *Info* below
==================  =========================================================================

and its datasets (symmetric storage, ``reciprocal`` True: only the upper triangle, row by
row, i <= j, as ``numpy.triu_indices``, n(k) = k (k + 1) / 2 numbers for a side k; general
storage, ``reciprocal`` False: the whole matrix, row by row (rows w_i, columns w_o),
n(k) = k^2):

- ``storage == "isotropic"``: group ``blocks`` with datasets ``m0``, ``m1``, ... one per
  azimuthal order m = 0..top, each of shape (channels, n(k_m)), k_m the number of
  basis functions with azimuthal order +m. Attribute ``sizes`` of the group: the k_m.
- ``storage == "dense"``: dataset ``matrix`` of shape (channels, n(size)).

A *model group* (the root for ``content = "model"``, the group ``lobe`` of a hybrid) holds
one parametric model: attributes ``family`` (a family of :func:`project.fit_model`),
``dtype`` and ``info`` (JSON text), and a group ``params`` with one dataset per parameter,
named after it, holding its values flattened (C order) in one dimension; the dataset's
attribute ``shape`` (integer array, empty for a scalar) gives the parameter's shape. A model
may store a packed form of its parameters (``stored_params``) that ``project.FittedModel``
accepts back: a symmetric ``"grid"`` table is stored as its (n (n + 1) / 2, m, C) upper
triangle.

A hybrid (``content = "hybrid"``) has the root attribute ``info`` (``Hybrid.info``), the
model group ``lobe`` and the matrix group ``residual``.

Checksums: every dataset carries an HDF5 Fletcher-32 checksum (``fletcher32=True``), which
HDF5 checks on every read, and the file is written in the format of HDF5 1.10 (h5py
``libver=("v110", "latest")``; readable by HDF5 1.10 and later): superblock version 3,
version-2 object headers, fractal heaps and chunk indices, each with a Jenkins lookup3
checksum that HDF5 verifies before parsing the structure (HDF5 File Format Specification
3.0). Text attributes are fixed-length UTF-8 strings, held in the object header (h5py's
default variable-length strings live in the global heap, which has no checksum; h5py reads
fixed-length ones as ``bytes``). So changed bytes anywhere in the metadata or the numbers
are detected instead of returned. Group
``provenance`` of the root repeats, as plain attributes for ``h5dump`` readers, the scalar
string and number entries of the top-level ``info`` among ``source``, ``method``,
``truncation_error``, ``error_estimate``, ``rel_error``, ``l2``, ``log`` and ``seconds``.
Readers use ``info``.

Info
~~~~
JSON text. Tagged objects keep their type: ``{"__ndarray__": [...], "dtype": "...",
"shape": [...]}`` for numeric numpy arrays, ``{"__tuple__": [...]}`` for tuples,
``{"__float__": "nan"}`` (or "inf", "-inf") for non-finite floats. Numpy scalars become
Python numbers. Entries that are none of numbers, strings, None, lists, tuples, dicts with
string keys and numeric arrays (e.g. an arbitrary object) are left out, with a
``UserWarning`` naming them.

Writing
-------
Writing is atomic: the file is written under a temporary name in the same directory and
renamed over the target only when complete, so a crash never leaves a half-written file
under the real name. :func:`save` refuses what :func:`load` could not read back: a dtype
too narrow for the values, and model parameters that :class:`project.FittedModel` rejects.

Reading
-------
:func:`load` returns what was saved or raises: every problem with a file raises
``ValueError`` naming the file and what is wrong (``FileNotFoundError`` and other ``OSError``
only for a file that is missing or unreadable), never another exception. Before reading any
numbers it checks, from the metadata alone,

- the HDF5 signature, the ``format`` attribute (foreign files) and the schema version
  (versions other than :data:`READABLE_VERSIONS`: upgrade the library);
- the type and range of every attribute (strings, integers, flags; orders up to the basis'
  ``max_order``; ``scalar`` only with 1 channel);
- the indirections of :mod:`project.hdf5`, anywhere in the file: soft, external and
  user-defined links, virtual datasets, external storage and references are refused (a
  scatmodes file is self-contained, and each of them may point at another file or another
  part of this one);
- every dataset: a real (hard-linked) dataset with no filter other than the checksum,
  of the declared floating-point dtype, of the exact
  shape that the basis kind, order and channels imply, and fully stored in the file;
- the size: the coefficients that the claimed order and channels imply must fit in the
  file, so a small file that claims a huge order is refused at once, before any basis is
  built;

and then, reading the numbers (checksums verified by HDF5): every value finite, and the
coefficients' sum of squares finite (by orthonormality, the squared L2 norm of the
represented function, so its evaluations stay finite too); the ``info`` JSON and its
tags well formed; and the rebuilt object accepted by its constructor (e.g. FittedModel's
parameter ranges, matching channels of a hybrid's parts).

Older versions
--------------
Each version has its own reader in ``_READERS``. Schema version 5 is version 6 without the
model family ``"grid"`` (:mod:`project.fitting.grid`), for the same reason as 4 and 5.
Schema version 4 is version 5 without the
model family ``"tucker"`` (:mod:`project.tucker`; a library that reads version 4 only
refuses version 5 files rather than meeting a family it does not know). Schema version 3
is version 4 without the
``reciprocal`` attribute: every matrix is symmetric (read back with ``reciprocal`` True).
Schema version 2 is version 3 restricted
to ``content = "coefficients"`` without the ``content`` attribute and without checksums, in
h5py's default (oldest) file format with variable-length strings. The structural checks
apply to such files too, but changed bytes among their numbers go undetected, and on some
damaged metadata of that format the HDF5 library itself may fail hard; saving them again
gives them checksums.
Schema version 1 (written by scatmodes 0.1.0 before the basis kinds had one vocabulary)
differs from 2 only in naming the hemisphere harmonics ``basis_kind = "hemi_sh"`` with a
separate ``basis_parity`` attribute (``"odd"`` or ``"even"``; ``"all"`` for the other kinds)
and in the ``dtype`` attribute being optional.
"""

from __future__ import annotations

import json
import math
import os
import stat
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple, NoReturn

import h5py
import numpy as np
from numpy.typing import NDArray

import basis
from basis import CoefficientMatrix
from project.hdf5 import Indirection, check_dataset, check_links, check_self_contained
from project.io import atomic_path

__all__ = ["CONTENTS", "FILE_KINDS", "FORMAT", "READABLE_VERSIONS", "SCHEMA_VERSION",
           "file_kind", "load", "save"]

#: Value of the ``format`` attribute that marks a scatmodes file.
FORMAT = "scatmodes.coefficients"
#: Schema written by :func:`save`.
SCHEMA_VERSION = 6
#: Values of the ``content`` attribute: what a file holds.
CONTENTS = ("coefficients", "model", "hybrid")
#: Storage precisions accepted by :func:`save`.
DTYPES = ("float64", "float32", "float16")
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_PROVENANCE_KEYS = ("source", "method", "truncation_error", "error_estimate", "rel_error",
                    "l2", "log", "seconds")
# the largest order each basis kind accepts, known without building a basis
_MAX_ORDER = {"zernike": basis.HemiZernike.max_order, "sh": basis.SphericalHarmonics.max_order,
              "harmonics": basis.HemiHarmonics.max_order,
              "harmonics-even": basis.HemiHarmonics.max_order}
_MIN_ORDER = {"harmonics": 1}
# a model has a handful of parameter arrays; more in a file means damage
_MAX_PARAMS = 64
_MAX_PARAM_NDIM = 8
# what h5py and numpy raise on damaged metadata; load turns them into ValueError
_LOW_LEVEL = (OSError, RuntimeError, KeyError, TypeError, IndexError, AttributeError,
              OverflowError, RecursionError, ValueError)


def save(obj: Any, path: str | os.PathLike, *, dtype: str = "float64") -> Path:
    """Write a coefficient matrix, a fitted model or a hybrid to an HDF5 file (schema 6).

    Parameters
    ----------
    obj : basis.CoefficientMatrix, project.FittedModel or compress.Hybrid
        A model may be any object with ``family`` (a family of :func:`project.fit_model`)
        and ``params`` (dict of str to arrays), such as
        :class:`project.factored.FactoredLobe`; so may
        a hybrid's lobe. Both are read back as :class:`project.FittedModel`.
    path : str or os.PathLike
        Target file; its directory must exist. An existing file is replaced atomically.
    dtype : {"float64", "float32", "float16"}
        Precision of the stored numbers (coefficients and model parameters). float64
        round-trips bit for bit; the others cost the rounding error reported by
        :func:`compress.precision`.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    TypeError
        ``obj`` is none of the above, or a hybrid's lobe has no ``family`` and ``params``.
    ValueError
        An unknown ``dtype``, values too large for it, or parameters that
        :class:`project.FittedModel` refuses (``load`` could not rebuild the model).

    Warns
    -----
    UserWarning
        Entries of an ``info`` dict that cannot be stored (see the module notes) are left out.

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
    from .hybrid import Hybrid

    if not isinstance(dtype, str) or dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {', '.join(map(repr, DTYPES))}, got {dtype!r}")
    # everything is checked and encoded before the file is created
    if isinstance(obj, CoefficientMatrix):
        content, info = "coefficients", obj.info
        parts = {"": _matrix_part(obj, dtype, "the matrix")}
    elif isinstance(obj, Hybrid):
        content, info = "hybrid", obj.info
        if not (hasattr(obj.lobe, "family") and hasattr(obj.lobe, "params")):
            raise TypeError(f"the lobe of this Hybrid, {type(obj.lobe).__name__}, has no family "
                            "and params, so it cannot be stored: save hybrids whose lobe is "
                            "fitted (compress.hybrid with a family name, project.fit_model, "
                            "project.factored.FactoredLobe)")
        parts = {"": _Part({"info": _info_text(obj.info, "Hybrid.info")}, {}, {}),
                 "lobe": _model_part(obj.lobe, dtype, "the hybrid's lobe"),
                 "residual": _matrix_part(obj.residual, dtype, "the hybrid's residual")}
    elif hasattr(obj, "family") and hasattr(obj, "params"):
        content, info = "model", getattr(obj, "info", None)
        parts = {"": _model_part(obj, dtype, "the model")}
    else:
        raise TypeError(f"save stores a basis.CoefficientMatrix, a project.FittedModel (or any "
                        f"model with family and params) or a compress.Hybrid, got "
                        f"{type(obj).__name__}")
    target = Path(os.fspath(path))
    # libver v110: superblock v3 and version-2 object headers, fractal heaps and chunk
    # indices, all of which carry checksums that HDF5 verifies before parsing them
    with (atomic_path(target, suffix=".tmp") as tmp,
          h5py.File(tmp, "w", libver=("v110", "latest")) as f):
        _set(f, "format", FORMAT)
        _set(f, "schema_version", SCHEMA_VERSION)
        _set(f, "library", f"scatmodes {_version()}")
        _set(f, "content", content)
        _set(f, "dtype", dtype)
        for name, part in parts.items():
            _write_part(f.create_group(name) if name else f, part)
        p = f.create_group("provenance")
        for key in _PROVENANCE_KEYS:
            v = info.get(key) if isinstance(info, Mapping) else None
            if isinstance(v, str | int | float) and not isinstance(v, bool):
                _set(p, key, v)
        f.flush()
    return target


#: What :func:`file_kind` tells apart.
FILE_KINDS = ("representation", "checkpoint", "rgl", "mbsdf", "merl", "measurements")
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_TENSOR_MAGIC = b"tensor_file\x00"  # RGL-EPFL .bsdf files (project.measured.rgl)
_MBSDF_MAGIC = b"NVIDIA ARC MBSDF V1\n"  # NVIDIA MDL .mbsdf files (project.measured.mbsdf)
_CHECKPOINT = "scatmodes-microgeometry-checkpoint-"  # project.microgeometry's --checkpoint


def file_kind(path: str | os.PathLike) -> str:
    """Tell what a file holds, from its first bytes (and the suffixes ``.binary``, ``.mbsdf``).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    str
        One of :data:`FILE_KINDS`: ``"representation"`` (any other HDF5 file: what
        :func:`load` reads, or refuses with its reason), ``"checkpoint"`` (a checkpoint of
        ``project.microgeometry.simulate``), ``"rgl"`` (an RGL-EPFL tensor file), ``"mbsdf"``
        (an NVIDIA MDL measured BSDF: its magic line or the ``.mbsdf`` suffix), ``"merl"``
        (a ``.binary`` file) or ``"measurements"`` (anything else: a text table for
        :func:`project.measured.read_measurements`). Only the kind is told; the readers
        check the content.

    Raises
    ------
    FileNotFoundError, IsADirectoryError
        The file is missing, or is a folder.
    ValueError
        It is not a regular file (a FIFO, a device), which could block a reader forever.
    """
    p = Path(os.fspath(path))
    if not p.exists():
        raise FileNotFoundError(f"file {str(p)!r} does not exist")
    if p.is_dir():
        raise IsADirectoryError(f"the path must be a file, got the directory {str(p)!r}")
    _regular_file(p)
    with open(p, "rb") as fh:
        head = fh.read(len(_MBSDF_MAGIC))
    if head == _MBSDF_MAGIC or p.suffix.lower() == ".mbsdf":
        return "mbsdf"
    head = head[:len(_TENSOR_MAGIC)]
    if head[:len(_HDF5_SIGNATURE)] == _HDF5_SIGNATURE:
        try:
            with h5py.File(p, "r") as f:
                fmt = f.attrs.get("format")
        except Exception:  # noqa: BLE001 - load reports what is wrong with the file
            fmt = None
        fmt = fmt.decode(errors="replace") if isinstance(fmt, bytes) else fmt
        checkpoint = isinstance(fmt, str) and fmt.startswith(_CHECKPOINT)
        return "checkpoint" if checkpoint else "representation"
    if head == _TENSOR_MAGIC:
        return "rgl"
    return "merl" if p.suffix.lower() == ".binary" else "measurements"


def _regular_file(p: Path) -> None:
    """Refuse a FIFO, a device or a socket before opening it (opening a FIFO blocks)."""
    mode = p.stat().st_mode
    if not stat.S_ISREG(mode):
        kind = "a FIFO (named pipe)" if stat.S_ISFIFO(mode) else "a device or a socket"
        raise ValueError(f"file {str(p)!r} must be a regular file, got {kind}: give the "
                         "path of a file on disk")


def load(path: str | os.PathLike) -> Any:
    """Read a coefficient matrix, a fitted model or a hybrid written by :func:`save`.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    basis.CoefficientMatrix, project.FittedModel or compress.Hybrid
        What was saved (a model with ``family`` and ``params`` comes back as a
        :class:`project.FittedModel`), in float64, with its ``info`` (numpy arrays and tuples
        restored). A matrix keeps its storage (isotropic blocks or dense).

    Raises
    ------
    FileNotFoundError
        The file does not exist (``IsADirectoryError``: it is a directory;
        ``BlockingIOError``: another process has it open for writing; other ``OSError``:
        it cannot be read).
    ValueError
        Anything wrong with the content, always naming the file: not HDF5, truncated or
        damaged (including checksum mismatches), a foreign HDF5 file (no ``format``
        attribute ``"scatmodes.coefficients"``), an unknown schema version, or content that
        contradicts the schema (see the module notes for the checks).
    """
    p = Path(os.fspath(path))
    name = repr(str(p))
    if not p.exists():
        raise FileNotFoundError(f"file {name} does not exist")
    if p.is_dir():
        raise IsADirectoryError(f"path must be a file, got the directory {name}")
    _regular_file(p)
    with open(p, "rb") as fh:
        head = fh.read(8)
    if head != _HDF5_SIGNATURE:
        raise ValueError(f"{name} is not an HDF5 file (no HDF5 signature in its first "
                         "bytes); scatmodes files are written by compress.save")
    size = p.stat().st_size
    try:
        f = h5py.File(p, "r")
    except _LOW_LEVEL as exc:
        # HDF5 file locking, and the superblock's mark of a file open for writing
        if "unable to lock file" in str(exc) or "already open for write" in str(exc):
            raise BlockingIOError(f"{name} is open for writing in another process; try again "
                                  "when it is done (if no process has it open, a writer "
                                  "crashed: 'h5clear -s FILE' removes the mark)") from None
        raise ValueError(f"{name} is a damaged or truncated HDF5 file and cannot be opened "
                         f"({_one_line(exc)}); write it again") from None
    try:
        with f:
            return _Reader(f, name, size).read()
    except _Refused as exc:
        raise ValueError(str(exc)) from None
    except _LOW_LEVEL as exc:
        raise ValueError(f"{name} is damaged: {type(exc).__name__}: {_one_line(exc)} "
                         "(restore it or write it again with compress.save)") from None


# -- writing ----------------------------------------------------------------------------------
class _Part(NamedTuple):
    """What goes into one group: its attributes, subgroups and datasets (relative paths)."""

    attrs: dict[str, Any]
    groups: dict[str, dict[str, Any]]
    datasets: dict[str, tuple[NDArray, dict[str, Any]]]


def _write_part(g: h5py.Group, part: _Part) -> None:
    for key, v in part.attrs.items():
        _set(g, key, v)
    for name, attrs in part.groups.items():
        sub = g.create_group(name)
        for key, v in attrs.items():
            _set(sub, key, v)
    for name, (data, attrs) in part.datasets.items():
        d = g.create_dataset(name, data=data, fletcher32=True)
        for key, v in attrs.items():
            _set(d, key, v)


def _set(obj: Any, key: str, value: Any) -> None:
    """Set an attribute; text as fixed-length UTF-8, kept in the checksummed object header.

    (h5py writes Python strings as variable-length strings, whose bytes live in the global
    heap, which has no checksum.)
    """
    if isinstance(value, str):
        raw = value.encode()
        obj.attrs.create(key, np.array(raw, dtype=f"S{max(1, len(raw))}"),
                         dtype=h5py.string_dtype("utf-8", max(1, len(raw))))
    else:
        obj.attrs[key] = value


def _matrix_part(cm: CoefficientMatrix, dtype: str, what: str) -> _Part:
    arrays = _packed(cm)
    _check_range(arrays.values(), dtype, what)
    attrs = {"basis_kind": cm.basis.kind, "basis_order": cm.basis.order,
             "quantity": cm.quantity, "channels": cm.channels, "scalar": bool(cm.is_scalar),
             "storage": "isotropic" if cm.is_isotropic else "dense",
             "reciprocal": bool(cm.reciprocal), "dtype": dtype,
             "info": _info_text(cm.info, f"{what}'s info")}
    if cm.is_isotropic:
        sizes = np.array([a.shape[-1] for a in cm.stored], dtype=np.int64)
        return _Part(attrs, {"blocks": {"sizes": sizes}},
                     {f"blocks/{m}": (a.astype(dtype), {}) for m, a in arrays.items()})
    return _Part(attrs, {}, {"matrix": (arrays["matrix"].astype(dtype), {})})


def _model_part(model: Any, dtype: str, what: str) -> _Part:
    from project.fitting import FittedModel

    # a model may store a packed form of its params (a symmetric grid: its upper triangle)
    family, params = model.family, getattr(model, "stored_params", model.params)
    if not isinstance(family, str):
        raise TypeError(f"{what}'s family must be a string, got {type(family).__name__}")
    if not isinstance(params, Mapping):
        raise TypeError(f"{what}'s params must be a dict of parameter arrays, got "
                        f"{type(params).__name__}")
    arrays = {}
    for key, value in params.items():
        if not isinstance(key, str) or not key or "/" in key or key == ".":
            raise ValueError(f"{what}'s parameter names must be non-empty strings without "
                             f"'/', got {key!r}")
        try:
            arrays[key] = np.array(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise TypeError(f"{what}'s parameter {key!r} must be numbers, got "
                            f"{value!r}") from None
        if arrays[key].ndim > _MAX_PARAM_NDIM:
            raise ValueError(f"{what}'s parameter {key!r} has {arrays[key].ndim} dimensions, "
                             f"at most {_MAX_PARAM_NDIM} can be stored")
    if len(arrays) > _MAX_PARAMS:
        raise ValueError(f"{what} has {len(arrays)} parameters, at most {_MAX_PARAMS} can be "
                         "stored")
    _check_range(arrays.values(), dtype, what)
    # the numbers load will see, rebuilt as load rebuilds them
    stored = {k: v.astype(dtype) for k, v in arrays.items()}
    try:
        FittedModel(family, {k: v.astype(np.float64) for k, v in stored.items()})
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} cannot be saved: load would rebuild it as "
                         f"project.FittedModel({family!r}, params), which refuses its "
                         f"parameters ({_one_line(exc)})") from None
    attrs = {"family": family, "dtype": dtype,
             "info": _info_text(getattr(model, "info", None) or {}, f"{what}'s info")}
    datasets = {f"params/{k}": (v.ravel(), {"shape": np.array(v.shape, dtype=np.int64)})
                for k, v in stored.items()}
    return _Part(attrs, {"params": {}}, datasets)


def _check_range(arrays: Any, dtype: str, what: str) -> None:
    top = float(np.finfo(dtype).max)
    worst = max((float(np.max(np.abs(a), initial=0.0)) for a in arrays), default=0.0)
    if not math.isfinite(worst):
        raise ValueError(f"{what} holds non-finite values; only finite numbers can be saved")
    if worst > top:
        raise ValueError(f"dtype {dtype!r} cannot hold the values of {what} up to "
                         f"{worst:.6g} (its largest finite value is {top:.6g}); use a wider "
                         "dtype")


def _info_text(info: Any, what: str) -> str:
    if not isinstance(info, Mapping):
        warnings.warn(f"{what} is a {type(info).__name__}, not a dict: not saved", UserWarning,
                      stacklevel=4)
        return "{}"
    dropped: list[str] = []
    encoded = _encode_lenient(info, "", dropped)
    if dropped:
        warnings.warn(f"{what}: entries {', '.join(dropped)} are not numbers, strings, None, "
                      "lists, tuples, dicts or numeric arrays and were not saved",
                      UserWarning, stacklevel=4)
    return json.dumps(encoded, allow_nan=False)


def _encode_lenient(obj: Mapping, prefix: str, dropped: list[str]) -> dict[str, Any]:
    out = {}
    for k, v in obj.items():
        where = f"{prefix}[{k!r}]"
        if not isinstance(k, str):
            dropped.append(where)
            continue
        try:
            out[k] = _encode(v)
        except (TypeError, ValueError, RecursionError):
            if isinstance(v, Mapping):
                out[k] = _encode_lenient(v, where, dropped)
            else:
                dropped.append(where)
    return out


def _encode(obj: Any) -> Any:
    """JSON-able form of an info value (arrays, tuples, numpy scalars, non-finite floats)."""
    if isinstance(obj, dict):
        if not all(isinstance(k, str) for k in obj):
            raise TypeError("info keys must be strings")
        return {k: _encode(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in "biuf":
            raise TypeError(f"info arrays must be numeric, got dtype {obj.dtype}")
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
    raise TypeError(f"cannot store a {type(obj).__name__}")


def _packed(cm: CoefficientMatrix) -> dict[str, NDArray[np.float64]]:
    """Upper triangles, (channels, k (k + 1) / 2), of each block or of the dense matrix.

    A general matrix (``cm.reciprocal`` False): the whole blocks, (channels, k^2), row by row.
    """
    def pack(blk: NDArray) -> NDArray:
        if not cm.reciprocal:
            return np.ascontiguousarray(blk.reshape(blk.shape[0], -1))
        iu = np.triu_indices(blk.shape[-1])
        return np.ascontiguousarray(blk[:, iu[0], iu[1]])

    if cm.is_isotropic:
        return {f"m{m}": pack(blk) for m, blk in enumerate(cm.stored)}
    return {"matrix": pack(cm.stored[0])}


# -- reading ----------------------------------------------------------------------------------
class _Refused(ValueError):
    """A complete message about a file, raised by the reader (load re-raises it as is)."""


def _block_sizes(kind: str, order: int) -> list[int]:
    """k_m, the functions of azimuthal order +m, m = 0..top, in closed form (no basis built).

    Spherical harmonics: degrees l = m..N; odd hemisphere harmonics: l + m odd, m < l <= N;
    even ones and Zernike polynomials: n + m even, m <= n <= N.
    """
    if kind == "sh":
        return [order - m + 1 for m in range(order + 1)]
    if kind == "harmonics":
        return [(order - 1 - m) // 2 + 1 for m in range(order)]
    return [(order - m) // 2 + 1 for m in range(order + 1)]


class _Reader:
    """Validating reader of one open file; every problem raises :class:`_Refused`."""

    def __init__(self, f: h5py.File, name: str, size: int) -> None:
        self.f, self.name, self.size = f, name, size

    # -- messages ---------------------------------------------------------------------------
    def damaged(self, what: str) -> NoReturn:
        raise _Refused(f"{self.name} is damaged: {what} (restore it or write it again with "
                       "compress.save)")

    def refuse(self, what: str) -> NoReturn:
        raise _Refused(f"{self.name} is refused: {what}")

    # -- entry ------------------------------------------------------------------------------
    def read(self) -> Any:
        f = self.f
        fmt = self.attr(f, "format", required=False)
        if not (isinstance(fmt, str) and fmt == FORMAT):
            shown = ("no format attribute" if fmt is None else "format attribute "
                     + (repr(fmt[:80]) if isinstance(fmt, str) else _kind(fmt)))
            raise _Refused(f"{self.name} is an HDF5 file but not a scatmodes file ({shown}, "
                           f"expected {FORMAT!r})")
        version = self.attr(f, "schema_version")
        reader = None
        if isinstance(version, int | np.integer) and not isinstance(version, bool | np.bool_):
            reader = _READERS.get(int(version))
        if reader is None:
            shown = str(int(version)) if isinstance(version, int | np.integer) else _kind(version)
            raise _Refused(f"{self.name} has schema version {shown}; this library "
                           f"(scatmodes {_version()}) reads schema versions "
                           f"{', '.join(map(str, READABLE_VERSIONS))}: upgrade scatmodes to "
                           "read it")
        self.self_contained()
        return reader(self)

    # -- attributes -------------------------------------------------------------------------
    def attr(self, obj: Any, key: str, *, required: bool = True) -> Any:
        where = f"{obj.name.rstrip('/')}/@{key}"
        try:
            if key not in obj.attrs:
                if not required:
                    return None
                self.damaged(f"the attribute {where} is missing")
            v = obj.attrs[key]
        except _LOW_LEVEL as exc:
            if isinstance(exc, _Refused):
                raise
            self.damaged(f"the attribute {where} cannot be read ({_one_line(exc)})")
        if isinstance(v, bytes):
            v = v.decode(errors="surrogateescape")
        if isinstance(v, str):
            try:
                v.encode()
            except UnicodeEncodeError:  # h5py's surrogate escapes of undecodable bytes
                self.damaged(f"the attribute {where} is not UTF-8 text")
        if isinstance(v, np.ndarray) and v.shape == () and v.dtype.kind in "biuf":
            v = v[()]
        return v

    def text(self, obj: Any, key: str, choices: tuple[str, ...] | None = None) -> str:
        v = self.attr(obj, key)
        where = f"{obj.name.rstrip('/')}/@{key}"
        if not isinstance(v, str):
            self.damaged(f"the attribute {where} must be a string, got {_kind(v)}")
        if choices is not None and v not in choices:
            self.damaged(f"the attribute {where} is {v[:80]!r}, expected one of "
                         f"{', '.join(map(repr, choices))}")
        return v

    def integer(self, obj: Any, key: str, low: int, high: int | None = None) -> int:
        v = self.attr(obj, key)
        where = f"{obj.name.rstrip('/')}/@{key}"
        if isinstance(v, bool | np.bool_) or not isinstance(v, int | np.integer):
            self.damaged(f"the attribute {where} must be an integer, got {_kind(v)}")
        v = int(v)
        if v < low or (high is not None and v > high):
            self.damaged(f"the attribute {where} is {v}, expected "
                         + (f">= {low}" if high is None else f"{low}..{high}"))
        return v

    def flag(self, obj: Any, key: str) -> bool:
        v = self.attr(obj, key)
        if isinstance(v, bool | np.bool_) or (isinstance(v, int | np.integer) and v in (0, 1)):
            return bool(v)
        self.damaged(f"the attribute {obj.name.rstrip('/')}/@{key} must be a boolean, got "
                     f"{_kind(v)}")

    def info(self, obj: Any) -> dict[str, Any]:
        where = f"{obj.name.rstrip('/')}/@info"
        text = self.text(obj, "info")
        try:
            out = _decode(json.loads(text))
        except (ValueError, TypeError, KeyError, RecursionError, OverflowError) as exc:
            self.damaged(f"the attribute {where} is not valid info JSON ({_one_line(exc)})")
        if not isinstance(out, dict):
            self.damaged(f"the attribute {where} must hold a JSON object, got "
                         f"{type(out).__name__}")
        return out

    def dtype(self, obj: Any, *, required: bool = True) -> np.dtype | None:
        if not required and self.attr(obj, "dtype", required=False) is None:
            return None
        return np.dtype(self.text(obj, "dtype", DTYPES))

    # -- links, groups, datasets ------------------------------------------------------------
    def links(self, g: h5py.Group, where: str) -> list[str]:
        """Names in ``g``, refusing soft, external and user-defined links."""
        try:
            return check_links(g)
        except Indirection as exc:
            self.refuse(str(exc))
        except _LOW_LEVEL as exc:
            self.damaged(f"the members of {where} cannot be listed ({_one_line(exc)})")

    def self_contained(self) -> None:
        """Refuse every indirection of :mod:`project.hdf5` anywhere in the file."""
        try:
            check_self_contained(self.f, filters=None)  # filters: see dataset
        except Indirection as exc:
            self.refuse(str(exc))

    def group(self, g: h5py.Group, key: str) -> h5py.Group:
        obj = self.member(g, key)
        if not isinstance(obj, h5py.Group):
            self.damaged(f"{obj.name} must be a group, got {_kind(obj)}")
        self.links(obj, obj.name)
        return obj

    def member(self, g: h5py.Group, key: str) -> Any:
        path = f"{g.name.rstrip('/')}/{key}"
        try:
            if key not in g:
                self.damaged(f"{path} is missing")
            return g[key]
        except _LOW_LEVEL as exc:
            if isinstance(exc, _Refused):
                raise
            self.damaged(f"{path} cannot be opened ({_one_line(exc)})")

    def dataset(self, g: h5py.Group, key: str, shape: tuple[int, ...],
                dtype: np.dtype | None) -> NDArray[np.float64]:
        """Check a dataset from its metadata, then read it as float64, all finite."""
        d = self.member(g, key)
        path = f"{g.name.rstrip('/')}/{key}"
        if not isinstance(d, h5py.Dataset):
            self.damaged(f"{path} must be a dataset, got {_kind(d)}")
        try:
            check_dataset(d, filters=None)  # the filters: below
        except Indirection as exc:
            self.refuse(str(exc))
        plist = d.id.get_create_plist()
        filters = [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]
        if any(x != h5py.h5z.FILTER_FLETCHER32 for x in filters):
            self.damaged(f"{path} uses HDF5 filters {filters}; scatmodes stores numbers "
                         "uncompressed, with at most a Fletcher-32 checksum")
        if d.dtype.kind != "f" or (dtype is not None and d.dtype.itemsize != dtype.itemsize):
            want = "floating point" if dtype is None else str(dtype)
            self.damaged(f"{path} holds {d.dtype}, expected {want}")
        if d.shape != shape:
            self.damaged(f"{path} has shape {d.shape}, the schema needs {shape}")
        nbytes = d.size * d.dtype.itemsize
        if nbytes > self.size or d.id.get_storage_size() < nbytes:
            self.damaged(f"{path} should hold {nbytes} bytes but the file stores "
                         f"{d.id.get_storage_size()} of them")
        try:
            data = np.asarray(d[()], dtype=np.float64)
        except (OSError, RuntimeError) as exc:
            checksum = " (its Fletcher-32 checksum does not match: the bytes changed on disk)"
            self.damaged(f"{path} cannot be read{checksum if d.fletcher32 else ''}: "
                         f"{_one_line(exc)}")
        bad = int(np.count_nonzero(~np.isfinite(data)))
        if bad:
            self.damaged(f"{path} holds {bad} non-finite value(s) (nan or inf)")
        return data

    def bounded(self, arrays: list[NDArray], what: str) -> None:
        """Refuse values whose sum of squares overflows (the L2 norm they represent)."""
        with np.errstate(over="ignore"):
            total = sum(float(np.sum(np.square(a))) for a in arrays)
        if not math.isfinite(4.0 * total):
            top = max(float(np.max(np.abs(a), initial=0.0)) for a in arrays)
            self.damaged(f"{what} reach {top:.3g}, so large that their sum of squares "
                         "overflows (evaluations would be infinite)")

    # -- content ----------------------------------------------------------------------------
    def matrix(self, g: h5py.Group, kind: str, dtype: np.dtype | None, *,
               general: bool = False) -> CoefficientMatrix:
        """Read a matrix group; ``general``: the schema has the ``reciprocal`` attribute."""
        where = g.name
        if kind not in basis.KINDS:
            self.damaged(f"{where.rstrip('/')}/@basis_kind names an unknown basis kind "
                         f"{kind!r} (known: {', '.join(map(repr, basis.KINDS))})")
        order = self.integer(g, "basis_order", _MIN_ORDER.get(kind, 0), _MAX_ORDER[kind])
        quantity = self.text(g, "quantity", basis.QUANTITIES)
        channels = self.integer(g, "channels", 1)
        scalar = self.flag(g, "scalar")
        storage = self.text(g, "storage", ("isotropic", "dense"))
        reciprocal = self.flag(g, "reciprocal") if general else True
        if scalar and channels != 1:
            self.damaged(f"the matrix in {where} is marked scalar (no channel axis) but holds "
                         f"{channels} channels")
        info = self.info(g)
        sizes = _block_sizes(kind, order)
        size = sum(sizes) + sum(sizes[1:])  # every m > 0 has cos and sin functions
        if storage == "isotropic":
            packed = [k * (k + 1) // 2 if reciprocal else k * k for k in sizes]
        else:
            packed = [size * (size + 1) // 2 if reciprocal else size * size]
        need = channels * sum(packed) * (8 if dtype is None else dtype.itemsize)
        if need > self.size:
            self.damaged(f"it claims a {kind} basis of order {order} with {channels} "
                         f"channel(s) ({storage}), {need} bytes of coefficients, but the file "
                         f"has only {self.size} bytes")
        if storage == "dense":
            data = self.dataset(g, "matrix", (channels, packed[0]), dtype)
            self.bounded([data], f"the coefficients in {where}")
            m = _unpack(data, size, channels, reciprocal)
            b = basis.make_basis(kind, order)
            return self.build(lambda: CoefficientMatrix(b, m[0] if scalar else m, quantity,
                                                         isotropic=False, info=info,
                                                         reciprocal=reciprocal))
        blocks_g = self.group(g, "blocks")
        claimed = self.attr(blocks_g, "sizes", required=False)
        if claimed is not None and not (isinstance(claimed, np.ndarray)
                                        and claimed.shape == (len(sizes),)
                                        and np.array_equal(claimed, sizes)):
            self.damaged(f"{blocks_g.name}/@sizes is {_kind(claimed)}, {kind} order {order} "
                         f"has the block sizes {sizes[:10]}{'...' if len(sizes) > 10 else ''}")
        names = set(blocks_g)
        want = {f"m{m}" for m in range(len(sizes))}
        if names != want:
            extra, missing = sorted(names - want), sorted(want - names)
            self.damaged(f"{blocks_g.name} should hold datasets m0..m{len(sizes) - 1} for "
                         f"{kind} order {order}"
                         + (f"; missing {', '.join(missing[:5])}" if missing else "")
                         + (f"; unexpected {', '.join(extra[:5])}" if extra else ""))
        datas = [self.dataset(blocks_g, f"m{m}", (channels, n), dtype)
                 for m, n in enumerate(packed)]
        self.bounded(datas, f"the coefficients in {where}")
        blocks = [_unpack(x, k, channels, reciprocal) for x, k in zip(datas, sizes, strict=True)]
        b = basis.make_basis(kind, order)
        return self.build(lambda: CoefficientMatrix.from_blocks(
            b, [x[0] if scalar else x for x in blocks], quantity, info=info,
            reciprocal=reciprocal))

    def model(self, g: h5py.Group) -> Any:
        from project.fitting import FAMILIES, FittedModel

        where = g.name
        family = self.text(g, "family")
        if family not in FAMILIES:
            self.damaged(f"{where.rstrip('/')}/@family is {family[:80]!r}, which this library "
                         f"does not know (families: {', '.join(map(repr, FAMILIES))}); a "
                         "newer scatmodes may read it")
        dtype = self.dtype(g)
        info = self.info(g)
        pg = self.group(g, "params")
        names = sorted(pg)
        if len(names) > _MAX_PARAMS:
            self.damaged(f"{pg.name} holds {len(names)} parameters, a model has at most "
                         f"{_MAX_PARAMS}")
        params = {}
        for key in names:
            d = self.member(pg, key)
            if not isinstance(d, h5py.Dataset):
                self.damaged(f"{pg.name}/{key} must be a dataset, got {_kind(d)}")
            shape = self.attr(d, "shape")
            if not (isinstance(shape, np.ndarray) and shape.ndim == 1
                    and shape.dtype.kind in "iu" and shape.size <= _MAX_PARAM_NDIM
                    and np.all(shape >= 0)):
                self.damaged(f"{pg.name}/{key}/@shape must be at most {_MAX_PARAM_NDIM} "
                             f"integers >= 0, got {_kind(shape)}")
            shape = tuple(int(n) for n in shape)
            count = math.prod(shape)
            if count * dtype.itemsize > self.size:
                self.damaged(f"{pg.name}/{key} claims shape {shape}, more numbers than the "
                             "file can hold")
            params[key] = self.dataset(pg, key, (count,), dtype).reshape(shape)
        self.bounded(list(params.values()), f"the parameters in {where}")
        return self.build(lambda: FittedModel(family, params, info=info))

    def build(self, make: Any) -> Any:
        try:
            return make()
        except (ValueError, TypeError) as exc:
            self.damaged(f"its content is inconsistent: {_one_line(exc)}")


def _read_v1(r: _Reader) -> CoefficientMatrix:
    f = r.f
    kind = r.text(f, "basis_kind")
    if kind == "hemi_sh":
        parity = r.attr(f, "basis_parity")
        kind = {"odd": "harmonics", "even": "harmonics-even"}.get(
            parity if isinstance(parity, str) else "")
        if kind is None:
            r.damaged(f"basis_parity {parity!r} of hemisphere harmonics is neither 'odd' nor "
                      "'even'")
    return r.matrix(f, kind, r.dtype(f, required=False))


def _read_v2(r: _Reader) -> CoefficientMatrix:
    return r.matrix(r.f, r.text(r.f, "basis_kind"), r.dtype(r.f))


def _read_v3(r: _Reader, *, general: bool = False) -> Any:
    from .hybrid import Hybrid

    f = r.f
    content = r.text(f, "content", CONTENTS)
    r.dtype(f)
    if content == "coefficients":
        return r.matrix(f, r.text(f, "basis_kind"), r.dtype(f), general=general)
    if content == "model":
        return r.model(f)
    info = r.info(f)
    lobe = r.model(r.group(f, "lobe"))
    res_g = r.group(f, "residual")
    residual = r.matrix(res_g, r.text(res_g, "basis_kind"), r.dtype(res_g), general=general)
    return r.build(lambda: Hybrid(lobe, residual, info))


def _read_v4(r: _Reader) -> Any:
    return _read_v3(r, general=True)


_READERS = {1: _read_v1, 2: _read_v2, 3: _read_v3, 4: _read_v4, 5: _read_v4, 6: _read_v4}
#: Schema versions :func:`load` understands.
READABLE_VERSIONS = tuple(sorted(_READERS))


# -- helpers ----------------------------------------------------------------------------------
def _version() -> str:
    try:
        from importlib.metadata import version

        return version("scatmodes")
    except Exception:  # noqa: BLE001 - not installed: still write a file
        return "unknown"


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:300] or type(exc).__name__


def _kind(v: Any) -> str:
    """Short description of an unexpected value for messages."""
    if isinstance(v, np.ndarray):
        return f"an array of {v.dtype} with shape {v.shape}"
    if isinstance(v, h5py.Group | h5py.Dataset):
        return f"a {type(v).__name__.lower()}"
    text = repr(v.item() if isinstance(v, np.generic) else v)
    return f"{type(v).__name__} {text[:60]}{'...' if len(text) > 60 else ''}"


def _unpack(data: NDArray, k: int, channels: int, reciprocal: bool = True
            ) -> NDArray[np.float64]:
    if not reciprocal:
        return np.array(data, dtype=np.float64).reshape(channels, k, k)
    out = np.zeros((channels, k, k))
    iu = np.triu_indices(k)
    out[:, iu[0], iu[1]] = data
    out[:, iu[1], iu[0]] = data
    return out


def _decode(obj: Any) -> Any:
    """Inverse of :func:`_encode`; ValueError on malformed tags."""
    if isinstance(obj, dict):
        if "__ndarray__" in obj:
            flat, dt, shape = obj["__ndarray__"], np.dtype(obj["dtype"]), obj["shape"]
            if (not isinstance(flat, list) or dt.kind not in "biuf" or not isinstance(shape, list)
                    or not all(isinstance(n, int) and n >= 0 for n in shape)
                    or math.prod(shape) != len(flat)):
                raise ValueError("malformed __ndarray__ tag")
            return np.array([_decode(x) for x in flat], dtype=dt).reshape(shape)
        if "__tuple__" in obj:
            if not isinstance(obj["__tuple__"], list):
                raise ValueError("malformed __tuple__ tag")
            return tuple(_decode(x) for x in obj["__tuple__"])
        if "__float__" in obj:
            if obj["__float__"] not in ("nan", "inf", "-inf"):
                raise ValueError(f"malformed __float__ tag {obj['__float__']!r}")
            return float(obj["__float__"])
        return {k: _decode(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_decode(x) for x in obj]
    return obj
