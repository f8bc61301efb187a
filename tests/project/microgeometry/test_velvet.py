"""Velvet: geometry of the fibre pile, energy balance, the lossless limit, isotropy, and the
velvet signature (grazing sheen and retroreflection), with bad input.

Monte Carlo assertions use k = 5 standard errors with fixed seeds (as test_scene.py). The
signature tests compare cone-averaged reflectances f (energy leaving within 10 degrees of a
direction c, divided by N and by int_cone cos(theta_o) d omega = Omega c_z (1 + cos 10) / 2)
against the Lambertian f = R / pi of the same directional albedo R; the numbers quoted in the
comments were measured with the seeds used here.
"""

from __future__ import annotations

import numpy as np
import pytest

from basis import HemiHarmonics
from project.microgeometry import Dielectric, Diffuse, Mirror, Scene, simulate, trace, velvet
from project.microgeometry.trace import ROULETTE
from tests.project.mc import K_SIGMA, rotated_z, rotation_action

#: a black velvet in micrometres: fibres of radius 5 and length 300, 40 um apart on average,
#: tilted up to 0.3 rad (17 degrees), dyed (sigma = 0.03 / um: 26 % lost across a diameter)
DYED = {"radius": 5.0, "length": 300.0, "density": 6.25e-4, "tilt": 0.3, "absorption": 0.03,
        "count": 200, "seed": 1}

CONE = np.radians(10.0)


def _dir(theta_deg: float, phi_deg: float = 0.0) -> np.ndarray:
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def cone_reflectance(paths, c: np.ndarray) -> tuple[float, float]:
    """(f, standard error): mean reflectance f of the exits within CONE of direction c."""
    x = paths.weights * (paths.directions @ c > np.cos(CONE))
    norm = 2 * np.pi * (1 - np.cos(CONE)) * c[2] * (1 + np.cos(CONE)) / 2
    return x.mean() / norm, x.std() / np.sqrt(x.size) / norm


def tubes(scene: Scene) -> np.ndarray:
    """(n, 9) tube rows (x0, y0, z0, x1, y1, z1, r, caps, 0) of a scene."""
    return np.concatenate([p.rows for p in scene.parts if p.kind == "tube"])


# -- geometry ---------------------------------------------------------------------------------

def test_velvet_geometry():
    s = velvet(5.0, 300.0, 6.25e-4, tilt=0.3, count=400, seed=3)
    t = tubes(s)
    # 400 fibres at 6.25e-4 per um^2: a square period of 800 um
    np.testing.assert_allclose(s.period, [800.0, 800.0], rtol=1e-15)
    assert t.shape == (400, 9) and np.all(t[:, 6] == 5.0) and np.all(t[:, 7] == 1.0)
    axis = t[:, 3:6] - t[:, 0:3]
    total = np.linalg.norm(axis, axis=1)
    axis /= total[:, None]
    cos_t = axis[:, 2]
    # tilts fill the cone up to 0.3 rad, uniformly in solid angle: cos(theta) uniform on
    # [cos 0.3, 1] (Kolmogorov-Smirnov distance, 1.63 / sqrt(n) is its 1 % point)
    assert np.all(cos_t >= np.cos(0.3) - 1e-15)
    u = np.sort((1 - cos_t) / (1 - np.cos(0.3)))
    ks = np.max(np.maximum(np.arange(1, 401) / 400 - u, u - np.arange(400) / 400))
    assert ks < 1.63 / np.sqrt(400)
    # random azimuths: the mean horizontal direction is ~0 (sigma 1 / sqrt(2 n) per axis)
    h = axis[:, :2] / np.linalg.norm(axis[:, :2], axis=1)[:, None]
    assert np.all(np.abs(h.mean(axis=0)) < K_SIGMA / np.sqrt(800))
    # each fibre stands `length` above the plane along its axis, feet inside the period, and
    # the highest point of its bottom cap (z0 + r sin theta) is below the base plane
    foot_t = -t[:, 2] / axis[:, 2]
    foot = t[:, 0:3] + foot_t[:, None] * axis
    np.testing.assert_allclose(total - foot_t, 300.0, rtol=1e-13)
    assert np.all((foot[:, :2] >= 0) & (foot[:, :2] < 800.0))
    assert np.all(t[:, 2] + 5.0 * np.sqrt(1 - cos_t ** 2) < 0)
    # the same seed gives the same pile
    np.testing.assert_array_equal(tubes(velvet(5.0, 300.0, 6.25e-4, tilt=0.3, count=400,
                                               seed=3)), t)


# -- energy -----------------------------------------------------------------------------------

@pytest.mark.parametrize("theta", [0.0, 60.0, 85.0])
def test_lossless_velvet_reflects_everything(theta):
    # clear fibres on a white base: no absorption anywhere, weights never change, so every
    # ray leaves with weight exactly 1 (after up to thousands of fibre events: light guided
    # along fibres by total internal reflection)
    s = velvet(5.0, 300.0, 6.25e-4, tilt=0.3, base=Diffuse(1.0), count=200, seed=1)
    p = trace(s, _dir(theta, 40.0), 4000, seed=3)
    assert p.lost.sum() == 0.0 and np.all(p.weights == 1.0) and np.all(p.absorbed == 0.0)
    assert np.all(p.directions[:, 2] > 0) and p.bounces.mean() > 5


def test_velvet_energy_closes():
    p = trace(velvet(**DYED), _dir(60.0), 20000, seed=4)
    tot = p.weights + p.absorbed + p.lost
    # exact for rays that never met roulette (exit weight above ROULETTE), k sigma overall
    sure = p.weights > ROULETTE
    assert sure.sum() > 100 and p.lost.sum() == 0.0
    np.testing.assert_allclose(tot[sure], 1.0, rtol=0, atol=1e-13)
    assert abs(tot.mean() - 1.0) < K_SIGMA * tot.std() / np.sqrt(tot.size)


# -- isotropy ---------------------------------------------------------------------------------

def test_velvet_is_isotropic():
    # random azimuths: turning the BRDF by 90 degrees changes nothing beyond the noise
    # (observed z 2.1 between two independent runs). Control: the same pile with every fibre
    # tilted 0.3 rad towards +x (slanted velvet) is clearly anisotropic (observed z 15.7).
    b = HemiHarmonics(4)
    a = rotation_action(b)
    kw = {"rays": 60000, "chunk": 1000}
    s = velvet(**DYED)
    r1 = simulate(s, b, seed=1, **kw)
    r2 = simulate(s, b, seed=2, **kw)
    assert rotated_z(r1, r2, a) < K_SIGMA
    e = r1.energy
    assert e["escaped"] == 0.0 and 0.01 < e["reflected"] < 0.05
    rng = np.random.default_rng(1)
    side = s.period[0]
    feet = np.column_stack([rng.uniform(0, side, (200, 2)), np.zeros(200)])
    ax = np.array([np.sin(0.3), 0.0, np.cos(0.3)])
    slanted = (Scene(side).add_plane(0.0, material=Diffuse(0.05))
               .add_tube(feet - 5.0 * (1 + np.tan(0.3)) * ax, feet + 300.0 * ax, 5.0,
                         material=Dielectric(1.5, 0.03)))
    q = simulate(slanted, b, seed=1, **kw)
    assert rotated_z(q, q, a) > 2 * K_SIGMA


# -- the velvet signature ---------------------------------------------------------------------

def test_velvet_brightens_towards_grazing():
    # At normal incidence most light falls between the fibres onto the dark base or into the
    # dyed fibres; at grazing incidence the pile is optically thick (the projected fibre area
    # per unit base area grows like 2 r length tan(theta) density) and light is scattered
    # by fibre tips and sides high in the pile: the directional albedo rises (observed 0.026
    # at 0 degrees, 0.065 at 80), unlike the constant albedo of a Lambertian.
    s = velvet(**DYED)
    p0 = trace(s, _dir(0.0), 20000, seed=5)
    p80 = trace(s, _dir(80.0), 20000, seed=5)
    r0, r80 = p0.weights.mean(), p80.weights.mean()
    se = np.hypot(2 * p0.weights.std() / np.sqrt(2e4), p80.weights.std() / np.sqrt(2e4))
    assert r80 - 2 * r0 > K_SIGMA * se
    # ... and the light leaves towards grazing: at 75 degrees incidence the reflectance seen
    # at 80 degrees (side azimuth) is far above that seen along the normal (observed 3.3 and
    # 0.22 times the Lambertian R / pi; a Lambertian gives 1 and 1)
    p75 = trace(s, _dir(75.0), 40000, seed=6)
    fg, sg = cone_reflectance(p75, _dir(80.0, 90.0))
    fn, sn = cone_reflectance(p75, _dir(0.0))
    assert fg - 5 * fn > K_SIGMA * np.hypot(sg, 5 * sn)


def test_velvet_retroreflects_at_grazing_incidence():
    # A smooth cylinder reflects (and refracts through and back) into the cone of directions
    # at the same angle to its axis as the incident ray; the cone passes through the retro
    # direction when the fibre is perpendicular to the light, i.e. tilted by 90 - theta_i
    # towards it. With tilts up to 0.3 rad (17 degrees) such fibres exist for theta_i >= 73
    # degrees: at 75 degrees the reflectance back towards the light is several times the
    # Lambertian R / pi (observed 5.4 +- 0.5), at 60 degrees it is not (observed 0.69 +- 0.09),
    # and upright fibres (tilt 0) do not retroreflect at 75 degrees (observed 0.10 +- 0.03:
    # their flat tips send light to the mirror direction instead, 92 R / pi). The mirror
    # lobe of the tips stays the strongest (16 R / pi for the tilted pile at 75 degrees).
    tilted = velvet(**DYED)
    upright = velvet(**{**DYED, "tilt": 0.0})
    rays = 40000
    for scene, theta, retro in ((tilted, 75.0, True), (tilted, 60.0, False),
                                (upright, 75.0, False)):
        p = trace(scene, _dir(theta, 30.0), rays, seed=7)
        lam = p.weights.mean() / np.pi
        f, se = cone_reflectance(p, _dir(theta, 30.0))
        if retro:
            assert f - 3 * lam > K_SIGMA * se, (f / lam, se / lam)
        else:
            assert f - 1.5 * lam < -K_SIGMA * se, (f / lam, se / lam)


# -- bad input --------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, exc, match", [
    ({"ior": 0.9}, ValueError, r"ior must be finite and >= 1 \(fibres denser than the air"),
    ({"ior": np.nan}, ValueError, r"ior must be finite and > 0, got nan"),
    ({"ior": np.inf}, ValueError, r"ior must be finite"),
    ({"absorption": -0.1}, ValueError, r"absorption must be finite and >= 0, got -0.1"),
    ({"radius": 25.0}, ValueError, r"radius must be below half the mean fibre spacing "
                                   r"1 / sqrt\(density\) = 40"),
    ({"radius": 0.0}, ValueError, r"radius must be finite and > 0, got 0.0"),
    ({"length": -1.0}, ValueError, r"length must be finite and > 0"),
    ({"density": np.inf}, ValueError, r"density must be finite and > 0"),
    ({"tilt": np.pi / 2}, ValueError, r"tilt must be in \[0, pi/2\) radians"),
    ({"tilt": -0.1}, ValueError, r"tilt must be finite and >= 0"),
    ({"count": 0}, ValueError, r"count must be > 0, got 0"),
    ({"count": 10.0}, TypeError, r"count must be an integer, got 10.0"),
    ({"seed": -1}, ValueError, r"seed must be in \[0, 2\*\*64\)"),
    ({"base": Dielectric(1.5)}, ValueError, r"base must be opaque \(Diffuse, Mirror\)"),
    ({"base": "black"}, TypeError, r"base must be a Material"),
    ({"radius": "thin"}, TypeError, r"radius must be a number, got 'thin'"),
])
def test_velvet_bad_input(kwargs, exc, match):
    args = {"radius": 5.0, "length": 300.0, "density": 6.25e-4, **kwargs}
    with pytest.raises(exc, match=match):
        velvet(**args)


def test_velvet_base_material():
    s = velvet(5.0, 300.0, 6.25e-4, base=Mirror(1.5), count=10)
    assert [repr(p.material) for p in s.parts] == ["Mirror(ior=1.5, k=0)", "Dielectric(1.5)"]
