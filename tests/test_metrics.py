"""Metric definitions on hand-computed cases."""

import numpy as np
import pytest

from quadformer.evaluation.metrics import evaluate, point_adjust, pointwise, runs

LABELS = np.array([0, 0, 1, 1, 1, 0, 0, 1, 1, 0])
ALARMS = np.array([0, 1, 0, 1, 1, 0, 0, 0, 0, 1])
T = np.arange(10) / 10.0


def test_runs():
    assert runs(LABELS) == [(2, 5), (7, 9)]
    assert runs(np.zeros(3)) == []
    assert runs(np.ones(2)) == [(0, 2)]


def test_pointwise_hand_case():
    # TP at 3, 4; FP at 1, 9; FN at 2, 7, 8
    p, r, f = pointwise(LABELS, ALARMS)
    assert (p, r) == (0.5, 0.4)
    assert f == pytest.approx(2 * 0.5 * 0.4 / 0.9)


def test_point_adjustment_differs_and_is_reported_separately():
    adj = point_adjust(LABELS, ALARMS)
    assert adj.tolist() == [0, 1, 1, 1, 1, 0, 0, 0, 0, 1]   # first window fully credited
    m = evaluate(np.zeros(10), T, LABELS, ALARMS.astype(float), ALARMS)
    assert m["f1"] == pytest.approx(0.4444, abs=1e-4)           # the headline stays raw
    assert m["f1_point_adjusted"] == pytest.approx(0.6)          # TP 3, FP 2, FN 2


def test_event_metrics_and_delay():
    m = evaluate(np.zeros(10), T, LABELS, ALARMS.astype(float), ALARMS)
    # windows [2,5) found, [7,9) missed; alarm runs [1,2) and [9,10) are false events
    assert m["windows"] == 2 and m["windows_found"] == 1 and m["false_events"] == 2
    assert m["event_precision"] == pytest.approx(1 / 3)
    assert m["event_recall"] == 0.5
    assert m["event_f1"] == pytest.approx(0.4)
    assert m["delay_median_s"] == pytest.approx(0.1)
    assert m["false_alarms_per_hour"] is None                   # no clean flight


def test_false_alarms_per_hour_on_clean_flights_only():
    n = 36000  # one hour at 10 Hz
    fid = np.r_[np.zeros(n), np.ones(10)]
    labels = np.r_[np.zeros(n), LABELS]
    alarms = np.zeros(n + 10, dtype=bool)
    alarms[[100, 101, 5000]] = True        # two alarm runs on the clean flight
    alarms[n:] = ALARMS.astype(bool)
    t = np.r_[np.arange(n) / 10.0, T]
    m = evaluate(fid, t, labels, alarms.astype(float), alarms)
    assert m["false_alarms_per_hour"] == pytest.approx(2.0)
    assert m["clean_flight_hours"] == pytest.approx(1.0)


def test_auc_and_offset_at_detection():
    scores = np.array([0.1, 0.2, 0.9, 0.8, 0.7, 0.3, 0.1, 0.6, 0.5, 0.2])
    offsets = np.array([0, 0, 1.0, 2.0, 3.0, 0, 0, 1.5, 2.5, 0])
    m = evaluate(np.zeros(10), T, LABELS, scores, scores > 0.55, offsets=offsets)
    assert m["auroc"] == 1.0 and m["auprc"] == 1.0
    assert m["offset_at_detection_median_m"] == pytest.approx(1.25)   # 1.0 and 1.5
