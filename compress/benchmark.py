"""How small, and how accurate, measured materials become: the MERL benchmark.

:func:`benchmark_merl` runs :func:`compress.select` on every MERL ``.binary`` file of a
folder (Matusik et al. 2003 layout), one process per material, and writes

- ``materials.csv``: per material, for each tolerance, the smallest representation that
  meets it (its family, storage type, bytes, l2 and log errors) and, for the strictest
  tolerance, the image error: the relative RMS difference of
  :func:`compress.render_sphere` pictures under three lights (from the view direction, 45
  degrees and 75 degrees off it), the source BRDF against the representation;
- ``candidates.csv``: every measured candidate of every material (bytes and errors);
- ``pareto.png``: bytes against l2 error per family, every measured candidate and, per
  family, the median over the materials of the smallest error within each size, with two
  published sizes marked: the neural BRDF of Sztrajman et al.
  (CGF 2021, 675 float32 = 2.7 kB) and the non-parametric factored microfacet model of
  Bagher, Snyder & Nowrouzezahrai (ACM TOG 2016, 3.2 kB);
- ``summary.json``: medians and counts per tolerance.

Each material's result is written to ``materials/NAME.json`` as soon as it is done
(atomically), so a run that is stopped resumes where it was: finished materials are read
back, not recomputed.
"""

from __future__ import annotations

import contextlib
import csv
import functools
import json
import math
import multiprocessing
import os
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from basis.validation import dask_client
from project.io import atomic_path

from .render import render_sphere
from .selection import DEFAULT_CANDIDATES, NoCandidateError, select

__all__ = ["PUBLISHED", "benchmark_merl", "image_error"]

#: Published sizes of compact MERL representations (bytes per material), for the chart.
PUBLISHED = {"neural BRDF (Sztrajman et al. 2021)": 2700,
             "factored microfacet (Bagher et al. 2016)": 3200}
#: Lights of the image error: unit vectors in the frame of the view (0, 0, 1).
LIGHTS = ((0.0, 0.0, 1.0),
          (math.sin(math.radians(45.0)), 0.0, math.cos(math.radians(45.0))),
          (0.0, math.sin(math.radians(75.0)), math.cos(math.radians(75.0))))
_VIEW = (0.0, 0.0, 1.0)


def image_error(brdf: Any, approx: Any, *, size: int = 128) -> float:
    """Relative RMS difference of lit-sphere pictures, ``approx`` against ``brdf``.

    Parameters
    ----------
    brdf, approx : BRDF
        Objects with ``eval(wi, wo)`` (``approx`` may also be a coefficient matrix).
    size : int
        Image side in pixels (:func:`compress.render_sphere`).

    Returns
    -------
    float
        sqrt(sum (I_approx - I)^2 / sum I^2) over the pixels on the sphere, the channels
        and the three lights of :data:`LIGHTS` (view along z), each light of unit
        irradiance.
    """
    num = den = 0.0
    for light in LIGHTS:
        ref = render_sphere(brdf, light, size=size, view=_VIEW)
        img = render_sphere(approx, light, size=size, view=_VIEW)
        if img.ndim < ref.ndim:
            img = img[..., None]
        on = np.isfinite(ref)
        num += float(np.sum((np.broadcast_to(img, ref.shape)[on] - ref[on]) ** 2))
        den += float(np.sum(ref[on] ** 2))
    return math.sqrt(num / den) if den > 0 else math.nan


def benchmark_merl(folder: str | os.PathLike, out: str | os.PathLike, *,
                   tols: Sequence[float] = (0.05, 0.10), workers: int = 2,
                   materials: Iterable[str] | None = None,
                   candidates: Sequence[dict] | None = None, error_n: int = 1 << 16,
                   progress: bool = False, client: Any = None) -> list[dict[str, Any]]:
    """Run :func:`compress.select` on every MERL file of ``folder`` and chart the result.

    Parameters
    ----------
    folder : path
        A folder of MERL ``.binary`` files (``NAME.binary``).
    out : path
        Output folder (created): the files of the module notes.
    tols : sequence of float
        Tolerances on the l2 error; the representation is selected for the smallest and
        the others are read off the same candidate table (candidates are built in order
        of size, so everything smaller than the strictest answer has been measured).
    workers : int
        Processes, one material each at a time (1: in this process).
    materials : iterable of str, optional
        Names (without ``.binary``) to run; default all files of ``folder``.
    candidates : sequence of dict, optional
        Passed to :func:`compress.select` (default its :data:`DEFAULT_CANDIDATES`).
    error_n : int
        Pairs of the error estimate of :func:`compress.select`.
    progress : bool
        Show a progress bar (tqdm).
    client : dask.distributed.Client, optional
        Run the materials as tasks on this Dask cluster instead (one task per material;
        ``workers`` is then ignored). The workers must see ``folder`` and ``out`` (a shared
        file system) and have scatmodes installed.

    Returns
    -------
    list of dict
        One row per material, as written to ``materials.csv``.

    Raises
    ------
    RuntimeError
        Some materials failed (after the tables of the others are written); the message
        names the first and why. A new call retries only those.
    """
    folder, out = Path(folder), Path(out)
    if not folder.is_dir():
        raise NotADirectoryError(f"no folder of MERL files at {str(folder)!r}")
    tols = tuple(sorted(float(t) for t in tols))
    if not tols or not all(0 < t < math.inf for t in tols):
        raise ValueError(f"tols must be positive numbers, got {tols}")
    names = sorted(p.name[:-len(".binary")] for p in folder.glob("*.binary"))
    if materials is not None:
        wanted = list(materials)
        missing = sorted(set(wanted) - set(names))
        if missing:
            raise FileNotFoundError(f"no {missing[0]}.binary in {str(folder)!r} (and "
                                    f"{len(missing) - 1} more missing)")
        names = wanted
    if not names:
        raise FileNotFoundError(f"no .binary files in {str(folder)!r}")
    if client is not None:
        dask_client(client, "benchmark_merl")
    (out / "materials").mkdir(parents=True, exist_ok=True)
    todo = [n for n in names if not (out / "materials" / f"{n}.json").is_file()]
    job = dict(tols=tols, candidates=None if candidates is None else list(candidates),
               error_n=error_n)
    bar = _bar(len(names), len(names) - len(todo), progress)
    failed: dict[str, str] = {}  # a material that fails is reported; the others go on

    def settle(name: str, result: Callable[[], None]) -> None:
        try:
            result()
        except (ValueError, OSError, RuntimeError, MemoryError) as e:
            failed[name] = f"{type(e).__name__}: {e}"
        bar.update(1)

    def path(name: str) -> str:
        return str(folder / f"{name}.binary")

    if client is not None:
        from distributed import as_completed as dask_completed

        futures = {client.submit(_run_one, path(n), str(out), job, pure=False,
                                 key=f"scatmodes-benchmark-{n}"): n for n in todo}
        for fut in dask_completed(futures):
            settle(futures[fut], fut.result)
    elif workers <= 1 or len(todo) <= 1:
        for n in todo:
            settle(n, functools.partial(_run_one, path(n), str(out), job))
    else:
        with _threads_per_worker(workers), ProcessPoolExecutor(
                max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(_run_one, path(n), str(out), job): n for n in todo}
            for fut in as_completed(futures):
                settle(futures[fut], fut.result)
    bar.close()
    rows, cands = [], []
    names = [n for n in names if n not in failed]
    if not names:
        first = next(iter(failed.items()))
        raise RuntimeError(f"all {len(failed)} materials failed: {first[0]}: {first[1]}")
    for n in names:
        rec = json.loads((out / "materials" / f"{n}.json").read_text())
        rows.append(rec["row"])
        cands.extend({"material": n, **c} for c in rec["candidates"])
    _write_csv(out / "materials.csv", rows)
    _write_csv(out / "candidates.csv", cands)
    summary = _summary(rows, tols)
    with atomic_path(out / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=2))
    _chart(cands, out / "pareto.png")
    if failed:
        first = next(iter(failed.items()))
        raise RuntimeError(f"{len(failed)} of {len(failed) + len(names)} materials failed "
                           f"(the tables in {str(out)!r} hold the others; run again to retry "
                           f"them): {first[0]}: {first[1]}")
    return rows


#: Thread counts of BLAS (OpenMP, OpenBLAS, MKL) and numba, set for the worker processes.
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                     "NUMBA_NUM_THREADS")


@contextlib.contextmanager
def _threads_per_worker(workers: int) -> Iterator[None]:
    """Share the cores among the worker processes while they are started.

    Each worker would otherwise start a BLAS and a numba thread per core, and ``workers``
    processes would run ``workers`` times as many threads as there are cores (measured:
    an SVD inside a fit took 0.1 s instead of milliseconds). Fresh (spawned) processes
    read these variables when they import numpy and numba; this process is not changed.
    """
    per = str(max(1, (os.cpu_count() or 1) // workers))
    saved = {k: os.environ.get(k) for k in _THREAD_VARIABLES}
    os.environ.update({k: per for k in _THREAD_VARIABLES})
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _run_one(path: str, out: str, job: dict) -> None:
    """Select for one material and write materials/NAME.json (in a worker process)."""
    from project.measured import read_merl

    name = Path(path).name[:-len(".binary")]
    start = time.perf_counter()
    brdf = read_merl(path)
    tols = job["tols"]
    kwargs = dict(candidates=job["candidates"] or DEFAULT_CANDIDATES, error_n=job["error_n"])
    rep = None
    try:
        rep = select(brdf, tols[0], **kwargs)
        table = rep.info["candidates"]
    except NoCandidateError as e:
        table = e.candidates
    seconds = time.perf_counter() - start
    row: dict[str, Any] = {"material": name, "select_seconds": round(seconds, 2)}
    measured = [r for r in table if r["status"] == "measured"]
    for t in tols:
        ok = [r for r in measured if r["l2"] <= t]
        pick = min(ok, key=lambda r: (r["bytes"], r["l2"])) if ok else \
            min(measured, key=lambda r: r["l2"])
        key = f"{t:g}"
        row.update({f"meets_{key}": bool(ok), f"family_{key}": pick["family"],
                    f"label_{key}": pick["label"], f"dtype_{key}": pick["dtype"],
                    f"bytes_{key}": pick["bytes"], f"l2_{key}": pick["l2"],
                    f"l2_stderr_{key}": pick["l2_stderr"], f"log_{key}": pick["log"]})
        if t == tols[0]:
            if rep is None:  # the most accurate measured candidate, rebuilt by its own fit
                rep = select(brdf, math.inf, candidates=[pick["candidate"]],
                             dtypes=(pick["dtype"],), error_n=1024)
            row[f"image_{key}"] = image_error(brdf, rep)
    keep = ("label", "form", "family", "dtype", "bytes", "l2", "l2_stderr", "log",
            "seconds", "status")
    rec = {"row": row, "candidates": [{k: _plain(r[k]) for k in keep} for r in table]}
    target = Path(out) / "materials" / f"{name}.json"
    with atomic_path(target) as tmp:
        tmp.write_text(json.dumps(rec, default=_plain))


def _plain(v: Any) -> Any:
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        return v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _write_csv(path: Path, rows: list[dict]) -> None:
    keys: list[str] = []
    for r in rows:
        keys.extend(k for k in r if k not in keys)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)


def _summary(rows: list[dict], tols: tuple[float, ...]) -> dict[str, Any]:
    out: dict[str, Any] = {"materials": len(rows)}
    for t in tols:
        key = f"{t:g}"
        ok = [r for r in rows if r[f"meets_{key}"]]
        fams: dict[str, int] = {}
        for r in ok:
            fams[r[f"family_{key}"]] = fams.get(r[f"family_{key}"], 0) + 1
        out[key] = {
            "meet": len(ok),
            "median_bytes": float(np.median([r[f"bytes_{key}"] for r in ok])) if ok else None,
            "max_bytes": int(max(r[f"bytes_{key}"] for r in ok)) if ok else None,
            "median_l2": float(np.median([r[f"l2_{key}"] for r in rows])),
            "families": fams,
            "fail": [r["material"] for r in rows if not r[f"meets_{key}"]],
        }
    first = f"{tols[0]:g}"
    images = [r[f"image_{first}"] for r in rows if r.get(f"image_{first}") is not None]
    out["median_image_error"] = float(np.median(images)) if images else None
    out["median_select_seconds"] = float(np.median([r["select_seconds"] for r in rows]))
    return out


def _chart(cands: list[dict], path: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.5, 5.0), layout="constrained")
    ax = fig.add_subplot()
    measured = [c for c in cands if c["status"] == "measured" and c["l2"] is not None]
    families = sorted({c["family"] for c in measured})
    materials = sorted({c["material"] for c in cands})
    for i, fam in enumerate(families):
        pts = [(c["bytes"], c["l2"]) for c in measured if c["family"] == fam]
        x, y = np.array(pts, dtype=float).T
        colour = f"C{i % 10}"
        ax.scatter(x, y, s=6, alpha=0.25, color=colour, linewidths=0)
        sizes, med = _envelope(measured, fam, materials)
        ax.plot(sizes, med, "o-", ms=3, color=colour, label=f"{fam}")
    for i, (name, size) in enumerate(PUBLISHED.items()):
        ax.axvline(size, color="0.3", ls=("--", ":")[i % 2], lw=1)
        ax.text(size * 1.03, 0.95 - 0.07 * i, name, transform=ax.get_xaxis_transform(),
                fontsize=7, color="0.3")
    ax.axhline(0.05, color="0.6", lw=0.8)
    ax.axhline(0.10, color="0.6", lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("bytes per material")
    ax.set_ylabel("relative L2 error of f cos cos (peak-resolving)")
    ax.set_title(f"MERL materials: size against error ({len({c['material'] for c in cands})}"
                 " materials)")
    ax.legend(fontsize=7, loc="lower left")
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=120, format="png")


def _envelope(measured: list[dict], family: str,
              materials: list[str]) -> tuple[NDArray, NDArray]:
    """Median over the materials of the smallest error of ``family`` within each size.

    A material counts at a size once one of its candidates of the family fits in it. A
    candidate that was not built (a smaller one met the tolerance first) counts with the
    error of the smaller one, so the curve is an upper bound of the true envelope; it
    avoids the bias of plain medians per size, where only the hardest materials reach the
    large candidates.
    """
    own = [c for c in measured if c["family"] == family]
    sizes = np.unique([c["bytes"] for c in own])
    best = np.full((len(materials), sizes.size), np.inf)
    index = {m: k for k, m in enumerate(materials)}
    for c in own:
        k = index[c["material"]]
        j = np.searchsorted(sizes, c["bytes"])
        best[k, j:] = np.minimum(best[k, j:], c["l2"])
    counted = np.isfinite(best).sum(axis=0) >= max(1, len(materials) // 2)
    med = np.array([np.median(col[np.isfinite(col)]) if ok else np.nan
                    for col, ok in zip(best.T, counted, strict=True)])
    return sizes[counted], med[counted]


class _NoBar:
    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


def _bar(total: int, done: int, progress: bool) -> Any:
    if not progress:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, initial=done, desc="benchmark", unit="material")
