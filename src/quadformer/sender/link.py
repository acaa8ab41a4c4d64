"""The test sender's end of the link: the receiver as the sender sees it (answers, commands,
status texts), packets with the link's sequence numbers, and the packets as they left: the
sensor samples, the GPS status reports and the vehicle's events."""

from __future__ import annotations

import math
import time
from typing import Any

import pandas as pd

from quadformer.sender.config import SendReport
from quadformer.sensors.mavlink import (Attitude, Baro, Gps, Imu, Mag, Odometry, Origin, VehicleEvents, decode,
                                        gps_status, mavlink2)

__all__ = ["Peer", "Recorder", "pack"]

SAMPLES = (Imu, Gps, Mag, Baro, Odometry, Attitude)     # the samples a monitor's link time counts


class Peer:
    """The receiver as the sender sees it: answers, commands, status texts."""

    def __init__(self, conn, report: SendReport):
        self.conn, self.report = conn, report
        self.answered = -1
        self.seen = False

    def poll(self) -> None:
        while True:
            m = self.conn.recv_msg()
            if m is None:
                return
            kind = m.get_type()
            if kind == "BAD_DATA":
                continue
            self.seen = True
            self.report.received[kind] = self.report.received.get(kind, 0) + 1
            if kind == "TIMESYNC" and m.tc1 != 0:
                self.answered = max(self.answered, int(m.ts1))
            elif kind == "STATUSTEXT":
                self.report.statustexts.append((int(m.severity), m.text))
            elif kind == "COMMAND_LONG":
                self.report.commands.append((int(m.command), (m.param1, m.param2, m.param3, m.param4, m.param5,
                                                              m.param6, m.param7)))
                self.conn.mav.command_ack_send(m.command, mavlink2.MAV_RESULT_ACCEPTED, 100, 0,
                                               m.get_srcSystem(), m.get_srcComponent())

    def wait(self, ts: int, timeout: float) -> bool:
        """Until the receiver answered TIMESYNC ``ts`` (processed every packet before it)."""
        end = time.monotonic() + timeout
        while True:
            self.poll()
            if self.answered >= ts:
                return True
            now = time.monotonic()
            if now >= end:
                return False
            self.conn.select(min(0.05, end - now))


def pack(conn, msg) -> bytes:
    """The bytes of ``msg`` with the link's next sequence number (as ``MAVLink.send`` does)."""
    buf = msg.pack(conn.mav)
    conn.mav.seq = (conn.mav.seq + 1) % 256
    return buf


class Recorder:
    """The packets that left intact, parsed back and decoded (samples in lists); every GPS
    status report (``gps_status``, receiver 0); the vehicle's events (``VehicleEvents``), timed
    as the monitor times them: at the latest stamp of a sample it takes (a 3D fix's, not a
    report's without one), the first sample's for those before it."""

    def __init__(self):
        self.parser = mavlink2.MAVLink(None)
        self.parser.robust_parsing = True
        self.rows: dict[str, list] = {k: [] for k in ("imu", "gps", "mag", "baro", "odometry", "attitude",
                                                      "receiver", "events")}
        self.origin: tuple[float, float, float] | None = None
        self.vehicle = VehicleEvents(start="at the link's first report")
        self.latest = -math.inf                  # the latest sample stamp
        self.early: list[tuple[str, str]] = []    # events before the first sample

    def add(self, buf: bytes) -> None:
        for m in self.parser.parse_buffer(buf) or []:
            status = gps_status(m)
            if status is not None and status.instance == 0:
                self.rows["receiver"].append([status.t, status.fix_type, status.satellites, status.eph, status.epv,
                                              status.speed_acc])
            for _, event, detail in self.vehicle.message(self.latest, m):
                if math.isfinite(self.latest):
                    self.rows["events"].append((self.latest, event, detail))
                else:
                    self.early.append((event, detail))
            for s in decode(m):
                if isinstance(s, SAMPLES) and not (isinstance(s, Gps) and s.fix_type < 3):
                    if not math.isfinite(self.latest):
                        self.rows["events"] += [(s.t, e, d) for e, d in self.early]
                    self.latest = max(self.latest, s.t)
                if isinstance(s, Imu):
                    self.rows["imu"].append([s.t, *s.x])
                elif isinstance(s, Mag):
                    self.rows["mag"].append([s.t, *s.field])
                elif isinstance(s, Baro):
                    self.rows["baro"].append([s.t, s.alt])
                elif isinstance(s, Gps):
                    self.rows["gps"].append([s.t, s.lat, s.lon, s.alt, *s.vel, s.eph, s.epv, s.speed_acc,
                                             s.fix_type, s.satellites])
                elif isinstance(s, Odometry):
                    self.rows["odometry"].append([s.t, *s.pos, *s.vel, *s.q])
                elif isinstance(s, Attitude):
                    self.rows["attitude"].append([s.t, *s.q])
                elif isinstance(s, Origin) and self.origin is None:
                    self.origin = (s.lat, s.lon, s.alt)

    def frames(self) -> dict[str, Any]:
        cols = {"imu": ["t", "ax", "ay", "az", "gx", "gy", "gz"],
                "gps": ["t", "lat", "lon", "alt", "vx", "vy", "vz", "eph", "epv", "speed_acc", "fix_type",
                        "satellites"],
                "mag": ["t", "mx", "my", "mz"], "baro": ["t", "alt"],
                "odometry": ["t", "x", "y", "z", "vx", "vy", "vz", "qx", "qy", "qz", "qw"],
                "attitude": ["t", "qx", "qy", "qz", "qw"],
                "receiver": ["t", "fix_type", "satellites", "eph", "epv", "speed_acc"]}
        out: dict[str, Any] = {k: (pd.DataFrame(v, columns=cols[k]) if v else None) for k, v in self.rows.items()
                               if k != "events"}
        out["events"] = list(self.rows["events"])
        out["origin"] = self.origin
        return out
