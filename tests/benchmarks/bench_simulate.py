"""Benchmark: tracing a Gaussian height field, ours (numba, max-mip pyramid) vs Mitsuba 3.

What it measures
----------------
One periodic Gaussian height field (sigma = 1, tau = 6.5, spacing tau / 4; ``--size`` grid
points per side, default 512: the 513 x 513 vertex mesh of 524,288 triangles of Westin et al.
1992, Fig 6) with lossless mirror facets, and ``--rays`` incident rays (cosine-distributed
directions, ``--targets`` rays per direction at uniform points of the period). Rows:

- ``ours simulate``: :func:`project.microgeometry.simulate` at ``HemiZernike(--order)``: the
  tracer (all bounces, on ``--threads`` numba threads) plus the coefficient accumulation
  (basis evaluation at every exit ray, the outer products, batch statistics).
- ``ours trace``: the same rays through the tracer alone (no accumulation).
- ``mitsuba intersect``: Mitsuba 3 (variant ``llvm_ad_rgb``, float32, its own BVH) with the
  same surface built in Python as one mesh of 2 n^2 triangles (the periodic tile plus its
  closing row and column, 513 x 513 vertices), ``Scene.ray_intersect`` called on the same
  incident ray batch and then on every bounce batch (mirror reflection about the geometric
  normal, computed with numpy between calls, only the still-active rays re-launched), until
  no ray hits. Mitsuba's mesh is not periodic: rays that leave the tile sideways stop, so it
  does at most as much work per ray as ours. The time counts only the ``ray_intersect``
  calls (plus Dr.Jit's evaluation of the result), not the numpy bounce logic.
- ``mitsuba + bounce``: the same, including the numpy bounce logic between calls.

rays/s = incident rays / wall time; ratio = ours / Mitsuba (> 1: we are faster). Each row is
run once untimed (JIT compile or cache load, BVH build) and then ``--repeats`` times; the best
time is reported. Both run on ``--threads`` threads (numba.set_num_threads and
``mi.set_log_level``/``dr.set_thread_count``). The machine may be shared: compare rows of one
run. Finally it prints the time our simulate needs to reach Q <= ``--qtarget`` at
HemiZernike(12) (rays doubled from 2^16 until Q meets the target).

Run: ``python tests/benchmarks/bench_simulate.py [--size 512] [--rays 1000000] [--quick]``.
mitsuba is optional (``pip install "scatmodes[bench]"``); without it only our rows print.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=512, help="grid points per side (mesh n+1)")
    p.add_argument("--rays", type=int, default=1_000_000, help="incident rays per row")
    p.add_argument("--targets", type=int, default=8, help="rays per incident direction")
    p.add_argument("--order", type=int, default=12, help="HemiZernike order for simulate")
    p.add_argument("--repeats", type=int, default=3, help="timed runs; the best is reported")
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="threads")
    p.add_argument("--qtarget", type=float, default=1e-3, help="Q target at HemiZernike(12)")
    p.add_argument("--quick", action="store_true",
                   help="small run: --size 128 --rays 100000 --repeats 1")
    args = p.parse_args(argv)
    if args.quick:
        args.size, args.rays, args.repeats = 128, 100_000, 1
    if min(args.size, args.rays, args.targets, args.repeats, args.threads) < 1:
        p.error("all sizes must be >= 1")
    return args


def best(fn, repeats: int) -> float:
    fn()  # untimed: compile / cache load / BVH build
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def mitsuba_runner(surface, dirs: np.ndarray, per: int, seed: int, threads: int):
    """Build the mesh and return fn(include_bounce_logic) -> (intersect seconds, hits)."""
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    dr.set_thread_count(threads)
    h = surface.heights
    ny, nx = h.shape
    sx, sy = surface.spacing
    # closed tile: (ny + 1) x (nx + 1) vertices, last row/column repeat the first
    hc = np.pad(h, ((0, 1), (0, 1)), mode="wrap")
    xs, ys = np.meshgrid(np.arange(nx + 1) * sx, np.arange(ny + 1) * sy)
    verts = np.stack([xs, ys, hc], -1).reshape(-1, 3).astype(np.float32)
    j, i = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    v00 = (j * (nx + 1) + i).reshape(-1)
    v10, v01, v11 = v00 + 1, v00 + nx + 1, v00 + nx + 2
    faces = np.concatenate([np.stack([v00, v10, v11], -1), np.stack([v00, v11, v01], -1)])
    mesh = mi.Mesh("heightfield", verts.shape[0], faces.shape[0])
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(verts.reshape(-1))
    params["faces"] = mi.UInt32(faces.astype(np.uint32).reshape(-1))
    params.update()
    scene = mi.load_dict({"type": "scene", "hf": mesh})
    # the same incident rays as ours: mean-plane points uniform over the tile
    rng = np.random.default_rng(seed)
    n = dirs.shape[0] * per
    d = -np.repeat(dirs, per, axis=0)
    lx, ly = nx * sx, ny * sy
    c = np.stack([rng.uniform(0, lx, n), rng.uniform(0, ly, n), np.zeros(n)], -1)
    zs = float(h.max()) + 1e-3
    o0 = c - d * (zs / -d[:, 2:3])
    d0 = d

    def run(bounce_logic: bool) -> tuple[float, int]:
        o, dd = o0.astype(np.float32), d0.astype(np.float32)
        spent, hits = 0.0, 0
        t_all = time.perf_counter()
        while o.shape[0]:
            ray = mi.Ray3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]),
                           mi.Vector3f(dd[:, 0], dd[:, 1], dd[:, 2]))
            t0 = time.perf_counter()
            si = scene.ray_intersect(ray)
            valid = np.array(si.is_valid())
            p = np.array(si.p).T  # Dr.Jit arrays convert to (3, n)
            nrm = np.array(si.n).T
            spent += time.perf_counter() - t0
            hits += int(valid.sum())
            p, nrm, dd = p[valid], nrm[valid], dd[valid]
            nrm *= np.sign(nrm[:, 2:3])  # geometric normal facing up
            dd = dd - 2.0 * np.sum(dd * nrm, axis=1, keepdims=True) * nrm
            o = (p + 1e-4 * nrm).astype(np.float32)
            dd = dd.astype(np.float32)
        return (time.perf_counter() - t_all if bounce_logic else spent), hits

    return run


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    import numba

    from basis import HemiZernike
    from project.microgeometry import GaussianSurface, simulate
    from project.microgeometry.trace import _alloc, _run, incident_directions

    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    surface = GaussianSurface(1.0, 6.5, resolution=args.size, seed=1)
    basis = HemiZernike(args.order)
    ndirs = -(-args.rays // args.targets)
    rays = ndirs * args.targets
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"threads {args.threads}, python {sys.version.split()[0]}, numba {numba.__version__}")
    print(f"# surface {surface.shape[0]}^2 points, {surface.triangles} triangles, "
          f"m = {surface.roughness:.4f}; {rays} incident rays, {args.targets} per direction")

    res = {}
    sim = {}

    def ours_sim():
        sim["r"] = simulate(surface, basis, rays=rays, seed=1, targets=args.targets)

    res["ours simulate"] = best(ours_sim, args.repeats)
    dirs = incident_directions(ndirs, np.uint64(1), 0, True)
    out = _alloc(rays)
    res["ours trace"] = best(lambda: _run(surface, dirs, args.targets, np.uint64(1), 0, out),
                             args.repeats)
    bounces_ours = float(np.mean(out[2]))
    try:
        run = mitsuba_runner(surface, dirs, args.targets, 1, args.threads)
    except ImportError as err:
        print(f"# mitsuba not available ({err}); our rows only")
        run = None
    if run is not None:
        hits = {}

        def mi_once(logic):
            t, hits[logic] = run(logic)
            return t

        for label, logic in [("mitsuba intersect", False), ("mitsuba + bounce", True)]:
            mi_once(logic)
            res[label] = min(mi_once(logic) for _ in range(args.repeats))
        print(f"# facet hits per incident ray: ours {bounces_ours:.4f}, mitsuba "
              f"{hits[False] / rays:.4f} (mitsuba's tile is not periodic)")
    ref = res.get("mitsuba intersect")
    print(f"{'row':<20} {'seconds':>9} {'rays/s':>12} {'ratio':>7}")
    for label, t in res.items():
        ratio = f"{ref / t:7.2f}" if ref is not None else "      -"
        print(f"{label:<20} {t:9.3f} {rays / t:12.4g} {ratio}")
    r = sim["r"]
    print(f"# simulate: Q = {r.asymmetry:.3g}, reflected = {r.energy['reflected']:.6f}, "
          f"single-bounce fraction = {r.single_scatter:.4f}")

    n = 2**16
    zb = HemiZernike(12)
    while True:
        t0 = time.perf_counter()
        q = simulate(surface, zb, rays=n, seed=2, targets=args.targets).asymmetry
        dt = time.perf_counter() - t0
        if q <= args.qtarget or n >= 2**26:
            break
        n *= 2
    print(f"# Q <= {args.qtarget:g} at HemiZernike(12): {n} rays, {dt:.2f} s (Q = {q:.3g})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
