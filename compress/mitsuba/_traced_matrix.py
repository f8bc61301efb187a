"""Coefficient matrices in Dr.Jit operations (see :mod:`compress.mitsuba._traced`).

Isotropic matrices, reciprocal or not, in the separable Chebyshev form that
:meth:`basis.evaluate.Evaluator.separable` exposes (per azimuthal order m a small block on the
Chebyshev values of both directions, times Re[(a_i conj a_o)^m]); anisotropic (dense) ones
function by function, each basis function from its radial factor in Chebyshev form, then
b(w_i)^T M b(w_o). Matrix entries are literal constants of the traced kernel.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from basis import CoefficientMatrix

__all__ = ["Traced", "matrix_form"]

#: A traced evaluator: (w_light, w_view) unit Vector3f above the horizon -> f per channel.
Traced = Callable[[Any, Any], list]


# -- coefficient matrices ---------------------------------------------------------------------

def _lift(w: Any, lift: float) -> tuple[Any, Any, Any]:
    """Directions with cos(theta) < ``lift`` moved up to it at the same azimuth."""
    x, y, z = w.x, w.y, w.z
    if lift > 0.0:
        s_lift = math.sqrt(1.0 - lift * lift)
        low = z < lift
        s = dr.sqrt(dr.fma(x, x, y * y))
        hp = s > 0.0
        fs = s_lift * dr.rcp(dr.select(hp, s, 1.0))
        x = dr.select(low, dr.select(hp, x * fs, s_lift), x)
        y = dr.select(low, dr.select(hp, y * fs, 0.0), y)
        z = dr.select(low, lift, z)
    return x, y, z


def _separable_geometry(kind: str, x: Any, y: Any, z: Any) -> tuple[Any, Any, Any]:
    """a(w) (real, imaginary) and the Chebyshev variable x(w) of a basis kind."""
    if kind == "zernike":
        r = dr.rsqrt(1.0 + z)
        return x * r, y * r, 1.0 - 2.0 * z
    return x, y, (z if kind == "sh" else dr.fma(2.0 * z, z, -1.0))


def _chebyshev(x: Any, k: int) -> list[Any]:
    """T_0(x) .. T_{k-1}(x) (at least T_0) by the three-term recurrence."""
    t = [mi.Float(1.0), x]
    for _ in range(2, k):
        t.append(dr.fma(2.0 * x, t[-1], -t[-2]))
    return t[:max(k, 1)]


_KINDS = ("zernike", "harmonics", "harmonics-even", "sh")


def _basis_rows(b: Any) -> tuple[int, list[tuple[int, bool, np.ndarray]]] | None:
    """Per function (m, sin?, Chebyshev coefficients of its polynomial part), from radial."""
    kind = b.kind
    if kind not in _KINDS:
        return None
    blocks = b.azimuthal_blocks()
    kmax = max((c.size for c in blocks.cos), default=1)
    nodes = 2 * kmax + 8
    t = np.cos(np.pi * (np.arange(nodes) + 0.5) / nodes)
    z = (1.0 - t) / 2.0 if kind == "zernike" else t if kind == "sh" else np.sqrt((t + 1) / 2)
    table = b.radial(z)
    cheb = np.polynomial.chebyshev.chebvander(t, max(kmax - 1, 0))
    degree = np.asarray(b.degree)
    rows: list[Any] = [None] * b.size
    for m, (ci, si) in enumerate(zip(blocks.cos, blocks.sin, strict=True)):
        if ci.size == 0:
            continue
        if kind == "zernike":
            fac = np.sqrt(1.0 - z) ** m
        else:
            fac = np.sqrt((1.0 - z) * (1.0 + z)) ** m * (z if kind == "harmonics" else 1.0)
        poly = table[:, ci] / fac[:, None]
        v, *_ = np.linalg.lstsq(cheb[:, :ci.size], poly, rcond=None)  # (k cheb, k funcs)
        for col, j in enumerate(ci):
            rows[j] = (m, False, v[:, col])
        for j in si:
            col = int(np.flatnonzero(degree[ci] == degree[j])[0])
            rows[j] = (m, True, v[:, col])
    return kmax, rows


def _dense(cm: CoefficientMatrix) -> Traced | None:
    """b(w_i)^T M b(w_o) with every basis function traced (anisotropic matrices)."""
    b = cm.basis
    built = _basis_rows(b)
    if built is None:
        return None
    kmax, rows = built
    mats = np.asarray(cm.matrix, dtype=np.float64)
    if mats.ndim == 2:
        mats = mats[None]
    kind = b.kind
    fcos = cm.quantity == "f_cos"
    lift = 1e-3 if fcos else 0.0
    top = max(r[0] for r in rows)

    def functions(w: Any) -> tuple[list[Any], Any]:
        x, y, z = _lift(w, lift)
        ar, ai, xc = _separable_geometry(kind, x, y, z)
        t = _chebyshev(xc, kmax)
        powers = [(mi.Float(1.0), mi.Float(0.0))]
        for _ in range(top):
            pr, pi = powers[-1]
            powers.append((pr * ar - pi * ai, pr * ai + pi * ar))
        g = z if kind == "harmonics" else None
        out = []
        for m, sin, coef in rows:
            p = None
            for a, v in enumerate(coef):
                if v != 0.0:
                    p = t[a] * float(v) if p is None else dr.fma(t[a], float(v), p)
            p = mi.Float(0.0) if p is None else p
            if m > 0:
                p = p * powers[m][1 if sin else 0]
            out.append(p if g is None else p * g)
        return out, z

    def f(wi: Any, wo: Any) -> list:
        bi, zi = functions(wi)
        bo, zo = functions(wo)
        res = []
        for mat in mats:
            q = None
            for k in range(mat.shape[1]):
                u = None
                for j in range(mat.shape[0]):
                    v = float(mat[j, k])
                    if v != 0.0:
                        u = bi[j] * v if u is None else dr.fma(bi[j], v, u)
                if u is not None:
                    q = u * bo[k] if q is None else dr.fma(u, bo[k], q)
            q = mi.Float(0.0) if q is None else q
            res.append(q * dr.rcp(zi * zo) if fcos else q)
        return res
    return f


def matrix_form(cm: CoefficientMatrix) -> Traced | None:
    """Return the traced evaluator of a coefficient matrix (None for an unknown basis)."""
    if not cm.is_isotropic:
        return _dense(cm)
    form = cm.evaluator().separable()
    if form is None:
        return None
    kind = form["kind"]
    coef, tri = form["coef"], form["tri"]
    coefa, tria = form["coefa"], form["tria"]
    fcos = form["fcos"]
    lift = form["min_cos"] if fcos else 0.0
    nb, nch, _ = coef.shape
    kmax = int(max(tri.max(), 1))
    kmax = int(round((math.sqrt(8 * kmax + 1) - 1) / 2))
    # packed (a, b) of entry q, as basis.evaluate packs them (column by column)
    sym = [(a, b) for b in range(kmax) for a in range(b + 1)]
    anti = [(a, b) for b in range(kmax) for a in range(b)]

    def geometry(w: Any) -> tuple[Any, Any, Any, Any]:
        x, y, z = _lift(w, lift)
        return (*_separable_geometry(kind, x, y, z), z)

    def cheb(x: Any) -> list[Any]:
        return _chebyshev(x, kmax)

    def f(wi: Any, wo: Any) -> list:
        ax, ay, xi, zi = geometry(wi)
        bx, by, xo, zo = geometry(wo)
        ti, to = cheb(xi), cheb(xo)
        # w = a_i conj(a_o)
        wr = ax * bx + ay * by
        wim = ay * bx - ax * by
        sp = {}
        for a, b in sym:
            if a == b:
                sp[a, b] = ti[a] * to[a]
            else:
                sp[a, b] = dr.fma(ti[a], to[b], ti[b] * to[a])
        sa = {}
        if tria.max(initial=0) > 0:
            for a, b in anti:
                sa[a, b] = dr.fma(ti[a], to[b], -(ti[b] * to[a]))
        tot = [mi.Float(0.0) for _ in range(nch)]
        pr, pim = mi.Float(1.0), mi.Float(0.0)
        for m in range(nb):
            for c in range(nch):
                acc = None
                for q in range(int(tri[m])):
                    v = float(coef[m, c, q])
                    if v != 0.0:
                        acc = sp[sym[q]] * v if acc is None else dr.fma(sp[sym[q]], v, acc)
                for q in range(int(tria[m])):
                    v = float(coefa[m, c, q])
                    if v != 0.0:
                        acc = sa[anti[q]] * v if acc is None else dr.fma(sa[anti[q]], v, acc)
                if acc is not None:
                    tot[c] = acc if m == 0 else dr.fma(pr, acc, tot[c])
            if m + 1 < nb:
                pr, pim = pr * wr - pim * wim, pr * wim + pim * wr
        zz = zi * zo
        if kind == "harmonics":
            scale = None if fcos else zz
        else:
            scale = dr.rcp(zz) if fcos else None
        return tot if scale is None else [v * scale for v in tot]
    return f
