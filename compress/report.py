"""A self-contained HTML page about one representation of a BRDF: :func:`report`.

The page shows, for a coefficient matrix, a fitted model, a hybrid, a measured BRDF (MERL,
RGL-EPFL) or a set of scattered measurements, with or without a reference to compare with:

1. **Summary**: the form, its size in bytes at each storage precision (what
   :func:`compress.save` writes with ``dtype="float64"``, ``"float32"``, ``"float16"``) and
   the error that rounding to it costs; the errors (relative L2 of q = f cos theta_i
   cos theta_o and the RMS log error of :mod:`project.sampling` on peak-resolving pairs,
   the image error of lit spheres) against the reference, or those recorded in ``info``;
   the reciprocity residual and floor (:func:`project.reciprocity`); the provenance held in
   ``info`` and in the file's header.
2. **Lobes**: f cos theta_o in the plane of incidence (polar plots) and over the outgoing
   hemisphere (heat maps, orthographic projection), at 0, 30, 60 and 75 degrees incidence;
   the reference on the same axes.
3. **Spheres**: :func:`compress.render_sphere` under three lights; the reference and the
   signed difference beside it.
4. **Where the error lives**: the share of the squared error of q, and the relative error
   within each band, by (theta_i, theta_o) band; the solid-angle fraction where a truncated
   expansion is negative.
5. **Resolution against error**: bytes against error for the candidates of a
   :func:`compress.select` table (``info["candidates"]``), or for a small table computed
   here; the representation marked, published sizes of compact MERL representations as
   reference lines.
6. **Measurements**: the samples over (theta_i, theta_o) and the residuals of the fit.

Everything is in one file: figures are PNG images in ``data:`` URIs, the style sheet
is inline (with a print style), nothing is fetched from the network. Colour maps are
perceptually uniform and readable with colour-vision deficiencies: viridis for values,
the diverging RdBu (Brewer) for signed differences.

References
----------
- Bagher, Snyder & Nowrouzezahrai 2016: M. M. Bagher, J. Snyder and D. Nowrouzezahrai, "A
  non-parametric factor microfacet model for isotropic BRDFs", ACM Transactions on
  Graphics 35(5), 2016.
- Sztrajman et al. 2021: A. Sztrajman, G. Rainer, T. Ritschel and T. Weyrich, "Neural BRDF
  representation and importance sampling", Computer Graphics Forum 40(6), 2021.
- Nunez, Smith & van der Walt 2018: J. R. Nunez, S. M. Colby and R. S. Renslow, "Optimizing
  colormaps with consideration for color vision deficiency to enable accurate
  interpretation of scientific data", PLoS ONE 13(7), 2018 (viridis and cividis).
"""

from __future__ import annotations

import base64
import html
import io
import math
import os
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

import project
from basis import CoefficientMatrix
from project.crossval import sample_errors
from project.io import atomic_path
from project.sampling import brdf_errors, peak_resolving_pairs

from .hybrid import Hybrid
from .render import render_sphere, tonemap
from .truncate import PRECISIONS, precision, truncate, unique_coefficients

__all__ = ["INCIDENCE_DEG", "LIGHTS", "PUBLISHED", "REPORT_CANDIDATES", "image_error",
           "read_source", "report"]

#: Incidence angles (degrees) of the lobe plots.
INCIDENCE_DEG = (0.0, 30.0, 60.0, 75.0)
#: Lights of the sphere pictures and of the image error: unit vectors in the frame of the
#: view (0, 0, 1): from the view direction, 45 degrees and 75 degrees off it.
LIGHTS = ((0.0, 0.0, 1.0),
          (math.sin(math.radians(45.0)), 0.0, math.cos(math.radians(45.0))),
          (0.0, math.sin(math.radians(75.0)), math.cos(math.radians(75.0))))
_VIEW = (0.0, 0.0, 1.0)
#: Published sizes of compact MERL representations (bytes per material), for the charts.
PUBLISHED = {"neural BRDF (Sztrajman et al. 2021)": 2700,
             "factored microfacet (Bagher et al. 2016)": 3200}
#: Candidates of the small table computed when the input holds none: a microfacet lobe, a
#: rank-1 factored lobe, two Zernike orders and three half/difference tables, one storage
#: type (float32): about 2 s of CPU on a MERL table.
REPORT_CANDIDATES: tuple[dict[str, Any], ...] = (
    {"form": "model", "family": "lambert+ggx", "restarts": 1},
    {"form": "model", "family": "factored", "rank": 1, "bins": (32, 24)},
    {"form": "modal", "kind": "zernike", "order": 4},
    {"form": "modal", "kind": "zernike", "order": 8},
    {"form": "model", "family": "tabulated", "bins": (16, 12, 4)},
    {"form": "model", "family": "tabulated", "bins": (24, 16, 16)},
    {"form": "model", "family": "tabulated", "bins": (32, 24, 16)},
)
#: The same for measurements (fitted to the samples, cross-validated).
_SAMPLE_CANDIDATES: tuple[dict[str, Any], ...] = (
    {"form": "model", "family": "lambert+ggx"},
    {"form": "model", "family": "lafortune", "lobes": 1, "restarts": 2},
    {"form": "modal", "kind": "zernike", "order": 2},
    {"form": "modal", "kind": "zernike", "order": 4},
)
#: Band edges (degrees) of theta_i and theta_o in section 4.
BANDS_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)
#: Pairs of the error estimates (project.sampling.peak_resolving_pairs); seed of the pairs.
ERROR_PAIRS = 1 << 15
_SEED = 2027
#: Pairs of the reciprocity estimate (about 0.1 s on a MERL table).
RECIPROCITY_PAIRS = 1 << 14
#: Side of the sphere pictures in pixels (that of the image error).
SPHERE_SIZE = 128
#: Pixels per side of the outgoing-hemisphere heat maps.
_HEAT = 61
#: Decades below the peak that a logarithmic radius spans in the polar plots.
_DECADES = 4
_DPI = 80

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_TENSOR_MAGIC = b"tensor_file\x00"
_CHECKPOINT = "scatmodes-microgeometry-checkpoint-"
_KINDS_READ = ("a file of compress.save (.h5: coefficient matrix, fitted model or hybrid), a "
               "MERL .binary table, an RGL-EPFL .bsdf file or a measurement table (text, CSV "
               "or Cornell .brdf)")


# -- reading ----------------------------------------------------------------------------------
def read_source(path: str | os.PathLike) -> Any:
    """Read any input of :func:`report` from a file.

    Parameters
    ----------
    path : str or os.PathLike
        A file of :func:`compress.save` (HDF5), a MERL ``.binary`` table
        (:func:`project.measured.read_merl`), an RGL-EPFL ``.bsdf`` tensor file
        (:func:`project.measured.read_rgl`) or a measurement table
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
    p = Path(os.fspath(path))
    if not p.exists():
        raise FileNotFoundError(f"file {str(p)!r} does not exist")
    if p.is_dir():
        raise IsADirectoryError(f"the input must be a file, got the directory {str(p)!r}")
    with open(p, "rb") as fh:
        head = fh.read(len(_TENSOR_MAGIC))
    if head[:len(_HDF5_SIGNATURE)] == _HDF5_SIGNATURE:
        if _checkpoint(p):
            raise ValueError(f"{str(p)!r} is a simulation checkpoint, not a representation: "
                             "finish the run (scatmodes simulate --resume) and report the "
                             ".h5 file it writes")
        from .store import load

        return load(p)
    from project.measured import read_measurements, read_merl, read_rgl

    if head == _TENSOR_MAGIC:
        return read_rgl(p)
    if p.suffix.lower() == ".binary":
        return read_merl(p)
    try:
        return read_measurements(p)
    except ValueError as exc:
        raise ValueError(f"{str(p)!r} is not {_KINDS_READ}; read as a measurement table: "
                         f"{' '.join(str(exc).split())}") from None


def _checkpoint(p: Path) -> bool:
    import h5py

    try:
        with h5py.File(p, "r") as f:
            fmt = f.attrs.get("format")
    except Exception:  # noqa: BLE001 - compress.load reports what is wrong with the file
        return False
    fmt = fmt.decode(errors="replace") if isinstance(fmt, bytes) else fmt
    return isinstance(fmt, str) and fmt.startswith(_CHECKPOINT)


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


# -- the image error --------------------------------------------------------------------------
def image_error(brdf: Any, approx: Any, *, size: int = SPHERE_SIZE) -> float:
    """Relative RMS difference of lit-sphere pictures, ``approx`` against ``brdf``.

    Parameters
    ----------
    brdf, approx : BRDF
        Objects with ``eval(wi, wo)`` (``approx`` may also be a coefficient matrix).
    size : int
        Image side in pixels (:func:`compress.render_sphere`).

    Returns
    -------
    float
        sqrt(sum (I_approx - I)^2 / sum I^2) over the pixels on the sphere, the channels
        and the three lights of :data:`LIGHTS` (view along z), each light of unit
        irradiance.

    Examples
    --------
    >>> from project.models import Lambert
    >>> round(image_error(Lambert(0.5), Lambert(0.55), size=32), 12)
    0.1
    """
    refs = [render_sphere(brdf, light, size=size, view=_VIEW) for light in LIGHTS]
    imgs = [render_sphere(approx, light, size=size, view=_VIEW) for light in LIGHTS]
    return _image_error(refs, imgs)


def _image_error(refs: Sequence[NDArray], imgs: Sequence[NDArray]) -> float:
    num = den = 0.0
    for ref, img in zip(refs, imgs, strict=True):
        if img.ndim < ref.ndim:
            img = img[..., None]
        on = np.isfinite(ref)
        num += float(np.sum((np.broadcast_to(img, ref.shape)[on] - ref[on]) ** 2))
        den += float(np.sum(ref[on] ** 2))
    return math.sqrt(num / den) if den > 0 else math.nan


# -- the report -------------------------------------------------------------------------------
def report(rep: Any, reference: Any = None, path: str | os.PathLike | None = None, *,
           title: str | None = None, table: bool = True, progress: bool = False) -> Any:
    """Write (or return) a self-contained HTML page about a representation of a BRDF.

    Parameters
    ----------
    rep : representation, BRDF, project.Measurements, str or os.PathLike
        A :class:`basis.CoefficientMatrix`, a :class:`project.FittedModel`, a
        :class:`compress.Hybrid`, any BRDF with ``eval(wi, wo)`` (e.g. a MERL table), or
        scattered measurements; or the path of a file holding one (:func:`read_source`).
        Measurements are shown through a fit of ``"lambert+ggx"``
        (:func:`project.fit_model`, cross-validated), whose residuals section 6 plots.
    reference : BRDF, representation, project.Measurements, str or os.PathLike, optional
        What ``rep`` is compared with: the errors, the reference curves and spheres and the
        error by band are measured against it. Measurements as a reference are compared
        at their samples.
    path : str or os.PathLike, optional
        Write the page there (atomically: a failed run leaves no partial file) and return
        the path; without it, return the HTML text.
    title : str, optional
        Title of the page (default: the name of the input).
    table : bool
        Compute the small table of section 5 (:data:`REPORT_CANDIDATES`, about 2 s of CPU
        on a MERL table) when ``rep.info`` holds no ``"candidates"``; False leaves the
        section to the table held, if any.
    progress : bool
        Show a progress bar over the sections (tqdm, on stderr).

    Returns
    -------
    str or pathlib.Path
        The HTML text, or ``path``.

    Raises
    ------
    TypeError
        ``rep`` or ``reference`` is none of the above.
    ValueError
        A file that cannot be read (see :func:`read_source`), or ``path`` in a folder that
        does not exist.

    Notes
    -----
    Warnings raised while the page is made (e.g. a BRDF with ideal mirror terms, which the
    pictures leave out) are listed at its end rather than passed on.

    Examples
    --------
    >>> import numpy as np
    >>> from basis import CoefficientMatrix, HemiZernike
    >>> cm = CoefficientMatrix(HemiZernike(2), np.eye(6) / 3, info={"source": "demo"})
    >>> page = report(cm, table=False)
    >>> page.startswith("<!DOCTYPE html>"), "coefficient matrix" in page
    (True, True)
    """
    target = None if path is None else _output(path)
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        page = _Page(rep, reference, title, table, progress).html(start)
        notes = [str(w.message) for w in caught]
    if notes:
        items = "".join(f"<li>{_e(n)}</li>" for n in dict.fromkeys(notes))
        page = page.replace("<!--notes-->", f"<section><h2>Notes</h2><p>Warnings raised "
                            f"while this page was made:</p><ul>{items}</ul></section>")
    if target is None:
        return page
    with atomic_path(target, suffix=".html") as tmp:
        tmp.write_text(page, encoding="utf-8")
    return target


def _output(path: str | os.PathLike) -> Path:
    """Check before any work that ``path`` can be written."""
    try:
        p = Path(os.fspath(path))
    except TypeError:
        raise TypeError(f"path must be a str or os.PathLike, got {type(path).__name__}"
                        ) from None
    folder = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise ValueError(f"path must name a file, got the directory {str(p)!r}")
    if not folder.is_dir():
        raise ValueError(f"cannot write {str(p)!r}: directory {str(folder)!r} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"cannot write {str(p)!r}: permission denied")
    return p


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


def _values(brdf: Any, wi: NDArray, wo: NDArray) -> NDArray[np.float64]:
    """BRDF values as (n, channels) float64."""
    v = np.asarray(brdf.eval(wi, wo), dtype=np.float64)
    return v.reshape(v.shape[0], -1) if v.ndim != 2 else v


class _Page:
    """The computations and figures of one report."""

    def __init__(self, rep: Any, reference: Any, title: str | None, table: bool,
                 progress: bool) -> None:
        self.file = None
        if isinstance(rep, str | os.PathLike):
            self.file = Path(os.fspath(rep))
            rep = read_source(rep)
        self.ref_file = None
        if isinstance(reference, str | os.PathLike):
            self.ref_file = Path(os.fspath(reference))
            reference = read_source(reference)
        self.kind = _kind(rep)
        self.rep = rep
        self.meas = rep if isinstance(rep, project.Measurements) else None
        self.ref_meas = self.ref = None
        if reference is not None:
            try:
                rk = _kind(reference)
            except TypeError as exc:
                raise TypeError(str(exc).replace("rep must", "reference must", 1)) from None
            if rk == "measurements":
                if self.meas is not None:
                    raise ValueError("rep and reference are both measurements: give a BRDF "
                                     "or a representation as one of them")
                self.ref_meas = reference
            else:
                self.ref = reference
        self.ref_kind = None if reference is None else _kind(reference)
        self.table = table
        self.progress = progress
        self.title = title or self._name()
        self.shown = rep
        self.fit_note = ""
        self.pairs = peak_resolving_pairs(ERROR_PAIRS, seed=_SEED)
        self.err: dict[str, float] = {}
        self.recip: Any = None
        self.image: float | None = None
        self.stored = "float64"

    def _name(self) -> str:
        if self.file is not None:
            return self.file.name
        return _describe(self.rep, self.kind)

    # -- the page -----------------------------------------------------------------------------
    def html(self, start: float) -> str:
        steps: list[tuple[str, Callable[[], str]]] = [
            ("fit", self._fit), ("summary", self._summary), ("lobes", self._lobes),
            ("spheres", self._spheres), ("bands", self._bands), ("table", self._resolution),
            ("measurements", self._measurements)]
        bar = None
        if self.progress:
            import sys

            from tqdm.auto import tqdm

            bar = tqdm(total=len(steps), desc="report", unit="section", file=sys.stderr,
                       leave=False)
        parts: list[str] = []
        for _, step in steps:
            parts.append(step())
            if bar is not None:
                bar.update(1)
        if bar is not None:
            bar.close()
        body = "\n".join(p for p in parts if p)
        from basis import __version__

        seconds = time.perf_counter() - start
        return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
                f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
                f"<title>{_e(self.title)}: scatmodes report</title><style>{_CSS}</style>"
                f"</head><body><main><h1>{_e(self.title)}</h1><p class=\"lead\">"
                f"{_e(self.kind)}{self._compared()}. Written by scatmodes {_e(__version__)} in "
                f"{seconds:.1f} s.</p>\n{body}\n<!--notes-->\n</main></body></html>\n")

    def _compared(self) -> str:
        if self.ref_kind is None:
            return ", no reference"
        ref = self.ref if self.ref is not None else self.ref_meas
        what = self.ref_file.name if self.ref_file is not None else \
            _describe(ref, self.ref_kind)
        return f", compared with {_e(what)}"

    # -- measurements: the fit that stands for them --------------------------------------------
    def _fit(self) -> str:
        if self.meas is None:
            return ""
        self.shown = project.fit_model(self.meas, "lambert+ggx")
        self.fit_note = ("The measurements are shown through a fit of the lambert+ggx "
                         "family (project.fit_model; errors cross-validated on held-out "
                         "samples).")
        return ""

    # -- 1. summary ---------------------------------------------------------------------------
    def _summary(self) -> str:
        rows: list[tuple[str, str]] = [("form", self.kind)]
        if self.file is not None:
            rows.append(("file", f"{self.file} ({self.file.stat().st_size:,} bytes on disk)"))
            header = _header(self.file)
            rows += header
            self.stored = dict(header).get("file dtype", "float64")
        rows += self._sizes()
        errors = self._errors()
        rows += errors
        rows += self._reciprocity()
        prov = _provenance(getattr(self.shown if self.meas is not None else self.rep,
                                   "info", None))
        size_table = self._precision_table()
        return (f"<section id=\"summary\"><h2>1. Summary</h2>{_p(self.fit_note)}"
                f"{_table(['quantity', 'value'], rows)}{size_table}"
                f"<h3>Provenance</h3>{prov}</section>")

    def _sizes(self) -> list[tuple[str, str]]:
        obj = self.shown
        if self.meas is not None:
            m = self.meas
            return [("samples", f"{len(m):,} direction pairs x {m.channels} channel(s) "
                                f"({', '.join(m.channel_names)})"),
                    ("bytes", f"{m.values.nbytes + m.wi.nbytes + m.wo.nbytes:,} as float64 "
                              "(values and both directions)"),
                    ("fit bytes", f"{obj.nparams * 8:,} ({obj.nparams} reals as float64)")]
        reals = _reals(obj)
        if reals is None:
            shape = getattr(getattr(obj, "table", None), "shape", None)
            extra = "" if shape is None else f"; a table of {int(np.prod(shape)):,} values"
            return [("bytes", f"not a compact representation{extra}")]
        rows = [("bytes", f"{reals * 8:,} as float64 ({reals:,} reals)")]
        info = getattr(obj, "info", {}) or {}
        if isinstance(info.get("bytes"), int | float) and info.get("dtype"):
            rows.append(("bytes as selected", f"{int(info['bytes']):,} ({info['dtype']})"))
        return rows

    def _precision_table(self) -> str:
        obj = self.shown
        if _reals(obj) is None:
            return ""
        f64 = _values(obj, self.pairs.wi, self.pairs.wo)
        out = []
        for dtype in PRECISIONS:
            try:
                rounded, n = _rounded(obj, dtype)
            except ValueError as exc:
                out.append([dtype, "n/a", _e(str(exc))])
                continue
            err = _rel_l2(f64, _values(rounded, self.pairs.wi, self.pairs.wo), self.pairs)
            out.append([dtype, f"{n * np.dtype(dtype).itemsize:,}", _num(err)])
        note = "" if self.stored == "float64" else (
            f" The file holds {_e(self.stored)} numbers already: rounding them to a type at "
            f"least as wide costs nothing.")
        return ("<h3>Storage precision</h3><p>Bytes that compress.save writes at each "
                "precision (the numbers held, the file header aside), and the relative L2 "
                f"change of q = f cos(theta_i) cos(theta_o) that rounding costs.{note}</p>"
                + _table(["dtype", "bytes", "rounding error (relative L2 of q)"], out,
                         raw=True))

    def _errors(self) -> list[tuple[str, str]]:
        rows: list[tuple[str, str]] = []
        if self.ref is not None:
            e = brdf_errors(self.ref, self.shown, self.pairs)
            self.err = dict(e)
            rows.append(("l2 error against the reference",
                         f"{_num(e['l2'])} +- {_num(e['l2_stderr'])} (relative L2 of q over "
                         f"H x H, {len(self.pairs):,} peak-resolving pairs)"))
            rows.append(("log error against the reference",
                         f"{_num(e['log'])} (RMS of log(1 + f cos theta_i) differences)"))
            return rows  # the image error is added by the spheres
        if self.ref_meas is not None:
            m = self.ref_meas
            e = sample_errors(m, _values(self.shown, m.wi, m.wo))
            self.err = {"l2": e["l2"], "log": e["log"], "l2_stderr": e["l2_stderr"]}
            rows.append(("l2 error at the reference samples",
                         f"{_num(e['l2'])} +- {_num(e['l2_stderr'])} ({len(m):,} samples)"))
            rows.append(("log error at the reference samples", _num(e["log"])))
            return rows
        info = getattr(self.shown, "info", None) or {}
        labels = {"l2": "l2 error (recorded)", "l2_stderr": "l2 standard error (recorded)",
                  "log": "log error (recorded)", "image": "image error (recorded)",
                  "rel_error": "projection error estimate (recorded)",
                  "truncation_error": "truncation error (recorded)"}
        for key, label in labels.items():
            v = info.get(key)
            if isinstance(v, int | float) and not isinstance(v, bool):
                rows.append((label, _num(v)))
                if key in ("l2", "log", "l2_stderr"):
                    self.err[key] = float(v)
        for key, v in info.items():
            if key.startswith("image_") and isinstance(v, int | float):
                rows.append((f"{key} (recorded)", _num(v)))
        if not rows:
            rows.append(("errors", "none recorded; give a reference to measure them"))
        return rows

    def _reciprocity(self) -> list[tuple[str, str]]:
        rows = []
        sources = [("", self.meas if self.meas is not None else self.shown)]
        if self.ref is not None or self.ref_meas is not None:
            sources.append((" of the reference", self.ref if self.ref is not None
                            else self.ref_meas))
        for label, src in sources:
            try:
                r = project.reciprocity(src, n=RECIPROCITY_PAIRS, seed=_SEED)
            except ValueError as exc:
                rows.append((f"reciprocity{label}", f"not estimated: {exc}"))
                continue
            if not math.isfinite(r.residual):
                rows.append((f"reciprocity{label}", f"unknown: {r.note}"))
                continue
            rows.append((f"reciprocity residual{label}",
                         f"{_num(r.residual)} +- {_num(r.residual_stderr)} "
                         "(||q - q^T|| / ||q||)"))
            rows.append((f"reciprocity floor{label}",
                         f"{_num(r.floor)} (no reciprocal form comes closer)"))
            if label == "" and self.ref is None:
                self.recip = r
        return rows

    # -- 2. lobes -----------------------------------------------------------------------------
    def _lobes(self) -> str:
        from matplotlib.figure import Figure
        from matplotlib.ticker import MaxNLocator

        ref = self.ref
        meas = self.meas if self.meas is not None else self.ref_meas
        s = np.radians(np.linspace(-89.5, 89.5, 359))
        curves = []
        for ti_deg in INCIDENCE_DEG:
            ti = math.radians(ti_deg)
            # light at phi_i = 180 deg (on the left), mirror direction at theta_o = +theta_i
            wi = np.broadcast_to([-math.sin(ti), 0.0, math.cos(ti)], (s.size, 3)).copy()
            wo = np.stack([np.sin(s), np.zeros_like(s), np.cos(s)], axis=1)
            f = _values(self.shown, wi, wo).mean(axis=1) * np.cos(s)
            g = None if ref is None else _values(ref, wi, wo).mean(axis=1) * np.cos(s)
            pts = _in_plane(meas, ti) if meas is not None else None
            curves.append((f, g, pts))
        # a sharp lobe is a spike on a linear radius: beyond two decades between the peak
        # and the median, the radius is logarithmic
        allv = np.concatenate([np.concatenate([c[0]] + ([] if c[1] is None else [c[1]]))
                               for c in curves])
        top_all = float(np.max(allv, initial=0.0))
        med = float(np.median(allv[allv > 0])) if np.any(allv > 0) else 0.0
        log = top_all > 0 and med > 0 and top_all / med > 100.0
        fig = Figure(figsize=(11, 3.4), layout="constrained")
        for k, ti_deg in enumerate(INCIDENCE_DEG):
            ax = fig.add_subplot(1, len(INCIDENCE_DEG), k + 1, projection="polar")
            ti = math.radians(ti_deg)
            f, g, pts = curves[k]
            top = max(float(np.max(f, initial=0.0)),
                      0.0 if g is None else float(np.max(g, initial=0.0)),
                      0.0 if pts is None or not pts[0].size else float(np.max(pts[1])))
            top = top if top > 0 else 1.0
            floor = top * 10.0 ** -_DECADES

            def radius(v: NDArray, floor: float = floor) -> NDArray:
                return np.log10(np.maximum(v, floor) / floor) if log else v

            ax.plot(s, radius(f), color="#21918c", lw=1.6, label=self._label())
            if g is not None:
                ax.plot(s, radius(g), color="#440154", lw=1.2, ls="--", label="reference")
            if pts is not None and pts[0].size:
                ax.plot(pts[0], radius(pts[1]), "o", ms=2.5, color="#fde725", mec="#3b528b",
                        mew=0.5, label="samples (within 3 deg of the plane)")
            ax.set_theta_zero_location("N")
            ax.set_theta_direction(-1)
            ax.set_thetamin(-90)
            ax.set_thetamax(90)
            rmax = float(_DECADES) if log else top * 1.05
            ax.set_ylim(0, rmax)
            ax.annotate("", xy=(-ti, rmax), xytext=(-ti, 0),
                        arrowprops=dict(arrowstyle="<-", color="0.4", lw=0.8))
            ax.set_title(f"theta_i = {ti_deg:g} deg", fontsize=9)
            ax.set_thetagrids([-90, -60, -30, 0, 30, 60, 90])
            if log:
                ax.set_yticks(np.arange(2.0, _DECADES + 1.0, 2.0),
                              [f"{floor * 10.0 ** d:.2g}" for d in range(2, _DECADES + 1, 2)])
            else:
                ax.yaxis.set_major_locator(MaxNLocator(3))
            ax.tick_params(labelsize=7)
            if k == 0:
                ax.set_ylabel("f cos(theta_o) (1/sr" + (", log scale)" if log else ")"),
                              fontsize=8, labelpad=14)
        fig.legend(*fig.axes[0].get_legend_handles_labels(), loc="outside lower center",
                   ncols=3, fontsize=8, frameon=False)
        polar = _img(fig, "Polar plots of f cos(theta_o) in the plane of incidence at "
                     "incidence angles 0, 30, 60 and 75 degrees"
                     + (", with the reference dashed" if ref is not None else ""),
                     "In the plane of incidence: f cos(theta_o) in 1/sr (the mean over the "
                     "channels; the radiance reflected towards theta_o under unit "
                     "irradiance) against theta_o in degrees. The light (grey arrow) is on "
                     "the left, the mirror direction on the right."
                     + (f" The radius is logarithmic over {_DECADES} decades below each "
                        "panel's peak (the lobes are sharp)." if log else "")
                     + (" Reference dashed." if ref is not None else ""))
        heat = self._heat_maps()
        return (f"<section id=\"lobes\"><h2>2. Lobes</h2><p>The scattering lobe at four "
                f"incidence angles: a cut through the plane of incidence, and the whole "
                f"outgoing hemisphere seen from above.</p>{polar}{heat}</section>")

    def _label(self) -> str:
        return "fit" if self.meas is not None else "this representation"

    def _heat_maps(self) -> str:
        from matplotlib.colors import LogNorm
        from matplotlib.figure import Figure

        x = np.linspace(-1.0, 1.0, _HEAT)
        X, Y = np.meshgrid(x, x[::-1])
        inside = X * X + Y * Y < 1.0
        wo = np.stack([X[inside], Y[inside], np.sqrt(1.0 - X[inside] ** 2 - Y[inside] ** 2)],
                      axis=1)
        rows = [("this representation" if self.meas is None else "fit", self.shown)]
        if self.ref is not None:
            rows.append(("reference", self.ref))
        maps = np.full((len(rows), len(INCIDENCE_DEG), _HEAT, _HEAT), np.nan)
        for k, ti_deg in enumerate(INCIDENCE_DEG):
            ti = math.radians(ti_deg)
            wi = np.broadcast_to([-math.sin(ti), 0.0, math.cos(ti)], wo.shape).copy()
            for r, (_, brdf) in enumerate(rows):
                maps[r, k][inside] = _values(brdf, wi, wo).mean(axis=1) * wo[:, 2]
        fig = Figure(figsize=(11, 0.6 + 2.6 * len(rows)), layout="constrained")
        axes = fig.subplots(len(rows), len(INCIDENCE_DEG), squeeze=False)
        for k, ti_deg in enumerate(INCIDENCE_DEG):
            col = maps[:, k]
            top = float(np.nanmax(col)) if np.any(col > 0) else 1.0
            norm = LogNorm(vmin=top * 1e-3, vmax=top)
            for r, (name, _) in enumerate(rows):
                ax = axes[r, k]
                im = ax.imshow(np.clip(maps[r, k], top * 1e-3, None), cmap="viridis",
                               norm=norm, extent=(-1, 1, -1, 1), interpolation="nearest")
                ti = math.radians(ti_deg)
                ax.plot([math.sin(ti)], [0.0], "+", color="white", ms=8, mew=1.2)
                ax.set_title(f"{name}, theta_i = {ti_deg:g} deg", fontsize=8)
                ax.set_xticks([-1, 0, 1])
                ax.set_yticks([-1, 0, 1])
                ax.tick_params(labelsize=7)
                ax.set_xlabel("sin(theta_o) cos(phi_o)", fontsize=7)
                if k == 0:
                    ax.set_ylabel("sin(theta_o) sin(phi_o)", fontsize=7)
            cb = fig.colorbar(im, ax=axes[:, k].tolist(), shrink=0.85, location="bottom")
            cb.set_label("f cos(theta_o) (1/sr, log scale)", fontsize=7)
            cb.ax.tick_params(labelsize=6)
        return _img(fig, "Heat maps of f cos(theta_o) over the outgoing hemisphere at "
                    "incidence angles 0, 30, 60 and 75 degrees"
                    + (", the representation above the reference" if self.ref is not None
                       else ""),
                    "Over the outgoing hemisphere, seen from above (orthographic: x = "
                    "sin(theta_o) cos(phi_o), y = sin(theta_o) sin(phi_o)): f cos(theta_o) "
                    "in 1/sr, log colour scale over three decades, one scale per column. "
                    "The light is at phi_i = 180 deg (left); + marks the mirror direction."
                    + (" Top row: this representation; bottom row: the reference."
                       if self.ref is not None else ""))

    # -- 3. spheres ---------------------------------------------------------------------------
    def _spheres(self) -> str:
        from matplotlib.colors import TwoSlopeNorm
        from matplotlib.figure import Figure

        mine = [render_sphere(self.shown, light, size=SPHERE_SIZE, view=_VIEW)
                for light in LIGHTS]
        refs = None if self.ref is None else [
            render_sphere(self.ref, light, size=SPHERE_SIZE, view=_VIEW) for light in LIGHTS]
        extra = ""
        if refs is not None:
            self.image = _image_error(refs, mine)
            extra = (f"<p>Image error (relative RMS over the three pictures, the "
                     f"reference's pixels as the norm): <strong>{_num(self.image)}</strong>."
                     f"</p>")
        base = refs if refs is not None else mine
        finite = np.concatenate([b[np.isfinite(b)].ravel() for b in base])
        white = float(np.percentile(finite, 99.5)) if finite.size else 1.0
        exposure = 1.0 / white if white > 0 else 1.0
        rows = [("this representation" if self.meas is None else "fit", mine)]
        if refs is not None:
            rows.append(("reference", refs))
        fig = Figure(figsize=(7.5, 0.5 + 2.4 * (len(rows) + (refs is not None))),
                     layout="constrained")
        nrow = len(rows) + (refs is not None)
        axes = fig.subplots(nrow, len(LIGHTS), squeeze=False)
        names = ("light at the view", "light 45 deg right", "light 75 deg up")
        for r, (name, imgs) in enumerate(rows):
            for k, img in enumerate(imgs):
                shown = tonemap(img, exposure, background=1.0)
                if shown.ndim == 3 and shown.shape[2] != 3:
                    shown = shown.mean(axis=2)
                ax = axes[r, k]
                ax.imshow(shown, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
                if r == 0:
                    ax.set_title(names[k], fontsize=8)
                if k == 0:
                    ax.text(-0.04, 0.5, name, rotation=90, ha="right", va="center",
                            fontsize=8, transform=ax.transAxes)
                ax.set_axis_off()
        if refs is not None:
            diffs = []
            for img, ref in zip(mine, refs, strict=True):
                a = img if img.ndim == 2 else img.mean(axis=2)
                b = ref if ref.ndim == 2 else ref.mean(axis=2)
                diffs.append(a - b)
            span = np.concatenate([np.abs(d[np.isfinite(d)]).ravel() for d in diffs])
            lim = float(np.percentile(span, 99.5)) if span.size else 1.0
            lim = lim if lim > 0 else 1.0
            norm = TwoSlopeNorm(vcenter=0.0, vmin=-lim, vmax=lim)
            for k, d in enumerate(diffs):
                ax = axes[-1, k]
                im = ax.imshow(d, cmap="RdBu_r", norm=norm, interpolation="nearest")
                if k == 0:
                    ax.text(-0.04, 0.5, "difference", rotation=90, ha="right", va="center",
                            fontsize=8, transform=ax.transAxes)
                ax.set_axis_off()
            cb = fig.colorbar(im, ax=axes[-1, :].tolist(), shrink=0.7, location="right")
            cb.set_label("radiance difference, representation - reference\n(1/sr per unit "
                         "irradiance, mean over the channels)", fontsize=7)
            cb.ax.tick_params(labelsize=6)
        alt = ("Spheres rendered under three lights"
               + (", the representation, the reference and their signed difference"
                  if refs is not None else ""))
        cap = ("A unit sphere under a directional light of unit irradiance, seen from the "
               "front (compress.render_sphere), one exposure for all pictures (the 99.5th "
               "percentile of the " + ("reference" if refs is not None else "pictures")
               + " maps to white), sRGB."
               + (" Bottom row: the signed difference (representation - reference), mean "
                  "over the channels, red where the representation is brighter."
                  if refs is not None else ""))
        return (f"<section id=\"spheres\"><h2>3. Spheres</h2>{extra}{_img(fig, alt, cap)}"
                f"</section>")

    # -- 4. where the error lives -------------------------------------------------------------
    def _bands(self) -> str:
        from matplotlib.figure import Figure

        parts = []
        edges = np.radians(BANDS_DEG)
        if self.ref is not None or self.ref_meas is not None or self.meas is not None:
            if self.ref is not None:
                wi, wo, w = self.pairs.wi, self.pairs.wo, self.pairs.weights
                f = _values(self.ref, wi, wo)
                how = (f"{len(self.pairs):,} peak-resolving pairs, weighted to integrate "
                       "over H x H; against the reference")
            else:
                m = self.ref_meas if self.ref_meas is not None else self.meas
                wi, wo, w = m.wi, m.wo, np.asarray(m.weights)
                f = np.asarray(m.values)
                how = (f"the {len(m):,} measured samples, with their weights"
                       + ("; the fit against the samples" if self.meas is not None else ""))
            fh = _values(self.shown, wi, wo)
            share, rel = _band_errors(wi, wo, w, f, fh, edges)
            fig = Figure(figsize=(10, 4.0), layout="constrained")
            a1, a2 = fig.subplots(1, 2)
            _band_map(fig, a1, 100 * share, "share of the squared error of q (%)", "{:.1f}")
            _band_map(fig, a2, rel, "relative L2 error of q within the band", "{:.2g}")
            fig.suptitle("Error of q = f cos(theta_i) cos(theta_o) by (theta_i, theta_o) "
                         "band, all channels", fontsize=9)
            parts.append(f"<p>On {_e(how)}. Left: where the squared error is (the shares "
                         f"sum to 100 %); right: how large it is relative to q in each "
                         f"band.</p>")
            parts.append(_img(fig, "Heat maps of the error of q by band of theta_i and "
                               "theta_o: share of the squared error and relative error"))
        else:
            parts.append("<p>Errors by band need a reference (--reference).</p>")
            r = self.recip
            if r is not None and r.residual > 0 and r.bands:
                rows = [[f"{b['theta_deg'][0]:g}-{b['theta_deg'][1]:g}",
                         _num(100 * b["share"]) if b["share"] is not None else "n/a",
                         _num(b["floor_below"])] for b in r.bands]
                parts.append("<p>Where the non-reciprocal part lives (by max(theta_i, "
                             "theta_o)):</p>" + _table(["band (deg)", "share of the "
                                                       "antisymmetric energy (%)",
                                                       "floor below the band's top"], rows))
        parts.append(self._negative())
        return (f"<section id=\"bands\"><h2>4. Where the error lives</h2>{''.join(parts)}"
                f"</section>")

    def _negative(self) -> str:
        expansion = self.shown if isinstance(self.shown, CoefficientMatrix) else \
            (self.shown if isinstance(self.shown, Hybrid) else None)
        if expansion is None:
            return "<p>Negative values: none possible (not a truncated expansion).</p>"
        wi, wo, w = self.pairs.wi, self.pairs.wo, self.pairs.weights
        neg = np.any(_values(expansion, wi, wo) < 0.0, axis=1)
        frac = float(np.sum(w[neg]) / np.sum(w))
        edges = np.radians(BANDS_DEG)
        nb = len(edges) - 1
        bi = np.clip(np.searchsorted(edges, np.arccos(np.clip(wi[:, 2], -1, 1))) - 1, 0, nb - 1)
        bo = np.clip(np.searchsorted(edges, np.arccos(np.clip(wo[:, 2], -1, 1))) - 1, 0, nb - 1)
        tot = np.zeros((nb, nb))
        bad = np.zeros((nb, nb))
        np.add.at(tot, (bi, bo), w)
        np.add.at(bad, (bi, bo), w * neg)
        text = (f"<p>Fraction of H x H (solid angle) where the expansion is negative in some "
                f"channel: <strong>{_num(frac)}</strong> ({_num(100 * frac)} %).</p>")
        if frac == 0.0:
            return text
        from matplotlib.figure import Figure

        fig = Figure(figsize=(5.2, 4.0), layout="constrained")
        ax = fig.add_subplot()
        _band_map(fig, ax, 100 * np.divide(bad, tot, out=np.zeros_like(bad), where=tot > 0),
                  "negative fraction within the band (%)", "{:.1f}")
        return text + _img(fig, "Heat map of the fraction of each (theta_i, theta_o) band "
                                "where the expansion is negative")

    # -- 5. resolution against error ----------------------------------------------------------
    def _resolution(self) -> str:
        info = getattr(self.rep, "info", None) or {}
        cands = info.get("candidates") if isinstance(info, Mapping) else None
        chosen = None
        if isinstance(cands, list) and cands and isinstance(cands[0], Mapping):
            rows = [dict(c) for c in cands]
            sel = info.get("selected")
            if isinstance(sel, Mapping):
                chosen = (sel.get("bytes"), sel.get("l2"), "selected")
            how = (f"The table compress.select recorded ({len(rows)} candidates and storage "
                   f"types; tolerance {_num(info.get('tol'))}).")
        elif not self.table:
            return ""
        else:
            rows, how = self._small_table()
            if rows is None:
                return (f"<section id=\"table\"><h2>5. Resolution against error</h2>"
                        f"{_p(how)}</section>")
            mine = _reals(self.shown)
            if mine is not None and "l2" in self.err and self.meas is None:
                chosen = (8 * mine, self.err["l2"], "this representation (float64)")
        measured = [r for r in rows if r.get("status") == "measured"
                    and _finite(r.get("l2")) and _finite(r.get("bytes"))]
        chart = _chart(measured, chosen, self.title) if measured else ""
        body = [[_e(str(r.get("label", ""))), _e(str(r.get("dtype", ""))),
                 "n/a" if not _finite(r.get("bytes")) else f"{int(r['bytes']):,}",
                 _num(r.get("l2")), _num(r.get("log")), _e(_short(str(r.get("status", ""))))]
                for r in sorted(rows, key=lambda r: (not _finite(r.get("bytes")),
                                                     r.get("bytes") or 0))]
        return (f"<section id=\"table\"><h2>5. Resolution against error</h2><p>{_e(how)}</p>"
                f"{chart}<details><summary>The table ({len(rows)} rows)</summary>"
                + _table(["candidate", "dtype", "bytes", "l2", "log", "status"], body,
                         raw=True) + "</details></section>")

    def _small_table(self) -> tuple[list[dict] | None, str]:
        from .selection import select

        target = self.ref if self.ref is not None else (
            self.meas if self.meas is not None else self.ref_meas)
        if target is None:
            target = self.shown
        if isinstance(target, CoefficientMatrix):
            return _truncations(target, self.pairs), (
                "Truncations of the matrix to lower orders (compress.truncate), errors "
                "against the matrix itself on peak-resolving pairs.")
        sampled = isinstance(target, project.Measurements)
        cands = _SAMPLE_CANDIDATES if sampled else REPORT_CANDIDATES
        what = "the measurements" if sampled else (
            "the reference" if target is self.ref else "this BRDF")
        try:
            rep = select(target, math.inf, candidates=cands, exhaustive=True,
                         error_n=1 << 14, dtypes=("float32",),
                         reciprocal=True if sampled else None)
        except (ValueError, TypeError) as exc:
            return None, f"No table: compress.select could not run on {what}: {exc}"
        return [dict(r) for r in rep.info["candidates"]], (
            f"A small table computed for this page: compress.select on {what} with "
            f"{len(cands)} candidates at float32, every one measured "
            + ("(errors cross-validated on held-out samples)." if sampled else
               "(errors on 16,384 peak-resolving pairs)."))

    # -- 6. measurements ----------------------------------------------------------------------
    def _measurements(self) -> str:
        m = self.meas if self.meas is not None else self.ref_meas
        if m is None:
            return ""
        from matplotlib.colors import Normalize
        from matplotlib.figure import Figure

        ti, phi_i, to, phi_o = m.angles()
        # theta_o signed by the side of the plane of incidence: + towards the mirror
        side = np.where(np.cos(phi_o - phi_i) <= 0.0, 1.0, -1.0)
        x = np.degrees(to) * side
        v = np.asarray(m.values)
        q = v.mean(axis=1) * np.cos(to)
        fh = _values(self.shown, m.wi, m.wo)
        res = (fh - v).mean(axis=1) * np.cos(to)
        e = sample_errors(m, fh)
        fig = Figure(figsize=(10, 4.0), layout="constrained")
        a1, a2 = fig.subplots(1, 2)
        tdeg = np.degrees(ti)
        norm = Normalize(vmin=0.0, vmax=90.0)
        pos = q > 0
        a1.scatter(x[pos], q[pos], c=tdeg[pos], s=7, cmap="viridis", norm=norm, linewidths=0)
        a1.set_yscale("log")
        a1.set_ylabel("measured f cos(theta_o) (1/sr, log scale)")
        sc = a2.scatter(x, res, c=tdeg, s=7, cmap="viridis", norm=norm, linewidths=0)
        a2.axhline(0.0, color="0.3", lw=0.8)
        a2.set_ylabel("residual (f_fit - f_measured) cos(theta_o) (1/sr)")
        fig.colorbar(sc, ax=[a1, a2]).set_label("theta_i (degrees)", fontsize=8)
        for ax, name in ((a1, "the samples"), (a2, "residuals of the fit")):
            ax.set_xlabel("theta_o (degrees; + on the mirror side of the plane of "
                          "incidence)", fontsize=8)
            ax.set_title(name, fontsize=9)
            ax.set_xlim(-92, 92)
            ax.grid(True, alpha=0.25)
        fig.suptitle("Measurements over the angles (mean over the channels; colour: the "
                     "incidence angle)", fontsize=9)
        who = "fit" if self.meas is not None else "representation"
        rows = [("samples", f"{len(m):,} x {m.channels} channel(s)"),
                (f"l2 error of the {who} at the samples (all used in the fit)"
                 if self.meas is not None else "l2 error at the samples",
                 f"{_num(e['l2'])} +- {_num(e['l2_stderr'])}"),
                ("log error at the samples", _num(e["log"])),
                ("largest |residual|", f"{_num(float(np.max(np.abs(fh - v))))} 1/sr")]
        figure = _img(fig, "Scatter plots of the measured values and of the residuals of "
                           "the fit against theta_o, coloured by theta_i")
        return (f"<section id=\"measurements\"><h2>6. Measurements</h2>{figure}"
                f"{_table(['quantity', 'value'], rows)}</section>")


# -- numbers ----------------------------------------------------------------------------------
def _reals(obj: Any) -> int | None:
    """Count the stored reals of a compact representation (None: a table, an analytic BRDF)."""
    if isinstance(obj, CoefficientMatrix):
        return unique_coefficients(obj)
    if isinstance(obj, Hybrid):
        lobe = _reals(obj.lobe)
        return None if lobe is None else lobe + unique_coefficients(obj.residual)
    if hasattr(obj, "family") and hasattr(obj, "params"):
        n = getattr(obj, "nparams", None)
        return int(n) if isinstance(n, int | np.integer) else \
            int(sum(np.size(v) for v in obj.params.values()))
    return None


def _rounded(obj: Any, dtype: str) -> tuple[Any, int]:
    """Round a representation to a storage type (held as float64); return it and its reals."""
    if isinstance(obj, CoefficientMatrix):
        return precision(obj, dtype), unique_coefficients(obj)
    if isinstance(obj, Hybrid):
        lobe, n = _rounded(obj.lobe, dtype)
        res = precision(obj.residual, dtype)
        return Hybrid(lobe, res, dict(obj.info)), n + unique_coefficients(obj.residual)
    top = float(np.finfo(dtype).max)
    params = {}
    for k, v in obj.params.items():
        if np.max(np.abs(v), initial=0.0) > top:
            raise ValueError(f"parameter {k!r} exceeds the largest {dtype}")
        params[k] = np.asarray(v).astype(dtype).astype(np.float64)
    model = project.FittedModel(obj.family, params, info=dict(obj.info or {}))
    return model, _reals(model)


def _rel_l2(f: NDArray, g: NDArray, pairs: Any) -> float:
    cc = (pairs.wi[:, 2] * pairs.wo[:, 2])[:, None] ** 2
    w = pairs.weights[:, None]
    den = np.sum(w * cc * f * f, axis=0)
    num = np.sum(w * cc * (g - f) ** 2, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.sqrt(num / den)
    return float(np.nanmax(rel)) if np.any(np.isfinite(rel)) else math.nan


def _band_errors(wi: NDArray, wo: NDArray, w: NDArray, f: NDArray, fh: NDArray,
                 edges: NDArray) -> tuple[NDArray, NDArray]:
    """Share of the squared error of q and relative error by (theta_i, theta_o) band."""
    nb = len(edges) - 1
    cc = (wi[:, 2] * wo[:, 2])[:, None]
    err2 = np.sum(w[:, None] * ((fh - f) * cc) ** 2, axis=1)
    ref2 = np.sum(w[:, None] * (f * cc) ** 2, axis=1)
    bi = np.clip(np.searchsorted(edges, np.arccos(np.clip(wi[:, 2], -1, 1))) - 1, 0, nb - 1)
    bo = np.clip(np.searchsorted(edges, np.arccos(np.clip(wo[:, 2], -1, 1))) - 1, 0, nb - 1)
    e = np.zeros((nb, nb))
    r = np.zeros((nb, nb))
    np.add.at(e, (bi, bo), err2)
    np.add.at(r, (bi, bo), ref2)
    total = e.sum()
    share = e / total if total > 0 else np.zeros_like(e)
    rel = np.full_like(e, np.nan)
    np.divide(e, r, out=rel, where=r > 0)
    return share, np.sqrt(rel)


def _truncations(cm: CoefficientMatrix, pairs: Any) -> list[dict[str, Any]]:
    f = _values(cm, pairs.wi, pairs.wo)
    rows = []
    orders = sorted({int(o) for o in np.linspace(0, cm.order, min(cm.order + 1, 7))})
    for o in orders:
        t = cm if o == cm.order else truncate(cm, o)
        err = _rel_l2(f, _values(t, pairs.wi, pairs.wo), pairs)
        rows.append({"label": f"truncated to order {o}", "family": cm.basis.kind,
                     "dtype": "float64", "bytes": 8 * unique_coefficients(t), "l2": err,
                     "log": math.nan, "status": "measured"})
    return rows


def _in_plane(meas: Any, ti: float, tol_deg: float = 3.0) -> tuple[NDArray, NDArray]:
    """Return the samples near the plane of incidence at ``ti``: signed theta_o, f cos theta_o."""
    wi, wo = meas.wi, meas.wo
    near_i = np.abs(np.arccos(np.clip(wi[:, 2], -1, 1)) - ti) < math.radians(tol_deg)
    # the plane of incidence: wo's azimuth equals wi's (back) or wi's + pi (mirror side)
    phi_i = np.arctan2(wi[:, 1], wi[:, 0])
    phi_o = np.arctan2(wo[:, 1], wo[:, 0])
    d = np.angle(np.exp(1j * (phi_o - phi_i)))
    sin_o = np.hypot(wo[:, 0], wo[:, 1])
    tol = math.radians(tol_deg)
    back = np.abs(d) * sin_o < tol
    front = (math.pi - np.abs(d)) * sin_o < tol
    keep = near_i & (back | front)
    theta_o = np.arccos(np.clip(wo[keep, 2], -1, 1))
    signed = np.where(front[keep], theta_o, -theta_o)
    if ti == 0.0:
        signed = np.where(wo[keep, 0] <= 0, theta_o, -theta_o)
    return signed, np.asarray(meas.values)[keep].mean(axis=1) * np.cos(theta_o)


# -- figures ----------------------------------------------------------------------------------
def _img(fig: Any, alt: str, caption: str = "") -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI)
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    cap = f"<figcaption>{_e(caption)}</figcaption>" if caption else ""
    return (f"<figure><img src=\"data:image/png;base64,{data}\" alt=\"{_e(alt)}\">{cap}"
            f"</figure>")


def _band_map(fig: Any, ax: Any, values: NDArray, label: str, fmt: str) -> None:
    nb = values.shape[0]
    im = ax.imshow(values, origin="lower", cmap="viridis", aspect="equal",
                   extent=(0, nb, 0, nb))
    for i in range(nb):
        for j in range(nb):
            v = values[i, j]
            if np.isfinite(v):
                ax.text(j + 0.5, i + 0.5, fmt.format(v), ha="center", va="center",
                        fontsize=6, color="white" if v < np.nanmax(values) * 0.6 else "black")
    ticks = np.arange(nb + 1)
    ax.set_xticks(ticks, [f"{b:g}" for b in BANDS_DEG], fontsize=7)
    ax.set_yticks(ticks, [f"{b:g}" for b in BANDS_DEG], fontsize=7)
    ax.set_xlabel("theta_o (degrees)", fontsize=8)
    ax.set_ylabel("theta_i (degrees)", fontsize=8)
    ax.set_title(label, fontsize=8)
    fig.colorbar(im, ax=ax, shrink=0.8).ax.tick_params(labelsize=6)


def _chart(rows: list[dict], chosen: tuple | None, title: str) -> str:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9.0, 4.6), layout="constrained")
    ax = fig.add_subplot()
    fams = sorted({str(r.get("family", r.get("form", ""))) for r in rows})
    markers = "osD^v<>ph*"
    for k, fam in enumerate(fams):
        own = sorted((r for r in rows if str(r.get("family", r.get("form", ""))) == fam),
                     key=lambda r: r["bytes"])
        x = np.array([float(r["bytes"]) for r in own])
        y = np.array([max(float(r["l2"]), 1e-12) for r in own])
        ax.plot(x, y, marker=markers[k % len(markers)], ls="-", lw=0.8, ms=5,
                color=f"C{k % 10}", label=fam)
    if chosen is not None and _finite(chosen[0]) and _finite(chosen[1]):
        ax.plot([float(chosen[0])], [max(float(chosen[1]), 1e-12)], "o", ms=16, mfc="none",
                mec="k", mew=1.6, label=str(chosen[2]))
    for i, (name, size) in enumerate(PUBLISHED.items()):
        ax.axvline(size, color="0.3", ls=("--", ":")[i % 2], lw=1)
        ax.text(size * (0.96 if i == 0 else 1.04), 0.03, name, rotation=90,
                transform=ax.get_xaxis_transform(), fontsize=7, color="0.3", va="bottom",
                ha="right" if i == 0 else "left")
    ax.set_xscale("log")
    ax.set_yscale("log")
    sizes = [float(r["bytes"]) for r in rows] + list(PUBLISHED.values())
    if chosen is not None and _finite(chosen[0]):
        sizes.append(float(chosen[0]))
    ax.set_xlim(min(sizes) / 1.6, max(sizes) * 1.6)
    ax.set_xlabel("bytes (stored numbers)")
    ax.set_ylabel("relative L2 error of q (f cos cos)")
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False,
              title="family", title_fontsize=7)
    ax.set_title(f"{_short(title, 70)}: size against error", fontsize=9)
    return _img(fig, "Chart of bytes against relative L2 error for the candidate "
                     "representations, the chosen one circled, published sizes as vertical "
                     "lines")


# -- text -------------------------------------------------------------------------------------
_CSS = """
:root { --ink: #1b1b1b; --muted: #555; --rule: #d0d0d0; }
body { margin: 0; color: var(--ink); background: #fff;
  font: 15px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; }
main { max-width: 1120px; margin: 0 auto; padding: 1.2rem 1.4rem 3rem; }
h1 { font-size: 1.6rem; margin: 0.2rem 0 0.3rem; }
h2 { font-size: 1.25rem; margin: 1.8rem 0 0.5rem; border-bottom: 1px solid var(--rule);
  padding-bottom: 0.2rem; }
h3 { font-size: 1.05rem; margin: 1.1rem 0 0.4rem; }
p.lead { color: var(--muted); margin-top: 0; }
table { border-collapse: collapse; margin: 0.4rem 0 0.8rem; font-size: 0.9rem; }
th, td { text-align: left; padding: 0.18rem 0.7rem 0.18rem 0; vertical-align: top;
  border-bottom: 1px solid #eee; }
th { font-weight: 600; border-bottom: 1px solid var(--rule); }
td:first-child { white-space: nowrap; }
td.num { font-variant-numeric: tabular-nums; }
figure { margin: 0.6rem 0 1rem; }
figcaption { color: var(--muted); font-size: 0.88rem; max-width: 62rem; }
img { max-width: 100%; height: auto; display: block; }
details summary { cursor: pointer; color: var(--muted); }
code { font-size: 0.9em; }
@media print {
  body { font-size: 10pt; }
  main { max-width: none; padding: 0; }
  section, figure, table { break-inside: avoid; page-break-inside: avoid; }
  h2 { break-after: avoid; page-break-after: avoid; }
  details > *:not(summary) { display: block; }
  details summary { display: none; }
  img { max-width: 100% !important; }
}
"""


def _e(text: str) -> str:
    return html.escape(str(text), quote=True)


def _p(text: str) -> str:
    return f"<p>{_e(text)}</p>" if text else ""


def _finite(x: Any) -> bool:
    return isinstance(x, int | float | np.floating | np.integer) and not isinstance(x, bool) \
        and math.isfinite(float(x))


def _num(x: Any) -> str:
    """Four significant digits; "n/a" for None and non-finite numbers."""
    return f"{float(x):.4g}" if _finite(x) else "n/a"


def _short(text: str, width: int = 160) -> str:
    text = " ".join(text.split())
    return text if len(text) <= width else text[:width - 3] + "..."


def _table(head: list[str], rows: Sequence[Sequence[str]], *, raw: bool = False) -> str:
    """Format an HTML table; cells are escaped unless ``raw`` (already escaped)."""
    cell = (lambda c: str(c)) if raw else _e
    out = ["<table><thead><tr>", *(f"<th>{_e(h)}</th>" for h in head), "</tr></thead><tbody>"]
    for r in rows:
        out.append("<tr>" + "".join(f"<td>{cell(c)}</td>" for c in r) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def _provenance(info: Any) -> str:
    if not isinstance(info, Mapping) or not info:
        return "<p>None recorded.</p>"
    rows = []
    for k, v in info.items():
        if k == "candidates" and isinstance(v, list):
            text = f"{len(v)} rows (section 5)"
        elif k == "selected" and isinstance(v, Mapping):
            text = (f"{v.get('label')} at {v.get('dtype')}: {v.get('bytes')} bytes, "
                    f"l2 {_num(v.get('l2'))}")
        elif isinstance(v, float):
            text = _num(v)
        elif isinstance(v, int) and not isinstance(v, bool):
            text = f"{v:,}"
        elif isinstance(v, Mapping):
            text = ", ".join(f"{a}: {_num(b) if isinstance(b, float) else b}"
                             for a, b in v.items())
        elif isinstance(v, np.ndarray):
            text = np.array2string(v, precision=4, threshold=8)
        else:
            text = str(v)
        rows.append((str(k), _short(text, 300)))
    return _table(["info key", "value"], rows)
