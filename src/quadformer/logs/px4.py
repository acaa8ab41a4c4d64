"""PX4 ULog reader: ``read_ulog(path) -> FlightLog`` through pyulog.

Topics and fields read (instance 0 unless said otherwise; NED/FRD converted by ``frames``):

* imu: ``sensor_combined`` (the sensor voter's primary IMU): ``gyro_rad`` at ``timestamp``,
  ``accelerometer_m_s2`` at ``timestamp + accelerometer_timestamp_relative``; when that offset
  is not zero the accelerometer is interpolated to the gyro times (noted); an offset equal
  to the "invalid" marker 0x7fffffff drops the sample.
* gps: ``vehicle_gps_position`` (what the estimator uses), else ``sensor_gps``; each fix stamped
  at its epoch from ``time_utc_usec`` where the receiver gives it (``logs.receiver_clock``); position as
  ``lat``/``lon`` (1e-7 deg integers) and ``alt`` (mm) in older versions or
  ``latitude_deg``/``longitude_deg``/``altitude_msl_m`` in newer ones; ``vel_n/e/d_m_s`` (NaN
  where ``vel_ned_valid`` is 0); ``fix_type``, ``satellites_used``, ``eph``, ``epv``,
  ``s_variance_m_s`` (speed accuracy), ``jamming_state`` (else ``jamming_indicator``),
  ``spoofing_state``. Samples without a position fix (fix_type < 2) are dropped.
* receiver: every sample of the same topic instance and device, fix or not: ``fix_type``,
  ``satellites_used``, the accuracies, jamming and spoofing as in gps, ``noise_per_ms`` (noise).
* baro: ``vehicle_air_data.baro_alt_meter``, else the baro fields of old ``sensor_combined``.
* mag: ``vehicle_magnetometer.magnetometer_ga``, else old ``sensor_combined.magnetometer_ga``,
  else ``sensor_mag`` (raw, sensor frame; noted).
* innovations: ``estimator_innovations`` (``gps_hpos`` N/E, ``gps_vpos`` D, ``gps_hvel``,
  ``gps_vvel``) with ``estimator_innovation_variances`` and
  ``estimator_innovation_test_ratios`` matched by nearest time; or old ``ekf2_innovations``
  (``vel_pos_innov[0..5]`` = vel N/E/D, pos N/E/D, and ``vel_pos_innov_var``) with test ratios
  from ``estimator_status``. ratio_pos is the larger horizontal position ratio, ratio_vel the
  largest velocity ratio, ratio_hgt the vertical position ratio. With several estimator
  instances, rows come from the primary one named by ``estimator_selector_status``
  (multi-instance k is taken to be estimator instance k).
* estimate: ``vehicle_local_position`` (x/y/z, vx/vy/vz NED); its ``ref_lat``/``ref_lon``/
  ``ref_alt`` (valid when ``xy_global``) are the autopilot's local origin; ``reset`` is set
  where ``xy_reset_counter`` or ``z_reset_counter`` changes or the reference moves.
* odometry: ``vehicle_visual_odometry`` (``position``/``velocity``/``q`` with ``pose_frame``
  and ``velocity_frame`` in newer versions, ``x``/``vx``/``q`` with ``local_frame`` in older).
* truth (SITL): ``vehicle_local_position_groundtruth`` (or the global one) with
  ``vehicle_attitude_groundtruth.q`` interpolated to its times.
* events: ``vehicle_status.arming_state`` (2 = armed, in every PX4 version: older ones count
  INIT 0, STANDBY 1, ARMED 2, newer DISARMED 1, ARMED 2) and ``vehicle_land_detected.landed``
  changes -> armed / disarmed and takeoff (landed 1 -> 0) / landed (0 -> 1); a log that starts
  armed (in the air) begins with armed (takeoff) at its first sample, the detail saying so;
  ``vehicle_status.nav_state`` changes -> mode (the detail gives the number: its names changed
  between versions).

Times are seconds from the ULog header's start timestamp. ``timestamp_sample`` is used when
every sample has one (it is when the data was measured), else ``timestamp``.

Pitfalls handled (each noted in ``FlightLog.notes``):

* unsigned timestamps earlier than the log start: subtracted in signed arithmetic, so they
  become negative seconds rather than ~5.8e5 years; a timestamp of 0 (never set by the
  publisher, as for ``ekf2_innovations`` in some old logs) drops the sample;
* two sources in one GPS topic: several instances or several ``device_id`` values; the
  instance 0 / the device with most samples is kept, the others are listed;
* innovations slower than GPS: a stream of its own, at its own rate, never resampled;
* EKF resets: ``reset`` in ``estimate``, with the logged ``delta_xy``/``delta_z`` in notes;
* the local origin far from the first fix: the autopilot's reference is used as origin,
  so ``gps`` and ``estimate`` share one frame; a reference that moves during the log is
  re-expressed about the first one;
* field names and types that change between versions (see gps above);
* appended data sections (crash dumps): read by pyulog, noted;
* damaged files: pyulog reads from memory with its work bounded by the file size (over a
  damaged stretch its definitions parser otherwise does quadratic work);
* dropouts and gaps: logger dropouts are noted; gaps split ``segments``;
* several IMU or EKF instances: ``sensor_combined`` is the primary IMU; estimator topics are
  filtered by ``estimator_selector_status``.
"""

from __future__ import annotations

import contextlib
import math
from pathlib import Path

import numpy as np
import pandas as pd

from quadformer.geometry import frames
from quadformer.logs._series import first_fix, interp_linear, quat_interp
from quadformer.logs.flightlog import GPS_GAP, IMU_GAP, FlightLog, assemble, gps_stream, make_stream
from quadformer.logs.px4_estimator import UlogEstimator
from quadformer.logs.px4_topics import INVALID_RELATIVE, load_ulog

__all__ = ["read_ulog"]


def read_ulog(path: str | Path, *, imu_gap: float = IMU_GAP, gps_gap: float = GPS_GAP) -> FlightLog:
    """Read a PX4 ULog file into a FlightLog (see the module docstring for the mapping)."""
    path = Path(path)
    ulog = load_ulog(path)
    return _UlogReader(ulog, path).read(imu_gap, gps_gap)


class _UlogReader(UlogEstimator):
    # ---------------------------------------------------------------- streams
    def read(self, imu_gap: float, gps_gap: float) -> FlightLog:
        u = self.ulog
        if u.file_corruption:
            self.notes.append("file: pyulog reported corrupt data; the damaged messages were "
                              "skipped")
        if u.has_data_appended:
            self.notes.append(f"file: {len(u._appended_offsets)} appended data section(s) "
                              "(e.g. a crash dump) read by pyulog")
        if u.dropouts:
            total = sum(d.duration for d in u.dropouts)
            self.notes.append(f"file: {len(u.dropouts)} logger dropouts ({total} ms lost)")
        vehicle = self.vehicle()
        imu = self.imu()
        gps_raw, receiver = self.gps()
        est_raw, ref_origin = self.local_position()
        if ref_origin is not None:
            origin, origin_source = ref_origin, "autopilot local origin"
        elif gps_raw is not None:
            origin, origin_source = first_fix(gps_raw), "first GPS fix"
        else:
            origin, origin_source = (math.nan,) * 3, "none"
            self.notes.append("origin: no autopilot local origin and no GPS fix; origin is NaN")
        streams = {
            "imu": imu,
            "gps": gps_stream(gps_raw, origin, self.notes),
            "baro": self.baro(),
            "mag": self.mag(),
            "innovations": self.innovations(),
            "estimate": self.estimate_stream(est_raw, origin),
            "attitude": self.attitude(),
            "odometry": self.odometry(),
            "truth": self.truth(origin),
            "receiver": receiver,
        }
        return assemble("px4-ulog", self.path, streams, self.notes, vehicle, origin,
                        origin_source, imu_gap, gps_gap, boot_start=self.start * 1e-6,
                        events=self.events())

    def vehicle(self) -> dict:
        info = self.ulog.msg_info_dict
        out = {"autopilot": "PX4"}
        for key in ("sys_name", "ver_hw", "ver_hw_subtype", "ver_sw", "ver_sw_branch",
                    "sys_os_name", "sys_os_ver", "sys_mcu", "sys_uuid", "sys_toolchain"):
            if key in info:
                out[key] = info[key]
        with contextlib.suppress(Exception):
            release = self.ulog.get_version_info_str()
            if release:
                out["ver_sw_release"] = release
        delay = self.ulog.initial_parameters.get("EKF2_GPS_DELAY")
        if isinstance(delay, (int, float)) and math.isfinite(delay) and delay >= 0:
            out["gps_delay_s"] = float(delay) / 1000.0      # the receiver latency EKF2 compensates
        return out

    def imu(self):
        d = self.dataset("sensor_combined")
        if d is None:
            self.notes.append("imu: no sensor_combined topic")
            return None
        t = self.times(d, "imu", use_sample=False)
        gyro = self.vector(d, "gyro_rad", 3)
        acc = self.vector(d, "accelerometer_m_s2", 3)
        rel = self.field(d, "accelerometer_timestamp_relative", required=False)
        rel = np.zeros(len(t), np.int64) if rel is None else rel.astype(np.int64)
        invalid = rel == INVALID_RELATIVE
        t_acc = t + np.where(invalid, 0, rel) * 1e-6
        if invalid.any():
            acc[invalid] = np.nan
            self.notes.append(f"imu: {int(invalid.sum())} samples with an invalid accelerometer "
                              "timestamp dropped")
        offset = np.abs(t_acc - t)[~invalid & np.isfinite(t)]
        if len(offset) and offset.max() > 0:
            ok = ~invalid & np.isfinite(t_acc)
            order = np.argsort(t_acc[ok], kind="stable")
            acc = interp_linear(t, t_acc[ok][order], acc[ok][order])
            self.notes.append(f"imu: accelerometer interpolated to the gyro times (offset up to "
                              f"{offset.max() * 1e3:.3f} ms)")
        a, g = frames.frd_to_flu(acc), frames.frd_to_flu(gyro)
        return make_stream("imu", t, {"ax": a[:, 0], "ay": a[:, 1], "az": a[:, 2],
                                      "gx": g[:, 0], "gy": g[:, 1], "gz": g[:, 2]})

    def gps(self) -> tuple[dict | None, pd.DataFrame | None]:
        """The raw fixes of the GPS topic (fix_type >= 2) and its receiver stream (every sample)."""
        cands = [d for name in ("vehicle_gps_position", "sensor_gps") for d in self.instances(name)]
        if not cands:
            self.notes.append("gps: no vehicle_gps_position or sensor_gps topic")
            return None, None
        d = cands[0]
        others = [f"{o.name}[{o.multi_id}] ({len(o.data['timestamp'])} samples)" for o in cands[1:]]
        self.notes.append(f"gps: read {d.name}[{d.multi_id}] ({len(d.data['timestamp'])} samples)"
                          + (f"; not used: {', '.join(others)}" if others else ""))
        t = self.times(d, "gps")
        keep = np.ones(len(t), bool)
        dev = self.field(d, "device_id", required=False)
        if dev is not None:
            ids, counts = np.unique(dev, return_counts=True)
            if len(ids) > 1:
                best = ids[np.argmax(counts)]
                keep = dev == best
                dropped = ", ".join(f"{i} ({c} samples)" for i, c in zip(ids, counts) if i != best)
                self.notes.append(f"gps: {len(ids)} devices publish into {d.name}; kept device "
                                  f"{best} ({counts.max()} samples), dropped {dropped}")
        lat_f = self.field(d, "latitude_deg", "lat")
        lon_f = self.field(d, "longitude_deg", "lon")
        alt_f = self.field(d, "altitude_msl_m", "alt")
        if lat_f.dtype.kind in "iu":
            lat, lon = lat_f * 1e-7, lon_f * 1e-7
            self.notes.append("gps: lat/lon logged as 1e-7 deg integers (older PX4)")
        else:
            lat, lon = lat_f.astype(float), lon_f.astype(float)
        alt = alt_f * 1e-3 if alt_f.dtype.kind in "iu" else alt_f.astype(float)
        fix = self.field(d, "fix_type").astype(float)
        nofix = keep & (fix < 2)
        if nofix.any():
            self.notes.append(f"gps: dropped {int(nofix.sum())} samples without a position fix "
                              "(fix_type < 2; the receiver stream keeps them)")
        bad = keep & ~nofix & ((np.abs(lat) > 90) | (np.abs(lon) > 180) | ((lat == 0) & (lon == 0)))
        if bad.any():
            self.notes.append(f"gps: dropped {int(bad.sum())} samples with an invalid latitude/"
                              "longitude")
        device = keep.copy()
        keep &= ~nofix & ~bad & np.isfinite(t) & np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt)
        status = {k: np.asarray(v, dtype=float) for k, v in self.indicators(d, fix).items() if v is not None}
        noise = self.field(d, "noise_per_ms", required=False)
        receiver = make_stream("receiver", t[device], {
            **{k: v[device] for k, v in status.items()},
            **({} if noise is None else {"noise": np.asarray(noise, dtype=float)[device]})}, self.notes)
        if not keep.any():
            self.notes.append("gps: no sample with a valid fix")
            return None, receiver
        vel = np.stack([self.field(d, f"vel_{a}_m_s").astype(float) for a in "ned"], axis=-1)
        valid = self.field(d, "vel_ned_valid", required=False)
        if valid is not None and (valid[keep] == 0).any():
            vel[valid == 0] = np.nan
            self.notes.append(f"gps: velocity NaN in {int((valid[keep] == 0).sum())} samples "
                              "flagged vel_ned_valid = 0")
        out = {"t": t, "lat": lat, "lon": lon, "alt": alt, "vel": frames.ned_to_enu(vel), **status}
        utc = self.field(d, "time_utc_usec", required=False)
        if utc is not None:                 # the receiver's time of the fix: stamped at its epoch
            u = np.asarray(utc, dtype=float) * 1e-6
            out["tow"] = np.where(u > 1e9, u, np.nan)      # 0 until the receiver knows the time
        return {k: np.asarray(v, dtype=float)[keep] for k, v in out.items()}, receiver

    def indicators(self, d, fix: np.ndarray) -> dict[str, np.ndarray | None]:
        """The receiver's own indicators in a GPS topic (None where a version lacks one)."""
        jam = self.field(d, "jamming_state", required=False)
        if jam is None:
            jam = self.field(d, "jamming_indicator", required=False)
            if jam is not None:
                self.notes.append("gps: jamming is jamming_indicator (0-255; no jamming_state)")
        return {"fix_type": fix, "satellites": self.field(d, "satellites_used", required=False),
                "eph": self.field(d, "eph", required=False), "epv": self.field(d, "epv", required=False),
                "speed_acc": self.field(d, "s_variance_m_s", required=False), "jamming": jam,
                "spoofing": self.field(d, "spoofing_state", required=False)}

    def events(self) -> list[tuple[float, str, str]]:
        """Arming, takeoff and landing, and mode changes from the vehicle's status topics."""
        out: list[tuple[float, str, str]] = []
        for topic, field, on, off, is_on in (
                ("vehicle_status", "arming_state", "armed", "disarmed", lambda v: v == 2),
                ("vehicle_land_detected", "landed", "takeoff", "landed", lambda v: v == 0)):
            d = self.dataset(topic)
            values = None if d is None else self.field(d, field, required=False)
            if values is None:
                continue
            t = self.times(d, "events")
            state = is_on(np.asarray(values))
            if state[0]:
                out.append((float(t[0]), on, f"{topic}.{field} {values[0]} at the log's start"))
            for i in np.flatnonzero(state[1:] != state[:-1]) + 1:
                out.append((float(t[i]), on if state[i] else off, f"{topic}.{field} {values[i]}"))
        d = self.dataset("vehicle_status")
        nav = None if d is None else self.field(d, "nav_state", required=False)
        if nav is not None:
            t = self.times(d, "events")
            for i in np.r_[0, np.flatnonzero(nav[1:] != nav[:-1]) + 1]:
                out.append((float(t[i]), "mode", f"vehicle_status.nav_state {nav[i]}"))
        return out


    def baro(self):
        d = self.dataset("vehicle_air_data")
        if d is not None:
            return make_stream("baro", self.times(d, "baro"),
                               {"alt": self.field(d, "baro_alt_meter")})
        d = self.dataset("sensor_combined")
        if d is not None and "baro_alt_meter" in d.data:
            idx, t = self.embedded(d, "baro_timestamp_relative", "baro")
            return make_stream("baro", t, {"alt": d.data["baro_alt_meter"][idx]})
        self.notes.append("baro: no vehicle_air_data topic")
        return None

    def mag(self):
        d = self.dataset("vehicle_magnetometer")
        if d is not None:
            t, m = self.times(d, "mag"), self.vector(d, "magnetometer_ga", 3)
        else:
            d = self.dataset("sensor_combined")
            if d is not None and "magnetometer_ga[0]" in d.data:
                idx, t = self.embedded(d, "magnetometer_timestamp_relative", "mag")
                m = self.vector(d, "magnetometer_ga", 3)[idx]
            else:
                d = self.dataset("sensor_mag")
                if d is None:
                    self.notes.append("mag: no vehicle_magnetometer or sensor_mag topic")
                    return None
                t = self.times(d, "mag")
                m = np.stack([self.field(d, k).astype(float) for k in "xyz"], axis=-1)
                self.notes.append("mag: from sensor_mag (raw, in the sensor's own frame)")
        m = frames.frd_to_flu(m)
        return make_stream("mag", t, {"mx": m[:, 0], "my": m[:, 1], "mz": m[:, 2]})

    def odometry(self):
        d = self.dataset("vehicle_visual_odometry")
        if d is None:
            return None
        t = self.times(d, "odometry")
        if "position[0]" in d.data:      # v1.14+: position/velocity with pose_frame
            pos, vel = self.vector(d, "position", 3), self.vector(d, "velocity", 3)
            pose_frame = self.field(d, "pose_frame", required=False)
        else:                            # older: x/y/z, vx/vy/vz with local_frame
            pos = np.stack([self.field(d, k).astype(float) for k in "xyz"], axis=-1)
            vel = np.stack([self.field(d, k).astype(float) for k in ("vx", "vy", "vz")], axis=-1)
            pose_frame = self.field(d, "local_frame", required=False)
        # BODY_FRD is 3 in both layouts (VELOCITY_FRAME_BODY_FRD, BODY_FRAME_FRD)
        vel_frame = self.field(d, "velocity_frame", required=False)
        q = frames.wxyz_to_xyzw(self.vector(d, "q", 4))
        if vel_frame is not None and np.any(vel_frame == 3):
            b = vel_frame == 3
            vel[b] = frames.quat_rotate(frames.quat_normalize(q[b]), vel[b])
            self.notes.append(f"odometry: {int(b.sum())} body-frame velocities rotated to the "
                              "world frame")
        codes = sorted(set(np.asarray(pose_frame).tolist())) if pose_frame is not None else "n/a"
        self.notes.append(f"odometry: vehicle_visual_odometry in its own NED/FRD world frame "
                          f"(pose frame codes {codes}); converted like NED (an FRD world frame "
                          "keeps its heading offset)")
        p, v = frames.ned_to_enu(pos), frames.ned_to_enu(vel)
        qe = frames.quat_ned_frd_to_enu_flu(q)
        return make_stream("odometry", t, {
            "x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2],
            "qx": qe[:, 0], "qy": qe[:, 1], "qz": qe[:, 2], "qw": qe[:, 3]})

    def truth(self, origin):
        lp = self.dataset("vehicle_local_position_groundtruth")
        gp = self.dataset("vehicle_global_position_groundtruth")
        att = self.dataset("vehicle_attitude_groundtruth")
        if lp is None and gp is None:
            return None
        has_origin = all(math.isfinite(v) for v in origin)
        if lp is not None:
            t = self.times(lp, "truth")
            ned = np.stack([self.field(lp, k).astype(float) for k in "xyz"], axis=-1)
            vel = frames.ned_to_enu(np.stack([self.field(lp, k).astype(float)
                                              for k in ("vx", "vy", "vz")], axis=-1))
            ref = np.stack([self.field(lp, k).astype(float) for k in ("ref_lat", "ref_lon", "ref_alt")],
                           axis=-1)
            pos = frames.ned_to_enu(ned)
            if has_origin and np.isfinite(ref).all():
                refs, inv = np.unique(ref, axis=0, return_inverse=True)
                pos += frames.geodetic_to_enu(refs[:, 0], refs[:, 1], refs[:, 2], origin)[inv.reshape(-1)]
            else:
                self.notes.append("truth: in the simulator's local frame (no common origin)")
            no_alt = np.all(ref[:, 2] == 0) and np.all(ned[:, 2] == 0)
            if no_alt and gp is not None:
                no_alt = np.all(self.field(gp, "alt") == 0)
            if no_alt:
                pos[:, 2] = np.nan
                vel[:, 2] = np.nan
                self.notes.append("truth: the simulator logged no altitude (ref_alt, z and alt all "
                                  "0); z and vz set to NaN")
            self.notes.append("truth: position from vehicle_local_position_groundtruth")
        else:
            t = self.times(gp, "truth")
            lat, lon, alt = (self.field(gp, k).astype(float) for k in ("lat", "lon", "alt"))
            pos = frames.geodetic_to_enu(lat, lon, alt, origin) if has_origin else \
                np.full((len(t), 3), np.nan)
            vel = np.full((len(t), 3), np.nan)
            self.notes.append("truth: position from vehicle_global_position_groundtruth; "
                              "no velocity")
        values = {"x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
                  "vx": vel[:, 0], "vy": vel[:, 1], "vz": vel[:, 2]}
        if att is not None:
            ta = self.times(att, "truth")
            q = frames.quat_ned_frd_to_enu_flu(frames.wxyz_to_xyzw(self.vector(att, "q", 4)))
            ok = np.isfinite(ta) & np.isfinite(q).all(axis=1)
            order = np.argsort(ta[ok], kind="stable")
            qi = quat_interp(t, ta[ok][order], q[ok][order])
            values.update({"qx": qi[:, 0], "qy": qi[:, 1], "qz": qi[:, 2], "qw": qi[:, 3]})
            self.notes.append("truth: attitude from vehicle_attitude_groundtruth, interpolated "
                              "(normalised lerp) to the position times")
        return make_stream("truth", t, values, self.notes)
