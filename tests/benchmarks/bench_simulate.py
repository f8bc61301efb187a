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
- ``ours trace``: the same rays through the tracer alone (no accumulation): the packet walk,
  as many rays per step as the CPU's vector registers hold doubles.
- ``ours trace, 1 ray``: the same through the ray-by-ray walk (the same bits): what the
  packets gain on this CPU.
- ``mitsuba intersect``: Mitsuba 3 (variant ``llvm_ad_rgb``, float32, its own BVH) with the
  same surface built in Python as one mesh of 2 n^2 triangles (the periodic tile plus its
  closing row and column, 513 x 513 vertices), ``Scene.ray_intersect`` called on the same
  incident ray batch and then on every bounce batch (mirror reflection about the geometric
  normal, computed with numpy between calls, only the still-active rays re-launched), until
  no ray hits. Mitsuba's mesh is not periodic: rays that leave the tile sideways stop, so it
  does at most as much work per ray as ours. The time counts only the ``ray_intersect``
  calls (plus Dr.Jit's evaluation of the result), not the numpy bounce logic.
- ``mitsuba + bounce``: the same, including the numpy bounce logic between calls.
- ``mitsuba 1 batch``: one ``Scene.ray_intersect`` of all incident rays at once (1M
  incoherent rays, all of which hit), the rays built as Dr.Jit arrays outside the timing and
  the result evaluated and synchronised: Mitsuba's best throughput, free of the per-call
  cost (~80 ms of tracing and kernel launch) and numpy conversions of the rows above.

casts = first-hit queries (ours: one per facet event plus the final miss of each path,
about 2.04 per incident ray; Mitsuba's mirror loop: the same count of its queries);
ratio = casts/s / the casts/s of ``mitsuba 1 batch`` (> 1: we are faster). Each row is
run once untimed (JIT compile or cache load, BVH build) and then ``--repeats`` times (our
height-field rows and ``mitsuba 1 batch``: ``--repeats`` + 2 times); the best time is
reported. Both run on ``--threads`` threads (numba.set_num_threads and
``dr.set_thread_count``). The machine may be shared: compare rows of one
run. Then ``--runs`` runs (default 3) of ``ours simulate`` against ``mitsuba 1 batch``,
alternated (best of ``--repeats`` each), one row and ratio per run: on a shared machine
the ratio of a single run is what can be relied on, so every run is shown. Finally it
prints the time our simulate needs to reach Q <= ``--qtarget`` at HemiZernike(12) (rays
doubled from 2^16 until Q meets the target).

Scenes (``--scenes``): the brushed-metal (aluminium cylinders on a plane) and velvet
(transparent capped fibres over a dark base) specimens of :mod:`project.microgeometry`,
traced by our periodic BVH (``ours simulate`` with HemiZernike(--order), ``ours trace``)
and by Mitsuba intersecting the same analytic primitives (its ``cylinder``, ``disk``,
``sphere`` shapes and one triangle mesh) in one shape group instanced on a 9 x 9 grid of
periods, rays launched over the central period. Our paths refract, reflect and get absorbed
as the materials say, Mitsuba's are mirror bounces, so the number of ray casts per incident
ray differs: those rows compare casts/s (first-hit queries per second, counting every query
including the final miss) and print the ratio of casts/s.

Run: ``python tests/benchmarks/bench_simulate.py [--size 512] [--rays 1000000] [--runs 3]
[--quick] [--scenes | --no-heightfield]``.
mitsuba is optional (``pip install "scatmodes[bench]"``); without it only our rows print.
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
    p.add_argument("--size", type=int, default=512, help="grid points per side (mesh n+1)")
    p.add_argument("--rays", type=int, default=1_000_000, help="incident rays per row")
    p.add_argument("--targets", type=int, default=8, help="rays per incident direction")
    p.add_argument("--order", type=int, default=12, help="HemiZernike order for simulate")
    p.add_argument("--repeats", type=int, default=3, help="timed runs; the best is reported")
    p.add_argument("--runs", type=int, default=3,
                   help="runs of the ours-vs-Mitsuba comparison printed one by one")
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
    if min(args.size, args.rays, args.targets, args.repeats, args.threads, args.runs) < 1:
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

    Every ``ray_intersect`` call costs ~80 ms of Dr.Jit tracing and kernel launch on top of
    the intersection work, so batches are padded to the next power of two (rays above the
    scene pointing up: they miss and are not counted) and the throughput of calls with at
    least 2^16 rays, where that overhead is amortised, is also returned (seconds, casts).
    New origins move ``offset`` along the facing normal; in float32 a ray can still slip
    into a closed solid (and bounce inside it forever), hence the cap ``max_bounces``."""
    top = float(max(o0[:, 2].max(), 1.0)) * 4.0

    def cast(o: np.ndarray, dd: np.ndarray):
        n = o.shape[0]
        m = 1 << max(0, (n - 1).bit_length())
        op = np.zeros((m, 3), np.float32)
        dp = np.zeros((m, 3), np.float32)
        op[:, 2] = top
        dp[:, 2] = 1.0
        op[:n], dp[:n] = o, dd
        ray = mi.Ray3f(mi.Point3f(op[:, 0], op[:, 1], op[:, 2]),
                       mi.Vector3f(dp[:, 0], dp[:, 1], dp[:, 2]))
        si = scene.ray_intersect(ray)
        valid = np.array(si.is_valid())[:n]
        p = np.array(si.p).T[:n]  # Dr.Jit arrays convert to (3, m)
        nrm = np.array(si.n).T[:n]
        return valid, p, nrm

    def run(bounce_logic: bool) -> tuple[float, int, int, tuple[float, int]]:
        o, dd = o0.astype(np.float32), d0.astype(np.float32)
        spent, hits, casts = 0.0, 0, 0
        big = [0.0, 0]
        t_all = time.perf_counter()
        for _ in range(max_bounces):
            if not o.shape[0]:
                break
            t0 = time.perf_counter()
            valid, p, nrm = cast(o, dd)
            dt = time.perf_counter() - t0
            spent += dt
            if o.shape[0] >= 2**16:
                big[0] += dt
                big[1] += o.shape[0]
            casts += o.shape[0]
            hits += int(valid.sum())
            p, nrm, dd = p[valid], nrm[valid], dd[valid]
            nrm *= -np.sign(np.sum(nrm * dd, axis=1, keepdims=True))  # facing the ray
            dd = dd - 2.0 * np.sum(dd * nrm, axis=1, keepdims=True) * nrm
            o = (p + offset * nrm).astype(np.float32)
            dd = dd.astype(np.float32)
        return ((time.perf_counter() - t_all if bounce_logic else spent), hits, casts,
                tuple(big))

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
    run = _mirror_loop(mi, scene, o0, d0)
    run.primary = _primary_batch(mi, scene, o0, d0)
    return run


def _primary_batch(mi, scene, o0: np.ndarray, d0: np.ndarray):
    """fn() -> seconds of one ``Scene.ray_intersect`` on the whole incident batch.

    The rays are Dr.Jit arrays built once, outside the timing (as a renderer holds them);
    the timing covers the call and Dr.Jit's evaluation of the hit point, normal and
    distance, synchronised (``dr.eval`` then ``dr.sync_thread``): Mitsuba's throughput on
    one large incoherent batch, without per-call overhead or numpy conversions."""
    import drjit as dr

    o = [mi.Float(o0[:, k].astype(np.float32)) for k in range(3)]
    d = [mi.Float(d0[:, k].astype(np.float32)) for k in range(3)]
    ray = mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*d))
    dr.eval(ray)
    dr.sync_thread()

    def run() -> float:
        t0 = time.perf_counter()
        si = scene.ray_intersect(ray)
        dr.eval(si.t, si.p, si.n)
        dr.sync_thread()
        return time.perf_counter() - t0

    return run


def _tube_mesh(p0: np.ndarray, p1: np.ndarray, r: float, caps: bool, sides: int):
    """(V, 3), (F, 3): a tube of ``sides`` quads about p0 -> p1, with fan caps if ``caps``;
    the polygon is circumscribed about the circle's mean radius (area-preserving scale)."""
    axis = (p1 - p0) / np.linalg.norm(p1 - p0)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    a = 2 * np.pi * np.arange(sides) / sides
    rr = r * np.sqrt(2 * np.pi / (sides * np.sin(2 * np.pi / sides)))  # same cross-section
    ring = rr * (np.cos(a)[:, None] * u + np.sin(a)[:, None] * v)
    verts = np.concatenate([p0 + ring, p1 + ring, [p0, p1]])
    k = np.arange(sides)
    k1 = (k + 1) % sides
    faces = [np.stack([k, k1, sides + k1], -1), np.stack([k, sides + k1, sides + k], -1)]
    if caps:
        faces += [np.stack([np.full(sides, 2 * sides), k1, k], -1),
                  np.stack([np.full(sides, 2 * sides + 1), sides + k, sides + k1], -1)]
    return verts, np.concatenate(faces)


def _sphere_mesh(c: np.ndarray, r: float, n: int):
    """(V, 3), (F, 3): a latitude-longitude sphere of n x 2n quads (poles as fans)."""
    th = np.pi * np.arange(1, n) / n
    ph = 2 * np.pi * np.arange(2 * n) / (2 * n)
    ring = np.stack([np.sin(th)[:, None] * np.cos(ph), np.sin(th)[:, None] * np.sin(ph),
                     np.cos(th)[:, None] * np.ones_like(ph)], -1).reshape(-1, 3)
    verts = c + r * np.concatenate([ring, [[0, 0, 1], [0, 0, -1]]])
    m = 2 * n
    faces = []
    for i in range(n - 2):
        k = np.arange(m)
        a, b = i * m + k, i * m + (k + 1) % m
        faces += [np.stack([a, a + m, b], -1), np.stack([b, a + m, b + m], -1)]
    k = np.arange(m)
    top, bot = (n - 1) * m, (n - 1) * m + 1
    faces += [np.stack([np.full(m, top), k, (k + 1) % m], -1),
              np.stack([np.full(m, bot), (n - 2) * m + (k + 1) % m, (n - 2) * m + k], -1)]
    return verts, np.concatenate(faces)


def scene_mesh(scene, sides: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """One period of a project Scene as one triangle mesh: its triangles as they are, its
    cylinders, tubes and spheres tessellated (``sides`` facets around)."""
    from project.microgeometry.bvh import CYLINDER, SPHERE, TRIANGLE, TUBE

    ptype, pdata, _ = scene._packed()
    parts = []
    tri = pdata[ptype == TRIANGLE].reshape(-1, 3)
    if tri.shape[0]:
        parts.append((tri, np.arange(tri.shape[0]).reshape(-1, 3)))
    for p in pdata[ptype == CYLINDER]:  # along x (p[0] = 0) or y, cut to [lo, hi] along it
        lo = np.array([p[4], p[1], p[2]] if p[0] == 0 else [p[1], p[4], p[2]])
        hi = np.array([p[5], p[1], p[2]] if p[0] == 0 else [p[1], p[5], p[2]])
        parts.append(_tube_mesh(lo, hi, p[3], False, 2 * sides))
    for p in pdata[ptype == TUBE]:
        parts.append(_tube_mesh(p[0:3], p[3:6], p[6], p[7] > 0, sides))
    for p in pdata[ptype == SPHERE]:
        parts.append(_sphere_mesh(p[0:3], p[3], sides // 2))
    verts, faces, base = [], [], 0
    for v, f in parts:
        verts.append(v)
        faces.append(f + base)
        base += v.shape[0]
    return np.concatenate(verts), np.concatenate(faces)


def mitsuba_scene_runner(scene, dirs: np.ndarray, per: int, seed: int, threads: int,
                         tiles: int = 2):
    """A project Scene as one Mitsuba mesh: :func:`scene_mesh` copied explicitly onto a
    (2 tiles + 1)^2 grid of periods (Mitsuba's shape-group instancing made every
    ``ray_intersect`` call take minutes in llvm mode here, so the copies are real
    triangles); fn(include_bounce_logic) -> (seconds, hits, casts)."""
    mi = _mitsuba(threads)
    verts, faces = scene_mesh(scene)
    lx, ly = scene.period
    shifts = [(ix * lx, iy * ly, 0.0) for ix in range(-tiles, tiles + 1)
              for iy in range(-tiles, tiles + 1)]
    allv = np.concatenate([verts + np.array(sh) for sh in shifts])
    allf = np.concatenate([faces + k * verts.shape[0] for k in range(len(shifts))])
    mscene = mi.load_dict({"type": "scene", "tiles": _mitsuba_mesh(mi, "tiles", allv, allf)})
    lo, hi = scene.bvh.bounds
    o0, d0 = _incident_rays(dirs, per, seed, lx, ly, float(hi[2]) + 1e-3 * float(lx))
    # float32 resolution at the scene's coordinates is ~1e-7 of the period
    run = _mirror_loop(mi, mscene, o0, d0, offset=1e-5 * float(max(lx, ly)))
    run.triangles = faces.shape[0]
    return run


def _casts(out: tuple) -> int:
    # first-hit queries of our paths: one per facet event, plus the final miss of every
    # path that escaped or was cut off (absorbed / roulette-killed paths end at a facet)
    _, w, nb, _, lost = out
    return int(nb.sum() + np.count_nonzero(w > 0) + np.count_nonzero(lost > 0))


def scene_rows(args: argparse.Namespace) -> None:
    """Brushed metal and velvet: ours (periodic BVH) vs Mitsuba on the same primitives."""
    from basis import HemiZernike
    from project.microgeometry import Mirror, brushed_metal, simulate
    from project.microgeometry._paths import _alloc  # private: benchmarks drive the runners
    from project.microgeometry.trace import MAX_BOUNCES, MAX_STEPS, incident_directions

    specimens = {"brushed metal": brushed_metal(0.4, 1.0, material=Mirror(0.96, 6.69))}
    try:
        from project.microgeometry import velvet
    except ImportError:
        print("# velvet not available in this version; brushed metal only")
    else:
        # black velvet (tests/project/microgeometry/test_velvet.py): 5 um fibres, 300 um
        # pile, 1000 fibres
        specimens["velvet"] = velvet(5.0, 300.0, 6.25e-4, tilt=0.3, absorption=0.03,
                                     count=1000, seed=1)
    basis = HemiZernike(args.order)
    ndirs = -(-args.rays // args.targets)
    rays = ndirs * args.targets
    dirs = incident_directions(ndirs, np.uint64(1), 0, True)
    print(f"# on {tag()}")
    print(f"# scenes: {rays} incident rays, {args.targets} per direction; casts = first-hit "
          "queries; ratio = casts/s / Mitsuba's casts/s on batches >= 2^16 rays")
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
            big = min((g[3] for g in got), key=lambda b: b[0] / max(b[1], 1))
            if big[1]:
                # Mitsuba's throughput on batches >= 2^16 rays (its per-call cost amortised)
                rows["mitsuba big batches"] = big
        ref = rows.get("mitsuba big batches", rows.get("mitsuba intersect"))
        for label, (t, casts) in rows.items():
            ratio = f"{(casts / t) / (ref[1] / ref[0]):6.2f}" if ref else "     -"
            per_ray = label != "mitsuba big batches"  # a subset of the casts: no rays/s
            rps = f"{rays / t:11.4g}" if per_ray else f"{'-':>11}"
            cpr = f"{casts / rays:9.3f}" if per_ray else f"{'-':>9}"
            print(f"{name:<14} {label:<20} {t:9.3f} {rps} {cpr} {casts / t:11.4g} {ratio}")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    import numba

    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    print(header())
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"threads {args.threads}, python {sys.version.split()[0]}, numba {numba.__version__}")
    if args.heightfield:
        heightfield_rows(args)
    if args.scenes:
        scene_rows(args)
    return 0


def runs_table(runs: int, repeats: int, ours, casts_ours: int, mitsuba, rays: int) -> None:
    """Print ours simulate vs ``mitsuba 1 batch`` for each of ``runs`` runs, one row each.

    A run times our simulate and Mitsuba's one batch ``repeats`` times each, alternating
    (ours, Mitsuba, ours, ...), and takes the best of each: on a shared machine the load
    changes within seconds, and timing all of ours before all of Mitsuba's let a change
    between the two halves decide the ratio (measured: Mitsuba's batch 0.41 s in one run,
    1.0 s in the others of the same invocation). The spread of the ratio over the runs
    shows what one run can give on a shared machine."""
    print(f"# on {tag()}")
    print(f"# {runs} runs, each: ours simulate and mitsuba 1 batch alternated, best of "
          f"{repeats} each")
    print(f"{'run':>4} {'ours s':>8} {'ours casts/s':>13} {'mitsuba s':>10} "
          f"{'mitsuba casts/s':>16} {'ratio':>6}")
    ratios = []
    for i in range(runs):
        t_ours = t_mi = np.inf
        for _ in range(repeats):
            t_ours = min(t_ours, _timed(ours))
            t_mi = min(t_mi, mitsuba())
        ratio = (casts_ours / t_ours) / (rays / t_mi)
        ratios.append(ratio)
        print(f"{i + 1:>4} {t_ours:8.3f} {casts_ours / t_ours:13.4g} {t_mi:10.3f} "
              f"{rays / t_mi:16.4g} {ratio:6.2f}")
    print(f"# ratio over the {runs} runs: min {min(ratios):.2f}, median "
          f"{float(np.median(ratios)):.2f}, max {max(ratios):.2f}")


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def heightfield_rows(args: argparse.Namespace) -> None:
    from basis import HemiZernike
    from project.microgeometry import GaussianSurface, simulate
    from project.microgeometry._paths import _alloc  # private: benchmarks drive the runners
    from project.microgeometry.trace import _run, incident_directions  # _run: private, as _alloc

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

    # our rows and Mitsuba's one-batch row: the best of repeats + 2 runs each
    res["ours simulate"] = best(ours_sim, args.repeats + 2)
    dirs = incident_directions(ndirs, np.uint64(1), 0, True)
    out = _alloc(rays)
    res["ours trace"] = best(lambda: _run(surface, dirs, args.targets, np.uint64(1), 0, out),
                             args.repeats + 2)
    res["ours trace, 1 ray"] = best(lambda: _run(surface, dirs, args.targets, np.uint64(1), 0,
                                                 out, packets=False), args.repeats + 2)
    bounces_ours = float(np.mean(out[2]))
    try:
        run = mitsuba_runner(surface, dirs, args.targets, 1, args.threads)
    except ImportError as err:
        print(f"# mitsuba not available ({err}); our rows only")
        run = None
    if run is not None:
        hits = {}

        def mi_once(logic):
            t, hits[logic], _, _ = run(logic)
            return t

        for label, logic in [("mitsuba intersect", False), ("mitsuba + bounce", True)]:
            mi_once(logic)
            res[label] = min(mi_once(logic) for _ in range(args.repeats))
        print(f"# facet hits per incident ray: ours {bounces_ours:.4f}, mitsuba "
              f"{hits[False] / rays:.4f} (mitsuba's tile is not periodic)")
    casts_ours = _casts(out)
    casts = {"ours simulate": casts_ours, "ours trace": casts_ours,
             "ours trace, 1 ray": casts_ours}
    if run is not None:
        for label in ("mitsuba intersect", "mitsuba + bounce"):
            casts[label] = hits[False] + rays  # every query of the mirror loop
        run.primary()
        res["mitsuba 1 batch"] = min(run.primary() for _ in range(args.repeats + 2))
        casts["mitsuba 1 batch"] = rays
    # the reference: Mitsuba's casts/s on one batch of all incident rays (the row);
    # our casts count every first-hit query of a path, including the final miss
    ref = casts["mitsuba 1 batch"] / res["mitsuba 1 batch"] if run is not None else None
    print(f"# on {tag()}")
    print(f"{'row':<20} {'seconds':>9} {'rays/s':>12} {'casts/s':>12} {'ratio':>7}")
    for label, t in res.items():
        cps = casts[label] / t
        ratio = f"{cps / ref:7.2f}" if ref is not None else "      -"
        rps = f"{rays / t:12.4g}" if label != "mitsuba 1 batch" else f"{'-':>12}"
        print(f"{label:<20} {t:9.3f} {rps} {cps:12.4g} {ratio}")
    print("# ratio = casts/s / Mitsuba's casts/s on one batch of all incident rays "
          f"({rays} rays, all hit); ours: {casts_ours / rays:.3f} casts per ray")
    r = sim["r"]
    print(f"# simulate: Q = {r.asymmetry:.3g}, reflected = {r.energy['reflected']:.6f}, "
          f"single-bounce fraction = {r.single_scatter:.4f}")
    if run is not None:
        runs_table(args.runs, args.repeats, ours_sim, casts_ours, run.primary, rays)

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
