"""MAVLink's sensor messages: pure conversions between MAVLink messages and the timestamped
samples every source of flights produces (a live link, a telemetry log; ``sensors.samples``,
importable from here too), in SI units, world ENU, body FLU (``geometry.frames`` does the frame
changes).

Decoding (``decode(msg) -> list of samples``; one message may carry several):

- ``HIGHRES_IMU`` -> ``Imu``, ``Mag``, ``Baro`` as ``fields_updated`` marks them: acceleration
  m/s^2 and rate rad/s FRD -> FLU, field gauss FRD -> FLU, ``pressure_alt`` m.
- ``SCALED_IMU``, ``SCALED_IMU2``, ``SCALED_IMU3`` -> ``Imu``, ``Mag``: mG, mrad/s, mgauss, FRD -> FLU.
- ``RAW_IMU`` -> as ``SCALED_IMU``: ArduPilot sends RAW_IMU in that scaling (mG, mrad/s,
  mgauss), not in raw sensor units (other autopilots' raw ADC counts are not supported).
- ``GPS_RAW_INT`` (receiver 0), ``GPS2_RAW`` (receiver 1) -> ``Gps``: lat/lon 1e-7 deg, alt mm
  (MSL); ground speed cm/s and course over ground cdeg -> ENU velocity, vertical NaN (the
  message has none; ``ResidueStream`` derives it); h_acc, v_acc mm and vel_acc mm/s -> eph,
  epv, speed accuracy (NaN when 0 or UINT32_MAX). ``eph``/``epv`` of these messages are
  dilutions of precision, not metres, and are not used.
- ``ODOMETRY`` -> ``Odometry``: north-aligned world frames only (NED: LOCAL_NED and the legacy
  MOCAP/VISION/ESTIM_NED; ENU: LOCAL_ENU and the legacy ENU ones; LOCAL_FRD/FLU are aligned
  with the vehicle's initial heading and are refused); the velocity in the child (body) frame
  or the world frame, rotated to world ENU; the quaternion (w, x, y, z) -> xyzw FLU -> ENU.
- ``ATTITUDE`` -> ``Attitude``: roll, pitch, yaw (NED/FRD, Z-Y-X) -> quaternion FLU -> ENU.
- ``SCALED_PRESSURE`` -> ``Baro``: press_abs hPa -> altitude in the standard atmosphere.
- ``GLOBAL_POSITION_INT``, ``LOCAL_POSITION_NED`` -> ``Estimate``: the autopilot's own
  estimate (reports only).
- ``GPS_GLOBAL_ORIGIN``, ``HOME_POSITION`` -> ``Origin``: lat/lon 1e-7 deg, alt mm.
- ``SYSTEM_TIME`` -> ``SystemTime``: maps UNIX-epoch stamps to time since boot.

``gps_status(msg)`` (not part of ``decode``) gives the receiver's own report in ``GPS_RAW_INT`` /
``GPS2_RAW`` as ``GpsStatus`` whether or not it holds a position: a receiver without a fix still
says so (fix_type 0/1), which ``Gps`` samples, needing a position, cannot.

``estimator_ratios(msg)`` (not part of ``decode`` either: it is the autopilot's evidence, not a
sensor) gives its innovation test ratios as ``EstimatorRatios``, each the square root of a test
ratio (1 at the gate):

- ArduPilot's ``EKF_STATUS_REPORT`` (``send_status_report`` of AP_NavEKF2/AP_NavEKF3's core, of
  the primary core): ``velocity_variance``, ``pos_horiz_variance``, ``pos_vert_variance``,
  ``compass_variance`` hold, despite their names, sqrt(velTestRatio), sqrt(posTestRatio),
  sqrt(hgtTestRatio) and the largest magnetometer one (EKF2: the length of the three), the
  values XKF4 logs as SV, SP, SH, SM (``logs.ardupilot_ratios``); ``terrain_alt_variance`` the
  range finder's or optical flow's (0 when neither is used), ``airspeed_variance`` the
  airspeed's; ``flags`` EKF_STATUS_FLAGS (EKF_GPS_GLITCHING 32768). The message has no time.
- PX4's ``ESTIMATOR_STATUS`` (the primary ``estimator_status``): ``vel_ratio``,
  ``pos_horiz_ratio``, ``pos_vert_ratio``, ``mag_ratio``, ``hagl_ratio``, ``tas_ratio`` are
  EKF2's ``vel_test_ratio``, ... each sqrt of the largest per-axis ratio of its group
  (``Ekf::get_innovation_test_status``; per axis innovation^2 / (gate^2 variance));
  ``flags`` ESTIMATOR_STATUS_FLAGS (ESTIMATOR_GPS_GLITCH 1024); ``pos_horiz_accuracy``,
  ``pos_vert_accuracy`` m; stamped ``time_usec``. The innovation check flags of
  ``estimator_status`` are not in the MAVLink message.

The vehicle's events (``VehicleEvents``, ``vehicle_heartbeat``, ``text_event``, ``TEXT_EVENTS``)
are ``sensors.vehicle_events``'s, importable from here too.

Times are the vehicle's own stamps in seconds: ``time_usec * 1e-6`` or ``time_boot_ms * 1e-3``.
Sentinels (UINT16_MAX ground speed or course, INT32_MAX latitude, NaN quaternion, ...) give no
value rather than a wrong one; a message without any usable value gives no sample.

Encoding (``encode_*``) is the inverse, for test senders: SI samples to message objects with
the same quantisation a vehicle applies (1e-7 deg, mm, cm/s, cdeg, float32).
"""

from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from quadformer.geometry.frames import (
    euler_to_quat,
    ned_to_enu,
    quat_ned_frd_to_enu_flu,
    quat_to_euler,
    quat_to_matrix,
    wxyz_to_xyzw,
    xyzw_to_wxyz,
)
from quadformer.sensors.samples import (Attitude, Baro, Estimate, EstimatorRatios, Gps, GpsStatus, Imu, Mag, Odometry,
                                       Origin, SystemTime)
from quadformer.sensors.vehicle_events import (  # noqa: F401 (re-exported)
    ARMED, NOT_VEHICLES, ON_GROUND, TEXT_EVENTS, VehicleEvents, text_event, vehicle_heartbeat)

__all__ = ["ARMED", "Attitude", "Baro", "Estimate", "EstimatorRatios", "Gps", "GpsStatus", "Imu", "Mag", "Odometry",
           "Origin", "RATIO_MESSAGES", "SystemTime", "TEXT_EVENTS", "VehicleEvents", "decode", "estimator_ratios",
           "gps_status", "text_event", "vehicle_heartbeat", "pressure_altitude", "altitude_pressure", "mavlink2"]

G = 9.80665                      # m/s^2 per g (MAVLink's mG)
P0_HPA = 1013.25                 # hPa, standard sea-level pressure
T0_K = 288.15                    # K, standard sea-level temperature
LAPSE = 0.0065                   # K/m, troposphere lapse rate
EXPONENT = 0.190263              # R L / (g M) of the standard atmosphere
UINT16_MAX = 65535
UINT32_MAX = 4294967295
INT32_MAX = 2147483647

#: HIGHRES_IMU.fields_updated bits
HIGHRES_ACC, HIGHRES_GYRO, HIGHRES_MAG, HIGHRES_PRESSURE_ALT = 0x0007, 0x0038, 0x01C0, 0x0800

#: world frames of ODOMETRY whose axes point north/east (MAV_FRAME numbers; 14-19 are the
#: legacy MOCAP/VISION/ESTIM frames, reserved in recent dialects)
NED_FRAMES = {1: "LOCAL_NED", 14: "MOCAP_NED", 16: "VISION_NED", 18: "ESTIM_NED"}
ENU_FRAMES = {4: "LOCAL_ENU", 15: "MOCAP_ENU", 17: "VISION_ENU", 19: "ESTIM_ENU"}
BODY_FRD, BODY_FLU = 12, 13      # MAV_FRAME_BODY_FRD; 13: legacy MAV_FRAME_BODY_FLU

GPS_MESSAGES = {"GPS_RAW_INT": 0, "GPS2_RAW": 1}
IMU_MESSAGES = ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3")   # preference order


# -- units ----------------------------------------------------------------------------------
def pressure_altitude(press_hpa: float) -> float:
    """Altitude (m) of a static pressure (hPa) in the standard atmosphere (troposphere)."""
    return T0_K / LAPSE * (1.0 - (press_hpa / P0_HPA) ** EXPONENT)


def altitude_pressure(alt_m: float) -> float:
    """Static pressure (hPa) at an altitude (m) in the standard atmosphere; inverse of
    ``pressure_altitude``."""
    return P0_HPA * (1.0 - LAPSE * alt_m / T0_K) ** (1.0 / EXPONENT)


def _frd(x: float, y: float, z: float, scale: float) -> np.ndarray:
    return np.array([x * scale, -y * scale, -z * scale])          # FRD -> FLU


def _acc(v: int, scale: float) -> float:
    """An accuracy field (mm or mm/s) in m or m/s; 0 (not sent) and UINT32_MAX give NaN."""
    return math.nan if v == 0 or v >= UINT32_MAX else v * scale


# -- decoding -------------------------------------------------------------------------------
def _highres_imu(m) -> list:
    t = m.time_usec * 1e-6
    bits = m.fields_updated
    src = f"HIGHRES_IMU#{m.id}"
    out: list = []
    if bits & HIGHRES_MAG:
        field = _frd(m.xmag, m.ymag, m.zmag, 1.0)
        if np.isfinite(field).all() and field.any():
            out.append(Mag(t, field, src))
    if bits & HIGHRES_PRESSURE_ALT and math.isfinite(m.pressure_alt):
        out.append(Baro(t, float(m.pressure_alt), src))
    if bits & (HIGHRES_ACC | HIGHRES_GYRO) or bits == 0:
        # fields_updated 0: a sender that does not fill the bitmap; acceleration and rates only
        x = np.concatenate([_frd(m.xacc, m.yacc, m.zacc, 1.0), _frd(m.xgyro, m.ygyro, m.zgyro, 1.0)])
        if np.isfinite(x).all():
            out.append(Imu(t, x, src))
    return out


def _scaled_imu(m, t: float, src: str) -> list:
    """SCALED_IMU* and ArduPilot's RAW_IMU: mG, mrad/s, mgauss in FRD. A magnetometer
    reading of exactly zero means none (ArduPilot sends zeros without a compass)."""
    x = np.concatenate([_frd(m.xacc, m.yacc, m.zacc, G * 1e-3), _frd(m.xgyro, m.ygyro, m.zgyro, 1e-3)])
    out: list = []
    if m.xmag or m.ymag or m.zmag:
        out.append(Mag(t, _frd(m.xmag, m.ymag, m.zmag, 1e-3), src))
    out.append(Imu(t, x, src))
    return out


def _gps(m, instance: int) -> list:
    if m.lat >= INT32_MAX or m.lon >= INT32_MAX:
        return []
    if m.vel >= UINT16_MAX or (m.cog >= UINT16_MAX and m.vel):
        vel = np.full(3, np.nan)                             # speed or (a moving vehicle's) course unknown
    elif m.cog >= UINT16_MAX:
        vel = np.array([0.0, 0.0, math.nan])
    else:
        v, c = m.vel * 1e-2, math.radians(m.cog * 1e-2)
        vel = np.array([v * math.sin(c), v * math.cos(c), math.nan])   # course over ground from north, clockwise
    return [Gps(m.time_usec * 1e-6, instance, int(m.fix_type), m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3, vel,
                # accuracies are MAVLink 2 extensions: a MAVLink 1 message has none
                _acc(getattr(m, "h_acc", 0), 1e-3), _acc(getattr(m, "v_acc", 0), 1e-3),
                _acc(getattr(m, "vel_acc", 0), 1e-3),
                math.nan if m.satellites_visible == 255 else float(m.satellites_visible))]


def gps_status(m) -> GpsStatus | None:
    """The receiver's status in a ``GPS_RAW_INT`` (instance 0) or ``GPS2_RAW`` (1), fix or not;
    None for other messages."""
    instance = GPS_MESSAGES.get(m.get_type())
    if instance is None:
        return None
    return GpsStatus(m.time_usec * 1e-6, instance, int(m.fix_type),
                     math.nan if m.satellites_visible == 255 else float(m.satellites_visible),
                     _acc(getattr(m, "h_acc", 0), 1e-3), _acc(getattr(m, "v_acc", 0), 1e-3),
                     _acc(getattr(m, "vel_acc", 0), 1e-3))


#: the autopilots' estimator status messages ``estimator_ratios`` reads
RATIO_MESSAGES = ("EKF_STATUS_REPORT", "ESTIMATOR_STATUS")
EKF_GPS_GLITCHING = 32768            # EKF_STATUS_FLAGS bit (ArduPilot)
ESTIMATOR_GPS_GLITCH = 1024          # ESTIMATOR_STATUS_FLAGS bit (PX4)


def estimator_ratios(m) -> EstimatorRatios | None:
    """The autopilot's innovation test ratios in an ``EKF_STATUS_REPORT`` (ArduPilot, untimed:
    t NaN) or ``ESTIMATOR_STATUS`` (PX4); None for other messages."""
    kind = m.get_type()
    if kind == "EKF_STATUS_REPORT":
        flags = int(m.flags)
        return EstimatorRatios(math.nan, kind, float(m.velocity_variance), float(m.pos_horiz_variance),
                               float(m.pos_vert_variance), float(m.compass_variance), float(m.terrain_alt_variance),
                               float(getattr(m, "airspeed_variance", math.nan)), flags,
                               bool(flags & EKF_GPS_GLITCHING))
    if kind == "ESTIMATOR_STATUS":
        flags = int(m.flags)
        return EstimatorRatios(m.time_usec * 1e-6 if m.time_usec else math.nan, kind, float(m.vel_ratio),
                               float(m.pos_horiz_ratio), float(m.pos_vert_ratio), float(m.mag_ratio),
                               float(m.hagl_ratio), float(m.tas_ratio), flags, bool(flags & ESTIMATOR_GPS_GLITCH),
                               float(m.pos_horiz_accuracy), float(m.pos_vert_accuracy))
    return None


def _odometry(m) -> list:
    q = np.array(m.q, dtype=float)
    vel = np.array([m.vx, m.vy, m.vz], dtype=float)
    pos = np.array([m.x, m.y, m.z], dtype=float)
    if not (np.isfinite(q).all() and np.isfinite(vel).all()) or not q.any():
        return []
    q = wxyz_to_xyzw(q)
    q = q / np.linalg.norm(q)
    if m.frame_id in NED_FRAMES:
        if m.child_frame_id == BODY_FRD:
            v_world = quat_to_matrix(q) @ vel                  # body FRD -> world NED
        elif m.child_frame_id == m.frame_id or m.child_frame_id in NED_FRAMES:
            v_world = vel
        else:
            return []
        return [Odometry(m.time_usec * 1e-6, ned_to_enu(pos), ned_to_enu(v_world), quat_ned_frd_to_enu_flu(q))]
    if m.frame_id in ENU_FRAMES:
        if m.child_frame_id == BODY_FLU:
            v_world = quat_to_matrix(q) @ vel                  # body FLU -> world ENU
        elif m.child_frame_id == m.frame_id or m.child_frame_id in ENU_FRAMES:
            v_world = vel
        else:
            return []
        q = np.where(q[3] < 0, -q, q)
        return [Odometry(m.time_usec * 1e-6, pos, v_world, q)]
    return []


def _attitude(m) -> list:
    r = np.array([m.roll, m.pitch, m.yaw], dtype=float)
    if not np.isfinite(r).all():
        return []
    return [Attitude(m.time_boot_ms * 1e-3, quat_ned_frd_to_enu_flu(euler_to_quat(*r)))]


def _pressure(m) -> list:
    p = float(m.press_abs)
    if not (math.isfinite(p) and p > 0):
        return []
    return [Baro(m.time_boot_ms * 1e-3, pressure_altitude(p), "SCALED_PRESSURE")]


def _global_position(m) -> list:
    vel = ned_to_enu(np.array([m.vx, m.vy, m.vz], dtype=float) * 1e-2)
    return [Estimate(m.time_boot_ms * 1e-3, "global", np.array([m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3]), vel)]


def _local_position(m) -> list:
    return [Estimate(m.time_boot_ms * 1e-3, "local", ned_to_enu(np.array([m.x, m.y, m.z], dtype=float)),
                     ned_to_enu(np.array([m.vx, m.vy, m.vz], dtype=float)))]


_DECODERS = {
    "HIGHRES_IMU": _highres_imu,
    "SCALED_IMU": lambda m: _scaled_imu(m, m.time_boot_ms * 1e-3, "SCALED_IMU#0"),
    "SCALED_IMU2": lambda m: _scaled_imu(m, m.time_boot_ms * 1e-3, "SCALED_IMU#1"),
    "SCALED_IMU3": lambda m: _scaled_imu(m, m.time_boot_ms * 1e-3, "SCALED_IMU#2"),
    "RAW_IMU": lambda m: _scaled_imu(m, m.time_usec * 1e-6, f"RAW_IMU#{m.id}"),
    "GPS_RAW_INT": lambda m: _gps(m, 0),
    "GPS2_RAW": lambda m: _gps(m, 1),
    "ODOMETRY": _odometry,
    "ATTITUDE": _attitude,
    "SCALED_PRESSURE": _pressure,
    "GLOBAL_POSITION_INT": _global_position,
    "LOCAL_POSITION_NED": _local_position,
    "GPS_GLOBAL_ORIGIN": lambda m: [Origin(m.latitude * 1e-7, m.longitude * 1e-7, m.altitude * 1e-3,
                                           "GPS_GLOBAL_ORIGIN")],
    "HOME_POSITION": lambda m: [Origin(m.latitude * 1e-7, m.longitude * 1e-7, m.altitude * 1e-3, "HOME_POSITION")],
    "SYSTEM_TIME": lambda m: [SystemTime(m.time_unix_usec * 1e-6, m.time_boot_ms * 1e-3)] if m.time_unix_usec else [],
}

#: message types ``decode`` turns into samples
DECODED = tuple(_DECODERS)


def decode(msg) -> list:
    """The samples a pymavlink message carries (an empty list for other messages, or when
    it holds no usable value)."""
    f = _DECODERS.get(msg.get_type())
    return f(msg) if f is not None else []


# -- encoding (test senders) ----------------------------------------------------------------
def usec(t: float) -> int:
    return int(round(t * 1e6))


def msec(t: float) -> int:
    return int(round(t * 1e3))


def _to_frd(v: np.ndarray) -> tuple[float, float, float]:
    return float(v[0]), float(-v[1]), float(-v[2])


def encode_highres_imu(t: float, imu: np.ndarray | None = None, mag: np.ndarray | None = None,
                       pressure_alt: float | None = None, instance: int = 0):
    """HIGHRES_IMU at t (s) with those of: IMU (6,) FLU, field (3,) gauss FLU, pressure altitude (m)."""
    bits = 0
    acc = gyro = field = (0.0, 0.0, 0.0)
    if imu is not None:
        acc, gyro = _to_frd(imu[:3]), _to_frd(imu[3:6])
        bits |= HIGHRES_ACC | HIGHRES_GYRO
    if mag is not None:
        field = _to_frd(mag)
        bits |= HIGHRES_MAG
    if pressure_alt is not None:
        bits |= HIGHRES_PRESSURE_ALT
    return mavlink2.MAVLink_highres_imu_message(
        usec(t), *acc, *gyro, *field, 0.0, 0.0, float(pressure_alt or 0.0), 20.0, bits, instance)


def encode_gps_raw_int(t: float, lat: float, lon: float, alt: float, vel_enu: np.ndarray, eph: float = math.nan,
                       epv: float = math.nan, speed_acc: float = math.nan, fix_type: int = 3,
                       satellites: int = 10, instance: int = 0):
    """GPS_RAW_INT (instance 0) or GPS2_RAW (instance 1): position deg/m, horizontal ENU velocity
    as ground speed and course; accuracies in m (NaN: not sent)."""
    ve, vn = float(vel_enu[0]), float(vel_enu[1])
    if math.isfinite(ve) and math.isfinite(vn):
        vel = min(int(round(math.hypot(ve, vn) * 100)), UINT16_MAX - 1)
        cog = int(round(math.degrees(math.atan2(ve, vn)) * 100)) % 36000
    else:
        vel, cog = UINT16_MAX, UINT16_MAX
    mm = lambda v: 0 if not math.isfinite(v) else min(int(round(v * 1000)), UINT32_MAX - 1)   # noqa: E731
    lat_i, lon_i, alt_i = int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000))
    dop = UINT16_MAX
    if instance == 0:
        return mavlink2.MAVLink_gps_raw_int_message(usec(t), fix_type, lat_i, lon_i, alt_i, dop, dop, vel, cog,
                                                    satellites, alt_i, mm(eph), mm(epv), mm(speed_acc), 0, 0)
    return mavlink2.MAVLink_gps2_raw_message(usec(t), fix_type, lat_i, lon_i, alt_i, dop, dop, vel, cog,
                                             satellites, 0, 0, 0, alt_i, mm(eph), mm(epv), mm(speed_acc), 0)


def encode_attitude(t: float, q_enu_flu: np.ndarray):
    roll, pitch, yaw = quat_to_euler(quat_ned_frd_to_enu_flu(q_enu_flu))
    return mavlink2.MAVLink_attitude_message(msec(t), float(roll), float(pitch), float(yaw), 0.0, 0.0, 0.0)


def encode_scaled_pressure(t: float, alt: float):
    return mavlink2.MAVLink_scaled_pressure_message(msec(t), altitude_pressure(float(alt)), 0.0, 2000, 0)


def encode_odometry(t: float, pos_enu: np.ndarray, vel_enu: np.ndarray, q_enu_flu: np.ndarray):
    """ODOMETRY in LOCAL_NED with the velocity in BODY_FRD (as PX4 streams it)."""
    q_ned = quat_ned_frd_to_enu_flu(q_enu_flu)
    v_ned = ned_to_enu(vel_enu)                       # the same permutation both ways
    v_body = quat_to_matrix(q_ned).T @ v_ned
    nan21 = [math.nan] + [0.0] * 20
    return mavlink2.MAVLink_odometry_message(
        usec(t), 1, BODY_FRD, *map(float, ned_to_enu(pos_enu)), [float(v) for v in xyzw_to_wxyz(q_ned)],
        *map(float, v_body), 0.0, 0.0, 0.0, nan21, nan21, 0, mavlink2.MAV_ESTIMATOR_TYPE_VIO, 100)


def encode_ekf_status_report(vel: float, pos_horiz: float, pos_vert: float, mag: float = 0.0, terrain: float = 0.0,
                             airspeed: float = 0.0, flags: int = 0x1FF):
    """ArduPilot's EKF_STATUS_REPORT: the square roots of the test ratios (float32)."""
    return mavlink2.MAVLink_ekf_status_report_message(flags, vel, pos_horiz, pos_vert, mag, terrain, airspeed)


def encode_estimator_status(t: float, vel: float, pos_horiz: float, pos_vert: float, mag: float = 0.0,
                            hagl: float = 0.0, tas: float = 0.0, flags: int = 0x3FF,
                            pos_horiz_accuracy: float = 0.5, pos_vert_accuracy: float = 0.8):
    """PX4's ESTIMATOR_STATUS at t (s): the square roots of the test ratios (float32)."""
    return mavlink2.MAVLink_estimator_status_message(usec(t), flags, vel, pos_horiz, pos_vert, mag, hagl, tas,
                                                     pos_horiz_accuracy, pos_vert_accuracy)


def encode_origin(lat: float, lon: float, alt: float, t: float = 0.0):
    return mavlink2.MAVLink_gps_global_origin_message(int(round(lat * 1e7)), int(round(lon * 1e7)),
                                                      int(round(alt * 1000)), usec(t))
