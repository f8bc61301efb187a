"""The ``scatmodes`` command line.

Commands: ``demo`` (no data files needed), ``project`` (an analytic model or a MERL file),
``convert`` (a MERL ``.binary``, RGL ``.bsdf`` or MDL ``.mbsdf`` file projected to HDF5; a
measurement file is fitted as by ``fit``), ``fit`` (a measurement file: our table, CSV or
Cornell ``.brdf``; a coefficient matrix, or a compact model with ``--model``), ``simulate``
(the microgeometry simulator), ``study`` (error and speed against order) and ``info``. Every
command has ``--help`` with examples.

A problem with the input (unknown model, bad parameter, missing or unreadable file,
unwritable output, bad order, ...) prints exactly one line ``scatmodes <command>: error:
...`` on stderr and exits with status 2, never a traceback. Library warnings (e.g. Gibbs
ringing of a sharp BRDF at a low order) print as ``scatmodes <command>: warning: ...``.
Long work shows a tqdm progress bar on stderr when stderr is a terminal (``--progress`` /
``--no-progress`` to force it either way).
"""

from __future__ import annotations

import argparse
import contextlib
import inspect
import os
import signal
import struct
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Any

# Only the standard library at import time: `scatmodes --version` and every `--help` answer
# without loading numba, SciPy, h5py or matplotlib; each command imports what it needs.

#: The basis kinds of ``basis.KINDS``, spelled out so that building the parser imports no
#: numba (tests/compress/cli/test_startup.py checks that the two agree).
KINDS = ("zernike", "harmonics", "harmonics-even", "sh")
#: Parameters of each model in the help examples and in the hints of error messages.
MODEL_EXAMPLES = {
    "Lambert": "albedo=0.5",
    "Minnaert": "k=1.5 albedo=0.5",
    "OrenNayar": "albedo=0.5 sigma=0.3",
    "Phong": "kd=0.3 ks=0.4 n=20",
    "BlinnPhong": "kd=0.3 ks=0.4 n=40",
    "Ward": "kd=0.2 ks=0.1 alpha_x=0.2 alpha_y=0.2",
    "CookTorrance": "kd=0.2 roughness=0.3 distribution=ggx ior=1.5",
    "AshikhminShirley": "rd=0.3 rs=0.1 nu=50 nv=50",
    "Lafortune": "kd=0.2 'lobes=-0.8,-0.8,0.8,20'",
    "GlossyPaint": "albedo=0.5 specular=0.02",
}


class UserError(Exception):
    """A problem with the user's input: reported in one line, exit status 2."""


#: exceptions reported as one line (the library raises ValueError/TypeError for bad values
#: and kinds, OSError for files, MemoryError for sizes it refuses to allocate)
USER_ERRORS = (UserError, ValueError, TypeError, MemoryError, OSError)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage block): ``<prog>: error: <message>``."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


# -- argument types --------------------------------------------------------------------------
def _order(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}")
    return n


def _count(text: str) -> int:
    try:
        n = int(float(text)) if "e" in text.lower() else int(text)
    except ValueError:
        n = 0
    if n <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer (e.g. 30000 or 3e4), "
                                         f"got {text!r}")
    return n


def _positive(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        x = float("nan")
    if not x > 0 or x == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return x


def _nonneg(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        x = float("nan")
    if not 0 <= x < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text!r}")
    return x


def _orders(text: str, name: str = "--orders") -> tuple[int, ...]:
    try:
        orders = tuple(int(o) for o in text.split(","))
    except ValueError:
        orders = ()
    if not orders or min(orders) < 0:
        raise UserError(f"{name} must be comma-separated integers >= 0, got {text!r}")
    return orders


def _kinds(text: str) -> tuple[str, ...]:
    from basis import KINDS as known  # the library's list, in case it grew

    kinds = tuple(k.strip() for k in text.split(",") if k.strip())
    bad = [k for k in kinds if k not in known]
    if not kinds or bad:
        raise UserError(f"--kinds must be comma-separated basis kinds from {', '.join(known)}, "
                        f"got {text!r}")
    return kinds


# -- models and files ------------------------------------------------------------------------
def model_classes() -> dict[str, type]:
    """Return the analytic models of :mod:`project.models` by name."""
    from project import BRDF, models

    return {n: getattr(models, n) for n in models.__all__
            if isinstance(getattr(models, n), type) and issubclass(getattr(models, n), BRDF)}


def _param_value(text: str) -> Any:
    """Parse a number, a comma list of numbers, lists separated by ';', None, or a word."""
    if ";" in text:
        return [_param_value(part) for part in text.split(";") if part.strip()]
    if "," in text:
        return [float(x) for x in text.split(",")]
    if text.lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        return text


def parse_model(name: str, params: list[str]) -> Any:
    """Build ``project.models.<name>`` from ``KEY=VALUE`` strings (name case-insensitive)."""
    classes = model_classes()
    lookup = {n.lower(): n for n in classes}
    if name.lower() not in lookup:
        raise UserError(f"MODEL must be one of {', '.join(classes)}, got {name!r}")
    cname = lookup[name.lower()]
    cls = classes[cname]
    sig = inspect.signature(cls)
    kw: dict[str, Any] = {}
    for p in params:
        key, eq, value = p.partition("=")
        key = key.strip()
        if not eq or not key or not value.strip():
            raise UserError(f"--param must be KEY=VALUE, got {p!r}")
        if key not in sig.parameters:
            raise UserError(f"--param {key!r} is not a parameter of {cname}, which takes "
                            f"{', '.join(sig.parameters)}")
        try:
            kw[key] = _param_value(value.strip())
            if key == "lobes" and kw[key] and not isinstance(kw[key][0], list):
                kw[key] = [kw[key]]  # one lobe Cx,Cy,Cz,n
        except ValueError:
            raise UserError(f"--param {key} must be a number, a comma list of numbers or a "
                            f"word, got {value!r}") from None
    missing = [k for k, v in sig.parameters.items() if v.default is inspect.Parameter.empty
               and v.kind is not inspect.Parameter.VAR_KEYWORD and k not in kw]
    if missing:
        raise UserError(f"{cname} needs --param for {', '.join(missing)} (e.g. --param "
                        f"{' --param '.join(MODEL_EXAMPLES.get(cname, '').split())})")
    return cls(**kw)


def _source(args: argparse.Namespace) -> Any:
    """Return the BRDF named by MODEL (+ --param) or --merl."""
    if args.merl is not None:
        if args.model is not None:
            raise UserError(f"give either MODEL or --merl, not both (got {args.model!r} and "
                            f"--merl {args.merl!r})")
        if args.param:
            raise UserError("--param applies to MODEL, not to --merl")
        from project.measured import read_merl

        _input_file(args.merl, "--merl")
        return read_merl(args.merl)
    if args.model is None:
        raise UserError("give a MODEL (e.g. Phong --param kd=0.3 --param ks=0.4 --param n=20) "
                        "or --merl FILE.binary")
    return parse_model(args.model, args.param)


def _input_file(path: str, name: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise UserError(f"{name} file {path!r} does not exist")
    if p.is_dir():
        raise UserError(f"{name} must be a file, got the directory {path!r}")
    if not p.is_file():  # a FIFO or a device: opening it could block forever
        raise UserError(f"{name} {path!r} must be a regular file, got a FIFO, a device or a "
                        "socket; copy it to a file first")
    if not os.access(p, os.R_OK):
        raise UserError(f"{name} file {path!r} is not readable")
    return p


def _output_file(path: str, name: str = "-o") -> Path:
    """Check before any work that ``path`` can be written (its folder exists, is writable)."""
    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise UserError(f"{name} must name a file, got the directory {path!r}")
    if not folder.is_dir():
        raise UserError(f"cannot write {name} {path!r}: directory {str(folder)!r} does not "
                        "exist")
    if not os.access(folder, os.W_OK | os.X_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise UserError(f"cannot write {name} {path!r}: permission denied")
    return p


def _output_dir(path: str, name: str = "--out") -> Path:
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UserError(f"{name} must be a directory, got the file {path!r}")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UserError(f"cannot create {name} directory {path!r}: "
                        f"{err.strerror or err}") from None
    if not os.access(p, os.W_OK | os.X_OK):
        raise UserError(f"cannot write to {name} directory {path!r}: permission denied")
    return p


def _progress(args: argparse.Namespace) -> bool:
    flag = getattr(args, "progress", None)
    return sys.stderr.isatty() if flag is None else bool(flag)


def _bar(iterable: Any, args: argparse.Namespace, desc: str, total: int | None = None) -> Any:
    from tqdm.auto import tqdm

    return tqdm(iterable, desc=desc, total=total, disable=not _progress(args), leave=False,
                file=sys.stderr, unit="step")


def _basis(kind: str, order: int) -> Any:
    from basis import make_basis

    return make_basis(kind, order)


# -- commands --------------------------------------------------------------------------------
def _demo(args: argparse.Namespace) -> int:
    from . import demo

    out = _output_dir(args.out)
    orders = _orders(args.orders)
    study_orders = _orders(args.study_orders, "--study-orders")
    # on a first run (the first cache miss) a second process compiles the Zernike kernel and
    # the simulation's kernels while this one compiles the harmonics', the quadrature's and
    # the evaluator's (about equal shares: with the evaluator in the second process this one
    # waited 4.6 s for the simulation's kernels; with no simulation the second process takes
    # the evaluator); later runs load them from numba's cache and start none
    steps: dict[str, tuple[int, ...]] = {"zernike": ()}
    if args.rays > 0:
        steps["simulation"] = (args.resolution,)
    else:
        steps["evaluator"] = ()
    with demo.CompileAhead(steps if args.compile_ahead else {}, lazy=True) as ahead:
        return _demo_steps(args, demo, out, orders, study_orders, ahead)


def _demo_steps(args: argparse.Namespace, demo: Any, out: Path, orders: tuple[int, ...],
                study_orders: tuple[int, ...], ahead: Any) -> int:
    print("scatmodes demo: orthonormal bases for BRDFs\n")
    print("1. Each basis evaluated at random directions; orthonormality error = max |G - I| "
          "of")
    print("its Gram matrix on an exact product quadrature rule.\n")

    def before_zernike(kind: str) -> None:
        if ahead.started:  # a first run: compile step 2's quadrature while Zernike compiles
            demo.compile_projection()
        ahead.wait(kind)

    print(demo.to_markdown(demo.basis_table(orders=orders, points=args.points,
                                            wait=before_zernike)))
    png = demo.plot_modes(out / "modes.png", order=4)
    print(f"\nwrote {png} (the isotropic modes up to order 4 at theta_i = 45 deg)\n")

    ahead.wait("evaluator")

    print("2. Two built-in models projected at orders "
          f"{', '.join(map(str, study_orders))} (f cos cos, quadrature to relative tolerance "
          f"{demo.STUDY_TOL:g}); errors against the model itself.")
    print("resolution = 180 deg / order, the half period of the highest degree kept; l2 = "
          "relative L2 error over H x H.\n")
    rows, md = [], []
    items = list(demo.demo_models().items())
    for name, brdf in _bar(items, args, "study"):
        st = demo.model_study(brdf, study_orders)
        rows += demo.resolution_rows(name, st)
        md.append(st.to_markdown())
        st.plot(str(out / f"study-{name}.png"))
    (out / "study.md").write_text("\n\n".join(md) + "\n", encoding="utf-8")
    print(demo.to_markdown(rows))
    print(f"\nwrote {out / 'study.md'} (all metrics) and "
          f"{', '.join(str(out / f'study-{n}.png') for n, _ in items)}\n")

    if args.rays > 0:
        ahead.wait("simulation")
        print(f"3. Monte Carlo microgeometry: {args.rays} rays through a Gaussian surface "
              "(sigma/tau = 1/6.5, mirror facets), HemiZernike(8), against Beckmann + Smith.\n")
        sim = demo.simulate_demo(rays=args.rays, resolution=args.resolution, seed=1,
                                 progress=_progress(args))
        for line in sim["lines"]:
            print(line)
        png = demo.plot_inplane(out / "simulated.png", sim["curves"], title=sim["title"])
        print(f"\nwrote {png} (in-plane f cos(theta_o): simulation, model, model projected)")
    return 0


def _info(args: argparse.Namespace) -> int:
    if args.file is not None:
        from .info import run

        return run(args.file, as_json=args.json)
    if args.json:
        raise UserError("--json describes a FILE: give one (e.g. scatmodes info phong.h5 --json)")
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
    print(f"basis kinds (--basis, --kinds): {', '.join(KINDS)}")
    print(f"models (MODEL): {', '.join(model_classes())}")
    return 0


def _describe(cm: Any) -> str:
    from compress import unique_coefficients

    n = unique_coefficients(cm)
    return (f"{cm.basis!r}, quantity {cm.quantity}, {cm.channels} channel(s), {n} "
            f"coefficients ({8 * n:,} bytes stored as float64)")


def _fmt(x: Any) -> str:
    return "n/a" if x is None else f"{x:.3g}"


def _project(args: argparse.Namespace) -> int:
    out = _hdf5_output(args.output)
    brdf = _source(args)
    tol = args.tol if args.tol is not None else (1e-3 if args.merl is not None else 1e-6)
    return _write_projection(brdf, args, out, args.quantity, tol)


def _write_projection(brdf: Any, args: argparse.Namespace, out: Path, quantity: str,
                      tol: float) -> int:
    """Project ``brdf`` onto ``--basis``/``--order``, save it to ``out`` and report."""
    from compress import save
    from project import project

    b = _basis(args.basis, args.order)
    cm = project(brdf, b, quantity=quantity, method=args.method, tol=tol)
    save(cm, out)
    info = cm.info
    nodes = info.get("nodes")
    nodes_text = (" x ".join(map(str, nodes)) if isinstance(nodes, tuple | list)
                  else str(nodes))
    print(f"wrote {out}: {brdf!r} in {_describe(cm)}; nodes {nodes_text}, error estimate "
          f"{_fmt(info.get('error_estimate'))}, truncation error "
          f"{_fmt(info.get('truncation_error'))}, {info.get('seconds', float('nan')):.2f} s")
    return 0


# -- what a file holds -----------------------------------------------------------------------
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_TENSOR_MAGIC = b"tensor_file\x00"  # RGL-EPFL .bsdf files (project.measured.rgl)
_MERL_HEADER = struct.pack("<3i", 90, 90, 180)  # project.measured.MERL_SHAPE[1:], int32
_MBSDF_MAGIC = b"NVIDIA ARC MBSDF V1\n"  # NVIDIA MDL .mbsdf files (project.measured.mbsdf)


def _file_kind(path: Path) -> str:
    """Return "hdf5", "rgl", "mbsdf", "merl" or "measurements" (any other file).

    By content and suffix; a damaged file with a known suffix goes to its reader, which says
    what is wrong.
    """
    with open(path, "rb") as fh:
        head = fh.read(len(_MBSDF_MAGIC))
    suffix = path.suffix.lower()
    if head.startswith(_HDF5_SIGNATURE):
        return "hdf5"
    if head == _MBSDF_MAGIC or suffix == ".mbsdf":
        return "mbsdf"
    head = head[:len(_TENSOR_MAGIC)]
    if head == _TENSOR_MAGIC or suffix == ".bsdf":
        return "rgl"
    if suffix == ".binary" or head.startswith(_MERL_HEADER):
        return "merl"
    return "measurements"


#: Defaults of the convert options that only a projection uses (MERL and RGL files).
_CONVERT_TOL, _CONVERT_METHOD = 1e-3, "quadrature"


def _convert(args: argparse.Namespace) -> int:
    out = _hdf5_output(args.output)
    suffix = Path(args.file).suffix.lower()
    label = {".binary": "--merl", ".bsdf": "RGL", ".mbsdf": "MBSDF"}.get(suffix, "measurement")
    p = _input_file(args.file, label)
    kind = _file_kind(p)
    if kind == "merl":  # exactly 'scatmodes project --merl FILE'
        args.merl, args.model, args.param = args.file, None, []
        return _project(args)
    if kind == "hdf5":
        raise UserError(f"FILE {args.file!r} is an HDF5 file, not a BRDF or measurements to "
                        f"convert ('scatmodes info {args.file}' describes it)")
    if kind == "rgl":
        from project.measured import read_rgl

        brdf = read_rgl(p)
        # the stored f grows like 1 / cos(theta_o) at grazing angles (the reference value is
        # f cos(theta_o)): as "f" it is not square integrable and the projection crawls
        quantity = "f_cos" if args.quantity == "auto" else args.quantity
        return _write_projection(brdf, args, out, quantity, args.tol)
    if kind == "mbsdf":
        from project.measured import read_mbsdf

        # f is bounded at grazing angles; f_cos is the projection's default quantity
        brdf = read_mbsdf(p)
        quantity = "f_cos" if args.quantity == "auto" else args.quantity
        return _write_projection(brdf, args, out, quantity, args.tol)
    # scattered measurements: a least-squares fit, as 'scatmodes fit FILE' with its defaults
    if args.tol != _CONVERT_TOL or args.method != _CONVERT_METHOD:
        raise UserError(f"--tol and --method apply to projecting a MERL, RGL or MBSDF file; "
                        f"{args.file!r} holds measurements, which convert fits as 'scatmodes "
                        "fit' does (drop them; 'scatmodes fit --help' lists the fit's options)")
    fit_args = argparse.Namespace(
        table=args.file, label="FILE", output=args.output, format="auto", angles=None,
        channels=None, wavelengths=None, model=None, basis=args.basis, order=args.order,
        quantity="f" if args.quantity == "auto" else args.quantity, isotropic=None,
        reciprocal=True, regularization="auto", penalty=None, modal_defaults={},
        note="measurements: fitted by least squares as 'scatmodes fit' does (its options: "
             "'scatmodes fit --help')",
        not_text="is neither a MERL .binary, an RGL .bsdf, an MDL .mbsdf nor a measurement "
                 "text file",
        **dict.fromkeys(_MODEL_OPTIONS))
    return _fit(fit_args)


#: The automatic choices of ``fit --regularization`` (``project.lstsq.REGULARIZATION_METHODS``).
_FIT_METHODS = ("auto", "gcv", "leave-incidence-out")
#: Formats of ``fit --format`` (``project.measured.tables.MEASUREMENT_FORMATS``) and angle units.
_FIT_FORMATS = ("table", "csv", "cornell")
_FIT_ANGLES = ("degrees", "radians")
#: Families of ``fit --model``: ``project.fitting.FAMILIES`` but "factored" (see _family).
_FIT_FAMILIES = ("lambert+ggx", "lambert+beckmann", "lafortune", "dsbrdf", "rr8807")
#: Options of the modal fit, refused with --model (when changed from their defaults), and
#: options of --model (``fit_model``'s), refused without it.
_MODAL_OPTIONS = ("basis", "order", "quantity", "isotropic", "reciprocal", "regularization",
                  "penalty")
_MODEL_OPTIONS = ("seed", "restarts", "lobes", "max_nfev", "folds")


def _fit_regularization(text: str) -> str | float:
    if text in _FIT_METHODS:
        return text
    try:
        x = float(text)
    except ValueError:
        x = float("nan")
    if not 0 <= x < float("inf"):
        raise argparse.ArgumentTypeError(f"must be one of {', '.join(_FIT_METHODS)} or a number "
                                         f">= 0, got {text!r}")
    return x


def _family(text: str) -> str:
    name = text.strip().lower()
    if name == "factored":
        raise argparse.ArgumentTypeError(
            "'factored' cannot be fitted to measurements: it tabulates a BRDF on a dense rule "
            "of half/difference angles and needs a BRDF that can be evaluated anywhere, which "
            f"scattered samples do not cover; choose one of {', '.join(_FIT_FAMILIES)}")
    if name not in _FIT_FAMILIES:
        raise argparse.ArgumentTypeError(f"must be one of {', '.join(_FIT_FAMILIES)}, got "
                                         f"{text!r}")
    return name


def _wavelength_list(text: str) -> tuple[float, ...]:
    try:
        nm = tuple(float(x) for x in text.split(","))
    except ValueError:
        nm = ()
    if not nm or not all(0 < x < float("inf") for x in nm) or \
            any(b <= a for a, b in zip(nm, nm[1:], strict=False)):
        raise argparse.ArgumentTypeError(f"must be comma-separated wavelengths in nm, > 0 and "
                                         f"increasing (e.g. 450,550,650), got {text!r}")
    return nm


def _channel_list(text: str) -> list[int | str]:
    items = [c.strip() for c in text.split(",")]
    if not all(items):
        raise argparse.ArgumentTypeError(f"must be comma-separated channel names or indices "
                                         f"(e.g. R,G or 0,2), got {text!r}")
    return [int(c) if c.lstrip("-").isdigit() else c for c in items]


def _read_measurements(path: str, label: str, fmt: str = "auto", angles: str | None = None,
                       not_text: str = "is not a text table") -> Any:
    """Read a measurement file (project.measured.read_measurements), errors in one line."""
    from project.measured import read_measurements

    p = _input_file(path, label)
    kind = _file_kind(p)
    if kind in ("rgl", "merl", "mbsdf"):
        what = {"rgl": "an RGL-EPFL .bsdf", "merl": "a MERL .binary",
                "mbsdf": "an NVIDIA MDL .mbsdf"}[kind]
        raise UserError(f"{label} {path!r} is {what} file, a BRDF that can be evaluated "
                        f"anywhere rather than scattered measurements: project it with "
                        f"'scatmodes convert {path} -o OUT.h5'")
    if kind == "hdf5":
        raise UserError(f"{label} {path!r} is an HDF5 file, not measurements ('scatmodes info "
                        f"{path}' describes it)")
    try:
        p.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as err:
        byte = err.object[err.start:err.start + 1].hex()
        raise UserError(f"{label} {path!r} {not_text}: it holds the byte 0x{byte}, "
                        f"which is not UTF-8 (a binary file?); give a text file of measurements "
                        f"(a table, CSV or Cornell .brdf: see 'scatmodes fit --help')") from None
    try:
        return read_measurements(p, None if fmt == "auto" else fmt, angles=angles)
    except ValueError as err:
        # read_measurements names the file (quoted) and the line; the argument is named here
        text, name = str(err), repr(str(p))
        if text.startswith(name):
            text = text[len(name):].lstrip(",: ")
        raise UserError(f"{label} {path!r}: {text}") from None


def _select(meas: Any, args: argparse.Namespace, label: str) -> Any:
    """Apply --channels, then --wavelengths (linear interpolation between channels)."""
    if args.channels is not None:
        try:
            meas = meas.select_channels(args.channels)
        except (ValueError, TypeError) as err:
            raise UserError(f"--channels: {err}") from None
    if args.wavelengths is not None:
        wl = meas.wavelengths
        if wl is None:
            raise UserError(f"--wavelengths needs spectral data: {label} {args.table!r} holds "
                            f"the channels {', '.join(meas.channel_names)} without wavelengths "
                            "(pick channels with --channels)")
        outside = [x for x in args.wavelengths if not wl[0] <= x <= wl[-1]]
        if outside:
            raise UserError(f"--wavelengths must lie within the measured range [{wl[0]:g}, "
                            f"{wl[-1]:g}] nm of {label} {args.table!r} (no extrapolation), "
                            f"got {outside[0]:g}")
        meas = meas.at_wavelengths(args.wavelengths)
    return meas


def _options_given(args: argparse.Namespace, names: tuple[str, ...],
                   defaults: dict[str, Any] | None = None) -> list[str]:
    """Return the option names of ``names`` whose value differs from its default (None)."""
    defaults = defaults or {}
    return ["--" + n.replace("_", "-") for n in names
            if getattr(args, n) != defaults.get(n)]


def _fit(args: argparse.Namespace) -> int:
    out = _hdf5_output(args.output)
    label = getattr(args, "label", "TABLE")
    if args.model is None:
        given = _options_given(args, _MODEL_OPTIONS)
        if given:
            raise UserError(f"{', '.join(given)} appl{'ies' if len(given) == 1 else 'y'} to "
                            "--model FAMILY (the fit of a parametric model)")
    else:
        given = _options_given(args, _MODAL_OPTIONS, args.modal_defaults)
        if given:
            raise UserError(f"{', '.join(given)} appl{'ies' if len(given) == 1 else 'y'} to the "
                            f"modal fit (a coefficient matrix), not to --model {args.model}")
        if args.lobes is not None and args.model not in ("lafortune", "dsbrdf"):
            raise UserError(f"--lobes applies to --model lafortune and dsbrdf, not to "
                            f"{args.model}")
    meas = _read_measurements(args.table, label, args.format, args.angles,
                              getattr(args, "not_text", "is not a text table"))
    info = meas.info
    note = getattr(args, "note", None)
    print(f"read {meas!r} from {args.table} ({info.get('format')} format, "
          f"{info.get('format_detected')})" + (f"; {note}" if note else ""))
    meas = _select(meas, args, label)
    if args.model is not None:
        return _fit_family(args, meas, out)
    from compress import save
    from project import fit

    b = _basis(args.basis, args.order)
    isotropic = args.isotropic
    if isotropic is None:  # as the file states, else isotropic
        isotropic = meas.isotropic is not False
    t0 = time.perf_counter()
    cm = fit(meas, b, quantity=args.quantity, isotropic=isotropic,
             regularization=args.regularization, penalty=args.penalty,
             reciprocal=args.reciprocal)
    seconds = time.perf_counter() - t0
    cm.info.setdefault("source", f"fit to {Path(args.table).name}")
    save(cm, out)
    i = cm.info
    resid = ", ".join(f"{r:.3g}" for r in i["residual_rms"])
    val, lam = i["validation_error"], i["lambert_validation_error"]
    how = i["regularization_method"]
    chosen = "given" if how == "given" else f"chosen by {how}"
    print(f"wrote {out}: {_describe(cm)}; {i['samples']} samples, condition number "
          f"{i['condition_number']:.3g}, rank {i['rank']} of {i['unknowns']} unknowns, "
          f"residual RMS {resid} ({args.quantity}), {seconds:.2f} s")
    print(f"regularization weight {i['regularization']:.3g} ({i['penalty']} penalty, {chosen}), "
          f"{i['effective_parameters']:.1f} effective parameters, condition number "
          f"{i['cond_regularized']:.3g} regularized; validation error "
          + ("not computed (weight given)" if val is None else
             f"{100 * val:.3g} % (relative RMS at held-out pairs), {100 * lam:.3g} % for a "
             "Lambertian fit"))
    return 0


def _fit_family(args: argparse.Namespace, meas: Any, out: Path) -> int:
    """Run ``fit --model FAMILY``: project.fit_model on the measurements, then compress.save."""
    from compress import save
    from project import fit_model

    options = {n: getattr(args, n) for n in _MODEL_OPTIONS if getattr(args, n) is not None}
    model = fit_model(meas, args.model, **options)
    save(model, out)
    i = model.info
    l2, se = i.get("l2"), i.get("l2_stderr")
    print(f"wrote {out}: {model!r}; {model.nparams} parameters ({model.nbytes:,} bytes stored "
          f"as float64), {model.channels} channel(s)")
    print(f"fitted to {len(meas)} samples: best of {i['restarts']} restarts (restart "
          f"{i['best_restart']}, {'converged' if i['converged'] else 'not converged'}), l2 error "
          f"{i['fit_l2']:.3g} on the fitted samples, {i['seconds']:.2f} s")
    print("cross-validated l2 error " + (
        "not computed (--folds 0)" if l2 is None else
        f"{l2:.3g} +- {se:.3g} ({i.get('validation', 'held-out samples')}; relative RMS of "
        "f cos(theta_i) cos(theta_o) at held-out samples, 1 = predicting zero)"))
    return 0


#: Suffixes of the HDF5 files that -o writes (compress.save); anything else is refused, so
#: that "-o result.txt" does not silently produce HDF5 under a text name.
HDF5_SUFFIXES = (".h5", ".hdf5", ".hdf", ".he5")


def _hdf5_output(path: str, name: str = "-o") -> Path:
    """Check that ``path`` names an HDF5 file by its suffix, then that it can be written."""
    if Path(path).is_dir():
        return _output_file(path, name)  # says that a directory is not a file
    suffix = Path(path).suffix
    if suffix.lower() not in HDF5_SUFFIXES:
        raise UserError(f"{name} {path!r} must end in {', '.join(HDF5_SUFFIXES)}: the command "
                        f"writes HDF5 (got {'no suffix' if not suffix else repr(suffix)}; e.g. "
                        f"{name} {Path(path).with_suffix('.h5')})")
    return _output_file(path, name)


def _simulate_quantity(text: str) -> str:
    if text != "f_cos":
        raise argparse.ArgumentTypeError(
            f"simulate supports only f_cos, got {text!r}: Westin's estimator gives the "
            "coefficients of f cos(theta_i) cos(theta_o); the written matrix still evaluates "
            "f (CoefficientMatrix.eval divides by the cosines)")
    return text


class _Terminated(SystemExit):
    """SIGTERM during simulate: simulate saves its checkpoint before this ends the command."""


def _raise_terminated(signum: int, frame: Any) -> None:
    raise _Terminated(128 + signum)


#: seconds to wait for --scheduler: a wrong address fails fast instead of hanging
_CONNECT_TIMEOUT = 5


@contextlib.contextmanager
def _dask_client(args: argparse.Namespace) -> Any:
    """Yield the Dask client of ``--workers N`` or ``--scheduler ADDRESS`` (None without)."""
    if args.workers is None and args.scheduler is None:
        yield None
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise UserError("--workers and --scheduler need dask.distributed, which is not "
                        "installed: pip install 'scatmodes[distributed]'") from None
    with contextlib.ExitStack() as stack:
        if args.workers is not None:
            # one thread per worker process: simulate gives each its share of the cores
            cluster = stack.enter_context(LocalCluster(
                n_workers=args.workers, threads_per_worker=1, processes=True,
                dashboard_address=None))
            client = stack.enter_context(Client(cluster))
        else:
            try:
                client = Client(args.scheduler, timeout=_CONNECT_TIMEOUT)
            except (OSError, ValueError) as err:
                raise UserError(f"--scheduler {args.scheduler!r}: cannot connect "
                                f"({' '.join(str(err).split())}); give the address the "
                                "scheduler prints (e.g. tcp://host:8786) and check that it "
                                "is running") from None
            stack.enter_context(client)
        yield client


def _simulate(args: argparse.Namespace) -> int:
    from compress import save
    from project.microgeometry import Diffuse, GaussianSurface, Mirror, simulate

    out = _hdf5_output(args.output)
    if args.checkpoint is not None:
        _output_file(args.checkpoint, "--checkpoint")
    elif args.checkpoint_interval is not None:
        raise UserError("--checkpoint-interval applies with --checkpoint PATH")
    if args.resume is not None:
        _input_file(args.resume, "--resume")
    if args.material == "mirror":
        if args.albedo is not None:
            raise UserError("--albedo applies to --material diffuse (mirror facets take --ior)")
        material = Mirror(args.ior)
    else:
        if args.ior is not None:
            raise UserError("--ior applies to --material mirror (diffuse facets take "
                            "--albedo)")
        material = Diffuse(1.0 if args.albedo is None else args.albedo)
    surface = GaussianSurface(args.sigma, args.tau, resolution=args.resolution,
                              seed=args.surface_seed, material=material)
    b = _basis(args.basis, args.order)
    interval = 60.0 if args.checkpoint_interval is None else args.checkpoint_interval
    # SIGTERM (a scheduler's kill) becomes an exception, so that simulate saves the final
    # checkpoint as it does for Ctrl-C; only the main thread may install handlers
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _raise_terminated) if main_thread else None
    saved = "" if args.checkpoint is None else (
        f"; the rays traced so far are saved in {args.checkpoint!r}: continue with --resume "
        f"{args.checkpoint} --checkpoint {args.checkpoint}")
    try:
        with _dask_client(args) as client:
            res = simulate(surface, b, rays=args.rays, seed=args.seed,
                           checkpoint=args.checkpoint, checkpoint_interval=interval,
                           resume=args.resume, progress=_progress(args), client=client)
    except KeyboardInterrupt:
        print(f"scatmodes simulate: interrupted{saved}", file=sys.stderr)
        return 130
    except _Terminated as stop:
        print(f"scatmodes simulate: terminated (SIGTERM){saved}", file=sys.stderr)
        return int(stop.code)
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)
    save(res.matrix, out)
    e = res.energy
    total = e["reflected"] + e["absorbed"] + e["escaped"]
    print(f"{surface!r}: measured Beckmann roughness m = {surface.roughness:.4f}")
    err = res.matrix.info["stderr_max"]  # NaN with a single chunk of directions
    print(f"traced {res.rays} rays in {res.seconds:.2f} s ({res.rays_per_second:.3g} rays/s); "
          f"Q = {res.asymmetry:.3g}; largest standard error "
          f"{'n/a (one batch)' if err != err else f'{err:.3g}'}")
    print(f"energy per unit incident: reflected {e['reflected']:.4f}, absorbed "
          f"{e['absorbed']:.4f}, escaped {e['escaped']:.4f} (sum {total:.4f}); single "
          f"scattering {res.single_scatter:.4f}")
    print(f"wrote {out}: {_describe(res.matrix)}")
    return 0


def _study(args: argparse.Namespace) -> int:
    from compress import METRICS, Study, study

    if args.stability:
        return _stability(args)
    if args.small:
        raise UserError("--small applies to --stability (the reduced stability atlas); a BRDF "
                        "study takes a MODEL or --merl, with --orders and --kinds for its size")
    if args.workers is not None or args.scheduler is not None:
        raise UserError("--workers and --scheduler apply to --stability (a BRDF study runs "
                        "in this process)")
    if args.metric not in METRICS:
        raise UserError(f"--metric must be one of {', '.join(METRICS)}, got {args.metric!r}")
    kinds = _kinds(args.kinds)
    orders = _orders(args.orders)
    brdf = _source(args)  # before the folder: bad input must not leave an empty one behind
    kw: dict[str, Any] = {}
    if args.tol is not None or args.merl is not None:
        kw["tol"] = args.tol if args.tol is not None else 1e-3
    existed = Path(args.out).is_dir()
    out = _output_dir(args.out)
    try:
        rows, messages, first = [], [], None
        pairs = [(k, o) for k in kinds for o in orders]
        for k, o in _bar(pairs, args, "study", total=len(pairs)):
            part = study(brdf, k, [o], quantity=args.quantity, smooth=args.smooth, **kw)
            first = first or part
            rows += part.rows
            messages += part.messages
        st = Study(rows, first.source, first.quantity, first.sampling, messages)
        text = st.to_markdown()
        (out / "study.md").write_text(text + "\n", encoding="utf-8")
        png = st.plot(str(out / "study.png"), metric=args.metric)
    except BaseException:
        if not existed:
            with contextlib.suppress(OSError):
                out.rmdir()  # only if still empty: what was written stays
        raise
    print(text)
    print(f"\nwrote {out / 'study.md'} and {png}")
    return 0


def _stability(args: argparse.Namespace) -> int:
    from compress.stability import write_all

    if args.model is not None or args.merl is not None:
        raise UserError("--stability takes no MODEL or --merl: it measures the library itself")
    out = _output_dir(args.out)
    print(f"writing the stability atlas to {out} ({'small' if args.small else 'full'} size; "
          "the full size takes several minutes)")
    with _dask_client(args) as client:
        for md, png in write_all(out, small=args.small, client=client).values():
            print(f"wrote {md} and {png}")
    return 0


# -- the parser ------------------------------------------------------------------------------
def _add_basis(p: argparse.ArgumentParser, *, kinds: tuple[str, ...] = KINDS,
               quantity: str = "auto", quantities: tuple[str, ...] = ("auto", "f_cos", "f"),
               order: int | None = 8) -> None:
    p.add_argument("--basis", choices=kinds, default="zernike",
                   help="hemisphere Zernike functions, odd or even hemisphere harmonics, or "
                        "full-sphere harmonics (default %(default)s)")
    p.add_argument("--order", type=_order, default=order, metavar="N",
                   help="basis order, inclusive (default %(default)s)")
    if not quantities:  # the command adds its own --quantity
        return
    p.add_argument("--quantity", choices=quantities, default=quantity,
                   help="what the matrix represents: f cos(theta_i) cos(theta_o) or f; auto: "
                        "f_cos for the odd harmonics (they vanish on the horizon) and for "
                        "mirror terms, f otherwise (default %(default)s)")


def _add_source(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", nargs="?", metavar="MODEL",
                   help="an analytic model of project.models: "
                        f"{', '.join(MODEL_EXAMPLES)} (case-insensitive)")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="a model parameter, repeated: a number, a comma list (per channel), "
                        "';'-separated lists (Lafortune lobes) or a word (distribution=ggx)")
    p.add_argument("--merl", metavar="FILE.binary", help="a MERL .binary file instead of MODEL")
    p.add_argument("--tol", type=_positive, default=None,
                   help="quadrature tolerance on the coefficients, relative (default 1e-6 for "
                        "models, 1e-3 for MERL tables, which converge slowly)")


def _add_dask(p: argparse.ArgumentParser, workers: str, scheduler: str) -> None:
    """Add the exclusive --workers N / --scheduler ADDRESS (read by _dask_client)."""
    dask = p.add_mutually_exclusive_group()
    dask.add_argument("--workers", type=_count, default=None, metavar="N",
                      help=f"{workers} (needs scatmodes[distributed])")
    dask.add_argument("--scheduler", default=None, metavar="ADDRESS",
                      help=f"{scheduler}, e.g. tcp://host:8786 (needs scatmodes[distributed])")


class _Version(argparse.Action):
    """``--version``: the distribution's version, looked up only when asked for."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS,
                 default: str = argparse.SUPPRESS, help: str | None = None) -> None:
        super().__init__(option_strings, dest, nargs=0, default=default, help=help)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        # importlib.metadata (behind basis.__version__) takes ~0.1 s to import: not for --help
        from basis import __version__

        print(f"scatmodes {__version__}")  # on stdout, as argparse's own version action
        parser.exit()


def _add_progress(p: argparse.ArgumentParser) -> None:
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help="show progress bars (default: when stderr is a terminal)")


def _parser() -> argparse.ArgumentParser:
    fmt = argparse.RawDescriptionHelpFormatter
    p = _Parser(
        prog="scatmodes", formatter_class=fmt,
        description="Reflectance functions in orthonormal spherical bases: what each "
                    "representation costs and how accurate it is.",
        epilog="examples:\n  scatmodes demo\n  scatmodes project Phong --param kd=0.3 "
               "--param ks=0.4 --param n=20 --order 8 -o phong.h5\n  scatmodes study "
               "CookTorrance --param kd=0.2 --param roughness=0.3 --orders 2,4,8\n\n"
               "Errors print one line and exit with status 2. 'scatmodes COMMAND --help' "
               "for each command.")
    p.add_argument("--version", action=_Version, help="show the version and exit")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    d = sub.add_parser(
        "demo", formatter_class=fmt,
        help="bases, two models at orders 2-8, a small simulation; charts (no data needed)",
        description="Runs the main job on built-in defaults, no data files: the basis table "
                    "(sizes, orthonormality errors, evaluation cost), a study of a Phong and a "
                    "Cook-Torrance model at a few orders (resolution against error), and a "
                    "small Monte Carlo simulation of a Gaussian surface against Beckmann + "
                    "Smith. Charts go to --out.",
        epilog="examples:\n  scatmodes demo\n  scatmodes demo --out /tmp/demo --orders 2,4 "
               "--study-orders 2,4 --rays 10000")
    d.add_argument("--out", default="scatmodes-out",
                   help="output folder, created if missing (default %(default)s)")
    d.add_argument("--orders", default="2,4,8,16,32",
                   help="comma-separated orders for the basis table (default %(default)s)")
    d.add_argument("--points", type=_count, default=20_000,
                   help="random directions for timing (default %(default)s)")
    d.add_argument("--study-orders", default="2,4,8",
                   help="orders of the model study (default %(default)s)")
    d.add_argument("--rays", type=_order, default=30_000,
                   help="rays of the simulation, 0 to skip it (default %(default)s)")
    d.add_argument("--resolution", type=_count, default=64,
                   help="height-field grid points per side (default %(default)s)")
    d.add_argument("--compile-ahead", action=argparse.BooleanOptionalAction, default=True,
                   help="on a first run, compile the kernels of the later steps in a second "
                        "process while the first step runs (default: yes)")
    _add_progress(d)
    d.set_defaults(func=_demo)

    pr = sub.add_parser(
        "project", formatter_class=fmt,
        help="project an analytic model or a MERL file onto a basis, write HDF5",
        description="Projects a BRDF onto products of basis functions by adaptive "
                    "quadrature and writes the coefficient matrix with compress.save. Prints "
                    "the rule size, the estimated quadrature error, the truncation error "
                    "(relative L2 norm missed by the order) and the time.",
        epilog="examples:\n"
               "  scatmodes project Lambert --param albedo=0.5 --order 2 -o lambert.h5\n"
               "  scatmodes project Phong --param kd=0.3 --param ks=0.4 --param n=20 "
               "--basis harmonics --order 8 -o phong.h5\n"
               "  scatmodes project CookTorrance --param kd=0.2,0.3,0.4 --param roughness=0.3 "
               "--order 12 -o ct.h5\n"
               "  scatmodes project --merl gold-metallic-paint.binary --order 8 -o gold.h5\n\n"
               "models and example parameters (each given as --param KEY=VALUE):\n" + "\n".join(
                   f"  {k:17s} {v}" for k, v in MODEL_EXAMPLES.items()))
    _add_source(pr)
    _add_basis(pr)
    pr.add_argument("--method", choices=("quadrature", "montecarlo", "lstsq"),
                    default="quadrature", help="projection method (default %(default)s)")
    pr.add_argument("-o", "--output", required=True, metavar="OUT.h5", help="HDF5 file to write")
    pr.set_defaults(func=_project)

    c = sub.add_parser(
        "convert", formatter_class=fmt,
        help="convert a MERL .binary, an RGL .bsdf, an MDL .mbsdf or a measurement file to "
             "coefficients",
        description="Turns a measured material into a coefficient matrix (HDF5, "
                    "compress.save),\nchoosing by the file's content and suffix:\n"
                    "  MERL .binary  read_merl (trilinear interpolation), projected exactly "
                    "as\n                'scatmodes project --merl FILE'\n"
                    "  RGL .bsdf     read_rgl (RGL-EPFL tensor file, RGB or spectral), "
                    "projected the\n                same way (it is not reciprocal: every "
                    "ordered pair of directions\n                is sampled); --quantity auto "
                    "is f_cos, "
                    "since the stored f grows\n                like 1/cos(theta_o) at grazing "
                    "angles\n"
                    "  MDL .mbsdf    read_mbsdf (NVIDIA MDL measured BSDF, reflection part, "
                    "the MDL\n                SDK's texel-centre lookup), projected the same "
                    "way (not\n                reciprocal); --quantity auto is f_cos\n"
                    "  anything else scattered measurements (a table, CSV or Cornell .brdf, "
                    "see\n                'scatmodes fit --help'): fitted by least squares "
                    "as 'scatmodes fit\n                FILE' does with its defaults "
                    "(--quantity auto is f); for its\n                options (--format, "
                    "--wavelengths, --channels, --model,\n                "
                    "--regularization, ...) run 'scatmodes fit' itself",
        epilog="examples:\n  scatmodes convert blue-acrylic.binary --order 8 -o blue.h5\n"
               "  scatmodes convert paper_white_rgb.bsdf --order 8 -o paper.h5\n"
               "  scatmodes convert cayman.brdf --order 6 -o cayman.h5")
    c.add_argument("file", metavar="FILE",
                   help="a MERL .binary, an RGL .bsdf, an MDL .mbsdf or a measurement text "
                        "file")
    _add_basis(c)
    c.add_argument("--tol", type=_positive, default=_CONVERT_TOL,
                   help="quadrature tolerance of the projection, MERL, RGL and MBSDF "
                        "(default "
                        "%(default)s)")
    c.add_argument("--method", choices=("quadrature", "montecarlo", "lstsq"),
                   default=_CONVERT_METHOD,
                   help="projection method, MERL, RGL and MBSDF (default %(default)s)")
    c.add_argument("-o", "--output", required=True, metavar="OUT.h5", help="HDF5 file to write")
    c.set_defaults(func=_convert)

    f = sub.add_parser(
        "fit", formatter_class=fmt,
        help="fit coefficients or a compact model to measurements, write HDF5",
        description="Fits scattered measurements read by "
                    "project.measured.read_measurements. TABLE\nis one of (--format; "
                    "detected by default):\n"
                    "  table    rows theta_i phi_i theta_o phi_o (degrees) and one value or R "
                    "G B\n           (1/sr), spaces or commas, '#' comments\n"
                    "  csv      a header row naming the angle columns (theta_i, phi_i, "
                    "theta_o,\n           phi_o or aliases, a unit such as [deg] allowed), an "
                    "optional\n           weight column, one column per channel (wavelengths "
                    "like 450nm\n           make the data spectral); --angles for angle "
                    "columns without a unit\n"
                    "  cornell  the Cornell / pbrt-v2 .brdf format (wavelength count, "
                    "wavelengths,\n           then theta_i phi_i theta_o phi_o in radians "
                    "and a value\n           per wavelength)\n"
                    "--channels keeps some channels, --wavelengths interpolates spectral data "
                    "to the\ngiven wavelengths (after --channels).\n\n"
                    "Without --model: a reciprocal coefficient matrix by least squares "
                    "(project.fit),\nregularised with a penalty on high degrees whose weight "
                    "10-fold cross-validation\non the measured pairs chooses (0, the plain "
                    "fit, unless regularising predicts\nheld-out pairs clearly better). "
                    "Prints the condition number, the rank, the\nresidual, the chosen weight "
                    "and the cross-validated error, with that of a\nLambertian fit.\n\n"
                    "With --model FAMILY: a compact parametric model (project.fit_model; not "
                    "'factored',\nwhich needs a BRDF evaluable anywhere). Prints the "
                    "parameters and the l2 error\ncross-validated on held-out samples (10 "
                    "folds by default) with its standard error.\n\n"
                    "Library warnings (e.g. a fit that predicts held-out samples no better "
                    "than zero)\nprint on stderr.",
        epilog="examples:\n  scatmodes fit brick.txt --order 8 -o brick.h5\n"
               "  scatmodes fit brick.txt --order 8 --regularization 0 -o plain.h5\n"
               "  scatmodes fit paint.csv --basis harmonics --order 6 --no-isotropic "
               "--regularization 1e-6 -o paint.h5\n"
               "  scatmodes fit cayman.brdf --wavelengths 450,550,650 --order 6 -o cayman.h5\n"
               "  scatmodes fit cayman.brdf --wavelengths 450,550,650 --model lambert+ggx "
               "-o cayman-ggx.h5\n"
               "  scatmodes fit scan.csv --angles radians --channels R --model lafortune "
               "--lobes 2 --restarts 8 -o scan.h5")
    f.add_argument("table", metavar="TABLE",
                   help="measurement file: a table, CSV or Cornell .brdf")
    f.add_argument("--format", choices=("auto", *_FIT_FORMATS), default="auto",
                   help="the file's format (default %(default)s: by extension and content)")
    f.add_argument("--angles", choices=_FIT_ANGLES, default=None,
                   help="unit of CSV angle columns whose name states none (default: the unit "
                        "of the other columns, else degrees if any theta exceeds pi/2)")
    f.add_argument("--channels", type=_channel_list, default=None, metavar="C[,C...]",
                   help="keep these channels, by name or index (e.g. R,G or '450 nm' or 0,2)")
    f.add_argument("--wavelengths", type=_wavelength_list, default=None, metavar="NM[,NM...]",
                   help="spectral data: interpolate linearly to these wavelengths in nm "
                        "(e.g. 450,550,650), inside the measured range")
    _add_basis(f, kinds=("zernike", "harmonics", "harmonics-even"), quantity="f",
               quantities=("f_cos", "f"))
    f.add_argument("--isotropic", action=argparse.BooleanOptionalAction, default=None,
                   help="fit only the isotropic blocks (default: yes, unless the file states "
                        "anisotropic data)")
    f.add_argument("--reciprocal", action=argparse.BooleanOptionalAction, default=True,
                   help="fit a symmetric matrix, reciprocal by construction (default); "
                        "--no-reciprocal fits a general one, for data that 'scatmodes info' "
                        "shows are not reciprocal (about twice the unknowns)")
    f.add_argument("--regularization", type=_fit_regularization, default="auto",
                   metavar="{auto,gcv,leave-incidence-out,LAMBDA}",
                   help="how to choose the Tikhonov weight (auto: 10-fold cross-validation "
                        "on direction pairs; gcv: generalised cross-validation; "
                        "leave-incidence-out: one fold per incidence direction), or the "
                        "weight LAMBDA >= 0 itself, 0 for the plain least-squares fit "
                        "(default %(default)s)")
    f.add_argument("--penalty", choices=("identity", "degree"), default=None,
                   help="the Tikhonov penalty: identity (the L2 norm of the fit) or degree "
                        "(high degrees, see project.fit); default degree for the automatic "
                        "choices, identity for a number")
    m = f.add_argument_group(
        "compact model", "--model replaces the modal fit: --basis, --order, --quantity, "
                         "--isotropic, --regularization and --penalty do not apply")
    m.add_argument("--model", type=_family, default=None, metavar="FAMILY",
                   help=f"fit a parametric family: {', '.join(_FIT_FAMILIES)}")
    m.add_argument("--restarts", type=_count, default=None, metavar="N",
                   help="starting points of the non-linear fit, the best kept (default 4; "
                        "more for several lobes)")
    m.add_argument("--seed", type=_order, default=None,
                   help="seed of the starting points and of the folds (default 0)")
    m.add_argument("--lobes", type=_count, default=None, metavar="N",
                   help="lobes of lafortune (default 1) and dsbrdf (default 3)")
    m.add_argument("--max-nfev", type=_count, default=None, metavar="N",
                   help="function evaluations per restart (default scipy's, 100 x the "
                        "number of parameters)")
    m.add_argument("--folds", type=_order, default=None, metavar="K",
                   help="folds of the cross-validated error, 0 to skip it (default 10)")
    f.add_argument("-o", "--output", required=True, metavar="OUT.h5",
                   help=f"HDF5 file to write ({', '.join(HDF5_SUFFIXES)})")
    f.set_defaults(func=_fit, modal_defaults={n: f.get_default(n) for n in _MODAL_OPTIONS})

    s = sub.add_parser(
        "simulate", formatter_class=fmt,
        help="Monte Carlo microgeometry simulation of a Gaussian surface, write HDF5",
        description="Traces rays through a periodic Gaussian random height field "
                    "(project.microgeometry) and estimates the matrix of f cos cos. Prints "
                    "Westin's asymmetry Q, the speed and the energy balance.",
        epilog="examples:\n  scatmodes simulate --sigma 1 --tau 6.5 --order 8 --rays 1e6 "
               "-o westin.h5\n  scatmodes simulate --sigma 1 --tau 3 --material diffuse "
               "--albedo 0.8 --rays 4e6 --checkpoint run.ckpt -o rough.h5\n"
               "  scatmodes simulate --sigma 1 --tau 3 --material diffuse --albedo 0.8 "
               "--rays 8e6 --resume run.ckpt --checkpoint run.ckpt -o rough.h5")
    s.add_argument("--sigma", type=_positive, required=True, help="RMS height")
    s.add_argument("--tau", type=_positive, required=True,
                   help="correlation length (Beckmann m = 2 sigma / tau)")
    s.add_argument("--resolution", type=_count, default=128,
                   help="grid points per side (default %(default)s)")
    s.add_argument("--surface-seed", type=int, default=0,
                   help="seed of the height field (default %(default)s)")
    s.add_argument("--material", choices=("mirror", "diffuse"), default="mirror",
                   help="facet material (default %(default)s, lossless)")
    s.add_argument("--ior", type=_positive, default=None,
                   help="mirror facets: refractive index for Fresnel (default: F = 1)")
    s.add_argument("--albedo", type=_nonneg, default=None,
                   help="diffuse facets: albedo (default 1)")
    _add_basis(s, quantities=())
    s.add_argument("--quantity", type=_simulate_quantity, default="f_cos", metavar="f_cos",
                   help="what the matrix represents: only f_cos, f cos(theta_i) "
                        "cos(theta_o), which Westin's estimator gives; the written matrix "
                        "evaluates f all the same (default %(default)s)")
    s.add_argument("--rays", type=_count, default=1_000_000,
                   help="incident rays, in total when resuming (default %(default)s)")
    s.add_argument("--seed", type=int, default=0, help="seed of the rays (default %(default)s)")
    s.add_argument("--checkpoint", metavar="PATH",
                   help="save the accumulators here as it runs, at the end and when "
                        "interrupted (Ctrl-C, SIGTERM); locked against a second run")
    s.add_argument("--checkpoint-interval", type=_positive, default=None, metavar="SECONDS",
                   help="seconds between checkpoints (default 60): at most this much work is "
                        "lost if the machine fails")
    s.add_argument("--resume", metavar="PATH", help="continue from this checkpoint")
    _add_dask(s, "trace on a local Dask cluster of N worker processes (same result as "
                 "without)", "trace on the running Dask cluster of this scheduler")
    s.add_argument("-o", "--output", required=True, metavar="OUT.h5",
                   help=f"HDF5 file to write ({', '.join(HDF5_SUFFIXES)})")
    _add_progress(s)
    s.set_defaults(func=_simulate)

    st = sub.add_parser(
        "study", formatter_class=fmt,
        help="error, size and speed against order and basis; markdown table and chart",
        description="Projects the BRDF at every order of every basis kind and measures the "
                    "errors against the BRDF itself (compress.study). Prints the table as "
                    "markdown and writes DIR/study.md and DIR/study.png (error against "
                    "order, bytes and evaluation time, with the Pareto front).",
        epilog="examples:\n  scatmodes study Phong --param kd=0.3 --param ks=0.4 --param n=20 "
               "--orders 2,4,8,12\n  scatmodes study --merl blue-acrylic.binary --kinds "
               "zernike,harmonics --orders 4,8 --out blue")
    _add_source(st)
    st.add_argument("--kinds", default="zernike,harmonics",
                    help=f"comma-separated basis kinds from {', '.join(KINDS)} "
                         "(default %(default)s)")
    st.add_argument("--orders", default="2,4,8",
                    help="comma-separated orders (default %(default)s)")
    st.add_argument("--quantity", choices=("auto", "f_cos", "f"), default="auto",
                    help="represented quantity (default %(default)s: as for project)")
    st.add_argument("--smooth", choices=("half-gaussian", "lanczos", "hann"), default=None,
                    help="filter every projection (default: none)")
    st.add_argument("--metric", default="l2", help="error plotted in the chart (default "
                    "%(default)s)")
    st.add_argument("--out", default="scatmodes-out", metavar="DIR",
                    help="output folder, created if missing (default %(default)s)")
    st.add_argument("--stability", action="store_true",
                    help="instead of a BRDF study, write the stability atlas "
                         "(compress.stability: where each method breaks) to DIR")
    st.add_argument("--small", action="store_true",
                    help="with --stability: reduced sizes (about half a minute)")
    _add_dask(st, "with --stability: run its measurements as tasks on a local Dask cluster "
                  "of N worker processes", "with --stability: run them on the running Dask "
                  "cluster of this scheduler")
    _add_progress(st)
    st.set_defaults(func=_study)

    from .benchmark import add_parser as add_benchmark

    add_benchmark(sub, fmt, _add_progress, _progress, _dask_client)

    from .render import add_parser as add_render
    from .report import add_parser as add_report

    add_render(sub, fmt, _add_progress, _progress)
    add_report(sub, fmt, _add_progress, _progress)

    from .export import add_parser as add_export

    add_export(sub, fmt)

    i = sub.add_parser("info", formatter_class=fmt,
                       help="versions, threads, limits, models; or what FILE holds",
                       description="Without FILE: versions, threads, basis limits, basis kinds "
                                   "and models. With FILE: what a saved representation holds "
                                   "(basis, order, quantity, channels, sizes, errors and "
                                   "provenance; family and parameters of a fitted model or a "
                                   "hybrid's lobe) or the progress of a simulate checkpoint. "
                                   "The file is checked in full: a damaged one is an error.",
                       epilog="examples:\n  scatmodes info\n  scatmodes info phong.h5\n"
                              "  scatmodes info run.ckpt --json")
    i.add_argument("file", nargs="?", metavar="FILE", help="an .h5 file written by scatmodes "
                   "(project, fit, convert, simulate, compress.save) or a --checkpoint file")
    i.add_argument("--json", action="store_true", help="print FILE's description as JSON")
    i.set_defaults(func=_info)
    return p


def _message(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror and exc.filename:
        text = f"{exc.strerror}: {exc.filename!r}"
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split())  # one line


def main(argv: list[str] | None = None) -> int:
    """Run the ``scatmodes`` console script (its entry point); return the exit status."""
    args = _parser().parse_args(argv)
    prog = f"scatmodes {args.command}"

    def show(message, category, filename, lineno, file=None, line=None):  # noqa: ARG001
        print(f"{prog}: warning: {' '.join(str(message).split())}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.simplefilter("default")
        warnings.showwarning = show
        try:
            return args.func(args)
        except KeyboardInterrupt:
            print(f"{prog}: interrupted", file=sys.stderr)
            return 130
        except USER_ERRORS as exc:
            print(f"{prog}: error: {_message(exc)}", file=sys.stderr)
            return 2
