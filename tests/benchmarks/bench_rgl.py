"""Benchmark: evaluating an RGL-EPFL measured material, ours against Mitsuba 3's ``measured``.

What it measures
----------------
One RGB ``.bsdf`` file (``--file``, default the copy in ``tests/data``) is read by
:func:`project.measured.read_rgl` and loaded as Mitsuba 3's ``measured`` plugin. At the same
``--pairs`` random pairs (seeded, uniform in solid angle on H x H):

- ``RGLBRDF.eval``: the public call, validation of the directions included (the target is
  at least 1 M pairs/s on 2 cores);
- Mitsuba ``scalar_rgb``, the variant available without LLVM (the default peer). It has no
  vectorised call, so it runs a Python loop over the first ``--scalar-pairs`` pairs and
  the per-pair rate is compared: it is dominated by the Python-to-C++ call (a second loop
  over the trivial ``diffuse`` plugin measures that overhead: on our 2-core machine both
  loops run at ~0.14 M pairs/s, so the model's own cost is lost in it), so this ratio
  (~20x) measures Python calls, not the model;
- with ``--llvm``, Mitsuba ``llvm_ad_rgb`` vectorised: one ``bsdf.eval`` on all pairs as
  drjit arrays, forced with ``dr.eval``, run once untimed first (tracing and compiling).
  The fair peer, but it needs a recent libLLVM: drjit 1.5 with the system's LLVM 14/15
  aborts the process ("LLVM ERROR: Cannot select ... fminimum"), hence opt-in.

Both libraries return f cos(theta_o) / f, so ours is multiplied by cos(theta_o) and the
largest difference is printed as a check (float32 in Mitsuba: ~1e-5 of the largest value).
Each timing is the best of ``--repeats`` runs; ratio > 1 means ours is faster. On a shared
machine compare rows of one run.

Run: ``python tests/benchmarks/bench_rgl.py [--pairs 1000000] [--file F.bsdf]``; needs the
``[bench]`` extra (``pip install mitsuba``).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from _machine import header, tag  # noqa: E402 - the machine: CPU, features, vector width

from project.measured import read_rgl  # noqa: E402


def pairs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Two (n, 3) arrays of directions uniform in solid angle on the upper hemisphere."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(2):
        w = rng.normal(size=(n, 3))
        w[:, 2] = np.abs(w[:, 2])
        out.append(w / np.linalg.norm(w, axis=1, keepdims=True))
    return out[0], out[1]


def best(fn, repeats: int) -> tuple[float, object]:
    """Best wall time of ``repeats`` calls of ``fn`` and its last result."""
    times, result = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t)
    return min(times), result


def main() -> int:
    """Time both and print rates, ratios and the agreement."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--file", default=str(ROOT / "tests" / "data" / "paper_white_rgb.bsdf"))
    p.add_argument("--pairs", type=int, default=1_000_000)
    p.add_argument("--scalar-pairs", type=int, default=20_000)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--llvm", action="store_true", help="also time llvm_ad_rgb (see above)")
    args = p.parse_args()
    print(header())
    wi, wo = pairs(args.pairs, args.seed)
    brdf = read_rgl(args.file)
    brdf.eval(wi[:10], wo[:10])  # compile or load the cached kernel
    print(f"On {tag()}: {brdf!r}; {args.pairs} pairs; load average "
          f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}; {os.cpu_count()} cpus")
    t_ours, ours = best(lambda: brdf.eval(wi, wo), args.repeats)
    ours_cos = ours * wo[:, 2:3]
    print(f"{'RGLBRDF.eval (with validation)':44s} {1e3 * t_ours:9.1f} ms "
          f"{args.pairs / t_ours / 1e6:8.2f} M pairs/s")
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError:
        print("mitsuba not installed: pip install mitsuba (the [bench] extra)")
        return 0

    if args.llvm:
        mi.set_variant("llvm_ad_rgb")
        plugin = mi.load_dict({"type": "measured", "filename": args.file})
        si = dr.zeros(mi.SurfaceInteraction3f, args.pairs)
        si.wi = mi.Vector3f(*(wi[:, k].astype(np.float32) for k in range(3)))
        wo_mi = mi.Vector3f(*(wo[:, k].astype(np.float32) for k in range(3)))
        ctx = mi.BSDFContext()

        def run():
            value = plugin.eval(ctx, si, wo_mi)
            dr.eval(value)
            return np.array(value)

        run()  # trace and compile
        t_llvm, ref = best(run, args.repeats)
        ref = np.asarray(ref).reshape(3, -1).T if np.asarray(ref).shape[0] == 3 else ref
        diff = np.abs(ours_cos - np.maximum(ref, 0)).max() / np.abs(ref).max()
        print(f"{'Mitsuba llvm_ad_rgb eval (vectorised)':44s} {1e3 * t_llvm:9.1f} ms "
              f"{args.pairs / t_llvm / 1e6:8.2f} M pairs/s   ours / Mitsuba: "
              f"{t_llvm / t_ours:.2f}x; max |diff| / max = {diff:.2g}")

    mi.set_variant("scalar_rgb")
    n = min(args.scalar_pairs, args.pairs)
    ctx, si = mi.BSDFContext(), mi.SurfaceInteraction3f()
    rows = {}
    for kind in ("measured", "diffuse"):
        spec = {"type": kind, "filename": args.file} if kind == "measured" else {"type": kind}
        plugin = mi.load_dict(spec)

        def loop(plugin=plugin):
            out = np.empty((n, 3))
            for k in range(n):
                si.wi = mi.Vector3f(*wi[k])
                out[k] = plugin.eval(ctx, si, mi.Vector3f(*wo[k]))
            return out

        rows[kind] = best(loop, max(1, args.repeats // 2))
    t_scalar, ref = rows["measured"]
    diff = np.abs(ours_cos[:n] - np.maximum(ref, 0)).max() / np.abs(ref).max()
    print(f"{'Mitsuba scalar_rgb eval (Python loop)':44s} {1e3 * t_scalar:9.1f} ms "
          f"{n / t_scalar / 1e6:8.3f} M pairs/s   ours / Mitsuba: "
          f"{(t_scalar / n) / (t_ours / args.pairs):.0f}x; max |diff| / max = {diff:.2g} "
          f"({n} pairs)")
    t_diffuse = rows["diffuse"][0]
    print(f"{'  same loop over the diffuse plugin':44s} {1e3 * t_diffuse:9.1f} ms "
          f"{n / t_diffuse / 1e6:8.3f} M pairs/s   (the Python call overhead)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
