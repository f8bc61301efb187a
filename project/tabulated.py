"""A BRDF tabulated on a grid of Rusinkiewicz angles, at any resolution: :class:`TabulatedBRDF`.

:func:`tabulate` samples any BRDF on a grid in (theta_h, theta_d, phi_d) and returns a
:class:`TabulatedBRDF`, which reads it back by trilinear interpolation. It is the form that
meets any tolerance the data resolve: its error falls as the grid is refined (second order in
the cell size for a smooth BRDF), down to the floor of the data themselves, and it holds
non-reciprocal data (phi_d over the whole turn). It is stored as the model family
``"tabulated"`` (``project.FittedModel("tabulated", params)``, :mod:`compress.store`).

Notes
-----
**What is stored: q, not f.** The table holds q = f cos(theta_i) cos(theta_o) by default
(``quantity="q"``), and the model returns f = q / (cos theta_i cos theta_o). Errors are
measured in q (:func:`project.sampling.value_errors`), and q stays bounded where f does not:
measured RGL data grow like 1/cos towards the horizon (the cosine-weighted values are what
the instrument sees), and so does any f whose q does not vanish there, which trilinear
interpolation of f would follow badly and float16 could overflow. ``quantity="f"`` stores f.
At a pair with cos theta_i cos theta_o = 0 (a direction on the horizon) q of every finite
BRDF is 0 and the model returns 0; above it the division uses max(cos cos, 1e-300) so that
every pair above the horizon evaluates to a finite value.

**Grid** (the same node placement as :class:`project.factored.FactoredLobe`). theta_h nodes
(pi/2) (i/(n_h - 1))^2, i = 0..n_h-1: uniform in sqrt(theta_h), dense near the specular
direction (the MERL warp, Matusik et al. 2003, with the last node at pi/2 instead of
constant extrapolation beyond (89/90)^2 pi/2). theta_d nodes (pi/2) j/(n_d - 1)
(``warp_d="linear"``) or (pi/2) (1 - (1 - j/(n_d - 1))^2) (``"grazing"``: dense towards
theta_d = pi/2, where Fresnel and the horizon change fastest). phi_d nodes k P / m,
k = 0..m-1, periodic with period P: ``phi_turn="full"``, P = 2 pi and m = n_phi, holds
non-reciprocal data (swapping w_i and w_o adds pi to phi_d, see
:class:`~project.factored.FactoredLobe`); ``"half"``, P = pi and m = n_phi / 2, folds phi_d
by reciprocity (f(w_i, w_o) == f(w_o, w_i) bit for bit): the same node spacing at half the
size. ``bins = (n_h, n_d, n_phi)`` always counts the phi_d nodes of the whole turn, so both
turns have the same spacing. The default turn is "half" for a BRDF whose ``reciprocal`` is
True and "full" otherwise. Nodes are evaluated at (theta_h, phi_h = 0, theta_d, phi_d)
(:func:`basis.from_rusinkiewicz`); the evaluation measures phi_d from the x axis when h = z,
as :class:`~project.measured.MERLBRDF` does.

**Interpolation.** Trilinear in the coordinates in which the nodes are uniform
(sqrt(2 theta_h / pi), the theta_d warp, phi_d), periodic in phi_d: continuous, reproduces
the nodes, and exact for a function that is trilinear in those coordinates. One numba
kernel, parallel over pairs (about 0.05 s per million pairs on 2 cores).

**Nodes below the horizon.** A node whose w_i or w_o lies at or below the horizon
(z <= 1e-9) has no value; it is filled with the value of the nearest valid node (Euclidean
distance in index space, as :class:`~project.measured.MERLBRDF` fills invalid cells), so
pairs just above the horizon read values continued from the valid side.

**Node values or cell averages** (``sample``). ``"nodes"`` (the default) evaluates the BRDF
at the nodes. ``"average"`` stores at each node the mean of the quantity over its dual cell
(half a cell either side, in the uniform coordinates) by a 2 x 2 x 2 Gauss-Legendre rule,
eight times the evaluations. For a smooth function the average raises each node by
h^2 u''/24, the same sign as the interpolation error itself (h^2 u''/12 on average), so it
helps only where the grid does not resolve a peak. Measured (l2 of q, 65536 peak-resolving
pairs, linear theta_d), nodes / averages: GGX alpha 0.05 at (16, 16, 16) 0.095 / 0.122, at
(64, 64, 64) 0.0075 / 0.0083; GGX alpha 0.2 at (32, 32, 32) 0.0100 / 0.0102; RGL
paper_white at (8, 8, 8) 0.122 / 0.096, at (32, 32, 32) 0.0135 / 0.0136. Only the coarsest
table of the matte paper gains, hence "nodes".

**Convergence** (the interpolation floor of each size). l2 of q (worst channel) on 65536
peak-resolving pairs (seed 7), independent of the grid; standard errors 0.0001-0.0017.
Table rounded to float16 (float32 agrees to 1e-4 everywhere: the storage type does not
matter at these sizes); bytes = 2 n_h n_d m C, m = n_phi (full turn, the RGL files) or
n_phi / 2 (the reciprocal GGX), C = 3 (RGL) or 1 (GGX, one channel). theta_d warp
"grazing" (the default) / "linear":

=============  ==========  ==============  ==============  ==============  ==============
bins           RGL bytes   paper_white     colodur_napoli  vch_golden_y.   GGX a=0.05
=============  ==========  ==============  ==============  ==============  ==============
(12, 8, 4)     2304        0.139 / 0.101   0.174 / 0.173   0.151 / 0.210   0.139 / 0.143
(16, 12, 4)    4608        0.112 / 0.096   0.164 / 0.160   0.116 / 0.199   0.092 / 0.096
(8, 8, 8)      3072        0.155 / 0.122   0.173 / 0.145   0.216 / 0.239   0.469 / 0.472
(16, 12, 8)    9216        0.073 / 0.056   0.111 / 0.108   0.095 / 0.175   0.091 / 0.096
(24, 16, 8)    18432       0.059 / 0.057   0.103 / 0.103   0.071 / 0.154   0.039 / 0.047
(16, 16, 16)   24576       0.037 / 0.039   0.059 / 0.069   0.070 / 0.149   0.091 / 0.095
(24, 16, 16)   36864       0.034 / 0.030   0.056 / 0.062   0.054 / 0.145   0.039 / 0.047
(32, 24, 16)   73728       0.029 / 0.030   0.052 / 0.055   0.037 / 0.078   0.022 / 0.028
(24, 24, 32)   110592      0.020 / 0.017   0.032 / 0.037   0.035 / 0.079   0.039 / 0.043
(32, 24, 32)   147456      0.017 / 0.016   0.030 / 0.033   0.030 / 0.075   0.022 / 0.028
(32, 32, 64)   393216      0.011 / 0.010   0.019 / 0.022   0.022 / 0.048   0.022 / 0.025
(48, 48, 64)   884736      0.007 / 0.006   0.013 / 0.015   0.012 / 0.025   0.010 / 0.012
(64, 64, 128)  3145728     - / 0.0035      0.0075 / 0.0087 0.0078 / 0.017  0.0053 / 0.0075
(90, 90, 360)  17496000    - / 0.0020      0.0045 / 0.0050 0.0047 / 0.011  0.0027 / 0.0043
=============  ==========  ==============  ==============  ==============  ==============

First size (of those above, grazing warp) at 10 %: paper_white (16, 12, 8) 9.2 kB (linear
(16, 12, 4), 4.6 kB); colodur (24, 16, 16) 36.9 kB; vch_golden_yellow (16, 12, 8) 9.2 kB;
GGX (16, 12, 4) 768 B. At 5 %: paper (16, 16, 16) 24.6 kB; colodur (24, 24, 32) 111 kB;
vch (32, 24, 16) 73.7 kB; GGX (24, 16, 8) 1.5 kB. Doubling all bins divides the error by
3-4 (second order) once the grid resolves the lobe; n_phi matters little on these
isotropic materials beyond 16 over the whole turn. A plain table does not reach 10 % on
the glossy RGL files at 4 kB.

References
----------
- W. Matusik, H. Pfister, M. Brand and L. McMillan, "A data-driven reflectance model", ACM
  Transactions on Graphics 22(3), 2003.
- S. Rusinkiewicz, "A new change of variables for efficient BRDF representation",
  Eurographics Rendering Workshop 1998.
- J. Dupuy and W. Jakob, "An adaptive parameterization for efficient material acquisition
  and rendering", ACM Transactions on Graphics 37(6), 2018.
"""

from __future__ import annotations

import math
import operator
from typing import Any

import numpy as np
from numpy.polynomial.legendre import leggauss
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from basis.directions import from_rusinkiewicz
from basis.jit import loopjit, run_parallel, writable
from basis.validation import check_bytes, choice

from ._halfdiff import cell, cell_trilinear, half_difference, periodic_cell
from .brdf import BRDF

__all__ = ["D_WARPS", "PHI_TURNS", "QUANTITIES", "SAMPLES", "TabulatedBRDF", "option_name",
           "tabulate", "table_nbytes"]

#: theta_d = (pi/2) (1 - (1 - s)^p), s uniform on the theta_d nodes: p of each warp.
D_WARPS = {"linear": 1.0, "grazing": 2.0}
#: The exponent p of the theta_h warp theta_h = (pi/2) s^p (the MERL "sqrt" warp).
H_WARP = 2.0
#: The part of the turn the phi_d nodes span, as a fraction of 2 pi.
PHI_TURNS = {"half": 0.5, "full": 1.0}
#: The stored quantity and its power of cos(theta_i) cos(theta_o) (the "cosines" param).
QUANTITIES = {"q": 1.0, "f": 0.0}
#: How :func:`tabulate` fills a node: the value there, or the mean over its dual cell.
SAMPLES = ("nodes", "average")
_HALF_PI = 0.5 * math.pi
#: A node direction with z at or below this is below the horizon (no value).
_HORIZON = 1e-9
#: Gauss-Legendre points per axis and dual cell for ``sample="average"``.
_GAUSS = 2
#: Pairs per call of ``brdf.eval`` when tabulating (bounds the memory).
_CHUNK = 1 << 18


def _bins(bins: object) -> tuple[int, int, int]:
    try:
        b = tuple(operator.index(x) for x in bins)  # type: ignore[union-attr]
    except TypeError:
        raise TypeError(f"bins must be three integers (n_h, n_d, n_phi), got {bins!r}") from None
    if len(b) != 3 or isinstance(bins, (str, bytes)):
        raise TypeError(f"bins must be three integers (n_h, n_d, n_phi), got {bins!r}")
    if b[0] < 2 or b[1] < 2 or b[2] < 2 or b[2] % 2:
        raise ValueError(f"bins must be (n_h >= 2, n_d >= 2, n_phi >= 2 and even), got {b}")
    return b  # type: ignore[return-value]


def table_nbytes(bins: object, channels: int = 3, *, phi_turn: str = "full",
                 itemsize: int = 2) -> int:
    """Bytes of the table of a :class:`TabulatedBRDF`: itemsize n_h n_d m channels.

    m = n_phi for ``phi_turn="full"``, n_phi / 2 for "half"; ``itemsize`` 2 for float16
    (:func:`compress.save` with ``dtype="float16"``), 4, 8.

    Examples
    --------
    >>> table_nbytes((16, 16, 32)), table_nbytes((16, 16, 32), phi_turn="half")
    (49152, 24576)
    """
    n_h, n_d, n_phi = _bins(bins)
    m = n_phi if choice(phi_turn, "phi_turn", tuple(PHI_TURNS)) == "full" else n_phi // 2
    return int(itemsize) * n_h * n_d * m * int(channels)


def option_name(params: dict[str, ArrayLike], key: str, table: dict[str, float]) -> str:
    """Return the name in ``table`` of the 0-d value ``params[key]`` (a stored grid option)."""
    v = np.asarray(params[key], dtype=np.float64)
    found = [k for k, x in table.items() if v.ndim == 0 and float(v) == x]
    if not found:
        raise ValueError(f"params[{key!r}] must be one of {table} (a 0-d value), got {v}")
    return found[0]


def _h_angle(s: NDArray) -> NDArray:
    return _HALF_PI * s ** H_WARP


def _d_angle(s: NDArray, p: float) -> NDArray:
    return _HALF_PI * (1.0 - (1.0 - s) ** p)


class TabulatedBRDF(BRDF):
    """An isotropic BRDF tabulated on a (theta_h, theta_d, phi_d) grid, read trilinearly.

    Parameters
    ----------
    table : (n_h, n_d, m) or (n_h, n_d, m, channels) array_like of float
        Values (q = f cos theta_i cos theta_o, or f; see ``quantity``) at the nodes of the
        module notes, finite and >= 0; m = n_phi (``phi_turn="full"``) or n_phi / 2
        ("half"); n_h, n_d, m >= 2. Copied.
    warp_d : {"linear", "grazing"}
        Spacing of the theta_d nodes.
    phi_turn : {"full", "half"}
        The period of phi_d: 2 pi (not reciprocal) or pi (reciprocal by construction).
    quantity : {"q", "f"}
        What ``table`` holds.
    info : dict, optional
        Kept as ``info`` (what :func:`tabulate` did).

    Attributes
    ----------
    bins : (int, int, int)
        (n_h, n_d, n_phi), n_phi the number of phi_d nodes over the whole turn.
    table : (n_h, n_d, m, channels) ndarray, read-only
    channels, nparams, nbytes, params, reciprocal, info
        ``nbytes`` is 8 ``nparams`` (float64); :func:`table_nbytes` gives other widths.

    Examples
    --------
    >>> tab = TabulatedBRDF(np.full((3, 3, 4), 0.25), phi_turn="half")
    >>> tab.bins, tab.warp_d, tab.reciprocal, tab.nbytes
    ((3, 3, 8), 'grazing', True, 288)
    >>> w = np.array([0.6, 0.0, 0.8])
    >>> round(float(tab.eval(w, w)), 12)  # f = q / cos^2
    0.390625
    """

    #: The name of this family in :func:`project.fit_model` and :mod:`compress.store`.
    family = "tabulated"
    isotropic = True

    def __init__(self, table: ArrayLike, *, warp_d: str = "grazing", phi_turn: str = "full",
                 quantity: str = "q", info: dict[str, Any] | None = None) -> None:
        self.warp_d = choice(warp_d, "warp_d", tuple(D_WARPS))
        self.phi_turn = choice(phi_turn, "phi_turn", tuple(PHI_TURNS))
        self.quantity = choice(quantity, "quantity", tuple(QUANTITIES))
        try:
            t = np.array(table, dtype=np.float64)
        except (TypeError, ValueError):
            raise TypeError(f"table must be an array of floats, got {type(table).__name__}"
                            ) from None
        if t.ndim == 3:
            t = t[..., None]
        if t.ndim != 4 or min(t.shape[:3]) < 2 or t.shape[3] < 1:
            raise ValueError(f"table must have shape (n_h >= 2, n_d >= 2, m >= 2) or "
                             f"(n_h, n_d, m, channels), got {t.shape}")
        if not np.all(np.isfinite(t)) or np.any(t < 0):
            raise ValueError(f"table must hold finite values >= 0, got min {np.min(t):.6g}, "
                             f"max {np.max(t):.6g}")
        t = np.ascontiguousarray(t)
        t.flags.writeable = False
        self._t = t
        self.reciprocal = self.phi_turn == "half"
        self.channels = int(t.shape[3])
        self._scalar = self.channels == 1
        self.info = {} if info is None else dict(info)

    @property
    def bins(self) -> tuple[int, int, int]:
        """(n_h, n_d, n_phi): nodes in theta_h, theta_d and over the whole turn of phi_d."""
        m = int(self._t.shape[2])
        return int(self._t.shape[0]), int(self._t.shape[1]), m * (2 if self.reciprocal else 1)

    @property
    def table(self) -> NDArray[np.float64]:
        """(n_h, n_d, m, channels) read-only node values."""
        return self._t.view()

    @property
    def nparams(self) -> int:
        """Number of stored reals: the table (the grid options are not counted)."""
        return int(self._t.size)

    @property
    def nbytes(self) -> int:
        """Storage in bytes, 8 (float64) per stored real."""
        return 8 * self.nparams

    @property
    def params(self) -> dict[str, NDArray[np.float64]]:
        """The stored arrays, as ``project.FittedModel("tabulated", params)`` takes them.

        ``table`` (n_h, n_d, m, channels), and as 0-d arrays ``warp_d`` (the exponent of
        :data:`D_WARPS`), ``phi_turn`` (the fraction of :data:`PHI_TURNS`) and ``cosines``
        (the power of cos theta_i cos theta_o in the stored quantity, :data:`QUANTITIES`:
        1 for q, 0 for f); all read-only and exact in float16.
        """
        out = {"table": self._t, "warp_d": np.array(D_WARPS[self.warp_d]),
               "phi_turn": np.array(PHI_TURNS[self.phi_turn]),
               "cosines": np.array(QUANTITIES[self.quantity])}
        for v in out.values():
            v.flags.writeable = False
        return out

    @classmethod
    def from_params(cls, params: dict[str, ArrayLike], *,
                    info: dict[str, Any] | None = None) -> TabulatedBRDF:
        """Rebuild from :attr:`params` (as :func:`compress.load` returns them)."""
        keys = {"table", "warp_d", "phi_turn", "cosines"}
        if set(params) != keys:
            raise ValueError(f"params of family 'tabulated' must be exactly {sorted(keys)}, "
                             f"got {sorted(params)}")
        names = {arg: option_name(params, key, table)
                 for key, arg, table in (("warp_d", "warp_d", D_WARPS),
                                         ("phi_turn", "phi_turn", PHI_TURNS),
                                         ("cosines", "quantity", QUANTITIES))}
        return cls(params["table"], info=info, **names)

    def _eval(self, wi: NDArray[np.float64], wo: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.empty((wi.shape[0], self.channels))
        # ~0.3 us a pair: parts of 256 pairs outweigh the hand-off to a thread
        run_parallel(_tabulated_kernel, wi.shape[0], writable(wi), writable(wo), self._t,
                     D_WARPS[self.warp_d], 2.0 * math.pi * PHI_TURNS[self.phi_turn],
                     self.quantity == "q", out, grain=256)
        return out

    def __repr__(self) -> str:
        return (f"TabulatedBRDF(bins={self.bins}, warp_d={self.warp_d!r}, "
                f"phi_turn={self.phi_turn!r}, quantity={self.quantity!r}, "
                f"channels={self.channels}, nbytes={self.nbytes})")


@loopjit
def _tabulated_kernel(first, stop, wi, wo, t, pd, period, divide,
                      out):  # pragma: no cover - compiled
    # Pairs first .. stop - 1 (run_parallel). wi, wo: (n, 3) directions with z >= 0;
    # t: (n_h, n_d, m, c) node values; out: (n, c). Angles from h = wi + wo and wi - wo (as
    # MERLBRDF), so the exchange of wi and wo leaves theta_h, theta_d unchanged bit for bit
    # and negates wi - wo exactly (phi_d + pi).
    nh, nd, m, nc = t.shape[0], t.shape[1], t.shape[2], t.shape[3]
    half = period < 4.0
    # an unsigned index: no negative-index test on a[p] (basis.jit.loopjit)
    for p in range(np.uint64(first), np.uint64(stop)):
        theta_h, theta_d, phi_d, iz, oz = half_difference(wi, wo, p, half)
        if phi_d < 0.0:
            phi_d += 2.0 * math.pi
        u = math.sqrt(min(theta_h / (0.5 * math.pi), 1.0)) * (nh - 1)
        x = min(theta_d / (0.5 * math.pi), 1.0)
        v = (1.0 - (1.0 - x) ** (1.0 / pd)) * (nd - 1)
        w = phi_d / period * m
        i0, tu = cell(u, nh)
        j0, tv = cell(v, nd)
        k0, k1, tw = periodic_cell(w, m)
        scale = 1.0
        if divide:
            cc = max(iz, 0.0) * max(oz, 0.0)
            scale = 0.0 if cc == 0.0 else 1.0 / max(cc, 1e-300)
        for c in range(nc):
            out[p, c] = cell_trilinear(t, i0, j0, k0, k1, tu, tv, tw, c) * scale


def tabulate(brdf: object, bins: object = (32, 32, 64), *, quantity: str = "q",
             phi_turn: str | None = None, warp_d: str = "grazing",
             sample: str = "nodes") -> TabulatedBRDF:
    """Sample a BRDF on a (theta_h, theta_d, phi_d) grid (module notes).

    Parameters
    ----------
    brdf : BRDF
        Any object with ``eval(wi, wo)`` returning finite values >= 0, (...) or
        (..., channels); isotropic (anisotropic BRDFs are read at phi_h = 0).
    bins : (int, int, int)
        (n_h, n_d, n_phi): nodes in theta_h and theta_d (>= 2 each) and over the whole turn
        of phi_d (>= 2, even). A half-turn table stores n_phi / 2 of them.
    quantity : {"q", "f"}
        Store q = f cos theta_i cos theta_o (the default: what errors measure, bounded at
        the horizon) or f.
    phi_turn : {None, "full", "half"}
        None: "half" if ``brdf.reciprocal`` is True, else "full".
    warp_d : {"linear", "grazing"}
        Spacing of the theta_d nodes.
    sample : {"nodes", "average"}
        Node values, or means over the dual cells by a 2 x 2 x 2 Gauss rule (8 times the
        evaluations; module notes).

    Returns
    -------
    TabulatedBRDF
        ``info`` holds ``"bins"``, ``"sample"``, ``"evaluations"`` and ``"filled"`` (the
        fraction of nodes below the horizon, filled from their neighbours).

    Raises
    ------
    TypeError
        ``brdf`` has no ``eval``; ``bins`` are not integers.
    ValueError
        Bad ``bins``, an unknown option, or the BRDF returns non-finite or negative values.

    Examples
    --------
    >>> from project.models import Lambert
    >>> tab = tabulate(Lambert(0.5), (4, 4, 8))
    >>> tab.bins, tab.phi_turn, tab.nparams
    ((4, 4, 8), 'half', 64)
    >>> z = np.array([0.0, 0.0, 1.0])  # a node: theta_h = theta_d = 0
    >>> bool(np.isclose(tab.eval(z, z), 0.5 / np.pi, rtol=1e-14, atol=0))
    True
    """
    if not callable(getattr(brdf, "eval", None)):
        raise TypeError(f"brdf must be a BRDF (an object with eval(wi, wo)), got "
                        f"{type(brdf).__name__}")
    n_h, n_d, n_phi = _bins(bins)
    choice(quantity, "quantity", tuple(QUANTITIES))
    choice(warp_d, "warp_d", tuple(D_WARPS))
    choice(sample, "sample", SAMPLES)
    if phi_turn is None:
        phi_turn = "half" if getattr(brdf, "reciprocal", False) is True else "full"
    choice(phi_turn, "phi_turn", tuple(PHI_TURNS))
    m = n_phi if phi_turn == "full" else n_phi // 2
    period = 2.0 * math.pi * PHI_TURNS[phi_turn]
    pd = D_WARPS[warp_d]
    s_h = np.arange(n_h) / (n_h - 1)
    s_d = np.arange(n_d) / (n_d - 1)
    s_p = np.arange(m) / m
    if sample == "nodes":
        offsets, weights = np.zeros(1), np.ones(1)
    else:
        x, wq = leggauss(_GAUSS)
        offsets, weights = 0.5 * x, 0.5 * wq  # over [-1/2, 1/2] cell widths
    points = offsets.size ** 3
    check_bytes(8.0 * n_h * n_d * m * (12 + 2 * 8), f"tabulating at bins {(n_h, n_d, n_phi)}")
    acc = None
    wsum = np.zeros((n_h, n_d, m))
    evaluations = 0
    for a, wa in zip(offsets, weights, strict=True):
        th = _h_angle(np.clip(s_h + a / (n_h - 1), 0.0, 1.0))
        for b, wb in zip(offsets, weights, strict=True):
            td = _d_angle(np.clip(s_d + b / (n_d - 1), 0.0, 1.0), pd)
            for c, wc in zip(offsets, weights, strict=True):
                pp = (s_p + c / m) * period
                vals, ok = _sample(brdf, th, td, pp, quantity)
                evaluations += vals.shape[0] * vals.shape[1] * vals.shape[2]
                if acc is None:
                    acc = np.zeros(vals.shape)
                w = wa * wb * wc * ok
                acc += w[..., None] * np.where(ok[..., None], vals, 0.0)
                wsum += w
    valid = wsum > 0
    table = acc / np.where(valid, wsum, 1.0)[..., None]
    if not valid.all():
        if not valid.any():
            raise ValueError("no node of the grid lies above the horizon")
        idx = ndimage.distance_transform_edt(~valid, return_distances=False,
                                             return_indices=True)
        table = table[tuple(idx)]
    info = {"bins": (n_h, n_d, n_phi), "sample": sample, "evaluations": evaluations,
            "points_per_node": points, "filled": float(1.0 - valid.mean())}
    return TabulatedBRDF(table, warp_d=warp_d, phi_turn=phi_turn, quantity=quantity,
                         info=info)


def _sample(brdf: object, th: NDArray, td: NDArray, pp: NDArray,
            quantity: str) -> tuple[NDArray, NDArray]:
    """(n_h, n_d, m, C) values of the quantity at the angles and the (n_h, n_d, m) mask."""
    shape = (th.size, td.size, pp.size)
    tt, dd, ph = np.meshgrid(th, td, pp, indexing="ij")
    wi, wo = from_rusinkiewicz(tt.ravel(), 0.0, dd.ravel(), ph.ravel())
    ok = (wi[:, 2] > _HORIZON) & (wo[:, 2] > _HORIZON)
    n = wi.shape[0]
    out = None
    idx = np.flatnonzero(ok)
    for start in range(0, idx.size, _CHUNK):
        sel = idx[start:start + _CHUNK]
        f = np.asarray(brdf.eval(wi[sel], wo[sel]), dtype=np.float64)
        f = f.reshape(sel.size, -1)
        if out is None:
            out = np.zeros((n, f.shape[1]))
        if not np.all(np.isfinite(f)) or np.any(f < 0):
            bad = int(np.argwhere(~(np.isfinite(f) & (f >= 0)))[0, 0])
            raise ValueError(f"brdf must return finite values >= 0, got {f[bad]} at "
                             f"wi={wi[sel][bad]}, wo={wo[sel][bad]}")
        if quantity == "q":
            f = f * (wi[sel, 2] * wo[sel, 2])[:, None]
        out[sel] = f
    if out is None:  # no pair above the horizon: ask for the channel count at the normal
        z = np.array([[0.0, 0.0, 1.0]])
        out = np.zeros((n, np.asarray(brdf.eval(z, z)).reshape(1, -1).shape[1]))
    return out.reshape(*shape, -1), ok.reshape(shape)
