"""Input validation shared by the public wrappers of every package of scatmodes.

Validation happens only at the public boundary; kernels assume clean, contiguous float64.
Messages follow one pattern: "<arg> must <rule>, got <value>". The module is public so that
``project``, ``compress`` and user code built on ``basis`` check their inputs the same way.
"""

from __future__ import annotations

import operator

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Largest array (in bytes) that a single call may allocate before it refuses and asks the
#: caller to work in chunks. 8 GiB leaves room for the caller's own arrays on a 24 GiB machine.
MAX_BYTES = 8 * 2**30

#: Tolerance on the length of direction vectors: | |w| - 1 | must not exceed this.
#: Accepted vectors are renormalised inside the kernels, so the result does not depend on it.
UNIT_ATOL = 1e-6


def nonneg_int(value: object, name: str, *, maximum: int | None = None, why: str = "") -> int:
    """Return ``value`` as an int after checking that it is an integer in [0, maximum]."""
    if isinstance(value, bool):
        raise TypeError(f"{name} must be an integer, got {value!r}")
    try:
        n = operator.index(value)  # rejects 2.0, "2", None
    except TypeError:
        raise TypeError(f"{name} must be an integer, got {value!r}") from None
    if n < 0:
        raise ValueError(f"{name} must be >= 0, got {n}")
    if maximum is not None and n > maximum:
        raise ValueError(f"{name} must be <= {maximum}{why}, got {n}")
    return n


def choice(value: object, name: str, allowed: tuple[str, ...]) -> str:
    """Check that ``value`` is one of the strings in ``allowed``."""
    if not isinstance(value, str) or value not in allowed:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, allowed))}, got {value!r}")
    return value


def check_bytes(nbytes: float, what: str) -> None:
    """Refuse an allocation larger than :data:`MAX_BYTES` with a message saying what to do."""
    if nbytes > MAX_BYTES:
        raise MemoryError(
            f"{what} would need {nbytes / 2**30:.3g} GiB, more than the limit of "
            f"{MAX_BYTES / 2**30:.3g} GiB (basis.validation.MAX_BYTES); "
            "use a lower order or work on fewer points at a time"
        )


def as_directions(
    dirs: ArrayLike, name: str = "dirs", *, upper: bool = False
) -> NDArray[np.float64]:
    """Validate an array of unit vectors, shape (..., 3), and return it as C-contiguous float64.

    Parameters
    ----------
    dirs : (..., 3) array_like of float
        Unit vectors. Lengths within :data:`UNIT_ATOL` of 1 are accepted (and renormalised by
        the kernels); anything else is rejected rather than silently normalised, because a
        non-unit "direction" is almost always a bug upstream (angles in degrees, a missing
        normalisation).
    name : str
        Argument name used in error messages.
    upper : bool
        If True, also require z >= 0 (within rounding, -1e-12).
    """
    try:
        d = np.asarray(dirs, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be an array of floats with shape (..., 3), "
                        f"got {type(dirs).__name__}") from None
    if d.ndim == 0 or d.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got shape {d.shape}")
    d = np.ascontiguousarray(d)
    if d.size == 0:
        return d
    bad = ~np.isfinite(d).all(axis=-1)
    if bad.any():
        first = np.flatnonzero(bad)[0]
        raise ValueError(f"{name} must be finite: {int(bad.sum())} of {bad.size} vectors hold "
                         f"NaN or inf (first at flat index {first})")
    norm = np.sqrt(np.einsum("...i,...i->...", d, d))
    off = np.flatnonzero(np.abs(norm - 1.0) > UNIT_ATOL)
    if off.size:
        k = off[0]
        hint = "zero-length vectors have no direction" if norm.flat[k] == 0 else \
            "normalise them first (w / np.linalg.norm(w, axis=-1, keepdims=True))"
        raise ValueError(f"{name} must be unit vectors: {off.size} of {norm.size} are not "
                         f"(first at flat index {k}, norm {norm.flat[k]:.6g}); {hint}")
    if upper:
        below = np.flatnonzero(d[..., 2] < -1e-12)
        if below.size:
            k = below[0]
            raise ValueError(f"{name} must lie in the upper hemisphere z >= 0: {below.size} of "
                             f"{norm.size} do not (first at flat index {k}, z = "
                             f"{d.reshape(-1, 3)[k, 2]:.6g})")
    return d


def broadcast_batch(wi: NDArray, wo: NDArray) -> tuple[int, ...]:
    """Return the broadcast batch shape of two (..., 3) direction arrays, or a clear ValueError."""
    try:
        return tuple(np.broadcast_shapes(wi.shape[:-1], wo.shape[:-1]))
    except ValueError:
        raise ValueError(f"wi and wo must have broadcastable batch shapes, got {wi.shape} and "
                         f"{wo.shape}") from None
