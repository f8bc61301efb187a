"""Start-up of the command line and the lazy packages: ``scatmodes --version`` and every
``--help`` answer without importing the numerical stack, and the lazy public names of
``basis``, ``project`` and ``compress`` are the objects of the modules that define them.

Each check runs in a fresh interpreter (a subprocess), since this test session has long
imported numpy and numba itself; the reference for what was imported is ``sys.modules`` of
that interpreter, and for the version string ``importlib.metadata``.
"""

from __future__ import annotations

import importlib.metadata
import json
import subprocess
import sys
import textwrap

import pytest

#: What a start-up must not load: each costs 0.1-1 s to import (numba alone ~0.3 s).
HEAVY = ("numba", "numpy", "scipy", "h5py", "matplotlib", "pyshtools", "ducc0", "tqdm")

#: Runs argv lists through compress.cli.main, then prints the heavy modules loaded (JSON).
PROBE = textwrap.dedent("""
    import contextlib, io, json, sys
    {prelude}
    from compress.cli import main
    outputs = []
    for argv in json.loads(sys.argv[1]):
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            try:
                status = main(argv)
            except SystemExit as stop:
                status = stop.code
        outputs.append([status, out.getvalue()])
    heavy = sorted(m for m in {heavy!r} if m in sys.modules)
    print(json.dumps({{"outputs": outputs, "heavy": heavy}}))
""")


def probe(argvs: list[list[str]], prelude: str = "") -> dict:
    code = PROBE.format(prelude=prelude, heavy=HEAVY)
    r = subprocess.run([sys.executable, "-c", code, json.dumps(argvs)], capture_output=True,
                       text=True, timeout=120, check=False)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.splitlines()[-1])


def commands() -> list[str]:
    from compress.cli.commands import _parser

    sub = next(a for a in _parser()._actions if a.dest == "command")
    return sorted(sub.choices)


def test_version_imports_nothing_heavy():
    got = probe([["--version"]])
    assert got["heavy"] == []
    (status, out), = got["outputs"]
    assert status == 0
    assert out == f"scatmodes {importlib.metadata.version('scatmodes')}\n"


def test_help_of_every_command_imports_nothing_heavy():
    names = commands()
    assert {"demo", "project", "fit", "simulate", "study", "info", "benchmark"} <= set(names)
    got = probe([["--help"]] + [[name, "--help"] for name in names])
    assert got["heavy"] == []
    for (status, out), argv in zip(got["outputs"], [["--help"]] + [[n] for n in names],
                                   strict=True):
        assert status == 0, argv
        assert out.startswith("usage: scatmodes"), (argv, out[:80])


def test_the_probe_sees_a_heavy_import():
    # negative control: the same probe after importing numpy reports it
    assert probe([["--version"]], prelude="import numpy")["heavy"] == ["numpy"]


def test_python_m_prints_the_version():
    r = subprocess.run([sys.executable, "-m", "compress.cli", "--version"], capture_output=True,
                       text=True, timeout=120, check=False)
    assert (r.returncode, r.stdout) == (0, f"scatmodes {importlib.metadata.version('scatmodes')}\n")


def test_parser_kinds_are_the_librarys():
    # the parser spells out basis.KINDS so that building it imports no numba
    import basis
    from compress.cli.commands import KINDS

    assert KINDS == basis.KINDS


def test_importing_the_packages_is_light():
    code = ("import sys, basis, project, compress, compress.cli\n"
            f"print(sorted(m for m in {HEAVY!r} if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120, check=True)
    assert r.stdout.strip() == "[]"


@pytest.mark.parametrize("package, module, name", [
    ("basis", "basis.sh", "SphericalHarmonics"),
    ("basis", "basis.kinds", "KINDS"),
    ("project", "project.quadrature", "project"),
    ("project", "project.reciprocity", "reciprocity"),
    ("compress", "compress.truncate", "truncate"),
    ("compress", "compress.study", "study"),
    ("compress", "compress.selection", "select"),
])
def test_lazy_names_are_the_defining_modules_objects(package, module, name):
    # the reference is the object in the module that defines it; a submodule of the same
    # name (compress.truncate) must not hide the function once that module is imported
    pkg = importlib.import_module(package)
    mod = importlib.import_module(module)
    assert getattr(pkg, name) is getattr(mod, name)
    assert name in dir(pkg) and name in pkg.__all__


def test_shadowed_function_survives_a_fresh_submodule_import():
    # in a fresh interpreter the module is imported first, then the package name is read
    code = ("import compress.truncate, compress.hybrid, project.reciprocity, compress, project\n"
            "print(type(compress.truncate).__name__, type(compress.hybrid).__name__, "
            "type(project.reciprocity).__name__)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120, check=True)
    assert r.stdout.split() == ["function"] * 3


def test_every_public_name_resolves():
    for package in ("basis", "project", "compress"):
        pkg = importlib.import_module(package)
        for name in pkg.__all__:
            assert getattr(pkg, name) is not None, (package, name)
        assert pkg.__version__ == importlib.metadata.version("scatmodes")


def test_submodules_load_on_first_use_and_unknown_names_raise():
    import basis
    import project

    assert project.microgeometry.__name__ == "project.microgeometry"
    with pytest.raises(AttributeError, match="module 'basis' has no attribute 'Nope'"):
        basis.Nope  # noqa: B018
    assert basis.SphericalHarmonics(4).size == 25  # (lmax + 1)^2
