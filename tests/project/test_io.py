"""project.io.atomic_path: the target appears whole or not at all, with the permissions
open() would give, and no temporary file is left behind: not on exceptions, not when the
writer is killed by SIGTERM or SIGINT, and stale ones of killed writers are cleaned up."""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from project.io import atomic_path


def _leftovers(folder):
    return [p.name for p in folder.iterdir() if p.name.startswith(".")]


def test_success_replaces_the_target(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp != target
        tmp.write_text("new")
        assert target.read_text() == "old"  # not yet visible
    assert target.read_text() == "new"
    assert _leftovers(tmp_path) == []
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~mask


def test_failure_keeps_the_old_file(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError, match="boom"), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert _leftovers(tmp_path) == []


def test_missing_directory(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"), \
            atomic_path(tmp_path / "nowhere" / "x.h5"):
        pass


def test_temporary_names_are_unique_and_carry_the_pid(tmp_path):
    target = tmp_path / "out.h5"
    with atomic_path(target) as a, atomic_path(target) as b:
        assert a != b
        for t in (a, b):
            assert t.name.startswith(f".out.h5.scatmodes-tmp-{os.getpid()}-")
            assert t.suffix == ".h5"  # matplotlib picks the format from it
        a.write_text("a")
        b.write_text("b")
    assert target.read_text() == "a"  # the outer write renames last
    assert _leftovers(tmp_path) == []


def test_signal_handlers_are_restored(tmp_path):
    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    with atomic_path(tmp_path / "x") as tmp:
        assert signal.getsignal(signal.SIGTERM) is not before[signal.SIGTERM]
        tmp.write_text("x")
    assert {s: signal.getsignal(s) for s in before} == before


def test_other_threads_write_without_handlers(tmp_path):
    seen = []

    def work():
        with atomic_path(tmp_path / "t") as tmp:
            seen.append(signal.getsignal(signal.SIGTERM))
            tmp.write_text("t")

    before = signal.getsignal(signal.SIGTERM)
    th = threading.Thread(target=work)
    th.start()
    th.join()
    assert seen == [before] and (tmp_path / "t").read_text() == "t"


def test_stale_temporaries_are_removed(tmp_path):
    day = 86400
    old = tmp_path / ".a.h5.scatmodes-tmp-123-abcd_e12.h5"
    fresh = tmp_path / ".b.png.scatmodes-tmp-456-zz99yy88.png"
    foreign = tmp_path / ".c.h5.tmp"  # not this library's pattern: never touched
    mine_elsewhere = tmp_path / "sub" / ".d.scatmodes-tmp-1-abcdefgh"
    mine_elsewhere.parent.mkdir()
    for p in (old, fresh, foreign, mine_elsewhere):
        p.write_text("x")
    t = time.time() - day - 60
    for p in (old, foreign, mine_elsewhere):
        os.utime(p, (t, t))
    with atomic_path(tmp_path / "new.txt") as tmp:
        tmp.write_text("new")
    assert not old.exists()
    assert fresh.exists() and foreign.exists() and mine_elsewhere.exists()


# project/io.py loaded on its own: importing the package (numba, scipy) would take seconds
_WRITER = """
import importlib.util, sys, time
from pathlib import Path
spec = importlib.util.spec_from_file_location("io_under_test", "project/io.py")
io = importlib.util.module_from_spec(spec)
spec.loader.exec_module(io)
with io.atomic_path(sys.argv[1]) as tmp:
    tmp.write_text("half")
    Path(sys.argv[2]).write_text(str(tmp))  # tell the parent the write is under way
    time.sleep(60)
"""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_killed_writer_leaves_no_temporary(tmp_path, sig):
    target = tmp_path / "out.txt"
    target.write_text("old")
    flag = tmp_path / "started"
    root = Path(__file__).resolve().parents[2]
    # a shell that starts the suite in the background hands its children SIGINT ignored;
    # the child restores the default, as a program started in a terminal has it
    with subprocess.Popen([sys.executable, "-c", _WRITER, str(target), str(flag)], cwd=root,
                          stderr=subprocess.PIPE,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)) \
            as proc:
        try:
            deadline = time.time() + 60
            # the flag is complete once it holds the temporary's name (not merely exists)
            while not (flag.exists() and flag.read_text()) and proc.poll() is None \
                    and time.time() < deadline:
                time.sleep(0.02)
            assert flag.exists(), proc.stderr.read() if proc.poll() is not None else "timeout"
            tmp = Path(flag.read_text())
            assert tmp.exists()
            proc.send_signal(sig)
            code = proc.wait(30)
        finally:
            if proc.poll() is None:
                proc.kill()
    # the process still dies by the signal (SIGINT: Python re-raises it after an unhandled
    # KeyboardInterrupt, so that the shell sees it)
    assert code == -sig
    assert not tmp.exists()
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt", "started"]
