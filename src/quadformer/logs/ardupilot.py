"""ArduPilot DataFlash (.bin) reader: ``read_dataflash(path) -> FlightLog`` via pymavlink.

Messages and fields read (times from ``TimeUS``, seconds after the first ``TimeUS`` of the
file; NED/FRD converted by ``frames``; DFReader applies the logged unit multipliers):

* imu: ``IMU`` instance ``I`` = 0 (the first IMU; other instances are dropped and noted):
  ``AccX..Z`` (specific force, FRD), ``GyrX..Z`` (FRD).
* gps: ``GPS`` instance 0: ``Lat``, ``Lng``, ``Alt`` (AMSL), ``Spd`` and ``GCrs`` (ground
  speed and course: v_east = Spd sin GCrs, v_north = Spd cos GCrs), ``VZ`` (down),
  ``Status`` (fix_type: the same codes as PX4, 3 = 3D fix; samples below 2 are dropped),
  ``NSats``; joined with ``GPA`` of the same ``TimeUS``: ``HAcc`` (eph), ``VAcc`` (epv),
  ``SAcc`` (speed_acc), ``VV`` (vz is NaN where 0). jamming/spoofing are not logged (NaN).
  Each fix is stamped at its epoch from the receiver's GPS time (``GWk``/``GMS``; ``Week``/
  ``TimeMS`` before 3.3): ``logs.receiver_clock``.
* receiver: every ``GPS`` message of the same instance, fix or not: ``Status`` (fix_type),
  ``NSats``, and the ``GPA`` accuracies as in gps; noise, jamming and spoofing are not logged.
* baro: ``BARO`` instance 0 ``Alt`` (relative to the ground calibration, as logged).
* mag: ``MAG`` instance 0 ``MagX..Z`` (milligauss, FRD) -> gauss FLU.
* innovations: ``XKF3`` ``IPN/IPE/IPD``, ``IVN/IVE/IVD`` (NED -> ENU) of the primary core;
  test ratios from ``XKF4`` of the same core: ``SV``, ``SP``, ``SH`` are the square roots of
  the EKF's velocity, position and height test ratios, so ratio_* = SV^2, SP^2, SH^2.
  Innovation variances are not logged: they are recovered from the ratios, the gates (PARM, else
  the defaults) and the innovations, each group's summed variance shared equally by its axes
  (``ardupilot_ratios``, which holds ArduPilot's definitions); NaN where a step or group holds
  none. The primary core is ``XKF4.PI`` at each time; the core index field is ``C`` (``Core`` is
  accepted too); without one, all rows are core 0. EKF2's ``NKF*`` and the first EKF's ``EKF*``
  are read alike where a log has no EKF3 messages; an estimator message without the fields read
  is noted and left out.
* estimate: ``XKF1`` ``PN/PE/PD``, ``VN/VE/VD`` of the primary core, relative to the EKF
  origin. ``reset`` is set where the primary core changes or where ``XKF4.OFN/OFE`` (the last
  position reset, m) changes.
* origin: the first ``ORGN`` of ``Type`` 0 (EKF origin), else the first GPS fix.
* odometry: ``VISP`` (``PX/PY/PZ`` NED, ``Roll/Pitch/Yaw`` deg) with ``VISV`` (``VX/VY/VZ``
  NED) matched by nearest time, if present. ``VISO`` holds deltas and is only noted.
* truth (SITL): ``SIM`` (``Lat/Lng/Alt``, attitude ``Q1..Q4`` = w, x, y, z body FRD -> NED)
  with velocity ``VN/VE/VD`` from ``SIM2`` interpolated to the ``SIM`` times.
* events: ``ARM``, ``EV``, ``ERR`` and ``MODE`` (see ``ardupilot_events``).

Pitfalls handled (each noted in ``FlightLog.notes``): several IMU, GPS, baro, mag instances
and EKF cores (one kept; the primary core follows ``XKF4.PI`` through lane switches); logs
recorded only while armed and dropouts (gaps split ``segments``; ARM events are noted);
EKF position resets (``reset``); corrupt input: DFReader is run with a guard that refuses
message formats shorter than their 3-byte header (such a format makes DFReader's indexer
loop forever on one offset) and the message loop is bounded by the file size
(at most one message per 3 bytes, with the read offset required to advance).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from quadformer.geometry import frames
from quadformer.logs._series import first_fix, interp_linear, median_period, nearest_index, take
from quadformer.logs.ardupilot_estimator import DataflashEstimator
from quadformer.logs.ardupilot_events import dataflash_events
from quadformer.logs.ardupilot_messages import WANTED, col, collect_messages
from quadformer.logs.flightlog import GPS_GAP, IMU_GAP, FlightLog, assemble, gps_stream, make_stream
from quadformer.logs.receiver_clock import week_seconds

__all__ = ["read_dataflash"]


def read_dataflash(path: str | Path, *, imu_gap: float = IMU_GAP,
                   gps_gap: float = GPS_GAP, epochs: bool = True) -> FlightLog:
    """Read an ArduPilot DataFlash .bin log into a FlightLog (see the module docstring).
    ``epochs`` False: the fixes keep the stamps the autopilot logged (as its link sends them)."""
    path = Path(path)
    rows, first_us, reports = collect_messages(path)
    return _DataflashReader(path, rows, first_us, reports).read(imu_gap, gps_gap, epochs)


class _DataflashReader(DataflashEstimator):
    def read(self, imu_gap: float, gps_gap: float, epochs: bool = True) -> FlightLog:
        vehicle = self.vehicle()
        self.arming()
        gps_rows = self.instance("GPS", "gps")
        accuracy = self.accuracy(gps_rows)
        gps_raw = self.gps(gps_rows, accuracy)
        origin, origin_source = self.origin(gps_raw)
        cores = self.cores()
        streams = {
            "imu": self.imu(),
            "gps": gps_stream(gps_raw, origin, self.notes, epochs),
            "baro": self.simple("BARO", "baro", ("Alt",), lambda v: {"alt": v[:, 0]}),
            "mag": self.simple("MAG", "mag", ("MagX", "MagY", "MagZ"), self._mag),
            "innovations": self.innovations(cores),
            "estimate": self.estimate(cores),
            "attitude": self.simple("ATT", "attitude", ("Roll", "Pitch", "Yaw"), self._attitude),
            "odometry": self.odometry(),
            "truth": self.truth(origin),
            "receiver": self.receiver(gps_rows, accuracy),
        }
        events = dataflash_events(self.rows, self.t, vehicle.get("firmware"))
        return assemble("ardupilot-dataflash", self.path, streams, self.notes, vehicle, origin,
                        origin_source, imu_gap, gps_gap, boot_start=self.first_us * 1e-6, events=events)

    def vehicle(self) -> dict:
        out: dict = {"autopilot": "ArduPilot"}
        if self.rows["VER"]:
            v = self.rows["VER"][0]
            for src, dst in (("FWS", "firmware"), ("BT", "board_type"), ("BST", "board_subtype"),
                             ("APJ", "board_id")):
                if src in v:
                    out[dst] = v[src]
            if "GH" in v:
                out["git_hash"] = f"{int(v['GH']):08x}"
            if all(k in v for k in ("Maj", "Min", "Pat")):
                out["version"] = f"{v['Maj']}.{v['Min']}.{v['Pat']}"
        texts = [r["Message"] for r in self.rows["MSG"] if "Message" in r]
        for text in texts:
            if "firmware" not in out and text.startswith(("Ardu", "Blimp", "AP_Periph")):
                out["firmware"] = text
            if text.startswith("Frame:") and "frame" not in out:
                out["frame"] = text.split(":", 1)[1].strip()
        out["messages"] = texts[:20]
        params = self.params()                                   # the values at the log's start
        delay = params.get("GPS1_DELAY_MS", params.get("GPS_DELAY_MS"))
        # the EKFs' own GPS latency, before GPS_DELAY_MS took their place: EKF2's, EKF1's (3.2 to 3.4)
        ekf = next(((n, params[n]) for n in ("EK3_GPS_DELAY", "EK2_GPS_DELAY", "EKF_POS_DELAY")
                    if isinstance(params.get(n), (int, float)) and math.isfinite(params[n]) and params[n] > 0), None)
        if isinstance(delay, (int, float)) and math.isfinite(delay) and delay > 0:
            out["gps_delay_s"] = float(delay) / 1000.0      # the receiver latency EKF3 compensates
        elif ekf is not None:
            out["gps_delay_s"] = float(ekf[1]) / 1000.0
            self.notes.append(f"gps: the receiver latency is the EKF's {ekf[0]} ({ekf[1]:g} ms)"
                              + (" (GPS_DELAY_MS 0: the driver's own)" if delay is not None else ""))
        elif delay is not None:
            self.notes.append("gps: GPS_DELAY_MS is 0 (the receiver driver's own latency, which the log does not "
                              "record); the replay estimates it from the log unless --gps-delay says otherwise")
        return out

    def arming(self) -> None:
        rows = self.rows["ARM"]
        if rows and "ArmState" in rows[0]:
            t = self.t(rows)
            events = ", ".join(f"{'armed' if r['ArmState'] else 'disarmed'} {ti:.2f} s"
                               for r, ti in zip(rows, t))
            self.notes.append(f"file: ARM events: {events}")

    def imu(self):
        rows = self.instance("IMU", "imu")
        if not rows:
            self.notes.append("imu: no IMU messages")
            return None
        self.require(rows, "IMU", WANTED["IMU"][1:])
        acc = frames.frd_to_flu(np.column_stack([col(rows, k) for k in ("AccX", "AccY", "AccZ")]))
        gyr = frames.frd_to_flu(np.column_stack([col(rows, k) for k in ("GyrX", "GyrY", "GyrZ")]))
        return make_stream("imu", self.t(rows), {
            "ax": acc[:, 0], "ay": acc[:, 1], "az": acc[:, 2],
            "gx": gyr[:, 0], "gy": gyr[:, 1], "gz": gyr[:, 2]})

    def accuracy(self, rows: list[dict]) -> dict[str, np.ndarray]:
        """GPA's eph, epv, speed_acc and VV (its vertical velocity flag) for each GPS row, joined
        by the same TimeUS; NaN where no GPA matches."""
        nan = np.full(len(rows), np.nan)
        gpa = self.instance("GPA", "gps") if rows else []
        if not gpa:
            if rows:
                self.notes.append("gps: no GPA messages; eph/epv/speed_acc NaN")
            return {"eph": nan, "epv": nan, "speed_acc": nan, "vv": nan}
        tg, tr = self.us(gpa), self.us(rows)
        order = np.argsort(tg, kind="stable")
        j = nearest_index(tr, tg[order], 0.0)
        j = np.where(j >= 0, order[np.clip(j, 0, None)], -1)
        if (j < 0).any():
            self.notes.append(f"gps: {int((j < 0).sum())} GPS samples without a GPA of the "
                              "same TimeUS; accuracies NaN there")
        return {"eph": take(col(gpa, "HAcc"), j), "epv": take(col(gpa, "VAcc"), j),
                "speed_acc": take(col(gpa, "SAcc"), j), "vv": take(col(gpa, "VV"), j)}

    def gps(self, rows: list[dict], accuracy: dict[str, np.ndarray]) -> dict | None:
        if not rows:
            self.notes.append("gps: no GPS messages")
            return None
        self.require(rows, "GPS", ("Status", "Lat", "Lng", "Alt"))
        t = self.t(rows)
        lat, lon, alt = col(rows, "Lat"), col(rows, "Lng"), col(rows, "Alt")
        fix = col(rows, "Status")
        keep = fix >= 2
        if (~keep).any():
            self.notes.append(f"gps: dropped {int((~keep).sum())} samples without a position fix "
                              "(Status < 2; the receiver stream keeps them)")
        bad = keep & ((np.abs(lat) > 90) | (np.abs(lon) > 180) | ((lat == 0) & (lon == 0)))
        if bad.any():
            self.notes.append(f"gps: dropped {int(bad.sum())} samples with an invalid "
                              "latitude/longitude")
        keep &= ~bad & np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt) & np.isfinite(t)
        if not keep.any():
            self.notes.append("gps: no sample with a valid fix")
            return None
        spd, crs = col(rows, "Spd"), np.deg2rad(col(rows, "GCrs"))
        vel = np.column_stack([spd * np.sin(crs), spd * np.cos(crs), -col(rows, "VZ")])
        vv = accuracy["vv"]
        if (vv[keep] == 0).any():
            vel[vv == 0, 2] = np.nan
            self.notes.append(f"gps: vz NaN in {int((vv[keep] == 0).sum())} samples (GPA.VV = 0)")
        if "Week" in rows[0]:              # before 3.3: Week and TimeMS (the time of week; T the stamp)
            tow = week_seconds(col(rows, "Week"), col(rows, "TimeMS"))
        else:
            tow = week_seconds(col(rows, "GWk"), col(rows, "GMS"))
        out = {"t": t, "tow": tow, "lat": lat, "lon": lon, "alt": alt, "fix_type": fix,
               "satellites": col(rows, "NSats"), "vel": vel,
               **{k: accuracy[k] for k in ("eph", "epv", "speed_acc")}}
        return {k: v[keep] for k, v in out.items()}

    def receiver(self, rows: list[dict], accuracy: dict[str, np.ndarray]):
        """Every GPS message of the kept instance, fix or not (the gps stream keeps the fixes)."""
        if not rows or "Status" not in rows[0]:
            return None
        return make_stream("receiver", self.t(rows), {
            "fix_type": col(rows, "Status"), "satellites": col(rows, "NSats"),
            **{k: accuracy[k] for k in ("eph", "epv", "speed_acc")}}, self.notes)

    def origin(self, gps_raw: dict | None):
        orgn = [r for r in self.rows["ORGN"] if r.get("Type") == 0 and all(k in r for k in ("Lat", "Lng", "Alt"))]
        if orgn:
            first = orgn[0]
            origin = (float(first["Lat"]), float(first["Lng"]), float(first["Alt"]))
            if all(math.isfinite(v) for v in origin) and not (origin[0] == 0 and origin[1] == 0):
                moved = {(r["Lat"], r["Lng"], r["Alt"]) for r in orgn} - {
                    (first["Lat"], first["Lng"], first["Alt"])}
                if moved:
                    self.notes.append(f"origin: ORGN type 0 logged {len(orgn)} times with "
                                      f"{len(moved)} other values; the first is used")
                return origin, "autopilot local origin"
        if gps_raw is not None:
            return first_fix(gps_raw), "first GPS fix"
        self.notes.append("origin: no ORGN message and no GPS fix; origin is NaN")
        return (math.nan,) * 3, "none"


    @staticmethod
    def _mag(v: np.ndarray) -> dict:
        m = frames.frd_to_flu(v * 1e-3)   # milligauss -> gauss
        return {"mx": m[:, 0], "my": m[:, 1], "mz": m[:, 2]}

    @staticmethod
    def _attitude(v: np.ndarray) -> dict:
        """ATT Roll, Pitch, Yaw (deg; body FRD -> world NED) -> quaternion FLU -> ENU."""
        q = frames.quat_ned_frd_to_enu_flu(frames.euler_to_quat(*np.deg2rad(v).T))
        return {"qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3]}

    def simple(self, name: str, label: str, fields: tuple[str, ...], convert):
        rows = self.instance(name, label)
        if not rows:
            self.notes.append(f"{label}: no {name} messages")
            return None
        self.require(rows, name, fields)
        return make_stream(label, self.t(rows),
                           convert(np.column_stack([col(rows, f) for f in fields])))

    # ------------------------------------------------------------ optional streams
    def odometry(self):
        if self.rows["VISO"]:
            self.notes.append("odometry: VISO (delta odometry) present, not converted")
        rows = self.rows["VISP"]
        if not rows:
            return None
        self.require(rows, "VISP", WANTED["VISP"])
        t = self.t(rows)
        pos = frames.ned_to_enu(np.column_stack([col(rows, k) for k in ("PX", "PY", "PZ")]))
        q = frames.euler_to_quat(*(np.deg2rad(col(rows, k)) for k in ("Roll", "Pitch", "Yaw")))
        q = frames.quat_ned_frd_to_enu_flu(q)
        values = {"x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
                  "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3]}
        visv = self.rows["VISV"]
        if visv and all(k in visv[0] for k in ("VX", "VY", "VZ")):
            tv = self.t(visv)
            order = np.argsort(tv, kind="stable")
            j = nearest_index(t, tv[order], 0.5 * median_period(tv[order]))
            j = np.where(j >= 0, order[np.clip(j, 0, None)], -1)
            vel = frames.ned_to_enu(take(np.column_stack([col(visv, k) for k in ("VX", "VY", "VZ")]), j))
            values.update({"vx": vel[:, 0], "vy": vel[:, 1], "vz": vel[:, 2]})
        self.notes.append("odometry: VISP/VISV in the vision system's own NED frame, converted "
                          "to ENU axes (its origin and heading are its own)")
        return make_stream("odometry", t, values, self.notes)

    def truth(self, origin):
        rows = self.rows["SIM"]
        if not rows:
            return None
        self.require(rows, "SIM", ("Lat", "Lng", "Alt"))
        t = self.t(rows)
        if all(math.isfinite(v) for v in origin):
            pos = frames.geodetic_to_enu(col(rows, "Lat"), col(rows, "Lng"), col(rows, "Alt"),
                                         origin)
        else:
            pos = np.full((len(t), 3), np.nan)
        values = {"x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2]}
        if all(k in rows[0] for k in ("Q1", "Q2", "Q3", "Q4")):
            q = frames.quat_ned_frd_to_enu_flu(frames.wxyz_to_xyzw(
                np.column_stack([col(rows, k) for k in ("Q1", "Q2", "Q3", "Q4")])))
            values.update({"qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3]})
        sim2 = self.rows["SIM2"]
        if sim2 and all(k in sim2[0] for k in ("VN", "VE", "VD")):
            t2 = self.t(sim2)
            order = np.argsort(t2, kind="stable")
            v = frames.ned_to_enu(interp_linear(
                t, t2[order], np.column_stack([col(sim2, k) for k in ("VN", "VE", "VD")])[order]))
            values.update({"vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2]})
            self.notes.append("truth: SIM position/attitude with SIM2 velocity interpolated to "
                              "the SIM times")
        return make_stream("truth", t, values, self.notes)
