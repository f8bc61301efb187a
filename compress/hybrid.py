"""Lobe + modes: a compact specular lobe with a spherical-basis residual for the rest.

A narrow specular peak holds almost all of the L2 norm of a glossy BRDF, so truncated
expansions in any of the bases of :mod:`basis` keep large errors on metals and plastics at
every practical order. A lobe model (an analytic microfacet lobe or a tabulated factored one)
captures the peak in a few hundred bytes but misses the broad remainder: the diffuse shape,
retro-reflection, grazing effects. :func:`hybrid` fits the lobe first and projects the residual
``f - lobe`` onto a basis, where it is smooth enough for a low order.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

import basis
import project
from basis import CoefficientMatrix
from basis.validation import nonneg_int
from project.crossval import cross_validate
from project.measurements import FOLDS

from .truncate import unique_coefficients

__all__ = ["Hybrid", "hybrid"]


class Hybrid:
    """A BRDF held as a lobe plus a coefficient-matrix residual: f = lobe + residual.

    Parameters
    ----------
    lobe : BRDF
        Any object with ``eval(wi, wo)``, ``channels`` and ``isotropic`` (a fitted model of
        :func:`project.fit_model`, or any model of :mod:`project.models`); ``nbytes`` is read
        when present (0 otherwise, e.g. for a built-in model whose parameters are not stored).
    residual : basis.CoefficientMatrix
        The expansion of ``f - lobe``.
    info : dict, optional
        Provenance and errors.

    Attributes
    ----------
    channels : int
        The larger of the lobe's and the residual's channel counts (one broadcasts).
    isotropic : bool
        True when both parts are isotropic.
    reciprocal : bool
        True when both parts are: a full-turn factored lobe or a general residual matrix
        (``reciprocal=False``) hold non-reciprocal data.

    Examples
    --------
    >>> import numpy as np
    >>> from basis import CoefficientMatrix, HemiZernike
    >>> from project.models import Lambert
    >>> zb = HemiZernike(2)
    >>> M = np.zeros((zb.size, zb.size)); M[0, 0] = 0.2  # f = 0.1 / pi
    >>> h = Hybrid(Lambert(0.4), CoefficientMatrix(zb, M, quantity="f"))
    >>> w = np.array([0.0, 0.0, 1.0])
    >>> bool(np.isclose(h.eval(w, w), 0.5 / np.pi))
    True
    """

    delta: tuple = ()

    def __init__(self, lobe: Any, residual: CoefficientMatrix,
                 info: dict[str, Any] | None = None) -> None:
        for attr in ("eval", "channels", "isotropic"):
            if not hasattr(lobe, attr):
                raise TypeError(f"lobe must be a BRDF with eval(wi, wo), channels and isotropic "
                                f"(e.g. project.models.CookTorrance(...)); "
                                f"{type(lobe).__name__} has no {attr!r}")
        if not isinstance(residual, CoefficientMatrix):
            raise TypeError(f"residual must be a basis.CoefficientMatrix, got "
                            f"{type(residual).__name__}")
        lc, rc = int(lobe.channels), residual.channels
        if lc != rc and 1 not in (lc, rc):
            raise ValueError(f"lobe and residual channels must match or one be 1, got {lc} "
                             f"and {rc}")
        self.lobe = lobe
        self.residual = residual
        self.channels = max(lc, rc)
        self.isotropic = bool(lobe.isotropic) and residual.is_isotropic
        self.reciprocal = bool(getattr(lobe, "reciprocal", True)) and residual.reciprocal
        self.info: dict[str, Any] = dict(info or {})

    @property
    def nbytes(self) -> int:
        """Bytes stored at float64: the lobe's parameters and the residual's unique coefficients.

        The residual counts as :func:`compress.unique_coefficients` (symmetric blocks stored
        once), as in a file of :func:`compress.save`, not the memory its blocks hold
        (:attr:`basis.CoefficientMatrix.nbytes`).
        """
        return int(getattr(self.lobe, "nbytes", 0)) + 8 * unique_coefficients(self.residual)

    def eval(self, wi: ArrayLike, wo: ArrayLike) -> NDArray[np.float64]:
        """Evaluate f(w_i, w_o) = lobe + residual in 1/sr.

        Parameters
        ----------
        wi, wo : (..., 3) array_like of float
            Unit vectors (towards the light and towards the viewer); batch shapes broadcast.

        Returns
        -------
        (...) or (..., channels) ndarray
            (...) only when both parts are single-channel without a channel axis; zero below
            the horizon.
        """
        return _combine(self.lobe.eval(wi, wo), self.residual.eval(wi, wo), 1.0)

    def __repr__(self) -> str:
        return f"Hybrid({self.lobe!r} + {self.residual!r})"


class _Residual:
    """f - lobe as a BRDF for projection: the values may be negative, which is the point."""

    def __init__(self, brdf: Any, lobe: Any) -> None:
        self.brdf, self.lobe = brdf, lobe
        # what the quadrature may assume when sampling (the fitted lobes are reciprocal)
        self.reciprocal = bool(getattr(brdf, "reciprocal", True))
        self.channels = max(int(brdf.channels), int(lobe.channels))
        self.isotropic = bool(brdf.isotropic) and bool(lobe.isotropic)
        self.delta = tuple(getattr(brdf, "delta", ()) or ())  # mirror terms stay residual

    def eval(self, wi: ArrayLike, wo: ArrayLike) -> NDArray[np.float64]:
        return _combine(self.brdf.eval(wi, wo), self.lobe.eval(wi, wo), -1.0)

    def __repr__(self) -> str:
        return f"({self.brdf!r} - {self.lobe!r})"


def _combine(a: ArrayLike, b: ArrayLike, sign: float) -> NDArray[np.float64]:
    """Return a + sign * b for BRDF values of which at most one lacks the channel axis."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.ndim < b.ndim:
        a = a[..., None]
    elif b.ndim < a.ndim:
        b = b[..., None]
    return a + sign * b


def hybrid(brdf: Any, order: int, *, lobe: Any = None, kind: str = "zernike",
           metric: str = "l2", lobe_options: dict[str, Any] | None = None,
           error_samples: int = 1 << 15, seed: int = 1, folds: int = FOLDS,
           **project_kwargs: Any) -> Hybrid:
    """Fit a lobe to ``brdf`` and expand the residual ``brdf - lobe`` in a basis.

    Parameters
    ----------
    brdf : BRDF or project.Measurements
        The BRDF to represent (an analytic model, a MERL table, ...), or scattered
        measurements: the lobe is then fitted to the samples, the residual's expansion by
        least squares to the samples' residuals (:func:`project.fit`, its regularisation
        chosen by cross-validation), and the errors are cross-validated (``folds``).
    order : int
        Order of the residual's basis.
    lobe : str or BRDF, optional
        A family of :func:`project.fit_model` (fitted to ``brdf`` with ``metric`` and
        ``lobe_options``), or a lobe already fitted (any BRDF), used as it is. Default
        ``"factored"`` for a BRDF and ``"lambert+ggx"`` for measurements (the factored
        tables need a BRDF that can be evaluated anywhere).
    kind : str
        Basis kind of the residual, one of :data:`basis.KINDS`.
    metric : {"l2", "log"}
        Passed to :func:`project.fit_model` when the lobe is fitted here.
    lobe_options : dict, optional
        Further options of :func:`project.fit_model`.
    error_samples : int
        Pairs of :func:`project.sampling.peak_resolving_pairs` on which the errors of the
        result are measured (0: skip); ``seed`` seeds them.
    seed : int
    folds : int
        Measurements only: folds of the cross-validated errors (0 skips them).
    **project_kwargs
        Passed to :func:`project.project` for the residual (``quantity``, ``tol``, ...),
        or to :func:`project.fit` for measurements (``quantity``, ``regularization``,
        ``isotropic``...).
        The quantity defaults to ``"f_cos"``: the residual's expansion is then the
        orthogonal projection of q - q_lobe in the L2 norm of q = f cos cos, the norm of the
        ``l2`` error, so the hybrid is never worse than its lobe alone in that norm (up to
        the quadrature error). With ``quantity="f"`` it can be: on a GGX Cook-Torrance
        (alpha 0.15, glass Fresnel, RGB kd) with a rank-1 factored lobe (l2 0.058), an f
        residual gave 0.065 / 0.086 / 0.071 at orders 2 / 4 / 8, an f_cos one 0.058 at
        order 2. ``"f"`` is the better choice for pointwise errors near grazing, where an
        f_cos expansion evaluated as f divides by the cosines (the ``log`` error of the
        same example: 0.0059 with f, 0.0102 with f_cos).

    Returns
    -------
    Hybrid
        ``info`` holds ``residual_truncation_error`` (the L2 truncation error of the
        residual's expansion relative to the residual itself), the lobe's, residual's and
        total bytes, and the errors of the whole against ``brdf``: ``l2`` (relative L2 of
        f cos cos over H x H), ``log`` and ``l2_stderr``, measured on pairs concentrated
        around the mirror direction as well as uniform (:mod:`project.sampling`), so sharp
        peaks are resolved. For measurements: the same errors on held-out samples, by
        k-fold cross-validation of the whole procedure (:func:`project.crossval.
        cross_validate`), with ``log_stderr``, ``folds`` and ``validation``.
    """
    order = nonneg_int(order, "order")
    b = basis.make_basis(kind, order)
    if isinstance(brdf, project.Measurements):
        return _hybrid_samples(brdf, order, b, lobe, kind, metric, lobe_options, folds,
                               project_kwargs)
    if lobe is None:
        lobe = "factored"
    if isinstance(lobe, str):
        from project.fitting import fit_model

        lobe = fit_model(brdf, lobe, metric=metric, **dict(lobe_options or {}))
    elif lobe_options:
        raise ValueError("lobe_options apply only when the lobe is fitted here (lobe given "
                         "as a family name)")
    project_kwargs.setdefault("quantity", "f_cos")
    project_kwargs.setdefault("reciprocal", True)  # a symmetric residual, as before
    res = project.project(_Residual(brdf, lobe), b, **project_kwargs)
    info = {"source": repr(brdf), "order": order, "kind": kind,
            "residual_truncation_error": res.info.get("truncation_error"),
            "lobe_bytes": int(getattr(lobe, "nbytes", 0)),
            "residual_bytes": 8 * unique_coefficients(res)}
    out = Hybrid(lobe, res, info)
    out.info["bytes"] = out.nbytes
    if nonneg_int(error_samples, "error_samples"):
        from project.sampling import brdf_errors, peak_resolving_pairs

        out.info.update(brdf_errors(brdf, out, peak_resolving_pairs(error_samples, seed=seed)))
    return out


def _hybrid_samples(meas: project.Measurements, order: int, b: basis.Basis, lobe: Any,
                    kind: str, metric: str, lobe_options: dict[str, Any] | None, folds: int,
                    fit_kwargs: dict[str, Any]) -> Hybrid:
    """hybrid(measurements, ...): lobe and residual fitted to the samples, errors by CV."""
    folds = nonneg_int(folds, "folds")
    if folds == 1:
        raise ValueError("folds must be 0 (no cross-validation) or >= 2, got 1")
    given = not isinstance(lobe, str) and lobe is not None
    if given and lobe_options:
        raise ValueError("lobe_options apply only when the lobe is fitted here (lobe given "
                         "as a family name)")
    family = "lambert+ggx" if lobe is None else lobe
    fit_kwargs = {"quantity": "f_cos", **fit_kwargs}
    isotropic = fit_kwargs.pop("isotropic", meas.isotropic is not False)

    def build(m: project.Measurements) -> Hybrid:
        lb = lobe if given else project.fit_model(m, family, metric=metric, folds=0,
                                                   **dict(lobe_options or {}))
        rest = np.asarray(lb.eval(m.wi, m.wo), dtype=np.float64).reshape(len(m), -1)
        res_meas = project.Measurements(m.wi, m.wo, m.values - rest, weights=m.weights,
                                        isotropic=m.isotropic)
        with warnings.catch_warnings():
            # the residual of a good lobe is mostly noise, which a Lambertian fit predicts
            # as well: that warning is about the residual, not about the hybrid
            warnings.filterwarnings("ignore", message="fit predicts held-out samples")
            res = project.fit(res_meas, b, isotropic=isotropic, **fit_kwargs)
        info = {"source": repr(meas), "order": order, "kind": kind,
                "lobe_bytes": int(getattr(lb, "nbytes", 0)),
                "residual_bytes": 8 * unique_coefficients(res),
                "residual_validation_error": res.info.get("validation_error")}
        out = Hybrid(lb, res, info)
        out.info["bytes"] = out.nbytes
        return out

    out = build(meas)
    if folds:
        out.info.update(cross_validate(meas, build, k=folds))
    return out
