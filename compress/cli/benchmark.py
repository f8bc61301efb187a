"""``scatmodes benchmark [merl|rgl|mbsdf] DIR``: compress.select over a folder of measured files."""

from __future__ import annotations

import argparse
import functools
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["add_parser"]


def add_parser(sub: argparse._SubParsersAction, fmt: type,
               add_progress: Callable[[argparse.ArgumentParser], None],
               wants_progress: Callable[[argparse.Namespace], bool],
               dask_client: Callable[[argparse.Namespace], Any]) -> None:
    """Register ``benchmark`` (targets ``merl``, ``rgl``, ``mbsdf``, or none: all) on ``sub``.

    ``add_progress`` adds the command line's ``--progress`` flag, ``wants_progress`` reads
    it, ``dask_client`` opens the Dask client of ``--scheduler`` (the conventions of
    :mod:`compress.cli.commands`, which calls this).
    """
    b = sub.add_parser(
        "benchmark", formatter_class=fmt,
        help="the smallest representation of every measured material (MERL, RGL, MDL) within "
             "a tolerance",
        description="Runs compress.select on every measured file of DIR -- MERL .binary, "
                    "RGL-EPFL .bsdf and NVIDIA MDL .mbsdf files, told apart by their suffix "
                    "(merl, rgl or mbsdf: only those) -- one process per material, and "
                    "writes OUT/materials.csv "
                    "(per material: the reciprocity residual and floor of the data and the "
                    "forms select let compete, the smallest error reached, the time of "
                    "select, and for each tolerance: family, storage type, bytes, l2 and "
                    "log errors, and the image error of lit-sphere renders), "
                    "OUT/candidates.csv, OUT/pareto.png (bytes against error per family, "
                    "non-reciprocal forms dashed, published sizes marked) and "
                    "OUT/summary.json. Finished materials are kept in OUT/materials/, so a "
                    "stopped run resumes.",
        epilog="examples:\n  scatmodes benchmark merl merl-folder --out bench --workers 2\n"
               "  scatmodes benchmark merl merl-folder --materials blue-acrylic,gold-paint\n"
               "  scatmodes benchmark rgl rgl-folder --tols 0.10,0.05\n"
               "  scatmodes benchmark measured-folder   # .binary, .bsdf and .mbsdf files")
    b.add_argument("target", nargs="?", choices=("merl", "rgl", "mbsdf"), default=None,
                   help="only MERL .binary, only RGL .bsdf or only MDL .mbsdf files (default: "
                        "all)")
    b.add_argument("folder", metavar="DIR", help="folder of measured files")
    b.add_argument("--out", default="scatmodes-benchmark", metavar="OUT",
                   help="output folder, created if missing (default %(default)s)")
    b.add_argument("--tols", default="0.05,0.10",
                   help="comma-separated l2 tolerances (default %(default)s)")
    b.add_argument("--workers", type=int, default=2,
                   help="local worker processes, one material each (default %(default)s)")
    b.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the materials as tasks on the running Dask cluster of this "
                        "scheduler instead, e.g. tcp://host:8786 (needs "
                        "scatmodes[distributed] and DIR, OUT on a shared file system)")
    b.add_argument("--materials", default=None,
                   help="comma-separated material names (default: every file in DIR)")
    b.add_argument("--error-pairs", type=int, default=1 << 16,
                   help="pairs of the peak-resolving error estimate (default %(default)s)")
    add_progress(b)
    b.set_defaults(func=functools.partial(run, wants_progress=wants_progress,
                                          dask_client=dask_client))


def run(args: argparse.Namespace, *, wants_progress: Callable[[argparse.Namespace], bool],
        dask_client: Callable[[argparse.Namespace], Any]) -> int:
    """Run the benchmark and print the summary."""
    from ..benchmark import FORMATS, benchmark_files

    try:
        tols = [float(t) for t in args.tols.split(",")]
    except ValueError:
        raise ValueError(f"--tols must be comma-separated numbers, got {args.tols!r}") from None
    if args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    names = None if args.materials is None else \
        [n.strip() for n in args.materials.split(",") if n.strip()]
    # --workers counts local processes here (no Dask needed); --scheduler alone uses Dask
    with dask_client(argparse.Namespace(workers=None, scheduler=args.scheduler)) as client:
        benchmark_files(args.folder, args.out,
                        formats=tuple(FORMATS) if args.target is None else (args.target,),
                        tols=tols, workers=args.workers, materials=names,
                        error_n=args.error_pairs, progress=wants_progress(args),
                        client=client)
    summary = json.loads((Path(args.out) / "summary.json").read_text())
    print(json.dumps(summary, indent=2))
    print(f"wrote {Path(args.out) / 'materials.csv'}, candidates.csv, pareto.png, "
          "summary.json")
    return 0
