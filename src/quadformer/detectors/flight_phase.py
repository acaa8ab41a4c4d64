"""Where the vehicle is: on the ground, in a take-off or landing transition, or in the air.

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
can say how it was known.

Landings. The ``land_s`` (10 s) before a landing are a transition too, as the seconds after a
take-off are: a hard landing's or a crash's transient (the vehicle stopping against the ground)
makes the GPS innovations large before the autopilot says it has landed. A landing is known
from (``Landing``, its ``how``):

- a ``landed`` event, or a ``disarmed`` event in the air (the vehicle was airborne, or its phase
  unknown), at the event's time (at the height's touchdown where one is pending);
- the height fallback's landing, dated at its touchdown: the first of the heights within
  ``climb_m / 2`` of the ground, ``land_hold_s`` before the landing is declared;
- an impact (``impact(t, crash)``, from ``detectors.impact``): a crash anywhere once the vehicle
  is seen down within ``impact_hold_s`` after it (a landed or disarmed event, the height near the
  ground, or the end of the data: a spike in the air that the vehicle flies on from is no landing,
  so a spoof that makes the vehicle jerk cannot have its alert relabelled); a smaller impact only
  near the ground: the last height within ``near_m`` (3 m) of the ground height, or
  within twice that while descending (it fell more than ``climb_m`` over the last ``sink_s``).
  Without a height only a crash counts. The ``impact_hold_s`` (5 s) after a counted impact are a
  transition where the phase would be ``air``.

The phase at a time is known only after it, so online (``update``) a step within ``land_s``
before a landing reads ``air`` until the landing is seen; ``pop_landings`` hands the landings
declared since it was last called to whoever labelled alerts with the phase (the online step
relabels its alerts raised in the air in ``[landing - land_s, landing seen)``: ``transition``,
with the landing's ``reason``). ``phases`` runs the same object over a whole log's times and
applies the same windows, so its phases are the labels the online alerts end with.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import pandas as pd

from quadformer.detectors.alarms import LANDING

PHASES = ("ground", "transition", "air")
VEHICLE_EVENTS = ("armed", "disarmed", "takeoff", "landed")   # the events the phase reads
MAX_LANDINGS = 64          # landings held for pop_landings at most (the oldest dropped beyond)


@dataclass(frozen=True)
class PhaseRule:
    settle_s: float = 5.0       # s after a take-off before "air" ("transition" until then)
    climb_m: float = 1.0        # m above the ground height that makes a take-off (height fallback)
    land_hold_s: float = 3.0    # s within climb_m / 2 of the ground that make a landing (height fallback)
    land_s: float = 10.0        # s before a landing that are its transition
    impact_hold_s: float = 5.0  # s after an impact counted as a landing that are a transition
    near_m: float = 3.0         # m above the ground height within which an impact is a touchdown (2x descending)
    sink_s: float = 3.0         # s over which a fall of more than climb_m is a descent

    def __post_init__(self):
        for name in ("settle_s", "climb_m", "land_hold_s", "land_s", "impact_hold_s", "near_m", "sink_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0):
                raise ValueError(f"PhaseRule.{name} must be a finite number >= 0, got {v!r}")
        if self.climb_m <= 0:
            raise ValueError(f"PhaseRule.climb_m must be > 0, got {self.climb_m!r}")


@dataclass(frozen=True)
class Landing:
    """A landing: ``t`` when the vehicle came down, ``seen_t`` when it was known (the height's
    touchdown is known ``land_hold_s`` later), ``how`` in words (``landed event``, ``disarmed
    event``, ``height``, or the impact's, e.g. ``crash: 7.0 g``)."""
    t: float
    seen_t: float
    how: str

    @property
    def reason(self) -> str:
        """The reason of an alert in its transition: ``landing at t=93.0 s (landed event)``."""
        return f"{LANDING}{self.t:.1f} s ({self.how})"


class FlightPhase:
    """The flight phase of one vehicle, online (see the module text): ``event(t, kind)`` for the
    vehicle's events, ``impact(t, crash)`` for an impact, ``update(t, height=None)`` for the phase
    at t (a height sample, where one is given, applied first), ``reason(t)`` for why it is a
    landing's transition, ``pop_landings()`` for the landings declared. Times are seconds on the
    clock of the data fed, in order."""

    def __init__(self, rule: PhaseRule = PhaseRule()):
        self.rule = rule
        self.armed: bool | None = None   # None: no arming or disarming seen
        self.airborne = False
        self.takeoff_t = math.nan        # s, the last take-off
        self.by_events = False           # a takeoff or landed event seen: events alone decide from then
        self.ground_h = math.nan         # m, the ground height (height fallback)
        self._low_since = math.nan       # s, the first of the current run of heights near the ground
        self._heights = False            # a height seen
        self.last_impact: Landing | None = None     # the last impact counted as a landing
        self._crash: tuple[float, str] | None = None   # (t, how) of a crash in the air not yet seen down
        self._recent: deque[tuple[float, float]] = deque()   # (t, h) of the last sink_s of heights
        self._landings: deque[Landing] = deque(maxlen=MAX_LANDINGS)

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
        if kind in ("landed", "disarmed") and self._crash is not None:
            self._confirm_crash(t, down=True)
        if kind in ("landed", "disarmed") and (self.airborne or self.source == "none"):
            self._land(min(t, self._low_since) if math.isfinite(self._low_since) else t, t, f"{kind} event")
        if kind == "takeoff":
            if not (self.by_events and self.airborne):      # a repeated take-off keeps the first
                self.takeoff_t = t
            self.by_events = self.airborne = True
            self._low_since = math.nan
        elif kind == "landed":
            self.by_events = True
            self.airborne = False
            self._low_since = math.nan
        elif kind == "armed":
            if not self.airborne:
                self.ground_h = math.nan                    # the next height is the ground
            self.armed = True
        elif kind == "disarmed":
            self.armed = self.airborne = False
            self._low_since = math.nan

    def update(self, t: float, height: float | None = None) -> str:
        """The phase at t (``PHASES``); ``height``: a height sample at t (m), used for the take-off
        and landing while no take-off or landing event has been seen, and for impacts always."""
        t = _time(t)
        if height is not None and math.isfinite(height):
            h = float(height)
            self._track(t, h)
            if not self.by_events:
                self._height(t, h)
        self._confirm_crash(t)
        return self._phase(t)

    def impact(self, t: float, crash: bool = False, how: str = "impact") -> bool:
        """An impact at t (``detectors.impact``; ``crash``: one that counts wherever the vehicle
        is; ``how``: in words, for the landing's reason); whether it counts as a landing (see the
        module text)."""
        t = _time(t)
        if self._near_ground():
            self.last_impact = self._land(t, t, how)
            return True
        if crash:                   # a crash in the air: a landing once the vehicle is seen down
            self._crash = (t, how)
        return False

    def finish(self, t: float) -> None:
        """The end of the data at t: a crash pending within ``impact_hold_s`` before it is a landing
        (the log or the link ended with it)."""
        self._confirm_crash(_time(t), ended=True)

    def _confirm_crash(self, t: float, ended: bool = False, down: bool = False) -> None:
        """Declare a pending crash a landing when the vehicle is down (``down``: a landed or disarmed
        event; else the height near the ground) or the data ended, within ``impact_hold_s`` after
        it; forget it after that."""
        if self._crash is None:
            return
        tc, how = self._crash
        if t > tc + self.rule.impact_hold_s + 1e-9:
            self._crash = None
        elif ended or down or self._near_ground():
            self._crash = None
            self.last_impact = self._land(tc, t, how)

    def reason(self, t: float) -> str | None:
        """Why the phase at t is a landing's transition (the impact hold): the impact's
        ``Landing.reason``; None otherwise (the take-off's transition, or not a transition)."""
        return self.last_impact.reason if self._held(_time(t)) else None

    def pop_landings(self) -> list[Landing]:
        """The landings declared since the last call, in order."""
        out = list(self._landings)
        self._landings.clear()
        return out

    def touchdown(self, t: float) -> float:
        """The earliest time a landing not yet declared at t can be dated at: a pending crash, the
        pending touchdown of the height fallback, else t."""
        out = min(t, self._low_since) if math.isfinite(self._low_since) else t
        return out if self._crash is None else min(out, self._crash[0])

    def _land(self, t: float, seen: float, how: str) -> Landing:
        landing = Landing(t, seen, how)
        self._landings.append(landing)
        return landing

    def _track(self, t: float, h: float) -> None:
        """Keep the last ``sink_s`` of heights (descent) and the ground height (impacts)."""
        if math.isnan(self.ground_h) and not self.airborne:
            self.ground_h = h
        q = self._recent
        q.append((t, h))
        while q[0][0] < t - self.rule.sink_s:
            q.popleft()

    def _near_ground(self) -> bool:
        """Whether the last height is near the ground: within ``near_m`` of it, or within twice that
        while descending (it fell more than ``climb_m`` over the last ``sink_s``)."""
        if not self._recent or math.isnan(self.ground_h):
            return False
        h = self._recent[-1][1]
        rise, r = h - self.ground_h, self.rule
        return rise <= r.near_m or (rise <= 2 * r.near_m and max(x for _, x in self._recent) - h > r.climb_m)

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
                self._land(self._low_since, t, "height")
                self.airborne, self._low_since = False, math.nan
        else:
            self._low_since = math.nan

    def _base(self, t: float) -> str:
        """The phase at t from the take-off and the landing alone (no impact hold)."""
        if self.airborne:
            return "transition" if t - self.takeoff_t < self.rule.settle_s else "air"
        return "air" if self.source == "none" else "ground"

    def _held(self, t: float) -> bool:
        """Whether t is in the last counted impact's hold where the phase would be ``air``."""
        return (self.last_impact is not None and 0 <= t - self.last_impact.t < self.rule.impact_hold_s
                and self._base(t) == "air")

    def _phase(self, t: float) -> str:
        return "transition" if self._held(t) else self._base(t)


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
           rule: PhaseRule = PhaseRule(), impacts: pd.DataFrame | None = None) -> np.ndarray:
    """The phase at each time of ``t`` (in order), from ``events`` (columns t, event, detail),
    ``height`` (columns t, h) and ``impacts`` (columns t, crash and detail: ``detectors.impact.
    impacts``), each row applied, in time order (at equal times: events, heights, impacts), before
    the times at or after it: ``FlightPhase`` run over a whole log. Then, looking ahead, the steps
    in the air within ``land_s`` before each landing (up to when it was seen) are ``transition``:
    the phases an online step's alerts end with, once relabelled at the landing."""
    t = np.asarray(t, dtype=float)
    if not np.isfinite(t).all():
        raise ValueError(f"phases: {int((~np.isfinite(t)).sum())} time(s) t not finite")
    if np.any(np.diff(t) < 0):
        raise ValueError("phases: the times t must be in order")
    for name, frame, cols in (("events", events, ("event",)), ("height", height, ("h",)),
                              ("impacts", impacts, ("crash",))):
        lacking = [c for c in cols if frame is not None and c not in frame.columns]
        if lacking:
            raise ValueError(f"{name}: no column {lacking[0]} (has {', '.join(map(str, frame.columns))})")
    fp = FlightPhase(rule)
    items = list(timeline(("events", events), ("height", height), ("impacts", impacts)))
    out, landings, k = [], [], 0

    def feed(ti: float, name: str, row: dict) -> None:
        if name == "events":
            fp.event(ti, str(row["event"]))
        elif name == "height":
            fp.update(ti, float(row["h"]))
        else:
            fp.impact(ti, bool(row["crash"]), str(row.get("detail", "impact")))

    for tk in t:
        while k < len(items) and items[k][0] <= tk:
            feed(*items[k])
            k += 1
        out.append(fp.update(tk))
        landings += fp.pop_landings()
    for item in items[k:]:                   # landings after the last time still relabel before it
        feed(*item)
    ends = ([float(t[-1])] if len(t) else []) + ([float(items[-1][0])] if items else [])
    if ends:
        fp.finish(max(ends))
    landings += fp.pop_landings()
    out = np.array(out, dtype=object)
    for landing in landings:
        window = (t >= landing.t - rule.land_s) & (t < landing.seen_t) & (out == "air")
        out[window] = "transition"
    return out
