"""Benchmark: start-up of the ``scatmodes`` command and the cost of a first ``scatmodes demo``.

What it measures
----------------
- ``scatmodes --version`` (``python -m compress.cli --version``, and the console script when
  installed next to this interpreter): best wall time of ``--repeats`` runs, against the bare
  interpreter (``python -c pass``) and against importing what the command imported before its
  imports became lazy (numba, scipy.stats, h5py, matplotlib): the ratio says how much of the
  start-up is ours.
- ``scatmodes demo`` with an empty numba cache (``NUMBA_CACHE_DIR`` set to a new temporary
  folder, so every kernel compiles: what a first run after installing costs), then again
  with that cache filled (warm), one run each, and their ratio. ``--no-ahead`` adds a cold
  and a warm run with ``--no-compile-ahead`` (every kernel compiled in the demo's own
  process, one after another; no second process), in a second empty cache.

On a shared machine the load changes absolute times by 2-3x between runs: compare the
ratios of one run. The header prints the 1-minute load average before and after. The CPU
column (user + system of the demo and its compiling process) is steadier under load; the
second process only pays in wall time when a core is idle, which a loaded machine lacks.

Run: ``python tests/benchmarks/bench_cli.py [--repeats 10] [--no-ahead] [--skip-demo]``.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _machine import header, tag  # the machine: CPU model, features, vector width

ROOT = Path(__file__).resolve().parents[2]


def wall(argv: list[str], env: dict[str, str] | None = None) -> float:
    """Wall time of one run of ``argv`` (its output discarded; a failure raises)."""
    t0 = time.perf_counter()
    r = subprocess.run(argv, cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                       stderr=subprocess.PIPE, text=True, check=False)
    seconds = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed:\n{r.stderr}")
    return seconds


def best(argv: list[str], repeats: int) -> float:
    return min(wall(argv) for _ in range(repeats))


def load() -> str:
    return f"{os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else "n/a"


def cpu() -> float:
    """CPU seconds (user + system) of the finished child processes and their children."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def demo(cache: Path, out: Path, *extra: str) -> tuple[float, float]:
    """Wall and CPU seconds of one ``scatmodes demo`` with numba's cache in ``cache``."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    c0 = cpu()
    t = wall([sys.executable, "-m", "compress.cli", "demo", "--out", str(out), "--no-progress",
              *extra], env=env)
    return t, cpu() - c0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=10, help="runs of each start-up command")
    ap.add_argument("--no-ahead", action="store_true",
                    help="also time a cold demo with --no-compile-ahead")
    ap.add_argument("--skip-demo", action="store_true", help="time the start-up only")
    args = ap.parse_args()
    py = sys.executable
    print(header())
    print(f"# scatmodes start-up and demo; {os.cpu_count()} cores, load {load()}")

    base = best([py, "-c", "pass"], args.repeats)
    heavy = best([py, "-c", "import numba, scipy.stats, h5py, matplotlib.figure"], args.repeats)
    version = best([py, "-m", "compress.cli", "--version"], args.repeats)
    print(f"\nOn {tag()}:")
    print(f"| start-up (best of {args.repeats}) | seconds | vs bare interpreter |")
    print("|---|---|---|")
    print(f"| python -c pass | {base:.3f} | 1.0 |")
    print(f"| import numba, scipy.stats, h5py, matplotlib | {heavy:.3f} | {heavy / base:.1f} |")
    print(f"| python -m compress.cli --version | {version:.3f} | {version / base:.1f} |")
    script = Path(py).parent / "scatmodes"
    if script.is_file():
        t = best([str(script), "--version"], args.repeats)
        print(f"| scatmodes --version | {t:.3f} | {t / base:.1f} |")
        t = best([str(script), "demo", "--help"], args.repeats)
        print(f"| scatmodes demo --help | {t:.3f} | {t / base:.1f} |")
    print(f"\n--version: {heavy / version:.1f}x faster than importing the numerical stack")
    if args.skip_demo:
        return

    tmp = Path(tempfile.mkdtemp(prefix="scatmodes-bench-cli-"))
    try:
        cold = demo(tmp / "cache", tmp / "out")
        warm = demo(tmp / "cache", tmp / "out")
        rows = [("demo, empty numba cache (cold)", cold), ("demo, cache filled (warm)", warm)]
        if args.no_ahead:
            rows.append(("demo cold, --no-compile-ahead",
                         demo(tmp / "cache2", tmp / "out", "--no-compile-ahead")))
            rows.append(("demo warm, --no-compile-ahead",
                         demo(tmp / "cache2", tmp / "out", "--no-compile-ahead")))
        print(f"\nOn {tag()}:")
        print("| scatmodes demo (one run each) | wall s | vs warm | CPU s (all processes) |")
        print("|---|---|---|---|")
        for label, (t, c) in rows:
            print(f"| {label} | {t:.1f} | {t / warm[0]:.2f} | {c:.1f} |")
        print(f"\ncold / warm = {cold[0] / warm[0]:.2f} wall, {cold[1] / warm[1]:.2f} CPU "
              f"(load {load()})")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
