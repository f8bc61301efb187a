"""``scatmodes render FILE``: a sphere rendered by Mitsuba 3 with a saved representation."""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # numpy loads when the command runs: --help stays instant
    import numpy as np

__all__ = ["add_parser", "run"]

VARIANTS = ("auto", "llvm_ad_rgb", "cuda_ad_rgb", "scalar_rgb")
#: Render passes (each with its own seed, averaged): the progress bar's steps.
_PASSES = 8


def add_parser(sub: argparse._SubParsersAction, fmt: type,
               add_progress: Callable[[argparse.ArgumentParser], None],
               wants_progress: Callable[[argparse.Namespace], bool]) -> None:
    """Register ``render`` on the subcommand parser.

    ``add_progress`` adds the command line's ``--progress`` flag and ``wants_progress``
    reads it (the conventions of :mod:`compress.cli.commands`, which calls this).
    """
    r = sub.add_parser(
        "render", formatter_class=fmt,
        help="render a sphere with Mitsuba 3 using a saved representation (PNG and EXR)",
        description="Renders a unit sphere under a constant environment and a point light "
                    "with Mitsuba 3's path tracer, its material the representation in FILE "
                    "(any file written by scatmodes: a coefficient matrix, fitted model or "
                    "hybrid) through the 'scatmodes' BSDF plugin (compress.mitsuba). Writes "
                    "OUT.png (sRGB) and OUT.exr (linear radiance). With --reference, also "
                    "renders an RGL .bsdf file through Mitsuba's 'measured' plugin or a "
                    "MERL .binary file through the plugin, writes OUT-reference.png/.exr "
                    "and OUT-difference.png/.exr (|image - reference|, the PNG scaled to "
                    "its maximum) and prints the relative RMSE of the image. Needs "
                    "scatmodes[mitsuba].",
        epilog="examples:\n  scatmodes render paper.h5 -o paper.png\n"
               "  scatmodes render paper.h5 --reference paper_white_rgb.bsdf -o paper.png "
               "--spp 64\n  scatmodes render gold.h5 --reference gold-paint.binary -o gold.png "
               "--size 64 --variant scalar_rgb")
    r.add_argument("file", metavar="FILE", help="an .h5 file written by scatmodes")
    r.add_argument("--reference", metavar="SOURCE", default=None,
                   help="an RGL-EPFL .bsdf file (Mitsuba's measured plugin) or a MERL "
                        ".binary file to render alongside and compare with")
    r.add_argument("-o", "--output", required=True, metavar="OUT.png",
                   help="PNG image to write (OUT.exr is written beside it)")
    r.add_argument("--spp", type=_positive_int, default=64,
                   help="samples per pixel (default %(default)s)")
    r.add_argument("--size", type=_positive_int, default=128,
                   help="image side in pixels (default %(default)s)")
    r.add_argument("--variant", choices=VARIANTS, default="auto",
                   help="Mitsuba variant (default %(default)s: llvm_ad_rgb where LLVM is "
                        "available, else scalar_rgb)")
    r.add_argument("--incident", choices=("light", "camera"), default="light",
                   help="which Mitsuba direction is the representation's w_i: 'light' "
                        "(physical, the default) or 'camera' (how Mitsuba's measured plugin "
                        "reads RGL files)")
    add_progress(r)
    r.set_defaults(func=functools.partial(run, wants_progress=wants_progress))


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return n


def _variant(mi: Any, name: str) -> str:
    """Set the variant (auto: LLVM when it runs here); return its name."""
    import drjit as dr

    if name in ("auto", "llvm_ad_rgb"):
        try:
            mi.set_variant("llvm_ad_rgb")
            dr.eval(mi.Float(1.0) + 1.0)
            return "llvm_ad_rgb"
        except Exception as exc:  # noqa: BLE001 - no usable LLVM: say so or fall back
            if name == "llvm_ad_rgb":
                raise ValueError(f"--variant llvm_ad_rgb needs LLVM >= 16 (libLLVM), which "
                                 f"Mitsuba cannot use here ({exc}); use --variant "
                                 f"scalar_rgb") from None
    if name == "cuda_ad_rgb":
        try:
            mi.set_variant("cuda_ad_rgb")
            dr.eval(mi.Float(1.0) + 1.0)
            return "cuda_ad_rgb"
        except Exception as exc:  # noqa: BLE001 - no usable CUDA device or driver
            raise ValueError(f"--variant cuda_ad_rgb needs an NVIDIA GPU with its driver, "
                             f"which Mitsuba cannot use here ({exc}); use --variant "
                             f"llvm_ad_rgb or scalar_rgb") from None
    mi.set_variant("scalar_rgb")
    return "scalar_rgb"


def _reference(path: Path, cmi: Any) -> Any:
    if not path.is_file():
        raise FileNotFoundError(2, "No such file", str(path))
    suffix = path.suffix.lower()
    if suffix == ".bsdf":
        return {"type": "measured", "filename": str(path)}
    if suffix == ".binary":
        from project.measured import read_merl
        return cmi.bsdf(read_merl(path))
    raise ValueError(f"--reference must be an RGL-EPFL .bsdf or a MERL .binary file, got "
                     f"{str(path)!r}")


def _traced(*materials: Any) -> bool:
    """Whether every material has a Dr.Jit form (Mitsuba's own plugins, given as dicts, do)."""
    return all(getattr(m, "traced", True) for m in materials if m is not None)


def _render(cmi: Any, material: Any, size: int, spp: int, bar: Any, traced: bool
            ) -> np.ndarray:
    """Average of up to _PASSES renders with their own seeds (spp split between them).

    ``traced``: Mitsuba's default (symbolic) mode, as ``mi.render``; otherwise evaluated
    mode, which a live material without a Dr.Jit form (an object of your own) needs, since
    Dr.Jit traces every live BSDF in a symbolic call.
    """
    import mitsuba as mi

    passes = min(_PASSES, spp)
    counts = [spp // passes + (k < spp % passes) for k in range(passes)]
    img = None
    for k, n in enumerate(counts):
        scene = cmi.sphere_scene(material, size=size, spp=n)
        image = mi.render(scene, seed=k) if traced else cmi.render(scene, seed=k)
        part = cmi.to_numpy(image) * (n / spp)
        img = part if img is None else img + part
        bar.update(1)
    return img


def _write(mi: Any, image: np.ndarray, png: Path, exr: Path, *, scale: float = 1.0) -> None:
    import numpy as np

    from project.io import atomic_path

    data = np.ascontiguousarray(image, dtype=np.float32)
    with atomic_path(exr) as tmp:
        mi.Bitmap(data).write(str(tmp))
    with atomic_path(png) as tmp:
        mi.util.convert_to_bitmap(np.ascontiguousarray(data * scale)).write(str(tmp))


def run(args: argparse.Namespace, *,
        wants_progress: Callable[[argparse.Namespace], bool]) -> int:
    """Render FILE (and the reference), write the images, print what was written."""
    import numpy as np

    out = Path(args.output)
    if out.suffix.lower() != ".png":
        raise ValueError(f"-o must name a .png file (OUT.exr is written beside it), got "
                         f"{str(out)!r}")
    if not (out.parent if str(out.parent) else Path(".")).is_dir():
        raise FileNotFoundError(2, "No such directory", str(out.parent))
    if args.size > 4096:
        raise ValueError(f"--size must be <= 4096, got {args.size}")
    try:
        import compress.mitsuba as cmi  # its ImportError says how to install Mitsuba
    except ImportError as exc:
        # an environment problem, reported in one line like other OSErrors (no import of
        # .commands here: it imports this module)
        raise OSError(str(exc)) from None
    import mitsuba as mi
    variant = _variant(mi, args.variant)
    from compress.store import load

    rep = load(args.file)
    material = cmi.bsdf(rep, incident=args.incident)
    reference = None if args.reference is None else _reference(Path(args.reference), cmi)
    from tqdm.auto import tqdm

    steps = min(_PASSES, args.spp) * (1 if reference is None else 2)
    with tqdm(total=steps, desc=f"render ({variant})", disable=not wants_progress(args),
              leave=False, file=sys.stderr, unit="pass") as bar:
        traced = _traced(material, reference)
        img = _render(cmi, material, args.size, args.spp, bar, traced)
        ref = None if reference is None else _render(cmi, reference, args.size, args.spp, bar,
                                                     traced)
    _write(mi, img, out, out.with_suffix(".exr"))
    written = [out, out.with_suffix(".exr")]
    # the traced path does not count what it clamps: measure it on random pairs
    stats = cmi.negative_fraction(rep) if material.traced else material.stats
    if stats.clamped:
        where = "of 65,536 random pairs" if material.traced else "of the evaluations"
        print(f"clamped negative values: {stats.fraction:.3%} {where} "
              f"({stats.mass_fraction:.3%} of their magnitude)")
    if ref is not None:
        stem = out.with_suffix("")
        diff = np.abs(img - ref)
        peak = float(diff.max())
        _write(mi, ref, Path(f"{stem}-reference.png"), Path(f"{stem}-reference.exr"))
        _write(mi, diff, Path(f"{stem}-difference.png"), Path(f"{stem}-difference.exr"),
               scale=1.0 / peak if peak > 0 else 1.0)
        written += [Path(f"{stem}-reference.png"), Path(f"{stem}-difference.png")]
        err = cmi.relative_rmse(img, ref)
        print(f"relative RMSE against {Path(args.reference).name}: {err:.4g} "
              f"({args.size}x{args.size}, {args.spp} spp, {variant}; Monte Carlo noise "
              f"included)")
    print("wrote " + ", ".join(str(p) for p in written))
    return 0
