"""Shared fixtures: a seeded random generator and random unit directions."""

from __future__ import annotations

from collections.abc import Callable

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
