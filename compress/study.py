"""Error/resolution studies: one row per (basis kind, order) with sizes, timings and errors.

Sampling (the "test set")
-------------------------
Errors are measured against the BRDF itself, never against another representation:

- isotropic BRDFs: the product rule over H x H in (z_i, z_o, dphi): ``nodes[0]``
  Gauss-Legendre nodes in each cosine and ``nodes[1]`` uniform azimuth differences in
  [0, 2 pi), phi_i = 0. Weights integrate over H x H in solid angle (they sum to (2 pi)^2).
- anisotropic BRDFs: ``nodes[0]^2 nodes[1]`` scrambled Sobol pairs (seeded), uniform in solid
  angle, equal weights.

Metrics (per channel, the table shows the largest over channels):

=================  ==========================================================================
``l2``             cosine-weighted relative L2 error over all of H x H: ||q_hat - q|| / ||q||
                   with q = f cos(theta_i) cos(theta_o) (the squared error that Lafortune
                   et al. 1997, sec. 6, minimise, made relative; for quantity "f_cos" it
                   equals the Parseval truncation error of the projection, up to the
                   quadrature error of the test set)
``max_abs``        max |f_hat - f| (1/sr)                                               [D]
``rel_rms``        ||f_hat - f|| / ||f|| with weight cos^2(theta_i), the weight of the RMSE
                   of Holzschuch & Pacanowski 2015 (sec. 6.3, eq. 31)                   [D]
``log_rms``        RMS of log(1 + f cos theta_i) - log(1 + max(f_hat, 0) cos theta_i)
                   (negative values clamped, as a renderer would)                       [D]
``smape``          mean of 100 |f_hat - f| / (|f_hat| + |f|) in percent (absolute values in
                   the denominator so negative f_hat stay in [0, 100]; 0 where both
                   vanish). Holzschuch & Pacanowski 2015 (sec. 6.1, eq. 30) use the same
                   ratio, in [0, 1], on image pixels                                    [D]
``negative``       solid-angle fraction of H x H where f_hat < 0
``albedo``         max over theta_i in D of |a_hat(theta_i) - a(theta_i)|, both by the same
                   rule (isotropic test sets only; None otherwise)
``reciprocity``    max |f_hat(wi, wo) - f_hat(wo, wi)| / max |f_hat|                    [D]
``*_all``          the same six pointwise metrics (``max_abs_all``, ``rel_rms_all``,
                   ``log_rms_all``, ``smape_all``, ``albedo_all``, ``reciprocity_all``) on all
                   of H x H, grazing pairs included
=================  ==========================================================================

D is the domain theta_i, theta_o < ``max_theta`` (default 1.4 rad = 80.2 deg) on which
Holzschuch & Pacanowski (2015, sec. 5.8 and sec. 6.3) fit and compare models to measured
data, leaving out grazing angles as Ngan et al. (2005) do; it avoids the band where measured
data are unreliable and f = q / (cos cos) is ill conditioned. The ``_all`` columns show what
that band costs. Pointwise metrics use f_hat as ``CoefficientMatrix.eval`` returns it by
default (``min_cos = 1e-3``); ``l2``, ``negative`` and the albedo use the expansion itself.
Solid-angle weighted means are used throughout.

References
----------
- Holzschuch & Pacanowski 2015: N. Holzschuch and R. Pacanowski, "A physically accurate
  reflectance model combining reflection and diffraction", Inria research report RR-8807,
  2015 (journal version: "A two-scale microfacet reflectance model combining reflection and
  diffraction", ACM Transactions on Graphics 36(4), SIGGRAPH 2017).
- Lafortune et al. 1997: E. P. F. Lafortune, S.-C. Foo, K. E. Torrance and D. P. Greenberg,
  "Non-linear approximation of reflectance functions", SIGGRAPH 97, pp. 117-126.
- Ngan et al. 2005: A. Ngan, F. Durand and W. Matusik, "Experimental analysis of BRDF
  models", Eurographics Symposium on Rendering 2005.
- Westin et al. 1992: S. H. Westin, J. R. Arvo and K. E. Torrance, "Predicting reflectance
  functions from complex surfaces", SIGGRAPH 92, pp. 255-264.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

import project
from basis import KINDS, CoefficientMatrix, make_basis
from basis.validation import nonneg_int
from project.crossval import out_of_fold, sample_errors
from project.io import atomic_path
from project.measurements import FOLDS

from .truncate import smooth as _smooth
from .truncate import unique_coefficients

__all__ = ["KINDS", "METRICS", "Study", "Samples", "errors", "make_basis", "pareto_front",
           "study", "reference_samples"]

# KINDS (from basis) names the basis kinds: the hemisphere Zernike functions, the odd
# hemisphere harmonics (Westin et al. 1992, sec. 2.5), the even completion, and the
# full-sphere harmonics (BRDF zero below the horizon).

#: Error columns of a study (see the module notes).
METRICS = ("l2", "max_abs", "rel_rms", "log_rms", "smape", "negative", "albedo", "reciprocity",
           "max_abs_all", "rel_rms_all", "log_rms_all", "smape_all", "albedo_all",
           "reciprocity_all")
#: ``min_cos`` of :meth:`basis.CoefficientMatrix.eval` by default: the pointwise metrics
#: measure f_hat as a user evaluates it.
DEFAULT_MIN_COS = 1e-3
#: Default test set: Gauss nodes per cosine, azimuth differences.
NODES = (40, 80)
#: Polar angle limit of the domain D of the pointwise metrics (theta < 1.4 rad, as in
#: Holzschuch & Pacanowski 2015, sec. 6.3).
MAX_THETA = 1.4
#: Evaluation is timed on this many pairs (best of three).
TIMING_PAIRS = 1 << 18


# -- the test set --------------------------------------------------------------------------
@dataclass
class Samples:
    """Direction pairs, their solid-angle weights and the reference BRDF values.

    Attributes
    ----------
    wi, wo : (n, 3) ndarray
    weights : (n,) ndarray
        Solid-angle quadrature weights on H x H (sum (2 pi)^2).
    values : (n, channels) ndarray
        The BRDF at the pairs.
    domain : (n,) bool ndarray
        Both polar angles below ``max_theta``.
    grid : (nz, nz, nphi) or None
        Shape of the isotropic product grid (pairs ordered z_i, z_o, dphi), None for Sobol.
    seconds : float
        Time spent evaluating the BRDF.
    """

    __test__ = False  # not a pytest class

    wi: NDArray[np.float64]
    wo: NDArray[np.float64]
    weights: NDArray[np.float64]
    values: NDArray[np.float64]
    domain: NDArray[np.bool_]
    grid: tuple[int, int, int] | None
    seconds: float
    description: str = ""


def isotropic_pairs(nz: int, nphi: int) -> tuple[NDArray, NDArray, NDArray]:
    """Return the isotropic product rule on H x H.

    Gauss-Legendre in each cosine x uniform dphi = phi_i - phi_o, with phi_i = 0 (an
    isotropic integrand does not depend on it).

    Returns
    -------
    wi, wo : (nz * nz * nphi, 3) ndarray
    weights : (nz * nz * nphi,) ndarray
        Summing to (2 pi)^2; exact for isotropic integrands of degree <= 2 nz - 1 in each
        cosine and < nphi in dphi.
    """
    t, w = np.polynomial.legendre.leggauss(nz)
    z, wz = 0.5 * (t + 1.0), 0.5 * w
    s = np.sqrt((1.0 - z) * (1.0 + z))
    dphi = 2.0 * np.pi * np.arange(nphi) / nphi
    zi, zo, dp = np.meshgrid(z, z, dphi, indexing="ij")
    si, so = np.meshgrid(s, s, dphi, indexing="ij")[:2]
    wi = np.stack([si, np.zeros_like(si), zi], axis=-1).reshape(-1, 3)
    wo = np.stack([so * np.cos(dp), -so * np.sin(dp), zo], axis=-1).reshape(-1, 3)
    weights = (np.multiply.outer(np.multiply.outer(wz, wz), np.full(nphi, 2.0 * np.pi / nphi))
               * 2.0 * np.pi).reshape(-1)
    return wi, wo, weights


def reference_samples(brdf: Any, *, nodes: tuple[int, int] = NODES, max_theta: float = MAX_THETA,
             seed: int = 0) -> Samples:
    """Sample the BRDF on the pairs on which a study measures errors (see the module notes).

    Parameters
    ----------
    brdf : BRDF
    nodes : (n_z, n_phi)
    max_theta : float
        Polar-angle limit (radians) of the pointwise metrics' domain.
    seed : int
        Sobol scramble (anisotropic BRDFs only).
    """
    nz, nphi = (nonneg_int(v, "nodes") for v in nodes)
    if nz < 1 or nphi < 1:
        raise ValueError(f"nodes must be two positive integers, got {tuple(nodes)}")
    if not 0 < max_theta <= np.pi / 2:
        raise ValueError(f"max_theta must lie in (0, pi/2], got {max_theta!r}")
    if getattr(brdf, "isotropic", False):
        wi, wo, weights = isotropic_pairs(nz, nphi)
        grid: tuple[int, int, int] | None = (nz, nz, nphi)
        desc = (f"isotropic product rule: {nz} Gauss nodes per cosine x {nphi} azimuth "
                f"differences ({wi.shape[0]} pairs)")
    else:
        from scipy.stats import qmc

        n = nz * nz * nphi
        u = qmc.Sobol(d=4, scramble=True, seed=seed).random(n)
        wi, wo = (_uniform_h(u[:, 0], u[:, 1]), _uniform_h(u[:, 2], u[:, 3]))
        weights = np.full(n, (2.0 * np.pi) ** 2 / n)
        grid = None
        desc = f"{n} scrambled Sobol pairs (seed {seed}), uniform in solid angle"
    t0 = time.perf_counter()
    v = np.asarray(brdf.eval(wi, wo), dtype=np.float64).reshape(wi.shape[0], -1)
    seconds = time.perf_counter() - t0
    zmin = np.cos(max_theta)
    domain = (wi[:, 2] > zmin) & (wo[:, 2] > zmin)
    return Samples(wi, wo, weights, v, domain, grid, seconds,
                   desc + f"; pointwise metrics on theta < {max_theta:.3g} rad")


def _uniform_h(u: NDArray, v: NDArray) -> NDArray:
    s = np.sqrt(np.maximum(0.0, 1.0 - u * u))
    return np.stack([s * np.cos(2 * np.pi * v), s * np.sin(2 * np.pi * v), u], axis=-1)


def _represented(cm: CoefficientMatrix, ts: Samples, min_cos: float = 1e-12
                 ) -> NDArray[np.float64]:
    """Return f_hat at the test pairs as (n, channels).

    The default tiny ``min_cos`` means no grazing lift, so that f_hat cos cos is exactly the
    expansion q_hat; ``min_cos=DEFAULT_MIN_COS`` is what ``cm.eval`` gives a user.
    """
    out = np.empty((ts.wi.shape[0], cm.channels))
    cm.evaluator(min_cos=min_cos).eval_flat(ts.wi, ts.wo, out)
    return out


def errors(cm: CoefficientMatrix, ts: Samples) -> dict[str, float | None]:
    """Every metric of :data:`METRICS` for ``cm`` on the test set ``ts`` (module notes).

    Parameters
    ----------
    cm : basis.CoefficientMatrix
    ts : Samples
        From :func:`reference_samples`.

    Returns
    -------
    dict
        Metric name -> value (the largest over channels); ``albedo`` and ``albedo_all`` are
        None for anisotropic test sets.
    """
    fh = _represented(cm, ts)
    f = ts.values
    if f.shape[1] != fh.shape[1] and 1 not in (f.shape[1], fh.shape[1]):
        raise ValueError(f"channels differ: the BRDF has {f.shape[1]}, the matrix "
                         f"{fh.shape[1]}")
    f, fh = np.broadcast_arrays(f, fh)
    w = ts.weights[:, None]
    cc = (ts.wi[:, 2] * ts.wo[:, 2])[:, None]
    q, qh = f * cc, fh * cc
    out: dict[str, float | None] = {}
    out["l2"] = _rel(np.sum(w * (qh - q) ** 2, axis=0), np.sum(w * q * q, axis=0))
    out["negative"] = float(np.max(np.sum(w * (fh < 0), axis=0) / np.sum(w)))
    # pointwise metrics of f as a user evaluates it (cm.eval's default grazing rule)
    fu = np.broadcast_to(_represented(cm, ts, DEFAULT_MIN_COS), f.shape)
    every = np.ones(ts.wi.shape[0], dtype=bool)
    for suffix, sel in (("", ts.domain), ("_all", every)):
        out.update({k + suffix: v for k, v in _pointwise(f[sel], fu[sel], w[sel],
                                                         ts.wi[sel, 2][:, None]).items()})
        out["albedo" + suffix] = _albedo_error(fh - f, ts, sel)  # exact, as cm.albedo
        sub = np.flatnonzero(sel)[:: max(1, int(np.sum(sel)) // 20000)]
        pair = [Samples(a[sub], b[sub], ts.weights[sub], f[sub], sel[sub], None, 0.0)
                for a, b in ((ts.wi, ts.wo), (ts.wo, ts.wi))]
        a, b = (_represented(cm, s, DEFAULT_MIN_COS) for s in pair)
        scale = float(np.max(np.abs(a), initial=0.0)) or 1.0
        out["reciprocity" + suffix] = float(np.max(np.abs(a - b), initial=0.0)) / scale
    return out


def _pointwise(f: NDArray, fh: NDArray, w: NDArray, zi: NDArray) -> dict[str, float]:
    """max_abs, rel_rms, log_rms and smape of f_hat against f on the given pairs."""
    out = {"max_abs": float(np.max(np.abs(fh - f), initial=0.0)),
           "rel_rms": _rel(np.sum(w * zi**2 * (fh - f) ** 2, axis=0),
                           np.sum(w * zi**2 * f**2, axis=0))}
    lg = np.log1p(f * zi) - np.log1p(np.maximum(fh, 0.0) * zi)
    wsum = float(np.sum(w)) or 1.0
    out["log_rms"] = float(np.max(np.sqrt(np.sum(w * lg * lg, axis=0) / wsum)))
    den = np.abs(fh) + np.abs(f)
    with np.errstate(invalid="ignore", divide="ignore"):
        sm = np.where(den > 0, np.abs(fh - f) / np.where(den > 0, den, 1.0), 0.0)
    out["smape"] = float(np.max(100.0 * np.sum(w * sm, axis=0) / wsum))
    return out


def _albedo_error(diff: NDArray, ts: Samples, sel: NDArray) -> float | None:
    """Return the max over the incident nodes in ``sel`` of |int (f_hat - f) cos dw_o|.

    The integral is taken by the product rule of the test set.
    """
    if ts.grid is None:
        return None
    nz, _, nphi = ts.grid
    ww = ts.weights.reshape(ts.grid)
    wz_i = ww.sum(axis=(1, 2)) / (2.0 * np.pi) ** 2  # Gauss weight of each z_i
    wo_w = ww / (2.0 * np.pi * wz_i[:, None, None])  # the w_o rule alone
    d = (diff * ts.wo[:, 2:3]).reshape(nz, nz, nphi, -1)
    alb = np.einsum("abp,abpc->ac", wo_w, d)
    rows = sel.reshape(nz, nz, nphi).any(axis=(1, 2))
    return float(np.max(np.abs(alb[rows]), initial=0.0))


def _rel(num: NDArray, den: NDArray) -> float:
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(den > 0, np.sqrt(num / np.where(den > 0, den, 1.0)), np.sqrt(num))
    return float(np.max(r))


def eval_ns(cm: CoefficientMatrix, *, pairs: int = TIMING_PAIRS, seed: int = 1) -> float:
    """Time the fastest evaluator of ``cm``: nanoseconds per BRDF sample.

    Best of three runs on ``pairs`` random pairs; all threads; compilation excluded.
    """
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(2, pairs, 3))
    w[..., 2] = np.abs(w[..., 2])
    w /= np.linalg.norm(w, axis=-1, keepdims=True)
    wi, wo = np.ascontiguousarray(w[0]), np.ascontiguousarray(w[1])
    ev = cm.evaluator()
    out = np.empty((pairs, cm.channels))

    def run() -> None:
        ev.eval_flat(wi, wo, out)
    run()
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - t0)
    return 1e9 * best / pairs


# -- the study ----------------------------------------------------------------------------
COLUMNS = ("kind", "order", "quantity", "coefficients", "bytes", "projection_s", "eval_ns",
           *METRICS, "truncation_error", "warnings")


@dataclass
class Study:
    """A table of representations of one BRDF: one row per (kind, order).

    Attributes
    ----------
    rows : list of dict
        Keys :data:`COLUMNS`: ``coefficients`` is the number of unique stored reals
        (symmetric, isotropic block storage, all channels), ``bytes`` that times 8 (float64,
        as ``compress.save`` writes it), ``projection_s`` the projection's wall time,
        ``eval_ns`` the evaluation time per sample, ``truncation_error`` the projection's
        Parseval estimate, ``warnings`` the number of warnings the projection raised
        (e.g. the Gibbs warning).
    source : str
        repr of the BRDF.
    quantity : str
    sampling : str
        Description of the test set.
    """

    rows: list[dict[str, Any]]
    source: str
    quantity: str
    sampling: str
    messages: list[str] = field(default_factory=list)

    def column(self, name: str) -> NDArray:
        """One column as an array (None becomes NaN)."""
        if name not in COLUMNS:
            raise ValueError(f"name must be one of {', '.join(COLUMNS)}, got {name!r}")
        vals = [r[name] for r in self.rows]
        if name in ("kind", "quantity"):
            return np.array(vals, dtype=object)
        return np.array([np.nan if v is None else v for v in vals], dtype=np.float64)

    def to_markdown(self) -> str:
        """Format the table as GitHub markdown, with the sampling and BRDF as a caption."""
        head = ["kind", "order", "quantity", "coefficients", "bytes", "projection s", "eval ns",
                *METRICS]
        lines = [f"Study of {self.source} (quantity {self.quantity!r}); {self.sampling}.", "",
                 "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for r in self.rows:
            cells = [r["kind"], str(r["order"]), r["quantity"], str(r["coefficients"]),
                     str(r["bytes"]),
                     f"{r['projection_s']:.3g}", f"{r['eval_ns']:.3g}"]
            cells += ["n/a" if r[m] is None else f"{r[m]:.3g}" for m in METRICS]
            lines.append("| " + " | ".join(cells) + " |")
        if self.messages:
            lines += ["", f"{len(self.messages)} projection warning(s); the first: "
                      f"{self.messages[0]}"]
        return "\n".join(lines)

    def pareto(self, cost: str = "eval_ns", metric: str = "l2") -> NDArray[np.bool_]:
        """Return the mask of the rows on the Pareto front of (cost, error).

        A row is on the front when no other row is at least as cheap and at least as
        accurate, and strictly better in one.
        """
        return pareto_front(self.column(cost), self.column(metric))

    def plot(self, path: str, *, metric: str = "l2") -> Path:
        """Write a PNG of the error against order, bytes and evaluation time.

        Three panels: error vs order, error vs bytes and error vs evaluation time (one line
        per kind; the Pareto front over all rows marked).

        Returns
        -------
        pathlib.Path
            The path written (atomically).
        """
        if metric not in METRICS:
            raise ValueError(f"metric must be one of {', '.join(METRICS)}, got {metric!r}")
        from matplotlib.figure import Figure  # no pyplot: the user's backend is left alone

        err = self.column(metric)
        floor = np.nanmin(err[err > 0]) / 10 if np.any(err > 0) else 1e-16
        err = np.where(err > 0, err, floor)
        kinds = self.column("kind")
        fig = Figure(figsize=(15, 4.5))
        axes = fig.subplots(1, 3)
        for ax, xname, xlabel in zip(axes, ("order", "bytes", "eval_ns"),
                                     ("order", "bytes (float64, symmetric storage)",
                                      "evaluation time per sample (ns)"), strict=True):
            x = self.column(xname)
            for k in dict.fromkeys(kinds):
                sel = kinds == k
                ax.plot(x[sel], err[sel], "o-", label=str(k))
            if xname != "order":
                front = pareto_front(x, err)
                order = np.argsort(x[front])
                ax.step(x[front][order], err[front][order], where="post", color="k", lw=1,
                        alpha=0.6, label="Pareto front")
                ax.plot(x[front], err[front], "o", mfc="none", mec="k", ms=11)
                ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel(xlabel)
            ax.set_ylabel(f"{metric} error")
            ax.grid(True, which="both", alpha=0.3)
        axes[0].legend()
        axes[2].legend(fontsize=8)
        fig.suptitle(f"{self.source}: {metric} error against order, storage and speed",
                     fontsize=10)
        fig.tight_layout()
        with atomic_path(path, suffix=".png") as tmp:
            fig.savefig(tmp, format="png", dpi=90)
        return Path(path)


def _study_samples(meas: project.Measurements, kinds: tuple[str, ...], orders: list[int],
                   quantity: str, smooth: str | None, max_theta: float, seed: int,
                   time_eval: bool, fit_kwargs: dict[str, Any]) -> Study:
    """study(measurements, ...): least-squares fits, every metric on held-out samples."""
    quantity = "f_cos" if quantity == "auto" else quantity
    fit_kwargs.setdefault("isotropic", meas.isotropic is not False)
    folds = meas.folds(FOLDS, seed=seed)
    zi, zo = meas.wi[:, 2], meas.wo[:, 2]
    domain = (zi > np.cos(max_theta)) & (zo > np.cos(max_theta))
    f, w = meas.values, meas.weights[:, None]
    rows, messages = [], []
    for k in kinds:
        for order in orders:
            b = make_basis(k, order)

            def fit(m: project.Measurements, b: Any = b) -> CoefficientMatrix:
                cm = project.fit(m, b, quantity=quantity, **fit_kwargs)
                return cm if smooth is None else _smooth(cm, smooth)

            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                start = time.perf_counter()
                cm = fit(meas)
                seconds = time.perf_counter() - start
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # the folds repeat the full fit's
                    (pred,) = out_of_fold(meas, fit, folds)
            messages += [str(c.message) for c in caught]
            row: dict[str, Any] = dict(kind=k if smooth is None else f"{k}/{smooth}",
                                       order=order, quantity=cm.quantity,
                                       coefficients=unique_coefficients(cm))
            row["bytes"] = 8 * row["coefficients"]
            row["projection_s"] = seconds
            row["eval_ns"] = eval_ns(cm) if time_eval else float("nan")
            row["l2"] = sample_errors(meas, pred, folds=folds)["l2"]
            g = np.broadcast_to(pred, f.shape)
            row["negative"] = float(np.max(np.sum(w * (g < 0), axis=0) / np.sum(w)))
            for suffix, sel in (("", domain), ("_all", np.ones_like(domain))):
                row.update({key + suffix: v for key, v in _pointwise(
                    f[sel], g[sel], w[sel], zi[sel, None]).items()})
                row["albedo" + suffix] = None
                a, r = cm.eval(meas.wi[sel], meas.wo[sel]), cm.eval(meas.wo[sel], meas.wi[sel])
                scale = float(np.max(np.abs(a), initial=0.0)) or 1.0
                row["reciprocity" + suffix] = float(np.max(np.abs(a - r), initial=0.0)) / scale
            row["truncation_error"] = None
            row["warnings"] = len(caught)
            rows.append(row)
    how = (f"{int(np.unique(folds).size)}-fold cross-validation on {len(meas)} held-out "
           "samples, weighted by their weights")
    return Study(rows, repr(meas), quantity, how, messages)


def pareto_front(cost: ArrayLike, error: ArrayLike) -> NDArray[np.bool_]:
    """Mask of the points not dominated in (cost, error), both to be minimised.

    Examples
    --------
    >>> pareto_front([1, 2, 3, 2], [5, 3, 4, 3]).tolist()
    [True, True, False, True]
    """
    c = np.asarray(cost, dtype=np.float64)
    e = np.asarray(error, dtype=np.float64)
    if c.shape != e.shape or c.ndim != 1:
        raise ValueError(f"cost and error must be 1-D of one length, got shapes {c.shape} "
                         f"and {e.shape}")
    le = (c[None, :] <= c[:, None]) & (e[None, :] <= e[:, None])
    lt = (c[None, :] < c[:, None]) | (e[None, :] < e[:, None])
    dominated = np.any(le & lt, axis=1)
    return ~dominated


def study(brdf: Any, kind: str | Sequence[str], orders: Sequence[int], *,
          quantity: str = "auto", smooth: str | None = None, nodes: tuple[int, int] = NODES,
          max_theta: float = MAX_THETA, seed: int = 0, time_eval: bool = True,
          **project_kwargs: Any) -> Study:
    """Project ``brdf`` at each order of each kind and measure every metric.

    Parameters
    ----------
    brdf : BRDF or project.Measurements
        For measurements, each row is a least-squares fit (:func:`project.fit`, its
        regularisation chosen by cross-validation) and every metric is measured on
        held-out samples: each sample is predicted by the fit to the other folds of a
        10-fold split (:meth:`project.Measurements.folds`, seeded by ``seed``), with the
        samples' weights as the measure; ``D`` is the samples with both polar angles below
        ``max_theta``; ``albedo`` and ``truncation_error`` are None (no rule over H x H);
        ``projection_s`` is the time of the fit to all samples, ``nodes`` is unused.
    kind : str or sequence of str
        Basis kinds, :data:`KINDS`: ``"zernike"`` (HemiZernike), ``"harmonics"``
        (HemiHarmonics, odd: Westin's choice), ``"harmonics-even"``, ``"sh"``
        (SphericalHarmonics). Several kinds put several curves on one chart.
    orders : sequence of int
    quantity : {"auto", "f_cos", "f"}
        As in :func:`project.project`; ``"auto"`` (:func:`project.default_quantity`) may pick
        a different quantity per kind, which the ``quantity`` column records.
    smooth : {"half-gaussian", "lanczos", "hann"}, optional
        Apply :func:`compress.smooth` with its defaults to every projection (the row's kind
        reads e.g. ``"zernike/hann"``).
    nodes, max_theta, seed
        The test set (module notes).
    time_eval : bool
        Measure ``eval_ns`` (about 0.05 s per row); NaN otherwise.
    **project_kwargs
        Passed to :func:`project.project` (``method``, ``tol``, ...).

    Returns
    -------
    Study
    """
    kinds = (kind,) if isinstance(kind, str) else tuple(kind)
    if not kinds:
        raise ValueError("kind must name at least one basis kind")
    for k in kinds:
        if k not in KINDS:
            raise ValueError(f"kind must be one of {', '.join(map(repr, KINDS))}, got {k!r}")
    orders = [nonneg_int(o, "orders") for o in orders]
    if not orders:
        raise ValueError("orders must hold at least one order")
    if isinstance(brdf, project.Measurements):
        return _study_samples(brdf, kinds, orders, quantity, smooth, max_theta, seed,
                              time_eval, project_kwargs)
    ts = reference_samples(brdf, nodes=nodes, max_theta=max_theta, seed=seed)
    rows, messages = [], []
    for k in kinds:
        for order in orders:
            b = make_basis(k, order)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                cm = project.project(brdf, b, quantity=quantity,
                                     **{"reciprocal": True, **project_kwargs})
            messages += [str(c.message) for c in caught]
            if smooth is not None:
                cm = _smooth(cm, smooth)
            row: dict[str, Any] = dict(kind=k if smooth is None else f"{k}/{smooth}",
                                       order=order, quantity=cm.quantity,
                                       coefficients=unique_coefficients(cm))
            row["bytes"] = 8 * row["coefficients"]
            row["projection_s"] = float(cm.info.get("seconds", np.nan))
            row["eval_ns"] = eval_ns(cm) if time_eval else float("nan")
            row.update(errors(cm, ts))
            row["truncation_error"] = cm.info.get("truncation_error")
            row["warnings"] = len(caught)
            rows.append(row)
    return Study(rows, repr(brdf), quantity, ts.description, messages)

