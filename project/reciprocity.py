r"""How far a BRDF, or a set of measurements, is from reciprocity f(w_i, w_o) = f(w_o, w_i).

Analytic models obey Helmholtz reciprocity by construction; measured BRDFs do not: the
light and the sensor of a gonio-photometer are different instruments, and the tables are
interpolated in the incidence direction, not symmetrically. A reciprocal representation
(a symmetric coefficient matrix, a microfacet model) cannot come closer to such data than
their antisymmetric part. :func:`reciprocity` measures that part and returns a
:class:`Reciprocity`: the relative distance between q and its transpose (``residual``),
the lower bound it sets on the error of any reciprocal representation (``floor``), where
in (theta_i, theta_o) it lives (``bands``) and per channel (``channels``).

Notes
-----
**Definitions.** With q(w_i, w_o) = f(w_i, w_o) cos theta_i cos theta_o (the quantity the
library projects) and the norm of L2(H x H) in solid angle,

    residual = ||q - q^T|| / ||q||,    floor = ||(q - q^T) / 2|| / ||q|| = residual / 2,

with q^T(w_i, w_o) = q(w_o, w_i), the largest over the channels. Both are reported: the
residual is the number usually quoted for measured data, the floor the one that bounds the
error of a representation (see :func:`reciprocity` for the proof).

**Estimates for a BRDF.** The integrals are Monte Carlo estimates on
:func:`project.sampling.peak_resolving_pairs` (half the pairs about the mirror direction,
which is mapped to itself by the exchange w_i <-> w_o, so the peak of f and of f^T are both
resolved). Each pair is evaluated in both orders and the estimates use the swap-closed set
of :func:`symmetrized_pairs` (every pair and its exchange, each with half the weight; the
density of the pairs is symmetric, so this is unbiased too). On that set the symmetric and
antisymmetric parts are orthogonal exactly, not only in expectation, so the estimated floor
is a lower bound for the error, estimated on the same pairs, of every reciprocal BRDF. The
standard errors come from the independent replicates of the pairs
(:mod:`project.sampling`, delta method for the ratio).

**Estimates for measurements.** Only samples whose reciprocal twin was measured too (within
``tol_deg`` per direction, up to a rotation and mirroring about the normal for isotropic
data: :func:`project.measurements.reciprocal_matches`) say anything about reciprocity. Each
matched sample i is compared with its nearest twin j: residual^2 =
sum_i w_i (q_i - q_j)^2 / sum_i w_i q_i^2 over the matched samples, with their weights, so
the estimate covers the configurations that were measured in both orders, not all of
H x H. Samples linked by twins form independent groups (connected components), and the
standard error is the delta-method standard error of that ratio over the groups (as in
:mod:`project.crossval`). On a swap-closed grid whose twins have equal weights (e.g. a
product quadrature rule) the sums are the quadrature of the integrals above and the floor
is again an exact lower bound on the samples; with unequal twin weights it is one up to the
difference between the arithmetic and harmonic means of the twin weights. When no sample
has a twin the residual is NaN, ``matched`` is 0 and ``note`` says why: gonio tables
measured at a few incidence angles with theta_o on another grid have no reciprocal pairs.

**Measured values** (n = 2**16 pairs, seed 0, bands of max(theta_i, theta_o) 0-30-60-75-90
degrees; RGL-EPFL files, Dupuy & Jakob 2018, read with :func:`project.measured.read_rgl`;
"floor below" is the floor over the pairs with both angles below 30 / 60 / 75 degrees, the
largest over the channels; "share" is the fraction of the antisymmetric energy with one
angle beyond 75 degrees, in the worst channel; standard errors about 0.4 % of the residual):

==========================  ========================  ======  ===================  =====
file                        residual R, G, B          floor   floor below          share
                                                              30 / 60 / 75 deg     >75
==========================  ========================  ======  ===================  =====
paper_white_rgb.bsdf        0.0446, 0.0437, 0.0429    0.0223  0.012 0.012 0.012    0.71
colodur_napoli_4f_rgb.bsdf  0.0695, 0.1047, 0.0973    0.0524  0.023 0.018 0.025    0.81
vch_golden_yellow_rgb.bsdf  0.1004, 0.1015, 0.1765    0.0882  0.173 0.115 0.055    0.87
==========================  ========================  ======  ===================  =====

For the white paper and the matte paint most of the antisymmetric part lies where one of
the directions is beyond 75 degrees, and a representation limited to angles below 60
degrees is bound by a floor 2 to 3 times lower (0.012 and 0.018 instead of 0.022 and
0.052). The glossy vinyl film differs by channel: its worst channel (blue, where the film
reflects little) has 87 % of its antisymmetric energy beyond 75 degrees but a floor of
0.17 near the normal, relative to its small q there; in red and green (residual 0.10,
floor 0.05) 55 % and 48 % of the antisymmetric energy lies below 30 degrees, in the
specular peak, and the floor below 30 degrees (0.058, 0.057) is no lower than overall.

References
----------
- J. Dupuy and W. Jakob, "An adaptive parameterization for efficient material acquisition
  and rendering", ACM TOG 37(6), 2018.
- H. von Helmholtz, Handbuch der physiologischen Optik, 1856, p. 169; F. E. Nicodemus et
  al., "Geometrical considerations and nomenclature for reflectance", NBS Monograph 160,
  1977 (reciprocity of the BRDF).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_array
from scipy.sparse.csgraph import connected_components

from basis.validation import nonneg_int

from .crossval import _ratio_and_stderr
from .measurements import RECIPROCAL_TOL_DEG, Measurements, reciprocal_matches
from .sampling import PairSamples, _l2_with_stderr, _values, peak_resolving_pairs

__all__ = ["DEFAULT_BANDS", "MIN_PAIRS", "Reciprocity", "reciprocity", "symmetrized_pairs"]

#: Default band edges (degrees) of max(theta_i, theta_o) for :attr:`Reciprocity.bands`.
DEFAULT_BANDS = (0.0, 30.0, 60.0, 75.0, 90.0)
#: Fewest pairs :func:`reciprocity` accepts for a BRDF (16 replicates of 32 pairs).
MIN_PAIRS = 512


@dataclass(frozen=True, eq=False)
class Reciprocity:
    """How far a BRDF or a set of measurements is from reciprocity (see :func:`reciprocity`).

    Attributes
    ----------
    residual : float
        ||q - q^T|| / ||q||, the largest over the channels; NaN when nothing was matched.
    residual_stderr : float
        Its standard error (NaN when it cannot be estimated: fewer than two groups).
    matched : int
        Pairs the estimate rests on: the pairs drawn (each evaluated in both orders) for a
        BRDF, the samples with a reciprocal twin for measurements.
    bands : tuple of dict
        One dict per band of max(theta_i, theta_o), in order, with ``theta_deg``
        ([low, high] in degrees; a pair is in the band when low <= max < high, the last band
        closed), ``pairs`` (how many matched pairs fall in it), ``share`` (its fraction of
        the antisymmetric energy sum w (q - q^T)^2, in the channel of :attr:`floor`; the
        shares sum to 1), ``floor_band`` (the floor over the pairs of the band alone) and
        ``floor_below`` with ``floor_below_stderr`` (the floor over the pairs with both
        angles below ``high``: what a representation restricted to those angles is bound
        by). Floors are the largest over the channels; NaN where a band holds no energy.
    channels : tuple of dict
        Per channel: ``name``, ``residual``, ``residual_stderr``, ``floor``,
        ``floor_stderr``.
    samples : str
        How the pairs were drawn or matched.
    source : str
        ``repr`` of what was measured.
    note : str
        Why there is no estimate, or what it covers; "" when nothing needs saying.
    tol_deg : float or None
        Matching tolerance (degrees, per direction) for measurements; None for a BRDF.
    """

    residual: float
    residual_stderr: float
    matched: int
    bands: tuple[dict[str, Any], ...]
    channels: tuple[dict[str, Any], ...]
    samples: str
    source: str
    note: str = ""
    tol_deg: float | None = None

    @property
    def floor(self) -> float:
        """||(q - q^T) / 2|| / ||q|| = residual / 2: no reciprocal q comes closer to q."""
        return self.residual / 2.0

    @property
    def floor_stderr(self) -> float:
        """Standard error of :attr:`floor` (half that of :attr:`residual`)."""
        return self.residual_stderr / 2.0

    def reciprocal_within(self, tol: float, *, sigmas: float = 2.0) -> bool:
        """Return whether the residual is at most ``tol``, ``sigmas`` standard errors spared.

        True when ``residual + sigmas * residual_stderr <= tol``; False when the standard
        error is unknown (NaN) and ``sigmas`` > 0.

        Raises
        ------
        ValueError
            ``tol`` or ``sigmas`` is not finite and >= 0, or there is no estimate
            (``matched == 0``): the data cannot tell.
        """
        t, s = _nonneg_real(tol, "tol"), _nonneg_real(sigmas, "sigmas")
        if self.matched == 0 or not math.isfinite(self.residual):
            raise ValueError(f"reciprocity is unknown: {self.note}")
        return bool(self.residual + (s * self.residual_stderr if s > 0 else 0.0) <= t)

    def describe(self) -> dict[str, Any]:
        """Return a JSON-able dict of the result (NaN as None) for a report."""
        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        def row(d: dict[str, Any]) -> dict[str, Any]:
            return {k: num(v) if isinstance(v, float) else v for k, v in d.items()}

        return {"residual": num(self.residual), "residual_stderr": num(self.residual_stderr),
                "floor": num(self.floor), "floor_stderr": num(self.floor_stderr),
                "matched": self.matched, "tol_deg": self.tol_deg,
                "bands": [row(b) for b in self.bands],
                "channels": [row(c) for c in self.channels],
                "samples": self.samples, "source": self.source, "note": self.note}

    def __repr__(self) -> str:
        if self.matched == 0 or not math.isfinite(self.residual):
            return f"Reciprocity(no estimate: {self.note}; source={self.source})"
        return (f"Reciprocity(residual={self.residual:.4g} +- {self.residual_stderr:.2g}, "
                f"floor={self.floor:.4g}, matched={self.matched}, source={self.source})")


def reciprocity(source: object, *, n: int = 2**16, seed: int = 0,
                bands: Sequence[float] = DEFAULT_BANDS, tol_deg: float = RECIPROCAL_TOL_DEG,
                isotropic: bool | None = None) -> Reciprocity:
    """Measure how far a BRDF or a set of measurements is from reciprocity.

    Parameters
    ----------
    source : BRDF or project.Measurements
        A BRDF (any object with ``eval(wi, wo)``; its ``reciprocal`` flag is not trusted,
        the values are compared; ideal mirror terms in ``delta``, reciprocal by
        construction, are left out), or scattered measurements.
    n : int
        Pairs drawn for a BRDF (>= :data:`MIN_PAIRS`); ignored for measurements.
    seed : int
        Seed of the pairs (:func:`project.sampling.peak_resolving_pairs`).
    bands : sequence of float
        Band edges of max(theta_i, theta_o) in degrees: strictly increasing from 0 to 90.
    tol_deg : float
        Measurements: angular tolerance (degrees, per direction) within which a sample
        counts as the reciprocal twin of another. Ignored for a BRDF.
    isotropic : bool or None
        Measurements: match twins up to a rotation and mirroring about the normal. Default:
        what the measurements state, strict matching when they do not say.

    Returns
    -------
    Reciprocity

    Raises
    ------
    TypeError
        ``source`` is neither a BRDF nor measurements; an argument of the wrong kind.
    ValueError
        ``n`` too small, ``bands`` not increasing from 0 to 90, ``tol_deg`` negative, the
        BRDF is 0 at every pair (the relative residual is undefined) or returns NaN.

    Notes
    -----
    **The floor is a lower bound.** Let T be the exchange (T q)(w_i, w_o) = q(w_o, w_i) on
    L2(H x H) with the solid-angle measure mu x mu, which T preserves; so T is an isometry,
    T^2 = 1, and <T a, b> = <a, T b>. Write q = s + a with s = (q + T q) / 2 (symmetric)
    and a = (q - T q) / 2 (antisymmetric). Then <s, a> = <T s, T a> = <s, -a>, so
    <s, a> = 0. A BRDF g is reciprocal exactly when its q_g = g cos theta_i cos theta_o is
    symmetric (cos theta_i cos theta_o is), and then <q_g - s, a> = 0 in the same way, so

        ||q - q_g||^2 = ||(s - q_g) + a||^2 = ||s - q_g||^2 + ||a||^2 >= ||a||^2,

    with equality if and only if q_g = s. The best reciprocal approximation is the
    symmetric part, and the relative error of any reciprocal one is >= ||a|| / ||q|| =
    floor. Since q - T q = 2 a, residual = 2 floor for the integrals and for every estimate
    here (both are sums of the same terms); the two are reported because the residual is
    the customary measure of (non-)reciprocity and the floor the bound on representations.
    The same argument holds for any measure invariant under T, in particular the swap-closed
    pair sets used for the estimates (module notes), and for the restriction to pairs with
    both angles below an edge (a set T maps to itself), which gives ``floor_below``.

    Examples
    --------
    >>> from project.models import CookTorrance
    >>> r = reciprocity(CookTorrance(0.2, 0.3), n=4096)
    >>> r.residual < 1e-12, r.reciprocal_within(1e-9)
    (True, True)
    """
    edges = _edges(bands)
    if isinstance(source, Measurements):
        tol = _nonneg_real(tol_deg, "tol_deg")
        if isotropic is not None and not isinstance(isotropic, (bool, np.bool_)):
            raise TypeError(f"isotropic must be True, False or None, got {isotropic!r}")
        return _from_measurements(source, edges, tol, isotropic)
    if not callable(getattr(source, "eval", None)):
        raise TypeError("source must be a BRDF (an object with eval(wi, wo)) or a "
                        f"project.Measurements, got {type(source).__name__}")
    count = nonneg_int(n, "n")
    if count < MIN_PAIRS:
        raise ValueError(f"n must be >= {MIN_PAIRS} (16 replicates of 32 pairs give the "
                         f"standard errors), got {count}")
    _nonneg_real(tol_deg, "tol_deg")
    return _from_brdf(source, edges, count, seed)


def symmetrized_pairs(samples: PairSamples) -> PairSamples:
    """Return the swap-closed set: every pair and its exchange, each with half the weight.

    For a measure invariant under the exchange (as that of
    :func:`project.sampling.peak_resolving_pairs`, whose pair density is symmetric) the
    weighted sums stay unbiased estimates of the integrals over H x H, and the symmetric and
    antisymmetric parts of any function are orthogonal in the estimate too. Replicates are
    kept, so the standard errors of :mod:`project.sampling` apply.

    Parameters
    ----------
    samples : PairSamples

    Returns
    -------
    PairSamples
        ``2 len(samples)`` pairs: the original ones, then the exchanged ones.

    Examples
    --------
    >>> s = symmetrized_pairs(peak_resolving_pairs(1024))
    >>> half = len(s) // 2
    >>> len(s) == 2 * len(peak_resolving_pairs(1024))
    True
    >>> bool(np.array_equal(s.wi[:half], s.wo[half:]) and np.array_equal(s.wo[:half], s.wi[half:]))
    True
    """
    if not isinstance(samples, PairSamples):
        raise TypeError(f"samples must be a PairSamples (from peak_resolving_pairs), got "
                        f"{type(samples).__name__}")
    w = samples.weights / 2.0
    return PairSamples(wi=np.concatenate([samples.wi, samples.wo]),
                       wo=np.concatenate([samples.wo, samples.wi]),
                       weights=np.concatenate([w, w]),
                       replicate=np.concatenate([samples.replicate, samples.replicate]),
                       replicates=samples.replicates, draws=samples.draws,
                       description=f"{samples.description}; each pair also exchanged "
                                   "(w_i <-> w_o), half weight each")


# -- BRDF --------------------------------------------------------------------------------------
def _from_brdf(brdf: Any, edges: NDArray, n: int, seed: int) -> Reciprocity:
    base = peak_resolving_pairs(n, seed=seed)
    pairs = len(base)
    f = _values(brdf.eval(base.wi, base.wo), "source.eval(wi, wo)", pairs)
    ft = _values(brdf.eval(base.wo, base.wi), "source.eval(wo, wi)", pairs)
    s = symmetrized_pairs(base)
    cc = (s.wi[:, 2] * s.wo[:, 2])[:, None]
    q = np.concatenate([f, ft]) * cc
    qt = np.concatenate([ft, f]) * cc
    mid = 0.5 * (q + qt)

    def floor(mask: NDArray) -> tuple[NDArray, NDArray]:
        """Per-channel floor (and standard error) over the pairs of ``mask``."""
        qm = q * mask[:, None]
        if not np.all(np.sum(s.weights[:, None] * qm * qm, axis=0) > 0.0):
            nan = np.full(q.shape[1], np.nan)
            return nan, nan
        return _l2_with_stderr(qm, mid * mask[:, None], s)

    res, res_se = _l2_with_stderr(q, qt, s)
    return _result(res, res_se, pairs, q, qt, s.weights, s.wi, s.wo, edges, floor,
                   _channel_names(brdf, q.shape[1]), s.description, repr(brdf), "", None)


# -- measurements ------------------------------------------------------------------------------
def _from_measurements(meas: Measurements, edges: NDArray, tol: float,
                       isotropic: bool | None) -> Reciprocity:
    iso = bool(meas.isotropic) if isotropic is None else bool(isotropic)
    wi, wo, w = meas.wi, meas.wo, meas.weights
    pairs = reciprocal_matches(wi, wo, tol, iso)
    first = np.ones(pairs.shape[0], dtype=bool)
    first[1:] = pairs[1:, 0] != pairs[:-1, 0]  # rows are sorted by i, nearest twin first
    i, j = pairs[first, 0], pairs[first, 1]
    how = (f"within {tol:g} deg per direction"
           + (", up to rotation and mirroring about the normal" if iso else ""))
    names = meas.channel_names
    if i.size == 0:
        note = (f"no sample has a reciprocal twin {how}, so the data cannot show how "
                "reciprocal the material is (gonio tables measured at a few incidence angles "
                "with theta_o on another grid have no reciprocal pairs)")
        if not iso and len(meas):
            k = np.unique(reciprocal_matches(wi, wo, tol, True)[:, 0]).size
            if k:
                note += (f"; {k} samples have a twin up to rotation and mirroring about the "
                         "normal: pass isotropic=True if the material is isotropic")
        nan = float("nan")
        bands = tuple({"theta_deg": [float(a), float(b)], "pairs": 0, "share": nan,
                       "floor_band": nan, "floor_below": nan, "floor_below_stderr": nan}
                      for a, b in zip(edges[:-1], edges[1:], strict=True))
        chans = tuple({"name": c, "residual": nan, "residual_stderr": nan, "floor": nan,
                       "floor_stderr": nan} for c in names)
        return Reciprocity(nan, nan, 0, bands, chans, f"0 of {len(meas)} samples matched "
                           f"{how}", _source_repr(meas), note, tol)
    cc_i = (wi[i, 2] * wo[i, 2])[:, None]
    cc_j = (wi[j, 2] * wo[j, 2])[:, None]
    q = meas.values[i] * cc_i
    qt = meas.values[j] * cc_j
    wm = w[i]
    if not np.all(np.sum(wm[:, None] * q * q, axis=0) > 0.0):
        c = int(np.flatnonzero(np.sum(wm[:, None] * q * q, axis=0) <= 0.0)[0])
        raise ValueError(f"measurements must not be 0 (or of weight 0) at every matched sample "
                         f"of channel {names[c]!r}: the relative residual is undefined")
    # samples linked by twins are one group: independent replicates for the standard errors
    graph = coo_array((np.ones(i.size), (i, j)), shape=(len(meas), len(meas)))
    _, label = connected_components(graph, directed=False)
    _, group = np.unique(label[i], return_inverse=True)
    groups = int(group.max()) + 1

    def sums(terms: NDArray) -> NDArray:
        out = np.zeros((groups, terms.shape[1]))
        np.add.at(out, group, terms)
        return out

    den_all = wm[:, None] * q * q
    num_all = wm[:, None] * (q - qt) ** 2

    def floor(mask: NDArray) -> tuple[NDArray, NDArray]:
        den = sums(den_all * mask[:, None])
        if not np.all(den.sum(axis=0) > 0.0):
            nan = np.full(q.shape[1], np.nan)
            return nan, nan
        return _ratio_and_stderr(sums(num_all * mask[:, None] / 4.0), den)

    res, res_se = _ratio_and_stderr(sums(num_all), sums(den_all))
    n = len(meas)
    desc = (f"{i.size} of {n} samples matched to a reciprocal twin {how} "
            f"({groups} independent groups)")
    note = "" if i.size == n else (f"the estimate covers the {i.size} samples measured in both "
                                  f"orders, not the other {n - i.size}")
    return _result(res, res_se, int(i.size), q, qt, wm, wi[i], wo[i], edges, floor,
                   names, desc, _source_repr(meas), note, tol)


# -- shared ------------------------------------------------------------------------------------
def _result(res: NDArray, res_se: NDArray, matched: int, q: NDArray, qt: NDArray,
            w: NDArray, wi: NDArray, wo: NDArray, edges: NDArray, floor: Any,
            names: Sequence[str], samples: str, source: str, note: str,
            tol: float | None) -> Reciprocity:
    """Assemble a :class:`Reciprocity` from per-channel residuals and the pair terms."""
    worst = int(np.argmax(res))
    per = 2 if tol is None else 1  # a BRDF's pairs come in both orders: count each once
    top = np.degrees(np.arccos(np.clip(np.minimum(wi[:, 2], wo[:, 2]), 0.0, 1.0)))
    anti = w * (q[:, worst] - qt[:, worst]) ** 2
    total = float(anti.sum())
    bands = []
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
        last = k == len(edges) - 2
        inside = (top >= lo) & ((top <= hi) if last else (top < hi))
        below = top <= hi if last else top < hi
        fb, _ = floor(inside)
        fl, fl_se = floor(below)
        bands.append({"theta_deg": [float(lo), float(hi)], "pairs": int(inside.sum()) // per,
                      "share": float(anti[inside].sum() / total) if total > 0 else float("nan"),
                      "floor_band": _max(fb), "floor_below": _max(fl),
                      "floor_below_stderr": float(fl_se[int(np.argmax(fl))])
                      if np.any(np.isfinite(fl)) else float("nan")})
    chans = tuple({"name": str(c), "residual": float(r), "residual_stderr": float(e),
                   "floor": float(r) / 2.0, "floor_stderr": float(e) / 2.0}
                  for c, r, e in zip(names, res, res_se, strict=True))
    return Reciprocity(float(res[worst]), float(res_se[worst]), matched, tuple(bands), chans,
                       samples, source, note, tol)


def _max(x: NDArray) -> float:
    return float(np.max(x)) if np.all(np.isfinite(x)) else float("nan")


def _channel_names(brdf: Any, channels: int) -> tuple[str, ...]:
    names = getattr(brdf, "channel_names", None)
    if names is not None and len(names) == channels:
        return tuple(str(c) for c in names)
    return ("R", "G", "B") if channels == 3 else tuple(str(c) for c in range(channels))


def _source_repr(meas: Measurements) -> str:
    where = "" if meas.source is None else f" from {str(meas.source)!r}"
    return f"{meas!r}{where}"


def _nonneg_real(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and v >= 0.0):
        raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
    return v


def _edges(bands: object) -> NDArray[np.float64]:
    if isinstance(bands, (str, bytes)) or not hasattr(bands, "__iter__"):
        raise TypeError(f"bands must be a sequence of band edges in degrees, got {bands!r}")
    vals = list(bands)  # type: ignore[call-overload]
    if not all(isinstance(b, numbers.Real) and not isinstance(b, bool) for b in vals):
        raise TypeError(f"bands must be a sequence of band edges in degrees, got {bands!r}")
    e = np.asarray(vals, dtype=np.float64)
    if (e.size < 2 or not np.all(np.isfinite(e)) or e[0] != 0.0 or e[-1] != 90.0
            or np.any(np.diff(e) <= 0.0)):
        raise ValueError("bands must be strictly increasing edges from 0 to 90 degrees, got "
                         f"{vals!r}")
    return e
