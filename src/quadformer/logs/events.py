"""The flight events: what the autopilot said happened, as ``FlightLog.events``.

The vocabulary every reader maps its autopilot's messages to (``EVENTS``), the frame of
(t, event, detail) rows that holds them (``make_events``) and its validation (``event_errors``),
kept apart from the sensor streams of ``flightlog``, which imports them from here.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

__all__ = ["EVENTS", "EVENT_COLUMNS", "EVENT_REPEAT", "event_errors", "make_events"]

#: What ``FlightLog.events`` may say, in the autopilot's own words mapped to one vocabulary:
#: armed / disarmed (the motors may spin), takeoff / landed (the land detector's verdict),
#: gps_glitch / gps_glitch_cleared (the autopilot rejects the fixes as inconsistent with its
#: estimate), gps_failsafe / gps_failsafe_cleared (the GPS failsafe is triggered / resolved),
#: gps_lost (the autopilot reports the GPS as lost), ekf_variance / ekf_variance_cleared (the
#: EKF check finds the estimator's variances over their thresholds / back under), mode (a
#: flight mode change; the detail names the mode).
EVENTS = ("armed", "disarmed", "takeoff", "landed", "gps_glitch", "gps_glitch_cleared", "gps_failsafe",
          "gps_failsafe_cleared", "gps_lost", "ekf_variance", "ekf_variance_cleared", "mode")
EVENT_COLUMNS = ("t", "event", "detail")
EVENT_REPEAT = 0.5   # s, the same event again within this time is one event told twice (kept once)


def event_errors(df: pd.DataFrame) -> list[str]:
    """What is wrong with an ``events`` frame (columns, types, order, vocabulary); empty when nothing."""
    if tuple(df.columns) != EVENT_COLUMNS:
        return [f"events: columns {list(df.columns)} != {list(EVENT_COLUMNS)}"]
    errors = []
    if df["t"].dtype != np.float64:
        errors.append(f"events.t: dtype {df['t'].dtype}, expected float64")
    else:
        t = df["t"].to_numpy()
        if len(t) == 0:
            errors.append("events: empty (use None for a log without events)")
        elif not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0):
            errors.append("events: t is not finite and non-decreasing")
    for col in ("event", "detail"):
        if not all(isinstance(v, str) for v in df[col]):
            errors.append(f"events.{col}: not all strings")
    unknown = sorted({str(v) for v in df["event"]} - set(EVENTS))
    if unknown:
        errors.append(f"events: unknown event(s) {unknown}; known: {list(EVENTS)}")
    return errors


def make_events(rows: list[tuple[float, str, str]], notes: list[str] | None = None) -> pd.DataFrame | None:
    """The ``events`` frame of (t, event, detail) rows: sorted by t (stably: rows of one time
    keep their order), an event told again within ``EVENT_REPEAT`` s of the same one kept once
    (an arming said by two messages; for ``mode``, the same mode), rows with a non-finite t
    dropped; None without rows. Every drop is noted when ``notes`` is given."""
    unknown = sorted({e for _, e, _ in rows} - set(EVENTS))
    if unknown:
        raise KeyError(f"events: unknown event(s) {unknown}; known: {list(EVENTS)}")
    finite = [r for r in rows if math.isfinite(r[0])]
    if len(finite) < len(rows) and notes is not None:
        notes.append(f"events: dropped {len(rows) - len(finite)} of {len(rows)} events with a non-finite time")
    kept: list[tuple[float, str, str]] = []
    last: dict[tuple[str, str], float] = {}
    for t, event, detail in sorted(finite, key=lambda r: r[0]):
        key = (event, detail if event == "mode" else "")
        if key in last and t - last[key] <= EVENT_REPEAT:
            continue
        last[key] = t
        kept.append((float(t), event, detail))
    if len(kept) < len(finite) and notes is not None:
        notes.append(f"events: {len(finite) - len(kept)} repeated event(s) (the same event again within "
                     f"{EVENT_REPEAT} s, e.g. an arming in two messages) kept once")
    if not kept:
        return None
    return pd.DataFrame({"t": np.array([r[0] for r in kept], dtype=np.float64),
                         "event": [r[1] for r in kept], "detail": [r[2] for r in kept]})
