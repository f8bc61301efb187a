"""Shared fixtures: a seeded random generator and random unit directions."""

from __future__ import annotations

import os
import threading
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
