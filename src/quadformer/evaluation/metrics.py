"""Detection metrics on per-step alarms, computed per flight and pooled.

- Point-wise precision / recall / F1 over GPS steps: the paper's metric. No point
  adjustment; ``point_adjusted_f1`` exists only to be shown next to the raw F1, labelled.
- Event-wise: an attack window (a run of label 1) is found when an alarm falls inside it;
  an alarm run that touches no window is a false event.
- Detection delay: first alarm inside a window minus its onset (s).
- False alarms per flight-hour: alarm runs on flights without any attack.
- AUROC / AUPRC of the raw scores (threshold free).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from sklearn.metrics import average_precision_score, roc_auc_score

from quadformer.detectors.alarms import runs


def prf(tp: int, fp: int, fn: int) -> tuple[float, float, float]:
    p = tp / (tp + fp) if tp + fp else 0.0
    r = tp / (tp + fn) if tp + fn else 0.0
    f = 2 * p * r / (p + r) if p + r else 0.0
    return p, r, f


def pointwise(labels: np.ndarray, alarms: np.ndarray) -> tuple[float, float, float]:
    y, a = np.asarray(labels, bool), np.asarray(alarms, bool)
    return prf(int((y & a).sum()), int((~y & a).sum()), int((y & ~a).sum()))


def point_adjust(labels: np.ndarray, alarms: np.ndarray) -> np.ndarray:
    """Point adjustment (for comparison with the literature only): a whole attack window
    counts as detected if any of its steps alarms. Inflates scores; never the headline."""
    out = np.asarray(alarms, bool).copy()
    for s, e in runs(labels):
        if out[s:e].any():
            out[s:e] = True
    return out


@dataclass
class FlightEval:
    """Event-level facts of one flight."""
    windows: int
    found: int
    alarm_runs: int
    false_runs: int
    delays: list[float]
    first_alarm_idx: list[int | None]


def flight_events(labels: np.ndarray, alarms: np.ndarray, t: np.ndarray) -> FlightEval:
    y, a = np.asarray(labels, bool), np.asarray(alarms, bool)
    wins = runs(y)
    aruns = runs(a)
    found, delays, firsts = 0, [], []
    for s, e in wins:
        hit = np.nonzero(a[s:e])[0]
        if hit.size:
            found += 1
            delays.append(float(t[s + hit[0]] - t[s]))
            firsts.append(int(s + hit[0]))
        else:
            firsts.append(None)
    false_runs = sum(1 for s, e in aruns if not y[s:e].any())
    return FlightEval(len(wins), found, len(aruns), false_runs, delays, firsts)


def evaluate(flight_ids: np.ndarray, t: np.ndarray, labels: np.ndarray, scores: np.ndarray,
             alarms: np.ndarray, gps_rate_hz: float = 10.0, offsets: np.ndarray | None = None
             ) -> dict[str, float | int | None]:
    """All metrics over the steps of several flights (rows grouped by flight, time-ordered).

    ``offsets``: per-step norm of the injected position offset (m), for the offset at detection.
    """
    flight_ids, t = np.asarray(flight_ids), np.asarray(t, float)
    y, a, s = np.asarray(labels, bool), np.asarray(alarms, bool), np.asarray(scores, float)
    p, r, f = pointwise(y, a)
    windows = found = alarm_runs = false_runs = 0
    delays: list[float] = []
    det_offsets: list[float] = []
    clean_time = 0.0
    clean_false = 0
    pa = np.zeros_like(a)
    for fid in np.unique(flight_ids):
        idx = np.nonzero(flight_ids == fid)[0]
        ev = flight_events(y[idx], a[idx], t[idx])
        pa[idx] = point_adjust(y[idx], a[idx])
        windows += ev.windows
        found += ev.found
        alarm_runs += ev.alarm_runs
        false_runs += ev.false_runs
        delays += ev.delays
        if offsets is not None:
            det_offsets += [float(offsets[idx][i]) for i in ev.first_alarm_idx if i is not None]
        if ev.windows == 0:
            clean_time += len(idx) / gps_rate_hz
            clean_false += ev.alarm_runs
    ev_p = (alarm_runs - false_runs) / alarm_runs if alarm_runs else 0.0
    ev_r = found / windows if windows else 0.0
    ev_f = 2 * ev_p * ev_r / (ev_p + ev_r) if ev_p + ev_r else 0.0
    both = 0 < y.sum() < y.size
    return {
        "precision": p, "recall": r, "f1": f,
        "event_precision": ev_p, "event_recall": ev_r, "event_f1": ev_f,
        "windows": windows, "windows_found": found, "false_events": false_runs,
        "delay_median_s": float(np.median(delays)) if delays else None,
        "delay_p95_s": float(np.percentile(delays, 95)) if delays else None,
        "false_alarms_per_hour": clean_false / (clean_time / 3600.0) if clean_time else None,
        "clean_flight_hours": clean_time / 3600.0,
        "auroc": float(roc_auc_score(y, s)) if both else None,
        "auprc": float(average_precision_score(y, s)) if both else None,
        "offset_at_detection_median_m": float(np.median(det_offsets)) if det_offsets else None,
        "f1_point_adjusted": pointwise(y, pa)[2],
    }
