"""The page of :func:`compress.report.report`: what each section computes and says.

:class:`_Page` holds the input, the reference and what the sections share (the pairs of
the error estimates, the errors, the reciprocity estimate); each section is one method
returning its HTML, in the order of the page. The figures are drawn in ``_figures``.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

import project
from basis import CoefficientMatrix
from project.crossval import sample_errors
from project.sampling import brdf_errors, peak_resolving_pairs

from ..hybrid import Hybrid
from ..render import render_sphere
from ..truncate import PRECISIONS
from ._figures import (
    _band_errors_figure,
    _chart,
    _heat_maps,
    _measurements,
    _negative_figure,
    _polar_lobes,
    _spheres,
)
from ._html import _document, _e, _finite, _num, _p, _provenance, _short, _table
from ._numbers import (
    _band_errors,
    _image_error,
    _in_plane,
    _negative_fractions,
    _reals,
    _rel_l2,
    _rounded,
    _truncations,
    _values,
)
from ._read import _describe, _header, _kind, read_source
from ._settings import (
    _HEAT,
    _SAMPLE_CANDIDATES,
    _SEED,
    _VIEW,
    BANDS_DEG,
    ERROR_PAIRS,
    INCIDENCE_DEG,
    LIGHTS,
    RECIPROCITY_PAIRS,
    REPORT_CANDIDATES,
    SHOWN_NM,
    SPHERE_SIZE,
)


def _three_channels(meas: Any) -> tuple[Any, str]:
    """Return ``meas`` at three of its channels, and the sentence that says which.

    A fit of every channel of a spectral table (31 wavelengths: 64 parameters, ten folds)
    takes minutes and shows no more than three do: the measured wavelengths nearest to
    :data:`SHOWN_NM` are kept (their values as measured), or without wavelengths the first,
    middle and last channels.
    """
    if meas.wavelengths is not None:
        lam = np.asarray(meas.wavelengths, dtype=np.float64)
        keep = sorted({int(np.argmin(np.abs(lam - nm))) for nm in SHOWN_NM})
        what = ", ".join(f"{lam[k]:g}" for k in keep) + " nm"
    else:
        n = meas.channels
        keep = sorted({0, n // 2, n - 1})
        what = "channels " + ", ".join(str(k) for k in keep)
    names = meas.channel_names
    sub = project.Measurements(
        meas.wi, meas.wo, meas.values[:, keep], weights=meas.weights,
        wavelengths=None if meas.wavelengths is None else np.asarray(meas.wavelengths)[keep],
        channel_names=None if names is None else tuple(names[k] for k in keep),
        isotropic=meas.isotropic, name=getattr(meas, "name", None),
        source=getattr(meas, "source", None))
    return sub, (f" The file holds {meas.channels} channels; this page fits and shows "
                 f"{len(keep)} of them ({what}).")


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
        self.channel_note = ""
        if self.meas is not None and self.meas.channels > len(SHOWN_NM):
            self.meas, self.channel_note = _three_channels(self.meas)
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
        for name, step in steps:
            if bar is not None:
                bar.set_description(f"report: {name}")
            parts.append(step())
            if bar is not None:
                bar.update(1)
        if bar is not None:
            bar.close()
        body = "\n".join(p for p in parts if p)
        from basis import __version__

        seconds = time.perf_counter() - start
        return _document(self.title, f"{_e(self.kind)}{self._compared()}. Written by "
                         f"scatmodes {_e(__version__)} in {seconds:.1f} s.", body)

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
                         "samples)." + self.channel_note)
        return ""

    # -- 1. summary ---------------------------------------------------------------------------
    def _summary(self) -> str:
        rows: list[tuple[str, str]] = [("form", self.kind)]
        if hasattr(self.rep, "family") and hasattr(self.rep, "params"):
            rows.append(("family", f"{self.rep!r}"))
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
        polar = _polar_lobes(s, curves, self._label(), ref is not None)
        heat = self._heat_maps()
        return (f"<section id=\"lobes\"><h2>2. Lobes</h2><p>The scattering lobe at four "
                f"incidence angles: a cut through the plane of incidence, and the whole "
                f"outgoing hemisphere seen from above.</p>{polar}{heat}</section>")

    def _label(self) -> str:
        return "fit" if self.meas is not None else "this representation"

    def _heat_maps(self) -> str:
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
        return _heat_maps(maps, [name for name, _ in rows], self.ref is not None)

    # -- 3. spheres ---------------------------------------------------------------------------
    def _spheres(self) -> str:
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
        figure = _spheres(mine, refs, "this representation" if self.meas is None else "fit")
        return f"<section id=\"spheres\"><h2>3. Spheres</h2>{extra}{figure}</section>"

    # -- 4. where the error lives -------------------------------------------------------------
    def _bands(self) -> str:
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
            parts.append(f"<p>On {_e(how)}. Left: where the squared error is (the shares "
                         f"sum to 100 %); right: how large it is relative to q in each "
                         f"band.</p>")
            parts.append(_band_errors_figure(share, rel))
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
        frac, by_band = _negative_fractions(expansion, wi, wo, w, np.radians(BANDS_DEG))
        text = (f"<p>Fraction of H x H (solid angle) where the expansion is negative in some "
                f"channel: <strong>{_num(frac)}</strong> ({_num(100 * frac)} %).</p>")
        if frac == 0.0:
            return text
        return text + _negative_figure(by_band)

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
        from ..selection import select

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
        ti, phi_i, to, phi_o = m.angles()
        # theta_o signed by the side of the plane of incidence: + towards the mirror
        side = np.where(np.cos(phi_o - phi_i) <= 0.0, 1.0, -1.0)
        x = np.degrees(to) * side
        v = np.asarray(m.values)
        q = v.mean(axis=1) * np.cos(to)
        fh = _values(self.shown, m.wi, m.wo)
        res = (fh - v).mean(axis=1) * np.cos(to)
        e = sample_errors(m, fh)
        figure = _measurements(x, q, res, np.degrees(ti))
        who = "fit" if self.meas is not None else "representation"
        rows = [("samples", f"{len(m):,} x {m.channels} channel(s)"),
                (f"l2 error of the {who} at the samples (all used in the fit)"
                 if self.meas is not None else "l2 error at the samples",
                 f"{_num(e['l2'])} +- {_num(e['l2_stderr'])}"),
                ("log error at the samples", _num(e["log"])),
                ("largest |residual|", f"{_num(float(np.max(np.abs(fh - v))))} 1/sr")]
        return (f"<section id=\"measurements\"><h2>6. Measurements</h2>{figure}"
                f"{_table(['quantity', 'value'], rows)}</section>")
