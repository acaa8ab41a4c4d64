"""The live monitor: a vehicle's MAVLink stream in, GPS spoofing alarms and GPS admission out.

It is ``quadformer detect`` fed one message at a time. Per message: ``mavlink.decode`` ->
the calls of ``estimator.online.ResidueStream`` (attitude, imu, gps, mag, baro, vio) -> each
residue row (one per fused GPS fix) -> ``detector.stream(1).update(row)`` -> the alarm ->
``resilience.Admission(["resilient"])`` -> actions (console, ``alerts.jsonl``, STATUSTEXT,
and with ``act`` the EKF source set switch). Causal throughout; the only state is the
residue stream's, the detector stream's (a recursion or ring buffers), the admission's,
fixed-size counters, a fixed-size latency histogram and the last fixes the attack typer
reads (``detectors.attack_types``; ``typing="shape"``: an alert's type is the shape fitted at
its first fix, confirmed ``confirm_s`` (5 s) later in an ``alert_type`` event): memory does not
grow with time.

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
ODOMETRY. The link intake (``live.intake``, ``live.packets``) turns messages into samples:
each UDP datagram parsed on its own, one source per sensor, the samples in order and on one
time base, ``t`` in seconds since the link's first sensor sample (as ``detect`` counts from its
log's start) with the vehicle's boot time ``boot_t`` beside it in the events, ``fixes.csv``, the
status line and the summary; each stream's rate measured, with a warning for one slower than
the filter needs (``actions.MIN_RATES``). Robustness, each counted, never an exception out of
the loop:

- a bad CRC or junk (corrupt bytes): pymavlink's ``BAD_DATA``, discarded, costing its own
  datagram only; lost, duplicate and reordered packets: MAVLink sequence numbers per sender,
  read together with time (an outage longer than the 8-bit sequence is counted whole);
- a sample stamped as the previous one of its stream (duplicate) or earlier (late, reordered):
  dropped;
- a stream whose clock goes back by more than ``restart_s`` for ``restart_confirm`` samples in
  a row (a reboot, a restarted log): a new segment (new residue stream, new detector stream;
  GPS stays excluded across it until re-admitted by the rule);
- an IMU gap longer than the filter's ``max_gap_s`` (``GapError``): a new segment;
- a stream that stops: "no GPS for N s" / "no IMU for N s" on the status line, and the state
  is "stale" while the IMU or GPS has been silent longer than ``stale_s`` (the admission state
  again once they flow); no rows without IMU; GPS and aiding samples more than ``max_gap_s``
  after the last IMU sample are dropped (they could never be fused and would only queue).
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

import numpy as np

from quadformer.config import SENSOR_NAMES
from quadformer.detectors.alarms import Alert
from quadformer.detectors.attack_types import TYPINGS, OnlineTyper, ShapeTyper
from quadformer.estimator.online import FilterConfig, GapError, ResidueStream
from quadformer.estimator.schema import GROUPS, SENSOR_GROUPS
from quadformer.geometry.frames import geodetic_to_enu
from quadformer.io import package_versions, write_json
from quadformer.live.actions import Records, VehicleLink, autopilot_name
from quadformer.live.intake import STREAMS, Intake
from quadformer.live.mavlink import Estimate, Gps, Origin, decode, local_address, mavlink2, open_link
from quadformer.resilience.admission import (
    BLENDING,
    EXCLUDE_NIS,
    EXCLUDED,
    FUSING,
    READMIT_STALE,
    Admission,
    AdmissionConfig,
)
from quadformer.resilience.step import OnlineStep

STATES = {FUSING: "fusing", EXCLUDED: "GPS excluded", BLENDING: "re-admitting GPS"}
STALE = "stale"                   # the state while the IMU or GPS the filter needs is silent
MAX_ALERTS = 1000                 # alerts kept in memory (all are in alerts.jsonl)
MAX_SEGMENTS = 100                # segment descriptions kept in memory


@dataclass(frozen=True)
class MonitorConfig:
    """How the monitor listens, decides and acts. Times in seconds."""
    connect: str                                   # any pymavlink connection string
    filter: FilterConfig = field(default_factory=FilterConfig)
    admission: AdmissionConfig = field(default_factory=AdmissionConfig)
    gps_instance: int | None = None                # receiver: 0 GPS_RAW_INT, 1 GPS2_RAW; None: first with a 3D fix
    system: int | None = None                      # vehicle system id; None: the first that sends sensor data
    act: bool = False                              # switch the vehicle's EKF source set on exclusion/re-admission
    act_source_set: int = 2                        # the vehicle's non-GPS source set (1..3)
    statustext: bool = True                        # send STATUSTEXT alerts to the vehicle
    request_rates: bool = False                    # ask the vehicle for the streams it needs (SET_MESSAGE_INTERVAL)
    out: Path | None = None                        # directory for alerts.jsonl, fixes.csv, summary.json
    duration_s: float | None = None                # stop after this long (wall clock)
    max_messages: int | None = None                # stop after this many messages
    status_s: float = 1.0                          # status line period (wall clock)
    stale_s: float = 1.0                           # a stream silent this long is reported stopped
    restart_s: float = 1.0                         # clock going back this far is a restart
    restart_confirm: int = 3                       # samples in a row that confirm a restart
    recv_timeout_s: float = 0.1                    # longest wait for one message
    heartbeat_s: float = 1.0                       # own HEARTBEAT period (routers forward to known peers)
    source_system: int = 255                       # this monitor's MAVLink identity
    source_component: int = 191                    # MAV_COMP_ID_ONBOARD_COMPUTER
    typing: str = "shape"                          # alert types: attack_types.TYPINGS

    def __post_init__(self) -> None:
        if not isinstance(self.connect, str) or not self.connect:
            raise ValueError("monitor.connect: a pymavlink connection string, e.g. udpin:127.0.0.1:14550")
        if self.gps_instance not in (None, 0, 1):
            raise ValueError(f"monitor.gps_instance must be 0 (GPS_RAW_INT) or 1 (GPS2_RAW), got {self.gps_instance!r}")
        if self.act_source_set not in (1, 2, 3):
            raise ValueError(f"monitor.act_source_set must be 1, 2 or 3, got {self.act_source_set!r}")
        for name in ("status_s", "stale_s", "restart_s", "recv_timeout_s", "heartbeat_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"monitor.{name} must be a positive number of seconds, got {v!r}")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ValueError(f"monitor.duration_s must be > 0, got {self.duration_s!r}")
        if self.max_messages is not None and not self.max_messages >= 1:
            raise ValueError(f"monitor.max_messages must be >= 1, got {self.max_messages!r}")
        if self.typing not in TYPINGS:
            raise ValueError(f"monitor.typing: unknown {self.typing!r}; choose from {', '.join(TYPINGS)}")
        if not (isinstance(self.restart_confirm, int) and self.restart_confirm >= 1):
            raise ValueError(f"monitor.restart_confirm must be an integer >= 1, got {self.restart_confirm!r}")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["out"] = None if self.out is None else str(self.out)
        return d


@dataclass(frozen=True)
class FixRecord:
    """One scored GPS fix, handed to ``on_fix`` (the monitor keeps none)."""
    segment: int
    t: float                       # s since the link's first sensor sample (the monitor's time base)
    score: float
    alarm: bool
    attack_type: str | None
    admission: str                 # state after this fix's decision
    std_scale: float               # GPS noise factor the admission asks for (blend)
    nis: float
    gps_pos: np.ndarray            # ENU m about the origin
    est_pos: np.ndarray
    ap_pos: np.ndarray             # the autopilot's own estimate (NaN when not received)
    latency_s: float               # from the message in hand to the admission decision
    columns: dict[str, float]      # the residue row as scored


def monitor_sensors(detector, config: FilterConfig) -> str:
    """The sensors the monitor's filter fuses: ``config.sensors``, else those of the data the
    detector was fit on, else GPS, IMU and the aiding sensors whose residues it reads. Raises
    ValueError when the detector reads residues that configuration cannot produce."""
    sensors = config.sensors
    if sensors is None:
        sim = (getattr(detector, "calibration_", None) or {}).get("sim_config") or {}
        sensors = sim.get("sensors")
    if sensors is None:
        feats = set(detector.features_)
        need = {s for s, groups in SENSOR_GROUPS.items() if any(c in feats for g in groups for c in GROUPS[g].columns)}
        sensors = "+".join(s for s in SENSOR_NAMES if s in {"gps", "imu"} | need)
    parts = set(sensors.split("+"))
    if not {"gps", "imu"} <= parts or parts - set(SENSOR_NAMES):
        raise ValueError(f"sensors: {sensors!r} must join gps, imu and any of vio, mag, baro with '+'")
    sensors = "+".join(s for s in SENSOR_NAMES if s in parts)
    absent = {g for s, groups in SENSOR_GROUPS.items() if s not in parts for g in groups}
    have = {c for g in GROUPS.values() if g.name not in absent for c in g.columns}
    lacking = [c for c in detector.features_ if c not in have]
    if lacking:
        raise ValueError(f"detector {detector.name} reads {', '.join(lacking[:4])}, which a filter fusing {sensors} "
                         f"does not produce; choose --sensors with the sensors it was fit with")
    return sensors


class _Latency:
    """Fixed-size log-spaced histogram (1 us to 10 s, about 2.3% per bin): percentiles over a
    whole run without keeping the samples."""

    LO, PER_DECADE, DECADES = -6.0, 100, 7

    def __init__(self):
        self.counts = np.zeros(self.PER_DECADE * self.DECADES + 1, dtype=np.int64)
        self.n, self.max = 0, 0.0

    def add(self, seconds: float) -> None:
        i = int((math.log10(max(seconds, 1e-6)) - self.LO) * self.PER_DECADE)
        self.counts[min(max(i, 0), len(self.counts) - 1)] += 1
        self.n += 1
        self.max = max(self.max, seconds)

    def quantile(self, q: float) -> float:
        if self.n == 0:
            return math.nan
        i = int(np.searchsorted(np.cumsum(self.counts), q * self.n))
        return 10 ** (self.LO + (i + 0.5) / self.PER_DECADE)


class _Segment:
    """One continuous stretch of the vehicle's clock: the residue stream and the online step
    (detector stream, admission, alert lifecycle and typer)."""

    def __init__(self, index: int, monitor: "Monitor", reason: str, excluded: bool):
        self.index, self.reason = index, reason
        self.stream = ResidueStream(monitor.filter_config, monitor.sensors, n=1)
        admission = Admission(["resilient"], monitor.filter_config.gps_rate_hz, monitor.config.admission)
        if excluded:           # the vehicle is still off GPS: re-admission follows the rule
            admission.state[:] = EXCLUDED
        typer = None if monitor.typer is None else OnlineTyper(monitor.typer, monitor.filter_config.gps_rate_hz)
        self.step = OnlineStep(monitor.detector.stream(1), admission, flight_ids=[index], typer=typer,
                               keep=MAX_ALERTS)
        self.first_imu: float | None = None
        self.last_imu: float | None = None
        self.fixes = 0
        self.last_score = math.nan

    @property
    def state(self) -> int:
        return int(self.step.admission.state[0])


class Monitor:
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
        self.sensors = monitor_sensors(detector, config.filter)
        self.on_fix, self.on_alert = on_fix, on_alert
        self.echo = echo or (lambda line: None)
        self.clock = clock
        # alert types: the shape typer over the last fixes (``OnlineTyper``)
        self.typer = ShapeTyper() if config.typing == "shape" else None
        self.conn = None
        self.link: VehicleLink | None = None
        self.records: Records | None = None
        self._stop = threading.Event()
        # state
        self.segment: _Segment | None = None
        self.n_segments = 0
        self.segments: deque[dict] = deque(maxlen=MAX_SEGMENTS)
        self.notes: deque[str] = deque(maxlen=50)
        # the link intake: sources, order, time base, activity, rates, packet accounting
        self.intake = Intake(self.sensors, stale_s=config.stale_s, restart_s=config.restart_s,
                             restart_confirm=config.restart_confirm, gps_instance=config.gps_instance,
                             note=self._note, clock=clock)
        self.origin: tuple[float, float, float] | None = None
        self.origin_source = "none"
        self.vehicle: int | None = config.system
        self.autopilot = "unknown"
        self.ap_pos = np.full(3, np.nan)
        self.alerts: deque[Alert] = deque(maxlen=MAX_ALERTS)
        self.n_alerts = 0
        self.latency = _Latency()
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
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            if src == (self.config.source_system, self.config.source_component):
                return
            samples = decode(msg)
            self.intake.packet(src, msg.get_seq(), samples)
            if kind == "TIMESYNC":
                if msg.tc1 == 0 and self.link is not None:
                    self.link.timesync_reply(msg.ts1)
                return
            if kind == "HEARTBEAT":
                self._heartbeat(msg, src)
                return
            if kind == "COMMAND_ACK":
                if self.vehicle is None or src[0] == self.vehicle:
                    line = self.link.on_ack(msg) if self.link is not None else None
                    if line:
                        self._note(line)
                return
            if not samples:
                return
            if self.vehicle is None:
                self.vehicle = src[0]
                if self.link is not None:
                    self.link.target = src
                self._note(f"vehicle: following system {src[0]} (the first to send sensor data)")
            elif src[0] != self.vehicle:
                self.dropped["other_system"] += 1
                return
            for s in samples:
                self._sample(s, kind, t_in)
        except Exception as e:          # noqa: BLE001 - the loop must outlive any one message
            self._error(e)

    def _error(self, e: Exception) -> None:
        self.errors += 1
        self.last_error = f"{type(e).__name__}: {e}"
        self._note(f"error: {self.last_error}; new segment")
        if self.segment is not None:
            self._new_segment(f"after an error ({self.last_error})")

    def _heartbeat(self, msg, src) -> None:
        if msg.autopilot == mavlink2.MAV_AUTOPILOT_INVALID or msg.type in (
                mavlink2.MAV_TYPE_GCS, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_TYPE_GIMBAL):
            return
        if self.vehicle is None:
            self.vehicle = src[0]
            self._note(f"vehicle: following system {src[0]} (the first vehicle heartbeat)")
        if src[0] == self.vehicle and self.link is not None:
            self.link.target = src
            self.autopilot = autopilot_name(msg.autopilot)
            if self.config.request_rates and not self._rates_requested:
                self._rates_requested = True
                self._note("requested streams: " + ", ".join(self.link.request_rates(self.autopilot)))

    def _sample(self, s, kind: str, t_in: float) -> None:
        if isinstance(s, Origin):
            if self.origin is None:
                self.origin, self.origin_source = (s.lat, s.lon, s.alt), s.source
                self._note(f"origin: {s.lat:.7f}, {s.lon:.7f}, {s.alt:.1f} m from {s.source}")
            return
        if isinstance(s, Estimate):
            if self.intake.boot_time(s.t) is None:
                return
            if s.kind == "global" and self.origin is not None:
                self.ap_pos = geodetic_to_enu(*s.pos, self.origin)
            elif s.kind == "local" and self.origin_source == "GPS_GLOBAL_ORIGIN":
                self.ap_pos = s.pos            # the autopilot's local frame is about the same origin
            return
        got = self.intake.accept(s, kind, may_switch=self.fixes == 0)
        if got is None:
            return
        if got.restart is not None:
            self._new_segment(got.restart)
        if self.segment is None:
            self._new_segment("start")
        seg, stream, t = self.segment, got.stream, got.t
        if stream == "imu":
            self._imu(seg, t, s.x, t_in)
            return
        if stream == "attitude":
            seg.stream.attitude(t, s.q)
            return
        if (stream == "gps" or seg.stream.filter is not None) and (
                seg.last_imu is None or t - seg.last_imu > self.filter_config.max_gap_s):
            self.dropped[f"{stream}_without_imu"] += 1       # could never be fused; would only queue
            return
        if stream == "gps":
            self._gps(seg, t, s)
        elif stream == "mag":
            seg.stream.mag(t, s.field)
        elif stream == "baro":
            seg.stream.baro(t, s.alt)
        else:
            seg.stream.vio(t, np.concatenate([s.vel, s.q]))

    def _imu(self, seg: _Segment, t: float, x: np.ndarray, t_in: float) -> None:
        if seg.first_imu is None:
            seg.first_imu = t
        try:
            rows = seg.stream.imu(t, x)
        except GapError as e:              # "imu: gap of X s before t = Y s (more than Z s); ..."
            seg = self._new_segment("IMU " + str(e).split(";")[0].removeprefix("imu: "))
            seg.first_imu = t
            rows = seg.stream.imu(t, x)
        seg.last_imu = t
        if rows:
            self._rows(rows, t_in)

    def _gps(self, seg: _Segment, t: float, s: Gps) -> None:
        if self.origin is None:
            self.origin, self.origin_source = (s.lat, s.lon, s.alt), "first fix"
            self._note(f"origin: {s.lat:.7f}, {s.lon:.7f}, {s.alt:.1f} m (the first fix)")
        pos = geodetic_to_enu(s.lat, s.lon, s.alt, self.origin)
        seg.stream.gps(t, pos, s.vel, s.eph, s.epv, s.speed_acc)

    # -- rows: score, decide, act ----------------------------------------------------------
    def _rows(self, rows: list[dict], t_in: float) -> None:
        seg = self.segment
        for row in rows:
            t = float(row["t"])
            before = seg.state
            try:
                out = seg.step.update(t, row)
            except ValueError as e:          # non-finite residues: not scored
                self.dropped["rows_not_scored"] += 1
                self.last_error = str(e)
                continue
            dec, after = out.decision, seg.state
            score, alarm = float(out.score[0]), bool(out.alarm[0])
            kind = out.attack_type[0] if out.attack_type is not None else None
            latency = time.perf_counter() - t_in
            self.latency.add(latency)
            seg.fixes += 1
            self.fixes += 1
            seg.last_score = score
            self._events(seg, out.events, after, exclusion=after == EXCLUDED and before != EXCLUDED)
            self._admission(t, before, after, int(dec.readmit[0]), int(dec.exclude[0]))
            cols = {c: float(v[0]) for c, v in out.columns.items()}
            rec = FixRecord(seg.index, t, score, alarm, kind, STATES[after], float(dec.std_scale[0]),
                            cols["res_gps_nis"], row["gps_pos"][0].copy(), row["est_pos"][0].copy(),
                            self.ap_pos.copy(), latency, cols)
            if self.records is not None:
                self.records.fix((seg.index, t, score, int(alarm), kind or "", STATES[after], rec.nis,
                                  *map(float, rec.gps_pos), *map(float, rec.est_pos), *map(float, rec.ap_pos),
                                  latency * 1e3))
            if self.on_fix is not None:
                self.on_fix(rec)

    def _admission(self, t: float, before: int, after: int, readmit: int = 0, exclude: int = 0) -> None:
        """The admission messages and actions of one fix; ``readmit`` / ``exclude``: the rule
        that acted at this fix (``Decision.readmit`` / ``Decision.exclude``)."""
        c = self.config
        if after == EXCLUDED and before != EXCLUDED:
            if exclude == EXCLUDE_NIS:
                self.echo(f"[t {t:.1f} s] GPS excluded (fix outside the agreement gate under the standing alarm)")
                if self.link is not None:
                    self.link.statustext("GPS excluded: fix disagrees, alert standing", mavlink2.MAV_SEVERITY_ALERT)
            else:
                self.echo(f"[t {t:.1f} s] GPS excluded (detector alarm)")
            if c.act and self.link is not None:
                self.link.set_source(c.act_source_set)
                self.echo(f"[t {t:.1f} s] act: EKF source set {c.act_source_set} (non-GPS) requested")
        elif after == BLENDING and before == EXCLUDED:
            if readmit == READMIT_STALE:
                self.echo(f"[t {t:.1f} s] GPS re-admitted (agreeing for {c.admission.stale_hold_s:g} s "
                          "despite a standing alarm)")
                if self.link is not None:
                    self.link.statustext("GPS re-admitted: fixes agree, alert stale", mavlink2.MAV_SEVERITY_NOTICE)
            else:
                self.echo(f"[t {t:.1f} s] GPS re-admitted (clear and agreeing for {c.admission.hold_s:g} s)")
                if self.link is not None:
                    self.link.statustext("GPS re-admitted: spoof alert cleared", mavlink2.MAV_SEVERITY_NOTICE)
            if c.act and self.link is not None:
                self.link.set_source(1)
                self.echo(f"[t {t:.1f} s] act: EKF source set 1 (GPS) requested")

    def _events(self, seg: _Segment, events: list, state: int, exclusion: bool = False) -> None:
        """The online step's alert events: counted, kept, written, sent and echoed."""
        for ev in events:
            a = ev.alert
            now = datetime.now(timezone.utc)
            event = {"event": ev.event, "segment": seg.index, "vehicle_t": ev.t,
                     "wall_time": now.isoformat(timespec="milliseconds"), "unix_time": now.timestamp()}
            if ev.event == "alert_type":
                event.update(start_s=a.start_s, attack_type=a.confirmed_type, raised_as=ev.raised_as)
                self.alerts = deque((dataclasses.replace(b, confirmed_type=a.confirmed_type)
                                     if b.flight_id == a.flight_id and b.start_s == a.start_s else b
                                     for b in self.alerts), maxlen=MAX_ALERTS)
                kind, raised = a.confirmed_type, ev.raised_as
                self.echo(f"[t {ev.t:.1f} s] alert of t {a.start_s:.1f} s: type {kind}"
                          + (f" (raised as {raised})" if kind != raised else " confirmed"))
            else:
                score = a.score if ev.event == "alert_end" else float(seg.last_score)
                event.update(score=score, onset_s=a.onset_s, attack_type=a.attack_type, admission=STATES[state],
                             threshold=float(self.detector.threshold_))
                if ev.event == "alert_start":
                    self.n_alerts += 1
                    text = f"GPS SPOOF ALERT {a.attack_type} s={score:.3g}"
                    if exclusion:
                        text += " GPS excluded"
                    if self.link is not None:
                        self.link.statustext(text, mavlink2.MAV_SEVERITY_ALERT)
                else:
                    self.alerts.append(a)
                    event.update(start_s=a.start_s, peak_score=a.score)
                when = f"t {ev.t:.1f} s" if ev.t is not None else "end of segment"
                self.echo(f"[{when}] {'ALERT' if ev.event == 'alert_start' else 'alert ended'}: {a.attack_type}, "
                          f"score {score:.3g} (threshold {self.detector.threshold_:.3g}), segment {seg.index}, "
                          f"{STATES[state]}")
            if self.records is not None:
                self.records.alert(event)
            if self.on_alert is not None:
                self.on_alert(event)

    # -- segments ---------------------------------------------------------------------------
    def _end_segment(self, why: str) -> None:
        seg = self.segment
        if seg is None:
            return
        self._events(seg, seg.step.finish(), seg.state)
        self.segments.append({"segment": seg.index, "started": seg.reason, "ended": why, "fixes": seg.fixes,
                              "first_imu_t": seg.first_imu, "last_imu_t": seg.last_imu})

    def _new_segment(self, reason: str) -> _Segment:
        excluded = False
        if self.segment is not None:
            self._end_segment(reason)
            excluded = self.segment.state != FUSING
            self._note(f"segment {self.n_segments}: {reason}")
        self.segment = _Segment(self.n_segments, self, reason, excluded)
        self.n_segments += 1
        return self.segment

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
        seg = self.segment
        if "imu" not in self.intake.last_t:
            return "waiting for IMU"
        if self.intake.silent():
            return STALE
        if seg is None or seg.fixes == 0:
            return "waiting for fix"
        return STATES[seg.state]

    def status_line(self, elapsed: float = 1.0) -> str:
        intake = self.intake
        rates = " ".join(f"{s} {intake.window[s] / max(elapsed, 1e-9):.0f}" for s in STREAMS if s in intake.last_t)
        seg = self.segment
        score = f"{seg.last_score:.3g}" if seg is not None and math.isfinite(seg.last_score) else "-"
        now = f"t {intake.now_t:.1f} s (boot {intake.time.boot(intake.now_t):.1f} s)" \
            if math.isfinite(intake.now_t) else "t -"
        parts = [now, f"seg {seg.index if seg else '-'}", f"{rates or 'no samples'} /s", f"fixes {self.fixes}",
                 f"score {score} (thr {self.detector.threshold_:.3g})", self.state_text()]
        need = ["imu", "gps"] + [s for s in ("mag", "baro", "vio") if s in self.sensors.split("+")]
        for s in need:
            age = intake.stale(s)
            if age > self.config.stale_s:
                parts.append(f"no {s.upper()} for {age:.0f} s")
        packets = intake.packets
        late = sum(v for k, v in self.dropped.items() if k.endswith(("_late", "_duplicate")))
        parts.append(f"packets lost {packets['lost']} bad {self.messages['BAD_DATA']} dup {packets['duplicate']}")
        parts.append(f"samples late/dup {late}")
        return " | ".join(parts)

    def _note(self, line: str) -> None:
        self.notes.append(line)
        self.echo(line)

    # -- summary --------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        elapsed = self.clock() - self._started
        dropped = dict(sorted(self.dropped.items()))
        intake, packets = self.intake, self.intake.packets
        return {
            "stop_reason": self.stop_reason, "wall_s": elapsed,
            "config": self.config.to_dict(), "filter": dataclasses.asdict(self.filter_config),
            "sensors": self.sensors,
            "detector": {"name": self.detector.name, "model": self.model, "threshold": float(self.detector.threshold_),
                         "features": list(self.detector.features_)},
            "vehicle": {"system": self.vehicle, "autopilot": self.autopilot, "imu": intake.imu_source,
                        "baro": intake.baro_source, "gps_receiver": intake.gps_instance,
                        "origin": self.origin, "origin_source": self.origin_source},
            "state": self.state_text(),
            "time": {"t": "s since the link's first sensor sample", "boot_t": "s since the vehicle's boot",
                     **intake.summary()},
            "rates_hz": dict(intake.rates),
            "messages": dict(sorted(self.messages.items())), "n_messages": self.n_messages,
            "messages_per_s": self.n_messages / elapsed if elapsed > 0 else math.nan,
            "samples": dict(intake.samples), "fixes_scored": self.fixes, "alerts": self.n_alerts,
            "alert_list": [dataclasses.asdict(a) for a in self.alerts],
            "link": {"lost_packets": packets["lost"], "corrupt_packets": self.messages["BAD_DATA"],
                     "duplicate_packets": packets["duplicate"], "reordered_packets": packets["reordered"],
                     "datagrams": intake.reader.datagrams if intake.reader is not None else None,
                     "duplicates": sum(v for k, v in dropped.items() if k.endswith("_duplicate")),
                     "late": sum(v for k, v in dropped.items() if k.endswith("_late")),
                     "dropped": dropped, "stream_gaps": intake.gaps},
            "segments": self.n_segments, "segment_list": list(self.segments),
            "errors": self.errors, "last_error": self.last_error,
            "latency_ms": {"p50": self.latency.quantile(0.5) * 1e3, "p99": self.latency.quantile(0.99) * 1e3,
                           "max": self.latency.max * 1e3, "n": self.latency.n},
            "actions": dict(self.link.counts) if self.link is not None else {},
            "vehicle_source_set": self.link.source_set if self.link is not None else None,
            "notes": list(self.notes), "versions": package_versions(),
        }

    @staticmethod
    def summary_text(s: dict[str, Any]) -> str:
        link = s["link"]
        msgs = ", ".join(f"{k} {v}" for k, v in sorted(s["messages"].items(), key=lambda kv: -kv[1])[:12])
        return "\n".join([
            f"monitor stopped ({s['stop_reason']}) after {s['wall_s']:.1f} s: {s['n_messages']} messages "
            f"({s['messages_per_s']:.0f}/s)",
            f"  messages: {msgs or 'none'}",
            f"  fixes scored {s['fixes_scored']}, alerts {s['alerts']}, segments {s['segments']}, errors {s['errors']}",
            f"  state at the end: {s['state']}; t counts from the link's first sensor sample, at "
            + (f"{s['time']['first_sample_boot_s']:.3f} s after the vehicle's boot"
               if s["time"]["first_sample_boot_s"] is not None else "none received"),
            f"  link: packets lost {link['lost_packets']}, corrupt {link['corrupt_packets']}, "
            f"duplicate packets {link['duplicate_packets']}, reordered {link['reordered_packets']}; "
            f"samples duplicate {link['duplicates']}, late {link['late']}; other drops "
            + (", ".join(f"{k} {v}" for k, v in link["dropped"].items()
                         if not k.endswith(("_duplicate", "_late"))) or "none"),
            f"  latency per fix (message in hand to admission decision): p50 {s['latency_ms']['p50']:.2f} ms, "
            f"p99 {s['latency_ms']['p99']:.2f} ms",
        ])
