"""The machine a benchmark ran on: CPU model, the SIMD features that matter, vector width.

Every script in this folder prints :func:`header` once at the top and names :func:`tag` in
its table headers, so that a row copied elsewhere still says which machine it came from.

The vector width is the one numba's LLVM compiles for (its target CPU and features, which
``NUMBA_CPU_NAME`` and ``NUMBA_CPU_FEATURES`` override, else the host's): 8 doubles with
avx512f, 4 with avx, 2 otherwise. The kernels' explicit vectors (``basis.jit.LANES``) are
two registers of that width (16, 8 or 4 doubles); LLVM's loop vectoriser may choose less
than the register (256 bits on Intel's AVX-512 server cores, which LLVM tunes with
``prefer-256-bit``, except in kernels marked with ``basis.jit.wide_loops``).
"""

from __future__ import annotations

import os
import platform
from functools import cache

#: The features printed: what decides the width and whether products and sums may fuse.
FEATURES = ("avx2", "fma", "avx512f")


def _cpuinfo() -> tuple[str, set[str]]:
    # (model name, flags) of the first processor in /proc/cpuinfo; ("", set()) elsewhere
    model, flags = "", set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                key = key.strip()
                if key == "model name" and not model:
                    model = value.strip()
                elif key == "flags" and not flags:
                    flags = set(value.split())
                if model and flags:
                    break
    except OSError:
        pass
    return model, flags


@cache
def machine() -> dict:
    """CPU model, features (True/False for each of :data:`FEATURES`), numba's target and width.

    Keys: ``model``, ``cores``, ``features`` (as /proc/cpuinfo reports them, or as LLVM
    detects them where there is no /proc/cpuinfo), ``llvm_cpu`` and ``llvm_features``
    (numba's target: the CPU name and those of :data:`FEATURES` it enables), ``doubles``
    (vector width in doubles of that target) and ``lanes`` (the width of the kernels'
    explicit vectors, ``basis.jit.LANES``).
    """
    import llvmlite.binding as llvm
    from numba.core import config

    model, flags = _cpuinfo()
    model = model or platform.processor() or platform.machine()
    host = llvm.get_host_cpu_features()
    cpu = config.CPU_NAME or llvm.get_host_cpu_name()
    target = config.CPU_FEATURES if config.CPU_FEATURES is not None else host.flatten()
    enabled = {f[1:] for f in target.split(",") if f.startswith("+")}
    if not target:  # NUMBA_CPU_FEATURES="": the named CPU's own features, not listed here
        doubles = None
    else:
        doubles = 8 if "avx512f" in enabled else 4 if "avx" in enabled else 2
    from basis.jit import LANES

    return {
        "model": model,
        "cores": os.cpu_count() or 1,
        "features": {f: (f in flags) if flags else bool(host.get(f)) for f in FEATURES},
        "llvm_cpu": cpu,
        "llvm_features": {f: f in enabled for f in FEATURES} if target else None,
        "doubles": doubles,
        "lanes": LANES,
    }


def tag() -> str:
    """A short name of the machine for table headers: model, features, width."""
    m = machine()
    feats = "+".join(f for f in FEATURES if m["features"][f]) or "no avx2/fma/avx512f"
    width = (f"vector registers of {m['doubles']} doubles" if m["doubles"]
             else f"numba cpu {m['llvm_cpu']}")
    return f"{m['model']}, {feats}, {width}"


def header() -> str:
    """One line for the top of a benchmark's output."""
    m = machine()
    have = ", ".join(f"{f} {'yes' if m['features'][f] else 'no'}" for f in FEATURES)
    if m["llvm_features"] is None:
        llvm_on = "its own features"
    else:
        llvm_on = "+".join(f for f in FEATURES if m["llvm_features"][f]) or "none of them"
    width = f"{m['doubles']} doubles per vector register" if m["doubles"] else "width not listed"
    return (f"# machine: {m['model']}, {m['cores']} cores; {have}; numba targets "
            f"{m['llvm_cpu']} ({llvm_on}): {width}; the kernels' explicit vectors hold "
            f"{m['lanes']} doubles")
