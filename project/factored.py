"""Factored half/difference-angle BRDFs: kd/pi + sum_k A_k(theta_h) B_k(theta_d) C_k(phi_d).

Glossy measured materials keep most of their L2 norm in a narrow specular peak, which
spherical bases resolve only at high order. Tabulating the BRDF as a few products of 1-D
tables in the half/difference angles of Rusinkiewicz (1998) puts nodes where the peak is
and costs a few kilobytes. This is the family of factored non-parametric models:
Lawrence, Rusinkiewicz & Ramamoorthi (2004) factor measured BRDFs by non-negative matrix
factorisation for importance sampling; Romeiro, Vasilyev & Zickler (2008) tabulate
isotropic BRDFs as functions of (theta_h, theta_d) only; Bagher, Snyder & Nowrouzezahrai
(2016) fit tabulated 1-D factors of a microfacet model to MERL data.

- :class:`FactoredLobe` is the model, a :class:`~project.brdf.BRDF`:
  f = kd/pi + sum_k w_k A_k(theta_h) B_k(theta_d) C_k(phi_d), tables >= 0, piecewise linear
  (continuous); reciprocal bit for bit with C_k over half a turn (the default), or not
  reciprocal with C_k over the whole turn (``phi_turn="full"``, for measured data).
- :func:`fit_factored` fits one to any isotropic BRDF in the cosine-weighted L2 norm of
  q = f cos(theta_i) cos(theta_o) over H x H, by non-negative alternating least squares.
- :func:`rusinkiewicz_rule` is the quadrature rule of the fit: the Jacobian
  d w_i d w_o = 4 cos(theta_d) sin(theta_h) sin(theta_d) d theta_h d phi_h d theta_d d phi_d,
  integrated over the part of each phi_d circle that is above the horizon.

Measurements
------------
Relative L2 error of q on the fitting rule (the channels summed), bytes at 8 per stored
real, for MERL surrogates (the network fits of Sztrajman et al., CGF 2021, written in the
MERL layout by ``../shared/tools/merl_surrogate.py``; not the measured tables of Matusik
et al. 2003). blue-acrylic / alum-bronze / gold-metallic-paint:

1. No phi_d factor (C = 1), colour in B (``color="theta_d"``), ``warp="sqrt"``::

       bins       rank  bytes   error
       (90, 32)    1    1512    0.178 / 0.189 / 0.147
       (90, 32)    2    3000    0.121 / 0.120 / 0.046
       (90, 32)    3    4488    0.116 / 0.109 / 0.044
       (48, 16)    1     792    0.181 / 0.195 / 0.147
       (48, 16)    2    1560    0.125 / 0.130 / 0.046
       (48, 16)    3    2328    0.121 / 0.119 / 0.044

   The floor -- the error of the best function of (theta_h, theta_d) at all, ``floor`` in
   ``info`` -- is 0.114 / 0.106 / 0.042: these surrogates vary by about +-15 % with phi_d at
   the peak, even at theta_h = 0 where an isotropic BRDF cannot. Without a phi_d factor
   no rank or bin count reaches 10 % on the first two.

2. Which factor carries the colour, rank 2, bins (90, 32), no phi_d factor: per-channel
   B_k (``"theta_d"``) 0.121 / 0.120 / 0.046 at 3000 bytes; per-channel A_k
   (``"theta_h"``) 0.126 / 0.122 / 0.064 at 4856; both 0.121 / 0.116 / 0.045 at 5880;
   shared tables with an RGB weight per term (``"weights"``) 0.127 / 0.137 / 0.067 at
   2024. Colour belongs in theta_d (Fresnel) rather than theta_h. Per byte,
   ``"weights"`` wins once a phi_d factor lets the rank grow: at ~2.7 kB, ``"weights"``
   rank 5 beats ``"theta_d"`` rank 3 on all three (table 3).

3. With an 8-node phi_d factor, ``warp="cbrt"``, ``color="weights"``, bins (32, 24, 8),
   ``warp_d="linear"`` (the defaults are these with rank 4 and ``warp_d="grazing"``:
   0.070 / 0.053 / 0.029 at 2168 bytes, 102 / 105 / 532 sweeps, 2.4 / 1.6 / 15 s)::

       rank  bytes   error
        1     560    0.185 / 0.200 / 0.154
        2    1096    0.119 / 0.099 / 0.063
        3    1632    0.085 / 0.077 / 0.035
        4    2168    0.070 / 0.056 / 0.029
        5    2704    0.063 / 0.048 / 0.021
        6    3240    0.058 / 0.044 / 0.020

   Against the same bytes: ``"theta_d"`` rank 3 (2712 bytes) 0.076 / 0.052 / 0.026;
   16 phi_d nodes instead of 8 (rank 3) 0.084 / 0.077 / 0.035 (no gain); bins (48, 32, 8)
   rank 4 (2936) 0.066 / 0.052 / 0.028. The theta_h warp matters: ``"cbrt"`` with 32-40
   nodes does as well as ``"sqrt"`` with 48-64 (blue-acrylic, rank 4, bins (40, 24, 8):
   0.068 against 0.077). Too few theta_d nodes costs much (``"theta_d"``, ``"sqrt"``,
   rank 3, blue-acrylic (48, 12, 8): 0.117, (48, 16, 8): 0.077).

4. Across 27 of the 100 MERL materials (the three above, chrome, aluminium, nickel,
   steel, brass, tungsten-carbide, two-layer-gold, black-obsidian, the black, specular
   black and specular red phenolics, red and gray plastic, green acrylic, teflon, delrin,
   white, dark red, pearl, color-changing and blue and silver metallic paints, white and
   beige fabric), the smallest model of the ladder 968 bytes (rank 2, bins (32, 24), no
   phi_d factor), 1248 (rank 3, (24, 16, 8)), 2168 (rank 4, (32, 24, 8)), 2704 (rank 5),
   3624 (rank 6, (40, 24, 8)) -- ``"weights"``, ``"cbrt"``, linear theta_d -- that is
   within 10 %: 968 bytes for 21 materials, 1248 for 5, 2168 for green-acrylic (floor
   0.214); within 5 %: 968 bytes for 4, 1248 for 8, 2168 for 11, 2704 for alum-bronze
   and tungsten-carbide; blue-acrylic (0.051 at 4392 bytes) and green-acrylic (0.075 at
   3624) do not get there. Median for 5 %: 2168 bytes.

5. Non-reciprocal data: ``phi_turn="full"`` (phi_d tables over [0, 2 pi)) against the
   default half turn, real RGL-EPFL measurements (Dupuy & Jakob 2018, read by
   :func:`project.measured.read_rgl`), rank 4, ``"weights"``; l2 error of q on
   independent peak-resolving pairs (worst channel, as ``fit_model`` reports it,
   standard errors 1-7e-4) and the floor of :func:`project.reciprocity` (what no
   reciprocal form goes below); the seconds on 2 shared cores::

       file                   floor   bins          bytes  half          full
       paper_white_rgb        0.0223  (32, 24, 8)   2168   0.0260 (20 s)  0.0221 (16 s)
                                      (32, 24, 16)  2424   0.0257 (29 s)  0.0219 (34 s)
       colodur_napoli_4f_rgb  0.0524  (32, 24, 8)   2168   0.0629 (10 s)  0.0531 (9 s)
                                      (32, 24, 16)  2424   0.0662 (6 s)   0.0522 (9 s)
       vch_golden_yellow_rgb  0.0882  (32, 24, 8)   2168   0.159 (5 s)    0.150 (2 s)
                                      (32, 24, 16)  2424   0.268 (3 s)    0.150 (2 s)

   The half turn stays above the floor, as it must; the full turn reaches it at the same
   bytes, but at rank 4 it takes only part of the antisymmetric energy (paper: about
   40 % if the symmetric misfit stays that of the half turn; on the fitting rule the
   channels-summed error 0.0218 against an antisymmetric part of 0.0219): most of it
   lies at grazing angles (:mod:`project.reciprocity`), where four shared products also
   have to hold the symmetric lobe. Rank 8, bins (32, 24, 16), 4824 bytes, goes below
   the floor on the paper (0.0167, 135 s, 1000 sweeps) and to 0.098 on the vinyl (95 s).
   At rank 4 the vinyl's worst channel stays near 0.15 either way, far above its floor:
   a misfit of the ``"weights"`` lobe, not of reciprocity (on the rule, channels summed:
   0.068 half, 0.055 full, antisymmetric part 0.052; the 0.268 is one poor local
   minimum). A reciprocal BRDF
   gives the same fit either way (the data and so every step are symmetric under
   phi_d -> phi_d + pi: GGX rank 2, 0.0149 both).

   *Why a whole turn rather than a separate antisymmetric term.* A term
   a(theta_h, theta_d) s(phi_d) with s(phi_d + pi) = -s(phi_d) changes sign, so f >= 0
   would no longer hold by construction and the non-negative least squares of the fit
   would not apply; its own theta_h and theta_d tables cost n_h + n_d + n_phi + C reals
   per term (67, 536 bytes, at (32, 24, 8) on RGB), while the whole turn costs
   rank x n_phi more reals than the half turn at the same phi_d resolution (256 bytes at
   rank 4), or nothing at the same bytes with the nodes twice as far apart -- which the
   table shows is the better use of them (0.0221 against 0.0260 on the paper). The
   separate term was not built and measured.

``warp_d="grazing"`` (theta_d nodes dense towards pi/2) pays on analytic microfacet lobes
(Cook-Torrance GGX alpha 0.1, glass Fresnel, rank 1, bins (32, 24): 0.035 against 0.047;
(32, 16): 0.046 against 0.080) and on 12 of 16 surrogates at rank 4 and the default bins
(the errors 3 % lower on average; e.g. gray-plastic 0.034 against 0.039, alum-bronze
0.053 against 0.056, blue-acrylic 0.070 against 0.070), hence the default.

A fit evaluates the BRDF at about 0.2 million pairs with the default bins (0.2-0.5 s for
a MERL table), then iterates: 0.5-10 s for most fits above on 2 shared cores, up to
30-70 s for the slowly converging ones (gold-metallic-paint needs ~420-540 sweeps at
rank 4).

Limitations: the fit is a local minimum of a non-convex problem (a different path can end
a few per cent, relative, apart); kd and a constant part of the terms can trade places
(only their sum is determined); the phi_d factor is measured from the x axis at h = z
(see :class:`FactoredLobe`); only the L2 norm of q is implemented; the model has no
importance sampler.

References
----------
- C. Boutsidis and E. Gallopoulos, "SVD based initialization: a head start for nonnegative
  matrix factorization", Pattern Recognition 41(4), 2008.
- A. M. S. Ang and N. Gillis, "Accelerating nonnegative matrix factorization algorithms
  using extrapolation", Neural Computation 31(2), 2019.
- M. M. Bagher, J. Snyder and D. Nowrouzezahrai, "A non-parametric factor microfacet model
  for isotropic BRDFs", ACM Transactions on Graphics 35(5), 2016.
- J. Kim and H. Park, "Fast nonnegative matrix factorization: an active-set-like method
  and comparisons", SIAM Journal on Scientific Computing 33(6), 2011.
- J. Lawrence, S. Rusinkiewicz and R. Ramamoorthi, "Efficient BRDF importance sampling
  using a factored representation", ACM Transactions on Graphics 23(3) (SIGGRAPH), 2004.
- W. Matusik, H. Pfister, M. Brand and L. McMillan, "A data-driven reflectance model",
  ACM Transactions on Graphics 22(3), 2003.
- F. Romeiro, Y. Vasilyev and T. Zickler, "Passive reflectometry", ECCV 2008.
- S. Rusinkiewicz, "A new change of variables for efficient BRDF representation",
  Eurographics Rendering Workshop 1998.
- A. Sztrajman, G. Rainer, T. Ritschel and T. Weyrich, "Neural BRDF representation and
  importance sampling", Computer Graphics Forum 40(6), 2021.
- K. E. Torrance and E. M. Sparrow, "Theory for off-specular reflection from roughened
  surfaces", JOSA 57(9), 1967.
- B. Walter, S. R. Marschner, H. Li and K. E. Torrance, "Microfacet models for refraction
  through rough surfaces", Eurographics Symposium on Rendering 2007.
"""

from __future__ import annotations

import contextlib
import functools
import math
import time
import warnings
import weakref
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from numpy.polynomial.legendre import leggauss
from numpy.typing import ArrayLike, NDArray
from scipy.linalg.lapack import dpotrf, dpotrs
from threadpoolctl import threadpool_limits

from basis import from_rusinkiewicz
from basis.validation import check_bytes, choice, nonneg_int

from .brdf import BRDF, as_color
from .measured import MERLBRDF

__all__ = ["COLORS", "D_WARPS", "PHI_TURNS", "WARPS", "FactoredLobe", "fit_factored",
           "reuse_samples", "rusinkiewicz_rule"]

#: theta_h = (pi/2) s^p with s in [0, 1] uniform on the theta_h nodes: p of each warp
#: (nodes dense near the specular direction theta_h = 0 for p > 1).
WARPS = {"linear": 1.0, "sqrt": 2.0, "cbrt": 3.0}
#: theta_d = (pi/2) (1 - (1 - s)^p) with s uniform on the theta_d nodes: p of each warp
#: (nodes dense towards grazing, theta_d = pi/2, for p > 1).
D_WARPS = {"linear": 1.0, "grazing": 2.0}
#: Which factor carries the channels (see :func:`fit_factored`).
COLORS = ("theta_d", "theta_h", "both", "weights")
#: The part of the turn the phi_d tables span, as a fraction of 2 pi: "half" (phi_d folded
#: to [0, pi), reciprocal by construction) or "full" ([0, 2 pi), not reciprocal).
PHI_TURNS = {"half": 0.5, "full": 1.0}
_METRICS = ("l2",)
_HALF_PI = 0.5 * math.pi
#: Gauss-Legendre nodes per panel of the fitting grid in theta_h and theta_d.
_GL = 3
#: Restarts of a term whose tables went to zero, per fit.
_RESEEDS = 4
#: Extrapolation step of the accelerated iteration: start, growth on success, cap.
_BETA = (0.5, 2.0, 10.0)
#: Plain iterations of each stage before the extrapolation starts: started at once it
#: sometimes steers the fit into a worse local minimum (measured on blue-acrylic).
_WAIT = 30


# -- piecewise-linear tables ----------------------------------------------------------------

def _angle(s: NDArray, p: float, top: bool) -> NDArray:
    """Return theta = (pi/2) s^p, or (pi/2) (1 - (1 - s)^p) with ``top`` (dense near pi/2)."""
    return _HALF_PI * (1.0 - (1.0 - s) ** p) if top else _HALF_PI * s ** p


def _unwarp(theta: NDArray, p: float, top: bool) -> NDArray:
    """Return s in [0, 1] from theta: the inverse of :func:`_angle`."""
    x = np.clip(theta / _HALF_PI, 0.0, 1.0)
    return 1.0 - (1.0 - x) ** (1.0 / p) if top else x ** (1.0 / p)


def _hat(x: NDArray[np.float64], n: int) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Left node and fraction of the piecewise-linear interpolant on nodes 0..n-1 at x."""
    i0 = np.clip(np.floor(x).astype(np.intp), 0, n - 2)
    return i0, np.clip(x - i0, 0.0, 1.0)


def _periodic_hat(phi: NDArray[np.float64], n: int, period: float = math.pi,
                  ) -> tuple[NDArray, NDArray, NDArray]:
    """Nodes e0, e1 and fraction of the periodic interpolant on n nodes k period/n at phi."""
    x = phi * (n / period)
    f = np.floor(x)
    e0 = f.astype(np.intp) % n
    return e0, (e0 + 1) % n, np.clip(x - f, 0.0, 1.0)


def _lookup(table: NDArray, i0: NDArray, t: NDArray) -> NDArray:
    """(rank, n, channels) values of tables (rank, nodes, channels) at hat positions."""
    return table[:, i0] * (1.0 - t)[None, :, None] + table[:, i0 + 1] * t[None, :, None]


def _as_table(value: ArrayLike, name: str, ndim: int = 3) -> NDArray[np.float64]:
    t = np.array(value, dtype=np.float64)
    if ndim == 3 and t.ndim == 2:
        t = t[:, :, None]
    if t.ndim != ndim or t.shape[0] < 1 or t.shape[1] < 2 or (ndim == 3 and t.shape[2] < 1):
        want = "(rank, nodes >= 2) or (rank, nodes, channels)" if ndim == 3 else \
            "(rank, nodes >= 2)"
        raise ValueError(f"{name} must have shape {want}, got {t.shape}")
    if not np.all(np.isfinite(t)) or np.any(t < 0):
        raise ValueError(f"{name} must hold finite values >= 0")
    return np.ascontiguousarray(t)


class FactoredLobe(BRDF):
    """An isotropic BRDF tabulated as a sum of products of 1-D factors.

    f(w_i, w_o) = kd/pi + sum_{k=1..rank} w_k A_k(theta_h) B_k(theta_d) C_k(phi_d)

    in every channel, with (theta_h, theta_d, phi_d) the half/difference angles of
    Rusinkiewicz (1998): theta_h the angle of h = (w_i + w_o)/|w_i + w_o| from the normal,
    theta_d the angle between w_i and h, phi_d the azimuth of w_i about h.
    :func:`fit_factored` makes one from any BRDF.

    Parameters
    ----------
    kd : float or (channels,) array_like of float
        Albedo of the Lambertian term kd/pi, >= 0.
    h_table : (rank, n_h) or (rank, n_h, channels) array_like of float
        A_k (1/sr) at the theta_h nodes (pi/2) (i / (n_h - 1))^p, i = 0..n_h-1, p the
        exponent of ``warp``; >= 0.
    d_table : (rank, n_d) or (rank, n_d, channels) array_like of float
        B_k (dimensionless) at the theta_d nodes (pi/2) (1 - (1 - j / (n_d - 1))^q),
        j = 0..n_d-1, q the exponent of ``warp_d`` (q = 1: uniform); >= 0.
    phi_table : None or (rank, n_phi) array_like of float
        C_k at phi_d = e P / n_phi, e = 0..n_phi-1, periodic with period P = pi
        (``phi_turn="half"``) or 2 pi (``"full"``); None means C_k = 1 (no phi_d dependence).
    weights : None or (rank, channels) array_like of float
        The colour w_k of each term, for tables without a channel axis; None means 1.
    warp : {"cbrt", "sqrt", "linear"}
        p = 3, 2, 1: the theta_h nodes are uniform in theta_h^(1/p), dense near the
        specular direction for p > 1 ("sqrt" is the MERL layout, Matusik et al. 2003).
    warp_d : {"grazing", "linear"}
        q = 2, 1: theta_d nodes dense towards grazing (theta_d = pi/2), or uniform.
    phi_turn : {"half", "full"}
        The period of the phi_d tables: half a turn (phi_d folded to [0, pi): f is
        reciprocal) or the whole turn ([0, 2 pi): f(w_i, w_o) and f(w_o, w_i) may differ).
        "full" needs a ``phi_table``.
    info : dict, optional
        Kept as ``info`` (the fit report of :func:`fit_factored`).

    Attributes
    ----------
    rank, bins, kd, h_table, d_table, phi_table, weights, nparams, nbytes, info
        See the properties; the tables are read-only views.
    phi_turn : str
        "half" or "full", as given.
    reciprocal : bool
        True for ``phi_turn="half"``, False for "full".

    Notes
    -----
    *Interpolation.* Each table is linear between its nodes in the coordinate in which the
    nodes are uniform (A_k in (2 theta_h / pi)^(1/p), B_k in 1 - (1 - 2 theta_d / pi)^(1/q),
    C_k in phi_d with wrap-around), so f is continuous; the nodes span [0, pi/2], all of
    theta_h and theta_d above the horizon.

    *Colour.* The channels are carried by whichever arrays have a channel axis: with
    :func:`fit_factored`'s ``color="theta_d"`` the B_k (Fresnel-like colour), with
    ``"theta_h"`` the A_k, with ``"both"`` both, with ``"weights"`` only the (rank, channels)
    ``weights`` (each term one shape and one RGB colour). kd is always per channel.

    *Reciprocity and isotropy.* Swapping w_i and w_o leaves theta_h and theta_d unchanged
    and turns phi_d into phi_d + pi (mod 2 pi). Proof, in the notation of
    :func:`basis.to_rusinkiewicz`: h = (w_i + w_o)/|w_i + w_o| is symmetric, so theta_h,
    phi_h and the rotation R = R_y(-theta_h) R_z(-phi_h) taking h to z are too; w_o is the
    mirror image of w_i about h, w_o = 2 (w_i . h) h - w_i, so with d = R w_i =
    (sin td cos pd, sin td sin pd, cos td) the difference vector of the exchanged pair is
    R w_o = 2 cos(td) z - d = (-sin td cos pd, -sin td sin pd, cos td): the same theta_d,
    and phi_d + pi. (Equivalently R (w_i - w_o) = 2 sin(theta_d) (cos phi_d, sin phi_d, 0),
    which the exchange negates; ``tests/project/test_factored.py`` checks this against
    ``to_rusinkiewicz``.) With ``phi_turn="half"`` the period pi of C_k absorbs the shift:
    the angles are computed from w_i + w_o and w_i - w_o, so f(w_i, w_o) == f(w_o, w_i) bit
    for bit. With ``"full"``, phi_d = atan2 of the components of R (w_i - w_o) in [0, 2 pi)
    of the pair in the order given, and C_k(phi_d) and C_k(phi_d + pi) are independent
    values: the lobe holds a non-reciprocal BRDF, its antisymmetric part
    sum_k w_k A_k B_k (C_k(phi_d) - C_k(phi_d + pi)) / 2 included. The exchange is still
    exact: it negates w_i - w_o bit for bit, so f(w_o, w_i) is the value at phi_d + pi.
    Nothing depends on phi_h, so f is unchanged by rotations about the normal, except on the
    set of measure zero h = z, where phi_d is measured from the x axis (as
    :class:`~project.measured.MERLBRDF` does) and a phi_d table makes f depend on the
    azimuth.

    *Values.* Every factor is >= 0, so f >= 0, and finite.

    Examples
    --------
    >>> lobe = FactoredLobe(0.2, [[50.0, 1.0, 0.0]], [[1.0, 1.2]])
    >>> lobe
    FactoredLobe(rank=1, bins=(3, 2), warp='cbrt', warp_d='grazing', channels=1, nbytes=48)
    >>> round(float(lobe.eval([0, 0, 1.0], [0, 0, 1.0])), 6)  # theta_h = theta_d = 0
    50.063662

    A full-turn phi_d table: brighter when w_i is on the +x side of h than in the exchange.

    >>> full = FactoredLobe(0.0, [[1.0, 1.0]], [[1.0, 1.0]], phi_table=[[2.0, 1.0, 0.0, 1.0]],
    ...                     phi_turn="full")
    >>> full.reciprocal, full.bins
    (False, (2, 2, 4))
    >>> wi, wo = [0.6, 0.0, 0.8], [-0.6, 0.0, 0.8]  # h = z, phi_d = 0 and pi
    >>> float(full.eval(wi, wo)), float(full.eval(wo, wi))
    (2.0, 0.0)
    """

    #: The name of this family in :func:`project.fit_model` and :mod:`compress.store`.
    family = "factored"

    def __init__(self, kd: ArrayLike, h_table: ArrayLike, d_table: ArrayLike, *,
                 phi_table: ArrayLike | None = None, weights: ArrayLike | None = None,
                 warp: str = "cbrt", warp_d: str = "grazing", phi_turn: str = "half",
                 info: dict[str, Any] | None = None) -> None:
        self._p = WARPS[choice(warp, "warp", tuple(WARPS))]
        self._period = 2.0 * math.pi * PHI_TURNS[choice(phi_turn, "phi_turn",
                                                         tuple(PHI_TURNS))]
        if phi_turn == "full" and phi_table is None:
            raise ValueError("phi_turn 'full' needs a phi_table (without one f does not "
                             "depend on phi_d and is reciprocal), got phi_table=None")
        self.phi_turn = phi_turn
        self._pd = D_WARPS[choice(warp_d, "warp_d", tuple(D_WARPS))]
        self.warp = warp
        self.warp_d = warp_d
        k = as_color(kd, "kd", low=0.0)
        a = _as_table(h_table, "h_table")
        b = _as_table(d_table, "d_table")
        r = a.shape[0]
        if b.shape[0] != r:
            raise ValueError(f"h_table and d_table must have the same rank (first axis), got "
                             f"{r} and {b.shape[0]}")
        c = None
        if phi_table is not None:
            c = _as_table(phi_table, "phi_table", ndim=2)
            if c.shape[0] != r:
                raise ValueError(f"phi_table must have rank {r} rows, got {c.shape[0]}")
        sizes = {"kd": k.size, "h_table": a.shape[2], "d_table": b.shape[2]}
        w = None
        if weights is not None:
            w = np.array(weights, dtype=np.float64)
            if w.ndim == 1:
                w = w[:, None]
            if w.ndim != 2 or w.shape[0] != r:
                raise ValueError(f"weights must have shape (rank, channels) with rank = {r}, "
                                 f"got {w.shape}")
            if not np.all(np.isfinite(w)) or np.any(w < 0):
                raise ValueError("weights must hold finite values >= 0")
            sizes["weights"] = w.shape[1]
        many = {s for s in sizes.values() if s > 1}
        if len(many) > 1:
            raise ValueError("per-channel arrays must have the same number of channels (or 1), "
                             "got " + ", ".join(f"{n}: {s}" for n, s in sizes.items()))
        self.channels = many.pop() if many else 1
        # scalar kd and tables without a channel axis: eval returns (...), as the models do
        self._scalar = (self.channels == 1 and np.ndim(kd) == 0 and np.ndim(h_table) == 2
                        and np.ndim(d_table) == 2 and weights is None)
        self.isotropic = True
        self.reciprocal = phi_turn == "half"
        for arr in (k, a, b, c, w):
            if arr is not None:
                arr.flags.writeable = False
        self._kd, self._a, self._b, self._c, self._w = k, a, b, c, w
        self.info: dict[str, Any] = dict(info or {})

    # -- read-only state ------------------------------------------------------------------
    @property
    def rank(self) -> int:
        """Number of product terms."""
        return int(self._a.shape[0])

    @property
    def bins(self) -> tuple[int, int] | tuple[int, int, int]:
        """Nodes of the tables: (n_h, n_d), or (n_h, n_d, n_phi) with a phi_d factor."""
        nb = (int(self._a.shape[1]), int(self._b.shape[1]))
        return nb if self._c is None else (*nb, int(self._c.shape[1]))

    @property
    def kd(self) -> NDArray[np.float64]:
        """(channels,) Lambertian albedo of the diffuse term kd/pi."""
        return np.broadcast_to(self._kd, (self.channels,)).copy()

    @property
    def h_table(self) -> NDArray[np.float64]:
        """(rank, n_h, 1 or channels) read-only values of A_k at the theta_h nodes (1/sr)."""
        return self._a.view()

    @property
    def d_table(self) -> NDArray[np.float64]:
        """(rank, n_d, 1 or channels) read-only values of B_k at the theta_d nodes."""
        return self._b.view()

    @property
    def phi_table(self) -> NDArray[np.float64] | None:
        """(rank, n_phi) read-only values of C_k at phi_d = j P / n_phi, or None (C = 1).

        P = pi for ``phi_turn="half"``, 2 pi for "full".
        """
        return None if self._c is None else self._c.view()

    @property
    def weights(self) -> NDArray[np.float64] | None:
        """(rank, channels) read-only colour of each term, or None (all ones)."""
        return None if self._w is None else self._w.view()

    @property
    def theta_h_nodes(self) -> NDArray[np.float64]:
        """(n_h,) angles (radians) of the theta_h nodes, (pi/2) (i / (n_h - 1))^p."""
        n = int(self._a.shape[1])
        return _angle(np.arange(n) / (n - 1), self._p, False)

    @property
    def theta_d_nodes(self) -> NDArray[np.float64]:
        """(n_d,) angles (radians) of the theta_d nodes, (pi/2) (1 - (1 - j/(n_d - 1))^q)."""
        n = int(self._b.shape[1])
        return _angle(np.arange(n) / (n - 1), self._pd, True)

    @property
    def nparams(self) -> int:
        """Number of stored reals: kd, the tables and the weights."""
        return int(sum(x.size for x in (self._kd, self._a, self._b, self._c, self._w)
                       if x is not None))

    @property
    def nbytes(self) -> int:
        """Storage in bytes, 8 (float64) per stored real."""
        return 8 * self.nparams

    @property
    def params(self) -> dict[str, NDArray[np.float64]]:
        """The stored arrays by name, as ``project.FittedModel("factored", params)`` takes them.

        ``kd`` (channels,), ``h_table``, ``d_table`` (with their channel axis), ``phi_table``
        and ``weights`` when present, and the warp exponents ``warp`` (p) and ``warp_d`` (q)
        as 0-d arrays; all read-only. A full-turn lobe also holds ``phi_turn``, the 0-d
        array 1.0 (the fraction of the turn its phi_d tables span, :data:`PHI_TURNS`); a
        half-turn lobe does not, so its params are what they were before full-turn lobes
        existed and parameters without ``phi_turn`` mean "half". The period cannot be told
        from the table length (n_phi nodes may span either), hence the entry.
        """
        out = {"kd": self.kd, "h_table": self._a, "d_table": self._b}
        if self._c is not None:
            out["phi_table"] = self._c
        if self._w is not None:
            out["weights"] = self._w
        out["warp"] = np.array(self._p)
        out["warp_d"] = np.array(self._pd)
        if self.phi_turn != "half":
            out["phi_turn"] = np.array(PHI_TURNS[self.phi_turn])
        for v in out.values():
            v.flags.writeable = False
        return out

    # -- evaluation -------------------------------------------------------------------------
    def _angles(self, wi: NDArray, wo: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """Return (theta_h, theta_d, phi_d) of (n, 3) unit pairs.

        From h = wi + wo and wi - wo (as MERLBRDF's kernel), so swapping wi and wo gives the
        same theta_h, theta_d bit for bit and negates wi - wo exactly. Half turn: phi_d
        folded into [0, pi) by reciprocity (symmetric in wi, wo); full turn: phi_d in
        [0, 2 pi) of the pair in the given order (the exchange adds pi). phi_d is measured
        from the x axis when h = z (phi_h taken as 0).
        """
        h = wi + wo
        dv = wi - wo
        r = np.sqrt(h[:, 0] ** 2 + h[:, 1] ** 2)
        hn = np.sqrt(r * r + h[:, 2] ** 2)
        theta_h = np.minimum(np.arctan2(r, h[:, 2]), _HALF_PI)
        theta_d = np.minimum(np.arctan2(np.sqrt(np.einsum("ij,ij->i", dv, dv)), hn), _HALF_PI)
        if self._c is None:
            return theta_h, theta_d, np.zeros_like(theta_h)
        pos = hn > 0
        ct = np.where(pos, h[:, 2] / np.where(pos, hn, 1.0), 1.0)
        st = np.where(pos, r / np.where(pos, hn, 1.0), 0.0)
        rp = r > 0
        cp = np.where(rp, h[:, 0] / np.where(rp, r, 1.0), 1.0)
        sp = np.where(rp, h[:, 1] / np.where(rp, r, 1.0), 0.0)
        a = ct * (cp * dv[:, 0] + sp * dv[:, 1]) - st * dv[:, 2] + 0.0
        b = cp * dv[:, 1] - sp * dv[:, 0] + 0.0
        if self.phi_turn == "full":
            return theta_h, theta_d, np.mod(np.arctan2(b, a), 2.0 * math.pi)
        flip = (b < 0) | ((b == 0) & (a < 0))
        a = np.where(flip, -a, a) + 0.0
        b = np.where(flip, -b, b) + 0.0
        return theta_h, theta_d, np.mod(np.arctan2(b, a), math.pi)

    def _eval(self, wi: NDArray, wo: NDArray) -> NDArray:
        wi = wi / np.sqrt(np.einsum("ij,ij->i", wi, wi))[:, None]
        wo = wo / np.sqrt(np.einsum("ij,ij->i", wo, wo))[:, None]
        theta_h, theta_d, phi_d = self._angles(wi, wo)
        n_h, n_d = int(self._a.shape[1]), int(self._b.shape[1])
        s = _unwarp(theta_h, self._p, False) * (n_h - 1)
        t = _unwarp(theta_d, self._pd, True) * (n_d - 1)
        ab = _lookup(self._a, *_hat(s, n_h)) * _lookup(self._b, *_hat(t, n_d))
        if self._c is not None:
            e0, e1, u = _periodic_hat(phi_d, self._c.shape[1], self._period)
            ab = ab * (self._c[:, e0] * (1.0 - u) + self._c[:, e1] * u)[:, :, None]
        if self._w is not None:
            ab = ab * self._w[:, None, :]
        out = np.broadcast_to(self._kd / math.pi, (wi.shape[0], self.channels)).copy()
        out += ab.sum(axis=0)
        return out

    def __repr__(self) -> str:
        turn = "" if self.phi_turn == "half" else f", phi_turn={self.phi_turn!r}"
        return (f"FactoredLobe(rank={self.rank}, bins={self.bins}, warp={self.warp!r}, "
                f"warp_d={self.warp_d!r}{turn}, channels={self.channels}, "
                f"nbytes={self.nbytes})")


# -- the fitting grid -----------------------------------------------------------------------

def _panel_rule(n_nodes: int, nodes: int, power: float, top: bool = False,
                ) -> tuple[NDArray, NDArray, NDArray]:
    """Composite Gauss-Legendre rule in theta on [0, pi/2], theta = _angle(s, power, top).

    [0, 1] in s is cut at the table nodes i / (n_nodes - 1), each bin into equal panels so
    that there are at least ``nodes`` nodes in all, _GL per panel. Returns theta, the
    weights of d theta, and the position s (n_nodes - 1) in node units.
    """
    bins = n_nodes - 1
    sub = max(1, -(-nodes // (_GL * bins)))
    edges = np.linspace(0.0, 1.0, bins * sub + 1)
    x, w = leggauss(_GL)
    lo, hi = edges[:-1, None], edges[1:, None]
    s = (0.5 * (lo + hi) + 0.5 * (hi - lo) * x).ravel()
    ws = (0.5 * (hi - lo) * w).ravel()
    dtheta = _HALF_PI * power * ((1.0 - s) if top else s) ** (power - 1.0)
    return _angle(s, power, top), ws * dtheta, s * bins


def _cosines(theta_h: NDArray, theta_d: NDArray, phi_d: NDArray) -> tuple[NDArray, NDArray]:
    """(z_i, z_o) of Rusinkiewicz angles: cos th cos td -/+ sin th sin td cos phi_d."""
    a = np.cos(theta_h) * np.cos(theta_d)
    b = np.sin(theta_h) * np.sin(theta_d) * np.cos(phi_d)
    return a - b, a + b


def _rule(bins: tuple[int, int], power: float, power_d: float,
          samples: tuple[int, int, int], full: bool = False):
    th, wth, s = _panel_rule(bins[0], samples[0], power)
    td, wtd, t = _panel_rule(bins[1], samples[1], power_d, top=True)
    # both directions above the horizon <=> |cos phi_d| <= cot(theta_h) cot(theta_d): the
    # interval [phi0, pi - phi0], integrated alone so the horizon is not inside the rule
    alpha = np.cos(th)[:, None] * np.cos(td)[None, :]
    beta = np.sin(th)[:, None] * np.sin(td)[None, :]
    c = np.where(beta > alpha, alpha / np.where(beta > 0, beta, 1.0), 1.0)
    half = _HALF_PI - np.arccos(np.clip(c, 0.0, 1.0))
    x, w = leggauss(samples[2])
    phi = _HALF_PI + half[..., None] * x
    jac = 4.0 * (np.sin(th) * wth)[:, None] * (np.cos(td) * np.sin(td) * wtd)[None, :]
    weights = (4.0 * math.pi) * (jac * half)[..., None] * w
    if full:  # the exchanged pairs: phi_d + pi, each half of the turn with half the weight
        phi = np.concatenate([phi, phi + math.pi], axis=2)
        weights = np.concatenate([0.5 * weights, 0.5 * weights], axis=2)
    return th, td, phi, weights, s, t


def rusinkiewicz_rule(bins: tuple[int, int] = (32, 24), warp: str = "cbrt",
                      samples: tuple[int, int, int] = (180, 64, 16), warp_d: str = "grazing",
                      phi_turn: str = "half") -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Return the quadrature rule over H x H in half/difference angles that fits use.

    Parameters
    ----------
    bins : (int, int)
        Table nodes (n_h, n_d) in theta_h and theta_d: the panels of the rule are cut at
        them, so a piecewise-linear table is a polynomial on each panel.
    warp : {"cbrt", "sqrt", "linear"}
        theta_h = (pi/2) s^p with p = 3, 2, 1; the panels are uniform in s.
    samples : (int, int, int)
        At least this many nodes in theta_h and theta_d (3-point Gauss-Legendre panels, each
        table bin cut into equal panels), and exactly this many in phi_d.
    warp_d : {"grazing", "linear"}
        theta_d = (pi/2) (1 - (1 - s)^q) with q = 2, 1; the panels are uniform in s.
    phi_turn : {"half", "full"}
        Half a turn: the nodes in [0, pi], for functions unchanged by phi_d -> phi_d + pi.
        Full turn: those nodes, then the same nodes shifted by pi (the exchanged pairs
        (w_o, w_i), see :class:`FactoredLobe`), each with half the weight.

    Returns
    -------
    theta_h : (N_h,) ndarray
    theta_d : (N_d,) ndarray
    phi_d : (N_h, N_d, n_phi) ndarray, or (N_h, N_d, 2 n_phi) for the full turn
        Gauss-Legendre nodes on the part of [0, pi] where both directions are above the
        horizon, an interval [phi0, pi - phi0] for each (theta_h, theta_d); for the full
        turn followed by the same nodes plus pi (the interval [pi + phi0, 2 pi - phi0]).
    weights : same shape as phi_d
        sum(weights * g) approximates the integral of g over H x H in solid angle,
        d w_i d w_o, for g that depends on (theta_h, theta_d, phi_d) only and is unchanged by
        phi_d -> phi_d + pi (every isotropic, reciprocal function); for the full turn, for
        every isotropic g.

    Notes
    -----
    The change of variables (w_i, w_o) -> (h, d) of Rusinkiewicz (1998) has

        d w_i d w_o = 4 cos(theta_d) d w_h d w_d
                    = 4 cos(theta_d) sin(theta_h) sin(theta_d)
                      d theta_h d phi_h d theta_d d phi_d.

    Derivation: for fixed w_i, the half vector h = (w_i + w_o)/|w_i + w_o| has
    d w_o = 4 (w_o . h) d w_h (Torrance & Sparrow 1967; Walter et al. 2007) and
    w_o . h = w_i . h = cos(theta_d); for fixed h, d = R(h)^-1 w_i is a rotation of w_i, so
    d w_i = d w_d. Over H x H, theta_h and theta_d run over [0, pi/2] and phi_d over the set
    where z_i = cos th cos td - sin th sin td cos phi_d and z_o (the same with +) are both
    >= 0. phi_h is integrated in closed form (2 pi, as nothing depends on it) and
    phi_d in [pi, 2 pi) contributes what [0, pi) does, whence the factor 4 pi times the
    Jacobian. The rule integrates 1 to (2 pi)^2 and z_i z_o to pi^2 (tested).

    Examples
    --------
    >>> th, td, phi, w = rusinkiewicz_rule()
    >>> round(float(w.sum() / (2 * np.pi) ** 2), 3)  # the horizon kink limits this one
    1.0
    >>> th, td, phi2, w2 = rusinkiewicz_rule(phi_turn="full")
    >>> phi2.shape[2] == 2 * phi.shape[2], bool(np.allclose(phi2[..., 16:], phi + np.pi))
    (True, True)
    >>> bool(np.isclose(w2.sum(), w.sum(), rtol=1e-14, atol=0))
    True
    """
    n_h, n_d = (nonneg_int(b, "bins") for b in bins)
    if n_h < 2 or n_d < 2:
        raise ValueError(f"bins must be (n_h, n_d) with both >= 2, got {bins!r}")
    power = WARPS[choice(warp, "warp", tuple(WARPS))]
    power_d = D_WARPS[choice(warp_d, "warp_d", tuple(D_WARPS))]
    samples = _samples(samples)
    full = PHI_TURNS[choice(phi_turn, "phi_turn", tuple(PHI_TURNS))] == 1.0
    th, td, phi, weights, _, _ = _rule((n_h, n_d), power, power_d, samples, full)
    return th, td, phi, weights


def _samples(samples: object) -> tuple[int, int, int]:
    try:
        out = tuple(nonneg_int(s, "samples") for s in samples)  # type: ignore[attr-defined]
    except TypeError:
        raise TypeError(f"samples must be a tuple of three integers, got {samples!r}") from None
    if len(out) != 3 or min(out) < 1:
        raise ValueError(f"samples must be (n_theta_h, n_theta_d, n_phi_d), each >= 1, got "
                         f"{samples!r}")
    return out  # type: ignore[return-value]


# -- sampling the BRDF on the rule ----------------------------------------------------------

def _merl_skip(brdf: MERLBRDF, th: NDArray, td: NDArray, phi: NDArray) -> NDArray[np.bool_]:
    """Return True where the MERL node nearest to (theta_h, theta_d, phi_d) is invalid."""
    valid = brdf.valid.all(axis=0)
    nh, nd, npd = valid.shape
    i = np.minimum((np.sqrt(th / _HALF_PI) * nh + 0.5).astype(np.intp), nh - 1)
    j = np.minimum((td / _HALF_PI * nd + 0.5).astype(np.intp), nd - 1)
    k = (phi / math.pi * npd + 0.5).astype(np.intp) % npd
    return ~valid[i, j, k]


def _values(brdf: Any, wi: NDArray, wo: NDArray, channels: int, angles: tuple) -> NDArray:
    """(n, channels) values of brdf.eval, checked finite and >= 0."""
    f = np.asarray(brdf.eval(wi, wo), dtype=np.float64)
    n = wi.shape[0]
    if f.shape in ((n,), (n, 1)):
        f = np.broadcast_to(f.reshape(n, 1), (n, channels))
    elif f.shape != (n, channels):
        raise ValueError(f"brdf.eval must return shape (n,), (n, 1) or (n, channels) for n "
                         f"direction pairs, got {f.shape} for n = {n}")
    bad = ~np.isfinite(f) | (f < 0)
    if bad.any():
        p, c = np.unravel_index(int(np.flatnonzero(bad)[0]), f.shape)
        ang = [float(np.degrees(a.reshape(-1)[p])) for a in angles]
        raise ValueError(
            f"brdf.eval must return finite values >= 0 above the horizon, got {f[p, c]!r} "
            f"(channel {c}) at theta_h = {ang[0]:.6g} deg, theta_d = {ang[1]:.6g} deg, "
            f"phi_d = {ang[2]:.6g} deg; {int(bad.sum())} of {f.size} values are bad")
    return f


def _sample(brdf: Any, th: NDArray, td: NDArray, phi: NDArray, weights: NDArray,
            channels: int, full: bool = False) -> dict[str, Any]:
    """Weights w z_i^2 z_o^2 and values of the BRDF on the rule.

    Half turn: the values of the reciprocal part (f(w_i, w_o) + f(w_o, w_i)) / 2. Full
    turn (the rule of both orders): f itself at every node, nothing symmetrised.
    Returns w (N_h, N_d, n_phi) (0 where a MERL table is invalid), f (C, N_h, N_d, n_phi),
    S (C,) = sum w f^2 (all of f), ``anti`` (C,), the energy of the non-reciprocal part
    (f(w_i, w_o) - f(w_o, w_i)) / 2 that the half-turn model does not see (0 for the full
    turn and for BRDFs that say they are reciprocal), and ``antisymmetric`` (C,), that
    energy on the rule in either case (for the report).
    """
    reciprocal = bool(getattr(brdf, "reciprocal", True)) or full
    shape = phi.shape
    zi, zo = _cosines(th[:, None, None], td[None, :, None], phi)
    w = weights * (zi * zo) ** 2
    total = float(w.sum())
    skipped = 0.0
    if isinstance(brdf, MERLBRDF):
        skip = _merl_skip(brdf, np.broadcast_to(th[:, None, None], shape),
                          np.broadcast_to(td[None, :, None], shape), phi)
        skipped = float(w[skip].sum()) / total
        w = np.where(skip, 0.0, w)
    f = np.empty((channels, *shape))
    S = np.zeros(channels)
    anti = np.zeros(channels)
    n_d, n_phi = shape[1], shape[2]
    rows = max(1, (1 << 20) // (n_d * n_phi))  # about 1M pairs per call of brdf.eval
    for start in range(0, shape[0], rows):
        sl = slice(start, start + rows)
        t3 = np.broadcast_to(th[sl, None, None], phi[sl].shape)
        d3 = np.broadcast_to(td[None, :, None], phi[sl].shape)
        wi, wo = from_rusinkiewicz(t3, 0.0, d3, phi[sl])
        # the nodes are strictly above the horizon; keep rounding from taking them below it
        wi[..., 2] = np.maximum(wi[..., 2], 0.0)
        wo[..., 2] = np.maximum(wo[..., 2], 0.0)
        wi, wo = wi.reshape(-1, 3), wo.reshape(-1, 3)
        ws = w[sl].reshape(-1)
        a = _values(brdf, wi, wo, channels, (t3, d3, phi[sl]))
        if not reciprocal:  # fitted to the reciprocal part, the mean of f(wi, wo), f(wo, wi)
            b = _values(brdf, wo, wi, channels, (t3, d3, phi[sl]))
            anti += ws @ (0.5 * (a - b)) ** 2
            a = 0.5 * (a + b)
        S += ws @ (a * a)
        f[:, sl] = a.T.reshape(channels, *phi[sl].shape)
    antisym = anti
    if full:  # the second half of the turn holds the exchanged pairs of the first
        m = shape[2] // 2
        antisym = np.einsum("ijp,cijp->c", w[..., :m] + w[..., m:],
                            (0.5 * (f[..., :m] - f[..., m:])) ** 2)
    return {"w": w, "f": f, "S": S + anti, "anti": anti, "antisymmetric": antisym,
            "skipped": skipped, "evaluations": int(phi.size * (1 if reciprocal else 2))}


# -- alternating non-negative least squares -------------------------------------------------

def _nnls(M: NDArray, c: NDArray, passive: NDArray[np.bool_] | None = None,
          ) -> tuple[NDArray, NDArray[np.bool_]]:
    """Minimise x^T M x - 2 c^T x over x >= 0 (M symmetric positive semi-definite).

    Block principal pivoting (Kim & Park 2011, alg. 1, with its backup rule) on the
    Jacobi-scaled normal equations plus a ridge of 1e-13, warm-started from the passive
    set ``passive`` of the previous solve. Returns x and its passive set.
    """
    n = c.size
    d = np.sqrt(np.diag(M).copy())
    d[~(d > 0)] = 1.0
    Ms = M / d[:, None] / d[None, :]
    Ms[np.diag_indices(n)] += 1e-13
    cs = c / d
    F = np.ones(n, dtype=bool) if passive is None else passive.copy()
    best, backup = n + 1, 3
    tol = 1e-12 * max(1.0, float(np.abs(cs).max()))
    x = np.zeros(n)
    for _ in range(5 * n + 10):
        x = np.zeros(n)
        if F.any():
            x[F] = _cholesky_solve(Ms if F.all() else Ms[np.ix_(F, F)], cs[F])
        y = Ms @ x - cs
        y[F] = 0.0
        bad = (F & (x < 0)) | (~F & (y < -tol))
        nbad = int(bad.sum())
        if nbad == 0:
            break
        if nbad < best:
            best, backup = nbad, 3
            F ^= bad
        elif backup > 0:
            backup -= 1
            F ^= bad
        else:  # the backup rule: exchange only the last infeasible variable
            F[np.flatnonzero(bad)[-1]] ^= True
    return np.maximum(x, 0.0) / d, F


def _cholesky_solve(M: NDArray, b: NDArray) -> NDArray:
    """Solve M x = b, M symmetric positive definite, by LAPACK's potrf and potrs.

    What ``scipy.linalg.cho_solve(cho_factor(M), b)`` computes, without its checks and
    copies: the steps solve a few thousand small systems per fit.
    """
    c, info = dpotrf(M, lower=False, clean=False)
    if info > 0:
        raise np.linalg.LinAlgError(f"{info}-th leading minor of the array is not positive "
                                    "definite")
    x, info = dpotrs(c, b, lower=False)
    if info != 0:
        raise ValueError(f"illegal value in argument {-info} of LAPACK potrs")
    return x


def _tridiag(n: int, r: int, d00: NDArray, d11: NDArray, d01: NDArray,
             periodic: bool) -> NDArray:
    """(n r, n r) normal matrix of piecewise-linear coefficients ordered (node, term).

    d00[e], d11[e], d01[e] (r x r) are the sums of w h0 h0 X X^T, w h1 h1 X X^T and
    w h0 h1 X X^T over the samples whose left node is e (h0, h1 the two hat weights).
    """
    M = np.zeros((n, r, n, r))
    m = n if periodic else n - 1
    e = np.arange(m)
    e1 = (e + 1) % n
    diag = np.zeros((n, r, r))
    diag[:m] += d00[:m]
    diag[e1] += d11[:m]
    every = np.arange(n)
    M[every, :, every, :] = diag
    # each (e, e1) pair occurs once per statement, so += adds every term
    M[e, :, e1, :] += d01[:m]
    M[e1, :, e, :] += np.swapaxes(d01[:m], 1, 2)
    return M.reshape(n * r, n * r)


def _solve(blocks: list, m: int, shared: bool, kd_free: bool, W0: float, F0: NDArray,
           passive: list | None) -> tuple[list[NDArray], NDArray, list, float]:
    """Solve the normal equations of one block of unknowns and kd.

    ``blocks[c]`` = (M_c, rhs_c, kd column_c) of channel c; with ``shared`` the channels
    share the unknowns (their M and rhs add up) and have their own kd. Returns the
    solutions, kd, the passive sets and the value x^T M x - 2 x^T rhs at the solution
    (the squared error minus sum w f^2).
    """
    C = len(blocks)
    groups = [list(range(C))] if shared else [[c] for c in range(C)]
    xs, kd, passives, value = [], np.zeros(C), [], 0.0
    for gi, chans in enumerate(groups):
        size = m + (len(chans) if kd_free else 0)
        M = np.zeros((size, size))
        rhs = np.zeros(size)
        for q, c in enumerate(chans):
            Mc, rc, kc = blocks[c]
            M[:m, :m] += Mc
            rhs[:m] += rc
            if kd_free:
                M[:m, m + q] = M[m + q, :m] = kc
                M[m + q, m + q] = W0 / math.pi ** 2
                rhs[m + q] = F0[c] / math.pi
        x, F = _nnls(M, rhs, None if passive is None else passive[gi])
        value += float(x @ M @ x - 2.0 * x @ rhs)
        xs.append(x[:m])
        if kd_free:
            kd[chans] = x[m:]
        passives.append(F)
    return xs, kd, passives, value


class _Problem:
    """The data of a fit, reduced to sums over the phi_d nodes of each (theta_h, theta_d).

    With a phi_d factor of n_phi nodes, each sample p (weight w_p, values f_p) lies between
    the nodes e0 and e1 = e0 + 1 with hat weights (1 - u_p, u_p); the sums S00, S01 (by e0),
    S11 (by e1), S0 (both) and Fe of w h h, w h and w h f per cell and node are all that
    the alternating steps need, so no step loops over the samples.
    """

    def __init__(self, data: dict, phi: NDArray, s: NDArray, t: NDArray,
                 bins: tuple[int, int], n_phi: int, period: float = math.pi) -> None:
        w, f = data["w"], data["f"]
        self.w, self.f = w, f
        self.n_h, self.n_d = bins
        self.hat_h = _hat(s, self.n_h)
        self.hat_d = _hat(t, self.n_d)
        self.P = _dense_hat(*self.hat_h, self.n_h)
        self.Q = _dense_hat(*self.hat_d, self.n_d)
        self.W = w.sum(axis=2)
        self.F = np.einsum("cijp,ijp->cij", f, w)
        self.W0 = float(self.W.sum())
        self.F0 = self.F.sum(axis=(1, 2))
        self.Fb = np.where(self.W > 0, self.F / np.where(self.W > 0, self.W, 1.0), 0.0)
        self.S = data["S"]
        self.anti = data["anti"]
        # what no phi_d-independent function fits, summed directly (no cancellation)
        self.floor = np.einsum("ijp,cijp->c", w, (f - self.Fb[..., None]) ** 2)
        self.n_phi = n_phi
        if n_phi:
            self.phat = _periodic_hat(phi, n_phi, period)
            e0, e1, u = self.phat
            N = self.W.size
            cell = (np.arange(N) * n_phi).reshape(self.W.shape)[..., None]

            def acc(idx: NDArray, x: NDArray) -> NDArray:
                return np.bincount((cell + idx).ravel(), x.ravel(), minlength=N * n_phi
                                   ).reshape(N, n_phi)

            v = 1.0 - u
            self.S00, self.S11, self.S01 = acc(e0, w * v * v), acc(e1, w * u * u), \
                acc(e0, w * u * v)
            self.S0 = acc(e0, w * v) + acc(e1, w * u)
            self.Fe = np.stack([acc(e0, w * v * fc) + acc(e1, w * u * fc) for fc in f])
            # per cell, the sums that the moments of the term pairs need (see moments)
            self._sums = np.concatenate([self.S00 + self.S11, self.S01], axis=1)
            # per node, by the left node of a sample: the sums of the phi_d step
            self._phi_sums = np.concatenate(
                [self.S00, np.roll(self.S11, -1, axis=1), self.S01], axis=1)

    def moments(self, Cphi: NDArray | None) -> dict[str, Any]:
        """Return the sums over phi_d of w c_k c_l, w c_k f and w c_k per cell.

        Keys: "Wkl" (N_h, N_d, P), the pairs k <= l packed in the order of
        :func:`_pairs`, "Fk" (C, N_h, N_d, r), "Wk" (N_h, N_d, r); only {"plain": True}
        without a phi_d factor (c_k = 1, where the steps use W and F). The products
        c_k c_l of the hat interpolants are those of the nodes (S00 + S11) plus those of
        neighbouring nodes (S01), so one product of (cells, 2 n_phi) by (2 n_phi, P)
        gives every pair; the pairs are symmetric in k, l, hence only k <= l.
        """
        if Cphi is None:
            return {"plain": True}
        r, n = Cphi.shape
        iu, ju = _pairs(r)
        Cs = np.roll(Cphi, -1, axis=1)
        K = np.concatenate([Cphi[iu] * Cphi[ju], Cphi[iu] * Cs[ju] + Cphi[ju] * Cs[iu]],
                           axis=1)
        shape = self.W.shape
        return {"plain": False,
                "Wkl": (self._sums @ K.T).reshape(*shape, iu.size),
                "Fk": (self.Fe @ Cphi.T).reshape(-1, *shape, r),
                "Wk": (self.S0 @ Cphi.T).reshape(*shape, r)}


@functools.lru_cache(maxsize=64)
def _pairs(r: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Return the pairs (k, l), k <= l, of r terms: the packed order of symmetric blocks."""
    iu, ju = np.triu_indices(r)
    iu.setflags(write=False)
    ju.setflags(write=False)
    return iu, ju


def _unpack(x: NDArray, r: int) -> NDArray:
    """(..., P) packed pairs k <= l -> (..., r, r) symmetric."""
    iu, ju = _pairs(r)
    out = np.empty((*x.shape[:-1], r, r))
    out[..., iu, ju] = x
    out[..., ju, iu] = x
    return out


def _dense_hat(i0: NDArray, t: NDArray, n: int) -> NDArray:
    """(len(i0), n) matrix of the hat functions (the piecewise-linear interpolation)."""
    m = np.zeros((i0.size, n))
    rows = np.arange(i0.size)
    m[rows, i0] = 1.0 - t
    m[rows, i0 + 1] += t
    return m


def _side_step(prob: _Problem, mom: dict, side: str, G: NDArray, kd_free: bool, shared: bool,
               passive: list | None) -> tuple[NDArray, NDArray, list, float]:
    """Solve for the theta_h (side "h") or theta_d ("d") tables and kd, the rest fixed.

    G (C, N_other, r): the other side's factors at its nodes of the rule, times the term
    weights. The unknowns are ordered (node, term), so the normal matrix is block
    tridiagonal, plus one row and column per kd. Shared tables have one normal matrix and
    right-hand side, the sums over the channels, which are formed before the contractions
    with the moments (they are linear in them).
    """
    if side == "h":
        (i0, t), n = prob.hat_h, prob.n_h
        sub, sub_c, sub_w = "ijk,jk->ik", "cijk,cjk->ik", "ijk,cjk->cik"
    else:
        (i0, t), n = prob.hat_d, prob.n_d
        sub, sub_c, sub_w = "ijk,ik->jk", "cijk,cik->jk", "ijk,cik->cjk"
    C, _, r = G.shape
    iu, ju = _pairs(r)
    onehot = np.zeros((n, i0.size))
    onehot[i0, np.arange(i0.size)] = 1.0
    u = 1.0 - t
    gg = G[:, :, iu] * G[:, :, ju]  # (C, N_other, P)
    plain = mom["plain"]
    if plain:
        W = prob.W if side == "h" else prob.W.T
        F = prob.F if side == "h" else prob.F.transpose(0, 2, 1)
    else:
        Wkl, Fk, Wk = mom["Wkl"], mom["Fk"], mom["Wk"]

    def matrix(ggc: NDArray) -> NDArray:
        H = W @ ggc if plain else np.einsum(sub, Wkl, ggc)
        d = onehot @ np.concatenate([H * (u * u)[:, None], H * (t * t)[:, None],
                                     H * (u * t)[:, None]], axis=1)
        P = iu.size
        return _tridiag(n, r, _unpack(d[:, :P], r), _unpack(d[:, P:2 * P], r),
                        _unpack(d[:, 2 * P:], r), periodic=False)

    def spread(x: NDArray) -> NDArray:  # per sample (..., k) -> per node of its hats
        out = onehot @ (x * u[:, None])
        out[1:] += (onehot @ (x * t[:, None]))[:-1]
        return out.reshape(-1)

    Wg = W @ G if plain else np.einsum(sub_w, Wk, G)  # (C, N_side, r)
    kcs = [spread(x) / math.pi for x in Wg]
    if shared:
        R = sum(F[c] @ G[c] for c in range(C)) if plain else np.einsum(sub_c, Fk, G)
        blocks = [(matrix(gg.sum(axis=0)), spread(R), kcs[0])]
        blocks += [(0.0, 0.0, kc) for kc in kcs[1:]]
    else:
        blocks = []
        for c in range(C):
            R = F[c] @ G[c] if plain else np.einsum(sub, Fk[c], G[c])
            blocks.append((matrix(gg[c]), spread(R), kcs[c]))
    xs, kd, passive, value = _solve(blocks, n * r, shared, kd_free, prob.W0, prob.F0, passive)
    return np.stack([x.reshape(n, r).T for x in xs], axis=-1), kd, passive, value


def _terms(prob: _Problem, A: NDArray, B: NDArray, w: NDArray) -> NDArray:
    """X (r, C, N_h * N_d): w_kc A_k(theta_h) B_kc(theta_d) at the (theta_h, theta_d) nodes."""
    r, C = w.shape
    PA = np.broadcast_to(np.einsum("ia,kac->kci", prob.P, A), (r, C, prob.P.shape[0]))
    QB = np.broadcast_to(np.einsum("jb,kbc->kcj", prob.Q, B), (r, C, prob.Q.shape[0]))
    return (PA[:, :, :, None] * (QB * w[:, :, None])[:, :, None, :]).reshape(r, C, -1)


def _phi_step(prob: _Problem, X: NDArray, kd_free: bool, passive: list | None):
    """Solve for the phi_d tables C (r, n_phi), shared by the channels, and kd."""
    r, C, _ = X.shape
    n = prob.n_phi
    iu, ju = _pairs(r)
    P = iu.size
    XX = np.empty((P, X.shape[2]))  # the channels summed
    for p in range(P):  # pair by pair: X[iu] would copy X P times over
        np.einsum("cn,cn->n", X[iu[p]], X[ju[p]], out=XX[p])
    d = (XX @ prob._phi_sums).reshape(P, 3, n)
    M = _tridiag(n, r, _unpack(d[:, 0].T, r), _unpack(d[:, 1].T, r), _unpack(d[:, 2].T, r),
                 periodic=True)
    rhs = np.tensordot(prob.Fe, X, axes=([0, 1], [1, 2])).reshape(-1)
    blocks = [(M if c == 0 else 0.0, rhs if c == 0 else 0.0,
               (X[:, c] @ prob.S0).T.reshape(-1) / math.pi) for c in range(C)]
    xs, kd, passive, value = _solve(blocks, n * r, True, kd_free, prob.W0, prob.F0, passive)
    return xs[0].reshape(n, r).T, kd, passive, value


def _weights_step(prob: _Problem, mom: dict, A: NDArray, B: NDArray, kd_free: bool):
    """Solve for the per-channel term weights w (r, C) and kd, shared tables fixed."""
    PA = prob.P @ A[:, :, 0].T  # (N_h, r)
    QB = prob.Q @ B[:, :, 0].T  # (N_d, r)
    r = PA.shape[1]
    pq = (PA[:, None, :] * QB[None, :, :]).reshape(-1, r)  # (N_h N_d, r)
    if mom["plain"]:
        Wf = prob.W.reshape(-1)
        M = pq.T @ (pq * Wf[:, None])
        rhs = prob.F.reshape(prob.F.shape[0], -1) @ pq
        kcol = Wf @ pq
    else:
        Wkl = mom["Wkl"].reshape(pq.shape[0], -1)
        M = _unpack(np.array([np.einsum("n,n,n->", pq[:, k], pq[:, l], Wkl[:, p])
                              for p, (k, l) in enumerate(zip(*_pairs(r), strict=True))]), r)
        rhs = np.einsum("cnk,nk->ck", mom["Fk"].reshape(-1, pq.shape[0], r), pq)
        kcol = np.einsum("nk,nk->k", mom["Wk"].reshape(-1, r), pq)
    blocks = [(M, rhs[c], kcol / math.pi) for c in range(rhs.shape[0])]
    xs, kd, _, value = _solve(blocks, r, False, kd_free, prob.W0, prob.F0, None)
    return np.stack(xs, axis=1), kd, value


def _error(prob: _Problem, X: NDArray, Cphi: NDArray | None, kd: NDArray) -> NDArray:
    """(C,) sum of w (f - model)^2 over the rule, non-reciprocal part included.

    Without a phi_d factor: the phi_d floor plus the misfit of the cell means, with no
    cancellation (so an exact fit shows errors at rounding level); with one: point by point.
    """
    if Cphi is None:
        model = X.sum(axis=0).reshape(prob.Fb.shape) + (kd / math.pi)[:, None, None]
        return prob.floor + prob.anti + np.einsum("ij,cij->c", prob.W, (prob.Fb - model) ** 2)
    e0, e1, u = prob.phat
    cv = (Cphi[:, e0] * (1.0 - u) + Cphi[:, e1] * u).reshape(Cphi.shape[0], X.shape[2], -1)
    out = np.empty(kd.size)
    for c in range(kd.size):
        model = np.einsum("kn,knp->np", X[:, c], cv) + kd[c] / math.pi
        out[c] = np.einsum("np,np->", prob.w.reshape(model.shape),
                           (prob.f[c].reshape(model.shape) - model) ** 2)
    return out + prob.anti


def _quadratic(prob: _Problem, mom: dict, X: NDArray, kd: NDArray) -> float:
    """Sum of w (f - model)^2 from the moments of a phi_d factor (S - 2 cross + quad)."""
    r, C, N = X.shape
    k = kd / math.pi
    Fk = mom["Fk"].reshape(C, N, r)
    Wk = mom["Wk"].reshape(N, r)
    iu, ju = _pairs(r)
    Wkl = mom["Wkl"].reshape(N, iu.size)
    twice = np.where(iu == ju, 1.0, 2.0)  # the pairs k < l stand for (k, l) and (l, k)
    cross = k * prob.F0 + np.einsum("kcn,cnk->c", X, Fk)
    pairs = np.zeros(C)
    for p in range(iu.size):  # pair by pair: X[iu] would copy X P times over
        pairs += np.einsum("cn,cn,n->c", X[iu[p]], X[ju[p]], Wkl[:, p] * twice[p])
    quad = k * k * prob.W0 + 2 * k * np.einsum("kcn,nk->c", X, Wk) + pairs
    return float(np.sum(prob.S - 2 * cross + quad))


def _normalise(A: NDArray, B: NDArray, Cphi: NDArray | None, w: NDArray,
               weights_mode: bool) -> list[int]:
    """Rescale each term in place (C_k mean 1, A_k and B_k balanced); return dead terms."""
    dead = []
    for k in range(A.shape[0]):
        a, b = float(A[k].max()), float(B[k].max())
        c = 1.0 if Cphi is None else float(Cphi[k].mean())
        if a <= 0.0 or b <= 0.0 or c <= 0.0 or (weights_mode and float(w[k].max()) <= 0.0):
            dead.append(k)
            continue
        if Cphi is not None:
            Cphi[k] /= c
            A[k] *= c
            a *= c
        if weights_mode:
            A[k] /= a
            B[k] /= b
            w[k] *= a * b
        else:
            g = math.sqrt(a * b)
            A[k] *= g / a
            B[k] *= g / b
    return dead


def _nndsvd(prob: _Problem, rank: int, rng: np.random.Generator) -> NDArray:
    """(rank, n_d) non-negative start for the theta_d tables.

    NNDSVD of Boutsidis & Gallopoulos ("SVD based initialization: a head start for
    nonnegative matrix factorization", Pattern Recognition 41(4), 2008) applied to
    diag(sqrt(w_h)) F diag(sqrt(w_d)), F the phi_d-averaged values summed over channels and
    w_h, w_d the row and column sums of the weights; zeros are filled with small random
    numbers (their variant NNDSVDar).
    """
    X = prob.Fb.sum(axis=0)
    wh = np.sqrt(prob.W.sum(axis=1))
    wd = np.sqrt(prob.W.sum(axis=0))
    U, sv, Vt = np.linalg.svd(wh[:, None] * X * wd[None, :], full_matrices=False)
    t = np.arange(prob.n_d, dtype=np.float64)
    t_fine = prob.hat_d[0] + prob.hat_d[1]
    out = np.empty((rank, prob.n_d))
    for k in range(rank):
        if k >= sv.size or not sv[k] > 0:
            v = rng.random(wd.size)
        elif k == 0:
            v = np.abs(Vt[0])
        else:
            u, v = U[:, k], Vt[k]
            up, un, vp, vn = (np.maximum(x, 0.0) for x in (u, -u, v, -v))
            pos = np.linalg.norm(up) * np.linalg.norm(vp)
            v = vp if pos >= np.linalg.norm(un) * np.linalg.norm(vn) else vn
        v = np.where(wd > 0, v / np.where(wd > 0, wd, 1.0), 0.0)
        b = np.interp(t, t_fine, v)
        b = b / b.max() if b.max() > 0 else np.ones_like(b)
        small = b < 1e-3
        b[small] = 1e-3 * rng.random(int(small.sum())) + 1e-6
        out[k] = b
    return out


#: What fits inside :func:`reuse_samples` blocks share: (weak reference to the BRDF, key,
#: value) for its samples on a rule and the sums of a fit on them; None outside a block.
_SHARED: list[tuple[weakref.ref, tuple, Any]] | None = None
#: Entries kept: the rules of the default ladder of ``compress.select`` are at most four.
_SHARED_MAX = 8


@contextlib.contextmanager
def reuse_samples() -> Iterator[None]:
    """Within the block, fits of one BRDF object on one rule evaluate it there only once.

    :func:`fit_factored` evaluates the BRDF at every node of its rule
    (:func:`rusinkiewicz_rule`) and sums the values per table cell. The rule depends on
    the table nodes in theta_h and theta_d, ``warp``, ``warp_d``, ``samples`` and
    ``phi_turn`` -- not on the rank or the phi_d nodes -- so a ladder of ranks, as
    ``compress.select`` fits, needs only a few: inside the block the samples and sums of
    each are kept and reused, and the fits are the same bit for bit (``info["evaluations"]``
    is then 0). The BRDF must not change inside the block. Blocks nest.

    Examples
    --------
    >>> from project.models import CookTorrance
    >>> ct = CookTorrance(0.1, 0.2, "ggx", ior=1.5)
    >>> with reuse_samples():
    ...     one = fit_factored(ct, rank=1, bins=(16, 8))
    ...     two = fit_factored(ct, rank=2, bins=(16, 8))
    >>> one.info["evaluations"] > 0, two.info["evaluations"]
    (True, 0)
    """
    global _SHARED
    outer = _SHARED
    if outer is None:
        _SHARED = []
    try:
        yield
    finally:
        if outer is None:
            _SHARED = None


def _shared(brdf: Any, key: tuple) -> Any:
    """Return what a fit of ``brdf`` inside :func:`reuse_samples` kept under ``key``, or None."""
    for ref, k, value in _SHARED or ():
        if k == key and ref() is brdf:
            return value
    return None


def kept_for(brdf: Any, key: tuple, make: Callable[[], Any]) -> Any:
    """Return ``make()``, or inside :func:`reuse_samples` what it returned for ``brdf``.

    The store behind :func:`reuse_samples`, for every fit that evaluates one BRDF on one
    set of points (the factored fits here, the error pairs of :func:`project.fit_model`):
    ``key`` names the points; arrays kept are made read-only.
    """
    value = _shared(brdf, key)
    if value is not None:
        return value
    value = make()
    if _SHARED is not None:
        try:
            ref = weakref.ref(brdf)
        except TypeError:  # an object without weak references is not kept
            return value
        # read-only from here: a fit that wrote into shared arrays would change the next
        for x in (value.values() if isinstance(value, dict) else vars(value).values()):
            for a in (x if isinstance(x, tuple) else (x,)):
                if isinstance(a, np.ndarray):
                    a.setflags(write=False)
        _SHARED.append((ref, key, value))
        del _SHARED[:-_SHARED_MAX]
    return value


def fit_factored(brdf: Any, *, rank: int = 4, bins: tuple[int, ...] = (32, 24, 8),
                 warp: str = "cbrt", warp_d: str = "grazing", color: str = "weights",
                 samples: tuple[int, int, int] = (180, 64, 16), metric: str = "l2",
                 diffuse: bool = True, seed: int = 0, max_iter: int = 1000,
                 tol: float = 1e-6, accelerate: bool = True, phi_turn: str = "half",
                 ) -> FactoredLobe:
    """Fit a :class:`FactoredLobe` to a BRDF in the cosine-weighted L2 norm over H x H.

    The fit minimises the squared error of q = f cos(theta_i) cos(theta_o),

        E = int_H int_H (q - q_model)^2 d w_i d w_o,

    by non-negative alternating least squares on the values of ``brdf`` at the nodes of
    :func:`rusinkiewicz_rule`.

    Parameters
    ----------
    brdf : BRDF
        Any isotropic object with ``eval(wi, wo)`` and ``channels``: an analytic model or a
        :class:`~project.measured.MERLBRDF`. It must return finite values >= 0 above the
        horizon. With ``phi_turn="half"``, a non-reciprocal BRDF (``reciprocal`` False) is
        fitted by its reciprocal part (f(w_i, w_o) + f(w_o, w_i))/2 and the rest counts as
        error; with ``"full"`` f itself is fitted, in both orders.
    rank : int
        Number of product terms, >= 1.
    bins : (n_h, n_d) or (n_h, n_d, n_phi)
        Nodes of the tables: theta_h, theta_d and, if given, phi_d (each >= 2). Without
        n_phi the model has no phi_d factor (C_k = 1).
    warp : {"cbrt", "sqrt", "linear"}
        Spacing of the theta_h nodes (see :class:`FactoredLobe`).
    warp_d : {"grazing", "linear"}
        Spacing of the theta_d nodes: dense towards grazing, or uniform (see the module
        notes for what each costs).
    color : {"weights", "theta_d", "theta_h", "both"}
        Which factor carries the channels: ``"weights"`` one colour per term (shared
        tables), ``"theta_d"`` per-channel B_k, ``"theta_h"`` per-channel A_k, ``"both"``
        per-channel A_k and B_k (an independent fit per channel but for the shared C_k).
        The phi_d tables are always shared. Ignored for one channel.
    samples : (int, int, int)
        Resolution of the fitting rule (see :func:`rusinkiewicz_rule`): at least this many
        nodes in theta_h and theta_d, this many in phi_d per (theta_h, theta_d). With the
        default bins ``brdf`` is evaluated at 205,344 pairs; the errors of the module notes
        move by < 0.001 between rules of 51k and 1.6M pairs.
    metric : {"l2"}
        The error measured: the L2 norm of q above (the only one so far).
    diffuse : bool
        Fit kd (True) or fix it at 0.
    seed : int
        Seeds the small random values of the starting tables and of restarted terms.
    max_iter : int
        Most sweeps of the alternating iteration (each updates every block once).
    tol : float
        Stop when a sweep lowers E by less than ``tol`` times E.
    accelerate : bool
        Extrapolate along the last sweep when that lowers E (see Notes).
    phi_turn : {"half", "full"}
        The period of the phi_d tables (see :class:`FactoredLobe`): "half" (pi, reciprocal
        by construction) or "full" (2 pi: the lobe also holds the antisymmetric part of a
        non-reciprocal BRDF, which the half turn leaves as error). The n_phi nodes of
        ``bins`` span the period, so "full" with 2 n_phi nodes has the resolution in phi_d
        of "half" with n_phi (and twice its phi_d tables); "full" needs n_phi. The rule
        then also holds every pair exchanged (:func:`rusinkiewicz_rule`), at no more
        evaluations of a non-reciprocal ``brdf`` than "half" (which evaluates both orders
        to symmetrise), and twice as many for a reciprocal one.

    Returns
    -------
    FactoredLobe
        Its ``info`` holds ``error`` (relative L2 error sqrt(E / int q^2) on the rule, the
        channels summed), ``error_channels``, ``floor`` (the error of the best
        phi_d-independent function: no model without a phi_d factor can go below it),
        ``iterations``, ``converged``, ``seconds``, ``evaluations`` (of ``brdf.eval``; 0
        when an earlier fit's samples were reused, :func:`reuse_samples`), ``skipped``
        (the fraction of the weight at invalid MERL cells), ``reseeds``, ``dead_terms``,
        ``history`` (the relative error after each sweep) and
        ``antisymmetric`` (the relative L2 norm of the antisymmetric part
        (q(w_i, w_o) - q(w_o, w_i))/2 on the rule, the channels summed, as ``error``: the
        floor of a half-turn lobe; 0 when a half-turn fit is given a BRDF that says it is
        reciprocal, since its transpose is then not evaluated).

    Raises
    ------
    ValueError
        ``brdf.eval`` returns a negative, NaN or infinite value above the horizon (the
        message gives the angles), the BRDF is anisotropic or zero, or an argument is out of
        range.
    TypeError
        ``brdf`` has no ``eval``, or an argument has the wrong type.

    Warns
    -----
    RuntimeWarning
        The iteration did not meet ``tol`` within ``max_iter`` sweeps (with the error
        reached); the best tables found are returned.
    UserWarning
        ``brdf`` has delta terms, which are left out.

    Notes
    -----
    *The rule.* With the Jacobian d w_i d w_o = 4 cos(theta_d) sin(theta_h) sin(theta_d)
    d theta_h d phi_h d theta_d d phi_d (see :func:`rusinkiewicz_rule`), E is a weighted
    sum over the nodes with weights w = (rule weight) z_i^2 z_o^2. Configurations below the
    horizon are outside the rule. For a :class:`~project.measured.MERLBRDF`, nodes whose
    nearest MERL cell is invalid in any channel (NaN in ``table``) get weight 0: ``eval``
    would return the value of the nearest valid cell there, a guess, not a measurement
    (those cells are the ones at the horizon, where z_i z_o, hence the weight, is ~0).

    *The iteration.* Each block -- the theta_h tables (with kd), the theta_d tables (with
    kd), the colour weights and the phi_d tables (with kd) -- is a linear least-squares
    problem with non-negativity when the others are fixed; it is solved exactly by block
    principal pivoting (Kim & Park, SIAM J. Sci. Comput. 33(6), 2011) on its normal
    equations, which are block tridiagonal because each sample touches two nodes of a
    table. The phi_d sums per (theta_h, theta_d) are formed once, so a sweep costs
    O(N_h N_d rank^2), not O(samples). kd is solved with every block rather than taken as
    a floor: the minimum of the data is not the diffuse part (it is pulled down by
    shadowing and by invalid cells), and a kd fixed too low would cost a term. The theta_d
    tables start from NNDSVD (Boutsidis & Gallopoulos 2008) of the phi_d-averaged data; the
    phi_d tables start at 1 after the phi_d-free problem has converged to 1e-4. After
    30 plain sweeps per stage, each sweep is followed by an extrapolation
    x + beta (x - x_prev), projected to >= 0 and kept only if it lowers E, with beta doubled
    on success (up to 10) and halved on failure (Ang & Gillis, Neural Computation 31(2),
    2019). A term whose tables become zero is restarted from random tables (up to 4 times).
    The problem is not convex: the result is a local minimum; different ``seed`` or
    ``accelerate`` can end a few per cent (relative) apart.

    Examples
    --------
    >>> from project.models import CookTorrance
    >>> ct = CookTorrance(0.1, 0.2, "ggx", ior=1.5)
    >>> lobe = fit_factored(ct, rank=2, bins=(24, 16))
    >>> lobe
    FactoredLobe(rank=2, bins=(24, 16), warp='cbrt', warp_d='grazing', channels=1, nbytes=648)
    >>> bool(lobe.info["error"] < 0.04), lobe.info["converged"]
    (True, True)

    A non-reciprocal BRDF, f = (1 + 0.5 cos theta_i) / pi: the half turn stops at its
    antisymmetric part, the full turn fits it.

    >>> from project.brdf import BRDF
    >>> class Tilted(BRDF):
    ...     channels, isotropic, reciprocal = 1, True, False
    ...     def _eval(self, wi, wo):
    ...         return (1.0 + 0.5 * wi[:, 2:3]) / np.pi
    >>> half = fit_factored(Tilted(), rank=2, bins=(16, 8, 8))
    >>> full = fit_factored(Tilted(), rank=2, bins=(16, 8, 8), phi_turn="full")
    >>> round(half.info["antisymmetric"], 3), bool(half.info["error"] >= 0.0496)
    (0.05, True)
    >>> full.reciprocal, bool(full.info["error"] < 0.01)
    (False, True)
    """
    start = time.perf_counter()
    rank = nonneg_int(rank, "rank")
    if rank < 1:
        raise ValueError(f"rank must be >= 1, got {rank}")
    try:
        nb = tuple(nonneg_int(b, "bins") for b in bins)
    except TypeError:
        raise TypeError(f"bins must be a tuple (n_h, n_d) or (n_h, n_d, n_phi) of integers, "
                        f"got {bins!r}") from None
    if len(nb) not in (2, 3) or nb[0] < 2 or nb[1] < 2 or (len(nb) == 3 and nb[2] < 2):
        raise ValueError(f"bins must be (n_h, n_d) or (n_h, n_d, n_phi), each >= 2, got "
                         f"{bins!r}")
    n_h, n_d = nb[:2]
    n_phi = nb[2] if len(nb) == 3 else 0
    full = PHI_TURNS[choice(phi_turn, "phi_turn", tuple(PHI_TURNS))] == 1.0
    if full and not n_phi:
        raise ValueError(f"phi_turn 'full' needs a phi_d factor: bins must be (n_h, n_d, "
                         f"n_phi), got {bins!r}")
    power = WARPS[choice(warp, "warp", tuple(WARPS))]
    power_d = D_WARPS[choice(warp_d, "warp_d", tuple(D_WARPS))]
    choice(color, "color", COLORS)
    choice(metric, "metric", _METRICS)
    samples = _samples(samples)
    max_iter = nonneg_int(max_iter, "max_iter")
    if max_iter < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    if not (isinstance(tol, (int, float)) and 0 <= tol < 1):
        raise ValueError(f"tol must be a number in [0, 1), got {tol!r}")
    if not callable(getattr(brdf, "eval", None)):
        raise TypeError(f"brdf must have an eval(wi, wo) method, got {type(brdf).__name__}")
    if getattr(brdf, "isotropic", True) is False:
        raise ValueError(f"brdf must be isotropic (a FactoredLobe is), got the anisotropic "
                         f"{brdf!r}")
    if getattr(brdf, "delta", ()):
        warnings.warn(f"{brdf!r} has ideal mirror (delta) terms, which a FactoredLobe cannot "
                      "hold; they are left out of the fit", UserWarning, stacklevel=2)
    C = nonneg_int(getattr(brdf, "channels", 1), "brdf.channels")
    scalar = C == 1 and np.ndim(brdf.eval([0.0, 0.0, 1.0], [0.0, 0.0, 1.0])) == 0

    th, td, phi, wq, s, t = _rule((n_h, n_d), power, power_d, samples, full)
    check_bytes(8.0 * phi.size * (C + 8), f"fitting on a rule of {phi.size} points")
    rule = (n_h, n_d, power, power_d, samples, full, C)
    reused = _shared(brdf, rule) is not None
    data = kept_for(brdf, rule, lambda: _sample(brdf, th, td, phi, wq, C, full))
    if not data["S"].sum() > 0:
        raise ValueError(f"brdf must not vanish on the upper hemisphere, got {brdf!r} = 0 "
                         "at every node of the rule")
    prob = kept_for(brdf, (*rule, n_phi), lambda: _Problem(
        data, phi, s, t, (n_h, n_d), n_phi, 2.0 * math.pi if full else math.pi))

    # the steps multiply small matrices (cells x nodes x rank^2): BLAS threads only add
    # synchronisation, and cost 5-10x when another process holds a core (rank 2, bins
    # (32, 24, 16), 2 cores, one busy: 25 s with two OpenBLAS threads, 3.8 s with one)
    with threadpool_limits(1, user_api="blas"):
        rng = np.random.default_rng(seed)
        CA = C if color in ("theta_h", "both") else 1
        CB = C if color in ("theta_d", "both") else 1
        weights_mode = color == "weights" and C > 1
        B = np.repeat(_nndsvd(prob, rank, rng)[:, :, None], CB, axis=2)
        A = np.zeros((rank, n_h, CA))
        w = np.ones((rank, C))
        kd = np.zeros(C)
        Cphi: NDArray | None = None
        history: list[float] = []
        reseeds = 0
        iterations = 0
        converged = False
        dead: list[int] = []
        stages = [False] + ([True] if n_phi else [])
        s_tot = float(prob.S.sum())
        for phi_active in stages:
            if phi_active:
                Cphi = np.ones((rank, n_phi))
            budget = max_iter - iterations if phi_active or not n_phi else max(1, max_iter // 2)
            # with a phi_d factor to come, the phi_d-free stage is only its starting point
            stage_tol = tol if phi_active or not n_phi else max(tol, 1e-4)
            mom = prob.moments(Cphi)
            pa = pb = pc = None
            last = math.inf
            converged = False
            prev = None
            beta = _BETA[0]
            for it_stage in range(budget):
                iterations += 1
                if mom is None:
                    mom = prob.moments(Cphi)
                G = np.stack([(prob.Q @ B[:, :, min(c, CB - 1)].T) * w[:, c] for c in range(C)])
                A, kd, pa, value = _side_step(prob, mom, "h", G, diffuse, CA == 1, pa)
                G = np.stack([(prob.P @ A[:, :, min(c, CA - 1)].T) * w[:, c] for c in range(C)])
                B, kd, pb, value = _side_step(prob, mom, "d", G, diffuse, CB == 1, pb)
                if weights_mode:
                    w, kd, value = _weights_step(prob, mom, A, B, diffuse)
                if phi_active:
                    Cphi, kd, pc, value = _phi_step(prob, _terms(prob, A, B, w), diffuse, pc)
                dead = _normalise(A, B, Cphi, w, weights_mode)
                for k in dead:
                    A[k] = 0.0
                    if reseeds < _RESEEDS:  # restart a term that died from a random theta_d table
                        reseeds += 1
                        B[k] = 0.1 + rng.random(B[k].shape)
                        w[k] = 1.0
                        if Cphi is not None:
                            Cphi[k] = 1.0
                        pa = pb = pc = None
                    else:
                        B[k] = 0.0
                if phi_active:
                    # the moments of the new phi_d tables are formed when the next sweep
                    # needs them, unless the extrapolation below is kept and brings its own
                    mom = None
                    # the value of the last solve is the squared error less sum w f^2
                    err = max(s_tot + value, 0.0)
                else:
                    err = float(_error(prob, _terms(prob, A, B, w), None, kd).sum())
                if accelerate and prev is not None and not dead and it_stage > _WAIT:
                    # extrapolate along the last sweep (Ang & Gillis 2019), keep it if it helps
                    y = [np.maximum(x + beta * (x - x0), 0.0) if x is not None else None
                         for x, x0 in zip((A, B, Cphi, w, kd), prev, strict=True)]
                    if not _normalise(y[0], y[1], y[2], y[3], weights_mode):
                        Xy = _terms(prob, y[0], y[1], y[3])
                        if phi_active:
                            mom_y = prob.moments(y[2])
                            err_y = max(_quadratic(prob, mom_y, Xy, y[4]), 0.0)
                        else:
                            err_y = float(_error(prob, Xy, None, y[4]).sum())
                        if err_y < err:
                            A, B, Cphi, w, kd = y
                            err = err_y
                            if phi_active:
                                mom = mom_y
                            beta = min(_BETA[2], _BETA[1] * beta)
                        else:
                            beta = max(0.05, 0.5 * beta)
                prev = tuple(None if x is None else x.copy() for x in (A, B, Cphi, w, kd))
                history.append(err)
                if err <= 1e-26 * s_tot or (
                        not dead and last < math.inf and last - err <= stage_tol * last):
                    converged = True
                    break
                last = err
        e_c = _error(prob, _terms(prob, A, B, w), Cphi, kd)
    S = prob.S
    rel = math.sqrt(float(e_c.sum() / S.sum()))
    info = {
        "error": rel,
        "error_channels": np.sqrt(e_c / np.where(S > 0, S, 1.0)),
        "floor": math.sqrt(float((prob.floor + prob.anti).sum() / S.sum())),
        "iterations": iterations,
        "converged": converged,
        "seconds": time.perf_counter() - start,
        "evaluations": 0 if reused else data["evaluations"],
        "skipped": data["skipped"],
        "reseeds": reseeds,
        "dead_terms": len(dead),
        "history": np.sqrt(np.array(history) / float(S.sum())),
        "antisymmetric": math.sqrt(float(data["antisymmetric"].sum() / S.sum())),
    }
    if not converged:
        dec = (history[-2] - history[-1]) / history[-2] if len(history) > 1 else float("nan")
        warnings.warn(f"fit_factored did not converge in max_iter = {max_iter} iterations: "
                      f"relative L2 error {rel:.4g}, last relative decrease of the squared "
                      f"error {dec:.3g} > tol = {tol:g}", RuntimeWarning, stacklevel=2)
    if scalar:
        return FactoredLobe(float(kd[0]), A[:, :, 0], B[:, :, 0], phi_table=Cphi, warp=warp,
                            warp_d=warp_d, phi_turn=phi_turn, info=info)
    return FactoredLobe(kd, A, B, phi_table=Cphi, weights=w if weights_mode else None,
                        warp=warp, warp_d=warp_d, phi_turn=phi_turn, info=info)
