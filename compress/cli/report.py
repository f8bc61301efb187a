"""``scatmodes report INPUT [--reference SOURCE] -o report.html``: one self-contained HTML page."""

from __future__ import annotations

import argparse
import functools
from collections.abc import Callable

__all__ = ["add_parser", "run"]


def add_parser(sub: argparse._SubParsersAction, fmt: type,
               add_progress: Callable[[argparse.ArgumentParser], None],
               wants_progress: Callable[[argparse.Namespace], bool]) -> None:
    """Register ``report`` on the subcommand parser.

    ``add_progress`` adds the command line's ``--progress`` flag and ``wants_progress``
    reads it (the conventions of :mod:`compress.cli.commands`, which calls this).
    """
    r = sub.add_parser(
        "report", formatter_class=fmt,
        help="a self-contained HTML page about a representation, a measured BRDF or "
             "measurements",
        description="Writes one HTML file (figures inline, no network needed, a print "
                    "style) with: 1. a summary (form, bytes at float64/32/16 and what "
                    "rounding costs, errors, reciprocity residual and floor, provenance); "
                    "2. lobes (polar plots in the plane of incidence and heat maps over the "
                    "outgoing hemisphere at 0, 30, 60 and 75 degrees incidence); 3. lit "
                    "spheres; 4. the error by (theta_i, theta_o) band and where an "
                    "expansion is negative; 5. bytes against error for a select table "
                    "(the one the file holds, or a small one computed here) with published "
                    "sizes; 6. for measurements, the samples and the residuals of a fit. "
                    "With --reference, errors, curves and pictures are compared with it.",
        epilog="examples:\n  scatmodes report blue-acrylic.binary -o blue.html\n"
               "  scatmodes report blue.h5 --reference blue-acrylic.binary -o blue.html\n"
               "  scatmodes report paper_white_rgb.bsdf -o paper.html\n"
               "  scatmodes report gonio.csv -o gonio.html")
    r.add_argument("input", metavar="INPUT",
                   help="a file of compress.save (.h5: coefficient matrix, fitted model or "
                        "hybrid), a MERL .binary table, an RGL-EPFL .bsdf file or a "
                        "measurement table (text, CSV or Cornell .brdf)")
    r.add_argument("--reference", metavar="SOURCE", default=None,
                   help="a file of the same kinds to compare with (e.g. the measured data a "
                        "representation was made from)")
    r.add_argument("--no-table", dest="table", action="store_false",
                   help="do not compute the small select table of section 5 when INPUT "
                        "holds none (saves about 2 s of CPU on a MERL table)")
    r.add_argument("--title", default=None, help="page title (default: INPUT's file name)")
    r.add_argument("-o", "--output", required=True, metavar="REPORT.html",
                   help="HTML file to write (replaced atomically)")
    add_progress(r)
    r.set_defaults(func=functools.partial(run, wants_progress=wants_progress))


def run(args: argparse.Namespace, *,
        wants_progress: Callable[[argparse.Namespace], bool]) -> int:
    """Write the report and print where it went."""
    import time

    from ..report import report

    start = time.perf_counter()
    path = report(args.input, args.reference, args.output, title=args.title,
                  table=args.table, progress=wants_progress(args))
    print(f"wrote {path} ({path.stat().st_size:,} bytes, {time.perf_counter() - start:.1f} s)")
    return 0
