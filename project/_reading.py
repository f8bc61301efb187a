"""Checks shared by the readers of files: regular files only, numbers in ASCII digits."""

from __future__ import annotations

import os
import re
import stat

#: A number as C's strtod reads it in a data file: ASCII digits only (Python's float() would
#: also take "1_5" as 15 and other scripts' digits, such as the Arabic-Indic "\u0661");
#: inf and nan are matched, for the caller to refuse as not finite.
NUMBER = re.compile(r"[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?"
                    r"|inf|infinity|nan)", re.ASCII | re.IGNORECASE)

_NOT_REGULAR = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
                (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def number(cell: str) -> float:
    """Return ``float(cell)`` if :data:`NUMBER` matches all of ``cell``, else raise ValueError.

    ``cell`` is expected stripped of surrounding whitespace. The message reads "must be a
    number, got ...", to follow the name of what was read (e.g. "cell"), and says what is
    wrong with a cell that ``float`` would have read.

    Examples
    --------
    >>> number("-1.5e3"), number("inf")
    (-1500.0, inf)
    >>> number("1_5")
    Traceback (most recent call last):
    ...
    ValueError: must be a number, got '1_5' (ASCII digits only, no '_' between them)
    """
    if not NUMBER.fullmatch(cell):
        try:
            float(cell)
        except ValueError:
            raise ValueError(f"must be a number, got {cell!r}") from None
        raise ValueError(f"must be a number, got {cell!r} (ASCII digits only, no '_' between "
                         "them)")
    return float(cell)


def regular_file(path: str | os.PathLike, what: str = "file") -> None:
    """Refuse, before opening it, a path that is not a regular file (or a link to one).

    Opening a FIFO for reading blocks until a writer appears, and a device may never end:
    readers of a path call this first.

    Parameters
    ----------
    path : str or os.PathLike
    what : str
        How the message names the file, e.g. ``"RGL file"``.

    Raises
    ------
    FileNotFoundError
        The path does not exist (from :func:`os.stat`).
    IsADirectoryError
        It is a directory.
    ValueError
        It is a FIFO, a device or a socket.
    """
    name = repr(os.fspath(path))
    mode = os.stat(path).st_mode
    if stat.S_ISREG(mode):
        return
    if stat.S_ISDIR(mode):
        raise IsADirectoryError(f"{what} {name} must be a file, got a directory")
    kind = next((k for test, k in _NOT_REGULAR if test(mode)), "not a regular file")
    raise ValueError(f"{what} {name} must be a regular file, got {kind}: give the path of "
                     "a file on disk")
