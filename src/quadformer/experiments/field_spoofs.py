"""Spoofs injected into real flights in air, and whether a detector's alerts catch them (the field
benchmark's third measure, ``experiments.field``).

Each clean log segment gets spoofs of each kind in ``INJECTED`` (bias, ramp, a drift switched on at
once, an accelerating drift, an SDR capture), the position and the matching velocity falsified, with
an onset drawn in the segment's longest stretch in air; the segment is replayed through the filter
with each spoof (the replays of one segment as one batch), scored, and its alerts raised with the
log's flight phase and receiver health. A capture also changes the receiver's reports
(``attacks.spoofed_reports``): the replay weighs its fixes by the spoofed accuracies and skips the
fixes it lost, and its alerts are labelled with the spoofed reports, not the log's clean ones. A
spoof is detected when a spoofing alert is raised in the air between its onset and its end.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from quadformer.config import AttackConfig
from quadformer.estimator.filter_config import FilterConfig
from quadformer.experiments.field_plan import INJECTED, FieldLog, FieldPlan
from quadformer.logs.detect import log_height, log_impacts, step_alerts
from quadformer.logs.replay import ekf_flights


__all__ = ["INJECTED", "INJECT_BEFORE_END_S", "Injected", "air_before", "inject", "injected_events", "log_alerts",
           "planned_injections"]

INJECT_BEFORE_END_S = 12.0  # s of air kept after an injected onset


def log_alerts(fl: FieldLog, rows: pd.DataFrame, scores: np.ndarray, det, rate: float,
               receiver: pd.DataFrame | None = None) -> list:
    """The alerts of a log's scored rows, raised through the online step with the log's own flight
    phase and receiver health (as ``detect`` raises them); ``receiver``: the receiver's reports to
    label them with instead of the log's (an injected capture's spoofed reports)."""
    return step_alerts(rows, scores, det, "shape", rate, events=fl.log.events,
                       receiver=fl.log.receiver if receiver is None else receiver, height=log_height(fl.log),
                       impacts=log_impacts(fl.log))



def planned_injections(plan: FieldPlan, fl: FieldLog, li: int, kind: str):
    """The attacks of ``kind`` (a name of ``INJECTED``) injected into each segment of a clean log in
    air: {segment: (t0, [AttackBatch])},
    their times counting from the segment's first fix (t0 on the log's clock), as the replay counts
    them. The onsets fall in the segment's longest stretch in air (a segment may hold a landing and a
    second take-off), from the first step in air to ``INJECT_BEFORE_END_S`` before its last."""
    from quadformer.attacks import sample_attacks
    from quadformer.detectors.alarms import runs
    from quadformer.rng import Stream, flight_generator

    out = {}
    t = fl.rows["t"].to_numpy(dtype=float)
    seg_ids = fl.rows["flight_id"].to_numpy()
    for seg in np.unique(seg_ids):
        mine = seg_ids == seg
        spans = runs(fl.phase[mine] == "air")
        if not spans:
            continue
        a, b = max(spans, key=lambda r: r[1] - r[0])
        air_t = t[mine][a:b]
        if len(air_t) < 2:
            continue
        part = fl.log.segment(int(seg)) if len(fl.log.segments) > 1 else fl.log
        t0 = float(part.gps["t"].iloc[0])
        lo, hi = air_t[0] - t0, air_t[-1] - t0 - INJECT_BEFORE_END_S
        if hi <= lo:
            continue
        spec = INJECTED[kind]
        ranges = {"bias": {"magnitude": plan.bias}, "ramp": {"rate": plan.ramp},
                  "drift": {"rate": plan.drift, "accel": plan.drift_accel, "onset_step": spec.onset_step},
                  "capture": {"magnitude": plan.capture, "rate": plan.capture_rate}}[spec.kind]
        cfg = AttackConfig(kind=spec.kind, fraction=1.0, onset=(lo, hi),
                           duration=(hi - lo + INJECT_BEFORE_END_S,) * 2, **ranges)
        batches = []
        for k in range(plan.injections):
            gen = flight_generator(plan.seed, 100_000 * (li + 1) + 1000 * int(seg) + k + spec.seed_offset,
                                   Stream.SCENARIO)
            b = sample_attacks([gen], cfg, np.ones(1, bool), air_t[-1] - t0)
            b = dataclasses.replace(b, end=np.minimum(b.end, air_t[-1] - t0))
            batches.append(b)
        out[int(seg)] = (t0, batches)
    return out


@dataclass
class Injected:
    """One spoof injected into a clean log's segment in air, and the replay's rows."""
    kind: str               # a name of ``INJECTED``
    segment: int
    onset: float            # s, on the log's clock
    end: float
    size: float             # m (bias, capture: the pull-off) or m/s (ramp, drift: the rate)
    rows: pd.DataFrame
    receiver: pd.DataFrame | None = None   # the receiver's reports under the spoof (None: the log's)


def inject(plan: FieldPlan, fl: FieldLog, li: int, config: FilterConfig) -> list[Injected]:
    """The spoofs injected into a clean log in air, each replayed through the filter (the replays of
    one segment together, as one batch, or as several where captures lose different fixes)."""
    from quadformer.attacks import spoofed_reports

    out = []
    for kind in plan.kinds:
        spec = INJECTED[kind]
        for seg, (t0, batches) in planned_injections(plan, fl, li, kind).items():
            for k, (f, b) in enumerate(zip(ekf_flights(fl.log, seg, config, batches), batches)):
                receiver = None
                if spec.kind == "capture" and fl.log.receiver is not None:
                    receiver = spoofed_reports(fl.log.receiver, b, t0)
                out.append(Injected(kind, seg, float(b.onset[0]) + t0, float(b.end[0]) + t0,
                                    float(getattr(b, spec.size)[0]), f.rows.assign(flight_id=np.int32(k)), receiver))
    return out


#: which of a log's physical floors (``logs.noise.DetectionFloor``) an injection's size is judged
#: against: an offset's (m) or a drift's (m/s); an accelerating drift has no step to see
FLOOR_OF = {"bias": "offset_m", "capture": "offset_m", "ramp": "drift_ms", "drift": "drift_ms"}
#: the same with the log's own tails (``DetectionFloor.offset_tail_m``, ``drift_tail_ms``)
TAIL_FLOOR_OF = {k: v.replace("_", "_tail_", 1) for k, v in FLOOR_OF.items()}


def air_before(fl: FieldLog, segment: int, t: float) -> float:
    """Seconds the segment's rows spent in the air before ``t`` (log clock): how long a detector that
    normalises itself in the air (``glr``) had to calibrate when a spoof began."""
    mine = fl.rows["flight_id"].to_numpy() == segment
    ts = fl.rows["t"].to_numpy(dtype=float)[mine]
    if len(ts) < 2:
        return 0.0
    air = fl.phase[mine] == "air"
    spent = np.concatenate([[0.0], np.cumsum(np.where(air[1:] & air[:-1], np.diff(ts), 0.0))])
    return float(np.interp(t, ts, spent))


def injected_events(fl: FieldLog, injected: list[Injected], method: str, dets: dict[str, Any],
                    rate: float, floor: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """One row per injected spoof and threshold: detected (a spoofing alert raised in air between the
    onset and the end), delay, offset at detection, the seconds in the air before the onset
    (``air_before_s``), and the log's physical floor for the spoof's kind (``floor``: the log's
    ``DetectionFloor`` as a dict; NaN where none applies), Gaussian and with the log's tails
    (``floor_tail``)."""
    rows_out = []
    for inj in injected:
        before = air_before(fl, inj.segment, inj.onset)
        scores = np.asarray(next(iter(dets.values())).decision_function(inj.rows), dtype=float)
        for thr_name, det in dets.items():
            alerts = log_alerts(fl, inj.rows, scores, det, rate, receiver=inj.receiver)
            hit = [a.start_s for a in alerts if a.kind == "spoofing" and a.phase == "air"
                   and inj.onset <= a.start_s < inj.end]
            delay = (min(hit) - inj.onset) if hit else None
            offset = None if delay is None else _offset_at(inj, min(hit), delay)
            key, tail = FLOOR_OF.get(inj.kind), TAIL_FLOOR_OF.get(inj.kind)
            rows_out.append({"log": fl.path.name, "segment": inj.segment, "kind": inj.kind, "size": inj.size,
                             "method": method, "threshold": thr_name, "detected": bool(hit),
                             "delay_s": delay, "offset_at_detection_m": offset, "air_before_s": before,
                             "floor": float((floor or {}).get(key, float("nan"))) if key else float("nan"),
                             "floor_tail": float((floor or {}).get(tail, float("nan"))) if tail else float("nan")})
    return rows_out


def _offset_at(inj: Injected, t: float, delay: float) -> float:
    """The spoof's position offset (m) when it was detected: a bias's size, a ramp's rate x delay;
    for the others the injected offset of the row the alert was raised at."""
    if inj.kind == "bias":
        return inj.size
    if inj.kind == "ramp":
        return inj.size * delay
    at = inj.rows[inj.rows["t"].to_numpy() >= t - 1e-9]
    d = at[["atk_d_x", "atk_d_y", "atk_d_z"]].to_numpy(dtype=float)
    return float(np.linalg.norm(d[0])) if len(d) else float("nan")
