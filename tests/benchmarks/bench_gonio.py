"""Held-out errors of fit_model(meas, "lambert+ggx") against a plain least-squares fit.

Stand-ins for goniometer tables of glossy paints (tests/project/gonio.py): eight analytic
paints and the RGL-EPFL files of ../shared/data/rgl seen through the Cornell layout, 31
wavelengths, noise, outliers. For each, 80/20 splits (seeds 0, 1): the held-out relative
l2 error of q and the log error (largest over the channels) of both fits, and whether
fit_model meets l2 <= 1.05 x plain + 0.01 and log <= 1.05 x plain + 0.002.

    python tests/benchmarks/bench_gonio.py [--select] [--splits N] [names...]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import compress  # noqa: E402
import project  # noqa: E402
from tests.project import gonio  # noqa: E402

RGL = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgl"


def stand_ins(names: list[str], near_mirror: bool = True) -> dict[str, project.Measurements]:
    """The stand-ins, in the layout with (or without) the positions around the mirror."""
    wi, wo = gonio.cornell_layout(0, near_mirror=near_mirror)
    out = {}
    for k, p in enumerate(gonio.paints()):
        if not names or p.name in names:
            out[p.name] = gonio.measure(p, wi, wo, seed=100 + k, clip=k % 2 == 1)
    for k, path in enumerate(sorted(RGL.glob("*.bsdf"))):
        name = path.stem.removesuffix("_rgb")
        if not names or name in names:
            b = gonio.rgl_spectral(project.measured.read_rgl(path))
            out[name] = gonio.measure(b, wi, wo, seed=200 + k, name=name)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("names", nargs="*")
    ap.add_argument("--splits", type=int, default=2)
    ap.add_argument("--select", action="store_true")
    ap.add_argument("--grid", action="store_true", help="the layout without near-mirror "
                    "positions")
    args = ap.parse_args()
    sets = stand_ins(args.names, near_mirror=not args.grid)
    print(f"{'table':22s} {'split':>5s} {'plain l2':>9s} {'fit l2':>8s} {'plain log':>9s} "
          f"{'fit log':>8s} {'alpha p/f':>15s} {'ok':>3s} {'s p/f':>9s}")
    fails = 0
    for name, meas in sets.items():
        for s in range(args.splits):
            train, test = gonio.split(meas, s)
            t0 = time.perf_counter()
            with threadpool_limits(1, "blas"):
                pf = gonio.plain_fit(train)
            t1 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                fm = project.fit_model(train, "lambert+ggx", folds=0)
            t2 = time.perf_counter()
            lp, gp = gonio.held_out(test, pf.eval(test.wi, test.wo))
            lf, gf = gonio.held_out(test, fm.eval(test.wi, test.wo))
            ok = lf <= 1.05 * lp + 0.01 and gf <= 1.05 * gp + 0.002
            fails += not ok
            print(f"{name:22s} {s:5d} {lp:9.4f} {lf:8.4f} {gp:9.5f} {gf:8.5f} "
                  f"{pf.alpha:7.4f}/{float(fm.params['alpha']):7.4f} {'yes' if ok else 'NO':>3s}"
                  f" {t1 - t0:4.1f}/{t2 - t1:4.1f}", flush=True)
    print(f"{fails} split(s) where fit_model is worse than the criteria")
    if args.select:
        for name, meas in sets.items():
            t0 = time.perf_counter()
            try:
                rep = compress.select(meas, 0.25)
                row = rep.info["selected"]
                print(f"select {name}: {row['label']} {row['dtype']} {row['bytes']} B "
                      f"l2 {row['l2']:.4f} ({time.perf_counter() - t0:.1f} s)", flush=True)
            except compress.NoCandidateError as e:
                print(f"select {name}: none ({time.perf_counter() - t0:.1f} s): {e}"[:300],
                      flush=True)


if __name__ == "__main__":
    main()
