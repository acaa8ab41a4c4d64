"""Receiver health: GPS degradation is not spoofing.

A receiver that loses its fix, or whose stated accuracy jumps, gives fixes the detectors find
inconsistent, and an alarm then is a degraded receiver, not a spoof. ``ReceiverHealth`` reads
the receiver's own status reports and the autopilot's GPS events, online, and says when the
receiver is degraded and why; an alert raised while it is (``Alert.kind`` ``degraded``) is
counted apart from the spoofing alerts, never dropped.

Signs of degradation, and only these:

- no fix: a report whose fix type is below ``min_fix`` (3, a 3D fix; PX4 and MAVLink number
  0-1 no fix, 2 2D, 3 3D, 4 and up DGPS and RTK), from that report until the next one with a fix,
  once the receiver has had a fix: a receiver still acquiring its first fix after power-up has
  lost nothing (the autopilot does not arm on it either);
- an accuracy jump: a report with a fix whose horizontal accuracy ``eph`` is above
  ``eph_floor_m`` and more than ``eph_ratio`` times the median eph of the reports with a fix
  over the ``window_s`` before it, until the next report. The median takes in every report, so a
  lasting rise becomes the new normal after about half the window;
- missed fixes: a report later than ``gap_ratio`` times the running median interval between
  reports (and at least ``gap_min_s``), at that report: a receiver that skips its own solutions
  is struggling (ArduPilot's GPS health checks the update interval too);
- the autopilot's ``gps_glitch`` and ``gps_failsafe``, each until its ``_cleared`` event, and
  ``gps_lost`` at its time.

NOT signs of degradation: fewer satellites, a higher noise floor, jamming indicators. A
spoofer's stronger signal raises the noise floor and captures or drowns satellites while the
receiver still reports a good 3D fix and a steady accuracy: that is what a spoof looks like, so a
detector alarm there stays ``spoofing``. Only a receiver that says its fix is lost or worse is
degraded.

The capture signature. A spoofer's capture of a receiver also moves its own indicators: the
satellites drop (``sat_drop``: to at most that share of their running median, and by 3 or more)
and recover, the noise (``noise_rise``) or jamming indicator (``jamming_rise``) rises, the
accuracy estimates inflate (the eph jump above; the speed accuracy above ``speed_acc_ratio``
times its running median and ``speed_acc_floor``). ``capture_sign(t)`` gives the latest such sign
within ``capture_hold_s`` (None otherwise). It is evidence, not a verdict: the online step
(``resilience.step``) calls a detector alarm raised with such a sign ``spoofing`` (reason
``capture: ...``) when the fix moves against the IMU at the same time (the raw innovation, which
the receiver's inflated accuracy cannot normalise away), whatever else the receiver or the
autopilot says then (a capture may lose the lock for a moment, and the autopilot calls the jump
a glitch); without a capture sign an alarm while the receiver is degraded stays ``degraded``.

An erratic fix (``ErraticFix``) is a receiver's fault, not a capture: the fix's horizontal
velocity against the IMU (the raw velocity innovation) above +``ERRATIC_SPEED`` and below
-``ERRATIC_SPEED`` m/s on one axis within ``ERRATIC_S`` seconds. No multirotor reverses 10 m/s
that fast unseen by its IMU, and a spoofer moves the fix one way (a pull-off, then a drift: a
capture's innovation swings one way and the filter absorbs it); a receiver whose solution
jumps back and forth does (a fault with a 3D fix and the satellites in view moving, as a capture's
do). The sign stands ``ERRATIC_HOLD_S`` seconds after it was last seen: a receiver that faulted
that way is not trusted to have been captured the moment its swings pause (on a shared real log
the swings recur for 28 s, and an alarm 14 s after the last read the fault's satellites, still
down, as a capture's). The online step calls an alarm raised then ``degraded`` (reason ``erratic
fix: ...``), the capture sign notwithstanding; the alarm itself, and what the admission does with
it, stand.

A degraded episode runs from its first sign to ``hold_s`` after its last, and is one ``Alert``
of kind ``degraded`` (attack type ``none``, score NaN, reason the first sign's), given as an
``alert_start`` event by the call that sees the sign, and an ``alert_end`` (its ``end_s`` the
episode's end) by the first call at or after that end. Separately, the receiver's own spoofing
verdict (``spoof_flag``: PX4's ``spoofing_state`` at or above ``spoof_level``, 2: spoofing
indicated) stands from the report that sets it to the next report.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from quadformer.detectors.alarms import Alert, AlertEvent, relabelled, with_reason

GPS_EVENTS = ("gps_glitch", "gps_glitch_cleared", "gps_failsafe", "gps_failsafe_cleared", "gps_lost")
REPORT_FIELDS = ("fix_type", "satellites", "eph", "epv", "speed_acc", "jamming", "noise", "spoofing")
SPOOFED = "receiver reports spoofing"       # the reason of an alert the receiver's own flag raised
_STANDING = {"gps_glitch": ("glitch", "autopilot GPS glitch"),
             "gps_failsafe": ("failsafe", "autopilot GPS failsafe")}
_CLEARS = {"gps_glitch_cleared": "glitch", "gps_failsafe_cleared": "failsafe"}
ERRATIC_S = 2.0            # s within which an erratic fix's velocity against the IMU swings both ways
ERRATIC_SPEED = 5.0        # m/s each way
ERRATIC_HOLD_S = 20.0      # s the sign stands after it was last seen: the fault is the receiver's


@dataclass(frozen=True)
class HealthRule:
    min_fix: int = 3             # the least fix type that is a fix (3: a 3D fix)
    eph_ratio: float = 2.5       # an eph above this many times its running median is a jump
    window_s: float = 10.0       # s, the running median's window
    eph_floor_m: float = 1.0     # m, an eph at or below this is never a jump
    hold_s: float = 3.0          # s a degraded episode lasts after its last sign
    spoof_level: int = 2         # the least spoofing state that is the receiver reporting spoofing
    sat_drop: float = 0.7        # satellites at or below this share of their running median are a drop ...
    sat_drop_min: int = 3        # ... of at least this many
    noise_rise: float = 1.15     # a noise indicator above this many times its running median is a rise
    jamming_rise: float = 20.0   # a jamming indicator this much above its running median is a rise (0-255)
    speed_acc_ratio: float = 2.5  # a speed accuracy above this many times its running median is a jump ...
    speed_acc_floor: float = 0.5  # ... and above this (m/s)
    capture_hold_s: float = 5.0  # s a capture sign stands after its report
    gap_ratio: float = 2.0       # a report later than this many times the median interval: fixes missed ...
    gap_min_s: float = 0.3       # ... when also at least this late (s)

    def __post_init__(self):
        for name in ("eph_ratio", "window_s", "eph_floor_m", "hold_s", "sat_drop", "noise_rise", "jamming_rise",
                     "speed_acc_ratio", "speed_acc_floor", "capture_hold_s", "gap_ratio", "gap_min_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"HealthRule.{name} must be a finite number >= 0, got {v!r}")
        if self.eph_ratio <= 1 or self.window_s <= 0:
            raise ValueError(f"HealthRule: eph_ratio must be > 1 and window_s > 0, got "
                             f"{self.eph_ratio!r} and {self.window_s!r}")
        for name in ("min_fix", "spoof_level"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and v >= 1):
                raise ValueError(f"HealthRule.{name} must be an integer >= 1, got {v!r}")


class ReceiverHealth:
    """The receiver health of one vehicle, online (see the module text). ``report`` takes every
    status report of the receiver (those without a fix too), ``event`` the autopilot's GPS
    events, ``tick`` the passing of time (a GPS step); each returns the alert events of the
    degraded episodes it opens or closes. ``flight_id``: the name its alerts carry; ``keep``:
    the closed alerts kept in ``alerts`` (all by default). Times in seconds, fed in order."""

    def __init__(self, rule: HealthRule = HealthRule(), flight_id: Any = 0, keep: int | None = None):
        self.rule, self.flight_id, self.keep = rule, flight_id, keep
        self.open: Alert | None = None
        self.alerts: list[Alert] = []
        self._eph: deque[tuple[float, float]] = deque()    # (t, eph) of the reports with a fix in the window
        self._report: str | None = None                    # the last report's sign, standing until the next
        self._kind_report: str | None = None               # fix or accuracy: what that sign is
        self._autopilot: dict[str, str] = {}               # standing autopilot signs: glitch, failsafe
        self._spoof = False
        self._had_fix = False                              # a report with a fix seen (acquisition over)
        self._last = -math.inf                             # s, when a sign was last present
        self._reason: str | None = None                    # the last sign's reason
        self._kind: str | None = None                      # what the last sign was: fix, accuracy, autopilot
        self._history: dict[str, deque] = {k: deque() for k in ("satellites", "noise", "jamming", "speed_acc")}
        self._capture: tuple[float, str] | None = None     # (t, reason) of the last capture sign
        self._last_report = -math.inf                      # s, the last report's time
        self._intervals: deque[tuple[float, float]] = deque()   # (t, interval) of the reports in the window

    # -- inputs ---------------------------------------------------------------------------
    def report(self, t: float, fix_type: float, satellites: float = math.nan, eph: float = math.nan,
               epv: float = math.nan, speed_acc: float = math.nan, jamming: float = math.nan,
               noise: float = math.nan, spoofing: float = math.nan, *, phase: str = "air",
               phase_reason: str | None = None) -> list[AlertEvent]:
        """One status report at t (NaN: not reported). Fix type and eph are read for signs,
        ``spoofing`` for the receiver's verdict; satellites, epv, speed accuracy, jamming and
        noise are taken and are no sign (see the module text). ``phase``: the flight phase an
        episode opened here is labelled with, ``phase_reason`` why (a landing transition's
        reason, added to the sign's)."""
        t, events = self._advance(t)
        fix, e, r = float(fix_type), float(eph), self.rule
        sign = None
        if math.isfinite(fix) and fix < r.min_fix:
            if self._had_fix:
                sign = f"fix lost (fix type {int(fix)})"
        elif math.isfinite(fix):
            self._had_fix = True
        gap = self._gap(t)
        if gap is not None and sign is None:
            sign = gap
        if math.isfinite(e) and not (math.isfinite(fix) and fix < r.min_fix):
            while self._eph and self._eph[0][0] < t - r.window_s:
                self._eph.popleft()
            if self._eph:
                median = _median([v for _, v in self._eph])
                if e > r.eph_floor_m and e > r.eph_ratio * median:
                    sign = f"accuracy jump (eph {e:.1f} m, median {median:.1f} m)"
            self._eph.append((t, e))
        self._report = sign
        self._kind_report = None if sign is None else "accuracy" if sign.startswith("accuracy") else "fix"
        if math.isfinite(fix) and fix >= r.min_fix:
            capture = self._capture_signs(t, {"satellites": satellites, "noise": noise, "jamming": jamming,
                                              "speed_acc": speed_acc})
            if sign is not None and sign.startswith("accuracy"):
                capture = [sign, *capture]
            if capture:
                self._capture = (t, "; ".join(capture))
        s = float(spoofing)
        self._spoof = math.isfinite(s) and s >= r.spoof_level
        if sign is not None:
            events += self._sign(t, sign, phase, phase_reason)
        return events

    def _gap(self, t: float) -> str | None:
        """A report later than ``gap_ratio`` times the running median interval between reports
        (and at least ``gap_min_s``): the receiver missed fixes (ArduPilot's GPS health likewise
        checks the update interval)."""
        r = self.rule
        last, self._last_report = self._last_report, t
        if not math.isfinite(last) or t <= last:
            return None
        dt = t - last
        ivs = self._intervals
        while ivs and ivs[0][0] < t - r.window_s:
            ivs.popleft()
        out = None
        if len(ivs) >= 5:
            m = _median([v for _, v in ivs])
            if dt > r.gap_ratio * m and dt >= r.gap_min_s:
                out = f"fixes missed ({dt:.2f} s since the last report, median {m:.2f} s)"
        ivs.append((t, dt))
        return out

    def _capture_signs(self, t: float, values: dict[str, float]) -> list[str]:
        """The capture signs of a report with a fix (see the module text), against the running
        medians of the reports before it within ``window_s``."""
        r, out = self.rule, []
        for name, v in values.items():
            v = float(v)
            hist = self._history[name]
            while hist and hist[0][0] < t - r.window_s:
                hist.popleft()
            if not math.isfinite(v):
                continue
            if hist:
                m = _median([x for _, x in hist])
                if name == "satellites" and v <= r.sat_drop * m and m - v >= r.sat_drop_min:
                    out.append(f"satellites {v:.0f} (median {m:.0f})")
                elif name == "noise" and m > 0 and v > r.noise_rise * m:
                    out.append(f"noise indicator {v:.0f} (median {m:.0f})")
                elif name == "jamming" and v > m + r.jamming_rise:
                    out.append(f"jamming indicator {v:.0f} (median {m:.0f})")
                elif name == "speed_acc" and v > r.speed_acc_floor and v > r.speed_acc_ratio * m:
                    out.append(f"speed accuracy {v:.1f} m/s (median {m:.1f})")
            hist.append((t, v))
        return out

    def capture_sign(self, t: float) -> str | None:
        """The receiver's latest capture sign within ``capture_hold_s`` before t (see the module
        text), None when there is none."""
        if self._capture is None or float(t) > self._capture[0] + self.rule.capture_hold_s:
            return None
        return self._capture[1]

    def degraded_by(self, t: float) -> str | None:
        """What the receiver's degradation at t is: ``fix`` (a report without a fix), ``accuracy``
        (an accuracy jump), ``autopilot`` (its glitch, failsafe or GPS lost), None when healthy."""
        if self._report is not None:
            return self._kind_report
        if self._autopilot:
            return "autopilot"
        return self._kind if float(t) < self._last + self.rule.hold_s else None

    def event(self, t: float, kind: str, *, phase: str = "air", phase_reason: str | None = None) -> list[AlertEvent]:
        """One of the autopilot's events at t (``GPS_EVENTS``; others only advance the clock);
        ``phase``, ``phase_reason`` as for ``report``."""
        t, events = self._advance(t)
        if kind in _STANDING:
            key, reason = _STANDING[kind]
            self._autopilot[key] = reason
            events += self._sign(t, reason, phase, phase_reason)
        elif kind in _CLEARS:
            self._autopilot.pop(_CLEARS[kind], None)
        elif kind == "gps_lost":
            events += self._sign(t, "autopilot reports GPS lost", phase, phase_reason)
        return events

    def tick(self, t: float) -> list[AlertEvent]:
        """Time at t with nothing new: closes the episode whose hold has run out."""
        return self._advance(t)[1]

    def finish(self) -> list[AlertEvent]:
        """The end of the data: the open episode closed (``end_s`` None)."""
        return [] if self.open is None else [self._close(None, None)]

    def relabel(self, start_s: float, phase: str, reason: str | None, t: float | None = None) -> AlertEvent | None:
        """Set the flight phase of the episode raised at ``start_s`` (open, or among those kept)
        and add ``reason`` to its own; the ``alert_relabel`` event (None: no such episode)."""
        if self.open is not None and self.open.start_s == start_s:
            was, self.open = self.open, relabelled(self.open, phase, reason)
            return AlertEvent("alert_relabel", 0, t, self.open, was=was.phase)
        for k in range(len(self.alerts) - 1, -1, -1):
            if self.alerts[k].start_s == start_s:
                was, self.alerts[k] = self.alerts[k], relabelled(self.alerts[k], phase, reason)
                return AlertEvent("alert_relabel", 0, t, self.alerts[k], was=was.phase)
        return None

    # -- state ----------------------------------------------------------------------------
    def degraded(self, t: float) -> str | None:
        """Why the receiver is degraded at t (the standing sign, else the last sign within
        ``hold_s``), None when it is healthy."""
        standing = self._standing()
        if standing is not None:
            return standing
        return self._reason if float(t) < self._last + self.rule.hold_s else None

    def spoof_flag(self, t: float) -> bool:
        """Whether the receiver itself reports spoofing at t (its last report's spoofing state)."""
        return self._spoof

    def _standing(self) -> str | None:
        return self._report or next(iter(self._autopilot.values()), None)

    def _advance(self, t) -> tuple[float, list[AlertEvent]]:
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"ReceiverHealth: a time must be finite, got {t!r}")
        if self._standing() is not None:
            self._last = max(self._last, t)          # the standing sign lasted until now
        elif self.open is not None and t >= self._last + self.rule.hold_s:
            return t, [self._close(self._last + self.rule.hold_s, t)]
        return t, []

    def _sign(self, t: float, reason: str, phase: str, phase_reason: str | None = None) -> list[AlertEvent]:
        self._last, self._reason = max(self._last, t), reason
        self._kind = ("fix" if reason.startswith(("fix lost", "fixes missed")) else "accuracy"
                      if reason.startswith("accuracy") else "autopilot")
        if self.open is not None:
            return []
        self.open = Alert(self.flight_id, t, t, "none", math.nan, None, kind="degraded", phase=phase,
                          reason=with_reason(reason, phase_reason))
        return [AlertEvent("alert_start", 0, t, self.open)]

    def _close(self, end_s: float | None, t: float | None) -> AlertEvent:
        a = dataclasses.replace(self.open, end_s=end_s)
        self.open = None
        self.alerts.append(a)
        if self.keep is not None and len(self.alerts) > self.keep:
            del self.alerts[0]
        return AlertEvent("alert_end", 0, t, a)


def _median(values: list[float]) -> float:
    """``float(np.median(values))`` of a short list of floats (the same number, NaN if one is),
    without numpy's cost per call: the medians are taken at every report."""
    s = sorted(values)
    n = len(s)
    if n == 0 or any(map(math.isnan, s)):
        return math.nan
    return s[n // 2] if n % 2 else (s[n // 2 - 1] + s[n // 2]) / 2


class ErraticFix:
    """The erratic-fix sign of a receiver fault (see the module text), fed each fix's raw
    horizontal velocity innovation in time order (``push``: the sign is seen where the fixes of
    the last ``window_s`` swing both ways); ``reason(t)``: the sign seen at t, or the last one
    seen within ``hold_s`` before t (with its age), or None."""

    def __init__(self, window_s: float = ERRATIC_S, speed: float = ERRATIC_SPEED, hold_s: float = ERRATIC_HOLD_S):
        if not (window_s > 0 and speed > 0 and hold_s >= 0):
            raise ValueError(f"erratic fix: window_s and speed must be positive and hold_s at least 0, got "
                             f"{window_s!r}, {speed!r}, {hold_s!r}")
        self.window_s, self.speed, self.hold_s = float(window_s), float(speed), float(hold_s)
        self.recent: deque[tuple[float, float, float]] = deque()
        self.last: tuple[float, str] | None = None       # (time, reason) of the sign last seen

    def push(self, t: float, vx: float, vy: float) -> None:
        t = float(t)
        if math.isfinite(t) and math.isfinite(vx) and math.isfinite(vy):
            self.recent.append((t, float(vx), float(vy)))
        while self.recent and self.recent[0][0] < t - self.window_s:
            self.recent.popleft()
        for k, axis in ((1, "east"), (2, "north")):
            v = [r[k] for r in self.recent]
            if v and max(v) >= self.speed and min(v) <= -self.speed:
                self.last = (t, f"erratic fix: its velocity against the IMU swung {max(v):+.1f} and {min(v):+.1f} "
                                f"m/s {axis} within {self.window_s:g} s (a receiver fault)")
                break

    def reason(self, t: float) -> str | None:
        if self.last is None:
            return None
        age = float(t) - self.last[0]
        if age <= 1e-9:
            return self.last[1]
        return f"{self.last[1]}, {age:.1f} s ago" if age <= self.hold_s else None
