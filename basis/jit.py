"""The numba decorators every kernel of scatmodes uses, so all are compiled and cached alike.

Public so that ``project`` and ``compress`` (and extensions) share one configuration.

Caching and editing the source: numba checks a cached kernel against the file that defines
it, not against the files of the kernels it calls (and inlines). After editing a module whose
kernels others call (``project/microgeometry/_paths.py`` under every tracer, for instance),
remove the caches (``make clean-cache``), or the callers keep running the old code. Installed
packages are not affected: installing a version rewrites every file.
"""

from functools import partial

import numba
import numpy as np

#: Serial kernel: compiled once, cached on disk next to the module.
njit = partial(numba.njit, cache=True, fastmath=False, nogil=True)

#: Kernel parallel over its outer ``prange`` loop (points or rays).
pjit = partial(numba.njit, cache=True, fastmath=False, nogil=True, parallel=True)

prange = numba.prange


def writable(a: np.ndarray) -> np.ndarray:
    """Return ``a``, or a copy if it is read-only, before it goes to a kernel.

    numba compiles (and caches) a separate specialisation of a kernel for read-only arrays,
    which rule points, broadcast views and frozen inputs are; copying an (n, 3) input is far
    cheaper than a second compilation on a cold start, and keeps one cache entry per kernel.
    """
    return a if a.flags.writeable else a.copy()
