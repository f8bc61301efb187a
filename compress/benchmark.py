"""How small, and how accurate, measured materials become: the benchmark on real files.

:func:`benchmark_files` runs :func:`compress.select` on every measured file of a folder --
MERL ``.binary`` tables (Matusik et al. 2003 layout, :func:`project.measured.read_merl`),
RGL-EPFL ``.bsdf`` tensor files (Dupuy & Jakob 2018, :func:`project.measured.read_rgl`) and
NVIDIA MDL ``.mbsdf`` files (:func:`project.measured.read_mbsdf`), told apart by their
suffix, all kinds in one folder allowed -- one process per material,
and writes

- ``materials.csv``: per material its ``format`` ("merl", "rgl" or "mbsdf"); for each tolerance the
  smallest representation that meets it (its family, storage type, bytes, l2 and log
  errors; the most accurate measured one when none does); the reciprocity of the data
  (``reciprocity_residual``, ``reciprocity_floor`` and its standard error: the relative L2
  norm of the antisymmetric part, below which no reciprocal form can go,
  :func:`project.reciprocity`) and the forms ``select`` let compete on it (``forms``);
  ``best_l2``, ``best_bytes``: the smallest error any candidate reached, which is what a
  ``NoCandidateError`` leaves; ``select_seconds``: the time of :func:`compress.select` alone;
  and, for the strictest tolerance, the image error: the relative RMS difference of
  :func:`compress.render_sphere` pictures under three lights (from the view direction, 45
  degrees and 75 degrees off it), the source BRDF against the representation;
- ``candidates.csv``: every candidate of every material (bytes, errors, whether its form is
  reciprocal);
- ``pareto.png``: bytes against l2 error per family, every measured candidate and, per
  family, the median over the materials of the smallest error within each size; the
  non-reciprocal forms (full-turn factored lobes, general matrices) drawn dashed with
  square markers; two published sizes marked: the neural BRDF of Sztrajman et al.
  (CGF 2021, 675 float32 = 2.7 kB) and the non-parametric factored microfacet model of
  Bagher, Snyder & Nowrouzezahrai (ACM TOG 2016, 3.2 kB);
- ``summary.json``: medians and counts per tolerance, and the medians of the reciprocity
  residual and floor, the image error and the time of ``select``;
- ``materials/NAME.html``: the page of :func:`compress.report` on the
  representation selected at the strictest tolerance, against the measured file (errors,
  lobes, spheres, error by band, and the candidate table with the selected one marked).

:func:`benchmark_merl` is the same on the MERL files of a folder only.

Each material's result is written to ``materials/NAME.json`` as soon as it is done
(atomically), so a run that is stopped resumes where it was: finished materials are read
back, not recomputed. NAME is the file name without its suffix, so a folder must not hold
``NAME.binary`` and ``NAME.bsdf`` both.

Notes
-----
**Image error on RGL files.** An RGL file's f grows like 1 / cos(theta_o) towards grazing
views (it stores f cos theta_o, see :mod:`project.measured.rgl`); the pictures hold
L = f cos theta_i, so the rim of the sphere is brighter than in a reciprocal BRDF, but the
pixels there are few: on ``paper_white_rgb.bsdf`` (size 128) the pixels with
cos theta_o < 0.1, 1.1 % of the disc, hold at most 2.6 % of the sum of squares of the
reference picture (under the 75-degree light; 1.1 % at 45 degrees, none with the light at
the view), so the image error is not dominated by the horizon.

**Measured example** (the eight RGL-EPFL files of ``../shared/data/rgl``, default
candidates, tolerances 0.10 and 0.05, 2 workers on 2 cores, 2 min 22 s in all; bytes and l2
of the smallest representation within each tolerance, float16 unless marked; floor the
reciprocity floor; seconds of select, both tolerances):

======================  ======  ========================  ========================  =======
file                    floor   0.10: form, B, l2         0.05: form, B, l2         seconds
======================  ======  ========================  ========================  =======
paper_white             0.022   Lambert+GGX, 16, 0.043    the same                  1.3
colodur_napoli_4f       0.051   factored, 124, 0.095      factored+Zernike, 720     10.5
ilm_l3_37_metallic      0.114   factored, 312 (f32)       Tucker, 502, 0.023        8.0
ilm_l3_37_matte         0.078   factored, 306, 0.094      Tucker, 2028, 0.047       25.7
cm_military_green       0.117   Tucker, 510, 0.084        Tucker, 2030, 0.045       21.5
cc_nothern_aurora       0.260   Tucker, 1006, 0.067       Tucker, 2034, 0.041       23.9
vch_golden_yellow       0.087   Tucker, 512, 0.072        Tucker, 2028, 0.036       45.6
chm_orange              0.408   Tucker, 2044, 0.095       Tucker, 8060, 0.042       29.0
======================  ======  ========================  ========================  =======

The paper is a Lambertian plus GGX lobe; the matte paint a rank-1 factored lobe at 0.10
and a full-turn factored lobe with a general Zernike residual at 0.05 (its floor exceeds
0.05); the films and the other paints full-turn Tucker tensors (:mod:`project.tucker`).
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

from .report import LIGHTS, PUBLISHED, image_error, report
from .selection import DEFAULT_CANDIDATES, NoCandidateError, _is_reciprocal, select

__all__ = ["FORMATS", "LIGHTS", "PUBLISHED", "benchmark_files", "benchmark_merl",
           "image_error"]

#: Measured file formats the benchmark reads, by suffix.
FORMATS = {"merl": ".binary", "rgl": ".bsdf", "mbsdf": ".mbsdf"}
#: Names of the formats in messages and titles.
_FORMAT_NAMES = {"merl": "MERL", "rgl": "RGL", "mbsdf": "MDL"}
#: Seed of select's error pairs (its default), with which the reciprocity of a material
#: that met no tolerance is measured again: the same pairs as select's own measurement.
_PAIR_SEED = 2027

def benchmark_merl(folder: str | os.PathLike, out: str | os.PathLike, *,
                   tols: Sequence[float] = (0.05, 0.10), workers: int = 2,
                   materials: Iterable[str] | None = None,
                   candidates: Sequence[dict] | None = None, error_n: int = 1 << 16,
                   progress: bool = False, client: Any = None) -> list[dict[str, Any]]:
    """Run :func:`compress.select` on every MERL file of ``folder`` and chart the result.

    :func:`benchmark_files` with ``formats=("merl",)``: the same arguments, tables and
    errors; ``folder`` holds MERL ``.binary`` files (``NAME.binary``), other files are
    ignored.
    """
    return benchmark_files(folder, out, formats=("merl",), tols=tols, workers=workers,
                           materials=materials, candidates=candidates, error_n=error_n,
                           progress=progress, client=client)


def benchmark_files(folder: str | os.PathLike, out: str | os.PathLike, *,
                    formats: Iterable[str] = tuple(FORMATS),
                    tols: Sequence[float] = (0.05, 0.10), workers: int = 2,
                    materials: Iterable[str] | None = None,
                    candidates: Sequence[dict] | None = None, error_n: int = 1 << 16,
                    progress: bool = False, client: Any = None) -> list[dict[str, Any]]:
    """Run :func:`compress.select` on every measured file of ``folder`` and chart the result.

    Parameters
    ----------
    folder : path
        A folder of measured files: MERL ``NAME.binary``, RGL-EPFL ``NAME.bsdf`` and MDL
        ``NAME.mbsdf`` (of the ``formats`` asked for; files with other suffixes are ignored).
    out : path
        Output folder (created): the files of the module notes.
    formats : iterable of str
        Which of :data:`FORMATS` to read (default all).
    tols : sequence of float
        Tolerances on the l2 error; the representation is selected for the smallest and
        the others are read off the same candidate table (candidates are built in order
        of size, so everything smaller than the strictest answer has been measured).
    workers : int
        Processes, one material each at a time (1: in this process).
    materials : iterable of str, optional
        Names (file names without the suffix) to run; default all files of ``folder``.
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
    NotADirectoryError
        ``folder`` is not a folder.
    FileNotFoundError
        No file of the formats in ``folder``, or a name of ``materials`` without its file.
    ValueError
        Bad ``formats`` or ``tols``, or two files of one name (``NAME.binary`` and
        ``NAME.bsdf``).
    RuntimeError
        Some materials failed (after the tables of the others are written); the message
        names the first and why. A new call retries only those.
    """
    folder, out = Path(folder), Path(out)
    kinds = tuple(dict.fromkeys([formats] if isinstance(formats, str) else formats))
    if not kinds or not set(kinds) <= set(FORMATS):
        raise ValueError(f"formats must name some of {tuple(FORMATS)}, got {formats!r}")
    suffixes = [FORMATS[k] for k in kinds]
    what = _listed([f"{_FORMAT_NAMES[k]} {FORMATS[k]}" for k in kinds], "and")
    if not folder.is_dir():
        kind = _FORMAT_NAMES[kinds[0]] if len(kinds) == 1 else f"measured ({what})"
        raise NotADirectoryError(f"no folder of {kind} files at {str(folder)!r}")
    tols = tuple(sorted(float(t) for t in tols))
    if not tols or not all(0 < t < math.inf for t in tols):
        raise ValueError(f"tols must be positive numbers, got {tols}")
    files: dict[str, Path] = {}
    for f in sorted(folder.iterdir()):
        if f.suffix not in suffixes or not f.is_file():
            continue
        if f.stem in files:
            raise ValueError(f"two files of the material {f.stem!r} in {str(folder)!r}: "
                             f"{files[f.stem].name} and {f.name}; rename one")
        files[f.stem] = f
    names = sorted(files)
    if materials is not None:
        wanted = list(materials)
        missing = sorted(set(wanted) - set(names))
        if missing:
            raise FileNotFoundError(
                f"no {_listed([missing[0] + x for x in suffixes], 'or')} in {str(folder)!r} "
                f"(and {len(missing) - 1} more missing)")
        names = wanted
    if not names:
        raise FileNotFoundError(f"no {_listed(suffixes, 'or')} files in {str(folder)!r}")
    if client is not None:
        dask_client(client, "benchmark_merl" if kinds == ("merl",) else "benchmark_files")
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
        return str(files[name])

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
    kinds_run = sorted({r.get("format", "merl") for r in rows})
    _chart(cands, out / "pareto.png",
           " and ".join(_FORMAT_NAMES[k] for k in kinds_run) + " materials")
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
    """Select for one material and write materials/NAME.json (in a worker process).

    select runs at the strictest tolerance and the others are read off its table, unless
    its reciprocity decision, which depends on the tolerance, lets other forms compete at
    a looser one and it left some candidates out at the strictest (a floor above the
    strictest tolerance but below a looser one lets the reciprocal forms, about half the
    size, compete at the looser one only); then it runs again at that tolerance.
    """
    from project.measured import read_mbsdf, read_merl, read_rgl

    p = Path(path)
    kind = next(k for k, suffix in FORMATS.items() if p.suffix == suffix)
    name = p.stem
    brdf = {"merl": read_merl, "rgl": read_rgl, "mbsdf": read_mbsdf}[kind](p)
    tols = job["tols"]
    strict = _select(brdf, tols[0], job)
    runs = {tols[0]: strict}
    for t in tols[1:]:
        forms = _forms_at(strict["reciprocity"], t)
        if forms == strict["reciprocity"]["forms"] or not _why(strict["table"]):
            runs[t] = {**strict, "seconds": 0.0,
                       "reciprocity": {**strict["reciprocity"], "forms": forms}}
        else:
            runs[t] = _select(brdf, t, job)
    first = runs[tols[0]]
    measured = _merged([r["table"] for r in runs.values()])
    measured = [r for r in measured if r["status"] == "measured"]
    if not measured:
        raise RuntimeError(f"no candidate of {name} could be measured: "
                           f"{first['table'][0]['status'] if first['table'] else '-'}")
    best = min(measured, key=lambda r: (r["l2"], r["bytes"]))
    rec = first["reciprocity"]
    row: dict[str, Any] = {
        "material": name, "format": kind,
        "reciprocity_residual": rec["residual"], "reciprocity_floor": rec["floor"],
        "reciprocity_floor_stderr": rec["floor_stderr"],
        "best_l2": best["l2"], "best_bytes": best["bytes"], "best_label": best["label"],
        "select_seconds": round(sum(r["seconds"] for r in runs.values()), 2)}
    for t in tols:
        own = [r for r in runs[t]["table"] if r["status"] == "measured"]
        ok = [r for r in own if r["l2"] <= t]
        pick = min(ok, key=lambda r: (r["bytes"], r["l2"])) if ok else \
            min(own or measured, key=lambda r: (r["l2"], r["bytes"]))
        key = f"{t:g}"
        row.update({f"meets_{key}": bool(ok), f"family_{key}": pick["family"],
                    f"label_{key}": pick["label"], f"dtype_{key}": pick["dtype"],
                    f"reciprocal_{key}": _is_reciprocal(pick["candidate"]),
                    f"bytes_{key}": pick["bytes"], f"l2_{key}": pick["l2"],
                    f"l2_stderr_{key}": pick["l2_stderr"], f"log_{key}": pick["log"],
                    f"forms_{key}": "+".join(runs[t]["reciprocity"]["forms"]),
                    f"seconds_{key}": round(runs[t]["seconds"], 2)})
        if t == tols[0]:
            rep = first["rep"]
            if rep is None:  # the most accurate measured candidate, rebuilt by its own fit
                rep = select(brdf, math.inf, candidates=[pick["candidate"]],
                             dtypes=(pick["dtype"],), error_n=1024,
                             reciprocal=_is_reciprocal(pick["candidate"]))
            row[f"image_{key}"] = image_error(brdf, rep)
            report(rep, brdf, Path(out) / "materials" / f"{name}.html",
                   title=f"{name}: {pick['label']} at {pick['dtype']}")
    keep = ("label", "form", "family", "dtype", "bytes", "l2", "l2_stderr", "log",
            "seconds", "status")
    cands = [{**{k: _plain(r[k]) for k in keep}, "reciprocal": _is_reciprocal(r["candidate"])}
             for r in _merged([r["table"] for r in runs.values()])]
    recorded = {k: _plain(rec[k]) for k in ("residual", "floor", "floor_stderr")}
    recorded.update(forms={f"{t:g}": r["reciprocity"]["forms"] for t, r in runs.items()},
                    why={f"{t:g}": r["reciprocity"]["why"] for t, r in runs.items()})
    record = {"row": {k: _plain(v) for k, v in row.items()}, "candidates": cands,
              "reciprocity": recorded}
    target = Path(out) / "materials" / f"{name}.json"
    with atomic_path(target) as tmp:
        tmp.write_text(json.dumps(record, default=_plain))


def _select(brdf: Any, tol: float, job: dict) -> dict[str, Any]:
    """Run select at ``tol``; return what the benchmark keeps of it.

    A dict: ``rep`` (None when no candidate met ``tol``), ``table``, ``reciprocity``
    (residual, floor, floor_stderr, forms, why) and ``seconds``.
    """
    import project
    from project.reciprocity import MIN_PAIRS

    candidates = job["candidates"] or DEFAULT_CANDIDATES
    start = time.perf_counter()
    try:
        rep = select(brdf, tol, candidates=candidates, error_n=job["error_n"])
    except NoCandidateError as e:
        seconds = time.perf_counter() - start
        # measured as select does (on its pairs), so the decision is select's
        r = project.reciprocity(brdf, n=max(job["error_n"], MIN_PAIRS), seed=_PAIR_SEED)
        rec = dict(residual=r.residual, floor=r.floor, floor_stderr=r.floor_stderr)
        rec.update(forms=_forms_at(rec, tol), why=_why(e.candidates))
        return dict(rep=None, table=e.candidates, reciprocity=rec, seconds=seconds)
    seconds = time.perf_counter() - start
    info = rep.info["reciprocity"]
    rec = {k: info[k] for k in ("residual", "floor", "floor_stderr", "forms", "why")}
    return dict(rep=rep, table=rep.info["candidates"], reciprocity=rec, seconds=seconds)


def _forms_at(rec: dict[str, Any], tol: float) -> list[str]:
    """Return the forms select's reciprocity decision lets compete at ``tol``."""
    from types import SimpleNamespace

    from .selection import _reciprocal_forms

    floor = math.nan if rec["floor"] is None else rec["floor"]
    se = math.nan if rec["floor_stderr"] is None else rec["floor_stderr"]
    allowed, _ = _reciprocal_forms(SimpleNamespace(floor=floor, floor_stderr=se, note=""),
                                   tol, None, False)
    return sorted("reciprocal" if a else "non-reciprocal" for a in allowed)


def _merged(tables: list[list[dict]]) -> list[dict]:
    """Return the first table with the candidates measured only in the later ones added."""
    out = list(tables[0])
    seen = {(r["label"], r["dtype"]) for r in out if r["status"] == "measured"}
    for table in tables[1:]:
        for r in table:
            if r["status"] == "measured" and (r["label"], r["dtype"]) not in seen:
                seen.add((r["label"], r["dtype"]))
                out = [o for o in out if (o["label"], o["dtype"]) != (r["label"], r["dtype"])]
                out.append(r)
    out.sort(key=lambda r: (r["bytes"] is None, r["bytes"] or 0, r["label"]))
    return out


#: Start of the status of a candidate that select left out for its form (reciprocal or not).
_SKIPPED_FORM = ("skipped: a reciprocal form (", "skipped: a non-reciprocal form (")


def _why(table: list[dict]) -> str:
    """Return select's reason for the forms, from a candidate it left out ("" if none)."""
    for r in table:
        for start in _SKIPPED_FORM:
            if r["status"].startswith(start):
                return r["status"][len(start):-1]
    return ""


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
            # what a NoCandidateError left: the smallest error reached, and the floor
            "fail_best": {r["material"]: {"l2": r[f"l2_{key}"],
                                          "floor": r.get("reciprocity_floor")}
                          for r in rows if not r[f"meets_{key}"]},
        }
    first = f"{tols[0]:g}"
    out["median_image_error"] = _median(r.get(f"image_{first}") for r in rows)
    out["median_select_seconds"] = _median(r.get("select_seconds") for r in rows)
    out["max_select_seconds"] = max((r["select_seconds"] for r in rows), default=None)
    # runs written before the reciprocity columns existed have none (their data: MERL)
    out["median_reciprocity_residual"] = _median(r.get("reciprocity_residual") for r in rows)
    out["median_reciprocity_floor"] = _median(r.get("reciprocity_floor") for r in rows)
    out["formats"] = {k: sum(r.get("format", "merl") == k for r in rows) for k in FORMATS}
    return out


def _listed(items: Sequence[str], word: str) -> str:
    """Return 'a', 'a or b', 'a, b or c' (``word`` joins the last two)."""
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])} {word} {items[-1]}"


def _median(values: Iterable[Any]) -> float | None:
    """Median of the finite numbers among ``values`` (None, NaN left out); None if none."""
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return float(np.median(v)) if v else None


def _chart(cands: list[dict], path: Path, title: str = "measured materials") -> list[str]:
    """Draw the chart of the module notes; return the labels of its legend."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.5, 5.0), layout="constrained")
    ax = fig.add_subplot()
    measured = [c for c in cands if c["status"] == "measured" and c["l2"] is not None]
    # a family's reciprocal and non-reciprocal forms (half- and full-turn factored lobes,
    # symmetric and general matrices) are drawn apart; records written before the
    # non-reciprocal forms existed hold reciprocal ones only
    groups = sorted({_group(c) for c in measured}, key=lambda g: (not g[1], g[0]))
    materials = sorted({c["material"] for c in cands})
    colours: dict[str, str] = {}
    for fam, reciprocal in groups:
        colour = colours.setdefault(fam, f"C{len(colours) % 10}")
        own = [c for c in measured if _group(c) == (fam, reciprocal)]
        x, y = np.array([(c["bytes"], c["l2"]) for c in own], dtype=float).T
        marker, line = ("o", "-") if reciprocal else ("s", "--")
        ax.scatter(x, y, s=6, alpha=0.25, color=colour, marker=marker, linewidths=0)
        sizes, med = _envelope(own, materials)
        ax.plot(sizes, med, marker=marker, ls=line, ms=3, color=colour,
                label=fam if reciprocal else f"{fam}, non-reciprocal")
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
    ax.set_title(f"{title}: size against error ({len(materials)} materials)")
    ax.legend(fontsize=7, loc="lower left")
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    return [t.get_text() for t in ax.get_legend().get_texts()]


def _group(c: dict) -> tuple[str, bool]:
    return c["family"], bool(c.get("reciprocal", True))


def _envelope(own: list[dict], materials: list[str]) -> tuple[NDArray, NDArray]:
    """Median over the materials of the smallest error of one family within each size.

    ``own`` holds the measured candidates of the family (of one form, reciprocal or not).
    A material counts at a size once one of its candidates of the family fits in it. A
    candidate that was not built (a smaller one met the tolerance first) counts with the
    error of the smaller one, so the curve is an upper bound of the true envelope; it
    avoids the bias of plain medians per size, where only the hardest materials reach the
    large candidates.
    """
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
