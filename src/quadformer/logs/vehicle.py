"""Which vehicle a log was flown on, and whether a vehicle profile (``logs.calibration.vehicle_profile``,
``quadformer calibrate --profile``) may score it."""

from __future__ import annotations

import re
from typing import Any

from quadformer.logs.flightlog import FlightLog, LogError

__all__ = ["check_profile", "vehicle_identity"]

_BOARD = re.compile(r"^[A-Za-z0-9_-]+ [0-9A-F]{8} [0-9A-F]{8} [0-9A-F]{8}$")


def vehicle_identity(log: FlightLog) -> dict[str, Any]:
    """What tells one vehicle from another in a log: its autopilot, its board's serial (the
    ``PX4v2 2A002500 ...`` line ArduPilot writes at boot, where logged) and its frame."""
    v = log.vehicle or {}
    board = next((m.strip() for m in v.get("messages", []) if _BOARD.match(m.strip())), None)
    return {"autopilot": v.get("autopilot") or log.source, "board": board, "frame": v.get("frame")}


def check_profile(detector, log: FlightLog, sensors: str) -> None:
    """Refuse, with the reason, a vehicle profile (a detector ``vehicle_profile`` wrote) for a log of
    another vehicle (another board or autopilot) or fusing another sensor set; nothing for a
    detector without a profile."""
    cal = getattr(detector, "calibration_", None) or {}
    want = cal.get("vehicle")
    if not want:
        return
    have = vehicle_identity(log)
    if want.get("board") and have.get("board") and want["board"] != have["board"]:
        raise LogError(f"{log.path}: the vehicle profile is for board {want['board']}; this log's board is "
                       f"{have['board']} (another vehicle: make its own profile with quadformer calibrate)")
    if want.get("autopilot") and have.get("autopilot") and want["autopilot"] != have["autopilot"]:
        raise LogError(f"{log.path}: the vehicle profile is for an {want['autopilot']} vehicle; this log is "
                       f"{have['autopilot']}'s")
    if cal.get("vehicle_sensors") and cal["vehicle_sensors"] != sensors:
        raise LogError(f"{log.path}: the vehicle profile was made fusing {cal['vehicle_sensors']}; this log fuses "
                       f"{sensors} (make a profile of this sensor set)")
