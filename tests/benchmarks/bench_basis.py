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
``OMP_NUM_THREADS``, which is set before sphericart is imported, along with
``OMP_WAIT_POLICY=PASSIVE`` unless the caller set a policy: numba's "omp" threading layer and
sphericart each load their own OpenMP runtime, and spinning idle threads in one slow the other.
Each evaluator is called once untimed (JIT compilation or cache load, first touch of buffers).
Then all evaluators of one L are called in turn for ``--repeats`` rounds under
``time.perf_counter``, and the best call of each is reported. A call includes what a user
pays: input validation and a fresh output array. On a shared or virtual machine the run-to-run
spread is larger than the gaps between rows, so compare rows from a single run. The header
line reports how busy the other processes kept the CPU.

Two more rows per L compare the arithmetic and the writes without the allocation: sphericart
writing into a preallocated array (the routine its numpy API calls once it has allocated;
skipped if a sphericart version lacks it) and ``basis.SphericalHarmonics.eval(dirs, out=buf)``
with a reused buffer; that row's ratio is to the preallocated sphericart row. Fresh rows minus
these rows is what allocating and first touching the output (page faults) costs each library.

Columns: ms per call; ns per (point x function), i.e. time / (points * functions); ratio =
our ns per (point x function) / sphericart's at the same L, so < 1 means we are faster;
throughput = its inverse (sphericart's ns / ours, > 1 means we are faster). The
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
from _machine import header, tag  # the machine: CPU model, features, vector width


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
                   help="largest accepted |ours - sphericart| (seen: 1.8e-13 at L=32)")
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


def best_times(fns: list, repeats: int) -> list[float]:
    """Best wall time (s) of each callable, calling them in turn, ``repeats`` rounds.

    Round robin rather than one evaluator after the other, so that a disturbance (another
    process, frequency changes) hits every evaluator alike. Results are dropped at once.
    """
    best = [np.inf] * len(fns)
    for _ in range(repeats):
        for j, fn in enumerate(fns):
            t0 = time.perf_counter()
            fn()
            best[j] = min(best[j], time.perf_counter() - t0)
    return best


def busy_cores(seconds: float = 1.0) -> float:
    """Cores kept busy by other processes while we sleep (Linux /proc/stat; nan elsewhere)."""
    def snapshot() -> tuple[int, int]:
        with open("/proc/stat") as f:
            ticks = [int(t) for t in f.readline().split()[1:]]
        return sum(ticks), ticks[3] + ticks[4]  # total, idle + iowait

    try:
        total0, idle0 = snapshot()
        time.sleep(seconds)
        total1, idle1 = snapshot()
    except (OSError, ValueError, IndexError):
        return float("nan")
    return (os.cpu_count() or 1) * (1.0 - (idle1 - idle0) / max(total1 - total0, 1))


def max_abs_diff(ours: np.ndarray, ref: np.ndarray, cols: np.ndarray, scale: float,
                 chunk: int = 16384) -> float:
    """max |ours - scale * ref[:, cols]|, by blocks of rows (no full-size temporaries)."""
    return max(float(np.max(np.abs(ours[i:i + chunk] - scale * ref[i:i + chunk, cols])))
               for i in range(0, ours.shape[0], chunk))


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    # OpenMP reads these when sphericart's runtime loads: set them before the import. numba's
    # "omp" threading layer uses a second OpenMP runtime; with the default wait policy each
    # runtime's idle threads spin after a call and slow the next call of the other (measured:
    # sphericart at L=8 took 12 to 28 ms, against 11 to 12 ms with PASSIVE).
    os.environ["OMP_NUM_THREADS"] = str(args.threads)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
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

    _fill_kernel(np.empty((1, 1)))  # compile; numba picks its threading layer here
    dirs = directions(args.points, args.seed)
    n = dirs.shape[0]
    busy = busy_cores()
    print(header())
    print(f"# bench_basis: {n} points, best of {args.repeats}, {platform.machine()} "
          f"({os.cpu_count()} cores), numpy {np.__version__}, numba {numba.__version__}, "
          f"sphericart {version('sphericart')}")
    env = {k: os.environ[k] for k in ("OMP_NUM_THREADS", "OMP_WAIT_POLICY")}
    print(f"# threads: numba.get_num_threads() = {numba.get_num_threads()} "
          f"({numba.threading_layer()} layer), {env}; other processes kept {busy:.2f} cores "
          "busy before start" + (" (timings will be disturbed)" if busy > 0.2 else ""))

    rows, failed = [], False
    for order in args.orders:
        sc = sphericart.SphericalHarmonics(order)
        ours = [b for b in (basis.SphericalHarmonics(order), basis.HemiZernike(order),
                            basis.HemiHarmonics(order)) if b.size]  # HemiHarmonics(0) is empty
        floor_shape = (n, (order + 1) ** 2)
        # Warm-up calls (JIT compile or cache load, first touch), which also check the values.
        y_sc = sc.compute(dirs)
        for b in ours:
            y = b.eval(dirs)
            if not isinstance(b, basis.SphericalHarmonics):  # HemiZernike: no reference here
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
        del y, y_sc

        names = ["sphericart.SphericalHarmonics"] + [f"basis.{type(b).__name__}" for b in ours]
        names.append("write floor (np.empty + fill)")
        sizes = [floor_shape[1]] + [b.size for b in ours] + [floor_shape[1]]
        fns = [partial(sc.compute, dirs)] + [partial(b.eval, dirs) for b in ours]
        fns.append(lambda shape=floor_shape: _fill_kernel(np.empty(shape)))
        # Like with like without the allocation: each library writes into a buffer it reused
        # (ours through ``out=``, sphericart through the routine its numpy API calls after
        # allocating). The gap to the fresh rows is the page-fault share of a call.
        warm = hasattr(sc, "_compute_numpy")
        if warm:
            buf_sc = np.empty(floor_shape)
            buf_sh = np.empty((n, ours[0].size))
            names += ["sphericart, preallocated output", "basis.SphericalHarmonics, out="]
            sizes += [floor_shape[1], ours[0].size]
            fns.append(partial(sc._compute_numpy, dirs, buf_sc, None, None))
            fns.append(partial(ours[0].eval, dirs, out=buf_sh))
        for name, size, t in zip(names, sizes, best_times(fns, args.repeats), strict=True):
            rows.append((name, order, size, t, t / (n * size)))
        if warm:
            del buf_sc, buf_sh

    print(f"\nOn {tag()}:")
    print("| basis | L | functions | ms per call | ns per (point x function) "
          "| ratio to sphericart | throughput vs sphericart |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    ref = {order: per for name, order, _, _, per in rows
           if name == "sphericart.SphericalHarmonics"}
    ref_warm = {order: per for name, order, _, _, per in rows
                if name == "sphericart, preallocated output"}
    for name, order, size, t, per in rows:
        if name == "basis.SphericalHarmonics, out=":  # against the preallocated sphericart row
            print(f"| {name} | {order} | {size} | {t * 1e3:.1f} | {per * 1e9:.3f} "
                  f"| {per / ref_warm[order]:.2f} (to preallocated) "
                  f"| {ref_warm[order] / per:.2f} (to preallocated) |")
            continue
        print(f"| {name} | {order} | {size} | {t * 1e3:.1f} | {per * 1e9:.3f} "
              f"| {per / ref[order]:.2f} | {ref[order] / per:.2f} |")
    if failed:
        print("\nbench_basis: sphericart and basis disagree (see the checks above)",
              file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
