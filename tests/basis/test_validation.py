"""basis.validation: the input checks every public wrapper shares, and their messages."""

from __future__ import annotations

import numpy as np
import pytest

from basis import validation as v


def test_as_directions_accepts_and_returns_contiguous_float64():
    d = v.as_directions(np.array([[0, 0, 1], [1, 0, 0]], dtype=np.int32)[:, ::-1][:, ::-1])
    assert d.dtype == np.float64 and d.flags.c_contiguous
    near = [0.0, 0.0, 1.0 + 0.9 * v.UNIT_ATOL]  # within the tolerance: accepted as given
    assert v.as_directions(near)[2] == near[2]
    assert v.as_directions(np.empty((0, 3))).shape == (0, 3)


@pytest.mark.parametrize("dirs, kw, exc, match", [
    ("up", {}, TypeError, r"w must be an array of floats"),
    ([0.0, 1.0], {}, ValueError, r"w must have shape \(\.\.\., 3\), got shape \(2,\)"),
    ([[0, 0, 1.0], [np.nan, 0, 1]], {}, ValueError, r"w must be finite: 1 of 2 .*index 1"),
    ([0, 0, 0.0], {}, ValueError, r"zero-length vectors have no direction"),
    ([0, 0, 2.0], {}, ValueError, r"w must be unit vectors: .*norm 2.*normalise them first"),
    ([0, 0, -1.0], dict(upper=True), ValueError, r"upper hemisphere z >= 0.*z = -1"),
])
def test_as_directions_errors(dirs, kw, exc, match):
    with pytest.raises(exc, match=match):
        v.as_directions(dirs, "w", **kw)


def test_integers_choices_bytes_and_batches():
    assert v.nonneg_int(np.int64(3), "n") == 3
    for bad, exc in ((2.0, TypeError), (True, TypeError), ("2", TypeError), (-1, ValueError)):
        with pytest.raises(exc, match="n must be"):
            v.nonneg_int(bad, "n")
    with pytest.raises(ValueError, match=r"n must be <= 4 \(why\), got 5"):
        v.nonneg_int(5, "n", maximum=4, why=" (why)")
    assert v.choice("a", "k", ("a", "b")) == "a"
    with pytest.raises(ValueError, match="k must be one of 'a', 'b', got 'c'"):
        v.choice("c", "k", ("a", "b"))
    v.check_bytes(v.MAX_BYTES, "fine")
    with pytest.raises(MemoryError, match=r"work would need .* GiB.*fewer points"):
        v.check_bytes(v.MAX_BYTES + 1, "work")
    a, b = np.zeros((4, 1, 3)), np.zeros((5, 3))
    assert v.broadcast_batch(a, b) == (4, 5)
    with pytest.raises(ValueError, match="wi and wo must have broadcastable batch shapes"):
        v.broadcast_batch(np.zeros((2, 3)), np.zeros((3, 3)))


def test_dask_client_check(monkeypatch):
    """The one check behind every client= argument: type, then a missing extra."""
    import sys

    from basis.validation import dask_client

    pytest.importorskip("distributed")
    with pytest.raises(TypeError, match="dask.distributed.Client, got str"):
        dask_client("tcp://host:8786", "simulate")
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed
    with pytest.raises(ImportError, match=r"write_all\(client=...\) needs dask.distributed.*"
                                          r"pip install 'scatmodes\[distributed\]'"):
        dask_client(object(), "write_all")


@pytest.mark.parametrize("dirs", [
    np.array([[0, 0, 1 + 1e-3j]]),
    [[0, 0, 1j]],
    np.array([0, 0, 1], dtype=np.complex64),  # imaginary part 0: still not a direction
])
def test_complex_directions_are_refused(dirs):
    # numpy would drop the imaginary part with only a ComplexWarning
    with pytest.raises(TypeError, match=r"dirs must be real \(float\), got complex"):
        v.as_directions(dirs)


def test_basis_eval_refuses_complex_directions():
    from basis import HemiZernike, SphericalHarmonics

    for b in (HemiZernike(2), SphericalHarmonics(2)):
        with pytest.raises(TypeError, match=r"dirs must be real \(float\), got complex128"):
            b.eval(np.array([[0.6, 0.0, 0.8 + 0.1j]]))
