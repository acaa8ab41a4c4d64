"""The split, the calibration rule and the tuning protocol."""

import numpy as np
import pandas as pd
import pytest

from quadformer.evaluation.protocol import best_f1_threshold, budget_threshold, split_flights, tune
from quadformer.detectors import runs
from quadformer.evaluation.metrics import pointwise


def _scenarios(n=50, attacked=25):
    return pd.DataFrame({"flight_id": np.arange(n), "attacked": np.arange(n) < attacked})


def test_split_by_flight_is_disjoint_stratified_and_seeded():
    sc = _scenarios()
    sp = split_flights(sc, seed=1)
    allf = np.concatenate([sp.train, sp.val, sp.test])
    assert sorted(allf.tolist()) == list(range(50))
    assert len(sp.train) == 30 and len(sp.val) == 10 and len(sp.test) == 10
    for part in (sp.train, sp.val, sp.test):
        assert 0 < np.isin(part, np.arange(25)).sum() < len(part)   # attacked and clean in each
    assert set(sp.labelled) <= set(sp.train) and len(sp.labelled) == 6
    again = split_flights(sc, seed=1)
    assert np.array_equal(again.test, sp.test)
    assert not np.array_equal(split_flights(sc, seed=2).test, sp.test)
    with pytest.raises(ValueError, match="fractions"):
        split_flights(sc, 0, fractions=(0.5, 0.5, 0.5))


def test_best_f1_threshold_hand_case_and_exhaustive():
    s = np.array([0.1, 0.4, 0.35, 0.8])
    y = np.array([0, 0, 1, 1])
    thr, f1 = best_f1_threshold(s, y)
    assert f1 == pytest.approx(0.8) and thr == pytest.approx(0.225)
    assert pointwise(y, s > thr)[2] == pytest.approx(0.8)
    rng = np.random.default_rng(0)
    for _ in range(20):
        y = rng.random(200) < 0.3
        s = np.round(rng.random(200) + y * 0.5, 2)          # ties on purpose
        thr, f1 = best_f1_threshold(s, y)
        brute = max(pointwise(y, s > c)[2] for c in np.r_[np.unique(s), -1.0])
        assert f1 == pytest.approx(brute)
        assert pointwise(y, s > thr)[2] == pytest.approx(f1)


def test_budget_threshold_allows_no_alarm_on_short_clean_time():
    s = np.array([0.1, 0.5, 0.2, 0.9, 0.3])
    fid = np.array([0, 0, 0, 1, 1])
    assert budget_threshold(s, fid, np.array([0]), hours=0.1) == 0.5
    assert np.all(s[fid == 0] <= 0.5)


def test_budget_threshold_search_lowers_the_threshold_to_the_allowed_alarm_runs():
    """Two clean flights, two hours: two alarm runs allowed. The search goes down from the
    top through the candidate thresholds while at most two runs alarm."""
    rng = np.random.default_rng(0)
    a = rng.uniform(0.0, 0.5, 200)
    b = rng.uniform(0.0, 0.5, 200)
    a[[20, 21, 22]], a[90], a[150] = 0.9, 0.8, 0.7       # one run of three steps and two single steps
    b[60] = 0.95
    s, fid = np.r_[a, b], np.repeat([0, 1], 200)

    def n_runs(thr):
        return sum(len(runs(s[fid == f] > thr)) for f in (0, 1))

    thr = budget_threshold(s, fid, np.array([0, 1]), hours=2.0, per_hour=1.0)
    assert 0.8 <= thr < 0.9 and n_runs(thr) == 2      # the 0.95 and 0.9 runs; 0.8 would make three
    assert budget_threshold(s, fid, np.array([0, 1]), hours=3.0) < 0.8    # three runs allowed
    assert budget_threshold(s, fid, np.array([0, 1]), hours=1.0) >= 0.9   # one run allowed
    assert n_runs(budget_threshold(s, fid, np.array([0, 1]), hours=1.0)) == 1


def test_tuning_reads_validation_only(bias_dataset):
    """Thresholds come from validation flights; test labels play no part."""
    f = bias_dataset.flights
    train, val = f[f.flight_id < 3].reset_index(drop=True), f[f.flight_id >= 3].reset_index(drop=True)
    y = train.label.to_numpy()
    tuned = tune("cusum", train, y, val)
    s = tuned.detector.decision_function(val)
    assert tuned.detector.threshold_ == pytest.approx(best_f1_threshold(s, val.label.to_numpy())[0])
    # the budget threshold: at most one alarm run per hour on the clean validation flights
    clean = val.groupby("flight_id").label.max() == 0
    hours = val.flight_id.isin(clean[clean].index).sum() / 10 / 3600
    alarms = sum(len(runs(g.to_numpy() > tuned.detector.budget_threshold_))
                 for f, g in pd.Series(s).groupby(val.flight_id.to_numpy()) if clean[f])
    assert clean.any() and alarms <= int(hours)
    assert tuned.val_f1 == max(g["val_f1"] for g in tuned.grid)


def test_split_keeps_groups_together():
    """Flights replayed from one recording (a group) never straddle train and test."""
    sc = pd.DataFrame({"flight_id": np.arange(40), "group": np.repeat(np.arange(10), 4),
                       "attacked": np.tile([True, False, True, False], 10)})
    sp = split_flights(sc, seed=3)
    part = {f: k for k in ("train", "val", "test") for f in getattr(sp, k)}
    assert sorted(part) == list(range(40))
    for g in range(10):
        assert len({part[f] for f in range(4 * g, 4 * g + 4)}) == 1
    assert len(sp.test) == 8 and len(sp.val) == 8 and set(sp.labelled) <= set(sp.train)
    assert np.array_equal(split_flights(sc, seed=3).test, sp.test)
