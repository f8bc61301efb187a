"""Scattered measurements in text files: plain tables, CSV and the Cornell format.

:func:`read_measurements` returns a :class:`project.Measurements`; :func:`write_measurements`
writes one in any of the formats, so that reading it back gives the same numbers.

Notes
-----
**Formats.**

- ``"table"``: the text table of :func:`project.read_table` (theta_i, phi_i, theta_o, phi_o
  in degrees, then 1 or 3 value columns; '#' comments; commas or whitespace). Read by
  :func:`project.read_table` itself.
- ``"csv"``: a header row of column names, then one row per sample, separated by commas
  (or semicolons, or tabs, or whitespace: whichever the header uses, in that order). Angle
  columns are found by name, case-insensitive: ``theta_i``/``phi_i`` and the aliases
  ``theta_in``, ``theta_inc``, ``theta_incident`` for the incident direction, ``theta_o``,
  ``theta_out``, ``theta_r`` (reflected), ``theta_s`` (scattered), ``theta_v`` (view) for
  the outgoing one (likewise phi; the underscore may be a space, a hyphen or nothing). A
  unit may follow the name: ``theta_i_deg``, ``theta_i [deg]``, ``theta_i (rad)``,
  ``theta_i degrees``... Columns without a unit take the ``angles`` argument, else the unit
  the other angle columns state, else a detected one: degrees if any such theta exceeds
  pi/2, radians otherwise (``info["angles_from"]`` says which applied, and a unit stated
  twice in contradiction is refused). An optional ``weight`` (or ``weights``) column gives
  the weights; every other column whose first row is numeric is a channel, and other
  columns are ignored (listed in ``info["ignored_columns"]``). When every channel is named
  like a wavelength (``450``, ``450nm``, ``450 nm``, ``wl_450``, ``lambda_450``; a number
  of at least :data:`MIN_WAVELENGTH` = 100 nm), the names give ``wavelengths``
  (increasing); otherwise they are the channel names. Leading
  '#' lines are comments; ``# name: ...`` and ``# isotropic: true|false`` there set the
  name and the stated isotropy.
- ``"cornell"``: the irregular isotropic format of the Cornell Program of Computer Graphics
  measurements that pbrt-v2 reads for ``.brdf`` files (``src/materials/measured.cpp``:
  ``ReadFloatFile`` then the layout below). '#' starts a comment to the end of the line;
  the rest is whitespace-separated numbers: the wavelength count W, the W wavelengths in
  nm, then rows of 4 + W numbers: theta_i, phi_i, theta_o, phi_o in radians (the files'
  header comment calls the outgoing pair "theta s, phi_s") and the W values. pbrt-v2 maps
  the angles with ``SphericalDirection(sin theta, cos theta, phi)``, our
  :func:`basis.from_angles`. The data are isotropic by definition (``isotropic=True``).
  Comment lines other than the format's own labels are kept in ``info["description"]``.

**The Cornell files.** The five files distributed with pbrt-v2's scenes (``acryl_blue``,
``cayman``, ``garnet_red``, ``krylon_blue``, ``mystique``) each hold 31 wavelengths
(400-700 nm in 10 nm steps) and 1,439 samples: 8 incidence angles theta_i = 10, 20, ...,
80 degrees, all at phi_i = 0; theta_o from 0 to 79.05 degrees; phi_o in [-175, 180]
degrees, signed (both sides of the plane of incidence); values 0 to 30 (acryl_blue) up to
655 1/sr (mystique), none negative, 0.5 % to 42 % exactly 0. No direction pair repeats, and
none is the reciprocal of another, even up to isotropy (no theta_o equals a theta_i).
Angles are printed with 6 decimals, so theta_i = 80 degrees reads 79.999977 degrees.

**Numbers** are read as C's ``strtod`` reads them, in ASCII digits: Python's ``float``
would also take ``1_5`` (as 15) and other scripts' digits, which are refused here (as by
the OBJ reader of :mod:`project.microgeometry`). A UTF-8 byte-order mark is skipped in
every format.

**Errors** name the file, the line and, for a cell, the column (1-based); missing files
raise FileNotFoundError, directories IsADirectoryError, and a FIFO or a device (which
could block the reader forever) ValueError.

**Writing** uses ``repr`` of each float (the shortest string that reads back to the same
double), so values, weights and wavelengths read back bit for bit, and the angles written
too; the directions are rebuilt from the angles, within a few ulp of the original ones.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from basis import from_angles
from basis.validation import choice

from .._reading import number
from ..io import atomic_path
from ..lstsq import read_table
from ..measurements import Measurements
from ._files import input_file, output_file

__all__ = ["ANGLE_UNITS", "MEASUREMENT_FORMATS", "MIN_WAVELENGTH", "read_measurements",
           "write_measurements"]

#: Formats of :func:`read_measurements` and :func:`write_measurements`.
MEASUREMENT_FORMATS = ("table", "csv", "cornell")
#: Smallest number (nm) a CSV column name may state as a wavelength: smaller numbers
#: ("0", "1", ...) are channel names.
MIN_WAVELENGTH = 100.0
#: Values of the ``angles`` argument of :func:`read_measurements`.
ANGLE_UNITS = ("degrees", "radians")

_IN = ("i", "in", "inc", "incident")
_OUT = ("o", "out", "r", "s", "v")
_ANGLE = re.compile(r"^(theta|phi)[_\s-]*(" + "|".join(_IN + _OUT) + r")$")
_UNIT_WORDS = {"deg": "degrees", "degs": "degrees", "degree": "degrees", "degrees": "degrees",
               "rad": "radians", "rads": "radians", "radian": "radians", "radians": "radians"}
_UNIT = re.compile(r"^(?P<base>.+?)[\s_-]*(?:[\[(]\s*(?P<u1>[a-z]+)\s*[\])]|[\s_-](?P<u2>"
                   + "|".join(_UNIT_WORDS) + r"))$")
_WAVELENGTH = re.compile(r"^(?:(?:wl|lambda|wavelength)[\s_-]*)?(\d+(?:\.\d*)?)\s*(?:nm)?$",
                         re.ASCII)
_CORNELL_LABELS = re.compile(r"^(num\s+wls|wls|theta\s+i\b.*)$", re.IGNORECASE)
_COLUMNS = ("theta_i", "phi_i", "theta_o", "phi_o")


class _Text:
    """A text file's lines (decoded as UTF-8) and the file name for messages."""

    def __init__(self, path: Path) -> None:
        self.path = path
        raw = path.read_bytes()
        try:
            text = raw.decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            line = raw[:exc.start].count(b"\n") + 1
            col = exc.start - (raw.rfind(b"\n", 0, exc.start) + 1) + 1
            raise ValueError(f"{self.where(line)}, byte {col}: the file must be UTF-8 text, "
                             f"got byte 0x{raw[exc.start]:02x}") from None
        self.lines = text.splitlines()

    def where(self, line: int, column: int | None = None) -> str:
        out = f"{str(self.path)!r}, line {line}"
        return out if column is None else f"{out}, column {column}"

    def error(self, line: int, message: str, column: int | None = None) -> ValueError:
        return ValueError(f"{self.where(line, column)}: {message}")


def _number(text: _Text, cell: str, line: int, column: int) -> float:
    try:
        x = number(cell)  # float() would also read "1_5" as 15, and non-ASCII digits
    except ValueError as exc:
        raise text.error(line, f"cell {exc}", column) from None
    if not math.isfinite(x):
        raise text.error(line, f"cell must be finite, got {cell!r}", column)
    return x


# -- reading -----------------------------------------------------------------------------------
def read_measurements(path: str | os.PathLike, format: str | None = None, *,
                      angles: str | None = None) -> Measurements:
    r"""Read scattered BRDF measurements from a text file.

    Parameters
    ----------
    path : str or os.PathLike
    format : {"table", "csv", "cornell"}, optional
        The layout (module notes). Default: detected, by the extension (``.csv``; ``.brdf``
        whose first number stands alone on its line, the Cornell wavelength count) and
        otherwise by the content (a first number alone on its line: cornell; a first row
        with a cell that is not a number: csv; else table). ``info["format_detected"]``
        says how.
    angles : {"degrees", "radians"}, optional
        Unit of CSV angle columns whose name states none. The table format is in degrees
        and the Cornell format in radians: stating the other unit is an error.

    Returns
    -------
    Measurements
        ``name`` from a ``# name:`` comment, else the file name without its extension;
        ``source`` the path; ``info`` holds ``format``, ``format_detected``, ``angles``
        (the unit of the angle columns, or a dict per column when they differ),
        ``angles_from`` and, where present, ``description`` and ``ignored_columns``.

    Raises
    ------
    FileNotFoundError, IsADirectoryError
        The path does not exist or is a directory.
    ValueError
        Naming the file, line and column: text that is not UTF-8, a ragged row, a cell that
        is not a number (in ASCII digits), NaN or inf, theta outside [0, 90] degrees /
        [0, pi/2], missing or repeated angle columns, no value column, a Cornell wavelength
        count that does not fit the numbers that follow, a unit stated in contradiction,
        an empty file; or a path that is not a regular file (a FIFO, a device).

    Examples
    --------
    >>> import os, tempfile
    >>> text = ("theta_i [deg], phi_i [deg], theta_o [deg], phi_o [deg], 450nm, 550nm\n"
    ...         "30, 0, 45, 180, 0.25, 0.5\n"
    ...         "30, 0, 60, 90, -0.001, 0.125\n")
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     path = os.path.join(tmp, "paint.csv")
    ...     with open(path, "w") as f:
    ...         _ = f.write(text)
    ...     meas = read_measurements(path)
    >>> meas
    Measurements(name='paint', samples=2, channels=2 (450 nm, 550 nm), isotropic=None)
    >>> meas.wavelengths.tolist(), meas.values[:, 1].tolist(), meas.info["angles"]
    ([450.0, 550.0], [0.5, 0.125], 'degrees')
    """
    p = input_file(path, "measurement")
    if format is not None:
        choice(format, "format", MEASUREMENT_FORMATS)
    if angles is not None:
        choice(angles, "angles", ANGLE_UNITS)
    text = _Text(p)
    if format is None:
        format, how = _detect(text)
    else:
        how = "given"
    meta = _comment_metadata(text)
    if format == "cornell":
        if angles == "degrees":
            raise ValueError(f"{str(p)!r}: the Cornell format holds angles in radians, got "
                             "angles='degrees'")
        parts = _read_cornell(text)
    elif format == "csv":
        parts = _read_csv(text, angles)
    else:
        if angles == "radians":
            raise ValueError(f"{str(p)!r}: the table format holds angles in degrees, got "
                             "angles='radians'")
        parts = _read_table(text)
    info = {"format": format, "format_detected": how, **parts.pop("info")}
    if meta.get("description"):
        info.setdefault("description", meta["description"])
    isotropic = parts.pop("isotropic", meta.get("isotropic"))
    name = meta.get("name") or p.stem
    try:
        return Measurements(**parts, isotropic=isotropic, name=name, source=p, info=info)
    except (TypeError, ValueError) as exc:  # the readers check what they can name a line for
        raise ValueError(f"{str(p)!r}: {exc}") from None


def _data_lines(text: _Text, comment_anywhere: bool) -> list[tuple[int, str]]:
    """(line number, stripped text) of the lines that are neither blank nor comments."""
    out = []
    for i, raw in enumerate(text.lines, start=1):
        line = raw.split("#", 1)[0] if comment_anywhere else \
            ("" if raw.lstrip().startswith("#") else raw)
        line = line.strip()
        if line:
            out.append((i, line))
    return out


def _detect(text: _Text) -> tuple[str, str]:
    """Return (format, how it was detected)."""
    data = _data_lines(text, comment_anywhere=True)
    if not data:
        raise ValueError(f"{str(text.path)!r}: the file holds no data (line 1 to "
                         f"{len(text.lines)} are blank or comments)")
    first = data[0][1]
    cornell_like = _cornell_header(data)
    suffix = text.path.suffix.lower()
    if suffix == ".csv":
        return "csv", "by extension .csv"
    if cornell_like:
        where = f"extension {suffix} and content" if suffix == ".brdf" else "content"
        return "cornell", f"by {where}: a wavelength count alone on its first line"
    cells = re.split(r"[\s,;]+", first.strip(", ;"))
    # float() only tells a header from a data row here: a cell it reads ("1_5") is data,
    # which the table reader then refuses naming the line and column
    for c in cells:
        try:
            float(c)
        except ValueError:
            return "csv", f"by content: a header row (line {data[0][0]})"
    return "table", "by content: numeric rows"


def _cornell_header(data: list[tuple[int, str]]) -> bool:
    """First number a count W >= 1, alone on its line or followed by W increasing numbers."""
    first = data[0][1].split()
    try:
        w = float(first[0])
    except ValueError:
        return False
    if not (1 <= w < 1e6 and w == int(w)):  # int(inf) would raise OverflowError
        return False
    if len(first) == 1:
        return True
    tokens = " ".join(line for _, line in data).split()
    try:
        wl = [float(t) for t in tokens[1:1 + int(w)]]
    except ValueError:
        return False
    body = len(tokens) - 1 - int(w)
    return len(wl) == int(w) and all(b > a for a, b in zip(wl, wl[1:], strict=False)) and \
        body > 0 and body % (4 + int(w)) == 0


def _comment_metadata(text: _Text) -> dict[str, Any]:
    """``name``, ``isotropic`` and ``description`` from the leading comment lines."""
    out: dict[str, Any] = {}
    lines = []
    for raw in text.lines:
        s = raw.strip()
        if not s:
            continue
        if not s.startswith("#"):
            break
        body = s.lstrip("#").strip()
        key, sep, value = body.partition(":")
        key, value = key.strip().lower(), value.strip()
        if sep and key == "name" and value:
            out["name"] = value
        elif sep and key == "isotropic" and value.lower() in ("true", "false"):
            out["isotropic"] = value.lower() == "true"
        elif body and not _CORNELL_LABELS.match(body) and body != "scatmodes measurements":
            lines.append(body)
    if lines:
        out["description"] = " / ".join(lines)
    return out


def _check_theta(text: _Text, theta: NDArray, lines: list[int], unit: str, name: str,
                 column: int | None = None) -> None:
    """Refuse theta outside [0, 90] degrees or [0, pi/2] radians, naming the first row."""
    top = 90.0 if unit == "degrees" else np.pi / 2
    bad = ~((theta >= 0.0) & (theta <= top))
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        shown = "[0, 90] degrees" if unit == "degrees" else "[0, pi/2] radians"
        raise text.error(lines[r], f"{name} must lie in {shown}, got {float(theta[r])!r}", column)


def _pairs(theta_phi: NDArray, unit: str) -> tuple[NDArray, NDArray]:
    """(n, 4) theta_i, phi_i, theta_o, phi_o -> wi, wo."""
    a = np.radians(theta_phi) if unit == "degrees" else theta_phi
    return from_angles(a[:, 0], a[:, 1]), from_angles(a[:, 2], a[:, 3])


# -- table -------------------------------------------------------------------------------------
def _read_table(text: _Text) -> dict[str, Any]:
    try:
        wi, wo, values = read_table(text.path)
    except ValueError as exc:
        msg = str(exc)
        if msg.startswith(str(text.path)):
            msg = msg[len(str(text.path)):].lstrip(": ")
            raise ValueError(f"{str(text.path)!r}: {msg} (line 1 to {len(text.lines)})") \
                from None
        raise ValueError(f"{str(text.path)!r}, {msg}") from None
    return {"wi": wi, "wo": wo, "values": values,
            "info": {"angles": "degrees", "angles_from": "the table format"}}


# -- Cornell -----------------------------------------------------------------------------------
def _read_cornell(text: _Text) -> dict[str, Any]:
    tokens: list[tuple[str, int, int]] = []  # (cell, line, column)
    for i, raw in enumerate(text.lines, start=1):
        cells = raw.split("#", 1)[0].split()
        tokens.extend((c, i, j) for j, c in enumerate(cells, start=1))
    if not tokens:
        raise ValueError(f"{str(text.path)!r}: the file holds no data (line 1 to "
                         f"{len(text.lines)} are blank or comments)")
    cell, line, col = tokens[0]
    w = _number(text, cell, line, col)
    if not (w >= 1 and w == int(w)):
        raise text.error(line, f"the first number must be the wavelength count, an integer "
                               f">= 1, got {cell!r}", col)
    nw = int(w)
    if len(tokens) < 1 + nw:
        raise text.error(line, f"the wavelength count {nw} must be followed by {nw} "
                               f"wavelengths, got {len(tokens) - 1} numbers in the file")
    wl = np.array([_number(text, *t) for t in tokens[1:1 + nw]])
    for k in range(nw):
        if wl[k] <= 0 or (k and wl[k] <= wl[k - 1]):
            _, line, col = tokens[1 + k]
            raise text.error(line, f"wavelengths must be > 0 and strictly increasing (nm), got "
                                   f"{float(wl[k])!r} after "
                                   f"{float(wl[k - 1]) if k else None!r}", col)
    body = tokens[1 + nw:]
    row = 4 + nw
    if not body or len(body) % row:
        start = body[len(body) - len(body) % row][1] if body else tokens[nw][1]
        raise text.error(start, f"the wavelength count {nw} (line {tokens[0][1]}) does not fit "
                                f"the body: {len(body)} numbers after the wavelengths are not "
                                f"a positive multiple of 4 + {nw} = {row} (the last row, from "
                                "this line, is incomplete or the count is wrong)")
    a = np.array([_number(text, *t) for t in body]).reshape(-1, row)
    lines = [body[r * row][1] for r in range(a.shape[0])]
    _check_theta(text, a[:, 0], lines, "radians", "theta_i")
    _check_theta(text, a[:, 2], lines, "radians", "theta_o")
    wi, wo = _pairs(a[:, :4], "radians")
    return {"wi": wi, "wo": wo, "values": a[:, 4:], "wavelengths": wl, "isotropic": True,
            "info": {"angles": "radians", "angles_from": "the Cornell format"}}


# -- CSV ---------------------------------------------------------------------------------------
def _split(line: str, delimiter: str | None) -> list[str]:
    if delimiter is None:
        return line.split()
    return [c.strip() for c in next(csv.reader([line], delimiter=delimiter,
                                               skipinitialspace=True))]


def _column(name: str) -> tuple[str, str | None]:
    """Return (kind, unit): kind an angle column name of _COLUMNS, 'weight' or 'value'."""
    s = name.strip().lower()
    unit = None
    m = _UNIT.match(s)
    if m:
        word = m.group("u1") or m.group("u2")
        if word in _UNIT_WORDS:
            s, unit = m.group("base").strip(), _UNIT_WORDS[word]
    a = _ANGLE.match(s)
    if a:
        return f"{a.group(1)}_{'i' if a.group(2) in _IN else 'o'}", unit
    if s in ("weight", "weights"):
        return "weight", None
    return "value", None


def _read_csv(text: _Text, angles: str | None) -> dict[str, Any]:
    data = _data_lines(text, comment_anywhere=False)
    if not data:
        raise ValueError(f"{str(text.path)!r}: the file holds no data (line 1 to "
                         f"{len(text.lines)} are blank or comments)")
    hline, header = data[0]
    delim = next((d for d in (",", ";", "\t") if d in header), None)
    try:
        names = _split(header, delim)
    except csv.Error as exc:
        raise text.error(hline, f"the header row cannot be split: {exc}") from None
    kinds: dict[str, int] = {}
    units: dict[str, str | None] = {}
    values: list[int] = []
    weight = None
    for j, nm in enumerate(names):
        if not nm:
            raise text.error(hline, "every column must have a name, got an empty one", j + 1)
        kind, unit = _column(nm)
        if kind in _COLUMNS:
            if kind in kinds:
                raise text.error(hline, f"{kind} must be given once, got columns "
                                        f"{names[kinds[kind]]!r} and {nm!r}", j + 1)
            kinds[kind], units[kind] = j, unit
        elif kind == "weight":
            if weight is not None:
                raise text.error(hline, f"the weight must be given once, got columns "
                                        f"{names[weight]!r} and {nm!r}", j + 1)
            weight = j
        else:
            values.append(j)
    missing = [c for c in _COLUMNS if c not in kinds]
    if missing:
        raise text.error(hline, f"the header must name the angle columns {', '.join(_COLUMNS)}"
                                f" (or aliases, see read_measurements), missing "
                                f"{', '.join(missing)}; got {names}")
    rows = data[1:]
    if not rows:
        raise text.error(hline, "the file must hold at least one data row after the header, "
                                "got none")
    cells: list[list[str]] = []
    for line, s in rows:
        try:
            c = _split(s, delim)
        except csv.Error as exc:
            raise text.error(line, f"the row cannot be split: {exc}") from None
        if len(c) != len(names):
            raise text.error(line, f"every row must have {len(names)} cells like the header "
                                   f"(line {hline}), got {len(c)}")
        cells.append(c)
    channels, ignored = [], []
    for j in values:
        try:
            float(cells[0][j])
        except ValueError:
            ignored.append(names[j])
            continue
        channels.append(j)
    if not channels:
        raise text.error(hline, f"the file must hold at least one numeric value column besides "
                                f"the angles and the weight, got {names}")
    used = [kinds[c] for c in _COLUMNS] + channels + ([] if weight is None else [weight])
    table = np.empty((len(rows), len(used)))
    for r, ((line, _), c) in enumerate(zip(rows, cells, strict=True)):
        for k, j in enumerate(used):
            table[r, k] = _number(text, c[j], line, j + 1)
    lines = [line for line, _ in rows]
    unit_of, angles_from = _angle_units(text, hline, units, angles, table, lines)
    for k, c in ((0, "theta_i"), (2, "theta_o")):
        _check_theta(text, table[:, k], lines, unit_of[c], c, kinds[c] + 1)
    tp = table[:, :4].copy()
    for k, c in enumerate(_COLUMNS):
        if unit_of[c] == "degrees":
            tp[:, k] = np.radians(tp[:, k])
    wi, wo = _pairs(tp, "radians")
    chan = [names[j] for j in channels]
    for k, nm in enumerate(chan):
        if nm in chan[:k]:
            raise text.error(hline, f"channel names must be distinct, got {nm!r} twice",
                             channels[k] + 1)
    wl = _wavelength_columns(text, hline, chan, [j + 1 for j in channels])
    unit_set = set(unit_of.values())
    out: dict[str, Any] = {
        "wi": wi, "wo": wo, "values": table[:, 4:4 + len(channels)],
        "weights": None if weight is None else table[:, -1],
        "wavelengths": wl, "channel_names": None if wl is not None else chan,
        "info": {"angles": unit_set.pop() if len(unit_set) == 1 else dict(unit_of),
                 "angles_from": angles_from},
    }
    if weight is not None:
        bad = table[:, -1] < 0
        if bad.any():
            r = int(np.flatnonzero(bad)[0])
            raise text.error(lines[r], f"weight must be >= 0, got {float(table[r, -1])!r}",
                             weight + 1)
        if not np.any(table[:, -1] > 0):
            raise text.error(hline, "the weights must not all be zero")
    if ignored:
        out["info"]["ignored_columns"] = ignored
    return out


def _angle_units(text: _Text, hline: int, units: dict[str, str | None], angles: str | None,
                 table: NDArray, lines: list[int]) -> tuple[dict[str, str], str]:
    """Return the unit of each angle column and a sentence saying where it came from."""
    stated = {c: u for c, u in units.items() if u is not None}
    if angles is not None:
        clash = {c: u for c, u in stated.items() if u != angles}
        if clash:
            raise text.error(hline, f"angles={angles!r} contradicts the unit stated in the "
                                    f"header for {', '.join(clash)} ({set(clash.values()).pop()})")
    if len(stated) == 4:
        return dict(stated), "stated in the column names"
    if angles is not None:
        return {c: stated.get(c, angles) for c in _COLUMNS}, (
            "the angles argument" if not stated else
            "stated in the column names and the angles argument")
    kinds = set(stated.values())
    if len(kinds) == 1:
        u = kinds.pop()
        return {c: stated.get(c, u) for c in _COLUMNS}, \
            f"stated in the column names ({', '.join(stated)}), taken for the others"
    if len(kinds) > 1:
        raise text.error(hline, f"the header states both degrees and radians "
                                f"({', '.join(f'{c}: {u}' for c, u in stated.items())}); "
                                "name the unit of every angle column")
    thetas = table[:, [0, 2]]
    top = float(thetas.max())
    if top > np.pi / 2:
        r = int(np.argwhere(thetas == top)[0][0])
        return {c: "degrees" for c in _COLUMNS}, (
            f"detected: theta up to {top:g} > pi/2 (line {lines[r]}), read as degrees")
    return {c: "radians" for c in _COLUMNS}, (
        f"detected: every theta <= pi/2 (max {top:g}), read as radians; pass "
        "angles='degrees' if they are degrees")


def _wavelength_columns(text: _Text, hline: int, names: list[str],
                        columns: list[int]) -> NDArray | None:
    """Return the wavelengths if every channel name is one, else None (refuse a bad order)."""
    wl = np.array([_wavelength_of(n) for n in names])
    if np.isnan(wl).any():
        return None
    for k in range(1, wl.size):
        if wl[k] <= wl[k - 1]:
            raise text.error(hline, f"wavelength columns must be strictly increasing, got "
                                    f"{names[k - 1]!r} then {names[k]!r}", columns[k])
    return wl


def _wavelength_of(name: str) -> float:
    """Return the wavelength (nm) a column name states, or NaN if it states none."""
    m = _WAVELENGTH.match(name.strip().lower())
    x = float(m.group(1)) if m else math.nan
    return x if x >= MIN_WAVELENGTH else math.nan


# -- writing -----------------------------------------------------------------------------------
def write_measurements(path: str | os.PathLike, meas: Measurements,
                       format: str = "csv") -> Path:
    """Write measurements to a text file that :func:`read_measurements` reads back.

    The file is written beside ``path`` and renamed over it when complete
    (:func:`project.io.atomic_path`).

    Parameters
    ----------
    path : str or os.PathLike
        Target file; its directory must exist.
    meas : project.Measurements
    format : {"csv", "table", "cornell"}
        ``"csv"`` (default) keeps everything: angles in radians, one column per channel
        (named by wavelength, "450.0 nm", when there are wavelengths), the weights if any
        differs from 1, and ``# name:`` / ``# isotropic:`` comments. ``"table"`` (degrees)
        holds 1 or 3 channels and no wavelengths or weights; ``"cornell"`` (radians) needs
        wavelengths and holds no weights, and refuses a set stated anisotropic. Both keep the
        name and isotropy in comments.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    ValueError
        If the format cannot hold the set (channels, wavelengths, weights, anisotropy), or
        a channel name would read back as something else.

    Examples
    --------
    >>> import os, tempfile
    >>> from basis import from_angles
    >>> m = Measurements(from_angles([0.1, 0.7], 0.0), from_angles([0.3, 0.2], [1.0, -2.0]),
    ...                  [[0.1, 0.2], [0.3, -0.01]], wavelengths=[500, 600], isotropic=True)
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     back = read_measurements(write_measurements(os.path.join(tmp, "m.brdf"), m,
    ...                                                 "cornell"))
    >>> bool(np.array_equal(back.values, m.values)), back.isotropic, back.info["format"]
    (True, True, 'cornell')
    >>> float(np.abs(back.wi - m.wi).max()) < 1e-15
    True
    """
    p = output_file(path)
    if not isinstance(meas, Measurements):
        raise TypeError(f"meas must be a project.Measurements, got {type(meas).__name__}")
    choice(format, "format", MEASUREMENT_FORMATS)
    unit_weights = bool(np.all(meas.weights == 1.0))
    if format != "csv" and not unit_weights:
        raise ValueError(f"the {format} format holds no weights and these are not all 1: "
                         "use format='csv'")
    ti, pi, to, po = meas.angles()
    head = ["# scatmodes measurements"]
    if meas.name is not None:
        if "\n" in meas.name or "\r" in meas.name:
            raise ValueError(f"meas.name must be one line to be written, got {meas.name!r}")
        head.append(f"# name: {meas.name}")
    if meas.isotropic is not None:
        head.append(f"# isotropic: {'true' if meas.isotropic else 'false'}")
    if format == "csv":
        body = _csv_text(meas, ti, pi, to, po, unit_weights)
    elif format == "table":
        if meas.channels not in (1, 3):
            raise ValueError(f"the table format holds 1 or 3 channels, got {meas.channels}: "
                             "use format='csv'")
        if meas.wavelengths is not None:
            raise ValueError("the table format holds no wavelengths: use format='csv' or "
                             "'cornell', or write Measurements(meas.wi, meas.wo, meas.values)")
        head.append("# theta_i phi_i theta_o phi_o (degrees) "
                    + " ".join(meas.channel_names))
        deg = np.degrees(np.stack([ti, pi, to, po], axis=1))
        body = _rows(np.concatenate([deg, meas.values], axis=1), " ")
    else:
        if meas.wavelengths is None:
            raise ValueError("the cornell format needs wavelengths: use format='csv'")
        if meas.isotropic is False:
            raise ValueError("the cornell format holds isotropic data, and these are stated "
                             "anisotropic: use format='csv'")
        wl = meas.wavelengths
        head += ["", "# num wls", str(wl.size), "", "# wls", " ".join(map(repr, wl.tolist())),
                 "", "# theta i, phi i, theta s, phi_s, spectral sample values"]
        body = _rows(np.concatenate([np.stack([ti, pi, to, po], axis=1), meas.values],
                                    axis=1), " ")
    with atomic_path(p, suffix=".tmp") as tmp:
        tmp.write_text("\n".join(head) + "\n" + body, encoding="utf-8")
    return p


def _rows(a: NDArray, sep: str) -> str:
    """Return lines of repr-exact numbers, one row of ``a`` each."""
    return "".join(sep.join(map(repr, row)) + "\n" for row in a.tolist())


def _csv_text(meas: Measurements, ti: NDArray, pi: NDArray, to: NDArray, po: NDArray,
              unit_weights: bool) -> str:
    if meas.wavelengths is not None:
        names = [f"{w!r} nm" for w in meas.wavelengths.tolist()]
    else:
        names = list(meas.channel_names)
        for n in names:
            if _column(n)[0] != "value" or not math.isnan(_wavelength_of(n)) or \
                    n != n.strip() or not n or any(ch in n for ch in "\n\r#"):
                raise ValueError(f"channel name {n!r} would not read back as a channel name "
                                 "(an angle, weight or wavelength name, blank, or a line break "
                                 "or '#'): rename the channels")
    header = ["theta_i [rad]", "phi_i [rad]", "theta_o [rad]", "phi_o [rad]", *names]
    cols = [np.stack([ti, pi, to, po], axis=1), meas.values]
    if not unit_weights:
        header.append("weight")
        cols.append(meas.weights[:, None])
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(header)
    return buf.getvalue() + _rows(np.concatenate(cols, axis=1), ",")
