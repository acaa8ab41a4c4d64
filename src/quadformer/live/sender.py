"""A test sender: a vehicle's sensor streams played as MAVLink over a pymavlink link.

``VehicleStreams`` holds what a vehicle would stream (SI units, ENU world, FLU body): a
recorded log's sensors (``VehicleStreams.from_log``, any object with a ``FlightLog``'s
DataFrames) or a simulated flight's (``from_simulation``, the ``sensors`` entry of
``simulate_batch(..., record_sensors=True)``). ``send(streams, connect, config)`` plays them as
HIGHRES_IMU (IMU, and the magnetometer in the same message when stamped alike),
GPS_RAW_INT, ATTITUDE, SCALED_PRESSURE, ODOMETRY (with VIO) and a HEARTBEAT per vehicle
second, in stamp order and, for equal stamps, in ``estimator.online.CALL_ORDER`` (the order of
the log replay), faster than real time:

- ``speed``: times real time (None: no pacing);
- flow control (``window`` > 0): a TIMESYNC request every ``window // 4`` packets and at most
  ``window`` packets ahead of the last one the receiver answered (a live monitor answers
  TIMESYNC as a companion computer does), so a UDP receiver is never overrun: "as fast as the
  receiver keeps up".

Faults, seeded (``np.random.default_rng(seed)``): packet loss, duplicates, reordering (a
packet held back behind the next), corrupt bytes (one payload byte flipped: a bad CRC), a
silent pause, an outage of some streams over a span of vehicle time, streams never sent, and
a restart with the vehicle's clock going back. TIMESYNC and HEARTBEAT packets are not
faulted.

With ``record=True`` the report holds the data exactly as encoded: every data packet that
left intact, parsed back and decoded (``mavlink.decode``), as FlightLog-like frames
(1e-7 deg, mm, cm/s and float32 quantisation included), so that an offline reference can be
computed on the very data the receiver got. Messages the receiver sends back (STATUSTEXT,
COMMAND_LONG, answered with COMMAND_ACK as a vehicle does) are collected in the report.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from quadformer.estimator.online import CALL_ORDER
from quadformer.geometry.frames import enu_to_geodetic
from quadformer.live.mavlink import (
    Attitude,
    Baro,
    Gps,
    Imu,
    Mag,
    Odometry,
    Origin,
    decode,
    encode_attitude,
    encode_gps_raw_int,
    encode_highres_imu,
    encode_odometry,
    encode_origin,
    encode_scaled_pressure,
    mavlink2,
    msec,
    open_link,
    usec,
)

#: a default geodetic origin for simulated flights (deg, deg, m)
SIM_ORIGIN = (47.3977418, 8.5455939, 488.0)
RANK = {name: i for i, name in enumerate(CALL_ORDER)}
FAULTY = ("imu", "gps", "mag", "baro", "vio", "attitude")


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
        out = cls(imu_t=log.imu["t"].to_numpy(), imu=log.imu[["ax", "ay", "az", "gx", "gy", "gz"]].to_numpy(),
                  gps_t=gps["t"].to_numpy(), gps_enu=gps[["x", "y", "z"]].to_numpy(),
                  gps_vel=gps[["vx", "vy", "vz"]].to_numpy(), origin=origin if has_origin else tuple(geo[0]),
                  gps_acc=gps[["eph", "epv", "speed_acc"]].to_numpy(),
                  gps_fix=np.nan_to_num(gps["fix_type"].to_numpy(), nan=3.0), gps_geo=geo, send_origin=has_origin)
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

    @property
    def start(self) -> float:
        return float(min(t[0] for t in self._times() if t is not None and len(t)))

    @property
    def end(self) -> float:
        return float(max(t[-1] for t in self._times() if t is not None and len(t)))

    def _times(self):
        return (self.imu_t, self.gps_t, self.mag_t, self.baro_t, self.vio_t, self.att_t)


@dataclass(frozen=True)
class SenderConfig:
    speed: float | None = None              # x real time; None: no pacing
    window: int = 128                       # packets ahead of the receiver's answers (0: no flow control)
    loss: float = 0.0                       # probability a data packet is not sent
    duplicate: float = 0.0                  # ... is sent twice
    reorder: float = 0.0                    # ... is held back behind the next one
    corrupt: float = 0.0                    # ... has one payload byte flipped
    seed: int = 0
    skip: tuple[str, ...] = ()              # streams never sent: imu, gps, mag, baro, vio, attitude
    outages: tuple[tuple[float, float, tuple[str, ...]], ...] = ()   # (start s, length s, streams) of vehicle
                                            # time during which those streams are not sent
    pause: tuple[float, float] | None = None            # (vehicle time, wall seconds): the link goes silent
    restart_at: float | None = None         # vehicle time at which the clock restarts ...
    restart_to: float = 1.0                 # ... at this time since boot
    boot_s: float = 1.0                     # time since boot of the first sample
    loops: int = 1                          # play the streams this many times, end to end (time continues,
                                            # positions continue from where the previous loop ended)
    system: int = 1                         # the vehicle's MAVLink identity
    component: int = 1
    autopilot: str = "px4"                  # px4 or ardupilot (its HEARTBEAT)
    record: bool = False                    # keep the data as encoded (tests; memory grows with the flight)
    peer_timeout_s: float = 10.0            # udpin: wait this long for the receiver's first packet
    sync_timeout_s: float = 10.0            # give up waiting for a TIMESYNC answer after this long
    timeout_s: float = 300.0                # overall wall-clock bound
    linger_s: float = 0.3                   # keep reading the receiver's messages after the end

    def __post_init__(self) -> None:
        for name in ("loss", "duplicate", "reorder", "corrupt"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"sender.{name} must be a probability, got {v!r}")
        unknown = set(self.skip) | {n for o in self.outages for n in o[2]}
        if unknown - set(FAULTY):
            raise ValueError(f"sender: unknown stream(s) {sorted(unknown - set(FAULTY))}; choose from {FAULTY}")
        if self.speed is not None and not self.speed > 0:
            raise ValueError(f"sender.speed must be > 0, got {self.speed!r}")
        if self.loops < 1 or self.window < 0:
            raise ValueError("sender.loops must be >= 1 and sender.window >= 0")


@dataclass
class SendReport:
    sent: int = 0                           # packets written (duplicates counted twice)
    data: int = 0                           # data packets produced (before faults)
    lost: int = 0
    duplicated: int = 0
    reordered: int = 0
    corrupted: int = 0
    paused_s: float = 0.0
    syncs: int = 0
    stalls: int = 0                         # TIMESYNC answers that never came (receiver stalled)
    wall_s: float = 0.0
    vehicle_s: float = 0.0                  # vehicle time played
    statustexts: list[tuple[int, str]] = field(default_factory=list)
    commands: list[tuple[int, tuple[float, ...]]] = field(default_factory=list)
    received: dict[str, int] = field(default_factory=dict)
    record: dict[str, Any] | None = None    # frames of the data as encoded (``record=True``)
    timed_out: bool = False


class _Recorder:
    """The data packets that left intact, parsed back and decoded (samples in lists)."""

    def __init__(self):
        self.parser = mavlink2.MAVLink(None)
        self.parser.robust_parsing = True
        self.rows: dict[str, list] = {k: [] for k in ("imu", "gps", "mag", "baro", "odometry", "attitude")}
        self.origin: tuple[float, float, float] | None = None

    def add(self, buf: bytes) -> None:
        for m in self.parser.parse_buffer(buf) or []:
            for s in decode(m):
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
                "attitude": ["t", "qx", "qy", "qz", "qw"]}
        out: dict[str, Any] = {k: (pd.DataFrame(v, columns=cols[k]) if v else None) for k, v in self.rows.items()}
        out["origin"] = self.origin
        return out


def _events(s: VehicleStreams, cfg: SenderConfig):
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
                yield tv, stamp, "gps", encode_gps_raw_int(te, *geo[i], s.gps_vel[i], *acc[i], fix_type=int(fix[i]))
            else:
                yield tv, stamp, "attitude", encode_attitude(te, s.att[i])
            j += 1


class _Peer:
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


def _pack(conn, msg) -> bytes:
    """The bytes of ``msg`` with the link's next sequence number (as ``MAVLink.send`` does)."""
    buf = msg.pack(conn.mav)
    conn.mav.seq = (conn.mav.seq + 1) % 256
    return buf


def send(streams: VehicleStreams, connect, config: SenderConfig = SenderConfig(), stop=None) -> SendReport:
    """Play ``streams`` to a MAVLink receiver. ``connect``: ``udpout:127.0.0.1:PORT`` (a
    receiver bound to PORT), ``udpin:127.0.0.1:PORT`` (wait for the receiver's first packet,
    then answer to it), or a connection from ``mavlink.open_link`` (closed at the end; a
    bound one waits for the receiver as udpin does). ``stop``: a ``threading.Event`` that
    ends the stream early. Returns the report; bounded by ``config.timeout_s`` of wall time."""
    cfg = config
    report = SendReport()
    if isinstance(connect, str):
        conn = open_link(connect, cfg.system, cfg.component)
        listen = connect.startswith("udpin")
    else:
        conn, listen = connect, bool(getattr(connect, "udp_server", False))
    peer = _Peer(conn, report)
    rng = np.random.default_rng(cfg.seed)
    rec = _Recorder() if cfg.record else None
    t_start = time.monotonic()
    deadline = t_start + cfg.timeout_s
    autopilot = mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA if cfg.autopilot == "ardupilot" else mavlink2.MAV_AUTOPILOT_PX4
    try:
        if listen:
            end = time.monotonic() + cfg.peer_timeout_s
            while not peer.seen and time.monotonic() < end:
                peer.poll()
                conn.select(0.05)
            if not peer.seen:
                report.timed_out = True
                return report

        def write(buf: bytes) -> None:
            conn.write(buf)
            report.sent += 1

        def control(msg) -> None:
            write(_pack(conn, msg))

        sync_every = max(cfg.window // 4, 1)
        next_sync, outstanding = 0, []
        held: bytes | None = None
        t0_vehicle: float | None = None
        next_heartbeat = -math.inf
        paused = False
        if streams.send_origin:
            o = encode_origin(*streams.origin)
            buf = _pack(conn, o)
            write(buf)
            if rec is not None:
                rec.add(buf)
        for tv, stamp, stream, msg in _events(streams, cfg):
            now = time.monotonic()
            if now > deadline:
                report.timed_out = True
                break
            if stop is not None and stop.is_set():
                break
            if t0_vehicle is None:
                t0_vehicle = tv
            report.vehicle_s = tv - t0_vehicle
            if tv >= next_heartbeat:
                next_heartbeat = tv + 1.0
                control(mavlink2.MAVLink_heartbeat_message(mavlink2.MAV_TYPE_QUADROTOR, autopilot, 0, 0,
                                                           mavlink2.MAV_STATE_ACTIVE, 3))
            if cfg.pause is not None and not paused and tv >= cfg.pause[0]:
                paused = True
                wait = min(cfg.pause[1], max(deadline - now, 0.0))
                time.sleep(wait)
                report.paused_s += wait
            kinds = stream.split("+")
            if any(k in cfg.skip for k in kinds):
                continue
            if any(a <= tv < a + n and any(k in names for k in kinds) for a, n, names in cfg.outages):
                continue
            if cfg.speed is not None:
                ahead = (tv - t0_vehicle) / cfg.speed - (time.monotonic() - t_start - report.paused_s)
                if ahead > 0:
                    time.sleep(min(ahead, 1.0))
            report.data += 1
            buf = _pack(conn, msg)
            u = rng.random(4)
            if u[0] < cfg.loss:
                report.lost += 1
                continue
            if u[1] < cfg.corrupt and len(buf) > 12:
                b = bytearray(buf)
                b[int(rng.integers(10, len(b)))] ^= 0xFF
                buf = bytes(b)
                report.corrupted += 1
            elif rec is not None:
                rec.add(buf)
            if u[3] < cfg.reorder and held is None:
                held = buf
                report.reordered += 1
                continue
            write(buf)
            if u[2] < cfg.duplicate:
                write(buf)
                report.duplicated += 1
            if held is not None:
                write(held)
                held = None
            if cfg.window:
                if report.data % sync_every == 0:
                    control(mavlink2.MAVLink_timesync_message(0, next_sync))
                    outstanding.append(next_sync)
                    next_sync += 1
                    report.syncs += 1
                peer.poll()
                while outstanding and outstanding[0] <= peer.answered:
                    outstanding.pop(0)
                if len(outstanding) > 4:
                    if not peer.wait(outstanding[0], min(cfg.sync_timeout_s, max(deadline - time.monotonic(), 0))):
                        report.stalls += 1
                        outstanding.clear()
            else:
                peer.poll()
        if held is not None:
            write(held)
        if cfg.window:                       # everything processed before the report
            control(mavlink2.MAVLink_timesync_message(0, next_sync))
            report.syncs += 1
            if not peer.wait(next_sync, min(cfg.sync_timeout_s, max(deadline - time.monotonic(), 0.0))):
                report.stalls += 1
        end = time.monotonic() + cfg.linger_s
        while time.monotonic() < end:
            peer.poll()
            conn.select(0.02)
    finally:
        report.wall_s = time.monotonic() - t_start
        if rec is not None:
            report.record = rec.frames()
        conn.close()
    return report

