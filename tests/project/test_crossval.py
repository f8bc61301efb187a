"""project.crossval: errors of predictions against measured samples (closed forms, weights,
the delta-method standard error against a brute-force computation and a jackknife, the log
metric's clamp) and k-fold cross-validation (every sample predicted once by a fit that did
not see it, twins never split, determinism, bad arguments)."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest

from basis import from_angles
from project import Measurements
from project.crossval import cross_validate, sample_errors
from tests.conftest import random_directions
from tests.conftest import twin_pairs as twins

#: upper-hemisphere unit vectors, (n, 3)
random_upper = partial(random_directions, upper=True)

EPS = np.finfo(np.float64).eps


@pytest.fixture
def meas(rng):
    """80 random pairs, 3 channels of positive values, random weights."""
    n = 80
    return Measurements(random_upper(rng, n), random_upper(rng, n),
                        rng.uniform(0.05, 2.0, (n, 3)), weights=rng.uniform(0.5, 2.0, n))


def weighted_l2(m, g):
    """sqrt(sum w (q_hat - q)^2 / sum w q^2) per channel, written out (module notes)."""
    cc = (m.wi[:, 2] * m.wo[:, 2])[:, None]
    w = m.weights[:, None]
    return np.sqrt(np.sum(w * ((g - m.values) * cc) ** 2, axis=0) /
                   np.sum(w * (m.values * cc) ** 2, axis=0))


# -- sample_errors: closed forms ----------------------------------------------------------------

def test_zero_prediction_scores_one_and_scaled_prediction_its_scale(meas):
    """Predicting 0 gives sum w q^2 / sum w q^2 = 1 exactly; 1.1 f gives |0.1| in every
    channel (the doctest's closed forms, on random data). Tolerance: a ratio of two sums of
    80 positive terms, each rounded, ~10 eps."""
    e0 = sample_errors(meas, np.zeros(len(meas)))
    np.testing.assert_allclose(e0["l2_channels"], 1.0, rtol=10 * EPS, atol=0)
    assert e0["l2"] == max(e0["l2_channels"])
    e1 = sample_errors(meas, 1.1 * meas.values)
    np.testing.assert_allclose(e1["l2_channels"], 0.1, rtol=1e-13, atol=0)
    np.testing.assert_allclose(e1["l2_channels"], weighted_l2(meas, 1.1 * meas.values),
                               rtol=1e-13, atol=0)
    # exact predictions: 0 in both metrics
    e = sample_errors(meas, meas.values)
    assert e["l2"] == 0.0 and e["log"] == 0.0


def test_largest_channel_and_its_stderr(meas):
    """l2 and log are the largest channel's, l2_stderr belongs to that channel."""
    g = meas.values * np.array([1.05, 1.3, 0.9])
    e = sample_errors(meas, g)
    np.testing.assert_allclose(e["l2_channels"], [0.05, 0.3, 0.1], rtol=1e-13, atol=0)
    assert e["l2"] == e["l2_channels"][1]
    one = sample_errors(meas.select_channels(1), g[:, 1])
    assert e["l2_stderr"] == pytest.approx(one["l2_stderr"], rel=1e-13, abs=0)


def test_one_prediction_column_stands_for_all_channels(meas):
    g = np.full(len(meas), 0.4)
    a = sample_errors(meas, g)
    b = sample_errors(meas, np.repeat(g[:, None], 3, axis=1))
    assert a == b


def test_weight_zero_sample_changes_nothing(meas, rng):
    """A sample of weight 0, whatever its value and prediction, leaves the errors unchanged
    (bit for bit up to the order of summation: 1e-14)."""
    g = meas.values * rng.uniform(0.8, 1.2, meas.values.shape)
    extra = Measurements(np.vstack([meas.wi, [0.0, 0.6, 0.8]]), np.vstack([meas.wo, [0, 0, 1.0]]),
                         np.vstack([meas.values, [50.0, -3.0, 7.0]]),
                         weights=np.r_[meas.weights, 0.0])
    a = sample_errors(meas, g)
    b = sample_errors(extra, np.vstack([g, [-40.0, 9.0, 0.0]]))
    for key in ("l2_channels", "log_channels"):
        np.testing.assert_allclose(b[key], a[key], rtol=1e-14, atol=0)
    # the folds of a real cross-validation are groups of samples: a weight-0 sample put in an
    # existing fold changes nothing in the standard errors either
    folds = np.arange(len(meas)) % 8
    a = sample_errors(meas, g, folds=folds)
    b = sample_errors(extra, np.vstack([g, [-40.0, 9.0, 0.0]]), folds=np.r_[folds, 3])
    for key in ("l2_stderr", "log_stderr"):
        assert b[key] == pytest.approx(a[key], rel=1e-13, abs=0)


def test_doubling_a_weight_equals_duplicating_the_sample(meas, rng):
    """w -> 2 w at sample 0 is the same sum as sample 0 twice (weight w each); with the
    duplicate in the same fold the group sums, so the standard errors, are equal too."""
    g = meas.values * rng.uniform(0.8, 1.2, meas.values.shape)
    w2 = meas.weights.copy()
    w2[0] *= 2.0
    doubled = Measurements(meas.wi, meas.wo, meas.values, weights=w2)
    dup = Measurements(np.vstack([meas.wi, meas.wi[:1]]), np.vstack([meas.wo, meas.wo[:1]]),
                       np.vstack([meas.values, meas.values[:1]]),
                       weights=np.r_[meas.weights, meas.weights[0]])
    folds = np.arange(len(meas)) % 8
    a = sample_errors(doubled, g, folds=folds)
    b = sample_errors(dup, np.vstack([g, g[:1]]), folds=np.r_[folds, folds[0]])
    for key in ("l2", "log", "l2_stderr", "log_stderr"):
        assert b[key] == pytest.approx(a[key], rel=1e-13, abs=0), key


# -- sample_errors: the standard error ----------------------------------------------------------

def delta_method_stderr(num, den):
    """se of sqrt(N / D), N, D sums of k iid group terms: grad^T Cov grad by brute force,
    the gradient by central differences and Cov = k cov(num_g, den_g) (np.cov, ddof 1)."""
    k = num.size
    cov = k * np.cov(np.stack([num, den]))
    big_n, big_d = num.sum(), den.sum()

    def g(a, b):
        return np.sqrt(a / b)

    hn, hd = 1e-6 * big_n, 1e-6 * big_d
    grad = np.array([(g(big_n + hn, big_d) - g(big_n - hn, big_d)) / (2 * hn),
                     (g(big_n, big_d + hd) - g(big_n, big_d - hd)) / (2 * hd)])
    return float(np.sqrt(grad @ cov @ grad))


def jackknife_stderr(num, den):
    """Leave-one-group-out jackknife of sqrt(N / D) (Efron & Tibshirani 1993, eq. 11.5)."""
    k = num.size
    loo = np.sqrt((num.sum() - num) / (den.sum() - den))
    return float(np.sqrt((k - 1) / k * np.sum((loo - loo.mean()) ** 2)))


def group_sums(m, g, folds):
    cc = m.wi[:, 2] * m.wo[:, 2]
    w = m.weights
    f, h = m.values[:, 0], g[:, 0]
    d = np.log1p(np.maximum(f, 0) * m.wi[:, 2]) - np.log1p(np.maximum(h, 0) * m.wi[:, 2])
    k = folds.max() + 1
    out = {name: np.bincount(folds, weights=t, minlength=k) for name, t in (
        ("e2", w * ((h - f) * cc) ** 2), ("q2", w * (f * cc) ** 2), ("d2", w * d * d),
        ("w", w))}
    return out


def test_stderr_is_the_delta_method(meas, rng):
    """The l2 and log standard errors over 40 folds equal a brute-force delta-method
    computation (numerical gradient, sample covariance of the fold sums): the two are the
    same formula written differently, so they agree to the 1e-6 of the central differences
    (measured 1e-9). A jackknife over the folds estimates the same quantity with an O(1/k)
    difference: within 15 % at k = 40 (measured 2-4 %)."""
    m = meas.select_channels(0)
    g = m.values * rng.uniform(0.7, 1.3, m.values.shape) + rng.normal(0.0, 0.05, m.values.shape)
    folds = rng.permutation(np.arange(len(m)) % 40)
    e = sample_errors(m, g, folds=folds)
    s = group_sums(m, g, folds)
    ref_l2 = delta_method_stderr(s["e2"], s["q2"])
    ref_log = delta_method_stderr(s["d2"], s["w"])
    assert e["l2_stderr"] == pytest.approx(ref_l2, rel=1e-6, abs=0)
    assert e["log_stderr"] == pytest.approx(ref_log, rel=1e-6, abs=0)
    assert e["l2_stderr"] == pytest.approx(jackknife_stderr(s["e2"], s["q2"]), rel=0.15)
    assert e["log_stderr"] == pytest.approx(jackknife_stderr(s["d2"], s["w"]), rel=0.15)
    # without folds every sample is its own group
    e1 = sample_errors(m, g)
    s1 = group_sums(m, g, np.arange(len(m)))
    assert e1["l2_stderr"] == pytest.approx(delta_method_stderr(s1["e2"], s1["q2"]),
                                            rel=1e-6, abs=0)
    # fold labels are names, not indices: relabelling changes nothing
    e2 = sample_errors(m, g, folds=100 + 7 * folds)
    assert e2 == e


def test_stderr_nan_for_one_group(meas):
    e = sample_errors(meas, 1.2 * meas.values, folds=np.zeros(len(meas), dtype=int))
    assert e["l2"] == pytest.approx(0.2, rel=1e-13) and np.isnan(e["l2_stderr"])


def test_log_metric_counts_negative_values_as_zero(rng):
    """log = sqrt(sum w d^2 / sum w), d = log(1 + max(f, 0) c_i) - log(1 + max(f_hat, 0) c_i):
    negative measurements (noise) and negative predictions (undershoot) count as 0. So a
    negative measurement predicted by 0 costs nothing, and two predictions that differ only
    below 0 score the same."""
    n = 30
    m = Measurements(random_upper(rng, n), random_upper(rng, n),
                     np.r_[rng.uniform(0.1, 1.0, n - 5), -rng.uniform(0.01, 0.1, 5)],
                     weights=rng.uniform(0.5, 2.0, n))
    g = np.r_[rng.uniform(0.1, 1.0, n - 5), np.zeros(5)]
    ci = m.wi[:, 2]
    f = m.values[:, 0]
    d = np.log1p(np.maximum(f, 0) * ci) - np.log1p(g * ci)
    want = np.sqrt(np.sum(m.weights * d * d) / np.sum(m.weights))
    e = sample_errors(m, g)
    assert e["log"] == pytest.approx(want, rel=1e-13, abs=0)
    g_neg = g.copy()
    g_neg[-5:] = -rng.uniform(0.1, 5.0, 5)
    assert sample_errors(m, g_neg)["log"] == pytest.approx(e["log"], rel=1e-13, abs=0)
    # the l2 metric does see the negative values: they are part of q
    assert sample_errors(m, g_neg)["l2"] > e["l2"]
    # exact prediction of the negative values: log 0 at those samples
    sub = m[n - 5:]
    assert sample_errors(sub, sub.values)["log"] == 0.0


@pytest.mark.parametrize("f_hat, error, match", [
    (np.ones(4), ValueError, r"f_hat must have shape \(5,\), \(5, 1\) or \(5, 2\), got \(4,\)"),
    (np.ones((5, 3)), ValueError, r"f_hat must have shape .*got \(5, 3\)"),
    (np.r_[1.0, np.nan, 1, 1, 1], ValueError, r"f_hat must be finite: 1 values are NaN or inf"),
    ("abc", TypeError, r"f_hat must be an array of floats, got str"),
])
def test_sample_errors_bad_predictions(rng, f_hat, error, match):
    m = Measurements(random_upper(rng, 5), random_upper(rng, 5), np.ones((5, 2)))
    with pytest.raises(error, match=match):
        sample_errors(m, f_hat)


def test_sample_errors_needs_measurements():
    with pytest.raises(TypeError, match=r"measurements must be a project.Measurements, got "
                                        r"ndarray"):
        sample_errors(np.ones((3, 3)), np.ones(3))


def test_sample_errors_bad_folds_and_zero_channel(rng):
    m = Measurements(random_upper(rng, 5), random_upper(rng, 5), np.ones((5, 2)))
    with pytest.raises(ValueError, match=r"folds must be \(5,\) integers, got float64 \(5,\)"):
        sample_errors(m, np.ones(5), folds=np.zeros(5))
    with pytest.raises(ValueError, match=r"folds must be \(5,\) integers, got int64 \(4,\)"):
        sample_errors(m, np.ones(5), folds=np.zeros(4, dtype=np.int64))
    z = Measurements(m.wi, m.wo, np.c_[np.ones(5), np.zeros(5)])
    with pytest.raises(ValueError, match=r"q = f cos cos is 0 at every sample of channel 1 "
                                         r"\(1\): the relative error is undefined"):
        sample_errors(z, np.ones(5))


# -- cross_validate -------------------------------------------------------------------------------

class _Constant:
    """Predicts a constant per channel; records the samples (ids) it was asked about."""

    def __init__(self, value, train_ids, log):
        self.value = np.asarray(value, dtype=float)
        self.train_ids = train_ids
        self.log = log

    def eval(self, wi, wo):
        self.log.append((self.train_ids, np.asarray(wi).copy(), np.asarray(wo).copy()))
        return np.broadcast_to(self.value, (len(wi), self.value.size)).copy()


def instrumented(ids_of):
    """A fit callable that fits the weighted mean and logs what it saw and predicted."""
    log = []
    calls = []

    def fit(train):
        calls.append(train)
        mean = np.average(train.values, axis=0, weights=train.weights)
        return _Constant(mean, frozenset(ids_of(train)), log)

    return fit, calls, log


def direction(theta, phi):
    return from_angles(np.asarray(theta, float), np.asarray(phi, float))


def twin_set(rng, isotropic):
    """50 pairs plus repeats, reciprocals and (isotropic) rotated and mirrored copies; the
    value of sample j is 1 + j, an id (positive, so q is never 0)."""
    ti, to = rng.uniform(0, 1.4, 50), rng.uniform(0, 1.4, 50)
    pi, po = rng.uniform(-3, 3, 50), rng.uniform(-3, 3, 50)
    wi, wo = direction(ti, pi), direction(to, po)
    rot = rng.uniform(-1, 1, 10)
    wi = np.vstack([wi, wi[:10], wo[10:20], direction(ti[20:30], pi[20:30] + rot),
                    direction(ti[30:40], -pi[30:40])])
    wo = np.vstack([wo, wo[:10], wi[10:20], direction(to[20:30], po[20:30] + rot),
                    direction(to[30:40], -po[30:40])])
    n = len(wi)
    return Measurements(wi, wo, 1.0 + np.arange(n), isotropic=isotropic)


@pytest.mark.parametrize("isotropic", [True, False])
@pytest.mark.parametrize("k", [2, 3, 10])
def test_every_sample_predicted_once_by_a_fit_that_did_not_see_it(rng, isotropic, k):
    m = twin_set(rng, isotropic)
    ids = np.rint(m.values[:, 0] - 1).astype(int)  # the value of sample j is 1 + j

    def ids_of(train):
        return np.rint(train.values[:, 0] - 1).astype(int).tolist()

    fit, calls, log = instrumented(ids_of)
    cv = cross_validate(m, fit, k=k)
    assert cv["folds"] == k == len(calls) == len(log)
    # which fit predicted which sample: the rows whose pair is one a fit was asked about
    # (repeats share a pair, and a fold, so a pair stands for all its rows)
    predicted_by = {}
    pred = np.empty(len(m))
    for train_ids, wi, wo in log:
        rows = {int(r) for a, b in zip(wi, wo, strict=True)
                for r in np.flatnonzero(np.all(m.wi == a, axis=1) & np.all(m.wo == b, axis=1))}
        assert len(rows) == len(wi), "a pair was predicted twice by one fit"
        for r in rows:
            assert r not in predicted_by, f"sample {r} predicted twice"
            predicted_by[r] = train_ids
            pred[r] = np.mean([1.0 + t for t in train_ids])
        # training and held-out sets partition the samples
        assert len(train_ids) + len(rows) == len(m)
    assert sorted(predicted_by) == list(range(len(m)))
    for r, train_ids in predicted_by.items():
        assert ids[r] not in train_ids, f"sample {r} was in its own training set"
    # twins of a held-out sample are held out with it
    pairs = twins(m.wi, m.wo, isotropic)
    assert len(pairs) == (40 if isotropic else 20)
    for i, j in pairs:
        assert ids[j] not in predicted_by[i] and ids[i] not in predicted_by[j]
    # the reported errors are those of the collected out-of-fold predictions
    folds = m.folds(k)
    e = sample_errors(m, pred, folds=folds)
    for key in ("l2", "l2_stderr", "log", "log_stderr"):
        assert cv[key] == pytest.approx(e[key], rel=1e-12), key
    for f, fl2 in enumerate(cv["fold_l2"]):
        t = folds == f
        assert fl2 == pytest.approx(float(weighted_l2(m[t], pred[t, None])[0]), rel=1e-12)
    assert cv["validation"] == f"{k}-fold CV on held-out samples, grouped by direction pair"
    assert cv["seconds"] >= 0.0


def test_by_incidence_holds_out_whole_incidences():
    th = np.radians([10.0, 20.0, 30.0, 40.0, 50.0])
    wi = np.repeat(direction(th, 0.0), 6, axis=0)
    wo = direction(np.tile(np.radians([5.0, 15.0, 25.0, 35.0, 45.0, 55.0]), 5), 1.0)
    m = Measurements(wi, wo, 1.0 + np.arange(30), isotropic=True)
    seen = []

    def fit(train):
        seen.append(set(np.round(train.wi[:, 2], 12).tolist()))
        return _Constant(train.values.mean(), None, [])

    cv = cross_validate(m, fit, k=5, by="incidence")
    assert cv["folds"] == 5
    assert cv["validation"] == "5-fold CV on held-out samples, grouped by incidence"
    # each fit saw 4 of the 5 incidences, each incidence left out once
    assert [len(s) for s in seen] == [4] * 5
    assert len(set.union(*seen)) == 5 and len(set.intersection(*seen)) == 0


def test_deterministic_and_seeded(rng):
    m = twin_set(rng, True)

    def fit(train):
        return _Constant(np.average(train.values, axis=0, weights=train.weights), None, [])

    a, b = cross_validate(m, fit, k=5, seed=3), cross_validate(m, fit, k=5, seed=3)
    a.pop("seconds"), b.pop("seconds")
    assert a == b
    c = cross_validate(m, fit, k=5, seed=4)
    assert c["fold_l2"] != a["fold_l2"]


def test_fewer_groups_than_folds(rng):
    """k larger than the number of twin groups: one fold per group."""
    a, b = direction(0.3, 0.0), direction(0.6, 2.0)
    m = Measurements([a, b, a, direction(0.9, 1.0)], [b, a, b, direction(0.2, 0.5)],
                     [1.0, 2.0, 3.0, 4.0], isotropic=False)
    cv = cross_validate(m, lambda t: _Constant(t.values.mean(), None, []), k=10)
    assert cv["folds"] == 2 and len(cv["fold_l2"]) == 2


@pytest.mark.parametrize("kwargs, error, match", [
    ({"k": 1}, ValueError, r"k must be >= 2 folds, got 1"),
    ({"k": 2.0}, TypeError, r"k must be an integer"),
    ({"k": -3}, ValueError, r"k must be"),
    ({"fit": "lstsq"}, TypeError, r"fit must be a callable fit\(train\) -> representation, "
                                  r"got str"),
    ({"measurements": np.ones((3, 3))}, TypeError,
     r"measurements must be a project.Measurements, got ndarray"),
    ({"by": "theta"}, ValueError, r"by must be one of 'pairs', 'incidence', got 'theta'"),
])
def test_cross_validate_bad_arguments(rng, kwargs, error, match):
    m = Measurements(random_upper(rng, 6), random_upper(rng, 6), np.ones(6))
    args = {"measurements": m, "fit": lambda t: _Constant(1.0, None, [])} | kwargs
    meas_arg, fit_arg = args.pop("measurements"), args.pop("fit")
    with pytest.raises(error, match=match):
        cross_validate(meas_arg, fit_arg, **args)


def test_cross_validate_needs_two_distinct_pairs():
    a, b = direction(0.3, 0.0), direction(0.6, 2.0)
    m = Measurements([a, b, a], [b, a, b], [1.0, 2.0, 3.0])  # one pair, its reciprocal, repeat
    with pytest.raises(ValueError, match=r"cross-validation needs at least 2 distinct direction "
                                         r"pairs, Measurements\(.*samples=3.*\) has 1"):
        cross_validate(m, lambda t: _Constant(1.0, None, []))
