"""materials.py: bad arguments of the facet materials (Mirror, Diffuse, Dielectric, MicroBRDF,
the Material check of a surface). Their optics are checked where they act: the facet-event
kernels in test_paths.py, MicroBRDF sampling in test_scatter.py, tracing in test_trace.py,
test_wavefront.py and test_scene.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from project.brdf import BRDF
from project.microgeometry import (
    Dielectric,
    Diffuse,
    GaussianSurface,
    Heightfield,
    MicroBRDF,
    Mirror,
    trace,
)
from project.models import Lambert
from tests.project.mc import direction


def test_bad_materials():
    with pytest.raises(TypeError, match="material must be a Material"):
        Heightfield(np.zeros((2, 2)), 1.0, material="mirror")
    with pytest.raises(ValueError, match=r"albedo must be <= 1, got 1.5"):
        Diffuse(1.5)
    with pytest.raises(ValueError, match=r"ior must be finite and > 0, got 0"):
        Mirror(0)
    with pytest.raises(ValueError, match=r"k must be 0 when ior is None"):
        Mirror(k=1.0)


@pytest.mark.parametrize("args, exc, match", [
    ((0.0,), ValueError, r"ior must be finite and > 0, got 0.0"),
    ((np.nan,), ValueError, r"ior must be finite and > 0, got nan"),
    ((-1.5,), ValueError, r"ior must be finite and > 0"),
    (("glass",), TypeError, r"ior must be a number, got 'glass'"),
    ((1.5, -0.1), ValueError, r"absorption must be finite and >= 0, got -0.1"),
    ((1.5, np.inf), ValueError, r"absorption must be finite and >= 0, got inf"),
])
def test_bad_dielectric(args, exc, match):
    with pytest.raises(exc, match=match):
        Dielectric(*args)


class _Negative(BRDF):
    def _eval(self, wi, wo):
        return np.full((wi.shape[0], 1), -0.1)


class _NegativeSomewhere(BRDF):
    """Non-negative on the construction grid (azimuth 0 incidence), negative elsewhere."""

    def _eval(self, wi, wo):
        return np.where(wi[:, 1:2] > 0.5, -1.0, 0.3)


def test_bad_micro_brdf():
    with pytest.raises(TypeError, match="brdf must be a BRDF .* got str"):
        MicroBRDF("lambert")
    with pytest.raises(ValueError, match="brdf must have 1 channel, got 3"):
        MicroBRDF(Lambert([0.1, 0.2, 0.3]))
    with pytest.raises(ValueError, match="brdf must be non-negative, got values down to -0.1"):
        MicroBRDF(_Negative())
    surf = GaussianSurface(1.0, 2.0, resolution=16, seed=1,
                           material=MicroBRDF(_NegativeSomewhere()))
    with pytest.raises(ValueError, match="brdf must be finite and non-negative, got -1.0"):
        trace(surf, direction(80, 90), 2000, seed=1)
