"""``scatmodes export INPUT --format mbsdf -o OUT``: a representation in another tool's format."""

from __future__ import annotations

import argparse

__all__ = ["FORMATS", "add_parser", "run"]

#: What ``export`` writes: NVIDIA MDL measured BSDFs (:func:`project.measured.write_mbsdf`).
FORMATS = ("mbsdf",)


def add_parser(sub: argparse._SubParsersAction, fmt: type) -> None:
    """Register ``export`` on the subcommand parser."""
    e = sub.add_parser(
        "export", formatter_class=fmt,
        help="write a representation or a measured BRDF in another renderer's format",
        description="Samples INPUT (any file of compress.save, a MERL .binary table, an "
                    "RGL-EPFL .bsdf or an MDL .mbsdf file) on the grid of the target format "
                    "and writes it atomically. mbsdf: an NVIDIA MDL measured BSDF (reflection "
                    "part, RGB or scalar), values at the texel centres, as MDL renderers read "
                    "it (project.measured.write_mbsdf).",
        epilog="examples:\n  scatmodes export paint.h5 --format mbsdf -o paint.mbsdf\n"
               "  scatmodes export paint.h5 --format mbsdf --resolution 90,180 -o fine.mbsdf")
    e.add_argument("input", metavar="INPUT", help="the file to export")
    e.add_argument("--format", required=True, choices=FORMATS, help="the target format")
    e.add_argument("--resolution", default="45,90", metavar="N_THETA,N_PHI",
                   help="mbsdf: cells in theta_in and theta_out over [0, pi/2] and in "
                        "delta_phi over [0, pi] (default 45,90: 2-degree cells)")
    e.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="file to write (replaced atomically)")
    e.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Write the file and print where it went."""
    from project.measured import write_mbsdf

    from ..report import read_source

    parts = args.resolution.split(",")
    try:
        resolution = tuple(int(x) for x in parts)
    except ValueError:
        resolution = ()
    if len(resolution) != 2:
        raise ValueError(f"--resolution must be two integers N_THETA,N_PHI, got "
                         f"{args.resolution!r}")
    rep = read_source(args.input)
    if not callable(getattr(rep, "eval", None)):
        raise ValueError(f"{args.input!r} holds scattered measurements, which cannot be "
                         "sampled on a grid: fit a representation first (scatmodes fit)")
    path = write_mbsdf(rep, args.output, resolution=resolution)
    print(f"wrote {path} ({path.stat().st_size:,} bytes, mbsdf {resolution[0]} x "
          f"{resolution[0]} x {resolution[1]}, {rep.channels} channel"
          f"{'s' if rep.channels > 1 else ''})")
    return 0
