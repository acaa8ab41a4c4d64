"""MAVLink telemetry logs (``.tlog``, as ground stations record a link): ``read_tlog(path) -> FlightLog``.

A tlog is the messages a ground station received, each after its receive time (8 bytes, UNIX
microseconds, big-endian). The messages become samples as on the live link
(``sensors.mavlink.decode``: units, frames, sentinels), timed by their receive time: the
vehicle's own stamps are not one clock in a tlog (GPS_RAW_INT carries GPS time on ArduPilot,
the others time since boot), so ``boot_t0`` is NaN. Streams:

* imu: the first IMU message type seen in ``IMU_MESSAGES``' preference order (``HIGHRES_IMU``,
  ``RAW_IMU``, ``SCALED_IMU``...), with the magnetometer it carries (``mag``);
* gps: receiver 0 (``GPS_RAW_INT``), fixes of at least 2D; baro: ``SCALED_PRESSURE`` or
  ``HIGHRES_IMU``'s pressure altitude; attitude: ``ATTITUDE``;
* estimate: ``GLOBAL_POSITION_INT`` (the autopilot's position) in ENU about the origin:
  ``GPS_GLOBAL_ORIGIN``, else ``HOME_POSITION``, else the first fix;
* receiver: every ``GPS_RAW_INT`` (``sensors.mavlink.gps_status``), fix or not: fix_type,
  satellites, accuracies; noise, jamming and spoofing are not in the message.

The records are read at once where they are all whole MAVLink packets (``tlog_records``), else
message by message with pymavlink's reader: the same messages either way.

A telemetry link's streams are slow (an IMU at a few Hz): the ekf replay refuses an IMU under
the filter's least rate, naming it. ``HEARTBEAT`` arming changes and ``STATUSTEXT`` texts go to
the notes and ``vehicle["messages"]``. Events (``FlightLog.events``) are the vehicle's messages
as ``sensors.mavlink.VehicleEvents`` reads them, the live monitor's conversion: arming and mode
from the autopilot's ``HEARTBEAT``, takeoff and landed from ``EXTENDED_SYS_STATE.landed_state``,
GPS glitches and failsafes and EKF variance from ``STATUSTEXT`` (``sensors.mavlink.TEXT_EVENTS``);
a log that starts armed (in the air) begins with armed (takeoff) at its first report.
"""

from __future__ import annotations

import contextlib
import io
import math
from collections import defaultdict
from pathlib import Path

import numpy as np
from pymavlink import mavutil

from quadformer.geometry import frames
from quadformer.logs.flightlog import GPS_GAP, IMU_GAP, FlightLog, LogError, assemble, gps_stream, make_stream
from quadformer.logs.tlog_records import whole_messages
from quadformer.sensors.mavlink import (ARMED, DECODED, IMU_MESSAGES, Estimate, Gps, GpsStatus, Origin, VehicleEvents,
                                        decode, gps_status, vehicle_heartbeat)

__all__ = ["looks_like_tlog", "read_tlog"]

_MAGIC = (0xFE, 0xFD)                     # MAVLink 1 and 2 start bytes
#: the message types ``read_tlog`` takes something from (the others are only counted)
TAKEN = frozenset((*DECODED, "HEARTBEAT", "STATUSTEXT", "EXTENDED_SYS_STATE"))
_UNIX_US = (1.0e15, 4.0e15)               # plausible receive times: 2001 to 2096


def looks_like_tlog(head: bytes) -> bool:
    """Whether a file's first bytes are a tlog record: a UNIX time in microseconds, then a
    MAVLink start byte."""
    return len(head) >= 9 and head[8] in _MAGIC and _UNIX_US[0] < int.from_bytes(head[:8], "big") < _UNIX_US[1]


def read_tlog(path: str | Path, *, imu_gap: float = IMU_GAP, gps_gap: float = GPS_GAP) -> FlightLog:
    """Read a MAVLink telemetry log into a FlightLog (see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise LogError(f"{path}: no such file")
    with open(path, "rb") as fh:
        if not looks_like_tlog(fh.read(16)):
            raise LogError(f"{path}: not a MAVLink telemetry log (no receive time and MAVLink start byte "
                           "at its start)")
    samples: dict[str, list] = defaultdict(list)
    notes: list[str] = []
    texts: list[str] = []
    events = VehicleEvents()
    rows: list[tuple[float, str, str]] = []
    armed, bad, count = None, 0, 0
    sink = io.StringIO()

    def take(m) -> None:
        nonlocal armed
        kind = m.get_type()
        t = float(m._timestamp)
        if kind == "HEARTBEAT" and vehicle_heartbeat(m):
            now = bool(m.base_mode & ARMED)
            if now != armed:
                samples["arming"].append((t, now))
                armed = now
        elif kind == "STATUSTEXT":
            texts.append(str(m.text))
        rows.extend(events.message(t, m))
        if kind == "GPS_RAW_INT":
            samples["GpsStatus"].append((t, gps_status(m)))
        for s in decode(m):
            samples[type(s).__name__].append((t, s))

    try:
        with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
            conn = mavutil.mavlink_connection(str(path), robust_parsing=True, dialect="ardupilotmega")
            try:
                whole = whole_messages(path.read_bytes(), conn.mav, TAKEN)
                if whole is not None:                  # every record a whole, valid MAVLink 1 packet
                    count, wanted = whole
                    for m in wanted:
                        take(m)
                else:
                    while (m := conn.recv_msg()) is not None:
                        count += 1
                        if m.get_type() == "BAD_DATA":
                            bad += 1
                        else:
                            take(m)
            finally:
                conn.close()
    except Exception as exc:          # pymavlink raises many types on damaged input
        raise LogError(f"{path}: not a readable MAVLink telemetry log ({type(exc).__name__}: {exc})") from exc
    if bad:
        notes.append(f"file: {bad} of {count} records unreadable (bad CRC or truncated), skipped")
    if not any(samples[k] for k in ("Imu", "Gps")):
        raise LogError(f"{path}: a telemetry log without IMU or GPS messages ({count} messages read)")
    t0 = min(v[0][0] for v in samples.values() if v)
    streams = _streams(samples, t0, notes)
    origin, origin_source = _origin(samples, streams.pop("gps_raw"), notes)
    streams["gps"] = gps_stream(_gps_raw(samples["Gps"], t0), origin, notes) if samples["Gps"] else None
    streams["estimate"] = _estimate(samples["Estimate"], t0, origin, notes)
    streams["receiver"] = _receiver(samples["GpsStatus"], t0, notes)
    for t, now in samples["arming"]:
        notes.append(f"file: {'armed' if now else 'disarmed'} at {t - t0:.2f} s (HEARTBEAT)")
    notes.append("time: receive times of the ground station (the vehicle's own stamps are not one clock in a "
                 "tlog); the link's latency and jitter are in them")
    vehicle = {"autopilot": "MAVLink", "messages": texts[:20]}
    return assemble("mavlink-tlog", path, streams, notes, vehicle, origin, origin_source, imu_gap, gps_gap,
                    events=[(t - t0, e, d) for t, e, d in rows])


def _streams(samples: dict[str, list], t0: float, notes: list[str]) -> dict:
    out: dict = {}
    imus = samples["Imu"]
    sources = {s.source for _, s in imus}
    source = next((src for kind in IMU_MESSAGES for src in sorted(sources) if src.startswith(kind + "#")), None)
    if source is not None:
        rows = [(t, s) for t, s in imus if s.source == source]
        if len(sources) > 1:
            notes.append(f"imu: {source} used of {', '.join(sorted(sources))}")
        x = np.array([s.x for _, s in rows])
        t = np.array([t for t, _ in rows]) - t0
        out["imu"] = make_stream("imu", t, dict(zip(("ax", "ay", "az", "gx", "gy", "gz"), x.T)))
        rate = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else 0.0
        notes.append(f"imu: {source.split('#')[0]} at {rate:.1f} Hz")
    if samples["Mag"]:
        f = np.array([s.field for _, s in samples["Mag"]])
        out["mag"] = make_stream("mag", np.array([t for t, _ in samples["Mag"]]) - t0,
                                 dict(zip(("mx", "my", "mz"), f.T)))
    if samples["Baro"]:
        out["baro"] = make_stream("baro", np.array([t for t, _ in samples["Baro"]]) - t0,
                                  {"alt": np.array([s.alt for _, s in samples["Baro"]])})
    if samples["Attitude"]:
        q = np.array([s.q for _, s in samples["Attitude"]])
        out["attitude"] = make_stream("attitude", np.array([t for t, _ in samples["Attitude"]]) - t0,
                                      dict(zip(("qx", "qy", "qz", "qw"), q.T)))
    out["gps_raw"] = [(t, s) for t, s in samples["Gps"] if s.instance == 0 and s.fix_type >= 2]
    return out


def _gps_raw(fixes: list[tuple[float, Gps]], t0: float) -> dict:
    fixes = [(t, s) for t, s in fixes if s.instance == 0 and s.fix_type >= 2]
    return {"t": np.array([t for t, _ in fixes]) - t0, "lat": np.array([s.lat for _, s in fixes]),
            "lon": np.array([s.lon for _, s in fixes]), "alt": np.array([s.alt for _, s in fixes]),
            "vel": np.array([s.vel for _, s in fixes]).reshape(-1, 3),
            "fix_type": np.array([s.fix_type for _, s in fixes], dtype=float),
            "satellites": np.array([s.satellites for _, s in fixes]), "eph": np.array([s.eph for _, s in fixes]),
            "epv": np.array([s.epv for _, s in fixes]), "speed_acc": np.array([s.speed_acc for _, s in fixes])}


def _receiver(reports: list[tuple[float, GpsStatus]], t0: float, notes: list[str]):
    reports = [(t, s) for t, s in reports if s.instance == 0]
    if not reports:
        return None
    cols = ("fix_type", "satellites", "eph", "epv", "speed_acc")
    return make_stream("receiver", np.array([t for t, _ in reports]) - t0,
                       {c: np.array([getattr(s, c) for _, s in reports], dtype=float) for c in cols}, notes)


def _origin(samples: dict[str, list], fixes: list, notes: list[str]):
    origins: list[Origin] = [s for _, s in samples["Origin"]]
    for source in ("GPS_GLOBAL_ORIGIN", "HOME_POSITION"):
        o = next((o for o in origins if o.source == source), None)
        if o is not None and math.isfinite(o.lat) and not (o.lat == 0 and o.lon == 0):
            return (o.lat, o.lon, o.alt), "autopilot local origin" if source == "GPS_GLOBAL_ORIGIN" else "home position"
    if fixes:
        s = fixes[0][1]
        return (s.lat, s.lon, s.alt), "first GPS fix"
    notes.append("origin: no origin message and no GPS fix; origin is NaN")
    return (math.nan,) * 3, "none"


def _estimate(rows: list[tuple[float, Estimate]], t0: float, origin, notes: list[str]):
    rows = [(t, s) for t, s in rows if s.kind == "global"]
    if not rows or not all(math.isfinite(v) for v in origin):
        return None
    p = np.array([s.pos for _, s in rows])
    v = np.array([s.vel for _, s in rows])
    enu = frames.geodetic_to_enu(p[:, 0], p[:, 1], p[:, 2], origin)
    return make_stream("estimate", np.array([t for t, _ in rows]) - t0,
                       {"x": enu[:, 0], "y": enu[:, 1], "z": enu[:, 2], "vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2]},
                       notes)
