"""Reading the inputs of the report, and naming what an input is.

:func:`read_source` tells a file's kind by its first bytes (and the ``.binary`` suffix);
``_kind`` and ``_describe`` name an object in a few words for the page.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import project
from basis import CoefficientMatrix

from ..hybrid import Hybrid
from ._html import _short

_KINDS_READ = ("a file of compress.save (.h5: coefficient matrix, fitted model or hybrid), a "
               "MERL .binary table, an RGL-EPFL .bsdf file, an MDL .mbsdf file or a "
               "measurement table (text, CSV or Cornell .brdf)")


def read_source(path: str | os.PathLike) -> Any:
    """Read any input of :func:`report` from a file.

    Parameters
    ----------
    path : str or os.PathLike
        A file of :func:`compress.save` (HDF5), a MERL ``.binary`` table
        (:func:`project.measured.read_merl`), an RGL-EPFL ``.bsdf`` tensor file
        (:func:`project.measured.read_rgl`), an NVIDIA MDL ``.mbsdf`` file
        (:func:`project.measured.read_mbsdf`) or a measurement table
        (:func:`project.measured.read_measurements`), told apart by their first bytes and
        the ``.binary`` suffix.

    Returns
    -------
    basis.CoefficientMatrix, project.FittedModel, compress.Hybrid, BRDF or
    project.Measurements

    Raises
    ------
    FileNotFoundError, IsADirectoryError
        The file is missing, or is a folder.
    ValueError
        The file is none of these, or is damaged (the message names it and says why).
    """
    from project.measured import read_mbsdf, read_measurements, read_merl, read_rgl

    from ..store import file_kind, load

    p = Path(os.fspath(path))
    kind = file_kind(p)
    if kind == "checkpoint":
        raise ValueError(f"{str(p)!r} is a simulation checkpoint, not a representation: "
                         "finish the run (scatmodes simulate --resume) and report the "
                         ".h5 file it writes")
    if kind == "representation":
        return load(p)
    if kind == "rgl":
        return read_rgl(p)
    if kind == "merl":
        return read_merl(p)
    if kind == "mbsdf":
        return read_mbsdf(p)
    try:
        return read_measurements(p)
    except ValueError as exc:
        raise ValueError(f"{str(p)!r} is not {_KINDS_READ}; read as a measurement table: "
                         f"{' '.join(str(exc).split())}") from None


def _header(p: Path) -> list[tuple[str, str]]:
    """Rows of the root attributes of a file of compress.save (empty for other files)."""
    import h5py

    try:
        with h5py.File(p, "r") as f:
            a = {k: a for k, a in f.attrs.items()
                 if k in ("schema_version", "library", "content", "dtype")}
    except OSError:
        return []
    return [(f"file {k}", v.decode(errors="replace") if isinstance(v, bytes) else str(v))
            for k, v in a.items()]


def _kind(obj: Any) -> str:
    if isinstance(obj, project.Measurements):
        return "measurements"
    if isinstance(obj, CoefficientMatrix):
        return "coefficient matrix"
    if isinstance(obj, Hybrid):
        return "hybrid"
    if hasattr(obj, "family") and hasattr(obj, "params"):
        return "fitted model"
    if callable(getattr(obj, "eval", None)):
        name = type(obj).__name__
        return {"MERLBRDF": "measured BRDF (MERL table)",
                "RGLBRDF": "measured BRDF (RGL-EPFL tensor file)"}.get(name, f"BRDF ({name})")
    raise TypeError(f"rep must be a coefficient matrix, a fitted model, a hybrid, a BRDF "
                    f"(an object with eval(wi, wo)), project.Measurements or the path of a "
                    f"file holding one, got {type(obj).__name__}")


def _describe(obj: Any, kind: str) -> str:
    """Name an object in a few words: its name, basis or family, else its kind."""
    name = getattr(obj, "name", None)
    if isinstance(name, str) and name:
        return f"{name} ({kind})"
    if isinstance(obj, CoefficientMatrix):
        return f"{obj.basis!r} coefficient matrix"
    if isinstance(obj, Hybrid):
        return f"hybrid: {getattr(obj.lobe, 'family', 'lobe')} + {obj.residual.basis!r}"
    if hasattr(obj, "family"):
        return f"fitted model {obj.family}"
    return _short(repr(obj), 80) if kind.startswith("BRDF") else kind
