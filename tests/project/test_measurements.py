"""project.Measurements: validation, immutability, subsets, channels, folds, describe().

References are written out here: directions from explicit sin/cos formulas, interpolated
values by hand, fold groups by brute-force comparison of pairs, reciprocal counts by a
double loop.
"""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest

from project import Measurements
from project import lstsq as lstsq_module
from project.measurements import HORIZON_ATOL, UNIT_ATOL
from tests.conftest import random_directions
from tests.conftest import twin_pairs as twins

#: upper-hemisphere unit vectors, (n, 3)
random_upper = partial(random_directions, upper=True)


def direction(theta, phi):
    """Unit vectors from angles, written out (z the normal, phi from x)."""
    theta, phi = np.broadcast_arrays(np.asarray(theta, float), np.asarray(phi, float))
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)],
                    axis=-1)


@pytest.fixture
def spectral(rng):
    """40 samples, 5 wavelengths 400..800 nm, some negative values, weights 1..2."""
    n = 40
    values = rng.normal(0.2, 0.3, size=(n, 5))
    return Measurements(random_upper(rng, n), random_upper(rng, n), values,
                        weights=rng.uniform(1, 2, n), wavelengths=[400, 500, 600, 700, 800],
                        isotropic=True, name="spec", source="/data/spec.csv",
                        info={"format": "csv"})


# ---------------------------------------------------------------------------- construction
def test_attributes_and_defaults(rng):
    wi, wo = random_upper(rng, 4), random_upper(rng, 4)
    m = Measurements(wi, wo, [1.0, -0.5, 0.0, 2.0])
    assert len(m) == 4 and m.channels == 1 and m.values.shape == (4, 1)
    assert m.channel_names == ("0",) and m.wavelengths is None and m.isotropic is None
    assert m.name is None and m.source is None and dict(m.info) == {}
    np.testing.assert_array_equal(m.weights, np.ones(4))
    # already unit vectors: renormalising changes them by at most an ulp or two
    np.testing.assert_allclose(m.wi, wi, rtol=0, atol=4e-16)
    for arr in (m.wi, m.wo, m.values, m.weights):
        assert arr.dtype == np.float64 and not arr.flags.writeable
    assert Measurements(wi, wo, np.ones((4, 3))).channel_names == ("R", "G", "B")
    assert Measurements(wi, wo, np.ones((4, 2))).channel_names == ("0", "1")
    s = Measurements(wi, wo, np.ones((4, 2)), wavelengths=[450, 632.8])
    assert s.channel_names == ("450 nm", "632.8 nm")
    assert Measurements(wi, wo, np.ones((4, 2)), channel_names=["a", "b"]).channel_names == \
        ("a", "b")
    assert repr(s) == "Measurements(name=None, samples=4, channels=2 (450 nm, 632.8 nm), " \
                      "isotropic=None)"


def test_renormalises_within_tolerance_and_puts_horizon_on_it():
    wi = np.array([[0.0, 0.0, 1.0 + 0.5 * UNIT_ATOL], [1.0, 0.0, -0.5 * HORIZON_ATOL]])
    m = Measurements(wi, wi[::-1], [1.0, 2.0])
    np.testing.assert_array_equal(np.linalg.norm(m.wi, axis=1), [1.0, 1.0])
    assert m.wi[1, 2] == 0.0 and m.wo[0, 2] == 0.0  # exactly on the horizon


def test_immutable(rng):
    m = Measurements(random_upper(rng, 3), random_upper(rng, 3), np.ones(3), name="a")
    with pytest.raises(AttributeError, match="immutable: cannot set 'name'"):
        m.name = "b"
    with pytest.raises(AttributeError, match="immutable: cannot set 'extra'"):
        m.extra = 1
    with pytest.raises(AttributeError, match="immutable: cannot delete"):
        del m.name
    with pytest.raises(ValueError, match="read-only"):
        m.values[0, 0] = 5.0
    view = m.wi
    with pytest.raises(ValueError, match="cannot set WRITEABLE"):
        view.flags.writeable = True
    with pytest.raises(TypeError, match="does not support item assignment"):
        m.info["x"] = 1


def test_input_is_copied(rng):
    wi, wo, v = random_upper(rng, 3), random_upper(rng, 3), np.ones(3)
    m = Measurements(wi, wo, v)
    wi[0] = [0.0, 0.0, 1.0]
    v[0] = 7.0
    assert m.values[0, 0] == 1.0 and m.wi[0, 2] != 1.0


UP = [[0.0, 0.0, 1.0]]


@pytest.mark.parametrize("kwargs, error, match", [
    ({"wi": [[0.0, 0.0, 1.0, 0.0]]}, ValueError,
     r"wi must have shape \(n, 3\), got shape \(1, 4\)"),
    ({"wi": [[0.0, 0.0, np.nan]]}, ValueError, r"wi must be finite: 1 of 1 rows .*row 0"),
    ({"wo": [[0.0, 0.0, 1.1]]}, ValueError,
     r"wo must be unit vectors .*first at row 0, norm 1.1"),
    ({"wo": [[0.6, 0.0, -0.8]]}, ValueError, r"wo must lie in the upper hemisphere .*row 0, "
                                             r"z = -0.8"),
    ({"wo": UP * 2}, ValueError, r"wo must have the shape of wi \(1, 3\), got shape \(2, 3\)"),
    ({"values": [1.0, 2.0]}, ValueError, r"values must have shape \(1,\) or \(1, channels"),
    ({"values": [[np.inf]]}, ValueError, "values must be finite: 1 entries .*row 0, channel 0"),
    ({"values": "abc"}, TypeError, "values must be an array of floats"),
    ({"weights": [-1.0]}, ValueError, "weights must be finite and >= 0, got -1.0 at row 0"),
    ({"weights": [0.0]}, ValueError, "weights must not all be zero"),
    ({"weights": [1.0, 1.0]}, ValueError, r"weights must have shape \(1,\)"),
    ({"wavelengths": [500, 400]}, ValueError, "wavelengths must be finite, > 0 and strictly"),
    ({"wavelengths": [500, 600, 700]}, ValueError, r"wavelengths must have shape \(2,\)"),
    ({"channel_names": ["a"]}, ValueError, r"one name per channel \(2\), got 1"),
    ({"channel_names": ["a", "a"]}, ValueError, "channel_names must be distinct"),
    ({"channel_names": "ab"}, TypeError, "channel_names must be a sequence of str"),
    ({"channel_names": ["a", 1]}, TypeError, "channel_names must be str, got 1"),
    ({"isotropic": 1}, TypeError, "isotropic must be True, False or None, got 1"),
    ({"name": 3}, TypeError, "name must be a str or None, got int"),
    ({"source": 3}, TypeError, "source must be a str, os.PathLike or None, got int"),
    ({"info": [1]}, TypeError, "info must be a mapping or None, got list"),
])
def test_bad_input(kwargs, error, match):
    args = {"wi": UP, "wo": UP, "values": [[1.0, 2.0]], **kwargs}
    wi, wo, values = args.pop("wi"), args.pop("wo"), args.pop("values")
    with pytest.raises(error, match=match):
        Measurements(wi, wo, values, **args)


def test_empty_set():
    m = Measurements(np.empty((0, 3)), np.empty((0, 3)), np.empty((0, 2)))
    assert len(m) == 0 and m.channels == 2
    assert m.folds().shape == (0,)
    d = m.describe()
    assert d["samples"] == 0 and d["reciprocal_pairs"] == 0 and d["value_range"] == []


# ---------------------------------------------------------------------------------- subsets
def test_indexing(spectral):
    m = spectral
    mask = m.values[:, 0] > 0.2
    for key, rows in [(mask, np.flatnonzero(mask)), (np.array([3, 0, -1]), [3, 0, 39]),
                      ([5, 6], [5, 6]), (slice(2, 9, 3), [2, 5, 8]), (7, [7]), (-1, [39]),
                      (np.int64(4), [4]), ([], [])]:
        sub = m[key]
        assert isinstance(sub, Measurements)
        np.testing.assert_array_equal(sub.wi, m.wi[rows])
        np.testing.assert_array_equal(sub.values, m.values[rows])
        np.testing.assert_array_equal(sub.weights, m.weights[rows])
        assert sub.channel_names == m.channel_names and sub.isotropic is True
        assert sub.name == "spec" and sub.source == m.source and sub.info == m.info
        assert not sub.values.flags.writeable
    assert len(m[7]) == 1 and m[7].values.shape == (1, 5)


@pytest.mark.parametrize("key, error, match", [
    (40, IndexError, "index 40 is out of range for 40 samples"),
    (np.array([0, 40]), IndexError, "index 40 is out of range"),
    (np.ones(3, bool), ValueError, r"boolean mask must have shape \(40,\), got shape \(3,\)"),
    (True, TypeError, "must be an int, a slice"),
    (1.5, TypeError, "got float"),
    (np.zeros((2, 2), int), TypeError, r"of dtype int64 and shape \(2, 2\)"),
    ("a", TypeError, "got str"),
])
def test_bad_index(spectral, key, error, match):
    with pytest.raises(error, match=match):
        spectral[key]


def test_angles_round_trip(rng):
    ti, to = rng.uniform(0, np.pi / 2, 20), rng.uniform(0, np.pi / 2, 20)
    pi, po = rng.uniform(-3, 3, 20), rng.uniform(-3, 3, 20)
    m = Measurements(direction(ti, pi), direction(to, po), np.ones(20))
    # arctan2 of exact sin/cos: a few ulp of pi
    for got, want in zip(m.angles(), (ti, pi, to, po), strict=True):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-14)


# --------------------------------------------------------------------------------- channels
def test_select_channels(spectral):
    m = spectral
    s = m.select_channels([1, "700 nm", -1])
    np.testing.assert_array_equal(s.values, m.values[:, [1, 3, 4]])
    np.testing.assert_array_equal(s.wavelengths, [500, 700, 800])
    assert s.channel_names == ("500 nm", "700 nm", "800 nm") and len(s) == len(m)
    np.testing.assert_array_equal(s.weights, m.weights)
    assert m.select_channels(2).channels == 1


@pytest.mark.parametrize("channels, error, match", [
    ([3, 1], ValueError, r"keep the wavelengths strictly increasing, got \[700.0, 500.0\]"),
    ([5], ValueError, r"channel index must lie in \[-5, 4\], got 5"),
    (["red"], ValueError, "indices or names among"),
    ([], ValueError, "at least one channel"),
    ([1.0], TypeError, "channels must be ints or names, got 1.0"),
    ([True], TypeError, "channels must be ints or names, got True"),
])
def test_bad_select_channels(spectral, channels, error, match):
    with pytest.raises(error, match=match):
        spectral.select_channels(channels)


def test_at_wavelengths_by_hand():
    wi = direction([0.1, 0.2], 0.0)
    v = np.array([[1.0, 3.0, 2.0, 0.0], [-1.0, 1.0, 5.0, 5.0]])
    m = Measurements(wi, wi, v, wavelengths=[400, 450, 550, 700])
    got = m.at_wavelengths([400, 425, 500, 650, 700])
    # by hand: 425 halfway 400-450; 500 halfway 450-550; 650 at 2/3 of 550-700
    want = [[1.0, 2.0, 2.5, 2.0 / 3.0, 0.0], [-1.0, 0.0, 3.0, 5.0, 5.0]]
    np.testing.assert_allclose(got.values, want, rtol=0, atol=4e-16)  # one rounding each
    assert got.values[0, 0] == 1.0 and got.values[1, 4] == 5.0  # measured: copied exactly
    assert got.channel_names == ("400 nm", "425 nm", "500 nm", "650 nm", "700 nm")
    np.testing.assert_array_equal(got.wavelengths, [400, 425, 500, 650, 700])
    assert m.at_wavelengths(450).values[:, 0].tolist() == [3.0, 1.0]


def test_at_wavelengths_rgb_of_a_31_band_set(rng):
    wl = np.arange(400.0, 701.0, 10.0)
    slope = rng.uniform(-1, 1, (6, 1))
    v = 0.5 + slope * (wl - 400.0) / 300.0  # linear in wavelength: interpolation is exact
    wi = random_upper(rng, 6)
    rgb = Measurements(wi, wi, v, wavelengths=wl).at_wavelengths([450, 550, 650])
    np.testing.assert_allclose(rgb.values, 0.5 + slope * np.array([50, 150, 250]) / 300.0,
                               rtol=0, atol=1e-15)


@pytest.mark.parametrize("nm, match", [
    (399.0, r"within the measured wavelengths \[400, 800\] nm \(no extrapolation\), got 399"),
    ([500, 900], "got 900"),
    ([600, 500], "strictly increasing"),
    ([np.nan], "finite"),
    ([[500]], "1-D"),
])
def test_bad_at_wavelengths(spectral, nm, match):
    with pytest.raises(ValueError, match=match):
        spectral.at_wavelengths(nm)


def test_at_wavelengths_needs_wavelengths(rng):
    m = Measurements(random_upper(rng, 2), random_upper(rng, 2), np.ones((2, 3)))
    with pytest.raises(ValueError, match=r"needs a set with wavelengths, got one with channels "
                                         r"\['R', 'G', 'B'\]"):
        m.at_wavelengths(500)


# ------------------------------------------------------------------------------------ folds
@pytest.fixture
def with_twins(rng):
    """60 pairs plus repeats, reciprocals and (isotropic) rotated and mirrored copies."""
    ti, to = rng.uniform(0, 1.4, 60), rng.uniform(0, 1.4, 60)
    pi, po = rng.uniform(-3, 3, 60), rng.uniform(-3, 3, 60)
    wi, wo = direction(ti, pi), direction(to, po)
    rot = rng.uniform(-1, 1, 10)
    wi = np.vstack([wi, wi[:10], wo[10:20], direction(ti[20:30], pi[20:30] + rot),
                    direction(ti[30:40], -pi[30:40])])
    wo = np.vstack([wo, wo[:10], wi[10:20], direction(to[20:30], po[20:30] + rot),
                    direction(to[30:40], -po[30:40])])
    return wi, wo


@pytest.mark.parametrize("isotropic", [True, False])
def test_folds_keep_twins_together(with_twins, isotropic):
    wi, wo = with_twins
    m = Measurements(wi, wo, np.ones(len(wi)), isotropic=isotropic)
    pairs = twins(m.wi, m.wo, isotropic)
    # repeats and reciprocals (20), plus rotations and mirrors (20) under isotropy
    assert len(pairs) == (40 if isotropic else 20)
    for k in (2, 3, 10):
        f = m.folds(k)
        assert all(f[i] == f[j] for i, j in pairs)
        assert set(f.tolist()) == set(range(k))


def test_folds_deterministic_and_seeded(with_twins):
    wi, wo = with_twins
    m = Measurements(wi, wo, np.ones(len(wi)))
    np.testing.assert_array_equal(m.folds(5, seed=3), m.folds(5, seed=3))
    assert not np.array_equal(m.folds(5, seed=3), m.folds(5, seed=4))


@pytest.mark.parametrize("isotropic", [True, False])
def test_folds_match_fit(rng, isotropic):
    # singleton groups: the split of project.fit (10 folds, seed 0) exactly
    wi, wo = random_upper(rng, 97), random_upper(rng, 97)
    m = Measurements(wi, wo, np.ones(97), isotropic=isotropic)
    want = lstsq_module._folds(m.wi, m.wo, isotropic, "auto")[0]
    np.testing.assert_array_equal(m.folds(), want)
    assert lstsq_module._FOLDS == 10  # the default k of folds()


def test_fold_sizes_near_equal(with_twins):
    wi, wo = with_twins
    m = Measurements(wi, wo, np.ones(len(wi)))
    for k in (2, 3, 7, 10):
        sizes = np.bincount(m.folds(k), minlength=k)
        # groups hold at most 2 samples here: greedy filling keeps sizes within 2
        assert sizes.sum() == len(m) and sizes.max() - sizes.min() <= 2, (k, sizes)


def test_folds_by_incidence():
    th = np.radians([10.0, 20.0, 30.0, 40.0, 50.0])
    wi = np.repeat(direction(th, 0.0), 4, axis=0)
    wo = direction(np.tile(np.radians([5.0, 15.0, 25.0, 35.0]), 5), 1.0)
    m = Measurements(wi, wo, np.ones(20), isotropic=True)
    f = m.folds(3, by="incidence")
    for g in range(5):
        assert len(set(f[4 * g:4 * g + 4].tolist())) == 1
    assert sorted(np.bincount(f).tolist()) == [4, 8, 8]
    # anisotropic grouping separates incidences of one theta and another phi
    wi2 = np.vstack([wi, direction(th, 2.0)])
    m2 = Measurements(wi2, np.vstack([wo, wo[:5]]), np.ones(25))
    assert len(set(m2.folds(10, by="incidence", isotropic=False).tolist())) == 10
    assert len(set(m2.folds(10, by="incidence", isotropic=True).tolist())) == 5


def test_fewer_groups_than_folds():
    wi = direction([0.1, 0.1, 0.2], 0.0)
    m = Measurements(wi, wi, np.ones(3))
    f = m.folds(10)
    assert f[0] == f[1] and sorted(np.bincount(f).tolist()) == [1, 2]  # two groups, two folds


def test_kfold(spectral):
    m = spectral
    f = m.folds(4, seed=1)
    seen = np.zeros(len(m), int)
    parts = list(m.kfold(4, seed=1))
    assert len(parts) == 4
    for j, (train, test) in enumerate(parts):
        assert len(train) + len(test) == len(m)
        np.testing.assert_array_equal(test.values, m.values[f == j])
        np.testing.assert_array_equal(train.wi, m.wi[f != j])
        assert train.wavelengths is not None and test.name == "spec"
        seen[f == j] += 1
    assert (seen == 1).all()


@pytest.mark.parametrize("kwargs, error, match", [
    ({"k": 1}, ValueError, "k must be >= 2, got 1"),
    ({"k": 2.0}, TypeError, "k must be an integer, got 2.0"),
    ({"by": "theta"}, ValueError, "by must be one of 'pairs', 'incidence', got 'theta'"),
    ({"isotropic": "yes"}, TypeError, "isotropic must be True, False or None"),
])
def test_bad_folds(spectral, kwargs, error, match):
    with pytest.raises(error, match=match):
        spectral.folds(**kwargs)


# --------------------------------------------------------------------------------- describe
def test_describe_counts():
    d_ = np.radians
    a, b, c = direction(d_(30), 0.0), direction(d_(60), d_(120)), direction(d_(45), d_(-90))
    # a rotated and mirrored: the isotropic twin of the swapped pair (b, a) up to rotation
    rot_b, rot_a = direction(d_(60), d_(10)), direction(d_(30), d_(-110))
    wi = np.array([a, b, a, c, c, rot_b, direction(d_(1e-3), 0.0)])
    wo = np.array([b, a, b, a, c, rot_a, direction(d_(1e-3), 0.0)])
    v = np.array([[0.5, -0.1], [0.4, 0.2], [0.5, 0.1], [-0.2, 0.3], [1.0, 2.0], [0.1, 0.1],
                  [0.0, 0.0]])
    m = Measurements(wi, wo, v, wavelengths=[500, 600], isotropic=True, name="x",
                     info={"format": "csv"})
    d = m.describe()
    assert d["samples"] == 7 and d["channels"] == 2 and d["wavelengths_nm"] == [500.0, 600.0]
    assert d["isotropic"] is True and d["name"] == "x" and d["info"] == {"format": "csv"}
    assert d["incidence_directions"] == 5
    assert d["theta_i_deg"] == [0.001, 30.0, 45.0, 60.0]
    np.testing.assert_allclose(d["theta_o_deg"], [0.001, 60.0], rtol=1e-12)
    assert d["phi_i_constant"] is False
    assert d["duplicate_pairs"] == 1  # row 2 repeats row 0
    # by hand: rows 0, 1, 2 have their swap measured; 3 (c, a) has not; 4 and 6 are
    # w_i = w_o; 5's swap (rot_a, rot_b) is a rotation of (a, b) only
    assert d["reciprocal_pairs"] == 3
    assert d["reciprocal_pairs_isotropic"] == 4
    assert d["negative_values"] == 2 and d["negative_fraction"] == 2 / 14
    assert d["value_range"] == [[-0.2, 1.0], [-0.1, 2.0]]
    assert d["weights"] == [1.0, 1.0]


def test_describe_phi_i_constant_and_tolerance():
    wi = direction(np.radians([0.0, 20.0, 40.0]), np.radians([33.0, 180.0, -180.0]))
    wo = direction(np.radians([20.0, 0.0, 10.0]), np.radians([180.0, 0.0, 0.0]))
    m = Measurements(wi, wo, np.ones(3))
    d = m.describe()
    assert d["phi_i_constant"] is True  # 180 and -180 are one azimuth; the pole has none
    assert d["reciprocal_pairs"] == 2
    # swap of row 0 displaced by 0.02 degrees: counted at tol 0.05, not at the default 0.01
    wo2 = wo.copy()
    wo2[1] = direction(np.radians(0.02), 0.0)
    m2 = Measurements(wi, wo2, np.ones(3))
    assert m2.describe()["reciprocal_pairs"] == 0
    assert m2.describe(tol_deg=0.05)["reciprocal_pairs"] == 2
    with pytest.raises(ValueError, match="tol_deg must be finite and >= 0, got -1"):
        m.describe(tol_deg=-1)


def test_describe_is_json_able(spectral):
    import json

    d = json.loads(json.dumps(spectral.describe()))
    assert d["source"] == "/data/spec.csv" and d["channels"] == 5
