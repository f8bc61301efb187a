"""Evaluation of coefficient matrices, kept here for code written against earlier versions.

The compiled evaluator lives in :mod:`basis.evaluate` and is what
:meth:`basis.CoefficientMatrix.eval` runs; :class:`FastEvaluator` is the same class.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basis import CoefficientMatrix
from basis import Evaluator as FastEvaluator

__all__ = ["FastEvaluator", "evaluate"]


def evaluate(cm: CoefficientMatrix, wi: ArrayLike, wo: ArrayLike, *,
             min_cos: float = 1e-3) -> NDArray[np.float64]:
    """Evaluate the BRDF of ``cm``; the same as ``cm.eval(wi, wo, min_cos=min_cos)``.

    Parameters
    ----------
    cm : basis.CoefficientMatrix
        Any matrix, isotropic or dense.
    wi, wo : (..., 3) array_like of float
        Unit vectors; batch shapes broadcast.
    min_cos : float
        As in :meth:`basis.CoefficientMatrix.eval`.

    Returns
    -------
    (...) or (..., channels) ndarray, as :meth:`basis.CoefficientMatrix.eval`.
    """
    if not isinstance(cm, CoefficientMatrix):
        raise TypeError(f"cm must be a basis.CoefficientMatrix, got {type(cm).__name__}")
    return cm.eval(wi, wo, min_cos=min_cos)
