"""The least-squares machinery of :func:`project.fitting.fit_model` (notes in its module).

One restart (:func:`_solve`) from a start (:func:`_start`) on the residuals of a metric
(:func:`_objective`), and the linearised covariance of the optimum (:func:`_covariance`)
with the helpers the families use to carry it to their natural parameters.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares, nnls

from ._geometry import _Geometry


def _solve(model, g: _Geometry, f: NDArray, w: NDArray, metric: str, k: int,
           rng: np.random.Generator, max_nfev: int | None):
    """One restart: least_squares from start k, channel by channel for a separable family.

    A separable family (no parameter shared between channels) has a cost that is a sum of
    per-channel costs; solving each channel alone reaches the same optimum with a Jacobian C
    times narrower (the solves cost ~C^2 less). The result is put together as if one solve:
    x, fun and a block Jacobian in the joint layout, the summed cost and evaluations, and the
    worst status.
    """
    if not getattr(model, "separable", False):
        res_fn, jac_fn, row = _objective(model, g, f, w, metric)
        x0 = _start(model, g, f, row, k, rng)
        return least_squares(res_fn, x0, jac=jac_fn, bounds=model.bounds, method="trf",
                             x_scale="jac", max_nfev=max_nfev)
    sub = model.channel_model()
    c, per = f.shape[1], sub.p
    runs = []
    for ch in range(c):
        res_fn, jac_fn, row = _objective(sub, g, f[:, ch:ch + 1], w, metric)
        x0 = sub.start(g, f[:, ch:ch + 1], row, k, rng)
        runs.append(least_squares(res_fn, x0, jac=jac_fn, bounds=sub.bounds, method="trf",
                                  x_scale=sub.x_scale, ftol=sub.ftol, max_nfev=max_nfev))
    jac = np.zeros((g.n, c, model.p))
    for ch, r in enumerate(runs):
        jac[:, ch, ch * per:(ch + 1) * per] = r.jac
    statuses = [int(r.status) for r in runs]
    return SimpleNamespace(
        x=np.concatenate([r.x for r in runs]), cost=float(sum(r.cost for r in runs)),
        fun=np.stack([r.fun for r in runs], axis=1).ravel(), jac=jac.reshape(g.n * c, -1),
        status=min(statuses) if min(statuses) <= 0 else max(statuses),
        nfev=int(sum(r.nfev for r in runs)), njev=int(sum(r.njev or 0 for r in runs)))


def _objective(model, g: _Geometry, f: NDArray, w: NDArray, metric: str):
    """Residual and Jacobian functions of the metric, and the row weights for NNLS starts."""
    n, c = f.shape
    cc = g.ci * g.co
    if hasattr(model, "residuals"):
        return _fused(model, g, f, w, metric)
    if metric == "l2":
        q = f * cc[:, None]
        scale = np.sqrt(w)[:, None] / np.sqrt(np.sum(w[:, None] * q * q, axis=0))

        def res(x: NDArray) -> NDArray:
            return (scale * (model.value(x, g) * cc[:, None] - q)).ravel()

        def jac(x: NDArray) -> NDArray:
            _, df = model.value(x, g, jac=True)
            return ((scale * cc[:, None])[:, :, None] * df).reshape(n * c, -1)

        return res, jac, scale * cc[:, None]
    ci = g.ci[:, None]
    target = np.log1p(f * ci)
    scale = np.sqrt(w / np.sum(w))[:, None]

    def res_log(x: NDArray) -> NDArray:
        return (scale * (np.log1p(model.value(x, g) * ci) - target)).ravel()

    def jac_log(x: NDArray) -> NDArray:
        fm, df = model.value(x, g, jac=True)
        return ((scale * ci / (1.0 + fm * ci))[:, :, None] * df).reshape(n * c, -1)

    # starts: the l2 rows (the log metric is not linear in kd, ks)
    l2 = np.sqrt(w)[:, None] / np.sqrt(np.sum(w[:, None] * (f * cc[:, None]) ** 2, axis=0))
    return res_log, jac_log, l2 * cc[:, None]


def _fused(model, g: _Geometry, f: NDArray, w: NDArray, metric: str):
    """:func:`_objective` for a family whose ``residuals`` gives both in one pass.

    scipy's trust-region reflective method asks for the Jacobian at every accepted point,
    right after the residuals there: both come from one pass over the pairs, and the
    Jacobian waits for that call (a rejected step only costs its unused Jacobian).
    """
    n, c = f.shape
    cc = g.ci * g.co
    q = f * cc[:, None]
    l2 = np.sqrt(w)[:, None] / np.sqrt(np.sum(w[:, None] * q * q, axis=0))
    if metric == "l2":
        scale, target = l2, q
    else:
        scale = np.broadcast_to(np.sqrt(w / np.sum(w))[:, None], (n, c))
        target = np.log1p(f * g.ci[:, None])
    scale, target = np.ascontiguousarray(scale), np.ascontiguousarray(target)
    log = metric != "l2"
    last: dict = {}

    def res(x: NDArray) -> NDArray:
        r, jac = model.residuals(x, g, scale, target, log)
        last.update(x=x.copy(), jac=jac)
        return r

    def jac(x: NDArray) -> NDArray:
        if "x" not in last or not np.array_equal(x, last["x"]):
            res(x)
        out = last.pop("jac")
        last.clear()
        return out

    return res, jac, l2 * cc[:, None]


def _start(model, g: _Geometry, f: NDArray, row: NDArray, k: int,
           rng: np.random.Generator) -> NDArray:
    """Return the starting point of restart k.

    The nonlinear part comes from a grid (k = 0) or at random, the linear part (kd and ks or
    rho) from non-negative least squares per channel.
    """
    lo, hi = model.bounds
    # the trailing nonlinear reals (2 per lobe), or the family's own start vector
    nl_lo, nl_hi = getattr(model, "nl_bounds", (lo[-2 * model.k:], hi[-2 * model.k:]))
    candidates = model.nonlinear_grid() if k == 0 else [model.nonlinear_random(rng)]
    best = None
    for xnl in candidates:
        xnl = np.clip(xnl, nl_lo, nl_hi)
        cols = model.columns(xnl, g)  # (n, m) shared, or (n, C, m) per channel
        lin = np.empty((f.shape[1], cols.shape[-1]))
        cost = 0.0
        for ch in range(f.shape[1]):
            a = (cols if cols.ndim == 2 else cols[:, ch]) * row[:, ch:ch + 1]
            lin[ch], rnorm = nnls(a, f[:, ch] * row[:, ch], maxiter=50 * a.shape[1])
            cost += rnorm ** 2
        if best is None or cost < best[0]:
            best = (cost, xnl, lin)
    _, xnl, lin = best
    x = model.assemble(lin, xnl) if hasattr(model, "assemble") else \
        np.r_[lin[:, 0], lin[:, 1:].T.ravel(), xnl]
    # strictly inside the bounds (the trust-region reflective method needs it)
    span = hi - lo
    return np.clip(x, lo + 1e-6 * span, hi - 1e-6 * span)


def _covariance(jac: NDArray, fun: NDArray, p: int) -> NDArray:
    """(J^T J)^-1 s^2 with s^2 = sum r^2 / (m - p); inf where the data do not determine."""
    m = fun.size
    s2 = float(fun @ fun) / max(m - p, 1)
    norms = np.linalg.norm(jac, axis=0)
    cov = np.full((p, p), np.inf)
    ok = norms > 0.0
    if not ok.any():
        return cov
    # columns scaled to unit norm, so that the rank test does not depend on units
    _, sv, vt = np.linalg.svd(jac[:, ok] / norms[ok], full_matrices=False)
    good = sv > 1e-10 * sv[0]
    inner = (vt[good].T / sv[good] ** 2) @ vt[good] * s2 / np.outer(norms[ok], norms[ok])
    weak = np.any(np.abs(vt[~good]) > 1e-3, axis=0) if (~good).any() else \
        np.zeros(int(ok.sum()), bool)
    inner[weak, :] = np.inf
    inner[:, weak] = np.inf
    cov[np.ix_(ok, ok)] = inner
    return cov


def _sqrt_diag(cov: NDArray) -> NDArray:
    return np.sqrt(np.diag(cov))


def _quad(grad: NDArray, cov: NDArray) -> float:
    """sqrt(grad^T cov grad) (inf if an involved variance is inf)."""
    idx = grad != 0.0
    sub = cov[np.ix_(idx, idx)]
    if np.any(np.isinf(sub)):
        return float(np.inf)
    return float(np.sqrt(max(grad[idx] @ sub @ grad[idx], 0.0)))
