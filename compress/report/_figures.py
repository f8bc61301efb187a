"""Figures of the report, drawn with matplotlib and inlined as PNG ``data:`` URIs.

Each function takes the numbers the page computed and returns a ``<figure>`` element (alt
text, and a caption where the figure needs one). Colour maps are perceptually uniform and
readable with colour-vision deficiencies: viridis for values, the diverging RdBu (Brewer) for
signed differences. matplotlib is imported inside the functions: it loads with the first
figure, not with the package.
"""

from __future__ import annotations

import base64
import io
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..render import tonemap
from ._html import _e, _finite, _short
from ._settings import _DECADES, _DPI, BANDS_DEG, INCIDENCE_DEG, LIGHTS, PUBLISHED


def _img(fig: Any, alt: str, caption: str = "") -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI)
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    cap = f"<figcaption>{_e(caption)}</figcaption>" if caption else ""
    return (f"<figure><img src=\"data:image/png;base64,{data}\" alt=\"{_e(alt)}\">{cap}"
            f"</figure>")


# -- 2. lobes ---------------------------------------------------------------------------------
def _polar_lobes(s: NDArray, curves: Sequence[tuple[NDArray, NDArray | None, Any]],
                 label: str, with_ref: bool) -> str:
    """Draw polar plots in the plane of incidence, one per angle of :data:`INCIDENCE_DEG`.

    ``curves`` holds, per angle, f cos theta_o at the signed theta_o ``s``, the same of the
    reference (or None) and the samples near the plane (signed theta_o, f cos theta_o; or
    None).
    """
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

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

        ax.plot(s, radius(f), color="#21918c", lw=1.6, label=label)
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
    return _img(fig, "Polar plots of f cos(theta_o) in the plane of incidence at "
                "incidence angles 0, 30, 60 and 75 degrees"
                + (", with the reference dashed" if with_ref else ""),
                "In the plane of incidence: f cos(theta_o) in 1/sr (the mean over the "
                "channels; the radiance reflected towards theta_o under unit "
                "irradiance) against theta_o in degrees. The light (grey arrow) is on "
                "the left, the mirror direction on the right."
                + (f" The radius is logarithmic over {_DECADES} decades below each "
                   "panel's peak (the lobes are sharp)." if log else "")
                + (" Reference dashed." if with_ref else ""))


def _heat_maps(maps: NDArray, names: Sequence[str], with_ref: bool) -> str:
    """Draw heat maps over the outgoing hemisphere: ``maps[row, angle]``, NaN off the disc."""
    from matplotlib.colors import LogNorm
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 0.6 + 2.6 * len(names)), layout="constrained")
    axes = fig.subplots(len(names), len(INCIDENCE_DEG), squeeze=False)
    for k, ti_deg in enumerate(INCIDENCE_DEG):
        col = maps[:, k]
        top = float(np.nanmax(col)) if np.any(col > 0) else 1.0
        norm = LogNorm(vmin=top * 1e-3, vmax=top)
        for r, name in enumerate(names):
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
                + (", the representation above the reference" if with_ref else ""),
                "Over the outgoing hemisphere, seen from above (orthographic: x = "
                "sin(theta_o) cos(phi_o), y = sin(theta_o) sin(phi_o)): f cos(theta_o) "
                "in 1/sr, log colour scale over three decades, one scale per column. "
                "The light is at phi_i = 180 deg (left); + marks the mirror direction."
                + (" Top row: this representation; bottom row: the reference."
                   if with_ref else ""))


# -- 3. spheres -------------------------------------------------------------------------------
def _spheres(mine: Sequence[NDArray], refs: Sequence[NDArray] | None, name: str) -> str:
    """Show spheres under :data:`LIGHTS`: ``mine`` (row ``name``), the reference, the difference."""
    from matplotlib.colors import TwoSlopeNorm
    from matplotlib.figure import Figure

    base = refs if refs is not None else mine
    finite = np.concatenate([b[np.isfinite(b)].ravel() for b in base])
    white = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    exposure = 1.0 / white if white > 0 else 1.0
    rows = [(name, mine)]
    if refs is not None:
        rows.append(("reference", refs))
    fig = Figure(figsize=(7.5, 0.5 + 2.4 * (len(rows) + (refs is not None))),
                 layout="constrained")
    nrow = len(rows) + (refs is not None)
    axes = fig.subplots(nrow, len(LIGHTS), squeeze=False)
    names = ("light at the view", "light 45 deg right", "light 75 deg up")
    for r, (row, imgs) in enumerate(rows):
        for k, img in enumerate(imgs):
            shown = tonemap(img, exposure, background=1.0)
            if shown.ndim == 3 and shown.shape[2] != 3:
                shown = shown.mean(axis=2)
            ax = axes[r, k]
            ax.imshow(shown, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            if r == 0:
                ax.set_title(names[k], fontsize=8)
            if k == 0:
                ax.text(-0.04, 0.5, row, rotation=90, ha="right", va="center",
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
    return _img(fig, alt, cap)


# -- 4. where the error lives -----------------------------------------------------------------
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


def _band_errors_figure(share: NDArray, rel: NDArray) -> str:
    """Map the share of the squared error of q and the relative error by band, side by side."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4.0), layout="constrained")
    a1, a2 = fig.subplots(1, 2)
    _band_map(fig, a1, 100 * share, "share of the squared error of q (%)", "{:.1f}")
    _band_map(fig, a2, rel, "relative L2 error of q within the band", "{:.2g}")
    fig.suptitle("Error of q = f cos(theta_i) cos(theta_o) by (theta_i, theta_o) "
                 "band, all channels", fontsize=9)
    return _img(fig, "Heat maps of the error of q by band of theta_i and "
                     "theta_o: share of the squared error and relative error")


def _negative_figure(fraction: NDArray) -> str:
    """Map the fraction of each band where an expansion is negative."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.2, 4.0), layout="constrained")
    ax = fig.add_subplot()
    _band_map(fig, ax, 100 * fraction, "negative fraction within the band (%)", "{:.1f}")
    return _img(fig, "Heat map of the fraction of each (theta_i, theta_o) band "
                     "where the expansion is negative")


# -- 5. resolution against error --------------------------------------------------------------
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


# -- 6. measurements --------------------------------------------------------------------------
def _measurements(x: NDArray, q: NDArray, res: NDArray, tdeg: NDArray) -> str:
    """Plot samples and residuals against signed theta_o ``x`` (degrees), coloured by theta_i."""
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4.0), layout="constrained")
    a1, a2 = fig.subplots(1, 2)
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
    return _img(fig, "Scatter plots of the measured values and of the residuals of "
                     "the fit against theta_o, coloured by theta_i")
