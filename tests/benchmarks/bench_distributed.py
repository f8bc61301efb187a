"""Benchmark: simulate on a Dask LocalCluster of 1, then 2 worker processes against the local run.

What it measures
----------------
One periodic Gaussian height field (sigma = 1, tau = 6.5, ``--size`` points per side, lossless
mirror facets) and :func:`project.microgeometry.simulate` at ``HemiZernike(--order)`` with
``--rays`` incident rays (``--chunk`` directions per chunk; default simulate's, 4096
directions of 8 rays). Rows:

- ``local``: ``simulate`` in this process (numba threads on every core).
- ``local 1 thread``: the same on one numba thread: the single-process, single-core time
  against which the scaling of worker processes is read (``/1 thread``).
- ``dask N``: the same call with ``client=`` on a ``LocalCluster(n_workers=N,
  threads_per_worker=1, processes=True)``; each worker process runs numba on its share of the
  cores. Every distributed matrix is checked to be bit-identical to the local one.

Columns: wall time; ``/local``, the wall time over the local run's (target: at most
0.75 of the single-process time for 2 workers on 2 cores, 1M rays, order 8; both readings of
"single process" are printed: all cores, and ``/1 thread``); ``efficiency``, the 1-worker
time over N times the N-worker time (1 = perfect scaling across workers); ``tasks``, the Dask
tasks of the run (a task traces a few consecutive chunks); ``overhead``, the N-worker time
minus the local time (scatter, submit, transfer and fold; on one machine a 1-worker cluster
runs the same kernels on the same cores as the local run).

Each row is run once untimed first (JIT compile or cache load in every process, cluster start
excluded) and then ``--repeats`` times; the best time is reported. The machine may be shared:
compare rows of one run.

Run: ``python tests/benchmarks/bench_distributed.py [--rays 1000000] [--order 8] [--size 512]
[--workers 1,2] [--quick]``; needs ``pip install 'scatmodes[distributed]'``.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np
from _machine import header, tag  # the machine: CPU model, features, vector width


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=None, help="grid points per side (512)")
    p.add_argument("--rays", type=int, default=None, help="incident rays per run (1000000)")
    p.add_argument("--order", type=int, default=8, help="HemiZernike order")
    p.add_argument("--chunk", type=int, default=None,
                   help="directions per chunk (task); default simulate's")
    p.add_argument("--workers", default="1,2", help="worker process counts, comma-separated")
    p.add_argument("--repeats", type=int, default=None,
                   help="timed runs; the best is reported (2)")
    p.add_argument("--quick", action="store_true",
                   help="reduced run: defaults --size 128 --rays 200000 --repeats 1")
    args = p.parse_args(argv)
    # --quick changes the defaults only: sizes given explicitly win
    for key, full, quick in (("size", 512, 128), ("rays", 1_000_000, 200_000),
                             ("repeats", 2, 1)):
        if getattr(args, key) is None:
            setattr(args, key, quick if args.quick else full)
    try:
        args.workers = [int(w) for w in args.workers.split(",")]
    except ValueError:
        p.error(f"--workers must be comma-separated integers, got {args.workers!r}")
    if min(args.size, args.rays, args.order + 1, args.repeats, *args.workers) < 1:
        p.error("all sizes must be >= 1")
    return args


def best(fn, repeats: int):
    """(best wall time, last result) of ``repeats`` calls."""
    times, res = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = fn()
        times.append(time.perf_counter() - t0)
    return min(times), res


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        print("bench_distributed needs dask.distributed: pip install 'scatmodes[distributed]'",
              file=sys.stderr)
        return 2
    import numba

    from basis import HemiZernike
    from project.microgeometry import GaussianSurface, simulate

    surface = GaussianSurface(1.0, 6.5, resolution=args.size, seed=1)
    basis = HemiZernike(args.order)
    run = {"rays": args.rays, "seed": 7, "chunk": args.chunk}
    print(header())
    print(f"{platform.node()}: {os.cpu_count()} cores; {surface!r}; {basis!r} "
          f"({basis.size} functions); {args.rays} rays")
    simulate(surface, basis, rays=1000, seed=1)  # JIT compile or cache load
    t_local, ref = best(lambda: simulate(surface, basis, **run), args.repeats)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        t_serial, ser = best(lambda: simulate(surface, basis, **run), args.repeats)
    finally:
        numba.set_num_threads(threads)
    if not np.array_equal(ser.matrix.matrix, ref.matrix.matrix):
        print("local 1 thread: the matrix differs from the local run's", file=sys.stderr)
        return 1
    from project.microgeometry import estimate  # private: how simulate groups chunks

    chunks = int(ref._acc["chunks"])  # private: the number of chunks of the run
    per_task = ref.meta["chunk"] * ref.meta["targets"]

    def tasks(n: int) -> int:
        group = max(1, min(-(-chunks // (estimate._TASKS_PER_WORKER * n)),
                           estimate._TASK_RAYS // per_task))
        return -(-chunks // group)

    print(f"On {tag()}:")
    print(f"{chunks} chunks of {ref.meta['chunk']} directions x {ref.meta['targets']} rays")
    print(f"{'run':>15} {'wall s':>8} {'/local':>7} {'/1 thread':>9} {'efficiency':>10} "
          f"{'tasks':>6} {'overhead':>9}")
    print(f"{'local':>15} {t_local:8.2f} {1.0:7.2f} {t_local / t_serial:9.2f}")
    print(f"{'local 1 thread':>15} {t_serial:8.2f} {t_serial / t_local:7.2f} {1.0:9.2f}")
    t_one = None
    for n in args.workers:
        with LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                          dashboard_address=None) as cluster, Client(cluster) as client:
            client.wait_for_workers(n)
            # every worker loads the kernels before timing (client.run: on each worker,
            # whereas tasks may all land on one), then one distributed run
            client.run(simulate, surface, basis, rays=8, seed=1)
            simulate(surface, basis, rays=8 * n, seed=1, chunk=1, client=client)
            t, res = best(lambda c=client: simulate(surface, basis, client=c, **run),
                          args.repeats)
        if not np.array_equal(res.matrix.matrix, ref.matrix.matrix):
            print(f"dask {n}: the matrix differs from the local run's", file=sys.stderr)
            return 1
        if n == 1:
            t_one = t
        eff = f"{t_one / (n * t):10.2f}" if t_one is not None else f"{'':>10}"
        print(f"{'dask ' + str(n):>15} {t:8.2f} {t / t_local:7.2f} {t / t_serial:9.2f} {eff} "
              f"{tasks(n):6d} {t - t_local:7.2f} s")
    print("every distributed matrix is bit-identical to the local one")
    return 0


if __name__ == "__main__":
    sys.exit(main())
