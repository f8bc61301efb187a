"""A BRDF as a Tucker tensor of piecewise-linear curves in Rusinkiewicz angles: :class:`TuckerBRDF`.

q = f cos(theta_i) cos(theta_o) is held as

    q_c(theta_h, theta_d, phi_d) = sum_{a, b, k, e} G[a, b, k, e] H_a(theta_h) D_b(theta_d)
                                   P_k(phi_d) K[c, e]

a Tucker decomposition (Tucker 1966; De Lathauwer, De Moor & Vandewalle 2000) whose three
angular factors are piecewise-linear curves on knots of their own, placed where the material
needs them, and whose colour factor K (channels x colour rank) is shared by every term. A
lobe that is a product of 1-D factors (the factored lobes of :mod:`project.factored`) is the
special case of ranks (1, 1, 1); a table (:mod:`project.tabulated`) is the case of full
ranks with knots at every node. In between, the core G holds the coupling of the three
angles that a sum of products cannot, such as the way a sharp lobe narrows, shifts and turns
asymmetric towards grazing angles, at a few kilobytes. It is the model family ``"tucker"``
(``project.FittedModel("tucker", params)``, :mod:`compress.store`) and holds non-reciprocal
data (phi_d over the whole turn) or, over half the turn, is reciprocal by construction.

Notes
-----
**Coordinates.** As :mod:`project.tabulated`: s_h = sqrt(2 theta_h / pi) (dense near the
specular direction), s_d = 1 - (1 - 2 theta_d / pi)^(1/p) (p = 2, ``warp_d="grazing"``,
dense towards grazing; p = 1 linear) and s_phi = phi_d / P with the period P = 2 pi
(``phi_turn="full"``) or pi ("half", phi_d folded by reciprocity). Each factor is linear in
its coordinate between its knots (strictly increasing in [0, 1]; theta_h and theta_d
clamp beyond the first and last knot, the phi_d factor is periodic on [0, 1)). Knots are
stored as values exact in float16, so rounding the model to any storage type moves no knot.

**Fitting** (:func:`fit_tucker`). The BRDF is tabulated once on a fine grid
(:func:`project.tabulated.tabulate`, default 256 x 64 x 128 over the whole turn), each node
weighted by the integral over its cell of the measure of H x H in these coordinates,

    d w_i d w_o = 4 cos(theta_d) sin(theta_d) sin(theta_h) d theta_h d theta_d d phi_h d phi_d,

so that the squared weighted sum is the L2 error of q over H x H that
:func:`project.sampling.value_errors` estimates. Each channel is divided by its own norm
first: the error that decides is the largest relative error over the channels, and a dim
channel (the blue of an orange film) must be held as well as a bright one. Then:

1. *Knots.* For each angle, the leading singular vectors of the weighted tensor unfolded
   along it (the curves every term of any Tucker decomposition is made of, weighted by their
   singular values) are fitted by piecewise-linear least squares, and knots are inserted one
   at a time at the middle of the interval with the largest weighted residual (greedy
   refinement, nested: every knot count has its set).
2. *Structure.* Under a budget of stored reals, the ranks (r_h, r_d, r_phi), colour rank and
   knot counts are chosen to minimise a bound on the squared error: the residuals of the
   knot fits of the kept singular vectors plus the discarded singular values of each
   unfolding (the higher-order SVD bound). The few best by that bound are fitted exactly and
   the one with the smallest largest-channel error on the fine grid is kept.
3. *Fit.* With knots fixed, the weighted least-squares projection onto the product of the
   three piecewise-linear spaces is exact (the weight is a product of one weight per angle),
   and the best Tucker approximation of the projected coefficients in the norm of those
   spaces (Cholesky factors of their Gram matrices) is found by the higher-order SVD followed
   by two sweeps of higher-order orthogonal iteration (HOOI). By Pythagoras, the error on the
   fine grid is the projection's plus the truncation's, both computed exactly.

The fine grid bounds what any structure can reach (its own interpolation error; on a glossy
film, 0.044 at 256 x 64 x 64 and 0.020 at 256 x 64 x 128, whose phi_d resolution matters
most). Grid nodes below the horizon are filled from their neighbours, as the tables are.

**Evaluation.** One numba kernel over pairs: the knot interval of each angle by bisection,
the three factor rows interpolated, then r_h r_d r_phi c_rank multiply-adds against the core.
A negative q (the fit is unconstrained) evaluates to 0, which can only lower the error
against data that are >= 0; at a pair on the horizon q is 0, as for every finite BRDF.

**Stored reals**: sum over the angles of m (r + 1) (knots and factor values), plus
r_h r_d r_phi c_rank (the core) and channels x c_rank (the colour factor).

**Measured** (l2 of q, worst channel, 61,970 peak-resolving pairs of
:func:`project.sampling.peak_resolving_pairs`, seed 2027, against the RGL-EPFL files read by
:func:`project.measured.read_rgl`; full turn, default grid; budgets 256 / 512 / 1024 / 2048 /
4096 / 8192 reals):

====================  =====================================================
file                  l2 per budget
====================  =====================================================
chm_orange (film)     0.186 / 0.133 / 0.095 / 0.059 / 0.042 / 0.034
vch_golden_yellow     0.072 / 0.055 / 0.036 / 0.025 / 0.018 / 0.015
cc_nothern_aurora     0.108 / 0.067 / 0.041 / 0.027 / 0.019 / 0.014
cm_military_green     0.084 / 0.062 / 0.046 / 0.036 / 0.023 / 0.017
ilm_l3_37_matte       0.077 / 0.059 / 0.048 / 0.035 / 0.026 / 0.020
colodur_napoli_4f     0.074 / 0.051 / 0.037 / 0.030 / 0.023 / 0.018
ilm_l3_37_metallic    0.023 / 0.015 / 0.010 / 0.007 / 0.005 / 0.004
paper_white           0.030 / 0.022 / 0.018 / 0.016 / 0.009 / 0.007
====================  =====================================================

The fine-grid error (``info["fit_l2"]``) tracks these within about 10 % on the films (it
cannot see the grid's own interpolation error, nor the clamping of negative values). A
full-turn factored lobe of rank 8 (3,180 bytes as select stored it) reaches 0.23 on chm_orange.

References
----------
- L. R. Tucker, "Some mathematical notes on three-mode factor analysis", Psychometrika 31,
  1966.
- L. De Lathauwer, B. De Moor and J. Vandewalle, "A multilinear singular value
  decomposition" and "On the best rank-1 and rank-(R1, R2, ..., RN) approximation of
  higher-order tensors", SIAM J. Matrix Anal. Appl. 21(4), 2000.
- S. Rusinkiewicz, "A new change of variables for efficient BRDF representation",
  Eurographics Rendering Workshop 1998.
- C. de Boor, "A Practical Guide to Splines", Springer 1978 (knot placement by
  equidistributed error).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import linalg
from threadpoolctl import threadpool_limits

from basis.jit import loopjit, njit, run_parallel, writable
from basis.validation import check_bytes, choice, nonneg_int

from ._halfdiff import half_difference
from .brdf import BRDF
from .factored import kept_for
from .tabulated import D_WARPS, PHI_TURNS, option_name, tabulate

__all__ = ["GRID", "TuckerBRDF", "fit_tucker", "tucker_reals"]

#: The fine grid of :func:`fit_tucker`: (n_h, n_d, n_phi), n_phi over the whole turn.
GRID = (256, 64, 128)
#: Ranks the structure search of :func:`fit_tucker` considers, per angle.
_RANKS = ((1, 2, 3, 4, 5, 6, 8, 10, 12, 14, 16, 20, 24, 28, 32),
          (1, 2, 3, 4, 5, 6, 8, 10, 12, 16),
          (1, 2, 3, 4, 5, 6, 8, 10, 12, 16))
#: Knot counts the search considers (up to the fine grid's nodes), and the fewest per angle
#: (two ends; four over a periodic turn).
_KNOTS = (2, 3, 4, 5, 6, 8, 10, 12, 14, 16, 20, 24, 28, 32, 40, 48, 56, 64, 80, 96)
_MIN_KNOTS = (2, 2, 4)
#: Colour ranks the search considers at most (spectral data: the leading spectra).
_COLOR_RANKS = 8
#: How many structures, best by the bound, are fitted exactly.
_REFITS = 3
#: Singular vectors that guide the knots (more carry too little weight to matter).
_GUIDES = 48
_NAMES = ("h", "d", "phi")
_HALF_PI = 0.5 * math.pi


def tucker_reals(knots: tuple[int, int, int], ranks: tuple[int, int, int], color_rank: int,
                 channels: int) -> int:
    """Return the stored reals of a :class:`TuckerBRDF` of this structure (module notes).

    Examples
    --------
    >>> tucker_reals((32, 16, 24), (8, 6, 4), 2, 3)
    910
    """
    return (sum(m * (r + 1) for m, r in zip(knots, ranks, strict=True))
            + math.prod(ranks) * color_rank + channels * color_rank)


class TuckerBRDF(BRDF):
    """A BRDF held as a Tucker tensor of piecewise-linear curves (module notes).

    Parameters
    ----------
    knots : sequence of three 1-D array_like
        Knots of the theta_h, theta_d and phi_d factors in their coordinates s, each
        strictly increasing in [0, 1] ([0, 1) for the periodic phi_d), at least 2 (4 for
        phi_d).
    factors : sequence of three 2-D array_like
        (m_h, r_h), (m_d, r_d), (m_phi, r_phi): each factor's values at its knots.
    core : (r_h, r_d, r_phi, c_rank) array_like
    color : (channels, c_rank) array_like
    warp_d : {"grazing", "linear"}
        Spacing of the theta_d coordinate (as :class:`project.tabulated.TabulatedBRDF`).
    phi_turn : {"full", "half"}
        The period of phi_d: 2 pi (not reciprocal) or pi (reciprocal by construction).
    info : dict, optional

    Attributes
    ----------
    ranks : (int, int, int)
    color_rank, channels, nparams, nbytes, params, reciprocal, info
        ``nbytes`` is 8 ``nparams`` (float64).

    Examples
    --------
    A product of one curve per angle (ranks 1) that is 0.1 everywhere:

    >>> t = TuckerBRDF([[0.0, 0.5], [0.0, 0.5], [0.0, 0.25, 0.5, 0.75]],
    ...                [np.ones((2, 1)), np.ones((2, 1)), np.ones((4, 1))],
    ...                np.full((1, 1, 1, 1), 0.1), np.ones((1, 1)))
    >>> t.ranks, t.nparams
    ((1, 1, 1), 18)
    >>> w = np.array([0.6, 0.0, 0.8])
    >>> round(float(t.eval(w, w)), 12)  # f = q / cos^2
    0.15625
    """

    #: The name of this family in :func:`project.fit_model` and :mod:`compress.store`.
    family = "tucker"
    isotropic = True

    def __init__(self, knots: Any, factors: Any, core: ArrayLike, color: ArrayLike, *,
                 warp_d: str = "grazing", phi_turn: str = "full",
                 info: dict[str, Any] | None = None) -> None:
        self.warp_d = choice(warp_d, "warp_d", tuple(D_WARPS))
        self.phi_turn = choice(phi_turn, "phi_turn", tuple(PHI_TURNS))
        if len(knots) != 3 or len(factors) != 3:
            raise ValueError(f"knots and factors must each hold three arrays (theta_h, "
                             f"theta_d, phi_d), got {len(knots)} and {len(factors)}")
        core = _array(core, "core", 4)
        color = _array(color, "color", 2)
        ks, fs = [], []
        for i, (k, f) in enumerate(zip(knots, factors, strict=True)):
            name = _NAMES[i]
            k = _array(k, f"{name} knots", 1)
            f = _array(f, f"{name} factor", 2)
            top = 1.0 if i < 2 else np.nextafter(1.0, 0.0)  # phi_d: periodic, [0, 1)
            if k.size < _MIN_KNOTS[i] or not (np.all(np.diff(k) > 0) and k[0] >= 0
                                              and k[-1] <= top):
                span = "[0, 1]" if i < 2 else "[0, 1)"
                raise ValueError(f"the {name} knots must be at least {_MIN_KNOTS[i]} values "
                                 f"strictly increasing in {span}, got {k}")
            if f.shape != (k.size, core.shape[i]):
                raise ValueError(f"the {name} factor must have shape (knots, rank) = "
                                 f"({k.size}, {core.shape[i]}) for core {core.shape}, got "
                                 f"{f.shape}")
            ks.append(k)
            fs.append(f)
        if color.shape[1] != core.shape[3] or color.shape[0] < 1:
            raise ValueError(f"color must have shape (channels, {core.shape[3]}) for core "
                             f"{core.shape}, got {color.shape}")
        self._knots, self._factors = tuple(ks), tuple(fs)
        self._core = np.ascontiguousarray(core)
        self._color = np.ascontiguousarray(color)
        for a in (*ks, *fs, self._core, self._color):
            a.flags.writeable = False
        self.reciprocal = self.phi_turn == "half"
        self.channels = int(color.shape[0])
        self._scalar = self.channels == 1
        self.info = {} if info is None else dict(info)

    @property
    def ranks(self) -> tuple[int, int, int]:
        """(r_h, r_d, r_phi): the ranks of the three angles."""
        return tuple(int(n) for n in self._core.shape[:3])  # type: ignore[return-value]

    @property
    def knot_counts(self) -> tuple[int, int, int]:
        """(m_h, m_d, m_phi): the knots of the three angles."""
        return tuple(int(k.size) for k in self._knots)  # type: ignore[return-value]

    @property
    def color_rank(self) -> int:
        """The rank of the colour factor (columns of ``color``)."""
        return int(self._core.shape[3])

    @property
    def nparams(self) -> int:
        """Number of stored reals (module notes); the grid options are not counted."""
        return tucker_reals(self.knot_counts, self.ranks, self.color_rank, self.channels)

    @property
    def nbytes(self) -> int:
        """Storage in bytes, 8 (float64) per stored real."""
        return 8 * self.nparams

    @property
    def params(self) -> dict[str, NDArray[np.float64]]:
        """The stored arrays, as ``project.FittedModel("tucker", params)`` takes them.

        ``h_knots``, ``d_knots``, ``phi_knots`` (m,), ``h_factor``, ``d_factor``,
        ``phi_factor`` (m, r), ``core`` (r_h, r_d, r_phi, c_rank), ``color`` (channels,
        c_rank), and as 0-d arrays ``warp_d`` (the exponent of :data:`project.tabulated.
        D_WARPS`) and ``phi_turn`` (the fraction of the turn); read-only.
        """
        out = {f"{n}_knots": k for n, k in zip(_NAMES, self._knots, strict=True)}
        out.update({f"{n}_factor": f for n, f in zip(_NAMES, self._factors, strict=True)})
        out.update(core=self._core, color=self._color,
                   warp_d=np.array(D_WARPS[self.warp_d]),
                   phi_turn=np.array(PHI_TURNS[self.phi_turn]))
        for v in out.values():
            v.flags.writeable = False
        return out

    @classmethod
    def from_params(cls, params: dict[str, ArrayLike], *,
                    info: dict[str, Any] | None = None) -> TuckerBRDF:
        """Rebuild from :attr:`params` (as :func:`compress.load` returns them)."""
        keys = {*(f"{n}_knots" for n in _NAMES), *(f"{n}_factor" for n in _NAMES), "core",
                "color", "warp_d", "phi_turn"}
        if set(params) != keys:
            raise ValueError(f"params of family 'tucker' must be exactly {sorted(keys)}, got "
                             f"{sorted(params)}")
        names = {key: option_name(params, key, table)
                 for key, table in (("warp_d", D_WARPS), ("phi_turn", PHI_TURNS))}
        return cls([params[f"{n}_knots"] for n in _NAMES],
                   [params[f"{n}_factor"] for n in _NAMES], params["core"], params["color"],
                   info=info, **names)

    def _eval(self, wi: NDArray[np.float64], wo: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.empty((wi.shape[0], self.channels))
        r = self.ranks
        run_parallel(_tucker_kernel, wi.shape[0], writable(wi), writable(wo),
                     *self._knots, *self._factors,
                     self._core.reshape(r[0], r[1], r[2] * self.color_rank), self._color,
                     D_WARPS[self.warp_d], 2.0 * math.pi * PHI_TURNS[self.phi_turn], out,
                     grain=64)
        return out

    def __repr__(self) -> str:
        return (f"TuckerBRDF(knots={self.knot_counts}, ranks={self.ranks}, "
                f"color_rank={self.color_rank}, warp_d={self.warp_d!r}, "
                f"phi_turn={self.phi_turn!r}, channels={self.channels}, "
                f"nbytes={self.nbytes})")


def _array(a: ArrayLike, name: str, ndim: int) -> NDArray[np.float64]:
    try:
        v = np.array(a, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be an array of floats, got {type(a).__name__}") from None
    if v.ndim != ndim or 0 in v.shape:
        raise ValueError(f"{name} must be a non-empty {ndim}-d array, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite, got {int(np.sum(~np.isfinite(v)))} "
                         "non-finite values")
    return v


# -- evaluation ---------------------------------------------------------------------------------

@njit(inline="always")
def _locate(k, s):  # pragma: no cover - compiled
    """Return the interval j (knots j, j + 1) of s in increasing knots k, clamped."""
    lo, hi = 0, k.size - 1
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if k[mid] <= s:
            lo = mid
        else:
            hi = mid
    return lo


@njit(inline="always")
def _row(k, f, s, out):  # pragma: no cover - compiled
    """Interpolate factor rows f (m, r) at s, clamped to the ends of the knots k."""
    m = k.size
    if s <= k[0]:
        for a in range(f.shape[1]):
            out[a] = f[0, a]
        return
    if s >= k[m - 1]:
        for a in range(f.shape[1]):
            out[a] = f[m - 1, a]
        return
    j = _locate(k, s)
    t = (s - k[j]) / (k[j + 1] - k[j])
    for a in range(f.shape[1]):
        out[a] = (1.0 - t) * f[j, a] + t * f[j + 1, a]


@njit(inline="always")
def _periodic_row(k, f, s, out):  # pragma: no cover - compiled
    """Interpolate factor rows f (m, r) at s in [0, 1), periodic knots k."""
    m = k.size
    if s < k[0] or s >= k[m - 1]:
        j0, j1 = m - 1, 0
        a0 = k[m - 1]
        span = k[0] + 1.0 - a0
        t = ((s if s >= a0 else s + 1.0) - a0) / span
    else:
        j0 = _locate(k, s)
        j1 = j0 + 1
        t = (s - k[j0]) / (k[j1] - k[j0])
    for a in range(f.shape[1]):
        out[a] = (1.0 - t) * f[j0, a] + t * f[j1, a]


@loopjit
def _tucker_kernel(first, stop, wi, wo, hk, dk, pk, hf, df, pf, core, color, pd, period,
                   out):  # pragma: no cover - compiled
    # Pairs first .. stop - 1 (run_parallel). core: (r_h, r_d, r_phi * c_rank), color:
    # (channels, c_rank); out: (n, channels). Angles as the tabulated kernel forms them.
    rh, rd, rpc = core.shape[0], core.shape[1], core.shape[2]
    rc = color.shape[1]
    nc = color.shape[0]
    h = np.empty(rh)
    d = np.empty(rd)
    p = np.empty(pf.shape[1])
    acc = np.empty(rpc)
    half = period < 4.0
    for q in range(np.uint64(first), np.uint64(stop)):
        theta_h, theta_d, phi_d, iz, oz = half_difference(wi, wo, q, half)
        cc = max(iz, 0.0) * max(oz, 0.0)
        if cc == 0.0:
            for c in range(nc):
                out[q, c] = 0.0
            continue
        if phi_d < 0.0:
            phi_d += 2.0 * math.pi
        _row(hk, hf, math.sqrt(min(theta_h / (0.5 * math.pi), 1.0)), h)
        x = min(theta_d / (0.5 * math.pi), 1.0)
        _row(dk, df, 1.0 - (1.0 - x) ** (1.0 / pd), d)
        _periodic_row(pk, pf, min(phi_d / period, 1.0) % 1.0, p)
        for e in range(rpc):
            acc[e] = 0.0
        for a in range(rh):
            for b in range(rd):
                w = h[a] * d[b]
                for e in range(rpc):  # contiguous: vectorised
                    acc[e] += w * core[a, b, e]
        scale = 1.0 / max(cc, 1e-300)
        for c in range(nc):
            v = 0.0
            for k in range(pf.shape[1]):
                for e in range(rc):
                    v += acc[k * rc + e] * p[k] * color[c, e]
            out[q, c] = max(v, 0.0) * scale


# -- fitting -----------------------------------------------------------------------------------

def _hats(s: NDArray, knots: NDArray, periodic: bool) -> NDArray[np.float64]:
    """(len(s), len(knots)) values of the piecewise-linear hat functions at s."""
    n, m = s.size, knots.size
    out = np.zeros((n, m))
    rows = np.arange(n)
    if periodic:
        ext = np.append(knots, knots[0] + 1.0)
        j = np.searchsorted(ext, s, side="right") - 1
        before = j < 0  # s below the first knot: the wrapped interval (last, first)
        j = np.where(before, m - 1, j)
        x = np.where(before, s + 1.0, s)
        t = (x - ext[j]) / (ext[j + 1] - ext[j])
        np.add.at(out, (rows, j), 1.0 - t)
        np.add.at(out, (rows, (j + 1) % m), t)
    else:
        j = np.clip(np.searchsorted(knots, s, side="right") - 1, 0, m - 2)
        t = np.clip((s - knots[j]) / (knots[j + 1] - knots[j]), 0.0, 1.0)
        out[rows, j] += 1.0 - t
        out[rows, j + 1] += t
    return out


def _mode(x: NDArray, a: NDArray, k: int) -> NDArray:
    """X times a (new, old) along axis k."""
    return np.moveaxis(np.tensordot(a, x, axes=(1, k)), 0, k)


def _unfold(x: NDArray, k: int) -> NDArray:
    return np.moveaxis(x, k, 0).reshape(x.shape[k], -1)


def _cell_weights(s: NDArray, angle: Any, measure: Any) -> NDArray:
    """Integral of the measure over the dual cell of each node s (half a cell each side)."""
    edges = np.concatenate([s[:1], 0.5 * (s[1:] + s[:-1]), s[-1:]])
    return np.diff(measure(angle(edges)))


class _Prepared:
    """A BRDF on the fine grid: weighted tensor, spectra, nested knots (shared by fits)."""

    def __init__(self, brdf: Any, grid: tuple[int, int, int], warp_d: str,
                 phi_turn: str) -> None:
        nodes = grid[0] * grid[1] * grid[2] * PHI_TURNS[phi_turn]
        channels = int(getattr(brdf, "channels", 1))
        # the table, the weighted and the normalised tensors, and one unfolding's product
        check_bytes(8.0 * 4 * nodes * channels,
                    f"a Tucker fit on the grid {grid} with {channels} channels")
        tab = tabulate(brdf, grid, phi_turn=phi_turn, warp_d=warp_d)
        t = np.array(tab.table)
        n_h, n_d, m = t.shape[:3]
        p = D_WARPS[warp_d]
        self.s = (np.arange(n_h) / (n_h - 1), np.arange(n_d) / (n_d - 1), np.arange(m) / m)
        # measure 4 cos td sin td sin th: primitives -cos th and 2 sin^2 td (module notes)
        wh = _cell_weights(self.s[0], lambda u: _HALF_PI * u * u, lambda a: -np.cos(a))
        wd = _cell_weights(self.s[1], lambda u: _HALF_PI * (1.0 - (1.0 - u) ** p),
                           lambda a: 2.0 * np.sin(a) ** 2)
        wp = np.full(m, 2.0 * math.pi * PHI_TURNS[phi_turn] / m)
        self.w = (wh, wd, wp)
        sw = np.sqrt(wh)[:, None, None] * np.sqrt(wd)[None, :, None] * np.sqrt(wp)
        x = t * sw[..., None]
        norms = np.sqrt(np.sum(x * x, axis=(0, 1, 2)))
        if np.any(norms == 0):
            raise ValueError(f"the BRDF is 0 everywhere on the grid in channel "
                             f"{int(np.flatnonzero(norms == 0)[0])}: nothing to decompose")
        self.norms = norms
        self.t = t / norms  # each channel of unit weighted norm
        self.x = x / norms
        self.channels = t.shape[3]
        self.evaluations = tab.info["evaluations"]
        self.spectra, self.knots, self.residuals = [], [], []
        for k in range(3):
            g = _unfold(self.x, k)
            ev, u = linalg.eigh(g @ g.T)
            ev, u = np.maximum(ev[::-1], 0.0), u[:, ::-1]
            self.spectra.append(ev)  # squared singular values
            top = min(_GUIDES, u.shape[1])
            guide = u[:, :top] * np.sqrt(ev[:top]) / np.sqrt(self.w[k])[:, None]
            order, res = _greedy_knots(self.s[k], guide, self.w[k], k == 2,
                                       min(max(_KNOTS), self.s[k].size))
            self.knots.append(order)
            self.residuals.append(res)
        g = _unfold(self.x, 3)
        self.spectra.append(np.maximum(np.linalg.eigvalsh(g @ g.T)[::-1], 0.0))

    def knot_set(self, k: int, m: int) -> NDArray[np.float64]:
        """Return the first m knots of angle k, sorted."""
        return np.sort(self.s[k][self.knots[k][:m]])

    def tail(self, k: int, r: int) -> float:
        """Squared singular values of unfolding k beyond rank r."""
        return float(self.spectra[k][r:].sum())

    def knot_errors(self, k: int, ranks: tuple[int, ...]) -> NDArray[np.float64]:
        """Return the weighted squared residual of the first r guides with m knots.

        Shape (len(ranks), len(_KNOTS)); inf where m is not allowed (below the rank or the
        first count, beyond the grid).
        """
        res = np.cumsum(self.residuals[k], axis=1)  # over the guides
        out = np.full((len(ranks), len(_KNOTS)), np.inf)
        for j, m in enumerate(_KNOTS):
            if m < res.shape[0]:
                for i, r in enumerate(ranks):
                    if r <= m and r <= res.shape[1]:
                        out[i, j] = res[m, r - 1]
        return out


def _greedy_knots(s: NDArray, guide: NDArray, w: NDArray, periodic: bool,
                  most: int) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Nested knots by greedy refinement; returns their order and the residuals per count.

    ``residual[m, a]``: weighted squared residual of guide a fitted with the first m knots
    (rows below the first count are inf).
    """
    n = s.size
    chosen = list(np.linspace(0, n, 4, endpoint=False).astype(int)) if periodic else [0, n - 1]
    residual = np.full((most + 1, guide.shape[1]), np.inf)
    while True:
        idx = np.sort(np.array(chosen))
        p = _hats(s, s[idx], periodic)
        pw = p * w[:, None]
        # normal equations of the hats (a tridiagonal, or cyclic, Gram matrix: well
        # conditioned for positive weights); 50x faster than an SVD-based lstsq
        coef = linalg.solve(p.T @ pw, pw.T @ guide, assume_a="pos")
        r = (p @ coef - guide) ** 2 * w[:, None]
        residual[len(chosen)] = r.sum(axis=0)
        if len(chosen) >= most:
            break
        per = np.concatenate([[0.0], np.cumsum(r.sum(axis=1))])
        ends = np.append(idx, idx[0] + n) if periodic else idx
        a, b = ends[:-1], ends[1:]
        # error of each interval (both ends), wrapping over the turn
        inside = per[np.minimum(b, n - 1) + 1] - per[a] + np.where(b >= n, per[b - n + 1], 0.0)
        inside = np.where(b - a >= 2, inside, -1.0)
        best = int(np.argmax(inside))
        if inside[best] < 0:
            break
        chosen.append(int((a[best] + b[best]) // 2) % n)
    return np.array(chosen), residual


def _fit_structure(prep: _Prepared, knots: tuple[int, int, int], ranks: tuple[int, int, int],
                   color_rank: int, sweeps: int = 2) -> tuple[dict, NDArray]:
    """Fit one structure; return the arrays of a TuckerBRDF and the errors on the grid.

    The errors are relative, per channel, on the fine grid (projection and truncation).
    """
    ks = [_f16(prep.knot_set(k, knots[k])) for k in range(3)]
    projs, chols = [], []
    for k in range(3):
        p = _hats(prep.s[k], ks[k], k == 2)
        gram = p.T @ (p * prep.w[k][:, None])
        chol = np.linalg.cholesky(gram)
        projs.append(linalg.cho_solve((chol, True), p.T * prep.w[k][None, :]))
        chols.append(chol)
    cp = prep.t
    for k in range(3):
        cp = _mode(cp, chols[k].T @ projs[k], k)  # coefficients in orthonormal coordinates
    ranks4 = (*ranks, color_rank)
    bs = [_leading(cp, k, ranks4[k]) for k in range(4)]
    for _ in range(sweeps):
        for k in range(4):
            y = cp
            for j in range(4):
                if j != k:
                    y = _mode(y, bs[j].T, j)
            bs[k] = _leading(y, k, ranks4[k])
    core = cp
    for k in range(4):
        core = _mode(core, bs[k].T, k)
    approx = core
    for k in range(4):
        approx = _mode(approx, bs[k], k)
    # Pythagoras: the projection's error plus the truncation's (channels of unit norm)
    kept = np.sum(cp * cp, axis=(0, 1, 2))
    err2 = np.maximum(1.0 - kept, 0.0) + np.sum((cp - approx) ** 2, axis=(0, 1, 2))
    factors = [linalg.solve_triangular(chols[k].T, bs[k], lower=False) for k in range(3)]
    color = bs[3] * prep.norms[:, None]
    # each factor column of largest magnitude 1, the scale in the core: no stored number
    # outruns float16 unless the core itself does
    for k, f in enumerate((*factors, color)):
        top = np.max(np.abs(f), axis=0)
        top = np.where(top > 0, top, 1.0)
        f /= top
        core = _mode(core, np.diag(top), k)
    arrays = {"knots": ks, "factors": factors, "core": core, "color": color}
    return arrays, np.sqrt(err2)


def _leading(x: NDArray, k: int, r: int) -> NDArray[np.float64]:
    """Return the r leading left singular vectors of x unfolded along k (by its Gram)."""
    g = _unfold(x, k)
    u = linalg.eigh(g @ g.T)[1]
    return np.ascontiguousarray(u[:, ::-1][:, :r])


def _f16(k: NDArray) -> NDArray[np.float64]:
    """Knots rounded to float16 values (exact in every storage type), kept increasing."""
    out = k.astype(np.float16).astype(np.float64)
    if not np.all(np.diff(out) > 0):
        raise ValueError("knots too close to be held in float16; use a coarser grid")
    return out


def _structures(prep: _Prepared, budget: int) -> list[tuple[float, tuple, tuple, int]]:
    """Return the structures within ``budget`` reals, best first by the error bound."""
    c = prep.channels
    sizes = [s.size for s in prep.s]
    knots = np.array(_KNOTS)
    errs = [prep.knot_errors(k, _RANKS[k]) for k in range(3)]
    tails = [[prep.tail(k, r) for r in _RANKS[k]] for k in range(3)]
    out = []
    for rc in range(1, min(c, _COLOR_RANKS) + 1):
        tail_c = prep.tail(3, rc)
        for i1, r1 in enumerate(_RANKS[0]):
            for i2, r2 in enumerate(_RANKS[1]):
                for i3, r3 in enumerate(_RANKS[2]):
                    ranks = (r1, r2, r3)
                    room = budget - r1 * r2 * r3 * rc - c * rc
                    if any(r > n for r, n in zip(ranks, sizes, strict=True)) or \
                            sum(max(r, _MIN_KNOTS[k]) * (r + 1)
                                for k, r in enumerate(ranks)) > room:
                        continue
                    rows = (errs[0][i1], errs[1][i2], errs[2][i3])
                    cost = [knots * (r + 1) for r in ranks]
                    best = _knapsack(rows, cost, room)
                    if best is None:
                        continue
                    err, ms = best
                    bound = err + tails[0][i1] + tails[1][i2] + tails[2][i3] + tail_c
                    out.append((bound, ms, ranks, rc))
    out.sort(key=lambda x: x[0])
    return out


def _knapsack(errs: tuple[NDArray, ...], costs: list[NDArray],
              room: int) -> tuple[float, tuple[int, int, int]] | None:
    """Return the knot counts (one per angle) of least summed error within ``room``."""
    cost = costs[0][:, None, None] + costs[1][None, :, None] + costs[2][None, None, :]
    err = errs[0][:, None, None] + errs[1][None, :, None] + errs[2][None, None, :]
    err = np.where(cost <= room, err, np.inf)
    i = int(np.argmin(err))
    if not np.isfinite(err.flat[i]):
        return None
    j = np.unravel_index(i, err.shape)
    return float(err.flat[i]), tuple(int(_KNOTS[x]) for x in j)  # type: ignore[return-value]


def fit_tucker(brdf: Any, *, budget: int | None = 2048,
               ranks: tuple[int, int, int] | None = None,
               knots: tuple[int, int, int] | None = None, color_rank: int | None = None,
               grid: tuple[int, int, int] = GRID, warp_d: str = "grazing",
               phi_turn: str | None = None) -> TuckerBRDF:
    """Fit a :class:`TuckerBRDF` to a BRDF in the L2 norm of q over H x H (module notes).

    Parameters
    ----------
    brdf : BRDF
        Any object with ``eval(wi, wo)`` returning finite values >= 0 (isotropic: it is read
        at phi_h = 0).
    budget : int, optional
        Stored reals at most (bytes = reals x the storage type's size); the ranks, colour
        rank and knot counts are chosen within it. Ignored when ``ranks`` and ``knots``
        are given.
    ranks, knots : (int, int, int), optional
        A structure of your own: ranks and knot counts of (theta_h, theta_d, phi_d).
    color_rank : int, optional
        With ``ranks``: the colour rank (default: the channels).
    grid : (int, int, int)
        The fine grid (n_h, n_d, n_phi over the whole turn) the BRDF is tabulated on.
    warp_d : {"grazing", "linear"}
    phi_turn : {None, "full", "half"}
        None: "half" if ``brdf.reciprocal`` is True, else "full".

    Returns
    -------
    TuckerBRDF
        ``info``: ``"ranks"``, ``"knots"``, ``"color_rank"``, ``"grid"``, ``"fit_l2"``
        (largest relative error over the channels on the fine grid, projection and
        truncation), ``"fit_l2_channels"``, ``"bound"`` (the search's error bound),
        ``"structures"`` (how many fitted exactly) and ``"evaluations"`` (0 when the fine
        grid was kept from an earlier fit, :func:`project.factored.reuse_samples`).

    Raises
    ------
    ValueError
        No structure fits within ``budget``, bad ranks or knots, or a BRDF that is not
        finite and >= 0, or 0 in a channel.

    Examples
    --------
    >>> from project.models import CookTorrance
    >>> ct = CookTorrance([0.3, 0.2, 0.1], 0.3, "ggx", ior=1.5)
    >>> t = fit_tucker(ct, budget=600, grid=(64, 32, 32))
    >>> t.nparams <= 600, t.reciprocal, bool(t.info["fit_l2"] < 0.05)
    (True, True, True)
    """
    if not callable(getattr(brdf, "eval", None)):
        raise TypeError(f"brdf must be a BRDF (an object with eval(wi, wo)), got "
                        f"{type(brdf).__name__}")
    grid = _grid(grid)
    warp_d = choice(warp_d, "warp_d", tuple(D_WARPS))
    if phi_turn is None:
        phi_turn = "half" if getattr(brdf, "reciprocal", False) is True else "full"
    phi_turn = choice(phi_turn, "phi_turn", tuple(PHI_TURNS))
    if (ranks is None) != (knots is None):
        raise ValueError("give ranks and knots together (or neither, and a budget)")
    # many small and medium products: on a shared machine (and under select's worker
    # processes) a second BLAS thread per process costs far more than it gains (the SVDs of
    # a 16,384-real fit of a glossy film: 5.2 s on two threads, 0.24 s on one, while another
    # process held a core)
    with threadpool_limits(limits=1, user_api="blas"):
        return _fit(brdf, budget, ranks, knots, color_rank, grid, warp_d, phi_turn)


def _fit(brdf: Any, budget: int | None, ranks: Any, knots: Any, color_rank: int | None,
         grid: tuple[int, int, int], warp_d: str, phi_turn: str) -> TuckerBRDF:
    made: list[_Prepared] = []

    def prepare() -> _Prepared:
        made.append(_Prepared(brdf, grid, warp_d, phi_turn))
        return made[0]

    prep = kept_for(brdf, ("tucker grid", grid, warp_d, phi_turn), prepare)
    sizes = [s.size for s in prep.s]
    if ranks is not None:
        ranks = tuple(nonneg_int(r, "ranks") for r in ranks)  # type: ignore[assignment]
        knots = tuple(nonneg_int(m, "knots") for m in knots)  # type: ignore[union-attr]
        rc = prep.channels if color_rank is None else nonneg_int(color_rank, "color_rank")
        if len(ranks) != 3 or len(knots) != 3 or min(ranks) < 1 or not 1 <= rc <= \
                prep.channels:
            raise ValueError(f"ranks and knots must be three integers >= 1 and color_rank in "
                             f"1..{prep.channels}, got {ranks}, {knots}, {rc}")
        for k in range(3):
            if not max(ranks[k], _MIN_KNOTS[k]) <= knots[k] <= sizes[k]:
                raise ValueError(f"the {_NAMES[k]} knots must be at least the rank "
                                 f"{ranks[k]} (and {_MIN_KNOTS[k]}) and at most the grid's "
                                 f"{sizes[k]} nodes, got {knots[k]}")
        tries = [(math.nan, knots, ranks, rc)]
    else:
        if budget is None:
            raise ValueError("give a budget of stored reals, or ranks and knots")
        budget = nonneg_int(budget, "budget")
        found = _structures(prep, budget)
        if not found:
            least = tucker_reals(_MIN_KNOTS, (1, 1, 1), 1, prep.channels)
            raise ValueError(f"no Tucker structure fits in {budget} reals (the smallest, "
                             f"ranks (1, 1, 1), takes {least})")
        tries = found[:_REFITS]
    best = None
    for bound, m, r, rc in tries:
        arrays, err = _fit_structure(prep, m, r, rc)
        if best is None or err.max() < best[1].max():
            best = (arrays, err, bound, m, r, rc)
    arrays, err, bound, m, r, rc = best
    evaluations = prep.evaluations if made else 0
    info = {"ranks": r, "knots": m, "color_rank": rc, "grid": grid, "budget": budget,
            "fit_l2": float(err.max()), "fit_l2_channels": err.tolist(),
            "bound": float(np.sqrt(bound / prep.channels)) if bound == bound else None,
            "structures": len(tries), "evaluations": evaluations}
    return TuckerBRDF(arrays["knots"], arrays["factors"], arrays["core"], arrays["color"],
                      warp_d=warp_d, phi_turn=phi_turn, info=info)


def _grid(grid: object) -> tuple[int, int, int]:
    try:
        g = tuple(int(x) for x in grid)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise TypeError(f"grid must be three integers (n_h, n_d, n_phi), got {grid!r}") from None
    if len(g) != 3 or g[0] < 4 or g[1] < 4 or g[2] < 8 or g[2] % 2:
        raise ValueError(f"grid must be (n_h >= 4, n_d >= 4, n_phi >= 8 and even), got {g}")
    return g  # type: ignore[return-value]
