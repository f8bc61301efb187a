"""Errors of representations fitted to scattered measurements, by k-fold cross-validation.

A representation fitted to measured samples cannot be judged on the samples it was fitted
to: the residual of a flexible fit falls with every parameter added, while its predictions
between the samples may grow worse. :func:`cross_validate` holds out each of k folds in
turn, fits the rest, and scores the held-out predictions (Stone 1974); every sample is
predicted once, by a fit that did not see it. The folds are those of
:meth:`project.Measurements.folds`: repeated measurements of a direction pair, and of its
reciprocal or (for isotropic data) its mirror image, share a fold, so a held-out sample
never has a twin in the training set.

The errors are those of :mod:`project.sampling`, with the samples' weights as the measure:

- ``l2``: relative L2 error of q = f cos(theta_i) cos(theta_o),
  sqrt(sum w (q_hat - q)^2 / sum w q^2), the largest over the channels. Predicting zero
  scores exactly 1, so an error >= 1 means the fit is worse than nothing;
- ``log``: root mean square of log(1 + f cos theta_i) - log(1 + f_hat cos theta_i), the
  largest over the channels, with negative values (noise in a measurement, undershoot of an
  expansion) counted as 0.

Standard errors treat the k folds as independent replicates: the pooled ratio of sums is
a ratio estimator whose variance follows from the spread of the per-fold sums (the delta
method), the same estimate :mod:`project.sampling` makes from its replicates.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basis.validation import nonneg_int

__all__ = ["cross_validate", "sample_errors"]

#: Folds of the default cross-validation.
FOLDS = 10


def _check_measurements(meas: object, name: str = "measurements") -> Any:
    from .measurements import Measurements

    if not isinstance(meas, Measurements):
        raise TypeError(f"{name} must be a project.Measurements, got {type(meas).__name__}")
    return meas


def _predictions(f_hat: ArrayLike, n: int, channels: int, name: str) -> NDArray[np.float64]:
    try:
        g = np.asarray(f_hat, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be an array of floats, got {type(f_hat).__name__}") \
            from None
    if g.ndim == 1:
        g = g[:, None]
    if g.ndim != 2 or g.shape[0] != n or g.shape[1] not in (1, channels):
        raise ValueError(f"{name} must have shape ({n},), ({n}, 1) or ({n}, {channels}), got "
                         f"{np.shape(f_hat)}")
    if not np.all(np.isfinite(g)):
        raise ValueError(f"{name} must be finite: {int(np.sum(~np.isfinite(g)))} values are "
                         "NaN or inf")
    return np.broadcast_to(g, (n, channels))


def _sums(meas: Any, g: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Per-sample terms: w (q_hat - q)^2, w q^2, w d^2 (log), w; each (n, channels)."""
    f = meas.values
    w = meas.weights[:, None]
    ci = meas.wi[:, 2:3]
    cc = ci * meas.wo[:, 2:3]
    q, q_hat = f * cc, g * cc
    d = np.log1p(np.maximum(f, 0.0) * ci) - np.log1p(np.maximum(g, 0.0) * ci)
    return w * (q_hat - q) ** 2, w * q * q, w * d * d, np.broadcast_to(w, f.shape)


def _ratio_and_stderr(num: NDArray, den: NDArray) -> tuple[NDArray, NDArray]:
    """sqrt(sum num / sum den) per channel, and its delta-method standard error.

    ``num`` and ``den`` are (groups, channels) sums over independent groups of samples.
    """
    n_tot, d_tot = num.sum(axis=0), den.sum(axis=0)
    ratio = np.divide(n_tot, d_tot, out=np.full_like(n_tot, np.inf), where=d_tot > 0)
    err = np.sqrt(ratio)
    k = num.shape[0]
    if k < 2:
        return err, np.full_like(err, np.nan)
    resid = num - np.where(np.isfinite(ratio), ratio, 0.0) * den
    with np.errstate(divide="ignore", invalid="ignore"):
        var = k / (k - 1) * np.sum(resid * resid, axis=0) / (d_tot * d_tot)
        se = np.where(err > 0, np.sqrt(var) / (2.0 * err), 0.0)
    return err, se


def sample_errors(measurements: Any, f_hat: ArrayLike, *,
                  folds: ArrayLike | None = None) -> dict[str, Any]:
    """Errors of predicted BRDF values against measured samples.

    Parameters
    ----------
    measurements : project.Measurements
        n samples with ``channels`` values each.
    f_hat : (n,) or (n, channels) array_like of float
        Predictions (1/sr) at the samples' direction pairs; one channel stands for all.
    folds : (n,) array_like of int, optional
        Groups of samples treated as independent replicates for the standard errors (the
        folds the predictions were made in); default: every sample its own group.

    Returns
    -------
    dict
        ``"l2"`` and ``"log"`` (largest over the channels, see the module notes),
        ``"l2_stderr"`` and ``"log_stderr"`` (of the channel where each is largest),
        ``"l2_channels"`` and ``"log_channels"`` (lists, one per channel).

    Raises
    ------
    ValueError
        Shapes that do not match, non-finite predictions, or measurements whose q is 0 at
        every sample of a channel (the relative error is undefined).

    Examples
    --------
    >>> from project import Measurements
    >>> w = np.array([[0.0, 0.6, 0.8], [0.6, 0.0, 0.8], [0.0, 0.0, 1.0]])
    >>> m = Measurements(w, w[::-1], [0.2, 0.3, 0.4])
    >>> e = sample_errors(m, 1.1 * m.values)
    >>> round(e["l2"], 12), sample_errors(m, np.zeros(3))["l2"]
    (0.1, 1.0)
    """
    meas = _check_measurements(measurements)
    n, c = meas.values.shape
    g = _predictions(f_hat, n, c, "f_hat")
    if folds is None:
        group = np.arange(n)
    else:
        group = np.asarray(folds)
        if group.shape != (n,) or not np.issubdtype(group.dtype, np.integer):
            raise ValueError(f"folds must be ({n},) integers, got {group.dtype} {group.shape}")
        group = np.unique(group, return_inverse=True)[1].reshape(-1)
    e2, q2, d2, w = _sums(meas, g)
    k = int(group.max()) + 1 if n else 0
    sums = []
    for term in (e2, q2, d2, w):
        s = np.zeros((k, c))
        np.add.at(s, group, term)
        sums.append(s)
    if np.any(sums[1].sum(axis=0) <= 0):
        ch = int(np.flatnonzero(sums[1].sum(axis=0) <= 0)[0])
        raise ValueError(f"the measured q = f cos cos is 0 at every sample of channel {ch} "
                         f"({meas.channel_names[ch]}): the relative error is undefined")
    l2, l2_se = _ratio_and_stderr(sums[0], sums[1])
    lg, lg_se = _ratio_and_stderr(sums[2], sums[3])
    i, j = int(np.argmax(l2)), int(np.argmax(lg))
    return {"l2": float(l2[i]), "l2_stderr": float(l2_se[i]), "log": float(lg[j]),
            "log_stderr": float(lg_se[j]), "l2_channels": [float(x) for x in l2],
            "log_channels": [float(x) for x in lg]}


def out_of_fold(measurements: Any, fit: Callable[[Any], Any], folds: NDArray,
                variants: Sequence[Callable[[Any], Any]] = ()) -> list[NDArray[np.float64]]:
    """Predictions of every sample by a fit to the other folds: one (n, C) array per variant.

    ``fit(train)`` returns a representation with ``eval(wi, wo)``; each variant maps that
    representation to another (e.g. its parameters rounded to a storage type) whose
    predictions are collected too. The first array is the fit's own.
    """
    meas = measurements
    n, c = meas.values.shape
    outs = [np.empty((n, c)) for _ in range(1 + len(variants))]
    for f in np.unique(folds):
        test = folds == f
        rep = fit(meas[~test])
        for out, v in zip(outs, (None, *variants), strict=True):
            r = rep if v is None else v(rep)
            out[test] = _predictions(r.eval(meas.wi[test], meas.wo[test]), int(test.sum()), c,
                                     "the prediction of a fold")
    return outs


def cross_validate(measurements: Any, fit: Callable[[Any], Any], *, k: int = FOLDS,
                   seed: int = 0, by: str = "pairs") -> dict[str, Any]:
    """k-fold cross-validated errors of a fitting procedure on measured samples.

    Parameters
    ----------
    measurements : project.Measurements
    fit : callable
        ``fit(train)`` takes a :class:`project.Measurements` and returns a representation
        with ``eval(wi, wo)`` (a fitted model, a coefficient matrix, a hybrid...).
    k : int
        Folds, >= 2 (fewer when there are fewer groups of twin samples).
    seed : int
        Seeds the assignment of samples to folds.
    by : {"pairs", "incidence"}
        Group the folds by direction pair (with twins) or by incidence direction
        (:meth:`project.Measurements.folds`).

    Returns
    -------
    dict
        The errors of :func:`sample_errors` on the held-out predictions, their standard
        errors over the folds, ``"folds"`` (the number used), ``"fold_l2"`` (the l2 error
        of each fold alone, largest channel), ``"validation"`` (a description) and
        ``"seconds"``.

    Examples
    --------
    Fitting a constant (the weighted mean of f) to Lambertian samples predicts them
    exactly:

    >>> from project import Measurements
    >>> rng = np.random.default_rng(0)
    >>> w = rng.normal(size=(400, 3)); w[:, 2] = abs(w[:, 2])
    >>> w /= np.linalg.norm(w, axis=1, keepdims=True)
    >>> m = Measurements(w[:200], w[200:], np.full(200, 0.2))
    >>> from project.models import Lambert
    >>> cv = cross_validate(m, lambda t: Lambert(np.pi * t.values.mean()))
    >>> cv["l2"] < 1e-12, cv["folds"]
    (True, 10)
    """
    meas = _check_measurements(measurements)
    k = nonneg_int(k, "k")
    if k < 2:
        raise ValueError(f"k must be >= 2 folds, got {k}")
    if not callable(fit):
        raise TypeError(f"fit must be a callable fit(train) -> representation, got "
                        f"{type(fit).__name__}")
    start = time.perf_counter()
    folds = meas.folds(k, seed=seed, by=by)
    used = int(np.unique(folds).size)
    if used < 2:
        raise ValueError(f"cross-validation needs at least 2 distinct direction pairs, "
                         f"{meas!r} has {used}")
    (pred,) = out_of_fold(meas, fit, folds)
    return fold_report(meas, pred, folds, by, start)


def fold_report(meas: Any, pred: NDArray, folds: NDArray, by: str, start: float) -> dict[str, Any]:
    """Return the cross-validation dict of :func:`cross_validate` from out-of-fold predictions."""
    err = sample_errors(meas, pred, folds=folds)
    used = np.unique(folds)
    fold_l2 = []
    for f in used:
        t = folds == f
        e2, q2, _, _ = _sums(meas[t], pred[t])
        with np.errstate(divide="ignore", invalid="ignore"):
            fold_l2.append(float(np.max(np.sqrt(e2.sum(axis=0) / q2.sum(axis=0)))))
    return {**err, "folds": int(used.size), "fold_l2": fold_l2,
            "validation": f"{used.size}-fold CV on held-out samples, grouped by "
                          f"{'direction pair' if by == 'pairs' else 'incidence'}",
            "seconds": time.perf_counter() - start}
