"""Stand-ins for goniometer tables of glossy paints, and an independent plain fit to compare with.

Imported as ``tests.project.gonio`` by the fitting and selection tests and by
``tests/benchmarks/bench_gonio.py``. Nothing here is tuned to a particular file:

- :func:`cornell_layout`: the sampling of the Cornell gonioreflectometer tables that pbrt-v2
  distributes (their layout as documented in :mod:`project.measured.tables`: 8 incidences
  theta_i = 10 ... 80 degrees at phi_i = 0, theta_o from 0 to 79.05 degrees, phi_o on both
  sides of the plane of incidence, no theta_o equal to a theta_i), with in-plane sweeps,
  out-of-plane rings, grazing views and positions within a degree or two of the mirror;
- :func:`paint`: an analytic glossy paint over 31 wavelengths (400-700 nm): a coloured
  diffuse base, an optional broader coloured lobe (pigment or flakes, with a colour that may
  shift with angle) and a clear coat (a sharp GGX lobe, alpha 0.002-0.05, with the exact
  Fresnel factor of a dielectric of index 1.5);
- :func:`measure`: what an instrument does to it: a finite detector aperture (a cone of
  0.6 degrees), multiplicative noise, an additive noise floor (small negative values where
  the paint is dark), a few outliers and optionally negative readings clipped to 0;
- :func:`plain_fit`: a plain least-squares fit of Lambert + GGX (kd and ks per channel,
  one alpha >= 0.005, one Schlick F0), absolute residuals of q = f cos cos over all
  channels, multi-start over alpha on a log grid. It shares no code with
  :mod:`project.fitting`: the formulas are written out below;
- :func:`held_out`: the relative l2 error of q and the log error on held-out samples,
  largest over the channels, also written out here.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares, nnls

from basis import from_angles
from project import Measurements

#: The Cornell tables' wavelengths, nm.
WAVELENGTHS = np.arange(400.0, 701.0, 10.0)
#: Half-angle of the detector's cone of acceptance, degrees.
APERTURE_DEG = 0.6


# -- the layout --------------------------------------------------------------------------------
def cornell_layout(seed: int = 0, *, near_mirror: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Return (wi, wo), about 1,440 pairs, in the layout of the Cornell paint tables.

    For each of 8 incidences (theta_i = 10 ... 80 degrees, phi_i = 0): the plane of
    incidence on both sides (phi_o = 180, the specular side, and phi_o = 0), rings of phi_o
    at several elevations, and with ``near_mirror`` a cross of positions within 8 degrees of
    the mirror direction, in and out of the plane (without it, a regular grid of 4-degree
    steps in theta_o and 5 to 10 degrees in phi_o near the plane: the crest of a sharp
    highlight falls between the samples). Elevations are jittered by up to 0.3 degrees
    (seeded) so that no theta_o equals a theta_i, and theta_o <= 79.05 degrees.
    """
    rng = np.random.default_rng(seed)
    ti_all, to_all, po_all = [], [], []
    for ti in np.arange(10.0, 81.0, 10.0):
        to, po = [], []
        if near_mirror:
            # in the plane, specular side: every 4 degrees, and within 8 degrees of the
            # mirror at 0.5 to 2 degree steps
            near = ti + np.array([-8, -6, -4, -3, -2, -1.5, -1, -0.5, 0.5, 1, 1.5, 2, 3, 4,
                                  6, 8])
            for t in np.r_[np.arange(1.0, 80.0, 4.0), near]:
                to.append(t)
                po.append(180.0)
            for t in np.arange(3.0, 80.0, 6.0):  # the back side (towards the source)
                to.append(t)
                po.append(0.0)
            for t in (12.0, 24.0, 36.0, 48.0, 60.0, 70.0, 78.5):  # rings
                for p in np.arange(-165.0, 180.0, 30.0):
                    to.append(t)
                    po.append(p)
            for dp in (-12, -8, -5, -3, -2, -1, 1, 2, 3, 5, 8, 12):  # around the mirror
                for dt in (-1.0, 0.4):
                    to.append(ti + dt)
                    po.append(180.0 + dp)
        else:
            grid = 79.05 - 3.95 * np.arange(20)  # 79.05 ... 3.95 degrees
            for t in grid:
                for p in (180.0, 175.0, -175.0, 165.0, 0.0):
                    to.append(t)
                    po.append(p)
            for t in grid[::2]:
                for p in np.arange(-140.0, 141.0, 40.0):
                    to.append(t)
                    po.append(p)
            to.append(0.5)
            po.append(0.0)
        to = np.array(to) + rng.uniform(-0.3, 0.3, len(to))
        to = np.clip(to, 0.2, 79.05)
        to[np.abs(to - ti) < 0.05] += 0.1
        po = (np.array(po) + 180.0) % 360.0 - 180.0
        po[po == -180.0] = 180.0
        ti_all.append(np.full(len(to), ti))
        to_all.append(to)
        po_all.append(po)
    ti, to, po = (np.radians(np.concatenate(a)) for a in (ti_all, to_all, po_all))
    return from_angles(ti, 0.0), from_angles(to, po)


# -- the paints --------------------------------------------------------------------------------
def _bump(center: float, width: float) -> np.ndarray:
    return np.exp(-0.5 * ((WAVELENGTHS - center) / width) ** 2)


def _ggx_d(hz: np.ndarray, alpha: float) -> np.ndarray:
    a2 = alpha * alpha
    den = hz * hz * (a2 - 1.0) + 1.0
    return a2 / (np.pi * den * den)


def _ggx_g1(c: np.ndarray, alpha: float) -> np.ndarray:
    c = np.maximum(c, 1e-9)
    return 2.0 * c / (c + np.sqrt(alpha * alpha * (1.0 - c * c) + c * c))


def _fresnel_dielectric(cd: np.ndarray, eta: float = 1.5) -> np.ndarray:
    g = np.sqrt(eta * eta - 1.0 + cd * cd)
    a = (g - cd) / (g + cd)
    b = (cd * (g + cd) - 1.0) / (cd * (g - cd) + 1.0)
    return 0.5 * a * a * (1.0 + b * b)


def _lobe(wi: np.ndarray, wo: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """D G / (4 c_i c_o) of GGX (separable Smith) and c_d = w_i . h."""
    h = wi + wo
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    ci, co = np.clip(wi[..., 2], 1e-9, 1.0), np.clip(wo[..., 2], 1e-9, 1.0)
    s = _ggx_d(h[..., 2], alpha) * _ggx_g1(ci, alpha) * _ggx_g1(co, alpha) / (4.0 * ci * co)
    return s, np.clip(np.sum(wi * h, axis=-1), 0.0, 1.0)


class Paint:
    """A glossy paint over :data:`WAVELENGTHS`: f(wi, wo) -> (..., 31) in 1/sr.

    f = (1 - F(c_i)) kd(lambda) / pi + kb(lambda, c_d) D_b G_b / (4 c_i c_o)
        + F(c_d) D_c G_c / (4 c_i c_o): diffuse base, a broader pigment or flake lobe whose
    hue may move with c_d = w_i . h (``shift`` nm from normal to grazing), and a clear coat
    (exact dielectric Fresnel, index 1.5; the factor 1 - F(c_i) is the light the coat lets
    through to the base).
    """

    channels = len(WAVELENGTHS)
    isotropic = True

    def __init__(self, name: str, kd: np.ndarray, alpha_coat: float, *,
                 base: tuple[float, float, float] | None = None, shift: float = 0.0,
                 coat: float = 1.0) -> None:
        self.name, self.kd, self.alpha_coat, self.coat = name, kd, alpha_coat, coat
        self.base, self.shift = base, shift  # base: (strength, hue centre nm, alpha)

    def eval(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        wi, wo = np.asarray(wi, float), np.asarray(wo, float)
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        ci = np.clip(wi[..., 2], 0.0, 1.0)
        f = (1.0 - _fresnel_dielectric(np.maximum(ci, 1e-6)))[..., None] * self.kd / np.pi
        s, cd = _lobe(wi, wo, self.alpha_coat)
        f = f + (self.coat * _fresnel_dielectric(cd) * s)[..., None]
        if self.base is not None:
            strength, centre, alpha = self.base
            sb, cd = _lobe(wi, wo, alpha)
            mid = centre + self.shift * (1.0 - cd)
            hue = np.exp(-0.5 * ((WAVELENGTHS - mid[..., None]) / 60.0) ** 2)
            f = f + strength * (0.1 + hue) * sb[..., None]
        return np.where(up[..., None], f, 0.0)

    def __repr__(self) -> str:
        return f"Paint({self.name!r}, alpha_coat={self.alpha_coat})"


def paints() -> list[Paint]:
    """Eight glossy paints spanning the range of real ones (not fitted to any file).

    Clear coats from alpha 0.002 (a mirror-like finish) to 0.05 (a satin), diffuse bases
    from near-black to bright in one band, with and without a pigment/flake lobe, one with a
    colour shift of 120 nm (an interference pigment).
    """
    return [
        Paint("gloss-red", 0.03 + 0.55 / (1 + np.exp(-(WAVELENGTHS - 600) / 15)), 0.004),
        Paint("gloss-blue", 0.02 + 0.35 * _bump(450, 35), 0.012),
        Paint("satin-green", 0.05 + 0.3 * _bump(530, 40), 0.05),
        Paint("black-lacquer", np.full(len(WAVELENGTHS), 0.015), 0.002),
        Paint("metallic-blue", 0.01 + 0.08 * _bump(460, 40), 0.008, base=(0.3, 470, 0.2)),
        Paint("metallic-silver", np.full(len(WAVELENGTHS), 0.02), 0.02, base=(0.5, 550, 0.12)),
        Paint("pearl-shift", 0.02 + 0.05 * _bump(520, 60), 0.003, base=(0.25, 480, 0.1),
              shift=120.0),
        Paint("candy-red", 0.01 + 0.2 / (1 + np.exp(-(WAVELENGTHS - 620) / 12)), 0.006,
              base=(0.15, 640, 0.3)),
    ]


def rgl_spectral(brdf) -> object:
    """An RGB BRDF seen over :data:`WAVELENGTHS`: B, G, R blended smoothly (450/550/650 nm)."""
    w = np.stack([_bump(450, 45), _bump(550, 45), _bump(650, 45)], axis=1)
    w /= w.sum(axis=1, keepdims=True)

    class Spectral:
        channels = len(WAVELENGTHS)
        isotropic = True
        name = getattr(brdf, "name", None)

        def eval(self, wi, wo):
            rgb = np.asarray(brdf.eval(wi, wo), dtype=float).reshape(*np.shape(wi)[:-1], 3)
            return rgb[..., ::-1] @ w.T  # R, G, B -> B, G, R order of the weights

    return Spectral()


# -- the instrument ----------------------------------------------------------------------------
def _aperture_offsets() -> np.ndarray:
    """Unit offsets of a 7-point disk rule (centre and a hexagon at 2/3 of the radius)."""
    ang = np.arange(6) * np.pi / 3.0
    return np.r_[[[0.0, 0.0]], np.c_[np.cos(ang), np.sin(ang)] * (2.0 / 3.0)]


def measure(brdf, wi: np.ndarray, wo: np.ndarray, *, seed: int, noise: float = 0.03,
            floor: float = 0.002, outliers: float = 0.003, clip: bool = False,
            name: str | None = None) -> Measurements:
    """Virtual measurement: the aperture, multiplicative and additive noise, outliers.

    ``noise``: relative standard deviation (per sample and channel, plus a common factor per
    sample of the same size: lamp drift); ``floor``: additive standard deviation in 1/sr
    (gives small negative values where the paint is dark); ``outliers``: the fraction of
    samples multiplied by a factor in [0.2, 5] in every channel; ``clip``: negative
    readings stored as 0, as some instruments' software does.
    """
    rng = np.random.default_rng(seed)
    # the detector integrates over a cone of APERTURE_DEG about wo
    t1 = np.cross(wo, [0.0, 0.0, 1.0])
    bad = np.linalg.norm(t1, axis=1) < 1e-9
    t1[bad] = [1.0, 0.0, 0.0]
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(wo, t1)
    r = np.radians(APERTURE_DEG)
    f = 0.0
    offsets = _aperture_offsets()
    for u, v in offsets:
        d = wo + r * (u * t1 + v * t2)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d[:, 2] = np.maximum(d[:, 2], 1e-6)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        f = f + np.asarray(brdf.eval(wi, d), dtype=float)
    f = f / len(offsets)
    n, c = f.shape
    f = f * (1.0 + noise * rng.standard_normal((n, 1))) \
        * (1.0 + noise * rng.standard_normal((n, c)))
    f = f + floor * rng.standard_normal((n, c))
    k = max(1, int(round(outliers * n)))
    idx = rng.choice(n, k, replace=False)
    f[idx] *= np.exp(rng.uniform(np.log(0.2), np.log(5.0), (k, 1)))
    if clip:
        f = np.maximum(f, 0.0)
    return Measurements(wi, wo, f, wavelengths=WAVELENGTHS, isotropic=True,
                        name=name or getattr(brdf, "name", None))


# -- the plain fit -----------------------------------------------------------------------------
class PlainFit:
    """Lambert + GGX fitted by plain least squares; ``eval(wi, wo) -> (n, C)``."""

    def __init__(self, kd: np.ndarray, ks: np.ndarray, alpha: float, f0: float) -> None:
        self.kd, self.ks, self.alpha, self.f0 = kd, ks, alpha, f0

    def eval(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        s, cd = _lobe(np.asarray(wi, float), np.asarray(wo, float), self.alpha)
        fr = self.f0 + (1.0 - self.f0) * (1.0 - cd) ** 5
        return self.kd / np.pi + self.ks * (fr * s)[:, None]


def plain_fit(meas: Measurements, alphas: np.ndarray | None = None) -> PlainFit:
    """Plain least squares of q = f cos cos (absolute residuals, all channels at once).

    Parameters kd, ks >= 0 per channel, alpha in [0.005, 1.5], F0 in [0, 1]. kd and ks
    enter linearly: for given (alpha, F0) they are the non-negative least-squares solution
    of each channel (variable projection, Golub & Pereyra 1973), so scipy's trust-region
    reflective least squares runs on (log alpha, F0) alone, on the residuals of all
    channels. Multi-start: from every alpha of a log grid (0.005 to 0.8, 12 values) at
    F0 = 0.05; the lowest cost is kept.
    """
    wi, wo, f = np.asarray(meas.wi), np.asarray(meas.wo), np.asarray(meas.values)
    n, c = f.shape
    cc = wi[:, 2] * wo[:, 2]
    q = f * cc[:, None]
    alphas = np.geomspace(0.005, 0.8, 12) if alphas is None else alphas

    def solve(x):
        s, cd = _lobe(wi, wo, float(np.exp(x[0])))
        fr = x[1] + (1.0 - x[1]) * (1.0 - cd) ** 5
        cols = np.stack([cc / np.pi, fr * s * cc], axis=1)
        lin = np.array([nnls(cols, q[:, ch])[0] for ch in range(c)])  # (c, 2)
        return lin, cols

    def resid(x):
        lin, cols = solve(x)
        return (cols @ lin.T - q).ravel()

    lo, hi = np.array([np.log(0.005), 0.0]), np.array([np.log(1.5), 1.0])
    best = None
    for a in alphas:
        x0 = np.clip([np.log(a), 0.05], lo + 1e-9, hi - 1e-9)
        run = least_squares(resid, x0, bounds=(lo, hi), method="trf", diff_step=1e-4,
                            max_nfev=60)
        if best is None or run.cost < best.cost:
            best = run
    lin, _ = solve(best.x)
    return PlainFit(lin[:, 0], lin[:, 1], float(np.exp(best.x[0])), float(best.x[1]))


# -- errors ------------------------------------------------------------------------------------
def held_out(meas: Measurements, pred: np.ndarray) -> tuple[float, float]:
    """Relative l2 of q and RMS log error on samples, each the largest over the channels.

    l2 = sqrt(sum w (q_hat - q)^2 / sum w q^2); log: RMS of log(1 + max(f, 0) cos theta_i)
    minus the same of the prediction (the metrics of :mod:`project.crossval`, written out).
    """
    f, g = np.asarray(meas.values), np.asarray(pred).reshape(len(meas), -1)
    w = np.asarray(meas.weights)[:, None]
    ci = meas.wi[:, 2:3]
    cc = ci * meas.wo[:, 2:3]
    l2 = np.sqrt(np.sum(w * ((g - f) * cc) ** 2, axis=0) / np.sum(w * (f * cc) ** 2, axis=0))
    d = np.log1p(np.maximum(f, 0) * ci) - np.log1p(np.maximum(g, 0) * ci)
    lg = np.sqrt(np.sum(w * d * d, axis=0) / np.sum(w, axis=0))
    return float(l2.max()), float(lg.max())


def split(meas: Measurements, seed: int) -> tuple[Measurements, Measurements]:
    """An 80/20 split of the samples (seeded): (train, test)."""
    test = np.random.default_rng(seed).permutation(len(meas)) < round(0.2 * len(meas))
    return meas[~test], meas[test]


# -- car paints --------------------------------------------------------------------------------
class CarPaint:
    """An RGB car paint: clear coat, metallic flake lobe with a colour shift, diffuse base.

    f = (1 - F(c_i)) kd / pi + k_f(c_d) D_f G_f / (4 c_i c_o) + F(c_d) D_c G_c / (4 c_i c_o):
    flakes a broad GGX lobe (``alpha_flake`` 0.1-0.3) whose colour moves from ``face`` (at
    the mirror direction of normal incidence, c_d = 1) to ``flop`` (grazing), a clear coat
    a sharp GGX lobe (``alpha_coat`` 0.01-0.03) with the Fresnel factor of index 1.5.
    """

    channels = 3
    isotropic = True

    def __init__(self, name: str, kd, face, flop, alpha_flake: float, alpha_coat: float):
        self.name = name
        self.kd, self.face, self.flop = (np.asarray(v, float) for v in (kd, face, flop))
        self.alpha_flake, self.alpha_coat = alpha_flake, alpha_coat

    def eval(self, wi, wo):
        wi, wo = np.asarray(wi, float), np.asarray(wo, float)
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        ci = np.clip(wi[..., 2], 0.0, 1.0)
        f = (1.0 - _fresnel_dielectric(np.maximum(ci, 1e-6)))[..., None] * self.kd / np.pi
        s, cd = _lobe(wi, wo, self.alpha_coat)
        f = f + (_fresnel_dielectric(cd) * s)[..., None]
        s, cd = _lobe(wi, wo, self.alpha_flake)
        t = ((1.0 - cd) ** 0.5)[..., None]
        f = f + ((1.0 - t) * self.face + t * self.flop) * s[..., None]
        return np.where(up[..., None], f, 0.0)

    def __repr__(self) -> str:
        return f"CarPaint({self.name!r})"


def car_paints() -> list[CarPaint]:
    """Three car paints: a red metallic, a blue pearl with a strong flop, a silver."""
    return [
        CarPaint("red-metallic", [0.10, 0.01, 0.01], [0.9, 0.12, 0.08], [0.35, 0.02, 0.03],
                 0.2, 0.02),
        CarPaint("blue-pearl", [0.01, 0.02, 0.08], [0.15, 0.35, 0.9], [0.35, 0.05, 0.5],
                 0.12, 0.01),
        CarPaint("silver", [0.05, 0.05, 0.05], [0.9, 0.9, 0.92], [0.25, 0.26, 0.3], 0.3,
                 0.03),
    ]


def sparkle(table: np.ndarray, seed: int, sigma: float = 0.15,
            floor: float = 0.003) -> np.ndarray:
    """A measured table's noise: flake glints (lognormal, per cell) and a noise floor."""
    rng = np.random.default_rng(seed)
    glint = np.exp(sigma * rng.standard_normal(table.shape[:3] + (1,)) - 0.5 * sigma ** 2)
    return table * glint + floor * rng.standard_normal(table.shape)
