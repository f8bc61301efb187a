"""Benchmark: evaluating truncated isotropic representations against MERL table lookup.

What it measures
----------------
For one MERL-format table (``--material``, made by ``../shared/tools/merl_surrogate.py``
when ``../shared`` is present; otherwise a synthetic table sampled from an analytic BRDF),
the wall time of evaluating the BRDF at the same ``--pairs`` random direction pairs (seeded,
uniform in solid angle on H x H), RGB:

- "MERL lookup (trilinear)": ``project.measured.merl._merl_lookup_kernel``, the numba kernel behind
  ``MERLBRDF.eval`` (no validation), parallel over pairs;
- "MERLBRDF.eval": the public call, with validation;
- for each order in ``--orders`` (default 4, 8, 16), the projection of the table onto
  HemiZernike(order) and HemiHarmonics(order) (odd), truncated from one projection at the
  highest order, evaluated by ``CoefficientMatrix.eval`` (the public call: validation, then
  the fused kernel of ``basis.evaluate``), by its ``evaluator().eval_flat`` (no validation),
  and, for the dense (anisotropic) storage of the same matrix, by ``CoefficientMatrix.eval``
  on at most 2^18 pairs, scaled.

Every evaluator is called once untimed (compilation, cache, first touch), then all are timed
in turn for ``--repeats`` rounds; the best call of each is reported. Columns: ms per call,
million samples (pairs) per second, ratio = throughput / MERL lookup's, and the l2 error of
the truncation (cosine-weighted relative L2 against the table, ``compress.errors`` on a
24 x 24 x 48 test set). The header reports numba's threads and the 1-minute load average:
on a shared machine other processes slow every row alike, so compare rows of one run.

Target: order-8 isotropic evaluation >= 20M samples/s on two cores.

Run: ``python tests/benchmarks/bench_compress.py [--quick] [--pairs N] [--orders 4 8 16]``.
``--quick``: 2^18 pairs, orders 4 and 8, 3 repeats, synthetic table (no surrogate).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numba
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from _machine import header, tag  # noqa: E402 - the machine: CPU, features, vector width

import basis  # noqa: E402
import compress  # noqa: E402
import project  # noqa: E402
from basis.jit import run_parallel  # noqa: E402
from project.measured.merl import MERLBRDF, _merl_lookup_kernel, merl_grid, read_merl  # noqa: E402
from tests.benchmarks.bench_eval import pairs  # noqa: E402 - the same test pairs


def _table(material: str | None, tmp: str) -> MERLBRDF:
    tool = ROOT.parent / "shared" / "tools" / "merl_surrogate.py"
    if material and tool.is_file():
        r = subprocess.run([sys.executable, str(tool), material, "-o", tmp],
                           capture_output=True, text=True, check=False)
        path = Path(tmp) / f"{material}.binary"
        if r.returncode == 0 and path.is_file():
            return read_merl(path)
        print(f"(surrogate for {material} failed: {r.stderr.strip()[-200:]}; synthetic table)")
    # synthetic: a Cook-Torrance BRDF sampled on the MERL grid
    th, td, pd = merl_grid()
    brdf = project.models.CookTorrance([0.3, 0.25, 0.2], 0.35)
    t, d, p = np.meshgrid(th, td, pd, indexing="ij")
    wi, wo = basis.from_rusinkiewicz(t, 0.0, d, p)
    ok = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    v = np.full((*t.shape, 3), np.nan)
    v[ok] = brdf.eval(wi[ok], wo[ok])
    return MERLBRDF(np.moveaxis(v, -1, 0), name="synthetic-cook-torrance")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=1 << 20)
    ap.add_argument("--orders", type=int, nargs="+", default=[4, 8, 16])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--material", default="gold-metallic-paint")
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args(argv)
    if a.quick:
        a.pairs, a.orders, a.repeats, a.material = 1 << 18, [4, 8], 3, None
    with tempfile.TemporaryDirectory() as tmp:
        brdf = _table(a.material, tmp)
    wi, wo = pairs(a.pairs, 7)
    print(header())
    print(f"bench_compress: {a.pairs} pairs, numba threads {numba.get_num_threads()}, "
          f"load average {os.getloadavg()[0]:.2f}, table {brdf.name}")
    runs: dict[str, tuple] = {}
    out3 = np.empty((a.pairs, 3))
    runs["MERL lookup (trilinear)"] = (
        lambda: run_parallel(_merl_lookup_kernel, a.pairs, wi, wo, brdf._lut, True, out3,
                             grain=128), a.pairs, None)
    runs["MERLBRDF.eval"] = (lambda: brdf.eval(wi, wo), a.pairs, None)
    ts = compress.reference_samples(brdf, nodes=(24, 48))
    top = max(a.orders)
    for kind in ("zernike", "harmonics"):
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # Gibbs warning at low order
            full = project.project(brdf, compress.make_basis(kind, top), tol=1e-6)
        print(f"projection onto {full.basis!r}: {time.perf_counter() - t0:.1f} s")
        for order in a.orders:
            cm = compress.truncate(full, order)
            ev = cm.evaluator()
            l2 = compress.errors(cm, ts)["l2"]
            runs[f"{kind} {order} CoefficientMatrix.eval"] = (lambda cm=cm: cm.eval(wi, wo),
                                                              a.pairs, l2)
            runs[f"{kind} {order} eval_flat"] = (lambda ev=ev: ev.eval_flat(wi, wo, out3),
                                                 a.pairs, l2)
            dense = basis.CoefficientMatrix(cm.basis, cm.matrix, cm.quantity, isotropic=False)
            m = min(a.pairs, 1 << 18)
            runs[f"{kind} {order} dense eval"] = (
                lambda d=dense, m=m: d.eval(wi[:m], wo[:m]), m, l2)
    best = {k: np.inf for k in runs}
    for fn, _, _ in runs.values():
        fn()
    for _ in range(a.repeats):
        for k, (fn, _, _) in runs.items():
            t0 = time.perf_counter()
            fn()
            best[k] = min(best[k], time.perf_counter() - t0)
    ref = runs["MERL lookup (trilinear)"][1] / best["MERL lookup (trilinear)"]
    print(f"\nOn {tag()}:")
    print("| evaluator | ms per 1M pairs | M samples/s | ratio to MERL lookup | l2 error |")
    print("|---|---|---|---|---|")
    for k, (_, n, l2) in runs.items():
        rate = n / best[k]
        err = "" if l2 is None else f"{l2:.3g}"
        print(f"| {k} | {1e3 * best[k] * 1e6 / n:.1f} | {rate / 1e6:.1f} | {rate / ref:.2f} | "
              f"{err} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
