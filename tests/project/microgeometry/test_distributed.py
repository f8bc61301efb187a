"""simulate(client=...) on a Dask LocalCluster: the same bits as the local run whatever the
completion order, after a worker dies mid-run, and when a distributed checkpoint is resumed
locally; clear errors without dask.distributed, with a closed client and for a bad scheduler
address on the command line.

One module-scoped cluster of 2 worker processes (1 thread each, no dashboard) serves every
test; the specimen and ray counts are small so the file runs in seconds once the workers are
up.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

from basis import HemiZernike  # noqa: E402
from compress.cli import commands as cli  # noqa: E402
from project.microgeometry import GaussianSurface, merge, simulate  # noqa: E402
from project.microgeometry import estimate as est_mod  # noqa: E402 - to hook its _fold

#: 40 chunks of 50 directions x 8 rays: enough tasks to be in flight when a worker dies
RUN = {"rays": 16000, "seed": 11, "chunk": 50}


@pytest.fixture(scope="module")
def surface() -> GaussianSurface:
    """A small rough mirror surface (32 x 32 points)."""
    return GaussianSurface(1.0, 4.0, resolution=32, seed=5)


@pytest.fixture(scope="module")
def basis() -> HemiZernike:
    """A small basis: 15 functions."""
    return HemiZernike(4)


@pytest.fixture(scope="module")
def client():
    """A LocalCluster of 2 worker processes, 1 thread each, no dashboard."""
    # the scheduler's HTTP server on a free port, not 8787: another cluster on the machine
    # would make distributed warn, an error under this suite's filterwarnings
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None,
                                  scheduler_kwargs={"dashboard_address": ":0"}) as cluster, \
            distributed.Client(cluster) as c:
        c.wait_for_workers(2, timeout=120)
        yield c


@pytest.fixture(scope="module")
def local(surface, basis):
    """The reference: the same run in this process."""
    return simulate(surface, basis, **RUN)


def assert_same_bits(a, b):
    assert np.array_equal(a.matrix.matrix, b.matrix.matrix)
    for key in a._acc:  # private: every accumulator, not only the matrix
        if key != "seconds":  # wall time
            assert np.array_equal(a._acc[key], b._acc[key]), key


def test_same_matrix_as_the_local_run(client, surface, basis, local):
    res = simulate(surface, basis, client=client, **RUN)
    assert_same_bits(res, local)
    assert res.rays == local.rays == 16000 and res._acc["chunks"] == 40
    assert set(res.meta["workers"]) <= set(client.scheduler_info()["workers"])
    assert res.meta["workers"]
    # a different seed gives different bits: the comparison above can fail
    other = simulate(surface, basis, client=client, **dict(RUN, seed=12))
    assert not np.array_equal(other.matrix.matrix, local.matrix.matrix)
    # merged runs keep every contributing worker; local runs list none
    assert merge(res, other).meta["workers"] == sorted({*res.meta["workers"],
                                                        *other.meta["workers"]})
    assert "workers" not in local.meta


class _Scrambled:
    """as_completed that hands out each batch of finished futures reversed, and twice."""

    seen: list[str] = []
    real = distributed.as_completed  # before the test replaces it

    def __init__(self):
        self._real = type(self).real()

    def add(self, future):
        self._real.add(future)

    def __iter__(self):
        import time

        while not self._real.is_empty():
            time.sleep(0.05)  # let several tasks finish, so that batches hold more than one
            batch = list(self._real.next_batch(block=True))[::-1]
            for fut in batch + batch:  # a duplicate, as from a retried task
                type(self).seen.append(fut.key)
                yield fut


def test_completion_order_and_duplicates_do_not_matter(client, surface, basis, local,
                                                       monkeypatch):
    _Scrambled.seen = []
    monkeypatch.setattr(distributed, "as_completed", _Scrambled)
    res = simulate(surface, basis, client=client, **RUN)
    order = [int(k.rsplit("-", 1)[1]) for k in _Scrambled.seen]
    first = list(dict.fromkeys(order))  # first appearance of each task
    # 40 chunks, 2 workers: 4 tasks per worker of 5 chunks each
    assert sorted(first) == list(range(8))
    assert first != sorted(first), "the scrambled order was the natural one: nothing tested"
    assert len(order) == 16  # each task handed out twice
    assert_same_bits(res, local)


def test_distributed_checkpoint_resumes_locally(client, surface, basis, local, tmp_path,
                                               monkeypatch):
    ckpt = tmp_path / "run.ckpt"
    real, folds = est_mod._fold, []

    def stop_after_15(acc, delta):
        if len(folds) == 15:
            raise KeyboardInterrupt
        real(acc, delta)
        folds.append(1)

    monkeypatch.setattr(est_mod, "_fold", stop_after_15)
    with pytest.raises(KeyboardInterrupt):
        simulate(surface, basis, client=client, checkpoint=ckpt, **RUN)
    monkeypatch.setattr(est_mod, "_fold", real)
    assert not ckpt.with_name("run.ckpt.lock").exists()
    res = simulate(surface, basis, resume=ckpt, checkpoint=ckpt, **RUN)
    assert res._acc["chunks"] == 40
    assert_same_bits(res, local)
    # and the other way: a local checkpoint of 20 chunks finished on the cluster
    part = simulate(surface, basis, checkpoint=tmp_path / "half.ckpt", **dict(RUN, rays=8000))
    assert part._acc["chunks"] == 20
    res = simulate(surface, basis, resume=tmp_path / "half.ckpt", client=client, **RUN)
    assert_same_bits(res, local)


def test_client_closed_mid_run_keeps_the_checkpoint(client, surface, basis, local, tmp_path,
                                                    monkeypatch):
    ckpt = tmp_path / "run.ckpt"
    other = distributed.Client(client.scheduler_info()["address"])
    real, folds = est_mod._fold, []

    def fold_then_close(acc, delta):
        real(acc, delta)
        folds.append(1)
        if len(folds) == 5:
            other.close()

    monkeypatch.setattr(est_mod, "_fold", fold_then_close)
    with pytest.raises(RuntimeError, match="resume from the checkpoint with a running client"):
        simulate(surface, basis, client=other, checkpoint=ckpt, **RUN)
    monkeypatch.setattr(est_mod, "_fold", real)
    assert 5 <= len(folds) < 40
    res = simulate(surface, basis, resume=ckpt, **RUN)
    assert_same_bits(res, local)


def test_missing_dask_is_a_clear_error(surface, basis, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed fails
    with pytest.raises(ImportError, match=r"pip install 'scatmodes\[distributed\]'"):
        simulate(surface, basis, client=object(), **RUN)
    status = cli.main(["simulate", "--sigma", "1", "--tau", "4", "--resolution", "16",
                       "--order", "2", "--rays", "400", "--workers", "2", "-o",
                       str(tmp_path / "x.h5")])
    err = capsys.readouterr().err.strip()
    assert status == 2
    assert err == ("scatmodes simulate: error: --workers and --scheduler need "
                   "dask.distributed, which is not installed: pip install "
                   "'scatmodes[distributed]'")
    assert not (tmp_path / "x.h5").exists()


def test_bad_client_is_refused_before_tracing(client, surface, basis, monkeypatch):
    monkeypatch.setattr(est_mod, "_chunk_delta", lambda *a: pytest.fail("traced"))
    with pytest.raises(TypeError, match="client must be a dask.distributed.Client, got str"):
        simulate(surface, basis, client="tcp://127.0.0.1:8786", **RUN)
    closed = distributed.Client(client.scheduler_info()["address"])
    closed.close()
    with pytest.raises(ValueError, match="status is 'closed': create a new Client"):
        simulate(surface, basis, client=closed, **RUN)


@pytest.mark.parametrize("address", ["tcp://127.0.0.1:1", "no-port"])
def test_bad_scheduler_address_is_one_line_exit_2(address, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(cli, "_CONNECT_TIMEOUT", 1)
    status = cli.main(["simulate", "--sigma", "1", "--tau", "4", "--resolution", "16",
                       "--order", "2", "--rays", "400", "--scheduler", address, "-o",
                       str(tmp_path / "x.h5")])
    err = capsys.readouterr().err.strip()
    assert status == 2
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith(f"scatmodes simulate: error: --scheduler '{address}': cannot "
                          "connect ("), err
    assert not (tmp_path / "x.h5").exists()


def test_cli_workers_and_scheduler_match_the_local_command(client, tmp_path, capsys,
                                                          monkeypatch):
    import contextlib

    from compress import load

    common = ["simulate", "--sigma", "1", "--tau", "4", "--resolution", "16", "--order", "2",
              "--rays", "30000", "--seed", "2"]  # 4 chunks of the default size
    assert cli.main([*common, "-o", str(tmp_path / "a.h5")]) == 0
    address = client.scheduler_info()["address"]
    assert cli.main([*common, "--scheduler", address, "-o", str(tmp_path / "b.h5")]) == 0
    # --workers: the module's cluster stands in for the one the command would start
    made = []

    @contextlib.contextmanager
    def local_cluster(**kwargs):
        made.append(kwargs)
        yield address

    monkeypatch.setattr(distributed, "LocalCluster", local_cluster)
    assert cli.main([*common, "--workers", "3", "-o", str(tmp_path / "c.h5")]) == 0
    assert made == [{"n_workers": 3, "threads_per_worker": 1, "processes": True,
                     "dashboard_address": None}]
    capsys.readouterr()
    a = load(tmp_path / "a.h5").matrix
    assert np.array_equal(a, load(tmp_path / "b.h5").matrix)
    assert np.array_equal(a, load(tmp_path / "c.h5").matrix)



def test_lost_scattered_scene_is_scattered_again(client, surface, basis, local, monkeypatch):
    # Dask keeps one replica of scattered data once no queued task needs the others, and a
    # worker dying with it cancels every task that needs it; cancelling the scattered
    # futures after the first fold does the same, deterministically
    real_scatter, scattered = client.scatter, []

    def scatter(data, **kwargs):
        fut = real_scatter(data, **kwargs)
        scattered.append(fut)
        return fut

    real, folds = est_mod._fold, []

    def fold_then_lose(acc, delta):
        real(acc, delta)
        folds.append(1)
        if len(folds) == 1:
            client.cancel(scattered[:2], force=True)

    monkeypatch.setattr(client, "scatter", scatter)
    monkeypatch.setattr(est_mod, "_fold", fold_then_lose)
    res = simulate(surface, basis, client=client, **RUN)
    assert len(scattered) >= 4, "the scene was never scattered again: nothing tested"
    assert len(folds) == 40  # every chunk folded once
    assert_same_bits(res, local)

# last in the module: the worker that replaces the victim is still starting when it ends
def test_same_matrix_after_a_worker_dies_mid_run(client, surface, basis, local, monkeypatch):
    victim = sorted(client.scheduler_info()["workers"])[0]
    real, folds, busy = est_mod._fold, [], []

    def fold_then_kill(acc, delta):
        real(acc, delta)
        folds.append(1)
        if len(folds) == 1:  # the first chunk is in: the other tasks are queued or running
            # its chunks running, or done and not yet folded (Dask recomputes those)
            busy.extend(k for k in [*client.processing([victim])[victim],
                                    *client.has_what([victim])[victim]]
                        if k.startswith("scatmodes-simulate-") and not k.endswith("-0"))
            client.run(os._exit, 1, workers=[victim], on_error="ignore")

    monkeypatch.setattr(est_mod, "_fold", fold_then_kill)
    res = simulate(surface, basis, client=client, **RUN)
    assert busy, "the victim had no task when it was killed: nothing tested"
    assert len(folds) == 40  # every chunk folded once: none lost, none counted twice
    assert_same_bits(res, local)
    # the victim did die (its nanny starts a new worker at another address)
    assert victim not in client.scheduler_info()["workers"]
