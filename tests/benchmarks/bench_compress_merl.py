"""Benchmark: the smallest representation of each of the 100 MERL materials (compress.select).

What it measures
----------------
MERL-format files for all 100 MERL material names are written by
``../shared/tools/merl_surrogate.py`` (network fits of Sztrajman et al., CGF 2021, on the
MERL grid: stand-ins for the measurements, not MERL itself) into ``--data`` (kept between
runs: they take ~5 minutes and 3.3 GB to write). Then ``scatmodes benchmark merl`` runs
:func:`compress.select` on each (``--workers`` processes) and reports, per tolerance, how many
materials meet it, the median and largest bytes, the families chosen, the median image error
and the median time of ``select`` per material. Errors are the relative L2 error of
f cos(theta_i) cos(theta_o) on peak-resolving pairs (:mod:`project.sampling`), largest over
the channels.

Targets: every material within 10 % l2 at <= 4 kB; median <= 2.7 kB at 5 %; a median
``select`` time of at most 3 s per material with 2 workers on 2 cores. Timings are wall
times of each material's process while ``--workers`` run at once, on a shared machine:
compare within a run.

Run: ``python tests/benchmarks/bench_compress_merl.py [--data DIR] [--out DIR]
[--workers 2] [--materials a,b,c]``. A stopped run resumes (finished materials are kept
in ``OUT/materials``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from _machine import header, tag  # the machine: CPU model, features, vector width

from compress.benchmark import benchmark_merl

HERE = Path(__file__).resolve()
SHARED = Path(os.environ.get("SCATMODES_SHARED", HERE.parents[3] / "shared"))
TOOL = SHARED / "tools" / "merl_surrogate.py"


def main() -> int:
    """Write the surrogates if needed, run the benchmark, print the targets."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default=os.path.join(os.environ.get("TMPDIR", "/tmp"),
                                                  "scatmodes-merl-surrogates"))
    p.add_argument("--out", default="scatmodes-benchmark-merl")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--materials", default=None, help="comma-separated names (default all)")
    args = p.parse_args()
    print(header())
    if not TOOL.is_file():
        print(f"skipped: {TOOL} not found (the MERL surrogates need ../shared)")
        return 0
    data = Path(args.data)
    data.mkdir(parents=True, exist_ok=True)
    names = args.materials.split(",") if args.materials else subprocess.run(
        [sys.executable, str(TOOL), "--list"], check=True, capture_output=True,
        text=True).stdout.split()
    missing = [n for n in names if not (data / f"{n}.binary").is_file()]
    if missing:
        print(f"writing {len(missing)} surrogate files to {data} ...", flush=True)
        subprocess.run([sys.executable, str(TOOL), *missing, "-o", str(data)], check=True)
    start = time.perf_counter()
    rows = benchmark_merl(data, args.out, workers=args.workers, materials=names,
                          progress=True)
    wall = time.perf_counter() - start
    summary = json.loads((Path(args.out) / "summary.json").read_text())
    print(json.dumps(summary, indent=2))
    s5, s10 = summary["0.05"], summary["0.1"]
    within = sum(1 for r in rows if r["meets_0.1"] and r["bytes_0.1"] <= 4096)
    print(f"\nOn {tag()}:")
    print(f"materials: {len(rows)}; wall time {wall / 60:.1f} min with {args.workers} "
          "workers")
    print(f"within 10 % at <= 4 kB: {within} / {len(rows)} (target: all); largest "
          f"{s10['max_bytes']} B")
    print(f"5 %: {s5['meet']} / {len(rows)} meet it; median bytes of those "
          f"{s5['median_bytes']} (target <= 2700)")
    print(f"median select time per material: {summary['median_select_seconds']:.1f} s "
          "(target <= 3 s with 2 workers on 2 cores)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
