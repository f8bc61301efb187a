"""Every scatmodes representation as a Mitsuba 3 BSDF: the plugin type ``"scatmodes"``.

>>> import mitsuba as mi                                            # doctest: +SKIP
>>> import compress.mitsuba
>>> compress.mitsuba.register()                                     # doctest: +SKIP
>>> mat = mi.load_dict({"type": "scatmodes", "filename": "rep.h5"})  # doctest: +SKIP
>>> img = mi.render(scene)                                          # doctest: +SKIP

:func:`register` registers the type for the current variant (``llvm_ad_rgb`` is set when
none is, ``scalar_rgb`` without LLVM); the parameter ``filename`` is any file written by
:func:`compress.save` (a coefficient matrix in any basis, reciprocal or not, a fitted model of
any family, a hybrid). :func:`bsdf` makes the same object from a representation in memory.
This module is not imported by :mod:`compress`; it needs Mitsuba 3
(``pip install 'scatmodes[mitsuba]'``).

Conventions
-----------
Mitsuba's BSDFs work in the local shading frame (z the normal); ``si.wi`` points to where the
path came from (the camera side in a path tracer, ``TransportMode.Radiance``) and ``wo`` is
the sampled or queried direction (towards the light); ``eval`` returns f cos(theta_o), with
the cosine of ``wo``, and 0 when either direction is below the horizon. Our representations
take (w_i towards the light, w_o towards the viewer). So the plugin evaluates
``rep.eval(wo, si.wi) * wo.z`` in radiance transport and ``rep.eval(si.wi, wo) * wo.z`` in
importance transport (where ``si.wi`` faces the light): the physical BRDF, which matters for
non-reciprocal data (general coefficient matrices, full-turn factored and tabulated models of
RGL measurements). Mitsuba's own ``measured`` plugin instead reads an RGL file with ``si.wi``
as the measurement's incidence (relying on reciprocity); the plugin parameter
``incident="camera"`` reproduces that reading for side-by-side comparisons.

The flags are ``GlossyReflection | FrontSide`` (one component). Negative values of a
truncated expansion are clamped to 0 and counted in the object's ``stats``
(:class:`ClampStats`); :func:`negative_fraction` measures the same on random pairs.

Evaluation and sampling
-----------------------
In the JIT variants (LLVM, CUDA) ``eval``, ``pdf``, ``eval_pdf`` and ``sample`` are Dr.Jit
code (:mod:`compress.mitsuba._traced`, :mod:`compress.mitsuba._traced_sampling`): Mitsuba
traces them symbolically into its kernels like its own plugins, so scenes render with
``mi.render`` in the default mode, from ``mi.load_dict`` or from XML files read by
``mi.load_file``. The forms: coefficient matrices in every basis (reciprocal or not,
isotropic or not), the fitted families "lambert+ggx", "lambert+beckmann", "lafortune",
"dsbrdf", "rr8807", "factored", "tucker" and "tabulated" (every family), the models
``Lambert``, ``Minnaert``, ``Phong``, ``BlinnPhong``, ``OrenNayar`` (qualitative) and
``CookTorrance`` (separable Smith G) of :mod:`project.models`, MERL tables, and hybrids of
these; the samplers below. Values agree with the numpy evaluation to float32 rounding. The
arrays the forms read are made once, at load time; nothing in the traced path touches numpy
or the host.

The numpy evaluation remains for everything else (RGL and other measured data read by
:mod:`project.measured`, other models of :mod:`project.models`, any object with ``eval``) and
in the scalar variants: called once per call of ``eval``, ``pdf``, ``eval_pdf`` or
``sample``, one wavefront of directions in the JIT variants (converted with ``numpy`` once
and the result wrapped back), one sample in the scalar variants. Such an instance cannot be
traced: in the JIT variants render with :func:`render` (or inside :func:`evaluated`), which
switches Dr.Jit to evaluated loops and calls; while it is alive every scene needs that,
since Dr.Jit traces every live BSDF of a symbolic call. The attribute ``traced`` of a plugin
object says which path it takes (set it to False to force the numpy path, e.g. as a
reference). Only the numpy path counts clamped values in ``stats``;
:func:`negative_fraction` measures them for any form.

Importance sampling
-------------------
``sample`` draws from the sampler :func:`sampler_for` chooses at load time and ``pdf``
returns its exact density. The candidates are a mixture of cosine-weighted hemisphere
sampling and one lobe (:class:`LobeSampler`: visible-normal sampling of the GGX or Beckmann
lobe of a fitted microfacet model or of a hybrid's microfacet lobe, a GGX lobe fitted to the
half-vector profile of a coefficient matrix, a tabulated inverse CDF over theta_h for any
other BRDF), a density of w_o tabulated from the representation per bin of theta_i and mixed
with cosine (``TableSampler``, isotropic representations), an even mixture of the two and
cosine alone; the one whose weights vary least on a fixed pilot set wins. Mitsuba's
chi-square test
(``mitsuba.chi2``) checks that sampling and density agree
(``tests/compress/test_mitsuba.py``); ``tests/benchmarks/bench_mitsuba.py`` compares the
variance against pure cosine sampling and against Mitsuba's ``measured`` plugin, and with
``--render`` the render time and per-sample costs against ``measured``. Each sampler is
chosen and built with numpy at load time; its Dr.Jit twin draws the same distribution and
reports the same density.
"""

from __future__ import annotations

try:
    import drjit  # noqa: F401
    import mitsuba  # noqa: F401
except ImportError:
    raise ImportError("compress.mitsuba needs Mitsuba 3: pip install 'scatmodes[mitsuba]'"
                      ) from None

from ._plugin import (
    INCIDENT,
    PLUGIN,
    ClampStats,
    bsdf,
    evaluated,
    negative_fraction,
    register,
    render,
    representation,
    set_default_variant,
)
from ._sampling import KINDS, LobeSampler, profile, sampler_for
from ._scene import relative_rmse, sphere_scene, to_numpy

__all__ = ["INCIDENT", "KINDS", "PLUGIN", "ClampStats", "LobeSampler", "bsdf", "evaluated",
           "negative_fraction", "profile", "register", "relative_rmse", "render",
           "representation", "sampler_for", "set_default_variant", "sphere_scene", "to_numpy"]
