"""The ``scatmodes`` command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


class UserError(Exception):
    """A problem with the user's input: reported in one line, exit status 2."""


def _demo(args: argparse.Namespace) -> int:
    from .demo import basis_table, plot_modes, to_markdown

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print("scatmodes demo: orthonormal bases for BRDFs\n")
    print("Each basis evaluated at random directions; orthonormality error = max |G - I| of")
    print("its Gram matrix on an exact product quadrature rule.\n")
    orders = _orders(args.orders)
    print(to_markdown(basis_table(orders=orders, points=args.points)))
    png = plot_modes(out / "modes.png", order=4)
    print(f"\nwrote {png} (the isotropic modes up to order 4 at theta_i = 45 deg)")
    return 0


def _orders(text: str) -> tuple[int, ...]:
    try:
        orders = tuple(int(o) for o in text.split(","))
    except ValueError:
        orders = ()
    if not orders or min(orders) < 0:
        raise UserError(f"--orders must be comma-separated integers >= 0, got {text!r}")
    return orders


def _info(args: argparse.Namespace) -> int:
    import numba
    import numpy as np
    import pyshtools

    import basis

    print(f"numpy {np.__version__}, numba {numba.__version__} ({numba.get_num_threads()} "
          f"threads), pyshtools {pyshtools.__version__} "
          f"(backend {pyshtools.backends.preferred_backend()})")
    for cls in (basis.SphericalHarmonics, basis.HemiHarmonics, basis.HemiZernike):
        print(f"{cls.__name__}: order <= {cls.max_order}")
    print(f"HelmholtzModes: order <= {basis.HelmholtzModes.max_order_isotropic} (isotropic), "
          f"<= {basis.HelmholtzModes.max_order_general} (general)")
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="scatmodes",
        description="Reflectance functions in orthonormal spherical bases: what each "
                    "representation costs and how accurate it is.")
    sub = p.add_subparsers(dest="command", required=True)
    d = sub.add_parser("demo", help="show the bases and write a picture of the modes "
                                    "(no data files needed)")
    d.add_argument("--out", default="scatmodes-out", help="output folder (default %(default)s)")
    d.add_argument("--orders", default="2,4,8,16,32",
                   help="comma-separated orders for the table (default %(default)s)")
    d.add_argument("--points", type=int, default=20_000,
                   help="random directions for timing (default %(default)s)")
    d.set_defaults(func=_demo)
    i = sub.add_parser("info", help="versions, threads and limits")
    i.set_defaults(func=_info)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``scatmodes`` console script."""
    args = _parser().parse_args(argv)
    try:
        return args.func(args)
    except (UserError, ValueError, TypeError, MemoryError, OSError) as exc:
        print(f"scatmodes {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
