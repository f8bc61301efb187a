"""estimate.py: the Monte Carlo estimator of the coefficient matrix -- its constants (flat
Lambertian and mirror planes against their projections, the lossless albedo), convergence,
determinism across threads and chunks, merging, checkpoints (interrupts, SIGTERM, the lock,
damaged files), memory limits, and bad input.

Monte Carlo assertions use k = 5 standard errors unless stated otherwise; seeds are fixed.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numba
import numpy as np
import pytest

from basis import HemiHarmonics, HemiZernike
from basis.jit import fma
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



@numba.njit(cache=False)
def _outer_reference(bu, c, sums):
    # m[j, k] = sum over d, in order, of (c_d bu[d, j]) sums[d, k], each term one fused
    # multiply-add: the operations the blocked, tiled kernel must perform for every entry
    nd, kk = bu.shape
    m = np.zeros((kk, kk))
    for j in range(kk):
        for k in range(kk):
            r = 0.0
            for d in range(nd):
                r = fma(c[d] * bu[d, j], sums[d, k], r)
            m[j, k] = r
    return m


@pytest.mark.parametrize("nd, kk", [(1, 1), (3, 5), (255, 7), (256, 6), (257, 10),
                                    (1031, 13)])
def test_outer_kernel_is_the_ordered_sum_of_fused_products(nd, kk):
    # tiles of _OUTER_TILE directions, blocks of four rows and of four directions, rows
    # past the end, the last tile's odd directions, signed zeros: bit for bit
    from basis.jit import run_parallel

    rng = np.random.default_rng(nd + kk)
    bu, sums = rng.normal(size=(nd, kk)), rng.normal(size=(nd, kk)) * 1e-3
    c = rng.random(nd) + 0.5
    bu[0, 0], sums[0, -1] = 0.0, -0.0
    m = np.empty((kk, kk))
    run_parallel(est_mod._outer_kernel, (kk + 3) // 4, bu, c, sums, m)
    assert np.array_equal(m.view(np.int64), _outer_reference(bu, c, sums).view(np.int64))


def test_lanes_give_the_bits_of_one_thread(rough, monkeypatch):
    # reference: the same run on one numba thread, where every chunk is traced and
    # accumulated in the calling thread; with two lanes (worker threads, see estimate._Lanes;
    # one per numba thread, here two whatever the machine) every chunk runs on a lane and
    # must give the same bits, not merely close ones
    basis = HemiZernike(4)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        ref = simulate(rough, basis, rays=24000, seed=5, chunk=150)
    finally:
        numba.set_num_threads(old)
    real, where = est_mod._chunk_delta, []

    def spy(*args):
        where.append(threading.current_thread().name)
        return real(*args)

    monkeypatch.setattr(est_mod, "_chunk_delta", spy)
    monkeypatch.setattr(est_mod, "_threads", lambda: 2)
    res = simulate(rough, basis, rays=24000, seed=5, chunk=150)
    assert len(where) == 20 and all(name.startswith("scatmodes-lane") for name in where), where
    for key in ("sum", "s2", "ns", "bounces"):
        assert np.array_equal(res._acc[key], ref._acc[key]), key
    assert not est_mod._SCRATCH._bufs  # the lanes' work arrays are released too


def test_reused_work_arrays_carry_nothing_between_runs(rough):
    # the chunks' work arrays are reused from chunk to chunk (20000 rays in chunks of 300
    # directions: the last chunk is smaller) until the run releases them; stale arrays of
    # the right shapes holding NaN and inf (as a run killed mid-chunk in this thread leaves
    # them) must be overwritten, not added to
    basis = HemiZernike(4)
    a = simulate(rough, basis, rays=20000, seed=5, chunk=300)
    assert not est_mod._SCRATCH._bufs  # released at the end of the run
    simulate(rough, HemiHarmonics(3), rays=3000, seed=9, chunk=77)
    n, k = 300 * 8, basis.size
    stale = {"dir": np.full((n, 3), np.nan), "w": np.full(n, np.inf),
             "bu": np.full((300, k), np.nan), "bv": np.full((n, k), np.nan),
             "sums": np.full((300, k), np.inf)}
    with est_mod._SCRATCH._lock:
        est_mod._SCRATCH._bufs[threading.get_ident()] = stale
    b = simulate(rough, basis, rays=20000, seed=5, chunk=300)
    assert np.array_equal(a.raw, b.raw)

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


# -- interrupts, locks and damaged checkpoints -------------------------------------------------

def _small_checkpoint(rough, path, **kw):
    args = {"surface": rough, "basis": HemiZernike(2), "seed": 5, "chunk": 50}
    res = simulate(**args, rays=2000, checkpoint=path, **kw)
    return args, res


def test_interrupt_inside_a_chunk_saves_the_last_complete_state(rough, tmp_path, monkeypatch):
    # the interrupt lands after the chunk has updated its accumulators: that half-counted
    # chunk must not reach the checkpoint (before, the accumulators were updated in place)
    basis, path = HemiZernike(2), tmp_path / "run.h5"
    full = simulate(rough, basis, rays=4000, seed=1, chunk=50)
    real, calls = est_mod._chunk, []

    def late(*args):
        real(*args)
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt

    monkeypatch.setattr(est_mod, "_chunk", late)
    with pytest.raises(KeyboardInterrupt):
        simulate(rough, basis, rays=4000, seed=1, chunk=50, checkpoint=path,
                 checkpoint_interval=3600.0)  # no periodic save: this is the final one
    monkeypatch.setattr(est_mod, "_chunk", real)
    part = simulate(rough, basis, rays=3 * 50 * 8, seed=1, chunk=50, resume=path)
    assert part.rays == 3 * 50 * 8
    rest = simulate(rough, basis, rays=4000, seed=1, chunk=50, resume=path)
    np.testing.assert_allclose(rest.raw, full.raw, rtol=0, atol=1e-13)
    assert not (tmp_path / "run.h5.lock").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]


def test_system_exit_from_a_signal_handler_saves_a_checkpoint(rough, tmp_path, monkeypatch):
    real, calls = est_mod._chunk, []

    def stop(*args):
        if len(calls) == 2:
            raise SystemExit(143)  # what a command line's SIGTERM handler raises
        calls.append(1)
        real(*args)

    monkeypatch.setattr(est_mod, "_chunk", stop)
    path = tmp_path / "run.h5"
    with pytest.raises(SystemExit):
        simulate(rough, HemiZernike(2), rays=4000, seed=1, chunk=50, checkpoint=path,
                 checkpoint_interval=3600.0)
    monkeypatch.setattr(est_mod, "_chunk", real)
    assert simulate(rough, HemiZernike(2), rays=800, seed=1, chunk=50, resume=path).rays == 800


_RUN = """
import sys
from pathlib import Path
from basis import HemiZernike
from project.microgeometry import GaussianSurface, estimate, simulate
real, count = estimate._chunk, []
def chunk(*args):
    real(*args)
    count.append(1)
    if len(count) == 3:
        Path(sys.argv[2]).write_text("3 chunks")
estimate._chunk = chunk
simulate(GaussianSurface(1.0, 6.5, resolution=64, seed=3), HemiZernike(2), rays=10**9, seed=1,
         chunk=50, checkpoint=sys.argv[1], checkpoint_interval=3600.0)
"""


def _run_until(code, args, flag, sig, cwd):
    with subprocess.Popen([sys.executable, "-c", code, *args], cwd=cwd,
                          stderr=subprocess.PIPE, text=True) as proc:
        try:
            deadline = time.time() + 120
            while not flag.exists() and proc.poll() is None and time.time() < deadline:
                time.sleep(0.05)
            assert flag.exists(), proc.stderr.read() if proc.poll() is not None else "timeout"
            proc.send_signal(sig)
            proc.wait(60)
            return proc.returncode, proc.stderr.read()
        finally:
            if proc.poll() is None:
                proc.kill()


def test_sigterm_saves_a_final_checkpoint_and_still_ends_the_process(rough, tmp_path):
    path, flag = tmp_path / "run.h5", tmp_path / "flag"
    root = Path(__file__).resolve().parents[3]
    code, err = _run_until(_RUN, [str(path), str(flag)], flag, signal.SIGTERM, root)
    assert code == -signal.SIGTERM, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flag", "run.h5"]  # no lock, no tmp
    done = simulate(rough, HemiZernike(2), rays=50 * 8, seed=1, chunk=50, resume=path)
    # the flag is written inside the third chunk: at least two are complete when it arrives
    assert done.rays >= 2 * 50 * 8 and done.rays % (50 * 8) == 0


def test_a_checkpoint_in_use_is_refused(rough, tmp_path, monkeypatch):
    path = tmp_path / "run.h5"
    monkeypatch.setattr(est_mod, "_chunk", lambda *a: pytest.fail("traced despite the lock"))
    with est_mod._locked(path):  # private: the lock a running simulate holds
        with pytest.raises(BlockingIOError, match=rf"checkpoint '.*run\.h5' is in use by "
                                                  rf"another run \(process {os.getpid()} on "):
            simulate(rough, HemiZernike(2), rays=1000, checkpoint=path)
    assert not (tmp_path / "run.h5.lock").exists()


_HOLD = """
import fcntl, os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o666)
fcntl.flock(fd, fcntl.LOCK_EX)
os.write(fd, f"{os.getpid()} elsewhere\\n".encode())
open(sys.argv[2], "w").close()
time.sleep(120)
"""


def test_lock_of_another_process_then_of_a_dead_one(rough, tmp_path):
    path, lock, flag = tmp_path / "run.h5", tmp_path / "run.h5.lock", tmp_path / "flag"
    with subprocess.Popen([sys.executable, "-c", _HOLD, str(lock), str(flag)]) as proc:
        try:
            deadline = time.time() + 30
            while not flag.exists() and time.time() < deadline:
                time.sleep(0.02)
            with pytest.raises(BlockingIOError, match=rf"in use by another run \(process "
                                                      rf"{proc.pid} on elsewhere"):
                simulate(rough, HemiZernike(2), rays=400, checkpoint=path)
        finally:
            proc.kill()  # SIGKILL: the lock file stays behind, its lock goes with the process
            proc.wait()
    assert lock.exists()
    with pytest.warns(RuntimeWarning, match=rf"taking over the lock file .* left by process "
                                            rf"{proc.pid}, which no longer holds it"):
        res = simulate(rough, HemiZernike(2), rays=400, checkpoint=path)
    assert res.rays == 400 and path.exists() and not lock.exists()


def test_lock_without_fcntl(rough, tmp_path, monkeypatch):
    monkeypatch.setattr(est_mod, "_fcntl", None)  # the O_CREAT | O_EXCL fallback
    path = tmp_path / "run.h5"
    with est_mod._locked(path):
        with pytest.raises(BlockingIOError, match="if no run is using it, delete the lock"):
            simulate(rough, HemiZernike(2), rays=400, checkpoint=path)
    assert simulate(rough, HemiZernike(2), rays=400, checkpoint=path).rays == 400
    assert not (tmp_path / "run.h5.lock").exists()


def test_files_beside_the_checkpoint_are_left_alone(rough, tmp_path):
    # before, the writability probe used the fixed name run.h5.tmp and deleted it
    other = tmp_path / "run.h5.tmp"
    other.write_text("someone else's")
    simulate(rough, HemiZernike(2), rays=400, checkpoint=tmp_path / "run.h5")
    assert other.read_text() == "someone else's"


def _resume(args, path):
    return simulate(**args, rays=2000, resume=path)


def test_damaged_checkpoints_fuzz(rough, tmp_path):
    path = tmp_path / "good.h5"
    args, res = _small_checkpoint(rough, path)
    data = path.read_bytes()
    bad = tmp_path / "bad.h5"
    rng = np.random.default_rng(14)
    outcomes = {"refused": 0, "identical": 0}

    def check(blob):
        bad.write_bytes(blob)
        try:
            back = _resume(args, bad)
        except (ValueError, OSError) as err:
            assert "\n" not in str(err) and "bad.h5" in str(err), str(err)
            outcomes["refused"] += 1
        else:
            # whatever was hit is not part of the content (padding, free space): same result
            np.testing.assert_array_equal(back.raw, res.raw)
            assert back.rays == res.rays
            outcomes["identical"] += 1

    for n in [0, 1, 8, 100, 511, len(data) // 3, len(data) // 2, len(data) - 64,
              len(data) - 1]:
        check(data[:n])
    for pos in rng.integers(0, len(data), 300):
        blob = bytearray(data)
        blob[pos] ^= int(rng.integers(1, 256))
        check(bytes(blob))
    # 94 of the 309 damaged files are refused; the other flips hit padding and free space
    assert outcomes["refused"] > 60, outcomes


def _indirections(path, key, tmp_path):
    """(label, change) pairs that make dataset ``key`` of a checkpoint take its numbers from
    elsewhere (one per indirection kind h5py can write, see project.hdf5): the numbers stay
    the same, so only the indirection itself can be the reason for a refusal."""
    import h5py

    with h5py.File(path, "r") as f:
        data = f[key][()]
    other = tmp_path / f"other-{key}.h5"
    with h5py.File(other, "w") as g:
        g[key] = data
    raw = tmp_path / f"raw-{key}.bin"
    raw.write_bytes(np.ascontiguousarray(data).tobytes())
    arr = np.asarray(data)

    def replace(make):
        def change(f):
            del f[key]
            make(f)
        return change

    def soft(f):
        f[f"stash/{key}"] = data
        f[key] = h5py.SoftLink(f"/stash/{key}")

    def virtual(f):
        layout = h5py.VirtualLayout(shape=arr.shape, dtype=arr.dtype)
        layout[...] = h5py.VirtualSource(str(other), key, shape=arr.shape)
        f.create_virtual_dataset(key, layout)

    def plugin(f):  # filter 32015, optional so that writing skips it
        dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        dcpl.set_chunk(arr.shape)
        dcpl.set_filter(32015, h5py.h5z.FLAG_OPTIONAL)
        space = h5py.h5s.create_simple(arr.shape)
        h5py.h5d.create(f.id, key.encode(), h5py.h5t.py_create(arr.dtype), space, dcpl=dcpl)
        f[key][...] = data

    out = [
        ("soft link", replace(soft)),
        ("external link", replace(lambda f: f.__setitem__(key, h5py.ExternalLink(str(other),
                                                                                  key)))),
        ("object reference", lambda f: f.create_dataset("ref", data=f[key].ref,
                                                        dtype=h5py.ref_dtype)),
        ("reference attribute", lambda f: f.attrs.__setitem__("ref", f[key].ref)),
    ]
    if arr.ndim:  # HDF5 maps, chunks and stores elsewhere only datasets with dimensions
        out += [("virtual dataset", replace(virtual)), ("plugin filter", replace(plugin)),
                ("external storage", replace(lambda f: f.create_dataset(
                    key, shape=arr.shape, dtype=arr.dtype,
                    external=[(str(raw), 0, arr.nbytes)]))),
                ("region reference", lambda f: f.create_dataset(
                    "ref", data=f[key].regionref[:1], dtype=h5py.regionref_dtype))]
    return out


_REFUSED = {"soft link": r"is a soft link to '/stash/", "external link": r"is an external link",
            "external storage": r"keeps its data in external file",
            "object reference": r"/ref holds object references",
            "reference attribute": r"the attribute /@ref holds object references",
            "virtual dataset": r"is a virtual dataset",
            "plugin filter": r"uses the HDF5 filter\(s\) \[32015\]",
            "region reference": r"/ref holds region references"}


def test_checkpoint_indirections_are_refused(rough, tmp_path):
    # every dataset of a checkpoint, through every indirection: resume refuses them all
    # (before, it followed them and used the other file's numbers; a format-2 checksum does
    # not help, as anyone can recompute it); scatmodes info refuses them too
    import h5py

    from compress.cli.info import describe

    path = tmp_path / "good.h5"
    args, _ = _small_checkpoint(rough, path)
    with h5py.File(path, "r") as f:
        keys = sorted(f)
    data = path.read_bytes()
    bad = tmp_path / "bad.h5"
    kinds, loaded = set(), []
    for key in keys:
        for label, change in _indirections(path, key, tmp_path):
            bad.write_bytes(data)
            _alter(bad, change)
            kinds.add(label)
            want = r"resume file '.*bad\.h5' is refused: .*" + _REFUSED[label]
            try:
                with pytest.raises(ValueError, match=want):
                    _resume(args, bad)
                with pytest.raises(ValueError, match=r"'.*bad\.h5' .*" + _REFUSED[label]):
                    describe(bad)
            except (AssertionError, pytest.fail.Exception) as err:
                loaded.append(f"{key} {label}: {str(err)[:300]}")
    assert kinds == set(_REFUSED)
    assert not loaded, "\n".join(loaded)


def test_checkpoint_format_attribute_of_another_type(rough, tmp_path):
    path = tmp_path / "run.h5"
    args, _ = _small_checkpoint(rough, path)
    _alter(path, lambda f: f.attrs.__setitem__("format", np.array([1, 2])))
    with pytest.raises(ValueError, match=r"resume file '.*run\.h5' is not a simulate "
                                         r"checkpoint \(its format attribute is an array of "
                                         r"int64 with shape \(2,\), expected"):
        _resume(args, path)
    _alter(path, lambda f: f.attrs.__setitem__("format", [est_mod._FORMAT.encode()] * 2))
    with pytest.raises(ValueError, match=r"run\.h5' is not a simulate checkpoint"):
        _resume(args, path)


def test_cli_resume_names_the_file_and_the_fault(tmp_path, capsys):
    import h5py

    from compress.cli import main

    sim = ["simulate", "--sigma", "1", "--tau", "6.5", "--resolution", "16", "--order", "2",
           "--rays", "2000", "--no-progress", "-o", str(tmp_path / "x.h5")]
    ckpt = tmp_path / "run.ckpt"
    assert main([*sim, "--checkpoint", str(ckpt)]) == 0
    good = ckpt.read_bytes()
    for change, match in [
        (lambda f: f.attrs.__setitem__("format", np.array([1, 2])),
         r"is not a simulate checkpoint \(its format attribute is an array of int64"),
        (_replace("sum", h5py.ExternalLink(str(tmp_path / "elsewhere.h5"), "/sum")),
         r"is refused: /sum is an external link to '.*elsewhere\.h5':'/sum'"),
    ]:
        ckpt.write_bytes(good)
        _alter(ckpt, change)
        capsys.readouterr()
        assert main([*sim, "--resume", str(ckpt)]) == 2
        err = capsys.readouterr().err
        assert re.search(r"resume file '.*run\.ckpt' " + match, err), err
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err


def _alter(path, change):
    import h5py

    with h5py.File(path, "r+") as f:
        change(f)


def _replace(key, value):
    def change(f):
        del f[key]
        f[key] = value
    return change


def _set(key, index, value):
    def change(f):
        a = f[key][()]
        a[index] = value
        f[key][...] = a
    return change


@pytest.mark.parametrize("change, match", [
    (_set("sum", (0, 0), np.nan), r"'sum' holds NaN or infinite values"),
    (_set("s2", (1, 1), -1.0), r"'s2' must be >= 0, got -1"),
    (_set("bounces", 2, -0.5), r"'bounces' must be >= 0"),
    (_replace("reflected", -3.0), r"'reflected' must be >= 0"),
    (_replace("seconds", np.inf), r"'seconds' holds NaN"),
    (_replace("rays", 1999), r"it holds 1999 rays, but directions_done = 250 at 8 rays per "
                             r"direction means 2000"),
    (lambda f: f.attrs.__setitem__("directions_done", np.int64(2**62)),
     r"it holds 2000 rays, but directions_done = 4611686018427387904"),
    (lambda f: f.attrs.__setitem__("directions_done", np.int64(-1)), r"directions_done must"),
    (_replace("chunks", 0), r"0 chunks cannot hold 250 directions"),
    (_replace("chunks", 1000), r"1000 chunks cannot hold 250 directions"),
    (_replace("n2", 1.0), r"n2 = 1 .* is impossible for 2000 rays in 5 chunks"),
    (_replace("bounces", np.full(8, 1e9)),
     r"the reflected energy per bounce count sums to 8e\+09, more than"),
    (_replace("sum", np.zeros((2, 2))), r"dataset 'sum' has shape \(2, 2\), expected \(6, 6\)"),
    (_replace("rays", "many"), r"dataset 'rays' must hold integers"),
    (_replace("n2", np.zeros(3)), r"dataset 'n2' has shape \(3,\)"),
    (lambda f: f.__delitem__("s2"), r"it lacks the dataset 's2'"),
    (lambda f: f.attrs.__delitem__("meta_targets"), r"lacks the attribute 'meta_targets'"),
    (lambda f: f.attrs.__setitem__("meta_chunk", 50.0), r"'meta_chunk' must be an integer"),
    (lambda f: f.attrs.__setitem__("meta_seeds", "five"), r"'meta_seeds' must be a list"),
    (lambda f: f.attrs.__setitem__("meta_basis", np.zeros(3)), r"'meta_basis' must be text"),
], ids=["nan", "negative-s2", "negative-bounces", "negative-reflected", "inf-seconds",
        "rays-vs-directions", "huge-directions", "negative-directions", "no-chunks",
        "many-chunks", "n2", "bounces-vs-reflected", "shape", "dtype", "scalar-shape",
        "missing-dataset", "missing-attribute", "float-chunk", "text-seeds", "array-basis"])
def test_altered_checkpoints_are_refused(rough, tmp_path, change, match):
    path = tmp_path / "run.h5"
    args, _ = _small_checkpoint(rough, path)
    # an unsigned (version 1) file: the values themselves are checked
    _alter(path, lambda f: (f.attrs.__setitem__("format", est_mod._FORMAT_1),
                            f.attrs.__delitem__("sha256")))
    _resume(args, path)  # still fine as it stands
    _alter(path, change)
    with pytest.raises(ValueError, match=r"resume file '.*run\.h5' is damaged: .*" + match):
        _resume(args, path)


def test_altered_signed_checkpoint_fails_its_checksum(rough, tmp_path):
    path = tmp_path / "run.h5"
    args, _ = _small_checkpoint(rough, path)
    _alter(path, _set("sum", (2, 3), 1e-3))  # a plausible value: only the checksum sees it
    with pytest.raises(ValueError, match=r"does not match its SHA-256 checksum"):
        _resume(args, path)


@pytest.mark.parametrize("blob, match", [
    (b"", r"is not a readable HDF5 checkpoint"),
    (b"\x89HDF\r\n\x1a\n" + bytes(200), r"is not a readable HDF5 checkpoint"),
    (b"hello", r"is not a readable HDF5 checkpoint"),
])
def test_not_a_checkpoint(rough, tmp_path, blob, match):
    path = tmp_path / "x.h5"
    path.write_bytes(blob)
    with pytest.raises(ValueError, match=match + r".*start afresh"):
        simulate(rough, HemiZernike(2), rays=400, resume=path)


def test_foreign_hdf5_is_not_a_checkpoint(rough, tmp_path):
    import h5py

    path = tmp_path / "x.h5"
    with h5py.File(path, "w") as f:
        f["data"] = np.zeros(3)
    with pytest.raises(ValueError, match=r"is not a simulate checkpoint \(its format attribute "
                                         r"is None"):
        simulate(rough, HemiZernike(2), rays=400, resume=path)


# -- memory ------------------------------------------------------------------------------------

def test_huge_basis_is_refused_before_allocating(rough, monkeypatch):
    monkeypatch.setattr(est_mod, "_chunk", lambda *a: pytest.fail("traced"))
    monkeypatch.setattr(est_mod, "_empty", lambda *a: pytest.fail("allocated"))
    with pytest.raises(MemoryError, match=r"simulate with HemiZernike\(250\) \(31626 functions: "
                                          r"10 \(31626, 31626\) accumulator matrices\).* would "
                                          r"need 84\.2 GiB, more than the limit"):
        simulate(rough, HemiZernike(250), rays=1000)


def test_memory_limit_counts_the_chunk(rough, monkeypatch):
    import basis.validation

    # HemiZernike(2): 6 functions; 32768 rays per chunk need 32768 * 36 * 8 = 9.4 MB
    monkeypatch.setattr(basis.validation, "MAX_BYTES", 5 * 2**20)
    with pytest.raises(MemoryError, match=r"32768 rays per chunk"):
        simulate(rough, HemiZernike(2), rays=1000)
    assert simulate(rough, HemiZernike(2), rays=1000, chunk=100).rays == 1000
