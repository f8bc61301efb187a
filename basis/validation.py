"""Input validation shared by the public wrappers of every package of scatmodes.

Validation happens only at the public boundary; kernels assume clean, contiguous float64.
Messages follow one pattern: "<arg> must <rule>, got <value>". The module is public so that
``project``, ``compress`` and user code built on ``basis`` check their inputs the same way.
"""

from __future__ import annotations

import operator

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .jit import njit

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
            "use a lower order or work on fewer points at a time, or, on a machine with "
            "the memory, raise the limit: basis.validation.MAX_BYTES = <bytes>"
        )


def as_float(value: ArrayLike, name: str) -> NDArray[np.float64]:
    """Return ``value`` as a float64 array, refusing complex numbers with a TypeError.

    numpy would drop the imaginary part with only a ``ComplexWarning``; a complex input is
    almost always a bug upstream (a square root of a negative number, an FFT's output), so it
    is refused, zero imaginary parts included: pass ``.real`` to mean the real part. Other
    conversion failures (text, ragged lists) are left to numpy's TypeError or ValueError.
    """
    a = value if isinstance(value, np.ndarray) else np.asarray(value)
    if a.dtype.kind == "c":
        raise TypeError(f"{name} must be real (float), got {a.dtype} values; numpy would drop "
                        f"their imaginary part: pass {name}.real if that is what you mean")
    return np.asarray(a, dtype=np.float64)


def dask_client(client: object, caller: str) -> None:
    """Check that ``client`` is a running ``dask.distributed.Client``.

    ``caller`` (e.g. ``"simulate"``) names the function in the messages. Raises
    ImportError with the install command when dask.distributed is missing, TypeError for
    another object and ValueError for a closed client.
    """
    try:
        from distributed import Client
    except ImportError:
        raise ImportError(f"{caller}(client=...) needs dask.distributed, which is not "
                          "installed: pip install 'scatmodes[distributed]'") from None
    if not isinstance(client, Client):
        raise TypeError(f"client must be a dask.distributed.Client, got "
                        f"{type(client).__name__}")
    if client.status != "running":
        raise ValueError(f"client must be connected to a running cluster, its status is "
                         f"{client.status!r}: create a new Client")


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
        d = as_float(dirs, name)
    except TypeError as exc:
        if "must be real" in str(exc):  # complex values: as_float's message
            raise
        raise TypeError(f"{name} must be an array of floats with shape (..., 3), "
                        f"got {type(dirs).__name__}") from None
    except ValueError:
        raise TypeError(f"{name} must be an array of floats with shape (..., 3), "
                        f"got {type(dirs).__name__}") from None
    if d.ndim == 0 or d.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got shape {d.shape}")
    d = np.ascontiguousarray(d)
    if d.size == 0:
        return d
    # one compiled pass finds the first offender of each kind; the messages below need only
    # it and the counts (numpy's isfinite/einsum passes cost ~20x more on large batches)
    n_bad, first_bad, n_off, first_off, norm_off, n_below, first_below = _scan(
        d.reshape(-1, 3), UNIT_ATOL, -1e-12 if upper else -np.inf)
    count = d.size // 3
    if n_bad:
        raise ValueError(f"{name} must be finite: {n_bad} of {count} vectors hold "
                         f"NaN or inf (first at flat index {first_bad})")
    if n_off:
        hint = "zero-length vectors have no direction" if norm_off == 0 else \
            "normalise them first (w / np.linalg.norm(w, axis=-1, keepdims=True))"
        raise ValueError(f"{name} must be unit vectors: {n_off} of {count} are not "
                         f"(first at flat index {first_off}, norm {norm_off:.6g}); {hint}")
    if n_below:
        raise ValueError(f"{name} must lie in the upper hemisphere z >= 0: {n_below} of "
                         f"{count} do not (first at flat index {first_below}, z = "
                         f"{d.reshape(-1, 3)[first_below, 2]:.6g})")
    return d


@njit
def _scan(d, atol, zmin):  # pragma: no cover - compiled
    # d (n, 3): counts and first flat index of non-finite, non-unit and below-zmin vectors
    n_bad = n_off = n_below = 0
    first_bad = first_off = first_below = -1
    norm_off = 0.0
    for k in range(d.shape[0]):
        x, y, z = d[k, 0], d[k, 1], d[k, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            n_bad += 1
            if first_bad < 0:
                first_bad = k
            continue
        r = np.sqrt(x * x + y * y + z * z)
        if abs(r - 1.0) > atol:
            n_off += 1
            if first_off < 0:
                first_off, norm_off = k, r
        if z < zmin:
            n_below += 1
            if first_below < 0:
                first_below = k
    return n_bad, first_bad, n_off, first_off, norm_off, n_below, first_below


def broadcast_batch(wi: NDArray, wo: NDArray) -> tuple[int, ...]:
    """Return the broadcast batch shape of two (..., 3) direction arrays, or a clear ValueError."""
    try:
        return tuple(np.broadcast_shapes(wi.shape[:-1], wo.shape[:-1]))
    except ValueError:
        raise ValueError(f"wi and wo must have broadcastable batch shapes, got {wi.shape} and "
                         f"{wo.shape}") from None
