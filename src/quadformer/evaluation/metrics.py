"""Detection metrics on per-step alarms, computed per flight and pooled.

- Point-wise precision / recall / F1 over GPS steps: the paper's metric. No point
  adjustment; ``point_adjusted_f1`` exists only to be shown next to the raw F1, labelled.
- Event-wise: an attack window (a run of label 1) is found when an alarm falls inside it;
  an alarm run that touches no window is a false event.
- Detection delay: first alarm inside a window minus its onset (s).
- False alarms per flight-hour: alarm runs on flights without any attack.
- AUROC / AUPRC of the raw scores (threshold free), and VUS-PR (``vus_pr``): the range-based
  PR curve's area averaged over label buffers (Paparrizos et al.), threshold free, no point
  adjustment.
- Event recall per attack type (``event_recall_by_type``) and a bootstrap interval of the
  point-wise F1 over flights (``bootstrap_f1``).
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
             alarms: np.ndarray, gps_rate_hz: float = 10.0, offsets: np.ndarray | None = None,
             vus: bool = True) -> dict[str, float | int | None]:
    """All metrics over the steps of several flights (rows grouped by flight, time-ordered).

    ``offsets``: per-step norm of the injected position offset (m), for the offset at detection.
    ``vus``: also VUS-PR (threshold free; ``vus_pr``), None otherwise.
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
        "vus_pr": vus_pr(y, s, flight_ids) if vus and both else None,
        "offset_at_detection_median_m": float(np.median(det_offsets)) if det_offsets else None,
        "f1_point_adjusted": pointwise(y, pa)[2],
    }


# -- VUS-PR ----------------------------------------------------------------------------------

#: largest label buffer of VUS-PR, GPS steps on each side of an attack window (5 s at 10 Hz)
VUS_MAX_BUFFER = 50
#: thresholds of each range-based PR curve (TSB-AD's ``thre``)
VUS_THRESHOLDS = 250


def _flight_bounds(flight_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per step, the index of its flight's first step and one past its last (rows grouped by flight)."""
    fid = np.asarray(flight_ids)
    n = fid.size
    change = np.nonzero(fid[1:] != fid[:-1])[0] + 1
    starts = np.r_[0, change]
    ends = np.r_[change, n]
    which = np.repeat(np.arange(len(starts)), ends - starts)
    return starts[which], ends[which]


def _anomaly_runs(y: np.ndarray, first: np.ndarray, stop: np.ndarray) -> tuple[np.ndarray, ...]:
    """Runs of label 1 that never cross a flight: (start, last step, flight start, flight stop)."""
    m = np.concatenate([[False], y, [False]]).astype(np.int8)
    d = np.diff(m)
    s, e = np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]        # [s, e) runs of the whole array
    if s.size == 0:
        return (np.zeros(0, int),) * 4
    # split runs at flight boundaries
    cuts = np.nonzero(y[1:] & y[:-1] & (first[1:] != first[:-1]))[0] + 1
    s = np.sort(np.r_[s, cuts])
    e = np.sort(np.r_[e, cuts])
    return s, e - 1, first[s], stop[s]


def range_soft_labels(labels: np.ndarray, window: int, flight_ids: np.ndarray | None = None) -> np.ndarray:
    """The range-based soft labels of Paparrizos et al. for buffer length ``window``.

    Each attack window [s, e] (a run of label 1) is extended by ``h = window // 2`` steps on
    each side; a step ``d`` steps before s or after e (1 <= d <= h) gets ``sqrt(1 - d / window)``;
    contributions of several windows are summed and the result clipped to 1 (label 1 inside the
    windows). With ``flight_ids`` (rows grouped by flight) no buffer crosses into another flight.
    """
    y = np.asarray(labels, bool)
    fid = np.zeros(y.size, int) if flight_ids is None else np.asarray(flight_ids)
    first, stop = _flight_bounds(fid) if y.size else (np.zeros(0, int), np.zeros(0, int))
    return _soft(y, window, _anomaly_runs(y, first, stop))


def _soft(y: np.ndarray, window: int, runs_: tuple[np.ndarray, ...]) -> np.ndarray:
    ext = y.astype(float)
    h = window // 2
    s, last, first, stop = runs_
    if h == 0 or s.size == 0:
        return ext
    d = np.arange(1, h + 1)
    val = np.sqrt(1.0 - d / window)
    right = last[:, None] + d[None, :]
    ok = right < stop[:, None]
    np.add.at(ext, right[ok], np.broadcast_to(val, right.shape)[ok])
    left = s[:, None] - d[None, :]
    ok = left >= first[:, None]
    np.add.at(ext, left[ok], np.broadcast_to(val, left.shape)[ok])
    return np.minimum(ext, 1.0)


def vus_pr(labels: np.ndarray, scores: np.ndarray, flight_ids: np.ndarray | None = None,
           max_buffer: int = VUS_MAX_BUFFER, thresholds: int = VUS_THRESHOLDS) -> float | None:
    """VUS-PR: the volume under the range-based precision-recall surface (Paparrizos, Boniol,
    Palpanas, Tsay, Elmore and Franklin, "Volume Under the Surface: a new accuracy evaluation
    measure for time-series anomaly detection", PVLDB 15(11), 2022), computed as TSB-AD 1.5 does
    (Liu and Paparrizos, NeurIPS 2024 Datasets and Benchmarks: ``get_metrics(score, labels,
    slidingWindow)`` -> ``generate_curve(labels, score, slidingWindow)`` ->
    ``basic_metricor.RangeAUC_volume_opt(labels, score, windowSize=slidingWindow, thre=250)``,
    which averages over the buffer lengths ``l = 0 .. slidingWindow``, every attack window
    extended by ``l // 2`` steps on each side). ``max_buffer`` is the largest extension on
    each side, ``slidingWindow / 2``: on one flight, ``vus_pr(labels, scores, max_buffer=B)``
    is TSB-AD's VUS-PR with ``slidingWindow = 2 * B`` (default B = 50 GPS steps, 5 s at 10 Hz).

    For each buffer length ``l = 0, 1, ..., 2 * max_buffer``:

    - soft labels ``y_l`` (``range_soft_labels``): every attack window [s, e] extended by
      ``l // 2`` steps on each side, valued ``sqrt(1 - d / l)`` at ``d`` steps from it, clipped
      to 1; extended windows whose buffers meet (``e_i + l//2 >= s_j - l//2``) merge into one
      range; buffers stop at flight boundaries;
    - thresholds: the scores at positions ``linspace(0, n - 1, thresholds)`` (cast to int) of
      the scores sorted in decreasing order; the prediction at threshold c is ``score >= c``;
    - at each threshold: ``TP = sum of y_l over predicted steps``; ``P = number of attacked
      steps``; ``P' = P + (sum of y_l over predicted steps outside the attack windows) / 2``;
      ``recall = min(TP / P', 1)``; ``existence`` = share of the (merged, extended) ranges
      holding a predicted step; ``TPR = recall * existence``; ``precision = TP / (predicted
      steps)``;
    - ``AP_l = sum_k (TPR_k - TPR_{k-1}) * precision_k`` over the thresholds in decreasing
      order, with ``TPR_0 = 0`` (a step-wise area, as in TSB-AD).

    VUS-PR is the mean of ``AP_l`` over the ``2 * max_buffer + 1`` buffer lengths. ``l = 0``
    gives a range-aware AUPRC without buffer. No point adjustment: a step outside an attack
    window is never credited as detected; the buffer only softens the labels next to the
    window. None when the labels hold no attack or no clean step.
    """
    y = np.asarray(labels, bool)
    s = np.asarray(scores, float)
    n = y.size
    P = int(y.sum())
    if P == 0 or P == n:
        return None
    fid = np.zeros(n, int) if flight_ids is None else np.asarray(flight_ids)
    first, stop = _flight_bounds(fid)
    runs_ = _anomaly_runs(y, first, stop)
    a_s, a_last, a_first, a_stop = runs_
    order = np.argsort(-s, kind="stable")
    desc = s[order]
    thr = desc[np.linspace(0, n - 1, thresholds).astype(int)]
    n_pred = np.searchsorted(-desc, -thr, side="right")          # steps with score >= threshold
    padded = np.r_[s, -np.inf]
    same_flight = a_first[1:] == a_first[:-1]
    ap = []
    for window in range(0, 2 * max_buffer + 1):
        h = window // 2
        ext = _soft(y, window, runs_)
        tp = np.cumsum(ext[order])[n_pred - 1]
        buf = np.cumsum(np.where(y, 0.0, ext)[order])[n_pred - 1]
        recall = np.minimum(tp / (P + 0.5 * buf), 1.0)
        # the extended ranges, merged where their buffers meet (within a flight)
        lo = np.maximum(a_s - h, a_first)
        hi = np.minimum(a_last + h, a_stop - 1)
        merge = same_flight & (a_last[:-1] + h >= a_s[1:] - h)
        heads = np.r_[0, np.nonzero(~merge)[0] + 1]
        g_lo = np.minimum.reduceat(lo, heads)
        g_hi = np.maximum.reduceat(hi, heads)
        seg_max = np.sort(np.maximum.reduceat(padded, np.ravel(np.c_[g_lo, g_hi + 1]))[::2])
        existence = (len(seg_max) - np.searchsorted(seg_max, thr, side="left")) / len(seg_max)
        tpr = recall * existence
        precision = tp / n_pred
        ap.append(float(np.sum(np.diff(np.r_[0.0, tpr]) * precision)))
    return float(np.mean(ap))


# -- per-type event recall, bootstrap ---------------------------------------------------------

def event_recall_by_type(flight_ids: np.ndarray, labels: np.ndarray, alarms: np.ndarray,
                         types: np.ndarray) -> dict[str, dict[str, float | int]]:
    """Event recall per true attack type: for each type, the attack windows (runs of label 1
    within a flight) of that type (``types`` at the window's first step) and how many hold an
    alarm. Returns ``{type: {"windows", "found", "recall"}}``."""
    fid = np.asarray(flight_ids)
    y, a = np.asarray(labels, bool), np.asarray(alarms, bool)
    types = np.asarray(types).astype(str)
    first, stop = _flight_bounds(fid) if y.size else (np.zeros(0, int), np.zeros(0, int))
    s, last, _, _ = _anomaly_runs(y, first, stop)
    out: dict[str, dict[str, float | int]] = {}
    if s.size == 0:
        return out
    alarms_before = np.r_[0, np.cumsum(a)]
    hits = alarms_before[last + 1] - alarms_before[s] > 0
    for k, found in zip(types[s], hits):
        row = out.setdefault(str(k), {"windows": 0, "found": 0})
        row["windows"] += 1
        row["found"] += int(found)
    for row in out.values():
        row["recall"] = row["found"] / row["windows"]
    return dict(sorted(out.items()))


def bootstrap_f1(flight_ids: np.ndarray, labels: np.ndarray, alarms: np.ndarray, n_boot: int = 2000,
                 seed: int = 0, level: float = 0.95) -> tuple[float, float] | None:
    """Percentile bootstrap interval of the point-wise F1 over flights: the flights are
    resampled with replacement ``n_boot`` times (generator seeded by ``seed``), attacked and
    clean flights separately (each resample keeps their numbers, as the stratified split
    does, so none is left without attacks), each resample's pooled TP, FP and FN give its F1,
    and the interval is the central ``level`` of those F1 values. None without flights."""
    fid = np.asarray(flight_ids)
    if fid.size == 0:
        return None
    y, a = np.asarray(labels, bool), np.asarray(alarms, bool)
    _, inv = np.unique(fid, return_inverse=True)
    counts = np.stack([np.bincount(inv, weights=(y & a)), np.bincount(inv, weights=(~y & a)),
                       np.bincount(inv, weights=(y & ~a))], axis=1)           # (flights, 3)
    attacked = np.bincount(inv, weights=y) > 0
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0xB007,)))
    total = np.zeros((n_boot, 3))
    for stratum in (np.nonzero(attacked)[0], np.nonzero(~attacked)[0]):
        if stratum.size:
            draws = stratum[rng.integers(stratum.size, size=(n_boot, stratum.size))]
            total += counts[draws].sum(axis=1)
    tp, fp, fn = total.T
    denom = 2 * tp + fp + fn
    f1 = np.divide(2 * tp, denom, out=np.zeros_like(denom), where=denom > 0)
    q = 100 * (1 - level) / 2
    lo, hi = np.percentile(f1, [q, 100 - q])
    return float(lo), float(hi)
