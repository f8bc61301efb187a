"""The Monte Carlo estimator of the coefficient matrix (Westin et al. 1992, eqs 17 and 25).

Constants. The estimators printed by Westin, Arvo & Torrance (1992, sec. 3, eqs 16-17, and
sec. 4.6, eq 25) are written for rho and leave out the density of the incident directions
(their sec. 2.5 represents rho cos(theta_i) cos(theta_r) but omits this from the formulas);
the constants below are derived here for hemisphere-orthonormal bases. For incident flux
uniform over the mean plane, a ray arriving from U leaves in direction V with energy R, and
E[R delta(V - .)] = f(U, V) cos(theta_o). The coefficient of q = f cos_i cos_o is

    M_jk = int_H int_H b_j(U) f(U, V) cos_i cos_o b_k(V) dU dV
         = E_U[ b_j(U) cos_i / p(U) * E[R b_k(V) | U] ],

so per traced ray: M += c(U) R b(U) b(V)^T / N with c = pi for cosine-distributed U
(p = cos_i / pi) and c = 2 pi cos_i for U uniform in solid angle (p = 1 / (2 pi)). With
full-sphere harmonics and Westin's odd completion across the equator (sec. 2.5) these
become 4 pi and 8 pi cos_i: the full-sphere coefficient of a function completed as odd in
each argument is twice its hemisphere integral in each argument. Every basis of this
library is orthonormal on its own domain and q vanishes below the horizon, so c is the
same for all of them. Check: a flat Lambertian plane of albedo a gives
pi a E[b(U)] E[b(V)]^T = project(Lambert(a), basis) (verified by the test suite).

Amortisation (Westin et al. 1992, sec. 4.6, eq 25): b(U) is evaluated once per incident
direction, shared by ``targets`` rays aimed at different points of the period; the exit sums
S_U = sum R b(V) are formed per direction, and one (D, K)^T (D, K) product per chunk adds
them to M.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import os
import signal
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from basis import Basis, CoefficientMatrix, validation
from basis.jit import fma, loopjit, run_parallel, wide_loops
from basis.validation import check_bytes, dask_client

from ..io import atomic_path, temporary_name
from ._checks import _positive_int, _seed
from ._paths import MAX_BOUNCES, MAX_STEPS, incident_directions
from .scene import Scene
from .surface import Heightfield
from .trace import _run

__all__ = ["SimulationResult", "merge", "simulate"]

#: energy leaving after 1, 2, ..., BOUNCE_BINS - 1 and >= BOUNCE_BINS facet interactions
BOUNCE_BINS = 8

#: checkpoints written now: version 1 plus a SHA-256 of their content (attribute sha256)
_FORMAT = "scatmodes-microgeometry-checkpoint-2"
#: version 1 (no checksum) is still read; its values are checked all the same
_FORMAT_1 = "scatmodes-microgeometry-checkpoint-1"

#: accumulators: (K, K) matrices, counts (integers), non-negative sums
_MATRICES = ("sum", "s2", "ns")
_COUNTS = ("chunks", "rays")
_SCALARS = ("n2", "seconds", "reflected", "absorbed", "lost")
_NONNEG = ("s2", "n2", "seconds", "reflected", "absorbed", "lost", "bounces")
_META_STR = ("surface", "surface_repr", "basis", "incident")
_META_INT = ("targets", "chunk")

#: (K, K) float64 arrays alive at once in simulate: the accumulators (sum, s2, ns), their
#: copy that a chunk updates (so that an interrupt always finds a consistent state to save)
#: and the chunk's own m, its symmetric part and two temporaries
_MATRIX_COPIES = 10
#: float64 numbers per traced ray (paths, exit directions, the wavefront tracer's state)
#: besides the ray's row of basis values
_PER_RAY = 30


class SimulationResult:
    """Outcome of :func:`simulate`: the matrix, its error estimates and the energy balance.

    Attributes
    ----------
    matrix : CoefficientMatrix
        Symmetrised estimate of f cos(theta_i) cos(theta_o) (``quantity="f_cos"``).
    raw : (K, K) ndarray
        The unsymmetrised estimate M~ (rows: incident basis function).
    asymmetry : float
        Westin's convergence measure Q (Westin et al. 1992, sec. 4.7, eqs 26-27), the mean
        absolute asymmetry (1/K^2) sum_jk |M~_jk - M~_kj|: the printed eq 27 normalises by
        1/N^2 and sums |A_ij|, read here as 1/K^2 (K x K matrix) and |A_jk|.
    stderr : (K, K) ndarray
        Batch-means standard error of each entry of the symmetrised matrix (one batch per
        chunk of incident directions; NaN with fewer than 2 chunks). With c chunks it has
        c - 1 degrees of freedom: use 10 or more chunks (``simulate(chunk=...)`` counts
        incident directions) before comparing in units of it.
    rays : int
        Incident rays traced.
    seconds : float
        Wall time spent tracing and accumulating (summed over merged or resumed runs).
    energy : dict
        Per unit incident energy: ``reflected`` (left the surface: what M describes),
        ``absorbed`` (by facets), ``escaped`` (paths cut off by the bounce or step cap and
        dropped from the estimate; normally 0). Their sum is 1 up to Russian-roulette noise.
    bounce_energy : (BOUNCE_BINS,) ndarray
        Reflected energy per unit incident energy after exactly 1, 2, ... facet
        interactions (last bin: BOUNCE_BINS or more).
    """

    def __init__(self, acc: dict[str, Any], basis: Basis, meta: dict[str, Any]) -> None:
        self._acc = acc
        self.basis = basis
        self.meta = dict(meta)
        n = float(acc["rays"])
        raw = acc["sum"] / n
        self.raw = raw
        k = raw.shape[0]
        self.asymmetry = float(np.sum(np.abs(raw - raw.T)) / (k * k)) if k else 0.0
        mean = 0.5 * (raw + raw.T)
        c = int(acc["chunks"])
        if c >= 2:
            ss = acc["s2"] - 2.0 * mean * acc["ns"] + mean * mean * acc["n2"]
            self.stderr = np.sqrt(np.maximum(ss, 0.0) * c / (c - 1.0)) / n
        else:
            self.stderr = np.full_like(mean, np.nan)
        self.rays = int(acc["rays"])
        self.seconds = float(acc["seconds"])
        self.energy = {"reflected": float(acc["reflected"] / n),
                       "absorbed": float(acc["absorbed"] / n),
                       "escaped": float(acc["lost"] / n)}
        self.bounce_energy = acc["bounces"] / n
        info = {"source": "microgeometry.simulate", "rays": self.rays,
                "asymmetry": self.asymmetry, "stderr_max": float(np.max(self.stderr))
                if c >= 2 else float("nan"), **self.meta}
        self.matrix = CoefficientMatrix(basis, mean, "f_cos", symmetrize=True, info=info)

    @property
    def rays_per_second(self) -> float:
        """Incident rays traced and accumulated per second of wall time."""
        return self.rays / self.seconds if self.seconds > 0 else float("inf")

    @property
    def single_scatter(self) -> float:
        """Fraction of the incident energy that leaves after exactly one facet interaction."""
        return float(self.bounce_energy[0])

    def merge(self, other: SimulationResult) -> SimulationResult:
        """Combine with an independent run (another seed) of the same specimen and basis."""
        return merge(self, other)

    def __repr__(self) -> str:
        return (f"SimulationResult({self.basis!r}, rays={self.rays}, Q={self.asymmetry:.3g}, "
                f"reflected={self.energy['reflected']:.4f})")


def merge(*results: SimulationResult) -> SimulationResult:
    """Merge independent runs: the accumulators are additive.

    Parameters
    ----------
    *results : SimulationResult
        Runs of the same surface, basis, incident sampling and targets, with different
        seeds (equal seeds would repeat the same rays).

    Returns
    -------
    SimulationResult
    """
    if not results:
        raise ValueError("results must hold at least one SimulationResult, got none")
    for r in results:
        if not isinstance(r, SimulationResult):
            raise TypeError(f"results must be SimulationResult objects, got {type(r).__name__}")
    first = results[0]
    seeds = set()
    for r in results:
        for key in ("surface", "incident", "targets"):
            if r.meta[key] != first.meta[key]:
                raise ValueError(f"results must share {key}: {r.meta[key]!r} != "
                                 f"{first.meta[key]!r}")
        if r.basis != first.basis:
            raise ValueError(f"results must share the basis: {r.basis!r} != {first.basis!r}")
        for s in r.meta["seeds"]:
            if s in seeds:
                raise ValueError(f"results must come from different seeds, seed {s} repeats")
            seeds.add(s)
    acc = {k: sum(r._acc[k] for r in results) for k in first._acc}
    meta = dict(first.meta, seeds=sorted(seeds))
    if any("workers" in r.meta for r in results):
        meta["workers"] = sorted({w for r in results for w in r.meta.get("workers", ())})
    return SimulationResult(acc, first.basis, meta)


def simulate(
    surface: Heightfield | Scene,
    basis: Basis,
    *,
    rays: int,
    seed: int = 0,
    incident: str = "cosine",
    targets: int = 8,
    chunk: int | None = None,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_interval: float = 60.0,
    resume: str | os.PathLike | None = None,
    progress: bool | None = None,
    client: Any = None,
) -> SimulationResult:
    """Estimate the coefficient matrix of f cos(theta_i) cos(theta_o) by Monte Carlo.

    Parameters
    ----------
    surface : Heightfield or Scene
        The specimen (e.g. :class:`GaussianSurface`, :func:`brushed_metal`), with its facet
        material(s).
    basis : basis.Basis
        Any hemisphere basis (``HemiZernike``, ``HemiHarmonics``) or ``SphericalHarmonics``.
    rays : int
        Incident rays to trace (> 0), rounded up to a multiple of ``targets``. With
        ``resume`` this is the total including the rays already in the file.
    seed : int
        Seed (>= 0) of the counter-based random streams; the result is the same for a given
        seed whatever the thread count.
    incident : {"cosine", "uniform"}
        Distribution of incident directions: pdf cos(theta_i) / pi (the default: lowest
        variance for f cos cos) or 1 / (2 pi).
    targets : int
        Rays per incident direction, aimed at independent uniform points of the period
        (Westin's N_p; b(U) is evaluated once for all of them).
    chunk : int, optional
        Incident directions per chunk (one batch of the batch-means error estimate, and the
        unit of checkpointing, and of the work of one thread: each of the threads
        (``numba.get_num_threads()``) traces and accumulates whole chunks, so use at least a
        few chunks per thread).
        Default: about 32768 rays per chunk.
    checkpoint : path, optional
        HDF5 file to which the accumulators are saved every ``checkpoint_interval`` seconds,
        at the end, and when the run is interrupted (KeyboardInterrupt, SIGINT, SIGTERM,
        SystemExit), so at most one interval of work is lost (atomically: temporary file +
        ``os.replace``; with a SHA-256 of the content). Checked for writability before
        tracing starts, and locked for the run (the file ``<checkpoint>.lock``, see Notes).
    checkpoint_interval : float
        Seconds between checkpoints (> 0).
    resume : path, optional
        A checkpoint to continue from (must match surface, basis, seed, incident, targets and
        chunk). Often the same path as ``checkpoint``. A damaged file (truncated, altered,
        with values no run can produce) is refused with a ValueError.
    progress : bool, optional
        Show a tqdm progress bar; None shows it for runs of 10^7 rays or more.
    client : dask.distributed.Client, optional
        Trace the chunks as tasks on this Dask cluster instead of in this process (needs
        ``pip install 'scatmodes[distributed]'``). The result is bit-identical to the local
        run's; ``result.meta["workers"]`` lists the addresses of the workers that traced
        chunks in this call. See Notes.

    Returns
    -------
    SimulationResult

    Raises
    ------
    MemoryError
        Before any work, if the accumulators and the arrays of one chunk would exceed
        ``basis.validation.MAX_BYTES`` (e.g. HemiZernike(250): 31626 functions, 10 (K, K)
        matrices of 7.5 GiB each).
    ValueError
        For a damaged or incompatible ``resume`` file, or an unwritable ``checkpoint``.
    BlockingIOError
        If another run holds the lock of ``checkpoint``.
    ImportError
        If ``client`` is given and dask.distributed is not installed.
    RuntimeError
        If the cluster loses a chunk for good (its workers died repeatedly, or the client
        was closed); the chunks folded so far are in the checkpoint.

    Notes
    -----
    Estimator: see the module docstring (Westin eq 17/25 with the corrected constants pi and
    2 pi cos_i for hemisphere-orthonormal bases). The estimate is unbiased for the
    coefficients of f cos cos within the basis; the asymmetry Q falls like 1/sqrt(rays).

    Interrupts: a chunk updates a copy of the accumulators, which replaces them only once
    the chunk is complete, so an interrupt at any moment leaves a consistent state, which
    is saved before the interrupt continues. SIGTERM, whose default action would end the
    process at once, is turned into an exception for the run (in the main thread, when no
    Python handler is installed) and raised again, with its default action, once the
    checkpoint is saved.

    Lock: two runs writing the same checkpoint would overwrite each other's work, so the
    run holds an exclusive ``fcntl.flock`` on ``<checkpoint>.lock`` (released by the
    operating system if the process dies) and removes that file at the end. A lock file
    left by a killed run (its lock gone with it) is taken over with a warning. Where
    ``fcntl`` is missing, the lock file is created with ``O_CREAT | O_EXCL`` instead, and a
    left-over one must be removed by hand.

    Dask: the surface and basis are scattered to every worker once; a task traces a few
    consecutive chunks of incident directions (about four tasks per worker, at most 2^20
    rays each: a task costs the cluster milliseconds), a pure function of the seed and its
    first direction (counter-based random streams), and at most a few tasks per worker are
    queued at a time. The chunks' results are folded into the accumulators one by one in
    chunk order, as in the local run, however the tasks finish, so the sums are the same
    bits; a task that Dask runs again after its worker died returns the same values and is
    counted once. The checkpoint (written by this process) holds the
    chunks folded so far, and can be resumed with or without a client. A worker process traces
    one task at a time, its chunks spread over threads that take its share of the
    host's cores (the cores over the worker processes on that host), so one Dask thread per
    worker is enough
    (``LocalCluster(n_workers=N, threads_per_worker=1)``). Workers need
    scatmodes installed and, to avoid compiling the kernels in every process, a writable
    ``NUMBA_CACHE_DIR``.

    Examples
    --------
    >>> import numpy as np
    >>> from basis import HemiHarmonics
    >>> from project.microgeometry import Diffuse, Heightfield, simulate
    >>> plane = Heightfield(np.zeros((4, 4)), 1.0, material=Diffuse(0.5))
    >>> res = simulate(plane, HemiHarmonics(1), rays=20000, seed=1)
    >>> round(float(res.matrix.matrix[0, 0]), 1)  # 2 a / 3 = 0.333
    0.3
    """
    if not isinstance(surface, (Heightfield, Scene)):
        raise TypeError(f"surface must be a Heightfield (e.g. GaussianSurface) or a Scene, got "
                        f"{type(surface).__name__}")
    if not isinstance(basis, Basis):
        raise TypeError(f"basis must be a basis object (e.g. basis.HemiZernike(8)), got "
                        f"{type(basis).__name__}")
    rays = _positive_int(rays, "rays")
    seed_u = _seed(seed)
    if client is not None:
        dask_client(client, "simulate")
    if incident not in ("cosine", "uniform"):
        raise ValueError(f"incident must be 'cosine' or 'uniform', got {incident!r}")
    targets = _positive_int(targets, "targets")
    k = basis.size
    if chunk is None:
        chunk = max(1, 32768 // targets)
    chunk = _positive_int(chunk, "chunk")
    if not checkpoint_interval > 0:
        raise ValueError(f"checkpoint_interval must be > 0, got {checkpoint_interval!r}")
    per_chunk = chunk * targets * (k + _PER_RAY) + chunk * (2 * k + 4)
    check_bytes(8.0 * (_MATRIX_COPIES * k * k + per_chunk),
                f"simulate with {basis!r} ({k} functions: {_MATRIX_COPIES} ({k}, {k}) "
                f"accumulator matrices) and {chunk * targets} rays per chunk")
    # chunks traced at once in this process (see _Lanes): one per numba thread, as
    # many as memory allows; each holds its work arrays, its (K, K) result and two queued
    lanes = max(1, min(_threads(), int((validation.MAX_BYTES / 8.0 - _MATRIX_COPIES * k * k)
                                       // (per_chunk + 3 * k * k))))
    meta = {"surface": surface.fingerprint(), "surface_repr": repr(surface),
            "basis": repr(basis), "incident": incident, "targets": targets, "chunk": chunk,
            "seeds": [int(seed)]}
    if checkpoint is not None:
        checkpoint = Path(checkpoint)
        _check_writable(checkpoint)
    ndirs = -(-rays // targets)
    cosine = incident == "cosine"
    show = rays >= 10**7 if progress is None else bool(progress)
    with contextlib.ExitStack() as stack:
        stack.callback(_SCRATCH.release)
        if checkpoint is not None:
            # outermost: the lock is released before SIGTERM takes its default action
            stack.enter_context(_sigterm_raises())
            stack.enter_context(_locked(checkpoint))
        if resume is not None:
            acc, done = _load(Path(resume), meta, k)
        else:
            acc, done = _empty(k), 0
        bar = None
        if show:
            from tqdm.auto import tqdm
            bar = stack.enter_context(
                tqdm(total=ndirs * targets, initial=min(done, ndirs) * targets, unit="ray",
                     unit_scale=True, desc="simulate"))
        # (accumulators, directions done): replaced as a whole once a chunk is complete
        state = (acc, done)
        workers: set[str] = set()
        steps = _local_steps(surface, basis, seed_u, state, ndirs, chunk, targets, cosine,
                             bar, lanes) if client is None else \
            _distributed_steps(client, surface, basis, seed_u, state, ndirs, chunk, targets,
                               cosine, bar, workers)
        last_save = time.perf_counter()
        try:
            # closing: an interrupt between two steps still cancels the submitted tasks
            with contextlib.closing(steps):
                for state in steps:
                    if checkpoint is not None and \
                            time.perf_counter() - last_save >= checkpoint_interval:
                        _save(checkpoint, *state, meta)
                        last_save = time.perf_counter()
        except (KeyboardInterrupt, SystemExit, _Terminated):
            if checkpoint is not None:
                _save_on_interrupt(checkpoint, *state, meta)
            raise
        except Exception:
            # a cluster can fail (workers lost for good, a closed client) while the chunks
            # folded so far are sound: keep them for resume
            if checkpoint is not None and client is not None:
                _save_on_interrupt(checkpoint, *state, meta)
            raise
        acc, done = state
        if checkpoint is not None:
            _save(checkpoint, acc, done, meta)
    if client is not None:
        # not in the checkpoint's meta: the workers are no property of the estimate
        meta = dict(meta, workers=sorted(workers))
    return SimulationResult(acc, basis, meta)


def _local_steps(surface: Heightfield | Scene, basis: Basis, seed: np.uint64,
                 state: tuple[dict[str, Any], int], ndirs: int, chunk: int, per: int,
                 cosine: bool, bar: Any, lanes: int) -> Iterator[tuple[dict[str, Any], int]]:
    """Trace the chunks in this process; yield (accumulators, directions done) after each."""
    acc, done = state
    todo = ((a, min(chunk, ndirs - a)) for a in range(done, ndirs, chunk))
    with _Lanes(surface, basis, seed, todo, per, cosine, lanes) as ahead:
        while done < ndirs:
            t0 = time.perf_counter()
            nd = min(chunk, ndirs - done)
            new = _copy(acc)
            _chunk(surface, basis, seed, done, nd, per, cosine, new, ahead)
            new["seconds"] += time.perf_counter() - t0
            acc, done = new, done + nd
            if bar is not None:
                bar.update(nd * per)
            yield acc, done


def _threads() -> int:
    import numba

    return int(numba.get_num_threads())


def _one_thread() -> None:
    import numba

    # per thread (numba's thread count is thread-local, and run_parallel reads it): the
    # lane's own kernels and basis evaluations run in the lane's thread
    numba.set_num_threads(1)


class _Lanes:
    """Chunks computed ahead, in order, each whole by one thread ("lane").

    Splitting every chunk over all threads ends each of its steps (tracing, the two basis
    evaluations, the two accumulation loops) with a wait for the slowest thread: on a
    machine shared with other jobs, a thread that loses its core for a time slice stalls all
    of them, measured at up to half the run's time for a million rays. Here ``lanes``
    threads each trace and accumulate whole chunks and take the next one as soon as they
    finish, waiting for nobody; :meth:`delta` hands the chunks' results over in order,
    keeping at most ``2 * lanes`` queued. A chunk's values do not depend on how many threads
    computed it (per-ray random streams, a fixed summation order), so every lane count gives
    the same bits.

    ``todo`` yields the (start, directions) of the chunks that :meth:`delta` will be asked
    for, in that order. With one lane or a single chunk, every chunk is computed when asked
    for, in the calling thread on all numba threads (a lane would give a single chunk one
    thread).
    """

    def __init__(self, surface: Heightfield | Scene, basis: Basis, seed: np.uint64,
                 todo: Iterator[tuple[int, int]], per: int, cosine: bool, lanes: int) -> None:
        self._args = (surface, basis, seed)
        self._per = per
        self._cosine = cosine
        self._todo = todo
        self._lanes = lanes
        self._pool: Any = None
        self._queued: dict[int, Any] = {}  # start -> future of its _chunk_delta

    def __enter__(self) -> _Lanes:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def delta(self, start: int, nd: int) -> dict[str, Any]:
        """Return :func:`_chunk_delta` of directions start .. start + nd - 1."""
        if self._pool is None and self._lanes > 1:
            self._start()
        fut = self._queued.pop(start, None)
        if fut is None:
            return _chunk_delta(*self._args, start, nd, self._per, self._cosine)
        self._fill()
        return fut.result()

    def _start(self) -> None:
        # at the first chunk: lanes only if there are at least two chunks to share out
        ahead = list(itertools.islice(self._todo, 2))
        self._todo = itertools.chain(ahead, self._todo)
        if len(ahead) < 2:
            self._lanes = 1
            return
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(self._lanes, thread_name_prefix="scatmodes-lane",
                                        initializer=_one_thread)
        self._fill()

    def _fill(self) -> None:
        while self._pool is not None and len(self._queued) < 2 * self._lanes:
            nxt = next(self._todo, None)
            if nxt is None:
                return
            self._queued[nxt[0]] = self._pool.submit(_chunk_delta, *self._args, *nxt,
                                                     self._per, self._cosine)

    def close(self) -> None:
        """Start no other chunk and wait for the running ones (at most a chunk's time)."""
        if self._pool is not None:
            for fut in self._queued.values():
                fut.cancel()
            self._queued.clear()
            self._pool.shutdown(wait=True)
            self._pool = None


#: a worker process traces one task at a time: the task's own lanes (:class:`_Lanes`)
#: already take the worker's share of the host's cores, and a second task at once would
#: only compete for them while holding another set of chunk arrays in memory
_WORKER_LOCK = threading.Lock()


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def _remote_chunks(surface: Heightfield | Scene, basis: Basis, seed: np.uint64,
                   chunks: list[tuple[int, int]], per: int, cosine: bool,
                   processes: dict[str, int]) -> tuple[str, list[dict[str, Any]]]:
    """Run :func:`_chunk_delta` on a Dask worker for each (start, directions) in ``chunks``.

    Returns the worker's address and the chunks' results, in order. ``processes`` maps host
    to the number of worker processes on it: the task's lanes (:class:`_Lanes`, one chunk
    each) get that share of the host's cores (the result does not depend on it).
    """
    import numba
    from distributed import get_worker

    address = get_worker().address
    host = _host(address)
    threads = max(1, min(numba.config.NUMBA_NUM_THREADS, _cpus() // processes.get(host, 1)))
    with _WORKER_LOCK:
        numba.set_num_threads(threads)
        with _Lanes(surface, basis, seed, iter(chunks), per, cosine, threads) as ahead:
            deltas = [ahead.delta(start, nd) for start, nd in chunks]
    return address, deltas


#: a distributed run cuts its chunks into about this many tasks per worker (a few, so that
#: the last ones balance the load), each at most _TASK_RAYS rays: a Dask task costs ~10 ms
#: of the client's and scheduler's time and ~7 ms of the worker's here, which one task per
#: chunk paid 31 times for a million rays
_TASKS_PER_WORKER = 4
_TASK_RAYS = 1 << 20
#: times a distributed run scatters the scene again after losing it with a worker
_RESCATTERS = 5


def _host(address: str) -> str:
    from urllib.parse import urlsplit

    return urlsplit(address).hostname or address


def _distributed_steps(client: Any, surface: Heightfield | Scene, basis: Basis,
                       seed: np.uint64, state: tuple[dict[str, Any], int], ndirs: int,
                       chunk: int, per: int, cosine: bool, bar: Any,
                       workers: set[str]) -> Iterator[tuple[dict[str, Any], int]]:
    """Trace the chunks as tasks of a Dask cluster; yield states as :func:`_local_steps`.

    A task traces a few consecutive chunks (see _TASKS_PER_WORKER) and returns each one's
    sums. They are kept by chunk index and folded in index order as soon as the next one is
    there, so the sums are those of the local run whatever the order in which tasks finish.
    A task that Dask runs again (its worker died) returns the same values and is folded once.
    """
    import uuid

    from distributed import CancelledError, KilledWorker, as_completed

    acc, done = state
    starts = list(range(done, ndirs, chunk))
    if not starts:
        return
    info = client.scheduler_info()["workers"]
    processes: dict[str, int] = {}
    for addr in info:
        processes[_host(addr)] = processes.get(_host(addr), 0) + 1
    # consecutive chunks per task; each chunk is still folded on its own, in order
    group = max(1, min(-(-len(starts) // (_TASKS_PER_WORKER * max(1, len(info)))),
                       _TASK_RAYS // (chunk * per)))
    tasks = [starts[t:t + group] for t in range(0, len(starts), group)]
    # a few tasks per worker queued so that none waits, and a bound on the results held
    # out of order (each holds a (K, K) matrix per chunk) behind a slow or retried task
    window = 2 * max(1, len(info)) + 2
    ahead = 4 * window
    # scattered once: the tasks refer to these copies instead of each carrying the scene
    shared = [client.scatter(surface, broadcast=True, hash=False),
              client.scatter(basis, broadcast=True, hash=False)]
    rounds = 0  # times the scattered copies were lost and scattered again
    prefix = f"scatmodes-simulate-{uuid.uuid4().hex}-"
    pending: dict[int, Any] = {}  # by task index: the task's live future
    results: dict[int, dict[str, Any]] = {}  # by chunk index
    queue = as_completed()
    nxt = folded = 0  # next task to submit; chunks folded
    t_last = time.perf_counter()

    def closed(t: int) -> RuntimeError:
        return RuntimeError(
            f"simulate: task {t} (directions {tasks[min(t, len(tasks) - 1)][0]}..) was "
            "cancelled on the cluster (the client or the cluster was closed during the run, "
            "or the workers kept dying); resume from the checkpoint with a running client")

    def launch(t: int) -> None:
        chunks = [(a, min(chunk, ndirs - a)) for a in tasks[t]]
        fut = client.submit(_remote_chunks, *shared, seed, chunks, per, cosine, processes,
                            key=f"{prefix}{rounds}-{t}", pure=False)
        pending[t] = fut
        queue.add(fut)

    def submit() -> None:
        nonlocal nxt
        if client.status != "running":
            raise closed(nxt)
        while nxt < len(tasks) and len(pending) < window and \
                nxt * group - folded < ahead * group:
            launch(nxt)
            nxt += 1

    try:
        submit()
        for fut in queue:
            t = int(fut.key.rsplit("-", 1)[1])
            if t not in pending or pending[t].key != fut.key:
                continue  # already counted (a task is folded exactly once), or superseded
            try:
                address, deltas = fut.result()
            except KilledWorker as err:
                raise RuntimeError(
                    f"simulate: task {t} (directions {tasks[t][0]}..) was lost because the "
                    f"workers running it died repeatedly ({err}); they may run out of "
                    "memory: give them more memory or use a smaller chunk, then resume from "
                    "the checkpoint") from None
            except CancelledError:
                if client.status != "running" or rounds >= _RESCATTERS:
                    raise closed(t) from None
                # Dask keeps a single replica of scattered data once no queued task needs
                # the others (its active memory manager), so a dying worker can take the
                # scene with it: the scheduler then cancels every task that needs it.
                # Scatter again and launch the unfinished tasks anew (same values).
                rounds += 1
                shared = [client.scatter(surface, broadcast=True, hash=False),
                          client.scatter(basis, broadcast=True, hash=False)]
                for tt in sorted(pending):
                    launch(tt)
                continue
            del pending[t]
            workers.add(address)
            for c, delta in enumerate(deltas, start=t * group):
                results[c] = delta
                if bar is not None:
                    bar.update(delta["rays"])
            while folded in results:
                new = _copy(acc)
                _fold(new, results.pop(folded))
                now = time.perf_counter()
                new["seconds"] += now - t_last  # wall time of the run, not summed worker time
                t_last = now
                acc, done = new, min(done + chunk, ndirs)
                folded += 1
                yield acc, done
            submit()
        if folded < len(starts):  # pragma: no cover - as_completed ends with every future
            raise RuntimeError(f"simulate: the cluster returned {folded} of {len(starts)} "
                               "chunks; resume from the checkpoint")
    finally:
        if client.status == "running":
            if pending:
                client.cancel(list(pending.values()))
            with contextlib.suppress(Exception):  # never mask the run's own error
                client.run(_release_scratch)


def _copy(acc: dict[str, Any]) -> dict[str, Any]:
    return {key: val.copy() if isinstance(val, np.ndarray) else val for key, val in acc.items()}


def _empty(k: int) -> dict[str, Any]:
    z = np.zeros((k, k))
    return {"sum": z.copy(), "s2": z.copy(), "ns": z.copy(), "n2": 0.0, "chunks": 0,
            "rays": 0, "seconds": 0.0, "reflected": 0.0, "absorbed": 0.0, "lost": 0.0,
            "bounces": np.zeros(BOUNCE_BINS)}


def _chunk(surface: Heightfield | Scene, basis: Basis, seed: np.uint64, start: int, nd: int,
           per: int, cosine: bool, acc: dict[str, Any], ahead: _Lanes | None = None) -> None:
    """Trace directions start .. start + nd - 1 (``per`` rays each) and accumulate.

    ``ahead``, if given, may already be computing this chunk on another thread.
    """
    _fold(acc, ahead.delta(start, nd) if ahead is not None else
          _chunk_delta(surface, basis, seed, start, nd, per, cosine))


def _chunk_delta(surface: Heightfield | Scene, basis: Basis, seed: np.uint64, start: int,
                 nd: int, per: int, cosine: bool) -> dict[str, Any]:
    """Trace directions start .. start + nd - 1 and return what they add (see :func:`_fold`).

    A pure function of its arguments (counter-based streams), so a chunk traced again, on
    another worker or after a retry, returns the same bits. Its large arrays are this
    thread's :data:`_SCRATCH`, reused by the next chunk of the same size.
    """
    u = incident_directions(nd, seed, start, cosine)
    n = nd * per
    k = basis.size
    out = (_SCRATCH.get("dir", (n, 3)), _SCRATCH.get("w", (n,)),
           _SCRATCH.get("bounces", (n,), np.int64), _SCRATCH.get("absorbed", (n,)),
           _SCRATCH.get("lost", (n,)))
    if isinstance(surface, Scene):
        surface._run(u, per, seed, start * per, out, MAX_BOUNCES, MAX_STEPS)
    else:
        _run(surface, u, per, seed, start * per, out)
    vdir, w, nb, absorbed, lost = out
    bu = basis.eval(u, out=_SCRATCH.get("bu", (nd, k)))  # once per direction (Westin eq 25)
    c = np.full(nd, np.pi) if cosine else 2.0 * np.pi * u[:, 2]
    sums = _exit_sums(basis, vdir, w, per, _SCRATCH.get("sums", (nd, k)))
    m = np.empty((k, k))
    run_parallel(_outer_kernel, (k + 3) // 4, bu, c, sums, m,
                 grain=max(1, _ACCUMULATE_WORK // max(1, 4 * nd * k)))
    return {"m": m, "rays": n, "reflected": float(w.sum()),
            "absorbed": float(absorbed.sum()), "lost": float(lost.sum()),
            "bounces": np.bincount(np.minimum(nb, BOUNCE_BINS), weights=w,
                                   minlength=BOUNCE_BINS + 1)[1:]}


class _Scratch:
    """Work arrays of the chunks, one set per thread, kept from one chunk to the next.

    Allocating them afresh for every chunk costs little in a plain process, but Dask's worker
    processes run with ``MALLOC_TRIM_THRESHOLD_=65536`` (the nanny's default, against memory
    fragmentation), under which glibc hands every large freed block back to the system: each
    chunk then page-faulted and zeroed its arrays again, measured at 64,000 page faults and
    0.35 s of system time per million rays at HemiZernike(8), a third of the run's time.
    :meth:`release` frees them (at the end of a run, and on the workers after a distributed
    one).
    """

    def __init__(self) -> None:
        self._bufs: dict[int, dict[str, np.ndarray]] = {}
        self._lock = threading.Lock()

    def get(self, name: str, shape: tuple[int, ...], dtype: type = np.float64) -> np.ndarray:
        """Return this thread's array ``name`` of this shape and dtype (any contents)."""
        with self._lock:
            bufs = self._bufs.setdefault(threading.get_ident(), {})
        a = bufs.get(name)
        if a is None or a.shape != shape or a.dtype != dtype:
            bufs[name] = None  # the old one is freed before the new one is allocated
            a = bufs[name] = np.empty(shape, dtype)
        return a

    def release(self) -> None:
        """Free the arrays of every thread (an array in use stays alive with its user)."""
        with self._lock:
            self._bufs.clear()


_SCRATCH = _Scratch()


def _release_scratch() -> None:
    # run on every Dask worker once a distributed run ends
    _SCRATCH.release()


def _fold(acc: dict[str, Any], delta: dict[str, Any]) -> None:
    """Add one chunk's contribution to the accumulators.

    Floating-point addition is not associative, so local and distributed runs both fold the
    chunks through this one function in chunk order: that makes their results bit-identical.
    """
    m, n = delta["m"], delta["rays"]
    ms = 0.5 * (m + m.T)
    acc["sum"] += m
    acc["s2"] += ms * ms
    acc["ns"] += n * ms
    acc["n2"] += float(n) * n
    acc["chunks"] += 1
    acc["rays"] += n
    acc["reflected"] += delta["reflected"]
    acc["absorbed"] += delta["absorbed"]
    acc["lost"] += delta["lost"]
    acc["bounces"] += delta["bounces"]


#: multiply-adds per part of run_parallel in the accumulation kernels (about 100 us)
_ACCUMULATE_WORK = 1 << 17


#: bytes of exit-direction basis values per thread evaluated at once (they stay in its L2
#: cache until the exit sums read them)
_EXIT_BYTES = 1 << 20


def _exit_sums(basis: Basis, vdir: np.ndarray, w: np.ndarray, per: int,
               sums: np.ndarray) -> np.ndarray:
    """Set ``sums`` (D, K) to S_d = sum_p w_dp b(V_dp) (Westin eq 25) and return it.

    ``vdir`` (D * per, 3) exit directions, ``w`` (D * per,) exit weights. The basis is
    evaluated a block of directions at a time, into a block that fits the threads' L2
    caches, and summed at once: evaluating all of a chunk first wrote its b(V) (24 MB for
    32768 rays at K = 91) to memory and read it back.

    Each S_d adds its rays one by one in increasing p, whatever the block or thread count.
    """
    nd, kk = sums.shape
    step = max(1, _EXIT_BYTES * _threads() // (8 * kk * per))  # directions
    bv = _SCRATCH.get("bv", (min(nd, step) * per, kk))
    for d0 in range(0, nd, step):
        d1 = min(nd, d0 + step)
        rows = slice(d0 * per, d1 * per)
        basis.eval(vdir[rows], out=bv[:(d1 - d0) * per])
        run_parallel(_exit_sums_kernel, d1 - d0, per, bv, w[rows], sums[d0:d1],
                     grain=max(1, _ACCUMULATE_WORK // max(1, per * kk)))
    return sums


@loopjit
def _exit_sums_kernel(first, stop, per, bv, w, sums):
    # directions first .. stop - 1 (run_parallel): sums[d] = sum_p w_dp b(V_dp)
    wide_loops()  # loops over k: eight doubles per instruction on any AVX-512 CPU
    kk = sums.shape[1]
    for d in range(first, stop):
        for k in range(kk):
            sums[d, k] = 0.0
        for p in range(d * per, (d + 1) * per):
            f = w[p]
            if f != 0.0:
                for k in range(kk):
                    sums[d, k] = fma(f, bv[p, k], sums[d, k])


#: directions per tile of the outer-product kernel: its rows of the exit sums (K doubles each)
#: stay in the L2 cache while every row block of m takes them (at K = 91, 186 kB)
_OUTER_TILE = 256


@loopjit
def _outer_kernel(first, stop, bu, c, sums, m):
    # blocks first .. stop - 1 (run_parallel) of four rows of m: m[j] = sum_d c_d bu[d, j] sums[d]
    # A block holds four rows of m in a local array and takes four directions per pass over
    # k, so each pass loads and stores the block once for sixteen multiply-adds: about 2x
    # faster than one row and one direction per pass (same bits). The multiply-adds are
    # fused (basis.jit.fma): 1.2-1.4x faster on AMD Zen 1, 2x on Intel's AVX-512 cores by
    # llvm-mca's model of Skylake-SP, where products and sums share two ports. The
    # directions run in tiles of _OUTER_TILE (a multiple of four), each taken by every block
    # in turn, its rows of sums read from the L2 cache instead of memory; a block's rows
    # are carried from tile to tile in m, so every entry adds the same products in the same
    # order as over all directions at once (the same bits).
    wide_loops()  # loops over k: eight doubles per instruction on any AVX-512 CPU
    nd, kk = bu.shape
    r = np.empty((4, kk))
    r0 = r[0]
    r1 = r[1]
    r2 = r[2]
    r3 = r[3]
    for t0 in range(0, nd, _OUTER_TILE):
        t1 = min(nd, t0 + _OUTER_TILE)
        for b in range(first, stop):
            j0 = 4 * b
            nj = min(4, kk - j0)
            # rows past the end repeat the last one (computed, not stored)
            ja = j0
            jb = j0 + min(1, nj - 1)
            jc = j0 + min(2, nj - 1)
            jd = j0 + min(3, nj - 1)
            if t0 == 0:
                r[:, :] = 0.0
            else:
                for k in range(kk):
                    r0[k] = m[ja, k]
                    r1[k] = m[jb, k]
                    r2[k] = m[jc, k]
                    r3[k] = m[jd, k]
            d = t0
            while d + 3 < t1:
                c0 = c[d]
                c1 = c[d + 1]
                c2 = c[d + 2]
                c3 = c[d + 3]
                a00 = c0 * bu[d, ja]
                a01 = c0 * bu[d, jb]
                a02 = c0 * bu[d, jc]
                a03 = c0 * bu[d, jd]
                a10 = c1 * bu[d + 1, ja]
                a11 = c1 * bu[d + 1, jb]
                a12 = c1 * bu[d + 1, jc]
                a13 = c1 * bu[d + 1, jd]
                a20 = c2 * bu[d + 2, ja]
                a21 = c2 * bu[d + 2, jb]
                a22 = c2 * bu[d + 2, jc]
                a23 = c2 * bu[d + 2, jd]
                a30 = c3 * bu[d + 3, ja]
                a31 = c3 * bu[d + 3, jb]
                a32 = c3 * bu[d + 3, jc]
                a33 = c3 * bu[d + 3, jd]
                s0 = sums[d]
                s1 = sums[d + 1]
                s2 = sums[d + 2]
                s3 = sums[d + 3]
                for k in range(kk):
                    x0 = s0[k]
                    x1 = s1[k]
                    x2 = s2[k]
                    x3 = s3[k]
                    r0[k] = fma(a30, x3, fma(a20, x2, fma(a10, x1, fma(a00, x0, r0[k]))))
                    r1[k] = fma(a31, x3, fma(a21, x2, fma(a11, x1, fma(a01, x0, r1[k]))))
                    r2[k] = fma(a32, x3, fma(a22, x2, fma(a12, x1, fma(a02, x0, r2[k]))))
                    r3[k] = fma(a33, x3, fma(a23, x2, fma(a13, x1, fma(a03, x0, r3[k]))))
                d += 4
            while d < t1:  # only in the last tile (the others hold a multiple of four)
                cd = c[d]
                a0 = cd * bu[d, ja]
                a1 = cd * bu[d, jb]
                a2 = cd * bu[d, jc]
                a3 = cd * bu[d, jd]
                s = sums[d]
                for k in range(kk):
                    x = s[k]
                    r0[k] = fma(a0, x, r0[k])
                    r1[k] = fma(a1, x, r1[k])
                    r2[k] = fma(a2, x, r2[k])
                    r3[k] = fma(a3, x, r3[k])
                d += 1
            for i in range(nj):
                for k in range(kk):
                    m[j0 + i, k] = r[i, k]


# -- checkpoints ------------------------------------------------------------------------------

def _check_writable(path: Path) -> None:
    try:
        if path.is_dir():
            raise IsADirectoryError(f"{path} is a directory")
        # a uniquely named probe: a fixed name would race with other runs in the folder
        temporary_name(path).unlink()
    except OSError as err:
        raise ValueError(f"checkpoint must be a writable file path, got {str(path)!r} "
                         f"({err})") from None


class _Terminated(BaseException):
    """SIGTERM during a run with a checkpoint (raised again as SIGTERM once it is saved)."""


@contextlib.contextmanager
def _sigterm_raises() -> Iterator[None]:
    """Turn SIGTERM into :class:`_Terminated` while the body runs, if nothing else handles it.

    Only when SIGTERM has its default action (which would end the process without the final
    checkpoint) and only in the main thread, where Python runs signal handlers. A Python
    handler that is already installed (a command line's, say) is left alone: the exception
    it raises reaches the same final save.
    """
    sig = getattr(signal, "SIGTERM", None)
    if sig is None or threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(sig) not in (signal.SIG_DFL, None):
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        raise _Terminated

    signal.signal(sig, handler)
    try:
        yield
    except _Terminated:
        signal.signal(sig, signal.SIG_DFL)
        signal.raise_signal(sig)  # the default action: the process ends here
        raise  # pragma: no cover - not reached
    finally:
        if signal.getsignal(sig) is handler:
            signal.signal(sig, signal.SIG_DFL)


def _save_on_interrupt(path: Path, acc: dict[str, Any], done: int, meta: dict[str, Any]) -> None:
    """Save the last consistent state; a failure warns rather than hiding the interrupt."""
    try:
        _save(path, acc, done, meta)
    except Exception as err:  # the interrupt, not the save, is what the caller must see
        warnings.warn(f"could not save the checkpoint {str(path)!r} on the interrupt: {err}",
                      RuntimeWarning, stacklevel=3)


try:
    import fcntl as _fcntl
except ImportError:  # pragma: no cover - not POSIX
    _fcntl = None  # type: ignore[assignment]


def _lock_owner(lock: Path) -> str:
    with contextlib.suppress(OSError, ValueError):
        text = lock.read_text(encoding="ascii", errors="replace").split()
        if text:
            return f"process {text[0]}" + (f" on {text[1]}" if len(text) > 1 else "")
    return "another process"


def _in_use(path: Path, lock: Path) -> BlockingIOError:
    return BlockingIOError(
        f"checkpoint {str(path)!r} is in use by another run ({_lock_owner(lock)}, lock file "
        f"{str(lock)!r}): wait for that run to finish or give another checkpoint path"
        + ("" if _fcntl is not None else "; if no run is using it, delete the lock file"))


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """Hold the exclusive lock of checkpoint ``path`` while the body runs (see simulate)."""
    import socket

    lock = path.with_name(path.name + ".lock")
    me = f"{os.getpid()} {socket.gethostname()}\n".encode()
    if _fcntl is None:  # pragma: no cover - exercised by patching _fcntl to None
        try:
            fd = os.open(lock, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            raise _in_use(path, lock) from None
        try:
            os.write(fd, me)
        finally:
            os.close(fd)
        try:
            yield
        finally:
            with contextlib.suppress(OSError):
                os.unlink(lock)
        return
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            _fcntl.flock(fd, _fcntl.LOCK_EX | _fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise _in_use(path, lock) from None
        # the holder may have removed the file between our open and flock: then the lock is
        # on an orphaned inode, and the name must be opened again
        try:
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        before = os.read(fd, 256).decode("ascii", errors="replace").split()
        if before:
            # the kernel released the lock when that process ended; only its file remained
            warnings.warn(f"checkpoint {str(path)!r}: taking over the lock file {str(lock)!r} "
                          f"left by process {before[0]}, which no longer holds it (it ended "
                          "without removing it)", RuntimeWarning, stacklevel=5)
        os.lseek(fd, 0, os.SEEK_SET)
        os.ftruncate(fd, 0)
        os.write(fd, me)
        yield
    finally:
        # remove the name before unlocking, so that a waiting run cannot lock a file that is
        # about to vanish (the inode check above catches the opposite order)
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)


def _canonical(acc: dict[str, Any], done: int, meta: dict[str, Any]) -> Iterator[bytes]:
    """Yield the content of a checkpoint that its SHA-256 covers, in a fixed encoding."""
    yield f"{_FORMAT}\0directions_done={int(done)}\0".encode()
    for key in sorted(meta):
        val = meta[key]
        text = ",".join(str(int(x)) for x in np.atleast_1d(val)) if key == "seeds" else \
            str(int(val)) if key in _META_INT else str(val)
        # h5py decodes undecodable bytes of damaged text as surrogates: keep them distinct
        yield f"meta_{key}={text}\0".encode("utf-8", "surrogateescape")
    for key in sorted(acc):
        a = np.ascontiguousarray(acc[key], dtype=np.int64 if key in _COUNTS else np.float64)
        yield f"{key}{a.shape}\0".encode()
        yield a.tobytes() if a.ndim == 0 else memoryview(a).cast("B")


def _checksum(acc: dict[str, Any], done: int, meta: dict[str, Any]) -> str:
    h = hashlib.sha256()
    for part in _canonical(acc, done, meta):
        h.update(part)
    return h.hexdigest()


def _save(path: Path, acc: dict[str, Any], done: int, meta: dict[str, Any]) -> None:
    import h5py

    with atomic_path(path, suffix=".tmp") as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = _FORMAT
        f.attrs["directions_done"] = np.int64(done)
        for key, val in meta.items():
            f.attrs["meta_" + key] = val if key != "seeds" else np.asarray(val, np.uint64)
        for key, val in acc.items():
            f.create_dataset(key, data=np.asarray(
                val, dtype=np.int64 if key in _COUNTS else np.float64))
        f.attrs["sha256"] = _checksum(acc, done, meta)


class _Damaged(ValueError):
    """What is wrong with a checkpoint file (reworded by :func:`_load` into one message)."""


def _load(path: Path, meta: dict[str, Any], k: int) -> tuple[dict[str, Any], int]:
    """Read and check a checkpoint: every failure is one ValueError naming the file."""
    import h5py

    from ..hdf5 import Indirection, check_self_contained

    if not path.is_file():
        raise FileNotFoundError(f"resume must name an existing checkpoint file, got "
                                f"{str(path)!r}")
    name = f"resume file {str(path)!r}"
    advice = ("it cannot be resumed: start afresh without resume (delete or move the file), "
              "or resume from a copy")
    try:
        f = h5py.File(path, "r")
    except Exception as err:  # h5py reports damage as OSError, KeyError, RuntimeError, ...
        raise ValueError(f"{name} is not a readable HDF5 checkpoint, it may be truncated or "
                         f"damaged ({' '.join(str(err).split())}); {advice}") from None
    with f:
        try:
            fmt = f.attrs.get("format")
        except Exception:  # an unreadable attribute table: not a checkpoint
            fmt = None
        if not (isinstance(fmt, str) and fmt in (_FORMAT, _FORMAT_1)):
            shown = (f"an array of {fmt.dtype} with shape {fmt.shape}"
                     if isinstance(fmt, np.ndarray) else repr(fmt)[:100])
            raise ValueError(f"{name} is not a simulate checkpoint (its format attribute is "
                             f"{shown}, expected {_FORMAT!r})")
        try:
            # from the metadata alone: links, virtual datasets, external storage, plugin
            # filters and references would make the reads below use other data
            check_self_contained(f)
        except Indirection as err:
            raise ValueError(f"{name} is refused: {err}; {advice}") from None
        except Exception as err:  # HDF5's errors on corrupt metadata have many types
            raise ValueError(f"{name} is damaged ({type(err).__name__}: "
                             f"{' '.join(str(err).split())}); {advice}") from None
        try:
            got, acc, done, checksum = _read(f, meta, k)
        except _Damaged as err:
            raise ValueError(f"{name} is damaged: {err}; {advice}") from None
        except Exception as err:  # HDF5's errors on corrupt metadata have many types
            raise ValueError(f"{name} is damaged ({type(err).__name__}: "
                             f"{' '.join(str(err).split())}); {advice}") from None
    if not acc:  # another basis: its matrices were not read
        _compatible(name, got, meta)
    if fmt == _FORMAT and checksum != _checksum(acc, done, got):
        raise ValueError(f"{name} is damaged: its content does not match its SHA-256 "
                         f"checksum (altered or corrupted after it was written); {advice}")
    _compatible(name, got, meta)
    try:
        _check_values(acc, done, meta, k)
    except _Damaged as err:
        raise ValueError(f"{name} is damaged: {err}; {advice}") from None
    return acc, done


def _read(f: Any, meta: dict[str, Any], k: int) -> tuple[dict[str, Any], dict[str, Any], int,
                                                          str | None]:
    """Read the attributes and accumulators of an open checkpoint, checking their types."""
    import h5py

    def attr(key: str) -> Any:
        if key not in f.attrs:
            raise _Damaged(f"it lacks the attribute {key!r}")
        return f.attrs[key]

    def integer(key: str, val: Any) -> int:
        if isinstance(val, (bool, np.bool_)) or not isinstance(val, (int, np.integer)):
            raise _Damaged(f"attribute {key!r} must be an integer, got {val!r}")
        return int(val)

    got: dict[str, Any] = {}
    for key in _META_STR:
        val = attr("meta_" + key)
        if not isinstance(val, str):
            raise _Damaged(f"attribute 'meta_{key}' must be text, got {val!r}")
        got[key] = val
    for key in _META_INT:
        got[key] = integer("meta_" + key, attr("meta_" + key))
    seeds = np.asarray(attr("meta_seeds"))
    if seeds.ndim != 1 or seeds.size == 0 or seeds.dtype.kind not in "iu":
        raise _Damaged(f"attribute 'meta_seeds' must be a list of integers, got {seeds!r}")
    got["seeds"] = [int(x) for x in seeds]
    done = integer("directions_done", attr("directions_done"))
    checksum = None
    if attr("format") == _FORMAT:  # a string: checked by _load
        checksum = attr("sha256")
        if not isinstance(checksum, str):
            raise _Damaged(f"attribute 'sha256' must be text, got {checksum!r}")
    if got["basis"] != meta["basis"]:
        # another basis: _compatible says so; its matrices have another shape
        return got, {}, done, checksum
    shapes = {**{key: (k, k) for key in _MATRICES}, "bounces": (BOUNCE_BINS,),
              **{key: () for key in _COUNTS + _SCALARS}}
    acc: dict[str, Any] = {}
    for key, shape in shapes.items():
        ds = f.get(key)
        if not isinstance(ds, h5py.Dataset):
            raise _Damaged(f"it lacks the dataset {key!r}")
        # the shape is checked before reading: a damaged header could announce terabytes
        if ds.shape != shape:
            raise _Damaged(f"dataset {key!r} has shape {ds.shape}, expected {shape}")
        want = "iu" if key in _COUNTS else "f"
        if ds.dtype.kind not in want:
            raise _Damaged(f"dataset {key!r} must hold {'integers' if key in _COUNTS else 'floats'}"
                           f", got dtype {ds.dtype}")
        val = ds[()]
        acc[key] = int(val) if key in _COUNTS else float(val) if not shape else \
            np.asarray(val, dtype=np.float64)
    return got, acc, done, checksum


def _compatible(name: str, got: dict[str, Any], meta: dict[str, Any]) -> None:
    labels = {"surface": "surface", "basis": "basis", "seeds": "seed", "incident": "incident",
              "targets": "targets", "chunk": "chunk"}
    for key, label in labels.items():
        if got[key] != meta[key]:
            raise ValueError(f"{name} is incompatible: it was made with a different {label} "
                             f"({got[key]!r}, this run {meta[key]!r})")


def _check_values(acc: dict[str, Any], done: int, meta: dict[str, Any], k: int) -> None:
    """Refuse accumulators that no run can have produced (raises _Damaged)."""
    for key, val in acc.items():
        a = np.asarray(val, dtype=np.float64)
        if not np.all(np.isfinite(a)):
            raise _Damaged(f"{key!r} holds NaN or infinite values")
        if (key in _NONNEG or key in _COUNTS) and np.any(a < 0):
            raise _Damaged(f"{key!r} must be >= 0, got {a.min():g}")
    if done < 0:
        raise _Damaged(f"directions_done must be >= 0, got {done}")
    targets, chunk = meta["targets"], meta["chunk"]
    rays, chunks = acc["rays"], acc["chunks"]
    if rays != done * targets:
        raise _Damaged(f"it holds {rays} rays, but directions_done = {done} at {targets} rays "
                       f"per direction means {done * targets}")
    if not (done == 0 == chunks or -(-done // chunk) <= chunks <= done):
        raise _Damaged(f"{chunks} chunks cannot hold {done} directions of at most {chunk} per "
                       "chunk")
    n2 = acc["n2"]
    if chunks and not (rays * rays / chunks * (1 - 1e-12) <= n2 <=
                       rays * chunk * targets * (1 + 1e-12)):
        raise _Damaged(f"n2 = {n2:g} (the sum of squared rays per chunk) is impossible for "
                       f"{rays} rays in {chunks} chunks")
    bounced = float(np.sum(acc["bounces"]))
    if bounced > acc["reflected"] * (1 + 1e-9) + 1e-300:
        raise _Damaged(f"the reflected energy per bounce count sums to {bounced:g}, more than "
                       f"the reflected total {acc['reflected']:g}")
