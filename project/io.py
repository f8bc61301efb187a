"""Atomic file output shared by every writer of the library.

The writers are those of MERL files, checkpoints, HDF5 coefficient files and charts: write to
a temporary file beside the target, flush it to disk, then rename it over the target, so a
crash never leaves a half-written file under the real name.

Temporary files are named ``.<target name>.scatmodes-tmp-<pid>-<random><suffix>``: unique
across processes and threads (``tempfile.mkstemp`` creates them with ``O_EXCL``), and
recognisable, so that those a killed process could not remove (SIGKILL, power loss) are
deleted by the next write to the same directory once they are older than
:data:`STALE_SECONDS`. SIGTERM and SIGINT arriving while a write is in progress remove the
temporary file before the process ends.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = ["STALE_SECONDS", "atomic_path", "temporary_name"]

#: Temporary files of this library older than this (seconds, by modification time) are
#: left-overs of a killed writer: a single write never takes a day.
STALE_SECONDS = 86400.0

_MARK = ".scatmodes-tmp-"
# mkstemp's random part: 8 characters of [a-z0-9_]
_STALE = re.compile(r"\..+" + re.escape(_MARK) + r"[0-9]+-[a-z0-9_]{8}")

#: the signals whose default action would end the process with the temporary file in place
_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGINT") if hasattr(signal, name))


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def temporary_name(path: str | os.PathLike, suffix: str = "") -> Path:
    """Create an empty, uniquely named temporary file beside ``path`` and return its path.

    The name follows this module's pattern (see the module notes), so a copy left behind by
    a killed process is cleaned up by a later :func:`atomic_path` in the same directory.
    The caller owns the file and must remove or rename it.

    Parameters
    ----------
    path : str or os.PathLike
        The target the temporary file stands in for; its directory must exist.
    suffix : str
        Ending of the temporary name (default: the target's suffix, which matplotlib needs
        to pick the format).

    Raises
    ------
    FileNotFoundError
        If the directory does not exist.
    OSError
        If the directory is not writable.
    """
    target = Path(path)
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"directory {str(folder)!r} does not exist (for {str(target)!r})")
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}{_MARK}{os.getpid()}-",
                               suffix=suffix or target.suffix, dir=folder)
    os.close(fd)
    return Path(tmp)


def _remove_stale(folder: Path, now: float) -> None:
    """Delete this library's temporary files in ``folder`` older than STALE_SECONDS."""
    with contextlib.suppress(OSError), os.scandir(folder) as entries:
        for e in entries:
            if not (e.name.startswith(".") and _MARK in e.name and _STALE.match(e.name)):
                continue
            # a vanished or unreadable entry is some other writer's business
            with contextlib.suppress(OSError):
                if e.is_file(follow_symlinks=False) and \
                        now - e.stat(follow_symlinks=False).st_mtime > STALE_SECONDS:
                    os.unlink(e.path)


@contextlib.contextmanager
def _cleanup_on_signals(tmp: Path) -> Iterator[None]:
    """Remove ``tmp`` if SIGTERM or SIGINT would end the process while the body runs.

    Each signal's previous handler is chained: a Python handler runs as before (an exception
    it raises, such as KeyboardInterrupt, unwinds through :func:`atomic_path`, which removes
    the file), an ignored signal stays ignored, and for the default action the file is
    removed, the default restored and the signal raised again, so the process still ends
    by it. Handlers can only be installed from the main thread; other threads write without.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous: dict[int, Any] = {}

    def handler(signum: int, frame: Any) -> Any:
        prev = previous[signum]
        if callable(prev):
            return prev(signum, frame)
        if prev == signal.SIG_IGN:
            return None
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        signal.signal(signum, signal.SIG_DFL)
        signal.raise_signal(signum)
        return None  # not reached for SIGTERM and SIGINT under their default action

    try:
        for sig in _SIGNALS:
            previous[sig] = signal.signal(sig, handler)
    except ValueError:  # not the main interpreter
        pass
    try:
        yield
    finally:
        for sig, prev in previous.items():
            # only if nothing replaced ours meanwhile (nested writes restore in LIFO order)
            if signal.getsignal(sig) is handler:
                signal.signal(sig, signal.SIG_DFL if prev is None else prev)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path in the target's directory; rename it to ``path`` on success.

    The caller writes the temporary file (by name, so h5py and matplotlib can too). On a
    clean exit it is fsynced, given the permissions ``open(path, "w")`` would give (0666 less
    the umask, where mkstemp alone gives 0600) and renamed over ``path``; on an exception, or
    SIGTERM / SIGINT while the body runs, it is removed. The directory must exist and be
    writable. Temporary files of this library older than :data:`STALE_SECONDS` in that
    directory (left by a killed process) are removed first.
    """
    target = Path(path)
    tmp = temporary_name(target, suffix)
    _remove_stale(tmp.parent, time.time())
    try:
        with _cleanup_on_signals(tmp):
            yield tmp
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
            os.chmod(tmp, 0o666 & ~_umask())
            os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
