"""The importance samplers of :mod:`compress.mitsuba._sampling` in Dr.Jit operations.

:func:`traced_sampler` turns the sampler that :func:`compress.mitsuba.sampler_for` chose
(built and chosen with numpy at load time) into an object whose ``sample`` and ``pdf`` are
written with Dr.Jit operations, so that Mitsuba traces them into its kernels. Each draws the
same distribution as the numpy sampler and reports the same density (to float32 rounding):

- cosine: ``mi.warp.square_to_cosine_hemisphere``;
- "ggx" and "beckmann" lobes: visible-normal sampling by ``mi.MicrofacetDistribution``
  (Heitz 2018 for GGX; Heitz & d'Eon 2014 for Beckmann, inverted numerically as the numpy
  sampler does) and its density, reflected about the sampled normal (Jacobian
  1 / (4 w_i . h), Walter et al. 2007);
- the "table" lobe: the inverse CDF over theta_h bins by ``dr.binary_search`` on a device
  copy of the CDF;
- :class:`~compress.mitsuba._sampling.TableSampler`: the inverse CDF over the (theta_o,
  azimuth) cells of the bin of theta_i, likewise;
- :class:`~compress.mitsuba._sampling.MixtureSampler`: u0 picks a technique and, rescaled,
  is its own u0 (all techniques are traced, the pick selects).
"""

from __future__ import annotations

import math
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from ._sampling import TABLE_BINS, LobeSampler, MixtureSampler, TableSampler

__all__ = ["traced_sampler"]

_INV_PI = 1.0 / math.pi
#: The largest float32 below 1: u in [0, 1) stays so after rescaling.
_ONE_MINUS = float(np.nextafter(np.float32(1.0), np.float32(0.0)))


def traced_sampler(sampler: Any) -> Any:
    """Return the Dr.Jit twin of a numpy sampler, or None for a kind it does not know.

    Parameters
    ----------
    sampler : LobeSampler, TableSampler or MixtureSampler

    Returns
    -------
    object or None
        With ``sample(wi, u0, u) -> (wo, pdf)`` (``wi`` a unit ``mi.Vector3f``, ``u0`` a
        ``mi.Float``, ``u`` a ``mi.Point2f``; ``pdf`` 0 for a failed sample) and
        ``pdf(wi, wo) -> mi.Float``.
    """
    if isinstance(sampler, LobeSampler):
        return _Lobe(sampler)
    if isinstance(sampler, TableSampler):
        return _Table(sampler)
    if isinstance(sampler, MixtureSampler):
        parts = [traced_sampler(s) for s in sampler.samplers]
        return None if any(p is None for p in parts) else _Mixture(parts, sampler.weights)
    return None


def _cosine(u: Any) -> Any:
    return mi.warp.square_to_cosine_hemisphere(u)


class _Lobe:
    """Cosine sampling mixed with one lobe of the half vector (see ``LobeSampler``)."""

    def __init__(self, s: LobeSampler) -> None:
        self.kind = s.kind
        self.weight = float(s.lobe_weight)
        self.distr = None
        if s.kind in ("ggx", "beckmann"):
            kind = mi.MicrofacetType.GGX if s.kind == "ggx" else mi.MicrofacetType.Beckmann
            self.distr = mi.MicrofacetDistribution(kind, float(s.alpha), True)
            self.alpha = float(s.alpha)
        elif s.kind == "table":
            self.cdf = mi.Float(s._cdf)
            self.mass = mi.Float(s.mass)
            self.density = mi.Float(s._density)
            self.cos_edges = mi.Float(s._cos_edges)

    def _half(self, wi: Any, u: Any) -> Any:
        if self.distr is not None:
            return self.distr.sample(wi, u)[0]
        u1 = dr.minimum(u.x, _ONE_MINUS)
        # first bin k with cdf[k + 1] > u1 (numpy: searchsorted(cdf[1:], u1, "right"))
        k = dr.binary_search(0, TABLE_BINS - 1,
                             lambda i: dr.gather(mi.Float, self.cdf, i + 1) <= u1)
        c_k = dr.gather(mi.Float, self.cdf, k)
        m_k = dr.gather(mi.Float, self.mass, k)
        t = dr.clip((u1 - c_k) / dr.maximum(m_k, 1e-30), 0.0, 1.0)
        c0 = dr.gather(mi.Float, self.cos_edges, k)
        c1 = dr.gather(mi.Float, self.cos_edges, k + 1)
        z = c0 - t * (c0 - c1)
        s = dr.safe_sqrt(1.0 - z * z)
        sp, cp = dr.sincos(2.0 * math.pi * u.y)
        return mi.Vector3f(s * cp, s * sp, z)

    def _half_pdf(self, wi: Any, h: Any) -> Any:
        if self.distr is not None:
            # D(h) G1(w_i) (w_i . h) / cos theta_i with the exact Smith G1 of the numpy
            # sampler (Mitsuba's own pdf approximates the Beckmann G1 by a rational fit)
            a = self.alpha
            a2 = a * a
            z2 = h.z * h.z
            s2 = dr.maximum(dr.fma(h.x, h.x, h.y * h.y), 0.0)
            if self.kind == "ggx":
                den = dr.fma(a2, z2, s2)
                d = a2 * _INV_PI / dr.maximum(den * den, 1e-30)
            else:
                z2 = dr.maximum(z2, 1e-30)
                d = dr.select(h.z > 0.0, dr.exp(-s2 / (z2 * a2)) * (_INV_PI / a2) / (z2 * z2),
                              0.0)
            c = dr.clip(wi.z, 1e-6, 1.0)
            sn = dr.safe_sqrt(1.0 - c * c)
            if self.kind == "ggx":
                g1 = 2.0 * c / (c + dr.sqrt(dr.fma(c, c, dr.square(a * sn))))
            else:
                big = sn <= 0.0
                x = c / dr.select(big, 1.0, a * sn)
                lam = 0.5 * (dr.erf(x) - 1.0) + dr.exp(-x * x) * (0.5 / math.sqrt(math.pi)) / x
                g1 = dr.select(big, 1.0, dr.rcp(1.0 + dr.maximum(lam, 0.0)))
            return d * g1 * dr.maximum(dr.dot(wi, h), 0.0) / c
        theta = dr.atan2(dr.sqrt(dr.fma(h.x, h.x, h.y * h.y)), h.z)  # exact near the pole
        k = mi.UInt32(dr.clip(dr.floor(TABLE_BINS * dr.safe_sqrt(theta * (2.0 / math.pi))),
                              0.0, TABLE_BINS - 1.0))
        return dr.gather(mi.Float, self.density, k)

    def sample(self, wi: Any, u0: Any, u: Any) -> tuple[Any, Any]:
        if self.weight == 0.0:
            wo = _cosine(u)
        else:
            h = self._half(wi, u)
            lobe_wo = 2.0 * dr.dot(wi, h) * h - wi
            wo = dr.select(u0 < self.weight, lobe_wo, _cosine(u))
        p = self.pdf(wi, wo)
        ok = (wi.z > 0.0) & (wo.z > 0.0) & (p > 0.0)
        return dr.select(ok, wo, 0.0), dr.select(ok, p, 0.0)

    def pdf(self, wi: Any, wo: Any) -> Any:
        up = (wi.z > 0.0) & (wo.z > 0.0)
        p = (1.0 - self.weight) * _INV_PI * dr.maximum(wo.z, 0.0)
        if self.weight > 0.0:
            h = wi + wo
            hn = dr.norm(h)
            good = up & (hn > 0.0)
            h = h * dr.rcp(dr.select(good, hn, 1.0))
            ih = dr.dot(wi, h)
            good &= ih > 0.0
            ph = dr.select(good, self._half_pdf(wi, h), 0.0)
            p = p + self.weight * ph / (4.0 * dr.select(good, ih, 1.0))
        return dr.select(up, p, 0.0)


class _Table:
    """Per bin of theta_i a density of w_o over (theta_o, azimuth) cells, mixed with cosine."""

    def __init__(self, s: TableSampler) -> None:
        self.k, self.j, self.l = s.shape
        self.weight = float(s.lobe_weight)
        self.cdf = mi.Float(np.ascontiguousarray(s._cdf).reshape(-1))
        self.mass = mi.Float(np.ascontiguousarray(s._mass).reshape(-1))
        self.density = mi.Float(np.ascontiguousarray(s._density).reshape(-1))
        self.cos_o = mi.Float(s._cos_o)
        self.dphi = float(s._dphi)

    @staticmethod
    def _bin(z: Any, count: int) -> Any:
        theta = dr.safe_acos(z)
        return mi.UInt32(dr.clip(dr.floor(theta * (2.0 * count / math.pi)), 0.0, count - 1.0))

    def sample(self, wi: Any, u0: Any, u: Any) -> tuple[Any, Any]:
        cells = self.j * self.l
        k = self._bin(wi.z, self.k)
        u1 = dr.minimum(u.x, _ONE_MINUS)
        row = k * (cells + 1)
        cell = dr.binary_search(0, cells - 1,
                                lambda i: dr.gather(mi.Float, self.cdf, row + i + 1) <= u1)
        mass = dr.gather(mi.Float, self.mass, k * cells + cell)
        c_lo = dr.gather(mi.Float, self.cdf, row + cell)
        t = dr.clip((u1 - c_lo) / dr.select(mass > 0.0, mass, 1.0), 0.0, 1.0)
        j = cell // self.l
        l = cell - j * self.l
        c0 = dr.gather(mi.Float, self.cos_o, j)
        c1 = dr.gather(mi.Float, self.cos_o, j + 1)
        z = c0 - t * (c0 - c1)
        s = dr.safe_sqrt(1.0 - z * z)
        phi = dr.atan2(wi.y, wi.x) + (mi.Float(l) + u.y) * self.dphi
        sp, cp = dr.sincos(phi)
        wo = dr.select(u0 < self.weight, mi.Vector3f(s * cp, s * sp, z), _cosine(u))
        p = self.pdf(wi, wo)
        ok = (wi.z > 0.0) & (wo.z > 0.0) & (p > 0.0)
        return dr.select(ok, wo, 0.0), dr.select(ok, p, 0.0)

    def pdf(self, wi: Any, wo: Any) -> Any:
        up = (wi.z > 0.0) & (wo.z > 0.0)
        k = self._bin(wi.z, self.k)
        j = self._bin(wo.z, self.j)
        rel = dr.atan2(wo.y, wo.x) - dr.atan2(wi.y, wi.x)
        rel = dr.select(rel < 0.0, rel + 2.0 * math.pi, rel)
        l = mi.UInt32(dr.clip(dr.floor(rel * (1.0 / self.dphi)), 0.0, self.l - 1.0))
        d = dr.gather(mi.Float, self.density, (k * self.j + j) * self.l + l)
        p = (1.0 - self.weight) * _INV_PI * dr.maximum(wo.z, 0.0) + self.weight * d
        return dr.select(up, p, 0.0)


class _Mixture:
    def __init__(self, parts: list, weights: Any) -> None:
        self.parts = parts
        self.weights = [float(w) for w in weights]
        self.cum = [float(c) for c in np.concatenate([[0.0], np.cumsum(weights)])]
        self.cum[-1] = 1.0

    def sample(self, wi: Any, u0: Any, u: Any) -> tuple[Any, Any]:
        wo = mi.Vector3f(0.0)
        for k, part in enumerate(self.parts):
            v0 = dr.clip((u0 - self.cum[k]) * (1.0 / self.weights[k]), 0.0, _ONE_MINUS)
            w_k, _ = part.sample(wi, v0, u)
            wo = w_k if k == 0 else dr.select(u0 >= self.cum[k], w_k, wo)
        p = self.pdf(wi, wo)
        ok = (wi.z > 0.0) & (wo.z > 0.0) & (p > 0.0)
        return dr.select(ok, wo, 0.0), dr.select(ok, p, 0.0)

    def pdf(self, wi: Any, wo: Any) -> Any:
        p = None
        for w, part in zip(self.weights, self.parts, strict=True):
            v = w * part.pdf(wi, wo)
            p = v if p is None else p + v
        return p
