"""Spoofs injected into real flights in air, and whether a detector's alerts catch them (the field
benchmark's third measure, ``experiments.field``).

Each clean log segment gets bias and ramp spoofs, the position and the matching velocity falsified,
with an onset drawn in the segment's longest stretch in air; the segment is replayed through the
filter with each spoof (the replays of one segment as one batch), scored, and its alerts raised with
the log's flight phase and receiver health. A spoof is detected when a spoofing alert is raised in
the air between its onset and its end.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from quadformer.config import AttackConfig
from quadformer.estimator.filter_config import FilterConfig
from quadformer.logs.detect import log_height, log_impacts, step_alerts
from quadformer.logs.replay import ekf_flights

if TYPE_CHECKING:
    from quadformer.experiments.field import FieldLog, FieldPlan

__all__ = ["INJECT_BEFORE_END_S", "Injected", "inject", "injected_events", "log_alerts", "planned_injections"]

INJECT_BEFORE_END_S = 12.0  # s of air kept after an injected onset


def log_alerts(fl: FieldLog, rows: pd.DataFrame, scores: np.ndarray, det, rate: float) -> list:
    """The alerts of a log's scored rows, raised through the online step with the log's own flight
    phase and receiver health (as ``detect`` raises them)."""
    return step_alerts(rows, scores, det, "shape", rate, events=fl.log.events, receiver=fl.log.receiver,
                       height=log_height(fl.log), impacts=log_impacts(fl.log))



def planned_injections(plan: FieldPlan, fl: FieldLog, li: int, kind: str):
    """The attacks injected into each segment of a clean log in air: {segment: (t0, [AttackBatch])},
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
        ranges = {"magnitude": plan.bias} if kind == "bias" else {"rate": plan.ramp}
        cfg = AttackConfig(kind=kind, fraction=1.0, onset=(lo, hi), duration=(hi - lo + INJECT_BEFORE_END_S,) * 2,
                           **ranges)
        batches = []
        for k in range(plan.injections):
            gen = flight_generator(plan.seed, 100_000 * (li + 1) + 1000 * int(seg) + k + (500 if kind == "ramp" else 0),
                                   Stream.SCENARIO)
            b = sample_attacks([gen], cfg, np.ones(1, bool), air_t[-1] - t0)
            b = dataclasses.replace(b, end=np.minimum(b.end, air_t[-1] - t0))
            batches.append(b)
        out[int(seg)] = (t0, batches)
    return out


@dataclass
class Injected:
    """One spoof injected into a clean log's segment in air, and the replay's rows."""
    kind: str
    segment: int
    onset: float            # s, on the log's clock
    end: float
    size: float             # m (bias) or m/s (ramp)
    rows: pd.DataFrame


def inject(plan: FieldPlan, fl: FieldLog, li: int, config: FilterConfig) -> list[Injected]:
    """The spoofs injected into a clean log in air, each replayed through the filter (the replays of
    one segment together, as one batch)."""
    out = []
    for kind in ("bias", "ramp"):
        for seg, (t0, batches) in planned_injections(plan, fl, li, kind).items():
            for k, (f, b) in enumerate(zip(ekf_flights(fl.log, seg, config, batches), batches)):
                size = float(b.magnitude[0]) if kind == "bias" else float(b.rate[0])
                out.append(Injected(kind, seg, float(b.onset[0]) + t0, float(b.end[0]) + t0, size,
                                    f.rows.assign(flight_id=np.int32(k))))
    return out


def injected_events(fl: FieldLog, injected: list[Injected], method: str, dets: dict[str, Any],
                    rate: float) -> list[dict[str, Any]]:
    """One row per injected spoof and threshold: detected (a spoofing alert raised in air between the
    onset and the end), delay, offset at detection."""
    rows_out = []
    for inj in injected:
        scores = np.asarray(next(iter(dets.values())).decision_function(inj.rows), dtype=float)
        for thr_name, det in dets.items():
            alerts = log_alerts(fl, inj.rows, scores, det, rate)
            hit = [a.start_s for a in alerts if a.kind == "spoofing" and a.phase == "air"
                   and inj.onset <= a.start_s < inj.end]
            delay = (min(hit) - inj.onset) if hit else None
            offset = None if delay is None else (inj.size if inj.kind == "bias" else inj.size * delay)
            rows_out.append({"log": fl.path.name, "segment": inj.segment, "kind": inj.kind, "size": inj.size,
                             "method": method, "threshold": thr_name, "detected": bool(hit),
                             "delay_s": delay, "offset_at_detection_m": offset})
    return rows_out
