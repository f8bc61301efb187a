"""compress.evaluate: the names of scatmodes 0.1 (FastEvaluator, evaluate) are the compiled
evaluator of basis.evaluate, checked against CoefficientMatrix.eval bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

import basis
import compress
from basis import CoefficientMatrix, Evaluator
from tests.conftest import random_directions


def test_compress_names_still_work(rng):
    # compress.FastEvaluator and compress.evaluate from scatmodes 0.1 are the same machinery
    x = rng.normal(size=(3, 10, 10))
    cm = CoefficientMatrix(basis.HemiZernike(3), x + x.swapaxes(1, 2), "f_cos",
                           isotropic=False).to_isotropic()
    wi = random_directions(rng, 50, upper=True)
    assert compress.FastEvaluator is Evaluator
    assert np.array_equal(compress.evaluate(cm, wi, wi[::-1]), cm.eval(wi, wi[::-1]))
    assert np.array_equal(compress.FastEvaluator(cm)(wi, wi[::-1]), cm.eval(wi, wi[::-1]))


def test_evaluate_refuses_other_objects():
    with pytest.raises(TypeError, match="cm must be a basis.CoefficientMatrix"):
        compress.evaluate(np.eye(3), [0, 0, 1.0], [0, 0, 1.0])
