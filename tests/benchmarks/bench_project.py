"""Benchmark: projecting BRDFs onto a basis, against a dense product quadrature in numpy.

What it measures
----------------
Each case runs ``project.project`` (the separable rule: Gauss-Legendre in z per direction,
uniform or graded azimuths, FFT/cosine sums, one small matrix product per azimuthal block)
with its own node refinement, and reports the wall time, the nodes it chose, its error
estimate and the number of BRDF evaluations. The baseline is the brute-force dense product
rule on the same nodes: every basis function at every node of ``hemisphere_rule(n_z, n_phi)``
for both directions and the BRDF at every pair of nodes, contracted with two matrix products
(``B^T W F W B``). The baseline's cost is (n_z n_phi)^2 evaluations, far too many to run whole
at these node counts, so it is timed on ``--rows`` incident nodes against all outgoing nodes
and scaled by the number of incident nodes (its cost is exactly linear in them; the printed
time is marked "scaled"). Its accuracy on the full rule would be the same as ours, since it
is the same quadrature.

Cases (with their targets on the 2-core machine):

1. an isotropic analytic BRDF to HemiZernike(16) with coefficient error <= 1e-8 (relative to
   max |M|): Cook-Torrance GGX (kd 0.2, alpha 0.3, ior 1.5) and Phong; target < 1 s;
2. anisotropic Ward (alpha 0.2 x 0.4) to HemiZernike(12), tolerance 1e-4 (the original
   Ward lobe has a sqrt(cos) singularity at the horizon, so the z rule converges
   algebraically): target < 10 s;
3. a MERL-format file, 3 channels, to HemiZernike(16), tolerance 1e-4 (the trilinear table
   converges like N^-2): target < 5 s. The file is made by ../shared/tools/merl_surrogate.py
   in a temporary folder; the case is skipped when ../shared is absent.

Then one row for a sharp measured material: blue-acrylic (a specular ridge about
0.003 wide in z_i - z_o) to HemiZernike(24) at tolerance 1e-4, skipped like case 3. It prints
our time, nodes and rule (for the diagonal rule, its nodes along and across the ridge) at
tolerances 1e-4 and 1e-3, the error against an independent brute-force reference, and the
same for the old method (the tensor Gauss rule in (z_i, z_o) only, folded onto z_i <= z_o as
if the table were mirror symmetric, as the rule did before the diagonal rules). The
reference resolves the ridge by brute force: Gauss in z_i (``--ref-nodes``) against a fine
Gauss rule in z_o (``--ref-fine``) so no pair sits exactly on z_i = z_o, 800 graded azimuths
(``--ref-azimuths``; with 400 the reference itself is 4e-6 off in azimuth).

Each case is run once untimed first (numba compilation and caches), then ``--repeats`` times;
the best time is reported.

Run: ``python tests/benchmarks/bench_project.py [--repeats 3] [--rows 8] [--quick]
[--no-sharp]``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from _machine import header, tag  # the machine: CPU model, features, vector width

from basis import HemiZernike, hemisphere_rule
from project import models, project
from project.measured import read_merl

SHARED = Path(__file__).resolve().parents[2].parent / "shared"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=3, help="timed runs; the best is reported")
    p.add_argument("--rows", type=int, default=8,
                   help="incident nodes the dense baseline is timed on (then scaled)")
    p.add_argument("--quick", action="store_true", help="lower orders, one repeat, no sharp row")
    p.add_argument("--no-sharp", action="store_true", help="skip the blue-acrylic row")
    p.add_argument("--ref-nodes", type=int, default=208, help="reference: Gauss nodes in z_i")
    p.add_argument("--ref-fine", type=int, default=2000, help="reference: Gauss nodes in z_o")
    p.add_argument("--ref-azimuths", type=int, default=800,
                   help="reference: graded azimuths (400 leaves 4e-6 of azimuth error)")
    args = p.parse_args(argv)
    if args.repeats < 1 or args.rows < 1:
        p.error("--repeats and --rows must be >= 1")
    return args


def best_of(fn, repeats: int):
    fn()  # compile, fill caches
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def dense_baseline(brdf, basis, quantity, nodes, rows, repeats) -> float:
    """Seconds the dense product rule would take on ``nodes``, timed on ``rows`` rows."""
    nz, nphi = nodes
    rule = hemisphere_rule(nz, nphi)
    pts, w = rule.points, rule.weights
    n = pts.shape[0]
    take = np.linspace(0, n - 1, min(rows, n)).astype(int)

    def run():
        bw = basis.eval(pts) * w[:, None]
        f = np.asarray(brdf.eval(pts[take, None, :], pts[None, :, :]))
        f = f.reshape(take.size, n, -1)
        if quantity == "f_cos":
            f = f * (pts[take, 2, None] * pts[None, :, 2])[..., None]
        # rows of B^T W F W B for the sampled incident nodes
        return np.einsum("aj,abc,bk->cjk", bw[take], f, bw, optimize=True)

    t, _ = best_of(run, repeats)
    return t * n / take.size


def fine_reference(brdf, basis, n_i: int, n_o: int, nphi: int = 400) -> list[np.ndarray]:
    """Isotropic blocks (k_m, k_m, channels) by brute force, for the sharp row.

    Gauss n_i in z_i against Gauss n_o >> n_i in z_o: every row resolves the ridge at
    z_o = z_i with many nodes, and the row integrals are smooth in z_i. The azimuth rule is
    the graded one of the projection (4e-6 from its value at 800 with 400 azimuths).
    """
    from project.quadrature import _azimuth_nodes, _gauss_z

    zi, wi = _gauss_z(n_i)
    zo, wo = _gauss_z(n_o)
    dphi, wphi = _azimuth_nodes(nphi, 6)
    az, ch = basis.azimuthal, int(brdf.channels)
    cosm = 2.0 * wphi[:, None] * np.cos(np.outer(dphi, np.arange(basis.order + 1)))
    pi, po = basis.radial(zi) * wi[:, None], basis.radial(zo) * wo[:, None]
    so = np.sqrt(1.0 - zo**2)
    out = np.stack([so[:, None] * np.cos(dphi), -so[:, None] * np.sin(dphi),
                    np.repeat(zo[:, None], dphi.size, 1)], axis=-1).reshape(-1, 3)
    rows = [np.zeros((n_i, int(np.sum(az == m)), ch)) for m in range(basis.order + 1)]
    for a in range(n_i):  # one incident node at a time: n_o x nphi / 2 pairs
        inc = np.broadcast_to([np.sqrt(1.0 - zi[a] ** 2), 0.0, zi[a]], out.shape)
        q = np.asarray(brdf.eval(inc, out)).reshape(n_o, dphi.size, ch)
        f = np.einsum("bsc,sm->bmc", q, cosm)
        for m in range(basis.order + 1):
            rows[m][a] = np.einsum("bc,bk->kc", f[:, m], po[:, az == m])
    blocks = []
    for m in range(basis.order + 1):
        b = (2.0 * np.pi if m == 0 else np.pi) * np.einsum("aj,akc->jkc", pi[:, az == m],
                                                           rows[m])
        blocks.append(0.5 * (b + b.swapaxes(0, 1)))
    return blocks


def block_error(cm, blocks) -> float:
    """max |M - reference| / max |reference| over the isotropic blocks."""
    got = [np.moveaxis(b, 0, -1) for b in cm.stored]
    err = max(float(np.max(np.abs(g - r))) for g, r in zip(got, blocks, strict=True))
    return err / max(float(np.max(np.abs(r))) for r in blocks)


def sharp_row(path: Path, args: argparse.Namespace, reps: int) -> None:
    """The blue-acrylic row: ours, the old tensor rule, both against the brute force."""
    from project import quadrature

    brdf, zb = read_merl(path), HemiZernike(24)
    t0 = time.perf_counter()
    ref = fine_reference(brdf, zb, args.ref_nodes, args.ref_fine, args.ref_azimuths)
    t_ref = time.perf_counter() - t0

    def run(tol=1e-4):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return project(brdf, zb, tol=tol)

    def old():  # before the diagonal rules: tensor Gauss only, folded as if mirror symmetric
        saved = quadrature.ISO_ZMAPS, quadrature._mirror_symmetric
        quadrature.ISO_ZMAPS, quadrature._mirror_symmetric = ("gauss",), lambda brdf: True
        try:
            return run()
        finally:
            quadrature.ISO_ZMAPS, quadrature._mirror_symmetric = saved

    runs = (("ours", run), ("ours, tol 1e-3", lambda: run(1e-3)), ("old", old))
    best = {name: np.inf for name, _ in runs}
    out = {}
    for _ in range(reps):  # interleaved: the machine's load hits all alike
        for name, fn in runs:
            t0 = time.perf_counter()
            out[name] = fn()
            best[name] = min(best[name], time.perf_counter() - t0)
    print(f"\nOn {tag()}:")
    print(f"Sharp measured material: blue-acrylic to {zb!r}, tol 1e-4; reference "
          f"{args.ref_nodes} x {args.ref_fine} Gauss x {args.ref_azimuths} azimuths "
          f"({t_ref:.0f} s)")
    print("| method | s | nodes (z, phi) | z rule (s x d nodes) | rel. error est. | "
          "error vs reference | "
          "evaluations |")
    print("|---" * 7 + "|")
    for name in best:
        info = out[name].info
        rule = info.get("z_rule", "-")
        if "combination" in info:
            rule += f" {info['combination']}"
        elif "diagonal_nodes" in info:
            rule += " {} x {}".format(*info["diagonal_nodes"])
        print(f"| {name} | {best[name]:.2f} | {info['nodes']} | {rule} | "
              f"{info['rel_error']:.1e}{'' if info['converged'] else ' (not met)'} | "
              f"{block_error(out[name], ref):.1e} | {info['evaluations']:,} |", flush=True)
    print(f"old / ours: {best['old'] / best['ours']:.3g} at tol 1e-4, "
          f"{best['old'] / best['ours, tol 1e-3']:.3g} at tol 1e-3")


def merl_file(folder: str, name: str = "gold-metallic-paint") -> Path | None:
    tool = SHARED / "tools" / "merl_surrogate.py"
    if not tool.is_file():
        return None
    subprocess.run([sys.executable, str(tool), name, "-o", folder], check=True,
                   capture_output=True)
    return Path(folder) / f"{name}.binary"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    print(header())
    reps = 1 if args.quick else args.repeats
    o_iso, o_aniso, o_merl = (8, 6, 8) if args.quick else (16, 12, 16)
    with tempfile.TemporaryDirectory() as tmp:
        merl = merl_file(tmp)
        cases = [
            ("Cook-Torrance GGX", models.CookTorrance(0.2, 0.3, distribution="ggx", ior=1.5),
             o_iso, 1e-8, 1.0),
            ("Phong n=20", models.Phong(0.3, 0.5, 20), o_iso, 1e-8, 1.0),
            ("Ward 0.2 x 0.4 (aniso)", models.Ward(0.2, 0.3, 0.2, 0.4), o_aniso, 1e-4, 10.0),
        ]
        if merl is not None:
            cases.append(("MERL gold-metallic-paint", read_merl(merl), o_merl, 1e-4, 5.0))
        else:
            print(f"(MERL case skipped: {SHARED} not found)")
        columns = ("| case | basis | ours s | target s | nodes (z, phi) | rel. error est. | "
                  "evaluations | dense s (scaled) | dense / ours |")
        print(f"On {tag()}:")
        print(columns)
        print("|---" * 9 + "|")
        for label, brdf, order, tol, target in cases:
            zb = HemiZernike(order)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # truncation notes, shown below
                t, cm = best_of(lambda b=brdf, z=zb, tl=tol: project(b, z, tol=tl), reps)
            info = cm.info
            dense = dense_baseline(brdf, zb, info["quantity"], info["nodes"], args.rows, 1)
            print(f"| {label} | {zb!r} | {t:.3f} | {target:g} | {info['nodes']} | "
                  f"{info['rel_error']:.1e}{'' if info['converged'] else ' (not met)'} | "
                  f"{info['evaluations']:,} | {dense:.3g} | {dense / t:.3g} |", flush=True)
        if not args.no_sharp and not args.quick:
            sharp = merl_file(tmp, "blue-acrylic")
            if sharp is None:
                print(f"(sharp MERL row skipped: {SHARED} not found)")
            else:
                sharp_row(sharp, args, reps)
    return 0


if __name__ == "__main__":
    sys.exit(main())
