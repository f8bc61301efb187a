"""Velvet: a pile of thin transparent fibres with randomly perturbed tilt over an absorbing base.

Westin, Arvo & Torrance (1992, sec. 5.3) simulated velvet as a forest of narrow cylinders
with randomly perturbed angles: transparent ideal-specular plastic fibres, which reflect a
ray with the Fresnel probability or transmit it, over a base plane that absorbs. Here every
fibre is a capped tube (a closed solid) of a :class:`~project.microgeometry.Dielectric`
material, so each hit reflects with the Fresnel probability or refracts into the fibre, where
light is absorbed along its path, and the base below absorbs what gets through the pile.
"""

from __future__ import annotations

import numpy as np

from ._checks import _number, _positive_int, _seed
from .materials import DIELECTRIC, Dielectric, Diffuse, Material
from .scene import Scene

__all__ = ["velvet"]


def velvet(radius: float, length: float, density: float, *, tilt: float = 0.25,
           ior: float = 1.5, absorption: float = 0.0, base: Material | None = None,
           count: int = 200, seed: int = 0) -> Scene:
    """Build velvet: ``count`` transparent fibres per period, standing on a base plane.

    Parameters
    ----------
    radius : float
        Fibre radius r > 0 (length unit of the scene, e.g. micrometres: r ~ 5-10 for nylon
        or silk velvet).
    length : float
        Fibre length above the base, along the fibre axis (> 0; the pile height is
        length cos(tilt angle)), same unit.
    density : float
        Fibres per unit base area (> 0, unit length^-2); the mean spacing is
        1 / sqrt(density), which must exceed the fibre diameter 2 r.
    tilt : float
        Largest tilt of a fibre from the normal, radians in [0, pi/2). Each fibre's axis is
        drawn uniformly in solid angle within this cone (so the azimuths are uniform: the
        pile is isotropic); 0 makes all fibres upright.
    ior : float
        Refractive index of the fibres relative to the surrounding air: finite and >= 1
        (about 1.5 for nylon, silk and polyester).
    absorption : float
        Absorption coefficient sigma >= 0 inside the fibres, per unit length (dyed fibres:
        a path of length t inside keeps exp(-sigma t)).
    base : Material, optional
        Opaque material of the base plane z = 0 (default ``Diffuse(0.05)``, a dark backing).
    count : int
        Fibres per period (>= 1); the period is square with side sqrt(count / density).
        Tens to a few thousand: more fibres make the periodic repetition less visible and
        the scene slower to build.
    seed : int
        Seed of the fibre positions and tilts (numpy ``default_rng``).

    Returns
    -------
    Scene
        Base plane plus ``count`` capped tubes of ``Dielectric(ior, absorption)``.

    Raises
    ------
    ValueError
        For non-finite or out-of-range parameters (e.g. ``ior < 1``, negative absorption,
        a radius not below half the mean spacing) or a dielectric base.
    TypeError
        For a non-numeric parameter, a ``base`` that is not a Material, or a non-integer
        ``count`` or ``seed``.

    Notes
    -----
    Fibre positions are uniform over the period (a Poisson pile); neighbouring fibres may
    intersect, which the tracer handles by its inside/outside rule (see
    :class:`~project.microgeometry.Dielectric`). Each fibre is planted in the base: its
    axis crosses the plane z = 0 at its foot point and continues r (1 + tan(theta)) below
    it (theta: the fibre's own tilt, at most ``tilt``), so the bottom cap lies entirely
    under the opaque plane and light inside a fibre meets the base itself (which reflects
    it back into the fibre, absorption continuing).

    Examples
    --------
    >>> s = velvet(5.0, 200.0, 2e-4, tilt=0.3, count=50, seed=1)
    >>> s
    Scene(period=[500.0, 500.0], triangles=2, cylinders=0, tubes=50)
    >>> round(float(s.period[0] ** 2 * 2e-4))  # fibres per period
    50
    """
    r = _number(radius, "radius", strict=True)
    ln = _number(length, "length", strict=True)
    rho = _number(density, "density", strict=True)
    spacing = 1.0 / np.sqrt(rho)
    if not 2.0 * r < spacing:
        raise ValueError(f"radius must be below half the mean fibre spacing 1 / sqrt(density) "
                         f"= {spacing:g} (fibres thinner than the gaps between them), got "
                         f"{radius!r}")
    t = _number(tilt, "tilt", strict=False)
    if not t < 0.5 * np.pi:
        raise ValueError(f"tilt must be in [0, pi/2) radians, got {tilt!r}")
    n = _number(ior, "ior", strict=True)
    if not n >= 1.0:
        raise ValueError(f"ior must be finite and >= 1 (fibres denser than the air around "
                         f"them; nylon, silk ~1.5), got {ior!r}")
    fibre = Dielectric(n, absorption)
    if base is None:
        base = Diffuse(0.05)
    if not isinstance(base, Material):
        raise TypeError(f"base must be a Material (Diffuse, Mirror), got "
                        f"{type(base).__name__}")
    if base.code == DIELECTRIC:
        raise ValueError(f"base must be opaque (Diffuse, Mirror): a plane has no inside for "
                         f"a Dielectric, got {base!r}")
    count = _positive_int(count, "count")
    rng = np.random.default_rng(int(_seed(seed)))
    side = float(np.sqrt(count / rho))
    foot = np.column_stack([rng.uniform(0.0, side, (count, 2)), np.zeros(count)])
    # uniform in solid angle within the cone: cos(theta) uniform on [cos(tilt), 1]
    cos_t = 1.0 - rng.uniform(0.0, 1.0, count) * (1.0 - np.cos(t))
    sin_t = np.sqrt((1.0 - cos_t) * (1.0 + cos_t))
    phi = rng.uniform(0.0, 2.0 * np.pi, count)
    axis = np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])
    # the bottom cap disc reaches r sin(theta) above its centre: burying the centre by
    # r (1 + tan(theta)) along the axis keeps the whole cap below the plane
    bury = r * (1.0 + sin_t / cos_t)
    scene = Scene(side).add_plane(0.0, material=base)
    return scene.add_tube(foot - bury[:, None] * axis, foot + ln * axis, r, caps=True,
                          material=fibre)

