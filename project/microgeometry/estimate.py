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

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from basis import Basis, CoefficientMatrix
from basis.jit import pjit, prange

from ..io import atomic_path
from ._checks import _positive_int, _seed
from ._paths import MAX_BOUNCES, MAX_STEPS, _alloc, incident_directions
from .scene import Scene
from .surface import Heightfield
from .trace import _run

__all__ = ["SimulationResult", "merge", "simulate"]

#: energy leaving after 1, 2, ..., BOUNCE_BINS - 1 and >= BOUNCE_BINS facet interactions
BOUNCE_BINS = 8

_FORMAT = "scatmodes-microgeometry-checkpoint-1"


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
        unit of checkpointing). Default: about 32768 rays per chunk (fewer, larger
        chunks amortise the start of the parallel kernels).
    checkpoint : path, optional
        HDF5 file to which the accumulators are saved every ``checkpoint_interval`` seconds
        and at the end (atomically: temporary file + ``os.replace``). Checked for
        writability before tracing starts.
    checkpoint_interval : float
        Seconds between checkpoints (> 0).
    resume : path, optional
        A checkpoint to continue from (must match surface, basis, seed, incident, targets and
        chunk). Often the same path as ``checkpoint``.
    progress : bool, optional
        Show a tqdm progress bar; None shows it for runs of 10^7 rays or more.

    Returns
    -------
    SimulationResult

    Notes
    -----
    Estimator: see the module docstring (Westin eq 17/25 with the corrected constants pi and
    2 pi cos_i for hemisphere-orthonormal bases). The estimate is unbiased for the
    coefficients of f cos cos within the basis; the asymmetry Q falls like 1/sqrt(rays).

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
    if incident not in ("cosine", "uniform"):
        raise ValueError(f"incident must be 'cosine' or 'uniform', got {incident!r}")
    targets = _positive_int(targets, "targets")
    k = basis.size
    if chunk is None:
        chunk = max(1, 32768 // targets)
    chunk = _positive_int(chunk, "chunk")
    if not checkpoint_interval > 0:
        raise ValueError(f"checkpoint_interval must be > 0, got {checkpoint_interval!r}")
    meta = {"surface": surface.fingerprint(), "surface_repr": repr(surface),
            "basis": repr(basis), "incident": incident, "targets": targets, "chunk": chunk,
            "seeds": [int(seed)]}
    if checkpoint is not None:
        checkpoint = Path(checkpoint)
        _check_writable(checkpoint)
    if resume is not None:
        acc, done = _load(Path(resume), meta, k)
    else:
        acc, done = _empty(k), 0
    ndirs = -(-rays // targets)
    cosine = incident == "cosine"
    show = rays >= 10**7 if progress is None else bool(progress)
    bar = None
    if show:
        from tqdm.auto import tqdm
        bar = tqdm(total=ndirs * targets, initial=min(done, ndirs) * targets, unit="ray",
                   unit_scale=True, desc="simulate")
    last_save = time.perf_counter()
    while done < ndirs:
        t0 = time.perf_counter()
        nd = min(chunk, ndirs - done)
        _chunk(surface, basis, seed_u, done, nd, targets, cosine, acc)
        done += nd
        acc["seconds"] += time.perf_counter() - t0
        if bar is not None:
            bar.update(nd * targets)
        if checkpoint is not None and time.perf_counter() - last_save >= checkpoint_interval:
            _save(checkpoint, acc, meta, done)
            last_save = time.perf_counter()
    if bar is not None:
        bar.close()
    if checkpoint is not None:
        _save(checkpoint, acc, meta, done)
    return SimulationResult(acc, basis, meta)


def _empty(k: int) -> dict[str, Any]:
    z = np.zeros((k, k))
    return {"sum": z.copy(), "s2": z.copy(), "ns": z.copy(), "n2": 0.0, "chunks": 0,
            "rays": 0, "seconds": 0.0, "reflected": 0.0, "absorbed": 0.0, "lost": 0.0,
            "bounces": np.zeros(BOUNCE_BINS)}


def _chunk(surface: Heightfield | Scene, basis: Basis, seed: np.uint64, start: int, nd: int,
           per: int, cosine: bool, acc: dict[str, Any]) -> None:
    """Trace directions start .. start + nd - 1 (``per`` rays each) and accumulate."""
    u = incident_directions(nd, seed, start, cosine)
    out = _alloc(nd * per)
    if isinstance(surface, Scene):
        surface._run(u, per, seed, start * per, out, MAX_BOUNCES, MAX_STEPS)
    else:
        _run(surface, u, per, seed, start * per, out)
    vdir, w, nb, absorbed, lost = out
    bu = basis.eval(u)  # (nd, K), once per direction (Westin eq 25)
    c = np.full(nd, np.pi) if cosine else 2.0 * np.pi * u[:, 2]
    bv = basis.eval(vdir)  # (nd * per, K)
    m = np.empty((bu.shape[1], bu.shape[1]))
    _accumulate_kernel(bu, c, bv, w, per, m)
    n = nd * per
    ms = 0.5 * (m + m.T)
    acc["sum"] += m
    acc["s2"] += ms * ms
    acc["ns"] += n * ms
    acc["n2"] += float(n) * n
    acc["chunks"] += 1
    acc["rays"] += n
    acc["reflected"] += float(w.sum())
    acc["absorbed"] += float(absorbed.sum())
    acc["lost"] += float(lost.sum())
    acc["bounces"] += np.bincount(np.minimum(nb, BOUNCE_BINS), weights=w,
                                  minlength=BOUNCE_BINS + 1)[1:]


@pjit
def _accumulate_kernel(bu, c, bv, w, per, m):
    # bu (D, K) b(U) per direction; c (D,) estimator constant; bv (D * per, K) b(V) per ray;
    # w (D * per,) exit weights; m (K, K) out: sum_d c_d b(U_d) S_d^T with the exit sums
    # S_d = sum_p w_dp b(V_dp) (Westin eq 25: one outer product per direction, not per ray).
    # No BLAS: its spinning threads fight numba's for the two cores.
    nd, kk = bu.shape
    sums = np.zeros((nd, kk))
    for d in prange(nd):
        for p in range(d * per, (d + 1) * per):
            f = w[p]
            if f != 0.0:
                for k in range(kk):
                    sums[d, k] += f * bv[p, k]
    for j in prange(kk):
        for k in range(kk):
            m[j, k] = 0.0
        for d in range(nd):
            a = c[d] * bu[d, j]
            for k in range(kk):
                m[j, k] += a * sums[d, k]


# -- checkpoints ------------------------------------------------------------------------------

def _check_writable(path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    try:
        if path.is_dir():
            raise IsADirectoryError(f"{path} is a directory")
        with open(tmp, "wb"):
            pass
        tmp.unlink()
    except OSError as err:
        raise ValueError(f"checkpoint must be a writable file path, got {str(path)!r} "
                         f"({err})") from None


def _save(path: Path, acc: dict[str, Any], meta: dict[str, Any], done: int) -> None:
    import h5py

    with atomic_path(path, suffix=".tmp") as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = _FORMAT
        f.attrs["directions_done"] = done
        for key, val in meta.items():
            f.attrs["meta_" + key] = val if key != "seeds" else np.asarray(val, np.uint64)
        for key, val in acc.items():
            f.create_dataset(key, data=val)


def _load(path: Path, meta: dict[str, Any], k: int) -> tuple[dict[str, Any], int]:
    import h5py

    if not path.is_file():
        raise FileNotFoundError(f"resume must name an existing checkpoint file, got "
                                f"{str(path)!r}")
    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != _FORMAT:
            raise ValueError(f"resume file {str(path)!r} is not a simulate checkpoint")
        names = {"surface": "surface", "basis": "basis", "seeds": "seed",
                 "incident": "incident", "targets": "targets", "chunk": "chunk"}
        for key, label in names.items():
            got = f.attrs["meta_" + key]
            got = [int(x) for x in got] if key == "seeds" else got
            got = int(got) if key in ("targets", "chunk") else got
            if got != meta[key]:
                raise ValueError(f"resume file {str(path)!r} is incompatible: it was made "
                                 f"with a different {label} ({got!r}, this run "
                                 f"{meta[key]!r})")
        acc = {key: (f[key][()] if f[key].shape else f[key][()].item()) for key in f}
        done = int(f.attrs["directions_done"])
    if acc["sum"].shape != (k, k):
        raise ValueError(f"resume file {str(path)!r} is incompatible: matrix shape "
                         f"{acc['sum'].shape}, basis needs ({k}, {k})")
    return acc, done
