"""Atomic file output shared by every writer of the library.

The writers are those of MERL files, checkpoints, HDF5 coefficient files and charts: write to
a temporary file beside the target, flush it to disk, then rename it over the target, so a
crash never leaves a half-written file under the real name.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["atomic_path"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path in the target's directory; rename it to ``path`` on success.

    The caller writes the temporary file (by name, so h5py and matplotlib can too). On a
    clean exit it is fsynced, given the permissions ``open(path, "w")`` would give (0666 less
    the umask, where mkstemp alone gives 0600) and renamed over ``path``; on an exception it
    is removed. The directory must exist and be writable.
    """
    target = Path(path)
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"directory {str(folder)!r} does not exist (for {str(target)!r})")
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix or target.suffix,
                               dir=folder)
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
