"""Paths of the measured-data readers and writers: one set of checks and messages."""

from __future__ import annotations

import os
from pathlib import Path

from .._reading import regular_file


def as_path(path: object, name: str = "path") -> Path:
    """Return ``path`` as a Path; TypeError for anything that is not str or os.PathLike."""
    try:
        return Path(os.fspath(path))  # type: ignore[arg-type]
    except TypeError:
        raise TypeError(f"{name} must be a str or os.PathLike, got {type(path).__name__}") \
            from None


def input_file(path: object, kind: str, what: str | None = None) -> Path:
    """Return the path of an existing file of ``kind`` (e.g. "MERL"), or raise naming it.

    ValueError for a FIFO, a device or a socket: opening one could block forever.
    """
    p = as_path(path)
    if not p.exists():
        raise FileNotFoundError(f"{kind} file {str(p)!r} does not exist")
    if p.is_dir():
        raise IsADirectoryError(f"path must be {what or f'a {kind} file'}, got the directory "
                                f"{str(p)!r}")
    regular_file(p, f"{kind} file")
    return p


def output_file(path: object) -> Path:
    """Return the path of a file to write: not a directory, in a directory that exists."""
    p = as_path(path)
    if p.is_dir():
        raise IsADirectoryError(f"path must be a file name, got the directory {str(p)!r}")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise FileNotFoundError(f"the directory of {str(p)!r} does not exist; create it first")
    return p
