"""scatter.py: one MicroBRDF facet event (FacetSampler). On a flat plane every ray meets one
facet, so the simulated BRDF is the microscale BRDF itself: its matrix must equal the
quadrature projection and its albedo the model's, for each kind of sampler (cosine, the
Beckmann / GGX / Phong / Blinn-Phong lobes, the ideal-mirror branch).

Monte Carlo assertions use k = 5 standard errors; seeds are fixed.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from basis import HemiHarmonics, HemiZernike
from project import project
from project.microgeometry import Diffuse, Heightfield, MicroBRDF, simulate, trace
from project.models import BlinnPhong, CookTorrance, GlossyPaint, Lambert, Phong
from tests.project.mc import K_SIGMA, direction


def _flat(material) -> Heightfield:
    return Heightfield(np.zeros((4, 4)), 1.0, material=material)


def _projected(brdf, basis) -> np.ndarray:
    with warnings.catch_warnings():  # sharp lobes in a low order: the truncation warning
        warnings.filterwarnings("ignore", "the expansion of", RuntimeWarning)
        warnings.filterwarnings("ignore", "the mirror term", RuntimeWarning)
        return project(brdf, basis, quantity="f_cos").matrix  # what simulate estimates


def test_flat_micro_lambert_equals_diffuse_and_lambert():
    basis = HemiHarmonics(3)
    micro = simulate(_flat(MicroBRDF(Lambert(0.6))), basis, rays=160000, seed=1, chunk=1000)
    diff = simulate(_flat(Diffuse(0.6)), basis, rays=160000, seed=1, chunk=1000)
    ref = project(Lambert(0.6), basis, quantity="f_cos").matrix
    err = np.abs(micro.matrix.matrix - ref)
    assert np.all(err <= K_SIGMA * micro.stderr + 1e-12), np.max(err / micro.stderr)
    # same streams, different tangent frames: statistically equal (independent-error bound)
    err = np.abs(micro.matrix.matrix - diff.matrix.matrix)
    assert np.all(err <= K_SIGMA * np.hypot(micro.stderr, diff.stderr) + 1e-12)
    # one event of factor exactly 0.6 > roulette threshold: the energy balance is exact
    assert micro.energy == pytest.approx({"reflected": 0.6, "absorbed": 0.4, "escaped": 0.0},
                                         abs=1e-12)


@pytest.mark.parametrize("brdf", [
    CookTorrance(0.0, 0.2, ior=1.5),          # Beckmann lobe sampler, dielectric Fresnel
    CookTorrance(0.1, 0.3, "ggx"),            # GGX sampler + Lambert
    Phong(0.2, 0.6, 30),                      # lobe about the mirror direction
    BlinnPhong(0.3, 0.5, 40),                 # half-vector lobe
    GlossyPaint(0.5, 0.3),                    # Lambert + ideal mirror (delta branch)
], ids=repr)
def test_flat_micro_glossy_reproduces_projection(brdf):
    # The key independent reference: one facet event on a flat plane is the microscale BRDF
    # itself, so the simulated matrix must equal the quadrature projection within
    # K_SIGMA = 5 batch-means standard errors per entry (largest observed deviation over the
    # 5 x 28 x 28 entries: 3.6 sigma).
    basis = HemiZernike(6)
    res = simulate(_flat(MicroBRDF(brdf)), basis, rays=160000, seed=2, chunk=1000)
    ref = _projected(brdf, basis)
    err = np.abs(res.matrix.matrix - ref)
    assert np.all(err <= K_SIGMA * res.stderr + 1e-12), np.max(err / res.stderr)


@pytest.mark.parametrize("theta", [0.0, 60.0, 85.0])
def test_flat_micro_albedo_is_model_albedo(theta):
    brdf = CookTorrance(0.0, 0.2)  # F = 1: albedo 0.99 ... 0.87, single scattering
    p = trace(_flat(MicroBRDF(brdf)), direction(theta, 30), 40000, seed=3)
    a = float(brdf.albedo(direction(theta, 30), n_theta=256, n_phi=512))
    se = p.weights.std() / np.sqrt(p.weights.size)
    assert abs(p.weights.mean() - a) < K_SIGMA * se, (p.weights.mean(), a, se)
    assert np.all(p.bounces == 1) and p.lost.sum() == 0
