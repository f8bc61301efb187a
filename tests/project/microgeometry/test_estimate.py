"""estimate.py: the Monte Carlo estimator of the coefficient matrix -- its constants (flat
Lambertian and mirror planes against their projections, the lossless albedo), convergence,
determinism across threads and chunks, merging, checkpoints, and bad input.

Monte Carlo assertions use k = 5 standard errors unless stated otherwise; seeds are fixed.
"""

from __future__ import annotations

import warnings

import numba
import numpy as np
import pytest

from basis import HemiHarmonics, HemiZernike
from project import project
from project.microgeometry import Diffuse, GaussianSurface, Heightfield, merge, simulate, trace
from project.microgeometry import estimate as est_mod  # to patch its private _chunk
from project.models import GlossyPaint, Lambert
from tests.project.mc import K_SIGMA, direction

# -- estimator constants ----------------------------------------------------------------------

@pytest.mark.parametrize("incident", ["cosine", "uniform"])
@pytest.mark.parametrize("basis", [HemiHarmonics(3), HemiZernike(4)], ids=repr)
def test_flat_diffuse_plane_is_lambert(incident, basis):
    plane = Heightfield(np.zeros((4, 4)), 1.0, material=Diffuse(0.6))
    res = simulate(plane, basis, rays=160000, seed=1, incident=incident, chunk=1000)
    ref = project(Lambert(0.6), basis, quantity="f_cos").matrix  # what simulate estimates
    err = np.abs(res.matrix.matrix - ref)
    assert np.all(err <= K_SIGMA * res.stderr + 1e-12), np.max(err / res.stderr)
    assert res.energy == pytest.approx({"reflected": 0.6, "absorbed": 0.4, "escaped": 0.0},
                                       abs=1e-12)


def test_flat_mirror_matches_closed_form_projection():
    basis = HemiZernike(6)
    res = simulate(Heightfield(np.zeros((4, 4)), 1.0), basis, rays=160000, seed=2, chunk=1000)
    with warnings.catch_warnings():  # the closed form converges to 2.6e-12, not 1e-14
        warnings.filterwarnings("ignore", "the mirror term", RuntimeWarning)
        ref = project(GlossyPaint(0.0, 1.0), basis, quantity="f_cos", nodes=(64, 128)).matrix
    err = np.abs(res.matrix.matrix - ref)
    assert np.all(err <= K_SIGMA * res.stderr + 1e-12), np.max(err / res.stderr)


def test_lossless_matrix_albedo_is_one(rough):
    # albedo(wi) cos(theta_i) = z is a degree-2 Zernike polynomial, so the matrix albedo is
    # exact up to Monte Carlo error; error bound from the entry standard errors (treated as
    # independent) divided by cos(theta_i)
    basis = HemiZernike(6)
    res = simulate(rough, basis, rays=200000, seed=3, chunk=500)
    g = basis.moments("none")
    for theta in [0.0, 30.0, 45.0, 60.0, 75.0]:
        wi = direction(theta, 40)
        b = basis.eval(wi)
        se = np.sqrt(np.sum((b[:, None] * res.stderr * g[None, :]) ** 2)) / wi[2]
        a = float(res.matrix.albedo(wi))
        assert abs(a - 1.0) < K_SIGMA * se + 1e-12, (theta, a, se)
    assert res.energy["reflected"] == 1.0


# -- convergence, determinism, merging --------------------------------------------------------

def test_q_falls_like_inverse_sqrt_rays(rough):
    basis = HemiZernike(4)
    n = np.array([4000, 16000, 64000, 256000])
    q = [simulate(rough, basis, rays=int(k), seed=11).asymmetry for k in n]
    slope = np.polyfit(np.log(n), np.log(q), 1)[0]
    # one realisation per N: the fitted slope scatters by ~0.05 around -1/2
    assert -0.62 < slope < -0.38, (slope, q)


def test_deterministic_across_threads_and_chunks(rough):
    basis = HemiZernike(4)
    a = simulate(rough, basis, rays=20000, seed=5, chunk=300)
    b = simulate(rough, basis, rays=20000, seed=5, chunk=300)
    assert np.array_equal(a.raw, b.raw)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        c = simulate(rough, basis, rays=20000, seed=5, chunk=300)
    finally:
        numba.set_num_threads(old)
    assert np.array_equal(a.raw, c.raw)  # per-ray streams, fixed summation order
    d = simulate(rough, basis, rays=20000, seed=5, chunk=700)
    np.testing.assert_allclose(d.raw, a.raw, rtol=0, atol=1e-12)  # summation order only
    e = simulate(rough, basis, rays=20000, seed=6, chunk=300)
    assert not np.array_equal(a.raw, e.raw)


def test_merge_is_additive(rough):
    basis = HemiHarmonics(3)
    a = simulate(rough, basis, rays=8000, seed=1, chunk=250)
    b = simulate(rough, basis, rays=24000, seed=2, chunk=250)
    m = merge(a, b)
    assert m.rays == 32000
    np.testing.assert_allclose(m.raw, (8000 * a.raw + 24000 * b.raw) / 32000, rtol=1e-13,
                               atol=1e-15)
    assert a.merge(b).rays == 32000
    with pytest.raises(ValueError, match="different seeds, seed 1 repeats"):
        merge(a, a)
    with pytest.raises(ValueError, match="must share the basis"):
        merge(a, simulate(rough, HemiZernike(2), rays=1000, seed=3))


# -- checkpoints ------------------------------------------------------------------------------

def test_checkpoint_resume_equals_uninterrupted(rough, tmp_path):
    basis = HemiZernike(4)
    path = tmp_path / "run.h5"
    full = simulate(rough, basis, rays=24000, seed=7, chunk=250)
    half = simulate(rough, basis, rays=12000, seed=7, chunk=250, checkpoint=path)
    assert path.is_file() and half.rays == 12000
    rest = simulate(rough, basis, rays=24000, seed=7, chunk=250, resume=path, checkpoint=path)
    assert rest.rays == 24000
    np.testing.assert_allclose(rest.raw, full.raw, rtol=0, atol=1e-13)
    np.testing.assert_allclose(rest.stderr, full.stderr, rtol=1e-10)


def test_interrupted_run_loses_at_most_one_interval(rough, tmp_path, monkeypatch):
    basis = HemiZernike(2)
    path = tmp_path / "run.h5"
    real = est_mod._chunk  # private: the per-chunk worker, patched to interrupt the run
    calls = []

    def flaky(*args):
        if len(calls) == 5:
            raise KeyboardInterrupt
        calls.append(1)
        real(*args)

    monkeypatch.setattr(est_mod, "_chunk", flaky)
    with pytest.raises(KeyboardInterrupt):
        # interval 1e-9 s: a checkpoint after every chunk
        simulate(rough, basis, rays=8000, seed=1, chunk=100, checkpoint=path,
                 checkpoint_interval=1e-9)
    monkeypatch.setattr(est_mod, "_chunk", real)
    done = simulate(rough, basis, rays=800 * 5 // 8 * 8, seed=1, chunk=100, resume=path)
    assert done.rays == 5 * 100 * 8  # the five finished chunks survived
    assert not (tmp_path / "run.h5.tmp").exists()


@pytest.mark.parametrize("change, match", [
    ({"seed": 8}, "different seed"),
    ({"basis": HemiZernike(3)}, "different basis"),
    ({"surface": GaussianSurface(1.0, 6.5, resolution=64, seed=4)}, "different surface"),
    ({"incident": "uniform"}, "different incident"),
])
def test_incompatible_resume(rough, tmp_path, change, match):
    path = tmp_path / "run.h5"
    args = {"surface": rough, "basis": HemiZernike(2), "seed": 7}
    simulate(**args, rays=1000, checkpoint=path)
    args.update(change)
    with pytest.raises(ValueError, match=match):
        simulate(**args, rays=2000, resume=path)


def test_unwritable_checkpoint_is_refused_before_tracing(rough, tmp_path, monkeypatch):
    monkeypatch.setattr(est_mod, "_chunk", lambda *a: pytest.fail("traced before checking"))
    with pytest.raises(ValueError, match="checkpoint must be a writable file path"):
        simulate(rough, HemiZernike(2), rays=1000, checkpoint=tmp_path / "no" / "run.h5")
    with pytest.raises(ValueError, match="checkpoint must be a writable file path"):
        simulate(rough, HemiZernike(2), rays=1000, checkpoint=tmp_path)
    with pytest.raises(FileNotFoundError, match="resume must name an existing checkpoint"):
        simulate(rough, HemiZernike(2), rays=1000, resume=tmp_path / "missing.h5")


# -- bad input --------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, exc, match", [
    ({"rays": 0}, ValueError, r"rays must be > 0, got 0"),
    ({"rays": -5}, ValueError, r"rays must be > 0, got -5"),
    ({"rays": 1e4}, TypeError, r"rays must be an integer, got 10000.0"),
    ({"rays": 10, "seed": -1}, ValueError, r"seed must be in \[0, 2\*\*64\), got -1"),
    ({"rays": 10, "incident": "sun"}, ValueError, r"incident must be 'cosine' or 'uniform'"),
    ({"rays": 10, "targets": 0}, ValueError, r"targets must be > 0, got 0"),
    ({"rays": 10, "checkpoint_interval": 0}, ValueError, r"checkpoint_interval must be > 0"),
])
def test_bad_simulate_arguments(rough, kwargs, exc, match):
    with pytest.raises(exc, match=match):
        simulate(rough, HemiZernike(2), **kwargs)


def test_bad_simulate_objects(rough):
    with pytest.raises(TypeError, match="surface must be a Heightfield"):
        simulate(np.zeros((4, 4)), HemiZernike(2), rays=10)
    with pytest.raises(TypeError, match="basis must be a basis object"):
        simulate(rough, "zernike", rays=10)
    with pytest.raises(ValueError, match="wi must be one unit vector with z > 0"):
        trace(rough, [0.6, 0.0, -0.8], 10)
    with pytest.raises(ValueError, match=r"rays must be > 0, got 0"):
        trace(rough, [0.0, 0.0, 1.0], 0)
