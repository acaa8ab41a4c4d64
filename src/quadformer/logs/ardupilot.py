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
* baro: ``BARO`` instance 0 ``Alt`` (relative to the ground calibration, as logged).
* mag: ``MAG`` instance 0 ``MagX..Z`` (milligauss, FRD) -> gauss FLU.
* innovations: ``XKF3`` ``IPN/IPE/IPD``, ``IVN/IVE/IVD`` (NED -> ENU) of the primary core;
  test ratios from ``XKF4`` of the same core: ``SV``, ``SP``, ``SH`` are the square roots of
  the EKF's velocity, position and height test ratios, so ratio_* = SV^2, SP^2, SH^2.
  Innovation variances are not logged (NaN). The primary core is ``XKF4.PI`` at each time;
  the core index field is ``C`` (``Core`` is accepted too); without one, all rows are core 0.
* estimate: ``XKF1`` ``PN/PE/PD``, ``VN/VE/VD`` of the primary core, relative to the EKF
  origin. ``reset`` is set where the primary core changes or where ``XKF4.OFN/OFE`` (the last
  position reset, m) changes.
* origin: the first ``ORGN`` of ``Type`` 0 (EKF origin), else the first GPS fix.
* odometry: ``VISP`` (``PX/PY/PZ`` NED, ``Roll/Pitch/Yaw`` deg) with ``VISV`` (``VX/VY/VZ``
  NED) matched by nearest time, if present. ``VISO`` holds deltas and is only noted.
* truth (SITL): ``SIM`` (``Lat/Lng/Alt``, attitude ``Q1..Q4`` = w, x, y, z body FRD -> NED)
  with velocity ``VN/VE/VD`` from ``SIM2`` interpolated to the ``SIM`` times.

Pitfalls handled (each noted in ``FlightLog.notes``): several IMU, GPS, baro, mag instances
and EKF cores (one kept; the primary core follows ``XKF4.PI`` through lane switches); logs
recorded only while armed and dropouts (gaps split ``segments``; ARM events are noted);
EKF position resets (``reset``); corrupt input: DFReader is run with a guard that refuses
message formats shorter than their 3-byte header (such a format makes DFReader's indexer
loop forever on one offset) and the message loop is bounded by the file size
(at most one message per 3 bytes, with the read offset required to advance).
"""

from __future__ import annotations

import contextlib
import io
import math
from pathlib import Path

import numpy as np
from pymavlink import DFReader

from quadformer.geometry import frames
from quadformer.logs._series import (first_fix, interp_linear, median_period, nearest_index,
                                     step_lookup, take)
from quadformer.logs.flightlog import GPS_GAP, IMU_GAP, FlightLog, LogError, assemble, gps_stream, make_stream

__all__ = ["read_dataflash"]

_HEADER = b"\xa3\x95"
_WANTED = {
    "IMU": ("I", "AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ"),
    "GPS": ("I", "Status", "NSats", "Lat", "Lng", "Alt", "Spd", "GCrs", "VZ"),
    "GPA": ("I", "HAcc", "VAcc", "SAcc", "VV"),
    "BARO": ("I", "Alt"),
    "MAG": ("I", "MagX", "MagY", "MagZ"),
    "ATT": ("Roll", "Pitch", "Yaw"),
    "XKF1": ("C", "Core", "PN", "PE", "PD", "VN", "VE", "VD"),
    "XKF3": ("C", "Core", "IPN", "IPE", "IPD", "IVN", "IVE", "IVD"),
    "XKF4": ("C", "Core", "SV", "SP", "SH", "OFN", "OFE", "PI"),
    "ORGN": ("Type", "Lat", "Lng", "Alt"),
    "SIM": ("Lat", "Lng", "Alt", "Q1", "Q2", "Q3", "Q4"),
    "SIM2": ("VN", "VE", "VD"),
    "VISP": ("PX", "PY", "PZ", "Roll", "Pitch", "Yaw"),
    "VISV": ("VX", "VY", "VZ"),
    "VISO": (),
    "ARM": ("ArmState",),
    "VER": ("BT", "BST", "Maj", "Min", "Pat", "FWT", "GH", "FWS", "APJ"),
    "MSG": ("Message",),
    "NKF3": (),
    "PARM": ("Name", "Value"),
}


class _CorruptFormat(Exception):
    pass


class _CheckedFormats(dict):
    """DFReader's format table, refusing formats whose length cannot hold the header."""

    def __setitem__(self, key, fmt) -> None:
        if getattr(fmt, "len", 0) < 3:
            raise _CorruptFormat(f"message format {getattr(fmt, 'name', key)!r} (type {key}) "
                                 f"has length {getattr(fmt, 'len', None)}")
        super().__setitem__(key, fmt)


class _GuardedReader(DFReader.DFReader_binary):
    """DFReader_binary with a checked format table; always the pure-Python indexer, so that
    the check applies while the file is indexed."""

    def init_arrays_fast(self, progress_callback=None):
        self.init_arrays(progress_callback)

    def init_arrays(self, progress_callback=None):
        self.formats = _CheckedFormats(self.formats)
        super().init_arrays(progress_callback)


def read_dataflash(path: str | Path, *, imu_gap: float = IMU_GAP,
                   gps_gap: float = GPS_GAP) -> FlightLog:
    """Read an ArduPilot DataFlash .bin log into a FlightLog (see the module docstring)."""
    path = Path(path)
    rows, first_us, reports = _collect(path)
    return _DataflashReader(path, rows, first_us, reports).read(imu_gap, gps_gap)


def _collect(path: Path) -> tuple[dict[str, list[dict]], int, int]:
    if not path.is_file():
        raise LogError(f"{path}: no such file")
    size = path.stat().st_size
    if size == 0:
        raise LogError(f"{path}: empty file (0 bytes); a DataFlash log starts with 0xA3 0x95")
    with open(path, "rb") as fh:
        if fh.read(2) != _HEADER:
            raise LogError(f"{path}: does not start with the DataFlash message header 0xA3 0x95; "
                           "not an ArduPilot .bin log (text .log files are not supported)")
    rows: dict[str, list[dict]] = {k: [] for k in _WANTED}
    first_us = None
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            reader = _GuardedReader(str(path), zero_time_base=True)
            try:
                reader._rewind()
                budget = size // 3 + 16
                last = -1
                for _ in range(budget):
                    m = reader.recv_msg()
                    if m is None:
                        break
                    if reader.offset <= last:
                        raise _CorruptFormat(f"the reader stopped advancing at offset {last}")
                    last = reader.offset
                    fmt = m.fmt
                    if first_us is None and "TimeUS" in fmt.colhash:
                        first_us = int(m.TimeUS)
                    name = fmt.name
                    if name in rows and "TimeUS" in fmt.colhash:
                        row = {"TimeUS": int(m.TimeUS)}
                        for f in _WANTED[name]:
                            if f in fmt.colhash:
                                row[f] = getattr(m, f)
                        rows[name].append(row)
                else:
                    raise _CorruptFormat(f"more than {budget} messages in {size} bytes")
            finally:
                reader.filehandle.close()
    except _CorruptFormat as exc:
        raise LogError(f"{path}: corrupt DataFlash log: {exc}; the file is damaged") from exc
    # DFReader raises many exception types on damaged input (struct.error, KeyError,
    # IndexError, RecursionError, its own bare Exception for unknown format characters).
    except Exception as exc:
        raise LogError(f"{path}: not a readable DataFlash log ({type(exc).__name__}: {exc}); "
                       "the file is truncated or corrupt") from exc
    if first_us is None:
        raise LogError(f"{path}: no timestamped (TimeUS) message; the log is empty or truncated "
                       "before its first data message (logs timed in TimeMS only, from before "
                       "ArduPilot 3.3, are not supported)")
    text = out.getvalue() + err.getvalue()
    reports = sum(text.count(k) for k in ("bad header", "Skipped", "Failed to parse", "bad msg"))
    return rows, first_us, reports


def _col(rows: list[dict], name: str, default=np.nan) -> np.ndarray:
    return np.array([r.get(name, default) for r in rows], dtype=float)


class _DataflashReader:
    def __init__(self, path: Path, rows: dict[str, list[dict]], first_us: int, reports: int):
        self.path = path
        self.rows = rows
        self.first_us = first_us
        self.notes: list[str] = []
        if reports:
            self.notes.append(f"file: DFReader skipped damaged data ({reports} reports)")

    def us(self, rows: list[dict]) -> np.ndarray:
        """TimeUS after the first one, as float64 microseconds. The difference is taken on
        Python integers: a damaged TimeUS may exceed the int64 range."""
        first = self.first_us
        return np.fromiter((r["TimeUS"] - first for r in rows), dtype=np.float64, count=len(rows))

    def t(self, rows: list[dict]) -> np.ndarray:
        return self.us(rows) * 1e-6

    def instance(self, name: str, label: str, field: str = "I") -> list[dict]:
        rows = self.rows[name]
        if not rows or field not in rows[0]:
            return rows
        ids = sorted({r.get(field) for r in rows})
        if len(ids) > 1:
            self.notes.append(f"{label}: {name} instances {ids} logged; kept instance {ids[0]} "
                              f"(dropped {sum(r.get(field) != ids[0] for r in rows)} samples)")
        return [r for r in rows if r.get(field) == ids[0]]

    def require(self, rows: list[dict], name: str, fields: tuple[str, ...]) -> None:
        missing = [f for f in fields if f not in rows[0]]
        if missing:
            raise LogError(f"{self.path}: {name} messages lack field(s) {', '.join(missing)} "
                           f"(have: {', '.join(sorted(rows[0]))}); this ArduPilot log layout "
                           "is not supported")

    def read(self, imu_gap: float, gps_gap: float) -> FlightLog:
        vehicle = self.vehicle()
        self.arming()
        gps_raw = self.gps()
        origin, origin_source = self.origin(gps_raw)
        cores = self.cores()
        streams = {
            "imu": self.imu(),
            "gps": gps_stream(gps_raw, origin, self.notes),
            "baro": self.simple("BARO", "baro", ("Alt",), lambda v: {"alt": v[:, 0]}),
            "mag": self.simple("MAG", "mag", ("MagX", "MagY", "MagZ"), self._mag),
            "innovations": self.innovations(cores),
            "estimate": self.estimate(cores),
            "attitude": self.simple("ATT", "attitude", ("Roll", "Pitch", "Yaw"), self._attitude),
            "odometry": self.odometry(),
            "truth": self.truth(origin),
        }
        return assemble("ardupilot-dataflash", self.path, streams, self.notes, vehicle, origin,
                        origin_source, imu_gap, gps_gap, boot_start=self.first_us * 1e-6)

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
        params: dict = {}
        for r in self.rows["PARM"]:                              # the values at the log's start
            if "Name" in r and "Value" in r:
                params.setdefault(r["Name"], r["Value"])
        delay = params.get("GPS1_DELAY_MS", params.get("GPS_DELAY_MS"))
        if isinstance(delay, (int, float)) and math.isfinite(delay) and delay > 0:
            out["gps_delay_s"] = float(delay) / 1000.0      # the receiver latency EKF3 compensates
        elif delay is not None:
            self.notes.append("gps: GPS_DELAY_MS is 0 (the receiver driver's own latency, which the log does not "
                              "record); fixes are fused at their stamps unless --gps-delay says otherwise")
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
        self.require(rows, "IMU", _WANTED["IMU"][1:])
        acc = frames.frd_to_flu(np.column_stack([_col(rows, k) for k in ("AccX", "AccY", "AccZ")]))
        gyr = frames.frd_to_flu(np.column_stack([_col(rows, k) for k in ("GyrX", "GyrY", "GyrZ")]))
        return make_stream("imu", self.t(rows), {
            "ax": acc[:, 0], "ay": acc[:, 1], "az": acc[:, 2],
            "gx": gyr[:, 0], "gy": gyr[:, 1], "gz": gyr[:, 2]})

    def gps(self) -> dict | None:
        rows = self.instance("GPS", "gps")
        if not rows:
            self.notes.append("gps: no GPS messages")
            return None
        self.require(rows, "GPS", ("Status", "Lat", "Lng", "Alt"))
        t = self.t(rows)
        lat, lon, alt = _col(rows, "Lat"), _col(rows, "Lng"), _col(rows, "Alt")
        fix = _col(rows, "Status")
        keep = fix >= 2
        if (~keep).any():
            self.notes.append(f"gps: dropped {int((~keep).sum())} samples without a position fix "
                              "(Status < 2)")
        bad = keep & ((np.abs(lat) > 90) | (np.abs(lon) > 180) | ((lat == 0) & (lon == 0)))
        if bad.any():
            self.notes.append(f"gps: dropped {int(bad.sum())} samples with an invalid "
                              "latitude/longitude")
        keep &= ~bad & np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt) & np.isfinite(t)
        if not keep.any():
            self.notes.append("gps: no sample with a valid fix")
            return None
        spd, crs = _col(rows, "Spd"), np.deg2rad(_col(rows, "GCrs"))
        vel = np.column_stack([spd * np.sin(crs), spd * np.cos(crs), -_col(rows, "VZ")])
        out = {"t": t, "lat": lat, "lon": lon, "alt": alt, "fix_type": fix,
               "satellites": _col(rows, "NSats"), "vel": vel}
        gpa = self.instance("GPA", "gps")
        if gpa:
            tg, tr = self.us(gpa), self.us(rows)
            order = np.argsort(tg, kind="stable")
            j = nearest_index(tr, tg[order], 0.0)
            j = np.where(j >= 0, order[np.clip(j, 0, None)], -1)
            for src, dst in (("HAcc", "eph"), ("VAcc", "epv"), ("SAcc", "speed_acc")):
                out[dst] = take(_col(gpa, src), j)
            vv = take(_col(gpa, "VV"), j)
            if (vv == 0).any():
                vel[vv == 0, 2] = np.nan
                self.notes.append(f"gps: vz NaN in {int((vv == 0).sum())} samples (GPA.VV = 0)")
            if (j < 0).any():
                self.notes.append(f"gps: {int((j < 0).sum())} GPS samples without a GPA of the "
                                  "same TimeUS; accuracies NaN there")
        else:
            self.notes.append("gps: no GPA messages; eph/epv/speed_acc NaN")
        return {k: v[keep] for k, v in out.items()}

    def origin(self, gps_raw: dict | None):
        orgn = [r for r in self.rows["ORGN"] if r.get("Type") == 0 and "Lat" in r]
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
                           convert(np.column_stack([_col(rows, f) for f in fields])))

    # ------------------------------------------------------------ EKF cores
    def cores(self) -> dict:
        """Primary-core signal from XKF4.PI and the core field name per message."""
        x4 = self.rows["XKF4"]
        info = {"field": {}}
        for name in ("XKF1", "XKF3", "XKF4"):
            rows = self.rows[name]
            info["field"][name] = next((f for f in ("C", "Core") if rows and f in rows[0]), None)
        if x4 and "PI" in x4[0]:
            t = self.t(x4)
            order = np.argsort(t, kind="stable")
            info["t"], info["primary"] = t[order], _col(x4, "PI")[order]
            switches = np.flatnonzero(np.diff(info["primary"]) != 0)
            if len(switches):
                self.notes.append("innovations/estimate: primary EKF core switched at t = "
                                  + ", ".join(f"{info['t'][i + 1]:.3f}" for i in switches[:10])
                                  + " s")
        else:
            info["t"], info["primary"] = np.array([0.0]), np.array([0.0])
            if x4:
                self.notes.append("innovations/estimate: XKF4 has no PI (primary core) field; "
                                  "core 0 used")
        return info

    def primary_rows(self, name: str, cores: dict, label: str) -> tuple[list[dict], np.ndarray]:
        rows = self.rows[name]
        field = cores["field"][name]
        if not rows:
            return [], np.array([])
        t = self.t(rows)
        core = _col(rows, field) if field else np.zeros(len(rows))
        if field is None:
            self.notes.append(f"{label}: {name} has no core field; all rows taken as core 0")
        keep = core == step_lookup(t, cores["t"], cores["primary"])
        ids = sorted(set(core.tolist()))
        if len(ids) > 1:
            self.notes.append(f"{label}: {name} logged for EKF cores {[int(i) for i in ids]}; "
                              "kept the primary core's rows")
        return [r for r, k in zip(rows, keep) if k], core[keep]

    def innovations(self, cores: dict):
        rows, core = self.primary_rows("XKF3", cores, "innovations")
        if not rows:
            ekf2 = " (EKF2 NKF* messages are present but not read)" if self.rows["NKF3"] else ""
            self.notes.append(f"innovations: no XKF3 (EKF3) messages{ekf2}")
            return None
        self.require(rows, "XKF3", ("IPN", "IPE", "IPD", "IVN", "IVE", "IVD"))
        t = self.t(rows)
        pos = frames.ned_to_enu(np.column_stack([_col(rows, k) for k in ("IPN", "IPE", "IPD")]))
        vel = frames.ned_to_enu(np.column_stack([_col(rows, k) for k in ("IVN", "IVE", "IVD")]))
        values = {"pos_x": pos[:, 0], "pos_y": pos[:, 1], "pos_z": pos[:, 2],
                  "vel_x": vel[:, 0], "vel_y": vel[:, 1], "vel_z": vel[:, 2]}
        x4 = self.rows["XKF4"]
        if x4 and all(k in x4[0] for k in ("SV", "SP", "SH")):
            j = self._same_core_nearest(t, core, x4, cores["field"]["XKF4"])
            for src, dst in (("SP", "ratio_pos"), ("SV", "ratio_vel"), ("SH", "ratio_hgt")):
                values[dst] = take(_col(x4, src) ** 2, j)
            self.notes.append("innovations: ratio_pos/vel/hgt = XKF4 SP^2/SV^2/SH^2 (logged as "
                              "square roots of the test ratios); variances are not logged")
        return make_stream("innovations", t, values, self.notes)

    def _same_core_nearest(self, t: np.ndarray, core: np.ndarray, rows: list[dict],
                           field: str | None) -> np.ndarray:
        ts = self.t(rows)
        rc = _col(rows, field) if field else np.zeros(len(rows))
        j = np.full(len(t), -1)
        for c in np.unique(core):
            idx = np.flatnonzero(rc == c)
            if not len(idx):
                continue
            order = idx[np.argsort(ts[idx], kind="stable")]
            k = nearest_index(t[core == c], ts[order], 0.5 * median_period(ts[order]))
            j[core == c] = np.where(k >= 0, order[np.clip(k, 0, None)], -1)
        return j

    def estimate(self, cores: dict):
        rows, core = self.primary_rows("XKF1", cores, "estimate")
        if not rows:
            self.notes.append("estimate: no XKF1 messages")
            return None
        self.require(rows, "XKF1", ("PN", "PE", "PD", "VN", "VE", "VD"))
        t = self.t(rows)
        pos = frames.ned_to_enu(np.column_stack([_col(rows, k) for k in ("PN", "PE", "PD")]))
        vel = frames.ned_to_enu(np.column_stack([_col(rows, k) for k in ("VN", "VE", "VD")]))
        reset = np.zeros(len(t), bool)
        reset[1:] |= np.diff(core) != 0
        x4 = self.rows["XKF4"]
        if x4 and "OFN" in x4[0] and "OFE" in x4[0]:
            j = self._same_core_nearest(t, core, x4, cores["field"]["XKF4"])
            off = take(np.column_stack([_col(x4, "OFN"), _col(x4, "OFE")]), j)
            same_core = np.concatenate([[False], np.diff(core) == 0])
            changed = np.concatenate([[False], np.any(np.diff(off, axis=0) != 0, axis=1)])
            changed &= same_core & np.isfinite(off).all(axis=1) & \
                np.concatenate([[False], np.isfinite(off[:-1]).all(axis=1)])
            reset |= changed
        if reset.any():
            self.notes.append(f"estimate: {int(reset.sum())} position resets (core switch or "
                              "XKF4 OFN/OFE change) at t = "
                              + ", ".join(f"{v:.3f}" for v in t[reset][:10]) + " s")
        return make_stream("estimate", t, {"x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
                                           "vx": vel[:, 0], "vy": vel[:, 1], "vz": vel[:, 2],
                                           "reset": reset})

    # ------------------------------------------------------------ optional streams
    def odometry(self):
        if self.rows["VISO"]:
            self.notes.append("odometry: VISO (delta odometry) present, not converted")
        rows = self.rows["VISP"]
        if not rows:
            return None
        self.require(rows, "VISP", _WANTED["VISP"])
        t = self.t(rows)
        pos = frames.ned_to_enu(np.column_stack([_col(rows, k) for k in ("PX", "PY", "PZ")]))
        q = frames.euler_to_quat(*(np.deg2rad(_col(rows, k)) for k in ("Roll", "Pitch", "Yaw")))
        q = frames.quat_ned_frd_to_enu_flu(q)
        values = {"x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
                  "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3]}
        visv = self.rows["VISV"]
        if visv and all(k in visv[0] for k in ("VX", "VY", "VZ")):
            tv = self.t(visv)
            order = np.argsort(tv, kind="stable")
            j = nearest_index(t, tv[order], 0.5 * median_period(tv[order]))
            j = np.where(j >= 0, order[np.clip(j, 0, None)], -1)
            vel = frames.ned_to_enu(take(np.column_stack([_col(visv, k) for k in ("VX", "VY", "VZ")]), j))
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
            pos = frames.geodetic_to_enu(_col(rows, "Lat"), _col(rows, "Lng"), _col(rows, "Alt"),
                                         origin)
        else:
            pos = np.full((len(t), 3), np.nan)
        values = {"x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2]}
        if all(k in rows[0] for k in ("Q1", "Q2", "Q3", "Q4")):
            q = frames.quat_ned_frd_to_enu_flu(frames.wxyz_to_xyzw(
                np.column_stack([_col(rows, k) for k in ("Q1", "Q2", "Q3", "Q4")])))
            values.update({"qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3]})
        sim2 = self.rows["SIM2"]
        if sim2 and all(k in sim2[0] for k in ("VN", "VE", "VD")):
            t2 = self.t(sim2)
            order = np.argsort(t2, kind="stable")
            v = frames.ned_to_enu(interp_linear(
                t, t2[order], np.column_stack([_col(sim2, k) for k in ("VN", "VE", "VD")])[order]))
            values.update({"vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2]})
            self.notes.append("truth: SIM position/attitude with SIM2 velocity interpolated to "
                              "the SIM times")
        return make_stream("truth", t, values, self.notes)
