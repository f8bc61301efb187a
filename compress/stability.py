"""Where each method breaks: a stability atlas.

Seven measurements, one function each, every one returning an :class:`Atlas` (a table with
``to_markdown()`` and ``plot(path)``); :func:`write_all` writes them all. Every fact in the
tables is computed when the function runs, nothing is assumed:

1. :func:`radial_accuracy`: digits kept by the textbook factorial formula, a naive power
   series and the library's recurrences, against mpmath, for the hemisphere Zernike radial
   polynomials (to order 300) and the spherical harmonics (to degree 2000), near the pole, in
   the interior and near the horizon.
2. :func:`hemisphere_conditioning`: condition number of the BRDF least-squares problem in
   full-sphere harmonics against the hemisphere bases, and the resulting fit error.
3. :func:`sparse_fits`: fit error against samples per unknown and noise for each order (the
   brick case of Koenderink, van Doorn & Stavridi 1996, sec. 6, is 66 measurements for 55
   unknowns at order 8), with and without Tikhonov regularisation (the best weight in
   hindsight, and the one ``project.fit`` chooses from the data), and what the condition
   number predicts.
4. :func:`sharp_lobes`: truncation and quadrature error against roughness and order, Gibbs
   ringing with and without each filter, and the grazing amplification of f = q / (cos cos).
5. :func:`monte_carlo`: microgeometry simulation error and Westin's Q against rays, noise
   per degree, and the bias of a too coarse height field.
6. :func:`fit_stability`: the spread of the final costs of :func:`project.fit_model` over
   restarts for each parametric family (Lafortune with 1, 2, 3 lobes, Lambert + GGX,
   DSBRDF, RR-8807), and how often the restarts reach the best minimum.
7. :func:`reciprocity_floors`: on non-reciprocal BRDFs with a closed-form floor
   (:class:`NonReciprocalDiffuse`), the floor measured by :func:`project.reciprocity`
   against the closed form, and the error of every reciprocal form (symmetric matrices,
   half-turn factored lobes and tables), which cannot go below it, and of its general
   counterpart (general matrices, full-turn lobes and tables), which can.

The "textbook factorial formula" and the "naive power series" of item 1 are implemented here
on purpose, as the unstable baselines being measured: they are not used anywhere else.
mpmath (a test extra) is needed by :func:`radial_accuracy` only and imported there.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

import basis
import project
from basis.validation import dask_client, nonneg_int
from project.io import atomic_path

from .evaluate import evaluate
from .study import isotropic_pairs, make_basis
from .truncate import SMOOTHING, ringing, smooth

__all__ = ["FIT_CASES", "NONRECIPROCAL_FAMILIES", "Atlas", "NonReciprocalDiffuse", "Panel",
           "fit_stability", "hemisphere_conditioning", "monte_carlo", "nonreciprocal_floor",
           "radial_accuracy", "reciprocity_floors", "sharp_lobes", "sparse_fits", "write_all"]

EPS = float(np.finfo(np.float64).eps)

#: Polar angles (radians) of the three regions of item 1.
REGIONS = {
    "pole": (1e-3, 5e-3, 2e-2),
    "interior": (0.4, 0.8, 1.2),
    "horizon": (np.pi / 2 - 2e-2, np.pi / 2 - 5e-3, np.pi / 2 - 1e-3),
}
#: References smaller than this are not representable with headroom in float64: skipped.
_TINY_REF = 1e-280


# -- the table ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Panel:
    """One chart panel: ``y`` against ``x``, one line per value of ``group``.

    ``group`` is a column or a tuple of columns; the panel shows the rows of ``table``
    matching ``where``.
    """

    x: str
    y: str
    group: str | tuple[str, ...] = ()
    where: dict[str, Any] = field(default_factory=dict)
    title: str = ""
    logx: bool = False
    logy: bool = False
    table: str = "main"


@dataclass
class Atlas:
    """A measured table: rows of dicts, findings, and how to chart them.

    Attributes
    ----------
    title : str
    rows : list of dict
        The main table (one dict per row, the same keys in every row).
    tables : dict of str to list of dict
        Further tables (e.g. ``"grazing"``), rendered after the main one.
    facts : dict of str to float
        Named summary numbers computed from the rows (what the tests pin).
    notes : list of str
        The findings in words, with the numbers.
    panels : list of Panel
    """

    title: str
    rows: list[dict[str, Any]]
    tables: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    facts: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    panels: list[Panel] = field(default_factory=list)

    def _table(self, table: str) -> list[dict[str, Any]]:
        if table == "main":
            return self.rows
        if table not in self.tables:
            raise ValueError(f"table must be 'main' or one of {sorted(self.tables)}, got "
                             f"{table!r}")
        return self.tables[table]

    def select(self, table: str = "main", **where: Any) -> list[dict[str, Any]]:
        """Return the rows whose columns equal the given values."""
        return [r for r in self._table(table) if all(r.get(k) == v for k, v in where.items())]

    def column(self, name: str, table: str = "main", **where: Any) -> NDArray:
        """Return one column of the matching rows as an array (float when numeric)."""
        vals = [r[name] for r in self.select(table, **where)]
        try:
            return np.array([np.nan if v is None else v for v in vals], dtype=np.float64)
        except (TypeError, ValueError):
            return np.array(vals, dtype=object)

    def to_markdown(self) -> str:
        """Render the tables as GitHub markdown, the findings first."""
        out = [f"## {self.title}", ""]
        out += [f"- {n}" for n in self.notes]
        out += ["", _markdown(self.rows)]
        for name, rows in self.tables.items():
            out += ["", f"### {name}", "", _markdown(rows)]
        return "\n".join(out) + "\n"

    def plot(self, path: str | Path) -> Path:
        """Write one PNG with a panel per :class:`Panel` (atomically); returns the path."""
        from matplotlib.figure import Figure  # no pyplot: the user's backend is left alone

        n = max(1, len(self.panels))
        cols = min(3, n)
        nrows = -(-n // cols)
        fig = Figure(figsize=(5.2 * cols, 4.0 * nrows))
        axes = fig.subplots(nrows, cols, squeeze=False)
        for ax, p in zip(axes.flat, self.panels, strict=False):
            rows = self.select(p.table, **p.where)
            keys = (p.group,) if isinstance(p.group, str) else tuple(p.group)
            labels = dict.fromkeys(tuple(r[k] for k in keys) for r in rows)
            for lab in labels:
                sel = [r for r in rows if tuple(r[k] for k in keys) == lab]
                x = np.array([r[p.x] for r in sel], dtype=float)
                y = np.array([np.nan if r[p.y] is None else r[p.y] for r in sel], dtype=float)
                if p.logy:
                    y = np.where(y > 0, y, np.nan)
                order = np.argsort(x)
                ax.plot(x[order], y[order], "o-", ms=3,
                        label=" ".join(str(v) for v in lab) or None)
            ax.set_xscale("log" if p.logx else "linear")
            ax.set_yscale("log" if p.logy else "linear")
            ax.set_xlabel(p.x)
            ax.set_ylabel(p.y)
            ax.set_title(p.title, fontsize=9)
            ax.grid(True, which="both", alpha=0.3)
            if keys:
                ax.legend(fontsize=7)
        for ax in list(axes.flat)[len(self.panels):]:
            ax.set_visible(False)
        fig.suptitle(self.title, fontsize=10)
        fig.tight_layout()
        with atomic_path(path, suffix=".png") as tmp:
            fig.savefig(tmp, format="png", dpi=80)
        return Path(path)


def _fmt(v: Any) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool | np.bool_):
        return str(bool(v))
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        return "nan" if np.isnan(v) else f"{float(v):.3g}"
    return str(v)


def _markdown(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return "(no rows)"
    head = list(rows[0])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(_fmt(r.get(k)) for k in head) + " |" for r in rows]
    return "\n".join(lines)


# -- item 1: radial and angular functions at high order ---------------------------------------
def _mpmath():
    try:
        import mpmath
    except ImportError:
        raise ImportError("radial_accuracy needs mpmath for its reference values; install it "
                          "with `pip install mpmath` (it is in the test extra: "
                          "`pip install scatmodes[test]`)") from None
    return mpmath


def zernike_factorial(n: int, l: int, rho: float) -> float:
    """Evaluate R_n^l(rho) by the textbook factorial sum, in float64 (an unstable baseline).

    sum_s (-1)^s (n - s)! / (s! ((n + l)/2 - s)! ((n - l)/2 - s)!) rho^(n - 2 s), every
    factorial a float64 (inf beyond 170!, so the result is NaN from n = 171).
    """
    from scipy.special import factorial

    k = (n - l) // 2
    total = 0.0
    with np.errstate(all="ignore"):
        for s in range(k + 1):
            c = factorial(n - s) / (factorial(s) * factorial((n + l) // 2 - s)
                                    * factorial(k - s))
            total += (-1.0) ** s * c * rho ** (n - 2 * s)
    return float(total)


def zernike_power(n: int, l: int, rho: float) -> float:
    """Evaluate R_n^l(rho) by the naive power series (an unstable baseline).

    R_n^l(rho) is rho^l times a polynomial in rho^2 with exact integer coefficients rounded
    once to float64, evaluated by Horner's rule.
    """
    k = (n - l) // 2
    acc = 0.0
    r2 = rho * rho
    with np.errstate(all="ignore"):
        for s in range(k + 1):  # highest power first
            c = math.factorial(n - s) // (math.factorial(s) * math.factorial((n + l) // 2 - s)
                                          * math.factorial(k - s))
            acc = acc * r2 + (-1.0) ** s * _to_float(c)
        return float(acc * rho**l)


def _to_float(c: int) -> float:
    try:
        return float(c)
    except OverflowError:
        return math.inf


def sh_factorial(l: int, m: int, z: float, s: float) -> float:
    """Evaluate the real orthonormal Y_lm at phi = 0 by the textbook formulas (unstable baseline).

    In float64: N_lm = sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!) and the explicit Legendre sum
    P_l^m = s^m 2^-l sum_k (-1)^k (2l-2k)! / (k! (l-k)! (l-2k-m)!) z^(l-2k-m), every factorial a
    float64 (so NaN once 2l > 170).
    """
    from scipy.special import factorial

    with np.errstate(all="ignore"):
        norm = np.sqrt((2 * l + 1) / (4 * np.pi) * factorial(l - m) / factorial(l + m))
        total = 0.0
        for k in range((l - m) // 2 + 1):
            c = factorial(2 * l - 2 * k) / (factorial(k) * factorial(l - k)
                                            * factorial(l - 2 * k - m)) / np.float64(2.0) ** l
            total += (-1.0) ** k * c * z ** (l - 2 * k - m)
        v = norm * total * s**m
    return float(v * (math.sqrt(2.0) if m else 1.0))


def sh_power(l: int, m: int, z: float, s: float) -> float:
    """Evaluate the real orthonormal Y_lm at phi = 0 by the naive power series (unstable baseline).

    Y_lm is s^m times a polynomial in z whose coefficients (normalisation included) are
    computed exactly and rounded once to float64, summed by Horner's rule; coefficients above
    1.8e308 overflow to inf.
    """
    mp = _mpmath()
    with mp.workdps(40):
        norm = mp.sqrt((2 * l + 1) / (4 * mp.pi) * mp.factorial(l - m) / mp.factorial(l + m))
        if m:
            norm *= mp.sqrt(2)
        norm /= mp.mpf(2) ** l
        coef = [float((-1) ** k * norm * mp.factorial(2 * l - 2 * k)
                      / (mp.factorial(k) * mp.factorial(l - k) * mp.factorial(l - 2 * k - m)))
                for k in range((l - m) // 2 + 1)]
    acc = 0.0
    with np.errstate(all="ignore"):
        for c in coef:
            acc = acc * (z * z) + c
        return float(acc * z ** ((l - m) % 2) * s**m)


def _zernike_ref(mp, n: int, l: int, rho: float):
    r = mp.mpf(rho)
    return r**l * mp.jacobi((n - l) // 2, 0, l, 2 * r * r - 1)


def _sh_ref(mp, l: int, m: int, d: NDArray):
    """Real Y_lm (phi = 0) at the exact float64 vector d (hypergeometric form of P_l^m)."""
    x, y, zz = (mp.mpf(float(v)) for v in d)
    r = mp.sqrt(x * x + y * y + zz * zz)
    z, s = zz / r, mp.sqrt(x * x + y * y) / r
    f = mp.hyp2f1(m - l, m + l + 1, m + 1, (1 - z) / 2)
    log_c = (mp.loggamma(l + m + 1) - mp.loggamma(l - m + 1)) / 2 - mp.loggamma(m + 1)
    v = mp.sqrt((2 * l + 1) / (4 * mp.pi)) * mp.exp(log_c) * mp.ldexp(1, -m) * s**m * f
    return v * mp.sqrt(2) if m else v


def _digits(rel: float) -> float:
    if not np.isfinite(rel):
        return 0.0
    return float(np.clip(-np.log10(max(rel, 1e-17)), 0.0, 16.0))


def radial_accuracy(*, zernike_orders: Sequence[int] = (10, 20, 40, 60, 80, 100, 150, 200, 300),
                    sh_degrees: Sequence[int] = (10, 20, 40, 60, 85, 100, 200, 500, 1000, 2000),
                    regions: dict[str, Sequence[float]] | None = None,
                    dps: int = 60) -> Atlas:
    """Measure the digits kept by three ways of evaluating the radial functions, against mpmath.

    Parameters
    ----------
    zernike_orders : sequence of int
        Radial degrees n of R_n^l (l = n mod 2, "low", and l ~ n / 2, "mid").
    sh_degrees : sequence of int
        Degrees l of Y_lm (m = 0, "low", and m = l // 2, "mid").
    regions : dict of str to sequence of float, optional
        Polar angles (radians) per region; default :data:`REGIONS` (pole, interior, horizon).
        For Zernike rho = sqrt(2) sin(theta / 2).
    dps : int
        mpmath working precision (its hypergeometric series raise it further when terms
        cancel).

    Returns
    -------
    Atlas
        One row per (family, method, order, m, region): ``rel_error`` is the median over the
        region's points of |value - reference| / |reference| (points whose reference is
        below 1e-280, unrepresentable in float64, are left out; NaN if none remain),
        ``digits`` = -log10(rel_error) clipped to [0, 16] (0 for inf/NaN results).
        Methods: ``factorial`` (:func:`zernike_factorial`, :func:`sh_factorial`), ``power``
        (:func:`zernike_power`, :func:`sh_power`) and ``recurrence``
        (:func:`basis.zernike_radial`, :class:`basis.SphericalHarmonics`).

    Notes
    -----
    The references are evaluated at the exact float64 inputs (rho, or the direction vector),
    so input rounding is not counted as error; what remains is the method's own rounding and
    cancellation. The naive sums lose about log10(sum |c_j| x^j / |R|) digits to cancellation;
    the factorial form also overflows (NaN) once a factorial passes 170!.
    """
    mp = _mpmath()
    regions = dict(REGIONS if regions is None else regions)
    rows: list[dict[str, Any]] = []
    zorders = [nonneg_int(n, "zernike_orders") for n in zernike_orders]
    sdeg = [nonneg_int(n, "sh_degrees") for n in sh_degrees]
    with mp.workdps(dps):
        for n in zorders:
            mids = {"low": n % 2, "mid": n // 2 + ((n - n // 2) % 2)}
            for mlab, l in mids.items():
                for reg, thetas in regions.items():
                    rels: dict[str, list[float]] = {"factorial": [], "power": [],
                                                    "recurrence": []}
                    for th in thetas:
                        rho = float(np.sqrt(2.0) * np.sin(th / 2.0))
                        ref = _zernike_ref(mp, n, l, rho)
                        if abs(ref) < _TINY_REF:
                            continue
                        vals = {"factorial": zernike_factorial(n, l, rho),
                                "power": zernike_power(n, l, rho),
                                "recurrence": float(basis.zernike_radial(n, l, rho))}
                        for k, v in vals.items():
                            rels[k].append(_rel(mp, v, ref))
                    for meth, rr in rels.items():
                        rel = float(np.median(rr)) if rr else float("nan")
                        rows.append(dict(family="zernike", method=meth, order=n, m=mlab,
                                         azimuthal=l, region=reg, points=len(rr), rel_error=rel,
                                         digits=_digits(rel) if rr else float("nan")))
        if sdeg:
            sh = basis.SphericalHarmonics(max(sdeg))
            for reg, thetas in regions.items():
                per = {}
                for th in thetas:
                    d = np.array([np.sin(th), 0.0, np.cos(th)])
                    per[th] = (d, sh.eval(d))
                for l in sdeg:
                    for mlab, m in {"low": 0, "mid": l // 2}.items():
                        rels = {"factorial": [], "power": [], "recurrence": []}
                        for th in thetas:
                            d, y = per[th]
                            ref = _sh_ref(mp, l, m, d)
                            if abs(ref) < _TINY_REF:
                                continue
                            nrm = float(np.sqrt(d @ d))
                            z, s = d[2] / nrm, d[0] / nrm
                            vals = {"factorial": sh_factorial(l, m, z, s),
                                    "power": sh_power(l, m, z, s),
                                    "recurrence": float(y[l * l + l + m])}
                            for k, v in vals.items():
                                rels[k].append(_rel(mp, v, ref))
                        for meth, rr in rels.items():
                            rel = float(np.median(rr)) if rr else float("nan")
                            rows.append(dict(family="sh", method=meth, order=l, m=mlab,
                                             azimuthal=m, region=reg, points=len(rr),
                                             rel_error=rel,
                                             digits=_digits(rel) if rr else float("nan")))
    atlas = Atlas("1. Radial and angular functions at high order: digits kept against mpmath",
                  rows)
    facts = atlas.facts
    for fam, orders in (("zernike", zorders), ("sh", sdeg)):
        for meth in ("factorial", "power", "recurrence"):
            for n in orders:
                dig = atlas.column("digits", family=fam, method=meth, order=n)
                dig = dig[np.isfinite(dig)]
                if dig.size:
                    facts[f"{fam}/{meth}/min_digits@{n}"] = float(dig.min())
            good = [n for n in orders if facts.get(f"{fam}/{meth}/min_digits@{n}", 0.0) >= 10]
            bad = [n for n in orders if facts.get(f"{fam}/{meth}/min_digits@{n}", 16.0) < 10]
            first_bad = min(bad) if bad else None
            facts[f"{fam}/{meth}/first_order_below_10_digits"] = \
                float("nan") if first_bad is None else float(first_bad)
            atlas.notes.append(
                f"{fam} {meth}: worst-case digits {_fmt_digits(facts, fam, meth, orders)}; "
                + (f"first order with < 10 digits: {first_bad}" if first_bad is not None
                   else f"keeps >= 10 digits up to {max(good) if good else '-'}"))
    pole = atlas.column("digits", family="zernike", method="power", region="pole")
    if pole.size:
        atlas.notes.append("near the pole (small rho, small x^j) the naive sums keep "
                           f"{np.nanmin(pole):.1f}+ digits for Zernike: cancellation needs "
                           "large terms, which only the interior and the rim produce")
    atlas.panels = [Panel("order", "digits", ("method", "m"), {"family": fam, "region": reg},
                          f"{fam}, {reg}", logx=True)
                    for fam in ("zernike", "sh") for reg in regions]
    return atlas


def _rel(mp, v: float, ref) -> float:
    if not np.isfinite(v):
        return float("inf")
    return float(abs((mp.mpf(v) - ref) / ref))


def _fmt_digits(facts: dict[str, float], fam: str, meth: str, orders: Sequence[int]) -> str:
    return ", ".join(f"{n}: {facts[f'{fam}/{meth}/min_digits@{n}']:.1f}" for n in orders
                     if f"{fam}/{meth}/min_digits@{n}" in facts)


# -- shared helpers for the fits -----------------------------------------------------------------
def _uniform_pairs(rng: np.random.Generator, n: int) -> tuple[NDArray, NDArray]:
    out = []
    for _ in range(2):
        z = rng.uniform(0.0, 1.0, n)
        phi = rng.uniform(0.0, 2.0 * np.pi, n)
        s = np.sqrt((1.0 - z) * (1.0 + z))
        out.append(np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1))
    return out[0], out[1]


def _iso_design(b: basis.Basis, wi: NDArray, wo: NDArray) -> NDArray[np.float64]:
    """Build the isotropic design matrix of :func:`project.lstsq.design_matrix` for any basis.

    Full-sphere harmonics are included (``project.fit`` refuses them on purpose).
    """
    from project.lstsq import design_matrix

    return design_matrix(wi, wo, b, isotropic=True)


def _cond(a: NDArray) -> float:
    s = np.linalg.svd(a, compute_uv=False)
    return float(s[0] / s[-1]) if s.size and s[-1] > 0 else float("inf")


def _tikhonov(a: NDArray, y: NDArray, rel_lambdas: Sequence[float], *,
              with_cond: bool = False) -> Any:
    """Solve min ||a z - y||^2 + lambda ||z||^2 for lambda = t * s_max^2 for each t.

    t = 0 gives the pseudoinverse with numpy's rank tolerance, as project.fit; with
    ``with_cond`` the condition number of ``a`` is returned too (one SVD for both).
    """
    u, s, vt = np.linalg.svd(a, full_matrices=False)
    uty = u.T @ y
    tol = s[0] * max(a.shape) * EPS
    out = []
    for t in rel_lambdas:
        if t == 0:
            filt = np.where(s > tol, 1.0 / np.where(s > tol, s, 1.0), 0.0)
        else:
            filt = s / (s * s + t * s[0] ** 2)
        out.append(vt.T @ ((filt * uty.T).T))
    if with_cond:
        return out, float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    return out


def _default_brdf() -> Any:
    return project.models.CookTorrance(0.3, 0.5)


def _q(brdf: Any, wi: NDArray, wo: NDArray) -> NDArray[np.float64]:
    f = np.asarray(brdf.eval(wi, wo), dtype=np.float64).reshape(wi.shape[0], -1)[:, 0]
    return f * wi[:, 2] * wo[:, 2]


# -- item 2: full-sphere harmonics on hemisphere data -------------------------------------------
def hemisphere_conditioning(orders: Sequence[int] = tuple(range(1, 9)), *,
                            kinds: Sequence[str] = ("sh", "harmonics", "harmonics-even",
                                                    "zernike"),
                            oversample: float = 4.0, noise: float = 0.01, brdf: Any = None,
                            seed: int = 0) -> Atlas:
    """Measure the condition numbers of the hemisphere least-squares problem and the fit error.

    Parameters
    ----------
    orders : sequence of int
    kinds : sequence of str
        :data:`compress.study.KINDS`: "sh" (full sphere), "harmonics" (odd), "harmonics-even",
        "zernike".
    oversample : float
        Random pairs per unknown for the random-sample fit.
    noise : float
        Gaussian noise added to the samples, relative to their RMS.
    brdf : BRDF, optional
        Truth for the fits (default ``CookTorrance(0.3, 0.5)``); q = f cos cos is fitted.
    seed : int

    Returns
    -------
    Atlas
        Per (kind, order): ``unknowns`` (isotropic), ``cond_direction`` (one direction, basis
        values weighted by an exact hemisphere rule: 1 for an orthonormal basis),
        ``cond_pairs_rule`` (the isotropic BRDF design on the exact isotropic product rule
        of H x H, weighted), ``cond_pairs_random`` (unweighted, on ``oversample`` x unknowns
        uniform random pairs), ``fit_error`` (relative L2 error of q on H x H after fitting
        the noisy random samples by the pseudoinverse), ``fit_error_clean`` (the same
        without noise) and ``coef_norm`` (||coefficients|| / ||q||: large values mean
        cancelling coefficients, and expansions that blow up below the horizon).
    """
    brdf = _default_brdf() if brdf is None else brdf
    rng = np.random.default_rng(seed)
    rows = []
    for order in orders:
        order = nonneg_int(order, "orders")
        tw, to, tv = isotropic_pairs(max(12, order + 4), max(24, 2 * order + 4))
        qt = _q(brdf, tw, to)
        qnorm = float(np.sqrt(tv @ (qt * qt)))
        for kind in kinds:
            b = make_basis(kind, order)
            rule = basis.hemisphere_rule(order + 1, 2 * order + 1)
            cd = _cond(b.eval(rule.points) * np.sqrt(rule.weights)[:, None])
            wi, wo, wts = isotropic_pairs(order + 1, 2 * order + 2)
            a = _iso_design(b, wi, wo)
            cp = _cond(a * np.sqrt(wts)[:, None])
            n = int(np.ceil(oversample * a.shape[1]))
            ri, ro = _uniform_pairs(rng, n)
            ar = _iso_design(b, ri, ro)
            y = _q(brdf, ri, ro)
            yn = y + noise * float(np.sqrt(np.mean(y * y))) * rng.standard_normal(n)
            (zz,), cr = _tikhonov(ar, np.stack([yn, y], axis=1), [0.0], with_cond=True)
            z_noisy, z_clean = zz[:, 0], zz[:, 1]
            at = _iso_design(b, tw, to)
            errs = []
            for z in (z_noisy, z_clean):
                r = at @ z - qt
                errs.append(float(np.sqrt(tv @ (r * r))) / qnorm)
            rows.append(dict(kind=kind, order=order, unknowns=int(a.shape[1]), cond_direction=cd,
                             cond_pairs_rule=cp, cond_pairs_random=cr, samples=n,
                             noise=noise, fit_error=errs[0], fit_error_clean=errs[1],
                             coef_norm=float(np.linalg.norm(z_noisy)) / qnorm))
    atlas = Atlas("2. Hemisphere data in full-sphere harmonics versus the hemisphere bases", rows)
    for kind in kinds:
        for col in ("cond_direction", "cond_pairs_rule", "cond_pairs_random", "fit_error"):
            v = atlas.column(col, kind=kind)
            o = atlas.column("order", kind=kind)
            if v.size:
                atlas.facts[f"{kind}/{col}@{int(o[-1])}"] = float(v[-1])
                atlas.facts[f"{kind}/max_{col}"] = float(np.nanmax(v))
    top = max(orders)
    atlas.notes += [
        f"{k}: at order {top}, condition {atlas.facts.get(f'{k}/cond_direction@{top}', 0):.3g} "
        f"(one direction), {atlas.facts.get(f'{k}/cond_pairs_rule@{top}', 0):.3g} (BRDF pairs, "
        f"exact rule), {atlas.facts.get(f'{k}/cond_pairs_random@{top}', 0):.3g} (random pairs); "
        f"fit error {atlas.facts.get(f'{k}/fit_error@{top}', 0):.3g} at noise {noise:g}"
        for k in kinds]
    atlas.notes.append("full-sphere harmonics restricted to the hemisphere are nearly "
                       "dependent (their even and odd halves approximate the same functions): "
                       "the condition grows geometrically with the order, and the BRDF "
                       "problem, a product of two directions, squares it; the hemisphere "
                       "bases are orthonormal (condition 1 on an exact rule)")
    atlas.panels = [Panel("order", c, "kind", {}, c, logy=True)
                    for c in ("cond_direction", "cond_pairs_rule", "cond_pairs_random",
                              "fit_error", "coef_norm")]
    return atlas


# -- item 3: sparse and noisy measurements ----------------------------------------------------
def sparse_fits(orders: Sequence[int] = (4, 6, 8), *,
                ratios: Sequence[float] = (66 / 55, 2.0, 4.0, 16.0),
                noise: Sequence[float] = (0.0, 0.01, 0.05),
                rel_lambdas: Sequence[float] = tuple(10.0 ** np.arange(-8.0, 0.5, 1.0)),
                trials: int = 4, brdf: Any = None, seed: int = 0) -> Atlas:
    """Fit HemiZernike to scattered samples: error against samples, noise and regularisation.

    Parameters
    ----------
    orders : sequence of int
    ratios : sequence of float
        Samples per unknown (isotropic unknowns of ``HemiZernike(order)``); 66 / 55 is the
        brick case of Koenderink et al. (1996, sec. 6) at order 8.
    noise : sequence of float
        Gaussian noise relative to the RMS of the samples.
    rel_lambdas : sequence of float
        Tikhonov parameters relative to the largest squared singular value of the design
        matrix; the best of them (an oracle choice: it knows the truth) is reported. The
        automatic choice of ``project.fit`` (``regularization="auto"``: degree penalty,
        weight by 10-fold cross-validation on the samples) is reported beside it.
    trials : int
        Independent sample sets per cell; the table shows medians.
    brdf : BRDF, optional
        Truth (default ``CookTorrance(0.3, 0.5)``); q = f cos cos is fitted.
    seed : int

    Returns
    -------
    Atlas
        Per (order, ratio, noise): ``error`` (relative L2 error of the fitted coefficients
        against the quadrature projection at the same order: Parseval, so also the L2 error
        of q against the truncated expansion) by the pseudoinverse, ``error_regularized``
        (the best Tikhonov parameter), ``best_lambda``, ``gain`` (their ratio),
        ``error_auto`` (``project.fit`` with ``regularization="auto"``), ``gain_auto``
        (error / error_auto), ``auto_plain`` (fraction of trials where the automatic
        choice kept the plain fit), ``cond``
        (condition number of the design matrix), ``bound`` = cond x (relative data
        perturbation: noise plus the truncated tail seen by the samples), the perturbation
        bound on the relative coefficient error, and ``bound_ratio`` = error / bound.
    """
    from project.lstsq import to_unknowns

    brdf = _default_brdf() if brdf is None else brdf
    rng = np.random.default_rng(seed)
    lams = [0.0, *[float(t) for t in rel_lambdas]]
    rows = []
    for order in orders:
        b = basis.HemiZernike(nonneg_int(order, "orders"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            ref = to_unknowns(project.project(brdf, b, quantity="f_cos"))
        rnorm = float(np.linalg.norm(ref))
        u = ref.size
        for ratio in ratios:
            n = max(u, int(round(ratio * u)))
            for sig in noise:
                res = {k: [] for k in ("e0", "eb", "lam", "cond", "bound", "ea", "plain")}
                for _ in range(trials):
                    wi, wo = _uniform_pairs(rng, n)
                    a = _iso_design(b, wi, wo)
                    y = _q(brdf, wi, wo)
                    rms = float(np.sqrt(np.mean(y * y)))
                    yn = y + sig * rms * rng.standard_normal(n)
                    sols, cond = _tikhonov(a, yn, lams, with_cond=True)
                    e = [float(np.linalg.norm(z - ref)) / rnorm for z in sols]
                    k = int(np.argmin(e[1:])) + 1
                    pert = float(np.linalg.norm(yn - a @ ref)) / float(np.linalg.norm(a @ ref))
                    res["e0"].append(e[0])
                    res["eb"].append(min(e[0], e[k]))
                    res["lam"].append(lams[k] if e[k] < e[0] else 0.0)
                    res["cond"].append(cond)
                    res["bound"].append(cond * pert)
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", RuntimeWarning)
                        auto = project.fit(wi, wo, yn / (wi[:, 2] * wo[:, 2]), b,
                                           quantity="f_cos", regularization="auto")
                    res["ea"].append(float(np.linalg.norm(to_unknowns(auto) - ref)) / rnorm)
                    res["plain"].append(float(auto.info["regularization"] == 0.0))
                med = {k: float(np.median(v)) for k, v in res.items()}
                rows.append(dict(order=b.order, unknowns=u, samples=n, ratio=n / u, noise=sig,
                                 error=med["e0"], error_regularized=med["eb"],
                                 best_lambda=med["lam"], gain=med["e0"] / med["eb"],
                                 error_auto=med["ea"], gain_auto=med["e0"] / med["ea"],
                                 auto_plain=float(np.mean(res["plain"])),
                                 cond=med["cond"], bound=med["bound"],
                                 bound_ratio=med["e0"] / med["bound"]))
    atlas = Atlas("3. Sparse and noisy measurements (HemiZernike, isotropic, q = f cos cos)",
                  rows)
    for r in rows:
        key = f"{r['order']}/{r['samples']}/{r['noise']:g}"
        atlas.facts[f"error@{key}"] = r["error"]
        atlas.facts[f"gain@{key}"] = r["gain"]
        atlas.facts[f"gain_auto@{key}"] = r["gain_auto"]
        atlas.facts[f"cond@{key}"] = r["cond"]
        atlas.facts[f"bound_ratio@{key}"] = r["bound_ratio"]
    brick = [r for r in rows if r["order"] == 8 and r["samples"] == 66]
    for r in brick:
        atlas.notes.append(f"brick case (66 samples, 55 unknowns, noise {r['noise']:g}): "
                           f"condition {r['cond']:.3g}, error {r['error']:.3g} by the "
                           f"pseudoinverse, {r['error_regularized']:.3g} regularised "
                           f"(gain {r['gain']:.3g}), {r['error_auto']:.3g} with the weight "
                           f"project.fit chooses (gain {r['gain_auto']:.3g})")
    big = [r for r in rows if r["ratio"] >= 8 and r["noise"] > 0]
    if big:
        atlas.notes.append(f"with >= 8 samples per unknown the regularisation gain is at most "
                           f"{max(r['gain'] for r in big):.3g}: it matters only near "
                           "samples ~ unknowns")
        atlas.notes.append("with >= 8 samples per unknown project.fit's automatic choice kept "
                           f"the plain fit in {np.mean([r['auto_plain'] for r in big]):.0%} of "
                           "the trials")
    atlas.notes.append("the bound cond x relative perturbation holds in every row (bound_ratio "
                       f"<= {max(r['bound_ratio'] for r in rows):.3g}); it is pessimistic by "
                       "about the condition number when the noise is white")
    atlas.panels = [Panel("ratio", "error", ("order", "noise"), {}, "pseudoinverse", logx=True,
                          logy=True),
                    Panel("ratio", "error_regularized", ("order", "noise"), {},
                          "best Tikhonov (oracle)", logx=True, logy=True),
                    Panel("ratio", "error_auto", ("order", "noise"), {},
                          'project.fit(regularization="auto")', logx=True, logy=True),
                    Panel("ratio", "cond", "order", {"noise": noise[0]}, "condition number",
                          logx=True, logy=True)]
    return atlas


# -- item 4: sharp lobes ------------------------------------------------------------------
GRAZING_BANDS = ((0.0, 60.0), (60.0, 70.0), (70.0, 80.0), (80.0, 85.0), (85.0, 88.0),
                 (88.0, 89.5))


def sharp_lobes(roughness: Sequence[float] = (0.5, 0.25, 0.12), orders: Sequence[int] = (4, 8),
                *, quantities: Sequence[str] = ("f_cos", "f"), kind: str = "zernike",
                filters: Sequence[str] = SMOOTHING, kd: float = 0.0, grazing_order: int = 8,
                grazing_roughness: float = 0.3, pairs: int = 20000, seed: int = 0) -> Atlas:
    """Project ever sharper Cook-Torrance (Beckmann) lobes and measure what breaks.

    Measured: truncation, quadrature, Gibbs ringing with and without filters, and grazing
    amplification.

    Parameters
    ----------
    roughness : sequence of float
        Beckmann RMS slopes (0.05 is near-mirror).
    orders : sequence of int
    quantities : sequence of {"f_cos", "f"}
    kind : str
        Basis kind (:func:`compress.study.make_basis`).
    filters : sequence of str
        :data:`compress.truncate.SMOOTHING` kinds compared with no filter.
    kd : float
        Lambertian part of the model.
    grazing_order, grazing_roughness : int, float
        The f_cos projection whose division by cos(theta_i) cos(theta_o) is measured.
    pairs : int
        Random pairs (uniform in solid angle on H x H) for the grazing table and ringing.
    seed : int

    Returns
    -------
    Atlas
        Main table per (roughness, order, quantity, filter): ``truncation_error`` (relative
        L2, Parseval, of the unfiltered projection), ``nodes_needed`` (z nodes of the adaptive
        rule at tol 1e-6), ``quad_error_fixed`` (relative max coefficient error of the fixed
        rule of 2 (order + 1) z nodes x 4 (order + 1) azimuths against the adaptive result),
        ``negative_fraction`` and ``overshoot`` (:func:`compress.ringing`, theta < 80 deg).
        Table ``grazing``: per band of max(theta_i, theta_o), the RMS error of q and of
        f = q / (cos cos) relative to their RMS over all pairs, and ``amplification`` (their
        ratio; mean 1 / (cos cos) in the band predicts it).
    """
    rows = []
    for r0 in roughness:
        brdf = project.models.CookTorrance(kd, float(r0))
        for order in orders:
            b = make_basis(kind, order)
            for quantity in quantities:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    cm = project.project(brdf, b, quantity=quantity, max_nodes=512)
                    fixed = project.project(brdf, b, quantity=quantity,
                                            nodes=(2 * (order + 1), 4 * (order + 1)))
                qerr = _matrix_diff(fixed, cm)
                for filt in ("none", *filters):
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", RuntimeWarning)
                        c = cm if filt == "none" else smooth(cm, filt)
                        rg = ringing(c, brdf, pairs=min(pairs, 8192), seed=seed)
                    rows.append(dict(roughness=float(r0), order=order, quantity=quantity,
                                     filter=filt, truncation_error=cm.info["truncation_error"],
                                     nodes_needed=int(cm.info["nodes"][0]),
                                     quad_error_fixed=qerr,
                                     negative_fraction=rg.negative_fraction,
                                     overshoot=rg.overshoot))
    atlas = Atlas("4. Sharp lobes: truncation, quadrature, ringing and grazing", rows)
    # grazing amplification
    brdf = project.models.CookTorrance(kd, float(grazing_roughness))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        cm = project.project(brdf, make_basis(kind, grazing_order), quantity="f_cos")
    rng = np.random.default_rng(seed)
    wi, wo = _uniform_pairs(rng, nonneg_int(pairs, "pairs"))
    f = np.asarray(brdf.eval(wi, wo), dtype=np.float64).reshape(-1)
    fh = np.asarray(evaluate(cm, wi, wo, min_cos=1e-12), dtype=np.float64).reshape(-1)
    cc = wi[:, 2] * wo[:, 2]
    q, qh = f * cc, fh * cc
    rq, rf = float(np.sqrt(np.mean(q * q))), float(np.sqrt(np.mean(f * f)))
    top = np.degrees(np.arccos(np.minimum(wi[:, 2], wo[:, 2])))
    graz = []
    for lo, hi in GRAZING_BANDS:
        sel = (top >= lo) & (top < hi)
        if not sel.any():
            continue
        eq = float(np.sqrt(np.mean((qh[sel] - q[sel]) ** 2))) / rq
        ef = float(np.sqrt(np.mean((fh[sel] - f[sel]) ** 2))) / rf
        graz.append(dict(band=f"{lo:g}-{hi:g}", theta_max=hi, pairs=int(sel.sum()),
                         error_q=eq, error_f=ef, amplification=ef / eq if eq > 0 else np.nan,
                         mean_inv_cos=float(np.mean(1.0 / cc[sel]))))
    atlas.tables["grazing"] = graz
    # facts
    for r in rows:
        key = f"{r['roughness']:g}/{r['order']}/{r['quantity']}/{r['filter']}"
        atlas.facts[f"negative@{key}"] = r["negative_fraction"]
        if r["filter"] == "none":
            atlas.facts[f"truncation@{key}"] = r["truncation_error"]
            atlas.facts[f"quad_fixed@{key}"] = r["quad_error_fixed"]
    amp = {g["band"]: g["amplification"] for g in graz}
    inner = [g["amplification"] for g in graz if g["theta_max"] <= 60]
    outer = [g["amplification"] for g in graz if g["theta_max"] > 85]
    if inner and outer:
        atlas.facts["grazing/amplification_below_60"] = float(inner[0])
        atlas.facts["grazing/amplification_above_85"] = float(max(outer))
    atlas.notes.append("grazing amplification of the error of f = q / (cos cos) relative to "
                       "that of q: " + ", ".join(f"{k} deg {v:.3g}" for k, v in amp.items()))
    for quantity in quantities:
        for order in orders:
            t = [f"{r['roughness']:g}: {r['truncation_error']:.3g}" for r in rows
                 if r["filter"] == "none" and r["quantity"] == quantity and r["order"] == order]
            atlas.notes.append(f"truncation error, {quantity}, order {order}, by roughness: "
                               + ", ".join(t))
    for filt in filters:
        pairs_ = [(r, s) for r in rows if r["filter"] == "none" for s in rows
                  if s["filter"] == filt and all(s[k] == r[k] for k in
                                                 ("roughness", "order", "quantity"))]
        if pairs_:
            better = sum(s["negative_fraction"] < r["negative_fraction"] for r, s in pairs_)
            atlas.notes.append(f"filter {filt}: negative fraction lower than unfiltered in "
                               f"{better} of {len(pairs_)} cases")
    atlas.panels = [
        Panel("roughness", "truncation_error", ("quantity", "order"), {"filter": "none"},
              "L2 truncation error", logx=True, logy=True),
        Panel("roughness", "quad_error_fixed", ("quantity", "order"), {"filter": "none"},
              "error of a fixed 2(n+1) x 4(n+1) rule", logx=True, logy=True),
        Panel("roughness", "negative_fraction", ("filter", "order"), {"quantity": "f_cos"},
              "negative fraction (f_cos)", logx=True),
        Panel("theta_max", "amplification", (), {}, "grazing amplification (f from f_cos)",
              logy=True, table="grazing"),
    ]
    return atlas


def _matrix_diff(a: basis.CoefficientMatrix, b: basis.CoefficientMatrix) -> float:
    x, y = np.asarray(a.matrix), np.asarray(b.matrix)
    return float(np.max(np.abs(x - y)) / np.max(np.abs(y)))


# -- item 5: Monte Carlo -------------------------------------------------------------------------
def monte_carlo(rays: Sequence[int] = (2000, 8000, 32000), *, order: int = 6, seeds: int = 6,
                sigma: float = 1.0, tau: float = 4.0, resolution: int = 64,
                coarsen: Sequence[int] = (1, 2, 4), resolution_rays: int = 64000,
                surface_seed: int = 1) -> Atlas:
    """Measure the error of the microgeometry simulation.

    Measured: error and Q against rays, noise per degree, and the bias of a coarse height
    field.

    Parameters
    ----------
    rays : sequence of int
        Ray counts; each is run with ``seeds`` independent seeds.
    order : int
        ``HemiZernike`` order.
    sigma, tau, resolution, surface_seed
        The :class:`project.microgeometry.GaussianSurface` (mirror facets; spacing tau / 4).
    coarsen : sequence of int
        The same surface sampled every k-th grid point (spacing k tau / 4, same period):
        k = 1 is the reference.
    resolution_rays : int
        Rays per coarsened surface.

    Returns
    -------
    Atlas
        Main table per ray count: ``error`` (RMS over seeds of ||M_s - M_mean||_F /
        ||M_mean||_F: the estimator is unbiased, so its spread is its error), ``q`` (mean
        Westin Q), ``stderr`` (mean batch-means standard error of the entries). Table
        ``degree``: per degree n (the larger of the pair) of the largest run, the mean
        standard error and the mean |M_jk|. Table ``resolution``: per coarsening, the
        measured roughness, ||M_k - M_1||_F, the Monte Carlo error of that difference
        sqrt(sum se_k^2 + se_1^2) and their ratio ``z`` (about 1 without bias).
    """
    from project.microgeometry import GaussianSurface, Heightfield, merge, simulate

    b = basis.HemiZernike(nonneg_int(order, "order"))
    surf = GaussianSurface(sigma, tau, resolution=resolution, seed=surface_seed)
    rows = []
    runs = {}
    for n in rays:
        n = nonneg_int(n, "rays")
        res = [simulate(surf, b, rays=n, seed=s + 1, chunk=max(1, n // 8 // 8))
               for s in range(seeds)]
        runs[n] = res
        mats = np.stack([r.matrix.matrix for r in res])
        mean = mats.mean(axis=0)
        dev = np.linalg.norm((mats - mean).reshape(seeds, -1), axis=1)
        err = float(np.sqrt(np.sum(dev**2) / (seeds - 1)) / np.linalg.norm(mean))
        rows.append(dict(rays=int(res[0].rays), seeds=seeds, error=err,
                         q=float(np.mean([r.asymmetry for r in res])),
                         stderr=float(np.mean([np.nanmean(r.stderr) for r in res]))))
    atlas = Atlas("5. Monte Carlo microgeometry: error against rays, order and resolution", rows)
    x = np.log(atlas.column("rays"))
    for col in ("error", "q"):
        slope = float(np.polyfit(x, np.log(atlas.column(col)), 1)[0]) if len(rows) > 1 \
            else float("nan")
        atlas.facts[f"slope_{col}"] = slope
    big = merge(*runs[max(runs)])
    deg = b.degree
    dmax = np.maximum.outer(deg, deg)
    per = []
    for d in range(b.order + 1):
        sel = dmax == d
        per.append(dict(degree=d, entries=int(sel.sum()),
                        stderr=float(np.mean(big.stderr[sel])),
                        mean_abs=float(np.mean(np.abs(big.matrix.matrix[sel]))),
                        relative=float(np.mean(big.stderr[sel]) /
                                       max(np.mean(np.abs(big.matrix.matrix[sel])), 1e-300))))
    atlas.tables["degree"] = per
    # degree 0 is no reference: b_0 is constant, so M_00 is fixed by the reflected energy,
    # which is exact for lossless mirrors (no noise at all); compare with degree 1
    first = per[min(1, len(per) - 1)]
    atlas.facts["stderr_ratio_top_to_1"] = per[-1]["stderr"] / first["stderr"]
    atlas.facts["relative_ratio_top_to_1"] = per[-1]["relative"] / first["relative"]
    resol = []
    base = None
    for k in coarsen:
        k = nonneg_int(k, "coarsen")
        s = surf if k == 1 else Heightfield(surf.heights[::k, ::k], surf.spacing[0] * k,
                                            material=surf.material)
        r = simulate(s, b, rays=resolution_rays, seed=100 + k,
                     chunk=max(1, resolution_rays // 8 // 8))
        if base is None:
            base = r
        diff = float(np.linalg.norm(r.matrix.matrix - base.matrix.matrix))
        mc = float(np.sqrt(np.sum(r.stderr**2) + np.sum(base.stderr**2))) if r is not base \
            else float(np.sqrt(np.sum(r.stderr**2)))
        resol.append(dict(coarsen=k, spacing_over_tau=float(s.spacing[0] / tau),
                          grid=int(s.heights.shape[0]), roughness=float(s.roughness),
                          difference=diff, mc_error=mc, z=diff / mc if r is not base else 0.0))
    atlas.tables["resolution"] = resol
    for r in resol:
        atlas.facts[f"resolution_z@{r['coarsen']}"] = r["z"]
        atlas.facts[f"roughness@{r['coarsen']}"] = r["roughness"]
    atlas.notes += [
        f"coefficient error falls like rays^{atlas.facts['slope_error']:.2f} and Q like "
        f"rays^{atlas.facts['slope_q']:.2f} (1/sqrt(rays) is -0.5)",
        f"standard error at degree {b.order} is {atlas.facts['stderr_ratio_top_to_1']:.3g} x "
        f"that at degree 1 (absolute noise does not grow), but relative to the coefficients' "
        f"size {atlas.facts['relative_ratio_top_to_1']:.3g} x: high orders are noisier in "
        "signal-to-noise terms (degree 0 of a lossless surface carries no noise at all)",
        "coarser height fields (same period): " + ", ".join(
            f"spacing {r['spacing_over_tau']:g} tau: m = {r['roughness']:.3g}, "
            f"difference = {r['z']:.3g} x MC error" for r in resol[1:]),
    ]
    atlas.panels = [Panel("rays", "error", (), {}, "relative coefficient error", logx=True,
                          logy=True),
                    Panel("rays", "q", (), {}, "Westin Q", logx=True, logy=True),
                    Panel("degree", "relative", (), {}, "stderr / mean |M| per degree",
                          logy=True, table="degree"),
                    Panel("spacing_over_tau", "z", (), {}, "bias / MC error vs spacing",
                          table="resolution")]
    return atlas


# -- item 6: fit stability across restarts ---------------------------------------------------
#: The (family, lobes) cases of :func:`fit_stability`; lobes None is the family's default.
FIT_CASES = (("lafortune", 1), ("lafortune", 2), ("lafortune", 3), ("lambert+ggx", None),
             ("dsbrdf", None), ("rr8807", None))

#: The small atlas: fewer pairs, a one-channel target, DSBRDF with 2 lobes.
FIT_SMALL = {"cases": FIT_CASES[:4] + (("dsbrdf", 2), ("rr8807", None)), "n": 512,
             "error_n": 1024, "restarts": 8, "channels": 1}


def _glossy_target(channels: int = 3) -> Any:
    """Return a glossy dielectric none of the families reproduces exactly."""
    kd = 0.3 if channels == 1 else [0.3, 0.2, 0.1]
    return project.models.CookTorrance(kd, 0.1, "beckmann", ior=1.5)


def fit_stability(cases: Sequence[tuple[str, int | None]] = FIT_CASES, *,
                  target: Any = None, restarts: int = 8, n: int = 4096, error_n: int = 8192,
                  seed: int = 0, metric: str = "l2", rtol: float = 1e-6,
                  channels: int = 3) -> Atlas:
    """Fit each family from several starts and measure how often they reach the best minimum.

    Ngan et al. 2005 found multi-lobe Lafortune fits to measured data unstable (recalled by
    Holzschuch & Pacanowski 2015, who report that their own one-step fit reaches its best
    optimum from about 30 % of random starts). Here every case is fitted by
    :func:`project.fit_model` with ``restarts`` starts (restart 0 from the family's grid, the
    others at random) on the same fitting pairs, and the final costs are compared.

    Measured with the defaults (RGB target, n = 4096, 8 restarts; 8 minutes on a loaded
    2-core machine, most of it dsbrdf): lafortune with 1 and 2 lobes, lambert+ggx and
    rr8807 reach one minimum from all 8 starts; lafortune with 3 lobes from 6 (the others
    10 % higher); dsbrdf with 3 lobes (108 reals) from 1, the other 7 spread from 5 % to
    36 % higher (min / median / max 0.00882 / 0.00980 / 0.01198), while reaching by far the
    lowest cost. The small atlas (one channel, n = 512, dsbrdf with 2 lobes; ~9 s): 3-lobe
    lafortune 2 of 8, dsbrdf 1 of 8 within 1e-6 but 5 within 1e-3.

    Parameters
    ----------
    cases : sequence of (family, lobes)
        Families of :data:`project.fitting.FAMILIES` (not "factored", which has no
        restarts); ``lobes`` for "lafortune" and "dsbrdf", None for the default.
    target : BRDF, optional
        What is fitted; default a Beckmann Cook-Torrance (roughness 0.1, kd (0.3, 0.2, 0.1),
        exact Fresnel of index 1.5), which no family reproduces exactly.
    restarts, n, error_n, seed, metric
        Options of :func:`project.fit_model`.
    rtol : float
        A restart reaches the best minimum when its cost is within ``rtol`` (relative) of
        the lowest.
    channels : {3, 1}
        Channels of the default target (kd = 0.3 for one).

    Returns
    -------
    Atlas
        Main table per case: ``nparams``, ``cost_min``, ``cost_median``, ``cost_max`` (final
        0.5 sum r^2 over the restarts: half the summed squared relative l2 errors per
        channel), ``at_best`` (fraction of restarts within ``rtol`` of the lowest),
        ``near_best`` (within 1e-3: a family stopped on a looser tolerance, as "dsbrdf",
        lands a little above the same minimum),
        ``next_excess`` (relative excess of the lowest cost above that tolerance, the next
        local minimum; nan if every restart reached the best), ``converged`` (fraction
        stopping on a tolerance, not on ``max_nfev``), ``l2`` (of the best restart, on
        independent pairs) and ``seconds``. Table ``restarts``: every restart's cost and
        its relative excess over the case's lowest, ranked.
    """
    target = _glossy_target(channels) if target is None else target
    restarts = nonneg_int(restarts, "restarts")
    rows, per = [], []
    for family, lobes in cases:
        opts = {} if lobes is None else {"lobes": lobes}
        with warnings.catch_warnings():
            # a restart stopping at max_nfev is measured (column converged), not warned
            warnings.simplefilter("ignore", RuntimeWarning)
            fit = project.fit_model(target, family, metric=metric, n=n, restarts=restarts,
                                    error_n=error_n, seed=seed, **opts)
        info = fit.info
        costs = np.array(info["cost"], dtype=np.float64)
        best = float(costs.min())
        tol = rtol * best if best > 0 else 0.0
        at = costs <= best + tol
        others = costs[~at]
        k = {"lafortune": "n", "dsbrdf": "kappa"}.get(family)
        nlobes = None if k is None else int(np.shape(fit.params[k])[0])
        case = family if nlobes is None else f"{family}/{nlobes}"
        rows.append(dict(case=case, family=family, lobes=nlobes, nparams=fit.nparams,
                         restarts=restarts, cost_min=best, cost_median=float(np.median(costs)),
                         cost_max=float(costs.max()), at_best=float(at.mean()),
                         near_best=float(np.mean(costs <= best * (1 + 1e-3))),
                         next_excess=float(others.min() / best - 1) if others.size and best > 0
                         else float("nan"),
                         converged=float(np.mean(np.array(info["status"]) > 0)),
                         l2=float(info["l2"]), seconds=float(info["seconds"])))
        for rank, c in enumerate(np.sort(costs)):
            per.append(dict(case=case, rank=rank, cost=float(c),
                            excess=float(c / best - 1) if best > 0 else 0.0))
    atlas = Atlas("6. Fit stability: final cost across restarts, per family", rows)
    atlas.tables["restarts"] = per
    for r in rows:
        atlas.facts[f"at_best@{r['case']}"] = r["at_best"]
        atlas.facts[f"spread@{r['case']}"] = r["cost_max"] / r["cost_min"] - 1 \
            if r["cost_min"] > 0 else 0.0
        atlas.notes.append(
            f"{r['case']} ({r['nparams']} reals): cost min / median / max "
            f"{r['cost_min']:.6g} / {r['cost_median']:.6g} / {r['cost_max']:.6g}, "
            f"{round(r['at_best'] * restarts)} of {restarts} restarts at the best (rtol "
            f"{rtol:g}), {round(r['near_best'] * restarts)} within 1e-3, l2 {r['l2']:.3g}, "
            f"{r['seconds']:.1f} s")
    atlas.panels = [
        Panel("rank", "excess", "case", {}, "cost / lowest - 1, restarts ranked", logy=True,
              table="restarts"),
        Panel("nparams", "at_best", (), {}, "fraction of restarts at the best minimum"),
    ]
    return atlas


# -- item 7: reciprocity floors ---------------------------------------------------------------
#: The families of :class:`NonReciprocalDiffuse`: g(mu) of f = kd (1 + c g(cos theta_i)) / pi.
NONRECIPROCAL_FAMILIES = ("cos", "grazing")
_COS75 = math.cos(math.radians(75.0))


def _g(family: str, mu: NDArray) -> NDArray:
    if family == "cos":
        return mu
    return np.maximum(1.0 - mu / _COS75, 0.0) ** 2  # "grazing": 0 above 75 deg, 1 at 90


class NonReciprocalDiffuse(project.BRDF):
    """f = kd (1 + c g(cos theta_i)) / pi: a diffuse BRDF brightened by incidence, not reciprocal.

    ``family="cos"``: g(mu) = mu (brighter towards normal incidence everywhere);
    ``"grazing"``: g(mu) = max(1 - mu / cos 75 deg, 0)^2, zero unless theta_i > 75 deg, so
    the antisymmetric part lives where one direction is grazing. The floor has a closed
    form: :func:`nonreciprocal_floor`.
    """

    isotropic = True
    reciprocal = False

    def __init__(self, kd: float, c: float, family: str = "cos") -> None:
        if family not in NONRECIPROCAL_FAMILIES:
            raise ValueError(f"family must be one of {NONRECIPROCAL_FAMILIES}, got {family!r}")
        self.kd, self.c, self.family = float(kd), float(c), family
        self.channels = 1
        self._scalar = True

    def _eval(self, wi: NDArray, wo: NDArray) -> NDArray:
        return (self.kd / np.pi * (1.0 + self.c * _g(self.family, wi[:, 2])))[:, None]

    def __repr__(self) -> str:
        return f"NonReciprocalDiffuse({self.kd:g}, {self.c:g}, {self.family!r})"


def nonreciprocal_floor(c: float, family: str = "cos") -> float:
    """Return the exact floor ||(q - q^T) / 2|| / ||q|| of :class:`NonReciprocalDiffuse`.

    With mu = cos theta, q = (kd / pi) mu_i mu_o (1 + c g(mu_i)) and its antisymmetric part
    a = (kd c / (2 pi)) mu_i mu_o (g(mu_i) - g(mu_o)); the azimuths give (2 pi)^2 to both
    norms, which cancels with kd / pi. With the moments M[h] = int_0^1 mu^2 h(mu) d mu,

        floor^2 = (c^2 / 2) (M[1] M[g^2] - M[g]^2) / (M[1] (M[1] + 2 c M[g] + c^2 M[g^2])).

    For g = mu (M = 1/3, 1/4, 1/5) this is c^2 / (160 (1/3 + c/2 + c^2/5)): 0.04967 at
    c = 0.5. The moments are computed by Gauss-Legendre rules on [0, cos 75 deg] and
    [cos 75 deg, 1] (the kink of "grazing"), exact for these piecewise polynomials.

    Examples
    --------
    >>> round(nonreciprocal_floor(0.5), 5)
    0.04967
    """
    if family not in NONRECIPROCAL_FAMILIES:
        raise ValueError(f"family must be one of {NONRECIPROCAL_FAMILIES}, got {family!r}")
    x, w = np.polynomial.legendre.leggauss(8)  # exact to degree 15; integrands degree <= 6
    mus, wts = [], []
    for lo, hi in ((0.0, _COS75), (_COS75, 1.0)):
        mus.append(lo + (hi - lo) * (x + 1.0) / 2.0)
        wts.append((hi - lo) / 2.0 * w)
    mu, wt = np.concatenate(mus), np.concatenate(wts) * np.concatenate(mus) ** 2
    g = _g(family, mu)
    m1, mg, mgg = float(wt.sum()), float(wt @ g), float(wt @ (g * g))
    c = float(c)
    num = 0.5 * c * c * (m1 * mgg - mg * mg)
    return math.sqrt(max(num, 0.0) / (m1 * (m1 + 2.0 * c * mg + c * c * mgg)))


#: The small atlas: the "cos" family at c = 0 and 0.5, orders 2 and 8, a coarser table (~2 s).
RECIPROCITY_SMALL = {"cs": (0.0, 0.5), "families": ("cos",), "orders": (2, 8),
                     "table_bins": (16, 16, 32), "n": 4096}


def reciprocity_floors(cs: Sequence[float] = (0.0, 0.1, 0.25, 0.5, 1.0), *,
                       families: Sequence[str] = NONRECIPROCAL_FAMILIES,
                       orders: Sequence[int] = (2, 4, 8), rank: int = 2,
                       factored_bins: tuple[int, int, int] = (16, 12, 8),
                       factored_samples: tuple[int, int, int] = (60, 32, 16),
                       table_bins: tuple[int, int, int] = (32, 32, 64),
                       kd: float = 0.5, n: int = 2**15, seed: int = 1) -> Atlas:
    """Measure where every reciprocal form stops on non-reciprocal data, and the general ones.

    For each family and c of :class:`NonReciprocalDiffuse` (c = 0 is reciprocal), the floor
    is measured by :func:`project.reciprocity` and compared with :func:`nonreciprocal_floor`;
    then each representation is built and its relative l2 error of q measured:

    - ``zernike/<order> symmetric`` and ``general``: :func:`project.project` in
      HemiZernike(order), quantity "f_cos", ``reciprocal=True`` and ``False``;
    - ``factored/<rank> half`` and ``full``: :func:`project.factored.fit_factored` with
      ``phi_turn="half"`` (``factored_bins``) and ``"full"`` (twice the phi_d nodes, the same
      spacing over the whole turn);
    - ``table half`` and ``full``: :func:`project.tabulated.tabulate` at ``table_bins``
      (linear theta_d), q over half or the whole turn of phi_d.

    Measured with the defaults (n = 2**15 pairs, seed 1; ~20 s). The floors of
    :func:`project.reciprocity` agree with the closed form within 0.5 standard errors (e.g.
    "cos", c = 0.5: 0.04963 +- 0.00009 against 0.04967). Every reciprocal form sits at or
    above the floor; every general one but the table goes below it:

    - "cos" (the antisymmetric part is smooth, 16 % of its energy beyond 75 deg): q is a
      polynomial of degree 4 in rho_i, so from order 4 the symmetric projection reaches the
      floor exactly (error / floor = 1 to 1e-12) and the general one is exact to rounding
      (~7e-15); at order 2 both truncate (1.20 and 0.945 x floor). The half-turn lobe of
      rank 2 sits at 1.0001 x floor, the full-turn lobe at 0.11-0.15 x. The half-turn
      table sits at 1.40-1.55 x: it stores f in one order only (f(w_o, w_i) is read where
      f(w_i, w_o) belongs), so its error on the antisymmetric part is 2 a on half the
      domain, sqrt(2) x floor, not the floor; the full-turn table (32, 32, 64) reaches
      0.0074-0.0087, an interpolation floor of its own, 0.10-0.68 x floor.
    - "grazing" (all of it beyond 75 deg, floor 0.0157 at c = 1): the symmetric forms stop
      at 1.10-1.21 x floor (the kink at 75 deg is not resolved either), the general matrix
      at 0.65 x (order 8), the full-turn lobe at 0.69 x, while the full-turn table's own
      interpolation error (0.009) is above the floor for c <= 0.5.

    Parameters
    ----------
    cs : sequence of float
        Strengths c of the non-reciprocal term (>= 0).
    families : sequence of {"cos", "grazing"}
    orders : sequence of int
        HemiZernike orders.
    rank, factored_bins, factored_samples
        Rank, (n_h, n_d, n_phi) of the half-turn lobe, and the fitting rule.
    table_bins : (int, int, int)
        Table resolution (n_phi over the whole turn, as :func:`project.tabulated.tabulate`).
    kd : float
        Albedo scale (the floors do not depend on it).
    n, seed
        Pairs and seed of :func:`project.reciprocity`. The errors are measured on the same
        swap-closed pairs (:func:`project.reciprocity.symmetrized_pairs` of
        :func:`project.sampling.peak_resolving_pairs`), independent of every fit: on them
        the symmetric and antisymmetric parts are orthogonal exactly, so a reciprocal form's
        estimated error is >= the estimated floor with no Monte Carlo slack.

    Returns
    -------
    Atlas
        Main table per (family, c, form): ``reciprocal`` (the form is reciprocal by
        construction), ``error`` with ``error_stderr`` (relative l2 of q, worst channel),
        ``floor`` (measured), ``excess_se`` ((error - floor) / floor standard error; NaN at
        c = 0), ``over_floor`` (error / floor), ``reals`` (numbers stored: the triangle of each
        symmetric block, every entry of a general one) and ``side``
        ("at/above" or "below" the floor within 3 standard errors, "-" at c = 0). Table
        ``floors`` per (family, c): ``floor_exact``, ``floor``, ``floor_stderr``, ``z``
        ((floor - floor_exact) / floor_stderr), ``residual`` and ``share_above_75`` (the
        antisymmetric energy with one angle beyond 75 deg). The main table also holds, per
        (family, c), a row ``floor (closed form)`` (``error`` = :func:`nonreciprocal_floor`,
        ``reciprocal`` None, ``over_floor`` closed form / measured), drawn as the line at 1
        in the panels of error / floor against c (c = 0, floor 0, is left out of them).
    """
    from project.factored import fit_factored
    from project.reciprocity import symmetrized_pairs
    from project.sampling import peak_resolving_pairs, value_errors
    from project.tabulated import table_nbytes, tabulate

    fams = list(families)
    for fam in fams:
        if fam not in NONRECIPROCAL_FAMILIES:
            raise ValueError(f"families must be in {NONRECIPROCAL_FAMILIES}, got {fam!r}")
    for c in cs:
        if not (isinstance(c, int | float | np.number) and math.isfinite(c) and c >= 0.0):
            raise ValueError(f"cs must be finite and >= 0, got {c!r}")
    orders = [nonneg_int(o, "orders") for o in orders]
    rank = nonneg_int(rank, "rank")
    pairs = symmetrized_pairs(peak_resolving_pairs(n, seed=seed))
    full_bins = (*factored_bins[:2], 2 * factored_bins[2])
    rows, floors = [], []
    for fam in fams:
        for c in cs:
            c = float(c)
            brdf = NonReciprocalDiffuse(kd, c, fam)
            rec = project.reciprocity(brdf, n=n, seed=seed)
            exact = nonreciprocal_floor(c, fam)
            fl, se = rec.floor, rec.floor_stderr
            share = sum(b["share"] for b in rec.bands if b["theta_deg"][0] >= 75.0)
            floors.append(dict(family=fam, c=c, floor_exact=exact, floor=fl, floor_stderr=se,
                               z=(fl - exact) / se if se > 0 else 0.0,
                               residual=rec.residual,
                               share_above_75=share if math.isfinite(share) else float("nan")))
            rows.append(dict(family=fam, c=c, form="floor (closed form)", reciprocal=None,
                             error=exact, error_stderr=0.0, floor=fl, excess_se=None,
                             over_floor=exact / fl if fl > 0 else float("nan"), reals=None,
                             side="floor"))
            f = brdf.eval(pairs.wi, pairs.wo)
            forms = []
            for order in orders:
                b = basis.HemiZernike(order)
                for recip, label in ((True, "symmetric"), (False, "general")):
                    cm = project.project(brdf, b, quantity="f_cos", reciprocal=recip)
                    # q itself (no clamp needed: f_cos is divided by cos cos exactly)
                    fh = cm.eval(pairs.wi, pairs.wo, min_cos=1e-12)
                    ks = [blk.shape[-1] for blk in cm.stored]
                    reals = sum(k * (k + 1) // 2 if recip else k * k for k in ks)
                    forms.append((f"zernike/{order} {label}", recip, fh, reals))
            for turn, bins in (("half", factored_bins), ("full", full_bins)):
                with warnings.catch_warnings():
                    # a fit stopping at max_iter is measured by its error, not warned
                    warnings.simplefilter("ignore", RuntimeWarning)
                    lobe = fit_factored(brdf, rank=rank, bins=bins, samples=factored_samples,
                                        phi_turn=turn, seed=seed)
                forms.append((f"factored/{rank} {turn}", turn == "half",
                              lobe.eval(pairs.wi, pairs.wo), lobe.nparams))
            for turn in ("half", "full"):
                tab = tabulate(brdf, table_bins, phi_turn=turn, warp_d="linear")
                forms.append((f"table {turn}", turn == "half", tab.eval(pairs.wi, pairs.wo),
                              table_nbytes(table_bins, 1, phi_turn=turn, itemsize=1)))
            for label, recip, fh, reals in forms:
                e = value_errors(f, fh, pairs)
                err, err_se = float(e["l2"]), float(e["l2_stderr"])
                if fl > 0:
                    excess = (err - fl) / se
                    side = "at/above" if excess >= -3.0 else "below"
                else:
                    excess, side = float("nan"), "-"
                rows.append(dict(family=fam, c=c, form=label, reciprocal=recip, error=err,
                                 error_stderr=err_se, floor=fl, excess_se=excess,
                                 over_floor=err / fl if fl > 0 else float("nan"),
                                 reals=int(reals), side=side))
    atlas = Atlas("7. Reciprocity floors: reciprocal and general forms on non-reciprocal data",
                  rows)
    atlas.tables["floors"] = floors
    for r in floors:
        key = f"{r['family']}/{r['c']:g}"
        atlas.facts[f"floor@{key}"] = r["floor"]
        atlas.facts[f"floor_exact@{key}"] = r["floor_exact"]
        atlas.facts[f"floor_z@{key}"] = r["z"]
    for r in rows:
        if r["reciprocal"] is not None:
            atlas.facts[f"error@{r['family']}/{r['c']:g}/{r['form']}"] = r["error"]
    pos = [r for r in rows if r["floor"] > 0]
    recs = [r for r in pos if r["reciprocal"] is True]
    gens = [r for r in pos if r["reciprocal"] is False]
    atlas.facts["reciprocal_min_excess_se"] = min((r["excess_se"] for r in recs),
                                                  default=float("nan"))
    atlas.facts["reciprocal_min_over_floor"] = min((r["over_floor"] for r in recs),
                                                   default=float("nan"))
    zmax = max((abs(r["z"]) for r in floors if r["floor_exact"] > 0), default=float("nan"))
    atlas.notes.append(f"the floor of project.reciprocity against the closed form: largest "
                       f"|z| = {zmax:.2f} standard errors over {len(floors)} cases")
    atlas.notes.append(
        f"every reciprocal form sits at or above the floor: error / floor >= "
        f"{atlas.facts['reciprocal_min_over_floor']:.6g} over {len(recs)} rows (on the "
        "swap-closed pairs the bound holds exactly, not only in expectation)")
    for label in dict.fromkeys(r["form"] for r in gens):
        sel = [r for r in gens if r["form"] == label]
        below = sum(r["side"] == "below" for r in sel)
        atlas.notes.append(f"{label}: below the floor in {below} of {len(sel)} cases (error / "
                           "floor " + ", ".join(f"{r['family']} c={r['c']:g}: "
                                                f"{r['over_floor']:.3g}" for r in sel) + ")")
    atlas.panels = [Panel("c", "over_floor", "form", {"family": fam},
                          f"{fam} family: error / floor against c (the floor row is 1)",
                          logy=True) for fam in fams]
    atlas.panels.append(Panel("c", "over_floor", ("family", "form"), {"reciprocal": True},
                              "reciprocal forms: error / floor (>= 1)"))
    return atlas


# -- everything ---------------------------------------------------------------------------------
def write_all(out_dir: str | Path, small: bool = False, *,
              client: Any = None) -> dict[str, tuple[Path, Path]]:
    """Run the seven measurements and write ``<name>.md`` and ``<name>.png`` for each.

    Parameters
    ----------
    out_dir : path
        An existing directory.
    small : bool
        Small sizes (seconds each, as the tests and notebook use) instead of the full atlas.
    client : dask.distributed.Client, optional
        Run the seven measurements as tasks on this Dask cluster (``pip install
        'scatmodes[distributed]'``); the files are written here, by the caller.

    Returns
    -------
    dict of name to (markdown path, png path)
    """
    out = Path(out_dir)
    if not out.is_dir():
        raise FileNotFoundError(f"out_dir must be an existing directory, got {str(out)!r}")
    if small:
        jobs = {
            "radial_accuracy": lambda: radial_accuracy(zernike_orders=(20, 60, 200),
                                                       sh_degrees=(20, 100, 1000)),
            "hemisphere_conditioning": lambda: hemisphere_conditioning((2, 4, 6)),
            "sparse_fits": lambda: sparse_fits((4, 8), ratios=(66 / 55, 16.0),
                                               noise=(0.0, 0.05), trials=2),
            "sharp_lobes": lambda: sharp_lobes((0.5, 0.2), (4,), quantities=("f_cos",),
                                               filters=("hann",), pairs=4096),
            "monte_carlo": lambda: monte_carlo((1000, 4000), seeds=3, resolution=32,
                                               coarsen=(1, 4), resolution_rays=16000),
            "fit_stability": lambda: fit_stability(**FIT_SMALL),
            "reciprocity_floors": lambda: reciprocity_floors(**RECIPROCITY_SMALL),
        }
    else:
        jobs = {
            "radial_accuracy": radial_accuracy,
            "hemisphere_conditioning": lambda: hemisphere_conditioning(tuple(range(1, 11))),
            "sparse_fits": lambda: sparse_fits((4, 6, 8, 10),
                                               ratios=(66 / 55, 1.5, 2.0, 4.0, 16.0, 64.0),
                                               noise=(0.0, 0.001, 0.01, 0.05)),
            "sharp_lobes": lambda: sharp_lobes((0.6, 0.3, 0.15, 0.08, 0.05), (4, 8, 12, 16)),
            "monte_carlo": lambda: monte_carlo((2000, 8000, 32000, 128000), seeds=8,
                                               resolution=128, coarsen=(1, 2, 4),
                                               resolution_rays=256000),
            "fit_stability": fit_stability,
            "reciprocity_floors": reciprocity_floors,
        }
    if client is not None:
        dask_client(client, "write_all")
        futures = {name: client.submit(job, pure=False, key=f"scatmodes-stability-{name}")
                   for name, job in jobs.items()}
        results = ((name, fut.result()) for name, fut in futures.items())
    else:
        results = ((name, job()) for name, job in jobs.items())  # each written when done
    written = {}
    for name, atlas in results:
        md = out / f"{name}.md"
        with atomic_path(md) as tmp:
            tmp.write_text(atlas.to_markdown())
        written[name] = (md, atlas.plot(out / f"{name}.png"))
    return written
