"""What the live monitor knows of the flight beside its sensors: the vehicle's events, its GPS
receiver's status reports, its height and the impacts in its IMU, fed to the online step's flight phase and receiver
health (``detectors.flight_phase``, ``detectors.receiver_health``) in time order, as ``detect``
feeds a log's (``logs.detect.step_alerts``), so that a flight's alerts get the same kind and
phase live and offline. Only the alerts' labels depend on them: the GPS admission does not.

From the followed vehicle's messages:

- events (``sensors.mavlink.VehicleEvents``, the telemetry log reader's conversion): armed and
  disarmed from the autopilot's HEARTBEAT, takeoff and landed from EXTENDED_SYS_STATE, GPS
  glitches and failsafes from STATUSTEXT. These messages carry no time of their own: an event
  is at the link's latest ``t`` when it arrives (0 before the first sensor sample), as a
  telemetry log times its messages by their arrival;
- receiver reports: every GPS_RAW_INT / GPS2_RAW of the receiver in use (receiver 0 until one
  has a 3D fix), with a fix or not (``sensors.mavlink.gps_status``), at its own stamp on the
  link's time base; a report stamped at or before the previous one (a duplicate) is dropped;
- heights: the barometer the intake uses; on a link without a barometer, the altitude of the
  GPS fixes. A barometer first heard after GPS heights is shifted onto the GPS altitude's datum
  there, so the change of datum is no climb;
- impacts: every IMU sample the intake accepts goes through ``detectors.impact.ImpactDetector``
  (a 50 ms running mean of the specific force: a few float operations per sample); only an
  impact it finds is queued, at the sample's time. A landing the phase declares from an
  impact, a height or an event relabels the segment's alerts raised in the air before it
  (``alert_relabel`` events, returned by ``feed`` with the receiver's).

Beside them, the autopilot's own evidence: its innovation test ratios (``EKF_STATUS_REPORT``,
``ESTIMATOR_STATUS``; ``sensors.mavlink.estimator_ratios``), counted with the last and the largest
of each (``ratios``), for the summary; the monitor writes each to ``autopilot_ratios.csv``. They
are not fed to the step: nothing scores them yet.

Order. The step scores a fix's row once the IMU has passed the fix, and the other messages
arrive around it, so the inputs wait in a queue sorted by time (at equal times: events,
reports, heights, impacts, the order of ``step_alerts``) and are fed to the segment's step: before each
row, those at or before the row's time; between rows, those before the watermark: the latest
receiver report (the GPS stream has passed them) or, while the GPS is silent, the link's latest
``t`` less ``stale_s``, but never at or after a fix still waiting for its row. A lost fix thus
raises its degraded alert at the next report, without waiting for a fix. The queue holds at most
``MAX_PENDING`` inputs: beyond, the oldest is fed (or, before the first segment, dropped and
counted); a segment's end feeds it all that is queued.
"""

from __future__ import annotations

import bisect
import math
from collections import Counter
from typing import Any

from quadformer.detectors.alarms import AlertEvent
from quadformer.detectors.flight_phase import FlightPhase
from quadformer.detectors.impact import ImpactDetector
from quadformer.resilience.step import OnlineStep
from quadformer.sensors.mavlink import EstimatorRatios, GpsStatus, VehicleEvents

__all__ = ["MAX_PENDING", "FlightState"]

MAX_PENDING = 2000                         # inputs queued at most
RANK = {"event": 0, "report": 1, "height": 2, "impact": 3}   # order at equal times, as step_alerts feeds a log's
REPORT = ("fix_type", "satellites", "eph", "epv", "speed_acc")   # the fields of a GpsStatus the health reads
RATIOS = ("vel", "pos_horiz", "pos_vert", "mag")    # the test ratios (square roots) the summary keeps


class FlightState:
    """The vehicle's events, receiver reports, heights and IMU impacts of one link, queued and fed
    to the segments' online steps (see the module text). ``phase``: the flight phase, one for the
    link, shared by its segments' steps; ``impacts``: the IMU's impact detector; ``counts``:
    events by name, reports, heights and impacts taken, inputs dropped."""

    def __init__(self, stale_s: float = 1.0, max_pending: int = MAX_PENDING):
        self.stale_s, self.max_pending = stale_s, max_pending
        self.phase = FlightPhase()
        self.impacts = ImpactDetector()
        self.vehicle_events = VehicleEvents(start="at the link's first report")
        self.pending: list[tuple[float, int, int, Any]] = []     # (t, rank, arrival, input)
        self.counts: Counter = Counter()
        self.last_report = -math.inf            # t of the latest receiver report
        self.height_source: str | None = None   # "baro" or "gps"
        self._datum = 0.0                       # m added to barometric heights (a switch from GPS heights)
        self._gps_h = math.nan
        self._arrivals = 0
        self.last_ratios: dict[str, Any] | None = None       # the autopilot's latest test ratios
        self.max_ratios: dict[str, float] = {}               # and the largest of each

    # -- inputs ---------------------------------------------------------------------------
    def message(self, t: float, msg) -> None:
        """A HEARTBEAT, EXTENDED_SYS_STATE or STATUSTEXT of the vehicle at the link's time t."""
        for ti, event, _ in self.vehicle_events.message(t, msg):
            self.counts[event] += 1
            self._queue(ti, "event", event)

    def report(self, t: float, status: GpsStatus) -> None:
        """A status report of the receiver in use, at t (its stamp on the link's time base)."""
        if t <= self.last_report:
            self.counts["reports_dropped"] += 1
            return
        self.last_report = t
        self.counts["reports"] += 1
        self._queue(t, "report", {c: getattr(status, c) for c in REPORT})

    def height(self, t: float, h: float, source: str) -> None:
        """A height at t (m): ``source`` "baro" (the barometer) or "gps" (a fix's altitude)."""
        if source == "gps":
            if self.height_source == "baro":
                return
            self.height_source, self._gps_h = "gps", h
        elif self.height_source != "baro":
            if self.height_source == "gps":
                self._datum = self._gps_h - h
            self.height_source = "baro"
        self.counts[f"heights_{source}"] += 1
        self._queue(t, "height", h + self._datum if source == "baro" else h)

    def ratios(self, t: float, r: EstimatorRatios) -> None:
        """The autopilot's own test ratios at t (``EstimatorRatios``): counted, the last and the
        largest kept; not fed to the step."""
        self.counts[f"ratios_{r.source}"] += 1
        self.counts["ratios_gps_glitch"] += r.gps_glitch
        self.last_ratios = {"t": t, "source": r.source, **{k: getattr(r, k) for k in RATIOS},
                            "gps_glitch": r.gps_glitch}
        for k in RATIOS:
            v = getattr(r, k)
            if math.isfinite(v) and not v <= self.max_ratios.get(k, -math.inf):
                self.max_ratios[k] = v

    def imu(self, t: float, x) -> bool:
        """An IMU sample at t (``x``: specific force in m/s^2 first, as ``sensors.samples.Imu``);
        whether it completed an impact (then queued)."""
        ax, ay, az = x[:3].tolist()
        imp = self.impacts.update(t, ax, ay, az)
        if imp is None:
            return False
        self.counts["impacts"] += 1
        self._queue(t, "impact", imp)
        return True

    def _queue(self, t: float, kind: str, value: Any) -> None:
        item = (float(t), RANK[kind], self._arrivals, (kind, value))
        self._arrivals += 1
        if not self.pending or item >= self.pending[-1]:
            self.pending.append(item)
        else:
            bisect.insort(self.pending, item)

    # -- feeding --------------------------------------------------------------------------
    def watermark(self, now_t: float, waiting: float) -> float:
        """The time before which the inputs may be fed between rows: the latest report, or the
        link's latest ``t`` less ``stale_s``, and not past ``waiting`` (the earliest fix waiting
        for its row, ``ResidueStream.waiting``)."""
        return min(max(self.last_report, now_t - self.stale_s), waiting)

    def feed(self, step: OnlineStep, until: float, inclusive: bool = True) -> list[AlertEvent]:
        """Feed ``step`` the inputs queued up to ``until`` (and the oldest beyond ``MAX_PENDING``),
        in order; the alert events of the receiver's degraded episodes they open or close and of
        the alerts a landing among them relabels."""
        events: list[AlertEvent] = []
        k, n = 0, len(self.pending)
        while k < n and (n - k > self.max_pending or self.pending[k][0] < until
                         or (inclusive and self.pending[k][0] == until)):
            t, _, _, (kind, value) = self.pending[k]
            if kind == "event":
                events += step.event(t, value)
            elif kind == "report":
                events += step.receiver(t, **value)
            elif kind == "height":
                events += step.height(t, value)
            else:
                events += step.impact(t, value.crash, value.detail)
            k += 1
        del self.pending[:k]
        return events

    def trim(self) -> None:
        """Without a step to feed (before the first segment): drop the oldest beyond ``MAX_PENDING``."""
        extra = len(self.pending) - self.max_pending
        if extra > 0:
            del self.pending[:extra]
            self.counts["inputs_dropped"] += extra

    def summary(self) -> dict[str, Any]:
        """The phase and its source, the height's source, the inputs taken and the autopilot's
        test ratios, the last and the largest (summary.json)."""
        return {"phase_source": self.phase.source, "height_source": self.height_source,
                "inputs": dict(sorted(self.counts.items())),
                "autopilot_ratios": {"what": "square roots of the autopilot's innovation test ratios (1: at its gate)",
                                     "last": self.last_ratios, "max": dict(self.max_ratios)}}
