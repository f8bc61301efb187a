"""Directional-diffuse scattering at a facet with a microscale BRDF (batched, numpy).

One event, for n rays at once, in the facet's local frame (z = facet normal): given the
direction towards the light w_i and uniforms u, choose w_o and the weight factor
f(w_i, w_o) cos(theta_o) / pdf(w_o), so that E[factor delta(w - w_o)] = f(w_i, w) cos(theta)
(unbiased; Westin et al. 1992, sec. 4.4, eqs 23-24, with one importance-sampled ray instead
of n uniform ones).

Sampling the smooth part: the one-sample mixture (balance-heuristic) density

    pdf(w_o) = (1 - p) cos(theta_o) / pi + p pdf_lobe(w_o),

with a lobe sampler for the models that have a closed-form one (CookTorrance: the
half-vector density D(h) cos(theta_h) of Beckmann or GGX, pdf_o = D h_z / (4 |w_o . h|);
Phong: (n + 1)/(2 pi) cos^n(alpha) about the mirror direction; BlinnPhong: the same in the
half vector, divided by 4 |w_o . h|), the BRDF's own sampler when it has ``sample(wi, u)``
and ``pdf(wi, wo)`` methods (e.g. :class:`project.MatrixBRDF`: two uniforms per sample, a
density that integrates to 1 over the upper hemisphere and is exactly the density of
``sample``), and p = 0 (pure cosine sampling, factor pi f) for every other BRDF. Because
the cosine density is part of every mixture, pdf > 0 wherever f cos(theta_o) > 0, so the
estimator is unbiased for any non-negative BRDF; the mixture fraction p only changes the
variance.

Ideal mirror terms (``brdf.delta``): at each event the mirror is chosen with probability
P = R / (R + A), clipped to [0.05, 0.95], where R is the summed delta reflectance at the local
theta_i and A a tabulated estimate of the smooth part's directional albedo (linear in
cos theta_i, azimuth 0). The mirror branch has factor R / P, the smooth branch its factor
divided by 1 - P: unbiased for any P in (0, 1); a poor estimate A only costs variance.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from basis.quadrature import hemisphere_rule

__all__ = ["FacetSampler"]

#: cos(theta_i) nodes of the smooth-albedo table (estimates for the delta/smooth choice)
_TABLE_COS = np.linspace(0.05, 1.0, 8)
#: mixture fraction of the lobe sampler is clipped to this range (the cosine part stays as a
#: defensive density: it bounds the weight where the lobe sampler's pdf is small)
_LOBE_RANGE = (0.25, 0.9)
#: the delta/smooth choice probability is clipped to this range
_DELTA_RANGE = (0.05, 0.95)


class FacetSampler:
    """Importance sampler and weight of one microscale BRDF (validated at construction).

    Parameters
    ----------
    brdf : BRDF
        One channel, evaluated in the facet frame.

    Attributes
    ----------
    lobe : str or None
        Name of the lobe sampler used in the mixture ("beckmann", "ggx", "phong",
        "blinn-phong", or "brdf" for the BRDF's own ``sample`` and ``pdf``), None for pure
        cosine sampling.
    lobe_fraction : float
        Mixture probability p of the lobe sampler (0 without one).
    uniforms : int
        Uniform numbers used per event (2, plus one per discrete choice).
    """

    def __init__(self, brdf: object) -> None:
        self.brdf = brdf
        self.deltas = tuple(getattr(brdf, "delta", ()) or ())
        rule = hemisphere_rule(16, 32)
        st = np.sqrt(1.0 - _TABLE_COS**2)
        wi = np.stack([st, np.zeros_like(st), _TABLE_COS], axis=-1)
        f = np.asarray(brdf.eval(wi[:, None, :], rule.points[None, :, :]), dtype=np.float64)
        f = f.reshape(wi.shape[0], rule.points.shape[0])
        if not np.all(np.isfinite(f)):
            raise ValueError("brdf must return finite values, got NaN or inf on a test grid")
        if np.any(f < 0):
            raise ValueError(f"brdf must be non-negative, got values down to {f.min():.3g} "
                             "on a test grid")
        self.albedo_table = f @ (rule.weights * rule.points[:, 2])
        self.lobe, self._lobe_params, kd = _lobe_of(brdf)
        if self.lobe is not None:
            spec = max(float(self.albedo_table.max()) - kd, 0.0)
            p = spec / (spec + kd) if spec + kd > 0 else 0.0
            self.lobe_fraction = float(np.clip(p, *_LOBE_RANGE))
        else:
            self.lobe_fraction = 0.0
        self.uniforms = 2 + (self.lobe is not None) + bool(self.deltas)

    def scatter(self, wi: NDArray, u: NDArray) -> tuple[NDArray, NDArray]:
        """Draw new directions and weight factors for n events.

        Parameters
        ----------
        wi : (n, 3) ndarray
            Unit vectors towards the light in the facet frame, z >= 0.
        u : (n, uniforms) ndarray
            Uniforms in [0, 1).

        Returns
        -------
        wo : (n, 3) ndarray
            Unit vectors (may point below the facet when the factor is 0).
        factor : (n,) ndarray
            f cos(theta_o) / pdf (the delta branch: R / P), >= 0.
        """
        n = wi.shape[0]
        wo = np.empty((n, 3))
        factor = np.zeros(n)
        col = 0
        smooth = np.ones(n, dtype=bool)
        p_smooth = np.ones(n)
        if self.deltas:
            ci = wi[:, 2]
            r = np.zeros(n)
            for d in self.deltas:
                r += d.reflectance(ci)[:, 0]
            a = np.interp(ci, _TABLE_COS, self.albedo_table)
            tot = r + a
            p = np.clip(np.divide(r, tot, out=np.full(n, 0.5), where=tot > 0), *_DELTA_RANGE)
            mirror = u[:, col] < p
            col += 1
            wo[mirror] = wi[mirror] * np.array([-1.0, -1.0, 1.0])
            factor[mirror] = r[mirror] / p[mirror]
            smooth = ~mirror
            p_smooth = 1.0 - p
        rows = np.flatnonzero(smooth)
        if rows.size:
            w_s = wi[rows]
            us = u[rows]
            if self.lobe is not None:
                use_lobe = us[:, col] < self.lobe_fraction
                col += 1
            else:
                use_lobe = np.zeros(rows.size, dtype=bool)
            o = _cosine(us[:, col], us[:, col + 1])
            if np.any(use_lobe):
                o[use_lobe] = self._lobe_sample(w_s[use_lobe], us[use_lobe, col],
                                                us[use_lobe, col + 1])
            pdf = (1.0 - self.lobe_fraction) * np.maximum(o[:, 2], 0.0) / np.pi
            if self.lobe is not None:
                pdf += self.lobe_fraction * self._lobe_pdf(w_s, o)
            f = np.asarray(self.brdf.eval(w_s, o), dtype=np.float64).reshape(rows.size)
            if np.any(f < 0) or not np.all(np.isfinite(f)):
                bad = float(f[~(f >= 0)][0])
                raise ValueError(f"brdf must be finite and non-negative, got {bad!r} at "
                                 "a sampled direction pair")
            ok = (pdf > 0) & (o[:, 2] > 0)
            fac = np.zeros(rows.size)
            fac[ok] = f[ok] * o[ok, 2] / (pdf[ok] * p_smooth[rows][ok])
            wo[rows] = o
            factor[rows] = fac
        return wo, factor

    # -- lobe samplers (closed-form densities) -------------------------------------------

    def _lobe_sample(self, wi: NDArray, u1: NDArray, u2: NDArray) -> NDArray:
        kind, q = self.lobe, self._lobe_params
        if kind == "brdf":
            return np.asarray(self.brdf.sample(wi, np.stack([u1, u2], axis=-1)), np.float64)
        if kind in ("beckmann", "ggx", "blinn-phong"):
            if kind == "beckmann":
                t2 = -q * q * np.log1p(-u1)  # tan^2 theta_h, exponential with mean m^2
                cz = 1.0 / np.sqrt(1.0 + t2)
            elif kind == "ggx":
                t2 = q * q * u1 / (1.0 - u1)
                cz = 1.0 / np.sqrt(1.0 + t2)
            else:
                cz = (1.0 - u1) ** (1.0 / (q + 1.0))  # (1 - u) in (0, 1]: cz > 0
            h = _around_z(cz, u2)
            wo = 2.0 * np.sum(wi * h, axis=1)[:, None] * h - wi
        else:  # phong: cos^n about the mirror direction
            r = wi * np.array([-1.0, -1.0, 1.0])
            ca = (1.0 - u1) ** (1.0 / (q + 1.0))
            wo = _rotate(r, _around_z(ca, u2))
        return wo / np.linalg.norm(wo, axis=1)[:, None]

    def _lobe_pdf(self, wi: NDArray, wo: NDArray) -> NDArray:
        kind, q = self.lobe, self._lobe_params
        if kind == "brdf":
            return np.asarray(self.brdf.pdf(wi, wo), dtype=np.float64).reshape(wi.shape[0])
        if kind == "phong":
            ca = np.sum(wo * (wi * np.array([-1.0, -1.0, 1.0])), axis=1)
            return np.where(ca > 0, (q + 1.0) / (2.0 * np.pi) * np.maximum(ca, 0.0) ** q, 0.0)
        h = wi + wo
        norm = np.linalg.norm(h, axis=1)
        ok = norm > 0
        h = np.where(ok[:, None], h / np.where(ok, norm, 1.0)[:, None], 0.0)
        h *= np.where(h[:, 2] < 0, -1.0, 1.0)[:, None]  # the sampled h has h_z >= 0
        cz = h[:, 2]
        dot = np.abs(np.sum(wo * h, axis=1))
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            c2 = cz * cz
            if kind == "beckmann":
                t2 = (1.0 - c2) / c2
                d = np.exp(-t2 / (q * q)) / (np.pi * q * q * c2 * c2)
            elif kind == "ggx":
                t2 = (1.0 - c2) / c2
                d = q * q / (np.pi * c2 * c2 * (q * q + t2) ** 2)
            else:  # blinn-phong: p_h = (n + 1)/(2 pi) h_z^n = D(h) h_z
                d = (q + 1.0) / (2.0 * np.pi) * cz ** (q - 1.0)
            pdf = d * cz / (4.0 * dot)
        return np.where(ok & (cz > 0) & (dot > 0) & np.isfinite(pdf), pdf, 0.0)


def _lobe_of(brdf: object) -> tuple[str | None, float, float]:
    """Return (sampler name, its parameter, Lambertian kd) for the models with a lobe sampler."""
    from project.models import BlinnPhong, CookTorrance, Phong

    if callable(getattr(brdf, "sample", None)) and callable(getattr(brdf, "pdf", None)):
        # its own sampler follows the whole of f cos (kd = 0): the mixture fraction is the
        # top of the range, the cosine part stays as the defensive density
        return "brdf", 0.0, 0.0
    if isinstance(brdf, CookTorrance):
        return brdf.distribution, float(brdf._raw["roughness"][0]), float(brdf._raw["kd"][0])
    if isinstance(brdf, (Phong, BlinnPhong)):
        if float(brdf._raw["ks"][0]) == 0.0:
            return None, 0.0, float(brdf._raw["kd"][0])
        name = "phong" if isinstance(brdf, Phong) else "blinn-phong"
        return name, float(brdf._raw["n"][0]), float(brdf._raw["kd"][0])
    return None, 0.0, 0.0


def _cosine(u1: NDArray, u2: NDArray) -> NDArray:
    """Return cosine-distributed unit vectors about z (pdf cos(theta) / pi)."""
    r = np.sqrt(u1)
    phi = 2.0 * np.pi * u2
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - u1, 0.0))],
                    axis=-1)


def _around_z(cz: NDArray, u2: NDArray) -> NDArray:
    """Return unit vectors with z = cz and azimuth 2 pi u2."""
    s = np.sqrt(np.maximum((1.0 - cz) * (1.0 + cz), 0.0))
    phi = 2.0 * np.pi * u2
    return np.stack([s * np.cos(phi), s * np.sin(phi), cz], axis=-1)


def _rotate(axis: NDArray, v: NDArray) -> NDArray:
    """Express v, given in a frame whose z is the unit ``axis`` (Duff et al. 2017), in world."""
    nx, ny, nz = axis[:, 0], axis[:, 1], axis[:, 2]
    sign = np.where(nz >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    t = np.stack([1.0 + sign * nx * nx * a, sign * b, -sign * nx], axis=-1)
    c = np.stack([b, sign + ny * ny * a, -ny], axis=-1)
    return v[:, 0:1] * t + v[:, 1:2] * c + v[:, 2:3] * axis


def facet_frame(g: NDArray) -> tuple[NDArray, NDArray]:
    """Return the tangent t and bitangent b of facets with unit normals g (g_z > 0).

    Both have shape (n, 3).

    t is the world x axis projected onto the facet plane, so anisotropic microscale BRDFs
    keep their x axis along the mean plane's x; (t, b, g) is right-handed.
    """
    t = -g[:, 0:1] * g
    t[:, 0] += 1.0
    t /= np.linalg.norm(t, axis=1)[:, None]
    return t, np.cross(g, t)
