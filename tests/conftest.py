"""Shared fixtures: a seeded random generator, random unit directions, a headless browser."""

from __future__ import annotations

import fcntl
import json
import os
import select as select_fd
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

#: One seed for the whole suite, so every failure reproduces exactly.
SEED = 20240611


def random_directions(rng: np.random.Generator, shape: int | tuple[int, ...] = (),
                      *, upper: bool = False) -> np.ndarray:
    """Unit vectors uniform on the sphere (or the upper hemisphere), shape ``(*shape, 3)``.

    Normalised Gaussian vectors are uniform on the sphere; ``upper=True`` reflects them into
    z >= 0, which keeps them uniform on the hemisphere.
    """
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    w = rng.normal(size=(*shape, 3))
    if upper:
        w[..., 2] = np.abs(w[..., 2])
    return w / np.linalg.norm(w, axis=-1, keepdims=True)


def twin_pairs(wi: np.ndarray, wo: np.ndarray, isotropic: bool) -> list[tuple[int, int]]:
    """Brute force: every (i, j), i < j, whose pairs are twins, i.e. repeats or reciprocal
    (w_i, w_o exchanged), and for isotropic data equal in cos theta_i, cos theta_o and
    w_i . w_o up to exchange: the reference for the fold grouping of Measurements.folds."""
    n = len(wi)
    out = []
    for i in range(n):
        for j in range(i + 1, n):
            if isotropic:
                a = sorted([wi[i, 2], wo[i, 2]]) + [wi[i] @ wo[i]]
                b = sorted([wi[j, 2], wo[j, 2]]) + [wi[j] @ wo[j]]
                same = np.allclose(a, b, rtol=0, atol=1e-12)
            else:
                same = (np.allclose(wi[i], wi[j], atol=1e-12) and
                        np.allclose(wo[i], wo[j], atol=1e-12)) or \
                       (np.allclose(wi[i], wo[j], atol=1e-12) and
                        np.allclose(wo[i], wi[j], atol=1e-12))
            if same:
                out.append((i, j))
    return out


@pytest.fixture
def rng() -> np.random.Generator:
    """A freshly seeded generator for each test (tests do not depend on their order)."""
    return np.random.default_rng(SEED)


@pytest.fixture
def unit_vectors(rng: np.random.Generator) -> Callable[..., np.ndarray]:
    """``unit_vectors(shape, upper=False)``: random unit directions drawn from ``rng``."""

    def make(shape: int | tuple[int, ...] = (), *, upper: bool = False) -> np.ndarray:
        return random_directions(rng, shape, upper=upper)

    return make


@pytest.fixture
def on_fifo(tmp_path: Path) -> Callable[..., Any]:
    """``on_fifo(reader, name="pipe")``: ``reader(path)`` on a new FIFO, in a thread.

    Returns what the reader returns and raises what it raises. A reader that opens the FIFO
    blocks until a writer appears: after 10 s the write end is opened and closed to release
    it (the reader then sees an empty file), and the test fails instead of hanging.
    """
    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs on this platform")

    def call(reader: Callable[[Path], Any], name: str = "pipe") -> Any:
        path = tmp_path / name
        os.mkfifo(path)
        out: dict[str, Any] = {}

        def target() -> None:
            try:
                out["value"] = reader(path)
            except BaseException as exc:  # noqa: BLE001 - raised again in the test's thread
                out["error"] = exc

        thread = threading.Thread(target=target, daemon=True)
        thread.start()
        thread.join(10.0)
        if thread.is_alive():
            try:
                os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))
            except OSError:  # no reader has it open: the reader is stuck elsewhere
                pass
            thread.join(10.0)
            pytest.fail(f"{getattr(reader, '__name__', reader)} blocked on the FIFO {path}")
        if "error" in out:
            raise out["error"]
        return out["value"]

    return call


#: Debian's chromium-headless-shell, which .ci/run installs
BROWSER = Path("/usr/bin/chromium-headless-shell")


class Chromium:
    """Headless Chromium driven over the DevTools protocol on a pipe (no extra package).

    ``--remote-debugging-pipe``: the browser reads JSON messages, each ended by a NUL byte,
    from file descriptor 3 and writes its answers and events to descriptor 4.
    """

    def __init__(self, profile: Path) -> None:
        a, self._write = os.pipe()
        self._read, b = os.pipe()
        # copies at descriptors >= 10 (close-on-exec), so that the dup2 onto 3 and 4 in the
        # child cannot overwrite one of them before it is copied
        to_browser = fcntl.fcntl(a, fcntl.F_DUPFD_CLOEXEC, 10)
        from_browser = fcntl.fcntl(b, fcntl.F_DUPFD_CLOEXEC, 10)
        os.close(a)
        os.close(b)

        def fds() -> None:  # in the child: the pipes at the descriptors the protocol uses
            os.dup2(to_browser, 3)  # dup2 clears close-on-exec: 3 and 4 reach the browser
            os.dup2(from_browser, 4)

        self.proc = subprocess.Popen(
            [str(BROWSER), "--no-sandbox", "--disable-gpu", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", "--no-first-run",
             f"--user-data-dir={profile}", "--remote-debugging-pipe", "about:blank"],
            close_fds=False, preexec_fn=fds,  # every other descriptor is close-on-exec
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(to_browser)
        os.close(from_browser)
        self._buf = b""
        self._id = 0
        self.events: list[dict] = []
        try:
            target = self.send("Target.createTarget", url="about:blank")["targetId"]
            self.session = self.send("Target.attachToTarget", targetId=target,
                                     flatten=True)["sessionId"]
        except BaseException:
            self.close()
            raise

    def _next(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            ready, _, _ = select_fd.select([self._read], [], [], max(0.0, deadline - time.time()))
            if not ready:
                raise TimeoutError("no answer from the browser within 60 s")
            chunk = os.read(self._read, 1 << 20)
            if not chunk:
                raise EOFError("the browser closed its pipe")
            self._buf += chunk
        raw, self._buf = self._buf.split(b"\0", 1)
        return json.loads(raw)

    def wait(self, method: str) -> dict:
        deadline = time.time() + 60
        while True:
            m = self._next(deadline)
            if m.get("method") == method:
                return m
            self.events.append(m)

    def send(self, method: str, *, session: str | None = None, **params) -> dict:
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        os.write(self._write, json.dumps(msg).encode() + b"\0")
        deadline = time.time() + 60
        while True:
            m = self._next(deadline)
            if m.get("id") == self._id:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m["result"]
            self.events.append(m)

    def page(self, method: str, **params) -> dict:
        return self.send(method, session=self.session, **params)

    def errors(self) -> list[dict]:
        """The events so far that report an error: exceptions, console errors, log errors."""
        return [e for e in self.events
                if e.get("method") == "Runtime.exceptionThrown"
                or (e.get("method") == "Runtime.consoleAPICalled"
                    and e["params"]["type"] in ("error", "assert"))
                or (e.get("method") == "Log.entryAdded"
                    and e["params"]["entry"]["level"] == "error")]

    def close(self) -> None:
        try:
            self.send("Browser.close")
        except (OSError, EOFError, TimeoutError):
            self.proc.kill()  # our own child, by its handle
        finally:
            os.close(self._write)
            os.close(self._read)
            self.proc.wait(30)


@pytest.fixture
def browser(tmp_path):
    if not BROWSER.is_file():
        pytest.skip(f"no headless browser at {BROWSER} (Debian package "
                    "chromium-headless-shell)")
    profile = Path(tempfile.mkdtemp(dir=tmp_path))
    b = Chromium(profile)
    try:
        yield b
    finally:
        b.close()
        shutil.rmtree(profile, ignore_errors=True)
