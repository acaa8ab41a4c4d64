"""What a vehicle streams, for the test sender: a recorded log's or a simulated flight's sensors,
optionally spoofed (``VehicleStreams.with_attack``), and those streams as encoded MAVLink messages
in sending order, loop after loop; and what the vehicle says of its state once a second
(HEARTBEAT, EXTENDED_SYS_STATE)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from quadformer.estimator.online import CALL_ORDER
from quadformer.geometry.frames import enu_to_geodetic
from quadformer.sender.config import SenderConfig
from quadformer.sensors.mavlink import (
    encode_attitude,
    encode_gps_raw_int,
    encode_highres_imu,
    encode_odometry,
    encode_scaled_pressure,
    mavlink2,
    msec,
    usec,
)

if TYPE_CHECKING:
    from quadformer.attacks import AttackBatch

__all__ = ["RANK", "SIM_ORIGIN", "VehicleStreams", "events", "state_messages"]

#: a default geodetic origin for simulated flights (deg, deg, m)
SIM_ORIGIN = (47.3977418, 8.5455939, 488.0)
RANK = {name: i for i, name in enumerate(CALL_ORDER)}
SATELLITES = 10          # satellites_visible sent when the streams do not say (gps_sats None)


@dataclass
class VehicleStreams:
    """Sensor streams of one vehicle; times in seconds (any zero), arrays row per sample."""
    imu_t: np.ndarray
    imu: np.ndarray                          # (N, 6) specific force, body rate, FLU
    gps_t: np.ndarray
    gps_enu: np.ndarray                      # (K, 3) ENU m about ``origin``
    gps_vel: np.ndarray                      # (K, 3) ENU m/s (NaN: not given)
    origin: tuple[float, float, float] = SIM_ORIGIN
    gps_acc: np.ndarray | None = None        # (K, 3) eph, epv m, speed accuracy m/s (NaN: not given)
    gps_fix: np.ndarray | None = None        # (K,) fix type (default 3)
    gps_geo: np.ndarray | None = None        # (K, 3) lat, lon, alt as recorded (used when given)
    gps_sats: np.ndarray | None = None       # (K,) satellites (default SATELLITES; NaN: not known, sent as 255)
    mag_t: np.ndarray | None = None
    mag: np.ndarray | None = None            # (M, 3) gauss, FLU
    baro_t: np.ndarray | None = None
    baro: np.ndarray | None = None           # (L,) m
    vio_t: np.ndarray | None = None
    vio: np.ndarray | None = None            # (V, 7) ENU velocity, quaternion xyzw FLU -> ENU
    att_t: np.ndarray | None = None
    att: np.ndarray | None = None            # (A, 4) quaternion xyzw FLU -> ENU
    send_origin: bool = False                # send GPS_GLOBAL_ORIGIN first

    @classmethod
    def from_simulation(cls, sensors: dict[str, Any], flight: int = 0,
                        origin: tuple[float, float, float] = SIM_ORIGIN) -> "VehicleStreams":
        """Flight ``flight`` of ``simulate_batch(..., record_sensors=True)["sensors"]``. The
        autopilot's attitude is the simulated filter's initial one, sent once at the first
        IMU stamp (what the replay's start needs)."""
        def a(key: str) -> np.ndarray:
            v = sensors[key][flight]
            return np.asarray(v.numpy() if hasattr(v, "numpy") else v, dtype=float)

        gps = a("gps")
        out = cls(imu_t=np.asarray(sensors["imu_t"], float), imu=a("imu"), gps_t=np.asarray(sensors["gps_t"], float),
                  gps_enu=gps[:, :3], gps_vel=gps[:, 3:6], origin=tuple(origin))
        if "mag" in sensors:
            out.mag_t, out.mag = np.asarray(sensors["mag_t"], float), a("mag")
        if "baro" in sensors:
            out.baro_t, out.baro = np.asarray(sensors["baro_t"], float), a("baro")[:, 0]
        if "vio" in sensors:
            out.vio_t, out.vio = np.asarray(sensors["vio_t"], float), a("vio")
        q0 = sensors["ekf0"].q[flight].numpy()
        out.att_t, out.att = out.imu_t[:1].copy(), q0[None]
        return out

    @classmethod
    def from_log(cls, log) -> "VehicleStreams":
        """A ``FlightLog``'s sensors (imu, gps, mag, baro, odometry, attitude); its origin is
        sent as GPS_GLOBAL_ORIGIN when it has one."""
        gps = log.gps
        origin = tuple(float(v) for v in log.origin)
        has_origin = all(math.isfinite(v) for v in origin)
        geo = gps[["lat", "lon", "alt"]].to_numpy()
        sats = gps["satellites"].to_numpy(dtype=float)
        out = cls(imu_t=log.imu["t"].to_numpy(), imu=log.imu[["ax", "ay", "az", "gx", "gy", "gz"]].to_numpy(),
                  gps_t=gps["t"].to_numpy(), gps_enu=gps[["x", "y", "z"]].to_numpy(),
                  gps_vel=gps[["vx", "vy", "vz"]].to_numpy(), origin=origin if has_origin else tuple(geo[0]),
                  gps_acc=gps[["eph", "epv", "speed_acc"]].to_numpy(),
                  gps_fix=np.nan_to_num(gps["fix_type"].to_numpy(), nan=3.0), gps_geo=geo, send_origin=has_origin,
                  gps_sats=sats if (np.isfinite(sats) & (sats > 0)).all() else None)
        if log.mag is not None:
            out.mag_t, out.mag = log.mag["t"].to_numpy(), log.mag[["mx", "my", "mz"]].to_numpy()
        if log.baro is not None:
            out.baro_t, out.baro = log.baro["t"].to_numpy(), log.baro["alt"].to_numpy()
        if log.odometry is not None:
            o = log.odometry
            out.vio_t, out.vio = o["t"].to_numpy(), o[["vx", "vy", "vz", "qx", "qy", "qz", "qw"]].to_numpy()
        if log.attitude is not None:
            out.att_t, out.att = log.attitude["t"].to_numpy(), log.attitude[["qx", "qy", "qz", "qw"]].to_numpy()
        return out

    def with_attack(self, attack: AttackBatch, t0: float | None = None, rate_hz: float | None = None
                    ) -> "VehicleStreams":
        """These streams with ``attack`` (an ``AttackBatch`` of one flight, its times counting from
        ``t0`` on these streams' clock; default the first fix, as a log replay counts them) injected
        into the GPS: the position and velocity of every fix (``attacks.inject_fixes``; ``rate_hz``,
        the fixes' rate for a replay's delay, default from their median interval) and, for a capture,
        what GPS_RAW_INT says of the receiver (``attacks.spoofed_reports``: eph, epv, vel_acc and
        satellites_visible scaled, fix_type 1 while the lock is lost). A new object; the recorded
        geodetic fixes are dropped (the spoofed positions are sent about ``origin``)."""
        from quadformer.attacks import inject_fixes, spoofed_reports

        if len(attack.kind) != 1:
            raise ValueError(f"with_attack takes the AttackBatch of one flight, got {len(attack.kind)} flights")
        t0 = float(self.gps_t[0]) if t0 is None else float(t0)
        if rate_hz is None:
            rate_hz = 1.0 / float(np.median(np.diff(self.gps_t))) if len(self.gps_t) > 1 else 1.0
        vel = np.where(np.isfinite(self.gps_vel), self.gps_vel, 0.0)
        pos, v, _, _ = inject_fixes(attack, self.gps_t - t0, self.gps_enu, vel, rate_hz)
        v = np.where(np.isfinite(self.gps_vel), v, np.nan)                 # a velocity not given stays so
        n = len(self.gps_t)
        acc = self.gps_acc if self.gps_acc is not None else np.full((n, 3), np.nan)
        fix = self.gps_fix if self.gps_fix is not None else np.full(n, 3.0)
        sats = self.gps_sats if self.gps_sats is not None else np.full(n, float(SATELLITES))
        reports = spoofed_reports(pd.DataFrame({"t": self.gps_t, "fix_type": fix, "satellites": sats,
                                                "eph": acc[:, 0], "epv": acc[:, 1], "speed_acc": acc[:, 2]}),
                                  attack, t0)
        return dataclasses.replace(self, gps_enu=pos, gps_vel=v, gps_geo=None,
                                   gps_acc=reports[["eph", "epv", "speed_acc"]].to_numpy(),
                                   gps_fix=reports["fix_type"].to_numpy(), gps_sats=reports["satellites"].to_numpy())

    @property
    def start(self) -> float:
        return float(min(t[0] for t in self._times() if t is not None and len(t)))

    @property
    def end(self) -> float:
        return float(max(t[-1] for t in self._times() if t is not None and len(t)))

    def _times(self):
        return (self.imu_t, self.gps_t, self.mag_t, self.baro_t, self.vio_t, self.att_t)


def events(s: VehicleStreams, cfg: SenderConfig):
    """(vehicle time, encoded time, stream, message) in sending order, loop after loop."""
    period = s.end - s.start + float(np.median(np.diff(s.imu_t)))
    shift_pos = s.gps_enu[-1] - s.gps_enu[0]
    offset = cfg.boot_s - s.start
    for k in range(cfg.loops):
        dt_k = k * period
        enu = s.gps_enu + k * shift_pos
        geo = s.gps_geo if (s.gps_geo is not None and k == 0) else enu_to_geodetic(enu, s.origin)
        n_gps = len(s.gps_t)
        acc = s.gps_acc if s.gps_acc is not None else np.full((n_gps, 3), np.nan)
        fix = s.gps_fix if s.gps_fix is not None else np.full(n_gps, 3.0)
        sats = (np.full(n_gps, SATELLITES) if s.gps_sats is None
                else np.where(np.isfinite(s.gps_sats), np.clip(s.gps_sats, 0, 254), 255).astype(int))
        if cfg.fix_lost is not None:
            a, n = cfg.fix_lost
            fix = np.where((s.gps_t + dt_k >= a) & (s.gps_t + dt_k < a + n), 1.0, fix)

        def enc_t(t: float) -> float:
            if cfg.restart_at is not None and t >= cfg.restart_at:
                return t - cfg.restart_at + cfg.restart_to
            return t + offset

        # (clock: 0 before a restart, 1 after; decoded stamp; rank; vehicle t; stream; index)
        items: list[tuple[int, float, int, float, str, int]] = []
        for stream, times, quant in (("attitude", s.att_t, msec), ("mag", s.mag_t, usec), ("baro", s.baro_t, msec),
                                     ("vio", s.vio_t, usec), ("gps", s.gps_t, usec), ("imu", s.imu_t, usec)):
            if times is None:
                continue
            scale = 1e-3 if quant is msec else 1e-6
            r = RANK[stream]
            for i, t in enumerate(times):
                tv = float(t) + dt_k
                clock = int(cfg.restart_at is not None and tv >= cfg.restart_at)
                items.append((clock, quant(enc_t(tv)) * scale, r, tv, stream, i))
        items.sort(key=lambda e: e[:3])
        j = 0
        while j < len(items):
            _, stamp, _, tv, stream, i = items[j]
            te = enc_t(tv)
            if stream == "imu":
                yield tv, stamp, "imu", encode_highres_imu(te, imu=s.imu[i])
            elif stream == "mag":
                nxt = items[j + 1] if j + 1 < len(items) else None
                if nxt is not None and nxt[4] == "imu" and nxt[1] == stamp and "imu" not in cfg.skip:
                    yield tv, stamp, "imu+mag", encode_highres_imu(te, imu=s.imu[nxt[5]], mag=s.mag[i])
                    j += 2
                    continue
                yield tv, stamp, "mag", encode_highres_imu(te, mag=s.mag[i])
            elif stream == "baro":
                yield tv, stamp, "baro", encode_scaled_pressure(te, s.baro[i])
            elif stream == "vio":
                yield tv, stamp, "vio", encode_odometry(te, np.zeros(3), s.vio[i, :3], s.vio[i, 3:7])
            elif stream == "gps":
                yield tv, stamp, "gps", encode_gps_raw_int(te, *geo[i], s.gps_vel[i], *acc[i], fix_type=int(fix[i]),
                                                           satellites=int(sats[i]))
            else:
                yield tv, stamp, "attitude", encode_attitude(te, s.att[i])
            j += 1


def state_messages(cfg: SenderConfig, tv: float) -> list:
    """What the vehicle says of its state at vehicle time tv: its HEARTBEAT (armed within
    ``cfg.armed``) and, with ``cfg.in_air``, EXTENDED_SYS_STATE (in the air within it, else on
    the ground)."""
    autopilot = mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA if cfg.autopilot == "ardupilot" else mavlink2.MAV_AUTOPILOT_PX4
    armed = cfg.armed is not None and cfg.armed[0] <= tv < cfg.armed[1]
    out = [mavlink2.MAVLink_heartbeat_message(mavlink2.MAV_TYPE_QUADROTOR, autopilot,
                                              mavlink2.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0, 0,
                                              mavlink2.MAV_STATE_ACTIVE, 3)]
    if cfg.in_air is not None:
        up = cfg.in_air[0] <= tv < cfg.in_air[1]
        out.append(mavlink2.MAVLink_extended_sys_state_message(
            mavlink2.MAV_VTOL_STATE_UNDEFINED,
            mavlink2.MAV_LANDED_STATE_IN_AIR if up else mavlink2.MAV_LANDED_STATE_ON_GROUND))
    return out
