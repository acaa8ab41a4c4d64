"""Where the vehicle is: on the ground, in its take-off transition, or in the air.

An alert raised on the ground (the receiver settling, the vehicle carried to its pad) or in the
seconds after take-off (the filter meeting real motion) is not what an operator is raised
for; alerts are labelled with the phase at their raise (``Alert.phase``) and counted apart,
never dropped. ``FlightPhase`` is the phase known online, from what the vehicle says:

- its own events (``event``): ``takeoff`` makes it airborne at that time, ``landed`` or
  ``disarmed`` grounds it; ``armed`` marks the arming (other events are ignored). The first
  ``settle_s`` after a take-off are ``transition``, then ``air`` until landed or disarmed;
  ``ground`` otherwise.
- while no ``takeoff`` or ``landed`` event has been seen, its height (``update(t, height)``:
  metres on any datum, a barometer or the GPS altitude): the ground is the height at arming
  (the first height seen where no arming was); the vehicle is airborne when it rises more than
  ``climb_m`` above the ground while armed or with its arming unknown (taking off at that
  sample), grounded again once within ``climb_m / 2`` of the ground (or below it) for
  ``land_hold_s``, or on disarming. A log that starts in flight reads as ground until it climbs
  another ``climb_m``: the height gives no absolute ground.
- with its arming alone (no take-off event, no height): ``ground``, until a take-off is seen.
  A source that logs arming but never its take-offs, and no height, reads as ground
  throughout; its alerts are still counted, beside the headline.
- with nothing at all: every step is ``air``, so no alert is ever labelled away unseen.

``source`` says which of these gave the phase (``events``, ``height`` or ``none``), so a report
can say how it was known. ``phases`` runs the same object over a whole log's times.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import pandas as pd

PHASES = ("ground", "transition", "air")
VEHICLE_EVENTS = ("armed", "disarmed", "takeoff", "landed")   # the events the phase reads


@dataclass(frozen=True)
class PhaseRule:
    settle_s: float = 5.0      # s after a take-off before "air" ("transition" until then)
    climb_m: float = 1.0       # m above the ground height that makes a take-off (height fallback)
    land_hold_s: float = 3.0   # s within climb_m / 2 of the ground that make a landing (height fallback)

    def __post_init__(self):
        for name in ("settle_s", "climb_m", "land_hold_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"PhaseRule.{name} must be a finite number >= 0, got {v!r}")
        if self.climb_m <= 0:
            raise ValueError(f"PhaseRule.climb_m must be > 0, got {self.climb_m!r}")


class FlightPhase:
    """The flight phase of one vehicle, online (see the module text): ``event(t, kind)`` for the
    vehicle's events, ``update(t, height=None)`` for the phase at t (a height sample, where one
    is given, applied first). Times are seconds on the clock of the data fed, in order."""

    def __init__(self, rule: PhaseRule = PhaseRule()):
        self.rule = rule
        self.armed: bool | None = None   # None: no arming or disarming seen
        self.airborne = False
        self.takeoff_t = math.nan        # s, the last take-off
        self.by_events = False           # a takeoff or landed event seen: events alone decide from then
        self.ground_h = math.nan         # m, the ground height (height fallback)
        self._low_since = math.nan       # s, the first of the current run of heights near the ground
        self._heights = False            # a height seen

    @property
    def source(self) -> str:
        """How the phase is known: ``events``, ``height`` or ``none``."""
        if self.by_events:
            return "events"
        if self._heights:
            return "height"
        return "events" if self.armed is not None else "none"

    def event(self, t: float, kind: str) -> None:
        """One of the vehicle's events at t (``VEHICLE_EVENTS``; others are ignored)."""
        t = _time(t)
        if kind == "takeoff":
            if not (self.by_events and self.airborne):      # a repeated take-off keeps the first
                self.takeoff_t = t
            self.by_events = self.airborne = True
            self._low_since = math.nan
        elif kind == "landed":
            self.by_events = True
            self.airborne = False
        elif kind == "armed":
            if not self.airborne:
                self.ground_h = math.nan                    # the next height is the ground
            self.armed = True
        elif kind == "disarmed":
            self.armed = self.airborne = False
            self._low_since = math.nan

    def update(self, t: float, height: float | None = None) -> str:
        """The phase at t (``PHASES``); ``height``: a height sample at t (m), used while no
        take-off or landing event has been seen."""
        t = _time(t)
        if height is not None and math.isfinite(height) and not self.by_events:
            self._height(t, float(height))
        return self._phase(t)

    def _height(self, t: float, h: float) -> None:
        self._heights = True
        if math.isnan(self.ground_h):
            self.ground_h = h
        rise = h - self.ground_h
        r = self.rule
        if not self.airborne:
            if rise > r.climb_m and self.armed is not False:
                self.airborne, self.takeoff_t, self._low_since = True, t, math.nan
        elif rise <= r.climb_m / 2:
            if math.isnan(self._low_since):
                self._low_since = t
            if t - self._low_since >= r.land_hold_s:
                self.airborne, self._low_since = False, math.nan
        else:
            self._low_since = math.nan

    def _phase(self, t: float) -> str:
        if self.airborne:
            return "transition" if t - self.takeoff_t < self.rule.settle_s else "air"
        return "air" if self.source == "none" else "ground"


def _time(t) -> float:
    t = float(t)
    if not math.isfinite(t):
        raise ValueError(f"a time must be finite, got {t!r}")
    return t


def timeline(*frames: tuple[str, pd.DataFrame | None]) -> Iterator[tuple[float, str, dict]]:
    """The rows of several time-stamped frames (``(name, frame)``, each with a column ``t`` in
    seconds; None or empty: none) merged in time order, as (t, name, row); at equal times in the
    order the frames are given, then in each frame's own order."""
    parts = []
    for k, (name, frame) in enumerate(frames):
        if frame is None or not len(frame):
            continue
        if "t" not in frame.columns:
            raise ValueError(f"{name}: no column t (has {', '.join(map(str, frame.columns))})")
        t = frame["t"].to_numpy(dtype=float)
        if not np.isfinite(t).all():
            raise ValueError(f"{name}: {int((~np.isfinite(t)).sum())} row(s) without a finite time t")
        parts.append((t, np.full(len(t), k), np.arange(len(t)), name, frame.to_dict("records")))
    if not parts:
        return iter(())
    t = np.concatenate([p[0] for p in parts])
    src = np.concatenate([p[1] for p in parts])
    pos = np.concatenate([p[2] for p in parts])
    records = {p[1][0]: (p[3], p[4]) for p in parts}
    order = np.lexsort((pos, src, t))
    return ((float(t[i]), records[src[i]][0], records[src[i]][1][pos[i]]) for i in order)


def phases(t, events: pd.DataFrame | None = None, height: pd.DataFrame | None = None,
           rule: PhaseRule = PhaseRule()) -> np.ndarray:
    """The phase at each time of ``t`` (in order), from ``events`` (columns t, event, detail) and
    ``height`` (columns t, h), each row applied, in time order, before the times at or after it:
    ``FlightPhase`` run over a whole log."""
    t = np.asarray(t, dtype=float)
    if np.any(np.diff(t) < 0):
        raise ValueError("phases: the times t must be in order")
    for name, frame, col in (("events", events, "event"), ("height", height, "h")):
        if frame is not None and col not in frame.columns:
            raise ValueError(f"{name}: no column {col} (has {', '.join(map(str, frame.columns))})")
    fp = FlightPhase(rule)
    items = list(timeline(("events", events), ("height", height)))
    out, k = [], 0
    for tk in t:
        while k < len(items) and items[k][0] <= tk:
            ti, name, row = items[k]
            if name == "events":
                fp.event(ti, str(row["event"]))
            else:
                fp.update(ti, float(row["h"]))
            k += 1
        out.append(fp.update(tk))
    return np.array(out, dtype=object)
