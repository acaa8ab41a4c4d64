"""Choosing the alarm threshold of a detector on validation flights.

The rule is ``alarm = score > threshold``. Two criteria, both the evaluation protocol's
(``evaluation.protocol``):

- ``best_f1_threshold``: the threshold that maximises point-wise F1 on the validation steps;
- ``budget_threshold``: the lowest threshold with at most ``per_hour`` alarm runs per
  flight-hour on the clean validation flights (a false-alarm budget).

``choose_thresholds`` applies both to one detector's validation scores; it is what
``Detector.calibrate`` runs. Test flights never enter here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from quadformer.detectors.runs import runs

#: the criteria ``Detector.calibrate`` accepts for ``threshold_``
CRITERIA = ("f1", "budget")


def best_f1_threshold(scores: np.ndarray, labels: np.ndarray) -> tuple[float, float]:
    """Threshold maximising point-wise F1 for the rule ``alarm = score > threshold``.

    Exact: every distinct score is a candidate; the threshold is placed halfway to the next
    lower distinct score. Returns (threshold, F1).
    """
    s = np.asarray(scores, float)
    y = np.asarray(labels, bool)
    if y.sum() == 0:
        return float(np.max(s)) if s.size else 0.0, 0.0
    order = np.argsort(-s, kind="stable")
    s_sorted, y_sorted = s[order], y[order]
    tp = np.cumsum(y_sorted)
    fp = np.cumsum(~y_sorted)
    last = np.nonzero(np.r_[s_sorted[1:] != s_sorted[:-1], True])[0]   # end of each tie group
    tp, fp = tp[last], fp[last]
    f1 = 2 * tp / (tp + fp + y.sum())
    i = int(np.argmax(f1))
    hi = s_sorted[last[i]]
    lo = s_sorted[last[i] + 1] if last[i] + 1 < s.size else hi - 1.0
    return float(0.5 * (hi + lo)), float(f1[i])


def budget_threshold(scores: np.ndarray, flight_ids: np.ndarray, clean_flights: np.ndarray,
                     hours: float, per_hour: float = 1.0) -> float:
    """Lowest threshold with at most ``per_hour * hours`` alarm runs on the clean flights."""
    mask = np.isin(flight_ids, clean_flights)
    s, fid = np.asarray(scores)[mask], np.asarray(flight_ids)[mask]
    if s.size == 0:
        return float("inf")
    allowed = int(np.floor(per_hour * hours))
    top = float(np.max(s))
    if allowed == 0:
        return top
    cands = np.unique(np.quantile(s, np.linspace(0.9, 1.0, 201)))[::-1]
    best = top
    for c in cands:
        n = sum(len(runs(s[fid == f] > c)) for f in np.unique(fid))
        if n > allowed:
            break
        best = float(c)
    return best


@dataclass(frozen=True)
class Thresholds:
    """The two thresholds chosen on validation flights."""
    f1: float               # maximises validation F1
    val_f1: float           # the validation F1 it reaches
    budget: float           # meets the false-alarm budget on the clean flights (inf without any)
    clean_hours: float      # flight-hours of the clean validation flights


def choose_thresholds(scores: np.ndarray, labels: np.ndarray, flight_ids: np.ndarray, gps_rate_hz: float,
                      budget_per_hour: float = 1.0) -> Thresholds:
    """Both thresholds for per-step validation ``scores`` and ``labels`` (1 attacked): the one
    of best F1, and the one with at most ``budget_per_hour`` alarm runs per flight-hour on the
    flights without an attacked step (``gps_rate_hz`` steps per second give their hours)."""
    s, y, fid = np.asarray(scores, float), np.asarray(labels), np.asarray(flight_ids)
    if not (s.shape == y.shape == fid.shape):
        raise ValueError(f"scores, labels and flight ids differ in length ({s.size}, {y.size}, {fid.size})")
    if not (np.isfinite(gps_rate_hz) and gps_rate_hz > 0):
        raise ValueError(f"gps_rate_hz must be positive, got {gps_rate_hz!r}")
    thr, f1 = best_f1_threshold(s, y == 1)
    clean = np.setdiff1d(np.unique(fid), np.unique(fid[y == 1]))
    hours = int(np.isin(fid, clean).sum()) / gps_rate_hz / 3600
    return Thresholds(thr, f1, budget_threshold(s, fid, clean, hours, budget_per_hour), hours)


def gps_rate(X: pd.DataFrame) -> float:
    """GPS steps per second of flights ``X``: one over the median step of ``t`` within a flight."""
    if "t" not in X.columns:
        raise ValueError("no column 't' to infer the GPS rate from: pass gps_rate_hz")
    t, fid = X["t"].to_numpy(dtype=float), X["flight_id"].to_numpy()
    same = fid[1:] == fid[:-1]
    dt = np.diff(t)[same]
    if dt.size == 0 or not np.median(dt) > 0:
        raise ValueError("cannot infer the GPS rate (no flight with two increasing times): pass gps_rate_hz")
    return float(1.0 / np.median(dt))
