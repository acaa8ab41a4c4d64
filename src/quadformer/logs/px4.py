"""PX4 ULog reader: ``read_ulog(path) -> FlightLog`` through pyulog.

Topics and fields read (instance 0 unless said otherwise; NED/FRD converted by ``frames``):

* imu: ``sensor_combined`` (the sensor voter's primary IMU): ``gyro_rad`` at ``timestamp``,
  ``accelerometer_m_s2`` at ``timestamp + accelerometer_timestamp_relative``; when that offset
  is not zero the accelerometer is interpolated to the gyro times (noted); an offset equal
  to the "invalid" marker 0x7fffffff drops the sample.
* gps: ``vehicle_gps_position`` (what the estimator uses), else ``sensor_gps``; position as
  ``lat``/``lon`` (1e-7 deg integers) and ``alt`` (mm) in older versions or
  ``latitude_deg``/``longitude_deg``/``altitude_msl_m`` in newer ones; ``vel_n/e/d_m_s`` (NaN
  where ``vel_ned_valid`` is 0); ``fix_type``, ``satellites_used``, ``eph``, ``epv``,
  ``s_variance_m_s`` (speed accuracy), ``jamming_state`` (else ``jamming_indicator``),
  ``spoofing_state``. Samples without a position fix (fix_type < 2) are dropped.
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
import io
import math
from pathlib import Path

import numpy as np
import pandas as pd
from pyulog import ULog

from quadformer.geometry import frames
from quadformer.logs._series import (first_fix, interp_linear, median_period, nearest_index,
                                     quat_interp, relative_seconds, relative_ticks, row_max,
                                     step_lookup, take)
from quadformer.logs.flightlog import GPS_GAP, IMU_GAP, FlightLog, LogError, assemble, gps_stream, make_stream

__all__ = ["read_ulog"]

_INVALID_RELATIVE = 0x7FFFFFFF   # PX4's RELATIVE_TIMESTAMP_INVALID


def read_ulog(path: str | Path, *, imu_gap: float = IMU_GAP, gps_gap: float = GPS_GAP) -> FlightLog:
    """Read a PX4 ULog file into a FlightLog (see the module docstring for the mapping)."""
    path = Path(path)
    ulog = _load(path)
    return _UlogReader(ulog, path).read(imu_gap, gps_gap)


class _WorkLimit(Exception):
    pass


class _BoundedBytes(io.BytesIO):
    """The file's bytes for pyulog, with a bound on the reading work.

    On a header it cannot use, pyulog's definitions parser moves on by one byte after
    reading the whole claimed message (up to 64 KiB): over a damaged stretch this is
    quadratic work, minutes for a few hundred KiB. A clean parse reads each byte about once
    in about one read call per byte or fewer, so reads are limited to 2.5 calls and 8 bytes
    per byte of file (plus a margin); beyond that the file is reported as corrupt."""

    def __init__(self, data: bytes) -> None:
        super().__init__(data)
        self.calls_left = int(2.5 * len(data)) + 10_000
        self.bytes_left = 8 * len(data) + (1 << 20)

    def read(self, size: int | None = -1) -> bytes:
        out = super().read(size)
        self.calls_left -= 1
        self.bytes_left -= len(out)
        if self.calls_left < 0 or self.bytes_left < 0:
            raise _WorkLimit("the parser kept re-reading the same bytes")
        return out


def _load(path: Path) -> ULog:
    if not path.is_file():
        raise LogError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise LogError(f"{path}: empty file (0 bytes); a ULog file starts with the 'ULog' header")
    captured = io.StringIO()
    try:
        with contextlib.redirect_stdout(captured):
            return ULog(_BoundedBytes(path.read_bytes()))
    # pyulog raises many exception types on damaged input (struct.error, IndexError,
    # ValueError, UnicodeDecodeError, its own ULogException, ...): all mean the same here.
    except Exception as exc:
        raise LogError(f"{path}: not a readable PX4 ULog file ({type(exc).__name__}: {exc}); "
                       "the file is truncated, corrupt or of another format") from exc


class _UlogReader:
    def __init__(self, ulog: ULog, path: Path) -> None:
        self.ulog = ulog
        self.path = path
        self.start = int(ulog.start_timestamp)
        self.notes: list[str] = []
        self.by_name: dict[str, list] = {}
        for d in sorted(ulog.data_list, key=lambda d: (d.name, d.multi_id)):
            if len(d.data.get("timestamp", ())):
                self.by_name.setdefault(d.name, []).append(d)

    # ---------------------------------------------------------------- helpers
    def instances(self, name: str) -> list:
        return self.by_name.get(name, [])

    def dataset(self, name: str):
        inst = self.instances(name)
        return inst[0] if inst else None

    def field(self, d, *names: str, required: bool = True) -> np.ndarray | None:
        for n in names:
            if n in d.data:
                return d.data[n]
        if required:
            fields = ", ".join(sorted(k for k in d.data if "[" not in k)[:40])
            raise LogError(f"{self.path}: topic {d.name} lacks field {' / '.join(names)} "
                           f"(fields: {fields}); this PX4 message layout is not supported")
        return None

    def vector(self, d, base: str, n: int, required: bool = True) -> np.ndarray | None:
        cols = [self.field(d, f"{base}[{i}]", required=required) for i in range(n)]
        if any(c is None for c in cols):
            return None
        return np.stack([c.astype(np.float64) for c in cols], axis=-1)

    def times(self, d, label: str, use_sample: bool = True) -> np.ndarray:
        stamps = d.data["timestamp"]
        sample = d.data.get("timestamp_sample") if use_sample else None
        if sample is not None and len(sample) and np.all(sample > 0) and np.all(sample <= stamps):
            stamps = sample
        t = relative_seconds(stamps, self.start, 1e-6)
        zero = np.asarray(stamps) == 0
        if zero.any():
            t[zero] = np.nan
            self.notes.append(f"{label}: {int(zero.sum())} of {len(t)} {d.name} samples have "
                              "timestamp 0 (never set by the publisher); dropped")
        early = np.isfinite(t) & (t < 0)
        if early.any():
            self.notes.append(f"{label}: {int(early.sum())} {d.name} samples stamped before the "
                              f"log start (earliest {np.nanmin(t):.3f} s); kept with negative t")
        return t

    def embedded(self, d, rel_field: str, label: str) -> tuple[np.ndarray, np.ndarray]:
        """Indices of the distinct samples of a sensor embedded in old ``sensor_combined``
        rows (``timestamp + <sensor>_timestamp_relative``, repeated until a new sample
        arrives) and their times; rows marked invalid are left out."""
        rel = self.field(d, rel_field).astype(np.int64)
        stamps = d.data["timestamp"]
        valid = (rel != _INVALID_RELATIVE) & (np.asarray(stamps) != 0)
        with np.errstate(over="ignore"):
            ticks = relative_ticks(stamps, self.start) + rel
        idx = np.flatnonzero(valid)
        _, first = np.unique(ticks[idx], return_index=True)
        idx = np.sort(idx[first])
        self.notes.append(f"{label}: from old sensor_combined: {len(idx)} distinct samples in "
                          f"{len(rel)} rows ({int((~valid).sum())} rows without {label} data)")
        return idx, ticks[idx] * 1e-6

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
        gps_raw = self.gps()
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
        }
        return assemble("px4-ulog", self.path, streams, self.notes, vehicle, origin,
                        origin_source, imu_gap, gps_gap, boot_start=self.start * 1e-6)

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
        invalid = rel == _INVALID_RELATIVE
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

    def gps(self) -> dict | None:
        cands = [d for name in ("vehicle_gps_position", "sensor_gps") for d in self.instances(name)]
        if not cands:
            self.notes.append("gps: no vehicle_gps_position or sensor_gps topic")
            return None
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
                              "(fix_type < 2)")
        bad = keep & ~nofix & ((np.abs(lat) > 90) | (np.abs(lon) > 180) | ((lat == 0) & (lon == 0)))
        if bad.any():
            self.notes.append(f"gps: dropped {int(bad.sum())} samples with an invalid latitude/"
                              "longitude")
        keep &= ~nofix & ~bad & np.isfinite(t) & np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt)
        if not keep.any():
            self.notes.append("gps: no sample with a valid fix")
            return None
        vel = np.stack([self.field(d, f"vel_{a}_m_s").astype(float) for a in "ned"], axis=-1)
        valid = self.field(d, "vel_ned_valid", required=False)
        if valid is not None and (valid[keep] == 0).any():
            vel[valid == 0] = np.nan
            self.notes.append(f"gps: velocity NaN in {int((valid[keep] == 0).sum())} samples "
                              "flagged vel_ned_valid = 0")
        jam = self.field(d, "jamming_state", required=False)
        if jam is None:
            jam = self.field(d, "jamming_indicator", required=False)
            if jam is not None:
                self.notes.append("gps: jamming is jamming_indicator (0-255; no jamming_state)")
        spoof = self.field(d, "spoofing_state", required=False)
        out = {"t": t, "lat": lat, "lon": lon, "alt": alt, "vel": frames.ned_to_enu(vel),
               "fix_type": fix, "satellites": self.field(d, "satellites_used", required=False),
               "eph": self.field(d, "eph", required=False),
               "epv": self.field(d, "epv", required=False),
               "speed_acc": self.field(d, "s_variance_m_s", required=False),
               "jamming": jam, "spoofing": spoof}
        return {k: np.asarray(v, dtype=float)[keep] for k, v in out.items() if v is not None}


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

    def primary_mask(self, label: str, t: np.ndarray, instance: int, n_instances: int) -> np.ndarray:
        sel = self.dataset("estimator_selector_status")
        if n_instances <= 1:
            return np.ones(len(t), bool)
        if sel is None:
            return np.full(len(t), instance == 0)
        st = self.times(sel, "estimator_selector_status", use_sample=False)
        ok = np.isfinite(st)
        primary = self.field(sel, "primary_instance")[ok]
        return step_lookup(t, st[ok], primary) == instance

    def innovations(self):
        inst = self.instances("estimator_innovations")
        if inst:
            return self._innovations_new(inst)
        d = self.dataset("ekf2_innovations")
        if d is not None:
            return self._innovations_old(d)
        self.notes.append("innovations: no estimator_innovations or ekf2_innovations topic")
        return None

    def _match(self, t: np.ndarray, name: str, multi_id: int):
        """The dataset ``name`` of one instance and, per row time t, its nearest sample."""
        cand = [d for d in self.instances(name) if d.multi_id == multi_id]
        if not cand:
            return None, np.full(len(t), -1)
        d = cand[0]
        ts = self.times(d, "innovations", use_sample=True)
        ok = np.isfinite(ts)
        idx_ok = np.flatnonzero(ok)
        order = np.argsort(ts[ok], kind="stable")
        j = nearest_index(t, ts[ok][order], 0.5 * median_period(ts[ok][order]))
        return d, np.where(j >= 0, idx_ok[order][np.clip(j, 0, None)], -1)

    def _innovations_new(self, inst: list):
        parts, ids = [], [d.multi_id for d in inst]
        sel = self.dataset("estimator_selector_status")
        if len(inst) > 1:
            how = ("the primary instance per estimator_selector_status" if sel is not None
                   else "instance 0 (no estimator_selector_status)")
            self.notes.append(f"innovations: estimator instances {ids} logged; kept rows of {how}")
        for d in inst:
            t = self.times(d, "innovations")
            rows = self.primary_mask("innovations", t, d.multi_id, len(inst))
            if not rows.any():
                continue
            hp = self.vector(d, "gps_hpos", 2)
            vp = self.field(d, "gps_vpos").astype(float)
            hv = self.vector(d, "gps_hvel", 2)
            vv = self.field(d, "gps_vvel").astype(float)
            pos = frames.ned_to_enu(np.column_stack([hp, vp]))
            vel = frames.ned_to_enu(np.column_stack([hv, vv]))
            values = {"pos_x": pos[:, 0], "pos_y": pos[:, 1], "pos_z": pos[:, 2],
                      "vel_x": vel[:, 0], "vel_y": vel[:, 1], "vel_z": vel[:, 2]}
            dv, j = self._match(t, "estimator_innovation_variances", d.multi_id)
            if dv is not None:
                pv = frames.ned_var_to_enu(take(np.column_stack(
                    [self.vector(dv, "gps_hpos", 2), self.field(dv, "gps_vpos")]), j))
                vvar = frames.ned_var_to_enu(take(np.column_stack(
                    [self.vector(dv, "gps_hvel", 2), self.field(dv, "gps_vvel")]), j))
                for k, a in enumerate("xyz"):
                    values[f"var_pos_{a}"] = pv[:, k]
                    values[f"var_vel_{a}"] = vvar[:, k]
            dr, j = self._match(t, "estimator_innovation_test_ratios", d.multi_id)
            if dr is not None:
                values["ratio_pos"] = take(row_max(self.vector(dr, "gps_hpos", 2)), j)
                values["ratio_hgt"] = take(self.field(dr, "gps_vpos"), j)
                values["ratio_vel"] = take(row_max(np.column_stack(
                    [self.vector(dr, "gps_hvel", 2), self.field(dr, "gps_vvel")])), j)
            parts.append(make_stream("innovations", t, values)[rows])
        if not parts:
            self.notes.append("innovations: no rows from the primary estimator instance")
            return None
        if not self.instances("estimator_innovation_variances"):
            self.notes.append("innovations: no estimator_innovation_variances; variances NaN")
        if not self.instances("estimator_innovation_test_ratios"):
            self.notes.append("innovations: no estimator_innovation_test_ratios; ratios NaN")
        out = pd.concat(parts, ignore_index=True) if len(parts) > 1 else parts[0]
        return out.sort_values("t", kind="stable").reset_index(drop=True)

    def _innovations_old(self, d):
        t = self.times(d, "innovations")
        innov = self.vector(d, "vel_pos_innov", 6)
        var = self.vector(d, "vel_pos_innov_var", 6, required=False)
        vel, pos = frames.ned_to_enu(innov[:, :3]), frames.ned_to_enu(innov[:, 3:])
        values = {"pos_x": pos[:, 0], "pos_y": pos[:, 1], "pos_z": pos[:, 2],
                  "vel_x": vel[:, 0], "vel_y": vel[:, 1], "vel_z": vel[:, 2]}
        if var is not None:
            vv, pv = frames.ned_var_to_enu(var[:, :3]), frames.ned_var_to_enu(var[:, 3:])
            for k, a in enumerate("xyz"):
                values[f"var_pos_{a}"] = pv[:, k]
                values[f"var_vel_{a}"] = vv[:, k]
        ds, j = self._match(t, "estimator_status", 0)
        if ds is not None:
            for col, f in (("ratio_pos", "pos_test_ratio"), ("ratio_vel", "vel_test_ratio"),
                           ("ratio_hgt", "hgt_test_ratio")):
                src = self.field(ds, f, required=False)
                if src is not None:
                    values[col] = take(src, j)
        self.notes.append("innovations: old ekf2_innovations (velocity/position innovations of "
                          "the fused aiding source); test ratios from estimator_status")
        return make_stream("innovations", t, values)

    def local_position(self):
        d = self.dataset("vehicle_local_position")
        if d is None:
            self.notes.append("estimate: no vehicle_local_position topic")
            return None, None
        t = self.times(d, "estimate")
        ned = np.stack([self.field(d, k).astype(float) for k in ("x", "y", "z")], axis=-1)
        vel = np.stack([self.field(d, k).astype(float) for k in ("vx", "vy", "vz")], axis=-1)
        ref = np.stack([d.data[k].astype(float) if k in d.data else np.full(len(t), np.nan)
                        for k in ("ref_lat", "ref_lon", "ref_alt")], axis=-1)
        valid = np.isfinite(ref).all(axis=1) & ~((ref[:, 0] == 0) & (ref[:, 1] == 0))
        valid &= (np.abs(ref[:, 0]) <= 90) & (np.abs(ref[:, 1]) <= 180)
        xy_global = self.field(d, "xy_global", required=False)
        if xy_global is not None:
            valid &= xy_global != 0
        reset = np.zeros(len(t), bool)
        for k in ("xy_reset_counter", "z_reset_counter"):
            c = self.field(d, k, required=False)
            if c is not None and len(c) > 1:
                reset[1:] |= np.diff(c.astype(np.int64)) != 0
        raw = {"t": t, "ned": ned, "vel": frames.ned_to_enu(vel), "ref": ref, "valid": valid,
               "reset": reset}
        if reset.any():
            dxy = self.vector(d, "delta_xy", 2, required=False)
            dz = self.field(d, "delta_z", required=False)
            big_xy = row_max(np.hypot(dxy[reset, 0], dxy[reset, 1])[None])[0] \
                if dxy is not None else np.nan
            big_z = row_max(np.abs(dz[reset])[None].astype(float))[0] if dz is not None else np.nan
            self.notes.append(f"estimate: {int(reset.sum())} position resets (reset counters) at t = "
                              + ", ".join(f"{v:.3f}" for v in t[reset][:10])
                              + f" s; largest |delta_xy| {big_xy:.3f} m, |delta_z| {big_z:.3f} m")
        if not valid.any():
            self.notes.append("estimate: the autopilot logged no local origin (ref_lat/ref_lon "
                              "unset); positions are in the estimator's own local frame")
            return raw, None
        origin = tuple(float(v) for v in ref[np.argmax(valid)])
        return raw, origin

    def estimate_stream(self, raw: dict | None, origin):
        if raw is None:
            return None
        pos = frames.ned_to_enu(raw["ned"])
        reset = raw["reset"].copy()
        valid = raw["valid"]
        if valid.any() and all(math.isfinite(v) for v in origin):
            refs, inverse = np.unique(raw["ref"][valid], axis=0, return_inverse=True)
            offsets = frames.geodetic_to_enu(refs[:, 0], refs[:, 1], refs[:, 2], origin)
            pos[valid] += offsets[inverse.reshape(-1)]
            if len(refs) > 1:
                idx = np.flatnonzero(valid)
                moved = idx[1:][np.any(raw["ref"][idx[1:]] != raw["ref"][idx[:-1]], axis=1)]
                reset[moved] = True
                self.notes.append(f"estimate: the local origin moved {len(moved)} times; positions "
                                  "re-expressed about the first origin and marked as resets")
            own = int((~valid).sum())
            if own:
                self.notes.append(f"estimate: {own} samples before the local origin was set are in "
                                  "the estimator's own frame")
        return make_stream("estimate", raw["t"], {
            "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2], "vx": raw["vel"][:, 0],
            "vy": raw["vel"][:, 1], "vz": raw["vel"][:, 2], "reset": reset})

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

    def attitude(self):
        d = self.dataset("vehicle_attitude")
        if d is None:
            self.notes.append("attitude: no vehicle_attitude topic")
            return None
        q = frames.quat_ned_frd_to_enu_flu(frames.wxyz_to_xyzw(self.vector(d, "q", 4)))
        return make_stream("attitude", self.times(d, "attitude"),
                           {"qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3]})

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
