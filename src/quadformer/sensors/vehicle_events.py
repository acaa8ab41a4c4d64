"""The vehicle's events from its autopilot's MAVLink messages, kept apart from the sample
conversions of ``sensors.mavlink`` (which re-exports these names).

The vehicle's events (``VehicleEvents``: one vocabulary with ``logs.flightlog.EVENTS``), from
the messages of the vehicle's autopilot (``vehicle_heartbeat``: a HEARTBEAT neither of a ground
station, an onboard controller or a gimbal, nor of a component without an autopilot), as a
telemetry log and the live link both read them:

* ``HEARTBEAT``: armed / disarmed where ``base_mode`` & 128 (MAV_MODE_FLAG_SAFETY_ARMED) changes,
  mode where the mode (``custom_mode``, named by pymavlink) changes;
* ``EXTENDED_SYS_STATE.landed_state`` (1 on ground, 2 in air, 3 taking off, 4 landing): takeoff
  where it leaves 1 for 2, 3 or 4, landed where it comes back to 1 (0, undefined, is skipped);
* a vehicle first heard armed (in the air) begins with armed (takeoff) at its first report;
* ``STATUSTEXT``, case-insensitive (``TEXT_EVENTS``, ``text_event``): ArduPilot's "GPS Glitch"
  and, since 3.6, "GPS Glitch or Compass error" -> gps_glitch; "GPS Glitch cleared" / "Glitch
  cleared" -> gps_glitch_cleared; "GPS failsafe" or ArduCopter 3.1's "Lost GPS!" -> gps_failsafe
  (a text with "cleared" or "resolved" -> gps_failsafe_cleared); "EKF variance" -> ekf_variance
  (sent at most every 30 s; it has no clearing text). Pre-arm check texts ("PreArm: ...", "Arm:
  ...") repeat a state while disarmed and give no event.
"""

from __future__ import annotations

import re

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

__all__ = ["ARMED", "NOT_VEHICLES", "ON_GROUND", "TEXT_EVENTS", "VehicleEvents", "text_event", "vehicle_heartbeat"]

ARMED = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED          # 128, HEARTBEAT.base_mode
ON_GROUND = mavlink2.MAV_LANDED_STATE_ON_GROUND      # 1 (0 undefined; 2, 3, 4 in the air)
NOT_VEHICLES = (mavlink2.MAV_TYPE_GCS, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_TYPE_GIMBAL)

#: STATUSTEXT -> event: the first pattern that matches (case-insensitive) wins
TEXT_EVENTS = ((re.compile(r"^(pre)?arm\b", re.I), None),
               (re.compile(r"glitch cleared", re.I), "gps_glitch_cleared"),
               (re.compile(r"gps glitch", re.I), "gps_glitch"),
               (re.compile(r"gps failsafe.*(cleared|resolved)", re.I), "gps_failsafe_cleared"),
               (re.compile(r"gps failsafe|lost gps", re.I), "gps_failsafe"),
               (re.compile(r"^ekf variance", re.I), "ekf_variance"))


def vehicle_heartbeat(m) -> bool:
    """Whether a HEARTBEAT is a vehicle's autopilot's: not a ground station's, an onboard
    controller's or a gimbal's, nor a component's without an autopilot (a camera)."""
    return m.autopilot != mavlink2.MAV_AUTOPILOT_INVALID and m.type not in NOT_VEHICLES


def text_event(text: str) -> str | None:
    """The event a STATUSTEXT says (``TEXT_EVENTS``), None for any other text."""
    return next((e for pattern, e in TEXT_EVENTS if pattern.search(text)), None)


class VehicleEvents:
    """The vehicle's events as its messages arrive, each method given the message's time t and
    returning the (t, event, detail) rows it gives (see the module text). Feed it the vehicle's
    messages only (``vehicle_heartbeat``); ``start`` words the detail of a state the vehicle
    was first heard in (a log's start, the link's first report)."""

    def __init__(self, start: str = "at the log's start") -> None:
        self.start = start
        self.armed: bool | None = None
        self.mode: str | None = None
        self.airborne: bool | None = None

    def heartbeat(self, t: float, m) -> list[tuple[float, str, str]]:
        rows = []
        armed = bool(m.base_mode & ARMED)
        if armed != self.armed and (armed or self.armed is not None):
            first = f" {self.start}" if self.armed is None else ""
            rows.append((t, "armed" if armed else "disarmed", f"HEARTBEAT base_mode {m.base_mode}{first}"))
        self.armed = armed
        mode = mavutil.mode_string_v10(m)
        if mode != self.mode:
            rows.append((t, "mode", f"HEARTBEAT mode {mode}"))
            self.mode = mode
        return rows

    def landed_state(self, t: float, state: int) -> list[tuple[float, str, str]]:
        if state == 0:
            return []
        rows = []
        airborne = state != ON_GROUND
        if airborne != self.airborne and (airborne or self.airborne is not None):
            first = f" {self.start}" if self.airborne is None else ""
            rows.append((t, "takeoff" if airborne else "landed", f"EXTENDED_SYS_STATE landed_state {state}{first}"))
        self.airborne = airborne
        return rows

    def text(self, t: float, text: str) -> list[tuple[float, str, str]]:
        event = text_event(text)
        return [] if event is None else [(t, event, f"STATUSTEXT {text!r}")]

    def message(self, t: float, m) -> list[tuple[float, str, str]]:
        """Any message of the vehicle: the rows of a vehicle HEARTBEAT, an EXTENDED_SYS_STATE or
        a STATUSTEXT, none for others."""
        kind = m.get_type()
        if kind == "HEARTBEAT":
            return self.heartbeat(t, m) if vehicle_heartbeat(m) else []
        if kind == "EXTENDED_SYS_STATE":
            return self.landed_state(t, int(m.landed_state))
        if kind == "STATUSTEXT":
            return self.text(t, str(m.text))
        return []
