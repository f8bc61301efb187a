"""The smallest representation of a BRDF that meets an error tolerance: :func:`select`.

Candidates of three forms compete, each at several storage precisions:

- ``"modal"``: a coefficient matrix in one of the bases of :mod:`basis` (a kind and an
  order, optionally a low-rank truncation), projected by :func:`project.project`;
- ``"model"``: a fitted model of :func:`project.fit_model` (a parametric family, or the
  tabulated ``"factored"`` family at a rank and table size);
- ``"hybrid"``: a fitted lobe plus a modal residual (:func:`compress.hybrid`).

Bytes are the stored reals times the size of the storage type (``float16``, ``float32``
or ``float64``: what ``compress.save(..., dtype=...)`` writes, the header aside). Each
candidate's error is measured after rounding to its storage type, against the BRDF, on
one set of pairs of :func:`project.sampling.peak_resolving_pairs` -- half uniform over
H x H, half concentrated about the mirror direction -- so a sharp specular peak is
resolved, grazing configurations are included, and the errors of all candidates are
paired (measured on the same pairs, so their differences are far more precise than their
standard errors). The pairs are independent of every fit.

Candidates are built in order of increasing (predicted) bytes, and building stops once
the next one could not be smaller than the smallest that already meets the tolerance: the
result is the smallest in the whole list, without fitting what cannot win. The table in
``info["candidates"]`` says for each one whether it was measured or why not.

**Measurements.** Given a :class:`project.Measurements` (scattered samples, e.g. a
gonioreflectometer's) instead of a BRDF, every candidate is fitted to the samples (models
by :func:`project.fit_model`, expansions by least squares, :func:`project.fit`) and its
error is cross-validated: k-fold (default 10) on held-out samples, each fold's fit rounded
to the storage type before it predicts, the folds grouped as :meth:`project.Measurements.
folds` groups twin pairs, and a standard error over the folds. The default candidates are
then :data:`SAMPLE_CANDIDATES`: compact models first, since an expansion of a few thousand
samples at a few incidence angles cannot follow a narrow highlight between them (see
:func:`project.fit`).

Why the three forms: a narrow specular peak holds almost all of the L2 norm of a glossy
material, which truncated expansions resolve only at orders far beyond their size budget
(above 90 % error at order 24 on metals and plastics), while a few kilobytes of tables in
the half/difference angles of Rusinkiewicz (1998) hold it; broad materials (fabrics,
matte paints) are often smallest as a low-order expansion. Between the factored lobes (sums
of products of 1-D tables, which cannot hold how a sharp lobe changes shape with theta_d
and phi_d) and full tables, the Tucker tensors of :mod:`project.tucker` hold that coupling
in a few kilobytes: on eight real RGL-EPFL films and paints every material met 10 % within
2.1 kB and 5 % within 8.1 kB (float16), where the full-turn factored lobes reached at
best 0.23 on a glossy film and the tables needed 17.5 MB.

**The source's size.** No candidate larger than the file it compresses is built
(``source_bytes``, by default the size of ``brdf.path``): a 659 kB RGL file is never
answered by a 17.5 MB table. When nothing smaller meets the tolerance,
:class:`NoCandidateError` says what the best candidate reached and how large the source is.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import basis
import project
from basis import CoefficientMatrix
from basis.validation import as_directions, choice, nonneg_int
from project.crossval import sample_errors
from project.factored import reuse_samples
from project.measurements import FOLDS
from project.reciprocity import MIN_PAIRS
from project.sampling import peak_resolving_pairs, value_errors
from project.tucker import tucker_reals

from .hybrid import Hybrid
from .hybrid import hybrid as make_hybrid
from .scene import Environment
from .truncate import PRECISIONS, lowrank, precision, unique_coefficients

__all__ = ["DEFAULT_CANDIDATES", "SAMPLE_CANDIDATES", "NoCandidateError", "select"]

FORMS = ("modal", "model", "hybrid")
#: Stopping tolerance of the factored fits among the default candidates: on the
#: gold-metallic-paint3 surrogate (rank 4) 1e-4 stops after 181 sweeps instead of 283 at
#: 1e-6 with the same l2 error (0.0442 on independent pairs).
_FACTORED_TOL = 1e-4
METRICS = ("l2", "log")
#: Budgets (stored reals) of the Tucker candidates among the defaults.
TUCKER_BUDGETS = (256, 512, 1024, 2048, 4096, 8192, 16384)
#: The finer grid of the last Tucker candidates (project.tucker.GRID is the default).
FINE_GRID = (384, 96, 192)
#: The default candidates: parametric lobes, a ladder of factored tables, low orders of
#: the Zernike basis (broad materials) and factored lobes with a Zernike residual.
DEFAULT_CANDIDATES: tuple[dict[str, Any], ...] = (
    {"form": "model", "family": "lambert+ggx", "restarts": 2},
    *({"form": "model", "family": "factored", "rank": r, "bins": b, "tol": _FACTORED_TOL}
      for r, b in ((1, (32, 24)), (2, (32, 24)), (3, (24, 16, 8)), (4, (32, 24, 8)),
                   (5, (32, 24, 8)), (6, (40, 24, 8)), (8, (48, 32, 8)))),
    {"form": "modal", "kind": "zernike", "order": 4},
    {"form": "modal", "kind": "zernike", "order": 8},
    {"form": "modal", "kind": "zernike", "order": 12},
    *({"form": "hybrid", "family": "factored", "rank": r, "bins": b, "tol": _FACTORED_TOL,
       "kind": "zernike", "order": n} for r, b, n in ((4, (32, 24, 8), 4),
                                                       (6, (40, 24, 8), 6))),
    # non-reciprocal forms, for data whose antisymmetric part the tolerance cannot absorb
    # (competing only when select's reciprocity decision lets them): factored lobes whose
    # phi_d factor covers the whole turn (16 nodes: the resolution of 8 over half a turn)
    # and general matrices
    *({"form": "model", "family": "factored", "rank": r, "bins": b, "tol": _FACTORED_TOL,
       "phi_turn": "full"} for r, b in ((1, (32, 24, 16)), (2, (32, 24, 16)),
                                        (3, (24, 16, 16)), (4, (32, 24, 16)),
                                        (6, (40, 24, 16)), (8, (48, 32, 16)))),
    {"form": "modal", "kind": "zernike", "order": 4, "reciprocal": False},
    {"form": "modal", "kind": "zernike", "order": 8, "reciprocal": False},
    {"form": "hybrid", "family": "factored", "rank": 4, "bins": (32, 24, 16),
     "tol": _FACTORED_TOL, "phi_turn": "full", "kind": "zernike", "order": 4,
     "reciprocal": False},
    # Tucker tensors of piecewise-linear curves (project.tucker): the coupling of the angles
    # that factored lobes lack, at budgets of 0.5 to 32 kB in float16; over half the turn
    # (reciprocal) and the whole turn (not)
    *({"form": "model", "family": "tucker", "budget": n, "phi_turn": turn}
      for n in TUCKER_BUDGETS for turn in ("half", "full")),
    # the same on a finer grid, whose own floor is lower (a glossy film: 0.011 instead of
    # 0.020): built only when no smaller candidate met the tolerance (each after the default
    # grid's candidate of its budget)
    *({"form": "model", "family": "tucker", "budget": n, "phi_turn": turn,
       "grid": FINE_GRID} for n in TUCKER_BUDGETS[-2:] for turn in ("half", "full")),
    # the ladder's end: tables of q in the half/difference angles (project.tabulated), which
    # meet any tolerance down to their interpolation floor (second order in the cell size;
    # 10 % at 9 to 37 kB on three RGL-EPFL files), up to the resolution of the MERL grid
    # (90 x 90 x 360: 0.2-1.1 % on those files, 0.6 % on the green-acrylic MERL surrogate,
    # 8.7 MB at float16 over half a turn); none larger than the source file is built
    *({"form": "model", "family": "tabulated", "bins": b, "phi_turn": turn}
      for b in ((16, 12, 4), (16, 12, 8), (24, 16, 16), (32, 24, 16), (48, 32, 32),
                (90, 90, 360))
      for turn in ("half", "full")),
    # the grid of an NVIDIA MDL measured BSDF (project.fitting.grid), at the source's own
    # resolution when it has one: the only form that holds what a coarse file makes of a
    # lobe narrower than its cells (a car paint's clear coat); reciprocal part and whole
    *({"form": "model", "family": "grid", "symmetric": s} for s in (True, False)),
)
#: The default candidates for measurements: parametric models (the factored tables need a
#: BRDF that can be evaluated anywhere), low orders of the Zernike basis fitted by least
#: squares, and microfacet lobes with a low-order residual. The first is
#: ``fit_model(meas, "lambert+ggx")`` with its defaults, cross-validated on the same folds,
#: so whatever select returns within a tolerance that fit meets predicts held-out samples
#: at least as well (up to storage rounding). A lobe fitted in the log metric is judged in
#: l2 like the others: it follows the shape of a sharp highlight rather than its few
#: brightest samples, and predicts held-out samples better on some glossy paints
#: (cross-validated l2 0.38-0.48 instead of 0.62-0.68, two fold seeds, on the Cornell
#: krylon-blue table at 450, 550 and 650 nm).
SAMPLE_CANDIDATES: tuple[dict[str, Any], ...] = (
    {"form": "model", "family": "lambert+ggx"},
    {"form": "model", "family": "lambert+ggx", "restarts": 2, "fit_metric": "log"},
    {"form": "model", "family": "lambert+beckmann", "restarts": 2},
    {"form": "model", "family": "lafortune", "lobes": 1, "restarts": 2},
    {"form": "model", "family": "lafortune", "lobes": 2, "restarts": 4},
    {"form": "modal", "kind": "zernike", "order": 2},
    {"form": "modal", "kind": "zernike", "order": 4},
    {"form": "modal", "kind": "zernike", "order": 8},
    {"form": "hybrid", "family": "lambert+ggx", "kind": "zernike", "order": 2},
    {"form": "hybrid", "family": "lambert+ggx", "kind": "zernike", "order": 4},
)
_FIT_KEYS = frozenset(project.fitting.GRID_OPTIONS) | frozenset(
    project.fitting.FACTORED_OPTIONS) | frozenset(
    project.fitting.TABULATED_OPTIONS) | frozenset(project.fitting.TUCKER_OPTIONS) | {
        "restarts", "lobes", "n", "max_nfev", "fit_metric"}
_KEYS = {"modal": {"kind", "order", "rank", "reciprocal"},
         "model": {"family"} | _FIT_KEYS,
         "hybrid": {"family", "kind", "order", "reciprocal"} | _FIT_KEYS}
#: ``reciprocal`` of :func:`select`: decide from the data, reciprocal forms only, or
#: non-reciprocal forms only.
RECIPROCAL_CHOICES = (None, True, False)
#: Families whose ``phi_turn`` says whether they are reciprocal ("half", the default of a
#: candidate) or not ("full").
_TURNED = ("factored", "tabulated", "tucker")


class NoCandidateError(ValueError):
    """No candidate of :func:`select` met the tolerance; ``candidates`` holds the table."""

    def __init__(self, message: str, candidates: list[dict[str, Any]]) -> None:
        super().__init__(message)
        self.candidates = candidates


@dataclass
class _Build:
    """One candidate structure (everything but the storage type) and how to make it."""

    spec: dict[str, Any]
    label: str
    bytes_per_real: int | None  # stored reals, or None when unknown before building
    dtypes: tuple[str, ...]
    rows: list[dict[str, Any]] = field(default_factory=list)

    def bytes(self, dtype: str) -> int | None:
        n = self.bytes_per_real
        return None if n is None else n * np.dtype(dtype).itemsize


def select(brdf: Any, tol: float, *, metric: str = "l2",
           candidates: Iterable[Mapping[str, Any]] | None = None,
           scene: Mapping[str, Any] | None = None,
           dtypes: Iterable[str] = ("float16", "float32", "float64"),
           error_n: int = 1 << 16, seed: int | None = None, exhaustive: bool = False,
           progress: bool = False, folds: int = FOLDS, reciprocal: bool | None = None,
           source_bytes: int | None = None) -> Any:
    """Return the representation of ``brdf`` with the fewest bytes whose error is <= ``tol``.

    Parameters
    ----------
    brdf : BRDF or project.Measurements
        Any object with ``eval(wi, wo)``, ``channels`` and ``isotropic`` returning finite
        values >= 0: an analytic model, :func:`project.measured.read_merl`, ...; or
        scattered measurements, whose candidates are fitted to the samples and judged by
        cross-validation (module notes).
    tol : float
        Tolerance, > 0, on ``metric`` (or on the radiance error with ``scene``); ``inf``
        returns the smallest candidate that can be built.
    metric : {"l2", "log"}
        ``"l2"``: relative L2 error of q = f cos(theta_i) cos(theta_o) over H x H, the
        largest over the channels; ``"log"``: RMS of log(1 + f cos(theta_i)) differences
        (:mod:`project.sampling`).
    candidates : iterable of dict, optional
        Each a dict with ``"form"`` (``"modal"``, ``"model"`` or ``"hybrid"``) and:
        modal: ``"kind"`` (one of :data:`basis.KINDS`), ``"order"``, optionally ``"rank"``
        (:func:`compress.lowrank`; bytes count the eigen-terms, one eigenvalue and one
        vector each); model: ``"family"`` and options of :func:`project.fit_model`
        (``"rank"``, ``"bins"``, ``"restarts"``, ..., and ``"fit_metric"``, the metric the
        fit minimises, default "l2"); hybrid: ``"family"``, its options,
        ``"kind"`` and ``"order"`` of the residual. Optionally ``"dtypes"``, overriding
        ``dtypes``. Default :data:`DEFAULT_CANDIDATES`.
    scene : dict, optional
        ``{"lights": Environment or (n, 3) directions, "views": (m, 3) directions}``, and
        optionally ``"light_weights"`` (for directions) and ``"resolution"`` (of the latlong
        grid an SH environment is sampled on, default 128 rows): measure each candidate
        by the radiance it reflects towards the views under those lights
        (:meth:`Environment.radiance`), relative RMS over the views, largest over the
        channels -- only what the scene can see counts. ``metric`` is then reported but
        does not decide.
    dtypes : iterable of str
        Storage types tried for every candidate (of :data:`compress.truncate.PRECISIONS`).
    error_n : int
        Pairs of the error estimate (:func:`project.sampling.peak_resolving_pairs`).
    seed : int, optional
        Seeds the error pairs (default 2027; fits use their own seeds, so the errors are
        independent), or, for measurements, the assignment of samples to folds (default 0,
        the folds of :func:`project.fit_model`'s own cross-validation, so that a candidate
        and the same fit made alone report the same error).
    exhaustive : bool
        Build and measure every candidate, also those that cannot be the smallest (for
        charts of bytes against error).
    progress : bool
        Print one line per candidate built.
    folds : int
        Measurements only: folds of the cross-validation, >= 2.
    reciprocal : {None, True, False}
        Which forms compete (module notes). Reciprocity is measured first
        (:func:`project.reciprocity`): the floor is the relative L2 norm of the data's
        antisymmetric part, which no reciprocal form can go below. ``None`` decides from
        it: reciprocal forms only when the floor is at most half the tolerance (two
        standard errors spared; they are about half the size), non-reciprocal forms only
        when the floor exceeds the tolerance, both otherwise. ``True``: reciprocal forms
        only, and the errors are measured against the reciprocal part of the data,
        (f(w_i, w_o) + f(w_o, w_i)) / 2 (the floor is reported, not counted). ``False``:
        non-reciprocal forms only (a full-turn factored lobe, ``phi_turn="full"``; a
        general matrix, ``"reciprocal": False`` in a modal or hybrid candidate).
        ``info["reciprocity"]`` records the measurement and the decision.
    source_bytes : int, optional
        The size of the source's own file: no candidate larger than it is built (a
        representation larger than its data is not compression). Default: the size of
        ``brdf.path`` when the BRDF was read from a file (:func:`project.measured.read_rgl`,
        :func:`~project.measured.read_merl`, ...), else no limit. ``info["source_bytes"]``
        records it.

    Returns
    -------
    basis.CoefficientMatrix, project.FittedModel or compress.Hybrid
        Rounded to its storage type (held as float64). ``info`` gains ``"selected"`` (its
        row of the table), ``"bytes"``, ``"dtype"`` and ``"candidates"``: one dict per
        candidate and storage type with ``label``, ``form``, ``candidate`` (its dict, to
        pass again as ``candidates=[...]``), ``family`` (the model family, the basis
        kind of a modal candidate, ``"<family> + <kind>"`` for a hybrid), ``dtype``,
        ``bytes``, ``l2``,
        ``log``, ``l2_stderr``, ``log_stderr`` (measurements), ``scene`` (with
        ``scene=``), ``error`` (what decides),
        ``meets``, ``seconds`` (to build) and ``status`` (``"measured"``,
        ``"skipped: ..."`` or ``"failed: ..."``).

    Raises
    ------
    NoCandidateError
        A ValueError: no candidate meets ``tol``; its message names the smallest error
        reached, its ``candidates`` attribute holds the table.
    ValueError, TypeError
        Bad arguments, an unknown candidate form or key, or a BRDF with non-finite or
        negative values.

    Notes
    -----
    Modal candidates hold q = f cos cos (quantity ``"f_cos"``) for ``metric="l2"``, whose
    L2 projection minimises exactly that error, and the quantity of
    :func:`project.default_quantity` for ``"log"``; hybrids project their residual as
    :func:`compress.hybrid` does. Both are projected on a fixed product rule (``nodes``
    of :func:`project.project`, twice the order plus 16 in z, four times plus 32 in
    azimuth) rather than refined to convergence: on a sharp measured material refinement
    costs minutes while the candidate loses anyway; an under-resolved projection can only
    make the candidate's measured error larger, never wrong. On the sharpest materials it
    is then above 1 (the aliased peak: 1.25 for the gold-metallic-paint3 MERL surrogate at
    Zernike orders 4 and 8), where the converged expansion would be just below 1.

    Examples
    --------
    >>> from project.models import CookTorrance
    >>> ct = CookTorrance([0.3, 0.2, 0.1], 0.3, "ggx", ior=1.5)
    >>> rep = select(ct, 0.06, error_n=4096, candidates=[
    ...     {"form": "model", "family": "lambert+ggx", "restarts": 1},
    ...     {"form": "modal", "kind": "zernike", "order": 8}])
    >>> rep.family, rep.info["dtype"], rep.info["bytes"]
    ('lambert+ggx', 'float16', 16)
    """
    if not (isinstance(tol, (int, float)) and not isinstance(tol, bool) and tol > 0):
        raise ValueError(f"tol must be a positive number (inf: the smallest candidate), "
                         f"got {tol!r}")
    metric = choice(metric, "metric", METRICS)
    dtypes = _dtypes(dtypes)
    sampled = isinstance(brdf, project.Measurements)
    if not sampled and not callable(getattr(brdf, "eval", None)):
        raise TypeError(f"brdf must be a BRDF (an object with eval(wi, wo)) or "
                        f"project.Measurements, got {type(brdf).__name__}")
    channels = nonneg_int(getattr(brdf, "channels", 1), "brdf.channels")
    default = SAMPLE_CANDIDATES if sampled else DEFAULT_CANDIDATES
    builds = [_build_spec(c, channels, dtypes, getattr(brdf, "resolution", None))
              for c in (default if candidates is None else list(candidates))]
    if not builds:
        raise ValueError("candidates must hold at least one candidate")
    if reciprocal not in RECIPROCAL_CHOICES:
        raise ValueError(f"reciprocal must be None, True or False, got {reciprocal!r}")
    if sampled:
        if scene is not None:
            raise ValueError("scene= needs a BRDF that can be evaluated under any light; "
                             "measurements hold values at their samples only: select on "
                             "the samples, then judge the result in the scene")
        if reciprocal is False:
            raise ValueError("reciprocal=False: no non-reciprocal form can be fitted to "
                             "samples yet (the parametric families and the least-squares "
                             "expansion are reciprocal); pass None or True")
        judge = None
        measure = _SampleJudge(brdf, nonneg_int(folds, "folds"), 0 if seed is None else seed,
                               metric)
        rec = project.reciprocity(brdf)
    else:
        pair_seed = 2027 if seed is None else seed
        samples = peak_resolving_pairs(nonneg_int(error_n, "error_n"), seed=pair_seed)
        f = np.asarray(brdf.eval(samples.wi, samples.wo), dtype=np.float64)
        if not np.all(np.isfinite(f)) or np.any(f < 0):
            raise ValueError(f"brdf must return finite values >= 0; {_short(brdf)} "
                             f"returns {int(np.sum(~np.isfinite(f)))} non-finite and "
                             f"{int(np.sum(f < 0))} negative values at the error pairs")
        rec = project.reciprocity(brdf, n=max(error_n, MIN_PAIRS),
                                  seed=pair_seed)
        if reciprocal is True:  # judged against the reciprocal part of the data
            f = 0.5 * (f + np.asarray(brdf.eval(samples.wo, samples.wi), dtype=np.float64))
        judge = _scene_judge(brdf, scene) if scene is not None else None
        measure = _PairJudge(brdf, samples, f, metric)
    allowed, why = _reciprocal_forms(rec, tol, reciprocal, sampled)
    recorded = {"residual": rec.residual, "floor": rec.floor, "floor_stderr": rec.floor_stderr,
                "choice": reciprocal, "forms": sorted("reciprocal" if a else "non-reciprocal"
                                                      for a in allowed), "why": why}
    for b in builds:
        if _is_reciprocal(b.spec) not in allowed:
            kind = "a reciprocal" if _is_reciprocal(b.spec) else "a non-reciprocal"
            b.rows = [_row(b, d, status=f"skipped: {kind} form ({why})") for d in b.dtypes]
    limit = _source_bytes(brdf, source_bytes)
    if limit is not None:
        for b in builds:
            least = b.bytes(b.dtypes[0])
            if not b.rows and least is not None and least > limit:
                b.rows = [_row(b, d, status=f"skipped: {_larger(b.bytes(d), limit)}")
                          for d in b.dtypes]
    excluded = [b for b in builds if b.rows]
    builds = [b for b in builds if not b.rows]
    if not builds:
        if limit is not None and all("than the source" in b.rows[0]["status"]
                                     for b in excluded if _is_reciprocal(b.spec) in allowed):
            raise ValueError(f"every candidate of the forms allowed is larger than the source "
                             f"({limit} bytes): add smaller candidates")
        raise ValueError(f"no candidate of the forms allowed ({why}): add "
                         + ("non-reciprocal candidates (phi_turn='full', 'reciprocal': False)"
                            if False in allowed else "reciprocal candidates"))

    # unknown sizes first (cheap parametric fits), then by the smallest size possible
    def order(b: _Build) -> tuple[int, int]:
        n = b.bytes(b.dtypes[0])
        return (0, 0) if n is None else (1, n)

    builds.sort(key=order)
    best: tuple[int, float, Any, dict] | None = None
    # the factored ladder fits one BRDF on a few rules: each is sampled once
    with reuse_samples():
        for b in builds:
            smallest = b.bytes(b.dtypes[0])
            if best is not None and not exhaustive and smallest is not None \
                    and smallest >= best[0]:
                b.rows = [_row(b, d, status=f"skipped: at least {b.bytes(d)} bytes, not fewer "
                                            f"than the {best[0]} of {best[3]['label']}")
                          for d in b.dtypes]
                continue
            start = time.perf_counter()
            try:
                with warnings.catch_warnings():
                    # a slow fit, or a fit worse than zero, is measured and reported in the table
                    warnings.simplefilter("ignore", RuntimeWarning)
                    measured = measure(b)
            except (ValueError, RuntimeError, np.linalg.LinAlgError, MemoryError) as e:
                b.rows = [_row(b, d, status=f"failed: {e}") for d in b.dtypes]
                continue
            for d, get in zip(b.dtypes, measured, strict=True):
                known = b.bytes(d)
                # a larger storage type of a structure whose smaller one already met the
                # tolerance (or of one larger than the best) cannot be the smallest: it is
                # not measured (equal bytes are, the smaller error wins the tie)
                if limit is not None and known is not None and known > limit:
                    b.rows.append(_row(b, d, status=f"skipped: {_larger(known, limit)}"))
                    continue
                if best is not None and not exhaustive and known is not None \
                        and known > best[0]:
                    b.rows.append(_row(b, d, status=f"skipped: {known} bytes, more than the "
                                                    f"{best[0]} of {best[3]['label']} "
                                                    f"({best[3]['dtype']})"))
                    continue
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", RuntimeWarning)
                        r, nbytes, err = get()
                except (ValueError, RuntimeError, np.linalg.LinAlgError, MemoryError) as e:
                    r, err = None, e
                if r is None:
                    b.rows.append(_row(b, d, status=f"failed: {err}"))
                    continue
                if limit is not None and nbytes is not None and nbytes > limit:
                    b.rows.append(_row(b, d, status=f"skipped: {_larger(nbytes, limit)}"))
                    continue
                row = _row(b, d, bytes=nbytes, status="measured", **err)
                if judge is not None:
                    row["scene"] = judge(r)
                row["error"] = row["scene"] if judge is not None else row[metric]
                row["meets"] = bool(row["error"] <= tol)
                b.rows.append(row)
                if row["meets"] and (best is None or (nbytes, row["error"]) < best[:2]):
                    best = (nbytes, row["error"], r, row)
            seconds = time.perf_counter() - start  # the build and its measurements
            for row in b.rows:
                if row["status"] == "measured":
                    row["seconds"] = seconds
            if progress:
                measured = [r for r in b.rows if r["status"] == "measured"]
                summary = ", ".join(f"{r['dtype']} {r['bytes']} B {r['error']:.4g}"
                                    for r in measured) or b.rows[-1]["status"]
                print(f"select: {b.label} ({seconds:.1f} s): {summary}", flush=True)
    table = [row for b in (*builds, *excluded) for row in b.rows]
    table.sort(key=lambda r: (r["bytes"] is None, r["bytes"] or 0, r["label"]))
    how = measure.description
    if best is None:
        done = [r for r in table if r["status"] == "measured"]
        # the closest, and among equally close (storage types of one fit) the smallest
        least = min((r["error"] for r in done), default=math.nan)
        closest = min((r for r in done if r["error"] <= least * (1 + 1e-4)),
                      key=lambda r: r["bytes"]) if done else None
        raise NoCandidateError(
            f"no candidate meets {'the scene radiance error' if judge else metric} <= "
            f"{tol:.4g} for {_short(brdf)}"
            + (f": the smallest error is {closest['error']:.4g}, {closest['label']} at "
               f"{closest['bytes']} bytes ({closest['dtype']})" if closest else
               ": every candidate failed (see .candidates)")
            + f" (errors {how}; {why})" + _resolution_note(done)
            + (f"; the source itself holds {limit} bytes, and no candidate larger than it "
               "is built (a representation larger than its data is no compression)"
               if limit is not None else "")
            + "; add larger candidates or raise the tolerance"
            + (", or let non-reciprocal forms compete (reciprocal=False): the data's "
               f"reciprocity floor, {rec.floor:.3g}, is a sizable part of that error"
               if False not in allowed and not sampled and math.isfinite(rec.floor)
               and rec.floor >= 0.25 * least else ""), table)
    nbytes, _, rep, row = best
    rep.info = {**rep.info, "selected": row, "bytes": nbytes, "dtype": row["dtype"],
                "candidates": table, "tol": tol, "metric": "scene" if judge else metric,
                "errors": how, "reciprocity": recorded, "source_bytes": limit}
    return rep


def _source_bytes(brdf: Any, given: int | None) -> int | None:
    """Return the size of the source's file (given, or of ``brdf.path``); None: no limit."""
    if given is not None:
        n = nonneg_int(given, "source_bytes")
        if n < 1:
            raise ValueError(f"source_bytes must be >= 1, got {given!r}")
        return n
    path = getattr(brdf, "path", None)
    if path is None:
        return None
    try:
        return os.path.getsize(path)
    except (OSError, TypeError):  # a file since moved: no limit known
        return None


def _larger(nbytes: int, limit: int) -> str:
    return f"{nbytes} bytes, more than the source ({limit} bytes)"


def _resolution_note(done: list[dict[str, Any]]) -> str:
    """Return what the finest measured table says about a tolerance nothing met."""
    tables = [r for r in done if r["family"] == "tabulated"]
    if not tables:
        return ""
    finest = min(tables, key=lambda r: r["error"])
    return (f"; the finest table, {finest['label']} ({finest['bytes']} bytes), reaches "
            f"{finest['error']:.4g}: below that a tolerance needs finer tables (larger "
            "'bins'), down to what the data themselves resolve (a measured table's "
            "resolution, its noise)")


# -- reciprocity --------------------------------------------------------------------------------

def _is_reciprocal(spec: Mapping[str, Any]) -> bool:
    """Whether a candidate's form is reciprocal by construction."""
    lobe = not (spec.get("family") in _TURNED
                and spec.get("phi_turn", "half") == "full")
    if spec.get("family") == "grid":
        lobe = bool(spec.get("symmetric", True))
    if spec["form"] == "model":
        return lobe
    residual = bool(spec.get("reciprocal", True))
    return residual if spec["form"] == "modal" else lobe and residual


def _reciprocal_forms(rec: Any, tol: float, choice_: bool | None,
                      sampled: bool) -> tuple[set[bool], str]:
    """Return the forms allowed (True: reciprocal, False: not) and why, from the floor."""
    floor, se = rec.floor, rec.floor_stderr
    measured = f"reciprocity floor {floor:.3g} +- {se:.2g}" if math.isfinite(floor) else \
        "reciprocity not measured: " + (rec.note or "no estimate")
    if choice_ is True:
        return {True}, f"reciprocal forms asked for; errors against the reciprocal part, {measured}"
    if choice_ is False:
        return {False}, f"non-reciprocal forms asked for; {measured}"
    if sampled:  # only reciprocal forms can be fitted to samples
        return {True}, f"{measured}; the forms fitted to samples are reciprocal"
    if not math.isfinite(floor) or floor + 2.0 * se <= 0.5 * tol:
        return {True}, f"{measured} <= tol / 2: reciprocal forms, about half the size"
    if floor - 2.0 * se >= tol:
        return {False}, f"{measured} >= tol: no reciprocal form can meet it"
    return {True, False}, f"{measured} between tol / 2 and tol: both forms"


# -- measuring candidates -------------------------------------------------------------------------

class _PairJudge:
    """Build a candidate from a BRDF; measure it, rounded, on the peak-resolving pairs."""

    def __init__(self, brdf: Any, samples: Any, f: np.ndarray, metric: str) -> None:
        self.brdf, self.samples, self.f, self.metric = brdf, samples, f, metric
        self.fits: dict[tuple, Any] = {}  # lobes fitted once, shared by models and hybrids
        self.description = f"on {len(samples)} pairs, {samples.description}"

    def __call__(self, b: _Build) -> list[Callable[[], tuple[Any, int | None, Any]]]:
        """Build ``b``; return per storage type a function: (rounded form, bytes, errors).

        Each storage type is rounded and measured only when its function is called, so
        that :func:`select` measures only those that can still be the smallest.
        """
        rep = _make(b.spec, self.brdf, self.fits, self.metric)

        def measure(d: str) -> tuple[Any, int | None, Any]:
            try:
                r, nbytes = _rounded(rep, d, b.spec)
            except ValueError as e:
                return None, None, e
            g = r.eval(self.samples.wi, self.samples.wo)
            return r, nbytes, value_errors(self.f, g, self.samples)

        return [lambda d=d: measure(d) for d in b.dtypes]


class _SampleJudge:
    """Fit a candidate to measurements; its errors by k-fold cross-validation.

    Each fold's fit is rounded to every storage type before it predicts its held-out
    samples; the representation returned is the fit to all samples, rounded. Lobes are
    fitted once per fold and shared by models and hybrids.
    """

    def __init__(self, meas: Any, k: int, seed: int, metric: str) -> None:
        if k < 2:
            raise ValueError(f"folds must be >= 2 for measurements, got {k}")
        self.meas, self.metric = meas, metric
        self.folds = meas.folds(k, seed=seed, by="pairs")
        self.ids = [int(i) for i in np.unique(self.folds)]
        if len(self.ids) < 2:
            raise ValueError(f"cross-validation needs at least 2 distinct direction pairs, "
                             f"{meas!r} has {len(self.ids)}")
        self.train = {i: meas[self.folds != i] for i in self.ids}
        self.fits: dict[Any, dict[tuple, Any]] = {i: {} for i in (*self.ids, "all")}
        self.description = (f"{len(self.ids)}-fold cross-validated on {len(meas)} held-out "
                            f"samples (seed {seed})")

    def __call__(self, b: _Build) -> list[Callable[[], tuple[Any, int | None, Any]]]:
        """Return per storage type of ``b`` a function: (rounded form, bytes, errors)."""
        meas = self.meas
        n, c = meas.values.shape
        preds: dict[str, Any] = {d: np.empty((n, c)) for d in b.dtypes}
        for i in self.ids:
            rep = _make(b.spec, self.train[i], self.fits[i], self.metric)
            test = self.folds == i
            for d in b.dtypes:
                if isinstance(preds[d], ValueError):
                    continue
                try:
                    r, _ = _rounded(rep, d, b.spec)
                except ValueError as e:  # a parameter beyond the storage type's range
                    preds[d] = e
                    continue
                g = np.asarray(r.eval(meas.wi[test], meas.wo[test]), dtype=np.float64)
                preds[d][test] = g.reshape(int(test.sum()), -1)
        rep = _make(b.spec, meas, self.fits["all"], self.metric)
        out: list[tuple[Any, int | None, Any]] = []
        for d in b.dtypes:
            try:
                if isinstance(preds[d], ValueError):
                    raise preds[d]
                r, nbytes = _rounded(rep, d, b.spec)
                err = sample_errors(meas, preds[d], folds=self.folds)
            except ValueError as e:
                out.append((None, None, e))
                continue
            out.append((r, nbytes, {k: err[k] for k in ("l2", "l2_stderr", "log",
                                                         "log_stderr")}))
        return [lambda x=x: x for x in out]


# -- candidates ---------------------------------------------------------------------------------

def _dtypes(dtypes: Iterable[str]) -> tuple[str, ...]:
    if isinstance(dtypes, str):
        dtypes = (dtypes,)
    out = tuple(sorted({choice(d, "dtypes", PRECISIONS) for d in dtypes},
                       key=lambda d: np.dtype(d).itemsize))
    if not out:
        raise ValueError(f"dtypes must name at least one of {PRECISIONS}")
    return out


def _build_spec(c: Mapping[str, Any], channels: int, dtypes: tuple[str, ...],
                resolution: Any = None) -> _Build:
    if not isinstance(c, Mapping):
        raise TypeError(f"each candidate must be a dict with a 'form', got {c!r}")
    spec = dict(c)
    form = choice(spec.pop("form", None), "candidate form", FORMS)
    own = _dtypes(spec.pop("dtypes")) if "dtypes" in spec else dtypes
    unknown = sorted(set(spec) - _KEYS[form])
    if unknown:
        raise ValueError(f"unknown key(s) {unknown} in the {form} candidate {dict(c)}; a "
                         f"{form} candidate takes {sorted(_KEYS[form])}")
    need = {"modal": ("kind", "order"), "model": ("family",),
            "hybrid": ("family", "kind", "order")}[form]
    missing = [k for k in need if k not in spec]
    if missing:
        raise ValueError(f"the {form} candidate {dict(c)} needs {missing}")
    spec["form"] = form
    if "kind" in spec:
        choice(spec["kind"], "candidate kind", tuple(basis.KINDS))
        spec["order"] = nonneg_int(spec["order"], "candidate order")
    if "family" in spec:
        choice(spec["family"], "candidate family", project.fitting.FAMILIES)
        if spec["family"] == "tucker":  # what _is_reciprocal assumes, whatever the BRDF says
            spec.setdefault("phi_turn", "half")
        if spec["family"] == "grid":  # the source's own grid, known before the fit
            spec["resolution"] = project.fitting.grid.grid_resolution(
                None, spec.get("resolution", resolution))
            if not isinstance(spec.setdefault("symmetric", True), bool):
                raise TypeError(f"candidate symmetric must be True or False, got "
                                f"{spec['symmetric']!r}")
    if "fit_metric" in spec:
        choice(spec["fit_metric"], "candidate fit_metric", METRICS)
    if not isinstance(spec.get("reciprocal", True), bool):
        raise TypeError(f"candidate reciprocal must be True or False, got "
                        f"{spec['reciprocal']!r}")
    reals = _reals(spec, channels)
    label = form + ": " + ", ".join(f"{k}={v}" for k, v in spec.items() if k != "form")
    return _Build(spec, label, reals, own)


def _reals(spec: dict[str, Any], channels: int) -> int | None:
    """Count the stored reals of a candidate from its structure (None: known once fitted)."""
    total = 0
    if spec["form"] in ("model", "hybrid"):
        lobe = _lobe_reals(spec, channels)
        if lobe is None:
            return None
        total += lobe
    if spec["form"] in ("modal", "hybrid"):
        sizes = basis.make_basis(spec["kind"], spec["order"]).azimuthal_blocks().sizes
        general = not spec.get("reciprocal", True)
        if spec["form"] == "modal" and spec.get("rank") is not None:
            # an eigen-term stores its eigenvalue and its vector (of its block m), a singular
            # term of a general block its value and two vectors; the largest blocks bound
            # it, so this is an upper bound until measured
            rank = nonneg_int(spec["rank"], "candidate rank")
            total += channels * rank * (1 + (2 if general else 1) * int(sizes.max()))
        else:
            per = sizes * sizes if general else sizes * (sizes + 1) // 2
            total += channels * int(np.sum(per))
    return total


def _lobe_reals(spec: dict[str, Any], channels: int) -> int | None:
    family, c = spec["family"], channels
    if family in ("lambert+ggx", "lambert+beckmann"):
        return 2 * c + 2
    if family == "lafortune":
        lobes = int(spec.get("lobes", 1))
        return c + lobes * (c + 2)
    if family == "tucker":
        if "ranks" in spec and "knots" in spec:
            ranks, knots = spec["ranks"], spec["knots"]
            return tucker_reals(tuple(knots), tuple(ranks), int(spec.get("color_rank", c)), c)
        # at most the budget (the fit chooses a structure within it): select compares it
        # with the smallest found so far as if it were exact
        return int(spec.get("budget", 2048))
    if family == "grid":
        return project.fitting.grid.grid_reals(spec["resolution"], c, spec["symmetric"])
    if family == "tabulated":
        n_h, n_d, n_phi = (int(x) for x in spec.get("bins", (32, 32, 64)))
        return n_h * n_d * (n_phi if spec.get("phi_turn") == "full" else n_phi // 2) * c
    if family != "factored":
        return None
    rank = int(spec.get("rank", 4))
    bins = tuple(spec.get("bins", (32, 24, 8)))
    color = spec.get("color", "weights") if c > 1 else "none"
    ca = c if color in ("theta_h", "both") else 1
    cb = c if color in ("theta_d", "both") else 1
    n = c + rank * (bins[0] * ca + bins[1] * cb)
    if len(bins) == 3:
        n += rank * bins[2]
    if color == "weights":
        n += rank * c
    return n


def _fit_options(spec: dict[str, Any]) -> dict[str, Any]:
    """Return the options of :func:`project.fit_model` in a candidate (``fit_metric``: metric)."""
    opts = {k: v for k, v in spec.items() if k in _FIT_KEYS}
    if "fit_metric" in opts:
        opts["metric"] = opts.pop("fit_metric")
    return opts


def _short(obj: Any, width: int = 100) -> str:
    """Return ``repr(obj)`` cut to ``width`` characters, marked with an ellipsis when cut."""
    text = repr(obj)
    return text if len(text) <= width else text[:width - 3] + "..."


def _lobe(spec: dict[str, Any], brdf: Any, fits: dict[tuple, Any]) -> Any:
    opts = _fit_options(spec)
    key = (spec["family"], tuple(sorted((k, repr(v)) for k, v in opts.items())))
    if key not in fits:
        if isinstance(brdf, project.Measurements):
            opts["folds"] = 0  # the candidate is cross-validated as a whole
        fits[key] = project.fit_model(brdf, spec["family"], **opts)
    return fits[key]


def _nodes(order: int) -> tuple[int, int]:
    return 2 * order + 16, 4 * order + 32


def _make(spec: dict[str, Any], brdf: Any, fits: dict[tuple, Any], metric: str) -> Any:
    form = spec["form"]
    sampled = isinstance(brdf, project.Measurements)
    if sampled and not _is_reciprocal(spec):
        raise ValueError("a non-reciprocal form cannot be fitted to samples yet (the "
                         "factored tables need a BRDF, the least-squares fit is reciprocal)")
    if form == "model":
        return _lobe(spec, brdf, fits)
    if form == "hybrid":
        if sampled:
            return make_hybrid(brdf, spec["order"], lobe=_lobe(spec, brdf, fits),
                               kind=spec["kind"], folds=0)
        return make_hybrid(brdf, spec["order"], lobe=_lobe(spec, brdf, fits),
                           kind=spec["kind"], error_samples=0,
                           nodes=_nodes(spec["order"]),
                           reciprocal=spec.get("reciprocal", True))
    b = basis.make_basis(spec["kind"], spec["order"])
    if sampled:
        cm = project.fit(brdf, b, quantity="f_cos" if metric == "l2" else "f",
                         isotropic=brdf.isotropic is not False)
        if spec.get("rank") is not None:
            cm = lowrank(cm, nonneg_int(spec["rank"], "candidate rank"))
        return cm
    # for the l2 error of q the L2(q) projection (f_cos) is the optimal expansion
    quantity = "f_cos" if metric == "l2" else "auto"
    cm = project.project(brdf, b, nodes=_nodes(spec["order"]), quantity=quantity,
                         reciprocal=spec.get("reciprocal", True))
    if spec.get("rank") is not None:
        cm = lowrank(cm, nonneg_int(spec["rank"], "candidate rank"))
    return cm


def _rounded(rep: Any, dtype: str, spec: dict[str, Any]) -> tuple[Any, int]:
    """Round a representation to a storage type; return it and its bytes there."""
    size = np.dtype(dtype).itemsize
    if isinstance(rep, CoefficientMatrix):
        r = precision(rep, dtype)
        n = rep.info["lowrank"]["numbers"] if "lowrank" in rep.info else \
            unique_coefficients(rep)
        return r, n * size
    if isinstance(rep, Hybrid):
        lobe, lb = _rounded(rep.lobe, dtype, spec)
        res, rb = _rounded(rep.residual, dtype, spec)
        return Hybrid(lobe, res, dict(rep.info)), lb + rb
    params = {}
    top = float(np.finfo(dtype).max)
    for k, v in rep.params.items():
        if np.max(np.abs(v), initial=0.0) > top:
            raise ValueError(f"parameter {k!r} (up to {np.max(np.abs(v)):.4g}) exceeds the "
                             f"largest {dtype}")
        params[k] = np.asarray(v).astype(dtype).astype(np.float64)
    return project.FittedModel(rep.family, params, info=dict(rep.info)), rep.nparams * size


def _row(b: _Build, dtype: str, **values: Any) -> dict[str, Any]:
    spec = b.spec
    family = {"model": spec.get("family"), "modal": spec.get("kind"),
              "hybrid": f"{spec.get('family')} + {spec.get('kind')}"}[spec["form"]]
    row = {"label": b.label, "form": spec["form"], "candidate": dict(spec),
           "family": family, "dtype": dtype,
           "bytes": b.bytes(dtype),
           "l2": math.nan, "log": math.nan, "l2_stderr": math.nan, "error": math.nan,
           "meets": False, "seconds": math.nan}
    row.update(values)
    return row


# -- scenes ------------------------------------------------------------------------------------

def _scene_judge(brdf: Any, scene: Mapping[str, Any]) -> Callable[[Any], float]:
    """Return a function: the radiance error of a representation under the scene."""
    if not isinstance(scene, Mapping) or "lights" not in scene or "views" not in scene:
        raise ValueError("scene must be a dict with 'lights' (an Environment or (n, 3) "
                         "light directions) and 'views' ((m, 3) view directions)")
    unknown = sorted(set(scene) - {"lights", "views", "light_weights", "resolution"})
    if unknown:
        raise ValueError(f"unknown scene key(s) {unknown}; the keys are 'lights', 'views', "
                         "'light_weights', 'resolution'")
    lights = scene["lights"]
    if not isinstance(lights, Environment):
        lights = Environment.directional(lights, scene.get("light_weights"))
    views = as_directions(scene["views"], "scene views").reshape(-1, 3)
    resolution = nonneg_int(scene.get("resolution", 128), "scene resolution")
    ref = lights.radiance(brdf, views, resolution=resolution)
    norm = np.sqrt(np.mean(ref * ref, axis=0))
    if not np.all(norm > 0):
        raise ValueError("the scene's lights reflect no radiance towards its views: the "
                         "radiance error is undefined (lights below the horizon?)")

    def judge(rep: Any) -> float:
        out = lights.radiance(rep, views, resolution=resolution)
        if out.shape[1] == 1 and ref.shape[1] > 1:
            out = np.broadcast_to(out, ref.shape)
        return float(np.max(np.sqrt(np.mean((out - ref) ** 2, axis=0)) / norm))

    return judge
