"""The ``scatmodes`` BSDF plugin: a Python :class:`mitsuba.BSDF` around any representation."""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np
from numpy.typing import NDArray

from ._sampling import LobeSampler, MixtureSampler, TableSampler, sampler_for
from ._traced import traced_eval
from ._traced_sampling import traced_sampler

__all__ = ["INCIDENT", "PLUGIN", "ClampStats", "bsdf", "evaluated", "register", "render",
           "negative_fraction", "representation", "set_default_variant"]

#: The plugin type name.
PLUGIN = "scatmodes"
#: Values of the plugin's ``incident`` parameter: which of Mitsuba's directions is the
#: representation's w_i (towards the light).
INCIDENT = ("light", "camera")
#: Rec. 709 luminance weights: an RGB representation in a monochrome variant.
_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
_CLASSES: dict[str, type] = {}
_PENDING: list[Any] = []


class ClampStats:
    """What the plugin clamped: negative values of a truncated expansion set to 0.

    Attributes
    ----------
    values : int
        Channel values evaluated above the horizon (pairs x channels).
    clamped : int
        How many of them were negative.
    negative, positive : float
        Sums of |negative values| and of positive values (1/sr): ``negative / (negative +
        positive)`` is the clamped fraction of the evaluated magnitude.
    """

    def __init__(self) -> None:
        self.values = 0
        self.clamped = 0
        self.negative = 0.0
        self.positive = 0.0

    def add(self, f: NDArray) -> None:
        """Count the values f (already restricted to pairs above the horizon)."""
        neg = f < 0
        self.values += int(f.size)
        self.clamped += int(neg.sum())
        self.negative -= float(f[neg].sum())
        self.positive += float(f[~neg].sum())

    @property
    def fraction(self) -> float:
        """Clamped fraction of the values (0 when nothing was evaluated)."""
        return self.clamped / self.values if self.values else 0.0

    @property
    def mass_fraction(self) -> float:
        """|negative| / (|negative| + positive) of the evaluated values."""
        total = self.negative + self.positive
        return self.negative / total if total > 0 else 0.0

    def __repr__(self) -> str:
        return (f"ClampStats(values={self.values}, clamped={self.clamped} "
                f"({self.fraction:.3%}), mass_fraction={self.mass_fraction:.3g})")


def representation(source: Any) -> Any:
    """Return what the plugin evaluates: a loaded file, or the object itself.

    Parameters
    ----------
    source : str, os.PathLike or BRDF
        A file written by :func:`compress.save` (a coefficient matrix, fitted model or
        hybrid), or an in-memory representation with ``eval(wi, wo)`` and ``channels``.

    Returns
    -------
    BRDF
    """
    if isinstance(source, str | os.PathLike):
        from ..store import load
        return load(Path(source))
    for attr in ("eval", "channels"):
        if not hasattr(source, attr):
            raise TypeError(f"rep must be a file name or a representation with eval(wi, wo) "
                            f"and channels (a CoefficientMatrix, FittedModel or Hybrid), "
                            f"got {type(source).__name__} without {attr!r}")
    return source


def set_default_variant() -> str:
    """Set ``llvm_ad_rgb`` when no variant is set (``scalar_rgb`` without LLVM); return it."""
    if mi.variant() is None:
        try:
            mi.set_variant("llvm_ad_rgb")
        except Exception:  # noqa: BLE001 - no LLVM >= 16: Mitsuba's scalar variant still works
            mi.set_variant("scalar_rgb")
    return str(mi.variant())


def _check_variant(variant: str) -> None:
    if "spectral" in variant or "polarized" in variant:
        raise ValueError(f"the scatmodes BSDF needs an RGB or monochrome Mitsuba variant "
                         f"(e.g. 'llvm_ad_rgb' or 'scalar_rgb'), got {variant!r}")


def register() -> type:
    """Register the BSDF type ``"scatmodes"`` with Mitsuba for the current variant.

    Sets ``llvm_ad_rgb`` first when no variant is set (``scalar_rgb`` where Mitsuba finds no
    LLVM). Idempotent. After it, ``mi.load_dict({"type": "scatmodes", "filename": path})``
    loads any file written by :func:`compress.save`; the optional parameter ``incident``
    (``"light"``, the default, or ``"camera"``) says which of Mitsuba's directions is the
    representation's w_i (see :mod:`compress.mitsuba`).

    Returns
    -------
    type
        The plugin class of the current variant (a subclass of ``mitsuba.BSDF``).
    """
    variant = set_default_variant()
    _check_variant(variant)
    cls = _CLASSES.get(variant)
    if cls is None:
        cls = _CLASSES[variant] = _make_class()
    mi.register_bsdf(PLUGIN, lambda props: cls(props))
    return cls


def bsdf(rep: Any, *, incident: str = "light") -> Any:
    """Return a Mitsuba BSDF object for a representation (in memory or a file name).

    Parameters
    ----------
    rep : str, os.PathLike or BRDF
        As :func:`representation` takes it.
    incident : {"light", "camera"}
        As the plugin parameter of the same name.

    Returns
    -------
    mitsuba.BSDF
        Usable as the ``bsdf`` of a shape in ``mi.load_dict``; its ``stats`` attribute is
        a :class:`ClampStats`, ``sampler`` what :func:`~compress.mitsuba.sampler_for` chose.
    """
    cls = register()
    props = mi.Properties(PLUGIN)
    props["incident"] = incident
    _PENDING.append(representation(rep))
    try:
        return cls(props)
    finally:
        _PENDING.clear()


@contextlib.contextmanager
def evaluated() -> Iterator[None]:
    """Run Dr.Jit loops and calls in evaluated (wavefront) mode inside the block.

    Needed only by representations without a Dr.Jit form (``traced`` False), whose numpy
    code needs concrete arrays; Mitsuba's JIT variants trace loops and virtual calls
    symbolically by default, where no array holds values yet. In evaluated
    mode every iteration of the path tracer's loop is a wavefront of concrete arrays, and the
    plugin is called once per wavefront (Dr.Jit's ``JitFlag.SymbolicLoops`` and
    ``JitFlag.SymbolicCalls`` off). A no-op in scalar variants.
    """
    with contextlib.ExitStack() as stack:
        if mi.variant() is not None and not mi.variant().startswith("scalar"):
            stack.enter_context(dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, False))
            stack.enter_context(dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False))
        yield


def render(scene: Any, *, spp: int | None = None, seed: int = 0) -> Any:
    """``mitsuba.render`` in evaluated mode (see :func:`evaluated`); returns the image tensor.

    Kept for representations without a Dr.Jit form and for compatibility: traced ones
    render with ``mi.render`` in Mitsuba's default mode (the same image, the same code).

    Parameters
    ----------
    scene : mitsuba.Scene
    spp : int, optional
        Samples per pixel (default: the sensor's sampler).
    seed : int
        Seed of the sampler.
    """
    with evaluated():
        img = mi.render(scene, spp=spp or 0, seed=seed)
        dr.eval(img)
    return img


# -- conversions ---------------------------------------------------------------------------

def _rows(v: Any, n: int | None = None) -> NDArray[np.float64]:
    """(n, 3) float64 rows of a Mitsuba 3-vector (scalar or a Dr.Jit array of any width)."""
    a = np.asarray(v, dtype=np.float64)
    a = a.reshape(3, -1).T
    if n is not None and a.shape[0] != n:
        a = np.broadcast_to(a, (n, 3))
    return a


def _flat(v: Any, n: int | None = None, dtype: Any = np.float64) -> NDArray:
    a = np.asarray(v, dtype=dtype).reshape(-1)
    if n is not None and a.shape[0] != n:
        a = np.broadcast_to(a, (n,))
    return a


def _unit(a: NDArray) -> NDArray[np.float64]:
    norm = np.linalg.norm(a, axis=1)
    return a / np.where(norm > 0, norm, 1.0)[:, None]


def _make_class() -> type:
    """Build the plugin class for the current variant (mitsuba.BSDF differs per variant)."""
    scalar = mi.variant().startswith("scalar")
    mono = "_mono" in mi.variant()
    flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide

    def spectrum(rgb: NDArray) -> Any:
        """(n, 3) float64 -> mi.Spectrum (Color1f in mono variants)."""
        if mono:
            y = rgb @ _LUMINANCE
            return mi.Color1f(float(y[0])) if scalar else mi.Color1f(mi.Float(y))
        if scalar:
            return mi.Color3f(float(rgb[0, 0]), float(rgb[0, 1]), float(rgb[0, 2]))
        return mi.Color3f(np.ascontiguousarray(rgb.T, dtype=np.float32))

    def floats(x: NDArray) -> Any:
        return float(x[0]) if scalar else mi.Float(np.ascontiguousarray(x, dtype=np.float32))

    def vectors(x: NDArray) -> Any:
        if scalar:
            return mi.Vector3f(float(x[0, 0]), float(x[0, 1]), float(x[0, 2]))
        return mi.Vector3f(np.ascontiguousarray(x.T, dtype=np.float32))

    class ScatmodesBSDF(mi.BSDF):
        """Mitsuba BSDF of a scatmodes representation: its Dr.Jit form, else numpy.

        Plugin parameters: ``filename`` (a file written by ``compress.save``) and
        ``incident`` ("light" or "camera"). ``traced`` is True when eval, pdf and sample
        are Dr.Jit code that Mitsuba traces (JIT variants, forms of
        :func:`compress.mitsuba._traced.traced_eval`); otherwise numpy runs once per call.
        """

        def __init__(self, props: Any) -> None:
            mi.BSDF.__init__(self, props)
            incident = props.get("incident", "light")
            if incident not in INCIDENT:
                raise ValueError(f"incident must be one of {INCIDENT}, got {incident!r}")
            if _PENDING:
                rep = _PENDING[0]
            elif "filename" in props:
                name = props.get("filename")
                rep = representation(str(name))
            else:
                raise ValueError("the scatmodes BSDF needs a 'filename' (a file written by "
                                 "compress.save), or use compress.mitsuba.bsdf(rep)")
            channels = int(rep.channels)
            if channels not in (1, 3):
                raise ValueError(f"the scatmodes BSDF renders 1 or 3 (RGB) channels, the "
                                 f"representation has {channels}: project spectral data to "
                                 f"RGB first")
            self.rep = rep
            self.incident = incident
            self.stats = ClampStats()
            # the Dr.Jit form (JIT variants): None where a form has none (numpy path)
            self._f = None if scalar else traced_eval(rep)
            self.sampler = sampler_for(rep, incident=incident)
            self.m_components = [flags]
            self.m_flags = flags

        @property
        def sampler(self) -> LobeSampler | TableSampler | MixtureSampler:
            """The importance sampler (numpy; its Dr.Jit twin is made when it is set)."""
            return self._sampler

        @sampler.setter
        def sampler(self, value: LobeSampler | TableSampler | MixtureSampler) -> None:
            self._sampler = value
            self._s = traced_sampler(value) if self._f is not None else None
            #: True when eval, pdf and sample are Dr.Jit code that Mitsuba traces
            self.traced = self._s is not None

        # -- the Dr.Jit core (traced) ------------------------------------------------------
        def _spectrum_jit(self, vals: list, cos_o: Any, ok: Any) -> Any:
            """Channel values f -> max(f, 0) cos, as mi.Spectrum; 0 where not ``ok``."""
            vals = [dr.select(ok, dr.maximum(v, 0.0) * cos_o, 0.0) for v in vals]
            if mono:
                y = vals[0] if len(vals) == 1 else (
                    float(_LUMINANCE[0]) * vals[0] + float(_LUMINANCE[1]) * vals[1]
                    + float(_LUMINANCE[2]) * vals[2])
                return mi.Color1f(y)
            if len(vals) == 1:
                return mi.Color3f(vals[0], vals[0], vals[0])
            return mi.Color3f(*vals)

        def _eval_jit(self, ctx: Any, wi: Any, wo: Any, ok: Any) -> Any:
            """Return f cos(theta of Mitsuba's wo) as mi.Spectrum (0 off ``ok``)."""
            importance = ctx.mode == mi.TransportMode.Importance
            to_light_is_wo = (self.incident == "light") != bool(importance)
            light, view = (wo, wi) if to_light_is_wo else (wi, wo)
            return self._spectrum_jit(self._f(light, view), wo.z, ok)

        def _inputs_jit(self, si: Any, wo: Any, active: Any) -> tuple[Any, Any, Any]:
            """Return unit directions and the mask of pairs above the horizon.

            Pairs off the mask (below the horizon, zero or NaN vectors: a failed sample's
            w_o is the zero vector) are replaced by the normal, so that no table index is
            formed from a NaN (a gather does not check its index).
            """
            wi, wo = dr.normalize(si.wi), dr.normalize(wo)
            ok = active & (wi.z > 0.0) & (wo.z > 0.0)
            z = mi.Vector3f(0.0, 0.0, 1.0)
            return dr.select(ok, wi, z), dr.select(ok, wo, z), ok

        # -- the numpy core -------------------------------------------------------------
        def _check(self) -> None:
            if not scalar and dr.flag(dr.JitFlag.SymbolicScope):
                raise RuntimeError(
                    f"the scatmodes BSDF of {type(self.rep).__name__} has no Dr.Jit form "
                    f"and evaluates numpy code, which cannot be traced symbolically: "
                    f"render with compress.mitsuba.render(scene) or inside "
                    f"compress.mitsuba.evaluated() (while this instance is alive, every "
                    f"scene needs that)")

        def _values(self, ctx: Any, wi: NDArray, wo: NDArray, ok: NDArray) -> NDArray:
            """Return f cos(theta of Mitsuba's wo) as (n, 3) RGB, 0 where not ``ok``."""
            out = np.zeros((wi.shape[0], 3))
            if not np.any(ok):
                return out
            importance = ctx.mode == mi.TransportMode.Importance
            # radiance transport: si.wi faces the camera, wo the light ("light"); Mitsuba's
            # measured plugin reads them the other way round ("camera")
            to_light_is_wo = (self.incident == "light") != bool(importance)
            a, b = _unit(wi[ok]), _unit(wo[ok])
            light, view = (b, a) if to_light_is_wo else (a, b)
            f = np.asarray(self.rep.eval(light, view), dtype=np.float64).reshape(
                int(ok.sum()), -1)
            bad = ~np.isfinite(f)
            if np.any(bad):
                raise FloatingPointError(f"the representation returned {int(bad.sum())} "
                                         f"non-finite values")
            self.stats.add(f)
            f = np.maximum(f, 0.0) * b[:, 2:3]
            out[ok] = f if f.shape[1] == 3 else np.repeat(f, 3, axis=1)
            return out

        def _inputs(self, si: Any, wo: Any, active: Any) -> tuple[NDArray, NDArray, NDArray]:
            n = 1 if scalar else max(dr.width(si.wi), dr.width(wo), dr.width(active))
            wi_ = _rows(si.wi, n)
            wo_ = _rows(wo, n)
            ok = _flat(active, n, bool) & (wi_[:, 2] > 0) & (wo_[:, 2] > 0)
            return wi_, wo_, ok

        # -- the mitsuba.BSDF interface -------------------------------------------------
        def eval(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
            """f(w_light, w_camera) cos(theta_o): Mitsuba's cosine-weighted BSDF."""
            if self.traced:
                wi, wo, ok = self._inputs_jit(si, wo, active)
                if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0):
                    ok = mi.Bool(False)
                return self._eval_jit(ctx, wi, wo, ok)
            self._check()
            wi_, wo_, ok = self._inputs(si, wo, active)
            ok &= bool(ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0))
            return spectrum(self._values(ctx, wi_, wo_, ok))

        def pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
            """Density of :meth:`sample`, per steradian."""
            if self.traced:
                wi, wo, ok = self._inputs_jit(si, wo, active)
                return dr.select(ok, self._s.pdf(wi, wo), 0.0)
            self._check()
            wi_, wo_, ok = self._inputs(si, wo, active)
            p = np.where(ok, self.sampler.pdf(_unit(wi_), _unit(wo_)), 0.0)
            return floats(p)

        def eval_pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> tuple[Any, Any]:
            """(:meth:`eval`, :meth:`pdf`) in one call."""
            if self.traced:
                wi, wo, ok = self._inputs_jit(si, wo, active)
                p = dr.select(ok, self._s.pdf(wi, wo), 0.0)
                if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0):
                    ok = mi.Bool(False)
                return self._eval_jit(ctx, wi, wo, ok), p
            self._check()
            wi_, wo_, ok = self._inputs(si, wo, active)
            p = np.where(ok, self.sampler.pdf(_unit(wi_), _unit(wo_)), 0.0)
            ok &= bool(ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0))
            return spectrum(self._values(ctx, wi_, wo_, ok)), floats(p)

        def sample(self, ctx: Any, si: Any, sample1: Any, sample2: Any,
                   active: Any = True) -> tuple[Any, Any]:
            """Draw wo from the mixture; the weight is eval / pdf (0 for failed samples)."""
            if self.traced:
                return self._sample_jit(ctx, si, sample1, sample2, active)
            self._check()
            n = 1 if scalar else max(dr.width(si.wi), dr.width(sample1), dr.width(sample2),
                                     dr.width(active))
            wi_ = _unit(_rows(si.wi, n))
            u0 = _flat(sample1, n)
            uv = np.asarray(sample2, dtype=np.float64).reshape(2, -1)
            u1, u2 = (np.broadcast_to(uv[k], (n,)) for k in range(2))
            wo_, p = self.sampler.sample(wi_, u0, u1, u2)
            ok = _flat(active, n, bool) & (p > 0) & (wi_[:, 2] > 0)
            ok &= bool(ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0))
            value = self._values(ctx, wi_, wo_, ok)
            weight = np.where(ok[:, None], value / np.where(ok, p, 1.0)[:, None], 0.0)
            bs = dr.zeros(mi.BSDFSample3f) if scalar else dr.zeros(mi.BSDFSample3f, n)
            bs.wo = vectors(wo_)
            bs.pdf = floats(np.where(ok, p, 0.0))
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = mi.UInt32(0)
            return bs, spectrum(weight)

        def _sample_jit(self, ctx: Any, si: Any, sample1: Any, sample2: Any,
                        active: Any) -> tuple[Any, Any]:
            wi = dr.normalize(si.wi)
            up = active & (wi.z > 0.0)
            wi = dr.select(up, wi, mi.Vector3f(0.0, 0.0, 1.0))
            wo, p = self._s.sample(wi, sample1, sample2)
            ok = up & (p > 0.0)
            if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0):
                ok = mi.Bool(False)
            # failed samples (w_o = 0) are evaluated at the normal, then masked
            value = self._eval_jit(ctx, wi, dr.select(ok, wo, mi.Vector3f(0.0, 0.0, 1.0)), ok)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = wo
            bs.pdf = dr.select(ok, p, 0.0)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = mi.UInt32(0)
            return bs, value * dr.select(ok, dr.rcp(dr.select(ok, p, 1.0)), 0.0)

        def traverse(self, callback: Any) -> None:
            """No differentiable parameters: the representation is fixed numpy data."""

        def parameters_changed(self, keys: Any = None) -> None:
            """Nothing to update."""

        def to_string(self) -> str:
            """Describe the representation, the sampler and the incident convention."""
            return f"ScatmodesBSDF[rep={self.rep!r}, sampler={self.sampler!r}, " \
                   f"incident={self.incident!r}]"

    return ScatmodesBSDF


def negative_fraction(rep: Any, n: int = 1 << 16, seed: int = 0) -> ClampStats:
    """Measure how much of a representation is negative on uniformly random pairs.

    Parameters
    ----------
    rep : BRDF
        A representation (a truncated expansion may dip below 0).
    n : int
        Pairs, both directions uniform on the upper hemisphere.
    seed : int

    Returns
    -------
    ClampStats
        ``fraction``: negative channel values among all; ``mass_fraction``: their magnitude
        relative to the total magnitude (what the plugin's clamping removes, unweighted).
    """
    rng = np.random.default_rng(seed)
    z = rng.random((2, n))
    phi = 2.0 * math.pi * rng.random((2, n))
    s = np.sqrt(1.0 - z * z)
    w = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1)
    stats = ClampStats()
    f = np.asarray(representation(rep).eval(w[0], w[1]), dtype=np.float64)
    stats.add(f.reshape(n, -1))
    return stats

