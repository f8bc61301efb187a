"""basis.kinds: one vocabulary of basis kinds and its factory, round trips with Basis.kind."""

from __future__ import annotations

import pytest

import basis

ALL = [basis.HemiZernike(7), basis.HemiHarmonics(7), basis.HemiHarmonics(6, parity="even"),
       basis.SphericalHarmonics(6)]


@pytest.mark.parametrize("b", ALL + [basis.HemiZernike(0)], ids=repr)
def test_make_basis_round_trips_kind(b):
    assert b.kind in basis.KINDS
    assert basis.make_basis(b.kind, b.order) == b


def test_make_basis_errors():
    with pytest.raises(ValueError, match="kind must be one of 'zernike', 'harmonics'"):
        basis.make_basis("hemi_sh", 3)
    with pytest.raises(ValueError, match="order must be >= 1 for kind='harmonics'"):
        basis.make_basis("harmonics", 0)
    with pytest.raises(TypeError, match="must be an integer"):
        basis.make_basis("zernike", 2.0)
