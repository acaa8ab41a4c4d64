"""PX4 ULog writer: ``write_ulog(log, path)``, one flight through pyulog's ``ULog`` objects and
``write_ulog``.

Topics in PX4 v1.14's message layouts (their fields below; pyulog's own format and
subscription classes hold them), each at its stream's own times (``timestamp`` =
``timestamp_sample`` = the vehicle's clock in microseconds):

* imu -> ``sensor_combined`` (``gyro_rad``, ``accelerometer_m_s2``, FRD; the accelerometer at
  the gyro's time);
* gps -> ``vehicle_gps_position`` (what EKF2 fuses and the reader prefers): ``latitude_deg``,
  ``longitude_deg``, ``altitude_msl_m``, ``vel_n/e/d_m_s``, ``fix_type`` (3 when not logged),
  ``eph``, ``epv``, ``s_variance_m_s`` (speed accuracy), ``time_utc_usec`` the time of the
  fix's measurement (``LogHeader.utc0`` + its epoch, ``writing.gps_utc``); ``satellites_used``
  and ``noise_per_ms`` as logged (0 when not: the noise from the receiver stream), dilution 1,
  jamming and spoofing states as logged (0, unknown, when not); with a receiver stream, its
  reports without a fix too (``writing.gps_reports``: the last fix repeated, its fix type below 2);
* baro -> ``vehicle_air_data`` (``baro_alt_meter`` = origin altitude + height above the origin:
  PX4 logs the barometric altitude above mean sea level; pressure and temperature from the
  standard atmosphere);
* mag -> ``vehicle_magnetometer`` (``magnetometer_ga``, gauss FRD);
* attitude -> ``vehicle_attitude`` (``q`` = w, x, y, z, body FRD -> NED);
* estimate -> ``vehicle_local_position`` (``x/y/z``, ``vx/vy/vz`` NED about ``ref_lat``/
  ``ref_lon``/``ref_alt`` = ``FlightLog.origin``; ``xy_reset_counter`` and ``z_reset_counter``
  count the ``reset`` rows);
* innovations -> ``estimator_innovations`` (``gps_hpos``, ``gps_vpos``, ``gps_hvel``,
  ``gps_vvel``: predicted minus measured, NED), ``estimator_innovation_variances`` (the same
  fields) and ``estimator_innovation_test_ratios`` (PX4's per-axis ratios, innovation^2 /
  (5^2 variance); where the stream has no variances, its one ratio per group: ratio_pos on both
  horizontal axes, ratio_vel on the three velocity axes, ratio_hgt on the vertical position);
  the other aiding sources' fields NaN;
* odometry -> ``vehicle_visual_odometry`` (``position`` and ``velocity`` NED, ``pose_frame``
  and ``velocity_frame`` NED, ``q``);
* truth -> ``vehicle_local_position_groundtruth`` (about the origin) and
  ``vehicle_attitude_groundtruth``;
* with ``LogHeader.airborne``, ``vehicle_status`` (``arming_state`` 2, armed; ``nav_state`` 3,
  AUTO_MISSION) and ``vehicle_land_detected`` (``landed`` false) at the first sample and
  every second.

The header carries ``sys_name``/``ver_hw``/``ver_sw`` naming the writer (not PX4 firmware),
``LogHeader.text`` as an INFO message and a few parameters (``EKF2_GPS_DELAY``:
``LogHeader.gps_delay_s`` in ms, 0 by default; the GPS gates, with ``LogHeader.params``). The
file is written atomically.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
from pyulog import ULog

from quadformer.geometry import frames
from quadformer.io import atomic_path
from quadformer.logs.flightlog import FlightLog
from quadformer.logs.writing import (GATE, LogHeader, clock_us, enu_to_ned, gps_reports, gps_utc, quat_ned_wxyz,
                                     start_us, values)

__all__ = ["TOPICS", "write_ulog"]

_LOCAL_POSITION = (
    "uint64_t timestamp;uint64_t timestamp_sample;uint64_t ref_timestamp;double ref_lat;double ref_lon;float x;"
    "float y;float z;float[2] delta_xy;float delta_z;float vx;float vy;float vz;float z_deriv;float[2] delta_vxy;"
    "float delta_vz;float ax;float ay;float az;float heading;float heading_var;float unaided_heading;"
    "float delta_heading;float tilt_var;float ref_alt;float dist_bottom;float eph;float epv;float evh;float evv;"
    "float vxy_max;float vz_max;float hagl_min;float hagl_max;bool xy_valid;bool z_valid;bool v_xy_valid;"
    "bool v_z_valid;uint8_t xy_reset_counter;uint8_t z_reset_counter;uint8_t vxy_reset_counter;"
    "uint8_t vz_reset_counter;uint8_t heading_reset_counter;bool heading_good_for_control;bool xy_global;"
    "bool z_global;bool dist_bottom_valid;uint8_t dist_bottom_sensor_bitfield;bool dead_reckoning;")
_ATTITUDE = ("uint64_t timestamp;uint64_t timestamp_sample;float[4] q;float[4] delta_q_reset;"
             "uint8_t quat_reset_counter;")
_INNOVATIONS = (
    "uint64_t timestamp;uint64_t timestamp_sample;float[2] gps_hvel;float gps_vvel;float[2] gps_hpos;"
    "float gps_vpos;float[2] ev_hvel;float ev_vvel;float[2] ev_hpos;float ev_vpos;float rng_vpos;float baro_vpos;"
    "float[2] aux_hvel;float[2] flow;float[2] terr_flow;float heading;float[3] mag_field;float[3] gravity;"
    "float[2] drag;float airspeed;float beta;float hagl;float hagl_rate;")
#: topic -> fields (PX4 v1.14's message definitions, without the trailing padding PX4 does not log)
TOPICS: dict[str, str] = {
    "sensor_combined": (
        "uint64_t timestamp;float[3] gyro_rad;uint32_t gyro_integral_dt;int32_t accelerometer_timestamp_relative;"
        "float[3] accelerometer_m_s2;uint32_t accelerometer_integral_dt;uint8_t accelerometer_clipping;"
        "uint8_t gyro_clipping;uint8_t accel_calibration_count;uint8_t gyro_calibration_count;"),
    "vehicle_gps_position": (
        "uint64_t timestamp;uint64_t timestamp_sample;double latitude_deg;double longitude_deg;"
        "double altitude_msl_m;double altitude_ellipsoid_m;uint64_t time_utc_usec;uint32_t device_id;"
        "float s_variance_m_s;float c_variance_rad;float eph;float epv;float hdop;float vdop;int32_t noise_per_ms;"
        "int32_t jamming_indicator;float vel_m_s;float vel_n_m_s;float vel_e_m_s;float vel_d_m_s;float cog_rad;"
        "int32_t timestamp_time_relative;float heading;float heading_offset;float heading_accuracy;"
        "float rtcm_injection_rate;uint16_t automatic_gain_control;uint8_t fix_type;uint8_t jamming_state;"
        "uint8_t spoofing_state;bool vel_ned_valid;uint8_t satellites_used;uint8_t selected_rtcm_instance;"
        "bool rtcm_crc_failed;uint8_t rtcm_msg_used;"),
    "vehicle_air_data": (
        "uint64_t timestamp;uint64_t timestamp_sample;uint32_t baro_device_id;float baro_alt_meter;"
        "float baro_temp_celcius;float baro_pressure_pa;float rho;float eas2tas;uint8_t calibration_count;"),
    "vehicle_magnetometer": ("uint64_t timestamp;uint64_t timestamp_sample;uint32_t device_id;"
                             "float[3] magnetometer_ga;uint8_t calibration_count;"),
    "vehicle_attitude": _ATTITUDE,
    "vehicle_local_position": _LOCAL_POSITION,
    "estimator_innovations": _INNOVATIONS,
    "estimator_innovation_variances": _INNOVATIONS,
    "estimator_innovation_test_ratios": _INNOVATIONS,
    "vehicle_visual_odometry": (
        "uint64_t timestamp;uint64_t timestamp_sample;float[3] position;float[4] q;float[3] velocity;"
        "float[3] angular_velocity;float[3] position_variance;float[3] orientation_variance;"
        "float[3] velocity_variance;uint8_t pose_frame;uint8_t velocity_frame;uint8_t reset_counter;"
        "int8_t quality;"),
    "vehicle_local_position_groundtruth": _LOCAL_POSITION,
    "vehicle_attitude_groundtruth": _ATTITUDE,
    "vehicle_status": (
        "uint64_t timestamp;uint64_t armed_time;uint64_t takeoff_time;uint64_t nav_state_timestamp;"
        "uint32_t valid_nav_states_mask;uint32_t can_set_nav_states_mask;uint16_t failure_detector_status;"
        "uint8_t arming_state;uint8_t latest_arming_reason;uint8_t latest_disarming_reason;"
        "uint8_t nav_state_user_intention;uint8_t nav_state;uint8_t executor_in_charge;uint8_t hil_state;"
        "uint8_t vehicle_type;bool failsafe;bool failsafe_and_user_took_over;uint8_t failsafe_defer_state;"
        "bool gcs_connection_lost;uint8_t gcs_connection_lost_counter;bool high_latency_data_link_lost;"
        "bool is_vtol;bool is_vtol_tailsitter;bool in_transition_mode;bool in_transition_to_fw;"
        "uint8_t system_type;uint8_t system_id;uint8_t component_id;bool safety_button_available;"
        "bool safety_off;bool power_input_valid;bool usb_connected;bool open_drone_id_system_present;"
        "bool open_drone_id_system_healthy;bool parachute_system_present;bool parachute_system_healthy;"
        "bool avoidance_system_required;bool avoidance_system_valid;bool rc_calibration_in_progress;"
        "bool calibration_enabled;bool pre_flight_checks_pass;"),
    "vehicle_land_detected": (
        "uint64_t timestamp;bool freefall;bool ground_contact;bool maybe_landed;bool landed;bool in_ground_effect;"
        "bool in_descend;bool has_low_throttle;bool vertical_movement;bool horizontal_movement;"
        "bool rotational_movement;bool close_to_ground_or_skipped_check;bool at_rest;"),
}
#: parameters every written log carries: the receiver latency (0; ``LogHeader.gps_delay_s`` sets it)
#: and EKF2's default GPS gates (the test ratios' scale)
PARAMS = {"EKF2_GPS_DELAY": 0.0, "EKF2_GPS_P_GATE": GATE, "EKF2_GPS_V_GATE": GATE}
ARMING_STATE_ARMED = 2
NAV_STATE_AUTO_MISSION = 3
VEHICLE_TYPE_ROTARY_WING = 1
FRAME_NED = 1                          # vehicle_odometry POSE_FRAME_NED, VELOCITY_FRAME_NED
_P0, _T0, _LAPSE = 101_325.0, 288.15, 0.0065   # standard atmosphere: Pa, K, K/m
_R_AIR = 287.05                                 # J/(kg K)


class _Topics:
    """A ULog from scratch: pyulog's format, subscription and data objects, one per topic."""

    def __init__(self, start: int) -> None:
        self.ulog = ULog(None)
        self.ulog._start_timestamp = start          # the header's stamp: the log's first sample
        self.ulog._file_version = 1

    def info(self, key: str, value: str) -> None:
        self.ulog.msg_info_dict[key] = value
        self.ulog._msg_info_dict_types[key] = f"char[{len(value.encode())}]"

    def add(self, name: str, stamps: np.ndarray, columns: dict[str, np.ndarray | float]) -> None:
        """Topic ``name``: one sample per stamp, its fields from ``columns`` (vectors as ``name[i]``
        or an (n, k) array under the base name; scalars broadcast; absent fields 0)."""
        u = self.ulog
        u.message_formats[name] = ULog.MessageFormat(f"{name}:{TOPICS[name]}".encode(), None)
        sub = ULog._MessageAddLogged(struct.pack("<BH", 0, len(u.data_list)) + name.encode(), None,
                                     u.message_formats)
        rows = np.zeros(len(stamps), dtype=sub.dtype)
        rows["timestamp"] = stamps
        if "timestamp_sample" in rows.dtype.names:
            rows["timestamp_sample"] = stamps
        for key, v in columns.items():
            v = np.asarray(v)
            if v.ndim == 2:
                for i in range(v.shape[1]):
                    rows[f"{key}[{i}]"] = v[:, i]
            else:
                rows[key] = v
        sub.buffer = bytearray(rows.tobytes())
        u.data_list.append(ULog.Data(sub))

    def text(self, stamp: int, message: str, level: str = "6") -> None:
        data = struct.pack("<BQ", ord(level), stamp) + message.encode()
        self.ulog.logged_messages.append(ULog.MessageLogging(data, None))


def write_ulog(log: FlightLog, path: str | Path, header: LogHeader = LogHeader()) -> Path:
    """Write ``log`` as a PX4 ULog file at ``path`` (see the module docstring); ValueError for a
    log without streams or a local origin."""
    from quadformer import __version__

    path = Path(path)
    if not all(math.isfinite(v) for v in log.origin):
        raise ValueError(f"{log.path}: the FlightLog has no origin (lat, lon, alt); ULog positions are "
                         "geodetic or about the estimator's reference")
    t0 = start_us(log)
    out = _Topics(t0)
    for key, value in (("sys_name", "quadformer"), ("ver_hw", "QUADFORMER_SIM"), ("ver_sw", __version__),
                       ("sys_os_name", "simulation")):
        out.info(key, value)
    for name, value in {**PARAMS, "EKF2_GPS_DELAY": round(1e3 * header.gps_delay_s, 3), **header.params}.items():
        out.ulog.initial_parameters[name] = float(value)
    out.text(t0, header.text)
    for write in (_imu, _gps, _baro, _mag, _attitude, _estimate, _innovations, _odometry, _truth):
        write(out, log, header)
    if header.airborne:
        _status(out, log, t0)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        out.ulog.write_ulog(fh)
    return path


def _imu(out: _Topics, log: FlightLog, header: LogHeader) -> None:
    d = log.imu
    if d is None:
        return
    us = clock_us(log, d["t"].to_numpy())
    dt = np.diff(us, prepend=us[0] - (us[1] - us[0] if len(us) > 1 else 0))
    out.add("sensor_combined", us, {"gyro_rad": frames.frd_to_flu(values(d, "gx", "gy", "gz")),
                                    "accelerometer_m_s2": frames.frd_to_flu(values(d, "ax", "ay", "az")),
                                    "gyro_integral_dt": dt, "accelerometer_integral_dt": dt})


def _gps(out: _Topics, log: FlightLog, header: LogHeader) -> None:
    d = gps_reports(log)
    if d is None:
        return
    t = d["t"].to_numpy()
    utc = gps_utc(header, t)
    v = enu_to_ned(d, "vx", "vy", "vz")
    col = {k: d[k].to_numpy(dtype=float) for k in ("fix_type", "satellites", "jamming", "spoofing")}
    out.add("vehicle_gps_position", clock_us(log, t), {
        "latitude_deg": d["lat"].to_numpy(), "longitude_deg": d["lon"].to_numpy(),
        "altitude_msl_m": d["alt"].to_numpy(), "altitude_ellipsoid_m": d["alt"].to_numpy(),
        "time_utc_usec": np.round(utc * 1e6) if utc is not None else 0,
        "s_variance_m_s": d["speed_acc"].to_numpy(), "c_variance_rad": np.nan, "eph": d["eph"].to_numpy(),
        "epv": d["epv"].to_numpy(), "hdop": 1.0, "vdop": 1.0, "vel_m_s": np.hypot(v[:, 0], v[:, 1]),
        "vel_n_m_s": v[:, 0], "vel_e_m_s": v[:, 1], "vel_d_m_s": v[:, 2], "cog_rad": np.arctan2(v[:, 1], v[:, 0]),
        "heading": np.nan, "heading_offset": np.nan, "heading_accuracy": np.nan,
        "fix_type": np.where(np.isfinite(col["fix_type"]), col["fix_type"], 3),
        "satellites_used": np.nan_to_num(col["satellites"]), "jamming_state": np.nan_to_num(col["jamming"]),
        "noise_per_ms": np.nan_to_num(d["noise"].to_numpy(dtype=float)),
        "spoofing_state": np.nan_to_num(col["spoofing"]), "vel_ned_valid": np.isfinite(v).all(axis=1)})


def _baro(out: _Topics, log: FlightLog, header: LogHeader) -> None:
    d = log.baro
    if d is None:
        return
    alt = log.origin[2] + d["alt"].to_numpy(dtype=float)                # above mean sea level
    temp = _T0 - _LAPSE * alt
    press = _P0 * (temp / _T0) ** 5.25588
    out.add("vehicle_air_data", clock_us(log, d["t"].to_numpy()), {
        "baro_alt_meter": alt, "baro_temp_celcius": temp - 273.15, "baro_pressure_pa": press,
        "rho": press / (_R_AIR * temp), "eas2tas": 1.0})


def _mag(out: _Topics, log: FlightLog, header: LogHeader) -> None:
    d = log.mag
    if d is None:
        return
    out.add("vehicle_magnetometer", clock_us(log, d["t"].to_numpy()),
            {"magnetometer_ga": frames.frd_to_flu(values(d, "mx", "my", "mz"))})


def _attitude(out: _Topics, log: FlightLog, header: LogHeader) -> None:
    d = log.attitude
    if d is None:
        return
    out.add("vehicle_attitude", clock_us(log, d["t"].to_numpy()), {"q": quat_ned_wxyz(d)})


def _local_position(log: FlightLog, d, resets: np.ndarray | None) -> dict:
    p, v = enu_to_ned(d, "x", "y", "z"), enu_to_ned(d, "vx", "vy", "vz")
    lat, lon, alt = log.origin
    counter = np.cumsum(resets) % 256 if resets is not None else 0
    nan = np.nan
    return {"ref_timestamp": start_us(log), "ref_lat": lat, "ref_lon": lon, "ref_alt": alt, "x": p[:, 0],
            "y": p[:, 1], "z": p[:, 2], "vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2], "z_deriv": v[:, 2],
            "ax": nan, "ay": nan, "az": nan, "heading": nan, "heading_var": nan, "unaided_heading": nan,
            "tilt_var": nan, "dist_bottom": nan, "eph": nan, "epv": nan, "evh": nan, "evv": nan, "vxy_max": nan,
            "vz_max": nan, "hagl_min": nan, "hagl_max": nan, "xy_valid": True, "z_valid": True,
            "v_xy_valid": True, "v_z_valid": True, "xy_reset_counter": counter, "z_reset_counter": counter,
            "heading_good_for_control": True, "xy_global": True, "z_global": True}


def _estimate(out: _Topics, log: FlightLog, header: LogHeader) -> None:
    d = log.estimate
    if d is None:
        return
    out.add("vehicle_local_position", clock_us(log, d["t"].to_numpy()),
            _local_position(log, d, d["reset"].to_numpy(dtype=np.int64)))


def _innovations(out: _Topics, log: FlightLog, header: LogHeader) -> None:
    d = log.innovations
    if d is None:
        return
    us = clock_us(log, d["t"].to_numpy())
    n = len(us)
    others = {k: (np.full((n, w), np.nan) if w else np.full(n, np.nan)) for k, w in   # other aiding sources
              (("ev_hvel", 2), ("ev_vvel", 0), ("ev_hpos", 2), ("ev_vpos", 0), ("rng_vpos", 0), ("baro_vpos", 0),
               ("aux_hvel", 2), ("flow", 2), ("terr_flow", 2), ("heading", 0), ("mag_field", 3), ("gravity", 3),
               ("drag", 2), ("airspeed", 0), ("beta", 0), ("hagl", 0), ("hagl_rate", 0))}

    def gps(pos: np.ndarray, vel: np.ndarray) -> dict:
        return {"gps_hpos": pos[:, :2], "gps_vpos": pos[:, 2], "gps_hvel": vel[:, :2], "gps_vvel": vel[:, 2],
                **others}

    out.add("estimator_innovations", us, gps(enu_to_ned(d, "pos_x", "pos_y", "pos_z"),
                                             enu_to_ned(d, "vel_x", "vel_y", "vel_z")))
    var = {k: frames.ned_var_to_enu(values(d, *(f"var_{k}_{a}" for a in "xyz"))) for k in ("pos", "vel")}
    out.add("estimator_innovation_variances", us, gps(var["pos"], var["vel"]))
    ratio = _test_ratios(d)
    out.add("estimator_innovation_test_ratios", us, gps(frames.ned_var_to_enu(ratio["pos"]),
                                                        frames.ned_var_to_enu(ratio["vel"])))


def _test_ratios(d) -> dict[str, np.ndarray]:
    """PX4's per-axis test ratios (ENU, (n, 3) for position and velocity) of an innovations
    stream: innovation^2 / (gate^2 variance), EKF2's ``setEstimatorAidStatusTestRatio`` with the
    5-sigma gates written (EKF2_GPS_P_GATE, EKF2_GPS_V_GATE); where an axis's variance is not
    known, its group's ratio column (ratio_pos on both horizontal axes, ratio_hgt vertically,
    ratio_vel on the three velocity axes)."""
    out = {}
    for k, fallback in (("pos", ("ratio_pos", "ratio_pos", "ratio_hgt")), ("vel", ("ratio_vel",) * 3)):
        innov = values(d, *(f"{k}_{a}" for a in "xyz"))
        var = values(d, *(f"var_{k}_{a}" for a in "xyz"))
        with np.errstate(divide="ignore", invalid="ignore"):
            r = innov ** 2 / (GATE ** 2 * var)
        out[k] = np.where(np.isfinite(r), r, values(d, *fallback))
    return out


def _odometry(out: _Topics, log: FlightLog, header: LogHeader) -> None:
    d = log.odometry
    if d is None:
        return
    nan3 = np.full((len(d), 3), np.nan)
    out.add("vehicle_visual_odometry", clock_us(log, d["t"].to_numpy()), {
        "position": enu_to_ned(d, "x", "y", "z"), "q": quat_ned_wxyz(d), "velocity": enu_to_ned(d, "vx", "vy", "vz"),
        "angular_velocity": nan3, "position_variance": nan3, "orientation_variance": nan3,
        "velocity_variance": nan3, "pose_frame": FRAME_NED, "velocity_frame": FRAME_NED, "quality": 100})


def _truth(out: _Topics, log: FlightLog, header: LogHeader) -> None:
    d = log.truth
    if d is None:
        return
    us = clock_us(log, d["t"].to_numpy())
    out.add("vehicle_local_position_groundtruth", us, _local_position(log, d, None))
    out.add("vehicle_attitude_groundtruth", us, {"q": quat_ned_wxyz(d)})


def _status(out: _Topics, log: FlightLog, t0: int) -> None:
    """Armed, in an autonomous mission, not landed: at the first sample and every second."""
    end = max(int(clock_us(log, [df["t"].iloc[-1]])[0]) for df in log.streams.values())
    us = np.arange(t0, end + 1, 1_000_000, dtype=np.int64)
    out.add("vehicle_status", us, {"armed_time": t0, "takeoff_time": t0, "nav_state_timestamp": t0,
                                   "arming_state": ARMING_STATE_ARMED, "nav_state": NAV_STATE_AUTO_MISSION,
                                   "nav_state_user_intention": NAV_STATE_AUTO_MISSION,
                                   "vehicle_type": VEHICLE_TYPE_ROTARY_WING, "system_type": 2, "system_id": 1,
                                   "component_id": 1, "safety_off": True, "pre_flight_checks_pass": True})
    out.add("vehicle_land_detected", us, {"landed": False, "maybe_landed": False, "ground_contact": False})
