"""The live monitor: a vehicle's MAVLink stream in, GPS spoofing alarms and GPS admission out.

It is ``quadformer detect`` fed one message at a time. Per message: ``mavlink.decode`` -> the
link intake (``live.intake``) -> the calls of ``estimator.online.ResidueStream`` (attitude, imu,
gps, mag, baro, vio) -> each residue row (one per fused GPS fix) -> the online step of the
segment (``live.segment``; ``detector.stream(1).update(row)`` -> the alarm ->
``resilience.Admission(["resilient"])``) -> actions (``live.alerts``: console, ``alerts.jsonl``,
STATUSTEXT, and with ``act`` the EKF source set switch). Alerts say their kind and flight phase:
the vehicle's events (HEARTBEAT arming, EXTENDED_SYS_STATE take-off and landing, STATUSTEXT GPS
glitches and failsafes), every GPS status report (fix or not), a height (the barometer, else
the GPS altitude) and the impacts in the IMU (a landing's or a crash's) feed the segment's flight
phase and receiver health in time order (``live.flight_state``), as ``detect`` feeds a log's; a
landing relabels the alerts raised in the air before it (``alert_relabel``). Causal throughout; the only state is the
residue stream's, the detector stream's (a recursion or ring buffers), the admission's,
fixed-size counters, a fixed-size latency histogram (``live.status``) and the last fixes the
attack typer reads (``detectors.attack_types``; ``typing="shape"``: an alert's type is the shape
fitted at its first fix, confirmed ``confirm_s`` (5 s) later in an ``alert_type`` event): memory
does not grow with time. ``Monitor`` owns the clock and the I/O; its settings are ``live.config``,
the vehicle it follows and the local frame ``live.vehicle``.

The receiver's latency (each fix is measured before the autopilot reads it, and a filter that
fuses it at its stamp reads every change of acceleration x that latency as an innovation): the
filter configuration's (``--gps-delay``, a vehicle profile's), else estimated from the link's own
IMU, attitude and fixes in the air (``estimator.latency.LatencyEstimator``, as ``detect`` does
on a log); once found (150 GPS intervals in the air at the least, checked every
``pipeline.LATENCY_EVERY``), the segment ends and the next fuses each fix that long before its
stamp, its detector calibrating itself afresh (the summary's ``gps_delay``).

The monitor's own filter always fuses GPS (it is the filter of ``detect``, so that its scores
equal offline scoring of the same data); the admission decision is what the monitor asks of
the vehicle: exclude GPS at the alarm, re-admit it after the detector has been clear and the
fixes have agreed with the estimate (NIS inside the gate) for ``hold_s``, or, under an alarm
that stands without a new onset (a detector's memory of an attack that has ended), after the
fixes have agreed for ``stale_hold_s``; then blend (its noise inflation is reported; the
vehicle's own EKF does its blending). After a stale re-admission the standing alarm does not
exclude GPS again; a new alarm onset or a fix outside the gate under it does. The rules are
``resilience.admission``'s, and the console says which one acted.

What the vehicle must send (``actions.RATES``; ``request_rates`` asks with SET_MESSAGE_INTERVAL):
an IMU (HIGHRES_IMU, or RAW_IMU / SCALED_IMU*) at 50-100 Hz or more, GPS_RAW_INT (or GPS2_RAW)
at 5-10 Hz, ATTITUDE (for the start), and for the configured aiding sensors the magnetometer
(in the IMU message), the barometer (SCALED_PRESSURE or HIGHRES_IMU's pressure altitude) and
ODOMETRY; and, recorded beside the scores (``autopilot_ratios.csv``, the summary's
``flight.autopilot_ratios``), the autopilot's estimator status with its own innovation test
ratios, EKF_STATUS_REPORT (ArduPilot) or ESTIMATOR_STATUS (PX4), at 10 Hz. ``t`` counts seconds from the link's first sensor sample, with the vehicle's boot time
``boot_t`` beside it (``intake.TimeBase``). Robustness, each counted, never an exception out of
the loop: corrupt bytes and lost, duplicate or reordered packets (``live.packets``); duplicate
and late samples, streams slower than the filter needs (``live.intake``); a stream's clock going
back (``restart_s``, ``restart_confirm``), an IMU gap longer than the filter's ``max_gap_s``
(``GapError``) or an error: a new segment, GPS staying excluded across it until re-admitted by
the rule; a stream that stops: "no GPS for N s" / "no IMU for N s" on the status line, and the
state is "stale" while the IMU or GPS has been silent longer than ``stale_s``; no rows without
IMU, and GPS and aiding samples more than ``max_gap_s`` after the last IMU sample are dropped
(they could never be fused and would only queue).
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter, deque
from pathlib import Path
from typing import Any, Callable

from quadformer.detectors.attack_types import ShapeTyper
from quadformer.estimator.latency import LatencyEstimator
from quadformer.io import write_json
from quadformer.live import status
from quadformer.live.actions import Records, VehicleLink
from quadformer.live.alerts import Alerting
from quadformer.live.config import FixRecord, MonitorConfig, monitor_sensors
from quadformer.live.flight_state import FlightState
from quadformer.live.intake import Intake
from quadformer.sensors.mavlink_link import local_address, open_link
from quadformer.sensors.receiver_epochs import ReceiverEpochs
from quadformer.live.pipeline import EVENT_MESSAGES, Pipeline  # noqa: F401 - EVENT_MESSAGES: importable here as before
from quadformer.live.segment import Segment
from quadformer.live.status import STALE, STATES, Latency
from quadformer.live.vehicle import Vehicle

__all__ = ["STALE", "STATES", "FixRecord", "Monitor", "MonitorConfig", "monitor_sensors"]

MAX_SEGMENTS = 100                # segment descriptions kept in memory


class Monitor(Pipeline):
    """Listen to one vehicle on a MAVLink connection and watch its GPS.

    ``Monitor(detector, MonitorConfig(connect=...)).run()`` returns the summary when a bound
    (``duration_s``, ``max_messages``), ``stop()`` (from another thread) or Ctrl-C ends it.
    ``process(msg)`` handles one pymavlink message (what ``run`` does per message), so the
    monitor can also be driven without a socket. ``on_fix`` receives every scored fix,
    ``on_alert`` every alert start/end event, ``echo`` every console line (None: silent);
    ``clock`` (seconds, monotonic) times the link's silences, the status lines and the bounds."""

    def __init__(self, detector, config: MonitorConfig, *, on_fix: Callable[[FixRecord], None] | None = None,
                 on_alert: Callable[[dict], None] | None = None, echo: Callable[[str], None] | None = print,
                 model: str | None = None, clock: Callable[[], float] = time.monotonic):
        if getattr(detector, "threshold_", None) is None:
            raise ValueError(f"{detector.name}: no alarm threshold; use a model written by `quadformer fit`")
        self.detector, self.config, self.model = detector, config, model
        self.filter_config = config.filter
        # the receiver's latency: the filter configuration's, else estimated from the link in the air
        unknown = config.filter.gps_delay_s is None
        self.receiver_latency = LatencyEstimator() if unknown else None
        self.latency_source = ("not yet estimated (no latency: fixes fused at their epochs)" if unknown
                               else "the filter's setting")
        self._latency_tried = -1                     # the estimator's interval count at the last try
        self.receiver_epochs = ReceiverEpochs()      # the fixes' epochs from their stamps
        self.sensors = monitor_sensors(detector, config.filter)
        self.on_fix = on_fix
        self.echo = echo or (lambda line: None)
        self.clock = clock
        # alert types: the shape typer over the last fixes (``OnlineTyper``)
        self.typer = ShapeTyper() if config.typing == "shape" else None
        self.conn = None
        self.link: VehicleLink | None = None
        self.records: Records | None = None
        self._stop = threading.Event()
        # state
        self.segment: Segment | None = None
        self.n_segments = 0
        self.segments: deque[dict] = deque(maxlen=MAX_SEGMENTS)
        self.notes: deque[str] = deque(maxlen=50)
        # the link intake: sources, order, time base, activity, rates, packet accounting
        self.intake = Intake(self.sensors, stale_s=config.stale_s, restart_s=config.restart_s,
                             restart_confirm=config.restart_confirm, gps_instance=config.gps_instance,
                             note=self._note, clock=clock)
        # the vehicle followed, its autopilot, the local origin and the autopilot's own estimate
        self.followed = Vehicle(config.system, note=self._note)
        # its events, receiver reports and height: the flight phase and receiver health of the alerts
        self.flight = FlightState(stale_s=config.stale_s)
        # alert events and admission transitions: console, STATUSTEXT, alerts.jsonl, on_alert
        self.alerting = Alerting(detector, config, self.echo, on_alert)
        self.latency = Latency()
        # counters: fixed keys, or keyed by message type / stream (bounded sets)
        self.messages: Counter = Counter()
        self.dropped: Counter = self.intake.dropped  # samples and rows not used, by reason
        self.errors = 0
        self.last_error = ""
        self.fixes = 0
        self.n_messages = 0
        self._t_status = self._t_heartbeat = 0.0
        self._started = clock()
        self._rates_requested = False
        self.stop_reason = ""

    # -- life cycle ---------------------------------------------------------------------
    def open(self) -> "Monitor":
        """Open the connection (and the output files); idempotent."""
        if self.conn is None:
            c = self.config
            self.conn = open_link(c.connect, c.source_system, c.source_component)
            self.link = VehicleLink(self.conn, self.echo, statustext=c.statustext)
            if c.system is not None:
                self.link.target = (c.system, 1)          # the autopilot component, until its heartbeat
            self.records = Records(c.out, boot_time=self.intake.time.boot)
            self.alerting.attach(self.link, self.records)
            self.intake.attach(self.conn)
            self._started = self.clock()
            self.link.heartbeat()
            self._t_heartbeat = self._started
            addr = local_address(self.conn)
            self.echo(f"monitor: listening on {c.connect}" + (f" ({addr[0]}:{addr[1]})" if addr else "")
                      + f"; detector {self.detector.name} (threshold {self.detector.threshold_:.4g}), "
                        f"filter fuses {self.sensors}")
        return self

    @property
    def address(self) -> tuple[str, int] | None:
        """The (host, port) the connection is bound to (an ephemeral port of udpin:HOST:0)."""
        return local_address(self.conn) if self.conn is not None else None

    def stop(self) -> None:
        """Ask ``run`` to return (from any thread); it finishes the message in hand first."""
        self._stop.set()

    def run(self) -> dict[str, Any]:
        """Read and process messages until a bound, ``stop()`` or Ctrl-C; returns the summary."""
        self.open()
        c = self.config
        deadline = self._started + c.duration_s if c.duration_s is not None else math.inf
        reason = "stopped"
        try:
            while True:
                if self._stop.is_set():
                    break
                now = self.clock()
                if now >= deadline:
                    reason = "duration"
                    break
                if c.max_messages is not None and self.n_messages >= c.max_messages:
                    reason = "max-messages"
                    break
                self._tick(now)
                try:
                    msg = self.intake.recv(min(c.recv_timeout_s, max(deadline - now, 1e-3)))
                except (OSError, ValueError) as e:     # a serial device unplugged, a socket error: wait, retry
                    self.dropped["link_errors"] += 1
                    if self.dropped["link_errors"] in (1, 10, 100, 1000):
                        self._note(f"link: {type(e).__name__}: {e}")
                    time.sleep(c.recv_timeout_s)
                    continue
                if msg is not None:
                    self.process(msg)
        except KeyboardInterrupt:
            reason = "interrupted"
        return self.close(reason)

    def close(self, reason: str = "stopped") -> dict[str, Any]:
        """End the last segment (its last IMU bin), write summary.json, close the link."""
        if self.stop_reason:
            return self.summary()
        self.stop_reason = reason
        if self.segment is not None:
            try:
                self._rows(self.segment.stream.flush(), time.perf_counter())
            except Exception as e:      # noqa: BLE001 - a damaged last bin must not lose the summary
                self._error(e)
            self._end_segment("end of monitoring")
        summary = self.summary()
        if self.link is not None and self.link.source_set not in (None, 1):
            self.echo(f"WARNING: the vehicle was left on EKF source set {self.link.source_set} (GPS excluded); "
                      "switch back with MAV_CMD_SET_EKF_SOURCE_SET 1 when GPS is trustworthy")
        if self.records is not None:
            self.records.close()
            if self.config.out is not None:
                write_json(Path(self.config.out) / "summary.json", summary)
        if self.conn is not None:
            try:
                self.conn.close()
            except OSError:
                pass
        self.echo(self.summary_text(summary))
        return summary

    def __enter__(self) -> "Monitor":
        return self.open()

    def __exit__(self, *exc) -> None:
        if self.conn is not None and not self.stop_reason:
            self.close("stopped")

    # -- periodic: heartbeat, status, acks ---------------------------------------------------
    def _tick(self, now: float) -> None:
        if self.link is None:
            return
        if now - self._t_heartbeat >= self.config.heartbeat_s:
            self._t_heartbeat = now
            self.link.heartbeat()
        for line in self.link.expired():
            self._note(line)
        if now - self._t_status >= self.config.status_s:
            elapsed = now - self._t_status if self._t_status else now - self._started
            self._t_status = now
            self.echo(self.status_line(elapsed))
            self.intake.window.clear()

    def stale(self, stream: str) -> float:
        """Seconds since the stream's last sample (``Intake.stale``)."""
        return self.intake.stale(stream)

    def state_text(self) -> str:
        """waiting for IMU, stale (the IMU or GPS silent longer than ``stale_s``), waiting for
        fix, or the admission state."""
        return status.state_text(self.intake, self.segment)

    def status_line(self, elapsed: float = 1.0) -> str:
        """The status line, with the stream rates over the last ``elapsed`` s."""
        return status.status_line(self, elapsed)

    def _note(self, line: str) -> None:
        self.notes.append(line)
        self.echo(line)

    # -- summary --------------------------------------------------------------------------
    alerts = property(lambda self: self.alerting.alerts, doc="The ended alerts kept (all are in alerts.jsonl).")
    n_alerts = property(lambda self: self.alerting.n_alerts, doc="Alerts raised.")
    alert_counts = property(lambda self: {k: int(v) for k, v in self.alerting.counts.items()},
                            doc="Alerts raised, counted apart by kind and flight phase (detectors.alert_counts).")
    vehicle = property(lambda self: self.followed.system, doc="The followed vehicle's system id.")
    autopilot = property(lambda self: self.followed.autopilot)
    origin = property(lambda self: self.followed.origin, doc="(lat deg, lon deg, alt m) of the ENU frame.")
    origin_source = property(lambda self: self.followed.origin_source)
    ap_pos = property(lambda self: self.followed.position, doc="The autopilot's estimate, ENU m.")

    def summary(self) -> dict[str, Any]:
        """Counters, sources, time base, link accounting, segments, alerts and latency."""
        return status.summary(self, self.clock() - self._started)

    summary_text = staticmethod(status.summary_text)
