"""The filter fed one timestamped sample at a time: recorded streams and live links alike.

Two levels:

- ``OnlineFilter`` (``online_filter``): the filter state and its sample queues (samples
  already in the filter's frames and units, the filter already initialised).
- ``ResidueStream``: a real vehicle's raw samples in (any source: a log's streams in time
  order, a live MAVLink link message by message), rows of the residue table out. It owns what
  a real vehicle needs around the filter, the same for every source: the IMU averaged down to
  ``FilterConfig.imu_rate_hz`` (as PX4 EKF2 predicts at 100 Hz), fixes fused at most at
  ``gps_rate_hz``, each fix's noise from the receiver's own accuracy, a missing GPS velocity
  from the change of position (with the std of that difference), and the start: at the first
  fix, from the latest attitude of the autopilot (or the accelerometer's tilt), the magnetic
  field of the last second, the barometer's offset. Everything is causal: a row depends on
  samples up to its fix. Its settings: ``FilterConfig`` (``filter_config``).

``OnlineFilter`` holds the state of the same error-state EKF as the closed loop (``predict``,
the aiding updates, ``gps_update``, ``ResidueTracker``, and the GPS-free reference beside it,
``GpsFreeReference``, fed the same IMU, VIO and barometer samples) for a batch of flights that share
timestamps (one flight for a log or a live vehicle). Samples arrive in time order per stream:
``imu(t, x)`` propagates, then applies the samples queued since with stamps at or before t,
in the order VIO, magnetometer, barometer, GPS; each GPS fix applied yields one row of
residues. ``estimator.replay.run_ekf`` drives it over whole arrays; a live monitor drives it
message by message, so both compute the same thing.

A gap in the IMU longer than ``max_gap`` cannot be propagated across: ``imu`` raises
``GapError`` (the caller starts a new segment, with a new filter).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from quadformer.config import SENSOR_NAMES
from quadformer.estimator.feed import AIDING, EPS
from quadformer.estimator.filter_config import FilterConfig, noise_for, noise_model_for

#: the order in which a source calls ``ResidueStream`` for samples with equal stamps (the log
#: replay sorts its events by (stamp, this order); a live link's sender streams in it)
CALL_ORDER = ("attitude", "mag", "baro", "vio", "gps", "imu")


#: the arithmetic a ``ResidueStream`` runs its filter with: ``numeric`` (``numeric.NumericFilter``,
#: compiled, the default) or ``torch`` (``online_filter.OnlineFilter``, the reference implementation)
BACKENDS = ("numeric", "torch")


def as_numpy(row: dict) -> dict[str, np.ndarray]:
    return {k: np.asarray(v) for k, v in row.items()}


def per_flight(x, n: int, k: int) -> np.ndarray:
    """A sample (n, k), or (k,) for every flight, as an (n, k) float array (a view where it can)."""
    x = np.asarray(x, dtype=float)
    if x.shape == (n, k):
        return x
    if x.shape == (k,):
        return x.reshape(1, k) if n == 1 else np.broadcast_to(x, (n, k))
    raise ValueError(f"a sample shaped {x.shape}, expected ({n}, {k}) or ({k},)")


def spaced(dt: float, rate_hz: float) -> bool:
    """A fix dt seconds after the previous fused one is fused (at most about rate_hz a second)."""
    return dt >= 0.9 / rate_hz


def rotation(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion (xyzw, body to world)."""
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def tilt(acc: np.ndarray) -> np.ndarray:
    """Roll and pitch from a mean specific force (FLU) of a (near) static vehicle, yaw 0 (xyzw)."""
    ax, ay, az = acc
    roll, pitch = math.atan2(ay, az), math.atan2(-ax, math.hypot(ay, az))
    cr, sr, cp, sp = math.cos(roll / 2), math.sin(roll / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    return np.array([sr * cp, cr * sp, -sr * sp, cr * cp])


def magnetic_yaw(q_tilt: np.ndarray, field: np.ndarray) -> np.ndarray:
    """The attitude ``q_tilt`` (roll and pitch, yaw 0; xyzw) turned about the vertical so that the
    horizontal part of the body ``field`` (FLU) points north (ENU +y): the magnetic heading."""
    level = rotation(q_tilt) @ field
    yaw = math.pi / 2 - math.atan2(level[1], level[0])
    x, y, z, w = q_tilt
    s, c = math.sin(yaw / 2), math.cos(yaw / 2)
    return np.array([c * x - s * y, c * y + s * x, c * z + s * w, c * w - s * z])   # (0,0,s,c) * q_tilt


class ResidueStream:
    """Raw samples of ``n`` flights that share timestamps in, residue rows out.

    Call the sample methods in time order per stream (streams may interleave freely within a
    few IMU steps; samples with equal stamps in ``CALL_ORDER``, as the log replay does).
    ``imu`` returns the rows of the fixes it let the filter apply, each a dict with ``t``, the
    fix as fused (``gps_pos``, ``gps_vel``), ``est_pos``, ``est_vel`` and the residue groups,
    values (n, k). ``flush`` ends the stream (the last IMU bin).

    A receiver's latency (``FilterConfig.gps_delay_s`` = D > 0) is compensated as PX4 EKF2 does,
    on a delayed horizon: each fix is fused at its measurement time (its stamp minus D), so the
    filter runs D behind the newest IMU sample (IMU samples are held back D) and a fix's row
    is returned up to D later; rows keep the fix's stamp as ``t``. ``hold_s`` (0 unless set) holds
    the IMU back that much more: fixes stamped at their receiver's epochs, earlier than they
    arrive (``sensors.receiver_epochs``), are still fused at their time."""

    INIT_WINDOW = 1.0     # s before the first fix from which the start's attitude, tilt and field come
    FIELD_S = 3.0         # s after the start over which the field is averaged (the autopilot's attitude)
    BARO_SETTLE = 5.0     # s after the start over which the barometer's offset to the filter's height is
                          # averaged before it is fused (one fix's vertical error would bias it for good)

    def __init__(self, config: FilterConfig, sensors: str, n: int = 1, backend: str = "numeric"):
        parts = sensors.split("+")
        if not {"gps", "imu"} <= set(parts) or set(parts) - set(SENSOR_NAMES):
            raise ValueError(f"sensors: {sensors!r} must join gps, imu and any of vio, mag, baro with '+'")
        if backend not in BACKENDS:
            raise ValueError(f"backend: {backend!r} is not one of {', '.join(BACKENDS)}")
        self.config, self.sensors, self.n, self.backend = config, sensors, n, backend
        self.aiding = tuple(s for s in AIDING if s in parts)
        self.filter = None                       # the filter (``NumericFilter`` or ``OnlineFilter``) once started
        self.t0: float | None = None
        self._bin: list[tuple[float, np.ndarray]] = []       # IMU samples of the current bin
        self._bin_id: int | None = None
        self._recent: dict[str, deque] = {k: deque() for k in ("imu", "att", "mag", "baro")}
        self._last_fix: tuple[float, np.ndarray] | None = None
        self._fused: dict[float, tuple[np.ndarray, float]] = {}   # measurement time -> (fix, stamp)
        self._baro_offset: np.ndarray | None = None             # barometric altitude minus the filter's height
        self._baro_diffs: list[np.ndarray] = []
        self._dt: float | None = None
        self.delay = float(config.gps_delay_s or 0.0)
        self._held: deque = deque()                             # IMU samples within D + hold_s of the newest
        self.hold_s = 0.0                                       # s the IMU is held back beyond D
        self._first_imu: float | None = None
        self._unready = 0                                       # fixes before the start could be made
        self._att: np.ndarray | None = None                     # the autopilot's latest attitude
        self._field_sum, self._field_n = np.zeros(3), 0         # the Earth field's running sum
        self.notes: list[str] = []

    # -- raw samples ----------------------------------------------------------------------
    def attitude(self, t: float, q: np.ndarray) -> None:
        """The autopilot's attitude estimate (xyzw, FLU body -> ENU world); used at the start and
        for the Earth field over the first ``FIELD_S`` seconds."""
        if self.filter is None:
            self._keep("att", t, np.asarray(q, dtype=float))
        self._att = np.asarray(q, dtype=float)

    def imu(self, t: float, x: np.ndarray) -> list[dict[str, Any]]:
        """Specific force and body rate (n, 6) or (6,), FLU."""
        x = per_flight(x, self.n, 6)
        lag = self.delay + self.hold_s
        if lag <= 0.0 and not self._held:
            return self._imu(t, x)
        self._held.append((t, x))
        rows: list[dict[str, Any]] = []
        while self._held and self._held[0][0] <= t - lag + EPS:
            rows += self._imu(*self._held.popleft())
        return rows

    def _imu(self, t: float, x: np.ndarray) -> list[dict[str, Any]]:
        if self.filter is None:
            self._keep("imu", t, x[0])
            if self._first_imu is None:
                self._first_imu = t
        rate = self.config.imu_rate_hz
        bin_id = math.floor(t * rate + 1e-9)
        rows: list[dict[str, Any]] = []
        if self._bin and bin_id != self._bin_id:
            rows = self._step()
        self._bin_id = bin_id
        self._bin.append((t, x))
        return rows

    def gps(self, t: float, pos: np.ndarray, vel: np.ndarray, eph: float | np.ndarray = math.nan,
            epv: float | np.ndarray = math.nan, speed_acc: float | np.ndarray = math.nan) -> None:
        """A fix: ENU position (n, 3) about the local origin and ENU velocity (n, 3; NaN where
        the receiver gives none), with the receiver's accuracies (m, m, m/s; NaN: none), one for
        every flight or one per flight (n,) (flights whose receivers report differently, as
        injected spoofs make them). A missing velocity component is the change of position since
        the previous fused fix, with the std of that difference (both fixes' position std over the
        interval) when larger than the velocity floor; at the first fix it is 0 (the start's
        velocity uncertainty)."""
        pos = per_flight(pos, self.n, 3)
        vel = np.array(per_flight(vel, self.n, 3))
        if self._last_fix is not None and not spaced(t - self._last_fix[0], self.config.gps_rate_hz):
            return                                         # at most gps_rate_hz fixes per second
        c = self.config
        if all(np.ndim(v) == 0 for v in (eph, epv, speed_acc)):
            use = c.receiver_accuracy
            acc = lambda v: v if use and math.isfinite(v) else 0.0   # noqa: E731
            std = np.array([max(acc(eph), c.gps_pos_noise)] * 2 + [max(acc(epv), c.gps_alt_noise)]
                           + [max(acc(speed_acc), c.gps_vel_noise)] * 3)
        else:
            std = self._stds(eph, epv, speed_acc)
        bad = ~np.isfinite(vel)
        std_n = None
        if bad.any():                                      # velocity from the change of position
            if self._last_fix is None:
                vel[bad] = 0.0
            else:
                t1, pos1, std1 = self._last_fix
                vel[bad] = ((pos - pos1) / (t - t1))[bad]
                # the difference of two fixes carries both fixes' position noise: its std, not the
                # velocity floor (a receiver without vertical velocity, e.g. MAVLink GPS_RAW_INT)
                derived = np.hypot(std1[..., :3], std[..., :3]) / (t - t1)
                std_n = np.array(np.broadcast_to(std, (self.n, 6)))
                std_n[:, 3:] = np.where(bad, np.maximum(std_n[:, 3:], derived), std_n[:, 3:])
        self._last_fix = (t, pos.copy(), std)
        fix = np.concatenate([pos, vel], axis=1)
        measured = t - self.delay
        if self.filter is None:
            if self._ready(t):
                self._start(measured, fix, std)
            else:
                self._unready += 1
        else:
            self._fused[measured] = (fix, t)
            self.filter.push("gps", measured, fix, np.broadcast_to(std, (self.n, 6)) if std_n is None else std_n)

    def mag(self, t: float, x: np.ndarray) -> None:
        """Magnetic field (n, 3) or (3,), gauss, FLU."""
        if "mag" not in self.aiding:
            return
        x = per_flight(x, self.n, 3)
        if self.filter is None:
            self._keep("mag", t, x[0])
            return
        if self.filter.mag_field is None:                    # no field yet: the first sample sets it
            self.filter.set_mag_field(rotation(self._q0) @ x[0])
            return
        if self._att is not None and t - self.t0 <= self.FIELD_S:
            # the field as the autopilot's attitude sees each sample, averaged from the start on
            self._field_sum, self._field_n = self._field_sum + rotation(self._att / np.linalg.norm(self._att)) @ x[0], \
                self._field_n + 1
            self.filter.set_mag_field(self._field_sum / self._field_n)
        self.filter.push("mag", t, np.array(x))

    def baro(self, t: float, alt: float) -> None:
        """Barometric altitude (m)."""
        if "baro" not in self.aiding:
            return
        if self.filter is None:
            self._keep("baro", t, np.array([float(alt)]))
            return
        if self._baro_offset is None:                          # settling: the offset, GPS carries height
            self._baro_diffs.append(float(alt) - self.filter.position[:, 2])
            if t - self.t0 >= self.BARO_SETTLE:
                self._baro_offset = np.mean(self._baro_diffs, axis=0)
            return
        h = float(alt) - self._baro_offset                      # height in the filter's frame, per flight
        self.filter.push("baro", t, h.reshape(self.n, 1))

    def vio(self, t: float, x: np.ndarray) -> None:
        """Visual odometry: ENU velocity and attitude quaternion (n, 7) or (7,)."""
        if "vio" in self.aiding and self.filter is not None:
            self.filter.push("vio", t, np.array(per_flight(x, self.n, 7)))

    @property
    def waiting(self) -> float:
        """The stamp of the earliest fix handed to the filter whose row has not come yet (inf:
        none): no row stamped before it can come from the fixes given so far."""
        return min((t for _, t in self._fused.values()), default=math.inf)

    def flush(self) -> list[dict[str, Any]]:
        """The rows of the IMU samples held back and of the last IMU bin (end of the stream)."""
        rows: list[dict[str, Any]] = []
        while self._held:
            rows += self._imu(*self._held.popleft())
        return rows + (self._step() if self._bin else [])

    # -- internals ----------------------------------------------------------------------
    def _stds(self, eph, epv, speed_acc) -> np.ndarray:
        """Per flight (n, 6), each fix's noise std: the larger of the receiver's accuracy (where
        used and finite) and the floor, as for one accuracy shared by every flight."""
        c = self.config
        out = []
        for v, floor, k in ((eph, c.gps_pos_noise, 2), (epv, c.gps_alt_noise, 1), (speed_acc, c.gps_vel_noise, 3)):
            v = np.asarray(v, dtype=float)
            if v.shape not in ((), (self.n,)):
                raise ValueError(f"gps: an accuracy shaped {v.shape}, expected one value or ({self.n},)")
            v = np.broadcast_to(v, (self.n,))
            a = np.where(np.isfinite(v), v, 0.0) if c.receiver_accuracy else np.zeros(self.n)
            out += [np.maximum(a, floor)] * k
        return np.stack(out, axis=1)

    def _keep(self, key: str, t: float, v: np.ndarray) -> None:
        q = self._recent[key]
        q.append((t, v))
        while q and q[0][0] < t - self.INIT_WINDOW:
            q.popleft()

    def _step(self) -> list[dict[str, Any]]:
        """Hand the completed IMU bin (its mean, stamped at its last sample) to the filter."""
        t = self._bin[-1][0]
        x = self._bin[0][1] if len(self._bin) == 1 else np.mean([v for _, v in self._bin], axis=0)
        self._bin = []
        if self.filter is None or t <= self.filter.t:
            return []
        out = []
        for stamp, row in self.filter.imu(t, x):
            fix, t_fix = self._fused.pop(stamp)
            out.append({"t": t_fix, "gps_pos": fix[:, :3], "gps_vel": fix[:, 3:], **as_numpy(row)})
        return out

    def _ready(self, t: float) -> bool:
        """Whether a fix at t can start the filter: IMU samples (the tilt), and the autopilot's
        attitude or a magnetometer (the heading), or else a whole ``INIT_WINDOW`` of IMU without
        either (the heading is then unknown). A fix stamped before them waits for the next."""
        if not self._recent["imu"]:
            return False
        if self._recent["att"] or ("mag" in self.aiding and self._recent["mag"]):
            return True
        return t - self._first_imu >= self.INIT_WINDOW

    def _field(self, q0: np.ndarray) -> np.ndarray:
        """The Earth field (world, ENU) the start's magnetometer samples give: each turned to the
        world with the autopilot's attitude nearest its time, as the vehicle may turn within the
        window (a simulated flight starts while its vehicle settles: one attitude for the whole
        second put the field 20 degrees off, and the heading updates against it then tilted the
        attitude), else with the start's attitude q0 (which the field's heading came from)."""
        att, mag = self._recent["att"], self._recent["mag"]
        if not att:
            return rotation(q0) @ np.mean([v for _, v in mag], axis=0)
        times = np.array([s for s, _ in att])
        world = []
        for s, v in mag:
            q = att[int(np.argmin(np.abs(times - s)))][1]
            world.append(rotation(q / np.linalg.norm(q)) @ v)
        return np.mean(world, axis=0)

    def _start(self, t0: float, fix: np.ndarray, std: np.ndarray) -> None:
        """The filter starts at the first fix that can start it (``_ready``): its position and
        velocity, the latest attitude of the autopilot, else the accelerometer's tilt with the
        magnetic heading, else the tilt with yaw unknown. How is noted."""
        c = self.config
        att, imu, mag = self._recent["att"], self._recent["imu"], self._recent["mag"]
        yaw_std = c.init_att_std_deg
        waited = f" ({self._unready} earlier fix(es) waited for the IMU and a heading)" if self._unready else ""
        if att:
            q0 = att[-1][1] / np.linalg.norm(att[-1][1])
            how = "the autopilot's attitude"
        else:
            q0 = tilt(np.mean([v[:3] for _, v in imu], axis=0))
            if "mag" in self.aiding and mag:
                q0 = magnetic_yaw(q0, np.mean([v for _, v in mag], axis=0))
                yaw_std = c.init_mag_yaw_std_deg
                how = f"the accelerometer's tilt and the magnetic heading (yaw std {yaw_std:g} deg)"
            else:
                yaw_std = c.init_yaw_std_deg
                how = f"the accelerometer's tilt, yaw unknown: 0 (std {yaw_std:g} deg)"
        yaw = math.degrees(math.atan2(2 * (q0[3] * q0[2] + q0[0] * q0[1]), 1 - 2 * (q0[1] ** 2 + q0[2] ** 2)))
        self.notes.append(f"filter: started at t = {t0:.3f} s from {how}, yaw {yaw:.0f} deg ENU{waited}")
        n = self.n
        rest = np.r_[[c.init_vel_std] * 3, np.deg2rad([c.init_att_std_deg] * 2 + [yaw_std]), [c.accel_bias_std] * 3,
                     [c.gyro_bias_std] * 3]
        p0, v0 = fix[:, :3], fix[:, 3:]
        q0n = np.broadcast_to(q0, (n, 4))
        if std.ndim == 1:
            P0 = np.broadcast_to(np.diag(np.r_[std[:3], rest] ** 2), (n, 15, 15))
        else:                                           # each flight's receiver accuracy
            P0 = np.stack([np.diag(np.r_[s[:3], rest] ** 2) for s in std])
        imu_t = [s for s, _ in self._recent["imu"]]
        dt = float(np.median(np.diff(imu_t))) if len(imu_t) > 2 else 1.0 / c.imu_rate_hz
        dt = max(dt, 1.0 / c.imu_rate_hz)               # the filter's step after averaging
        self._q0 = q0
        field = None
        if "mag" in self.aiding and self._recent["mag"]:
            field = self._field(q0)
            self._field_sum, self._field_n = field * len(self._recent["mag"]), len(self._recent["mag"])
        self._baro_offset, self._baro_diffs = None, []
        if self.backend == "numeric":
            from quadformer.estimator.numeric.filter import NumericFilter

            self.filter = NumericFilter(p0, v0, q0n, P0, noise_for(c, dt, field), dt, t0, c.gps_rate_hz,
                                        self.aiding, c.max_gap_s)
        else:
            import torch

            from quadformer.estimator.eskf import init_state
            from quadformer.estimator.online_filter import OnlineFilter

            z = np.zeros((n, 3))
            ekf0 = init_state(*(torch.as_tensor(np.array(a)) for a in (p0, v0, q0n, z, z, P0)))
            self.filter = OnlineFilter(ekf0, noise_model_for(c, dt, field), dt, t0, c.gps_rate_hz, self.aiding,
                                       c.max_gap_s)
        self.t0 = t0
        self._fused: dict[float, tuple[np.ndarray, float]] = {}   # measurement time -> (fix, stamp)
        self._recent = {k: deque() for k in self._recent}
