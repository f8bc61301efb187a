"""Fixtures for the project tests: MERL-format surrogate files made by the shared tool.

``merl_surrogate(name)`` runs ``<repo>/../shared/tools/merl_surrogate.py`` (numpy and h5py,
both dependencies of this package) once per material and session, and returns the path of
the 34,992,012-byte ``.binary`` file in a session temporary directory. Generating one file
takes about 2.5-4 s (14 s on a cold start) and about 0.9 GB of memory. Tests that use it skip
when ``../shared`` is absent or the tool cannot import its dependencies.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest


def _repo_root() -> Path:
    """The directory holding pyproject.toml, above this file."""
    for d in Path(__file__).resolve().parents:
        if (d / "pyproject.toml").is_file():
            return d
    raise RuntimeError(f"no pyproject.toml above {__file__}")


SURROGATE_TOOL = _repo_root().parent / "shared" / "tools" / "merl_surrogate.py"
SURROGATE_ZIP = _repo_root().parent / "shared" / "data" / "merl_nbrdf.zip"


@pytest.fixture(scope="session")
def merl_surrogate(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Path]:
    """``make(name) -> Path`` of a MERL-format surrogate file for MERL material ``name``.

    Files are cached for the session; ``make.seconds[name]`` records how long each took.
    """
    if not SURROGATE_TOOL.is_file() or not SURROGATE_ZIP.is_file():
        pytest.skip(f"MERL surrogate tool or data not found ({SURROGATE_TOOL}, "
                    f"{SURROGATE_ZIP}): ../shared is absent")
    outdir = tmp_path_factory.mktemp("merl")
    cache: dict[str, Path] = {}
    seconds: dict[str, float] = {}

    def make(name: str) -> Path:
        if name not in cache:
            start = time.perf_counter()
            proc = subprocess.run([sys.executable, str(SURROGATE_TOOL), name, "-o", str(outdir)],
                                  capture_output=True, text=True, timeout=600, check=False)
            seconds[name] = time.perf_counter() - start
            if proc.returncode != 0:
                if "ModuleNotFoundError" in proc.stderr or "ImportError" in proc.stderr:
                    pytest.skip(f"merl_surrogate.py lacks a dependency: "
                                f"{proc.stderr.strip().splitlines()[-1]}")
                pytest.fail(f"merl_surrogate.py {name} failed ({proc.returncode}):\n"
                            f"{proc.stderr}")
            path = outdir / f"{name}.binary"
            if not path.is_file():
                pytest.fail(f"merl_surrogate.py {name} did not write {path}:\n{proc.stdout}")
            cache[name] = path
        return cache[name]

    make.seconds = seconds  # type: ignore[attr-defined]
    return make
