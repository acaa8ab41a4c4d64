"""What the live monitor does with its decisions: the vehicle side (STATUSTEXT, the EKF source
set switch, stream-rate requests, heartbeats, timesync replies) and the operator side
(console lines, ``alerts.jsonl``, ``fixes.csv``).

Vehicle actions are MAVLink messages sent back on the monitor's link; nothing is retried and
nothing blocks. STATUSTEXTs are rate-limited by a token bucket (a burst of 5, then one a
second) so that a flickering alarm cannot flood the link; suppressed ones are counted.

``--act`` switches the vehicle's position source with ``MAV_CMD_SET_EKF_SOURCE_SET``
(ArduPilot, COMMAND_LONG, param1 = source set 1..3): the configured non-GPS set when GPS is
excluded, set 1 when it is re-admitted. The vehicle must have that source set configured
(EK3_SRC2_* on ArduPilot, e.g. optical flow or external navigation); otherwise ArduPilot
switches to a set without a position source. A false alarm switches a flying vehicle's
navigation source.
"""

from __future__ import annotations

import csv
import json
import math
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, TextIO

from quadformer.io import json_default
from quadformer.sensors.mavlink import mavlink2

STATUSTEXT_MAX = 50            # characters of a STATUSTEXT (MAVLink's field)
MAV_CMD_SET_EKF_SOURCE_SET = mavlink2.MAV_CMD_SET_EKF_SOURCE_SET          # 42007
MAV_CMD_SET_MESSAGE_INTERVAL = mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL      # 511
ACK_TIMEOUT_S = 3.0            # s, a command unacknowledged this long is reported

#: stream rates (Hz) the monitor needs, per autopilot; what ``--request-rates`` asks for
#: (the estimator's status with its test ratios at the GPS rate, recorded beside the scores)
RATES = {
    "px4": {"HIGHRES_IMU": 100.0, "GPS_RAW_INT": 10.0, "ATTITUDE": 10.0, "ODOMETRY": 30.0,
            "GLOBAL_POSITION_INT": 5.0, "ESTIMATOR_STATUS": 10.0},
    "ardupilot": {"RAW_IMU": 100.0, "GPS_RAW_INT": 10.0, "ATTITUDE": 10.0, "SCALED_PRESSURE": 25.0,
                  "GLOBAL_POSITION_INT": 5.0, "EKF_STATUS_REPORT": 10.0},
}



def autopilot_name(code: int) -> str:
    return {mavlink2.MAV_AUTOPILOT_PX4: "px4", mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot"}.get(code, "other")


@dataclass
class _Pending:
    command: int
    param1: float
    sent: float                  # monotonic s


class VehicleLink:
    """MAVLink messages the monitor sends to the vehicle over its connection."""

    def __init__(self, conn, echo: Callable[[str], None], statustext: bool = True, burst: int = 5,
                 refill_s: float = 1.0):
        self.conn, self.echo, self.statustext_on = conn, echo, statustext
        self.burst, self.refill_s = burst, refill_s
        self.tokens, self.refilled = float(burst), time.monotonic()
        self.target = (1, 1)                      # vehicle (system, component)
        self.pending: dict[int, deque[_Pending]] = {}   # command id -> unacknowledged sends, oldest first
        self.counts = {"statustext_sent": 0, "statustext_suppressed": 0, "commands_sent": 0,
                       "commands_accepted": 0, "commands_refused": 0, "commands_unacknowledged": 0,
                       "send_errors": 0}
        self.source_set: int | None = None        # the EKF source set this monitor last commanded

    def _send(self, fn, *args) -> bool:
        try:
            fn(*args)
            return True
        except (OSError, ValueError, TypeError) as e:        # a closed or broken link: counted, never raised
            self.counts["send_errors"] += 1
            self.echo(f"link: could not send ({e})")
            return False

    def heartbeat(self) -> None:
        self._send(self.conn.mav.heartbeat_send, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
                   mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, mavlink2.MAV_STATE_ACTIVE)

    def timesync_reply(self, ts1: int) -> None:
        """Answer a TIMESYNC request (tc1 = 0) with this machine's clock (ns)."""
        self._send(self.conn.mav.timesync_send, time.monotonic_ns(), ts1)

    def statustext(self, text: str, severity: int = mavlink2.MAV_SEVERITY_ALERT) -> bool:
        if not self.statustext_on:
            return False
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.refilled) / self.refill_s)
        self.refilled = now
        if self.tokens < 1.0:
            self.counts["statustext_suppressed"] += 1
            return False
        self.tokens -= 1.0
        ok = self._send(self.conn.mav.statustext_send, severity, text[:STATUSTEXT_MAX].encode("ascii", "replace"))
        self.counts["statustext_sent"] += ok
        return ok

    def command(self, command: int, *params: float) -> None:
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        if self._send(self.conn.mav.command_long_send, self.target[0], self.target[1], command, 0, *p):
            self.counts["commands_sent"] += 1
            self.pending.setdefault(command, deque(maxlen=16)).append(_Pending(command, p[0], time.monotonic()))

    def set_source(self, source_set: int) -> None:
        """ArduPilot's MAV_CMD_SET_EKF_SOURCE_SET (param1: source set 1..3)."""
        self.command(MAV_CMD_SET_EKF_SOURCE_SET, source_set)
        self.source_set = source_set

    def request_rates(self, autopilot: str) -> list[str]:
        """SET_MESSAGE_INTERVAL for each message the monitor needs (``RATES``)."""
        asked = []
        for name, hz in RATES.get(autopilot, RATES["px4"]).items():
            self.command(MAV_CMD_SET_MESSAGE_INTERVAL, float(getattr(mavlink2, f"MAVLINK_MSG_ID_{name}")), 1e6 / hz)
            asked.append(f"{name} {hz:g} Hz")
        return asked

    def on_ack(self, msg) -> str | None:
        """A COMMAND_ACK from the vehicle: a line to report for the commands the monitor tracks."""
        queue = self.pending.get(msg.command)
        if not queue:
            return None
        p = queue.popleft()
        if msg.result == mavlink2.MAV_RESULT_ACCEPTED:
            self.counts["commands_accepted"] += 1
            return None
        self.counts["commands_refused"] += 1
        results = mavlink2.enums["MAV_RESULT"]
        name = results[msg.result].name if msg.result in results else msg.result
        return f"vehicle refused command {msg.command} (param1 {p.param1:g}): {name}"

    def expired(self) -> list[str]:
        now = time.monotonic()
        lines = []
        for cmd, queue in self.pending.items():
            while queue and now - queue[0].sent > ACK_TIMEOUT_S:
                p = queue.popleft()
                self.counts["commands_unacknowledged"] += 1
                lines.append(f"no acknowledgement of command {cmd} (param1 {p.param1:g}) after {ACK_TIMEOUT_S:g} s")
        return lines


class Records:
    """``alerts.jsonl`` (one object per alert event: start, end, confirmed type, relabelled
    phase), ``fixes.csv`` (one line per scored fix) and, once the vehicle sends them,
    ``autopilot_ratios.csv`` (one line per EKF_STATUS_REPORT or ESTIMATOR_STATUS: the square roots
    of the autopilot's test ratios) in the output directory, appended and flushed as they happen:
    nothing is kept in memory. ``summary.json`` is written atomically at the end by the monitor.

    Times are ``t``, seconds since the link's first sensor sample (as ``detect`` counts from its
    log's start), with ``boot_t``, the vehicle's time since boot, beside it: ``boot_time`` maps one to the
    other (a fix's ``t`` is its second value; an event's is ``vehicle_t``)."""

    FIX_COLUMNS = ("segment", "t", "boot_t", "score", "alarm", "attack_type", "admission", "phase", "nis", "gps_x",
                   "gps_y", "gps_z", "est_x", "est_y", "est_z", "ap_x", "ap_y", "ap_z", "latency_ms")
    RATIO_COLUMNS = ("t", "boot_t", "source", "vel", "pos_horiz", "pos_vert", "mag", "terrain", "airspeed", "flags",
                     "gps_glitch", "pos_horiz_accuracy", "pos_vert_accuracy")

    def __init__(self, out: Path | None, boot_time: Callable[[float | None], float | None] = lambda t: None):
        self.boot_time = boot_time
        self.out = Path(out) if out is not None else None
        self._alerts: TextIO | None = None
        self._fixes: TextIO | None = None
        self._csv = None
        if self.out is not None:
            self.out.mkdir(parents=True, exist_ok=True)
            self._alerts = open(self.out / "alerts.jsonl", "a", encoding="utf-8")
            new = not (self.out / "fixes.csv").exists() or (self.out / "fixes.csv").stat().st_size == 0
            self._fixes = open(self.out / "fixes.csv", "a", encoding="utf-8", newline="")
            self._csv = csv.writer(self._fixes)
            if new:
                self._csv.writerow(self.FIX_COLUMNS)
        self._unflushed = 0
        self._ratios: TextIO | None = None
        self._ratios_csv = None
        self._ratios_unflushed = 0

    def alert(self, event: dict[str, Any]) -> None:
        if self._alerts is not None:
            if "vehicle_t" in event and "boot_t" not in event:
                event = {**event, "t": event["vehicle_t"], "boot_t": self.boot_time(event["vehicle_t"])}
            self._alerts.write(json.dumps(event, default=json_default) + "\n")
            self._alerts.flush()

    def fix(self, values: tuple) -> None:
        """One scored fix: FIX_COLUMNS without ``boot_t`` (taken from its ``t``), or all of them;
        times to the microsecond, other numbers to 6 significant digits."""
        if self._csv is not None:
            if len(values) == len(self.FIX_COLUMNS) - 1:
                boot = self.boot_time(values[1])
                values = (*values[:2], math.nan if boot is None else boot, *values[2:])
            self._csv.writerow(["" if isinstance(v, float) and math.isnan(v) else
                                (f"{v:.6f}" if i in (1, 2) else f"{v:.6g}") if isinstance(v, float) else v
                                for i, v in enumerate(values)])
            self._unflushed += 1
            if self._unflushed >= 50:
                self._fixes.flush()
                self._unflushed = 0

    def ratios(self, t: float, r) -> None:
        """The autopilot's test ratios at t (a ``sensors.samples.EstimatorRatios``): one line of
        ``autopilot_ratios.csv``, the file opened (with its header) at the first."""
        if self.out is None:
            return
        if self._ratios is None:
            path = self.out / "autopilot_ratios.csv"
            new = not path.exists() or path.stat().st_size == 0
            self._ratios = open(path, "a", encoding="utf-8", newline="")
            self._ratios_csv = csv.writer(self._ratios)
            if new:
                self._ratios_csv.writerow(self.RATIO_COLUMNS)
        boot = self.boot_time(t)
        row = [f"{t:.6f}", "" if boot is None else f"{boot:.6f}", r.source]
        for k in self.RATIO_COLUMNS[3:]:
            v = getattr(r, k)
            row.append(int(v) if isinstance(v, (bool, int)) else "" if math.isnan(v) else f"{v:.6g}")
        self._ratios_csv.writerow(row)
        self._ratios_unflushed += 1
        if self._ratios_unflushed >= 50:
            self._ratios.flush()
            self._ratios_unflushed = 0

    def close(self) -> None:
        for f in (self._alerts, self._fixes, self._ratios):
            if f is not None:
                f.close()
        self._alerts = self._fixes = self._csv = self._ratios = self._ratios_csv = None
