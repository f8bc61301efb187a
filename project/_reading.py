"""Checks shared by the readers of files: numbers in ASCII digits."""

from __future__ import annotations

import re

#: A number as C's strtod reads it in a data file: ASCII digits only (Python's float() would
#: also take "1_5" as 15 and other scripts' digits, such as the Arabic-Indic "\u0661");
#: inf and nan are matched, for the caller to refuse as not finite.
NUMBER = re.compile(r"[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?"
                    r"|inf|infinity|nan)", re.ASCII | re.IGNORECASE)


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
