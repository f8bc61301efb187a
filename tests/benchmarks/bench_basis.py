"""Benchmark: evaluating the bases at many directions, against sphericart.

What it measures
----------------
For each order L in ``--orders`` (default 8, 16, 32), the wall time of one call of

- ``sphericart.SphericalHarmonics(L).compute(xyz)``, the numpy API, (L+1)^2 functions;
- ``basis.SphericalHarmonics(L).eval(dirs)``, (L+1)^2 functions;
- ``basis.HemiZernike(L).eval(dirs)``, (L+1)(L+2)/2 functions;
- ``basis.HemiHarmonics(L).eval(dirs)`` (parity "odd"), L(L+1)/2 functions;
- "write floor": allocating a fresh float64 array of sphericart's output shape and filling it
  with a parallel numba loop. No evaluator can beat this, since they all return a fresh array.

Every evaluator sees the same ``--points`` random directions (seeded and uniform on the
sphere, with z replaced by |z| so the hemisphere bases accept them) and runs on the same
number of threads. numba gets ``numba.set_num_threads`` and sphericart's OpenMP gets
``OMP_NUM_THREADS``, which is set before sphericart is imported. Each evaluator is called
once untimed (JIT compilation or cache load, first touch of buffers), then ``--repeats``
times under ``time.perf_counter``, and the best call is reported. A call includes what a user
pays: input validation and a fresh output array.

Columns: ms per call; ns per (point x function), i.e. time / (points * functions); ratio =
our ns per (point x function) / sphericart's at the same L, so < 1 means we are faster. The
hemisphere bases have fewer functions than sphericart at the same L, so their ratio compares
the cost per function, not per call.

Before timing, the script checks that sphericart and ``basis.SphericalHarmonics`` compute the
same functions in the same column order, k = l*l + l + m (real, orthonormal, no
Condon-Shortley phase). It also checks that HemiHarmonics equals sqrt(2) times the
sphericart columns with l + |m| odd. It prints both maximum differences and exits with
status 1 if either is above ``--tol``.

Run: ``python tests/benchmarks/bench_basis.py [--points N] [--orders 8 16 32] [--repeats 7]``.
sphericart is an optional dependency: ``pip install "scatmodes[bench]"``.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from functools import partial

import numpy as np


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--points", type=int, default=200_000, help="number of directions")
    p.add_argument("--orders", type=int, nargs="+", default=[8, 16, 32], help="orders L")
    p.add_argument("--repeats", type=int, default=7, help="timed calls; the best is reported")
    p.add_argument("--threads", type=int,
                   default=int(os.environ.get("OMP_NUM_THREADS", os.cpu_count() or 1)),
                   help="threads for numba and OpenMP (default: $OMP_NUM_THREADS or all cores)")
    p.add_argument("--seed", type=int, default=20240607, help="seed of the random directions")
    p.add_argument("--tol", type=float, default=1e-12,
                   help="largest accepted |ours - sphericart| (observed about 3e-14 at L=32)")
    args = p.parse_args(argv)
    if args.points < 1 or args.repeats < 1 or args.threads < 1 or min(args.orders) < 0:
        p.error("--points, --repeats and --threads must be >= 1, and --orders >= 0")
    return args


def directions(n: int, seed: int) -> np.ndarray:
    """(n, 3) uniform random unit vectors with z >= 0 (|z| of a uniform sample on the sphere)."""
    v = np.random.default_rng(seed).normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[:, 2] = np.abs(v[:, 2])
    return v


def best_time(fn, repeats: int) -> tuple[float, np.ndarray]:
    """Warm up once, then return (best of ``repeats`` wall times in s, the last result)."""
    out = fn()
    best = np.inf
    for _ in range(repeats):
        del out  # free the previous result first, so at most one extra result is held
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def max_abs_diff(ours: np.ndarray, ref: np.ndarray, cols: np.ndarray, scale: float,
                 chunk: int = 16384) -> float:
    """max |ours - scale * ref[:, cols]|, by blocks of rows (no full-size temporaries)."""
    return max(float(np.max(np.abs(ours[i:i + chunk] - scale * ref[i:i + chunk, cols])))
               for i in range(0, ours.shape[0], chunk))


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    # OpenMP reads OMP_NUM_THREADS when sphericart's runtime loads: set it before the import.
    os.environ["OMP_NUM_THREADS"] = str(args.threads)
    try:
        import sphericart
    except ImportError:
        print("bench_basis: sphericart is not installed; it is an optional dependency, "
              "install it with: pip install 'scatmodes[bench]'", file=sys.stderr)
        return 2
    from importlib.metadata import version

    import numba

    import basis

    if args.threads > numba.config.NUMBA_NUM_THREADS:
        print(f"bench_basis: --threads must be <= {numba.config.NUMBA_NUM_THREADS} "
              f"(NUMBA_NUM_THREADS), got {args.threads}", file=sys.stderr)
        return 2
    numba.set_num_threads(args.threads)

    @numba.njit(parallel=True, cache=False)
    def _fill_kernel(out):
        # out (n, m): every element written once, rows split over threads like the bases
        for i in numba.prange(out.shape[0]):
            for j in range(out.shape[1]):
                out[i, j] = 1.0

    dirs = directions(args.points, args.seed)
    n = dirs.shape[0]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"# bench_basis: {n} points, best of {args.repeats}, {platform.machine()}"
          f" ({os.cpu_count()} cores), numpy {np.__version__}, numba {numba.__version__}, "
          f"sphericart {version('sphericart')}")
    print(f"# threads: numba.get_num_threads() = {numba.get_num_threads()}, OMP_NUM_THREADS = "
          f"{os.environ['OMP_NUM_THREADS']}; 1-minute load average before start {load:.2f}"
          + (" (other processes are busy: timings will be disturbed)" if load > 0.5 else ""))

    rows, failed = [], False
    for order in args.orders:
        sc = sphericart.SphericalHarmonics(order)
        t_sc, y_sc = best_time(partial(sc.compute, dirs), args.repeats)
        per_sc = t_sc / (n * y_sc.shape[1])
        rows.append(("sphericart.SphericalHarmonics", order, y_sc.shape[1], t_sc, per_sc))

        ours = [basis.SphericalHarmonics(order), basis.HemiZernike(order),
                basis.HemiHarmonics(order)]
        for b in ours:
            if b.size == 0:  # HemiHarmonics(0): the odd parity has no function of degree 0
                continue
            t, y = best_time(partial(b.eval, dirs), args.repeats)
            rows.append((f"basis.{type(b).__name__}", order, b.size, t, t / (n * b.size)))
            if not isinstance(b, basis.SphericalHarmonics):  # HemiZernike: no reference
                continue
            # our column order from our own (l, m) labels; sphericart's is l*l + l + m
            k = b.degree * b.degree + b.degree + b.azimuthal
            hemi = isinstance(b, basis.HemiHarmonics)
            if not hemi and not np.array_equal(k, np.arange(b.size)):
                print(f"# check L={order}: FAIL, SphericalHarmonics columns are not l*l+l+m")
                failed = True
            err = max_abs_diff(y, y_sc, k, np.sqrt(2.0) if hemi else 1.0)
            failed |= not err <= args.tol
            print(f"# check L={order}: max |{type(b).__name__} - "
                  f"{'sqrt(2) * ' if hemi else ''}sphericart| = {err:.2e} "
                  f"({'ok' if err <= args.tol else 'FAIL'}, tol {args.tol:.0e})")
        del y_sc
        t_fl, _ = best_time(lambda order=order: _fill_kernel(np.empty((n, (order + 1) ** 2))),
                            args.repeats)
        rows.append(("write floor (np.empty + fill)", order, (order + 1) ** 2, t_fl,
                     t_fl / (n * (order + 1) ** 2)))

    print()
    print("| basis | L | functions | ms per call | ns per (point x function) "
          "| ratio to sphericart |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    ref = {order: per for name, order, _, _, per in rows if name.startswith("sphericart")}
    for name, order, size, t, per in rows:
        print(f"| {name} | {order} | {size} | {t * 1e3:.1f} | {per * 1e9:.3f} "
              f"| {per / ref[order]:.2f} |")
    if failed:
        print("\nbench_basis: sphericart and basis disagree (see the checks above)",
              file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
