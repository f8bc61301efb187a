"""Benchmark: BRDF evaluation from coefficients against MERL table lookup, and the cold start.

What it measures
----------------
1. Evaluation. For one MERL-format table (``--material``, written by
   ``../shared/tools/merl_surrogate.py`` when ``../shared`` is present; otherwise a synthetic
   table sampled from a Cook-Torrance model on the MERL grid), and for RGB isotropic matrices of
   HemiZernike(``--order``) and HemiHarmonics(``--order``) with seeded random symmetric blocks
   (the cost does not depend on the values; projecting the table takes minutes and is timed by
   ``bench_project.py``), at the same ``--pairs`` random direction pairs (seeded, uniform in
   solid angle on H x H), one call of

   - ``MERLBRDF.eval`` (the peer: trilinear lookup, the public call with validation);
   - ``project.measured.merl._merl_lookup_kernel``, the lookup kernel alone (no validation);
   - ``CoefficientMatrix.eval`` (the public call with validation) for each basis;
   - ``Evaluator.eval_flat`` (no validation, preallocated output) for each basis;
   - the compact forms ``select`` chooses on real materials, fitted to the table once
     (untimed): full-turn factored lobes of rank 4 and 8 (``project.factored``) and Tucker
     tensors of 1024 and 4096 reals (``project.tucker``), ``FittedModel.eval``.

   Every callable runs once untimed (compilation, cache, first touch), then all run in turn
   for ``--repeats`` rounds and the best call of each is reported: ms per call, million pairs
   per second, and the throughput ratio to ``MERLBRDF.eval`` (> 1: faster than the lookup).

2. Cold start (skip with ``--no-cold-start``). ``scatmodes demo`` runs twice in fresh
   processes with an empty numba cache (``NUMBA_CACHE_DIR`` set to a new temporary folder):
   the first run compiles every kernel it uses and writes the cache, the second loads it.
   Reported: both wall times and their ratio. The demo's own options are passed through
   ``--demo-args``.

On a shared machine the other processes slow every row alike; compare rows of one run (the
header reports the load average).

Run: ``python tests/benchmarks/bench_eval.py [--pairs N] [--order 8] [--no-cold-start]``.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from _machine import header, tag  # noqa: E402 - the machine: CPU, features, vector width

import basis  # noqa: E402
import project  # noqa: E402
from basis.jit import run_parallel  # noqa: E402
from project.measured.merl import MERLBRDF, _merl_lookup_kernel, merl_grid, read_merl  # noqa: E402


def pairs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Two (n, 3) C-contiguous arrays of directions uniform in solid angle on the hemisphere."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(2):
        z = rng.uniform(0.0, 1.0, n)
        phi = rng.uniform(0.0, 2 * np.pi, n)
        s = np.sqrt(1 - z * z)
        out.append(np.ascontiguousarray(np.stack([s * np.cos(phi), s * np.sin(phi), z], -1)))
    return out[0], out[1]


def table(material: str | None) -> MERLBRDF:
    """The surrogate MERL table of ``material`` if the tool is there, else a synthetic one."""
    tool = ROOT.parent / "shared" / "tools" / "merl_surrogate.py"
    if material and tool.is_file():
        with tempfile.TemporaryDirectory() as tmp:
            r = subprocess.run([sys.executable, str(tool), material, "-o", tmp],
                               capture_output=True, text=True, check=False)
            path = Path(tmp) / f"{material}.binary"
            if r.returncode == 0 and path.is_file():
                return read_merl(path)
        print(f"(surrogate for {material} failed: {r.stderr.strip()[-200:]}; synthetic table)")
    th, td, pd = merl_grid()
    model = project.models.CookTorrance([0.3, 0.25, 0.2], 0.35)
    t, d, p = np.meshgrid(th, td, pd, indexing="ij")
    wi, wo = basis.from_rusinkiewicz(t, 0.0, d, p)
    ok = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    v = np.full((*t.shape, 3), np.nan)
    v[ok] = model.eval(wi[ok], wo[ok])
    return MERLBRDF(np.moveaxis(v, -1, 0), name="synthetic-cook-torrance")


def best_times(fns: dict, repeats: int) -> dict[str, float]:
    """Best wall time (s) of each callable, called in turn (a disturbance hits all alike)."""
    for fn in fns.values():
        fn()
    best = dict.fromkeys(fns, np.inf)
    for _ in range(repeats):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            best[k] = min(best[k], time.perf_counter() - t0)
    return best


def evaluation(args: argparse.Namespace) -> None:
    brdf = table(args.material)
    wi, wo = pairs(args.pairs, 7)
    out = np.empty((args.pairs, 3))
    fns = {"MERLBRDF.eval (peer)": lambda: brdf.eval(wi, wo),
           "MERL lookup kernel": lambda: run_parallel(_merl_lookup_kernel, args.pairs, wi, wo,
                                                      brdf._lut, True, out, grain=128)}
    rng = np.random.default_rng(11)
    for b in (basis.HemiZernike(args.order), basis.HemiHarmonics(args.order)):
        blocks = [rng.normal(size=(3, i.size, i.size)) for i in b.azimuthal_blocks().cos]
        cm = basis.CoefficientMatrix.from_blocks(b, blocks, "f_cos")  # symmetrised
        ev = cm.evaluator()
        fns[f"{b!r} CoefficientMatrix.eval"] = lambda cm=cm: cm.eval(wi, wo)
        fns[f"{b!r} eval_flat"] = lambda ev=ev: ev.eval_flat(wi, wo, out)
    with project.factored.reuse_samples():
        forms = [project.fit_model(brdf, "factored", rank=r, bins=b, phi_turn="full",
                                   error_n=4096) for r, b in ((4, (32, 24, 16)),
                                                              (8, (48, 32, 16)))]
        forms += [project.fit_model(brdf, "tucker", budget=n, phi_turn="full", error_n=4096)
                  for n in (1024, 4096)]
    for m in forms:
        fns[f"{m!r}"[:90]] = lambda m=m: m.eval(wi, wo)
    best = best_times(fns, args.repeats)
    ref = best["MERLBRDF.eval (peer)"]
    print(f"\n{args.pairs} pairs, RGB, table {brdf.name}, on {tag()}:")
    print("| evaluator | ms per call | M pairs/s | throughput ratio to MERLBRDF.eval |")
    print("| --- | ---: | ---: | ---: |")
    for k, t in best.items():
        print(f"| {k} | {t * 1e3:.1f} | {args.pairs / t / 1e6:.1f} | {ref / t:.2f} |")


def cold_start(args: argparse.Namespace) -> None:
    exe = shutil.which("scatmodes", path=str(Path(sys.executable).parent)) or "scatmodes"
    cmd = [exe, "demo", *shlex.split(args.demo_args)]
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, NUMBA_CACHE_DIR=str(Path(tmp) / "numba"))
        times = []
        for run in (1, 2):
            t0 = time.perf_counter()
            r = subprocess.run([*cmd, "--out", str(Path(tmp) / f"out{run}")], env=env,
                               capture_output=True, text=True, check=False)
            times.append(time.perf_counter() - t0)
            if r.returncode:
                print(f"cold start: {' '.join(cmd)} failed:\n{r.stderr[-2000:]}")
                return
    print(f"\n`{' '.join(cmd)}` with an empty numba cache, then again")
    print(f"On {tag()}:")
    print("| run | wall s |")
    print("| --- | ---: |")
    print(f"| first (compiles, writes the cache) | {times[0]:.1f} |")
    print(f"| second (loads the cache) | {times[1]:.1f} |")
    print(f"| ratio first / second | {times[0] / times[1]:.2f} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=1 << 20)
    ap.add_argument("--order", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--material", default="gold-metallic-paint")
    ap.add_argument("--no-cold-start", dest="cold", action="store_false")
    ap.add_argument("--demo-args", default="", help="extra options of scatmodes demo")
    args = ap.parse_args(argv)
    print(header())
    print(f"# bench_eval: numba threads {numba.get_num_threads()}, "
          f"load average {os.getloadavg()[0]:.2f}")
    evaluation(args)
    if args.cold:
        cold_start(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
