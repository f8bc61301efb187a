"""The numba decorators every kernel of scatmodes uses, so all are compiled and cached alike.

Public so that ``project`` and ``compress`` (and extensions) share one configuration.
"""

from functools import partial

import numba

#: Serial kernel: compiled once, cached on disk next to the module.
njit = partial(numba.njit, cache=True, fastmath=False, nogil=True)

#: Kernel parallel over its outer ``prange`` loop (points or rays).
pjit = partial(numba.njit, cache=True, fastmath=False, nogil=True, parallel=True)

prange = numba.prange
