"""What a DataFlash log says happened, as ``FlightLog.events``: the ``ARM``, ``EV``, ``ERR`` and
``MODE`` messages mapped to ``flightlog.EVENTS``.

The codes are ArduPilot's (AP_Logger's ``LogEvent``, ``LogErrorSubsystem`` and ``LogErrorCode``,
unchanged since the ArduCopter 3.x ``DATA_*`` / ``ERROR_SUBSYSTEM_*`` defines they replaced):

* ``ARM.ArmState`` 1 / 0 -> armed / disarmed;
* ``EV.Id`` 10 ARMED -> armed, 11 DISARMED -> disarmed, 28 NOT_LANDED -> takeoff, 18 LAND_COMPLETE
  -> landed, 19 LOST_GPS -> gps_lost; 15 AUTO_ARMED -> armed only where the log has no arming
  since the last disarming (ArduCopter logs it when the throttle is first raised after an
  arming, seconds after EV 10: it is the arming only in a log that lacks the arming itself);
  17 LAND_COMPLETE_MAYBE is left out (the land detector's first guess, which LAND_COMPLETE
  confirms or a NOT_LANDED takes back); other ids (home set, autotune, fence...) are left out;
* ``ERR`` Subsys 11 GPS: ECode 2 GPS_GLITCH -> gps_glitch, 0 ERROR_RESOLVED -> gps_glitch_cleared;
  Subsys 7 FAILSAFE_GPS: 1 FAILSAFE_OCCURRED -> gps_failsafe, 0 FAILSAFE_RESOLVED ->
  gps_failsafe_cleared (older ArduCopter; AP_Logger keeps the code as "not used", a lost GPS
  being left to the EKF failsafe); Subsys 16 EKFCHECK: 2 EKFCHECK_BAD_VARIANCE -> ekf_variance,
  0 EKFCHECK_VARIANCE_CLEARED -> ekf_variance_cleared; other subsystems are left out;
* ``MODE`` -> mode where the mode changes (a MODE repeating the mode in force is left out), the
  detail naming it by pymavlink's mode table for the vehicle the firmware string names.

An arming told by both ``ARM`` and ``EV`` 10 is one event (``flightlog.make_events``). Messages
of the logs before ArduPilot 3.3 carry no time (``EV``, ``ERR``, ``MODE``): they take the time of
the timed message before them, or of the first one for those before any (an arming logged as the
log starts; ``ardupilot_messages.collect_messages``).
"""

from __future__ import annotations

import math

from pymavlink import mavutil

__all__ = ["ERR_EVENTS", "EV_EVENTS", "dataflash_events"]

EV_EVENTS = {10: "armed", 11: "disarmed", 15: "armed", 18: "landed", 19: "gps_lost", 28: "takeoff"}
AUTO_ARMED = 15
ERR_EVENTS = {(11, 2): "gps_glitch", (11, 0): "gps_glitch_cleared", (7, 1): "gps_failsafe",
              (7, 0): "gps_failsafe_cleared", (16, 2): "ekf_variance", (16, 0): "ekf_variance_cleared"}
_FIRMWARE_TYPES = (   # firmware string prefix -> the MAV_TYPE whose mode numbers it uses
    (("ArduCopter", "APM:Copter"), mavutil.mavlink.MAV_TYPE_QUADROTOR),
    (("ArduPlane", "APM:Plane"), mavutil.mavlink.MAV_TYPE_FIXED_WING),
    (("ArduRover", "APMrover2", "APM:Rover"), mavutil.mavlink.MAV_TYPE_GROUND_ROVER),
    (("ArduSub",), mavutil.mavlink.MAV_TYPE_SUBMARINE),
)


def _int(v) -> int | None:
    """A logged code as an int; None for a damaged one (NaN, text)."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return int(f) if math.isfinite(f) and f == int(f) else None


def _mode_names(firmware: str | None) -> dict[int, str]:
    for prefixes, mav_type in _FIRMWARE_TYPES:
        if firmware and firmware.startswith(prefixes):
            return mavutil.mode_mapping_bynumber(mav_type) or {}
    return {}


def dataflash_events(rows: dict[str, list[dict]], times, firmware: str | None) -> list[tuple[float, str, str]]:
    """(t, event, detail) rows of a DataFlash log's ARM, EV, ERR and MODE messages; ``times``
    gives a list of rows' times (s, the streams' raw clock); ``firmware`` is the firmware
    string (e.g. "ArduCopter V3.3-dev (78b42024)") that names the mode table."""
    candidates: list[tuple[float, int, str, str]] = []   # (t, order, event, detail); order keeps the log's order
    for name in ("ARM", "EV", "ERR", "MODE"):
        for r, t in zip(rows.get(name, []), times(rows.get(name, []))):
            candidates.append((float(t), len(candidates), name, r))
    candidates.sort(key=lambda c: (c[0], c[1]))
    names = _mode_names(firmware)
    out: list[tuple[float, str, str]] = []
    armed, mode = False, None
    for t, _, name, r in candidates:
        event, detail = None, ""
        if name == "ARM":
            state = _int(r.get("ArmState"))
            if state is not None:
                event, detail = ("armed" if state else "disarmed"), f"ARM ArmState {state}"
        elif name == "EV":
            code = _int(r.get("Id"))
            event, detail = EV_EVENTS.get(code), f"EV Id {code}"
            if code == AUTO_ARMED and armed:
                event = None
        elif name == "ERR":
            key = (_int(r.get("Subsys")), _int(r.get("ECode")))
            event, detail = ERR_EVENTS.get(key), f"ERR Subsys {key[0]} ECode {key[1]}"
        else:
            number = _int(r.get("ModeNum", r.get("Mode")))
            if number is not None and number != mode:
                mode = number
                event = "mode"
                detail = f"MODE {number}" + (f" {names[number]}" if number in names else "")
        if event is None:
            continue
        if event in ("armed", "disarmed"):
            armed = event == "armed"
        out.append((t, event, detail))
    return out

