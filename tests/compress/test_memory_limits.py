"""Every public entry point refuses work beyond basis.validation.MAX_BYTES at once, before
allocating: one MemoryError that names the limit and says how to raise it."""

from __future__ import annotations

import time

import numpy as np
import pytest

import basis.validation
import compress
import project
from basis import HemiZernike
from project.microgeometry import GaussianSurface, simulate
from project.models import Lambert

LIMIT = r"\(basis\.validation\.MAX_BYTES\).*raise the limit: basis\.validation\.MAX_BYTES = "


def _pairs(n, seed=0):
    w = np.random.default_rng(seed).normal(size=(2 * n, 3))
    w[:, 2] = np.abs(w[:, 2])
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    return w[:n], w[n:]


def _small_limit(monkeypatch):
    monkeypatch.setattr(basis.validation, "MAX_BYTES", 2**20)


# (label, call, whether the 8 GiB limit is lowered to 1 MiB first): sizes beyond the
# limit; before, fit worked 69 s on the index arrays of 206 million unknowns and project
# sampled the BRDF for minutes before numpy's own "Unable to allocate"
CASES = [
    ("fit", lambda: project.fit(*_pairs(10), np.ones(10), HemiZernike(200), isotropic=False),
     False),
    ("project", lambda: project.project(Lambert(0.5), HemiZernike(300), isotropic=False),
     False),
    ("study", lambda: compress.study(Lambert(0.5), "zernike", [300], isotropic=False,
                                     time_eval=False), False),
    ("simulate", lambda: simulate(GaussianSurface(1.0, 6.5, resolution=16, seed=3),
                                  HemiZernike(250), rays=1000), False),
    ("render_sphere", lambda: compress.render_sphere(Lambert(0.5), [0, 0, 1.0], size=4096),
     True),
    ("select", lambda: compress.select(Lambert(0.5), 0.01), True),
    ("fit_model", lambda: project.fit_model(Lambert(0.5), "lambert+ggx"), True),
]


@pytest.mark.parametrize("label, call, small", CASES, ids=[c[0] for c in CASES])
def test_refused_at_once(monkeypatch, label, call, small):
    if small:
        _small_limit(monkeypatch)
    # the first call also loads the numba kernels of the input checks from their caches
    # (over a second on a loaded machine); the refusal itself is timed on the second
    with pytest.raises(MemoryError, match=LIMIT):
        call()
    t0 = time.perf_counter()
    with pytest.raises(MemoryError, match=LIMIT):
        call()
    seconds = time.perf_counter() - t0
    assert seconds < 1.0, f"{label} took {seconds:.2f} s to refuse"
