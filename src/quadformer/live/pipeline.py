"""The live monitor's pipeline: one MAVLink message in, samples fed to the segment, its rows
scored, alert events and fix records out. ``Pipeline`` is the base of ``live.monitor.Monitor``
and holds what it does per message (``process``: routing by kind, the vehicle's events,
receiver reports, heights and IMU samples (for impacts) to ``live.flight_state``, samples
through ``live.intake`` to the segment), per
residue row (score, admission, ``FixRecord``) and per segment (a restart, an IMU gap or an error
ends one and starts the next); the autopilot's own test ratios (EKF_STATUS_REPORT,
ESTIMATOR_STATUS) are recorded beside, not scored; ``Monitor`` sets the state up in ``__init__``
and adds the clock and the I/O (the link loop, the periodic heartbeat and status line, the
summary)."""

from __future__ import annotations

import dataclasses
import math
import time
from collections import Counter, deque
from typing import Any, Callable

import numpy as np

from quadformer.detectors.attack_types import ShapeTyper
from quadformer.estimator.feed import GapError
from quadformer.estimator.latency import LatencyEstimator
from quadformer.estimator.online import FilterConfig
from quadformer.live.actions import Records, VehicleLink, autopilot_name
from quadformer.live.alerts import Alerting
from quadformer.live.config import FixRecord, MonitorConfig
from quadformer.live.flight_state import FlightState
from quadformer.live.intake import Intake
from quadformer.live.packets import header
from quadformer.live.segment import Segment
from quadformer.live.status import STATES, Latency
from quadformer.live.vehicle import Vehicle
from quadformer.resilience.admission import EXCLUDED, FUSING
from quadformer.sensors.receiver_epochs import ReceiverEpochs
from quadformer.sensors.mavlink import GPS_MESSAGES, RATIO_MESSAGES, Estimate, Origin, decode, estimator_ratios, gps_status

__all__ = ["EVENT_MESSAGES", "Pipeline"]

EVENT_MESSAGES = ("EXTENDED_SYS_STATE", "STATUSTEXT")    # the vehicle's messages read for events only
LATENCY_EVERY = 25        # GPS intervals in the air between two tries at the receiver's latency


class Pipeline:
    """One message, its samples and rows, and the segments, over the state ``Monitor`` sets up;
    ``_note(line)`` (the monitor's notes and console) is the subclass's."""

    detector: Any
    config: MonitorConfig
    filter_config: FilterConfig
    sensors: str
    typer: ShapeTyper | None
    on_fix: Callable[[FixRecord], None] | None
    link: VehicleLink | None
    records: Records | None
    intake: Intake
    followed: Vehicle
    flight: FlightState
    alerting: Alerting
    latency: Latency
    segment: Segment | None
    n_segments: int
    segments: deque[dict]
    messages: Counter
    dropped: Counter
    errors: int
    last_error: str
    fixes: int
    n_messages: int
    _rates_requested: bool
    vehicle: int | None
    autopilot: str | None
    receiver_latency: LatencyEstimator | None
    receiver_epochs: ReceiverEpochs
    latency_source: str
    _latency_tried: int

    def _note(self, line: str) -> None:
        raise NotImplementedError

    # -- one message --------------------------------------------------------------------
    def process(self, msg) -> None:
        """Handle one pymavlink message. Never raises for what a link can carry: problems are
        counted (``summary()``) and, inside the filter, start a new segment."""
        t_in = time.perf_counter()
        self.n_messages += 1
        kind = msg.get_type()
        self.messages[kind] += 1
        if kind == "BAD_DATA":
            return
        try:
            src, seq, checked = header(msg)
            if src == (self.config.source_system, self.config.source_component):
                return
            samples = decode(msg)
            self.intake.packet(src, seq, samples, checked)
            if kind == "TIMESYNC":
                if msg.tc1 == 0 and self.link is not None:
                    self.link.timesync_reply(msg.ts1)
                return
            if kind == "HEARTBEAT":
                self._heartbeat(msg, src)
                self._vehicle_message(msg, src)
                return
            if kind in EVENT_MESSAGES:
                self._vehicle_message(msg, src)
                return
            if kind in RATIO_MESSAGES:
                self._ratios(msg, src)
                return
            if kind == "COMMAND_ACK":
                if self.vehicle is None or src[0] == self.vehicle:
                    line = self.link.on_ack(msg) if self.link is not None else None
                    if line:
                        self._note(line)
                return
            if not samples and kind not in GPS_MESSAGES:
                return
            first = self.vehicle is None
            if not self.followed.follows(src, "the first to send sensor data"):
                self.dropped["other_system"] += 1
                return
            if first and self.link is not None:
                self.link.target = src
            for s in samples:
                self._sample(s, kind, t_in)
            if kind in GPS_MESSAGES:
                self._receiver(msg)
        except Exception as e:          # noqa: BLE001 - the loop must outlive any one message
            self._error(e)

    def _error(self, e: Exception) -> None:
        self.errors += 1
        self.last_error = f"{type(e).__name__}: {e}"
        self._note(f"error: {self.last_error}; new segment")
        if self.segment is not None:
            self._new_segment(f"after an error ({self.last_error})")

    def _heartbeat(self, msg, src) -> None:
        if self.followed.heartbeat(msg, src) and self.link is not None:
            self.link.target = src
            self.followed.autopilot = autopilot_name(msg.autopilot)
            if self.config.request_rates and not self._rates_requested:
                self._rates_requested = True
                self._note("requested streams: " + ", ".join(self.link.request_rates(self.autopilot)))

    def _vehicle_message(self, msg, src) -> None:
        """A HEARTBEAT, EXTENDED_SYS_STATE or STATUSTEXT: the followed vehicle's events, at the
        link's latest t."""
        if self.vehicle is not None and src[0] == self.vehicle:
            now = self.intake.now_t
            self.flight.message(now if math.isfinite(now) else 0.0, msg)
            self._advance()

    def _ratios(self, msg, src) -> None:
        """An EKF_STATUS_REPORT or ESTIMATOR_STATUS of the followed vehicle: the autopilot's own
        test ratios, recorded (``FlightState.ratios``, ``autopilot_ratios.csv``) at their stamp on
        the link's time base, or, untimed (EKF_STATUS_REPORT), at the link's latest t; not scored."""
        if self.vehicle is None or src[0] != self.vehicle:
            self.dropped["ratios_before_vehicle" if self.vehicle is None else "ratios_other_system"] += 1
            return
        ratios = estimator_ratios(msg)
        t = self.intake.link_time(ratios.t) if math.isfinite(ratios.t) else None
        if t is None:
            now = self.intake.now_t
            t = now if math.isfinite(now) else 0.0
        self.flight.ratios(t, ratios)
        if self.records is not None:
            self.records.ratios(t, ratios)

    def _receiver(self, msg) -> None:
        """A GPS message: the status report of the receiver in use (receiver 0 until one is)."""
        status = gps_status(msg)
        if status.instance != (self.intake.gps_instance or 0):
            return
        t = self.intake.link_time(status.t)
        if t is None:
            self.dropped["receiver_report_untimed"] += 1
            return
        self.flight.report(t, status)
        self._advance()

    def _advance(self) -> None:
        """Feed the segment's step the flight inputs before the watermark (``FlightState``)."""
        seg = self.segment
        if seg is None:
            self.flight.trim()
            return
        until = self.flight.watermark(self.intake.now_t, seg.stream.waiting)
        self._labelled(seg, self.flight.feed(seg.step, until, inclusive=False))

    def _labelled(self, seg: Segment, events: list) -> None:
        """The alert events of the receiver's degraded episodes and of the alerts a landing
        relabels, between fixes."""
        if events:
            self.alerting.events(events, seg.index, seg.last_score, seg.state)

    def _sample(self, s, kind: str, t_in: float) -> None:
        if isinstance(s, Origin):
            self.followed.set_origin(s)
            return
        if isinstance(s, Estimate):
            if self.intake.boot_time(s.t) is not None:
                self.followed.estimate(s)
            return
        got = self.intake.accept(s, kind, may_switch=self.fixes == 0)
        if got is None:
            return
        if got.restart is not None:
            self._new_segment(got.restart)
        if self.segment is None:
            self._new_segment("start")
        seg, stream, t = self.segment, got.stream, got.t
        if stream in ("baro", "gps"):
            self.flight.height(t, s.alt, stream)
            self._advance()
        if self.receiver_latency is not None:
            if stream == "attitude":
                self.receiver_latency.attitude(t, s.q)
            elif stream == "imu":
                self.receiver_latency.imu(t, s.x[:3])
        if stream == "imu":
            self.flight.imu(t, s.x)          # an impact is queued, fed in time order with the rows
            self._imu(seg, t, s.x, t_in)
        elif stream != "attitude" and not seg.fusable(stream, t):
            self.dropped[f"{stream}_without_imu"] += 1       # could never be fused; would only queue
        elif stream == "gps":
            # fused at the receiver's epoch found from the stamps, the IMU held back for the late reads
            t_fix = self.receiver_epochs.epoch(t)
            seg.stream.hold_s = self.receiver_epochs.allowance
            seg.feed(stream, t_fix, s, self.followed.enu(s))
        else:
            seg.feed(stream, t, s, None)

    def _imu(self, seg: Segment, t: float, x: np.ndarray, t_in: float) -> None:
        try:
            rows = seg.imu(t, x)
        except GapError as e:              # "imu: gap of X s before t = Y s (more than Z s); ..."
            rows = self._new_segment("IMU " + str(e).split(";")[0].removeprefix("imu: ")).imu(t, x)
        if rows:
            self._rows(rows, t_in)

    # -- rows: score, decide, act ----------------------------------------------------------
    def _rows(self, rows: list[dict], t_in: float) -> None:
        seg = self.segment
        for row in rows:
            t = float(row["t"])
            self._labelled(seg, self.flight.feed(seg.step, t))
            before = seg.state
            try:
                out = seg.score(t, row)
            except ValueError as e:          # non-finite residues: not scored
                self.dropped["rows_not_scored"] += 1
                self.last_error = str(e)
                continue
            dec, after = out.decision, seg.state
            score, alarm = seg.last_score, bool(out.alarm[0])
            kind = out.attack_type[0] if out.attack_type is not None else None
            latency = time.perf_counter() - t_in
            self.latency.add(latency)
            self.fixes += 1
            self.alerting.events(out.events, seg.index, score, after,
                                 exclusion=after == EXCLUDED and before != EXCLUDED)
            self._admission(t, before, after, int(dec.readmit[0]), int(dec.exclude[0]), float(dec.held[0]))
            cols = {c: float(v[0]) for c, v in out.columns.items()}
            phase = self.flight.phase.update(t)
            rec = FixRecord(seg.index, t, score, alarm, kind, STATES[after], phase, float(dec.std_scale[0]),
                            cols["res_gps_nis"], row["gps_pos"][0].copy(), row["est_pos"][0].copy(),
                            self.followed.position.copy(), latency, cols)
            if self.records is not None:
                self.records.fix((seg.index, t, score, int(alarm), kind or "", STATES[after], phase, rec.nis,
                                  *map(float, rec.gps_pos), *map(float, rec.est_pos), *map(float, rec.ap_pos),
                                  latency * 1e3))
            if self.on_fix is not None:
                self.on_fix(rec)
            if self.receiver_latency is not None:
                self.receiver_latency.fix(t, row["gps_vel"][0], phase == "air")
        self._latency_check()

    def _latency_check(self) -> None:
        """Once the link's IMU and fixes in the air show the receiver's latency
        (``estimator.latency.LatencyEstimator``, every ``LATENCY_EVERY`` intervals from its
        ``min_intervals``), the filter fuses each fix that long before its stamp from a new segment
        on (its detector goes on from the scales it had calibrated and calibrates itself afresh on
        the sharper residues); once per monitor."""
        est = self.receiver_latency
        if est is None or est.taken % LATENCY_EVERY or est.taken == self._latency_tried:
            return
        self._latency_tried, n = est.taken, est.intervals
        found = est.estimate()
        if found is None:
            return
        self.receiver_latency = None
        self.filter_config = dataclasses.replace(self.filter_config, gps_delay_s=found)
        self.latency_source = (f"estimated from the link's IMU and GPS over {n} intervals in the air "
                               "(estimator.latency)")
        self._note(f"gps: receiver latency {found * 1e3:.0f} ms {self.latency_source}; each fix fused that "
                   "long before its stamp from the next segment on")
        self._new_segment(f"receiver latency {found * 1e3:.0f} ms", resume=True)

    def _admission(self, t: float, before: int, after: int, readmit: int = 0, exclude: int = 0,
                   held: float | None = None) -> None:
        """The admission messages and actions of one fix (``Alerting.admission``)."""
        self.alerting.admission(t, before, after, readmit, exclude, held)

    # -- segments ---------------------------------------------------------------------------
    def _end_segment(self, why: str) -> None:
        seg = self.segment
        if seg is None:
            return
        self._labelled(seg, self.flight.feed(seg.step, math.inf))
        self.alerting.events(seg.step.finish(), seg.index, seg.last_score, seg.state)
        self.segments.append(seg.describe(why))

    def _new_segment(self, reason: str, resume: bool = False) -> Segment:
        """End the segment (if any) and start the next, for ``reason``; ``resume``: the same
        flight goes on (the filter restarts, not the vehicle): the detector's calibration too."""
        excluded = False
        before = self.segment
        if self.segment is not None:
            self._end_segment(reason)
            excluded = self.segment.state != FUSING
            self._note(f"segment {self.n_segments}: {reason}")
        self.segment = Segment(self.n_segments, reason, self.detector, self.filter_config, self.sensors,
                               self.config.admission, self.typer, excluded, phase=self.flight.phase,
                               resume=before if resume else None)
        self.n_segments += 1
        return self.segment
