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


# -- VUS-PR ---------------------------------------------------------------------------------

from quadformer.evaluation.metrics import (  # noqa: E402
    bootstrap_f1, event_recall_by_type, range_soft_labels, vus_pr,
)


def test_range_soft_labels_hand_case_and_flight_boundaries():
    r75 = np.sqrt(1 - 1 / 4)
    # window 4: two steps of buffer on each side, sqrt(1 - d/4) at d = 1, 2
    got = range_soft_labels(np.array([0, 0, 0, 1, 1, 0, 0, 0]), 4)
    assert got == pytest.approx([0, np.sqrt(0.5), r75, 1, 1, r75, np.sqrt(0.5), 0])
    # buffers never cross into another flight
    y, fid = np.array([1, 0, 0, 0]), np.array([0, 0, 1, 1])
    assert range_soft_labels(y, 4, fid) == pytest.approx([1, r75, 0, 0])
    assert range_soft_labels(y, 4) == pytest.approx([1, r75, np.sqrt(0.5), 0])
    # overlapping buffers add up, clipped to 1; window 0 and 1 leave the labels as they are
    assert range_soft_labels(np.array([1, 0, 1]), 4) == pytest.approx([1, 1, 1])
    assert range_soft_labels(np.array([1, 0, 0, 0, 1]), 4)[2] == pytest.approx(1.0)     # 2 sqrt(1/2), clipped
    assert range_soft_labels(LABELS, 1).tolist() == LABELS.tolist()


def test_vus_pr_hand_case():
    """One flight of six steps, attack window steps 2-3, max buffer 1 step (buffer lengths
    l = 0, 1, 2). Scores in decreasing order: 0.9 (step 2), 0.6 (1), 0.5 (4), 0.3 (3), 0.2 (5),
    0.1 (0); the 250 threshold positions cover all six. P = 2.

    l = 0 and l = 1 (no buffer, l // 2 = 0): one range, found from the first threshold.
      threshold 0.9: TP 1, recall 1/2, precision 1            -> +0.5 * 1
      0.6: TP 1 (precision 1/2); 0.5: TP 1 (1/3)              -> TPR unchanged, +0
      0.3: TP 2, TPR 1, precision 2/4                         -> +0.5 * 0.5
      0.2, 0.1: TPR 1                                         -> +0
      AP_0 = AP_1 = 0.75.
    l = 2 (one step of buffer each side, valued r = sqrt(1 - 1/2)): soft labels
      [0, r, 1, 1, r, 0]; one extended range [1, 4], found from the first threshold.
      0.9: TP 1, P' = 2, TPR 1/2, precision 1                             -> 0.5
      0.6: predicted {1, 2}: TP 1 + r, P' = 2 + r/2, precision (1 + r)/2
      0.5: predicted {1, 2, 4}: TP 1 + 2r, P' = 2 + r, precision (1 + 2r)/3
      0.3: predicted {1..4}: TP 2 + 2r, P' = 2 + r, TPR min((2 + 2r)/(2 + r), 1) = 1,
           precision (2 + 2r)/4
      AP_2 = 0.5 + (R2 - 0.5) p2 + (R3 - R2) p3 + (1 - R3) p4 with Rk = TPR, pk = precision.
    VUS-PR = (AP_0 + AP_1 + AP_2) / 3.
    """
    y = np.array([0, 0, 1, 1, 0, 0])
    s = np.array([0.1, 0.6, 0.9, 0.3, 0.5, 0.2])
    r = np.sqrt(0.5)
    R2, p2 = (1 + r) / (2 + r / 2), (1 + r) / 2
    R3, p3 = (1 + 2 * r) / (2 + r), (1 + 2 * r) / 3
    p4 = (2 + 2 * r) / 4
    ap2 = 0.5 + (R2 - 0.5) * p2 + (R3 - R2) * p3 + (1 - R3) * p4
    assert ap2 == pytest.approx(0.918650, abs=1e-6)
    assert vus_pr(y, s, max_buffer=1) == pytest.approx((0.75 + 0.75 + ap2) / 3, abs=1e-12)
    assert vus_pr(y, s, max_buffer=0) == pytest.approx(0.75, abs=1e-12)
    assert vus_pr(np.zeros(6), s) is None and vus_pr(np.ones(6), s) is None
    # a perfect ranking scores 1 whatever the buffer
    assert vus_pr(y, y + 0.01 * np.arange(6), max_buffer=2) == pytest.approx(1.0)


def _vus_reference(y, s, fid, max_buffer, thresholds=250):
    """The definition of ``vus_pr``'s docstring written out step by step (slow)."""
    y = np.asarray(y, bool)
    n, P = len(y), y.sum()
    bounds = {f: (np.nonzero(fid == f)[0][0], np.nonzero(fid == f)[0][-1]) for f in np.unique(fid)}
    wins = [(s0 + i0, e0 + i0 - 1, f) for f, (i0, i1) in bounds.items() for s0, e0 in runs(y[i0:i1 + 1])]
    desc = np.sort(s)[::-1]
    aps = []
    for l in range(2 * max_buffer + 1):
        h = l // 2
        ext = y.astype(float)
        for a, b, f in wins:
            for d in range(1, h + 1):
                if b + d <= bounds[f][1]:
                    ext[b + d] += np.sqrt(1 - d / l)
                if a - d >= bounds[f][0]:
                    ext[a - d] += np.sqrt(1 - d / l)
        ext = np.minimum(ext, 1)
        ranges = []
        for a, b, f in wins:
            lo, hi = max(a - h, bounds[f][0]), min(b + h, bounds[f][1])
            if ranges and ranges[-1][2] == f and ranges[-1][3] + h >= a - h:
                ranges[-1] = (ranges[-1][0], hi, f, b)
            else:
                ranges.append((lo, hi, f, b))
        prev, ap = 0.0, 0.0
        for i in np.linspace(0, n - 1, thresholds).astype(int):
            pred = s >= desc[i]
            tp = ext[pred].sum()
            p_new = (P + P + ext[pred & ~y].sum()) / 2
            found = sum(pred[lo:hi + 1].any() for lo, hi, _, _ in ranges)
            tpr = min(tp / p_new, 1) * found / len(ranges)
            ap += (tpr - prev) * tp / pred.sum()
            prev = tpr
        aps.append(ap)
    return np.mean(aps)


def test_vus_pr_equals_the_step_by_step_definition_on_random_flights():
    rng = np.random.default_rng(3)
    for trial in range(4):
        fid = np.repeat(np.arange(3), [70, 50, 80])
        y = np.zeros(200, bool)
        for a, b in ((5, 12), (15, 17), (60, 70), (70, 75), (130, 131), (190, 200)):   # near and across flights
            y[a:b] = True
        s = np.round(rng.random(200) + 0.6 * y, 1 + trial % 2)          # ties on purpose
        got = vus_pr(y, s, fid, max_buffer=6, thresholds=120)
        assert got == pytest.approx(_vus_reference(y, s, fid, 6, 120), abs=1e-12)


def test_evaluate_reports_vus_pr_per_flight_buffers():
    scores = np.array([0.1, 0.2, 0.9, 0.8, 0.7, 0.3, 0.1, 0.6, 0.5, 0.2])
    m = evaluate(np.zeros(10), T, LABELS, scores, scores > 0.55)
    assert m["vus_pr"] == pytest.approx(vus_pr(LABELS, scores, np.zeros(10)))
    assert 0 < m["vus_pr"] <= 1


# -- per-type event recall, bootstrap ---------------------------------------------------------

def test_event_recall_by_type_hand_case():
    """Two flights: flight 0 has a bias window (found) and an intermittent attack of two on
    phases (one found); flight 1 a ramp window (missed). Per type: bias 1/1, intermittent 1/2,
    ramp 0/1. A window that ends a flight and one that starts the next stay two windows."""
    fid = np.repeat([0, 1], 10)
    y = np.zeros(20, int)
    types = np.array(["none"] * 20, dtype=object)
    y[1:3], types[1:3] = 1, "bias"
    y[5:6], y[8:10], types[5:10] = 1, 1, "intermittent"
    y[10:13], types[10:13] = 1, "ramp"
    a = np.zeros(20, bool)
    a[2] = a[9] = True
    a[14] = True                      # after the ramp window: a false alarm, not a hit
    got = event_recall_by_type(fid, y, a, types)
    assert got == {"bias": {"windows": 1, "found": 1, "recall": 1.0},
                   "intermittent": {"windows": 2, "found": 1, "recall": 0.5},
                   "ramp": {"windows": 1, "found": 0, "recall": 0.0}}
    assert event_recall_by_type(fid, np.zeros(20), a, types) == {}


def test_bootstrap_f1_interval_is_seeded_and_brackets_the_f1():
    rng = np.random.default_rng(0)
    fid = np.repeat(np.arange(30), 50)
    y = np.zeros(1500, bool)
    for f in range(0, 30, 2):
        y[50 * f + 20:50 * f + 35] = True
    a = y ^ (rng.random(1500) < 0.1)
    lo, hi = bootstrap_f1(fid, y, a, seed=1)
    f1 = pointwise(y, a)[2]
    assert lo < f1 < hi and hi - lo < 0.2
    assert bootstrap_f1(fid, y, a, seed=1) == (lo, hi) and bootstrap_f1(fid, y, a, seed=2) != (lo, hi)
    assert bootstrap_f1(fid, y, y, seed=1) == (1.0, 1.0)          # perfect alarms: no spread
    assert bootstrap_f1(np.zeros(0), np.zeros(0), np.zeros(0)) is None


def test_bootstrap_keeps_the_number_of_attacked_flights():
    """One attacked and one clean flight: every resample holds the attacked flight once, so
    the interval is that of the clean flight's false alarms only (here none: F1 fixed)."""
    fid = np.repeat([0, 1], 10)
    y = np.r_[np.zeros(10), np.r_[np.zeros(3), np.ones(4), np.zeros(3)]].astype(bool)
    a = y.copy()
    a[15] = False                         # TP 3, FN 1 on the attacked flight; no false alarm
    assert bootstrap_f1(fid, y, a, seed=0) == pytest.approx((6 / 7, 6 / 7))
