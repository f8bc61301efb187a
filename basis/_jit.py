"""The one numba decorator the package uses, so every kernel is cached the same way."""

from functools import partial

import numba

#: Serial kernel: compiled once, cached on disk next to the module.
njit = partial(numba.njit, cache=True, fastmath=False, nogil=True)

#: Kernel parallel over its outer ``prange`` loop (points or rays).
pjit = partial(numba.njit, cache=True, fastmath=False, nogil=True, parallel=True)

prange = numba.prange
