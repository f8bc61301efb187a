"""Importance sampling for the ``scatmodes`` BSDF: one lobe mixed with cosine sampling (numpy).

Everything here is plain float64 numpy, independent of Mitsuba: the plugin converts Mitsuba's
arrays once per call and hands them to :meth:`LobeSampler.sample` and :meth:`LobeSampler.pdf`.
Directions are in the local frame (z the normal); ``wi`` is the fixed direction of the query
(Mitsuba's ``si.wi``) and ``wo`` the sampled one; both point away from the surface.

The density is the mixture (one-sample multiple importance sampling, Veach 1997, sec. 9.2.2)

    p(w_o) = (1 - w) cos(theta_o) / pi + w p_lobe(w_o | w_i),

with p_lobe a density of the half vector h = (w_i + w_o)/|w_i + w_o| turned into one of w_o
by the Jacobian of reflection, 1 / (4 (w_i . h)) (Walter et al. 2007, eq. 14). Lobes:

- ``"ggx"``: the distribution of visible normals of GGX (Heitz 2018, exact inversion);
- ``"beckmann"``: that of Beckmann, inverted numerically (Heitz & d'Eon 2014, with the
  bracketed Newton iteration of Mitsuba's microfacet code, run to 1e-12);
- ``"table"``: a density of h that is piecewise constant in solid angle over bins of
  theta_h and uniform in phi_h, sampled through its tabulated inverse CDF;
- ``"cosine"``: no lobe (w = 0).

:class:`TableSampler` is the other kind: a density of w_o tabulated from the representation
itself at load time, piecewise constant per (theta_o, phi_o - phi_i) cell for each bin of
theta_i, mixed with cosine sampling as well; :class:`MixtureSampler` mixes samplers.
:func:`sampler_for` builds the candidates and keeps the one whose sample weights vary least
on a fixed pilot set.

``sample`` returns exactly the density ``pdf`` reports (the same float64 formulas), which the
chi-square tests of Mitsuba check. A sampled w_o below the horizon, or a half vector facing
away from w_i, is a failed sample (density 0); the missing mass is simply not returned, as in
Mitsuba's own microfacet plugins.

References
----------
- E. Veach, "Robust Monte Carlo methods for light transport simulation", PhD thesis,
  Stanford University, 1997.
- B. Walter, S. Marschner, H. Li and K. Torrance, "Microfacet models for refraction through
  rough surfaces", EGSR 2007.
- E. Heitz and E. d'Eon, "Importance sampling microfacet-based BSDFs using the distribution
  of visible normals", Computer Graphics Forum 33(4), 2014.
- E. Heitz, "Sampling the GGX distribution of visible normals", JCGT 7(4), 2018.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import erf, erfcx, erfinv

from basis import CoefficientMatrix
from basis.directions import from_rusinkiewicz

__all__ = ["KINDS", "LobeSampler", "MixtureSampler", "TableSampler", "profile", "sampler_for"]

#: The lobe kinds of :class:`LobeSampler`, and ``"table2d"`` of :class:`TableSampler`.
KINDS = ("cosine", "ggx", "beckmann", "table", "table2d")
#: Bins of the theta_h profile and of the "table" lobe; edges (pi/2) (k / K)^2, dense near
#: the specular direction (the warp of MERL's theta_h axis, Matusik et al. 2003).
TABLE_BINS = 128
#: theta_d (radians) and phi_d values averaged over by :func:`profile`: close to the
#: specular configuration, where a microfacet lobe is D(h) G F / (4 cos cos) with G, F ~ 1.
_PROFILE_TD = (0.0, 0.2, 0.4)
_PROFILE_PD = (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi)
#: The diffuse floor is the smallest mean f over theta_h below this angle (grazing half
#: vectors put one direction near the horizon, where truncated expansions ring most).
_FLOOR_THETA = math.radians(60.0)
#: Mixture weight of the lobe: at least/most this when there is a lobe; none below
#: _NO_LOBE of the total albedo.
_WEIGHT_RANGE = (0.1, 0.9)
_NO_LOBE = 1e-3
#: Grid (theta_i, theta_o, phi_o - phi_i bins) of the TableSampler built by sampler_for.
TABLE_SHAPE = (16, 32, 64)
#: The pilot set of sampler_for: incidences (radians), samples per incidence and seed.
_PILOT_THETA = np.radians([0.0, 30.0, 60.0, 80.0])
_PILOT_N = 4096
_PILOT_SEED = 0
#: GGX alphas tried when a lobe is fitted to a modal expansion's profile.
_ALPHAS = np.geomspace(0.01, 1.2, 64)
_SQRT_PI = math.sqrt(math.pi)


class LobeSampler:
    """A lobe mixed with cosine-weighted hemisphere sampling, with its exact density.

    Parameters
    ----------
    kind : {"cosine", "ggx", "beckmann", "table"}
    lobe_weight : float
        Probability w in [0, 1] of sampling the lobe (0 for ``"cosine"``).
    alpha : float, optional
        Roughness of ``"ggx"`` (alpha) and ``"beckmann"`` (RMS slope), > 0.
    mass : (TABLE_BINS,) array_like of float, optional
        For ``"table"``: probability of each theta_h bin (>= 0, normalised here); the bin
        edges are :attr:`edges`.

    Attributes
    ----------
    kind, lobe_weight, alpha
    edges : (TABLE_BINS + 1,) ndarray
        theta_h bin edges (radians) of the table.

    Examples
    --------
    >>> s = LobeSampler("ggx", lobe_weight=0.5, alpha=0.2)
    >>> rng = np.random.default_rng(0)
    >>> wi = np.tile([0.6, 0.0, 0.8], (4, 1))
    >>> wo, pdf = s.sample(wi, *rng.random((3, 4)))
    >>> bool(np.allclose(pdf, s.pdf(wi, wo)))
    True
    """

    def __init__(self, kind: str, *, lobe_weight: float = 0.0, alpha: float | None = None,
                 mass: Any = None) -> None:
        if kind not in KINDS[:-1]:
            raise ValueError(f"kind must be one of {KINDS[:-1]}, got {kind!r} (a 'table2d' "
                             f"sampler is a TableSampler)")
        if not 0.0 <= lobe_weight <= 1.0:
            raise ValueError(f"lobe_weight must lie in [0, 1], got {lobe_weight!r}")
        self.kind = kind
        self.lobe_weight = 0.0 if kind == "cosine" else float(lobe_weight)
        self.alpha = None
        if kind in ("ggx", "beckmann"):
            if alpha is None or not alpha > 0.0:
                raise ValueError(f"alpha must be > 0 for a {kind!r} lobe, got {alpha!r}")
            self.alpha = float(alpha)
        self.edges = 0.5 * math.pi * (np.arange(TABLE_BINS + 1) / TABLE_BINS) ** 2
        self._cos_edges = np.cos(self.edges)
        self._cos_edges[-1] = 0.0
        if kind == "table":
            m = np.asarray(mass, dtype=np.float64)
            if m.shape != (TABLE_BINS,) or not np.all(np.isfinite(m)) or np.any(m < 0) \
                    or m.sum() <= 0:
                raise ValueError(f"mass must be {TABLE_BINS} finite values >= 0 with a "
                                 f"positive sum")
            self.mass = m / m.sum()
            self._cdf = np.concatenate([[0.0], np.cumsum(self.mass)])
            self._cdf[-1] = 1.0
            # density of h per steradian in each bin: mass / (2 pi (cos e_k - cos e_k+1))
            self._density = self.mass / (2.0 * math.pi * np.diff(-self._cos_edges))

    def __repr__(self) -> str:
        extra = f", alpha={self.alpha:.4g}" if self.alpha is not None else ""
        return f"LobeSampler({self.kind!r}, lobe_weight={self.lobe_weight:.3g}{extra})"

    # -- sampling ---------------------------------------------------------------------------
    def sample(self, wi: NDArray, u0: NDArray, u1: NDArray, u2: NDArray
               ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Draw w_o for each w_i from three uniform numbers in [0, 1).

        Parameters
        ----------
        wi : (n, 3) ndarray of float
            Unit vectors; w_i below the horizon gives a failed sample.
        u0, u1, u2 : (n,) ndarray of float
            u0 chooses between the cosine and the lobe technique, (u1, u2) the direction.

        Returns
        -------
        wo : (n, 3) ndarray
            Unit vectors (zero vectors for failed samples).
        pdf : (n,) ndarray
            The mixture density of :meth:`pdf` at w_o (per steradian), 0 for failed samples.
        """
        wi = np.asarray(wi, dtype=np.float64)
        u0, u1, u2 = (np.asarray(u, dtype=np.float64) for u in (u0, u1, u2))
        n = wi.shape[0]
        wo = np.zeros((n, 3))
        lobe = u0 < self.lobe_weight
        cos = ~lobe
        if np.any(cos):
            wo[cos] = _cosine_sample(u1[cos], u2[cos])
        if np.any(lobe):
            wo[lobe] = self._lobe_sample(wi[lobe], u1[lobe], u2[lobe])
        pdf = self.pdf(wi, wo)
        ok = (wi[:, 2] > 0) & (wo[:, 2] > 0) & (pdf > 0)
        wo[~ok] = 0.0
        return wo, np.where(ok, pdf, 0.0)

    def pdf(self, wi: NDArray, wo: NDArray) -> NDArray[np.float64]:
        """Mixture density of w_o given w_i, per steradian; 0 if either is below the horizon.

        Parameters
        ----------
        wi, wo : (n, 3) ndarray of float
            Unit vectors.

        Returns
        -------
        (n,) ndarray
        """
        wi = np.asarray(wi, dtype=np.float64)
        wo = np.asarray(wo, dtype=np.float64)
        up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
        p = (1.0 - self.lobe_weight) * np.maximum(wo[:, 2], 0.0) / math.pi
        if self.lobe_weight > 0.0:
            h = wi + wo
            hn = np.linalg.norm(h, axis=1)
            good = up & (hn > 0)
            h = h / np.where(good, hn, 1.0)[:, None]
            ih = np.einsum("ij,ij->i", wi, h)
            good &= ih > 0
            ph = np.where(good, self._half_pdf(wi, h, ih), 0.0)
            p = p + self.lobe_weight * ph / (4.0 * np.where(good, ih, 1.0))
        return np.where(up, p, 0.0)

    # -- the lobes --------------------------------------------------------------------------
    def _lobe_sample(self, wi: NDArray, u1: NDArray, u2: NDArray) -> NDArray:
        if self.kind == "table":
            h = self._table_sample(u1, u2)
        elif self.kind == "ggx":
            h = _ggx_visible_normal(wi, self.alpha, u1, u2)
        else:
            h = _beckmann_visible_normal(wi, self.alpha, u1, u2)
        ih = np.einsum("ij,ij->i", wi, h)
        return 2.0 * ih[:, None] * h - wi

    def _half_pdf(self, wi: NDArray, h: NDArray, ih: NDArray) -> NDArray:
        """Density of the half vector h (per steradian) given w_i."""
        if self.kind == "table":
            theta = np.arccos(np.clip(h[:, 2], -1.0, 1.0))
            k = np.clip(np.searchsorted(self.edges, theta, side="right") - 1, 0,
                        TABLE_BINS - 1)
            return self._density[k]
        ci = np.maximum(wi[:, 2], 1e-300)
        d = _ndf(h, self.alpha, self.kind)
        return d * _g1(wi[:, 2], self.alpha, self.kind) * np.maximum(ih, 0.0) / ci

    def _table_sample(self, u1: NDArray, u2: NDArray) -> NDArray:
        u1 = np.clip(u1, 0.0, np.nextafter(1.0, 0.0))
        k = np.clip(np.searchsorted(self._cdf[1:], u1, side="right"), 0, TABLE_BINS - 1)
        t = np.clip((u1 - self._cdf[k]) / np.maximum(self.mass[k], 1e-300), 0.0, 1.0)
        c0, c1 = self._cos_edges[k], self._cos_edges[k + 1]
        z = c0 - t * (c0 - c1)  # cos theta_h uniform in the bin: constant density per sr
        s = np.sqrt(np.maximum(1.0 - z * z, 0.0))
        phi = 2.0 * math.pi * u2
        return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


def _cosine_sample(u1: NDArray, u2: NDArray) -> NDArray:
    r = np.sqrt(u1)
    phi = 2.0 * math.pi * u2
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - u1, 0.0))],
                    axis=1)


def _ndf(h: NDArray, alpha: float, kind: str) -> NDArray:
    """D(h) of :class:`project.models.CookTorrance` (int D cos theta_h dw = 1)."""
    a2 = alpha * alpha
    z2 = h[:, 2] ** 2
    s2 = np.maximum(h[:, 0] ** 2 + h[:, 1] ** 2, 0.0)
    if kind == "ggx":
        den = a2 * z2 + s2
        return a2 / (math.pi * np.maximum(den * den, 1e-300))
    z2 = np.maximum(z2, 1e-300)
    return np.where(h[:, 2] > 0, np.exp(-s2 / (z2 * a2)) / (math.pi * a2 * z2 * z2), 0.0)


def _g1(c: NDArray, alpha: float, kind: str) -> NDArray:
    """Smith's G1 = 1 / (1 + Lambda) at cos theta = c > 0 (the masking of the model)."""
    c = np.clip(c, 1e-12, 1.0)
    s = np.sqrt(np.maximum(1.0 - c * c, 0.0))
    if kind == "ggx":
        return 2.0 * c / (c + np.sqrt(c * c + (alpha * s) ** 2))
    with np.errstate(divide="ignore"):
        a = c / (alpha * s)  # inf at normal incidence, where G1 = 1
    # 1 + Lambda = (1 + erf(a) + exp(-a^2) / (a sqrt(pi))) / 2, written with erfcx so that
    # large a neither overflows nor cancels
    lam2 = 2.0 - np.exp(-a * a) * (erfcx(a) - 1.0 / (a * _SQRT_PI))
    return np.where(np.isinf(a), 1.0, 2.0 / lam2)


def _stretch(wi: NDArray, alpha: float) -> tuple[NDArray, NDArray, NDArray]:
    v = np.stack([alpha * wi[:, 0], alpha * wi[:, 1], wi[:, 2]], axis=1)
    v /= np.linalg.norm(v, axis=1)[:, None]
    r = np.hypot(v[:, 0], v[:, 1])
    cp = np.where(r > 0, v[:, 0] / np.where(r > 0, r, 1.0), 1.0)
    sp = np.where(r > 0, v[:, 1] / np.where(r > 0, r, 1.0), 0.0)
    return v, cp, sp


def _ggx_visible_normal(wi: NDArray, alpha: float, u1: NDArray, u2: NDArray) -> NDArray:
    """Heitz 2018, listing 1: exact inversion of the GGX distribution of visible normals."""
    v, cp, sp = _stretch(wi, alpha)
    t1 = np.stack([-sp, cp, np.zeros_like(cp)], axis=1)
    t2 = np.cross(v, t1)
    r = np.sqrt(u1)
    phi = 2.0 * math.pi * u2
    p1, p2 = r * np.cos(phi), r * np.sin(phi)
    s = 0.5 * (1.0 + v[:, 2])
    p2 = (1.0 - s) * np.sqrt(np.maximum(1.0 - p1 * p1, 0.0)) + s * p2
    p3 = np.sqrt(np.maximum(1.0 - p1 * p1 - p2 * p2, 0.0))
    nh = p1[:, None] * t1 + p2[:, None] * t2 + p3[:, None] * v
    m = np.stack([alpha * nh[:, 0], alpha * nh[:, 1], np.maximum(nh[:, 2], 0.0)], axis=1)
    return m / np.maximum(np.linalg.norm(m, axis=1), 1e-300)[:, None]


def _beckmann_visible_normal(wi: NDArray, alpha: float, u1: NDArray, u2: NDArray) -> NDArray:
    """Heitz & d'Eon 2014: visible slopes of the stretched (alpha = 1) Beckmann surface."""
    v, cp, sp = _stretch(wi, alpha)
    theta = np.arccos(np.clip(v[:, 2], -1.0, 1.0))
    u1 = np.clip(u1, 1e-12, 1.0 - 1e-12)
    u2 = np.clip(u2, 1e-12, 1.0 - 1e-12)
    tan_t = np.tan(np.minimum(theta, 0.5 * math.pi - 1e-9))
    normal = theta < 1e-4
    cot = 1.0 / np.maximum(tan_t, 1e-150)  # cot^2 stays finite at normal incidence
    # the CDF of the x slope in the erf domain b = erf(x_m) on [-1, erf(cot theta)]:
    # C(b) = (1 + b + tan theta exp(-erfinv(b)^2) / sqrt(pi)) / (1 + c + tan theta
    # exp(-cot^2) / sqrt(pi)), c = erf(cot theta); inverted by bracketed Newton steps
    lo = np.full_like(u1, -1.0)
    hi = erf(cot)
    norm = 1.0 / (1.0 + hi + tan_t * np.exp(-cot * cot) / _SQRT_PI)
    fit = 1.0 + theta * (-0.876 + theta * (0.4265 - 0.0594 * theta))
    b = hi - (1.0 + hi) * (1.0 - u1) ** fit
    for _ in range(60):
        bad = ~((b >= lo) & (b <= hi))
        b = np.where(bad, 0.5 * (lo + hi), b)
        ie = erfinv(b)
        val = norm * (1.0 + b + tan_t * np.exp(-ie * ie) / _SQRT_PI) - u1
        der = norm * (1.0 - ie * tan_t)
        hi = np.where(val > 0, b, hi)
        lo = np.where(val > 0, lo, b)
        if np.all(np.abs(val) < 1e-13):
            break
        b = b - val / np.where(der != 0, der, 1.0)
    sx = erfinv(np.clip(b, -1.0 + 1e-16, 1.0 - 1e-16))
    sy = erfinv(2.0 * u2 - 1.0)
    r = np.sqrt(-np.log(1.0 - u1))
    ph = 2.0 * math.pi * u2
    sx = np.where(normal, r * np.cos(ph), sx)
    sy = np.where(normal, r * np.sin(ph), sy)
    # rotate back to the azimuth of w_i and unstretch the slopes
    x = alpha * (cp * sx - sp * sy)
    y = alpha * (sp * sx + cp * sy)
    m = np.stack([-x, -y, np.ones_like(x)], axis=1)
    return m / np.linalg.norm(m, axis=1)[:, None]


class TableSampler:
    """A density of w_o tabulated per bin of theta_i, mixed with cosine-weighted sampling.

    For each of K bins of theta_i (uniform in angle) the density of w_o is piecewise
    constant in solid angle over J x L cells: J bins of theta_o (uniform in angle) times L
    bins of the azimuth phi_o - phi_i over the whole turn (the representation must be
    isotropic). A cell's probability is its tabulated value times its solid angle, so a
    table of f cos(theta_o) gives a density proportional to the integrand of the
    directional albedo, up to the resolution of the grid. The mixture is

        p(w_o) = c cos(theta_o) / pi + (1 - c) p_table(w_o | bin of theta_i),

    where the cosine share c bounds the weight f cos / p by pi f / c where the table
    underestimates f (between its nodes). Every sample lies above the horizon: no sample
    fails. The inverse CDF over the cells of a bin picks a cell, then cos theta_o and the
    azimuth are uniform within it (uniform in solid angle: the density is exactly the
    tabulated one).

    Parameters
    ----------
    values : (K, J, L) array_like of float
        Values >= 0 of the density's shape (e.g. f cos(theta_o)) at each (theta_i bin,
        theta_o bin, azimuth bin); a bin of theta_i whose values are all 0 samples
        uniformly in solid angle.
    cosine : float
        Probability c in (0, 1] of the cosine technique.

    Attributes
    ----------
    kind : str
        ``"table2d"``.
    lobe_weight : float
        1 - c, the probability of the table.
    shape : tuple of int
        (K, J, L).

    Examples
    --------
    >>> grid = TableSampler.grid((4, 8, 16))
    >>> values = np.cos(grid[1])[None, :, None] * np.ones((4, 1, 16))   # a Lambertian f cos
    >>> s = TableSampler(values)
    >>> rng = np.random.default_rng(0)
    >>> wi = np.tile([0.6, 0.0, 0.8], (4, 1))
    >>> wo, pdf = s.sample(wi, *rng.random((3, 4)))
    >>> bool(np.allclose(pdf, s.pdf(wi, wo)))
    True
    """

    kind = "table2d"

    def __init__(self, values: Any, *, cosine: float = 0.1) -> None:
        v = np.asarray(values, dtype=np.float64)
        if v.ndim != 3 or min(v.shape) < 1:
            raise ValueError(f"values must have shape (K, J, L) with K, J, L >= 1, got shape "
                             f"{v.shape}")
        if not np.all(np.isfinite(v)) or np.any(v < 0):
            raise ValueError("values must be finite and >= 0")
        if not 0.0 < cosine <= 1.0:
            raise ValueError(f"cosine must lie in (0, 1], got {cosine!r}")
        self.shape = v.shape
        self.lobe_weight = 1.0 - float(cosine)
        k, j, l = v.shape
        self._cos_o = np.cos(0.5 * math.pi * np.arange(j + 1) / j)
        self._cos_o[-1] = 0.0
        self._dphi = 2.0 * math.pi / l
        solid = np.broadcast_to(((self._cos_o[:-1] - self._cos_o[1:]) * self._dphi)[:, None],
                                (j, l))
        mass = v * solid
        total = mass.sum(axis=(1, 2), keepdims=True)
        mass = np.where(total > 0, mass, solid)  # nothing tabulated: uniform in solid angle
        mass = (mass / mass.sum(axis=(1, 2), keepdims=True)).reshape(k, j * l)
        self._mass = mass
        self._density = mass / solid.reshape(1, j * l)  # per steradian
        self._cdf = np.concatenate([np.zeros((k, 1)), np.cumsum(mass, axis=1)], axis=1)
        self._cdf[:, -1] = 1.0

    def __repr__(self) -> str:
        return f"TableSampler(shape={self.shape}, lobe_weight={self.lobe_weight:.3g})"

    @staticmethod
    def grid(shape: tuple[int, int, int]) -> tuple[NDArray, NDArray, NDArray]:
        """Return the bin centres (theta_i, theta_o, phi_o - phi_i), radians, of a table shape."""
        k, j, l = shape
        return (0.5 * math.pi * (np.arange(k) + 0.5) / k,
                0.5 * math.pi * (np.arange(j) + 0.5) / j,
                2.0 * math.pi * (np.arange(l) + 0.5) / l)

    @classmethod
    def from_function(cls, g: Any, shape: tuple[int, int, int] = (16, 32, 64),
                      sub: int = 2, **options: Any) -> TableSampler:
        """Tabulate g(w_i, w_o) >= 0: the mean of sub x sub points per cell, theta_i at centres.

        Parameters
        ----------
        g : callable
            ``g(wi, wo)`` with (n, 3) unit vectors, returning (n,) values >= 0 (e.g. f
            cos(theta_o) in the convention of the sampler's w_i).
        shape : (K, J, L) tuple of int
        sub : int
            Points per cell side (theta_o, azimuth) at which g is averaged.
        **options
            Passed to the constructor (``cosine``).

        Returns
        -------
        TableSampler
        """
        k, j, l = shape
        ti = TableSampler.grid(shape)[0]
        frac = (np.arange(sub) + 0.5) / sub
        to = 0.5 * math.pi * (np.arange(j)[:, None] + frac[None, :]).ravel() / j
        po = 2.0 * math.pi * (np.arange(l)[:, None] + frac[None, :]).ravel() / l
        a, b, c = np.meshgrid(ti, to, po, indexing="ij")
        wi = np.stack([np.sin(a), np.zeros_like(a), np.cos(a)], axis=-1).reshape(-1, 3)
        wo = np.stack([np.sin(b) * np.cos(c), np.sin(b) * np.sin(c), np.cos(b)],
                      axis=-1).reshape(-1, 3)
        v = np.asarray(g(wi, wo), dtype=np.float64).reshape(k, j, sub, l, sub)
        v = np.where(np.isfinite(v), np.maximum(v, 0.0), 0.0)
        return cls(v.mean(axis=(2, 4)), **options)

    def _bins(self, w: NDArray, count: int) -> NDArray:
        theta = np.arccos(np.clip(w[:, 2], -1.0, 1.0))
        return np.clip((theta * (2.0 * count / math.pi)).astype(np.int64), 0, count - 1)

    def sample(self, wi: NDArray, u0: NDArray, u1: NDArray, u2: NDArray
               ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Draw w_o for each w_i from three uniform numbers in [0, 1) (as LobeSampler)."""
        wi = np.asarray(wi, dtype=np.float64)
        u0, u1, u2 = (np.asarray(u, dtype=np.float64) for u in (u0, u1, u2))
        wo = np.zeros((wi.shape[0], 3))
        table = u0 < self.lobe_weight
        if np.any(~table):
            wo[~table] = _cosine_sample(u1[~table], u2[~table])
        if np.any(table):
            wo[table] = self._table_sample(wi[table], u1[table], u2[table])
        pdf = self.pdf(wi, wo)
        ok = (wi[:, 2] > 0) & (wo[:, 2] > 0) & (pdf > 0)
        wo[~ok] = 0.0
        return wo, np.where(ok, pdf, 0.0)

    def _table_sample(self, wi: NDArray, u1: NDArray, u2: NDArray) -> NDArray:
        k_all = self._bins(wi, self.shape[0])
        u1 = np.clip(u1, 0.0, np.nextafter(1.0, 0.0))
        cell = np.empty(wi.shape[0], dtype=np.int64)
        for k in np.unique(k_all):
            sel = k_all == k
            cell[sel] = np.searchsorted(self._cdf[k, 1:], u1[sel], side="right")
        n_cells = self.shape[1] * self.shape[2]
        cell = np.clip(cell, 0, n_cells - 1)
        mass = self._mass[k_all, cell]
        t = np.clip((u1 - self._cdf[k_all, cell]) / np.where(mass > 0, mass, 1.0), 0.0, 1.0)
        j, l = np.divmod(cell, self.shape[2])
        c0, c1 = self._cos_o[j], self._cos_o[j + 1]
        z = c0 - t * (c0 - c1)
        s = np.sqrt(np.maximum(1.0 - z * z, 0.0))
        phi = np.arctan2(wi[:, 1], wi[:, 0]) + (l + u2) * self._dphi
        return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)

    def pdf(self, wi: NDArray, wo: NDArray) -> NDArray[np.float64]:
        """Mixture density of w_o given w_i, per steradian; 0 if either is below the horizon."""
        wi = np.asarray(wi, dtype=np.float64)
        wo = np.asarray(wo, dtype=np.float64)
        up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
        k = self._bins(wi, self.shape[0])
        j = self._bins(wo, self.shape[1])
        rel = np.mod(np.arctan2(wo[:, 1], wo[:, 0]) - np.arctan2(wi[:, 1], wi[:, 0]),
                     2.0 * math.pi)
        l = np.clip((rel / self._dphi).astype(np.int64), 0, self.shape[2] - 1)
        p = (1.0 - self.lobe_weight) * np.maximum(wo[:, 2], 0.0) / math.pi \
            + self.lobe_weight * self._density[k, j * self.shape[2] + l]
        return np.where(up, p, 0.0)


class MixtureSampler:
    """A mixture of samplers (one-sample MIS, Veach 1997, sec. 9.2.2), with its exact density.

    Parameters
    ----------
    samplers : sequence of LobeSampler or TableSampler
        The techniques.
    weights : sequence of float
        Their probabilities (> 0, normalised here).

    Attributes
    ----------
    kind : str
        ``"mixture"``.
    samplers, weights

    Examples
    --------
    >>> m = MixtureSampler([LobeSampler("cosine"), LobeSampler("ggx", lobe_weight=1.0,
    ...                     alpha=0.3)], [0.5, 0.5])
    >>> rng = np.random.default_rng(0)
    >>> wi = np.tile([0.6, 0.0, 0.8], (4, 1))
    >>> wo, pdf = m.sample(wi, *rng.random((3, 4)))
    >>> bool(np.allclose(pdf, m.pdf(wi, wo)))
    True
    """

    kind = "mixture"

    def __init__(self, samplers: Any, weights: Any) -> None:
        self.samplers = list(samplers)
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (len(self.samplers),) or not np.all(w > 0) or not np.all(np.isfinite(w)):
            raise ValueError(f"weights must be one finite value > 0 per sampler "
                             f"({len(self.samplers)}), got {weights!r}")
        self.weights = w / w.sum()
        self._cum = np.concatenate([[0.0], np.cumsum(self.weights)])
        self._cum[-1] = 1.0

    def __repr__(self) -> str:
        parts = ", ".join(f"{w:.2g} {s!r}" for w, s in zip(self.weights, self.samplers,
                                                            strict=True))
        return f"MixtureSampler({parts})"

    def sample(self, wi: NDArray, u0: NDArray, u1: NDArray, u2: NDArray
               ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Draw w_o: u0 picks a technique and, rescaled, is that technique's own u0."""
        wi = np.asarray(wi, dtype=np.float64)
        u0, u1, u2 = (np.asarray(u, dtype=np.float64) for u in (u0, u1, u2))
        wo = np.zeros((wi.shape[0], 3))
        pick = np.clip(np.searchsorted(self._cum[1:], u0, side="right"), 0,
                       len(self.samplers) - 1)
        for k, smp in enumerate(self.samplers):
            sel = pick == k
            if np.any(sel):
                v0 = np.clip((u0[sel] - self._cum[k]) / self.weights[k], 0.0,
                             np.nextafter(1.0, 0.0))
                wo[sel] = smp.sample(wi[sel], v0, u1[sel], u2[sel])[0]
        pdf = self.pdf(wi, wo)
        ok = (wi[:, 2] > 0) & (wo[:, 2] > 0) & (pdf > 0)
        wo[~ok] = 0.0
        return wo, np.where(ok, pdf, 0.0)

    def pdf(self, wi: NDArray, wo: NDArray) -> NDArray[np.float64]:
        """Sum of weight x density of the techniques, per steradian."""
        return sum(w * s.pdf(wi, wo) for w, s in zip(self.weights, self.samplers, strict=True))


# -- choosing the sampler of a representation ------------------------------------------------

def profile(brdf: Any) -> tuple[NDArray, NDArray, float]:
    """Return the half-vector profile of a BRDF: what its normal distribution D(theta_h) would be.

    f is averaged over pairs near the specular configuration (theta_d in 0, 0.2, 0.4 rad, four
    phi_d) at the centre of each theta_h bin of :class:`LobeSampler`; the diffuse floor
    f_0 (the smallest mean below theta_h = 60 degrees, >= 0) is removed, and
    D(theta_h) ~ 4 (f - f_0) cos theta_i cos theta_o, the microfacet relation with G = F = 1.

    Parameters
    ----------
    brdf : BRDF
        Anything with ``eval(wi, wo)``; channels are averaged.

    Returns
    -------
    theta : (TABLE_BINS,) ndarray
        Bin centres (radians).
    d : (TABLE_BINS,) ndarray
        The profile, >= 0 (1/sr).
    floor : float
        f_0 (1/sr): pi f_0 estimates the diffuse albedo.
    """
    edges = 0.5 * math.pi * (np.arange(TABLE_BINS + 1) / TABLE_BINS) ** 2
    theta = 0.5 * (edges[:-1] + edges[1:])
    th, td, pd = np.meshgrid(theta, _PROFILE_TD, _PROFILE_PD, indexing="ij")
    wi, wo = from_rusinkiewicz(th, np.zeros_like(th), td, pd)
    valid = (wi[..., 2] > 1e-6) & (wo[..., 2] > 1e-6)
    wi = np.where(valid[..., None], wi, [0.0, 0.0, 1.0])
    wo = np.where(valid[..., None], wo, [0.0, 0.0, 1.0])
    f = np.asarray(brdf.eval(wi, wo), dtype=np.float64)
    if f.ndim == th.ndim + 1:
        f = f.mean(axis=-1)
    f = np.where(valid & np.isfinite(f), f, 0.0)
    count = np.maximum(valid.sum(axis=(1, 2)), 1)
    mean_f = f.sum(axis=(1, 2)) / count
    floor = max(float(np.min(mean_f[theta <= _FLOOR_THETA])), 0.0)
    q = np.maximum(f - floor, 0.0) * wi[..., 2] * wo[..., 2] * valid
    d = 4.0 * q.sum(axis=(1, 2)) / count
    return theta, d, floor


def _specular_albedo(theta: NDArray, d: NDArray) -> float:
    """Return int D cos theta_h dw_h over the bins of the profile (the lobe's albedo, G = F = 1)."""
    edges = 0.5 * math.pi * (np.arange(TABLE_BINS + 1) / TABLE_BINS) ** 2
    dw = 2.0 * math.pi * -np.diff(np.cos(edges))
    return float(np.sum(d * np.cos(theta) * dw))


def _weight(spec: float, diffuse: float) -> float:
    total = spec + diffuse
    if not total > 0 or spec <= _NO_LOBE * total:
        return 0.0
    return float(np.clip(spec / total, *_WEIGHT_RANGE))


def _microfacet(model: Any) -> tuple[str, float] | None:
    """(distribution, alpha) of a fitted "lambert+ggx" / "lambert+beckmann" model, else None."""
    family = getattr(model, "family", None)
    if family in ("lambert+ggx", "lambert+beckmann"):
        return family.split("+")[1], float(model.params["alpha"])
    return None


def _mass(theta: NDArray, d: NDArray) -> NDArray:
    """Probability of each theta_h bin: D cos theta_h times the bin's solid angle."""
    edges = 0.5 * math.pi * (np.arange(TABLE_BINS + 1) / TABLE_BINS) ** 2
    return d * np.cos(theta) * 2.0 * math.pi * -np.diff(np.cos(edges))


def _table(brdf: Any) -> NDArray | None:
    theta, d, _ = profile(brdf)
    mass = _mass(theta, d)
    return mass if mass.sum() > 0 else None


def _fit_ggx(theta: NDArray, d: NDArray) -> float:
    """GGX alpha whose D, scaled freely, is closest to the profile (weighted least squares)."""
    edges = 0.5 * math.pi * (np.arange(TABLE_BINS + 1) / TABLE_BINS) ** 2
    w = np.cos(theta) * -np.diff(np.cos(edges))
    h = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=1)
    best, best_err = float(_ALPHAS[-1]), np.inf
    for a in _ALPHAS:
        g = _ndf(h, float(a), "ggx")
        s = np.sum(w * g * d) / np.sum(w * g * g)
        err = np.sum(w * (d - s * g) ** 2)
        if s > 0 and err < best_err:
            best, best_err = float(a), err
    return best


def sampler_for(rep: Any, *, incident: str = "light"
                ) -> LobeSampler | TableSampler | MixtureSampler:
    """Choose the importance sampler of a representation.

    The candidates are a :class:`LobeSampler`, for isotropic representations a
    :class:`TableSampler` of f cos(theta_o) on a (16, 32, 64) grid (theta_i, theta_o,
    phi_o - phi_i) and an even :class:`MixtureSampler` of the two (the grid resolves broad
    lobes, the lobe sampler narrow peaks between its nodes), and pure cosine sampling. Each
    draws the same pilot set
    (4096 samples at each of theta_i = 0, 30, 60 and 80 degrees, seeded) and the candidate
    whose sample weights f cos / pdf have the smallest summed relative variance is
    returned (ties go to the first). The lobe sampler is:

    - a fitted ``"lambert+ggx"`` / ``"lambert+beckmann"`` model: visible-normal sampling of
      its lobe (its alpha), weighted by the specular albedo mean(ks) (F0 + (1 - F0) / 21)
      (Schlick's F averaged over the hemisphere) against the diffuse albedo mean(kd);
    - a hybrid: its lobe's sampler (visible normals of a microfacet lobe, else the table of
      the lobe's profile), weighted by the whole hybrid's profile;
    - a coefficient matrix: a GGX lobe fitted to its half-vector :func:`profile`;
    - anything else (factored, tabulated and the other fitted families, measured data): the
      "table" lobe of its profile, the profile times cos theta_h.

    The weights of the last three come from the profile: the lobe's albedo int D cos
    theta_h dw_h against the diffuse pi f_0, the lobe weight clipped to [0.1, 0.9], or no
    lobe when it holds less than 0.1 % of the total.

    Parameters
    ----------
    rep : BRDF
        A :class:`basis.CoefficientMatrix`, :class:`project.FittedModel`,
        :class:`compress.Hybrid` or any object with ``eval(wi, wo)``.
    incident : {"light", "camera"}
        Which of the sampler's directions is the representation's w_i: with "light" (the
        plugin's default in radiance transport) the sampled w_o is the light direction and
        the table holds f(w_o, w_i) cos(theta_o); with "camera", f(w_i, w_o) cos(theta_o).
        Only the efficiency depends on it: every candidate reports its exact density.

    Returns
    -------
    LobeSampler, TableSampler or MixtureSampler
    """
    if incident not in ("light", "camera"):
        raise ValueError(f"incident must be 'light' or 'camera', got {incident!r}")
    cands: list[Any] = [_lobe_sampler(rep)]
    g = _integrand(rep, incident)
    if _isotropic(rep):
        cands.append(TableSampler.from_function(g, TABLE_SHAPE))
    if cands[0].kind != "cosine":
        if len(cands) == 2:  # the table resolves broad lobes, the lobe narrow peaks
            cands.append(MixtureSampler(cands[:2], [0.5, 0.5]))
        cands.append(LobeSampler("cosine"))
    if len(cands) == 1:
        return cands[0]
    scores = [_pilot_score(c, g) for c in cands]
    return cands[int(np.argmin(scores))]


def _isotropic(rep: Any) -> bool:
    """Whether f depends on the azimuths through phi_o - phi_i only (the table's premise)."""
    if isinstance(rep, CoefficientMatrix):
        return bool(rep.is_isotropic)
    return getattr(rep, "isotropic", False) is True


def _integrand(rep: Any, incident: str) -> Any:
    """g(w_i, w_o) = max(f, 0) cos(theta_o), channels averaged, in the plugin's reading."""

    def g(wi: NDArray, wo: NDArray) -> NDArray:
        light, view = (wo, wi) if incident == "light" else (wi, wo)
        f = np.asarray(rep.eval(light, view), dtype=np.float64).reshape(wi.shape[0], -1)
        f = np.where(np.isfinite(f), np.maximum(f, 0.0), 0.0).mean(axis=1)
        return f * np.maximum(wo[:, 2], 0.0)

    return g


def _pilot_score(sampler: Any, g: Any) -> float:
    """Sum over the pilot incidences of var(w) / mean(w)^2 of the weights w = g / pdf."""
    rng = np.random.default_rng(_PILOT_SEED)
    n = _PILOT_N
    th = np.repeat(_PILOT_THETA, n)
    wi = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], axis=1)
    wo, p = sampler.sample(wi, *rng.random((3, th.size)))
    ok = p > 0
    w = np.zeros(th.size)
    w[ok] = g(wi[ok], wo[ok]) / p[ok]
    w = w.reshape(_PILOT_THETA.size, n)
    mean = w.mean(axis=1)
    rel = np.where(mean > 0, w.var(axis=1) / np.where(mean > 0, mean * mean, 1.0), 0.0)
    return float(rel.sum())


def _lobe_sampler(rep: Any) -> LobeSampler:
    """Return the cosine + lobe sampler of a representation (see :func:`sampler_for`)."""
    mf = _microfacet(rep)
    if mf is not None:
        p = rep.params
        f0 = float(p["f0"])
        spec = float(np.mean(p["ks"])) * (f0 + (1.0 - f0) / 21.0)
        return LobeSampler(mf[0], lobe_weight=_weight(spec, float(np.mean(p["kd"]))),
                           alpha=mf[1])
    theta, d, floor = profile(rep)
    weight = _weight(_specular_albedo(theta, d), math.pi * floor)
    if weight == 0.0:
        return LobeSampler("cosine")
    lobe = getattr(rep, "lobe", None)
    if lobe is not None and hasattr(rep, "residual"):  # a Hybrid
        mf = _microfacet(lobe)
        if mf is not None:
            return LobeSampler(mf[0], lobe_weight=weight, alpha=mf[1])
        mass = _table(lobe)
        return LobeSampler("table", lobe_weight=weight, mass=mass) if mass is not None \
            else LobeSampler("cosine")
    if isinstance(rep, CoefficientMatrix):
        return LobeSampler("ggx", lobe_weight=weight, alpha=_fit_ggx(theta, d))
    return LobeSampler("table", lobe_weight=weight, mass=_mass(theta, d))
