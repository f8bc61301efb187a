"""Error measurement that resolves specular peaks: importance-sampled pairs and error metrics.

Errors of approximations to sharp specular BRDFs come out wrong on a fixed product grid of
(w_i, w_o): the grid either puts nodes exactly on the mirror configuration (where a narrow
lobe is largest, so the error is overstated) or steps over the peak (understated). Here the
integrals over H x H that define the errors are Monte Carlo estimates from pairs
concentrated around the mirror direction as well as spread uniformly, with weights that keep
them unbiased and with a standard error for the estimate.

- :func:`peak_resolving_pairs` draws the pairs (:class:`PairSamples`).
- :func:`relative_l2` and :func:`log_rms` turn BRDF values at the pairs into errors.
- :func:`brdf_errors` evaluates two BRDFs once and returns both errors and the standard
  error of the l2 estimate.

Notes
-----
**Sampling.** w_i is uniform in solid angle on the upper hemisphere (pdf 1/(2 pi)): cos
theta_i and phi_i / (2 pi) are the first two coordinates of a scrambled Sobol sequence
(``scipy.stats.qmc.Sobol``: linear matrix scrambling with a random digital shift, so every
point on its own is uniform and the estimates are unbiased). w_o comes from a defensive
mixture (Hesterberg 1995): a fraction 1 - ``mirror_fraction`` of the draws is uniform on the
hemisphere, the rest is split evenly between lobes about the mirror direction. A lobe of
width alpha draws a half vector h from the GGX distribution of normals D(h) cos theta_h
(Walter et al. 2007, sec. 5.3: tan^2 theta_h = alpha^2 u / (1 - u), phi_h = 2 pi v) and
reflects w_i about it, w_o = 2 (w_i . h) h - w_i; the density of w_o in solid angle is
D(h) cos theta_h / (4 (w_o . h)) with h = (w_i + w_o) / |w_i + w_o|, the Jacobian of the
half-vector map (Walter et al. 2007, eq. 14). The draws of each component are a fixed
number per replicate (stratified by component), and every pair gets the balance-heuristic
weight of the multi-sample model (Veach & Guibas 1995, sec. 3):
weight = 2 pi / (R sum_k n_k p_k(w_o | w_i)), where n_k is the number of draws of component
k in the pair's replicate, p_k its density and R the number of replicates. Because the
uniform component alone has density (1 - mirror_fraction) / (2 pi), no weight exceeds
(2 pi)^2 / (R n_0), whatever the lobes.

**Below the horizon.** A lobe draw whose w_o falls below the horizon (w_o . z < 0) is
*dropped*; its draw still counts in n_k, so the estimator of an integral over H x H stays
unbiased (the dropped pairs would contribute 0). ``PairSamples.draws`` is the number of draws,
``len(samples)`` the number of pairs kept.

**Standard errors.** The pairs form R independent replicates (independent scramblings, R = 16
by default); each replicate alone is an unbiased estimate, so the spread of the replicate
estimates gives the standard error of their mean, the usual practice of randomised quasi-Monte Carlo
(L'Ecuyer & Lemieux 2002). The relative l2 error is a ratio of two such integrals; its
standard error is the delta-method (ratio-estimator) standard error of the replicate means,
halved by the square root.

**Metrics.** With q = f cos theta_i cos theta_o, the relative l2 error is
sqrt(int (q_hat - q)^2 / int q^2) over H x H in solid angle, the norm in which the library
projects ("f_cos", Westin et al. 1992). The log metric is the root mean square over H x H of
log(1 + f cos theta_i) - log(1 + max(f_hat, 0) cos theta_i), the compressive transform used
to fit and compare models to measured BRDFs by Löw et al. 2012 and used as the training
loss of the neural MERL fits of Sztrajman et al. 2021; it weights the dim, wide-angle part of
the BRDF comparably to the peak.

References
----------
- T. Hesterberg, "Weighted average importance sampling and defensive mixture
  distributions", Technometrics 37(2), 1995, pp. 185-194.
- P. L'Ecuyer and C. Lemieux, "Recent advances in randomized quasi-Monte Carlo methods", in
  Modeling Uncertainty, Kluwer, 2002, pp. 419-474.
- J. Löw, J. Kronander, A. Ynnerman and J. Unger, "BRDF models for accurate and efficient
  rendering of glossy surfaces", ACM Transactions on Graphics 31(1), 2012.
- A. Sztrajman, G. Rainer, T. Ritschel and T. Weyrich, "Neural BRDF representation and
  importance sampling", Computer Graphics Forum 40(6), 2021.
- E. Veach and L. J. Guibas, "Optimally combining sampling techniques for Monte Carlo
  rendering", SIGGRAPH 95, pp. 419-428.
- B. Walter, S. R. Marschner, H. Li and K. E. Torrance, "Microfacet models for refraction
  through rough surfaces", Eurographics Symposium on Rendering 2007.
- S. H. Westin, J. R. Arvo and K. E. Torrance, "Predicting reflectance functions from
  complex surfaces", SIGGRAPH 92, pp. 255-264.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import qmc

from basis.validation import nonneg_int

__all__ = ["PairSamples", "brdf_errors", "log_rms", "peak_resolving_pairs", "relative_l2",
           "value_errors"]

#: Default lobe widths (GGX alpha of the half-vector lobes about the mirror direction).
DEFAULT_WIDTHS = (0.02, 0.08, 0.3)


@dataclass(frozen=True, eq=False)
class PairSamples:
    """Direction pairs with weights that integrate over H x H in solid angle.

    ``sum(weights * g(wi, wo))`` is an unbiased estimate of
    int_H int_H g(w_i, w_o) dw_i dw_o for any integrable g.

    Attributes
    ----------
    wi, wo : (n, 3) ndarray of float64, read-only
        Unit vectors towards the light and the viewer, both in the upper hemisphere.
    weights : (n,) ndarray of float64, read-only
        Positive weights (sr^2).
    replicate : (n,) ndarray of int, read-only
        Which independent replicate (0 .. replicates - 1) each pair belongs to; each
        replicate alone, its weights times ``replicates``, is an unbiased estimator too.
    replicates : int
        Number of independent replicates.
    draws : int
        Pairs drawn; draws below the horizon were dropped, so ``len(self) <= draws``.
    description : str
        How the pairs were drawn (for reports).
    """

    wi: NDArray[np.float64]
    wo: NDArray[np.float64]
    weights: NDArray[np.float64]
    replicate: NDArray[np.int64]
    replicates: int
    draws: int
    description: str

    def __post_init__(self) -> None:
        for name in ("wi", "wo", "weights", "replicate"):
            getattr(self, name).flags.writeable = False

    def __len__(self) -> int:
        return int(self.weights.shape[0])

    def __repr__(self) -> str:
        return f"PairSamples({len(self)} pairs: {self.description})"


def peak_resolving_pairs(n: int, *, seed: int = 0, mirror_fraction: float = 0.5,
                         widths: Sequence[float] = DEFAULT_WIDTHS,
                         replicates: int = 16) -> PairSamples:
    """Draw direction pairs that resolve specular peaks, weighted to integrate over H x H.

    Parameters
    ----------
    n : int
        Number of pairs to draw (lobe draws that fall below the horizon are dropped, so
        slightly fewer are returned). Split evenly between the replicates.
    seed : int
        Seed (>= 0) of the scramblings; the same seed gives the same pairs bit for bit.
    mirror_fraction : float
        Fraction of the w_o draws taken from the lobes about the mirror direction, in
        [0, 1); the rest is uniform on the hemisphere, which bounds every weight.
        0 gives a uniform-only sampler.
    widths : sequence of float
        GGX alpha (> 0, <= 10) of each half-vector lobe; the lobe draws are split evenly
        between them. Cover the widths of the lobes to be measured: a lobe much narrower
        than the narrowest width is still estimated without bias, with more variance.
    replicates : int
        Number of independent scramblings (>= 2), whose spread gives standard errors.

    Returns
    -------
    PairSamples

    Raises
    ------
    TypeError
        ``n``, ``seed`` or ``replicates`` is not an integer, ``mirror_fraction`` not a
        number, ``widths`` not a sequence of numbers.
    ValueError
        A value out of range, or ``n`` too small to give every component a draw in every
        replicate.

    Notes
    -----
    The sampling, the weights and the handling of the horizon are described in the module
    notes (:mod:`project.sampling`).

    Examples
    --------
    >>> s = peak_resolving_pairs(4096, seed=1)
    >>> s.wi.shape == s.wo.shape == (len(s), 3)
    True
    >>> round(float(s.weights.sum() / (2 * np.pi) ** 2), 2)  # int 1 over H x H
    1.0
    """
    n = nonneg_int(n, "n")
    seed = nonneg_int(seed, "seed")
    reps = nonneg_int(replicates, "replicates")
    if reps < 2:
        raise ValueError(f"replicates must be >= 2 (standard errors need two), got {reps}")
    m = _fraction(mirror_fraction)
    alphas = _widths(widths)
    k = len(alphas) if m > 0.0 else 0
    need = _min_replicate_size(m, k)
    if n < need * reps:
        raise ValueError(f"n must be >= {need * reps} so that each of the {reps} replicates "
                         f"gives every component (uniform + {k} lobes) a draw, got {n}")
    children = np.random.SeedSequence(seed).spawn(reps)
    wi_parts, wo_parts, w_parts, r_parts = [], [], [], []
    for r in range(reps):
        size = n // reps + (r < n % reps)
        counts = _allocate(size, m, k)
        streams = children[r].spawn(len(counts))
        wi_r, wo_r = [], []
        for j, c in enumerate(counts):
            if c == 0:
                continue
            u = _sobol(c, streams[j])
            wi = _uniform_dirs(u[:, 0], u[:, 1])
            if j == 0:
                wo = _uniform_dirs(u[:, 2], u[:, 3])
            else:
                wo = _ggx_reflect(wi, u[:, 2], u[:, 3], alphas[j - 1])
            keep = wo[:, 2] >= 0.0
            wi_r.append(wi[keep])
            wo_r.append(wo[keep])
        wi_r = np.concatenate(wi_r)
        wo_r = np.concatenate(wo_r)
        dens = counts[0] / (2.0 * np.pi) + np.zeros(wi_r.shape[0])
        for j, a in enumerate(alphas[:k]):
            dens += counts[j + 1] * _ggx_reflect_pdf(wi_r, wo_r, a)
        wi_parts.append(wi_r)
        wo_parts.append(wo_r)
        w_parts.append(2.0 * np.pi / (reps * dens))
        r_parts.append(np.full(wi_r.shape[0], r))
    wi = np.ascontiguousarray(np.concatenate(wi_parts))
    wo = np.ascontiguousarray(np.concatenate(wo_parts))
    kept = wi.shape[0]
    lobes = (f"{m:.3g} from GGX half-vector lobes about the mirror, alpha = "
             + ", ".join(f"{a:.3g}" for a in alphas)) if k else "no mirror lobes"
    desc = (f"peak-resolving pairs: {n} draws, {kept} kept ({n - kept} below the horizon "
            f"dropped); w_i uniform, w_o {1.0 - m:.3g} uniform + {lobes}; balance-heuristic "
            f"weights; scrambled Sobol, {reps} replicates, seed {seed}")
    return PairSamples(wi=wi, wo=wo, weights=np.concatenate(w_parts),
                       replicate=np.concatenate(r_parts).astype(np.int64), replicates=reps,
                       draws=n, description=desc)


def _fraction(value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"mirror_fraction must be a number in [0, 1), got {value!r}")
    m = float(value)
    if not (0.0 <= m < 1.0):
        raise ValueError(f"mirror_fraction must lie in [0, 1) (the uniform part bounds the "
                         f"weights), got {value!r}")
    return m


def _widths(value: object) -> tuple[float, ...]:
    if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
        raise TypeError(f"widths must be a sequence of numbers (GGX alpha), got {value!r}")
    out = []
    for w in value:
        if isinstance(w, bool) or not isinstance(w, numbers.Real):
            raise TypeError(f"widths must be a sequence of numbers (GGX alpha), got {value!r}")
        out.append(float(w))
    if not out:
        raise ValueError("widths must hold at least one lobe width, got an empty sequence")
    if not all(math.isfinite(w) and 0.0 < w <= 10.0 for w in out):
        raise ValueError(f"widths must be finite, > 0 and <= 10, got {value!r}")
    return tuple(out)


def _allocate(size: int, m: float, k: int) -> list[int]:
    """Draws per component in a replicate of ``size``: [uniform, lobe 1, ..., lobe k]."""
    if k == 0:
        return [size]
    lobes = int(round(m * size))
    return [size - lobes] + [lobes // k + (j < lobes % k) for j in range(k)]


def _min_replicate_size(m: float, k: int) -> int:
    """Smallest replicate size that gives every component at least one draw."""
    size = 1
    while min(_allocate(size, m, k)) < 1:  # monotone in size, ends by size ~ k / m
        size += 1
    return size


def _sobol(count: int, stream: np.random.SeedSequence) -> NDArray[np.float64]:
    """First ``count`` points of a scrambled 4-D Sobol sequence (a power-of-2 prefix)."""
    engine = qmc.Sobol(d=4, scramble=True, rng=np.random.default_rng(stream))
    return engine.random_base2(max(0, math.ceil(math.log2(count))))[:count]


def _uniform_dirs(u: NDArray, v: NDArray) -> NDArray[np.float64]:
    """Uniform directions in solid angle on the upper hemisphere (z = 1 - u in (0, 1])."""
    z = 1.0 - u
    s = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    p = 2.0 * np.pi * v
    return np.stack([s * np.cos(p), s * np.sin(p), z], axis=-1)


def _ggx_reflect(wi: NDArray, u: NDArray, v: NDArray, alpha: float) -> NDArray[np.float64]:
    """Reflect w_i about half vectors drawn from D_GGX(h) cos theta_h; (n, 3) w_o."""
    t2 = alpha * alpha * u / (1.0 - u)  # u < 1: Sobol points lie in [0, 1)
    c = 1.0 / np.sqrt(1.0 + t2)
    s = np.sqrt(t2) * c
    p = 2.0 * np.pi * v
    h = np.stack([s * np.cos(p), s * np.sin(p), c], axis=-1)
    d = np.einsum("ij,ij->i", wi, h)
    wo = 2.0 * d[:, None] * h - wi
    wo /= np.linalg.norm(wo, axis=1)[:, None]
    wo[d <= 0.0, 2] = -1.0  # w_i . h <= 0 reflects below the horizon: mark for dropping
    return wo


def _ggx_reflect_pdf(wi: NDArray, wo: NDArray, alpha: float) -> NDArray[np.float64]:
    """Density in solid angle of w_o given w_i: D(h) cos theta_h / (4 w_o . h)."""
    h = wi + wo
    norm = np.linalg.norm(h, axis=1)
    ok = norm > 0.0
    h = h / np.where(ok, norm, 1.0)[:, None]
    a2 = alpha * alpha
    den = a2 * h[:, 2] ** 2 + h[:, 0] ** 2 + h[:, 1] ** 2
    dist = a2 / (np.pi * den * den)
    # w_o . h = |w_i + w_o| / 2 for unit vectors
    return np.where(ok, dist * h[:, 2] / (2.0 * np.where(ok, norm, 1.0)), 0.0)


# -- metrics ------------------------------------------------------------------------------------

def _values(f: ArrayLike, name: str, n: int) -> NDArray[np.float64]:
    """BRDF values at the n pairs as (n, C) float64, checked finite."""
    try:
        a = np.asarray(f, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be an array of floats, got {type(f).__name__}") from None
    if a.ndim not in (1, 2) or a.shape[0] != n:
        raise ValueError(f"{name} must have shape (n,) or (n, channels) with n = {n} pairs, "
                         f"got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite: {int(np.sum(~np.isfinite(a)))} values are "
                         "NaN or inf")
    return a.reshape(n, -1)


def _pair(f: ArrayLike, f_hat: ArrayLike,
          samples: PairSamples) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    if not isinstance(samples, PairSamples):
        raise TypeError(f"samples must be a PairSamples (from peak_resolving_pairs), got "
                        f"{type(samples).__name__}")
    a = _values(f, "f", len(samples))
    b = _values(f_hat, "f_hat", len(samples))
    if a.shape != b.shape:
        raise ValueError(f"f and f_hat must have the same shape, got {np.shape(f)} and "
                         f"{np.shape(f_hat)}")
    return a, b


def _reduce(per: NDArray[np.float64], per_channel: bool) -> float | NDArray[np.float64]:
    return per.copy() if per_channel else float(per.max())


def relative_l2(f: ArrayLike, f_hat: ArrayLike, samples: PairSamples, *,
                per_channel: bool = False) -> float | NDArray[np.float64]:
    """Relative l2 error of ``f_hat`` against ``f`` in q = f cos theta_i cos theta_o.

    sqrt(int (q_hat - q)^2 / int q^2) over H x H in solid angle, each integral estimated
    with the weights of ``samples``.

    Parameters
    ----------
    f, f_hat : (n,) or (n, channels) array_like of float
        Reference and approximate BRDF values at the n pairs of ``samples``.
    samples : PairSamples
    per_channel : bool
        Return one error per channel instead of the largest.

    Returns
    -------
    float, or (channels,) ndarray when ``per_channel``

    Raises
    ------
    ValueError
        Shapes do not match the samples, values are not finite, or the reference is 0 at
        every pair (the relative error is undefined).

    Examples
    --------
    >>> s = peak_resolving_pairs(256)
    >>> f = np.full(len(s), 0.3)
    >>> round(relative_l2(f, 1.1 * f, s), 12)
    0.1
    """
    a, b = _pair(f, f_hat, samples)
    cc = (samples.wi[:, 2] * samples.wo[:, 2])[:, None]
    q, q_hat = a * cc, b * cc
    w = samples.weights[:, None]
    den = np.sum(w * q * q, axis=0)
    if np.any(den <= 0.0):
        raise ValueError("f must not be 0 at every pair (channel "
                         f"{int(np.flatnonzero(den <= 0.0)[0])}): the relative error is "
                         "undefined")
    return _reduce(np.sqrt(np.sum(w * (q_hat - q) ** 2, axis=0) / den), per_channel)


def log_rms(f: ArrayLike, f_hat: ArrayLike, samples: PairSamples, *,
            per_channel: bool = False) -> float | NDArray[np.float64]:
    """Root mean square over H x H of log(1 + f cos theta_i) - log(1 + f_hat cos theta_i).

    ``f_hat`` is clamped at 0 (approximations may dip below 0; the log would not exist).

    Parameters
    ----------
    f : (n,) or (n, channels) array_like of float
        Reference BRDF values at the pairs of ``samples``, >= 0.
    f_hat : (n,) or (n, channels) array_like of float
        Approximate values (negative values count as 0).
    samples : PairSamples
    per_channel : bool
        Return one value per channel instead of the largest.

    Returns
    -------
    float, or (channels,) ndarray when ``per_channel``

    Notes
    -----
    The mean is taken with the solid-angle weights of ``samples`` (normalised to sum to 1),
    so it is the root mean square over H x H, independent of how the pairs were drawn. See
    the module notes for where the metric comes from.

    Examples
    --------
    >>> s = peak_resolving_pairs(256)
    >>> f = np.full(len(s), 0.3)
    >>> log_rms(f, f, s)
    0.0
    """
    a, b = _pair(f, f_hat, samples)
    if np.any(a < 0.0):
        raise ValueError(f"f must be >= 0 for the log metric, got min {a.min():.6g}")
    ci = samples.wi[:, 2:3]
    d = np.log1p(a * ci) - np.log1p(np.maximum(b, 0.0) * ci)
    w = samples.weights[:, None]
    return _reduce(np.sqrt(np.sum(w * d * d, axis=0) / np.sum(w)), per_channel)


def _l2_with_stderr(q: NDArray, q_hat: NDArray,
                    samples: PairSamples) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-channel relative l2 error and its standard error from the replicate spread."""
    w = samples.weights[:, None]
    reps = samples.replicates
    # bincount adds in the order of the pairs, as np.add.at does (the same sums bit for
    # bit), several times faster
    num = w * (q_hat - q) ** 2
    den = w * q * q
    num_r = np.stack([np.bincount(samples.replicate, weights=num[:, c], minlength=reps)
                      for c in range(q.shape[1])], axis=1)
    den_r = np.stack([np.bincount(samples.replicate, weights=den[:, c], minlength=reps)
                      for c in range(q.shape[1])], axis=1)
    num_r *= reps  # each replicate alone estimates the integrals
    den_r *= reps
    num, den = num_r.mean(axis=0), den_r.mean(axis=0)
    if np.any(den <= 0.0):
        raise ValueError("the reference BRDF must not be 0 at every pair (channel "
                         f"{int(np.flatnonzero(den <= 0.0)[0])}): the relative error is "
                         "undefined")
    ratio = num / den
    # delta method for the ratio of two replicate means
    var = np.sum((num_r - ratio * den_r) ** 2, axis=0) / (reps * (reps - 1) * den * den)
    err = np.sqrt(ratio)
    se = np.divide(np.sqrt(var), 2.0 * err, out=np.zeros_like(err), where=err > 0.0)
    return err, se


def _evaluate(brdf: object, name: str, samples: PairSamples) -> NDArray[np.float64]:
    if not callable(getattr(brdf, "eval", None)):
        raise TypeError(f"{name} must be a BRDF (an object with eval(wi, wo)), got "
                        f"{type(brdf).__name__}")
    return _values(brdf.eval(samples.wi, samples.wo), f"{name}.eval(wi, wo)", len(samples))


def brdf_errors(reference_brdf: object, approx: object, samples: PairSamples) -> dict:
    """Evaluate two BRDFs once at ``samples`` and return their errors.

    Parameters
    ----------
    reference_brdf, approx : BRDF
        Any objects with ``eval(wi, wo)`` (e.g. a measured BRDF and a fit or a coefficient
        matrix); the same number of channels, or ``approx`` with one channel.
    samples : PairSamples
        Typically :func:`peak_resolving_pairs`; independent of any pairs used to build
        ``approx``, or the errors are biased low.

    Returns
    -------
    dict
        ``"l2"``: :func:`relative_l2` (the largest over the channels); ``"log"``:
        :func:`log_rms` (largest over the channels); ``"l2_stderr"``: the Monte Carlo
        standard error of ``"l2"`` (of the channel where it is largest), from the spread of
        the independent replicates of ``samples`` (module notes).

    Examples
    --------
    >>> from project.models import CookTorrance
    >>> s = peak_resolving_pairs(4096)
    >>> e = brdf_errors(CookTorrance(0.2, 0.1, "ggx"), CookTorrance(0.2, 0.11, "ggx"), s)
    >>> sorted(e)
    ['l2', 'l2_stderr', 'log']
    >>> bool(0.0 < e["l2_stderr"] < 0.2 * e["l2"])
    True
    """
    if not isinstance(samples, PairSamples):
        raise TypeError(f"samples must be a PairSamples (from peak_resolving_pairs), got "
                        f"{type(samples).__name__}")
    return value_errors(_evaluate(reference_brdf, "reference_brdf", samples),
                        _evaluate(approx, "approx", samples), samples)


def value_errors(f: ArrayLike, f_hat: ArrayLike, samples: PairSamples) -> dict:
    """Return the errors of :func:`brdf_errors` from values evaluated at ``samples``.

    For comparing many approximations with one reference: evaluate the reference once.

    Parameters
    ----------
    f, f_hat : (n,) or (n, channels) array_like of float
        Reference and approximation (1/sr) at the n pairs of ``samples``; ``f_hat`` may
        have one channel, which then stands for all.
    samples : PairSamples

    Returns
    -------
    dict
        ``"l2"``, ``"log"`` and ``"l2_stderr"``, as :func:`brdf_errors`.
    """
    if not isinstance(samples, PairSamples):
        raise TypeError(f"samples must be a PairSamples (from peak_resolving_pairs), got "
                        f"{type(samples).__name__}")
    f = _values(f, "f", len(samples))
    g = _values(f_hat, "f_hat", len(samples))
    if g.shape[1] == 1 and f.shape[1] > 1:
        g = np.broadcast_to(g, f.shape)
    if f.shape != g.shape:
        raise ValueError(f"the reference and the approximation must have the same number of "
                         f"channels, got {f.shape[1]} and {g.shape[1]}")
    cc = (samples.wi[:, 2] * samples.wo[:, 2])[:, None]
    err, se = _l2_with_stderr(f * cc, g * cc, samples)
    worst = int(np.argmax(err))
    return {"l2": float(err[worst]), "log": float(log_rms(f, g, samples)),
            "l2_stderr": float(se[worst])}
