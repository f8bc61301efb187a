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
from scipy.sparse import csr_matrix

from basis.jit import njit

from ._geometry import _Geometry

#: From this many channels on, a family whose parameters are mostly per channel is solved
#: with a sparse Jacobian (each row depends on its channel's parameters and the shared
#: ones) and LSMR steps: a dense SVD of (n C) x (2 C + 2) per step took 1-2 s for a
#: 1,439-sample, 31-wavelength table.
SPARSE_CHANNELS = 8


def _solve(model, g: _Geometry, f: NDArray, w: NDArray, metric: str, k: int,
           rng: np.random.Generator, max_nfev: int | None):
    """One restart: least_squares from start k, channel by channel for a separable family.

    A separable family (no parameter shared between channels) has a cost that is a sum of
    per-channel costs; solving each channel alone reaches the same optimum with a Jacobian C
    times narrower (the solves cost ~C^2 less). The result is put together as if one solve:
    x, fun and a block Jacobian in the joint layout, the summed cost and evaluations, and the
    worst status.
    """
    if metric == "l2" and getattr(model, "projected", False):
        return _projected(model, g, f, w, k, rng, max_nfev)
    if not getattr(model, "separable", False):
        res_fn, jac_fn, row = _objective(model, g, f, w, metric)
        x0 = _start(model, g, f, row, k, rng)
        if f.shape[1] < SPARSE_CHANNELS:
            return least_squares(res_fn, x0, jac=jac_fn, bounds=model.bounds, method="trf",
                                 x_scale="jac", max_nfev=max_nfev)
        run = least_squares(res_fn, x0, jac=lambda x: csr_matrix(jac_fn(x)),
                            bounds=model.bounds, method="trf", x_scale="jac",
                            tr_solver="lsmr", max_nfev=max_nfev)
        run.jac = run.jac.toarray()
        return run
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


def _projected(model, g: _Geometry, f: NDArray, w: NDArray, k: int, rng: np.random.Generator,
               max_nfev: int | None):
    """One restart of a family with two linear parameters per channel, in the l2 metric.

    Variable projection (Golub & Pereyra 1973): for given nonlinear parameters (roughness,
    F0) the linear ones (kd, ks per channel) that minimise the cost within their bounds
    follow in closed form (:func:`_box_2x2`), so the search runs over the nonlinear ones
    alone, with the residuals of every channel: restart 0 from the best point of a grid
    (``model.search_grid()``: the whole range of roughness on a log scale, F0 on a few
    values), restart k from the k-th best local minimum of that grid's profile over
    roughness (another basin of the cost), or a random point when there are fewer. The
    optimum is a stationary point of the full problem too; its residuals and Jacobian are
    those of all parameters.
    """
    n, c = f.shape
    cc = g.ci * g.co
    q = f * cc[:, None]
    qn2 = np.sum(w[:, None] * q * q, axis=0)
    scale = np.sqrt(w)[:, None] / np.sqrt(qn2)
    u2 = w * cc * cc  # sum_p u2 (a_p . x - f_p)^2 is the unscaled squared l2 error of q
    lo, hi = model.bounds
    lin_lo = np.stack([lo[:c], lo[c:2 * c]], axis=1)
    lin_hi = np.stack([hi[:c], hi[c:2 * c]], axis=1)
    nl_lo, nl_hi = lo[2 * c:], hi[2 * c:]
    fu = (u2[:, None] * f)  # (n, C)
    f_const = (np.full(n, 1.0 / np.pi) @ fu)  # column 0 (kd / pi) against the data

    def linear(xnl: NDArray) -> tuple[NDArray, NDArray]:
        cols = model.columns(xnl, g)  # (n, 2): 1/pi and the lobe with its Fresnel factor
        a1 = cols[:, 1]
        gram = np.array([[u2.sum() / np.pi ** 2, (u2 @ a1) / np.pi],
                         [(u2 @ a1) / np.pi, u2 @ (a1 * a1)]])
        b = np.stack([f_const, a1 @ fu], axis=1)  # (C, 2)
        lin = _box_2x2(gram, b, lin_lo, lin_hi)
        cost = (qn2 - 2.0 * np.sum(lin * b, axis=1)
                + np.einsum("ci,ij,cj->c", lin, gram, lin)) / qn2
        return lin, cost

    def full(xnl: NDArray) -> NDArray:
        lin, _ = linear(xnl)
        return np.r_[lin[:, 0], lin[:, 1], xnl]

    def res(xnl: NDArray) -> NDArray:
        return (scale * (model.value(full(xnl), g) * cc[:, None] - q)).ravel()

    grid = model.search_grid()  # (m, 2) nonlinear points
    key = (id(model), id(f), id(w))  # the restarts of one fit share the search
    kept = getattr(g, "_search", None)
    if kept is None or kept[0] != key:
        costs = np.array([0.5 * linear(x)[1].sum() for x in grid])
        g._search = kept = (key, _basins(grid, costs, getattr(model, "profile_axis", 0)))
    starts = kept[1]
    x0 = starts[k] if k < len(starts) else model.nonlinear_random(rng)
    span = nl_hi - nl_lo
    x0 = np.clip(x0, nl_lo + 1e-6 * span, nl_hi - 1e-6 * span)
    run = least_squares(res, x0, bounds=(nl_lo, nl_hi), method="trf", x_scale=1.0,
                        diff_step=1e-6, max_nfev=max_nfev)
    x = full(np.clip(run.x, nl_lo, nl_hi))
    res_fn, jac_fn, _ = _objective(model, g, f, w, "l2")
    fun = res_fn(x)
    return SimpleNamespace(x=x, cost=0.5 * float(fun @ fun), fun=fun, jac=jac_fn(x),
                           status=int(run.status), nfev=int(run.nfev) + len(grid),
                           njev=int(run.njev or 0))


def _basins(grid: NDArray, costs: NDArray, axis: int = 0) -> list[NDArray]:
    """Grid points at the local minima of the cost's profile over one coordinate.

    The profile is the least cost over the other coordinates at each value of coordinate
    ``axis`` (the roughness or the exponent); its local minima (the lowest first) are the
    starting points of distinct basins.
    """
    first = grid[:, axis]
    values = np.unique(first)
    best = [int(np.flatnonzero(first == v)[np.argmin(costs[first == v])]) for v in values]
    prof = costs[best]
    minima = [i for i in range(len(values))
              if (i == 0 or prof[i] <= prof[i - 1]) and (i == len(values) - 1
                                                          or prof[i] <= prof[i + 1])]
    minima.sort(key=lambda i: prof[i])
    return [grid[best[i]] for i in minima]


def _box_2x2(gram: NDArray, b: NDArray, lo: NDArray, hi: NDArray) -> NDArray:
    """Minimise x^T G x - 2 b_c^T x over lo_c <= x <= hi_c, for every row c at once.

    ``gram`` (2, 2) positive semi-definite, ``b``, ``lo``, ``hi`` (C, 2). The minimum of a
    convex quadratic over a rectangle is the unconstrained one when that is inside, else
    on an edge, where the minimum along the edge clipped to it is the edge's best: the
    least of these candidates is the answer.
    """
    out = np.empty_like(b)
    _box_kernel(float(gram[0, 0]), float(gram[0, 1]), float(gram[1, 1]),
                np.ascontiguousarray(b), np.ascontiguousarray(lo), np.ascontiguousarray(hi),
                out)
    return out


@njit(inline="always")
def _box_value(g00, g01, g11, b0, b1, x0, x1):  # pragma: no cover - compiled
    return g00 * x0 * x0 + 2.0 * g01 * x0 * x1 + g11 * x1 * x1 - 2.0 * (b0 * x0 + b1 * x1)


@njit
def _box_kernel(g00, g01, g11, b, lo, hi, out):  # pragma: no cover - compiled
    # b, lo, hi (C, 2) -> out (C, 2): the candidates of _box_2x2, the least kept
    det = g00 * g11 - g01 * g01
    regular = det > 1e-12 * max(g00 * g11, 1e-300)
    for c in range(b.shape[0]):
        best, bx0, bx1 = np.inf, lo[c, 0], lo[c, 1]
        if regular:
            x0 = (g11 * b[c, 0] - g01 * b[c, 1]) / det
            x1 = (g00 * b[c, 1] - g01 * b[c, 0]) / det
            if lo[c, 0] <= x0 <= hi[c, 0] and lo[c, 1] <= x1 <= hi[c, 1]:
                out[c, 0], out[c, 1] = x0, x1
                continue
        for side in range(2):
            x0 = lo[c, 0] if side == 0 else hi[c, 0]
            x1 = (b[c, 1] - g01 * x0) / g11 if g11 > 0.0 else lo[c, 1]
            x1 = min(max(x1, lo[c, 1]), hi[c, 1])
            v = _box_value(g00, g01, g11, b[c, 0], b[c, 1], x0, x1)
            if v < best:
                best, bx0, bx1 = v, x0, x1
            x1 = lo[c, 1] if side == 0 else hi[c, 1]
            x0 = (b[c, 0] - g01 * x1) / g00 if g00 > 0.0 else lo[c, 0]
            x0 = min(max(x0, lo[c, 0]), hi[c, 0])
            v = _box_value(g00, g01, g11, b[c, 0], b[c, 1], x0, x1)
            if v < best:
                best, bx0, bx1 = v, x0, x1
        out[c, 0], out[c, 1] = bx0, bx1


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
    # columns scaled to unit norm, so that the rank test does not depend on units; the
    # singular values and vectors of the triangular factor are those of J (a tall J:
    # QR first halves the time)
    scaled = jac[:, ok] / norms[ok]
    r = np.linalg.qr(scaled, mode="r") if scaled.shape[0] > 2 * scaled.shape[1] else scaled
    _, sv, vt = np.linalg.svd(r, full_matrices=False)
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
