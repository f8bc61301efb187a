"""Benchmark: importance sampling of the ``scatmodes`` Mitsuba BSDF, against cosine sampling
and Mitsuba 3's ``measured`` plugin.

What it measures
----------------
For each RGL-EPFL RGB file (``--files``; default ``tests/data/paper_white_rgb.bsdf`` and
the files of ``../shared/data/rgl`` when present), the material is compressed to a
``"tabulated"`` model at ``--bins`` (project.tabulated.tabulate) and loaded three ways in
``llvm_ad_rgb``:

- ours: ``compress.mitsuba.bsdf(model, incident="camera")`` (the reading of ``measured``),
  sampled by what ``compress.mitsuba.sampler_for`` chooses (for these tables the density of
  w_o tabulated per bin of theta_i, mixed with cosine);
- the same BSDF with the cosine + theta_h-lobe mixture that the table competes with
  ("lobe"), and with pure cosine-weighted hemisphere sampling ("cosine");
- Mitsuba's ``measured`` plugin on the file itself (its sampling warps through the
  file's VNDF and luminance tables, Dupuy & Jakob 2018).

At each incidence of ``--angles`` one ``sample()`` call draws ``--samples`` directions
(seeded); the estimator of the directional albedo is the mean sample weight, and its
per-sample variance (mean over channels) is printed: ``var cos / var ours`` > 1 means our
sampling needs fewer samples than cosine sampling for the same noise, ``var measured / var
ours`` > 1 fewer than ``measured``'s. The albedos themselves are printed as a check (ours
and measured agree to the compression error of the table). Then a fitted GGX model
(``lambert+ggx``, alpha 0.1, the glossy case) is compared against cosine sampling alone.

Time per sample: one ``sample()`` call on ``--samples`` directions, best of ``--repeats``
(our numpy path against ``measured``'s compiled kernel, run once untimed first for
tracing). On a shared machine compare rows of one run.

Render speed (``--render``): the sphere scene of ``compress.mitsuba.sphere_scene``
(``--size`` 256, ``--spp`` 256, ``max_depth`` 2) rendered with ``mi.render`` in Mitsuba's
default (symbolic) mode, for one RGL file (``--material``, default vch_golden_yellow): by
``measured`` on the file, and by our plugin on ``compress.select(read_rgl(file), 0.10)``'s
answer, a full-turn factored lobe (rank 5, bins (32, 24, 16)), a ``lambert+ggx`` fit, a
``HemiZernike(8)`` projection, and Mitsuba's ``diffuse`` (the cost of everything but the
BSDF). The forms are built once and kept in ``--cache``. Rounds alternate the materials;
the first round traces and compiles, the table shows each later round's time and its ratio
to ``measured`` in the same round. Then the per-sample cost of ``eval`` and ``sample``
(one call on ``--samples`` pairs at theta_i = 30 degrees, kernels compiled, best of
``--repeats``), for each form against ``measured``: the profile of where a render's time
goes (render time minus ``diffuse``'s is the BSDF's share).

Run: ``python tests/benchmarks/bench_mitsuba.py [--samples 262144] [--bins 16,12,8]``
or ``... --render [--size 256 --spp 256 --rounds 3]``; needs the ``[mitsuba]`` extra and
LLVM >= 16 for ``llvm_ad_rgb``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

mi.set_variant("llvm_ad_rgb")

from _machine import header, tag  # noqa: E402 - the machine: CPU, features, vector width

import compress.mitsuba as cmi  # noqa: E402
from compress.mitsuba._sampling import _lobe_sampler  # noqa: E402
from project import FittedModel  # noqa: E402
from project.measured import read_rgl  # noqa: E402
from project.tabulated import tabulate  # noqa: E402


def weights(b, theta: float, n: int, seed: int) -> np.ndarray:
    """(n, 3) sample weights of one sample() call at incidence theta (radians)."""
    rng = np.random.default_rng(seed)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(math.sin(theta), 0.0, math.cos(theta))
    u = rng.random((3, n)).astype(np.float32)
    _, w = b.sample(mi.BSDFContext(), si, mi.Float(u[0]), mi.Point2f(u[1:]))
    dr.eval(w)
    return np.array(w, dtype=np.float64).T


def seconds(b, n: int, repeats: int) -> float:
    weights(b, 0.5, n, 0)  # trace and compile once
    best = math.inf
    for k in range(repeats):
        t = time.perf_counter()
        weights(b, 0.5, n, k + 1)
        best = min(best, time.perf_counter() - t)
    return best


def compare(name: str, cands: dict, angles: list[float], n: int) -> None:
    print(f"\n{name}")
    head = "theta  " + "  ".join(f"{k:>22s}" for k in cands) + "   var ratios (other / ours)"
    print(head)
    for deg in angles:
        row, var = [], {}
        for k, b in cands.items():
            w = weights(b, math.radians(deg), n, seed=int(deg))
            var[k] = float(np.mean(w.var(axis=0)))
            row.append(f"{np.mean(w):8.4f} (var {var[k]:.3g})")
        ratios = ", ".join(f"{k} {var[k] / var['ours']:.3g}" for k in var if k != "ours")
        print(f"{deg:5.1f}  " + "  ".join(f"{r:>22s}" for r in row) + f"   {ratios}")


def _forms(path: Path, cache: Path) -> dict[str, Path]:
    """Build (once) the forms of one RGL file that --render compares; return their files."""
    import warnings

    import basis
    import compress
    import project
    cache.mkdir(parents=True, exist_ok=True)
    stem = path.name.split(".")[0]
    makers = {
        "select 10 %": lambda b: compress.select(b, 0.10),
        "factored full turn": lambda b: project.fit_model(b, "factored", rank=5,
                                                          bins=(32, 24, 16),
                                                          phi_turn="full", tol=1e-4),
        "lambert+ggx": lambda b: project.fit_model(b, "lambert+ggx"),
        "HemiZernike(8)": lambda b: project.project(b, basis.HemiZernike(8)),
    }
    out = {}
    brdf = None
    for name, make in makers.items():
        f = cache / f"{stem}-{name.replace(' ', '_').replace('%', 'pc')}.h5"
        if not f.exists():
            brdf = brdf or read_rgl(path)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                compress.save(make(brdf), f)
        out[name] = f
    return out


def _render_seconds(scene: object) -> float:
    t = time.perf_counter()
    img = mi.render(scene, seed=1)
    dr.eval(img)
    dr.sync_thread()
    return time.perf_counter() - t


def _call_seconds(fn: object, repeats: int) -> float:
    fn()  # trace and compile
    best = math.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        dr.sync_thread()
        best = min(best, time.perf_counter() - t)
    return best


def render_speed(path: Path, cache: Path, size: int, spp: int, rounds: int, n: int,
                 repeats: int) -> None:
    """The --render tables: render times against measured, per-sample eval/sample costs."""
    import compress
    files = _forms(path, cache)
    materials = {"measured": {"type": "measured", "filename": str(path)},
                 "diffuse": {"type": "diffuse"}}
    reps = {}
    for name, f in files.items():
        reps[name] = compress.load(f)
        materials[name] = cmi.bsdf(f)
        print(f"{name:20s} {reps[name]!r}; sampler {materials[name].sampler!r}; "
              f"traced {materials[name].traced}")
    scenes = {k: cmi.sphere_scene(m, size=size, spp=spp) for k, m in materials.items()}
    times: dict[str, list[float]] = {k: [] for k in scenes}
    for _ in range(rounds):
        for k, sc in scenes.items():
            times[k].append(_render_seconds(sc))
    print(f"\n{path.name}: sphere scene {size} x {size}, {spp} spp, {mi.variant()}, "
          f"mi.render (symbolic); seconds per round (first: tracing and compilation), "
          f"ratio to measured per later round")
    for k, v in times.items():
        ratios = " ".join(f"{v[r] / times['measured'][r]:.2f}" for r in range(1, rounds))
        print(f"{k:20s} {' '.join(f'{x:6.2f}' for x in v)}   ratio {ratios}")
    rng = np.random.default_rng(0)
    wo = rng.normal(size=(n, 3))
    wo[:, 2] = np.abs(wo[:, 2])
    wo = mi.Vector3f((wo / np.linalg.norm(wo, axis=1)[:, None]).T.astype(np.float32))
    u = rng.random((3, n)).astype(np.float32)
    u0, u12 = mi.Float(u[0]), mi.Point2f(u[1:])
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(0.5, 0.0, math.sqrt(0.75))
    ctx = mi.BSDFContext()
    print(f"\nper-sample cost (ns; one call on {n} pairs, theta_i = 30 deg, best of "
          f"{repeats}); eval, pdf, sample (= draw + pdf + eval: the draw is the rest), and "
          f"the render's BSDF share (render - diffuse) per sample of the last round")
    base = times["diffuse"][-1]
    for k, b in materials.items():
        if k == "diffuse":
            continue
        b = b if not isinstance(b, dict) else mi.load_dict(b)
        t_eval = _call_seconds(lambda b=b: dr.eval(b.eval(ctx, si, wo)), repeats)
        t_pdf = _call_seconds(lambda b=b: dr.eval(b.pdf(ctx, si, wo)), repeats)
        t_samp = _call_seconds(lambda b=b: dr.eval(b.sample(ctx, si, u0, u12)), repeats)
        share = (times[k][-1] - base) / (size * size * spp)
        print(f"{k:20s} eval {1e9 * t_eval / n:6.1f}  pdf {1e9 * t_pdf / n:6.1f}  sample "
              f"{1e9 * t_samp / n:6.1f} (draw ~{1e9 * (t_samp - t_eval - t_pdf) / n:6.1f})  "
              f"render share {1e9 * share:6.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", nargs="*", default=None)
    ap.add_argument("--samples", type=int, default=1 << 18)
    ap.add_argument("--bins", default="16,12,8")
    ap.add_argument("--angles", default="0,30,60,80")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--render", action="store_true", help="render speed (module notes)")
    ap.add_argument("--material", default=str(ROOT.parent / "shared" / "data" / "rgl" /
                                              "vch_golden_yellow_rgb.bsdf"))
    ap.add_argument("--cache", default=str(ROOT / ".bench-cache"))
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    if args.render:
        render_speed(Path(args.material), Path(args.cache), args.size, args.spp, args.rounds,
                     args.samples, args.repeats)
        return
    files = [Path(f) for f in args.files] if args.files else \
        [ROOT / "tests" / "data" / "paper_white_rgb.bsdf"] + \
        sorted(p for p in (ROOT.parent / "shared" / "data" / "rgl").glob("*.bsdf")
               if p.name != "paper_white_rgb.bsdf")
    bins = tuple(int(b) for b in args.bins.split(","))
    angles = [float(a) for a in args.angles.split(",")]
    n = args.samples
    print(header())
    print(f"On {tag()}: samples per call {n}, table bins {bins}, variant {mi.variant()}")
    for path in files:
        tab = FittedModel("tabulated", tabulate(read_rgl(path), bins).params)
        ours = cmi.bsdf(tab, incident="camera")
        lobe = cmi.bsdf(tab, incident="camera")
        lobe.sampler = _lobe_sampler(tab)
        cosine = cmi.bsdf(tab, incident="camera")
        cosine.sampler = cmi.LobeSampler("cosine")
        measured = mi.load_dict({"type": "measured", "filename": str(path)})
        compare(f"{path.name}: {ours.sampler!r}",
                {"ours": ours, "lobe": lobe, "cosine": cosine, "measured": measured},
                angles, n)
        t_ours, t_meas = seconds(ours, n, args.repeats), seconds(measured, n, args.repeats)
        print(f"time per sample: ours {1e9 * t_ours / n:.0f} ns, measured "
              f"{1e9 * t_meas / n:.0f} ns, ratio measured/ours {t_meas / t_ours:.3g}")
    ggx = FittedModel("lambert+ggx", {"kd": [0.05] * 3, "ks": [0.9] * 3, "alpha": 0.1,
                                      "f0": 0.9})
    ours = cmi.bsdf(ggx)
    cosine = cmi.bsdf(ggx)
    cosine.sampler = cmi.LobeSampler("cosine")
    compare(f"lambert+ggx alpha 0.1: {ours.sampler!r}", {"ours": ours, "cosine": cosine},
            angles, n)


if __name__ == "__main__":
    main()
