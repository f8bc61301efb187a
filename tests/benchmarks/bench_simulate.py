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

Scenes (``--scenes``, issue 6): the brushed-metal (aluminium cylinders on a plane) and velvet
(transparent capped fibres over a dark base) specimens of :mod:`project.microgeometry`,
traced by our periodic BVH (``ours simulate`` with HemiZernike(--order), ``ours trace``)
and by Mitsuba intersecting the same analytic primitives (its ``cylinder``, ``disk``,
``sphere`` shapes and one triangle mesh) in one shape group instanced on a 9 x 9 grid of
periods, rays launched over the central period. Our paths refract, reflect and get absorbed
as the materials say, Mitsuba's are mirror bounces, so the number of ray casts per incident
ray differs: those rows compare casts/s (first-hit queries per second, counting every query
including the final miss) and print the ratio of casts/s.

Run: ``python tests/benchmarks/bench_simulate.py [--size 512] [--rays 1000000] [--quick]
[--scenes | --no-heightfield]``.
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
    p.add_argument("--scenes", action=argparse.BooleanOptionalAction, default=True,
                   help="also time the brushed-metal and velvet scenes (default on)")
    p.add_argument("--heightfield", action=argparse.BooleanOptionalAction, default=True,
                   help="time the Gaussian height field (default on)")
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


def _mitsuba(threads: int):
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    mi.set_log_level(mi.LogLevel.Error)  # its cylinders warn of rounding-level "shear"
    dr.set_thread_count(threads)
    return mi


def _mitsuba_mesh(mi, name: str, verts: np.ndarray, faces: np.ndarray):
    mesh = mi.Mesh(name, verts.shape[0], faces.shape[0])
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(verts.astype(np.float32).reshape(-1))
    params["faces"] = mi.UInt32(faces.astype(np.uint32).reshape(-1))
    params.update()
    return mesh


def _incident_rays(dirs: np.ndarray, per: int, seed: int, lx: float, ly: float, zs: float):
    # the same incident rays as ours: mean-plane points uniform over one period
    rng = np.random.default_rng(seed)
    n = dirs.shape[0] * per
    d = -np.repeat(dirs, per, axis=0)
    c = np.stack([rng.uniform(0, lx, n), rng.uniform(0, ly, n), np.zeros(n)], -1)
    return c - d * (zs / -d[:, 2:3]), d


def _mirror_loop(mi, scene, o0: np.ndarray, d0: np.ndarray, offset: float = 1e-4,
                 max_bounces: int = 100):
    """fn(include_bounce_logic) -> (seconds, hits, casts): mirror bounces until all miss.

    New origins move ``offset`` along the facing normal; in float32 a ray can still slip
    into a closed solid (and bounce inside it forever), hence the cap ``max_bounces``."""
    def run(bounce_logic: bool) -> tuple[float, int, int]:
        o, dd = o0.astype(np.float32), d0.astype(np.float32)
        spent, hits, casts = 0.0, 0, 0
        t_all = time.perf_counter()
        for _ in range(max_bounces):
            if not o.shape[0]:
                break
            ray = mi.Ray3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]),
                           mi.Vector3f(dd[:, 0], dd[:, 1], dd[:, 2]))
            t0 = time.perf_counter()
            si = scene.ray_intersect(ray)
            valid = np.array(si.is_valid())
            p = np.array(si.p).T  # Dr.Jit arrays convert to (3, n)
            nrm = np.array(si.n).T
            spent += time.perf_counter() - t0
            casts += o.shape[0]
            hits += int(valid.sum())
            p, nrm, dd = p[valid], nrm[valid], dd[valid]
            nrm *= -np.sign(np.sum(nrm * dd, axis=1, keepdims=True))  # facing the ray
            dd = dd - 2.0 * np.sum(dd * nrm, axis=1, keepdims=True) * nrm
            o = (p + offset * nrm).astype(np.float32)
            dd = dd.astype(np.float32)
        return (time.perf_counter() - t_all if bounce_logic else spent), hits, casts

    return run


def mitsuba_runner(surface, dirs: np.ndarray, per: int, seed: int, threads: int):
    """Build the height-field mesh; fn(include_bounce_logic) -> (seconds, hits, casts)."""
    mi = _mitsuba(threads)
    h = surface.heights
    ny, nx = h.shape
    sx, sy = surface.spacing
    # closed tile: (ny + 1) x (nx + 1) vertices, last row/column repeat the first
    hc = np.pad(h, ((0, 1), (0, 1)), mode="wrap")
    xs, ys = np.meshgrid(np.arange(nx + 1) * sx, np.arange(ny + 1) * sy)
    verts = np.stack([xs, ys, hc], -1).reshape(-1, 3)
    j, i = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    v00 = (j * (nx + 1) + i).reshape(-1)
    v10, v01, v11 = v00 + 1, v00 + nx + 1, v00 + nx + 2
    faces = np.concatenate([np.stack([v00, v10, v11], -1), np.stack([v00, v11, v01], -1)])
    scene = mi.load_dict({"type": "scene", "hf": _mitsuba_mesh(mi, "heightfield", verts,
                                                               faces)})
    o0, d0 = _incident_rays(dirs, per, seed, nx * sx, ny * sy, float(h.max()) + 1e-3)
    return _mirror_loop(mi, scene, o0, d0)


def mitsuba_scene_runner(scene, dirs: np.ndarray, per: int, seed: int, threads: int,
                         tiles: int = 4):
    """A project Scene as Mitsuba shapes (one shape group, instanced on a (2 tiles + 1)^2
    grid of periods); fn(include_bounce_logic) -> (seconds, hits, casts)."""
    from project.microgeometry.bvh import CYLINDER, SPHERE, TRIANGLE, TUBE

    mi = _mitsuba(threads)
    T = mi.ScalarTransform4f
    ptype, pdata, _ = scene._packed()
    group: dict = {"type": "shapegroup"}
    tri = pdata[ptype == TRIANGLE].reshape(-1, 3)
    if tri.shape[0]:
        group["mesh"] = _mitsuba_mesh(mi, "triangles", tri, np.arange(tri.shape[0]).reshape(-1, 3))

    def disk(c, axis, r):
        up = [1.0, 0.0, 0.0] if abs(axis[2]) > 0.9 else [0.0, 0.0, 1.0]
        frame = T().look_at(origin=[0, 0, 0], target=list(map(float, axis)), up=up)
        return {"type": "disk", "to_world": T().translate(list(map(float, c))) @ frame
                @ T().scale(float(r))}

    lx, ly = scene.period
    for k, (t, p) in enumerate(zip(ptype, pdata, strict=True)):
        if t == CYLINDER:  # along x (p[0] = 0) or y, cut to [lo, hi] along it
            a = int(p[0])
            p0 = [p[4], p[1], p[2]] if a == 0 else [p[1], p[4], p[2]]
            p1 = [p[5], p[1], p[2]] if a == 0 else [p[1], p[5], p[2]]
            group[f"c{k}"] = {"type": "cylinder", "p0": p0, "p1": p1, "radius": float(p[3])}
        elif t == TUBE:
            group[f"t{k}"] = {"type": "cylinder", "p0": p[0:3].tolist(),
                              "p1": p[3:6].tolist(), "radius": float(p[6])}
            if p[7] > 0:
                axis = (p[3:6] - p[0:3]) / np.linalg.norm(p[3:6] - p[0:3])
                group[f"a{k}"] = disk(p[0:3], -axis, p[6])
                group[f"b{k}"] = disk(p[3:6], axis, p[6])
        elif t == SPHERE:
            group[f"s{k}"] = {"type": "sphere", "center": p[0:3].tolist(),
                              "radius": float(p[3])}
    desc = {"type": "scene", "tile": group}
    for ix in range(-tiles, tiles + 1):
        for iy in range(-tiles, tiles + 1):
            desc[f"i{ix}_{iy}"] = {"type": "instance", "shapegroup": {"type": "ref",
                                                                      "id": "tile"},
                                   "to_world": T().translate([ix * lx, iy * ly, 0.0])}
    mscene = mi.load_dict(desc)
    lo, hi = scene.bvh.bounds
    o0, d0 = _incident_rays(dirs, per, seed, lx, ly, float(hi[2]) + 1e-3)
    # float32 resolution at the scene's coordinates is ~1e-7 of the period
    return _mirror_loop(mi, mscene, o0, d0, offset=1e-5 * float(max(lx, ly)))


def _casts(out: tuple) -> int:
    # first-hit queries of our paths: one per facet event, plus the final miss of every
    # path that escaped or was cut off (absorbed / roulette-killed paths end at a facet)
    _, w, nb, _, lost = out
    return int(nb.sum() + np.count_nonzero(w > 0) + np.count_nonzero(lost > 0))


def scene_rows(args: argparse.Namespace) -> None:
    """Brushed metal and velvet: ours (periodic BVH) vs Mitsuba on the same primitives."""
    from basis import HemiZernike
    from project.microgeometry import Mirror, brushed_metal, simulate
    from project.microgeometry.trace import MAX_BOUNCES, MAX_STEPS, _alloc, incident_directions

    specimens = {"brushed metal": brushed_metal(0.4, 1.0, material=Mirror(0.96, 6.69))}
    try:
        from project.microgeometry import velvet
    except ImportError:
        print("# velvet not available in this version; brushed metal only")
    else:
        # black velvet (tests/project/test_velvet.py): 5 um fibres, 300 um pile, 1000 fibres
        specimens["velvet"] = velvet(5.0, 300.0, 6.25e-4, tilt=0.3, absorption=0.03,
                                     count=1000, seed=1)
    basis = HemiZernike(args.order)
    ndirs = -(-args.rays // args.targets)
    rays = ndirs * args.targets
    dirs = incident_directions(ndirs, np.uint64(1), 0, True)
    print(f"# scenes: {rays} incident rays, {args.targets} per direction; casts = first-hit "
          "queries; ratio = our casts/s / Mitsuba's")
    print(f"{'scene':<14} {'row':<20} {'seconds':>9} {'rays/s':>11} {'casts/ray':>9} "
          f"{'casts/s':>11} {'ratio':>6}")
    for name, scene in specimens.items():
        rows = {}

        out = _alloc(rays)

        def ours_sim(scene=scene):
            simulate(scene, basis, rays=rays, seed=1, targets=args.targets)

        def ours_trace(scene=scene, out=out):
            scene._run(dirs, args.targets, np.uint64(1), 0, out, MAX_BOUNCES, MAX_STEPS)

        rows["ours trace"] = (best(ours_trace, args.repeats), _casts(out))
        rows["ours simulate"] = (best(ours_sim, args.repeats), _casts(out))
        try:
            run = mitsuba_scene_runner(scene, dirs, args.targets, 1, args.threads)
        except ImportError as err:
            print(f"# mitsuba not available ({err}); our rows only")
            run = None
        if run is not None:
            for label, logic in [("mitsuba intersect", False), ("mitsuba + bounce", True)]:
                run(logic)
                got = [run(logic) for _ in range(args.repeats)]
                t = min(g[0] for g in got)
                rows[label] = (t, got[0][2])
        ref = rows.get("mitsuba intersect")
        for label, (t, casts) in rows.items():
            ratio = f"{(casts / t) / (ref[1] / ref[0]):6.2f}" if ref else "     -"
            print(f"{name:<14} {label:<20} {t:9.3f} {rays / t:11.4g} {casts / rays:9.3f} "
                  f"{casts / t:11.4g} {ratio}")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    import numba

    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"threads {args.threads}, python {sys.version.split()[0]}, numba {numba.__version__}")
    if args.heightfield:
        heightfield_rows(args)
    if args.scenes:
        scene_rows(args)
    return 0


def heightfield_rows(args: argparse.Namespace) -> None:
    from basis import HemiZernike
    from project.microgeometry import GaussianSurface, simulate
    from project.microgeometry.trace import _alloc, _run, incident_directions

    surface = GaussianSurface(1.0, 6.5, resolution=args.size, seed=1)
    basis = HemiZernike(args.order)
    ndirs = -(-args.rays // args.targets)
    rays = ndirs * args.targets
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
            t, hits[logic], _ = run(logic)
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


if __name__ == "__main__":
    sys.exit(main())
