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

import os
import time
import warnings
from pathlib import Path
from typing import Any

from project.io import atomic_path

from ._html import _notes
from ._numbers import _band_errors as _band_errors  # tests check it against a closed form
from ._numbers import image_error
from ._page import _Page
from ._read import read_source
from ._settings import BANDS_DEG as BANDS_DEG
from ._settings import ERROR_PAIRS as ERROR_PAIRS
from ._settings import (
    INCIDENCE_DEG,
    LIGHTS,
    PUBLISHED,
    REPORT_CANDIDATES,
)
from ._settings import RECIPROCITY_PAIRS as RECIPROCITY_PAIRS
from ._settings import SPHERE_SIZE as SPHERE_SIZE

__all__ = ["INCIDENCE_DEG", "LIGHTS", "PUBLISHED", "REPORT_CANDIDATES", "image_error",
           "read_source", "report"]


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
    page = _notes(page, notes)
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
