"""Specimens shared by the microgeometry test modules (module-scoped: built once per module)."""

from __future__ import annotations

import pytest

from project.microgeometry import GaussianSurface


@pytest.fixture(scope="module")
def rough() -> GaussianSurface:
    """Westin's specimen in units of sigma: sigma/tau = 10/65, m = 0.3077; 64 x 64 points."""
    return GaussianSurface(1.0, 6.5, resolution=64, seed=3)


@pytest.fixture(scope="module")
def big() -> GaussianSurface:
    """1024^2 points (period 256 tau): the specimen's own slope-histogram noise is ~2 %."""
    return GaussianSurface(1.0, 6.5, resolution=1024, seed=7)
