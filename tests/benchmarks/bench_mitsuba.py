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

Run: ``python tests/benchmarks/bench_mitsuba.py [--samples 262144] [--bins 16,12,8]``;
needs the ``[mitsuba]`` extra and LLVM >= 16 for ``llvm_ad_rgb``.
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", nargs="*", default=None)
    ap.add_argument("--samples", type=int, default=1 << 18)
    ap.add_argument("--bins", default="16,12,8")
    ap.add_argument("--angles", default="0,30,60,80")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
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
