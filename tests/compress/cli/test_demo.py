"""compress.cli.demo: the numbers ``scatmodes demo`` prints, against exact quadrature facts."""

from __future__ import annotations

import numpy as np
import pytest

import basis
from compress.cli.demo import (
    modes_orthonormality_error,
    orthonormality_error,
    resolution_deg,
    to_markdown,
)


@pytest.mark.parametrize("b", [basis.HemiZernike(8), basis.HemiHarmonics(8),
                               basis.SphericalHarmonics(8)], ids=repr)
def test_orthonormality_error_is_rounding(b):
    # exact rules: the Gram matrix is I up to rounding (sums of ~100 O(1) products)
    assert orthonormality_error(b) < 1e-13


def test_orthonormality_error_sees_a_wrong_basis():
    # negative control: functions scaled by 1/2 have the Gram matrix I / 4
    class Halved(basis.HemiZernike):
        def _eval_flat(self, dirs, out):
            super()._eval_flat(dirs, out)
            out *= 0.5

    assert orthonormality_error(Halved(2)) == pytest.approx(0.75)


def test_modes_orthonormality_error_is_rounding():
    assert modes_orthonormality_error(basis.HelmholtzModes(4)) < 1e-13


def test_resolution_and_markdown():
    assert resolution_deg(8) == 22.5 and resolution_deg(0) == np.inf
    md = to_markdown([{"basis": "Z(2)", "error": 1.5e-16, "ns per value": 3.25,
                       "gap": float("nan")}])
    assert md.splitlines() == ["| basis | error | ns per value | gap |", "|---|---|---|---|",
                               "| Z(2) | 1.50e-16 | 3.2 | - |"]
